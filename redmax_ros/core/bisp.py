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

Deviation (stated): the implicit (h D_m, h^2 K_m) corrections of maximal springs and body damping
are not in f_ext (their explicit values at q are); they change the joint normal forces by O(h).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin


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
        from .forces import spring_terms
        fs, *_ = spring_terms(mech, kin.X, kin.J)
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


def joint_alphas(mech, fm, data, q, v_prev_r, v_con_r, h, fx_local, loop_force):
    """alpha (J+Lf, kmax): Eq. (16) multipliers of every frictional joint and loop pin.

    fx_local (njoints,6): all external wrenches (local frames); loop_force (Lf,3): world force of each
    frictional loop on its site b [N]."""
    fext = fm.fext
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


def subtree_matrix(mech, jids):
    """(len(jids), njoints) 0/1: Pinocchio joint i is in the subtree of joint j (body i hangs below j)."""
    model = mech.model
    Sub = np.zeros((len(jids), model.njoints))
    for r, j in enumerate(jids):
        Sub[r, list(model.subtrees[int(j)])] = 1.0
    return Sub


def _cross(a, b, axis=-1):
    """a x b along ``axis`` (np.cross without its per-call overhead; broadcasting)."""
    a0, a1, a2 = np.take(a, 0, axis), np.take(a, 1, axis), np.take(a, 2, axis)
    b0, b1, b2 = np.take(b, 0, axis), np.take(b, 1, axis), np.take(b, 2, axis)
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=axis)


def _wrench_cols(x, F):
    """World wrenches (force, moment about the origin) of forces F (...,3) at points x (...,3)."""
    return np.concatenate([F, _cross(x, F)], axis=-1)


def _skew_batch(v):
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def _world_inertias(mech, R, p):
    """(nj-1,6,6) spatial inertias of the joint bodies about the world origin, world axes (Pinocchio
    order: linear, angular), from the joint placements R (nj,3,3), p (nj,3)."""
    cache = getattr(mech, "_inertia_cache", None)
    if cache is None:
        model = mech.model
        ins = [model.inertias[i] for i in range(1, model.njoints)]
        cache = (np.array([y.mass for y in ins]), np.array([y.lever for y in ins]),
                 np.array([y.inertia for y in ins]))
        mech._inertia_cache = cache
    m, c, Ic = cache
    R, p = R[1:], p[1:]
    cw = p + np.einsum("bij,bj->bi", R, c)
    Icw = np.matmul(np.matmul(R, Ic), R.transpose(0, 2, 1))
    C = _skew_batch(cw)
    out = np.zeros((len(m), 6, 6))
    out[:, :3, :3] = m[:, None, None] * np.eye(3)
    out[:, :3, 3:] = -m[:, None, None] * C
    out[:, 3:, :3] = m[:, None, None] * C
    out[:, 3:, 3:] = Icw - m[:, None, None] * np.matmul(C, C)
    return out


def _dual_inverse(R, p):
    """(k,6,6) maps of world wrenches (about the origin) to local joint-frame wrenches."""
    Rt = R.transpose(0, 2, 1)
    D = np.zeros((len(R), 6, 6))
    D[:, :3, :3] = Rt
    D[:, 3:, 3:] = Rt
    D[:, 3:, :3] = -np.matmul(Rt, _skew_batch(p))
    return D


def linear_alphas(mech, fm, data, kin, q, v_prev_r, h, v0, PX, lam0, LamX, fx_static_local, cs, nu, nf,
                  cons, site_forces=None, ext=None):
    """The joint multipliers as an affine function of the staggered unknowns x = [alpha_U; beta]:
    alpha_joints = a0 + M x  (shapes ((J+Lf)*kmax,), ((J+Lf)*kmax, nu+nf)).

    Everything in Eq. (15)-(17) is linear in x once q and qdot^prev are fixed: the constrained velocity
    qdot^con = qdot_0 + P X^T x (PX = P [U^T, -T^T]), the bilateral multipliers lambda = lambda_0 +
    LamX x, the ground impulses and the loop-pin friction moments. The constant part is one RNEA
    (backward pass = the leaf-to-root distribution of §5.2.2); the linear part is the same backward
    sum written with world-frame composite terms: the wrench through joint j is
    sum_{i in subtree(j)} (I_i^w J_i^w a - f_ext,i^w), taken to the joint frame. This makes each
    staggered iteration a matrix-vector product instead of a Newton-Euler pass (same numbers)."""
    model = mech.model
    nv, nx = mech.nv, nu + nf
    T = mech.T
    to_r = (lambda X: X) if T is None else (lambda X: T @ X)
    nj = model.njoints
    ext = ExternalForces(mech, data) if ext is None else ext
    # constant part: a0 = (qdot_0 - qdot_prev)/h, external forces at x = 0 (static + lambda_0 terms)
    fx0 = fx_static_local.copy()
    loopF0, loopdF, E = _lambda_forces(mech, fm, kin, ext, fx0, lam0, LamX, cons, h, nx)
    fext = fm.fext
    for i in range(1, nj):
        fext[i] = pin.Force(fx0[i])
    pin.rnea(model, data, q, v_prev_r, (to_r(v0) - v_prev_r) / h, fext)
    ntree = fm.n_tree
    W0 = np.zeros((len(fm.fj_names), 6))
    for k, j in enumerate(fm.fj_jid):
        W0[k] = data.f[int(j)].vector
    W0[ntree:, :3] = loopF0
    # linear part, world frame
    if nc := (0 if cs is None else len(cs.keys)):
        Fn = _wrench_cols(cs.X, cs.n) / h  # (c,6) per unit alpha
        np.add.at(E, (cs.jid, slice(None), np.arange(nc)), Fn)
        for k in range(2):
            Ft = -_wrench_cols(cs.X, cs.t[:, k]) / h
            np.add.at(E, (cs.jid, slice(None), nu + 2 * np.arange(nc) + k), Ft)
    nl = len(fm.loop_index)
    if nl:
        ab = mech.loop_ab[fm.loop_index]
        Mw = np.concatenate([np.zeros((nl, 3)), (fm.loop_radius / h)[:, None] * fm.loop_axis], axis=1)
        cols = nu + nf - nl + np.arange(nl)
        np.add.at(E, (mech.site_jid[ab[:, 1]], slice(None), cols), Mw)
        np.add.at(E, (mech.site_jid[ab[:, 0]], slice(None), cols), -Mw)
    A_x = to_r(PX) / h  # (nv, nx) acceleration per unit x
    Jw = data.J.reshape(6, nv)
    Iw = _world_inertias(mech, ext.R, ext.p)  # (nj-1,6,6)
    IJ = np.matmul(Iw, Jw[None] * mech_support(mech)[1:, None, :])  # (nj-1,6,nv)
    Sub = fm.sub[:, 1:]
    Kw = np.tensordot(Sub, IJ, axes=(1, 0))  # (J,6,nv)
    Ew = np.tensordot(Sub, E[1:], axes=(1, 0))  # (J,6,nx)
    Wx_w = np.matmul(Kw, A_x) - Ew  # (J,6,nx) world
    D = _dual_inverse(ext.R[fm.fj_jid], ext.p[fm.fj_jid])
    Wx = np.zeros((len(fm.fj_names), 6, nx))
    Wx[:ntree] = np.matmul(D, Wx_w)
    Wx[ntree:, :3] = loopdF
    a0 = h * np.einsum("jkl,jl->jk", fm.L, W0)
    Mx = h * np.matmul(fm.L, Wx)  # (J+Lf, kmax, nx)
    return a0.reshape(-1), Mx.reshape(-1, nx)


def mech_support(mech):
    """(njoints, nv) bool: DOFs supporting each Pinocchio joint (cached on the mechanism)."""
    s = getattr(mech, "_joint_support", None)
    if s is None:
        s = mech.joint_support.astype(float)
        mech._joint_support = s
    return s


def _lambda_forces(mech, fm, kin, ext, fx0, lam0, LamX, cons, h, nx):
    """External-constraint forces of the tree (§5.3): loops (both sites) and prescribed sites, at
    lambda_0 (added to fx0, local frames) and per unit x (world wrenches E (njoints,6,nx)).
    Returns (loopF0 (Lf,3), loopdF (Lf,3,nx), E)."""
    nj = mech.model.njoints
    E = np.zeros((nj, 6, nx))
    nl = len(fm.loop_index)
    loopF0, loopdF = np.zeros((nl, 3)), np.zeros((nl, 3, nx))
    if cons.loop_rows.stop:
        ab, rows_ab = mech.loop_ab, mech.loop_rows_ab
        xa, xb = kin.X[rows_ab[:, 0]], kin.X[rows_ab[:, 1]]
        L = len(ab)
        Sel = mech.loop_select  # (rows, 3L): phi = Sel (x_a - x_b) stacked
        nr = Sel.shape[0]
        F0 = (Sel.T @ lam0[:nr]).reshape(L, 3) / h
        dF = (Sel.T @ LamX[:nr]).reshape(L, 3, nx) / h
        ext.add(fx0, mech.site_jid[ab[:, 0]], -F0, xa)
        ext.add(fx0, mech.site_jid[ab[:, 1]], F0, xb)
        wa = np.concatenate([dF, _cross(xa[:, :, None], dF, axis=1)], axis=1)  # (L,6,nx)
        wb = np.concatenate([dF, _cross(xb[:, :, None], dF, axis=1)], axis=1)
        np.add.at(E, mech.site_jid[ab[:, 0]], -wa)
        np.add.at(E, mech.site_jid[ab[:, 1]], wb)
        if nl:
            loopF0[:] = F0[fm.loop_index]
            loopdF[:] = dF[fm.loop_index]
    for name, sl in cons.site_rows.items():
        s = mech.site_index[name]
        x = kin.X[kin.row[s]]
        ext.add(fx0, [mech.site_jid[s]], (-lam0[sl] / h)[None], x[None])
        dF = -LamX[sl] / h  # (3,nx)
        E[mech.site_jid[s]] += np.concatenate([dF, _cross(x[:, None], dF, axis=0)], axis=0)
    return loopF0, loopdF, E
