"""Condensation of the bilateral rows for the staggered solve (staggered.py), compiled (numba).

The step's linear system A qdot = b (Eq. 2) with the bilateral rows G qdot = g (loop closures,
prescriptions; Eq. 5-7) is condensed once per step (the dual / Schur-complement form of the QPs of
Eq. 11-12 and 17c/18, whose equality rows are eliminated):
    Y = A^-1 G^T,  S = G Y,  P = A^-1 - Y S^-1 Y^T,  qdot_0 = P b + Y S^-1 g,
so that an impulse RX^T x of the staggered unknowns x = [alpha_U; beta] (RX = [U; -T]: ground normals
and limit rows U, friction rows T) moves the velocity by PX x, PX = P RX^T, and the contact and
friction QPs see the Delassus blocks of WX = RX P RX^T. The multipliers of the bilateral rows are
lambda = lambda_0 + LamX x (lambda_0 = S^-1 (Y^T b - g), LamX = S^-1 Y^T RX^T): the external constraint
forces of §5.3 that enter the BISP joint reactions.

Structure used: G and RX are sparse (a joint friction row r e_j has one or two nonzeros after the
coupling matrix, ground and loop rows only the DOFs of their supporting chains), so every product
with them runs over their nonzeros (O(nnz n) instead of O(rows n^2)); the dense work left is the
Cholesky inverse of A, S^-1 and P (n = DOFs, m = bilateral rows). The symmetric products S = G A^-1 G^T
and WX = RX P RX^T are formed in their lower triangles and mirrored (the walker's 47 x 47 WX: half the
multiply-adds; condense 28.3 -> 25.9 us standalone on its matrices).
"""
from __future__ import annotations


import numpy as np
from numba import njit

from redmax_ros.core.friction.arena import take, take1
from redmax_ros.core.linalg import cholesky


@njit(cache=True, nogil=True)
def ancestor_chains(A):
    """(lam, work): lam[k] the largest j < k with A[k, j] != 0 (-1: none), and about the multiply-adds of
    tree_inverse, or work = -1 when A has no branch-induced sparsity, i.e. when some nonzero A[k, j], j < k,
    is not on k's chain lam(k), lam(lam(k)), ... (Featherstone, Rigid Body Dynamics Algorithms §6.5: the
    reduced mass matrix of a tree in depth-first DOF order has it; eliminating the leaves first, A = L^T L,
    then makes no fill)."""
    lam = np.empty(A.shape[0], dtype=np.int64)
    return lam, ancestor_chains_into(A, lam)


@njit(cache=True, nogil=True)
def ancestor_chains_into(A, lam):
    """:func:`ancestor_chains` into lam (n,); returns work."""
    n = A.shape[0]
    lam[:] = -1
    work = 0
    for k in range(n):
        for j in range(k - 1, -1, -1):
            if A[k, j] != 0.0:
                lam[k] = j
                break
        c = lam[k]
        depth = 0
        for j in range(c, -1, -1):
            if A[k, j] != 0.0:
                while c > j:
                    c = lam[c]
                if c != j:
                    return -1
        while c >= 0:  # the rest of the chain
            c = lam[c]
        c = lam[k]
        while c >= 0:
            depth += 1
            c = lam[c]
        work += (depth + 1) * (depth + 1) + (depth + 1) * k
    return work


@njit(cache=True, nogil=True)
def tree_inverse(A, lam):
    """A^-1 of a symmetric positive definite A with branch-induced sparsity (ancestor_chains): the LTL
    factorisation A = L^T L (Featherstone, RBDA Table 6.3: the rows from the last up, each update along the
    ancestor chains only, no fill), L^-1 on the same pattern, A^-1 = L^-1 L^-T summed over the common
    ancestors; O(n d^2 + n^2 d) for chains of depth d instead of O(n^3). ok = False when A is not positive
    definite."""
    n = A.shape[0]
    Ainv = np.empty((n, n))
    return Ainv, tree_inverse_into(A, lam, np.empty((n, n)), np.empty((n, n)), Ainv)


@njit(cache=True, nogil=True)
def tree_inverse_into(A, lam, L, Li, Ainv):
    """:func:`tree_inverse` into Ainv, with L and Li (n, n) as scratch; returns ok."""
    n = A.shape[0]
    L[:, :] = 0.0
    for k in range(n):
        L[k, k] = A[k, k]
        c = lam[k]
        while c >= 0:
            L[k, c] = A[k, c]
            c = lam[c]
    for k in range(n - 1, -1, -1):
        if not L[k, k] > 0.0:
            return False
        d = np.sqrt(L[k, k])
        L[k, k] = d
        i = lam[k]
        while i >= 0:
            L[k, i] /= d
            i = lam[i]
        i = lam[k]
        while i >= 0:
            f = L[k, i]
            j = i
            while j >= 0:
                L[i, j] -= f * L[k, j]
                j = lam[j]
            i = lam[i]
    Li[:, :] = 0.0
    for i in range(n):
        Li[i, i] = 1.0 / L[i, i]
        k = lam[i]
        while k >= 0:  # (L^-1 L)_ik = 0: over the chain members m > k of row i
            s = 0.0
            m = i
            while m > k:
                s += Li[i, m] * L[m, k]
                m = lam[m]
            Li[i, k] = -s / L[k, k]
            k = lam[k]
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            k = j
            while k >= 0:  # common ancestors of i and j: j's chain (Li[i, k] is zero off i's chain)
                s += Li[i, k] * Li[j, k]
                k = lam[k]
            Ainv[i, j] = s
            Ainv[j, i] = s
    return True


@njit(cache=True, nogil=True)
def spd_inverse(A):
    """Inverse of a symmetric positive definite matrix; ok = False when A is not positive definite. With
    branch-induced sparsity cheap enough to use (a tree's mass matrix: ancestor_chains' work below n^3/6)
    through tree_inverse, else through the dense Cholesky factor (A = L L^T, A^-1 = L^-T L^-1; the
    factorisation is linalg.cholesky)."""
    n = A.shape[0]
    Ainv = np.empty((n, n))
    ok = spd_inverse_into(A, np.empty(n, dtype=np.int64), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), Ainv)
    return Ainv, ok


@njit(cache=True, nogil=True)
def spd_inverse_into(A, lam, L, Li, LiT, Ainv):
    """:func:`spd_inverse` into Ainv (n, n), with lam (n,) and L, Li, LiT (n, n) as scratch; returns ok."""
    n = A.shape[0]
    work = ancestor_chains_into(A, lam)
    if 0 <= work and 6 * work < n * n * n:
        return tree_inverse_into(A, lam, L, Li, Ainv)
    return dense_spd_inverse_into(A, L, Li, LiT, Ainv)


@njit(cache=True, nogil=True)
def dense_spd_inverse(A):
    """Inverse of a symmetric positive definite matrix through its Cholesky factor (A = L L^T,
    A^-1 = L^-T L^-1; the factorisation is linalg.cholesky); ok = False when A is not positive definite."""
    n = A.shape[0]
    Ainv = np.empty((n, n))
    ok = dense_spd_inverse_into(A, np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), Ainv)
    return Ainv, ok


@njit(cache=True, nogil=True)
def dense_spd_inverse_into(A, L, Li, LiT, Ainv):
    """:func:`dense_spd_inverse` into Ainv (n, n), with L, Li, LiT (n, n) as scratch; returns ok."""
    n = A.shape[0]
    L[:, :] = 0.0
    if not cholesky(A, L):
        return False
    Li[:, :] = 0.0  # L^-1 by rows: row i accumulates -L[i, k] row k for k < i (each entry's terms in
    for i in range(n):     # increasing k, as the column-by-column recurrence), contiguous rows: vectorised
        Li[i, i] = 1.0 / L[i, i]
        si = Li[i]
        for k in range(i):
            f = L[i, k]
            rk = Li[k, :k + 1]
            for j in range(rk.shape[0]):
                si[j] -= f * rk[j]
        d = L[i, i]
        for j in range(i):
            si[j] = si[j] / d
    _transpose_into(Li, LiT)
    np.dot(LiT, Li, Ainv)
    return True


FIXED_ROW = 1e-9  # W_kk <= FIXED_ROW * (T A^-1 T^T)_kk: the bilateral rows fix the row's slip


@njit(cache=True, nogil=True)
def fixed_row_weights(wT, T, Ainv, ptr, idx):
    """Convergence weights of friction rows whose slip the bilateral rows fix (in place).

    The staggered loop's convergence test (Alg. 2 line 12) weighs the change of a friction bound by the
    Delassus diagonal W_kk = (T P T^T)_kk, the velocity change a unit impulse makes. When prescriptions
    fix the slip of a row (a crank driven at a prescribed rate fixes every pin of a 1-DOF linkage),
    W_kk is zero up to round-off: the friction impulse no longer moves the velocity but still loads the
    drive (its required torque, Eq. 7), and a zero weight would declare the loop converged before the
    friction QP has run. Such rows (W_kk <= FIXED_ROW (T A^-1 T^T)_kk) are weighed by their
    unconstrained mobility (T A^-1 T^T)_kk instead; every other row keeps W_kk. The double sum runs over
    the row's nonzeros in increasing column order (the same terms in the same order as over all pairs),
    from T's row pattern ``ptr``, ``idx`` (pattern_of)."""
    for i in range(T.shape[0]):
        u = 0.0
        for p in range(ptr[i], ptr[i + 1]):
            a = idx[p]
            ta = T[i, a]
            Aa = Ainv[a]
            for q in range(ptr[i], ptr[i + 1]):
                c = idx[q]
                u += ta * Aa[c] * T[i, c]
        if wT[i] <= FIXED_ROW * u:
            wT[i] = u


@njit(cache=True, nogil=True)
def pattern_of(R):
    """Row-wise nonzero pattern of a dense matrix (CSR pointers and column indices, increasing columns)."""
    rows, cols = R.shape
    ptr = np.empty(rows + 1, dtype=np.int64)
    nnz = 0
    for i in range(rows):
        for c in range(cols):
            if R[i, c] != 0.0:
                nnz += 1
    idx = np.empty(nnz, dtype=np.int64)
    pattern_into(R, ptr, idx)
    return ptr, idx


@njit(cache=True, nogil=True)
def pattern_into(R, ptr, idx):
    """:func:`pattern_of` into ptr (rows + 1,) and idx (at least nnz(R),); returns nnz (the pattern is
    idx[:nnz])."""
    rows, cols = R.shape
    ptr[0] = 0
    k = 0
    for i in range(rows):
        for c in range(cols):
            if R[i, c] != 0.0:
                idx[k] = c
                k += 1
        ptr[i + 1] = k
    return k


@njit(cache=True, nogil=True)
def _sparse_left_into(R, ptr, idx, B, out):
    """out (r, k) = R @ B over the nonzeros of R (R (r,n) with pattern ptr/idx, B (n,k))."""
    out[:, :] = 0.0
    for i in range(R.shape[0]):
        for q in range(ptr[i], ptr[i + 1]):
            c = idx[q]
            rc = R[i, c]
            for j in range(B.shape[1]):
                out[i, j] += rc * B[c, j]


@njit(cache=True, nogil=True)
def _sparse_right_t_into(BT, R, ptr, idx, lower, outT):
    """outT (r, k) = (B @ R^T)^T over the nonzeros of R, given BT = B^T (n,k) contiguous, R (r,n) with pattern
    ptr/idx: row j accumulates R[j, c] times row c of B^T over the row's nonzeros (contiguous rows: vectorised),
    each entry summed in the order of R's pattern. ``lower`` (k = r, a symmetric product such as G A^-1 G^T or
    RX P RX^T): the entries i >= j only, mirrored into the upper triangle (outT is then the product itself)."""
    k = BT.shape[1]
    outT[:, :] = 0.0
    for j in range(R.shape[0]):
        i0 = j if lower else 0
        oj = outT[j, i0:]
        for q in range(ptr[j], ptr[j + 1]):
            c = idx[q]
            rc = R[j, c]
            bc = BT[c, i0:]
            for i in range(oj.shape[0]):
                oj[i] += bc[i] * rc
    if lower:
        for j in range(k):
            for i in range(j):
                outT[j, i] = outT[i, j]


@njit(cache=True, nogil=True)
def _transpose_into(src, dst):
    """dst (c, r) = src (r, c)^T."""
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            dst[i, j] = src[j, i]


@njit(cache=True, nogil=True)
def _symmetrize(P):
    """P := (P + P^T) / 2 in place (the diagonal is unchanged: (x + x) / 2 = x exactly)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s


@njit(cache=True, nogil=True)
def arena_size(n, m, nx):
    """(floats, ints) of the scratch :func:`condense_into` carves for n DOFs, m bilateral rows and nx staggered
    rows (an upper bound: every take of condense_into counted)."""
    floats = 6 * n * n + 5 * m * m + 4 * m * n + 2 * n * nx + 2 * nx * nx + 2 * m * nx + 3 * n + 3 * m + 3 * nx
    ints = n + m * n + nx * n + m + 2 * nx + 3
    return floats, ints


@njit(cache=True, nogil=True)
def condense(A, b, G, g, RX, nu):
    """:func:`condense_into` on an arena of its own (arena_size): the reference pipeline's call."""
    nf_, ni_ = arena_size(len(b), G.shape[0], RX.shape[0])
    return condense_into(A, b, G, g, RX, nu, np.empty(nf_), np.empty(ni_, dtype=np.int64), np.zeros(2, dtype=np.int64))


@njit(cache=True, nogil=True)
def condense_into(A, b, G, g, RX, nu, buf, ibuf, off):
    """Returns (status, qdot_0, PX, W_U, X_UT, X_TU, W_T, U qdot_0, T qdot_0, diag W_U, diag W_T,
    lambda_0, LamX) for RX = [U (nu rows); -T] (module docstring); X_UT = U P T^T.
    status: 0 ok, 1 A not positive definite, 2 G A^-1 G^T not positive definite (redundant rows).
    S = G A^-1 G^T is formed in its lower triangle (all the Cholesky factorisation reads) and inverted
    densely: it couples every pair of rows whose chains share a DOF, so it has no tree sparsity to use.
    WX is exactly symmetric (its lower triangle mirrored), so W_U, W_T are and X_TU = X_UT^T.
    Every array, the returned ones too, is a view of the arena (``buf`` floats, ``ibuf`` ints, their offsets
    ``off`` (2,), reset here; arena_size says how much it takes; a take past the end allocates instead): the
    compiled step hands it the same arena every step, so the condensation allocates nothing, and the results
    live until its next call."""
    n, m, nx = len(b), G.shape[0], RX.shape[0]
    nf = nx - nu
    off[0] = 0
    off[1] = 0
    Ainv = take(buf, off, n, n)
    ok = spd_inverse_into(A, take1(ibuf, off, 1, n), take(buf, off, n, n), take(buf, off, n, n),
                          take(buf, off, n, n), Ainv)
    status = 0 if ok else 1
    GA = take(buf, off, m, n)  # G A^-1 = Y^T
    SG = take(buf, off, m, n)
    P = take(buf, off, n, n)
    v0 = take1(buf, off, 0, n)
    lam0 = take1(buf, off, 0, m)
    GA[:, :] = 0.0
    SG[:, :] = 0.0
    v0[:] = 0.0
    lam0[:] = 0.0
    if ok and m:
        gptr = take1(ibuf, off, 1, m + 1)
        gidx = take1(ibuf, off, 1, m * n)
        pattern_into(G, gptr, gidx)
        _sparse_left_into(G, gptr, gidx, Ainv, GA)
        GAT = take(buf, off, n, m)
        _transpose_into(GA, GAT)
        S = take(buf, off, m, m)
        _sparse_right_t_into(GAT, G, gptr, gidx, True, S)
        Sinv = take(buf, off, m, m)
        ok = dense_spd_inverse_into(S, take(buf, off, m, m), take(buf, off, m, m), take(buf, off, m, m), Sinv)
        if ok:
            np.dot(Sinv, GA, SG)  # S^-1 Y^T
            np.dot(GAT, SG, P)
            for i in range(n):
                for j in range(n):
                    P[i, j] = Ainv[i, j] - P[i, j]
            t1, t2 = take1(buf, off, 0, n), take1(buf, off, 0, n)
            np.dot(P, b, t1)
            np.dot(g, SG, t2)
            for i in range(n):
                v0[i] = t1[i] + t2[i]
            t3 = take1(buf, off, 0, m)
            np.dot(GA, b, t3)
            for i in range(m):
                t3[i] = t3[i] - g[i]
            np.dot(Sinv, t3, lam0)
        else:
            status = 2
            P[:, :] = Ainv
    else:
        if ok:
            np.dot(Ainv, b, v0)
        P[:, :] = Ainv
    _symmetrize(P)
    PX = take(buf, off, n, nx)
    WX = take(buf, off, nx, nx)
    Xv0 = take1(buf, off, 0, nx)
    LamX = take(buf, off, m, nx)
    PX[:, :] = 0.0
    WX[:, :] = 0.0
    Xv0[:] = 0.0
    LamX[:, :] = 0.0
    rptr = take1(ibuf, off, 1, nx + 1)
    ridx = take1(ibuf, off, 1, nx * n)
    pattern_into(RX, rptr, ridx)
    if nx and status == 0:
        RXP = take(buf, off, nx, n)
        _sparse_left_into(RX, rptr, ridx, P, RXP)  # RX P = PX^T
        _transpose_into(RXP, PX)
        _sparse_right_t_into(PX, RX, rptr, ridx, True, WX)  # symmetric, as P
        np.dot(RX, v0, Xv0)
        if m:
            SGT = take(buf, off, n, m)
            _transpose_into(SG, SGT)
            LamXT = take(buf, off, nx, m)
            _sparse_right_t_into(SGT, RX, rptr, ridx, False, LamXT)  # S^-1 Y^T RX^T
            _transpose_into(LamXT, LamX)
    W_U = take(buf, off, nu, nu)
    X_UT = take(buf, off, nu, nf)
    X_TU = take(buf, off, nf, nu)
    W_T = take(buf, off, nf, nf)
    for i in range(nu):
        for j in range(nu):
            W_U[i, j] = WX[i, j]
        for j in range(nf):
            X_UT[i, j] = -WX[i, nu + j]
            X_TU[j, i] = X_UT[i, j]
    for i in range(nf):
        for j in range(nf):
            W_T[i, j] = WX[nu + i, nu + j]
    U_v0, T_v0 = take1(buf, off, 0, nu), take1(buf, off, 0, nf)
    wU, wT = take1(buf, off, 0, nu), take1(buf, off, 0, nf)
    for i in range(nu):
        U_v0[i] = Xv0[i]
        wU[i] = max(W_U[i, i], 0.0)
    for i in range(nf):
        T_v0[i] = -Xv0[nu + i]
        wT[i] = max(W_T[i, i], 0.0)
    if nf and status == 0:
        fptr = take1(ibuf, off, 1, nf + 1)
        for i in range(nf + 1):
            fptr[i] = rptr[nu + i] - rptr[nu]
        fixed_row_weights(wT, RX[nu:], Ainv, fptr, ridx[rptr[nu]:])
    return status, v0, PX, W_U, X_UT, X_TU, W_T, U_v0, T_v0, wU, wT, lam0, LamX
