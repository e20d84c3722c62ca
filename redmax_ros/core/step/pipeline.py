"""One RedMax step as a pure function of (mechanism, state, commands, h) -> (new state, result).

Stages (each a small module, in the spirit of Brax/MJX pipelines):
  1. kinematics.compute   Pinocchio CRBA/RNEA/Jacobians, site positions and point Jacobians
  2. forces.assemble      LHS/RHS of Eq. (2) (implicit/explicit, reduced/maximal), T-projected (Eq. 9-10)
  3. constraints.build    bilateral rows (loops, Eq. 7 prescriptions) and joint limits (Eq. 5)
  4. solve.solve_direct   Cholesky / KKT Schur complement / ProxSuite QP
  5. configuration update on the manifold, q+ = integrate(q, h qdot+), loop post-stabilization
  6. outputs              required torques *f_r = *G_r^T lam / h and point forces (Eq. 7), energies

The pin.Data passed in is a workspace only; the returned State is new, the input is never modified,
so a StepError leaves the caller's state exactly as it was.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics import constraints
from redmax_ros.core.dynamics import forces
from redmax_ros.core.dynamics import kinematics
from redmax_ros.core.dynamics import stabilization
from redmax_ros.core.friction import staggered
from redmax_ros.core.dynamics.energy import energies
from redmax_ros.core.errors import StepError
from redmax_ros.core.solvers.kkt import max_row_residual
from redmax_ros.core.solvers.direct import solve_direct

MAX_SPEED = 1e6  # |qdot| above this (rad/s or m/s) is reported as divergence


@dataclass(frozen=True)
class State:
    t: float  # s
    q: np.ndarray  # (nq,) Pinocchio configuration
    v: np.ndarray  # (ndof,) hyper-reduced velocity qdot_R (= qdot_r without couplings)
    friction_cache: np.ndarray | None = None  # warm start of the friction impulses (staggered.py)


@dataclass
class Commands:
    joint_velocities: dict = field(default_factory=dict)  # prescribed joint -> (nv_j,) [rad/s, m/s]
    site_velocities: dict = field(default_factory=dict)  # prescribed site -> (3,) world [m/s]
    site_axes: dict = field(default_factory=dict)  # prescribed site -> (k,3) world directions (default: x, y, z)
    joint_torques: np.ndarray | None = None  # (nv,) explicit applied joint torques [N m, N]
    site_forces: dict = field(default_factory=dict)  # site -> (3,) explicit world force [N]


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


def step(mech, data, state: State, cmd: Commands, h: float) -> tuple:
    """Advance one step of Eq. (2). Returns (State, StepResult); raises StepError on failure."""
    t0 = time.perf_counter()
    if not (h > 0 and math.isfinite(h)):
        raise StepError(f"time step must be positive and finite, got {h}")
    tau = mech.torque0 if cmd.joint_torques is None else mech.torque0 + cmd.joint_torques
    if not math.isfinite(state.q @ state.q + state.v @ state.v + tau @ tau):  # cheap test; names it below
        check_inputs(state, tau, cmd)
    psites = cmd.site_velocities
    sf = {mech.site_index[n]: f for n, f in cmd.site_forces.items()} if cmd.site_forces else None
    extra = [mech.site_index[n] for n in psites] + (list(sf) if sf else [])

    ext = mech.extras
    if ext is not None:  # catalogue: time of the timed loads, J_rR of spline/exp joints at q (catalogue.py)
        ext.begin(mech, state)
    v_r = mech.to_reduced(state.v)
    kin = kinematics.compute(mech, data, state.q, v_r, extra)  # 1
    system = forces.assemble(mech, data, kin, state.q, v_r, tau, h, sf)  # 2
    cons = constraints.build(mech, kin, state.q, cmd.joint_velocities, psites, h, cmd.site_axes)  # 3
    if cons.m and not math.isfinite(cons.g @ cons.g):
        check_inputs(state, tau, cmd)
    fric = fcache = None
    if mech.friction is None:
        sol = solve_direct(system, cons)  # 4
    else:  # 4': Staggered Projections / BISP (Alg. 2/3) for ground contact and joint friction
        sol, fric, fcache = staggered.solve(mech, data, kin, system, cons, state.q, v_r, h,
                                            state.friction_cache, sf)
    if not sol.v @ sol.v <= MAX_SPEED * MAX_SPEED:  # cheap test (also catches NaN), then the exact one
        vmax = float(np.abs(sol.v).max())
        if not vmax <= MAX_SPEED:
            raise StepError(f"step diverged: max |qdot| = {vmax:.3g} (limit {MAX_SPEED:g})")

    v_new = mech.to_reduced(sol.v)  # 5
    q_new = pin.integrate(mech.model, state.q, h * v_new)
    if len(mech.loop_ab):
        q_new, viol_pos = stabilization.project_chord(mech, data, q_new, cons.G[cons.loop_rows],
                                                      mech.held_dofs(cmd.joint_velocities))
        if not math.isfinite(q_new @ q_new):
            raise StepError("non-finite configuration after loop stabilization")
    v_hyper = sol.v
    if ext is not None:  # catalogue: spline/exp joint coordinates and carriers, linear joint constraints
        q_new, v_hyper, v_new = ext.end(mech, data, q_new, sol.v, mech.held_dofs(cmd.joint_velocities), h)

    effort = tau.copy()  # 6: *f_r = *G_r^T lam / h (Eq. 7), sign: A qdot = b - G^T lam
    for name, sl in cons.joint_rows.items():
        j = mech.joint_index[name]
        effort[j.idx_v:j.idx_v + j.nv] -= sol.lam[sl] / h
    site_forces = {}
    if cons.site_rows:
        f_all = sol.lam * (-1.0 / h)
        site_forces = {name: f_all[sl] for name, sl in cons.site_rows.items()}
        for name, P in cmd.site_axes.items():
            if name in site_forces:
                site_forces[name] = P.T @ site_forces[name]  # world-frame force of the prescribed rows
    ek, ep, es = energies(mech, data, q_new, v_new)
    if ext is not None or not len(mech.loop_ab):  # else: max|phi| at q_new from the projection
        viol_pos = stabilization.loop_violation(mech, data)
    viol_vel = sol.violation if fric is None else max_row_residual(cons.G, sol.v, cons.g)
    if not math.isfinite(ek + ep + es):
        raise StepError("non-finite energy after the step")
    diag = Diagnostics(ek, ep, es, ek + ep + es, viol_pos, viol_vel, sol.iterations, sol.solver,
                       time.perf_counter() - t0, sol, fric)
    new = State(state.t + h, q_new, v_hyper, fcache)
    return new, StepResult(new.t, q_new, v_new, effort, site_forces, diag)


