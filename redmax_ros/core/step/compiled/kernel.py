"""The compiled RedMax step: one native call per run of steps, ``step_n_kernel`` (a single step is a run of one),
its step reading as the list of its stages (each ``f(m, d, ...)`` in its own module, Model static, Data the
preallocated workspace):

    point(m, d, q, qdot_R, history, hh)    # 0  BDF1, or BDF2's q^, q*, v*, v^ (scheme.py; step/scheme.py)
    kinematics(m, d, q*, v*, warm)         # 1  forward kinematics, twists, inertias, sites (kinematics.py)
    assemble(m, d, q^, v*, v^, tau, hh)    # 2  A_R, b_R of Eq. (2), Eq. (9-10) (forces.py)
    rows(m, d, q^, hh, gj, sv)             # 3  loops, prescribed joints and sites (Eq. 7), limits (rows.py)
    kkt_solve_tree_into(A_R, b_R, G, g, ...)  # 4  L^T D L on the tree (or Cholesky) + Schur complement of Eq. (6)/(7) (solvers/kkt.py)
    active_set(m, d)                       # 4' joint limits of Eq. (5), when one is crossed (limits.py)
    friction_solve(m, d, c, h, cache, ...) # 4'' instead of 4: contact and joint friction, Alg. 2-3 (friction.py)
    update_configuration(m, d, q^, hh)     # 5  manifold update, loop post-stabilization (update.py)
    required_forces(m, d, tau, hh)         # 6  Eq. 7 torques and site forces (update.py)
    energies(m, d, q+, qdot_r+, placed)    #    diagnostics (energy.py): BDF1 steps, and BDF2 steps a run returns

with hh = h for BDF1 (q^ = q* = q_k, v^ = v* = qdot_k: the paper's step), hh = 2h/3 for BDF2 (history 1) and hh
= h for the bdf2 scheme's start-up (history 2: q* = q_k (+) h qdot_k, step/scheme.startup_point). A BDF2 step
that the order control rejects (scheme.accepted, step/scheme.accepts) is taken again from the same state as
BDF1; d.out[OUT_ORDER] says which order the step has.

There are two kernels, each compiled once with every stage inlined (numba compile time grows with the inlined
code: ~13 min of one core for step_n_kernel here), so a single step is not a kernel of its own: the backend runs
``step_n_kernel`` / ``friction_step_n_kernel`` with n = 1 on copies of the state.

A step returns a status: OK, or REFERENCE with the stage that asked for it in d.out[OUT_STAGE]: whatever the
kernel does not finish itself (a joint-limit active set that does not settle; a loop projection that
needs the full Newton; a rank-deficient or non-positive-definite system; any input the divergence checks
of step/state.py reject) is redone by the Pinocchio pipeline, which solves it or raises the StepError
naming the problem. Nothing the kernel wrote is then used, so the step's outcome is the reference's.
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import njit, njit_inline
from redmax_ros.core.step.compiled.cache import drop_stale
from redmax_ros.core.solvers.kkt import kkt_residual_into, kkt_solve_tree_into
from redmax_ros.core.step.compiled.data import (OUT_ITERS, OUT_E_KIN, OUT_E_POT, OUT_E_SPRING, OUT_ORDER, OUT_RESIDUAL,
                                                OUT_STAGE, OUT_VIOL_POS, OUT_VIOL_VEL, data_views)
from redmax_ros.core.step.compiled.energy import energies
from redmax_ros.core.step.compiled.forces import assemble
from redmax_ros.core.step.compiled.friction import (NOT_PD, PAUSED, RANK_DEFICIENT, REP_ITERS, REP_KKT,
                                                    bilateral_residual, friction_solve, friction_views)
from redmax_ros.core.step.compiled.kinematics import kinematics
from redmax_ros.core.step.compiled.limits import active_set, bilateral_violation
from redmax_ros.core.step.compiled.model import model_views
from redmax_ros.core.step.compiled.rows import rows
from redmax_ros.core.step.compiled.scheme import accepted, point
from redmax_ros.core.step.compiled.update import required_forces, update_configuration
from redmax_ros.core.solvers.recursive import jv_kernel
from redmax_ros.core.step.state import MAX_SPEED, impulse_beyond, row_beyond

drop_stale()  # before numba looks at the cache of the kernels below (cache.py)

OK, REFERENCE = 0, 1
# the stage that handed the step to the reference (d.out[OUT_STAGE])
(STAGE_NONE, STAGE_INPUT, STAGE_IMPULSE, STAGE_ROWS, STAGE_FACTOR, STAGE_SCHUR, STAGE_LIMITS, STAGE_SPEED,
 STAGE_PROJECTION, STAGE_ENERGY, STAGE_FRICTION_BUDGET) = range(11)
STAGE_NAMES = ("none", "non-finite input or RHS", "applied impulse beyond the limit", "prescribed row beyond the limit",
               "LHS not positive definite", "constraint rows rank-deficient", "joint-limit active set did not settle",
               "velocity beyond the limit", "loop projection (full Newton)", "non-finite energy",
               "friction loop beyond its first work budget (step budget)")


@njit
def _finite_sum(x):
    s = 0.0
    for i in range(x.shape[0]):
        s += x[i]
    return s - s == 0.0


@njit
def _handoff(out, stage):
    out[OUT_STAGE] = stage
    return REFERENCE


@njit_inline
def one_step(m, d, q, vR, tau, h, gj, sv, qp, vp, hist, warm, report, residual):
    """One step on the Model and Data namedtuples: BDF2 (``hist``) kept if the order control accepts it, else
    BDF1 from the same state; returns OK or REFERENCE. ``warm``: d holds the placements and twists at (q, vR),
    left by the previous step of the run (its energies); a BDF1 step uses them (kinematics.kinematics).
    ``report``: the step's outputs are returned (the last step of a run, or a recorded one), so under BDF2 its
    energies are computed (tail_stages); ``residual``: its KKT residual too (a diagnostic only: the StepResults of
    single steps and step_results carry it, a Rollout's rows do not); else those outputs are NaN."""
    order = hist
    while True:  # one call site: the stages are inlined once (a plain call copies the namedtuples)
        status = stages(m, d, q, vR, tau, h, gj, sv, qp, vp, order, warm, report, residual)
        # a reported BDF2 step's energies (tail_stages) left the placements at q+, which the springs' check reads
        if order == 1 and status == OK and not accepted(m, d, q, 2.0 * h / 3.0, report):
            order = 0
            warm = False  # the BDF2 attempt moved the placements to its q*
            continue
        break
    d.out[OUT_ORDER] = 2.0 if order == 1 else 1.0
    return status


@njit_inline
def stages(m, d, q, vR, tau, h, gj, sv, qp, vp, hist, warm, report, residual):
    """The stages of one step (BDF2 with ``hist``, else BDF1) on the Model and Data namedtuples; returns OK or
    REFERENCE. ``report``, ``residual``: see one_step."""
    status, hh = rigid_stages(m, d, q, vR, tau, h, gj, sv, qp, vp, hist, warm)  # 0-3
    if status != OK:
        return status
    status, ratio, viol, limits_ok = kkt_solve_tree_into(d.AR, d.bR, d.G, d.g, m.limit_rows, d.lo, d.hi, d.kkt_par,
                                                         d.kkt_allowed, d.kkt_span, d.kkt_L, d.kkt_Y, d.kkt_S, d.kkt_LS, d.kkt_y,
                                                         d.v_hyper, d.lam)  # 4
    if status == 1:
        return _handoff(d.out, STAGE_FACTOR)
    if status == 2 or ratio <= 1e-6:
        return _handoff(d.out, STAGE_SCHUR)
    d.out[OUT_ITERS] = 1.0
    if limits_ok:
        d.mu[:] = 0.0
    else:  # 4': joint limits of Eq. (5) by the active set (limits.py)
        ok, iters = active_set(m, d)
        if not ok:
            return _handoff(d.out, STAGE_LIMITS)
        viol = bilateral_violation(d)
        d.out[OUT_ITERS] = float(iters + 1)  # KKT solves: the unconstrained one and one per working-set change
    if not (d.v_hyper @ d.v_hyper <= MAX_SPEED * MAX_SPEED):
        return _handoff(d.out, STAGE_SPEED)
    d.out[OUT_VIOL_VEL] = viol
    if residual:
        d.out[OUT_RESIDUAL] = kkt_residual_into(d.AR, d.bR, d.v_hyper, d.G, d.lam, m.limit_rows, d.mu, d.kkt_r)
    else:
        d.out[OUT_RESIDUAL] = np.nan
    return tail_stages(m, d, tau, hh, report or not hist)  # 5-6


@njit_inline
def rigid_stages(m, d, q, vR, tau, h, gj, sv, qp, vp, hist, warm):
    """Stages 0-3 with the input checks of step/state.py: (OK or REFERENCE, hh). ``warm``: see one_step (BDF1
    only: a BDF2 step's kinematics are at q*)."""
    d.out[OUT_STAGE] = 0.0
    vv = vR @ vR
    if not (_finite_sum(q) and vv - vv == 0.0 and _finite_sum(tau)) or vv > MAX_SPEED * MAX_SPEED:
        return _handoff(d.out, STAGE_INPUT), h  # step/state.applied_torques names it
    hh = 2.0 * h / 3.0 if hist == 1 else h
    point(m, d, q, vR, qp, vp, hist, hh)  # 0
    kinematics(m, d, d.q_lin, d.v_r, warm and not hist)  # 1
    if hist == 1:  # 2, BDF2: the momentum of v^; with the start-up (hist 2) too, the maximal springs linearised
        # about q* (springs.spring_shift)
        jv_kernel(m.parents, m.idx_v, m.nv_j, d.St, d.v_mom, d.ovm)
        vm, ovm = d.v_mom, d.ovm
    else:
        vm, ovm = d.v_r, d.ov
    assemble(m, d, d.q_base, d.v_r, vm, ovm, tau, hh, hist != 0)  # one call site: inlined once
    if not _finite_sum(d.bR):
        return _handoff(d.out, STAGE_INPUT), hh
    if impulse_beyond(d.AR, m.T, tau, d.free_mask, hh, MAX_SPEED) >= 0:
        return _handoff(d.out, STAGE_IMPULSE), hh
    rows(m, d, d.q_base, hh, gj, sv)  # 3
    if d.g.shape[0]:
        if not _finite_sum(d.g):
            return _handoff(d.out, STAGE_INPUT), hh
        if row_beyond(d.G, d.g, MAX_SPEED) >= 0:
            return _handoff(d.out, STAGE_ROWS), hh
    return OK, hh


@njit_inline
def tail_stages(m, d, tau, hh, energy):
    """Stages 5-6 and, with ``energy``, the energies after a solve (d.v_hyper, d.lam); returns OK or REFERENCE.
    Without ``energy`` (a BDF2 step whose outputs the run does not return: nobody reads its energies, and the
    next step, BDF2 from q* or a BDF1 retry, computes its own kinematics instead of reusing theirs) d.out's
    energies are NaN."""
    converged, viol_pos, placed = update_configuration(m, d, d.q_base, hh)  # 5
    if not converged or not _finite_sum(d.q_new):
        return _handoff(d.out, STAGE_PROJECTION)
    required_forces(m, d, tau, hh)  # 6
    if energy:
        ek, ep, es = energies(m, d, d.q_new, d.v_new, placed)
        if not (ek + ep + es) - (ek + ep + es) == 0.0:
            return _handoff(d.out, STAGE_ENERGY)
    else:
        ek = ep = es = np.nan
    d.out[OUT_E_KIN] = ek
    d.out[OUT_E_POT] = ep
    d.out[OUT_E_SPRING] = es
    d.out[OUT_VIOL_POS] = viol_pos
    return OK


@njit_inline
def one_friction_step(m, d, c, q, vR, tau, h, gj, sv, cache, has_cache, cache_new, jn, rep, work_cap, warm, report):
    """One BDF1 step with ground contact and joint friction: stages 0-3, the Staggered Projections / BISP solve
    (friction.py) in place of stage 4, stages 5-6; returns OK or REFERENCE. ``warm``, ``report``: see one_step."""
    status, hh = rigid_stages(m, d, q, vR, tau, h, gj, sv, q, vR, 0, warm)  # 0-3
    if status != OK:
        return status
    fs = friction_solve(m, d, c, hh, cache, has_cache, cache_new, jn, rep, work_cap, report)  # 4''
    if fs == NOT_PD:
        return _handoff(d.out, STAGE_FACTOR)
    if fs == RANK_DEFICIENT:
        return _handoff(d.out, STAGE_SCHUR)
    if fs == PAUSED:
        return _handoff(d.out, STAGE_FRICTION_BUDGET)
    d.out[OUT_ITERS] = rep[REP_ITERS]
    if not (d.v_hyper @ d.v_hyper <= MAX_SPEED * MAX_SPEED):
        return _handoff(d.out, STAGE_SPEED)
    d.out[OUT_VIOL_VEL] = bilateral_residual(d)
    d.out[OUT_RESIDUAL] = rep[REP_KKT]
    return tail_stages(m, d, tau, hh, True)  # 5-6


@njit_inline
def _put(row, j, a):
    """row[j:j + len(a)] = a; returns j + len(a)."""
    for i in range(a.shape[0]):
        row[j + i] = a[i]
    return j + a.shape[0]


@njit_inline
def record_step(row, d):
    """A run's record of one step (the ``rec`` rows of the kernels below; backend.record_layout names the
    fields): q_new, v_hyper, v_new, effort, site_force (row-major), out, lam, mu. Returns the next free column."""
    j = _put(row, 0, d.q_new)
    j = _put(row, j, d.v_hyper)
    j = _put(row, j, d.v_new)
    j = _put(row, j, d.effort)
    for s in range(d.site_force.shape[0]):
        j = _put(row, j, d.site_force[s])
    j = _put(row, j, d.out)
    j = _put(row, j, d.lam)
    return _put(row, j, d.mu)


@njit_inline
def record_row(k, every, phase, rows):
    """The row of a run's record that step k of the run goes to, or -1: every ``every``-th step is recorded,
    counted from ``phase`` steps taken before the run (0 <= phase < every), while rows remain."""
    r = k + 1 + phase
    if r % every:
        return -1
    i = r // every - 1
    return i if i < rows else -1


@njit
def friction_step_n_kernel(mf, mi, mt, df, di, dt, ff, fi, ft, q, vR, tau, h, gj, sv, n, cache, has_cache, cache_new,
                           jn, rep, work_cap, rec, every, phase):
    """Up to n frictional steps with the same commands: (q, vR) and the friction ``cache`` advanced in place
    after every step taken; returns the number of steps taken (as step_n_kernel). ``rec`` (rows, width): the
    outputs of every ``every``-th step (record_row) go to its rows (record_step, then rep and jn); (0, 0)
    records nothing."""
    m = model_views(mf, mi, mt)
    d = data_views(df, di, dt)
    c = friction_views(ff, fi, ft)
    for k in range(n):  # after the first step, d holds the placements and twists at (q, vR) (one_step)
        i = record_row(k, every, phase, rec.shape[0])
        if one_friction_step(m, d, c, q, vR, tau, h, gj, sv, cache, has_cache, cache_new, jn, rep, work_cap,
                             k > 0, k == n - 1 or i >= 0) != OK:
            return k
        if i >= 0:
            j = record_step(rec[i], d)
            _put(rec[i], _put(rec[i], j, rep), jn)
        q[:] = d.q_new
        vR[:] = d.v_hyper
        cache[:] = cache_new
        has_cache = 1
    return n


@njit
def step_n_kernel(mf, mi, mt, df, di, dt, q, vR, tau, h, gj, sv, n, qp, vp, hist, bdf2, rec, every, phase, residuals):
    """Up to n steps with the same commands, (q, vR) advanced in place; returns the number of steps taken
    (< n: the next step was handed back, d.out[OUT_STAGE] says why). The Data holds the last step's outputs.
    ``bdf2`` nonzero: integrator.scheme bdf2, the history (qp, vp) kept in place (the state before the last
    step taken; ``hist`` whether the input's history is valid for h), else every step is BDF1. ``rec``
    (rows, width): the outputs of every ``every``-th step (record_row, counted from ``phase`` steps before the
    run) go to its rows (record_step); (0, 0) records nothing. ``residuals`` nonzero: every recorded step
    computes its KKT residual (StepResults), else only the run's last step (a Rollout's rows have none, its
    ``last`` has)."""
    m = model_views(mf, mi, mt)
    d = data_views(df, di, dt)
    for k in range(n):  # after the first step, d holds the placements and twists at (q, vR) (one_step)
        i = record_row(k, every, phase, rec.shape[0])
        last = k == n - 1
        if one_step(m, d, q, vR, tau, h, gj, sv, qp, vp, hist, k > 0, last or i >= 0,
                    last or (residuals != 0 and i >= 0)) != OK:
            return k
        if i >= 0:
            record_step(rec[i], d)
        if bdf2:
            qp[:] = q
            vp[:] = vR
            hist = 1
        q[:] = d.q_new
        vR[:] = d.v_hyper
    return n
