"""The lockstep PCG solves of Eq. (4) (Wang et al. 2019, §3) as compiled calls on preallocated arrays.

k independent preconditioned CG recurrences A x_c = b_c, c = 0..k-1 (u = A^-1 b and the columns of
Z = A^-1 H^T), advanced together: every iteration applies the LHS of Eq. (2) (pcg.lhs_kernel, one forward
and one backward pass plus O(m) spring work) and the Projected Block Jacobi Preconditioner (Alg. 1 lines
10-18, preconditioner.apply_kernel) to each active column, then the CG scalars and vector updates, all
inside one compiled call. A column stops when ||r_c|| <= rtol ||b_c|| or when p^T A p <= 0 (A not
positive definite on p). :func:`lockstep_start` computes the initial residuals, preconditioned residuals
and search directions; :func:`lockstep_iterate` runs iterations it_from .. it_to - 1 and can be resumed
(the step budget checks its deadline between calls, solvers/lockstep_pcg.block_pcg); :func:`lockstep_solve`
is the two in one call (the start and the iterations before the first check). Memory: O(k n). Dot
products are linalg.dot's four interleaved sums. :func:`spd_solve_kernel` is the small dense solve
(H Z) lambda = H u - g of Eq. (4).

The cached kernels here contain lhs_kernel and apply_kernel: this module is in step/compiled/cache.py's
SOURCES, so an edit of either drops its cache too (when the step package loads, as for pcg.py's own).

Arguments ``A`` and ``P`` below are the tuples of MatrixFreeSystem.lhs_args() and
ProjectedBlockJacobi.apply_args(), spelled out because numba takes arrays, not objects; ``Ys`` = (Y, W, F)
and ``Ps`` = (beta, u, acc) are their scratch arrays.
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import njit
from redmax_ros.core.linalg import cholesky, chol_solve, dot
from redmax_ros.core.solvers.pcg import lhs_kernel
from redmax_ros.core.solvers.preconditioner import apply_kernel


@njit
def lockstep_start(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag,
                   PSt, Ut, psi, psi_off, Y, W, F, beta, u, acc,
                   B, X, warm, rtol, R, Zr, Pd, AP, bn, tol, rn, rz, active, conv, its):
    """Initial state of the k solves (rows of B (k, n)): X the warm start (``warm`` False: X = 0),
    R = B - A X, Zr = P^-1 R, Pd = Zr, rz = r.z; bn, tol = rtol bn, rn = ||r|| per column; active/conv
    flags, its = 0. Returns the number of active columns."""
    k = B.shape[0]
    n_active = 0
    for c in range(k):
        its[c] = 0
        bn[c] = np.sqrt(dot(B[c], B[c]))
        tol[c] = rtol * bn[c]
        act = bn[c] > 0.0
        if not warm or not act:
            X[c, :] = 0.0
        if warm and act:
            lhs_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, X[c], Y, W, F,
                       AP[c])
            for i in range(B.shape[1]):
                R[c, i] = B[c, i] - AP[c, i]
        else:
            R[c, :] = B[c]
        rn[c] = np.sqrt(dot(R[c], R[c]))
        done = act and rn[c] <= tol[c]
        conv[c] = (not act) or done
        active[c] = act and not done
        if active[c]:
            n_active += 1
            apply_kernel(parents, idx_v, nv_j, PSt, Ut, psi, psi_off, R[c], Zr[c], beta, u, acc)
            Pd[c, :] = Zr[c]
            rz[c] = dot(R[c], Zr[c])
    return n_active


@njit
def lockstep_iterate(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag,
                     PSt, Ut, psi, psi_off, Y, W, F, beta, u, acc,
                     X, R, Zr, Pd, AP, tol, rn, rz, active, conv, its, it_from, it_to):
    """PCG iterations it_from .. it_to - 1 of every active column (the state of :func:`lockstep_start`,
    updated in place). Returns the number of columns still active (0: every column finished)."""
    k, n = X.shape
    n_active = 0
    for c in range(k):
        n_active += active[c]
    for it in range(it_from, it_to):
        n_active = 0
        for c in range(k):
            if not active[c]:
                continue
            pc, apc = Pd[c], AP[c]
            lhs_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, pc, Y, W, F, apc)
            pAp = dot(pc, apc)
            if not pAp > 0.0:  # A not positive definite on p: give up on that column
                active[c] = False
                continue
            alpha = rz[c] / pAp
            xc, rc = X[c], R[c]
            for i in range(n):
                xc[i] += alpha * pc[i]
                rc[i] -= alpha * apc[i]
            its[c] += 1
            rn[c] = np.sqrt(dot(rc, rc))
            if rn[c] <= tol[c]:
                conv[c] = True
                active[c] = False
                continue
            zc = Zr[c]
            apply_kernel(parents, idx_v, nv_j, PSt, Ut, psi, psi_off, rc, zc, beta, u, acc)
            rz_new = dot(rc, zc)
            bet = rz_new / rz[c]
            for i in range(n):
                pc[i] = zc[i] + bet * pc[i]
            rz[c] = rz_new
            n_active += 1
        if n_active == 0:
            break
    return n_active


@njit
def lockstep_solve(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag,
                   PSt, Ut, psi, psi_off, Y, W, F, beta, u, acc,
                   B, X, warm, rtol, R, Zr, Pd, AP, bn, tol, rn, rz, active, conv, its, it_to):
    """:func:`lockstep_start`, then iterations 0 .. it_to - 1 (:func:`lockstep_iterate`) in the same call.
    Returns the number of columns still active."""
    lockstep_start(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag,
                   PSt, Ut, psi, psi_off, Y, W, F, beta, u, acc,
                   B, X, warm, rtol, R, Zr, Pd, AP, bn, tol, rn, rz, active, conv, its)
    return lockstep_iterate(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag,
                            PSt, Ut, psi, psi_off, Y, W, F, beta, u, acc,
                            X, R, Zr, Pd, AP, tol, rn, rz, active, conv, its, 0, it_to)


@njit
def relative_residuals(bn, rn):
    """||r_c|| / ||b_c|| per column (0 where b_c = 0)."""
    out = np.empty(bn.shape[0])
    for c in range(bn.shape[0]):
        out[c] = rn[c] / bn[c] if bn[c] > 0 else 0.0
    return out


@njit
def spd_solve_kernel(S, rhs, L, y):
    """y = S^-1 rhs for the small dual matrix S = H Z of Eq. (4) (its lower triangle is read) by Cholesky
    (linalg.cholesky / chol_solve). Returns 0 when a pivot is not positive (y not set), 2 when the factor's
    diagonal spreads beyond 1e6 (nearly redundant rows: the caller checks the rank; y is set), else 1."""
    if not cholesky(S, L):
        return 0
    n = S.shape[0]
    dmin, dmax = np.inf, 0.0
    for i in range(n):
        d = abs(L[i, i])
        dmin = min(dmin, d)
        dmax = max(dmax, d)
    y[:] = rhs
    chol_solve(L, y)
    return 2 if n and dmin <= 1e-6 * dmax else 1


@njit
def dual_solve_kernel(H, X, g, S, L, rhs, y, v):
    """The small dense step of Eq. (4) after the lockstep solves, with u = X[0] and Z = X[1:]^T (the solutions
    of A u = b and A Z = H^T): S = H Z symmetrised, rhs = H u - g, y = S^-1 rhs (:func:`spd_solve_kernel`) and
    v = u - Z y. Returns spd_solve_kernel's status; v is set unless it is 0 (then y is not set either). Sums
    by linalg.dot, so the result agrees with numpy's products to round-off."""
    l, n = H.shape
    for i in range(l):
        for j in range(l):
            S[i, j] = dot(H[i], X[1 + j])
        rhs[i] = dot(H[i], X[0]) - g[i]
    for i in range(l):
        for j in range(i):
            s = 0.5 * (S[i, j] + S[j, i])
            S[i, j] = s
            S[j, i] = s
    status = spd_solve_kernel(S, rhs, L, y)
    if status != 0:
        for k in range(n):
            v[k] = X[0, k]
        for j in range(l):
            yj = y[j]
            Zj = X[1 + j]
            for k in range(n):
                v[k] -= yj * Zj[k]
    return status


@njit
def kkt_residual_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, Y, W, F,
                        v, b, H, y, limited, mu, m, g, r):
    """The true residual of the KKT stationarity equation of Eq. (4)-(5) in reduced coordinates,
    r = A v - b + H^T y (+ mu on the limited DOFs), by one :func:`lhs_kernel` product (``A``: the arrays of
    MatrixFreeSystem.lhs_args, Y, W, F its scratch). Returns (r.r, b.b, max_i<m |H_i v - g_i|): the squared
    norms of the relative residual and the velocity violation of the first m rows (the constraint rows, before
    the couplings')."""
    lhs_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, v, Y, W, F, r)
    n = v.shape[0]
    for k in range(n):
        r[k] -= b[k]
    for i in range(H.shape[0]):
        yi = y[i]
        Hi = H[i]
        for k in range(n):
            r[k] += yi * Hi[k]
    for i in range(limited.shape[0]):
        r[limited[i]] += mu[i]
    viol = 0.0
    for i in range(m):
        viol = max(viol, abs(dot(H[i], v) - g[i]))
    return dot(r, r), dot(b, b), viol
