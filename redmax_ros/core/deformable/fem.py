"""Tetrahedral FEM with co-rotated linear elasticity, lumped mass and Rayleigh damping.

Sifakis & Barbic, "FEM Simulation of 3D Deformable Solids: A practitioner's guide to theory, discretization
and model reduction" (SIGGRAPH 2012 course), §3.4-§4 (the cited reference of Wang et al. 2019 for RedMax's
FEM): per tetrahedron the deformation gradient F = D_s D_m^-1 (D_s, D_m the edge matrices of the deformed and
rest tetrahedron), its polar decomposition F = R S (R a proper rotation, from the SVD with the reflection
moved to the smallest singular value), the co-rotated linear energy density

    Psi(F) = mu |F - R|_F^2 + lambda/2 tr^2(R^T F - I),   P = dPsi/dF = 2 mu (F - R) + lambda tr(R^T F - I) R,

the nodal forces f_a = -V P b_a (b_a the gradient of vertex a's shape function, the rows of D_m^-1 and minus
their sum), and the stiffness K = -df/dx linearised each step with the exact differential of P (including
the rotation's, so K is the energy's Hessian and the FD check holds to round-off):

    dP = 2 mu dF + lambda tr(R^T dF) R + (lambda tr(S - I) - 2 mu) dR,   dR = R [w]_x,
    (tr(S) I - S) w = axial(R^T dF - dF^T R)        (from F = R S, S symmetric; course notes §5.?)

mu, lambda the Lame parameters of Young's modulus E and Poisson's ratio nu. Mass: each tetrahedron's
density * volume split equally over its four vertices (lumped). Damping (Rayleigh): D = alpha M + beta K.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from redmax_ros.core.deformable.string import block_coo


def lame(young: float, poisson: float) -> tuple:
    """(mu, lambda) of Young's modulus [Pa] and Poisson's ratio."""
    return young / (2.0 * (1.0 + poisson)), young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))


def polar(F):
    """(R, S) with F = R S, R a proper rotation (det +1), S symmetric, for a batch (T,3,3) of F."""
    U, s, Vt = np.linalg.svd(F)
    flip = np.linalg.det(U) * np.linalg.det(Vt) < 0
    if flip.any():
        U = U.copy()
        U[flip, :, 2] *= -1.0
    R = U @ Vt
    S = np.swapaxes(R, 1, 2) @ F
    return R, 0.5 * (S + np.swapaxes(S, 1, 2))


class TetFEM:
    """A tetrahedral mesh: rest vertices x0 (n,3) [m], tets (T,4) vertex indices; ``young`` [Pa],
    ``poisson`` (< 0.5), ``density`` [kg/m^3]; Rayleigh ``alpha`` [1/s], ``beta`` [s]. Inverted rest
    tetrahedra are reoriented; degenerate ones (volume <= 1e-14 of the bounding box's) are an error."""

    kind = "fem"

    def __init__(self, x0, tets, young: float, poisson: float, density: float, alpha: float = 0.0,
                 beta: float = 0.0):
        x0 = np.asarray(x0, dtype=float)
        tets = np.array(tets, dtype=np.int64)
        if x0.ndim != 2 or x0.shape[1] != 3 or tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
            raise ValueError("a tet mesh needs vertices (n,3) and tetrahedra (T,4)")
        if tets.min() < 0 or tets.max() >= len(x0):
            raise ValueError("tetrahedron vertex index out of range")
        if not (young > 0 and -1.0 < poisson < 0.5 and density > 0):
            raise ValueError("young > 0, -1 < poisson < 0.5 and density > 0 are required")
        Dm = np.swapaxes(x0[tets[:, 1:]] - x0[tets[:, :1]], 1, 2)
        det = np.linalg.det(Dm)
        neg = det < 0
        if neg.any():
            tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
            Dm = np.swapaxes(x0[tets[:, 1:]] - x0[tets[:, :1]], 1, 2)
            det = np.linalg.det(Dm)
        scale = np.ptp(x0, axis=0).prod() or 1.0
        if np.any(det <= 1e-14 * scale):
            raise ValueError(f"degenerate tetrahedron {int(np.argmin(det))} (zero volume)")
        self.x0, self.tets, self.n, self.n_elements = x0, tets, len(x0), len(tets)
        self.vol = det / 6.0
        Dinv = np.linalg.inv(Dm)
        B = np.empty((len(tets), 4, 3))
        B[:, 1:] = Dinv
        B[:, 0] = -Dinv.sum(axis=1)
        self.B = B
        self.young, self.poisson, self.density = float(young), float(poisson), float(density)
        self.mu, self.lam = lame(young, poisson)
        self.alpha, self.beta = float(alpha), float(beta)
        m = np.zeros(self.n)
        np.add.at(m, tets.ravel(), np.repeat(density * self.vol / 4.0, 4))
        self.mass = m

    def kinematics(self, x):
        """(F, R, S) of every tetrahedron at x; the last one is kept (force, stiffness and energy of one step
        share one SVD)."""
        x = np.asarray(x, float)
        key = x.tobytes()
        if getattr(self, "_last_key", None) != key:
            F = self.deformation_gradient(x)
            R, S = polar(F)
            self._last_key, self._last = key, (F, R, S)
        return self._last

    def deformation_gradient(self, x):
        """(T,3,3) F = D_s D_m^-1 = sum_a x_a b_a^T."""
        return np.einsum("tai,tak->tik", np.asarray(x, float)[self.tets], self.B)

    def stress(self, x):
        """(T,3,3) first Piola-Kirchhoff stress P [Pa] per tetrahedron."""
        F, R, S = self.kinematics(x)
        return 2.0 * self.mu * (F - R) + (self.lam * (np.trace(S, axis1=1, axis2=2) - 3.0))[:, None, None] * R

    def energy(self, x) -> float:
        F, R, S = self.kinematics(x)
        psi = self.mu * np.sum((F - R) ** 2, axis=(1, 2)) + 0.5 * self.lam * (np.trace(S, axis1=1, axis2=2) - 3.0) ** 2
        return float(self.vol @ psi)

    def force(self, x) -> np.ndarray:
        """(n,3) elastic forces f_a = -sum_t V_t P_t b_ta."""
        fe = -self.vol[:, None, None] * np.einsum("tik,tak->tai", self.stress(x), self.B)
        f = np.zeros((self.n, 3))
        np.add.at(f, self.tets.ravel(), fe.reshape(-1, 3))
        return f

    def element_stiffness(self, x) -> np.ndarray:
        """(T,12,12) per-tetrahedron K_e = -df_e/dx_e (exact, with the rotation's differential), in closed form
        over the 12 unit displacements (vertex a, component c): dF = e_c b_a^T, so R^T dF = r_c b_a^T (r_c the
        c-th row of R), tr(R^T dF) = r_c . b_a, axial(R^T dF - dF^T R) = b_a x r_c, and
        K[(b,d),(a,c)] = V [2 mu (b_a . b_b) delta_cd + lambda (r_c . b_a)(R b_b)_d
                            + (lambda tr(S - I) - 2 mu) (R (w_ac x b_b))_d],  (tr S I - S) w_ac = b_a x r_c."""
        F, R, S = self.kinematics(x)
        B = self.B
        T = len(F)
        trS = np.trace(S, axis1=1, axis2=2)
        RT = np.swapaxes(R, 1, 2)
        BB = B @ np.swapaxes(B, 1, 2)  # (T,4,4) b_a . b_b
        RB = B @ RT  # (T,4,3) [a,c] = r_c . b_a = (R b_a)_c
        axial = np.cross(B[:, :, None, :], R[:, None, :, :])  # (T,4,3,3) b_a x r_c
        Ainv = np.linalg.inv(trS[:, None, None] * np.eye(3) - S)
        w = axial @ np.swapaxes(Ainv, 1, 2)[:, None]  # (T,4,3,3) w_ac
        RwB = np.cross(w[:, :, :, None, :], B[:, None, None, :, :]) @ RT[:, None, None]  # (T,a,c,b,d)
        coef = self.lam * (trS - 3.0) - 2.0 * self.mu
        K = coef[:, None, None, None, None] * RwB
        K += self.lam * RB[:, :, :, None, None] * RB[:, None, None, :, :]
        K += 2.0 * self.mu * BB[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
        K *= self.vol[:, None, None, None, None]
        return np.ascontiguousarray(K.transpose(0, 3, 4, 1, 2)).reshape(T, 12, 12)

    def stiffness(self, x) -> sp.csr_matrix:
        """(3n,3n) K = -df/dx, sparse (assembled from element_stiffness)."""
        Ke = self.element_stiffness(x)
        T = len(Ke)
        blocks = Ke.reshape(T, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4).reshape(-1, 3, 3)
        bi = np.repeat(self.tets, 4, axis=1).ravel()
        bj = np.tile(self.tets, (1, 4)).ravel()
        return block_coo(blocks, bi, bj, self.n)

    def surface(self) -> np.ndarray:
        """(F,3) boundary triangles (faces of one tetrahedron only), outward-oriented at rest."""
        faces = np.concatenate([self.tets[:, [1, 2, 3]], self.tets[:, [0, 3, 2]], self.tets[:, [0, 1, 3]],
                                self.tets[:, [0, 2, 1]]])
        key = np.sort(faces, axis=1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return faces[cnt[inv.ravel()] == 1]
