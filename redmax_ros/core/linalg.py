"""Small dense linear algebra in compiled kernels (no allocation): Cholesky factor and solve, shared by
the KKT kernels (solvers/kkt.py), the condensation of the friction rows and the loop projection."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import njit


@njit
def cholesky(A, L):
    """L (n,n) lower-triangular with A = L L^T; returns False when a pivot is not positive."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@njit
def chol_solve(L, x):
    """x <- (L L^T)^-1 x in place."""
    n = L.shape[0]
    for i in range(n):
        s = x[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
