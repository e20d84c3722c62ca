"""Joint trajectory prescriptions: the per-step right-hand side of a prescribed joint's rows (hybrid
dynamics, notes §2.10, Eq. 2.114 with the velocity prescribed; paper Eq. 7, *G_r qdot_r = *qdot_r).

A joint that follows a position trajectory q_p(t) (scene/timefunctions.JointTrajectory: time functions and
a gain b [1/s]) keeps the rows of a velocity prescription, the identity on its DOFs projected by J_rR
(dynamics/constraints.py); only their right-hand side changes per step, to the velocity-level law

    *qdot_r = qdot_p(t_k+1) + b (q_p(t_k+1) - q_k)

evaluated at the end time t_k+1 of the step and the configuration q_k at its start. :func:`resolve` turns
Commands.joint_trajectories into Commands.joint_velocities for one step (after the velocity prescriptions,
in command order), so every backend, the divergence checks (step/state.py), loop stabilization and the
required torques (Eq. 7: effort = tau - *G_r^T lam / h) treat them exactly as velocity prescriptions.

Joints whose positions are their coordinates qualify (TRAJECTORY_JOINT_TYPES with nq = nv), and revolute
joints with a (cos, sin) configuration (Pinocchio's unbounded revolute, URDF 'continuous'): their error
q_p - q_k is wrapped to (-pi, pi]. Joints whose configuration is not a vector (MANIFOLD_JOINT_TYPES:
quaternion ``spherical``, ``planar``, ``free``, the composite ``free3d``) take their positions per velocity
DOF in the joint_states convention (roll, pitch, yaw for rotations, model/dof_positions.py) and follow
the same law on the manifold (step/joint_targets.py):

    *qdot_r = v_p(t_k+1) + b log(q_k^-1 q_p(t_k+1))      (pin.difference restricted to the joint)

with v_p the target's velocity in the joint's own velocity coordinates (body angular velocity
omega_b = E_b(rpy) rpy_dot for a quaternion rotation).
"""
from __future__ import annotations

import math

import numpy as np

from redmax_ros.core.step import joint_targets, trajectory_rates

TRAJECTORY_JOINT_TYPES = ("revolute", "prismatic", "universal", "translational", "planar_translation")
MANIFOLD_JOINT_TYPES = ("spherical", "planar", "free", "free3d")  # positions: model/dof_positions.py convention


def trajectory_problem(mech, name: str, traj) -> str | None:
    """Why joint ``name`` cannot follow ``traj`` (a message naming the joint), or None."""
    j = mech.joint_index[name]
    coordinates = j.type in TRAJECTORY_JOINT_TYPES and (j.nq == j.nv or (j.nq, j.nv) == (2, 1))
    manifold = j.type in MANIFOLD_JOINT_TYPES and joint_targets.supported(mech.model.joints[j.jid])
    if not (coordinates or manifold):
        kinds = TRAJECTORY_JOINT_TYPES + MANIFOLD_JOINT_TYPES
        return (f"joint '{name}' ({j.type}) cannot follow a position trajectory "
                f"(trajectories: {', '.join(kinds)} joints)")
    if traj.nv != j.nv:
        return f"trajectory of joint '{name}' needs {j.nv} position function(s), got {traj.nv}"
    return None


def joint_rate(mech, name: str, traj, q, t_next: float) -> np.ndarray:
    """The prescribed velocity (nv,) of joint ``name`` for the step from configuration ``q`` to time t_next."""
    j = mech.joint_index[name]
    if j.type in MANIFOLD_JOINT_TYPES:
        q_p, v_p = joint_targets.target(mech.model.joints[j.jid], traj.position(t_next), traj.velocity(t_next))
        return v_p + traj.b * joint_targets.joint_error(mech.model, j.jid, q, q_p)
    if j.nq == j.nv:
        return traj.rate(t_next, q[j.idx_q:j.idx_q + j.nq])
    c, s = q[j.idx_q], q[j.idx_q + 1]
    return traj.rate(t_next, [math.atan2(s, c)], wrap=True)


def resolve(mech, state, cmd, h: float, q_base=None):
    """Commands for the step of h from ``state`` with every trajectory turned into its velocity row's value
    (a new Commands; ``cmd`` itself unchanged). Commands without trajectories are returned as they are.
    ``q_base``: the configuration the step advances from (BDF2: q^ of step/scheme.py; default state.q)."""
    if not cmd.joint_trajectories:
        return cmd
    t_next = state.time_after(h)
    q = state.q if q_base is None else q_base
    vel = dict(cmd.joint_velocities)
    plan = trajectory_rates.sine_plan(mech, cmd.joint_trajectories, TRAJECTORY_JOINT_TYPES, MANIFOLD_JOINT_TYPES)
    if plan is not None:  # all sines and constants on coordinate joints: one compiled call, the same numbers
        vel.update(trajectory_rates.rates(plan, q, t_next))
    else:
        for name, traj in cmd.joint_trajectories.items():
            vel[name] = joint_rate(mech, name, traj, q, t_next)
    # dataclasses.replace's result without its field introspection (~6 -> ~2 us; Commands has no __post_init__)
    return type(cmd)(**{**cmd.__dict__, "joint_velocities": vel, "joint_trajectories": {}})
