"""Projected Block Jacobi Preconditioner (Wang et al. 2019, §3, Eq. (3) and Alg. 1).

    P = J_mr^T (M_m + blkdiag(h D_m - h^2 K_m)) J_mr + h D_r - h^2 K_r          (Eq. (3))

(plus the joint armature on the reduced diagonal). Alg. 1 solves y = P^{-1} x in O(n): a
preprocessing backward pass (lines 1-8, :meth:`ProjectedBlockJacobi.factor`, once per LHS) and one
backward and one forward pass per right-hand side (lines 10-18, :meth:`ProjectedBlockJacobi.apply`).
It is the recursive forward-dynamics (articulated-body) algorithm with zero velocities and the
two implicit terms added: maximal 6x6 blocks to the body inertia (line 3/5) and reduced terms
inside the joint inverse (line 4/6). See also Sueda's notes §2.13 (Alg. 9).

Frames: as in :mod:`redmax_ros.core.recursive`, every 6-D quantity is expressed in the world frame
at the world origin, Pinocchio ordering (linear, angular). Then all adjoints {}^i_j Ad, {}^c_j Ad,
{}^j_p Ad of Alg. 1 are identities: M_j is the world spatial inertia of body j, S_j the world motion
subspace (Pinocchio's data.J columns), and the accumulations are plain sums.

Inputs (positive-stiffness convention, K = -df/dx, as in the LHS of Eq. (2) used by the stepper):

* ``body_blocks`` (njoints, 6, 6): the maximal term of line 3, blkdiag(h D_m + h^2 K_m) per body,
  world frame (row 0, the universe, is ignored). For a spring with 3x3 matrix C = h D + h^2 K
  attached at world point x of body i, body i's block receives X^T C X with X = [1, -[x]]
  (:func:`redmax_ros.core.recursive.point_block`); with the paper's sign this is
  h D_m - h^2 K_m.
* ``reduced_diag`` (nv,): the reduced term of line 4, h D_r + h^2 K_r per DOF (diagonal).
* ``model.armature`` (from the Topology) is added to the reduced diagonal like A_r (line 6).
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.solvers.recursive import Topology, Workspace, njit


@njit
def _chol_inverse(D, n, out, L, Li):
    """out[:n,:n] = D[:n,:n]^{-1} for SPD D (Cholesky; L, Li are 6x6 scratch).
    Returns False if D is not positive definite."""
    for i in range(n):
        for k in range(i + 1):
            s = D[i, k]
            for l in range(k):
                s -= L[i, l] * L[k, l]
            if i == k:
                if not s > 0.0:
                    return False
                L[i, i] = np.sqrt(s)
            else:
                L[i, k] = s / L[k, k]
    # Linv (lower triangular)
    for i in range(n):
        Li[i, i] = 1.0 / L[i, i]
        for k in range(i):
            s = 0.0
            for l in range(k, i):
                s -= L[i, l] * Li[l, k]
            Li[i, k] = s / L[i, i]
    for i in range(n):
        for k in range(n):
            s = 0.0
            for l in range(max(i, k), n):
                s += Li[l, i] * Li[l, k]
            out[i, k] = s
    return True


@njit
def factor_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, dr, Mhat, Ut, psi, psi_off):
    """Alg. 1 lines 1-8 (world frame, all Ad = identity). Psi_j (line 6) is stored compactly: the n_j x n_j
    block of joint j row-major at psi[psi_off[j]:], so P^-1 x reads sum_j n_j^2 numbers instead of 36 per
    joint. Returns 0 or the failing joint index."""
    nj = parents.shape[0]
    D = np.zeros((6, 6))
    L = np.zeros((6, 6))
    Li = np.zeros((6, 6))
    Pj = np.zeros((6, 6))
    PU = np.zeros((6, 6))
    for j in range(1, nj):
        for a in range(6):
            for b in range(6):
                Mhat[j, a, b] = I[j, a, b]
                if use_blocks:
                    Mhat[j, a, b] += blocks[j, a, b]  # line 3: maximal term A^m_j
    for j in range(nj - 1, 0, -1):  # backward traversal; children (> j) already added their Pi
        i0 = idx_v[j]
        n = nv_j[j]
        # U_j = Mhat_j S_j  (6 x n)
        for k in range(n):
            for a in range(6):
                s = 0.0
                for b in range(6):
                    s += Mhat[j, a, b] * St[i0 + k, b]
                Ut[i0 + k, a] = s
        # line 6: Psi_j = (S^T Mhat S + A^r_j)^{-1}, A^r_j diagonal (reduced term of line 4 + armature)
        for k in range(n):
            for l in range(n):
                s = 0.0
                for a in range(6):
                    s += St[i0 + k, a] * Ut[i0 + l, a]
                D[k, l] = s
            D[k, k] += dr[i0 + k]
        if n > 0:
            if not _chol_inverse(D, n, Pj, L, Li):
                return j
            o = psi_off[j]
            for k in range(n):
                for l in range(n):
                    psi[o + k * n + l] = Pj[k, l]
        # line 7: Pi_j = Mhat_j - U Psi U^T ; line 5 (for the parent): Mhat_p += Pi_j
        par = parents[j]
        if par > 0:
            for k in range(n):  # PU = Psi U^T (n x 6), once per joint
                for b in range(6):
                    t = 0.0
                    for l in range(n):
                        t += Pj[k, l] * Ut[i0 + l, b]
                    PU[k, b] = t
            for a in range(6):
                for b in range(6):
                    s = Mhat[j, a, b]
                    for k in range(n):
                        s -= Ut[i0 + k, a] * PU[k, b]
                    Mhat[par, a, b] += s
    return 0


@njit
def factor_at_kernel(parents, idx_v, nv_j, St_now, St, I, blocks, use_blocks, armature, use_armature, rd, dr, Mhat,
                     Ut, psi, psi_off):
    """:func:`factor_kernel` for the configuration whose world subspaces are St_now (copied to St, kept for
    apply), with the reduced term dr = armature (with ``use_armature``) + rd (an empty rd: none) of lines 4/6."""
    St[:, :] = St_now
    for i in range(dr.shape[0]):
        d = 0.0
        if use_armature:
            d += armature[i]
        if rd.shape[0]:
            d += rd[i]
        dr[i] = d
    return factor_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, dr, Mhat, Ut, psi, psi_off)


_NO_DIAG = np.zeros(0)


@njit
def apply_kernel(parents, idx_v, nv_j, St, Ut, psi, psi_off, x, y, beta, u, acc):
    """Alg. 1 lines 10-18 (world frame), Psi_j compact as :func:`factor_kernel` stores it. beta, acc:
    (njoints, 6) scratch; u: (nv,) scratch holding x_j - S_j^T Bhat_j between the two passes."""
    nj = parents.shape[0]
    w = np.empty(6)
    for j in range(nj):
        for a in range(6):
            beta[j, a] = 0.0
    for j in range(nj - 1, 0, -1):  # lines 11-14, backward traversal
        i0 = idx_v[j]
        n = nv_j[j]
        # beta[j] currently holds Bhat_j = sum_c beta_c (line 12)
        for k in range(n):
            s = x[i0 + k]
            for a in range(6):
                s -= St[i0 + k, a] * beta[j, a]
            u[i0 + k] = s
        o = psi_off[j]
        for k in range(n):
            s = 0.0
            for l in range(n):
                s += psi[o + k * n + l] * u[i0 + l]
            w[k] = s
        par = parents[j]
        for a in range(6):  # line 13: beta_j = Bhat_j + Mhat_j S_j Psi_j (x_j - S_j^T Bhat_j)
            s = beta[j, a]
            for k in range(n):
                s += Ut[i0 + k, a] * w[k]
            beta[par, a] += s
    for a in range(6):
        acc[0, a] = 0.0
    for j in range(1, nj):  # lines 15-18, forward traversal
        i0 = idx_v[j]
        n = nv_j[j]
        par = parents[j]
        for k in range(n):  # line 16: x_j - S^T Mhat Vdot_p - S^T Bhat_j = u_j - U_j^T Vdot_p
            s = u[i0 + k]
            for a in range(6):
                s -= Ut[i0 + k, a] * acc[par, a]
            w[k] = s
        for a in range(6):
            acc[j, a] = acc[par, a]
        o = psi_off[j]
        for k in range(n):
            s = 0.0
            for l in range(n):
                s += psi[o + k * n + l] * w[l]
            y[i0 + k] = s
            for a in range(6):  # line 17: Vdot_j = Vdot_p + S_j y_j
                acc[j, a] += St[i0 + k, a] * s


class ProjectedBlockJacobi:
    """y = P^{-1} x for P of Eq. (3), by Alg. 1. Usage::

        P = ProjectedBlockJacobi(topo)
        P.factor(ws, body_blocks, reduced_diag)   # once per step (lines 1-8)
        y = P.apply(x)                            # per PCG iteration (lines 10-18)

    Without maximal blocks and reduced terms P is the mass matrix (with armature) and ``apply`` is
    an O(n) M^{-1} x.
    """

    def __init__(self, topo: Topology):
        self.topo = topo
        nj, nv = topo.njoints, topo.nv
        self._Mhat = np.zeros((nj, 6, 6))
        self.Ut = np.zeros((nv, 6))
        sq = np.asarray(topo.nv_j, dtype=np.int64) ** 2
        self.psi_off = np.ascontiguousarray(np.cumsum(sq) - sq)  # Psi_j at psi[psi_off[j]:], n_j x n_j row-major
        self.psi = np.zeros(int((topo.nv_j ** 2).sum()))
        self.St = np.zeros((nv, 6))
        self.beta = np.zeros((nj, 6))
        self.acc = np.zeros((nj, 6))
        self.u = np.zeros(nv)
        self._dr = np.zeros(nv)  # the reduced term A^r of line 4 (armature + h D_r + h^2 K_r)
        self._noblocks = np.zeros((1, 6, 6))
        self.factored = False

    def factor(self, ws: Workspace, body_blocks: np.ndarray | None = None,
               reduced_diag: np.ndarray | None = None, include_armature: bool = True) -> "ProjectedBlockJacobi":
        """Alg. 1 lines 1-8 for the configuration in ``ws`` (see the module docstring for the
        inputs). Raises ValueError if a joint's S^T Mhat S + A^r (line 6) is not positive definite."""
        topo = self.topo
        rd = _NO_DIAG if reduced_diag is None else np.asarray(reduced_diag, dtype=float).reshape(topo.nv)
        if body_blocks is None:
            blocks, use = self._noblocks, False
        else:
            blocks = np.ascontiguousarray(body_blocks, dtype=float).reshape(topo.njoints, 6, 6)
            use = True
        bad = factor_at_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, self.St, ws.I, blocks, use,
                               topo.armature, include_armature, rd, self._dr, self._Mhat, self.Ut, self.psi,
                               self.psi_off)
        if bad:
            self.factored = False
            raise ValueError(f"Alg. 1 line 6: S^T Mhat S + A^r is not positive definite at joint {bad}")
        self.factored = True
        return self

    def apply(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """y = P^{-1} x (Alg. 1 lines 10-18), O(n)."""
        if not self.factored:
            raise RuntimeError("call factor() before apply()")
        topo = self.topo
        x = np.ascontiguousarray(x, dtype=float).reshape(topo.nv)
        out = np.empty(topo.nv) if out is None else out
        apply_kernel(topo.parents, topo.idx_v, topo.nv_j, self.St, self.Ut, self.psi, self.psi_off, x, out,
                     self.beta, self.u, self.acc)
        return out

    __call__ = apply

    def apply_args(self) -> tuple:
        """(St, Ut, psi, psi_off): the factored arrays :func:`apply_kernel` reads, for compiled callers
        (solvers/lockstep_kernel.py); its scratch is (beta, u, acc)."""
        return self.St, self.Ut, self.psi, self.psi_off
