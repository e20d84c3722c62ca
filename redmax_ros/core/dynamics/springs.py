"""Maximal point-to-point springs and joint springs: forces, 3x3 stiffness/damping and energy, one
formula for every pipeline (forces.py, tree_forces.py, energy.py, friction/bisp.py)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.jit import njit


def spring_forces(mech, X: np.ndarray, V: np.ndarray | None = None):
    """Per spring, from the positions X (rows in mech.spring_rows): force on end a (P,3), 3x3 stiffness
    K (P,3,3), 3x3 damping D (P,3,3), lengths (P,). Shared by every pipeline (the compiled step calls
    :func:`spring_kernel` itself).

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
    P = len(mech.spring_k)
    ex = getattr(mech, "spring_explicit", None)  # None: all implicit (also for stand-ins)
    ex = np.zeros(P, dtype=np.int64) if ex is None else np.asarray(ex, dtype=np.int64)
    if V is None:
        if needs_velocities(mech):
            raise ValueError("explicit spring dampers need the site velocities V")
        V = _NO_V
    f, K, D, l = np.empty((P, 3)), np.empty((P, 3, 3)), np.empty((P, 3, 3)), np.empty(P)
    rows = np.asarray(mech.spring_rows, dtype=np.int64)
    spring_kernel(np.ascontiguousarray(X, dtype=float), rows[:, 0].copy(), rows[:, 1].copy(),
                  np.asarray(mech.spring_k, float), np.asarray(mech.spring_d, float), np.asarray(mech.spring_rest, float),
                  ex, np.ascontiguousarray(V, dtype=float), f, K, D, l)
    return f, K, D, l


_NO_V = np.zeros((0, 3))


@njit
def spring_kernel(X, a, b, k, c, L0, explicit, V, f, K, D, l):
    """spring_forces' formulas for springs between rows a[s] and b[s] of X (P,): f (P,3), K and D (P,3,3),
    l (P,) written in place. V: site velocities (rows as X) for explicit dampers, or (0,3) when none is."""
    for s in range(a.shape[0]):
        d0 = X[a[s], 0] - X[b[s], 0]
        d1 = X[a[s], 1] - X[b[s], 1]
        d2 = X[a[s], 2] - X[b[s], 2]
        ls = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        l[s] = ls
        tiny = ls <= 1e-12
        safe = 1.0 if tiny else ls
        u0, u1, u2 = d0 / safe, d1 / safe, d2 / safe
        fk = -(k[s] * (ls - L0[s]))
        f[s, 0], f[s, 1], f[s, 2] = fk * u0, fk * u1, fk * u2
        if explicit[s]:
            K[s] = 0.0
            D[s] = 0.0
            if c[s] != 0.0:
                dv0 = V[a[s], 0] - V[b[s], 0]
                dv1 = V[a[s], 1] - V[b[s], 1]
                dv2 = V[a[s], 2] - V[b[s], 2]
                fd = c[s] * (u0 * dv0 + u1 * dv1 + u2 * dv2)
                f[s, 0] -= fd * u0
                f[s, 1] -= fd * u1
                f[s, 2] -= fd * u2
            continue
        trans = 1.0 if tiny else max(1.0 - L0[s] / safe, 0.0)
        u = (u0, u1, u2)
        for r in range(3):
            for q in range(3):
                uu = u[r] * u[q]
                K[s, r, q] = k[s] * (uu + trans * ((1.0 if r == q else 0.0) - uu))
                D[s, r, q] = c[s] * uu


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
