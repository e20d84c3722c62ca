"""1-D deformable: a string of point masses joined by segment springs (the RedMax reference code's
deformable string; Wang et al. 2019, §4).

Each segment s = (i, i+1) of rest length L (the initial spacing) has the energy
E_s = 1/2 (EA / L) (l - L)^2 = 1/2 EA L eps^2 with the strain eps = (l - L) / L, l = |x_i+1 - x_i|, EA the
axial stiffness [N] (force per unit strain). Force on i+1: -(EA/L)(l - L) u, u = (x_i+1 - x_i)/l; its exact
Hessian block (the stiffness K = -df/dx of Eq. 2's form) is (EA/L) [u u^T + (1 - L/l)(I - u u^T)] with signs
[[K, -K], [-K, K]]. Mass: consistent lumping of a uniform line density (interior vertices m/(n-1), the two
ends half of that), so a hanging string converges to the continuous elastic catenary at O(1/n^2).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


class String:
    """n point masses x0 (n,3) in a chain; ``mass`` the total [kg], ``stiffness`` EA [N]; Rayleigh damping
    D = alpha M + beta K."""

    kind = "string"

    def __init__(self, x0, mass: float, stiffness: float, alpha: float = 0.0, beta: float = 0.0, rest=None):
        x0 = np.asarray(x0, dtype=float)
        if x0.ndim != 2 or x0.shape[1] != 3 or len(x0) < 2:
            raise ValueError("a string needs at least 2 points (n,3)")
        self.x0 = x0
        self.n = len(x0)
        self.seg = np.stack([np.arange(self.n - 1), np.arange(1, self.n)], axis=1)
        self.rest = np.linalg.norm(np.diff(x0, axis=0), axis=1) if rest is None else np.asarray(rest, float)
        if np.any(self.rest <= 0):
            raise ValueError("string points must be distinct (zero rest length)")
        self.k = float(stiffness)
        self.alpha, self.beta = float(alpha), float(beta)
        w = mass / self.rest.sum()  # line density
        m = np.zeros(self.n)
        np.add.at(m, self.seg[:, 0], 0.5 * w * self.rest)
        np.add.at(m, self.seg[:, 1], 0.5 * w * self.rest)
        self.mass = m
        self.n_elements = len(self.seg)

    def _geom(self, x):
        d = x[self.seg[:, 1]] - x[self.seg[:, 0]]
        l = np.linalg.norm(d, axis=1)
        return d, l, d / l[:, None]

    def energy(self, x) -> float:
        _, l, _ = self._geom(np.asarray(x, float))
        return float(0.5 * np.sum(self.k / self.rest * (l - self.rest) ** 2))

    def strain(self, x) -> np.ndarray:
        _, l, _ = self._geom(np.asarray(x, float))
        return (l - self.rest) / self.rest

    def force(self, x) -> np.ndarray:
        """(n,3) elastic forces -dE/dx."""
        _, l, u = self._geom(np.asarray(x, float))
        fs = (self.k / self.rest * (l - self.rest))[:, None] * u  # tension along +u pulls i toward i+1
        f = np.zeros((self.n, 3))
        np.add.at(f, self.seg[:, 0], fs)
        np.add.at(f, self.seg[:, 1], -fs)
        return f

    def stiffness(self, x) -> sp.csr_matrix:
        """(3n,3n) K = -df/dx (exact Hessian of the energy), sparse."""
        _, l, u = self._geom(np.asarray(x, float))
        uu = u[:, :, None] * u[:, None, :]
        c = (self.k / self.rest)[:, None, None]
        Kb = c * (uu + (1.0 - self.rest / l)[:, None, None] * (np.eye(3) - uu))  # (S,3,3)
        blocks = np.concatenate([Kb, -Kb, -Kb, Kb])  # (ii, ij, ji, jj)
        i, j = self.seg[:, 0], self.seg[:, 1]
        bi = np.concatenate([i, i, j, j])
        bj = np.concatenate([i, j, i, j])
        return block_coo(blocks, bi, bj, self.n)


def block_coo(blocks, bi, bj, n):
    """Sparse (3n,3n) from 3x3 blocks at block rows bi and columns bj (duplicates summed)."""
    r = (3 * bi[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    c = (3 * bj[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    return sp.coo_matrix((blocks.ravel(), (r.ravel(), c.ravel())), shape=(3 * n, 3 * n)).tocsr()
