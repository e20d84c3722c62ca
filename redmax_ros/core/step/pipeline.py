"""One RedMax step, written once for every backend: (mech, workspace, state, commands, h) -> (State,
StepResult).

    ws.deadline = budget.start()                        # the step budget (solvers/budget.py), or None
    cmd = trajectory.resolve(mech, state, cmd, h)       # joint trajectories -> this step's velocity rows
    cmd = body_twist.resolve(cmd, t_k+1)                # timed body-twist components
    tau = applied_torques(mech, state, cmd, h)          # inputs checked (non-finite ones named)
    ws.extras.begin(...)                                # catalogue: J_rR of joint maps at q, load time
    vs = velocity(mech, ws, state, cmd, tau, h)         # stages 1-4 of the backend (below); inputs beyond
                                                        # the divergence limit rejected before the solve
    check_speed(vs.sol.v)                               # divergence
    q+ = integrate(q, h J_rR qdot_R+)                   # 5: manifold update (pin.integrate)
    q+ = stabilization.project_chord(q+, G_loop)        #    loop post-stabilization
    q+, qdot_R+ = ws.extras.end(...)                    #    catalogue: coordinates, charts, projections
    effort, site forces = *G^T lam / h                  # 6: required torques and forces (Eq. 7)
    energies, violations -> Diagnostics                 #    one implementation (energy.py)

The velocity stages are what really differs between backends (MJX's "two implementations behind one
entry point"): :func:`pinocchio_velocity` here (kinematics.compute on pin.Data -> forces.assemble (Eq.
2, Eq. 9-10) -> constraints.build (Eq. 5-7) -> solvers.direct.solve_direct or friction.staggered.solve)
and step.data_free_stages.data_free_velocity (the recursive passes, PCG with Alg. 1 or the dense
data-free direct solver). The returned State is new and the input is never modified, so a StepError
leaves the caller's state exactly as it was; the workspace is scratch.

Bounded work: with a ``budget`` (solvers/budget.StepBudget) the step's Deadline is ``ws.deadline`` while
it runs; the iterative solvers check it between their iterations and raise StepError("step budget
exceeded: ...") past it. Inputs whose step must diverge (a prescribed velocity or an applied force beyond
the divergence limit, step/state.py) are rejected after the kinematics and forces, before any solve.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics import constraints, forces, kinematics, self_collision, stabilization
from redmax_ros.core.dynamics.energy import energies
from redmax_ros.core.dynamics.springs import linearisation_miss
from redmax_ros.core.errors import StepError
from redmax_ros.core.friction import staggered
from redmax_ros.core.solvers.direct import solve_direct
from redmax_ros.core.solvers.kkt import max_row_residual
from redmax_ros.core.step import body_twist, trajectory
from redmax_ros.core.step.scheme import accepts, bdf2_point, next_history
from redmax_ros.core.step.state import (Diagnostics, State, StepResult, applied_torques, check_applied, check_inputs,
                                        check_rows, check_speed)


@dataclass
class VelocitySolve:
    """What a backend's velocity stages (1-4) hand to the common tail of the step."""
    sol: object  # .v hyper-reduced qdot+, .lam bilateral multipliers, .iterations, .solver, .residual
    joint_rows: dict  # prescribed joint -> slice of lam
    site_rows: dict  # prescribed site -> slice of lam
    G_loop: np.ndarray | None  # hyper-reduced loop rows at q_k (post-stabilization), None without loops
    violation_vel: float  # max |G qdot+ - g| of the bilateral rows
    solver: str
    iterations: int
    friction: object = None  # staggered.FrictionReport
    friction_cache: np.ndarray | None = None  # warm start of the next step's friction impulses
    body_rows: dict | None = None  # prescribed body -> slice of lam (body_twist.py)
    contacts: object = None  # self_collision.ContactReport (scenes with a collision section), also sol.contacts


def step(mech, ws, state: State, cmd, h: float, velocity, budget=None) -> tuple:
    """Advance one step of Eq. (2) with the backend's ``velocity`` stages. Returns (State, StepResult);
    raises StepError on failure (the input state is never modified). ``budget``: a StepBudget (CPU time of
    the step's iterative solvers, QP iteration caps) or None (unlimited). With integrator.scheme bdf2 the
    step is the linearly implicit BDF2 of step/scheme.py (its start-up BDF1 step, about the explicit Euler
    predictor, when the state has no history for h; Eq. 2 itself when the order control of step/scheme.accepts
    rejects the BDF2 step: then it is redone as that)."""
    t0 = time.perf_counter()
    ws.deadline = None if budget is None else budget.start()
    try:
        if mech.scheme == "bdf2":
            ws.bdf2 = bdf2_point(mech.model, ws.to_reduced, state.q, state.v, state.history, h)
        warm = ws.cache.get(_ACTIVE_KEY)
        ws.spring_ends = None
        new, res = _step(mech, ws, state, cmd, h, velocity, t0)
        if ws.bdf2 is not None and ws.bdf2.order == 2 and not accepts(mech.model, state.q, ws.bdf2.q_lin, new.q,
                                                                      spring_miss(mech, ws, ws.bdf2.h)):
            ws.bdf2 = None  # order control (step/scheme.py): the step again, as BDF1 (Eq. 2), from the same warm start
            if warm is not None:
                ws.cache[_ACTIVE_KEY] = warm
            new, res = _step(mech, ws, state, cmd, h, velocity, t0)
        return new, res
    finally:
        ws.deadline = None
        ws.bdf2 = None


def spring_miss(mech, ws, hh: float) -> float:
    """What a BDF2 step's linearisation of its implicit maximal springs about q* missed at q+ [m]
    (springs.linearisation_miss): the ends at q* that the velocity stages kept in ws.spring_ends, the sites at q+
    from the forward kinematics that energies() left in the workspace (pin.Data or the recursive Context); 0
    without springs."""
    if ws.spring_ends is None:
        return 0.0
    pa, pb = ws.spring_ends
    X = kinematics.site_positions(mech, ws.data, mech.jac_sites) if ws.data is not None else ws.tree.jac_positions()
    ctx = ws.tree
    sa = ctx.spring_arrays  # the springs' rows, stiffness and explicit flags (springs.spring_arrays)
    return linearisation_miss(np.ascontiguousarray(pa), np.ascontiguousarray(pb), np.ascontiguousarray(X),
                              sa.a, sa.b, sa.k, sa.explicit, ctx.spring_ja, ctx.spring_jb, ctx.topo.mass, hh * hh)


def _step(mech, ws, state: State, cmd, h: float, velocity, t0) -> tuple:
    pt = ws.bdf2
    # BDF2: the velocity stages see the extrapolated state (q*, v*) and hat h (step/scheme.py)
    lin, hs, q_base = (state, h, state.q) if pt is None else (
        dataclasses.replace(state, q=pt.q_lin, v=pt.v_lin), pt.h, pt.q_base)
    cmd = trajectory.resolve(mech, state, cmd, h, q_base)  # joint trajectories -> this step's prescribed velocities
    cmd = body_twist.resolve(cmd, state.time_after(h))  # timed body-twist components at t_k+1
    tau = applied_torques(mech, state, cmd, h)
    if ws.extras is not None:  # catalogue: time of the timed loads, J_rR of spline/exp joints at q
        ws.extras.begin(mech, ws, state)
    vs = velocity(mech, ws, lin, cmd, tau, hs)  # 1-4
    check_speed(vs.sol.v)
    q_new, v_hyper, v_new, viol_pos = update_configuration(mech, ws, q_base, vs, cmd, hs)  # 5
    effort, site_forces = required_forces(mech, tau, vs, cmd, hs)  # 6
    wrenches = body_twist.wrenches(vs.sol.lam, vs.body_rows, cmd.body_twists, hs) if vs.body_rows else {}
    ek, ep, es = energies(mech, ws, q_new, v_new)
    if not math.isfinite(ek + ep + es):
        raise StepError("non-finite energy after the step")
    diag = Diagnostics(ek, ep, es, ek + ep + es, viol_pos, vs.violation_vel, vs.iterations, vs.solver,
                       time.perf_counter() - t0, vs.sol, vs.friction, order=1 if pt is None else pt.order)
    new = state.advanced(h, q_new, v_hyper, vs.friction_cache, history=next_history(mech.scheme, state.q, state.v, h))
    return new, StepResult(new.t, q_new, v_new, effort, site_forces, diag, wrenches)


def update_configuration(mech, ws, q, vs: VelocitySolve, cmd, h) -> tuple:
    """Stage 5: q+ = q (+) h J_rR qdot_R+ on the manifold (BDF2: q = q^, h = hat h, step/scheme.py), loop post-stabilization (stabilization.py) and the
    catalogue's end-of-step hooks. Returns (q+, qdot_R+, qdot_r+, max loop violation [m])."""
    v_new = ws.to_reduced(vs.sol.v)
    # every joint a vector space (Context.additive): pin.integrate is this sum
    q_new = q + h * v_new if ws.tree.additive else pin.integrate(mech.model, q, h * v_new)
    viol_pos = None
    if vs.G_loop is not None and not mech.loop_baumgarte:  # Baumgarte: the rows' RHS did it (constraints.build)
        q_new, viol_pos = stabilization.project_chord(ws.tree, q_new, vs.G_loop,
                                                      constraints.held_dofs(mech, ws, cmd.joint_velocities))
        if not math.isfinite(q_new @ q_new):
            raise StepError("non-finite configuration after loop stabilization")
    v_hyper = vs.sol.v
    if ws.extras is not None:  # catalogue: spline/exp joint coordinates and carriers, linear joint constraints
        q_new, v_hyper, v_new = ws.extras.end(mech, ws, q_new, vs.sol.v,
                                              constraints.held_dofs(mech, ws, cmd.joint_velocities), h)
    if ws.extras is not None or viol_pos is None:  # else: max|phi| at q_new from the projection
        viol_pos = stabilization.loop_violation(ws.tree, q_new)
    return q_new, v_hyper, v_new, viol_pos


def required_forces(mech, tau, vs: VelocitySolve, cmd, h) -> tuple:
    """Stage 6 (Eq. 7): effort = tau - *G_r^T lam / h on the prescribed joints (sign: A qdot = b - G^T lam;
    BDF2: h = hat h, the constraint force at t_k+1 of M (qdot+ - v^) = hat h f, step/scheme.py),
    and the world force every prescribed site requires (its prescribed axes' rows mapped back)."""
    sol = vs.sol
    effort = tau.copy()
    for name, sl in vs.joint_rows.items():
        j = mech.joint_index[name]
        effort[j.idx_v:j.idx_v + j.nv] -= sol.lam[sl] / h
    site_forces = {}
    if vs.site_rows:
        f_all = sol.lam * (-1.0 / h)
        site_forces = {name: f_all[sl] for name, sl in vs.site_rows.items()}
        for name, P in cmd.site_axes.items():
            if name in site_forces:
                site_forces[name] = P.T @ site_forces[name]  # world-frame force of the prescribed rows
    return effort, site_forces


# ----------------------------------------------------------------------------------------------
# the Pinocchio backend's velocity stages


def site_jacobian_rows(mech, ws, kin, sites) -> np.ndarray:
    """(s, 3, nv) point Jacobians of the prescribed sites from Kinematics.J."""
    return kin.J[[kin.row[mech.site_index[n]] for n in sites]]


@dataclass
class SkeletonStages:
    """What stages 1-3 on pin.Data leave for a solve: the kinematics, Eq. (2)'s system and the rows."""
    kin: kinematics.Kinematics
    system: object  # solvers.problem.LinearSystem
    cons: object  # solvers.problem.Constraints
    v_r: np.ndarray  # (nv,) reduced velocity at the linearisation point
    site_forces: dict | None  # site row -> explicit world force [N], or None


def skeleton_stages(mech, ws, state: State, cmd, tau, h) -> SkeletonStages:
    """Stages 1-3 on pin.Data: kinematics.compute (CRBA, RNEA, Jacobians, site Jacobians), forces.assemble
    (Eq. 2, projected by J_rR, Eq. 9-10; applied inputs beyond the divergence limit rejected), constraints.build
    (loops, Eq. 7 prescriptions, joint limits of Eq. 5). Used by :func:`pinocchio_velocity` and by the step
    with deformables (deformable_stages.py), which adds its own DOFs and rows to these."""
    psites = cmd.site_velocities
    sf = {mech.site_index[n]: f for n, f in cmd.site_forces.items()} if cmd.site_forces else None
    extra = [mech.site_index[n] for n in psites] + (list(sf) if sf else [])
    v_r = ws.to_reduced(state.v)
    kin = kinematics.compute(mech, ws, state.q, v_r, extra)  # 1
    system = forces.assemble(mech, ws, kin, state.q, v_r, tau, h, sf)  # 2
    check_applied(mech, ws, system.A, tau, h, cmd,
                  [(n, kin.J[kin.row[mech.site_index[n]]].T @ f) for n, f in cmd.site_forces.items()] if sf else ())
    G_loop = constraints.loop_rows_of(mech, kin.J) if len(mech.loop_ab) else None
    J_sites = site_jacobian_rows(mech, ws, kin, psites) if psites else None
    cons = constraints.build(mech, ws, G_loop, J_sites, state.q if ws.bdf2 is None else ws.bdf2.q_base,
                             cmd.joint_velocities, psites, h, cmd.site_axes)  # 3
    return SkeletonStages(kin, system, cons, v_r, sf)


_ACTIVE_KEY = "active unilateral rows"  # ws.cache: (the step count they are for, labels of the active rows)


def _warm_rows(ws, state, cons) -> list:
    """Unilateral rows (by label and occurrence) that were active at the step that produced ``state``, with
    whether at their upper bound (mu > 0): the active set's start
    (solvers/active_set.py). Empty after a reset, a set_state or a load (the step count does not follow on), so
    such a run solves as a fresh one does."""
    k, keys = ws.cache.get(_ACTIVE_KEY, (-1, {}))
    if k != state.k or cons.C is None:
        return []
    return [(i, keys[key]) for i, key in enumerate(_row_keys(cons.C_labels)) if key in keys]


def _row_keys(labels) -> list:
    """(label, its occurrence) per row: a pair's witness row and its capsule-end rows share a label."""
    seen = {}
    out = []
    for lab in labels:
        j = seen.get(lab, 0)
        seen[lab] = j + 1
        out.append((lab, j))
    return out


def pinocchio_velocity(mech, ws, state: State, cmd, tau, h) -> VelocitySolve:
    """Stages 1-4 on pin.Data: :func:`skeleton_stages` (1-3), self-collision rows (3'), then solve_direct
    (Cholesky / KKT / ProxSuite QP) or, with contact or joint friction, the Staggered Projections / BISP
    iterations (Alg. 2/3)."""
    sk = skeleton_stages(mech, ws, state, cmd, tau, h)
    kin, system, cons, v_r, sf = sk.kin, sk.system, sk.cons, sk.v_r, sk.site_forces
    body_rows = body_twist.append_rows(mech, ws, ws.data, cons, cmd.body_twists) if cmd.body_twists else None
    contacts = self_collision.append_rows(mech, ws, cons, h, state.v) if mech.collision is not None else None  # 3'
    if cons.m:
        if not math.isfinite(cons.g @ cons.g):
            check_inputs(state, tau, cmd)
        check_rows(cons)  # prescribed velocities no step below the divergence limit can meet
    if mech.friction is None:
        t_solve = time.perf_counter()
        warm = None if contacts is None or ws.contact_qp != "active-set" else _warm_rows(ws, state, cons)
        try:
            sol = solve_direct(system, cons, deadline=ws.deadline, warm=warm)  # 4 (contact rows: the QP of Eq. 5)
        except StepError:
            if not (contacts is not None and self_collision.relax_rows(cons, contacts)):
                raise
            sol = solve_direct(system, cons, deadline=ws.deadline, warm=warm)  # without the contacts' position correction
        if contacts is not None and cons.C is not None:
            keys = _row_keys(cons.C_labels)
            ws.cache[_ACTIVE_KEY] = (state.k + 1, {keys[i]: bool(sol.mu[i] > 0) for i in np.flatnonzero(sol.mu)})
        fric = fcache = None
        viol_vel = sol.violation
        if contacts is not None:
            sol.contacts = self_collision.finish_report(contacts, sol.mu, time.perf_counter() - t_solve)
    else:  # 4': Staggered Projections / BISP (Alg. 2/3) for ground contact and joint friction
        sol, fric, fcache = staggered.solve(mech, ws.friction, kin, system, cons, state.q, v_r, h,
                                            state.friction_cache, sf, ws.deadline,
                                            None if ws.extras is None else ws.extras.jdot_qdot)
        viol_vel = max_row_residual(cons.G, sol.v, cons.g)
    return VelocitySolve(sol, cons.joint_rows, cons.site_rows,
                         cons.G[cons.loop_rows] if len(mech.loop_ab) else None, viol_vel, sol.solver,
                         sol.iterations, fric, fcache, body_rows, contacts)
