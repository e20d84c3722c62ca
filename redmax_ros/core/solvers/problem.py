"""What the solvers take: the linear system of Eq. (2) and the constraint rows of Eq. (5)-(7).

Sign convention: A qdot = b - G^T lam - C^T mu, so -G^T lam is the constraint impulse; rows are in the
coordinates of the system (hyper-reduced on the Pinocchio pipeline, reduced on the PCG path).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class LinearSystem:
    A: np.ndarray  # (n,n) LHS of Eq. (2), symmetric positive definite (unless symmetric is False)
    b: np.ndarray  # (n,) RHS of Eq. (2)
    symmetric: bool = True  # False with integrator.coriolis: implicit (A has h K_v, K_v not symmetric)


@dataclass
class Constraints:
    G: np.ndarray  # (m,n) bilateral rows
    g: np.ndarray  # (m,)
    label_spans: list  # (label, number of rows) in row order; labels are built only for error messages
    joint_rows: dict = field(default_factory=dict)  # prescribed joint -> slice of rows
    site_rows: dict = field(default_factory=dict)  # prescribed site -> slice of rows
    site_axes: dict = field(default_factory=dict)  # prescribed site -> (k,3) world directions of its k rows (k < 3 or
    #                                                given axes; absent: the rows are world x, y, z)
    loop_rows: slice = field(default_factory=lambda: slice(0, 0))
    C: np.ndarray | None = None  # (p,n) unilateral rows
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    C_labels: list = field(default_factory=list)

    @property
    def m(self) -> int:
        return len(self.g)

    @property
    def labels(self) -> list:
        """One label per bilateral row (for error messages)."""
        return [lab for lab, n in self.label_spans for _ in range(n)]
