"""Maximal point-to-point springs and joint springs: forces, 3x3 stiffness/damping and energy, one
formula for every pipeline (forces.py, tree_forces.py, energy.py, friction/bisp.py)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin


def spring_forces(mech, X: np.ndarray):
    """Per spring, from the positions X (rows in mech.spring_rows): force on end a (P,3), 3x3 stiffness
    K (P,3,3), 3x3 damping D (P,3,3), lengths (P,). Shared by the direct and matrix-free paths.

    f_a = -k (l - L0) u,  K = k [u u^T + max(0, 1 - L0/l) (I - u u^T)],  D = c u u^T.
    The transverse (geometric) term is clamped at zero for compressed springs so that the LHS of
    Eq. (2) stays positive definite (a compressed spring's negative transverse stiffness would
    otherwise make the linear system indefinite).
    """
    a, b = mech.spring_rows[:, 0], mech.spring_rows[:, 1]
    d = X[a] - X[b]
    l = np.sqrt(np.einsum("pi,pi->p", d, d))
    tiny = l <= 1e-12
    safe = np.where(tiny, 1.0, l)
    u = d / safe[:, None]
    k, c, L0 = mech.spring_k, mech.spring_d, mech.spring_rest
    f = -(k * (l - L0))[:, None] * u
    uu = u[:, :, None] * u[:, None, :]
    trans = np.where(tiny, 1.0, np.maximum(1.0 - L0 / safe, 0.0))
    K = k[:, None, None] * (uu + trans[:, None, None] * (_I3 - uu))
    D = c[:, None, None] * uu
    return f, K, D, l


def spring_terms(mech, X: np.ndarray, J: np.ndarray):
    """:func:`spring_forces` plus the Jacobian of the end difference (P,3,nv) from J (K,3,nv):
    returns (f_a, K, D, J_a - J_b, lengths)."""
    f, K, D, l = spring_forces(mech, X)
    return f, K, D, J[mech.spring_rows[:, 0]] - J[mech.spring_rows[:, 1]], l


_I3 = np.eye(3)[None]


def joint_displacement(mech, q: np.ndarray) -> np.ndarray:
    """q - q_rest on the configuration manifold (pin.difference), per velocity DOF."""
    return pin.difference(mech.model, mech.q_rest, q)


def spring_energy(mech, X, q) -> float:
    """E_spring [J]: maximal springs (ends at X, rows of mech.jac_sites) + joint springs at q.
    Shared by the direct and matrix-free paths."""
    es = 0.0
    if len(mech.spring_ab):
        d = X[mech.spring_rows[:, 0]] - X[mech.spring_rows[:, 1]]
        l = np.sqrt(np.einsum("pi,pi->p", d, d))
        es += 0.5 * float(mech.spring_k @ (l - mech.spring_rest) ** 2)
    if mech.has_stiffness:
        dq = joint_displacement(mech, q)
        es += 0.5 * float(mech.stiffness @ (dq * dq))
    return es
