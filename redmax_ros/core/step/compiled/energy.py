"""The compiled step's energy diagnostics [J] (dynamics/energy.py's formulas): kinetic per body at its COM
plus armature, gravitational -m g.c, maximal springs 1/2 k (l - L0)^2 and joint springs 1/2 K_r dq^2."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.dynamics.energy import body_energies
from redmax_ros.core.jit import njit, njit_inline
from redmax_ros.core.solvers.recursive import jv_kernel
from redmax_ros.core.step.compiled.kinematics import placements
from redmax_ros.core.step.compiled.manifold import difference


@njit_inline
def energies(m, d, q, v, placed):
    """(E_kin, E_pot, E_spring) at (q, qdot_r); leaves the placements and twists of (q, v) in d. ``placed``: d
    holds the placements at q already (update.update_configuration's last loop-residual evaluation)."""
    if not placed:
        placements(m, d, q, False, v)
    jv_kernel(m.parents, m.idx_v, m.nv_j, d.St, v, d.ov)
    ek, ep = body_energies(d.R, d.p, d.ov, m.mass, m.com, m.inertia_com, m.gravity)
    if m.scalars[2] != 0.0:
        s = 0.0
        for i in range(v.shape[0]):
            s += m.armature[i] * (v[i] * v[i])
        ek += 0.5 * s
    es = 0.0
    P = m.spring_a.shape[0]
    if P:
        s = 0.0
        for k in range(P):
            a, b = m.spring_a[k], m.spring_b[k]
            l2 = 0.0
            for r in range(3):
                dx = d.X[a, r] - d.X[b, r]
                l2 += dx * dx
            e = np.sqrt(l2) - m.spring_rest[k]
            s += m.spring_k[k] * (e * e)
        es += 0.5 * s
    if m.scalars[1] != 0.0:
        difference(m.kind, m.idx_q, m.idx_v, m.q_rest, q, d.dq)
        s = 0.0
        for i in range(d.dq.shape[0]):
            s += m.stiffness[i] * (d.dq[i] * d.dq[i])
        es += 0.5 * s
    return ek, ep, es
