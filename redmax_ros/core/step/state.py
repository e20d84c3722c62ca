"""What a step takes and gives: State (immutable), Commands, Diagnostics, StepResult, Rollout; the input checks and
the divergence limit shared by every backend (SI units: m, rad, s, N, N m, J).

Divergence is the step's velocity beyond MAX_SPEED (check_speed, after the solve). Inputs that cannot give
a step below it are rejected before any solve ("step diverged (rejected before solving): ..."), as their
solves are the slow ones (the QP of Eq. 5 cannot reach its absolute tolerance at their scale):

* the state's velocity beyond MAX_SPEED (applied_torques);
* a bilateral row G_i qdot = g_i (prescribed joint or site velocity, Eq. 7) with |g_i| > MAX_SPEED
  sum_j |G_ij|: every qdot with max |qdot| <= MAX_SPEED has |G_i qdot| <= MAX_SPEED sum_j |G_ij|, so no
  solution is below the limit (check_rows; exact, never rejects a step that could pass check_speed);
* an applied joint torque or site force whose impulse alone would change the velocity of the free
  (unconstrained) system by more than MAX_SPEED in one step: A dv = h f gives h |f_k| <= sum_j |A_kj|
  max |dv| for every DOF k, so h |f_k| > MAX_SPEED sum_j |A_kj| (A: the LHS of Eq. 2 at this state,
  inertia + armature + h D + h^2 K) means max |dv| > MAX_SPEED (check_applied). Components on prescribed
  joints are left out (their multipliers take them exactly). A joint limit, a loop or contact could still
  hold such a force, but it is 1e6 times what changes the DOF's velocity by 1 rad/s (m/s) in one step
  (hand, h = 1 ms, at q0: from 4.2e4 N m on thumb_ip to 1.7e7 N m on the wrist and 9.5e7 N m on the elbow;
  walker: from 2.4e6 N m) and its reaction is beyond the solvers' precision (it is what made the
  joint-limit QP run for 64 s). Checked on the Pinocchio and dense data-free paths (where A is formed); the PCG path solves
  at any scale in its capped iterations, and its step fails by check_speed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.errors import StepError
from redmax_ros.core.jit import njit
from redmax_ros.core.linalg import all_finite

MAX_SPEED = 1e6  # |qdot| above this (rad/s or m/s) is reported as divergence
_UP_FRONT = "step diverged (rejected before solving)"


@dataclass(frozen=True)
class State:
    t: float  # s
    q: np.ndarray  # (nq,) Pinocchio configuration
    v: np.ndarray  # (ndof,) hyper-reduced velocity qdot_R (= qdot_r without couplings)
    friction_cache: np.ndarray | None = None  # warm start of the friction impulses (staggered.py)
    k: int = 0  # steps taken since the time origin t0
    t0: float | None = None  # time origin [s] (None: t); t = t0 + k h after k steps of h, one rounding
    history: object = None  # step.scheme.History (q_k-1, qdot_k-1, h) for integrator.scheme bdf2, else None
    deform: object = None  # deformable.system.DeformState (vertex positions, velocities) with deformables, else None

    def advanced(self, h: float, q, v, friction_cache=None, steps: int = 1, history=None, deform=None) -> "State":
        """The state after ``steps`` steps of h: t = t0 + (k + steps) h, computed from the step count, not by
        accumulating h (after 380,910 steps of 1 ms the sum gave 380.909999998 s; t0 + k h is the float
        nearest to the exact time, so round(t * 1e9) is the exact nanosecond count when h is). ``history``:
        what a BDF2 step needs of the last step (step.scheme.History), None for BDF1. ``deform``: the
        deformables' state after the step (step/deformable_stages.py), None without deformables."""
        t0 = self.t if self.t0 is None else self.t0
        return State(t0 + (self.k + steps) * h, q, v, friction_cache, self.k + steps, t0, history, deform)

    def time_after(self, h: float) -> float:
        """t_k+1 = t0 + (k + 1) h: the time the next step of h ends at (as ``advanced`` computes it)."""
        return (self.t if self.t0 is None else self.t0) + (self.k + 1) * h


@dataclass
class Commands:
    joint_velocities: dict = field(default_factory=dict)  # prescribed joint -> (nv_j,) [rad/s, m/s]
    site_velocities: dict = field(default_factory=dict)  # prescribed site -> (3,) world [m/s]
    site_axes: dict = field(default_factory=dict)  # prescribed site -> (k,3) world directions (default: x, y, z)
    joint_torques: np.ndarray | None = None  # (nv,) explicit applied joint torques [N m, N]
    site_forces: dict = field(default_factory=dict)  # site -> (3,) explicit world force [N]
    # prescribed joint -> scene.timefunctions.JointTrajectory: position trajectory q_p(t), velocity row
    # qdot_p(t_k+1) + b (q_p(t_k+1) - q_k) each step (step/trajectory.py); a joint is in one of the two dicts
    joint_trajectories: dict = field(default_factory=dict)
    # prescribed body -> step.body_twist.BodyTwist (selected twist components, body or world frame)
    body_twists: dict = field(default_factory=dict)


@dataclass
class Diagnostics:
    E_kin: float  # J
    E_pot: float  # J (gravity)
    E_spring: float  # J (maximal springs + joint springs)
    E_total: float
    violation_pos: float  # max loop-closure residual after the step [m]
    violation_vel: float  # max |G qdot - g| of the bilateral rows
    iterations: int
    solver: str
    wall_time: float  # s
    solution: object = field(default=None, repr=False)
    friction: object = None  # staggered.FrictionReport when the scene has contact or joint friction
    order: int = 1  # the step taken: 2 a BDF2 step, 1 Eq. (2) (integrator.scheme euler, BDF2's start-up, or a
    # BDF2 step the order control redid as Eq. (2), step/scheme.accepts)

    @property
    def residual(self) -> float:
        """Relative KKT residual of the solve (computed on first access)."""
        return 0.0 if self.solution is None else self.solution.residual


@dataclass
class StepResult:
    t: float
    q: np.ndarray  # (nq,)
    v: np.ndarray  # (nv,) reduced velocities
    effort: np.ndarray  # (nv,) applied torque + required torque of prescribed DOFs [N m, N]
    site_forces: dict  # prescribed site -> required force (3,) world frame [N]
    diagnostics: Diagnostics
    body_wrenches: dict = field(default_factory=dict)  # prescribed body -> required wrench (6,) [N m; N], its frame


@dataclass
class BatchResult:
    """What Simulator.step_batch gives: per instance its State after the steps it took, their number and the
    StepError message that stopped it (None: all n steps taken)."""
    states: list
    steps_done: np.ndarray
    errors: list


@dataclass
class Rollout:
    """What Simulator.rollout gives: the outputs of every ``every``-th step of a run, stacked; row i holds
    the numbers of the StepResult of step (i + 1) every (SI units, as StepResult and Diagnostics)."""
    t: np.ndarray  # (k,) time after the step [s]
    q: np.ndarray  # (k, nq) configuration
    v: np.ndarray  # (k, nv) reduced velocities
    effort: np.ndarray  # (k, nv) applied + required torques [N m, N]
    site_forces: dict  # prescribed site -> (k, 3) required force, world frame [N]
    E_kin: np.ndarray  # (k,) [J]
    E_pot: np.ndarray  # (k,) [J]
    E_spring: np.ndarray  # (k,) [J]
    violation_pos: np.ndarray  # (k,) max loop-closure residual [m]
    violation_vel: np.ndarray  # (k,) max |G qdot - g| of the bilateral rows
    iterations: np.ndarray  # (k,) int
    solver: list  # (k,) the solver label of each row's step
    last: StepResult | None = None  # the last row's full StepResult (multipliers, friction report)
    body_wrenches: dict = field(default_factory=dict)  # prescribed body -> (k, 6) required wrench [N m; N], its frame
    order: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (k,) Diagnostics.order

    def __len__(self) -> int:
        return len(self.t)

    @property
    def E_total(self) -> np.ndarray:
        return self.E_kin + self.E_pot + self.E_spring

    @classmethod
    def from_results(cls, results: list) -> "Rollout":
        """The rows of these StepResults, in order."""
        d = [r.diagnostics for r in results]
        names = list(results[0].site_forces) if results else []
        return cls(np.array([r.t for r in results], dtype=float), np.array([r.q for r in results], dtype=float),
                   np.array([r.v for r in results], dtype=float), np.array([r.effort for r in results], dtype=float),
                   {n: np.array([r.site_forces[n] for r in results], dtype=float) for n in names},
                   np.array([x.E_kin for x in d], dtype=float), np.array([x.E_pot for x in d], dtype=float),
                   np.array([x.E_spring for x in d], dtype=float), np.array([x.violation_pos for x in d], dtype=float),
                   np.array([x.violation_vel for x in d], dtype=float),
                   np.array([x.iterations for x in d], dtype=np.int64), [x.solver for x in d],
                   results[-1] if results else None,
                   {n: np.array([r.body_wrenches[n] for r in results], dtype=float)
                    for n in (results[0].body_wrenches if results else {})},
                   np.array([x.order for x in d], dtype=np.int64))

    @classmethod
    def concatenate(cls, parts: list) -> "Rollout":
        """One Rollout of the rows of ``parts`` (non-empty), in order; ``last`` the last part's."""
        if len(parts) == 1:
            return parts[0]
        cat = np.concatenate
        return cls(cat([p.t for p in parts]), cat([p.q for p in parts]), cat([p.v for p in parts]),
                   cat([p.effort for p in parts]), {n: cat([p.site_forces[n] for p in parts]) for n in parts[0].site_forces},
                   cat([p.E_kin for p in parts]), cat([p.E_pot for p in parts]), cat([p.E_spring for p in parts]),
                   cat([p.violation_pos for p in parts]), cat([p.violation_vel for p in parts]),
                   cat([p.iterations for p in parts]), [s for p in parts for s in p.solver], parts[-1].last,
                   {n: cat([p.body_wrenches[n] for p in parts]) for n in parts[0].body_wrenches},
                   cat([p.order for p in parts]))


def step_each(step, states, cmd, h, n, budget=None) -> BatchResult:
    """BatchResult of n steps of each state, one after the other, with ``step(state, cmd, h, budget)`` (a
    backend's step); an instance whose step fails keeps its state from before it and reports the reason."""
    out, done, errors = [], np.zeros(len(states), dtype=np.int64), []
    for b, st in enumerate(states):
        err = None
        for _ in range(int(n)):
            try:
                st, _ = step(st, cmd, h, budget)
            except StepError as e:
                err = e.reason
                break
            done[b] += 1
        out.append(st)
        errors.append(err)
    return BatchResult(out, done, errors)


def _finite(name, x):
    if not np.all(np.isfinite(x)):
        raise StepError(f"non-finite {name}")


def check_inputs(state, tau, cmd):
    """Name the first non-finite input (slow path, only after the cheap check failed)."""
    _finite("configuration q", state.q)
    _finite("velocity", state.v)
    _finite("joint torques", tau)
    for name, v in cmd.joint_velocities.items():
        _finite(f"prescribed velocity of joint '{name}'", v)
    for name, v in cmd.site_velocities.items():
        _finite(f"prescribed velocity of site '{name}'", v)
    for n, f in cmd.site_forces.items():
        _finite(f"force on site '{n}'", f)


def applied_torques(mech, state, cmd, h) -> np.ndarray:
    """tau = constant joint torques + commanded ones (nv,); StepError on a bad step size, a non-finite
    input (named) or a state velocity beyond MAX_SPEED."""
    if not (h > 0 and math.isfinite(h)):
        raise StepError(f"time step must be positive and finite, got {h}")
    tau = mech.torque0 if cmd.joint_torques is None else mech.torque0 + cmd.joint_torques
    q, v = np.asarray(state.q, dtype=float), np.asarray(state.v, dtype=float)  # no copy for float arrays
    finite, vmax = _finite_and_speed(q, v, np.asarray(tau, dtype=float))  # one compiled pass
    if not finite:  # names it below
        check_inputs(state, tau, cmd)
    if vmax > MAX_SPEED:
        k = int(np.argmax(np.abs(v)))
        raise StepError(f"{_UP_FRONT}: the state's velocity {v[k]:.3g} (DOF {k}) is beyond the limit {MAX_SPEED:g}")
    for f in cmd.site_forces.values():
        if not np.all(np.isfinite(f)):
            check_inputs(state, tau, cmd)
    return tau


@njit
def _finite_and_speed(q, v, tau):
    """(every entry of q, v and tau finite, max |v|): applied_torques' input test in one pass."""
    finite = all_finite(q) and all_finite(v) and all_finite(tau)
    vmax = 0.0
    for i in range(v.shape[0]):
        vmax = max(vmax, abs(v[i]))
    return finite, vmax


@njit
def row_beyond(G, g, limit):
    """The first row i with |g_i| > limit sum_j |G_ij| > 0 (G_i qdot = g_i needs max |qdot| > limit), or -1."""
    for i in range(len(g)):
        gi = abs(g[i])
        if gi == 0.0:
            continue
        s = 0.0
        for j in range(G.shape[1]):
            s += abs(G[i, j])
        if s > 0.0 and gi > limit * s:
            return i
    return -1


def check_rows(cons, scale: float = 1.0) -> None:
    """StepError naming the first bilateral row (prescribed joint or site velocity) that no velocity with
    max |qdot| <= MAX_SPEED meets: |g_i| > MAX_SPEED sum_j |G_ij|. ``scale``: bound of max |G-coordinates
    velocity| / max |qdot| (1 when the rows are in the coordinates check_speed tests; max_i sum_j |T_ij|
    for reduced-coordinate rows and hyper-reduced qdot, T = J_rR). Rows acting on no DOF are left to the
    solver's rank check."""
    i = row_beyond(cons.G, cons.g, MAX_SPEED * scale)
    if i >= 0:
        s = float(np.abs(cons.G[i]).sum()) * scale
        raise StepError(f"{_UP_FRONT}: {cons.labels[i]}: velocity {cons.g[i]:.3g} needs max |qdot| >= "
                        f"{abs(cons.g[i]) / s:.3g} (limit {MAX_SPEED:g})")


@njit
def _any_nonzero(x):
    for i in range(x.shape[0]):
        if x[i] != 0.0:
            return True
    return False


@njit
def impulse_beyond(A, T, f, mask, h, limit):
    """The first DOF k of A with h |F_k| > limit sum_j |A_kj| (then A dv = h F has max |dv| > limit), or -1;
    F = T^T (mask * f) (an empty T: identity, an empty mask: ones)."""
    n = A.shape[0]
    nr = len(f)
    if not _any_nonzero(f):  # F = 0 (the rows below would all find h |F_k| = 0)
        return -1
    for k in range(n):
        if T.shape[0]:
            F = 0.0
            for d in range(nr):
                F += T[d, k] * (f[d] if mask.shape[0] == 0 else f[d] * mask[d])
        else:
            F = f[k] if mask.shape[0] == 0 else f[k] * mask[k]
        t = h * abs(F)
        if t <= limit * abs(A[k, k]):  # sum_j |A_kj| >= |A_kk|: cannot be beyond
            continue
        s = 0.0
        for j in range(n):
            s += abs(A[k, j])
        if t > limit * s:
            return k
    return -1


_NONE = np.zeros(0)
_NO_T = np.zeros((0, 0))


def _free_mask(mech, ws, prescribed) -> np.ndarray | None:
    """(nv,) 1.0 on the reduced DOFs of joints not prescribed, 0.0 on prescribed ones (cached per set), or
    None when nothing is prescribed."""
    if not prescribed:
        return None
    key = ("free dofs", *prescribed)
    mask = ws.cache.get(key)
    if mask is None:
        mask = np.ones(mech.nv)
        for name in prescribed:
            j = mech.joint_index[name]
            mask[j.idx_v:j.idx_v + j.nv] = 0.0
        ws.cache[key] = mask
    return mask


def check_applied(mech, ws, A, tau, h, cmd, site_terms=()) -> None:
    """StepError when an applied joint torque (``tau``, reduced, nv) or site force (``site_terms``: [(site,
    J_site^T f (nv,))]) would alone change the free system's velocity by more than MAX_SPEED in one step:
    h |f_k| > MAX_SPEED sum_j |A_kj| on a DOF k of ``A`` (the LHS of Eq. 2, hyper-reduced by the
    workspace's J_rR when it has couplings). Components on prescribed joints are left out. One compiled
    pass per source (the torques; each site force; all together)."""
    mask = _free_mask(mech, ws, cmd.joint_velocities)
    mk = _NONE if mask is None else mask
    T = _NO_T if ws.T is None else ws.T
    if not site_terms:  # the usual case: one compiled pass (~1 us on the hand)
        k = impulse_beyond(A, T, tau, mk, h, MAX_SPEED)
        if k >= 0:
            raise StepError(_applied_message(mech, ws, A, h, cmd, "torque", None, tau, mask, k))
        return
    sources = [("torque", None, tau)] + [("force", name, f) for name, f in site_terms]
    if len(sources) > 2 or tau @ tau != 0.0:
        sources.append(("together", None, sum(f for _, _, f in sources)))
    for kind, site, f in sources:
        k = impulse_beyond(A, T, f, mk, h, MAX_SPEED)
        if k >= 0:
            raise StepError(_applied_message(mech, ws, A, h, cmd, kind, site, f, mask, k))


def _applied_message(mech, ws, A, h, cmd, kind, site, f, mask, k) -> str:
    fm = f if mask is None else f * mask
    T = ws.T
    fR = fm if T is None else T.T @ fm
    s = float(np.abs(A[k]).sum())
    what = f"impulse h |f| = {h * abs(fR[k]):.3g} > {MAX_SPEED:g} x {s:.3g} (the DOF's row of the LHS of Eq. 2)"
    if kind == "torque":
        d = k if T is None else int(np.argmax(np.abs(T[:, k] * fm)))
        j = next(j for j in mech.joints if j.idx_v <= d < j.idx_v + j.nv)
        unit = {"revolute": "N m", "universal": "N m", "spherical": "N m", "prismatic": "N"}.get(j.type, "N m or N")
        comp = f" (DOF {d - j.idx_v} of {j.nv})" if j.nv > 1 else ""
        name = f"applied torque of joint '{j.name}'{comp} = {f[d]:.3g} {unit}"
    elif kind == "force":
        name = f"applied force on site '{site}' (|f| = {float(np.linalg.norm(cmd.site_forces[site])):.3g} N)"
    else:
        name = "applied torques and site forces together"
    return (f"{_UP_FRONT}: {name} would change the velocity by more than the limit {MAX_SPEED:g} in one step: "
            f"{what}")


def check_speed(v) -> None:
    """StepError when max |qdot| exceeds MAX_SPEED (or is not finite): the step diverged."""
    if not v @ v <= MAX_SPEED * MAX_SPEED:  # cheap test (also catches NaN), then the exact one
        vmax = float(np.abs(v).max())
        if not vmax <= MAX_SPEED:
            raise StepError(f"step diverged: max |qdot| = {vmax:.3g} (limit {MAX_SPEED:g})")
