"""All deformables of a scene as one block of maximal DOFs (3 per vertex, world frame) and their state.

Per step (Eq. 2's form, Wang et al. 2019 §4: M_d qdot_d = f_d, linearised implicitly):
A_d = M_d + h D_d + h^2 K_d,  b_d = M_d v_d + h f_d(x),  D_d = alpha M_d + beta K_d per element,
K_d = -df_d/dx at the step's x (fem.py, string.py), f_d the elastic forces plus gravity.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


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

    @property
    def mass(self) -> np.ndarray:
        return np.concatenate([e.mass for e in self.elements])

    def initial(self) -> DeformState:
        x = np.concatenate([e.x0 for e in self.elements])
        return DeformState.of(x, np.zeros_like(x))

    def part(self, i, a):
        return a[self.offsets[i]:self.offsets[i + 1]]

    def assemble(self, x, v, h):
        """(A_d sparse CSC (3N,3N), b_d (3N,)) of the step."""
        blocks, rhs = [], []
        for i, e in enumerate(self.elements):
            xe, ve = self.part(i, x), self.part(i, v)
            K = e.stiffness(xe)
            m3 = np.repeat(e.mass, 3)
            A = sp.diags(m3 * (1.0 + h * e.alpha)) + (h * e.beta + h * h) * K
            f = e.force(xe) + e.mass[:, None] * self.gravity
            rhs.append(m3 * ve.ravel() + h * f.ravel())
            blocks.append(A)
        return sp.block_diag(blocks, format="csc"), np.concatenate(rhs)

    def energies(self, x, v) -> tuple:
        """(kinetic, gravitational, elastic) [J]; gravity relative to x = 0."""
        m = self.mass
        ek = 0.5 * float(m @ np.sum(v * v, axis=1))
        eg = -float(m @ (x @ self.gravity))
        ee = sum(e.energy(self.part(i, x)) for i, e in enumerate(self.elements))
        return ek, eg, float(ee)

    def momentum(self, x, v) -> tuple:
        """(linear (3,), angular about the origin (3,)) of the deformable vertices."""
        p = self.mass[:, None] * v
        return p.sum(axis=0), np.cross(x, p).sum(axis=0)

    def describe(self) -> list:
        """(name, kind, vertices, elements) per deformable."""
        return [(n, e.kind, e.n, e.n_elements) for n, e in zip(self.names, self.elements)]
