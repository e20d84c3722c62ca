"""Eq. (2) on the recursive passes, without ``pin.Data`` (the data-free pipeline: PCG and the dense
data-free direct solver):

* the RHS in O(n + m) (:func:`rhs`): M qdot + h (tau - nle - K_r (q - q_rest) + J^T f_m), nle from
  Newton-Euler wrenches of the world-frame body twists and the bias accelerations, all projected by
  one J^T pass;
* the maximal 6x6 blocks (:func:`maximal_blocks`: body damping h D_m and the springs' lever-arm stiffness)
  for solvers.pcg.MatrixFreeSystem;
* a dense LHS (:func:`dense_lhs`) for the data-free direct solver: a CRBA-style pass over composite
  inertias (M_m plus the 6x6 diagonal blocks of the maximal stiffness/damping) plus the cross-body
  spring terms, O(n d + sum_s d_a d_b) for tree depth d.

Conventions match the Pinocchio pipeline (forces.py); test/core/step/test_matrix_free.py checks each piece.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.springs import clamp_lever_blocks, geometric_blocks_kernel, joint_displacement
from redmax_ros.core.dynamics.tree_kinematics import Context
from redmax_ros.core.jit import njit
from redmax_ros.core.solvers import recursive as rc


@njit
def nle_wrench_kernel(I, ov, acc, g, W):
    """Newton-Euler wrenches (world, at the origin) for the quadratic-velocity and gravity terms:
    W_j = I_j (a_j - (g, 0)) + ov_j x* (I_j ov_j), with a_j = Jdot_j qdot (bias acceleration).
    J^T W = nle = -J^T (f_m - M_m Jdot qdot) of Eq. (1)-(2) (Pinocchio's RNEA at zero acceleration)."""
    nj = I.shape[0]
    a = np.empty(6)
    hm = np.empty(6)
    for j in range(1, nj):
        for r in range(6):
            a[r] = acc[j, r]
        a[0] -= g[0]
        a[1] -= g[1]
        a[2] -= g[2]
        for r in range(6):
            s = 0.0
            t = 0.0
            for c in range(6):
                s += I[j, r, c] * a[c]
                t += I[j, r, c] * ov[j, c]
            W[j, r] = s
            hm[r] = t
        rc.add_motion_cross_force(ov[j], hm, W[j])  # W += v x* h (gyroscopic/bias wrench)
    for r in range(6):
        W[0, r] = 0.0


@njit
def dense_crba_kernel(parents, idx_v, nv_j, St, Ic, A):
    """A += J^T blkdiag(Ic) J by the composite-rigid-body algorithm in the world frame.
    Ic (njoints,6,6) holds each body's 6x6 block on entry and is overwritten by the composites.
    Every column pair (c of joint j, c2 of an ancestor-or-self joint k) gets S_c2^T Ic_j S_c."""
    nj = parents.shape[0]
    for j in range(nj - 1, 0, -1):
        p = parents[j]
        if p > 0:
            for a in range(6):
                for b in range(6):
                    Ic[p, a, b] += Ic[j, a, b]
    F = np.empty(6)
    for j in range(1, nj):
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            for a in range(6):
                s = 0.0
                for b in range(6):
                    s += Ic[j, a, b] * St[c, b]
                F[a] = s
            k = j
            while k > 0:
                for c2 in range(idx_v[k], idx_v[k] + nv_j[k]):
                    s = 0.0
                    for a in range(6):
                        s += St[c2, a] * F[a]
                    if c2 == c:
                        A[c, c] += s
                    elif c2 < c or k != j:
                        A[c2, c] += s
                        A[c, c2] += s
                k = parents[k]


@njit
def spring_cross_kernel(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A):
    """A -= J_a^T C J_b + J_b^T C J_a for springs between two different moving bodies (the
    off-diagonal blocks of sum_s J_s^T C_s J_s; the diagonal blocks are in the composite inertias)."""
    nv = St.shape[0]
    cols_a = np.empty(nv, np.int64)
    cols_b = np.empty(nv, np.int64)
    Pa = np.empty((nv, 3))
    Pb = np.empty((nv, 3))
    CPb = np.empty((nv, 3))
    for s in range(ja.shape[0]):
        i, k = ja[s], jb[s]
        if i == 0 or k == 0 or i == k:
            continue
        na = 0
        j = i
        while j > 0:
            for c in range(idx_v[j], idx_v[j] + nv_j[j]):
                w0, w1, w2 = St[c, 3], St[c, 4], St[c, 5]
                x = pa[s]
                Pa[na, 0] = St[c, 0] + w1 * x[2] - w2 * x[1]
                Pa[na, 1] = St[c, 1] + w2 * x[0] - w0 * x[2]
                Pa[na, 2] = St[c, 2] + w0 * x[1] - w1 * x[0]
                cols_a[na] = c
                na += 1
            j = parents[j]
        nb = 0
        j = k
        while j > 0:
            for c in range(idx_v[j], idx_v[j] + nv_j[j]):
                w0, w1, w2 = St[c, 3], St[c, 4], St[c, 5]
                x = pb[s]
                Pb[nb, 0] = St[c, 0] + w1 * x[2] - w2 * x[1]
                Pb[nb, 1] = St[c, 1] + w2 * x[0] - w0 * x[2]
                Pb[nb, 2] = St[c, 2] + w0 * x[1] - w1 * x[0]
                cols_b[nb] = c
                nb += 1
            j = parents[j]
        for m in range(nb):
            for a in range(3):
                CPb[m, a] = C[s, a, 0] * Pb[m, 0] + C[s, a, 1] * Pb[m, 1] + C[s, a, 2] * Pb[m, 2]
        for l in range(na):
            ca = cols_a[l]
            for m in range(nb):
                cb = cols_b[m]
                val = Pa[l, 0] * CPb[m, 0] + Pa[l, 1] * CPb[m, 1] + Pa[l, 2] * CPb[m, 2]
                A[ca, cb] -= val
                A[cb, ca] -= val


def body_damping_blocks(ctx: Context, h: float) -> np.ndarray | None:
    """Maximal 6x6 blocks h D_m per joint (world twists), D_m = c diag(m_d I3, R I_d R^T) at the COM:
    (m_d, I_d) = (m, I_com) for body-damping form 'mass', (1, I3) for form 'twist' (D_m = c I6 on the
    body twist, notes §1.9.1); the same D_m as forces.assemble."""
    if not len(ctx.damp_jid):
        return None
    ws = ctx.ws
    B = np.zeros((ctx.topo.njoints, 6, 6))
    for j, com, Ic, m, c in zip(ctx.damp_jid, ctx.damp_com, ctx.damp_I, ctx.damp_m, ctx.damp_c):
        R, p = ws.R[j], ws.p[j]
        x = R @ com + p
        Iw = R @ Ic @ R.T
        X = np.zeros((3, 6))  # COM velocity = v_o + w x x = [1, -[x]] (v_o, w)
        X[:, :3] = np.eye(3)
        X[:, 3:] = -pin.skew(x)
        blk = m * X.T @ X
        blk[3:, 3:] += Iw
        B[j] += (h * c) * blk
    return B


def maximal_blocks(ctx: Context, h: float, springs=None) -> np.ndarray | None:
    """The maximal 6x6 blocks per joint (world twists) of the LHS: body damping h D_m
    (:func:`body_damping_blocks`) plus, with integrator.spring_stiffness: full, the springs' lever-arm
    stiffness h^2 B (springs.geometric_blocks_kernel, kept above minus half of each body's spatial inertia by
    springs.clamp_lever_blocks) from ``springs`` = (f_a (P,3), positions of mech.jac_sites); None when there is
    neither. The same terms as forces.assemble."""
    D = body_damping_blocks(ctx, h)
    mech = ctx.mech
    if springs is None or not len(mech.spring_ab) or not mech.spring_geometric:
        return D
    fs, X = springs
    B = np.zeros((ctx.topo.njoints, 6, 6))
    rows = mech.spring_rows
    ex = np.zeros(len(fs), np.int64) if mech.spring_explicit is None else mech.spring_explicit.astype(np.int64)
    geometric_blocks_kernel(ctx.spring_ja, np.ascontiguousarray(X[rows[:, 0]]), ctx.spring_jb,
                            np.ascontiguousarray(X[rows[:, 1]]), np.ascontiguousarray(fs), ex, h * h, ctx.ws.I, B)
    clamp_lever_blocks(ctx.ws.I, B)
    return B if D is None else B + D


def rhs(ctx: Context, q, v_r, tau, h, site_forces=None, springs=None) -> np.ndarray:
    """RHS of Eq. (2) in reduced coordinates, O(n + m), for the (q, v_r) held in ctx.ws:
    b = M v_r + h (tau - nle - K_r (q - q_rest) + J_s^T f_springs + wrenches + J^T site forces).
    ``springs``: (f_a (P,3), positions of mech.jac_sites) from :func:`spring_terms`."""
    mech, topo, ws = ctx.mech, ctx.topo, ctx.ws
    acc = rc.bias_acceleration(topo, ws)
    W = np.empty((topo.njoints, 6))
    nle_wrench_kernel(ws.I, ws.ov, acc, ctx.gravity, W)
    # W_total = I ov - h W_nle + h W_ext, then one J^T pass
    W *= -h
    W += np.einsum("jab,jb->ja", ws.I, ws.ov)
    ext = np.zeros((topo.njoints, 6))
    if springs is not None and len(mech.spring_ab):
        fs, X = springs
        a, b = mech.spring_rows[:, 0], mech.spring_rows[:, 1]
        rc.accumulate_site_forces(ext, ctx.spring_ja, X[a], fs)
        rc.accumulate_site_forces(ext, ctx.spring_jb, X[b], -fs)
    if len(ctx.wrench_jid):
        for j, com, fw in zip(ctx.wrench_jid, ctx.wrench_com, ctx.wrench_fw):
            if j == 0:
                continue
            x = ws.R[j] @ com + ws.p[j]
            ext[j, :3] += fw[:3]
            ext[j, 3:] += np.cross(x, fw[:3]) + fw[3:]
    if site_forces:
        idx = np.array(list(site_forces), dtype=int)
        F = np.array([site_forces[i] for i in idx], dtype=float).reshape(-1, 3)
        rc.accumulate_site_forces(ext, ctx.site_jid[idx], ctx.site_positions(idx), F)
    ext[0] = 0.0
    W += h * ext
    b = rc.jtw(topo, ws, W)
    b += ctx.armature * v_r
    f_r = np.array(tau, dtype=float)
    if mech.has_stiffness:
        f_r -= mech.stiffness * joint_displacement(mech, q)
    b += h * f_r
    return b


def dense_lhs(ctx: Context, h: float, blocks: np.ndarray, springs_C: np.ndarray | None,
              pa: np.ndarray | None, pb: np.ndarray | None) -> np.ndarray:
    """Dense LHS of Eq. (2) (reduced coordinates, positive-stiffness convention) from the recursive
    workspace: J^T (I + blocks) J by composite inertias, minus the cross-body spring terms, plus
    armature + h D_r + h^2 K_r. ``blocks``: the blkdiag maximal blocks (MatrixFreeSystem's
    preconditioner_blocks), ``springs_C``: (P,3,3) h D_s + h^2 K_s at world points pa, pb."""
    topo, ws = ctx.topo, ctx.ws
    nv = topo.nv
    A = np.zeros((nv, nv))
    Ic = ws.I + blocks
    Ic[0] = 0.0
    dense_crba_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, Ic, A)
    if springs_C is not None and len(springs_C):
        spring_cross_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, ctx.spring_ja, pa, ctx.spring_jb, pb,
                             springs_C, A)
    A[np.diag_indices(nv)] += ctx.armature + ctx.reduced_diag(h)
    return A
