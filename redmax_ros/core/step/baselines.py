"""Explicit reduced-coordinate baselines on Pinocchio's ABA (STAR §4 reduced coordinates):
semi-implicit (symplectic) Euler and classical RK4, with the same forces as Eq. (2) evaluated
explicitly. For tree scenes without couplings or loops (pin.aba has neither). ``ws``: a
step.workspace.Workspace with pin.Data (``Workspace(mech, pin_data=True)``).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.springs import joint_displacement, spring_terms
from redmax_ros.core.dynamics.kinematics import site_jacobians
from redmax_ros.core.dynamics.energy import energies


def _check(mech):
    if mech.T is not None or len(mech.loop_ab):
        raise ValueError("explicit ABA baselines support tree scenes without couplings or loops")


def applied_force(mech, ws, q, v, tau=None) -> np.ndarray:
    """All non-inertial generalized forces [N m] except gravity/Coriolis (which ABA adds):
    joint torques, joint springs/dampers, maximal springs/dampers (J^T f), evaluated at (q, v)."""
    f = mech.torque0.copy() if tau is None else mech.torque0 + tau
    f -= mech.damping * v
    if mech.has_stiffness:
        f -= mech.stiffness * joint_displacement(mech, q)
    if len(mech.spring_ab):
        pin.computeJointJacobians(mech.model, ws.data, q)
        X, J = site_jacobians(mech, ws, mech.jac_sites)
        fs, _, D, Jd, _ = spring_terms(mech, X, J, v)  # explicit (implicit: false) dampers already in fs, D = 0
        vrel = np.einsum("pin,n->pi", Jd, v)
        fs = fs - np.einsum("pij,pj->pi", D, vrel)  # damper force -c (u.v) u
        f += np.einsum("pin,pi->n", Jd, fs)
    return f


def acceleration(mech, ws, q, v, tau=None) -> np.ndarray:
    """qddot = ABA(q, v, applied forces) (Featherstone's articulated-body algorithm, via Pinocchio)."""
    return pin.aba(mech.model, ws.data, q, v, applied_force(mech, ws, q, v, tau)).copy()


def semi_implicit_euler(mech, ws, q, v, h, tau=None):
    """v+ = v + h qddot(q, v);  q+ = q (+) h v+."""
    _check(mech)
    v1 = v + h * acceleration(mech, ws, q, v, tau)
    return pin.integrate(mech.model, q, h * v1), v1


def rk4(mech, ws, q, v, h, tau=None):
    """Classical fourth-order Runge-Kutta on (q, v), with q updated on the manifold."""
    _check(mech)
    model = mech.model

    def f(qq, vv):
        return vv, acceleration(mech, ws, qq, vv, tau)

    k1q, k1v = f(q, v)
    k2q, k2v = f(pin.integrate(model, q, 0.5 * h * k1q), v + 0.5 * h * k1v)
    k3q, k3v = f(pin.integrate(model, q, 0.5 * h * k2q), v + 0.5 * h * k2v)
    k4q, k4v = f(pin.integrate(model, q, h * k3q), v + h * k3v)
    dq = (k1q + 2 * k2q + 2 * k3q + k4q) / 6.0
    dv = (k1v + 2 * k2v + 2 * k3v + k4v) / 6.0
    return pin.integrate(model, q, h * dq), v + h * dv


def mechanical_energy(mech, ws, q, v) -> float:
    """E_kin + E_pot + E_spring [J] of a baseline state (the step's energies, energy.py)."""
    return float(sum(energies(mech, ws, q, v)))
