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

from redmax_ros.core.linalg import cholesky


@njit(cache=True, nogil=True)
def ancestor_chains(A):
    """(lam, work): lam[k] the largest j < k with A[k, j] != 0 (-1: none), and about the multiply-adds of
    tree_inverse, or work = -1 when A has no branch-induced sparsity, i.e. when some nonzero A[k, j], j < k,
    is not on k's chain lam(k), lam(lam(k)), ... (Featherstone, Rigid Body Dynamics Algorithms §6.5: the
    reduced mass matrix of a tree in depth-first DOF order has it; eliminating the leaves first, A = L^T L,
    then makes no fill)."""
    n = A.shape[0]
    lam = np.full(n, -1, dtype=np.int64)
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
                    return lam, -1
        while c >= 0:  # the rest of the chain
            c = lam[c]
        c = lam[k]
        while c >= 0:
            depth += 1
            c = lam[c]
        work += (depth + 1) * (depth + 1) + (depth + 1) * k
    return lam, work


@njit(cache=True, nogil=True)
def tree_inverse(A, lam):
    """A^-1 of a symmetric positive definite A with branch-induced sparsity (ancestor_chains): the LTL
    factorisation A = L^T L (Featherstone, RBDA Table 6.3: the rows from the last up, each update along the
    ancestor chains only, no fill), L^-1 on the same pattern, A^-1 = L^-1 L^-T summed over the common
    ancestors; O(n d^2 + n^2 d) for chains of depth d instead of O(n^3). ok = False when A is not positive
    definite."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for k in range(n):
        L[k, k] = A[k, k]
        c = lam[k]
        while c >= 0:
            L[k, c] = A[k, c]
            c = lam[c]
    for k in range(n - 1, -1, -1):
        if not L[k, k] > 0.0:
            return L, False
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
    Li = np.zeros((n, n))
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
    Ainv = np.empty((n, n))
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            k = j
            while k >= 0:  # common ancestors of i and j: j's chain (Li[i, k] is zero off i's chain)
                s += Li[i, k] * Li[j, k]
                k = lam[k]
            Ainv[i, j] = s
            Ainv[j, i] = s
    return Ainv, True


@njit(cache=True, nogil=True)
def spd_inverse(A):
    """Inverse of a symmetric positive definite matrix; ok = False when A is not positive definite. With
    branch-induced sparsity cheap enough to use (a tree's mass matrix: ancestor_chains' work below n^3/6)
    through tree_inverse, else through the dense Cholesky factor (A = L L^T, A^-1 = L^-T L^-1; the
    factorisation is linalg.cholesky)."""
    n = A.shape[0]
    lam, work = ancestor_chains(A)
    if 0 <= work and 6 * work < n * n * n:
        return tree_inverse(A, lam)
    return dense_spd_inverse(A)


@njit(cache=True, nogil=True)
def dense_spd_inverse(A):
    """Inverse of a symmetric positive definite matrix through its Cholesky factor (A = L L^T,
    A^-1 = L^-T L^-1; the factorisation is linalg.cholesky); ok = False when A is not positive definite."""
    n = A.shape[0]
    L = np.zeros((n, n))
    if not cholesky(A, L):
        return L, False
    Li = np.zeros((n, n))  # L^-1 by rows: row i accumulates -L[i, k] row k for k < i (each entry's terms in
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
    return np.ascontiguousarray(Li.T) @ Li, True


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
    ptr = np.zeros(rows + 1, dtype=np.int64)
    nnz = 0
    for i in range(rows):
        for c in range(cols):
            if R[i, c] != 0.0:
                nnz += 1
    idx = np.empty(nnz, dtype=np.int64)
    k = 0
    for i in range(rows):
        for c in range(cols):
            if R[i, c] != 0.0:
                idx[k] = c
                k += 1
        ptr[i + 1] = k
    return ptr, idx


@njit(cache=True, nogil=True)
def _sparse_left(R, ptr, idx, B):
    """R @ B over the nonzeros of R (R (r,n) with pattern ptr/idx, B (n,k))."""
    out = np.zeros((R.shape[0], B.shape[1]))
    for i in range(R.shape[0]):
        for q in range(ptr[i], ptr[i + 1]):
            c = idx[q]
            rc = R[i, c]
            for j in range(B.shape[1]):
                out[i, j] += rc * B[c, j]
    return out


@njit(cache=True, nogil=True)
def _sparse_right_t(BT, R, ptr, idx, lower=False):
    """B @ R^T over the nonzeros of R, given BT = B^T (n,k) contiguous, R (r,n) with pattern ptr/idx -> (k, r):
    row j of the transposed product accumulates R[j, c] times row c of B^T over the row's nonzeros (contiguous
    rows: vectorised), each entry summed in the order of R's pattern. ``lower`` (k = r, a symmetric product
    such as G A^-1 G^T or RX P RX^T): the entries i >= j only, mirrored into the upper triangle."""
    k = BT.shape[1]
    outT = np.zeros((R.shape[0], k))
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
        return outT
    return np.ascontiguousarray(outT.T)


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
def condense(A, b, G, g, RX, nu):
    """Returns (status, qdot_0, PX, W_U, X_UT, X_TU, W_T, U qdot_0, T qdot_0, diag W_U, diag W_T,
    lambda_0, LamX) for RX = [U (nu rows); -T] (module docstring); X_UT = U P T^T.
    status: 0 ok, 1 A not positive definite, 2 G A^-1 G^T not positive definite (redundant rows).
    S = G A^-1 G^T is formed in its lower triangle (all the Cholesky factorisation reads) and inverted
    densely: it couples every pair of rows whose chains share a DOF, so it has no tree sparsity to use.
    WX is exactly symmetric (its lower triangle mirrored), so W_U, W_T are and X_TU = X_UT^T."""
    n, m, nx = len(b), G.shape[0], RX.shape[0]
    nf = nx - nu
    Ainv, ok = spd_inverse(A)
    status = 0 if ok else 1
    GA = np.zeros((m, n))  # G A^-1 = Y^T
    SG = np.zeros((m, n))
    P = Ainv
    v0 = np.zeros(n)
    lam0 = np.zeros(m)
    LamX = np.zeros((m, nx))
    if ok and m:
        gptr, gidx = pattern_of(G)
        GA = _sparse_left(G, gptr, gidx, Ainv)
        GAT = np.ascontiguousarray(GA.T)
        Sinv, ok = dense_spd_inverse(_sparse_right_t(GAT, G, gptr, gidx, True))
        if ok:
            SG = Sinv @ GA  # S^-1 Y^T
            P = Ainv - GAT @ SG
            v0 = P @ b + (g @ SG)
            lam0 = Sinv @ (GA @ b - g)
        else:
            status = 2
    elif ok:
        v0 = Ainv @ b
        P = Ainv.copy()
    _symmetrize(P)
    PX = np.zeros((n, nx))
    WX = np.zeros((nx, nx))
    Xv0 = np.zeros(nx)
    rptr, ridx = pattern_of(RX)
    if nx and status == 0:
        RXP = _sparse_left(RX, rptr, ridx, P)  # RX P = PX^T
        PX = np.ascontiguousarray(RXP.T)
        WX = _sparse_right_t(PX, RX, rptr, ridx, True)  # symmetric, as P
        Xv0 = RX @ v0
        if m:
            LamX = _sparse_right_t(np.ascontiguousarray(SG.T), RX, rptr, ridx)  # S^-1 Y^T RX^T
    W_U = np.ascontiguousarray(WX[:nu, :nu])
    X_UT = np.ascontiguousarray(-WX[:nu, nu:])
    X_TU = np.ascontiguousarray(X_UT.T)
    W_T = np.ascontiguousarray(WX[nu:, nu:])
    wU, wT = np.zeros(nu), np.zeros(nf)
    for i in range(nu):
        wU[i] = max(W_U[i, i], 0.0)
    for i in range(nf):
        wT[i] = max(W_T[i, i], 0.0)
    if nf and status == 0:
        fixed_row_weights(wT, RX[nu:], Ainv, rptr[nu:] - rptr[nu], ridx[rptr[nu]:])
    return status, v0, PX, W_U, X_UT, X_TU, W_T, Xv0[:nu].copy(), -Xv0[nu:], wU, wT, lam0, LamX
