"""Maximal point-to-point springs and joint springs: forces, 3x3 stiffness/damping and energy, one
formula for every pipeline (forces.py, tree_forces.py, energy.py, friction/bisp.py)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin


def spring_forces(mech, X: np.ndarray, V: np.ndarray | None = None):
    """Per spring, from the positions X (rows in mech.spring_rows): force on end a (P,3), 3x3 stiffness
    K (P,3,3), 3x3 damping D (P,3,3), lengths (P,). Shared by the direct and matrix-free paths.

    f_a = -k (l - L0) u,  K = k [u u^T + max(0, 1 - L0/l) (I - u u^T)],  D = c u u^T
    (notes §1.9.5 point-to-point force, §1.9.9 spring damper).
    The transverse (geometric) term is clamped at zero for compressed springs so that the LHS of
    Eq. (2) stays positive definite (a compressed spring's negative transverse stiffness would
    otherwise make the linear system indefinite).

    Springs with ``implicit: false`` (mech.spring_explicit) are explicit (notes §1.9: "for explicit
    integration we only need f and not K and D"): K = D = 0, so nothing of theirs enters the LHS of
    Eq. (2), and their whole force is evaluated at step k, f_a = -k (l - L0) u - c (u . (v_a - v_b)) u
    with the site velocities V (rows as X; needed only when such a spring has damping).
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
    ex = getattr(mech, "spring_explicit", None)  # None: all implicit (also for stand-ins)
    if ex is not None and ex.any():
        K[ex] = 0.0
        D[ex] = 0.0
        damped = ex & (c != 0.0)
        if damped.any():
            if V is None:
                raise ValueError("explicit spring dampers need the site velocities V")
            dv = V[a[damped]] - V[b[damped]]
            f[damped] -= (c[damped] * np.einsum("pi,pi->p", u[damped], dv))[:, None] * u[damped]
    return f, K, D, l


def needs_velocities(mech) -> bool:
    """True when some spring is explicit (implicit: false) and has damping (spring_forces needs V)."""
    ex = getattr(mech, "spring_explicit", None)  # None: all implicit (also for stand-ins)
    return ex is not None and bool((ex & (mech.spring_d != 0.0)).any())


def spring_terms(mech, X: np.ndarray, J: np.ndarray, v: np.ndarray | None = None):
    """:func:`spring_forces` plus the Jacobian of the end difference (P,3,nv) from J (K,3,nv):
    returns (f_a, K, D, J_a - J_b, lengths). ``v`` (nv,) the reduced velocity at step k (site
    velocities V = J v, for explicit spring dampers)."""
    V = np.einsum("kin,n->ki", J, v) if v is not None and needs_velocities(mech) else None
    f, K, D, l = spring_forces(mech, X, V)
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
