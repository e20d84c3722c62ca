"""Energy diagnostics [J]: kinetic (incl. armature), gravitational, spring (maximal + joint + catalogue
direction springs). One entry point, :func:`energies`, for every pipeline; the kinematics under it are
the workspace's: Pinocchio's (computeKineticEnergy/computePotentialEnergy on pin.Data, one C++ call
each) where the workspace has a pin.Data, else the recursive Context (tree_kinematics.py), whose
compiled per-body sums are :func:`tree_energies`. The spring energies are springs.spring_energy on pin.Data
and springs.point_spring_energy_kernel plus joint_spring_energy on the Context."""
from __future__ import annotations

import numpy as np

import pinocchio as pin

from redmax_ros.core.dynamics.kinematics import site_positions
from redmax_ros.core.dynamics.springs import joint_spring_energy, point_spring_energy_kernel, spring_energy
from redmax_ros.core.dynamics.tree_kinematics import Context
from redmax_ros.core.jit import njit


def energies(mech, ws, q, v_r) -> tuple:
    """(E_kin, E_pot, E_spring) [J] at (q, v_r) (reduced velocities), with the workspace's kinematics
    (pin.Data when it has one, else its recursive Context) and catalogue runtime (direction springs).
    Leaves the forward kinematics of q in that workspace."""
    data = ws.data
    if data is None:
        return tree_energies(ws.tree, q, v_r, ws.extras)
    ek = pin.computeKineticEnergy(mech.model, data, q, v_r)  # also runs forward kinematics
    if mech.has_armature:
        ek += 0.5 * float(mech.armature @ (v_r * v_r))
    ep = pin.computePotentialEnergy(mech.model, data)
    X = site_positions(mech, data, mech.jac_sites) if len(mech.spring_ab) else None
    es = spring_energy(mech, X, q)
    if ws.extras is not None:  # direction springs (catalogue_hooks.py)
        es += ws.extras.energy(site_positions(mech, data))
    return float(ek), float(ep), es


def tree_energies(ctx: Context, q, v_r, extras=None) -> tuple:
    """(E_kin, E_pot, E_spring) [J] at (q, v_r) on the recursive Context (no pin.Data). ``extras``: the
    workspace's catalogue runtime (direction springs) or None. Leaves (q, v_r) in ctx.ws."""
    mech, topo = ctx.mech, ctx.topo
    ws = ctx.fk(q, v_r)
    ek, ep = body_energies(ws.R, ws.p, ws.ov, topo.mass, topo.com, topo.inertia_com, ctx.gravity)
    if mech.has_armature:
        ek += 0.5 * float(mech.armature @ (v_r * v_r))
    es = joint_spring_energy(mech, q, ctx.additive)
    if len(mech.spring_ab):  # the maximal springs' from the placements in ws, one compiled call
        sa = ctx.spring_arrays
        es = point_spring_energy_kernel(ws.R, ws.p, ctx.spring_ja, ctx.spring_oa, ctx.spring_jb, ctx.spring_ob,
                                        sa.k, sa.rest) + es
    if extras is not None:  # direction springs (catalogue_hooks.py)
        es += extras.energy(ctx.site_positions())
    return float(ek), float(ep), es


@njit
def body_energies(R, p, ov, mass, com, Ic, g):
    """(E_kin, E_pot) of the bodies from the world placements (R, p) and twists at the world origin ov
    (v_o, w): per body at its COM c = R com + p (no lever arm to the origin, whose cancellation would cost
    round-off), 1/2 m |v_o + w x c|^2 + 1/2 w_b^T I_c w_b with w_b = R^T w, and -m g.c."""
    ek = 0.0
    ep = 0.0
    for j in range(1, R.shape[0]):
        c0 = R[j, 0, 0] * com[j, 0] + R[j, 0, 1] * com[j, 1] + R[j, 0, 2] * com[j, 2] + p[j, 0]
        c1 = R[j, 1, 0] * com[j, 0] + R[j, 1, 1] * com[j, 1] + R[j, 1, 2] * com[j, 2] + p[j, 1]
        c2 = R[j, 2, 0] * com[j, 0] + R[j, 2, 1] * com[j, 1] + R[j, 2, 2] * com[j, 2] + p[j, 2]
        w0, w1, w2 = ov[j, 3], ov[j, 4], ov[j, 5]
        v0 = ov[j, 0] + w1 * c2 - w2 * c1
        v1 = ov[j, 1] + w2 * c0 - w0 * c2
        v2 = ov[j, 2] + w0 * c1 - w1 * c0
        b0 = R[j, 0, 0] * w0 + R[j, 1, 0] * w1 + R[j, 2, 0] * w2
        b1 = R[j, 0, 1] * w0 + R[j, 1, 1] * w1 + R[j, 2, 1] * w2
        b2 = R[j, 0, 2] * w0 + R[j, 1, 2] * w1 + R[j, 2, 2] * w2
        rot = (b0 * (Ic[j, 0, 0] * b0 + Ic[j, 0, 1] * b1 + Ic[j, 0, 2] * b2)
               + b1 * (Ic[j, 1, 0] * b0 + Ic[j, 1, 1] * b1 + Ic[j, 1, 2] * b2)
               + b2 * (Ic[j, 2, 0] * b0 + Ic[j, 2, 1] * b1 + Ic[j, 2, 2] * b2))
        ek += 0.5 * mass[j] * (v0 * v0 + v1 * v1 + v2 * v2) + 0.5 * rot
        ep -= mass[j] * (c0 * g[0] + c1 * g[1] + c2 * g[2])
    return ek, ep
