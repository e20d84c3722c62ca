"""BISP contact multipliers of the frictional joints (paper §5.2.1-5.2.3 and §5.3; Sueda's notes §2.12).

Eq. (15)/(17): the joint reaction force is f_a = M_m (J_mr qdot_r^con - qdot_m^unc) / h, i.e. per body
the Newton-Euler residual of the constrained (reduced) motion,
    f_a,i = M_i (v_i^con - v_i^prev)/h + (Coriolis)_i - f_i - f_beta,i - f_ext,i ,
where f_ext holds every external force of the step: gravity, maximal springs, wrenches, the ground
contact and ground friction impulses of the current staggered iterate, and the external bilateral
constraint forces (loop closures f_lambda = -J^T G^T lambda / h and prescribed sites, §5.3, with
lambda from the constrained reduced solve of Eq. 17c). The leaf-to-root distribution of §5.2.2 ("a
leaf's portion of f_a is its joint's reaction; subtract it, transformed by the adjoint, from the
parent") is exactly the backward pass of the recursive Newton-Euler algorithm: Pinocchio's RNEA with
the finite-difference acceleration (qdot^con - qdot^prev)/h, the step's velocity qdot^prev (the
quadratic velocity vector of Eq. 2 is evaluated there) and the external forces ``fext`` returns in
data.f[j] the wrench joint j transmits to its subtree (joint frame). Its constraint part is then
distributed over the implicit contact points by the constant local operator of Eq. (16) built in
contact.compile_friction; the loop-closing pins get their reaction straight from lambda.

In the step the map is compiled (numba) and affine in the staggered unknowns x = [alpha_U; beta],
W = W0 + Wx x per frictional joint, evaluated by the same Newton-Euler pass in the world frame at the
origin (recursive.py's convention) on the FrictionModel's own kinematics workspace (body_frames):
the constant part W0 once per step (wrench_map), the linear part Wx x at each staggered iterate
(apply_wrenches: one pass with that iterate's velocity change, multipliers and impulses; Wx itself is
never formed: building it took one pass per column of x, ~50 us a walker step against ~1-2 us a pass);
each iteration then needs alpha_j = h L_j W_j. ExternalForces, static_external and joint_alphas are the
direct Pinocchio evaluation (one RNEA with fext per iterate) kept as the test reference.

Deviation (stated): the implicit (h D_m, h^2 K_m) corrections of maximal springs and body damping
are not in f_ext (their explicit values at q are); they change the joint normal forces by O(h).
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np
import pinocchio as pin
from numba import njit

from redmax_ros.core.jit import njit_inline
from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.friction.arena import empty_arena, take, take1
from redmax_ros.core.friction.contact import FrictionWork, coupling_csr
from redmax_ros.core.dynamics.forces import spring_terms


class ExternalForces:
    """World forces/moments on bodies accumulated as local joint-frame wrenches for Pinocchio's fext."""

    def __init__(self, mech, data):
        nj = mech.model.njoints
        self.R = np.array([data.oMi[i].rotation for i in range(nj)])  # (nj,3,3)
        self.p = np.array([data.oMi[i].translation for i in range(nj)])  # (nj,3)
        self.base = np.zeros((nj, 6))

    def local(self, jid, F, x=None, Mw=None):
        """(c,6) local wrenches of world forces F (c,3) at world points x (c,3) and/or world moments Mw."""
        R, p = self.R[jid], self.p[jid]
        mom = np.zeros_like(F) if Mw is None else Mw.copy()
        if x is not None:
            mom += _cross(x - p, F)  # moment about the joint origin
        return np.concatenate([np.einsum("cji,cj->ci", R, F), np.einsum("cji,cj->ci", R, mom)], axis=1)

    def add(self, out, jid, F, x=None, Mw=None):
        jid = np.asarray(jid, dtype=int)
        if len(jid):
            np.add.at(out, jid, self.local(jid, F, x, Mw))


def static_external(mech, kin, ext: ExternalForces, data, site_forces=None):
    """Explicit maximal forces of the step (springs at q, constant wrenches, commanded site forces)."""
    out = ext.base
    if len(mech.spring_ab):
        fs, *_ = spring_terms(mech, kin.X, kin.J, kin.v)
        a, b = mech.spring_ab[:, 0], mech.spring_ab[:, 1]
        xa, xb = kin.X[mech.spring_rows[:, 0]], kin.X[mech.spring_rows[:, 1]]
        ext.add(out, mech.site_jid[a], fs, xa)
        ext.add(out, mech.site_jid[b], -fs, xb)
    if len(mech.wrench_body):
        jid = mech.body_jid[mech.wrench_body]
        com = np.array([data.oMi[int(j)].act(c) for j, c in zip(jid, mech.body_com[mech.wrench_body])])
        ext.add(out, jid, mech.wrench_fw[:, :3], com, mech.wrench_fw[:, 3:])
    if site_forces:
        idx = np.array(list(site_forces), dtype=int)
        ext.add(out, mech.site_jid[idx], np.array(list(site_forces.values())), kin.X[[kin.row[s] for s in idx]])
    return out


def joint_alphas(mech, fm, work: FrictionWork, data, q, v_prev_r, v_con_r, h, fx_local, loop_force):
    """alpha (J+Lf, kmax): Eq. (16) multipliers of every frictional joint and loop pin.

    fx_local (njoints,6): all external wrenches (local frames); loop_force (Lf,3): world force of each
    frictional loop on its site b [N]."""
    fext = work.fext
    for i in range(1, len(fx_local)):
        fext[i] = pin.Force(fx_local[i])
    pin.rnea(mech.model, data, q, v_prev_r, (v_con_r - v_prev_r) / h, fext)
    W = np.zeros((len(fm.fj_names), 6))
    f = data.f
    for k, j in enumerate(fm.fj_jid):
        W[k] = f[int(j)].vector
    if len(loop_force):
        W[fm.n_tree:, :3] = loop_force
    return h * np.einsum("jkl,jl->jk", fm.L, W)


def _cross(a, b, axis=-1):
    """a x b along ``axis`` (np.cross without its per-call overhead; broadcasting)."""
    a0, a1, a2 = np.take(a, 0, axis), np.take(a, 1, axis), np.take(a, 2, axis)
    b0, b1, b2 = np.take(b, 0, axis), np.take(b, 1, axis), np.take(b, 2, axis)
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=axis)


def body_frames(fm, work: FrictionWork, q, v_prev_r):
    """Forward kinematics of the step for the BISP map and contact detection (recursive.py kernels on
    the friction stage's own workspace ``work.tree``: no per-joint Pinocchio calls): world placements R,
    p, motion subspaces St (= data.J^T), spatial inertias I at the origin, twists ov = J qdot^prev and the
    bias accelerations Z = Jdot qdot^prev (the quadratic velocity term of Eq. 2). Returns (ws, Z)."""
    topo, ws = fm.topo, work.tree
    if fm.planar is None:
        rc.update_kinematics(topo, ws, q, v_prev_r)
    else:  # every FALLBACK joint is a Pinocchio planar joint: constant S, zero bias, transform from q
        rc.planar_placements(fm.planar, topo.idx_q, q, ws.jR, ws.jp)
        rc.fk_kernel(topo.parents, topo.kind, topo.idx_q, topo.idx_v, topo.nv_j, topo.axis, topo.pitch,
                      topo.place_R, topo.place_p, q, ws.jR, ws.jp, ws.Sl, ws.R, ws.p, ws.St)
        rc.world_inertia_kernel(topo.mass, topo.com, topo.inertia_com, ws.R, ws.p, ws.I)
        ws.v = v_prev_r
        rc.jv_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, v_prev_r, ws.ov)
    return ws, rc.bias_acceleration(topo, ws, work.Z)


def static_external_world(mech, kin, ws, site_forces=None):
    """(njoints,6) world wrenches (about the origin) of the explicit maximal forces of the step: springs
    at q, constant body wrenches, commanded site forces."""
    out = np.zeros((mech.model.njoints, 6))
    if len(mech.spring_ab):
        fs, *_ = spring_terms(mech, kin.X, kin.J, kin.v)
        a, b = mech.spring_ab[:, 0], mech.spring_ab[:, 1]
        xa, xb = kin.X[mech.spring_rows[:, 0]], kin.X[mech.spring_rows[:, 1]]
        np.add.at(out, mech.site_jid[a], np.hstack([fs, _cross(xa, fs)]))
        np.add.at(out, mech.site_jid[b], -np.hstack([fs, _cross(xb, fs)]))
    if len(mech.wrench_body):
        jid = mech.body_jid[mech.wrench_body]
        com = ws.p[jid] + np.einsum("cij,cj->ci", ws.R[jid], mech.body_com[mech.wrench_body])
        F, Mw = mech.wrench_fw[:, :3], mech.wrench_fw[:, 3:]
        np.add.at(out, jid, np.hstack([F, Mw + _cross(com, F)]))
    if site_forces:
        idx = np.array(list(site_forces), dtype=int)
        F = np.array(list(site_forces.values()), dtype=float).reshape(-1, 3)
        x = kin.X[[kin.row[s] for s in idx]]
        np.add.at(out, mech.site_jid[idx], np.hstack([F, _cross(x, F)]))
    return out


# ------------------------------------------------------------------------------------------------
# The joint wrenches as a function of x = [alpha_U; beta] (compiled; world frame at the origin as in
# recursive.py, Pinocchio's (linear, angular) order): the constant part once per step, the part linear
# in x evaluated at each iterate (apply_wrenches) by one Newton-Euler pass over the tree
# ------------------------------------------------------------------------------------------------
WrenchMap = namedtuple("WrenchMap", [
    "nu", "inv_h",  # unilateral rows of x; 1/h [1/s]
    "PX", "T_ptr", "T_idx", "T_val",  # velocity per unit x (hyper-reduced, condense.py), coupling matrix (Eq. 9, CSR)
    "LamX", "sel_r", "sel_c", "sel_v",  # bilateral multipliers per unit x; lambda -> point forces (triplets)
    "loop_index", "n_tree",  # frictional loops' point forces (their pins' wrench rows follow the tree joints')
    "c_jid", "c_X", "c_n", "c_t",  # ground contacts: body, point, normal, tangents (world)
    "pin_ja", "pin_jb", "pin_col0", "pin_mh",  # loop-pin friction moments per unit beta (/h)
    "f_ja", "f_jb", "f_xa", "f_xb",  # point forces: -F on body f_ja at f_xa (none: -1), +F on f_jb at f_xb
    "parents", "idx_v", "nv_j", "St", "I", "R", "p", "jids",  # the tree (body_frames) and the frictional joints
    "dense",  # (6J, nx): an explicitly given linear part (no tree: parents empty)
    "s_u", "s_acc", "s_lam", "s_F", "s_E", "s_A", "s_a", "s_h", "s_f",  # scratch
])


@njit(cache=True, nogil=True)
def _point_forces(lam, sel_r, sel_c, sel_v, inv_h, F):
    """F (k,3) = Sel^T lambda / h: the point forces of the bilateral rows (loop closures, prescribed sites)."""
    F[:] = 0.0
    for q in range(len(sel_r)):
        c = sel_c[q]
        F[c // 3, c % 3] += sel_v[q] * lam[sel_r[q]]
    for k in range(F.shape[0]):
        for a in range(3):
            F[k, a] *= inv_h


@njit_inline
def _external(wm, x, F, E):
    """E (nj,6) += the external forces of the tree (§5.3, Eq. 17-18) as world wrenches per body:
      * ground contact c (Eq. 11-12) at X_c: n alpha_c / h - t_k beta_(2c+k) / h;
      * loop-pin friction moments r axis beta / h (site b +, site a -);
      * point forces F of the bilateral rows (loop closures f_lambda = -J^T G^T lambda / h: -F on site a,
        +F on site b; prescribed sites on one body).
    The contact and pin terms are skipped with x empty (the constant part)."""
    nu, s = wm.nu, wm.inv_h
    if x.shape[0]:
        f = wm.s_f
        for c in range(len(wm.c_jid)):
            a, b0, b1 = x[c], x[nu + 2 * c], x[nu + 2 * c + 1]
            for k in range(3):
                f[k] = wm.c_n[c, k] * a - wm.c_t[c, 0, k] * b0 - wm.c_t[c, 1, k] * b1
            rc.add_point_wrench(E, wm.c_jid[c], wm.c_X[c], f, s)
        for q in range(len(wm.pin_ja)):
            b = x[wm.pin_col0 + q]
            for a in range(3):
                E[wm.pin_jb[q], 3 + a] += wm.pin_mh[q, a] * b
                E[wm.pin_ja[q], 3 + a] -= wm.pin_mh[q, a] * b
    for k in range(F.shape[0]):
        if wm.f_ja[k] >= 0:
            rc.add_point_wrench(E, wm.f_ja[k], wm.f_xa[k], F[k], -1.0)
        rc.add_point_wrench(E, wm.f_jb[k], wm.f_xb[k], F[k], 1.0)


@njit_inline
def _reactions(wm, ov, Z, g, acc, E, bias, W):
    """Eq. (15)/(17) and the leaf-to-root distribution of §5.2.2 as one Newton-Euler pass: body accelerations
    a_i = J_i acc (+ Z_i - (g, 0) with ``bias``; forward, tree prefix sums), body wrenches F_i = I_i a_i
    (+ ov_i x* (I_i ov_i) with ``bias``) - E_i, backward subtree sums (the backward pass of the RNEA), and each
    frictional joint's wrench in its joint frame (f = R^T F, tau = R^T (tau_o - p x F)) into W (J,6).
    With bias (the constant part) it equals Pinocchio's rnea(q, qdot^prev, acc, fext).f; without, its
    part linear in (acc, E). E is overwritten by the subtree sums; the loop pins' rows of W are untouched."""
    parents, idx_v, nv_j, St, I = wm.parents, wm.idx_v, wm.nv_j, wm.St, wm.I
    nj = parents.shape[0]
    A, a, hm = wm.s_A, wm.s_a, wm.s_h
    A[0, :] = 0.0
    if bias:
        A[0, 0], A[0, 1], A[0, 2] = -g[0], -g[1], -g[2]
    for j in range(1, nj):
        par = parents[j]
        for r in range(6):
            A[j, r] = A[par, r]
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            ac = acc[c]
            for r in range(6):
                A[j, r] += St[c, r] * ac
        for r in range(6):
            a[r] = A[j, r] + Z[j, r] if bias else A[j, r]
        Ij, Ej = I[j], E[j]
        for r in range(6):
            s = 0.0
            for k in range(6):
                s += Ij[r, k] * a[k]
            Ej[r] = s - Ej[r]
        if bias:
            for r in range(6):
                t = 0.0
                for k in range(6):
                    t += Ij[r, k] * ov[j, k]
                hm[r] = t
            rc.add_motion_cross_force(ov[j], hm, Ej)  # F += v x* h (gyroscopic/bias wrench)
    for j in range(nj - 1, 0, -1):
        par = parents[j]
        for r in range(6):
            E[par, r] += E[j, r]
    R, p, jids = wm.R, wm.p, wm.jids
    for q in range(len(jids)):
        j = jids[q]
        px, py, pz = p[j, 0], p[j, 1], p[j, 2]
        fx, fy, fz, tx, ty, tz = E[j, 0], E[j, 1], E[j, 2], E[j, 3], E[j, 4], E[j, 5]
        tx -= py * fz - pz * fy
        ty -= pz * fx - px * fz
        tz -= px * fy - py * fx
        for r in range(3):
            W[q, r] = R[j, 0, r] * fx + R[j, 1, r] * fy + R[j, 2, r] * fz
            W[q, 3 + r] = R[j, 0, r] * tx + R[j, 1, r] * ty + R[j, 2, r] * tz


@njit_inline
def _pin_rows(wm, F, W):
    """The frictional loop pins' rows of W: their loop's point force (world)."""
    for q in range(len(wm.loop_index)):
        li = wm.loop_index[q]
        for a in range(3):
            W[wm.n_tree + q, a] = F[li, a]
        for a in range(3, 6):
            W[wm.n_tree + q, a] = 0.0


@njit_inline
def constant_wrenches(wm, ov, Z, g, v0, v_prev, lam0, E0, W0):
    """W0 (J,6): the joint wrenches of Eq. (15)-(17) at x = 0: reduced accelerations (T qdot_0 - qdot^prev)/h,
    the point forces of lambda_0, the constant world wrenches E0 (nj,6; overwritten) of the step."""
    acc = wm.s_acc
    for i in range(acc.shape[0]):
        s = 0.0
        for q in range(wm.T_ptr[i], wm.T_ptr[i + 1]):
            s += wm.T_val[q] * v0[wm.T_idx[q]]
        acc[i] = (s - v_prev[i]) * wm.inv_h
    _point_forces(lam0, wm.sel_r, wm.sel_c, wm.sel_v, wm.inv_h, wm.s_F)
    _external(wm, v0[:0], wm.s_F, E0)
    _reactions(wm, ov, Z, g, acc, E0, True, W0)
    _pin_rows(wm, wm.s_F, W0)


@njit_inline
def apply_wrenches(wm, x, out):
    """out (6J,) = the part of the joint wrenches linear in x = [alpha_U; beta], W(x) - W(0) (Eq. 15-17), in
    one Newton-Euler pass: the velocity change PX x gives the acceleration T PX x / h (Eq. 9), the
    multipliers LamX x the point forces of the bilateral rows, x itself the contact impulses and pin
    moments. With no tree (``dense`` map): out = dense x."""
    if wm.parents.shape[0] == 0:
        np.dot(wm.dense, x, out)
        return
    u, acc, lam, E = wm.s_u, wm.s_acc, wm.s_lam, wm.s_E
    np.dot(wm.PX, x, u)
    for i in range(acc.shape[0]):
        s = 0.0
        for q in range(wm.T_ptr[i], wm.T_ptr[i + 1]):
            s += wm.T_val[q] * u[wm.T_idx[q]]
        acc[i] = s * wm.inv_h
    if lam.shape[0]:
        np.dot(wm.LamX, x, lam)
    _point_forces(lam, wm.sel_r, wm.sel_c, wm.sel_v, wm.inv_h, wm.s_F)
    E[:] = 0.0
    _external(wm, x, wm.s_F, E)
    W = out.reshape((out.shape[0] // 6, 6))
    _reactions(wm, E[:, :0], E[:, :0], E[0, :0], acc, E, False, W)
    _pin_rows(wm, wm.s_F, W)


@njit(cache=True, nogil=True)
def wrench_work(wm):
    """About the multiply-adds of one apply_wrenches (the staggered loop's work units, solvers/budget.py)."""
    return float(wm.PX.size + wm.LamX.size + wm.dense.size + 90 * wm.parents.shape[0] + 40 * wm.jids.shape[0])


@njit(cache=True, nogil=True)
def make_wrench_map(nu, h, PX, T_ptr, T_idx, T_val, LamX, sel_r, sel_c, sel_v, loop_index, n_tree, c_jid, c_X, c_n,
                    c_t, pin_ja, pin_jb, pin_moment, f_ja, f_jb, f_xa, f_xb, parents, idx_v, nv_j, St, I, R, p, jids):
    """:func:`make_wrench_map_into` with its scratch allocated here (the reference pipeline's call)."""
    buf, ibuf, off = empty_arena()
    return make_wrench_map_into(nu, h, PX, T_ptr, T_idx, T_val, LamX, sel_r, sel_c, sel_v, loop_index, n_tree, c_jid,
                                c_X, c_n, c_t, pin_ja, pin_jb, pin_moment, f_ja, f_jb, f_xa, f_xb, parents, idx_v,
                                nv_j, St, I, R, p, jids, buf, off)


@njit(cache=True, nogil=True)
def wrench_map_arena_size(n, nv, m, n_pts, nj, n_pins):
    """Floats that :func:`make_wrench_map_into` takes from its arena for n DOFs (PX rows), nv velocity DOFs,
    m bilateral rows, n_pts point forces, nj tree joints and n_pins loop pins."""
    return 3 * n_pins + n + nv + m + 3 * n_pts + 12 * nj + 15


@njit(cache=True, nogil=True)
def make_wrench_map_into(nu, h, PX, T_ptr, T_idx, T_val, LamX, sel_r, sel_c, sel_v, loop_index, n_tree, c_jid, c_X,
                         c_n, c_t, pin_ja, pin_jb, pin_moment, f_ja, f_jb, f_xa, f_xb, parents, idx_v, nv_j, St, I, R,
                         p, jids, buf, off):
    """The WrenchMap of a step, its scratch and the pin moments divided by h taken from the float arena ``buf``
    (offsets ``off``: arena.py, wrench_map_arena_size; not reset here)."""
    n_pts = f_ja.shape[0]
    pin_mh = take(buf, off, pin_moment.shape[0], 3)
    for q in range(pin_moment.shape[0]):  # as pin_moment / h
        for a in range(3):
            pin_mh[q, a] = pin_moment[q, a] / h
    nj = parents.shape[0]
    return WrenchMap(nu, 1.0 / h, PX, T_ptr, T_idx, T_val, LamX, sel_r, sel_c, sel_v, loop_index, n_tree, c_jid, c_X,
                     c_n, c_t, pin_ja, pin_jb, PX.shape[1] - len(pin_ja), pin_mh, f_ja, f_jb, f_xa, f_xb,
                     parents, idx_v, nv_j, St, I, R, p, jids, take(buf, off, 0, PX.shape[1]),
                     take1(buf, off, 0, PX.shape[0]), take1(buf, off, 0, len(T_ptr) - 1),
                     take1(buf, off, 0, LamX.shape[0]), take(buf, off, n_pts, 3), take(buf, off, nj, 6),
                     take(buf, off, nj, 6), take1(buf, off, 0, 6), take1(buf, off, 0, 6), take1(buf, off, 0, 3))


def dense_wrench_map(Mx):
    """A WrenchMap whose linear part is the given matrix Mx (rows, nx) (apply_wrenches: Mx x), for callers
    with the map in closed form (the maximal-coordinates baseline, tests)."""
    Mx = np.ascontiguousarray(Mx, dtype=float)
    nx = Mx.shape[1]
    i0, f0 = np.zeros(0, dtype=np.int64), np.zeros(0)
    f2, f3 = np.zeros((0, 3)), np.zeros((0, 6, 6))
    return WrenchMap(0, 1.0, np.zeros((0, nx)), np.zeros(1, dtype=np.int64), i0, f0, np.zeros((0, nx)), i0, i0, f0,
                     i0, 0, i0, f2, f2, np.zeros((0, 2, 3)), i0, i0, 0, f2, i0, i0, f2, f2, i0, i0, i0,
                     np.zeros((0, 6)), f3, np.zeros((0, 3, 3)), f2, i0, Mx, f0, f0, f0, f2, np.zeros((0, 6)),
                     np.zeros((0, 6)), np.empty(6), np.empty(6), np.empty(3))


def wrench_map(mech, fm, work: FrictionWork, kin, ws, Z, h, v0, PX, v_prev_r, lam0, LamX, cs, nu, nf, cons,
               site_forces=None, jdot_qdot=None):
    """The joint wrenches of Eq. (15)-(17) as a function of the staggered unknowns x = [alpha_U; beta]:
    W(x) = W0 + (the linear part, apply_wrenches(wm, x)), J = frictional joints + frictional loop pins rows;
    the multipliers of Eq. (16) are then alpha_j = h L_j W_j (L_j the constant local least-squares operator,
    contact.ls_operator). Returns (W0 (J,6), wm).

    Everything is linear in x once q and qdot^prev are fixed: the constrained velocity qdot_0 + PX x
    (hyper-reduced; PX = P [U^T, -T^T], condense.py) gives the acceleration (qdot^con - qdot^prev)/h in
    reduced coordinates through the coupling matrix (Eq. 9), the bilateral multipliers lambda = lambda_0 +
    LamX x (§5.3: loop closures and prescribed sites act as external forces), the ground impulses
    (Eq. 11-12) and the loop-pin friction moments. The constant part is one Newton-Euler pass over the tree
    here, the linear part one pass per staggered iterate (a pass costs about what a product with the
    dense (6J x nx) map would, which then needs no building). Same numbers as Pinocchio's RNEA with the
    external forces (bisp.joint_alphas, the test reference).
    With a configuration-dependent J_rR (catalogue joint maps) the reduced acceleration of the step is
    (J_rR qdot_R^con - qdot_r^prev)/h + Jdot_rR qdot_R (Eq. 2.89, the term forces.assemble puts in the RHS):
    ``jdot_qdot`` (nv,) is added by passing qdot_r^prev - h jdot_qdot as the previous velocity (without it
    a spherical_exp joint's reaction misses M Sdot gdot, an O(1) error in its normal forces)."""
    topo = fm.topo
    E0 = static_external_world(mech, kin, ws, site_forces)
    J = len(fm.fj_names)
    nloops = len(mech.loop_ab) if cons.loop_rows.stop else 0
    sel_r, sel_c, sel_v = (fm.sel_r, fm.sel_c, fm.sel_v) if nloops else (_NO_INT, _NO_INT, _NO_F)
    f_ja, f_jb = fm.loop_ja[:nloops], fm.loop_jb[:nloops]
    f_xa, f_xb = kin.X[fm.loop_xa[:nloops]], kin.X[fm.loop_xb[:nloops]]
    if cons.site_rows:  # prescribed sites (§5.3), rare: their rows' point forces -P^T lambda / h on one body
        rows, cols, vals, jb, xb = [sel_r], [sel_c], [sel_v], [f_jb], [f_xb]
        k = nloops
        for name, sl in cons.site_rows.items():
            s = mech.site_index[name]
            P = cons.site_axes.get(name)
            P = np.eye(3) if P is None else P
            r = np.arange(sl.start, sl.stop)
            rr, aa = np.meshgrid(r, np.arange(3), indexing="ij")
            rows.append(rr.ravel())
            cols.append(3 * k + aa.ravel())
            vals.append(-P.reshape(-1))
            jb.append([mech.site_jid[s]])
            xb.append(kin.X[kin.row[s]][None])
            k += 1
        sel_r, sel_c = np.concatenate(rows).astype(np.int64), np.concatenate(cols).astype(np.int64)
        sel_v = np.concatenate(vals).astype(float)
        f_jb = np.concatenate([np.asarray(a, dtype=np.int64) for a in jb])
        f_xb = np.concatenate(xb)
        f_ja = np.concatenate([f_ja, np.full(k - nloops, -1, dtype=np.int64)])
        f_xa = np.concatenate([f_xa, np.zeros((k - nloops, 3))])
    if cs is None:
        c_jid, c_X, c_n, c_t = _NO_INT, _NO_3, _NO_3, _NO_23
    else:
        c_jid, c_X, c_n, c_t = cs.jid, cs.X, cs.n, cs.t
    v_prev = v_prev_r if jdot_qdot is None else v_prev_r - h * jdot_qdot
    wm = make_wrench_map(nu, h, np.ascontiguousarray(PX), *coupling_csr(fm, work), np.ascontiguousarray(LamX), sel_r,
                         sel_c, sel_v, fm.loop_index, fm.n_tree, c_jid, c_X, c_n, c_t, fm.pin_ja, fm.pin_jb,
                         fm.pin_moment, f_ja, f_jb, np.ascontiguousarray(f_xa), np.ascontiguousarray(f_xb),
                         topo.parents, topo.idx_v, topo.nv_j, ws.St, ws.I, ws.R, ws.p, fm.fj_jid)
    W0 = np.zeros((J, 6))
    constant_wrenches(wm, ws.ov, Z, fm.gravity, v0, v_prev, lam0, E0, W0)
    return W0, wm


_NO_INT = np.zeros(0, dtype=np.int64)
_NO_F = np.zeros(0)
_NO_3 = np.zeros((0, 3))
_NO_23 = np.zeros((0, 2, 3))


def joint_alphas_at(fm, h, W0, wm, x):
    """alpha of the frictional joints at x (((J) kmax,)): Eq. (16) applied to W0 + the linear part at x."""
    W = W0.reshape(-1) + _apply(wm, x)
    return (h * np.einsum("jkl,jl->jk", fm.L, W.reshape(-1, 6))).reshape(-1)


def _apply(wm, x):
    out = np.zeros(6 * len(wm.jids) + 6 * len(wm.loop_index) if wm.parents.shape[0] else wm.dense.shape[0])
    apply_wrenches(wm, np.ascontiguousarray(x, dtype=float), out)
    return out


def linear_alphas(mech, fm, work: FrictionWork, kin, q, v_prev_r, h, v0, PX, lam0, LamX, cs, nu, nf, cons,
                  site_forces=None):
    """x -> the joint multipliers alpha at x from the condensed velocity qdot_0 + PX x (hyper-reduced) and
    lambda_0 + LamX x: body_frames + wrench_map + Eq. (16) (tests, reference)."""
    ws, Z = body_frames(fm, work, q, v_prev_r)
    W0, wm = wrench_map(mech, fm, work, kin, ws, Z, h, v0, PX, v_prev_r, lam0, LamX, cs, nu, nf, cons, site_forces)
    return lambda x: joint_alphas_at(fm, h, W0, wm, x)
