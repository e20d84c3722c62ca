"""Small dense linear algebra in compiled kernels (no allocation): Cholesky factor and solve, shared by
the KKT kernels (solvers/kkt.py), the condensation of the friction rows and the loop projection.

Both are written so that LLVM vectorises their inner loops without fast-math: every hot loop is an axpy
over a contiguous row view indexed from 0 (numba's ``range(lo, n)`` loops with a variable start keep the
scalar wraparound check and are not vectorised; dot-product reductions are not vectorised without
reassociation, so the forward solve splits its sums into four independent ones).
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import njit, njit_inline

PANEL = 8  # rows of U = L^T factored together; the trailing rows get one rank-PANEL update per panel
_TILE = 16  # tile edge of the transposed copy of A's lower triangle


@njit
def cholesky(A, L):
    """L (n,n) lower-triangular with A = L L^T (A's lower triangle is read), zeros above the diagonal;
    returns False when a pivot is not positive (L is then incomplete).

    Right-looking blocked Cholesky (Golub and Van Loan, Matrix Computations, 4th ed., Alg. 4.2.2 with the
    outer-product updates blocked as in §4.2.9) on U = L^T, held row-major in the upper triangle of L so that
    every update is a contiguous row operation: A's lower triangle is copied transposed into L's upper one; per
    panel of PANEL rows, the panel is factored by rank-1 updates of its own rows, written to L's lower triangle
    (column k of L = row k of U) and applied to the trailing rows as one rank-PANEL update; the upper
    triangle is zeroed at the end. n^3/3 flops as the textbook algorithm; the summation order differs from
    it (and from LAPACK's), so the factor agrees to round-off. Up to PANEL rows (one panel, no trailing
    update): :func:`_cholesky_panel`, the same operations without the tiles and row views."""
    n = A.shape[0]
    if n <= PANEL:
        return _cholesky_panel(A, L)
    for i0 in range(0, n, _TILE):  # L[i, j] = A[j, i] for j >= i, by tiles (A's columns are strided)
        for j0 in range(i0, n, _TILE):
            for j in range(j0, min(j0 + _TILE, n)):
                for i in range(i0, min(i0 + _TILE, j + 1)):
                    L[i, j] = A[j, i]
    k0 = 0
    while k0 < n:
        e = min(k0 + PANEL, n)
        for k in range(k0, e):  # the panel: rows k0..e-1 of U, rank-1 updates among themselves
            s = L[k, k]
            if not s > 0.0:
                return False
            d = np.sqrt(s)
            L[k, k] = d
            Uk = L[k, k + 1:]
            for j in range(Uk.shape[0]):
                Uk[j] = Uk[j] / d
            for i in range(k + 1, e):
                f = L[k, i]
                Ui = L[i, i:]
                Rk = L[k, i:]
                for j in range(Ui.shape[0]):
                    Ui[j] -= f * Rk[j]
        for j in range(k0, n):  # column k of L = row k of U (L's lower triangle, below the panel's rows)
            for k in range(k0, min(e, j + 1)):
                L[j, k] = L[k, j]
        if e - k0 == PANEL:
            _rank8_update(L, k0, e)
        else:  # the last, short panel
            for k in range(k0, e):
                for i in range(e, n):
                    f = L[k, i]
                    Ui = L[i, i:]
                    Rk = L[k, i:]
                    for j in range(Ui.shape[0]):
                        Ui[j] -= f * Rk[j]
        k0 = e
    for i in range(n):
        Ui = L[i, i + 1:]
        for j in range(Ui.shape[0]):
            Ui[j] = 0.0
    return True


@njit
def _cholesky_panel(A, L):
    """:func:`cholesky` of a matrix of at most PANEL rows, its single panel: U = L^T by rank-1 updates of its
    rows (the same operations in the same order, so the same factor bit for bit), written on indices: for a few
    DOFs the tiled copies and the row views' vectorised loops cost more than the arithmetic (5 DOFs: 150 ns
    against 105 ns, measured)."""
    n = A.shape[0]
    for j in range(n):
        for i in range(j + 1):
            L[i, j] = A[j, i]
    for k in range(n):
        s = L[k, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[k, k] = d
        for j in range(k + 1, n):
            L[k, j] = L[k, j] / d
        for i in range(k + 1, n):
            f = L[k, i]
            for j in range(i, n):
                L[i, j] -= f * L[k, j]
    for j in range(n):  # L = U^T
        for k in range(j + 1):
            L[j, k] = L[k, j]
    for i in range(n):  # zeros above the diagonal
        for j in range(i + 1, n):
            L[i, j] = 0.0
    return True


@njit
def _rank8_update(L, k0, e):
    """U[i, i:] -= sum_p U[p, i] U[p, i:] over the panel rows p = k0..k0+7, for the trailing rows i >= e
    (U = L^T in L's upper triangle); one contiguous 8-term row update per row (two rows at a time, sharing
    the panel's loads, measured 8 % slower: 42.8 against 39.3 us for n = 100)."""
    n = L.shape[0]
    p0, p1, p2, p3, p4, p5, p6, p7 = k0, k0 + 1, k0 + 2, k0 + 3, k0 + 4, k0 + 5, k0 + 6, k0 + 7
    for i in range(e, n):
        f0, f1, f2, f3 = L[p0, i], L[p1, i], L[p2, i], L[p3, i]
        f4, f5, f6, f7 = L[p4, i], L[p5, i], L[p6, i], L[p7, i]
        R0, R1, R2, R3 = L[p0, i:], L[p1, i:], L[p2, i:], L[p3, i:]
        R4, R5, R6, R7 = L[p4, i:], L[p5, i:], L[p6, i:], L[p7, i:]
        Ui = L[i, i:]
        for j in range(Ui.shape[0]):
            Ui[j] -= ((f0 * R0[j] + f1 * R1[j]) + (f2 * R2[j] + f3 * R3[j])) + ((f4 * R4[j] + f5 * R5[j]) + (f6 * R6[j] + f7 * R7[j]))


@njit_inline
def dot(a, b):
    """sum_k a[k] b[k] over a's length (b at least as long), in four interleaved partial sums (independent
    dependency chains: about 3x the speed of one running sum for long vectors, no fast-math needed). Inlined
    into its callers: a call costs more than the sums of a short row (chol_solve of 5 DOFs: 95 ns against
    63 ns, measured)."""
    n = a.shape[0]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    k = 0
    while k + 4 <= n:
        s0 += a[k] * b[k]
        s1 += a[k + 1] * b[k + 1]
        s2 += a[k + 2] * b[k + 2]
        s3 += a[k + 3] * b[k + 3]
        k += 4
    while k < n:
        s0 += a[k] * b[k]
        k += 1
    return (s0 + s1) + (s2 + s3)


@njit
def chol_solve(L, x):
    """x <- (L L^T)^-1 x in place: forward substitution by rows of L (:func:`dot`), back substitution as
    axpys over the rows of L (columns of L^T)."""
    n = L.shape[0]
    for i in range(n):
        x[i] = (x[i] - dot(L[i, :i], x)) / L[i, i]
    for i in range(n - 1, -1, -1):
        xi = x[i] / L[i, i]
        x[i] = xi
        Li = L[i, :i]
        for k in range(Li.shape[0]):
            x[k] -= xi * Li[k]


@njit
def mirror_lower(A):
    """A[j, i] = A[i, j] for j < i: the upper triangle from the lower one (by tiles: A's columns are strided)."""
    n = A.shape[0]
    for i0 in range(0, n, _TILE):
        for j0 in range(0, i0 + 1, _TILE):
            for i in range(i0, min(i0 + _TILE, n)):
                for j in range(j0, min(j0 + _TILE, i)):
                    A[j, i] = A[i, j]


@njit
def add_lower_symmetric(M, A):
    """A += M + (M strictly below the diagonal)^T: the symmetric matrix whose lower triangle is M's."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            A[i, j] += M[i, j]
    for i0 in range(0, n, _TILE):
        for j0 in range(0, i0 + 1, _TILE):
            for i in range(i0, min(i0 + _TILE, n)):
                for j in range(j0, min(j0 + _TILE, i)):
                    A[j, i] += M[i, j]


@njit
def all_finite(x):
    """True when every entry of the vector x is finite (no NaN or infinity): one pass, no temporary."""
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return False
    return True
