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

In the step the whole map is compiled (numba) and affine in the staggered unknowns x = [alpha_U; beta]
(linear_wrenches): the same Newton-Euler pass in the world frame at the origin (recursive.py's
convention) on the FrictionModel's own kinematics workspace (body_frames), giving W = W0 + Wx x per
frictional joint; each staggered iteration then needs only W and alpha_j = h L_j W_j. ExternalForces,
static_external and joint_alphas are the direct Pinocchio evaluation (one RNEA with fext per iterate)
kept as the test reference.

Deviation (stated): the implicit (h D_m, h^2 K_m) corrections of maximal springs and body damping
are not in f_ext (their explicit values at q are); they change the joint normal forces by O(h).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin
from numba import njit

from redmax_ros.core.solvers import recursive as rc
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


# ------------------------------------------------------------------------------------------------
# The affine map x = [alpha_U; beta] -> joint wrenches (compiled; world frame at the origin as in
# recursive.py, Pinocchio's (linear, angular) order)
# ------------------------------------------------------------------------------------------------
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


@njit(cache=True, nogil=True)
def _add_wrench(E, j, col, x, f, s):
    """E[j, :, col] += s [f; x x f] (world wrench about the origin of force f at point x)."""
    E[j, 0, col] += s * f[0]
    E[j, 1, col] += s * f[1]
    E[j, 2, col] += s * f[2]
    E[j, 3, col] += s * (x[1] * f[2] - x[2] * f[1])
    E[j, 4, col] += s * (x[2] * f[0] - x[0] * f[2])
    E[j, 5, col] += s * (x[0] * f[1] - x[1] * f[0])


@njit(cache=True, nogil=True)
def _external_kernel(nu, h, c_jid, c_X, c_n, c_t, pin_ja, pin_jb, pin_col0, pin_m, lp_ja, lp_jb, xa, xb, F0, dF,
                     E0, E):
    """External forces of the tree (§5.3, Eq. 17-18) as world wrenches per body: E0 (nj,6) at x = 0 and
    E (nj,6,nx) per unit x = [alpha_U; beta]:
      * ground contact c (Eq. 11-12): +n/h per unit alpha_c, -t_k/h per unit beta_(2c+k), at X_c;
      * loop-pin friction moments r axis/h per unit beta (site b +, site a -);
      * loop closures f_lambda = -J^T G^T lambda / h: F = Sel^T lambda / h on site b, -F on site a,
        F0 (at lambda_0) into E0, dF (L,3,nx) per unit x into E."""
    s = 1.0 / h
    for c in range(len(c_jid)):
        j = c_jid[c]
        _add_wrench(E, j, c, c_X[c], c_n[c], s)
        _add_wrench(E, j, nu + 2 * c, c_X[c], c_t[c, 0], -s)
        _add_wrench(E, j, nu + 2 * c + 1, c_X[c], c_t[c, 1], -s)
    for q in range(len(pin_ja)):
        col = pin_col0 + q
        for a in range(3):
            E[pin_jb[q], 3 + a, col] += pin_m[q, a]
            E[pin_ja[q], 3 + a, col] -= pin_m[q, a]
    nx = E.shape[2]
    f = np.empty(3)
    for lp in range(len(lp_ja)):
        ja, jb = lp_ja[lp], lp_jb[lp]
        for a in range(3):
            f[a] = F0[lp, a]
        x, y = xa[lp], xb[lp]
        E0[ja, 0] -= f[0]
        E0[ja, 1] -= f[1]
        E0[ja, 2] -= f[2]
        E0[ja, 3] -= x[1] * f[2] - x[2] * f[1]
        E0[ja, 4] -= x[2] * f[0] - x[0] * f[2]
        E0[ja, 5] -= x[0] * f[1] - x[1] * f[0]
        E0[jb, 0] += f[0]
        E0[jb, 1] += f[1]
        E0[jb, 2] += f[2]
        E0[jb, 3] += y[1] * f[2] - y[2] * f[1]
        E0[jb, 4] += y[2] * f[0] - y[0] * f[2]
        E0[jb, 5] += y[0] * f[1] - y[1] * f[0]
        d0, d1, d2 = dF[lp, 0], dF[lp, 1], dF[lp, 2]  # _add_wrench's terms, as row operations over the columns
        Ea, Eb = E[ja], E[jb]
        for col in range(nx):
            f0, f1, f2 = d0[col], d1[col], d2[col]
            Ea[0, col] += -1.0 * f0
            Ea[1, col] += -1.0 * f1
            Ea[2, col] += -1.0 * f2
            Ea[3, col] += -1.0 * (x[1] * f2 - x[2] * f1)
            Ea[4, col] += -1.0 * (x[2] * f0 - x[0] * f2)
            Ea[5, col] += -1.0 * (x[0] * f1 - x[1] * f0)
            Eb[0, col] += 1.0 * f0
            Eb[1, col] += 1.0 * f1
            Eb[2, col] += 1.0 * f2
            Eb[3, col] += 1.0 * (y[1] * f2 - y[2] * f1)
            Eb[4, col] += 1.0 * (y[2] * f0 - y[0] * f2)
            Eb[5, col] += 1.0 * (y[0] * f1 - y[1] * f0)


@njit(cache=True, nogil=True)
def _reaction_kernel(parents, idx_v, nv_j, St, I, ov, Z, g, acc0, Ax, E0, E, R, p, jids, W0, Wx):
    """Eq. (15)/(17) and the leaf-to-root distribution of §5.2.2 as one Newton-Euler pass, affine in x:
    body accelerations a_i = J_i (acc0 + Ax x) + Z_i - (g, 0) (forward, tree prefix sums), body wrenches
    F_i = I_i a_i + ov_i x* (I_i ov_i) - f_ext,i (E0 + E x), backward subtree sums (the backward pass of
    the RNEA), and each frictional joint's wrench in its joint frame (f = R^T F, tau = R^T (tau_o - p x F)):
    W0 (J,6) constant part, Wx (J,6,nx) per unit x. Equals Pinocchio's rnea(q, qdot^prev, acc, fext).f.
    E is scratch: it is overwritten by the linear part of the body wrenches and their subtree sums."""
    nj = parents.shape[0]
    nx = Ax.shape[1]
    A0 = np.zeros((nj, 6))
    AX = np.zeros((nj, 6, nx))
    F0 = np.zeros((nj, 6))
    FX = E  # in place: FX_i = I_i AX_i - E_i element by element
    A0[0, 0], A0[0, 1], A0[0, 2] = -g[0], -g[1], -g[2]
    a = np.empty(6)
    hm = np.empty(6)
    for j in range(1, nj):  # the per-x parts as row operations over the columns (contiguous rows: vectorised)
        par = parents[j]
        AXj, AXp = AX[j], AX[par]
        for r in range(6):
            A0[j, r] = A0[par, r]
            Rj, Rp = AXj[r], AXp[r]
            for col in range(nx):
                Rj[col] = Rp[col]
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            Axc = Ax[c]
            for r in range(6):
                sc = St[c, r]
                A0[j, r] += sc * acc0[c]
                Rj = AXj[r]
                for col in range(nx):
                    Rj[col] += sc * Axc[col]
        for r in range(6):
            a[r] = A0[j, r] + Z[j, r]
        for r in range(6):
            s = 0.0
            t = 0.0
            for k in range(6):
                s += I[j, r, k] * a[k]
                t += I[j, r, k] * ov[j, k]
            F0[j, r] = s - E0[j, r]
            hm[r] = t
        rc.add_motion_cross_force(ov[j], hm, F0[j])  # F0 += v x* h (gyroscopic/bias wrench)
        FXj = FX[j]
        X0, X1, X2, X3, X4, X5 = AXj[0], AXj[1], AXj[2], AXj[3], AXj[4], AXj[5]
        for r in range(6):  # FX_j = I_j AX_j - E_j, the six products of a row in one pass over the columns
            Fr = FXj[r]
            i0, i1, i2, i3, i4, i5 = I[j, r, 0], I[j, r, 1], I[j, r, 2], I[j, r, 3], I[j, r, 4], I[j, r, 5]
            for col in range(nx):
                Fr[col] = -Fr[col] + i0 * X0[col] + i1 * X1[col] + i2 * X2[col] + i3 * X3[col] + i4 * X4[col] \
                    + i5 * X5[col]
    for j in range(nj - 1, 0, -1):
        par = parents[j]
        FXj, FXp = FX[j], FX[par]
        for r in range(6):
            F0[par, r] += F0[j, r]
            Fp, Fj = FXp[r], FXj[r]
            for col in range(nx):
                Fp[col] += Fj[col]
    tq = np.empty((3, nx))  # moments about the joint origin, per column
    for q in range(len(jids)):
        j = jids[q]
        px, py, pz = p[j, 0], p[j, 1], p[j, 2]
        fx, fy, fz, tx, ty, tz = F0[j, 0], F0[j, 1], F0[j, 2], F0[j, 3], F0[j, 4], F0[j, 5]
        tx -= py * fz - pz * fy
        ty -= pz * fx - px * fz
        tz -= px * fy - py * fx
        for r in range(3):
            W0[q, r] = R[j, 0, r] * fx + R[j, 1, r] * fy + R[j, 2, r] * fz
            W0[q, 3 + r] = R[j, 0, r] * tx + R[j, 1, r] * ty + R[j, 2, r] * tz
        # the same per column x, as row operations over the columns (contiguous: vectorised)
        Fx, Fy, Fz = FX[j, 0], FX[j, 1], FX[j, 2]
        Tx, Ty, Tz = FX[j, 3], FX[j, 4], FX[j, 5]
        mx, my, mz = tq[0], tq[1], tq[2]
        for col in range(nx):
            mx[col] = Tx[col] - (py * Fz[col] - pz * Fy[col])
            my[col] = Ty[col] - (pz * Fx[col] - px * Fz[col])
            mz[col] = Tz[col] - (px * Fy[col] - py * Fx[col])
        for r in range(3):
            r0, r1, r2 = R[j, 0, r], R[j, 1, r], R[j, 2, r]
            Wf, Wt = Wx[q, r], Wx[q, 3 + r]
            for col in range(nx):
                Wf[col] = r0 * Fx[col] + r1 * Fy[col] + r2 * Fz[col]
                Wt[col] = r0 * mx[col] + r1 * my[col] + r2 * mz[col]


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


def linear_wrenches(mech, fm, work: FrictionWork, kin, ws, Z, h, v0, PX, v_prev_r, lam0, LamX, cs, nu, nf, cons,
                    site_forces=None, jdot_qdot=None):
    """The joint wrenches of Eq. (15)-(17) as an affine function of the staggered unknowns
    x = [alpha_U; beta]: W = W0 + Wx x, W0 (J+Lf, 6), Wx (J+Lf, 6, nx); the multipliers of Eq. (16) are
    then alpha_j = h L_j W_j (L_j the constant local least-squares operator, contact.ls_operator).

    Everything is linear in x once q and qdot^prev are fixed: the constrained velocity qdot_0 + PX x
    (hyper-reduced; PX = P [U^T, -T^T], condense.py) gives the acceleration (qdot^con - qdot^prev)/h in
    reduced coordinates through the coupling matrix (Eq. 9), the bilateral multipliers lambda = lambda_0 +
    LamX x (§5.3: loop closures and prescribed sites act as external forces), the ground impulses
    (Eq. 11-12) and the loop-pin friction moments. One compiled Newton-Euler pass over the tree
    (map_kernel) gives both parts; the loop pins' rows are the loop forces F = Sel^T lambda / h (world).
    Same numbers as Pinocchio's RNEA with the external forces (bisp.joint_alphas, the test reference).
    With a configuration-dependent J_rR (catalogue joint maps) the reduced acceleration of the step is
    (J_rR qdot_R^con - qdot_r^prev)/h + Jdot_rR qdot_R (Eq. 2.89, the term forces.assemble puts in the RHS):
    ``jdot_qdot`` (nv,) is added by passing qdot_r^prev - h jdot_qdot as the previous velocity (without it
    a spherical_exp joint's reaction misses M Sdot gdot, an O(1) error in its normal forces)."""
    topo = fm.topo
    nx = nu + nf
    E0 = static_external_world(mech, kin, ws, site_forces)
    E = np.zeros((topo.njoints, 6, nx))
    J = len(fm.fj_names)
    W0, Wx = np.zeros((J, 6)), np.zeros((J, 6, nx))
    for name, sl in cons.site_rows.items():  # prescribed sites (§5.3), rare: numpy
        s = mech.site_index[name]
        x = kin.X[kin.row[s]]
        j = mech.site_jid[s]
        f0, dFs = -lam0[sl] / h, -LamX[sl] / h
        P = cons.site_axes.get(name)
        if P is not None:  # rows along the site's k prescribed directions: their world force P^T f
            f0, dFs = P.T @ f0, P.T @ dFs
        E0[j] += np.concatenate([f0, _cross(x, f0)])
        E[j] += np.concatenate([dFs, _cross(x[:, None], dFs, axis=0)], axis=0)
    if cs is None:
        c_jid, c_X, c_n, c_t = _NO_INT, _NO_3, _NO_3, _NO_23
    else:
        c_jid, c_X, c_n, c_t = cs.jid, cs.X, cs.n, cs.t
    nloops = len(mech.loop_ab) if cons.loop_rows.stop else 0
    v_prev = v_prev_r if jdot_qdot is None else v_prev_r - h * jdot_qdot
    map_kernel(nu, h, v0, PX, v_prev, *coupling_csr(fm, work), lam0, LamX, fm.sel_r, fm.sel_c, fm.sel_v,
                nloops, kin.X, fm.loop_xa, fm.loop_xb, fm.loop_index, fm.n_tree, c_jid, c_X, c_n, c_t, fm.pin_ja,
                fm.pin_jb, fm.pin_moment, fm.loop_ja, fm.loop_jb, topo.parents, topo.idx_v, topo.nv_j, ws.St, ws.I,
                ws.ov, Z, fm.gravity, ws.R, ws.p, fm.fj_jid, E0, E, W0, Wx)
    return W0, Wx


_NO_INT = np.zeros(0, dtype=np.int64)
_NO_3 = np.zeros((0, 3))
_NO_23 = np.zeros((0, 2, 3))


@njit(cache=True, nogil=True)
def map_kernel(nu, h, v0, PX, v_prev, T_ptr, T_idx, T_val, lam0, LamX, sel_r, sel_c, sel_v, nloops, X, rows_a,
                rows_b, loop_index, n_tree, c_jid, c_X, c_n, c_t, pin_ja, pin_jb, pin_m, lp_ja, lp_jb, parents, idx_v,
                nv_j, St, I, ov, Z, g, R, p, jids, E0, E, W0, Wx):
    """linear_wrenches in one compiled call: reduced accelerations acc0 = (T qdot_0 - qdot^prev)/h and
    Ax = T PX / h (T = coupling matrix of Eq. 9 in CSR form), loop forces F = Sel^T (lambda_0 + LamX x) / h
    (Sel as triplets), then _external_kernel and _reaction_kernel."""
    nv, nx = len(v_prev), PX.shape[1]
    inv_h = 1.0 / h
    acc0 = np.empty(nv)
    Ax = np.zeros((nv, nx))
    for i in range(nv):
        s = 0.0
        for q in range(T_ptr[i], T_ptr[i + 1]):
            c, t = T_idx[q], T_val[q]
            s += t * v0[c]
            for col in range(nx):
                Ax[i, col] += t * PX[c, col]
        acc0[i] = (s - v_prev[i]) * inv_h
        for col in range(nx):
            Ax[i, col] *= inv_h
    F0 = np.zeros((nloops, 3))
    dF = np.zeros((nloops, 3, nx))
    if nloops:
        for q in range(len(sel_r)):
            r, c, sv = sel_r[q], sel_c[q], sel_v[q]
            lp, a = c // 3, c % 3
            F0[lp, a] += sv * lam0[r]
            for col in range(nx):
                dF[lp, a, col] += sv * LamX[r, col]
        for lp in range(nloops):
            for a in range(3):
                F0[lp, a] *= inv_h
                for col in range(nx):
                    dF[lp, a, col] *= inv_h
        for q in range(len(loop_index)):
            li = loop_index[q]
            for a in range(3):
                W0[n_tree + q, a] = F0[li, a]
                for col in range(nx):
                    Wx[n_tree + q, a, col] = dF[li, a, col]
    xa = np.empty((nloops, 3))
    xb = np.empty((nloops, 3))
    for lp in range(nloops):
        for a in range(3):
            xa[lp, a] = X[rows_a[lp], a]
            xb[lp, a] = X[rows_b[lp], a]
    pin_mh = pin_m * inv_h
    _external_kernel(nu, h, c_jid, c_X, c_n, c_t, pin_ja, pin_jb, nx - len(pin_ja), pin_mh, lp_ja[:nloops],
                     lp_jb[:nloops], xa, xb, F0, dF, E0, E)
    _reaction_kernel(parents, idx_v, nv_j, St, I, ov, Z, g, acc0, Ax, E0, E, R, p, jids, W0, Wx)


def affine_alphas(fm, h, W0, Wx):
    """(a0 ((J+Lf) kmax,), Mx ((J+Lf) kmax, nx)): alpha_joints = a0 + Mx x (Eq. 16 applied to W0 + Wx x)."""
    a0 = h * np.einsum("jkl,jl->jk", fm.L, W0)
    Mx = h * np.matmul(fm.L, Wx)
    return a0.reshape(-1), Mx.reshape(-1, Wx.shape[2])


def linear_alphas(mech, fm, work: FrictionWork, kin, q, v_prev_r, h, v0, PX, lam0, LamX, cs, nu, nf, cons,
                  site_forces=None):
    """alpha_joints = a0 + Mx x from the condensed velocity qdot_0 + PX x (hyper-reduced) and
    lambda_0 + LamX x: body_frames + linear_wrenches + affine_alphas in one call (tests, reference)."""
    ws, Z = body_frames(fm, work, q, v_prev_r)
    W0, Wx = linear_wrenches(mech, fm, work, kin, ws, Z, h, v0, np.ascontiguousarray(PX), v_prev_r, lam0, LamX, cs,
                             nu, nf, cons, site_forces)
    return affine_alphas(fm, h, W0, Wx)
