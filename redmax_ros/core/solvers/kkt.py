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
TREE_SHARE = 0.25  # kkt_solve_tree_into: the tree factorisation when its flops are below this share of the dense


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
def _multipliers(S, LS, G, v, g, lam):
    """lam = S^-1 (G v - g) with v = A^-1 b, by S = L_S L_S^T into LS; returns the pivot ratio min/max diagonal
    of L_S, or -1 when S is not positive definite."""
    if not cholesky(S, LS):
        return -1.0
    dmin, dmax = LS[0, 0], LS[0, 0]
    for r in range(1, S.shape[0]):
        d = LS[r, r]
        dmin = min(dmin, d)
        dmax = max(dmax, d)
    _rows_minus(G, v, g, lam)
    chol_solve(LS, lam)
    return dmin / dmax


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
        ratio = _multipliers(S, LS, G, v, g, lam)
        if ratio < 0.0:
            return 2, 0.0, 0.0, False
        viol = _correct(G, g, L, Y, lam, y, v)
    return 0, ratio, viol, _limits_ok(C, v, lo, hi)


# ------------------------------------------------------------------------------------------------
# the same solve on A's branch-induced sparsity: Featherstone's L^T D L factorisation (RBDA section 6.5)


@njit
def tree_structure(A, par, allowed):
    """par[n] = 1 if the L^T D L path pays (flops sum_k depth_k^2 below TREE_SHARE of the dense n^3 / 3: its
    chain walks do not vectorise, so a chain or a spring-filled matrix stays with the dense Cholesky), else 0.
    The elimination tree of A's nonzero pattern for the L^T D L factorisation below (eliminating from the
    last DOF to the first): par[k] (-1 at a root) is the largest j < k joined to k once the DOFs after k are
    eliminated (their fill included), and allowed[k, j] = 1 for the j on k's chain par[k], par[par[k]], ...
    (and j = k): every nonzero of L (and of A) in row k is on that chain (RBDA section 6.5; for a kinematic
    tree ordered parents first this is the tree itself and nothing fills). O(n^3) at most; run when A's
    pattern leaves ``allowed`` (kkt_solve_tree_into)."""
    n = A.shape[0]
    F = np.zeros((n, n), dtype=np.bool_)
    for i in range(n):
        for j in range(i):
            if A[i, j] != 0.0 or A[j, i] != 0.0:
                F[i, j] = True
    for k in range(n - 1, -1, -1):
        p = -1
        for j in range(k - 1, -1, -1):
            if F[k, j]:
                p = j
                break
        par[k] = p
        for a in range(k):  # the lower neighbours of k become a clique (fill)
            if F[k, a]:
                for b in range(a):
                    if F[k, b]:
                        F[a, b] = True
    allowed[:, :] = 0
    work = 0
    for k in range(n):
        allowed[k, k] = 1
        depth = 1
        j = par[k]
        while j != -1:
            allowed[k, j] = 1
            depth += 1
            j = par[j]
        work += depth * depth
    par[n] = 1 if work < TREE_SHARE * n * n * n / 3.0 else 0


@njit
def _within(A, allowed):
    """Whether every nonzero below A's diagonal is in ``allowed`` (the chains of tree_structure)."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i):
            if A[i, j] != 0.0 and allowed[i, j] == 0:
                return False
    return True


@njit
def ltdl(A, par, H):
    """A = L^T D L on the chains ``par`` (RBDA Table 6.3): H gets L below the diagonal (unit diagonal
    implied) and D on it; entries off the chains are never read or written. False if a pivot is not
    positive (A not positive definite)."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            H[i, j] = A[i, j]
    for k in range(n - 1, -1, -1):
        d = H[k, k]
        if not d > 0.0:
            return False
        i = par[k]
        while i != -1:
            a = H[k, i] / d
            j = i
            while j != -1:
                H[i, j] -= a * H[k, j]
                j = par[j]
            H[k, i] = a
            i = par[i]
    return True


@njit
def _ltdl_solve(H, par, x):
    """x <- A^-1 x = L^-1 D^-1 L^-T x with H from ltdl (RBDA Table 6.4)."""
    n = H.shape[0]
    for i in range(n - 1, -1, -1):  # L^T y = x
        xi = x[i]
        j = par[i]
        while j != -1:
            x[j] -= H[i, j] * xi
            j = par[j]
    for i in range(n):
        x[i] /= H[i, i]
    for i in range(n):  # L x = y
        s = x[i]
        j = par[i]
        while j != -1:
            s -= H[i, j] * x[j]
            j = par[j]
        x[i] = s


@njit
def kkt_solve_tree_into(A, b, G, g, C, lo, hi, par, allowed, span, L, Y, S, LS, y, v, lam):
    """kkt_solve_into on A's tree sparsity: A = L^T D L (ltdl) instead of a dense Cholesky, Y = L^-T G^T (n, m)
    by one back substitution along the chains for all m rows, S = Y^T D^-1 Y (its lower triangle, all the
    Cholesky of S reads) over each row's nonzeros (a fingertip's rows are nonzero on its own chain only), and
    the correction v -= L^-1 D^-1 (Y lam). ``par``, ``allowed``: tree_structure of A, recomputed here when A has
    a nonzero off its chains (par[0] == -2: not yet made; par has n + 1 entries, the last one tree_structure's
    choice: 0 sends the solve to the dense kkt_solve_into). ``span`` (2, n) int scratch: the first and last row
    of G whose entry in Y[i] can be nonzero (G's own nonzeros in column i and those of the DOFs below i on the
    tree), so the back substitution and S touch only those (the same sums as over all m rows, minus exact zeros:
    the same numbers). Returns what kkt_solve_into returns, the pivot ratio from the Cholesky factor of S."""
    n, m = A.shape[0], G.shape[0]
    if par[0] == -2 or (par[n] == 1 and not _within(A, allowed)):
        tree_structure(A, par, allowed)
    if par[n] == 0:
        return kkt_solve_into(A, b, G, g, C, lo, hi, L, Y, S, LS, y, v, lam)
    v[:] = b
    lam[:] = 0.0
    if not ltdl(A, par, L):
        return 1, 0.0, 0.0, False
    _ltdl_solve(L, par, v)
    ratio, viol = 1.0, 0.0
    if m:
        for i in range(n):  # Y = G^T, and the span of G's nonzeros in each column
            Yi = Y[i]
            r0, r1 = m, -1
            for r in range(m):
                x = G[r, i]
                Yi[r] = x
                if x != 0.0:
                    r0 = min(r0, r)
                    r1 = r
            span[0, i] = r0
            span[1, i] = r1
        for i in range(n - 1, -1, -1):  # Y = L^-T G^T: row axpys up the chain, over Y[i]'s span (final: i's subtree is done)
            r0, r1 = span[0, i], span[1, i]
            if r1 < r0:
                continue
            Yi = Y[i, r0:r1 + 1]  # views indexed from 0: the axpys vectorise (linalg.py)
            j = par[i]
            while j != -1:
                lij = L[i, j]
                Yj = Y[j, r0:r1 + 1]
                for r in range(Yj.shape[0]):
                    Yj[r] -= lij * Yi[r]
                span[0, j] = min(span[0, j], r0)
                span[1, j] = max(span[1, j], r1)
                j = par[j]
        for r in range(m):
            Sr = S[r, :r + 1]
            for c in range(Sr.shape[0]):
                Sr[c] = 0.0
        for k in range(n):  # S = Y^T D^-1 Y (lower triangle), each row's span only
            r0 = span[0, k]
            dk = 1.0 / L[k, k]
            Yk = Y[k, r0:span[1, k] + 1]
            for r in range(Yk.shape[0]):
                w = Yk[r] * dk
                Sr = S[r0 + r, r0:r0 + r + 1]
                for c in range(Sr.shape[0]):
                    Sr[c] += w * Yk[c]
        ratio = _multipliers(S, LS, G, v, g, lam)
        if ratio < 0.0:
            return 2, 0.0, 0.0, False
        for k in range(n):  # v -= L^-1 D^-1 (Y lam)
            y[k] = dot(Y[k], lam) / L[k, k]
        for i in range(n):
            s = y[i]
            j = par[i]
            while j != -1:
                s -= L[i, j] * y[j]
                j = par[j]
            y[i] = s
        for k in range(n):
            v[k] -= y[k]
        viol = max_row_residual(G, v, g)
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
    return kkt_residual_into(A, b, v, G, lam, C, mu, np.empty(A.shape[0]))


@njit
def kkt_residual_into(A, b, v, G, lam, C, mu, r):
    """:func:`kkt_residual` with the residual vector into ``r`` (n,) scratch (no allocation)."""
    n = A.shape[0]
    for i in range(n):
        r[i] = -b[i]
    for i in range(n):
        r[i] += dot(A[i], v)
    for j in range(G.shape[0]):
        for i in range(n):
            r[i] += G[j, i] * lam[j]
    for j in range(C.shape[0]):
        if mu[j] != 0.0:  # an inactive limit row adds exact zeros
            for i in range(n):
                r[i] += C[j, i] * mu[j]
    return np.sqrt((r @ r) / max(b @ b, 1e-300))
