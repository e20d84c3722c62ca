"""Matrix-free solve of the LHS of Eq. (2) (Wang et al. 2019, §3): preconditioned conjugate
gradients with the Projected Block Jacobi Preconditioner (Eq. (3), Alg. 1), the O(n + m) LHS
product, and the loop-closure path of §3.1 Eq. (4).

LHS convention (positive stiffness, K = -df/dx, so every term is symmetric positive semi-definite):

    A = M_r (incl. armature) + J^T B_m J + diag(h D_r + h^2 K_r) + sum_s J_s^T (h D_s + h^2 K_s) J_s

which is the LHS of Eq. (2), J^T (M_m + h D_m - h^2 K_m) J + h D_r - h^2 K_r, written with the
paper's stiffness sign flipped. B_m are optional per-body maximal 6x6 blocks (e.g. body damping
h D_m), J_s = J_site_a - J_site_b is the 3 x nv world-frame Jacobian of the difference of the two
points of spring s, and D_s, K_s are its 3x3 damping and stiffness matrices. Frames as in
:mod:`redmax_ros.core.recursive` (world frame at the world origin, linear first).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from redmax_ros.core.solvers.preconditioner import ProjectedBlockJacobi
from redmax_ros.core.solvers.recursive import Topology, Workspace, jtw_kernel, jv_kernel, njit, site_positions

Operator = Callable[[np.ndarray], np.ndarray]


# --------------------------------------------------------------------------------------------
# PCG
# --------------------------------------------------------------------------------------------
@dataclass
class PCGResult:
    x: np.ndarray  # solution estimate
    iterations: int  # number of A products after the initial residual (0 if x0 already solves)
    residual: float  # ||b - A x|| / ||b|| (recursively updated residual)
    converged: bool


def pcg(apply_A: Operator, apply_Pinv: Operator, b: np.ndarray, x0: np.ndarray | None = None,
        rtol: float = 1e-6, max_iter: int | None = None) -> PCGResult:
    """Preconditioned conjugate gradients for A x = b, A and P symmetric positive definite, given
    only the products ``apply_A(x) = A x`` and ``apply_Pinv(r) = P^{-1} r``.

    Stops when ||r||_2 <= rtol ||b||_2 (or after ``max_iter`` iterations, default 2 nv + 10).
    ``x0`` warm-starts (e.g. with the previous step's velocity). Stops unconverged if p^T A p <= 0
    (A not positive definite)."""
    b = np.asarray(b, dtype=float).reshape(-1)
    n = b.shape[0]
    max_iter = 2 * n + 10 if max_iter is None else max_iter
    bnorm = float(np.linalg.norm(b))
    if bnorm == 0.0:
        return PCGResult(np.zeros(n), 0, 0.0, True)
    tol = rtol * bnorm
    if x0 is None:
        x = np.zeros(n)
        r = b.copy()
    else:
        x = np.array(x0, dtype=float).reshape(n)
        r = b - apply_A(x)
    rnorm = float(np.linalg.norm(r))
    if rnorm <= tol:
        return PCGResult(x, 0, rnorm / bnorm, True)
    z = apply_Pinv(r)
    p = z.copy()
    rz = float(r @ z)
    for k in range(1, max_iter + 1):
        Ap = apply_A(p)
        pAp = float(p @ Ap)
        if not pAp > 0.0:
            return PCGResult(x, k, rnorm / bnorm, False)
        alpha = rz / pAp
        x += alpha * p
        r -= alpha * Ap
        rnorm = float(np.linalg.norm(r))
        if rnorm <= tol:
            return PCGResult(x, k, rnorm / bnorm, True)
        z = apply_Pinv(r)
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return PCGResult(x, max_iter, rnorm / bnorm, False)


# --------------------------------------------------------------------------------------------
# LHS of Eq. (2), matrix-free
# --------------------------------------------------------------------------------------------
@dataclass
class PointSprings:
    """Maximal point-to-point springs between site a (on body ``joint_a``, ``offset_a`` in that
    joint's frame) and site b. Joint 0 means the world (offset = world point).
    ``stiffness`` K_s = -d f_a / d x_a and ``damping`` D_s = -d f_a / d xdot_a (m, 3, 3), symmetric
    positive semi-definite, world frame [N/m], [N s/m]."""

    joint_a: np.ndarray
    offset_a: np.ndarray
    joint_b: np.ndarray
    offset_b: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray | None = None

    def __post_init__(self):
        self.joint_a = np.ascontiguousarray(self.joint_a, dtype=np.int64).reshape(-1)
        m = len(self.joint_a)
        self.joint_b = np.ascontiguousarray(self.joint_b, dtype=np.int64).reshape(m)
        self.offset_a = np.ascontiguousarray(self.offset_a, dtype=float).reshape(m, 3)
        self.offset_b = np.ascontiguousarray(self.offset_b, dtype=float).reshape(m, 3)
        self.stiffness = np.ascontiguousarray(self.stiffness, dtype=float).reshape(m, 3, 3)
        self.damping = (np.zeros((m, 3, 3)) if self.damping is None
                        else np.ascontiguousarray(self.damping, dtype=float).reshape(m, 3, 3))

    @property
    def m(self) -> int:
        return len(self.joint_a)


@njit
def lhs_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, x,
                Y, W, F, out):
    """out = J^T ((I + B) J x + sum_s X_s^T C_s X_s J x) + diag * x in one forward and one backward
    pass (Alg. 5 and Alg. 6 of Sueda's notes, world frame) plus O(m) spring work."""
    jv_kernel(parents, idx_v, nv_j, St, x, Y)
    nj = parents.shape[0]
    for a in range(6):
        W[0, a] = 0.0
    for j in range(1, nj):
        for a in range(6):
            s = 0.0
            for b in range(6):
                s += I[j, a, b] * Y[j, b]
            if use_blocks:
                for b in range(6):
                    s += blocks[j, a, b] * Y[j, b]
            W[j, a] = s
    for s in range(ja.shape[0]):  # scalars, no array views (10-20 % faster on 2e4 springs, measured)
        i, k = ja[s], jb[s]
        xa0, xa1, xa2 = pa[s, 0], pa[s, 1], pa[s, 2]
        xb0, xb1, xb2 = pb[s, 0], pb[s, 1], pb[s, 2]
        # point velocity difference u_a - u_b, u = v_o + w x x
        d0 = (Y[i, 0] + Y[i, 4] * xa2 - Y[i, 5] * xa1) - (Y[k, 0] + Y[k, 4] * xb2 - Y[k, 5] * xb1)
        d1 = (Y[i, 1] + Y[i, 5] * xa0 - Y[i, 3] * xa2) - (Y[k, 1] + Y[k, 5] * xb0 - Y[k, 3] * xb2)
        d2 = (Y[i, 2] + Y[i, 3] * xa1 - Y[i, 4] * xa0) - (Y[k, 2] + Y[k, 3] * xb1 - Y[k, 4] * xb0)
        f0 = C[s, 0, 0] * d0 + C[s, 0, 1] * d1 + C[s, 0, 2] * d2
        f1 = C[s, 1, 0] * d0 + C[s, 1, 1] * d1 + C[s, 1, 2] * d2
        f2 = C[s, 2, 0] * d0 + C[s, 2, 1] * d1 + C[s, 2, 2] * d2
        # J_a^T f - J_b^T f as wrenches (f, x x f) at the world origin
        W[i, 0] += f0
        W[i, 1] += f1
        W[i, 2] += f2
        W[i, 3] += xa1 * f2 - xa2 * f1
        W[i, 4] += xa2 * f0 - xa0 * f2
        W[i, 5] += xa0 * f1 - xa1 * f0
        W[k, 0] -= f0
        W[k, 1] -= f1
        W[k, 2] -= f2
        W[k, 3] -= xb1 * f2 - xb2 * f1
        W[k, 4] -= xb2 * f0 - xb0 * f2
        W[k, 5] -= xb0 * f1 - xb1 * f0
    jtw_kernel(parents, idx_v, nv_j, St, W, F, out)
    for c in range(x.shape[0]):
        out[c] += diag[c] * x[c]


@njit
def add_spring_end(B, j, alpha, x0, x1, x2, C, CX):
    """B[j] += X^T C X with X = [alpha 1, -[x]], x = (x0, x1, x2), the zero entries of X left out, for one end
    of a spring (alpha = 1), a spring with both ends on one body (alpha = 0, x = x_a - x_b) or a point damper
    (the compiled step's body damping). CX: 3x6 scratch."""
    for a in range(3):
        c0, c1, c2 = C[a, 0], C[a, 1], C[a, 2]
        CX[a, 0] = alpha * c0
        CX[a, 1] = alpha * c1
        CX[a, 2] = alpha * c2
        CX[a, 3] = c1 * (-x2) + c2 * x1
        CX[a, 4] = c0 * x2 + c2 * (-x0)
        CX[a, 5] = c0 * (-x1) + c1 * x0
    for b in range(6):
        B[j, 0, b] += alpha * CX[0, b]
        B[j, 1, b] += alpha * CX[1, b]
        B[j, 2, b] += alpha * CX[2, b]
        B[j, 3, b] += (-x2) * CX[1, b] + x1 * CX[2, b]
        B[j, 4, b] += x2 * CX[0, b] + (-x0) * CX[2, b]
        B[j, 5, b] += (-x1) * CX[0, b] + x0 * CX[1, b]


@njit
def spring_blocks_kernel(ja, pa, jb, pb, C, blocks):
    """:func:`spring_blocks_into` with a scratch of its own."""
    spring_blocks_into(ja, pa, jb, pb, C, blocks, np.empty((3, 6)))


@njit
def spring_blocks_into(ja, pa, jb, pb, C, blocks, CX):
    """blkdiag over bodies of sum_s J_s^T C_s J_s in maximal (body-twist) coordinates: each end gets
    X^T C X; a spring with both ends on the same body gives its exact own block. CX: (3, 6) scratch."""
    for s in range(ja.shape[0]):
        i, k = ja[s], jb[s]
        if i == k:
            add_spring_end(blocks, i, 0.0, pa[s, 0] - pb[s, 0], pa[s, 1] - pb[s, 1], pa[s, 2] - pb[s, 2], C[s], CX)
        else:
            add_spring_end(blocks, i, 1.0, pa[s, 0], pa[s, 1], pa[s, 2], C[s], CX)
            add_spring_end(blocks, k, 1.0, pb[s, 0], pb[s, 1], pb[s, 2], C[s], CX)
    for a in range(6):
        for b in range(6):
            blocks[0, a, b] = 0.0


_NO_POINTS = np.zeros((0, 3))  # pa, pb and C of a system without springs
_NO_MATRICES = np.zeros((0, 3, 3))


class MatrixFreeSystem:
    """The LHS matrix A of Eq. (2) (module docstring) as an O(n + m) operator, for the
    configuration held in ``ws`` (call :meth:`refresh` after each ``update_kinematics``).

    ``reduced_diag`` (nv,) is h D_r + h^2 K_r; ``body_blocks`` (njoints, 6, 6) optional maximal
    blocks B_m (world frame, e.g. h D_m); ``springs`` a :class:`PointSprings`; the armature of the
    model is added unless ``include_armature`` is False.
    """

    def __init__(self, topo: Topology, ws: Workspace, h: float, reduced_diag: np.ndarray | None = None,
                 springs: PointSprings | None = None, body_blocks: np.ndarray | None = None,
                 include_armature: bool = True):
        self.topo = topo
        self.include_armature = include_armature
        nv, nj = topo.nv, topo.njoints
        self._Y = np.zeros((nj, 6))
        self._W = np.zeros((nj, 6))
        self._F = np.zeros((nj, 6))
        self._noblocks = np.zeros((1, 6, 6))
        self._zero_blocks = np.zeros((nj, 6, 6))
        self._zero_diag = np.zeros(nv)
        self._no_springs = PointSprings(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)),
                                        np.zeros((0, 3, 3)))
        self.h = None
        self._diag_of = None  # the reduced_diag array self._diag was made from (renew)
        self.renew(ws, h, reduced_diag, springs, body_blocks)

    def renew(self, ws: Workspace, h: float, reduced_diag: np.ndarray | None = None,
              springs: PointSprings | None = None, body_blocks: np.ndarray | None = None,
              ends: tuple | None = None, C: np.ndarray | None = None) -> "MatrixFreeSystem":
        """The LHS of another step on the same tree (the constructor's arguments but the topology), keeping the
        scratch arrays: one system per step workspace serves every step of the data-free pipeline. ``ends``:
        the springs' world end points (pa, pb) at ``ws`` and ``C`` their h D + h^2 K (:meth:`refresh`) when the
        caller has them (else :meth:`refresh` computes them). The reduced diagonal is kept while the same
        ``reduced_diag`` array (a per-h constant of the caller, not modified) comes with the same h."""
        same_diag = reduced_diag is not None and reduced_diag is self._diag_of and self.h == float(h)
        self.ws, self.h = ws, float(h)
        if not same_diag:
            self._diag_of = reduced_diag
            self.reduced_diag = (self._zero_diag if reduced_diag is None
                                 else np.asarray(reduced_diag, dtype=float).reshape(self.topo.nv).copy())
            self._diag = np.ascontiguousarray(self.diag)
        self.springs = springs if springs is not None else self._no_springs
        self.body_blocks = (None if body_blocks is None
                            else np.ascontiguousarray(body_blocks, dtype=float).reshape(self.topo.njoints, 6, 6))
        self.refresh(ends, C)
        return self

    @property
    def diag(self) -> np.ndarray:
        """Reduced diagonal: armature + h D_r + h^2 K_r."""
        return self.reduced_diag + (self.topo.armature if self.include_armature else 0.0)

    def refresh(self, ends: tuple | None = None, C: np.ndarray | None = None) -> None:
        """Recompute the springs' world points (or take ``ends`` = (pa, pb), (m, 3) contiguous) and
        C_s = h D_s + h^2 K_s from ``ws`` (or take ``C``, (m, 3, 3) contiguous)."""
        sp = self.springs
        if sp.m:
            if ends is None:
                self.pa = site_positions(self.ws, sp.joint_a, sp.offset_a)
                self.pb = site_positions(self.ws, sp.joint_b, sp.offset_b)
            else:
                self.pa, self.pb = ends
            self.C = np.ascontiguousarray(self.h * sp.damping + self.h * self.h * sp.stiffness) if C is None else C
        else:
            self.pa = self.pb = _NO_POINTS
            self.C = _NO_MATRICES

    def apply(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """A x, O(n + m)."""
        topo, ws, sp = self.topo, self.ws, self.springs
        x = np.ascontiguousarray(x, dtype=float).reshape(topo.nv)
        out = np.empty(topo.nv) if out is None else out
        blocks = self._noblocks if self.body_blocks is None else self.body_blocks
        lhs_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, ws.I, blocks, self.body_blocks is not None,
                    sp.joint_a, self.pa, sp.joint_b, self.pb, self.C, self._diag, x,
                    self._Y, self._W, self._F, out)
        return out

    __call__ = apply

    def lhs_args(self) -> tuple:
        """The arrays of :func:`lhs_kernel` before ``x`` (tree, inertias, blocks, springs, diagonal), for
        compiled callers that apply A themselves (solvers/lockstep_kernel.py)."""
        t, sp = self.topo, self.springs
        blocks = self._noblocks if self.body_blocks is None else self.body_blocks
        return (t.parents, t.idx_v, t.nv_j, self.ws.St, self.ws.I, blocks, self.body_blocks is not None,
                sp.joint_a, self.pa, sp.joint_b, self.pb, self.C, self._diag)

    def lhs_scratch(self) -> tuple:
        """(Y, W, F): the (njoints, 6) scratch of :func:`lhs_kernel`."""
        return self._Y, self._W, self._F

    def preconditioner_blocks(self) -> np.ndarray:
        """The maximal term of Alg. 1 line 3 for this system: per body, B_m plus the 6x6 diagonal
        blocks of sum_s J_s^T C_s J_s in body-twist coordinates (the blkdiag filter of Eq. (3))."""
        nj = self.topo.njoints
        blocks = np.zeros((nj, 6, 6)) if self.body_blocks is None else self.body_blocks.copy()
        sp = self.springs
        spring_blocks_kernel(sp.joint_a, self.pa, sp.joint_b, self.pb, self.C, blocks)
        return blocks

    def preconditioner(self, P: ProjectedBlockJacobi | None = None) -> ProjectedBlockJacobi:
        """Factor (Alg. 1 lines 1-8) the Projected Block Jacobi Preconditioner of this system."""
        P = ProjectedBlockJacobi(self.topo) if P is None else P
        # without springs and body blocks the maximal term is zero: a kept zero array (factor only reads it)
        blocks = self._zero_blocks if self.body_blocks is None and not self.springs.m else self.preconditioner_blocks()
        return P.factor(self.ws, blocks, self.reduced_diag, include_armature=self.include_armature)

    def solve(self, b: np.ndarray, x0: np.ndarray | None = None, rtol: float = 1e-6,
              max_iter: int | None = None, P: ProjectedBlockJacobi | None = None) -> PCGResult:
        """PCG solve of A x = b with the Projected Block Jacobi Preconditioner (factored here
        unless an already factored ``P`` is given)."""
        P = self.preconditioner() if P is None else P
        return pcg(self.apply, P.apply, b, x0=x0, rtol=rtol, max_iter=max_iter)


# --------------------------------------------------------------------------------------------
# Loop closure, §3.1 Eq. (4)
# --------------------------------------------------------------------------------------------
@dataclass
class LoopClosureResult:
    x: np.ndarray  # velocity satisfying A x = b - G^T lam, G x = g
    lam: np.ndarray  # (l,) Lagrange multipliers (impulses)
    iterations: list = field(default_factory=list)  # PCG iterations: [RHS solve, one per row of G]
    converged: bool = True  # all PCG solves converged
    constraint_residual: float = 0.0  # ||G x - g||_inf


def solve_loop_closure(apply_A: Operator, apply_Pinv: Operator, b: np.ndarray, G: np.ndarray,
                       g: np.ndarray | None = None, x0: np.ndarray | None = None, rtol: float = 1e-6,
                       max_iter: int | None = None) -> LoopClosureResult:
    """Bilateral constraints G x = g (G: l x nv dense rows, g defaults to 0) with the dual of
    §3.1 Eq. (4): (G A^{-1} G^T) lam = G A^{-1} b - g, A x = b - G^T lam.

    Runs l + 1 PCG solves (u = A^{-1} b, warm-started with ``x0``, and Z = A^{-1} G^T column by
    column), then the small dense l x l solve for lam, and returns x = u - Z lam (by linearity this
    replaces the paper's final PCG solve and satisfies G x = g to the accuracy of lam)."""
    b = np.asarray(b, dtype=float).reshape(-1)
    n = b.shape[0]
    G = np.atleast_2d(np.asarray(G, dtype=float))
    l = G.shape[0]
    g = np.zeros(l) if g is None else np.asarray(g, dtype=float).reshape(l)
    res = pcg(apply_A, apply_Pinv, b, x0=x0, rtol=rtol, max_iter=max_iter)
    iters, ok = [res.iterations], res.converged
    u = res.x
    Z = np.empty((n, l))
    for k in range(l):
        rk = pcg(apply_A, apply_Pinv, G[k], rtol=rtol, max_iter=max_iter)
        Z[:, k] = rk.x
        iters.append(rk.iterations)
        ok = ok and rk.converged
    Sd = G @ Z
    Sd = 0.5 * (Sd + Sd.T)
    rhs = G @ u - g
    try:
        L = np.linalg.cholesky(Sd)
        lam = np.linalg.solve(L.T, np.linalg.solve(L, rhs))
    except np.linalg.LinAlgError:  # redundant constraints: minimum-norm multipliers
        lam = np.linalg.lstsq(Sd, rhs, rcond=None)[0]
    x = u - Z @ lam
    viol = float(np.max(np.abs(G @ x - g))) if l else 0.0
    return LoopClosureResult(x=x, lam=lam, iterations=iters, converged=ok, constraint_residual=viol)
