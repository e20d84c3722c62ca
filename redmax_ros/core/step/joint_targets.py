"""Target configuration and velocity of a joint whose configuration is not a plain vector (issue 13 item 3),
for the trajectory law of step/trajectory.py on the configuration manifold.

A trajectory gives one position function per velocity DOF in the convention of model/dof_positions.py
(the joint_states positions, and the scene files' q0): roll, pitch, yaw [rad] for a quaternion rotation
(R = Rz(yaw) Ry(pitch) Rx(roll)); x, y [m], theta [rad] for ``planar``; x, y, z [m] then roll, pitch, yaw
for a FreeFlyer (``free``, URDF floating bases); composites (``free3d``) sub-joint by sub-joint. From the
positions p(t) and their rates pdot(t) (exact derivatives of the time functions) :func:`target` gives

* the joint configuration q_p (unit quaternion, (cos, sin), ...) and
* the target velocity v_p in the joint's velocity convention (notes §2.5.5/2.5.8/2.5.11: Pinocchio's
  joint-local velocities):

  - quaternion rotation: the body angular velocity omega_b = E_b(rpy) rpy_dot, from R^T Rdot = [omega_b]x
    with R = Rz(y) Ry(p) Rx(r) (the local-frame roll-pitch-yaw Jacobian, pin.rpy.computeRpyJacobian LOCAL):

        omega_b = [ rdot - sin p ydot,
                    cos r pdot + sin r cos p ydot,
                   -sin r pdot + cos r cos p ydot ];

  - FreeFlyer: [R^T xyz_dot; omega_b] (linear velocity of the joint origin in the joint frame);
  - planar: [R(theta)^T (xdot, ydot); theta_dot] (Pinocchio's planar velocity is joint-local);
  - joints whose positions are coordinates (nq = nv; translation parts of composites): p_dot itself;
    unbounded revolute ((cos, sin), nq = 2, nv = 1): theta_dot.

The trajectory's row is then qdot+ = v_p(t_k+1) + b log(q_k^-1 q_p(t_k+1)), the log being
pin.difference restricted to the joint (the Lie-group error of q_p relative to q_k in the same local
velocity coordinates; paper Eq. 7's prescribed row *G_r qdot_r = *qdot_r).
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from redmax_ros.core.spatial import rpy_matrix


def body_rates(rpy, rpy_dot) -> np.ndarray:
    """Body angular velocity omega_b (3,) [rad/s] of R(t) = Rz(yaw) Ry(pitch) Rx(roll) from the rpy rates."""
    r, p, _ = rpy
    rd, pd, yd = rpy_dot
    sr, cr, sp, cp = math.sin(r), math.cos(r), math.sin(p), math.cos(p)
    return np.array([rd - sp * yd, cr * pd + sr * cp * yd, -sr * pd + cr * cp * yd])


def supported(jm) -> bool:
    """Whether :func:`target` handles the Pinocchio joint model ``jm`` (composites: every sub-joint)."""
    short = jm.shortname()
    if short == "JointModelComposite":
        return all(supported(s) for s in jm.extract().joints)
    return short in ("JointModelSpherical", "JointModelFreeFlyer", "JointModelPlanar") or jm.nq == jm.nv or (
        jm.nq, jm.nv) == (2, 1)


def target(jm, pos, rate) -> tuple:
    """(q_p (nq,), v_p (nv,)) of joint model ``jm`` at per-DOF positions ``pos`` (nv,) with rates ``rate``."""
    q, v = np.empty(jm.nq), np.empty(jm.nv)
    _fill(jm, np.asarray(pos, float), np.asarray(rate, float), q, v, 0, 0)
    return q, v


def _fill(jm, pos, rate, q, v, iq, iv):
    short = jm.shortname()
    p, pd = pos[iv:iv + jm.nv], rate[iv:iv + jm.nv]
    if short == "JointModelComposite":
        for s in jm.extract().joints:
            _fill(s, pos, rate, q, v, iq, iv)
            iq += s.nq
            iv += s.nv
    elif short == "JointModelSpherical":
        q[iq:iq + 4] = pin.Quaternion(rpy_matrix(p)).coeffs()
        v[iv:iv + 3] = body_rates(p, pd)
    elif short == "JointModelFreeFlyer":
        R = rpy_matrix(p[3:])
        q[iq:iq + 3] = p[:3]
        q[iq + 3:iq + 7] = pin.Quaternion(R).coeffs()
        v[iv:iv + 3] = R.T @ pd[:3]
        v[iv + 3:iv + 6] = body_rates(p[3:], pd[3:])
    elif short == "JointModelPlanar":
        c, s = math.cos(p[2]), math.sin(p[2])
        q[iq:iq + 4] = (p[0], p[1], c, s)
        v[iv:iv + 3] = (c * pd[0] + s * pd[1], -s * pd[0] + c * pd[1], pd[2])
    elif jm.nq == jm.nv:
        q[iq:iq + jm.nq] = p
        v[iv:iv + jm.nv] = pd
    elif (jm.nq, jm.nv) == (2, 1):
        q[iq:iq + 2] = (math.cos(p[0]), math.sin(p[0]))
        v[iv] = pd[0]
    else:
        raise ValueError(f"no trajectory target for {short} (nq {jm.nq}, nv {jm.nv})")


def joint_error(model, jid: int, q, q_joint) -> np.ndarray:
    """log(q_k^-1 q_p) (nv,) of joint ``jid``: pin.difference from the configuration ``q`` to ``q`` with the
    joint's entries replaced by ``q_joint`` (only the joint's own entries differ, so only its velocity
    entries are non-zero)."""
    jm = model.joints[jid]
    qt = np.array(q, float)
    qt[jm.idx_q:jm.idx_q + jm.nq] = q_joint
    return pin.difference(model, q, qt)[jm.idx_v:jm.idx_v + jm.nv]
