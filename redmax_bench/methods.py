"""Problems, reference solutions and the methods compared by ``redmax_bench accuracy``.

A *case* (registered with :func:`register_case`) is a scene plus an initial state, a duration and
the time steps to try; :func:`make_problem` instantiates it. A *method* (registered with
:func:`register_method`, one line each) turns (problem, h) into a :class:`Run`: configurations,
energies, constraint violations and required torques at fixed sample times, the wall time spent
stepping, and a status (ok, blow-up, drift, nonconvergence) that is never silent.

Dynamics used by the explicit baselines and the references (all Pinocchio):
  * trees: ``pin.aba`` with the same applied forces as Eq. (2) (``core.baselines.applied_force``);
  * loops: ``pin.constraintDynamics`` with one CONTACT_3D RigidConstraintModel per loop (the
    proximal solver absorbs the redundant out-of-plane row of a planar loop) and Pinocchio's
    Baumgarte corrector for the baselines (Kp, Kd below; none for the reference);
  * hybrid (a prescribed joint, e.g. the hand's elbow): the reduced equations split into free and
    prescribed hyper-reduced coordinates, M_ff a_f = b_f - M_fp a_p, with the required torque
    tau_p = M_pp a_p + M_pf a_f - b_p (this is ``pin.rnea`` on the prescribed motion, with the
    coupling projection T of Eq. 9).
"""
from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pinocchio as pin

from redmax_ros.core import Simulator, State, StepError, Workspace
from redmax_ros.core.dynamics.kinematics import site_jacobians, site_positions
from redmax_ros.core.step import baselines
from redmax_ros.core.step.backends import make_backend
from redmax_bench import exudyn_planar, mujoco_export
from redmax_bench.maximal import MaximalModel

MAX_SPEED = 1e6  # |v| above this is a blow-up (same limit as the stepper's)
LOOP_KP, LOOP_KD = 100.0, 20.0  # Pinocchio's Baumgarte corrector for the loop baselines [1/s^2, 1/s]


def default_cache_dir() -> Path:
    """Where :func:`reference` caches its solutions by default: runs/accuracy_cache under the current
    directory (/runs/ is git-ignored in the repository)."""
    return Path.cwd() / "runs" / "accuracy_cache"


# ---------------------------------------------------------------------------------------------
# cases and problems


@dataclass
class Case:
    name: str
    chart: str  # conservative | stiff | loop | hybrid | bridge
    scene: str
    overrides: list = field(default_factory=list)
    T: float = 2.0  # simulated duration [s]
    hs: tuple = (2e-2, 1e-2, 5e-3, 2e-3, 1e-3, 5e-4, 2e-4, 1e-4)
    sample_dt: float = 0.02  # error sample spacing [s]; a multiple of every h
    h_ref: float = 1e-4  # first reference step (halved until converged)
    prepare: Callable | None = None  # (mech, q0, vR0) -> (q0, vR0), may edit mech (e.g. rest lengths)
    hybrid: dict | None = None  # {"joint": name, "q": f(t), "v": f(t), "a": f(t)}
    note: str = ""
    probe: str | None = None  # a joint whose error at the end of the run is recorded too (probe_final)


CASES: dict = {}


def register_case(case: Case) -> Case:
    CASES[case.name] = case
    return case


@dataclass
class Problem:
    case: Case
    sim: Simulator
    mech: object
    q0: np.ndarray
    vR0: np.ndarray  # hyper-reduced initial velocity (consistent with loops / prescriptions)
    T: float
    sample_dt: float
    hybrid: object | None = None  # HybridSplit
    E_eq: float | None = None  # energy at static equilibrium (stability scale), tree scenes

    @property
    def n_samples(self) -> int:
        return int(round(self.T / self.sample_dt))


def make_problem(case: Case, T: float | None = None, sample_dt: float | None = None, extra=()) -> Problem:
    """Instantiate a case; ``extra`` overrides go after the case's own (e.g. solver=pcg). The simulator has
    no step budget (budget=None): the work-precision charts and stability maps measure the method's
    unbounded cost and accuracy (a large h can need long PCG/QP solves), and a run's wall-time limit is
    the ``budget`` of run_ours (seconds per run, not per step)."""
    sim = Simulator.load(case.scene, list(case.overrides) + list(extra), budget=None)
    mech = sim.mech
    q0, vR0 = mech.q0.copy(), mech.v0.copy()
    if case.prepare is not None:
        q0, vR0 = case.prepare(mech, q0, vR0)
        # prepare edits the Mechanism (spring rest lengths): rebuild the backend, whose constants (the compiled
        # step's packed Model) were read when the simulator was made
        sim.backend = make_backend(mech, sim.spec.solver)
    hyb = None
    if case.hybrid is not None:
        hyb = HybridSplit(mech, case.hybrid)
        vR0 = vR0.copy()
        vR0[hyb.p] = hyb.v(0.0)
    if len(mech.loop_ab):
        vR0 = project_velocity(mech, q0, vR0)
    return Problem(case, sim, mech, q0, vR0, case.T if T is None else T,
                   case.sample_dt if sample_dt is None else sample_dt, hyb)


def project_velocity(mech, q, vR):
    """Closest velocity (mass metric) satisfying the loop rows: what Eq. (2) does to v0."""
    model = mech.model
    ws = Workspace(mech, pin_data=True)
    G = loop_jacobian(mech, ws, q)
    M = pin.crba(model, ws.data, q)
    M = np.triu(M) + np.triu(M, 1).T
    v = mech.to_reduced(vR)
    lam = np.linalg.solve(G @ np.linalg.solve(M, G.T), G @ v)
    v = v - np.linalg.solve(M, G.T @ lam)
    return v if mech.T is None else np.linalg.lstsq(mech.T, v, rcond=None)[0]


def loop_jacobian(mech, ws, q):
    """Loop-closure rows G (reduced velocities) at q; ``ws``: a Workspace with pin.Data."""
    pin.computeJointJacobians(mech.model, ws.data, q)
    pin.updateFramePlacements(mech.model, ws.data)
    rows = []
    for (a, b), P in zip(mech.loop_ab, mech.loop_axes):
        _, J = site_jacobians(mech, ws, [int(a), int(b)])
        rows.append(np.asarray(P) @ (J[0] - J[1]))
    return np.vstack(rows) if rows else np.zeros((0, mech.nv))


def loop_residual(mech, data, q) -> float:
    if not len(mech.loop_ab):
        return 0.0
    pin.forwardKinematics(mech.model, data, q)
    X = site_positions(mech, data)
    return float(max(np.abs(np.asarray(P) @ (X[a] - X[b])).max() for (a, b), P in zip(mech.loop_ab, mech.loop_axes)))


def static_equilibrium(mech, q, iters: int = 60):
    """Newton on f_applied(q, 0) - g(q) = 0 (trees), numerical tangent stiffness, least squares for
    directions without stiffness (free rotations of bodies whose springs act through the COM)."""
    model = mech.model
    ws = Workspace(mech, pin_data=True)
    nv = model.nv
    zero = np.zeros(nv)

    def F(qq):
        return baselines.applied_force(mech, ws, qq, zero) - pin.computeGeneralizedGravity(model, ws.data, qq)

    f = F(q)
    for _ in range(iters):
        if np.linalg.norm(f) < 1e-11:
            break
        eps = 1e-7
        K = np.empty((nv, nv))
        for i in range(nv):
            e = np.zeros(nv)
            e[i] = eps
            K[:, i] = -(F(pin.integrate(model, q, e)) - f) / eps
        dq = np.linalg.lstsq(K, f, rcond=1e-10)[0]
        a = 1.0
        while a > 1e-4:
            qn = pin.integrate(model, q, a * dq)
            fn = F(qn)
            if np.linalg.norm(fn) < np.linalg.norm(f):
                break
            a *= 0.5
        q, f = qn, fn
    return q, float(np.linalg.norm(f))


# ---------------------------------------------------------------------------------------------
# dynamics for the explicit baselines and the references


class HybridSplit:
    """Reduced dynamics with one prescribed joint (hyper-reduced coordinate p), free coordinates f."""

    def __init__(self, mech, spec):
        self.mech = mech
        j = mech.joint_index[spec["joint"]]
        if j.nv != 1:
            raise ValueError("hybrid benchmark: the prescribed joint must have one DOF")
        T = mech.T if mech.T is not None else np.eye(mech.nv)
        cols = np.flatnonzero(T[j.idx_v])
        if len(cols) != 1 or np.count_nonzero(T[:, cols[0]]) != 1:
            raise ValueError("hybrid benchmark: the prescribed joint must not be coupled")
        self.T = T
        self.p = int(cols[0])
        self.f = np.array([i for i in range(T.shape[1]) if i != self.p])
        self.joint = spec["joint"]
        self.dof = j.idx_v
        self.q, self.v, self.a = spec["q"], spec["v"], spec["a"]

    def accel(self, ws, q, vR, t):
        """(aR, required torque of the prescribed joint [N m]); ``ws``: a Workspace with pin.Data."""
        mech, T = self.mech, self.T
        v = T @ vR
        M = pin.crba(mech.model, ws.data, q)
        M = np.triu(M) + np.triu(M, 1).T
        nle = pin.rnea(mech.model, ws.data, q, v, np.zeros(mech.nv))
        b = T.T @ (baselines.applied_force(mech, ws, q, v) - nle)
        MR = T.T @ M @ T
        ap = self.a(t)
        f, p = self.f, self.p
        aR = np.empty(T.shape[1])
        aR[p] = ap
        aR[f] = np.linalg.solve(MR[np.ix_(f, f)], b[f] - MR[f, p] * ap)
        tau = float(MR[p] @ aR - b[p])
        return aR, tau


class LoopDynamics:
    """pin.constraintDynamics with one CONTACT_3D constraint per loop."""

    def __init__(self, mech, kp=0.0, kd=0.0):
        if mech.T is not None:
            raise ValueError("loops with couplings are not supported by the Pinocchio loop baseline")
        model = mech.model
        self.models = pin.StdVec_RigidConstraintModel()
        for a, b in mech.loop_ab:
            cm = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, model,
                                          int(mech.site_jid[a]), pin.SE3(np.eye(3), np.asarray(mech.site_local[a], float)),
                                          int(mech.site_jid[b]), pin.SE3(np.eye(3), np.asarray(mech.site_local[b], float)),
                                          pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
            if kp or kd:
                cm.setBaumgarteCorrectorParameters(pin.BaumgarteCorrectorParameters(kp, kd))
            self.models.append(cm)
        self.datas = pin.StdVec_RigidConstraintData()
        for cm in self.models:
            self.datas.append(cm.createData())
        self.mech = mech
        self.ws = Workspace(mech, pin_data=True)
        self.data = self.ws.data
        pin.initConstraintDynamics(model, self.data, self.models, self.datas)
        self.settings = pin.ProximalSettings(1e-13, 1e-10, 50)

    def accel(self, q, v):
        m = self.mech
        tau = baselines.applied_force(m, self.ws, q, v)
        return pin.constraintDynamics(m.model, self.data, q, v, tau, self.models, self.datas, self.settings).copy()


def make_dynamics(problem: Problem, baumgarte: bool):
    """f(q, vR, t) -> (aR, required torque or None) for the problem's mechanism."""
    mech = problem.mech
    ws = Workspace(mech, pin_data=True)
    if problem.hybrid is not None:
        hyb = problem.hybrid
        return lambda q, vR, t: hyb.accel(ws, q, vR, t)
    if len(mech.loop_ab):
        ld = LoopDynamics(mech, *((LOOP_KP, LOOP_KD) if baumgarte else (0.0, 0.0)))
        return lambda q, v, t: (ld.accel(q, v), None)
    if mech.T is not None:
        raise ValueError("couplings without a prescribed joint: no Pinocchio baseline")
    return lambda q, v, t: (baselines.acceleration(mech, ws, q, v), None)


# ---------------------------------------------------------------------------------------------
# runs


@dataclass
class Run:
    method: str
    h: float
    status: str = "ok"  # ok | blow-up | drift | nonconvergence | not-applicable | timeout
    reason: str = ""
    t: list = field(default_factory=list)
    q: list = field(default_factory=list)
    E: list = field(default_factory=list)
    viol: list = field(default_factory=list)
    tau: list = field(default_factory=list)
    wall: float = 0.0  # s spent stepping (wall clock)
    cpu: float = 0.0  # s spent stepping (process CPU time: robust to other load on a shared machine)
    steps: int = 0

    def fail(self, status, reason):
        self.status, self.reason = status, reason
        return self


class _Recorder:
    """Sampling loop shared by all methods: n_sub steps between samples, blow-up checks, budget."""

    def __init__(self, problem, h, method, energy_cap=None, budget=None):
        self.p, self.h, self.run = problem, h, Run(method, h)
        ratio = problem.sample_dt / h
        self.n_sub = int(round(ratio))
        if abs(ratio - self.n_sub) > 1e-9 * ratio:
            raise ValueError(f"h = {h} does not divide the sample spacing {problem.sample_dt}")
        self.energy_cap = energy_cap  # E above this: blow-up
        self.budget = budget

    def record(self, k, q, E, viol, tau=None, vmax=0.0):
        r = self.run
        r.t.append((k + 1) * self.p.sample_dt)
        r.q.append(np.asarray(q, float).copy())
        r.E.append(float(E))
        r.viol.append(float(viol))
        if tau is not None:
            r.tau.append(float(tau))
        if not (np.all(np.isfinite(q)) and math.isfinite(E) and vmax <= MAX_SPEED):
            r.fail("blow-up", f"non-finite state or |v| > {MAX_SPEED:g} at t = {r.t[-1]:.4g} s")
            return False
        if self.energy_cap is not None and E > self.energy_cap:
            r.fail("blow-up", f"energy {E:.4g} J above the cap {self.energy_cap:.4g} J at t = {r.t[-1]:.4g} s")
            return False
        if self.budget is not None and r.wall > self.budget:
            r.fail("timeout", f"wall-time budget {self.budget:g} s exceeded at t = {r.t[-1]:.4g} s")
            return False
        return True


def secant_rate(hyb, t, h):
    """The prescribed joint's velocity row for the step [t, t + h] of the paper's step: the secant of q_p."""
    return (hyb.q(t + h) - hyb.q(t)) / h


def end_rate(hyb, t, h):
    """The prescribed joint's velocity row for BDF2: q_p's rate at the step's end time t + h (step/scheme.py)."""
    return hyb.v(t + h)


def run_ours(problem, h, energy_cap=None, budget=None, name="ours (direct)", require_solver=None, rate=secant_rate):
    sim = problem.sim
    sim.reset()
    sim.dt = h
    sim.set_state(State(0.0, problem.q0.copy(), problem.vR0.copy()))
    rec = _Recorder(problem, h, name, energy_cap, budget)
    run = rec.run
    hyb = problem.hybrid
    _warm_up(sim, hyb, h, rate)
    if hyb is None:
        return _run_ours_blocks(problem, rec, require_solver)

    def sample():  # the steps of one sample, the prescribed joint's rate set before each
        for _ in range(rec.n_sub):
            sim.commands.joint_velocities[hyb.joint] = np.array([rate(hyb, sim.time, h)])
            res = sim.step(1)
        return res

    for k in range(problem.n_samples):
        res, failed = _timed(run, sample)
        if failed:
            return failed
        run.steps += rec.n_sub
        d = res.diagnostics
        if require_solver and require_solver not in str(d.solver):
            return run.fail("not-applicable", f"the stepper ran solver '{d.solver}', not '{require_solver}'")
        tau = float(res.effort[hyb.dof])
        if not rec.record(k, res.q, d.E_total, d.violation_pos, tau, float(np.abs(res.v).max(initial=0.0))):
            return run
    return run


def _timed(run, take):
    """take() with its wall and CPU time added to ``run``: (its value, None), or (None, ``run`` failed) on a
    StepError: a blow-up when the step diverged or went non-finite, else nonconvergence."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        out, err = take(), None
    except StepError as e:
        out, err = None, str(e)
    run.wall += time.perf_counter() - t0
    run.cpu += time.process_time() - c0
    if err is None:
        return out, None
    bad = "diverged" in err or "non-finite" in err
    return None, run.fail("blow-up" if bad else "nonconvergence", err)


def _warm_up(sim, hyb, h, rate):
    """One untimed step from the start state, then the start state again: the one-time work of a model's first
    step with these commands (the compiled backend builds its Data and record layout then; JIT-compiled helpers
    load) stays out of the run's time, as MuJoCo's export and mj_makeData and the Pinocchio baselines'
    createData do. The run then starts from exactly the state it would have had (BDF2: no history)."""
    start = sim.state
    if hyb is not None:
        sim.commands.joint_velocities[hyb.joint] = np.array([rate(hyb, sim.time, h)])
    try:
        sim.step_results(1) if hyb is not None else sim.rollout(1)
    except StepError:
        pass  # the timed run meets it again and reports it
    sim.set_state(start)


SAMPLES_PER_CALL = 100  # samples per timed block (ours, MuJoCo): the per-sample checks and the budget run between blocks


def _run_ours_blocks(problem, rec, require_solver=None):
    """run_ours without prescriptions: blocks of SAMPLES_PER_CALL samples, each timed as a whole (the clock read
    once per block, not per sample, as run_mujoco does) and the blow-up and budget checks after it (a blow-up
    inside a block is caught at its sample, as with single calls). A block is one ``Simulator.rollout(n,
    n_sub)`` call, as a user who wants a sampled trajectory takes it: on the compiled path one kernel call that
    records the sampled steps only, the numbers single steps give (test_rollout.py), where MuJoCo's block is one
    mj_step(nstep=n_sub) call and a copy of qpos and qvel per sample."""
    sim, run = problem.sim, rec.run
    k = 0
    while k < problem.n_samples:
        n = min(SAMPLES_PER_CALL, problem.n_samples - k)
        ro, failed = _timed(run, lambda: sim.rollout(n, rec.n_sub))
        if failed:
            return failed
        run.steps += n * rec.n_sub
        E = ro.E_total
        for i in range(n):
            if require_solver and require_solver not in str(ro.solver[i]):
                return run.fail("not-applicable", f"the stepper ran solver '{ro.solver[i]}', not '{require_solver}'")
            if not rec.record(k, ro.q[i], float(E[i]), float(ro.violation_pos[i]), None,
                              float(np.abs(ro.v[i]).max(initial=0.0))):
                return run
            k += 1
    return run


def run_explicit(problem, h, scheme: str, energy_cap=None, budget=None, baumgarte=True, name=None):
    """Semi-implicit Euler ('sie') or RK4 ('rk4') on the Pinocchio dynamics of the problem."""
    mech = problem.mech
    model = mech.model
    dyn = make_dynamics(problem, baumgarte)
    T = problem.hybrid.T if problem.hybrid is not None else None
    ws = Workspace(mech, pin_data=True)
    rec = _Recorder(problem, h, name or f"{scheme} (Pinocchio)", energy_cap, budget)
    run = rec.run
    q, v = problem.q0.copy(), problem.vR0.copy()

    def qdot(vv):
        return vv if T is None else T @ vv

    t = 0.0
    for k in range(problem.n_samples):
        t0, c0 = time.perf_counter(), time.process_time()
        with np.errstate(all="ignore"):
            for _ in range(rec.n_sub):
                if scheme == "sie":
                    a, _ = dyn(q, v, t)
                    v = v + h * a
                    q = pin.integrate(model, q, h * qdot(v))
                else:
                    k1v, _ = dyn(q, v, t)
                    k1q = v
                    q2, v2 = pin.integrate(model, q, 0.5 * h * qdot(k1q)), v + 0.5 * h * k1v
                    k2v, _ = dyn(q2, v2, t + 0.5 * h)
                    q3, v3 = pin.integrate(model, q, 0.5 * h * qdot(v2)), v + 0.5 * h * k2v
                    k3v, _ = dyn(q3, v3, t + 0.5 * h)
                    q4, v4 = pin.integrate(model, q, h * qdot(v3)), v + h * k3v
                    k4v, _ = dyn(q4, v4, t + h)
                    dq = (v + 2 * v2 + 2 * v3 + v4) / 6.0
                    q = pin.integrate(model, q, h * qdot(dq))
                    v = v + h * (k1v + 2 * k2v + 2 * k3v + k4v) / 6.0
                t += h
                if not math.isfinite(v.sum()):
                    break
        run.wall += time.perf_counter() - t0
        run.cpu += time.process_time() - c0
        run.steps += rec.n_sub
        tau = None
        E = float("nan")
        if math.isfinite(v.sum()) and math.isfinite(q.sum()):
            if problem.hybrid is not None:
                _, tau = dyn(q, v, t)
            E = baselines.mechanical_energy(mech, ws, q, qdot(v))
        if not rec.record(k, q, E, loop_residual(mech, ws.data, q), tau, float(np.abs(v).max())):
            return run
    return run


def run_maximal(problem, h, energy_cap=None, budget=None, omega_b=None):
    mm = MaximalModel(problem.mech, omega_b)
    s = mm.from_reduced(problem.q0, problem.mech.to_reduced(problem.vR0))
    rec = _Recorder(problem, h, "maximal + Baumgarte", energy_cap, budget)
    run = rec.run
    q_prev = problem.q0
    for k in range(problem.n_samples):
        t0, c0 = time.perf_counter(), time.process_time()
        with np.errstate(all="ignore"):
            try:
                for _ in range(rec.n_sub):
                    s = mm.step(s, h)
            except np.linalg.LinAlgError as e:
                run.wall += time.perf_counter() - t0
                run.cpu += time.process_time() - c0
                return run.fail("nonconvergence", f"KKT solve failed: {e}")
        run.wall += time.perf_counter() - t0
        run.cpu += time.process_time() - c0
        run.steps += rec.n_sub
        finite = np.all(np.isfinite(s.x)) and np.all(np.isfinite(s.v)) and np.all(np.isfinite(s.w))
        if finite:
            q, E, viol = mm.to_reduced(s, q_prev), mm.energy(s), max(mm.violation(s))
            q_prev = q
            vmax = float(max(np.abs(s.v).max(), np.abs(s.w).max()))
        else:
            q, E, viol, vmax = np.full(problem.mech.nq, np.nan), float("nan"), float("nan"), float("inf")
        if not rec.record(k, q, E, viol, None, vmax):
            return run
    return run


def run_mujoco(problem, h, integrator, energy_cap=None, budget=None):
    import mujoco  # optional: mujoco

    mech = problem.mech
    ex = mujoco_export.export(mech, h, integrator)
    d = ex.make_data()
    d.qpos[:] = ex.qpos(problem.q0)
    d.qvel[:] = ex.qvel(problem.q0, mech.to_reduced(problem.vR0))
    ws = Workspace(mech, pin_data=True)
    rec = _Recorder(problem, h, f"MuJoCo {integrator}", energy_cap, budget)
    run = rec.run
    m = ex.model
    k = 0
    while k < problem.n_samples:  # blocks of samples timed as a whole, as _run_ours_blocks does ours
        n = min(SAMPLES_PER_CALL, problem.n_samples - k)

        def block():  # n samples: n_sub steps each, the state after them
            states = []
            for _ in range(n):
                mujoco.mj_step(m, d, nstep=rec.n_sub)
                states.append((d.qpos.copy(), d.qvel.copy()))
            return states

        states, _ = _timed(run, block)
        run.steps += n * rec.n_sub
        for w in ("mjWARN_BADQPOS", "mjWARN_BADQVEL", "mjWARN_BADQACC"):  # MuJoCo resets the state on these
            if int(d.warning[getattr(mujoco.mjtWarning, w)].number):
                return run.fail("blow-up", f"MuJoCo: {w} (state reset to qpos0) before t = {d.time:.4g} s")
        for qpos, qvel in states:
            q = ex.q(qpos)
            v = ex.v(q, qvel)
            E = baselines.mechanical_energy(mech, ws, q, v) if np.all(np.isfinite(v)) else float("nan")
            if not rec.record(k, q, E, loop_residual(mech, ws.data, q), None, float(np.abs(qvel).max())):
                return run
            k += 1
    return run


def run_exudyn(problem, h, energy_cap=None, budget=None):
    """Exudyn's generalized-alpha on the planar export (exudyn_planar.py), one SolveDynamic call for the run;
    CPU time is that call's (model building excluded, as for MuJoCo)."""
    mech = problem.mech
    model = exudyn_planar.PlanarModel(mech, problem.q0, mech.to_reduced(problem.vR0), h, problem.T, problem.sample_dt)
    rec = _Recorder(problem, h, "Exudyn generalized-alpha", energy_cap, budget)
    run = rec.run
    ok, cpu, wall = model.solve()
    run.cpu, run.wall, run.steps = cpu, wall, int(round(problem.T / h))
    if not ok:
        return run.fail("nonconvergence", "Exudyn: SolveDynamic did not converge")
    t, q, v = model.samples()
    ws = Workspace(mech, pin_data=True)
    for k in range(problem.n_samples):
        i = int(np.argmin(np.abs(t - (k + 1) * problem.sample_dt)))
        if abs(t[i] - (k + 1) * problem.sample_dt) > 0.5 * h:
            return run.fail("nonconvergence", f"Exudyn: no sample at t = {(k + 1) * problem.sample_dt:g} s")
        E = baselines.mechanical_energy(mech, ws, q[i], v[i]) if np.all(np.isfinite(v[i])) else float("nan")
        if not rec.record(k, q[i], E, loop_residual(mech, ws.data, q[i]), None, float(np.abs(v[i]).max())):
            return run
    return run


def _exudyn_applies(p):
    if not exudyn_planar.available():
        return "exudyn is not installed (pip install exudyn)"
    if p.hybrid is not None:
        return "prescribed motion (hybrid dynamics) is not in the Exudyn export"
    return exudyn_planar.applies(p.mech)


# ---------------------------------------------------------------------------------------------
# methods (one line each to add a curve)


@dataclass
class Method:
    name: str
    run: Callable  # (problem, h, energy_cap=None, budget=None) -> Run
    applies: Callable  # (problem) -> None or the reason it does not apply
    style: dict = field(default_factory=dict)


METHODS: dict = {}


def register_method(name, run, applies=lambda p: None, **style) -> Method:
    METHODS[name] = Method(name, run, applies, style)
    return METHODS[name]


def _pinocchio_applies(p):
    m = p.mech
    if p.hybrid is None and m.T is not None:
        return "couplings without a prescribed joint"
    if len(m.loop_ab) and m.T is not None:
        return "loops with couplings"
    if len(m.limited) and p.case.chart != "hybrid":
        return "joint limits (unilateral) are not in pin.aba"
    return None


def _maximal_applies(p):
    if p.hybrid is not None:
        return "prescribed motion (hybrid dynamics) is not in the maximal baseline"
    try:
        MaximalModel(p.mech)
    except NotImplementedError as e:
        return str(e)
    return None


def _mujoco_applies(p):
    if not mujoco_export.available():
        return "mujoco is not installed (pip install -e .[bench])"
    if p.hybrid is not None:
        return "prescribed motion (hybrid dynamics) is not exported to MuJoCo"
    try:
        mujoco_export.export(p.mech, 1e-3)
    except NotImplementedError as e:
        return str(e)
    return None


_PCG_STATUS = {}


def _pcg_applies(p):
    """PCG counts only when the stepper really runs it (diagnostics.solver)."""
    key = p.case.scene
    if key not in _PCG_STATUS:
        try:
            sim = Simulator.load(p.case.scene, list(p.case.overrides) + ["solver=pcg"], budget=None)  # as make_problem
            res = sim.step(1)
            _PCG_STATUS[key] = None if "pcg" in str(res.diagnostics.solver).lower() else \
                f"the stepper does not run PCG yet (diagnostics.solver = '{res.diagnostics.solver}')"
        except Exception as e:  # noqa: BLE001 - reported, never silent
            _PCG_STATUS[key] = f"PCG unavailable: {e}"
    return _PCG_STATUS[key]


def _ours_pcg(rtol=None):
    """Our step with solver=pcg; with ``rtol``, the simulator steps with a PCG backend of that tolerance."""
    name = "ours (PCG)" if rtol is None else f"ours (PCG rtol {rtol:g})"

    def run(problem, h, energy_cap=None, budget=None):
        p2 = make_problem(problem.case, problem.T, problem.sample_dt, ["solver=pcg"])
        if rtol is not None:
            p2.sim.backend = make_backend(p2.sim.mech, "pcg", rtol=rtol)
        return run_ours(p2, h, energy_cap=energy_cap, budget=budget, name=name, require_solver="pcg")
    return run


def _ours_bdf2(problem, h, energy_cap=None, budget=None):
    """Our step with integrator.scheme bdf2 (step/scheme.py), the prescribed joint's rate at each step's end."""
    p2 = make_problem(problem.case, problem.T, problem.sample_dt, ["integrator.scheme=bdf2"])
    return run_ours(p2, h, energy_cap=energy_cap, budget=budget, name="ours BDF2 (direct)", rate=end_rate)


register_method("ours (direct)", lambda p, h, **kw: run_ours(p, h, **kw), color="C3", marker="o", lw=2.2)
register_method("ours BDF2 (direct)", _ours_bdf2, color="C1", marker="*", lw=2.2, ms=8)
for _tol, _c in ((1e-4, "#f4a259"), (1e-8, "#c0661b")):  # PCG at several tolerances
    register_method(f"ours (PCG rtol {_tol:g})", _ours_pcg(_tol), _pcg_applies, color=_c, marker="o", ms=4)
register_method("semi-implicit Euler (Pinocchio)", lambda p, h, **kw: run_explicit(p, h, "sie", name="semi-implicit Euler (Pinocchio)", **kw),
                _pinocchio_applies, color="C0", marker="s")
register_method("RK4 (Pinocchio)", lambda p, h, **kw: run_explicit(p, h, "rk4", name="RK4 (Pinocchio)", **kw),
                _pinocchio_applies, color="C2", marker="^")
register_method("maximal + Baumgarte", lambda p, h, **kw: run_maximal(p, h, **kw), _maximal_applies, color="C4", marker="D")
register_method("MuJoCo Euler", lambda p, h, **kw: run_mujoco(p, h, "euler", **kw), _mujoco_applies, color="C7", marker="v", ls="--")
register_method("MuJoCo implicitfast", lambda p, h, **kw: run_mujoco(p, h, "implicitfast", **kw), _mujoco_applies,
                color="C5", marker="P", ls="--")
register_method("MuJoCo RK4", lambda p, h, **kw: run_mujoco(p, h, "rk4", **kw), _mujoco_applies, color="C8", marker="X", ls="--")
register_method("Exudyn generalized-alpha", run_exudyn, _exudyn_applies, color="C6", marker="h", ls="-.")
register_method("MuJoCo discrete", lambda p, h, **kw: run_mujoco(p, h, "discrete", **kw), _mujoco_applies,
                color="C9", marker="s", ls="--")  # MuJoCo 3.13+: implicit in joint/tendon stiffness


# ---------------------------------------------------------------------------------------------
# reference solutions and errors


@dataclass
class Reference:
    h: float
    halving_diff: float  # max over samples of the RMS joint difference between h and 2h runs
    t: np.ndarray
    q: np.ndarray
    E: np.ndarray
    tau: np.ndarray | None
    E0: float
    method: str
    wall: float


def _cache_key(problem):
    c = problem.case
    raw = repr((c.name, c.scene, list(c.overrides), problem.T, problem.sample_dt, c.h_ref,
                problem.q0.round(14).tolist(), problem.vR0.round(14).tolist()))
    return hashlib.sha1(raw.encode()).hexdigest()[:16]


def reference(problem, tol=1e-9, h_min=1e-6, use_cache=True, log=print, cache_dir=None) -> Reference:
    """RK4 on the Pinocchio dynamics (aba / constraintDynamics without Baumgarte / hybrid split),
    halving h until two successive runs differ by less than ``tol`` (max over samples of the RMS
    joint difference); the finer run is the reference. Cached (``use_cache``) in ``cache_dir``,
    by default :func:`default_cache_dir`."""
    cache = default_cache_dir() if cache_dir is None else Path(cache_dir)
    path = cache / f"{problem.case.name}-{_cache_key(problem)}.npz"
    if use_cache and path.exists():
        z = np.load(path, allow_pickle=False)
        return Reference(float(z["h"]), float(z["diff"]), z["t"], z["q"], z["E"], z["tau"] if z["tau"].size else None,
                         float(z["E0"]), str(z["method"]), float(z["wall"]))
    mech = problem.mech
    model = mech.model
    E0 = baselines.mechanical_energy(mech, Workspace(mech, pin_data=True), problem.q0, mech.to_reduced(problem.vR0))
    h = problem.case.h_ref
    t0, c0 = time.perf_counter(), time.process_time()
    prev = run_explicit(problem, h, "rk4", baumgarte=False, name="reference")
    while True:
        cur = run_explicit(problem, h / 2, "rk4", baumgarte=False, name="reference")
        if prev.status != "ok" or cur.status != "ok":
            diff = float("inf")
        else:
            diff = max(_rms(pin.difference(model, a, b)) for a, b in zip(prev.q, cur.q))
        log(f"    reference {problem.case.name}: h = {h:.3g} vs {h / 2:.3g}: diff {diff:.2e}")
        h /= 2
        if diff < tol or h / 2 < h_min:
            break
        prev = cur
    what = "RK4 on " + ("the hybrid split (rnea)" if problem.hybrid else
                        "pin.constraintDynamics" if len(mech.loop_ab) else "pin.aba")
    ref = Reference(h, diff, np.array(cur.t), np.array(cur.q), np.array(cur.E),
                    np.array(cur.tau) if cur.tau else None, E0, what, time.perf_counter() - t0)
    if use_cache:
        cache.mkdir(parents=True, exist_ok=True)
        np.savez(path, h=ref.h, diff=diff, t=ref.t, q=ref.q, E=ref.E,
                 tau=ref.tau if ref.tau is not None else np.zeros(0), E0=E0, method=what, wall=ref.wall)
    return ref


def _rms(x):
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x))) if x.size else 0.0


def errors(problem, ref: Reference, run: Run) -> dict:
    model = problem.mech.model
    n = len(run.q)
    out = {"samples": n, "complete": n == len(ref.q) and run.status == "ok"}
    if n == 0:
        return out
    e = [_rms(pin.difference(model, ref.q[k], run.q[k])) if np.all(np.isfinite(run.q[k])) else float("inf")
         for k in range(n)]
    out["state_max"] = float(max(e))
    out["state_final"] = float(e[-1])
    if problem.case.probe is not None and out["complete"]:  # |error| of one joint at t = T [rad, m]
        j = problem.mech.joint_index[problem.case.probe]
        d = pin.difference(model, ref.q[-1], run.q[-1])
        out["probe_final"] = float(np.abs(d[j.idx_v:j.idx_v + j.nv]).max())
    E = np.asarray(run.E)
    out["energy_drift"] = float(np.nanmax(np.abs(E - ref.E0))) if E.size else None
    out["energy_final"] = float(E[-1] - ref.E0) if E.size else None
    out["violation_max"] = float(np.nanmax(run.viol)) if run.viol else 0.0
    if ref.tau is not None and run.tau:
        de = np.abs(np.asarray(run.tau) - ref.tau[:len(run.tau)])
        out["torque_max"] = float(de.max())
        out["torque_final"] = float(de[-1])
    return out
