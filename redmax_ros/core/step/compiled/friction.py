"""Stage 4'' of the compiled step, ``friction_solve(m, d, c, ...)``: ground contact (Staggered Projections, paper
Alg. 2, Eq. 11-12) and joint friction (BISP, Alg. 3, Eq. 15-18) in place of the KKT solve, on the kinematics,
the A_R, b_R of Eq. (2) and the bilateral rows G, g the stages before it left in the Data (no pin.Data).

The kernels are those of the reference pipeline's friction stage (friction/staggered.solve), called in its
order, so both paths compute the same numbers from the same inputs:

    Z = Jdot qdot^prev                            # bias accelerations (recursive.bias_kernel)
    RX, lo_U = rows_kernel_into(...)              # detection, rows [U; -T] (contact.py; Eq. 11-12, 1.90-1.91)
    qdot_0, PX, W_U, W_T, ... = condense_into(...)  # the bilateral rows condensed once (condense.py), on its arena
    beta = warm_start_into(cache)                 # friction impulses of the last step [Kaufman et al. 2008]
    wm = make_wrench_map_into(...); constant_wrenches(wm, ...)  # joint wrenches of Eq. (15)-(17): the map of x, W0 (bisp.py)
    staggered_kernel(...)                         # the loop: contact, BISP (Eq. 16), friction, Anderson
    finish_into(...)                              # qdot_R+, lambda, the new cache, the report's counts

A step allocates nothing: every array it makes is a view of an arena of the friction pack (friction/arena.py),
sized in build_friction for the most rows a step can have: the condensation's (condense.arena_size), the
loop's work vectors (staggered.loop_scratch_size) and the step arena for the rest (step_arena_size); a step
that needed more would allocate what did not fit, with the same numbers.

:data:`FRICTION_SPEC` packs the constants of a Mechanism's contact.FrictionModel (built once, like the Model);
:func:`friction_unsupported` says which friction scenes stay on the reference pipeline (spherical joint
friction's per-point bounds, ProxSuite inner solves, maximal springs' explicit forces in the joint reactions,
BDF2). Units SI.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np

from redmax_ros.core.friction.arena import take, take1
from redmax_ros.core.friction.bisp import constant_wrenches, make_wrench_map_into, wrench_map_arena_size
from redmax_ros.core.friction.condense import arena_size, condense_into
from redmax_ros.core.friction.contact import rows_arena_size, rows_kernel_into
from redmax_ros.core.friction.staggered import (finish_into, finish_scratch_size, loop_scratch_size, loop_state_into,
                                                loop_state_size, staggered_kernel, warm_start_into)
from redmax_ros.core.jit import njit_inline
from redmax_ros.core.solvers.kkt import kkt_residual_into, max_row_residual
from redmax_ros.core.solvers.recursive import bias_kernel
from redmax_ros.core.step.compiled.packing import f1, f2, f3, i1, pack

FRICTION_SPEC = (
    # contact spheres and planes (contact.FrictionModel)
    ("sph_jid", "i", 1), ("sph_local", "f", 2), ("sph_radius", "f", 1), ("sph_support", "f", 2), ("sph_mu", "f", 1),
    ("plane_n", "f", 2), ("plane_off", "f", 1), ("plane_t", "f", 3), ("plane_mu", "f", 1),
    # coupling matrix T (Eq. 9) in CSR form, constant friction rows, loop-pin rows
    ("T_ptr", "i", 1), ("T_idx", "i", 1), ("T_val", "f", 1), ("rows_fixed", "f", 2), ("pin_moment", "f", 2),
    ("loop_sdiff", "f", 2),
    # BISP map (bisp.make_wrench_map): loop selection triplets, frictional loops and joints, Eq. (16) operators
    ("sel_r", "i", 1), ("sel_c", "i", 1), ("sel_v", "f", 1), ("loop_index", "i", 1), ("pin_ja", "i", 1),
    ("pin_jb", "i", 1), ("loop_ja", "i", 1), ("loop_jb", "i", 1), ("fj_jid", "i", 1), ("L_ops", "f", 3), ("L_of", "i", 1),
    ("bound_mu", "f", 1), ("gravity", "f", 1),
    # scalars: see SC_* below
    ("scalars", "f", 1),
    # not constants: the condensation's scratch (condense.condense_into's arena, floats, ints and offsets), reused
    # every step, sized for the most rows a step can have (build_friction)
    ("arena", "f", 1), ("iarena", "i", 1), ("arena_off", "i", 1),
    # and the staggered loop's work vectors (staggered.loop_scratch_size)
    ("loop_scratch", "f", 1),
    # and the rest of a step's arrays (friction_solve; arena.py: floats, ints and offsets, step_arena_size)
    ("step_arena", "f", 1), ("step_iarena", "i", 1), ("step_off", "i", 1),
)
FrictionConsts = namedtuple("FrictionConsts", [n for n, _, _ in FRICTION_SPEC])

# FrictionConsts.scalars
SC_TOL, SC_MAX_ITER, SC_DEPTH, SC_MARGIN, SC_ERP, SC_N_TREE, SC_N_SLOTS, SC_SLOT0, SC_JOINT, SC_CONTACTS = range(10)
# the report of a step (friction_solve's ``rep``): FrictionReport's fields
(REP_ITERS, REP_CONVERGED, REP_RESIDUAL, REP_CONTACTS, REP_ACTIVE, REP_PENETRATION, REP_STICKING, REP_PAUSED,
 REP_KKT) = range(9)
N_REP = 9
# friction_solve's status
SOLVED, NOT_PD, RANK_DEFICIENT, PAUSED = range(4)


@njit_inline
def friction_views(f, i, t):
    """The FrictionConsts namedtuple of views into the packed buffers (FRICTION_SPEC order)."""
    return FrictionConsts(i1(i, t, 0), f2(f, t, 1), f1(f, t, 2), f2(f, t, 3), f1(f, t, 4),
                          f2(f, t, 5), f1(f, t, 6), f3(f, t, 7), f1(f, t, 8),
                          i1(i, t, 9), i1(i, t, 10), f1(f, t, 11), f2(f, t, 12), f2(f, t, 13),
                          f2(f, t, 14),
                          i1(i, t, 15), i1(i, t, 16), f1(f, t, 17), i1(i, t, 18), i1(i, t, 19),
                          i1(i, t, 20), i1(i, t, 21), i1(i, t, 22), i1(i, t, 23), f3(f, t, 24), i1(i, t, 25),
                          f1(f, t, 26), f1(f, t, 27),
                          f1(f, t, 28), f1(f, t, 29), i1(i, t, 30), i1(i, t, 31), f1(f, t, 32),
                          f1(f, t, 33), i1(i, t, 34), i1(i, t, 35))


def friction_unsupported(mech) -> list:
    """What keeps a scene with contact or joint friction off the compiled path (empty: supported)."""
    fm = mech.friction
    if fm is None:
        return []
    out = []
    if fm.has_joint_friction and fm.bound_mu is None:
        out.append("joint friction on spherical joints")
    if fm.settings.qp != "pgs":
        out.append("friction.qp: proxsuite")
    if len(mech.spring_ab):
        out.append("maximal springs with contact or joint friction")
    if mech.scheme == "bdf2":
        out.append("integrator.scheme: bdf2 with contact or joint friction")
    return out


def build_friction(mech):
    """Pack the constants of ``mech.friction`` (friction_unsupported is empty). Returns a packing.Packed."""
    fm = mech.friction
    st = fm.settings
    contacts = len(fm.plane_n) > 0 and len(fm.sph_jid) > 0
    joint = fm.has_joint_friction
    values = dict(
        sph_jid=fm.sph_jid if contacts else np.zeros(0), sph_local=fm.sph_local.reshape(-1, 3),
        sph_radius=fm.sph_radius, sph_support=fm.sph_support_f.reshape(len(fm.sph_jid), mech.nv),
        sph_mu=fm.sph_mu, plane_n=fm.plane_n.reshape(-1, 3), plane_off=fm.plane_off,
        plane_t=fm.plane_t.reshape(-1, 2, 3), plane_mu=fm.plane_mu,
        T_ptr=fm.T_ptr, T_idx=fm.T_idx, T_val=fm.T_val, rows_fixed=fm.rows_fixed.reshape(-1, mech.ndof),
        pin_moment=fm.pin_moment.reshape(-1, 3), loop_sdiff=fm.loop_sdiff.reshape(-1, mech.nv),
        sel_r=fm.sel_r, sel_c=fm.sel_c, sel_v=fm.sel_v, loop_index=fm.loop_index, pin_ja=fm.pin_ja,
        pin_jb=fm.pin_jb, loop_ja=fm.loop_ja, loop_jb=fm.loop_jb, fj_jid=fm.fj_jid,
        L_ops=fm.L_ops if joint else np.zeros((0, 6, 1)), L_of=fm.L_of if joint else np.zeros(0, dtype=np.int64),
        bound_mu=fm.bound_mu if joint else np.zeros(0),
        gravity=fm.gravity,
        scalars=np.array([st.tol, st.max_iter, st.anderson, st.margin, st.erp, fm.n_tree, fm.n_slots, fm.joint_slot0,
                          float(joint), float(contacts)], dtype=float),
    )
    # the most rows a step can have: bilateral (loops + every DOF prescribed) and staggered (contact normals,
    # two-sided limits, ground tangents, constant joint rows, loop pins; contact.rows_kernel's RX)
    n_pairs = len(fm.sph_jid) * len(fm.plane_n) if contacts else 0
    m_max = (0 if mech.loop_select is None else mech.loop_select.shape[0]) + mech.ndof
    nx_max = 3 * n_pairs + 2 * len(mech.limited) + values["rows_fixed"].shape[0] + values["loop_sdiff"].shape[0]
    nfl, nin = arena_size(mech.ndof, m_max, nx_max)
    values.update(arena=np.zeros(nfl), iarena=np.zeros(nin, dtype=np.int64), arena_off=np.zeros(2, dtype=np.int64),
                  loop_scratch=np.zeros(loop_scratch_size(nx_max, nx_max, int(st.anderson), 6 * len(values["L_of"]))))
    sfl, sin = step_arena_size(mech, values, m_max)
    values.update(step_arena=np.zeros(sfl), step_iarena=np.zeros(sin, dtype=np.int64),
                  step_off=np.zeros(2, dtype=np.int64))
    return pack(FRICTION_SPEC, values)


def step_arena_size(mech, values, m_max):
    """(floats, ints) that friction_solve takes from the step arena (step_arena, step_iarena): every take
    counted, with every sphere/plane pair in contact, both bounds of every limited coordinate finite and m_max
    bilateral rows (the most a step can have). ``values``: build_friction's constants."""
    ndof, nv_T, nj = mech.ndof, len(values["T_ptr"]) - 1, mech.model.njoints
    K = len(values["sph_jid"])
    P = len(values["plane_off"]) if K else 0
    nlim = 2 * len(mech.limited)
    F1, Lf = values["rows_fixed"].shape[0], values["pin_moment"].shape[0]
    rfl, rin = rows_arena_size(K, P, mech.nv, ndof, nlim, F1, Lf)
    nu = K * P + nlim
    nf = 2 * K * P + F1 + Lf
    nw, kmax, nloops = len(values["L_of"]), values["L_ops"].shape[2], len(mech.loop_ab)
    depth, n_slots = int(values["scalars"][SC_DEPTH]), int(values["scalars"][SC_N_SLOTS])
    floats = (6 * nj + nlim * ndof + nlim + rfl  # Z, the limit rows, the contacts and rows
              + nf + 6 * nw + 6 * nloops  # beta, W0, the loops' points
              + wrench_map_arena_size(ndof, nv_T, m_max, nloops, nj, Lf) + 6 * nj  # the wrench map, E0
              + nu + loop_state_size(nu, nf, depth, nw * kmax)  # alpha, the loop's state
              + 2 * ndof + m_max + n_slots + nw + finish_scratch_size(nu + nf, ndof, m_max)  # finish
              + ndof)  # the KKT residual's vector
    return floats, rin + nf + 3


@njit_inline
def unilateral_limit_rows(C, lo, hi, buf, off):
    """(CU, lo_CU): the joint-limit rows of Eq. (5) as unilateral rows CU qdot >= lo_CU, the finite lower bounds
    (rows C) first, then the finite upper ones (rows -C), as contact.staggered_rows stacks them; taken from the
    float arena ``buf`` (offsets ``off``, arena.py)."""
    n_lo, n_hi = 0, 0
    for r in range(lo.shape[0]):
        if np.isfinite(lo[r]):
            n_lo += 1
        if np.isfinite(hi[r]):
            n_hi += 1
    CU = take(buf, off, n_lo + n_hi, C.shape[1])
    lo_CU = take1(buf, off, 0, n_lo + n_hi)
    k = 0
    for r in range(lo.shape[0]):
        if np.isfinite(lo[r]):
            CU[k] = C[r]
            lo_CU[k] = lo[r]
            k += 1
    for r in range(lo.shape[0]):
        if np.isfinite(hi[r]):
            CU[k] = -C[r]
            lo_CU[k] = -hi[r]
            k += 1
    return CU, lo_CU


@njit_inline
def friction_solve(m, d, c, h, cache, has_cache, cache_new, jn, rep, work_cap, report):
    """qdot_R+ (d.v_hyper) and the bilateral multipliers (d.lam) of the frictional step, from the kinematics at
    (q_k, qdot_k) in d (stage 1), A_R, b_R (stage 2) and G, g, limits (stage 3). ``cache``: the last step's
    friction impulses (n_slots,; ``has_cache`` 0: a cold start); the new cache goes into ``cache_new``, the
    joints' normal loads sum_k |alpha_k| / h [N] into ``jn``, the report into ``rep`` (REP_*). ``work_cap``: the
    staggered loop's work budget (staggered.KERNEL_FIRST_WORK under a step budget, else inf). Returns SOLVED,
    NOT_PD (A_R not positive definite), RANK_DEFICIENT (G A^-1 G^T singular) or PAUSED (the loop reached
    ``work_cap`` before it finished: the reference pipeline takes the step under its deadline). ``report``: the
    KKT residual (rep[REP_KKT], a diagnostic) is computed, else NaN (kernel.one_step)."""
    sc = c.scalars
    ndof = d.AR.shape[0]
    buf, ibuf, off = c.step_arena, c.step_iarena, c.step_off  # every array of the step is taken from it
    off[0] = 0
    off[1] = 0
    Z = take(buf, off, m.parents.shape[0], 6)
    bias_kernel(m.parents, m.idx_v, m.nv_j, d.St, d.ov, d.v_r, d.R, d.p, d.c_local, Z)
    CU, lo_CU = unilateral_limit_rows(m.limit_rows, d.lo, d.hi, buf, off)
    ks, ps, X, n, t, gap, mu_g, jid, N, Tv, lo, RX, lo_U, nu = rows_kernel_into(
        d.R, d.p, d.St, c.sph_jid, c.sph_local, c.sph_radius, c.sph_support, c.sph_mu, c.plane_n, c.plane_off,
        c.plane_t, c.plane_mu, sc[SC_MARGIN], sc[SC_ERP], h, m.T, c.T_ptr, c.T_idx, c.T_val, ndof, c.rows_fixed,
        c.pin_moment, c.loop_sdiff, CU, lo_CU, buf, ibuf, off)
    nc = ks.shape[0]
    nf = RX.shape[0] - nu
    status, v0, PX, W_U, X_UT, X_TU, W_T, U_v0, T_v0, wU, wT, lam0, LamX = condense_into(
        d.AR, d.bR, d.G, d.g, RX, nu, c.arena, c.iarena, c.arena_off)
    if status == 1:
        return NOT_PD
    if status == 2:
        return RANK_DEFICIENT
    slots, beta = warm_start_into(cache, has_cache != 0, ks, ps, c.plane_n.shape[0], int(sc[SC_SLOT0]),
                                  take1(ibuf, off, 1, nf), take1(buf, off, 0, nf))
    joint = sc[SC_JOINT] != 0.0
    nw = c.L_of.shape[0]
    kmax = c.L_ops.shape[2]
    W0 = take(buf, off, nw, 6)
    W0[:, :] = 0.0
    nloops = m.loop_a.shape[0]
    xa = take(buf, off, nloops, 3)
    xb = take(buf, off, nloops, 3)
    for lp in range(nloops):
        for a in range(3):
            xa[lp, a] = d.X[m.loop_a[lp], a]
            xb[lp, a] = d.X[m.loop_b[lp], a]
    wm = make_wrench_map_into(nu, h, PX, c.T_ptr, c.T_idx, c.T_val, LamX, c.sel_r, c.sel_c, c.sel_v, c.loop_index,
                              int(sc[SC_N_TREE]), jid, X, n, t, c.pin_ja, c.pin_jb, c.pin_moment, c.loop_ja[:nloops],
                              c.loop_jb[:nloops], xa, xb, m.parents, m.idx_v, m.nv_j, d.St, d.I, d.R, d.p, c.fj_jid,
                              buf, off)
    if joint:  # Eq. (15)-(17): the constant part W0 here, the part linear in x = [alpha_U; beta] in the loop
        E0 = take(buf, off, d.ext.shape[0], d.ext.shape[1])
        E0[:, :] = d.ext  # constant world wrenches of the step (stage 2; no maximal springs here)
        constant_wrenches(wm, d.ov, Z, c.gravity, v0, d.v_r, lam0, E0, W0)
    alpha = take1(buf, off, 0, nu)
    alpha[:] = 0.0
    nal = nw * kmax
    depth = int(sc[SC_DEPTH])
    sbuf, sint = loop_state_into(nu, nf, depth, nal, buf, ibuf, off)  # a new loop's state
    scratch = c.loop_scratch
    if loop_scratch_size(nu, nf, depth, 6 * nw) > scratch.shape[0]:  # more rows than build_friction counted
        scratch = np.empty(loop_scratch_size(nu, nf, depth, 6 * nw))
    alpha, beta, bound, al, it, converged, resid, paused = staggered_kernel(
        W_U, X_UT, X_TU, U_v0, lo_U, W_T, T_v0, mu_g, W0.reshape(-1), wm, c.L_ops, c.L_of, h, c.bound_mu,
        kmax, joint, wU, wT, sc[SC_TOL], int(sc[SC_MAX_ITER]), depth, alpha, beta, sbuf, sint, work_cap, scratch)
    if paused:
        return PAUSED
    if not joint:
        al = al[:0]
    nx = nu + nf
    v, r, lam = take1(buf, off, 0, ndof), take1(buf, off, 0, ndof), take1(buf, off, 0, lam0.shape[0])
    new_cache, jnv = take1(buf, off, 0, int(sc[SC_N_SLOTS])), take1(buf, off, 0, al.shape[0] // kmax)
    active, max_pen, sticking = finish_into(
        v0, PX, d.bR, RX, lam0, LamX, alpha, beta, bound, al, slots, gap, kmax, h, v, r, lam, new_cache, jnv,
        take1(buf, off, 0, finish_scratch_size(nx, ndof, lam0.shape[0])))
    d.v_hyper[:] = v
    d.lam[:] = lam
    d.mu[:] = 0.0
    cache_new[:] = new_cache
    jn[:] = jnv
    rep[REP_ITERS] = it
    rep[REP_CONVERGED] = 1.0 if converged else 0.0
    rep[REP_RESIDUAL] = resid
    rep[REP_CONTACTS] = nc
    rep[REP_ACTIVE] = active
    rep[REP_PENETRATION] = max_pen
    rep[REP_STICKING] = sticking
    rep[REP_PAUSED] = 0.0
    # the relative KKT residual of the last contact stage's system A qdot = b + RX^T x - G^T lambda
    rep[REP_KKT] = kkt_residual_into(d.AR, r, d.v_hyper, d.G, d.lam, m.limit_rows[:0], d.mu[:0],
                                     take1(buf, off, 0, ndof)) if report else np.nan
    return SOLVED


@njit_inline
def bilateral_residual(d):
    """max|G qdot_R+ - g| [m/s] of the bilateral rows."""
    return max_row_residual(d.G, d.v_hyper, d.g)
