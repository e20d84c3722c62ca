"""Simulator: the stateful facade used by the runner, the node and the benchmarks.

It owns a Mechanism (frozen), a stepping backend with its Workspace (step/backends.py), the current
State and the current Commands, and validates every command before changing anything
(CommandError). Stepping goes through step.pipeline.step; the state is replaced only when a step
succeeds. Every step is held to ``budget`` (a solvers/budget.StepBudget: 50 ms of CPU time for its
iterative solvers, ProxSuite iteration caps; None for unlimited), past which it fails with
StepError("step budget exceeded: ...").
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.dynamics.energy import energies
from redmax_ros.core.dynamics.tree_kinematics import Context, all_site_positions, body_poses
from redmax_ros.core.errors import CommandError, SceneError, StepError
from redmax_ros.core.model.collision import shape_poses
from redmax_ros.core.model.dof_positions import DofPositions
from redmax_ros.core.model.mechanism import Mechanism
from redmax_ros.core.scene.loader import load_scene, parse_joint_trajectory, parse_time_function
from redmax_ros.core.scene.spec import SceneSpec
from redmax_ros.core.solvers.budget import StepBudget
from redmax_ros.core.step.backends import check_dense_size, make_backend
from redmax_ros.core.step import body_twist, trajectory
from redmax_ros.core.step.compile import compile_scene
from redmax_ros.core.step.deformable_stages import deform_state
from redmax_ros.core.step.state import BatchResult, Commands, Rollout, State, StepResult, step_each


_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def _axes_matrix(site, axes) -> np.ndarray:
    """(k,3) unit world directions from ['x', 'z'] or vectors; CommandError if malformed or dependent."""
    try:
        P = np.array([_AXES[a] if isinstance(a, str) else a for a in axes], dtype=float).reshape(-1, 3)
    except (KeyError, ValueError, TypeError):
        raise CommandError(f"axes of site '{site}' must be 'x', 'y', 'z' or 3-vectors, got {axes!r}") from None
    n = np.linalg.norm(P, axis=1) if len(P) else np.zeros(0)
    if not 1 <= len(P) <= 3 or not np.all(np.isfinite(P)) or np.any(n < 1e-12):
        raise CommandError(f"axes of site '{site}' must be 1-3 non-zero directions, got {axes!r}")
    P = P / n[:, None]
    if np.linalg.matrix_rank(P) < len(P):
        raise CommandError(f"axes of site '{site}' must be linearly independent, got {axes!r}")
    return P


@dataclass
class Coupling:
    name: str
    joints: list
    ratios: list


@dataclass
class SceneDescription:
    name: str
    nq: int
    nv: int
    ndof: int
    bodies: list
    joint_names: list
    joint_types: list
    joint_nq: list
    joint_nv: list
    position_names: list
    velocity_names: list
    sites: list
    site_bodies: list
    prescribable_joints: list
    prescribable_sites: list
    couplings: list
    loops: list
    springs: list
    dt: float
    dof_positions: object = None  # dof_positions.DofPositions: one position per velocity DOF (joint_states)
    deformables: list = field(default_factory=list)  # (name, kind 'string'|'fem', vertices, elements) per deformable


def _mapping(what, value) -> dict:
    """``value`` if it is a mapping name -> value, else CommandError."""
    if not isinstance(value, dict):
        raise CommandError(f"{what} must be a mapping of names to values, got {value!r}")
    return value


def _names(what, value) -> list:
    """``value`` as a list of names (a list, tuple or set of strings), else CommandError."""
    if not isinstance(value, (list, tuple, set, frozenset)) or not all(isinstance(n, str) for n in value):
        raise CommandError(f"{what} must be a list of names, got {value!r}")
    return list(value)


def _step_count(n) -> int:
    """n as a step count (an integer >= 1, given as an int or an integral float), else CommandError."""
    if type(n) is int and 1 <= n <= MAX_STEPS:  # the common case, without the checks below
        return n
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, float, np.integer, np.floating)) \
            or not math.isfinite(n) or int(n) != n or not 1 <= n <= MAX_STEPS:
        raise CommandError(f"step count must be a positive integer (at most {MAX_STEPS}), got {n!r}")
    return int(n)


def _linalg_reason(e) -> str:
    return (f"linear algebra failed ({e}); the numbers overflowed or are degenerate (a huge position, size, "
            f"stiffness or time step?)")


MAX_STEPS = 2 ** 62  # steps of one call (the kernels count them in int64)
RECORD_ROWS = 4096  # steps recorded per kernel call by step_results (the record array: rows x ~10^2 floats)
DEFAULT_BUDGET = StepBudget()  # 50 ms CPU time of the iterative solvers (JIT excluded), QP caps 1000 / 50


class Simulator:
    def __init__(self, spec: SceneSpec, solver: str | None = None, budget: StepBudget | None = DEFAULT_BUDGET):
        self.spec = spec
        self.budget = budget
        check_dense_size(spec.source, solver or spec.solver, sum(j.nv for j in spec.joints))  # before the compile
        try:
            self.mech: Mechanism = compile_scene(spec)
        except np.linalg.LinAlgError as e:
            raise SceneError(spec.source, "scene", f"the model cannot be set up: {_linalg_reason(e)}") from None
        # solver: the scene's 'solver' key (direct | pcg | auto) unless overridden; see docs/solvers.md
        self.backend = make_backend(self.mech, solver or spec.solver)
        self._query = Context(self.mech)  # kinematics for body poses, spring ends, energies between steps
        self._shape_data = None  # pin.Data for collision_shapes (made on first use)
        self._surfaces = None  # deformable_surfaces, found on first use
        self.dt = float(spec.dt)
        for name, traj in spec.prescribed_trajectories.items():
            entry = f"prescribed.joints.{name}"
            if name not in self.mech.joint_index:
                raise SceneError(spec.source, entry, f"unknown joint '{name}'")
            problem = trajectory.trajectory_problem(self.mech, name, traj)
            if problem:
                raise SceneError(spec.source, entry, problem)
        try:
            self._check_body_path(list(spec.prescribed_bodies), ValueError)
        except ValueError as e:
            raise SceneError(spec.source, "prescribed.bodies", str(e)) from None
        self.reset()

    @classmethod
    def load(cls, name_or_path: str, overrides=(), solver: str | None = None, *, allowed_dirs=None,
             budget: StepBudget | None = DEFAULT_BUDGET) -> "Simulator":
        """Load a scene by name (scenes/) or path; ``overrides``: ["key=value", ...]. Raises SceneError.
        ``allowed_dirs``: see ``load_scene`` (None: any path; a list: only scenes in scenes/ and there).
        ``budget``: the step budget (StepBudget; None: unlimited)."""
        return cls(load_scene(name_or_path, overrides, allowed_dirs=allowed_dirs), solver, budget)

    @property
    def budget(self) -> StepBudget | None:
        """The work each step may do (solvers/budget.StepBudget), None for unlimited; settable, e.g.
        ``sim.budget = StepBudget(cpu_time=0.02)`` or ``sim.budget = StepBudget.from_ms(ms)``."""
        return self._budget

    @budget.setter
    def budget(self, value: StepBudget | None) -> None:
        if value is not None and not isinstance(value, StepBudget):
            raise CommandError(f"budget must be a StepBudget or None, got {value!r}")
        self._budget = value

    # -- state
    @property
    def scene_name(self) -> str:
        return self.spec.name

    @property
    def time(self) -> float:
        return self.state.t

    @property
    def workspace(self):
        """The stepping backend's Workspace (step/workspace.py; with solver 'auto', that of the backend
        stepping now)."""
        return self.backend.workspace

    @property
    def data(self):
        """pin.Data of the Pinocchio pipeline's workspace; None while a data-free backend steps."""
        return self.backend.workspace.data

    def reset(self) -> None:
        """Initial state, t = 0, the scene's default prescriptions, no applied torques or forces."""
        m = self.mech
        self.state = State(0.0, m.q0.copy(), m.v0.copy())
        self.backend.at_state(self.state.q, 0.0)  # J_rR of spline/exp joints back at q0 (refreshed in place by steps)
        self.commands = Commands(
            joint_velocities={k: np.array(v, float) for k, v in self.spec.prescribed_joints.items()},
            site_velocities={k: np.array(v, float) for k, v in self.spec.prescribed_sites.items()},
            site_axes={k: np.array(P, float) for k, P in self.spec.prescribed_site_axes.items()},
            joint_torques=np.zeros(m.nv),
            joint_trajectories=dict(self.spec.prescribed_trajectories),
            body_twists=dict(self.spec.prescribed_bodies),
        )
        self.last: StepResult | None = None

    def _checked_state(self, state, what="state") -> State:
        """``state`` with q (nq,) and v (ndof,) as float arrays, or CommandError naming what does not fit this
        scene (non-finite values are the step's to report)."""
        if not isinstance(state, State):
            raise CommandError(f"{what} must be a State, got {type(state).__name__}")
        m = self.mech
        arrays = {}
        for key, ref in (("q", m.q0), ("v", m.v0)):
            x = getattr(state, key)
            try:
                a = np.asarray(x, dtype=float)
            except (TypeError, ValueError):
                a = None
            if a is None or a.shape != ref.shape:
                shape = None if a is None else a.shape
                raise CommandError(f"{what}.{key} must be {len(ref)} numbers for scene '{self.scene_name}', got "
                                   f"{type(x).__name__} of shape {shape}")
            arrays[key] = a if a is x else a.copy()
        t = state.t
        if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) or not math.isfinite(t):
            raise CommandError(f"{what}.t must be a finite number, got {t!r}")
        if state.t0 is not None and not (isinstance(state.t0, (int, float, np.floating)) and math.isfinite(state.t0)):
            raise CommandError(f"{what}.t0 must be None or a finite number, got {state.t0!r}")
        if isinstance(state.k, bool) or not isinstance(state.k, (int, np.integer)) or not 0 <= state.k <= MAX_STEPS:
            raise CommandError(f"{what}.k must be a step count >= 0, got {state.k!r}")
        if arrays["q"] is state.q and arrays["v"] is state.v:
            return state
        return dataclasses.replace(state, **arrays)

    def set_state(self, state: State) -> None:
        """Make ``state`` the current state; CommandError (nothing changed) if it does not fit the scene."""
        state = self._checked_state(state)
        self.backend.at_state(state.q, state.t)  # configuration-dependent J_rR at the new configuration
        self.state = state

    def joint_positions(self) -> np.ndarray:
        return self.state.q.copy()

    def joint_velocities(self) -> np.ndarray:
        """Reduced joint velocities qdot_r = J_rR qdot_R (nv,) of the current state [rad/s, m/s]."""
        return self.backend.workspace.to_reduced(self.state.v).copy()

    def energies(self) -> tuple:
        """(E_kin, E_pot, E_spring) [J] of the current state (as the step's diagnostics compute them; with
        deformables their kinetic, gravitational and elastic energies are included)."""
        ek, ep, es = energies(self.mech, self.backend.workspace, self.state.q, self.joint_velocities())
        dm = self.deformables
        if dm is not None:
            ds = deform_state(dm, self.state)
            dk, dg, de = dm.energies(ds.x, ds.v)
            ek, ep, es = ek + dk, ep + dg, es + de
        return ek, ep, es

    # -- commands
    @staticmethod
    def _floats(what, value) -> np.ndarray:
        """``value`` (a number or a list of numbers) as a 1-d float array, else CommandError naming ``what``."""
        if isinstance(value, (str, bytes, dict)) or value is None:
            raise CommandError(f"{what}: expected a number or a list of numbers, got {value!r}")
        try:
            return np.atleast_1d(np.asarray(value, dtype=float))
        except (TypeError, ValueError):
            raise CommandError(f"{what}: expected a number or a list of numbers, got {value!r}") from None

    def _joint_vector(self, name, value, allowed=None, what="joint"):
        m = self.mech
        if not isinstance(name, str) or name not in m.joint_index:
            raise CommandError(f"unknown joint '{name}' (known: {', '.join(m.joint_index)})")
        if allowed is not None and name not in allowed:
            raise CommandError(f"joint '{name}' is not prescribable in scene '{self.scene_name}' "
                               f"(prescribable: {', '.join(allowed)})")
        nv = m.joint_index[name].nv
        arr = self._floats(f"{what} '{name}'", value)
        if arr.shape != (nv,):
            raise CommandError(f"{what} '{name}' needs {nv} value(s), got {arr.size}")
        if not np.all(np.isfinite(arr)):
            raise CommandError(f"{what} '{name}': non-finite value {arr.tolist()}")
        return arr

    def _site_vector(self, name, value, allowed=None, what="site"):
        m = self.mech
        if not isinstance(name, str) or name not in m.site_index:
            raise CommandError(f"unknown site '{name}' (known: {', '.join(m.site_names)})")
        if allowed is not None and name not in allowed:
            raise CommandError(f"site '{name}' is not prescribable in scene '{self.scene_name}' "
                               f"(prescribable: {', '.join(allowed)})")
        arr = self._floats(f"{what} '{name}'", value).reshape(-1)
        if arr.shape != (3,):
            raise CommandError(f"{what} '{name}' needs 3 values, got {arr.size}")
        if not np.all(np.isfinite(arr)):
            raise CommandError(f"{what} '{name}': non-finite value {arr.tolist()}")
        return arr

    def _joint_trajectory(self, name, d):
        """A validated JointTrajectory from ``{position: <time function(s)>, b: 5}`` (CommandError)."""
        m = self.mech
        self._joint_vector(name, np.zeros(m.joint_index[name].nv) if name in m.joint_index else 0.0,
                           m.prescribable_joints, "trajectory of joint")  # unknown / not prescribable
        try:
            traj = parse_joint_trajectory(f"trajectory of joint '{name}'", d, m.joint_index[name].nv)
        except SceneError as e:
            raise CommandError(f"{e.entry}: {e.problem}") from None
        problem = trajectory.trajectory_problem(m, name, traj)
        if problem:
            raise CommandError(problem)
        return traj

    def prescribe_joints(self, prescriptions: dict) -> None:
        """Prescribe joint motions (hybrid dynamics, Eq. 7, *G_r; notes §2.10). All-or-nothing. A value is

        * a velocity [rad/s or m/s] (a number, or nv of them): the row *G_r qdot_r = value, held; or
        * a trajectory ``{position: <time function, or a list of nv>, b: 5}`` in the scene grammar
          (docs/scenes.md, scene/timefunctions.py): each step's row is *G_r qdot_r = qdot_p(t_k+1) +
          b (q_p(t_k+1) - q_k), b >= 0 [1/s] (step/trajectory.py).

        Either replaces the joint's previous prescription; the required torque is ``StepResult.effort``."""
        vel, traj = {}, {}
        for n, v in _mapping("joint prescriptions", prescriptions).items():
            if isinstance(v, dict):
                traj[n] = self._joint_trajectory(n, v)
            else:
                vel[n] = self._joint_vector(n, v, self.mech.prescribable_joints, "prescribed velocity of joint")
        cmd = self.commands
        for n in vel:
            cmd.joint_trajectories.pop(n, None)
        for n in traj:
            cmd.joint_velocities.pop(n, None)
        cmd.joint_velocities.update(vel)
        cmd.joint_trajectories.update(traj)

    def release_joints(self, names) -> None:
        names = _names("joints to release", names)
        for n in names:
            if n not in self.mech.joint_index:
                raise CommandError(f"unknown joint '{n}'")
        for n in names:
            self.commands.joint_velocities.pop(n, None)
            self.commands.joint_trajectories.pop(n, None)

    def prescribe_sites(self, velocities: dict, axes: dict | None = None) -> None:
        """Prescribe site (point) velocities, world frame [m/s] (Eq. 7, *G_m = point Jacobian).

        ``axes`` {site: directions} imposes the velocity only along those world directions ('x', 'y',
        'z' or unit vectors), e.g. ['x', 'z'] for a planar mechanism moving in the xz plane; sites
        without an entry are prescribed along all three."""
        new = {n: self._site_vector(n, v, self.mech.prescribable_sites, "prescribed velocity of site")
               for n, v in _mapping("site velocities", velocities).items()}
        new_axes = {}
        for n, ax in _mapping("site axes", axes or {}).items():
            if n not in new:
                raise CommandError(f"axes given for site '{n}' without a velocity")
            new_axes[n] = _axes_matrix(n, ax)
        for n in new:
            self.commands.site_axes.pop(n, None)
        self.commands.site_velocities.update(new)
        self.commands.site_axes.update(new_axes)

    def release_sites(self, names) -> None:
        names = _names("sites to release", names)
        for n in names:
            if n not in self.mech.site_index:
                raise CommandError(f"unknown site '{n}'")
        for n in names:
            self.commands.site_velocities.pop(n, None)
            self.commands.site_axes.pop(n, None)

    def _check_body_path(self, names, exc):
        if names and self.backend.workspace.data is None:
            raise exc(f"body-twist prescriptions ({', '.join(names)}) need the Pinocchio pipeline (solver 'direct' "
                      f"with at most 100 DOFs); scene '{self.scene_name}' steps on the data-free path "
                      f"(backend {getattr(self.backend, 'name', type(self.backend).__name__)})")

    def prescribe_bodies(self, twists: dict) -> None:
        """Prescribe components of body twists (maximal hybrid dynamics, Eq. 7, *G_m = the body's 6 x nv
        twist Jacobian): ``{body: {"angular": [wx, wy, wz], "linear": [vx, vy, vz], "frame": "body" | "world"}}``
        with 'angular' [rad/s] and/or 'linear' [m/s, velocity of the body origin]; frame 'body' (default)
        or 'world' (world-aligned axes at the body origin). A component is a number (constant), None (free)
        or a time function of the scene grammar (``{"type": "sine", ...}``, scene/timefunctions.py)
        evaluated at the end time t_k+1 of every step. Held until released; replaces the body's previous
        prescription; all-or-nothing (CommandError naming the body and component). The required wrench is
        ``StepResult.body_wrenches[body]`` (6,) [torque N m; force N] in the prescription's frame.
        Pinocchio pipeline only (CommandError on the data-free path)."""
        new = {}
        for n, d in _mapping("body twists", twists).items():
            entry = f"body '{n}'"
            try:
                new[n] = body_twist.parse(n, d, self.mech.bodies,
                                          lambda key, x, entry=entry: parse_time_function(entry, key, x))
            except ValueError as e:
                raise CommandError(f"prescribed twist: {e}") from None
            except SceneError as e:
                raise CommandError(f"prescribed twist: {e.entry}: {e.problem}") from None
        self._check_body_path(list(new), CommandError)
        self.commands.body_twists.update(new)

    def release_bodies(self, names) -> None:
        """Release body-twist prescriptions (CommandError for unknown bodies; not prescribed: no-op)."""
        names = _names("bodies to release", names)
        for n in names:
            if n not in self.mech.bodies:
                raise CommandError(f"unknown body '{n}'")
        for n in names:
            self.commands.body_twists.pop(n, None)

    def prescribed_bodies(self) -> dict:
        """Prescribed body -> {components: [...], values (k,), frame}; timed components at the end time of
        the next step, t_k+1 (what its rows impose)."""
        names = ("wx", "wy", "wz", "vx", "vy", "vz")
        t1 = self.state.time_after(self.dt)
        return {n: {"components": [names[int(np.argmax(r))] for r in bt.P], "values": bt.at(t1).g.copy(),
                    "frame": bt.frame} for n, bt in self.commands.body_twists.items()}

    def set_joint_torques(self, torques: dict) -> None:
        """Explicit applied joint torques [N m or N], held until changed."""
        new = {n: self._joint_vector(n, v, None, "torque of joint") for n, v in _mapping("joint torques", torques).items()}
        tau = self.commands.joint_torques.copy()
        for n, v in new.items():
            j = self.mech.joint_index[n]
            tau[j.idx_v:j.idx_v + j.nv] = v
        self.commands.joint_torques = tau

    def set_site_forces(self, forces: dict) -> None:
        """Explicit world-frame forces [N] at sites, held until changed (empty dict clears)."""
        new = {n: self._site_vector(n, f, None, "force on site") for n, f in _mapping("site forces", forces).items()}
        self.commands.site_forces = new

    def restore_prescriptions(self, joints=(), sites=(), bodies=()) -> None:
        """Joints and sites back to the scene's own prescription (its ``prescribed:`` entry, as after
        reset), or to passive dynamics where the scene prescribes none. CommandError for unknown names."""
        joints, sites, bodies = _names("joints", joints), _names("sites", sites), _names("bodies", bodies)
        for n in joints:
            if n not in self.mech.joint_index:
                raise CommandError(f"unknown joint '{n}'")
        for n in sites:
            if n not in self.mech.site_index:
                raise CommandError(f"unknown site '{n}'")
        for n in bodies:
            if n not in self.mech.bodies:
                raise CommandError(f"unknown body '{n}'")
        spec, cmd = self.spec, self.commands
        for n in bodies:
            cmd.body_twists.pop(n, None)
            if n in spec.prescribed_bodies:
                cmd.body_twists[n] = spec.prescribed_bodies[n]
        for n in joints:
            cmd.joint_velocities.pop(n, None)
            cmd.joint_trajectories.pop(n, None)
            if n in spec.prescribed_joints:
                cmd.joint_velocities[n] = np.array(spec.prescribed_joints[n], float)
            elif n in spec.prescribed_trajectories:
                cmd.joint_trajectories[n] = spec.prescribed_trajectories[n]
        for n in sites:
            cmd.site_axes.pop(n, None)
            if n in spec.prescribed_sites:
                cmd.site_velocities[n] = np.array(spec.prescribed_sites[n], float)
                if n in spec.prescribed_site_axes:
                    cmd.site_axes[n] = np.array(spec.prescribed_site_axes[n], float)
            else:
                cmd.site_velocities.pop(n, None)

    def prescribed_joints(self) -> dict:
        """Prescribed joint -> the velocity its rows impose on the next step [rad/s, m/s]: the held value,
        or for a trajectory qdot_p(t_k+1) + b (q_p(t_k+1) - q_k) at the current state (step order:
        velocities, then trajectories)."""
        out = {k: v.copy() for k, v in self.commands.joint_velocities.items()}
        if self.commands.joint_trajectories:
            t1 = self.state.time_after(self.dt)
            for k, tr in self.commands.joint_trajectories.items():
                out[k] = trajectory.joint_rate(self.mech, k, tr, self.state.q, t1)
        return out

    def joint_trajectories(self) -> dict:
        """Joints following a position trajectory -> their scene.timefunctions.JointTrajectory (``position(t)``,
        ``velocity(t)``, ``b``)."""
        return dict(self.commands.joint_trajectories)

    def prescribed_sites(self) -> dict:
        return {k: v.copy() for k, v in self.commands.site_velocities.items()}

    # -- stepping
    def _failure(self, e, steps_done: int) -> StepError:
        """The StepError that step, step_results and rollout raise for a failed step: its time and reason (a
        LinAlgError: non-finite numbers reaching a factorisation, huge scene values), after ``steps_done`` steps."""
        reason = e.reason if isinstance(e, StepError) else _linalg_reason(e)
        return StepError(f"step at t = {self.state.t:.6g} s failed: {reason}", steps_done=steps_done)

    def step(self, n: int = 1) -> StepResult:
        """Advance n steps; returns the last StepResult. On StepError the state is that after the last
        successful step (``err.steps_done`` of them); the failing step changed nothing."""
        n = _step_count(n)
        res = None
        run = getattr(self.backend, "step_run", None)  # the compiled backend: runs of steps in one call
        done = 0
        while done < n:
            try:
                if run is None:
                    self.state, res = self.backend.step(self.state, self.commands, self.dt, self._budget)
                    k = 1
                else:
                    self.state, res, k = run(self.state, self.commands, self.dt, int(n) - done, self._budget)
            except (StepError, np.linalg.LinAlgError) as e:
                raise self._failure(e, done) from None
            done += k
            self.last = res
        return res

    def step_results(self, n: int = 1) -> list:
        """Advance n steps; returns every step's StepResult, in order (``step`` returns the last one). On the
        compiled path each run of steps is one kernel call that records every step's outputs, so a result
        per step costs no step call of its own (the node publishing joint_states every step). The results are
        those of n single steps (test_step_results.py). On StepError the state is that after the last
        successful step (``err.steps_done`` of them) and ``err.results`` holds their results."""
        n = _step_count(n)
        out = []
        run = getattr(self.backend, "step_run", None)
        while len(out) < n:
            try:
                if run is None:
                    self.state, res = self.backend.step(self.state, self.commands, self.dt, self._budget)
                    out.append(res)
                else:
                    self.state, res, _ = run(self.state, self.commands, self.dt, min(int(n) - len(out), RECORD_ROWS),
                                             self._budget, record=True)
                    out.extend(res)
            except (StepError, np.linalg.LinAlgError) as e:
                err = self._failure(e, len(out))
                err.results = out
                raise err from None
            self.last = out[-1]
        return out

    def rollout(self, n: int = 1, every: int = 1) -> Rollout:
        """Advance n * every steps; returns the outputs of every ``every``-th step (n rows) stacked in arrays, a
        Rollout whose rows hold the numbers step_results gives for those steps (test_rollout.py). On the compiled
        path each run of steps is one kernel call that records only those steps, and under BDF2 computes the
        energies of those steps only: no Python object per step, the way to take long trajectories (sweeps,
        work-precision runs). On StepError the state is that after the last successful step (``err.steps_done``
        of them) and ``err.rollout`` holds the rows recorded before it (or None)."""
        n = _step_count(n)
        try:
            every = _step_count(every)
        except CommandError:
            raise CommandError(f"rollout's every (steps per recorded row) must be a positive integer, got {every!r}") from None
        parts, rows, phase, done = [], 0, 0, 0
        run = getattr(self.backend, "rollout_run", None)
        while rows < n:
            try:
                if run is None:
                    self.state, res = self.backend.step(self.state, self.commands, self.dt, self._budget)
                    part, k = (Rollout.from_results([res]) if phase + 1 == every else None), 1
                else:
                    steps = min((n - rows) * every - phase, RECORD_ROWS * every)
                    self.state, part, k = run(self.state, self.commands, self.dt, steps, every, phase, self._budget)
            except (StepError, np.linalg.LinAlgError) as e:
                err = self._failure(e, done)
                err.rollout = Rollout.concatenate(parts) if parts else None
                raise err from None
            done += k
            phase = (phase + k) % every
            if part is not None:
                parts.append(part)
                rows += len(part)
                self.last = part.last
        return Rollout.concatenate(parts)

    def step_batch(self, states, n: int = 1):
        """Advance each of the independent ``states`` (of this scene) by n steps with this simulator's commands
        and dt; the simulator's own state is untouched. On the compiled path the instances run in parallel in
        one call, each bitwise equal to stepping it alone. Returns a BatchResult (states, steps_done, errors:
        None or the StepError message that stopped an instance, whose state is from before that step)."""
        n = _step_count(n)
        if not isinstance(states, (list, tuple)):
            raise CommandError(f"states must be a list of State, got {type(states).__name__}")
        states = [self._checked_state(s, f"states[{i}]") for i, s in enumerate(states)]
        if not states:
            return BatchResult([], np.zeros(0, dtype=np.int64), [])
        batch = getattr(self.backend, "step_batch", None)
        try:
            if batch is not None:
                return batch(list(states), self.commands, self.dt, int(n), self._budget)
            return step_each(self.backend.step, list(states), self.commands, self.dt, int(n), self._budget)
        except np.linalg.LinAlgError as e:
            raise StepError(f"batch step failed: {_linalg_reason(e)}") from None

    # -- description and geometry for markers
    def describe(self) -> SceneDescription:
        m = self.mech
        site_bodies = [s.body for s in self.spec.sites]
        return SceneDescription(
            name=self.scene_name, nq=m.nq, nv=m.nv, ndof=m.ndof, bodies=list(m.bodies),
            joint_names=[j.name for j in m.joints], joint_types=[j.type for j in m.joints],
            joint_nq=[j.nq for j in m.joints], joint_nv=[j.nv for j in m.joints],
            position_names=m.position_names(), velocity_names=m.velocity_names(),
            sites=list(m.site_names), site_bodies=site_bodies,
            prescribable_joints=list(m.prescribable_joints), prescribable_sites=list(m.prescribable_sites),
            couplings=[Coupling(c.name, list(c.joints), c.ratios.tolist()) for c in self.spec.couplings],
            loops=list(m.loop_names), springs=list(m.spring_names), dt=self.dt,
            dof_positions=DofPositions.from_model(m.model),
            deformables=self.deformables.describe() if self.deformables is not None else [],
        )

    # -- deformables (docs/deformables.md)
    @property
    def deformables(self):
        """The scene's deformable.system.Deformables (None without deformables)."""
        return getattr(self.backend, "deformables", None)

    def deformable_positions(self) -> dict:
        """name -> (n,3) world vertex positions [m] of each deformable at the current state."""
        dm = self.deformables
        if dm is None:
            return {}
        x = deform_state(dm, self.state).x
        return {n: dm.part(i, x).copy() for i, n in enumerate(dm.names)}

    def deformable_surfaces(self) -> dict:
        """name -> (F,3) vertex indices of each deformable's boundary triangles (FEM) or (S,2) segments (string),
        indices into deformable_positions()[name] (for TRIANGLE_LIST / LINE_LIST markers)."""
        dm = self.deformables
        if dm is None:
            return {}
        if self._surfaces is None:  # constant per scene: the boundary faces are found once (np.unique over all faces)
            self._surfaces = {n: (e.surface() if e.kind == "fem" else e.seg) for n, e in zip(dm.names, dm.elements)}
        return {n: f.copy() for n, f in self._surfaces.items()}

    def deformable_report(self) -> dict | None:
        """{E_kin, E_grav, E_elastic [J], attachment_drift [m]} of the deformables at the current state (the
        drift: what the last step left before the post-stabilization), None without deformables."""
        dm = self.deformables
        if dm is None:
            return None
        ds = deform_state(dm, self.state)
        ek, eg, ee = dm.energies(ds.x, ds.v)
        return {"E_kin": ek, "E_grav": eg, "E_elastic": ee, "attachment_drift": self.backend.timing["attachment_drift"]}

    def body_poses(self) -> dict:
        """Body frames in the world: name -> (position (3,) [m], quaternion xyzw (4,))."""
        return body_poses(self._query, self.state.q)

    def collision_shapes(self) -> list:
        """model.collision.ShapePose of every primitive collision shape (spheres, boxes, cylinders, capsules) at
        the current state; [] without a collision section (docs/collisions.md)."""
        if self.mech.collision is None:
            return []
        if self._shape_data is None:
            self._shape_data = self.mech.model.createData()
        return shape_poses(self.mech, self._shape_data, self.state.q)

    def site_positions(self) -> np.ndarray:
        """World positions (S,3) [m] of every site (mech.site_names order) at the current state."""
        return all_site_positions(self._query, self.state.q).copy()

    def spring_segments(self) -> list:
        """(spring name, end a (3,), end b (3,)) world frame [m]."""
        m = self.mech
        x = all_site_positions(self._query, self.state.q)
        return [(n, x[a].copy(), x[b].copy()) for n, (a, b) in zip(m.spring_names, m.spring_ab)]
