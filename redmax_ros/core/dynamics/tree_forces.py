"""Eq. (2) on the recursive passes, without ``pin.Data`` (the data-free pipeline: PCG and the dense
data-free direct solver):

* the RHS in O(n + m) (:func:`rhs`): M qdot + h (tau - nle - K_r (q - q_rest) + J^T f_m), nle from
  Newton-Euler wrenches of the world-frame body twists and the bias accelerations, all projected by
  one J^T pass;
* the maximal 6x6 blocks (:func:`maximal_blocks`: body damping h D_m and the springs' lever-arm stiffness)
  for solvers.pcg.MatrixFreeSystem;
* a dense LHS (:func:`dense_lhs`) for the data-free direct solver: a CRBA-style pass over composite
  inertias (M_m plus the 6x6 diagonal blocks of the maximal stiffness/damping) plus the cross-body
  spring terms by composites of the spring ends' wrenches, O(n d + sum_s (d_a + d_b) + n nv) for tree
  depth d; both lower-triangle kernels (the compiled step's) whose rows are contiguous, vectorised loops.

Conventions match the Pinocchio pipeline (forces.py); test/core/step/test_matrix_free.py checks each piece.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.springs import clamp_lever_blocks, geometric_blocks_kernel, joint_displacement
from redmax_ros.core.dynamics.tree_kinematics import Context
from redmax_ros.core.jit import njit
from redmax_ros.core.linalg import add_lower_symmetric
from redmax_ros.core.solvers import recursive as rc


@njit
def _row6(M, j, r, x):
    """sum_c M[j, r, c] x[c] over c < 6 (one row of a body's 6x6 block times a 6-vector or 6-tuple)."""
    s = 0.0
    for c in range(6):
        s += M[j, r, c] * x[c]
    return s


@njit
def nle_wrench_kernel(I, ov, acc, g, W):
    """Newton-Euler wrenches (world, at the origin) for the quadratic-velocity and gravity terms:
    W_j = I_j (a_j - (g, 0)) + ov_j x* (I_j ov_j), with a_j = Jdot_j qdot (bias acceleration).
    J^T W = nle = -J^T (f_m - M_m Jdot qdot) of Eq. (1)-(2) (Pinocchio's RNEA at zero acceleration)."""
    nj = I.shape[0]
    for j in range(1, nj):
        a = (acc[j, 0] - g[0], acc[j, 1] - g[1], acc[j, 2] - g[2], acc[j, 3], acc[j, 4], acc[j, 5])
        for r in range(6):
            W[j, r] = _row6(I, j, r, a)
        o = ov[j]
        hm = (_row6(I, j, 0, o), _row6(I, j, 1, o), _row6(I, j, 2, o), _row6(I, j, 3, o), _row6(I, j, 4, o),
              _row6(I, j, 5, o))
        rc.add_motion_cross_force(o, hm, W[j])  # W += v x* h (gyroscopic/bias wrench)
    for r in range(6):
        W[0, r] = 0.0


@njit
def all_support_runs(parents, idx_v, nv_j):
    """The DOFs that move each joint's body (its own and its ancestors') as maximal runs of consecutive
    indices: (ptr (njoints+1,), runs (R, 2)), joint j's runs (lo, hi) in runs[ptr[j]:ptr[j+1]], from j towards
    the root (decreasing indices; j's own DOFs end the first). In Pinocchio's depth-first order a serial chain
    is one run per joint, and a path through a branch point starts a new run at each child that is not the
    first. O(total runs): j's from its parent's, merged when the parent's DOFs end where j's start."""
    nj = parents.shape[0]
    ptr = np.zeros(nj + 1, np.int64)
    for j in range(1, nj):
        p = parents[j]
        n = ptr[p + 1] if p > 0 else 0  # the parent's count (ptr holds counts until the prefix sum)
        if not (p > 0 and idx_v[p] + nv_j[p] == idx_v[j]):
            n += 1
        ptr[j + 1] = n
    for j in range(nj):
        ptr[j + 1] += ptr[j]
    runs = np.empty((ptr[nj], 2), np.int64)
    for j in range(1, nj):
        p = parents[j]
        o = ptr[j]
        lo, hi = idx_v[j], idx_v[j] + nv_j[j]
        q0 = ptr[p] if p > 0 else 0
        q1 = ptr[p + 1] if p > 0 else 0
        if p > 0 and idx_v[p] + nv_j[p] == lo:
            lo = runs[q0, 0]
            q0 += 1
        runs[o, 0], runs[o, 1] = lo, hi
        for q in range(q0, q1):
            runs[o + 1 + q - q0, 0], runs[o + 1 + q - q0, 1] = runs[q, 0], runs[q, 1]
    return ptr, runs


@njit
def crba_lower_kernel(parents, idx_v, nv_j, St, Ic, A):
    """:func:`crba_runs_kernel` with its support runs and scratch made here (allocates)."""
    ptr, runs = all_support_runs(parents, idx_v, nv_j)
    crba_runs_kernel(parents, idx_v, nv_j, St, Ic, A, ptr, runs, np.empty((6, St.shape[0])))


@njit
def crba_runs_kernel(parents, idx_v, nv_j, St, Ic, A, ptr, runs, StT):
    """A's lower triangle (diagonal included) += that of J^T blkdiag(Ic) J, by the composite-rigid-body
    algorithm in the world frame (Featherstone, Rigid Body Dynamics Algorithms, §6.2). Ic (njoints,6,6) holds
    each body's 6x6 block on entry and is overwritten by the composites. Column c of joint j gives row c of the
    lower triangle: A[c, c2] += S_c2^T (Ic_j S_c) for c2 <= c on the DOFs supporting j (``ptr``, ``runs``: the
    constant :func:`all_support_runs` of the tree), each run as one contiguous (vectorised) row update over
    ``StT`` (6, nv) scratch, St transposed."""
    nj = parents.shape[0]
    nv = St.shape[0]
    for j in range(nj - 1, 0, -1):
        p = parents[j]
        if p > 0:
            for a in range(6):
                for b in range(6):
                    Ic[p, a, b] += Ic[j, a, b]
    for c in range(nv):
        for a in range(6):
            StT[a, c] = St[c, a]
    for j in range(1, nj):
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            Sc = St[c]  # F = Ic_j S_c
            f0, f1, f2 = _row6(Ic, j, 0, Sc), _row6(Ic, j, 1, Sc), _row6(Ic, j, 2, Sc)
            f3, f4, f5 = _row6(Ic, j, 3, Sc), _row6(Ic, j, 4, Sc), _row6(Ic, j, 5, Sc)
            for r in range(ptr[j], ptr[j + 1]):
                lo, hi = runs[r, 0], (c + 1 if r == ptr[j] else runs[r, 1])
                Ar = A[c, lo:hi]
                S0, S1, S2 = StT[0, lo:hi], StT[1, lo:hi], StT[2, lo:hi]
                S3, S4, S5 = StT[3, lo:hi], StT[4, lo:hi], StT[5, lo:hi]
                for t in range(Ar.shape[0]):
                    Ar[t] += ((f0 * S0[t] + f1 * S1[t]) + (f2 * S2[t] + f3 * S3[t])) + (f4 * S4[t] + f5 * S5[t])


@njit
def dense_crba_kernel(parents, idx_v, nv_j, St, Ic, A):
    """A += J^T blkdiag(Ic) J (both triangles): :func:`crba_lower_kernel` into a scratch matrix, added to A
    symmetrically. Ic is overwritten by the composites."""
    M = np.zeros(A.shape)
    crba_lower_kernel(parents, idx_v, nv_j, St, Ic, M)
    add_lower_symmetric(M, A)


@njit
def _add_end_wrenches(StT, x, y, C, transpose, runs, r0, r1, Q, W):
    """W[:, c] += X_x^T C' X_y S_c (6 x nv) over the runs runs[r0:r1] (the support of the other end): the
    wrench at the world origin of the force C' J_y[:, c] at the end x, J_y[:, c] = X_y S_c the point Jacobian
    of the other end y, X_y = [I, -[y]] (Eq. S2.4), X_x^T f = (f, x x f); C' = C, or C^T with ``transpose``.
    Q (6, 6) scratch: X_x^T C' X_y, then one contiguous 6-term row update per row of W."""
    x0, x1, x2 = x[0], x[1], x[2]
    y0, y1, y2 = y[0], y[1], y[2]
    for a in range(3):
        if transpose:
            c0, c1, c2 = C[0, a], C[1, a], C[2, a]
        else:
            c0, c1, c2 = C[a, 0], C[a, 1], C[a, 2]
        Q[a, 0], Q[a, 1], Q[a, 2] = c0, c1, c2
        Q[a, 3] = c2 * y1 - c1 * y2
        Q[a, 4] = c0 * y2 - c2 * y0
        Q[a, 5] = c1 * y0 - c0 * y1
    for b in range(6):
        Q[3, b] = x1 * Q[2, b] - x2 * Q[1, b]
        Q[4, b] = x2 * Q[0, b] - x0 * Q[2, b]
        Q[5, b] = x0 * Q[1, b] - x1 * Q[0, b]
    for r in range(r0, r1):
        lo, hi = runs[r, 0], runs[r, 1]
        S0, S1, S2 = StT[0, lo:hi], StT[1, lo:hi], StT[2, lo:hi]
        S3, S4, S5 = StT[3, lo:hi], StT[4, lo:hi], StT[5, lo:hi]
        for a in range(6):
            q0, q1, q2, q3, q4, q5 = Q[a, 0], Q[a, 1], Q[a, 2], Q[a, 3], Q[a, 4], Q[a, 5]
            Wa = W[a, lo:hi]
            for t in range(Wa.shape[0]):
                Wa[t] += ((q0 * S0[t] + q1 * S1[t]) + (q2 * S2[t] + q3 * S3[t])) + (q4 * S4[t] + q5 * S5[t])


@njit
def _clear_columns(W, lo, hi):
    for a in range(6):
        Wa = W[a, lo:hi]
        for t in range(Wa.shape[0]):
            Wa[t] = 0.0


@njit
def spring_cross_slots(parents) -> int:
    """The accumulators :func:`spring_cross_lower_into` has alive at once (its W's first size): the finished
    subtrees not yet merged into their parent's, at most, over the reverse depth-first visit (at least 1)."""
    nj = parents.shape[0]
    nchild = np.zeros(nj, np.int64)
    for j in range(1, nj):
        if parents[j] > 0:
            nchild[parents[j]] += 1
    pending = 0
    cap = 1
    for j in range(nj - 1, 0, -1):
        pending += 1 - nchild[j]
        cap = max(cap, pending)
        if parents[j] == 0:
            pending -= 1
    return cap


@njit
def spring_cross_iwork_size(nj, P, cap):
    """Length of :func:`spring_cross_lower_into`'s int64 scratch for nj joints, P springs, cap slots."""
    return 3 * nj + 2 * P + 3 * cap


@njit
def spring_cross_lower_kernel(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A):
    """:func:`spring_cross_lower_into` with scratch of its own."""
    nv, nj = St.shape[0], parents.shape[0]
    cap = spring_cross_slots(parents)
    ptr, runs = all_support_runs(parents, idx_v, nv_j)
    spring_cross_lower_into(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A, ptr, runs, np.empty((cap, 6, nv)),
                            np.empty(spring_cross_iwork_size(nj, ja.shape[0], cap), np.int64), np.empty((6, nv)),
                            np.empty((6, 6)))


@njit
def spring_cross_lower_into(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A, ptr, runs, W, iwork, StT, Q):
    """A's lower triangle (diagonal included) -= that of N = sum_s J_a^T C J_b + J_b^T C^T J_a, over the
    springs between two different moving bodies (the off-diagonal body blocks of sum_s J_s^T C_s J_s; the
    diagonal ones are in the composite inertias).

    By composites, as the CRBA (Featherstone, Rigid Body Dynamics Algorithms, §6.2) treats the inertias: row r
    of joint j is N[r, :] = S_r^T Wbar_j, where Wbar_j (6 x nv) = sum over the spring ends on the bodies of j's
    subtree of X_e^T C' J_o, the world-origin wrench of the end's force per unit velocity of each DOF moving the
    spring's other end (J_o its point Jacobian, X_e^T f = (f, x_e x f), C' = C at end a and C^T at end b). The
    joints are visited leaves first (reverse depth-first order) with a stack of the finished subtrees'
    accumulators, a joint's Wbar accumulated in place of its first child's, each over the column range [lo, hi)
    its ends touched: each spring end adds O(d_o) (d_o DOFs support the other end), each row costs O(hi - lo),
    instead of O(d_a d_b) per spring pair by pair; every loop is a contiguous (vectorised) row.

    Nothing is allocated: ``ptr``, ``runs`` the tree's :func:`all_support_runs`; scratch ``W`` (cap, 6, nv) with cap
    = :func:`spring_cross_slots` (parents), ``iwork`` (:func:`spring_cross_iwork_size`,) int64, ``StT`` (6, nv), ``Q`` (6, 6)."""
    nv = St.shape[0]
    nj = parents.shape[0]
    P = ja.shape[0]
    cap = W.shape[0]
    head, nxt = iwork[:nj], iwork[nj:nj + 2 * P]
    off = nj + 2 * P
    lo, hi, free = iwork[off:off + cap], iwork[off + cap:off + 2 * cap], iwork[off + 2 * cap:off + 3 * cap]
    off += 3 * cap
    st_joint, st_slot = iwork[off:off + nj], iwork[off + nj:off + 2 * nj]
    for j in range(nj):
        head[j] = -1  # spring ends per joint (e = 2 s + end), linked through nxt
    nends = 0
    for s in range(P):
        i, k = ja[s], jb[s]
        if i == 0 or k == 0 or i == k:
            continue
        nxt[2 * s] = head[i]
        head[i] = 2 * s
        nxt[2 * s + 1] = head[k]
        head[k] = 2 * s + 1
        nends += 2
    if nends == 0:
        return
    W[:, :, :] = 0.0
    for c in range(cap):
        lo[c], hi[c], free[c] = nv, 0, c
    nfree = cap
    sp = 0
    for c in range(nv):
        for a in range(6):
            StT[a, c] = St[c, a]
    for j in range(nj - 1, 0, -1):
        w = -1
        while sp > 0 and parents[st_joint[sp - 1]] == j:  # j's children, finished just before it
            sp -= 1
            c = st_slot[sp]
            if w < 0:
                w = c
                continue
            if hi[c] > lo[c]:
                Wc, Ww = W[c], W[w]
                for a in range(6):
                    src, dst = Wc[a, lo[c]:hi[c]], Ww[a, lo[c]:hi[c]]
                    for t in range(src.shape[0]):
                        dst[t] += src[t]
                _clear_columns(Wc, lo[c], hi[c])
                lo[w] = min(lo[w], lo[c])
                hi[w] = max(hi[w], hi[c])
            lo[c], hi[c] = nv, 0
            free[nfree] = c
            nfree += 1
        if w < 0:
            nfree -= 1
            w = free[nfree]
        Ww = W[w]
        e = head[j]
        while e >= 0:
            s = e // 2
            o = jb[s] if e % 2 == 0 else ja[s]
            if e % 2 == 0:
                _add_end_wrenches(StT, pa[s], pb[s], C[s], False, runs, ptr[o], ptr[o + 1], Q, Ww)
            else:
                _add_end_wrenches(StT, pb[s], pa[s], C[s], True, runs, ptr[o], ptr[o + 1], Q, Ww)
            lo[w] = min(lo[w], runs[ptr[o + 1] - 1, 0])
            hi[w] = max(hi[w], runs[ptr[o], 1])
            e = nxt[e]
        if hi[w] > lo[w]:
            l0 = lo[w]
            for r in range(max(idx_v[j], l0), idx_v[j] + nv_j[j]):
                s0, s1, s2, s3, s4, s5 = St[r, 0], St[r, 1], St[r, 2], St[r, 3], St[r, 4], St[r, 5]
                m = min(r + 1, hi[w])
                Ar = A[r, l0:m]
                W0, W1, W2, W3, W4, W5 = Ww[0, l0:m], Ww[1, l0:m], Ww[2, l0:m], Ww[3, l0:m], Ww[4, l0:m], Ww[5, l0:m]
                for t in range(Ar.shape[0]):
                    Ar[t] -= ((s0 * W0[t] + s1 * W1[t]) + (s2 * W2[t] + s3 * W3[t])) + (s4 * W4[t] + s5 * W5[t])
        if parents[j] == 0:  # a subtree of the world: nothing to merge into
            if hi[w] > lo[w]:
                _clear_columns(Ww, lo[w], hi[w])
            lo[w], hi[w] = nv, 0
            free[nfree] = w
            nfree += 1
        else:
            st_joint[sp] = j
            st_slot[sp] = w
            sp += 1


@njit
def spring_cross_kernel(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A):
    """A -= J_a^T C J_b + J_b^T C^T J_a (both triangles) for springs between two different moving bodies:
    :func:`spring_cross_lower_kernel` into a scratch matrix, subtracted from A symmetrically."""
    M = np.zeros(A.shape)
    spring_cross_lower_kernel(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, M)
    add_lower_symmetric(M, A)


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


def maximal_blocks(ctx: Context, h: float, springs=None, ends: tuple | None = None) -> np.ndarray | None:
    """The maximal 6x6 blocks per joint (world twists) of the LHS: body damping h D_m
    (:func:`body_damping_blocks`) plus, with integrator.spring_stiffness: full, the springs' lever-arm
    stiffness h^2 B (springs.geometric_blocks_kernel, kept above minus half of each body's spatial inertia by
    springs.clamp_lever_blocks) from ``springs`` = (f_a (P,3), positions of mech.jac_sites); None when there is
    neither. The same terms as forces.assemble. ``ends``: the springs' end points (X[a], X[b]) (rows of
    springs.spring_arrays) when the caller has them."""
    D = body_damping_blocks(ctx, h)
    mech = ctx.mech
    if springs is None or not len(mech.spring_ab) or not mech.spring_geometric:
        return D
    fs, X = springs
    B = np.zeros((ctx.topo.njoints, 6, 6))
    sa = ctx.spring_arrays
    pa, pb = (X[sa.a], X[sa.b]) if ends is None else ends
    geometric_blocks_kernel(ctx.spring_ja, np.ascontiguousarray(pa), ctx.spring_jb, np.ascontiguousarray(pb),
                            np.ascontiguousarray(fs), sa.explicit, h * h, ctx.ws.I, B)
    clamp_lever_blocks(ctx.ws.I, B)
    return B if D is None else B + D


def rhs(ctx: Context, q, v_r, tau, h, site_forces=None, springs=None) -> np.ndarray:
    """RHS of Eq. (2) in reduced coordinates, O(n + m), for the (q, v_r) held in ctx.ws:
    b = M v_r + h (tau - nle - K_r (q - q_rest) + J_s^T f_springs + wrenches + J^T site forces).
    ``springs``: (f_a (P,3), positions of mech.jac_sites) from :func:`spring_terms`."""
    mech, topo, ws = ctx.mech, ctx.topo, ctx.ws
    if ws.v is None:
        raise ValueError("rhs needs a velocity: call update_kinematics(topo, ws, q, v)")
    ext = np.zeros((topo.njoints, 6))
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
    # joint springs: f_r = tau - K_r (q (-) q_rest), the difference (qa - qb) formed in rhs_kernel where it is q - q_rest
    if not mech.has_stiffness:
        k, qa, qb = _NO_STIFFNESS, _NO_STIFFNESS, _NO_STIFFNESS
    elif ctx.additive:
        k, qa, qb = mech.stiffness, q, mech.q_rest
    else:
        k, qa, qb = mech.stiffness, joint_displacement(mech, q), ctx.zero_v
    if springs is not None and len(mech.spring_ab):
        fs, X = springs
        sa = ctx.spring_arrays
        sja, a, sjb, sb = ctx.spring_ja, sa.a, ctx.spring_jb, sa.b
        X, fs = np.ascontiguousarray(X, dtype=float), np.ascontiguousarray(fs, dtype=float)
    else:
        sja = a = sjb = sb = _NO_INDICES
        X = fs = _NO_POINTS
    b = np.empty(topo.nv)
    rhs_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, ws.ov, ws.v, ws.R, ws.p, ws.c_local, ws.I, ctx.gravity, h,
               np.empty((topo.njoints, 6)), np.empty((topo.njoints, 6)), sja, a, sjb, sb, X, fs, ext, ctx.armature,
               np.ascontiguousarray(v_r, dtype=float), np.asarray(tau, dtype=float), k, qa, qb, ws.tmp6, b)
    return b


_NO_INDICES = np.zeros(0, dtype=np.int64)  # rhs_kernel's spring arrays without springs
_NO_POINTS = np.zeros((0, 3))
_NO_STIFFNESS = np.zeros(0)  # rhs_kernel's joint-spring arrays without joint springs


@njit
def rhs_kernel(parents, idx_v, nv_j, St, ov, v, R, p, c_local, I, g, h, acc, W, sja, sa, sjb, sb, X, fs, ext,
               armature, v_r, tau, k, qa, qb, F, b):
    """b of Eq. (2) in reduced coordinates (:func:`rhs`) in one call, for the kinematics (ov, v, R, p, c_local,
    I) of the workspace: W = -h W_nle (:func:`bias_wrench_kernel`), W += I ov (the momentum M v_r as a wrench),
    ext += the point springs' wrenches (f[s] on sites X[sa[s]] of bodies sja[s], -f[s] on X[sb[s]] of sjb[s];
    recursive.spring_wrench_kernel; empty arrays without springs) on top of the caller's external wrenches,
    then :func:`rhs_sum_kernel` (b = J^T (W + h ext) + armature v_r + h f_r) with the joint forces
    f_r = tau - k (qa - qb) (joint springs k [N m/rad, N/m] at the displacement qa - qb; k empty: f_r = tau).
    acc, W, F: scratch."""
    bias_wrench_kernel(parents, idx_v, nv_j, St, ov, v, R, p, c_local, I, g, h, acc, W)
    for j in range(W.shape[0]):
        for a in range(6):
            s = 0.0
            for c in range(6):
                s += I[j, a, c] * ov[j, c]
            W[j, a] += s
    rc.spring_wrench_kernel(sja, sa, sjb, sb, X, fs, ext)
    f_r = tau.copy()
    for i in range(k.shape[0]):
        f_r[i] -= k[i] * (qa[i] - qb[i])
    rhs_sum_kernel(parents, idx_v, nv_j, St, W, ext, h, armature, v_r, f_r, F, b)


@njit
def bias_wrench_kernel(parents, idx_v, nv_j, St, ov, v, R, p, c_local, I, g, h, acc, W):
    """W = -h W_nle: the Newton-Euler wrenches of :func:`nle_wrench_kernel` at the bias accelerations
    acc = Jdot qdot (recursive.bias_kernel, left in acc), scaled as in the RHS of Eq. (2) (:func:`rhs`)."""
    rc.bias_kernel(parents, idx_v, nv_j, St, ov, v, R, p, c_local, acc)
    nle_wrench_kernel(I, ov, acc, g, W)
    for j in range(W.shape[0]):
        for a in range(6):
            W[j, a] *= -h


@njit
def rhs_sum_kernel(parents, idx_v, nv_j, St, W, ext, h, armature, v_r, f_r, F, b):
    """The last sums of :func:`rhs` in its order: W += h ext (ext[0], the world's, cleared), b = J^T W (Alg. 6,
    F scratch), b += armature v_r, b += h f_r."""
    for a in range(6):
        ext[0, a] = 0.0
    for j in range(W.shape[0]):
        for a in range(6):
            W[j, a] += h * ext[j, a]
    rc.jtw_kernel(parents, idx_v, nv_j, St, W, F, b)
    for i in range(b.shape[0]):
        b[i] += armature[i] * v_r[i]
    for i in range(b.shape[0]):
        b[i] += h * f_r[i]


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
