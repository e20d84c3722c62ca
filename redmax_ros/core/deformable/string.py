"""1-D deformable: a string of point masses joined by segment springs (the RedMax reference code's
deformable string; Wang et al. 2019, §4).

Each segment s = (i, i+1) of rest length L (the initial spacing) has the energy
E_s = 1/2 (EA / L) (l - L)^2 = 1/2 EA L eps^2 with the strain eps = (l - L) / L, l = |x_i+1 - x_i|, EA the
axial stiffness [N] (force per unit strain). Force on i+1: -(EA/L)(l - L) u, u = (x_i+1 - x_i)/l; its exact
Hessian block (the stiffness K = -df/dx of Eq. 2's form) is (EA/L) [u u^T + (1 - L/l)(I - u u^T)] with signs
[[K, -K], [-K, K]]. Mass: consistent lumping of a uniform line density (interior vertices m/(n-1), the two
ends half of that), so a hanging string converges to the continuous elastic catenary at O(1/n^2).
Energy, forces and stiffness come from one compiled loop (``string_add``) scattering into the string's fixed
CSR pattern (sparsity.py).
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.deformable.sparsity import PatternElement, add_block
from redmax_ros.core.jit import drop_stale_caches, njit, njit_inline

# the kernels below inline sparsity.add_block: an edit of sparsity.py recompiles them
drop_stale_caches("deformable/string.py", ("deformable/string.py", "deformable/sparsity.py", "jit.py"))


@njit_inline
def segment_terms(x, i, j, L, k, fs, Kb):
    """Segment (i, j) of rest length L [m] and axial stiffness k = EA [N] at x (n,3) [m]: fs (3,) := the
    force on i, (EA/L)(l - L) u [N] (-fs on j); Kb (3,3) := (EA/L) [u u^T + (1 - L/l)(I - u u^T)] [N/m], the
    block of K = -df/dx with signs [[Kb, -Kb], [-Kb, Kb]]. Returns the energy 1/2 (EA/L)(l - L)^2 [J]."""
    d0, d1, d2 = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
    l = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    u = (d0 / l, d1 / l, d2 / l)
    kl = k / L
    t = kl * (l - L)
    g = 1.0 - L / l
    for a in range(3):
        fs[a] = t * u[a]
        for b in range(3):
            Kb[a, b] = kl * (u[a] * u[b] + g * ((1.0 if a == b else 0.0) - u[a] * u[b]))
    return 0.5 * kl * (l - L) ** 2


@njit
def string_add(x, seg, rest, k, blk, stride, ck, hf, data, f):
    """Over every segment: f (n,3) += hf * (elastic forces [N]) when hf != 0, the CSR ``data`` of a
    sparsity.BlockPattern += ck * (segment stiffness blocks [N/m]) when ck != 0. Returns the elastic energy
    [J]. x (n,3) [m], seg (S,2), rest (S,) [m], k = EA [N]."""
    fs, Kb = np.empty(3), np.empty((3, 3))
    energy = 0.0
    for s in range(len(seg)):
        i, j = seg[s, 0], seg[s, 1]
        energy += segment_terms(x, i, j, rest[s], k, fs, Kb)
        if hf != 0.0:
            for c in range(3):
                f[i, c] += hf * fs[c]
                f[j, c] -= hf * fs[c]
        if ck != 0.0:
            add_block(data, blk[s, 0, 0], stride[i], ck, Kb)
            add_block(data, blk[s, 0, 1], stride[i], -ck, Kb)
            add_block(data, blk[s, 1, 0], stride[j], -ck, Kb)
            add_block(data, blk[s, 1, 1], stride[j], ck, Kb)
    return energy


class String(PatternElement):
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
        self.cells = self.seg
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

    def add(self, x, ck: float, hf: float, data, f) -> float:
        """f (n,3) += hf * elastic forces [N], pattern's ``data`` += ck * K [N/m]; returns the elastic energy
        [J] at x (n,3) [m] (``string_add``)."""
        return string_add(np.ascontiguousarray(x, dtype=float), self.seg, self.rest, self.k, self.pattern.blk,
                          self.pattern.stride, ck, hf, data, f)

    def strain(self, x) -> np.ndarray:
        """(S,) axial strain (l - L) / L of every segment."""
        l = np.linalg.norm(np.diff(np.asarray(x, float), axis=0), axis=1)
        return (l - self.rest) / self.rest
