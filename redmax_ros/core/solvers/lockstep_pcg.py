"""PCG solves run in lockstep (paper §3, Eq. (4)) and the joint-limit active set on their dual system.

:func:`block_pcg` runs k independent preconditioned CG solves A x_c = b_c (the l + 1 solves
u = A^-1 b and Z = A^-1 H^T of Eq. (4)) together: all iterations of all right-hand sides in one compiled
call on preallocated arrays (solvers/lockstep_kernel.py; under a step budget in slices sized to the time
left), with the LHS products of :class:`~redmax_ros.core.solvers.pcg.MatrixFreeSystem` and the Projected
Block Jacobi Preconditioner of Alg. 1, :mod:`~redmax_ros.core.solvers.preconditioner`).
:func:`active_set` imposes the joint limits of Eq. (5) by a primal active set on the same dual system
(limit rows enter as equalities at their bound, multipliers checked for sign), with Z columns computed
only for the rows that become active. :class:`Fallback` tells the caller to redo the step with the
direct solver. Under a step budget both check the step's deadline (solvers/budget.py) between their
iterations and raise its StepError (no fallback) when the step's time is up.
"""
from __future__ import annotations

import time

import numpy as np

from redmax_ros.core.solvers.direct import check_rank
from redmax_ros.core.solvers.lockstep_kernel import (dual_solve_kernel, lockstep_iterate, lockstep_solve,
                                                     relative_residuals, spd_solve_kernel)
from redmax_ros.core.solvers.pcg import MatrixFreeSystem
from redmax_ros.core.solvers.preconditioner import ProjectedBlockJacobi

DEFAULT_RTOL = 1e-6
MAX_ITER_CAP = 1000  # per PCG solve, whatever n; then the step falls back to the direct solver


class Ops:
    """The arrays of a MatrixFreeSystem (A, Eq. 2) and its factored preconditioner (P^-1, Alg. 1) for the
    compiled lockstep solves (solvers/lockstep_kernel.py). ``scratch``: a dict kept across steps (e.g. in the
    step workspace's cache) holding the (k, n) work arrays per number of columns k, so a step allocates only
    its solutions."""

    def __init__(self, system: MatrixFreeSystem, P: ProjectedBlockJacobi, scratch: dict | None = None):
        self.s, self.P = system, P
        self.t = system.topo
        self.args = system.lhs_args() + P.apply_args() + system.lhs_scratch() + (P.beta, P.u, P.acc)
        self.scratch = {} if scratch is None else scratch

    def work(self, k: int, n: int) -> tuple:
        """(R, Zr, Pd, AP, bn, tol, rn, rz, active, conv, its) for k columns of length n."""
        w = self.scratch.get(k)
        if w is None or w[0].shape[1] != n:
            f = np.empty
            w = self.scratch[k] = (f((k, n)), f((k, n)), f((k, n)), f((k, n)), f(k), f(k), f(k), f(k),
                                   np.zeros(k, dtype=np.bool_), np.zeros(k, dtype=np.bool_), np.zeros(k, dtype=np.int64))
        return w


PCG_NAME = "lockstep PCG (Eq. 4)"


def block_pcg(ops: Ops, B: np.ndarray, X0: np.ndarray | None, rtol: float, max_iter: int, deadline=None):
    """Independent preconditioned CG solves A x_c = b_c for the rows b_c of B (k, n), run in lockstep by the
    compiled kernels of solvers/lockstep_kernel.py. Each column stops when ||r_c|| <= rtol ||b_c||. Returns
    (X, iterations (k,), converged (k,), relative residuals (k,)). ``X0``: the warm starts (k, n), a contiguous
    float array that becomes X (the solutions are written into it), or None (zero starts). ``deadline``: the
    step's budget.Deadline, checked between slices of the iterations that fit in the time left
    (Deadline.iterations_left; None: no budget, all iterations in one call): the first slice at the pace of the
    previous call on ``ops``'s scratch (wall time per column and iteration, start included, times k columns;
    one iteration when there is none), the later ones at the pace of this call so far. The slicing does not
    change the iterations: the result is bitwise that of one call."""
    if deadline is not None:
        deadline.begin()
    B = np.ascontiguousarray(B, dtype=float)
    k, n = B.shape
    X = np.zeros((k, n)) if X0 is None else X0
    R, Zr, Pd, AP, bn, tol, rn, rz, active, conv, its = ops.work(k, n)
    pace = ops.scratch.get(_PACE)
    if deadline is None:
        it = max_iter
    else:  # the iterations before the first check
        it = min(1, max_iter) if pace is None else deadline.iterations_left(pace * k, max_iter)
    t0 = time.perf_counter()
    left = lockstep_solve(*ops.args, B, X, X0 is not None, float(rtol), R, Zr, Pd, AP, bn, tol, rn, rz, active,
                          conv, its, it)
    while left and it < max_iter:
        deadline.check(PCG_NAME, it)
        to = it + deadline.iterations_left((time.perf_counter() - t0) / it, max_iter - it)
        left = lockstep_iterate(*ops.args, X, R, Zr, Pd, AP, tol, rn, rz, active, conv, its, it, to)
        it = to
    its = its.copy()
    if deadline is not None:
        ops.scratch[_PACE] = (time.perf_counter() - t0) / max(1, sum(its.tolist()))  # (a numpy sum: ~1 us more)
    return X, its, conv.copy(), relative_residuals(bn, rn)


_PACE = "pace"  # Ops.scratch: wall time [s] per column and iteration of the last budgeted block_pcg


def default_max_iter(nv: int) -> int:
    """PCG iteration cap per solve: 2 nv + 10 (exact arithmetic needs <= nv), at most MAX_ITER_CAP."""
    return int(min(2 * nv + 10, MAX_ITER_CAP))


class Fallback(Exception):
    """PCG (or the preconditioner, or the active set) failed: redo the step with the direct solver.
    args: (reason, PCG iterations spent)."""
    pass


def spd_solve(S, rhs, labels):
    """y = S^-1 rhs for the dual matrix S = H Z of Eq. (4) (symmetrised) by the compiled Cholesky
    (lockstep_kernel.spd_solve_kernel); a singular or nearly singular S has its redundant rows named
    (direct.check_rank raises StepError), else a non-positive-definite one is solved by least squares."""
    S = 0.5 * (S + S.T)
    n = S.shape[0]
    y = np.empty(n)
    status = spd_solve_kernel(S, np.ascontiguousarray(rhs, dtype=float), np.empty((n, n)), y)
    if status == 1:
        return y
    check_rank(S, labels)
    return y if status == 2 else np.linalg.lstsq(S, rhs, rcond=None)[0]


def dual_solve(H, X, g, labels):
    """(y, v) of Eq. (4) from the lockstep solutions X = [u; Z^T] (:func:`block_pcg` of [b; H]): y = (H Z)^-1
    (H u - g), v = u - Z y, in one compiled call (lockstep_kernel.dual_solve_kernel); a singular or nearly
    singular H Z is handled as in :func:`spd_solve` (redundant rows named, else least squares)."""
    l, n = H.shape
    S, rhs, y, v = np.empty((l, l)), np.empty(l), np.empty(l), np.empty(n)
    status = dual_solve_kernel(H, X, g, S, np.empty((l, l)), rhs, y, v)
    if status == 1:
        return y, v
    check_rank(S, labels)
    if status == 0:
        y = np.linalg.lstsq(S, rhs, rcond=None)[0]
        v = X[0] - X[1:].T @ y
    return y, v


def active_set(ops, rows, H, gH, Z, u, v, y, labels, rtol, max_iter, stats, deadline=None):
    """Primal active set for lo <= v[C_idx] <= hi on top of the equality solution (Eq. 5); the step's
    deadline (or None) is checked between its iterations and in its PCG solves."""
    if deadline is not None:
        deadline.begin()
    idx, lo, hi = rows.C_idx, rows.lo, rows.hi
    tol = 1e-12
    mu = np.zeros(len(idx))
    viol = (v[idx] < lo - tol) | (v[idx] > hi + tol)
    if not viol.any():
        return v, y, mu, 0
    nv = len(u)
    l = len(H)
    zlim = {}  # limit row -> A^-1 e_d
    extra = 0
    active = {}  # limit row -> 'lo' | 'hi'

    def ensure(rws):
        nonlocal extra
        need = [i for i in rws if i not in zlim]
        if need:
            E = np.zeros((len(need), nv))
            E[np.arange(len(need)), idx[need]] = 1.0
            Xc, its, conv, _ = block_pcg(ops, E, None, rtol, max_iter, deadline)
            extra += int(its.sum())
            if not conv.all():
                raise Fallback(f"PCG did not converge on a joint-limit row in {max_iter} iterations", extra)
            for i, x in zip(need, Xc):
                zlim[i] = x

    def worst_violation(v):
        c = v[idx]
        over = np.maximum(lo - c, c - hi)
        for i in active:
            over[i] = -np.inf
        i = int(np.argmax(over))
        return (i, "lo" if lo[i] - c[i] > c[i] - hi[i] else "hi") if over[i] > tol else (None, None)

    i, side = worst_violation(v)
    for k in range(3 * len(idx) + 10):
        if i is None:
            break
        if deadline is not None and k:
            deadline.check("joint-limit active set (PCG)", k)
        active[i] = side
        ensure([i])
        act = list(active)
        while True:
            Zw = np.column_stack([Z] + [zlim[a] for a in act]) if l else np.column_stack([zlim[a] for a in act])
            Cw = np.zeros((len(act), nv))
            Cw[np.arange(len(act)), idx[act]] = 1.0
            Hw = np.vstack([H, Cw]) if l else Cw
            bound = np.array([lo[a] if active[a] == "lo" else hi[a] for a in act])
            rhs = Hw @ u - np.concatenate([gH, bound])
            yy = spd_solve(Hw @ Zw, rhs, labels + [f"joint limit {a}" for a in act])
            mus = yy[l:]
            sgn = np.array([1.0 if active[a] == "hi" else -1.0 for a in act])
            wrong = sgn * mus < -1e-12 * max(1.0, float(np.abs(mus).max()))
            if wrong.any():  # a bound pulls instead of pushing: release the worst one
                k = int(np.argmin(sgn * mus))
                del active[act[k]]
                act = list(active)
                if not act:
                    yy = np.linalg.solve(H @ Z, H @ u - gH) if l else np.zeros(0)
                    mus = np.zeros(0)
                    Zw = Z
                    break
                continue
            break
        v = u - Zw @ yy if len(yy) else u.copy()
        y = yy[:l]
        mu = np.zeros(len(idx))
        mu[act] = mus
        i, side = worst_violation(v)
    else:
        raise Fallback("joint-limit active set did not settle", extra)
    if i is not None:
        raise Fallback("joint-limit active set did not settle", extra)
    stats["active_limits"] = len(active)
    return v, y, mu, extra
