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

The formulas are implemented once, compiled, in fem_kernels.py (polar decomposition, P, forces, the exact
element stiffness, the scatter into a fixed CSR pattern); this module holds the mesh and its precomputed
rest data (B, volumes, masses, the sparsity pattern).
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.deformable import fem_kernels
from redmax_ros.core.deformable.sparsity import PatternElement


def lame(young: float, poisson: float) -> tuple:
    """(mu, lambda) of Young's modulus [Pa] and Poisson's ratio."""
    return young / (2.0 * (1.0 + poisson)), young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))


def polar(F):
    """(R, S) with F = R S, R a proper rotation (det +1; for det F < 0 the reflection on the smallest
    singular value, S then indefinite), S symmetric, for a batch (T,3,3) of F (fem_kernels.polar3)."""
    return fem_kernels.polar_batch(np.ascontiguousarray(F, dtype=float).reshape(-1, 3, 3))


class TetFEM(PatternElement):
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
        self.cells = tets
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

    def add(self, x, ck: float, hf: float, data, f) -> float:
        """f (n,3) += hf * elastic forces [N], pattern's ``data`` += ck * K [N/m]; returns the elastic energy
        [J] at x (n,3) [m] (fem_kernels.fem_add)."""
        return fem_kernels.fem_add(np.ascontiguousarray(x, dtype=float), self.tets, self.B, self.vol, self.mu,
                                   self.lam, self.pattern.blk, self.pattern.stride, ck, hf, data, f)

    def stress(self, x) -> np.ndarray:
        """(T,3,3) first Piola-Kirchhoff stress P [Pa] per tetrahedron."""
        return fem_kernels.fem_stress(np.ascontiguousarray(x, dtype=float), self.tets, self.B, self.mu, self.lam)

    def element_stiffness(self, x) -> np.ndarray:
        """(T,12,12) per-tetrahedron K_e = -df_e/dx_e [N/m] (exact, with the rotation's differential), row
        3a + c the force component c of vertex a, column 3b + d the displacement component d of vertex b."""
        Kb = fem_kernels.fem_element_stiffness(np.ascontiguousarray(x, dtype=float), self.tets, self.B,
                                               self.vol, self.mu, self.lam)
        return np.ascontiguousarray(Kb.transpose(0, 1, 3, 2, 4)).reshape(-1, 12, 12)

    def surface(self) -> np.ndarray:
        """(F,3) boundary triangles (faces of one tetrahedron only), outward-oriented at rest."""
        faces = np.concatenate([self.tets[:, [1, 2, 3]], self.tets[:, [0, 3, 2]], self.tets[:, [0, 1, 3]],
                                self.tets[:, [0, 2, 1]]])
        key = np.sort(faces, axis=1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return faces[cnt[inv.ravel()] == 1]
