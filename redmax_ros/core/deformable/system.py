"""All deformables of a scene as one block of maximal DOFs (3 per vertex, world frame) and their state.

Per step (Eq. 2's form, Wang et al. 2019 §4: M_d qdot_d = f_d, linearised implicitly):
A_d = M_d + h D_d + h^2 K_d,  b_d = M_d v_d + h f_d(x),  D_d = alpha M_d + beta K_d per element,
K_d = -df_d/dx at the step's x (fem.py, string.py), f_d the elastic forces plus gravity.

A_d has a fixed sparsity pattern (the vertex blocks that share an element, and every vertex's diagonal
block; sparsity.py), computed once per Deformables (``csr_pattern``); each step the compiled element kernels
write its CSR values and b_d into preallocated arrays (``fill``) with no COO triplets and no sort.
``assemble`` wraps both into a scipy CSR matrix.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from redmax_ros.core.deformable.sparsity import stack, start_system
from redmax_ros.core.spatial import skew


@dataclass(frozen=True)
class DeformState:
    """Positions x (N,3) [m] and velocities v (N,3) [m/s] of every deformable vertex (read-only arrays)."""
    x: np.ndarray
    v: np.ndarray

    def __post_init__(self):
        for a in (self.x, self.v):
            a.setflags(write=False)

    @staticmethod
    def of(x, v) -> "DeformState":
        return DeformState(np.array(x, dtype=float).reshape(-1, 3), np.array(v, dtype=float).reshape(-1, 3))


@dataclass(frozen=True)
class Attachments:
    """Vertices held to body points (body >= 0, ``local`` in that body's COM frame) or world points
    (body -1, ``local`` the world point)."""
    vertex: np.ndarray  # (a,) global vertex index
    body: np.ndarray  # (a,) body index, -1 world
    local: np.ndarray  # (a,3)
    labels: list  # (a,) "deformable/vertex -> body" for error messages


@dataclass(frozen=True)
class Deformables:
    """The scene's deformables: ``elements`` (String / TetFEM), their ``names``, vertex ``offsets`` into the
    global vertex array, attachments, the floor height (vertices kept above it by unilateral rows, or None)
    and gravity."""
    names: list
    elements: list
    offsets: np.ndarray  # (E+1,)
    attach: Attachments
    gravity: np.ndarray
    floor: float | None = None
    floor_vertices: np.ndarray | None = None  # global indices of vertices that touch the floor
    floor_mu: float = 0.0  # Coulomb friction of the floor contacts (four-sided pyramid on world x, y)

    @property
    def n_vertices(self) -> int:
        return int(self.offsets[-1])

    @cached_property
    def mass(self) -> np.ndarray:
        """(N,) lumped vertex masses [kg] (read-only; built on the first call)."""
        m = np.concatenate([e.mass for e in self.elements])
        m.setflags(write=False)
        return m

    def initial(self) -> DeformState:
        x = np.concatenate([e.x0 for e in self.elements])
        return DeformState.of(x, np.zeros_like(x))

    def part(self, i, a):
        return a[self.offsets[i]:self.offsets[i + 1]]

    @cached_property
    def _csr(self) -> tuple:
        """(indptr, indices, data offsets of the elements) of A_d (sparsity.stack of the element patterns)."""
        return stack([e.pattern for e in self.elements])

    def csr_pattern(self) -> tuple:
        """(indptr (3N+1,) int32, indices (nnz,) int32): the CSR pattern of A_d (3N,3N), DOF 3i + c the
        world axis c of global vertex i; column indices sorted in every row; every vertex's 3 x 3 diagonal
        block is present. Fixed for the Deformables (computed on the first call; the same arrays after: do
        not modify them). ``fill`` writes the values in this order."""
        indptr, indices, _ = self._csr
        return indptr, indices

    def fill(self, x, v, h: float, data: np.ndarray, b: np.ndarray) -> float:
        """The step's system in place: data (nnz,) := the CSR values of A_d = M_d + h D_d + h^2 K_d [kg] in
        ``csr_pattern``'s order, b (3N,) := b_d = M_d v + h f_d [N s] (f_d the elastic forces and gravity
        [N]), at positions x (N,3) [m], velocities v (N,3) [m/s], step h [s]. One compiled element loop per
        deformable (fem_kernels.fem_add, string.string_add), no allocation of the size of A_d. Returns the
        elastic energy at x [J], which the element loop computes on the way."""
        _, indices, at = self._csr
        for a, shape in ((data, indices.shape), (b, (3 * self.n_vertices,))):
            if a.shape != shape or a.dtype != np.float64 or not a.flags.c_contiguous:
                raise ValueError(f"fill writes into contiguous float64 arrays data {indices.shape} and b "
                                 f"({3 * self.n_vertices},), not {a.dtype} {a.shape}")
        x = np.ascontiguousarray(x, dtype=float).reshape(-1, 3)
        v = np.ascontiguousarray(v, dtype=float).reshape(-1, 3)
        g = np.ascontiguousarray(self.gravity, dtype=float)
        elastic = 0.0
        for i, e in enumerate(self.elements):
            lo, hi = self.offsets[i], self.offsets[i + 1]
            d, be = data[at[i]:at[i + 1]], b[3 * lo:3 * hi]
            p = e.pattern
            start_system(e.mass, v[lo:hi], h, g, 1.0 + h * e.alpha, p.diag, p.stride, d, be)
            elastic += float(e.add(x[lo:hi], h * e.beta + h * h, h, d, be.reshape(-1, 3)))
        return elastic

    def assemble(self, x, v, h):
        """(A_d sparse CSR (3N,3N) [kg], b_d (3N,) [N s]) of the step (``fill`` on ``csr_pattern``)."""
        indptr, indices = self.csr_pattern()
        data, b = np.empty(len(indices)), np.empty(3 * self.n_vertices)
        self.fill(x, v, h, data, b)
        n = 3 * self.n_vertices
        return sp.csr_matrix((data, indices, indptr), shape=(n, n)), b

    def energies(self, x, v, elastic: float | None = None) -> tuple:
        """(kinetic, gravitational, elastic) [J]; gravity relative to x = 0; ``elastic`` when already known
        (``fill`` at x returns it)."""
        m = self.mass
        vv = v * v  # |v_i|^2 by columns: np.sum(v * v, axis=1)'s (a + b) + c at ~6 instead of ~14 us (N = 222)
        ek = 0.5 * float(m @ ((vv[:, 0] + vv[:, 1]) + vv[:, 2]))
        eg = -float(m @ (x @ self.gravity))
        if elastic is None:
            elastic = sum(e.energy(self.part(i, x)) for i, e in enumerate(self.elements))
        return ek, eg, float(elastic)

    def momentum(self, x, v) -> tuple:
        """(linear (3,), angular about the origin (3,)) of the deformable vertices."""
        p = self.mass[:, None] * v
        return p.sum(axis=0), np.cross(x, p).sum(axis=0)

    def locked_inertia(self, x) -> np.ndarray:
        """(6,6) spatial inertia of the vertices at x (N,3) [m] locked together, about the world origin, linear
        rows first: [[M I, -[s]], [[s], tr(S) I - S]] with s = sum m_i x_i, S = sum m_i x_i x_i^T (a rigid twist
        (v_O, w) of them has the momentum of :meth:`momentum` locked_inertia @ (v_O, w))."""
        m = self.mass
        s = m @ x
        S = (x * m[:, None]).T @ x
        out = np.zeros((6, 6))
        out[:3, :3] = float(m.sum()) * np.eye(3)
        out[3:, :3] = skew(s)
        out[:3, 3:] = -out[3:, :3]
        out[3:, 3:] = np.trace(S) * np.eye(3) - S
        return out

    def describe(self) -> list:
        """(name, kind, vertices, elements) per deformable."""
        return [(n, e.kind, e.n, e.n_elements) for n, e in zip(self.names, self.elements)]
