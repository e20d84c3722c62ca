"""PCG solves run in lockstep (paper §3, Eq. (4)) and the joint-limit active set on their dual system.

:func:`block_pcg` runs k independent preconditioned CG solves A x_c = b_c (the l + 1 solves
u = A^-1 b and Z = A^-1 H^T of Eq. (4)) together: one compiled call per iteration for all right-hand
sides (the LHS products of :class:`~redmax_ros.core.solvers.pcg.MatrixFreeSystem` and the Projected
Block Jacobi Preconditioner of Alg. 1, :mod:`~redmax_ros.core.solvers.preconditioner`).
:func:`active_set` imposes the joint limits of Eq. (5) by a primal active set on the same dual system
(limit rows enter as equalities at their bound, multipliers checked for sign), with Z columns computed
only for the rows that become active. :class:`Fallback` tells the caller to redo the step with the
direct solver. Under a step budget both check the step's deadline (solvers/budget.py) between their
iterations and raise its StepError (no fallback) when the step's time is up.
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import njit
from redmax_ros.core.solvers.direct import check_rank
from redmax_ros.core.solvers.pcg import MatrixFreeSystem, lhs_kernel
from redmax_ros.core.solvers.preconditioner import ProjectedBlockJacobi, apply_kernel

DEFAULT_RTOL = 1e-6
MAX_ITER_CAP = 1000  # per PCG solve, whatever n; then the step falls back to the direct solver




@njit
def _lhs_multi(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, X, active, Y, W, F, OUT):
    for c in range(X.shape[0]):
        if active[c]:
            lhs_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, X[c], Y, W, F,
                        OUT[c])


@njit
def _pinv_multi(parents, idx_v, nv_j, St, Ut, Psi, X, active, beta, u, acc, OUT):
    for c in range(X.shape[0]):
        if active[c]:
            apply_kernel(parents, idx_v, nv_j, St, Ut, Psi, X[c], OUT[c], beta, u, acc)


class Ops:
    """Multi-column A and P^-1 products of a MatrixFreeSystem and its factored preconditioner."""

    def __init__(self, system: MatrixFreeSystem, P: ProjectedBlockJacobi):
        self.s, self.P = system, P
        self.t = system.topo

    def A(self, X, active):
        s, t = self.s, self.t
        OUT = np.zeros_like(X)
        blocks = s._noblocks if s.body_blocks is None else s.body_blocks
        sp = s.springs
        _lhs_multi(t.parents, t.idx_v, t.nv_j, s.ws.St, s.ws.I, blocks, s.body_blocks is not None, sp.joint_a,
                   s.pa, sp.joint_b, s.pb, s.C, s._diag, X, active, s._Y, s._W, s._F, OUT)
        return OUT

    def Pinv(self, X, active):
        P, t = self.P, self.t
        OUT = np.zeros_like(X)
        _pinv_multi(t.parents, t.idx_v, t.nv_j, P._St, P._Ut, P._Psi, X, active, P._beta, P._u, P._acc, OUT)
        return OUT


PCG_NAME = "lockstep PCG (Eq. 4)"


def block_pcg(ops: Ops, B: np.ndarray, X0: np.ndarray | None, rtol: float, max_iter: int, deadline=None):
    """Independent preconditioned CG solves A x_c = b_c for the rows b_c of B (k, n), run in lockstep.
    Each column stops when ||r_c|| <= rtol ||b_c||. Returns (X, iterations (k,), converged (k,),
    relative residuals (k,)). ``deadline``: the step's budget.Deadline, checked every iteration (None: no
    budget)."""
    if deadline is not None:
        deadline.begin()
    k, n = B.shape
    X = np.zeros((k, n)) if X0 is None else np.array(X0, dtype=float)
    bn = np.sqrt(np.einsum("ij,ij->i", B, B))
    tol = rtol * bn
    active = bn > 0.0
    X[~active] = 0.0
    R = B - ops.A(X, active) if X0 is not None else B.copy()
    rn = np.sqrt(np.einsum("ij,ij->i", R, R))
    its = np.zeros(k, dtype=int)
    conv = ~active
    done = active & (rn <= tol)
    conv = conv | done
    active = active & ~done
    if not active.any():
        return X, its, conv, np.where(bn > 0, rn / np.where(bn > 0, bn, 1.0), 0.0)
    Z = ops.Pinv(R, active)
    Pd = Z.copy()
    rz = np.einsum("ij,ij->i", R, Z)
    with np.errstate(divide="ignore", invalid="ignore"):
        for it in range(max_iter):
            if deadline is not None and it:
                deadline.check(PCG_NAME, it)
            AP = ops.A(Pd, active)
            pAp = np.einsum("ij,ij->i", Pd, AP)
            active = active & (pAp > 0.0)  # A not positive definite on p: give up on that column
            alpha = np.where(active, rz / pAp, 0.0)
            X += alpha[:, None] * Pd
            R -= alpha[:, None] * AP
            its += active
            rn = np.sqrt(np.einsum("ij,ij->i", R, R))
            done = active & (rn <= tol)
            conv = conv | done
            active = active & ~done
            if not active.any():
                break
            Z = ops.Pinv(R, active)
            rz_new = np.einsum("ij,ij->i", R, Z)
            beta = np.where(active, rz_new / rz, 0.0)
            Pd = Z + beta[:, None] * Pd
            rz = np.where(active, rz_new, rz)
    rel = np.where(bn > 0, rn / np.where(bn > 0, bn, 1.0), 0.0)
    return X, its, conv, rel


def default_max_iter(nv: int) -> int:
    """PCG iteration cap per solve: 2 nv + 10 (exact arithmetic needs <= nv), at most MAX_ITER_CAP."""
    return int(min(2 * nv + 10, MAX_ITER_CAP))


class Fallback(Exception):
    """PCG (or the preconditioner, or the active set) failed: redo the step with the direct solver.
    args: (reason, PCG iterations spent)."""
    pass


def spd_solve(S, rhs, labels):
    S = 0.5 * (S + S.T)
    try:
        L = np.linalg.cholesky(S)
        d = np.abs(np.diag(L))
        if d.min() <= 1e-6 * d.max():
            check_rank(S, labels)
        return np.linalg.solve(L.T, np.linalg.solve(L, rhs))
    except np.linalg.LinAlgError:
        check_rank(S, labels)
        return np.linalg.lstsq(S, rhs, rcond=None)[0]


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
