"""Energy diagnostics [J]: kinetic (incl. armature), gravitational, spring (maximal + joint + catalogue
direction springs). One implementation for every pipeline, on the recursive kinematics Context
(tree_kinematics.py)."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.dynamics.springs import spring_energy
from redmax_ros.core.dynamics.tree_kinematics import Context


def energies(ctx: Context, q, v_r, extras=None) -> tuple:
    """(E_kin, E_pot, E_spring) [J] at (q, v_r) (reduced velocities). ``extras``: the workspace's
    catalogue runtime (direction springs) or None. Leaves (q, v_r) in ctx.ws."""
    mech, topo = ctx.mech, ctx.topo
    ws = ctx.fk(q, v_r)
    R, ov = ws.R[1:], ws.ov[1:]
    com = np.einsum("jab,jb->ja", R, topo.com[1:]) + ws.p[1:]
    # per body at its COM (no lever arm to the world origin, whose cancellation would cost round-off):
    # 1/2 m |v_c|^2 + 1/2 w_b^T I_c w_b, v_c = v_o + w x c, w_b = R^T w
    w = ov[:, 3:]
    v_c = ov[:, :3] + np.cross(w, com)
    w_b = np.einsum("jba,jb->ja", R, w)
    ek = 0.5 * float(topo.mass[1:] @ np.einsum("ja,ja->j", v_c, v_c))
    ek += 0.5 * float(np.einsum("ja,jab,jb->", w_b, topo.inertia_com[1:], w_b))
    if mech.has_armature:
        ek += 0.5 * float(mech.armature @ (v_r * v_r))
    ep = -float(topo.mass[1:] @ (com @ ctx.gravity))
    es = spring_energy(mech, ctx.jac_positions() if len(mech.spring_ab) else None, q)
    if extras is not None:  # direction springs (catalogue_hooks.py)
        es += extras.energy(ctx.site_positions())
    return float(ek), float(ep), es
