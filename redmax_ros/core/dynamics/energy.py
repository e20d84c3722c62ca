"""Energy diagnostics [J]: kinetic (incl. armature), gravitational, spring (maximal + joint)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.forces import joint_displacement
from redmax_ros.core.dynamics.kinematics import site_positions


def energies(mech, data, q, v_r):
    """(E_kin, E_pot, E_spring) at (q, v_r). Leaves forward kinematics of q in data."""
    ek = pin.computeKineticEnergy(mech.model, data, q, v_r)  # also runs forward kinematics
    if mech.has_armature:
        ek += 0.5 * float(mech.armature @ (v_r * v_r))
    ep = pin.computePotentialEnergy(mech.model, data)
    X = site_positions(mech, data, mech.jac_sites) if len(mech.spring_ab) else None
    es = spring_energy(mech, X, q)
    if mech.extras is not None:  # direction springs (catalogue.py)
        es += mech.extras.energy(mech, data)
    return float(ek), float(ep), es


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
