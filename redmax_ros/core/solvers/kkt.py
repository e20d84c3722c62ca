"""Small dense KKT solve of Eq. (6)/(7) in one compiled call (numba).

    [A  G^T] [qdot+]   [b]
    [G   0 ] [ lam ] = [g]        A symmetric positive definite (LHS of Eq. 2), G full row rank

by the Schur complement: A = L L^T, W = L^-1 G^T, S = G A^-1 G^T = W^T W = L_S L_S^T,
lam = S^-1 (G A^-1 b - g), qdot+ = A^-1 b - L^-T (W lam) (sign convention of solvers/direct.py:
A qdot = b - G^T lam). W is formed by one forward substitution for all m rows at once and S as a sum of
rank-one rows of W, both as axpys over contiguous rows (linalg.py's rule for loops LLVM vectorises); the
correction needs one back substitution, not m.

For the small systems of hands, legs and short chains (n <= SMALL_N) the NumPy/Eigen route costs
a dozen interpreter round trips of 1-5 us each while the arithmetic is a few thousand flops; this
kernel does the factorisations, the triangular solves, the joint-limit feasibility test of Eq. (5)
and the velocity-level residual max|G qdot+ - g| in one call. Larger systems keep Eigen's blocked
LLT (solvers/direct.py), which is faster from a few dozen DOFs on (measured in docs/architecture.md).
kkt_solve_lu is the same solve for a non-symmetric A (integrator.coriolis: implicit): LU with partial
pivoting for A and for the Schur complement S.
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import njit
from redmax_ros.core.linalg import chol_solve, cholesky, dot

SMALL_N = 64  # DOFs at or below which solve.solve_direct uses this kernel


@njit
def _rows_minus(G, v, g, out):
    """out = G v - g."""
    for r in range(G.shape[0]):
        s = -g[r]
        for k in range(G.shape[1]):
            s += G[r, k] * v[k]
        out[r] = s


@njit
def max_row_residual(G, v, g):
    """max|G v - g| (0 without rows) [m/s, rad/s]: the velocity-level violation of the bilateral rows."""
    viol = 0.0
    for r in range(G.shape[0]):
        s = -g[r]
        for k in range(G.shape[1]):
            s += G[r, k] * v[k]
        viol = max(viol, abs(s))
    return viol


@njit
def _correct(G, g, L, W, lam, z, v):
    """v <- v - L^-T (W lam) (qdot+ of the Schur complement, z scratch (n,)); returns max|G v - g| afterwards."""
    n = L.shape[0]
    for k in range(n):
        z[k] = dot(W[k], lam)
    for i in range(n - 1, -1, -1):  # L^T x = z, x into z: axpys over the rows of L
        xi = z[i] / L[i, i]
        z[i] = xi
        Li = L[i, :i]
        for k in range(Li.shape[0]):
            z[k] -= xi * Li[k]
    for k in range(n):
        v[k] -= z[k]
    return max_row_residual(G, v, g)


@njit
def _correct_by(G, g, Y, lam, v):
    """v <- v - Y lam with Y = A^-1 G^T (kkt_solve_lu); returns max|G v - g| afterwards."""
    n, m = Y.shape
    for k in range(n):
        s = 0.0
        for r in range(m):
            s += Y[k, r] * lam[r]
        v[k] -= s
    return max_row_residual(G, v, g)


@njit
def _forward_rows(L, G, W):
    """W = L^-1 G^T (n, m): forward substitution for the m columns at once, row i of W from the rows above it."""
    n, m = W.shape
    for i in range(n):
        Wi = W[i]
        for r in range(m):
            Wi[r] = G[r, i]
        for k in range(i):
            lik = L[i, k]
            Wk = W[k]
            for r in range(m):
                Wi[r] -= lik * Wk[r]
        d = L[i, i]
        for r in range(m):
            Wi[r] /= d


@njit
def _gram(W, S):
    """S = W^T W (m, m), a sum over the rows of W of their outer products."""
    n, m = W.shape
    S[:, :] = 0.0
    for k in range(n):
        Wk = W[k]
        for r in range(m):
            wr = Wk[r]
            Sr = S[r]
            for c in range(m):
                Sr[c] += wr * Wk[c]


@njit
def _limits_ok(C, v, lo, hi):
    """lo - 1e-12 <= C v <= hi + 1e-12 (no QP needed for the unilateral rows of Eq. 5)."""
    for r in range(C.shape[0]):
        s = 0.0
        for k in range(C.shape[1]):
            s += C[r, k] * v[k]
        if s < lo[r] - 1e-12 or s > hi[r] + 1e-12:
            return False
    return True


@njit
def kkt_solve(A, b, G, g, C, lo, hi):
    """Returns (status, qdot+ (n,), lam (m,), S (m,m), pivot ratio, max|G qdot+ - g|, limits_ok).

    status: 0 solved, 1 A not positive definite, 2 Schur complement S not positive definite.
    pivot ratio = min/max diagonal of L_S (small: redundant or conflicting rows, see solve._check_rank).
    limits_ok: lo - 1e-12 <= C qdot+ <= hi + 1e-12 (no QP needed for the unilateral rows of Eq. 5).
    """
    n, m = A.shape[0], G.shape[0]
    v = np.empty(n)
    lam = np.zeros(m)
    S = np.zeros((m, m))
    status, ratio, viol, ok = kkt_solve_into(A, b, G, g, C, lo, hi, np.empty((n, n)), np.empty((n, m)), S,
                                             np.empty((m, m)), np.empty(n), v, lam)
    return status, v, lam, S, ratio, viol, ok


@njit
def kkt_solve_into(A, b, G, g, C, lo, hi, L, Y, S, LS, y, v, lam):
    """kkt_solve without allocation: the factors and scratch in L (n,n), Y (n,m: W = L^-1 G^T), S (m,m),
    LS (m,m), y (n,); qdot+ into v (n,), the multipliers into lam (m,). Returns (status, pivot ratio,
    max|G qdot+ - g|, limits_ok)."""
    n, m = A.shape[0], G.shape[0]
    v[:] = b
    lam[:] = 0.0
    if not cholesky(A, L):
        return 1, 0.0, 0.0, False
    chol_solve(L, v)
    ratio, viol = 1.0, 0.0
    if m:
        _forward_rows(L, G, Y)  # W
        _gram(Y, S)  # S = W^T W = G A^-1 G^T
        if not cholesky(S, LS):
            return 2, 0.0, 0.0, False
        dmin, dmax = LS[0, 0], LS[0, 0]
        for r in range(1, m):
            d = LS[r, r]
            dmin = min(dmin, d)
            dmax = max(dmax, d)
        ratio = dmin / dmax
        _rows_minus(G, v, g, lam)
        chol_solve(LS, lam)
        viol = _correct(G, g, L, Y, lam, y, v)
    return 0, ratio, viol, _limits_ok(C, v, lo, hi)


# ------------------------------------------------------------------------------------------------
# non-symmetric A (integrator.coriolis: implicit, forces.coriolis_jacobian): LU with partial pivoting


@njit
def _lu(A, LU, piv):
    """LU (n,n) packed (unit lower L below the diagonal, U on and above it) with row pivots piv:
    P A = L U. Returns (ok, min |U_ii|, max |U_ii|); ok is False for an exactly zero pivot."""
    n = A.shape[0]
    LU[:, :] = A
    umin, umax = np.inf, 0.0
    for j in range(n):
        p, best = j, abs(LU[j, j])
        for i in range(j + 1, n):
            if abs(LU[i, j]) > best:
                p, best = i, abs(LU[i, j])
        piv[j] = p
        if p != j:
            for k in range(n):
                t = LU[j, k]
                LU[j, k] = LU[p, k]
                LU[p, k] = t
        d = LU[j, j]
        umin = min(umin, abs(d))
        umax = max(umax, abs(d))
        if d == 0.0 or not np.isfinite(d):
            return False, umin, umax
        for i in range(j + 1, n):
            LU[i, j] /= d
            l = LU[i, j]
            if l != 0.0:
                for k in range(j + 1, n):
                    LU[i, k] -= l * LU[j, k]
    return True, umin, umax


@njit
def _lu_solve(LU, piv, x):
    """x <- A^-1 x in place (P A = L U from _lu)."""
    n = LU.shape[0]
    for j in range(n):
        p = piv[j]
        if p != j:
            t = x[j]
            x[j] = x[p]
            x[p] = t
    for i in range(n):
        s = x[i]
        for k in range(i):
            s -= LU[i, k] * x[k]
        x[i] = s
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= LU[i, k] * x[k]
        x[i] = s / LU[i, i]


@njit
def kkt_solve_lu(A, b, G, g, C, lo, hi):
    """kkt_solve for a non-symmetric A (LHS of Eq. 2 with the implicit Coriolis term): the same Schur
    complement with LU factorisations, Y = A^-1 G^T, S = G Y (not symmetric either), lam = S^-1 (G A^-1 b - g).
    Same outputs; status 1: A singular, 2: S singular. pivot ratio = sqrt(min/max |U_S ii|), comparable
    with the Cholesky ratio of kkt_solve (whose L_S diagonal is the square root of the pivots)."""
    n, m = A.shape[0], G.shape[0]
    LU = np.empty((n, n))
    piv = np.empty(n, np.int64)
    v = b.copy()
    lam = np.zeros(m)
    S = np.zeros((m, m))
    ok, _, _ = _lu(A, LU, piv)
    if not ok:
        return 1, v, lam, S, 0.0, 0.0, False
    _lu_solve(LU, piv, v)
    ratio, viol = 1.0, 0.0
    if m:
        Y = np.empty((n, m))
        for r in range(m):
            y = G[r].copy()
            _lu_solve(LU, piv, y)
            Y[:, r] = y
        for r in range(m):
            for c in range(m):
                s = 0.0
                for k in range(n):
                    s += G[r, k] * Y[k, c]
                S[r, c] = s
        LUS = np.empty((m, m))
        pivS = np.empty(m, np.int64)
        ok, umin, umax = _lu(S, LUS, pivS)
        if not ok:
            return 2, v, lam, S, 0.0, 0.0, False
        ratio = np.sqrt(umin / umax)
        _rows_minus(G, v, g, lam)
        _lu_solve(LUS, pivS, lam)
        viol = _correct_by(G, g, Y, lam, v)
    return 0, v, lam, S, ratio, viol, _limits_ok(C, v, lo, hi)


@njit
def kkt_residual(A, b, v, G, lam, C, mu):
    """Relative residual |A v - b + G^T lam + C^T mu| / |b| of the KKT stationarity equation (one
    compiled call; C may have zero rows)."""
    n = A.shape[0]
    r = -b.copy()
    for i in range(n):
        r[i] += dot(A[i], v)
    for j in range(G.shape[0]):
        for i in range(n):
            r[i] += G[j, i] * lam[j]
    for j in range(C.shape[0]):
        for i in range(n):
            r[i] += C[j, i] * mu[j]
    return np.sqrt((r @ r) / max(b @ b, 1e-300))
