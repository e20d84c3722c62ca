"""The joint catalogue of RedMax (Sueda's notes §2.5) on Pinocchio.

Every joint of the notes is described twice here:

1. **Reference kinematics** (functions ``ref_*``): the joint transform Q(q), the joint Jacobian S(q)
   and its time derivative Sdot(q, qdot) written from the notes' formulas (Eq. 2.24: S q = log Q,
   ``[S_j] = Q^-1 dQ/dq_j``). They are used by the tests (finite differences of Q, and comparison with
   the Pinocchio joint that the model actually uses: ``JointData.M == Q``, ``JointData.S == S``,
   ``JointData.c == Sdot qdot``) and, for the joints Pinocchio lacks, by the dynamics itself
   (:mod:`redmax_ros.core.joint_maps`).
2. **The Pinocchio joint model** used in the compiled model (:func:`pin_joint_model`).

Conventions. Twists are in Pinocchio's order (linear first): ``xi = (v, w)``; the notes write
``(w, v)``, so the notes' ``S = (0 0 1 0 0 0)^T`` of a z revolute joint is ``(0 0 0 0 0 1)^T`` here.
S is the body (child joint frame) Jacobian: the relative twist of the joint is ``S qdot`` expressed in
the joint's own frame, as in the notes (Eq. 2.9) and in Pinocchio (``JointData.S``).

Catalogue (scene-file ``type`` -> notes section -> Pinocchio joint):

=====================  =======  ===========================================================================
type                   DOF      realisation
=====================  =======  ===========================================================================
fixed                  0        §2.5.1; bodies merged (no Pinocchio joint)
prismatic              1        §2.5.2; PX/PY/PZ or PrismaticUnaligned
planar_translation     2        §2.5.3 (the notes' "planar joint": Q = [I, B q]); Composite(P_a1, P_a2)
translational          3        §2.5.4; Translation
spherical              3        §2.5.5/§2.5.8 via Pinocchio's unit quaternion (see below); Spherical
spherical_euler        3        §2.5.5 three-angle charts (XYZ default, any Euler/Tait-Bryan chart);
                                Composite(R_a1, R_a2, R_a3); with switch_charts: coordinate map onto a
                                Spherical carrier, chart switched near gimbal lock (euler_charts.py)
spherical_exp          3        §2.5.8 exponential coordinates with Grassia's reparameterisation;
                                coordinate map onto a quaternion Spherical carrier (joint_maps.py)
universal              2        §2.5.6; Universal(a1, a2) (R = exp(a1 q1) exp(a2 q2))
revolute               1        §2.5.7; RX/RY/RZ or RevoluteUnaligned
composite              sum      §2.5.9; Composite of the listed sub-joints (each with its placement)
free2d                 3        §2.5.10 (planar XY then revolute Z); Composite(PX, PY, RZ)
planar                 3        Pinocchio's Planar: the same motion as free2d, but with body-frame
                                velocities (vx, vy in the moving frame); kept for existing scenes
free3d                 6        §2.5.11 (translational then spherical); Composite(Translation, Spherical):
                                world(parent)-frame linear velocity, body-frame angular velocity
free3d_exp             6        §2.5.11 in reverse order (Eq. 2.65-2.66): exponential-coordinate rotation r
                                (§2.5.8) then a translation t in the rotated frame; coordinate map onto a
                                FreeFlyer carrier (joint_maps.py), Grassia's reparameterisation of r
free                   6        Pinocchio's FreeFlyer: body-frame twist (v, w)
spline_curve           1        §2.5.12 (Lee & Terzopoulos 2008); coordinate map (joint_maps.py)
spline_surface         2        §2.5.13; coordinate map (joint_maps.py)
=====================  =======  ===========================================================================

Spherical joints and Pinocchio's quaternion. Pinocchio stores a spherical joint as a unit quaternion
and its velocity as the body angular velocity w, with S = (0; I) constant and Sdot = 0, and
integrates ``R+ = R exp([h w])``. In the notes' terms this is the exponential-coordinate joint of
§2.5.8 re-centred at every step: the exponential coordinates of the step increment are ``h w`` (always
far from the singular shell ||q|| = 2 pi), and the notes' remark after Eq. 2.50 ("we are constantly
re-parameterizing") applies. ``spherical`` is therefore the default and the cheapest choice.
``spherical_exp`` keeps the notes' global exponential coordinates q (R = exp([q])) as the joint's
generalized coordinates, with S(q) of Eq. 2.48-2.49 and Sdot of Eq. 2.52, reparameterised by
q <- (1 - 2 pi/||q||) q when ||q|| > pi [Grassia 1998]; it is realised as a coordinate map
qdot_pin = S(q) qdot on a quaternion carrier joint (see joint_maps.py). ``spherical_euler`` is the
notes' 3-parameter chart (Eq. 2.33-2.37 for XYZ) as a Pinocchio composite of three revolute joints;
it has the chart's singularity (q2 = ±pi/2 for Tait-Bryan charts, q2 = 0, pi for proper Euler
charts) where S, and therefore the mass matrix, become singular. A Pinocchio model's joint types are
fixed once built, so with ``switch_charts: true`` the joint is instead realised as a coordinate map on a
quaternion carrier (joint_maps.py), like ``spherical_exp``, and changes chart near the singularity
(Eq. 2.40; euler_charts.py). ``free3d_exp`` is the notes' 3D free joint concatenated in reverse order
(§2.5.11, Eq. 2.65-2.66): the exponential-coordinate rotation r first, then a translation t in the
rotated frame, realised as a coordinate map on a FreeFlyer carrier; Grassia's map acts on r only.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from redmax_ros.core.spatial import placement, rpy_matrix

# ----------------------------------------------------------------------------------------------
# small spatial helpers (Pinocchio ordering: linear first)

_AX = {"X": np.array([1.0, 0.0, 0.0]), "Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}
EULER_CHARTS = ("XYX", "XZX", "YZY", "YXY", "ZXZ", "ZYZ", "XYZ", "XZY", "YZX", "YXZ", "ZXY", "ZYX")


def skew(w) -> np.ndarray:
    """[w]: the 3x3 cross-product matrix (notes Eq. 1.6)."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def Ad(M: pin.SE3) -> np.ndarray:
    """6x6 adjoint of M (Pinocchio order): the twist in the frame of M's target, seen in M's source."""
    return M.action


def ad(xi) -> np.ndarray:
    """6x6 ad of a twist (Pinocchio order): ad(xi) eta = xi x eta (Motion cross product)."""
    return pin.Motion(np.asarray(xi, float)).action


def exp6(xi) -> pin.SE3:
    return pin.exp6(pin.Motion(np.asarray(xi, float)))


def log6(M: pin.SE3) -> np.ndarray:
    return pin.log6(M).vector


def twist_lin(a) -> np.ndarray:
    """The twist of a unit translation along a (Pinocchio order: (a, 0))."""
    return np.concatenate([np.asarray(a, float), np.zeros(3)])


def twist_ang(a) -> np.ndarray:
    """The twist of a unit rotation about a through the origin (Pinocchio order: (0, a))."""
    return np.concatenate([np.zeros(3), np.asarray(a, float)])


def from_notes(S_notes: np.ndarray) -> np.ndarray:
    """Reorder rows of a notes-convention S (angular first) into Pinocchio's order (linear first)."""
    S_notes = np.asarray(S_notes, float)
    return np.concatenate([S_notes[3:6], S_notes[0:3]], axis=0)


# ----------------------------------------------------------------------------------------------
# reference kinematics (notes §2.5): each returns (Q: SE3, S: (6,n), Sdot: (6,n))


def ref_fixed():
    """§2.5.1: Q = I, S is 6x0."""
    return pin.SE3.Identity(), np.zeros((6, 0)), np.zeros((6, 0))


def ref_prismatic(a, q, qd=0.0):
    """§2.5.2, Eq. 2.25-2.26: Q = [I, a q; 0, 1], S = (a; 0) (notes: (0; a)), Sdot = 0."""
    a = np.asarray(a, float)
    return pin.SE3(np.eye(3), a * float(np.atleast_1d(q)[0])), twist_lin(a)[:, None], np.zeros((6, 1))


def ref_planar_translation(B, q, qd=None):
    """§2.5.3, Eq. 2.27-2.28: Q = [I, B q; 0, 1] with B (3x2) the two directions, S = (B; 0), Sdot = 0."""
    B = np.asarray(B, float).reshape(3, 2)
    S = np.zeros((6, 2))
    S[:3] = B
    return pin.SE3(np.eye(3), B @ np.asarray(q, float)), S, np.zeros((6, 2))


def ref_translational(q, qd=None):
    """§2.5.4, Eq. 2.29-2.30: Q = [I, q; 0, 1], S = (I; 0), Sdot = 0."""
    S = np.zeros((6, 3))
    S[:3] = np.eye(3)
    return pin.SE3(np.eye(3), np.asarray(q, float)), S, np.zeros((6, 3))


def ref_revolute(a, q, qd=0.0):
    """§2.5.7, Eq. 2.45-2.46: Q = exp([S q]), S = (0; a) (notes: (a; 0)), Sdot = 0."""
    a = np.asarray(a, float)
    return pin.SE3(pin.exp3(a * float(np.atleast_1d(q)[0])), np.zeros(3)), twist_ang(a)[:, None], np.zeros((6, 1))


def ref_spherical_quat(quat_xyzw, w=None):
    """Pinocchio's spherical joint: Q = R(quat), S = (0; I), Sdot = 0 (velocity = body angular velocity)."""
    R = pin.Quaternion(np.asarray(quat_xyzw, float)).normalized().matrix()
    S = np.zeros((6, 3))
    S[3:] = np.eye(3)
    return pin.SE3(R, np.zeros(3)), S, np.zeros((6, 3))


def ref_compose(parts):
    """§2.5.9 composite joint, Eq. 2.53-2.58, for a chain of sub-joints.

    ``parts``: list of (P_i: SE3 placement, Q_i: SE3, S_i (6,n_i), Sdot_i (6,n_i), qdot_i (n_i,)); the
    composite transform is Q = (P_1 Q_1)(P_2 Q_2)...; for two parts S = [Ad(T_2^-1) S_1, S_2] and
    Sdot = [-ad(S_2 qdot_2) Ad(T_2^-1) S_1 + Ad(T_2^-1) Sdot_1, Sdot_2] with T_2 = P_2 Q_2 (the constant
    placement does not change the body Jacobian of T_2). Longer chains fold left: Q_1 (Q_2 Q_3) ...
    """
    P, Q, S, Sd, qd = parts[0]
    T = P * Q
    S, Sd, qd = np.asarray(S, float), np.asarray(Sd, float), np.atleast_1d(np.asarray(qd, float))
    for P2, Q2, S2, Sd2, qd2 in parts[1:]:
        T2 = P2 * Q2
        S2, Sd2, qd2 = np.asarray(S2, float), np.asarray(Sd2, float), np.atleast_1d(np.asarray(qd2, float))
        A = Ad(T2.inverse())
        AS = A @ S
        Sd = np.hstack([-ad(S2 @ qd2) @ AS + A @ Sd, Sd2])
        S = np.hstack([AS, S2])
        qd = np.concatenate([qd, qd2])
        T = T * T2
    return T, S, Sd


def ref_euler(chart, q, qd):
    """§2.5.5: three-angle chart R = exp(a1 q1) exp(a2 q2) exp(a3 q3) (e.g. XYZ: Eq. 2.33), with S and
    Sdot from the composite rule (for XYZ these are Eq. 2.36-2.37; the other charts are Tables 1-2)."""
    q, qd = np.asarray(q, float), np.asarray(qd, float)
    parts = []
    for k, c in enumerate(chart.upper()):
        Qk, Sk, Sdk = ref_revolute(_AX[c], q[k])
        parts.append((pin.SE3.Identity(), Qk, Sk, Sdk, qd[k:k + 1]))
    return ref_compose(parts)


def ref_euler_xyz_closed(q, qd):
    """Eq. 2.33, 2.36, 2.37 exactly as printed in the notes (XYZ chart), reordered to Pinocchio's order."""
    q1, q2, q3 = q
    _, qd2, qd3 = qd
    c1, c2, c3, s1, s2, s3 = np.cos(q1), np.cos(q2), np.cos(q3), np.sin(q1), np.sin(q2), np.sin(q3)
    R = np.array([[c2 * c3, -c2 * s3, s2],
                  [c1 * s3 + c3 * s1 * s2, c1 * c3 - s1 * s2 * s3, -c2 * s1],
                  [s1 * s3 - c1 * c3 * s2, c3 * s1 + c1 * s2 * s3, c1 * c2]])
    Sn = np.zeros((6, 3))
    Sn[:3] = [[c2 * c3, s3, 0], [-c2 * s3, c3, 0], [s2, 0, 1]]
    Sdn = np.zeros((6, 3))
    Sdn[:3] = [[-qd2 * c3 * s2 - qd3 * c2 * s3, qd3 * c3, 0],
               [qd2 * s2 * s3 - qd3 * c2 * c3, -qd3 * s3, 0],
               [qd2 * c2, 0, 0]]
    return pin.SE3(R, np.zeros(3)), from_notes(Sn), from_notes(Sdn)


def ref_universal(a1, a2, q, qd):
    """§2.5.6: R = exp(a1 q1) exp(a2 q2) (Eq. 2.41 for a1 = x, a2 = y), S and Sdot (Eq. 2.43-2.44)."""
    Q1, S1, Sd1 = ref_revolute(a1, q[0])
    Q2, S2, Sd2 = ref_revolute(a2, q[1])
    I = pin.SE3.Identity()
    return ref_compose([(I, Q1, S1, Sd1, qd[:1]), (I, Q2, S2, Sd2, qd[1:2])])


def ref_free2d(q, qd):
    """§2.5.10: XY planar translation then Z revolute, Eq. 2.59-2.61 (S rows hold Q_2's rows)."""
    I = pin.SE3.Identity()
    B = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    Q1, S1, Sd1 = ref_planar_translation(B, q[:2])
    Q2, S2, Sd2 = ref_revolute([0, 0, 1], q[2])
    return ref_compose([(I, Q1, S1, Sd1, qd[:2]), (I, Q2, S2, Sd2, qd[2:3])])


def ref_free2d_closed(q, qd):
    """Eq. 2.60-2.61 as printed (notes' order), reordered to Pinocchio's order."""
    c, s = math.cos(q[2]), math.sin(q[2])
    Sn = np.zeros((6, 3))
    Sn[2, 2] = 1.0
    Sn[3:5, 0] = [c, -s]
    Sn[3:5, 1] = [s, c]
    Sdn = np.zeros((6, 3))
    Sdn[3:5, 0] = [-qd[2] * s, -qd[2] * c]
    Sdn[3:5, 1] = [qd[2] * c, -qd[2] * s]
    Q = pin.SE3(pin.exp3(np.array([0, 0, q[2]])), np.array([q[0], q[1], 0.0]))
    return Q, from_notes(Sn), from_notes(Sdn)


def ref_free3d(p, quat_xyzw, pd, w):
    """§2.5.11: translational then spherical, Eq. 2.62-2.64: S = [[R^T, 0], [0, I]] (Pinocchio order),
    Sdot = [[-[w] R^T, 0], [0, 0]]."""
    I = pin.SE3.Identity()
    Q1, S1, Sd1 = ref_translational(p)
    Q2, S2, Sd2 = ref_spherical_quat(quat_xyzw)
    return ref_compose([(I, Q1, S1, Sd1, pd), (I, Q2, S2, Sd2, w)])


# -- exponential coordinates (§2.5.8)

def _exp_coeffs(u):
    """a = (1 - cos t)/t^2, b = (t - sin t)/t^3 and their derivatives w.r.t. u = t^2 (series when small)."""
    if u < 1e-2:  # series to u^4: truncation < 1e-15 for t < 0.1
        a = 0.5 - u / 24 + u * u / 720 - u ** 3 / 40320 + u ** 4 / 3628800
        da = -1 / 24 + 2 * u / 720 - 3 * u * u / 40320 + 4 * u ** 3 / 3628800
        b = 1 / 6 - u / 120 + u * u / 5040 - u ** 3 / 362880 + u ** 4 / 39916800
        db = -1 / 120 + 2 * u / 5040 - 3 * u * u / 362880 + 4 * u ** 3 / 39916800
        return a, da, b, db
    t = math.sqrt(u)
    s, c = math.sin(t), math.cos(t)
    a = (1 - c) / u
    b = (t - s) / (u * t)
    # d/du = (1/(2t)) d/dt
    da = (t * s - 2 * (1 - c)) / (u * t) / (2 * t)
    db = ((1 - c) * t - 3 * (t - s)) / (u * u) / (2 * t)
    return a, da, b, db


def exp_jacobian(q, qd=None):
    """(R, S_w, Sdot_w): R = exp([q]) and the 3x3 angular blocks of S and Sdot of the exponential-coordinate
    spherical joint (§2.5.8, Eq. 2.47-2.52), in the closed form S_w = I - a [q] + b [q]^2 (the SO(3)
    right Jacobian; equal to Eq. 2.49's R^T dR/dq_j, see :func:`exp_jacobian_notes`) with coefficients
    evaluated by series near q = 0 (the notes' limit S = I at ||q|| -> 0)."""
    q = np.asarray(q, float)
    qd = np.zeros(3) if qd is None else np.asarray(qd, float)
    u = float(q @ q)
    a, da, b, db = _exp_coeffs(u)
    K, Kd = skew(q), skew(qd)
    K2 = K @ K
    S = np.eye(3) - a * K + b * K2
    ud = 2.0 * float(q @ qd)
    Sd = -a * Kd - da * ud * K + b * (Kd @ K + K @ Kd) + db * ud * K2
    return pin.exp3(q), S, Sd


def exp_jacobian_notes(q, qd):
    """Eq. 2.48-2.52 literally (valid for ||q|| > 0): dR/dq_j = A_j R, A_j = (B_j + C_j) d, B_j = q_j [q],
    C_j = [[q](I - R) e_j], d = 1/(q^T q); [S_j] = R^T A_j R; [Sdot_j] = Rdot^T A_j R + R^T Adot_j R
    + R^T A_j Rdot with Rdot = sum_j A_j R qdot_j (Eq. 2.50)."""
    q, qd = np.asarray(q, float), np.asarray(qd, float)
    R = pin.exp3(q)
    d = 1.0 / float(q @ q)
    K, Kd = skew(q), skew(qd)
    I = np.eye(3)
    A = [(q[j] * K + skew(K @ (I - R) @ I[:, j])) * d for j in range(3)]
    Rd = sum(A[j] @ R * qd[j] for j in range(3))
    dd = -2.0 * float(q @ qd) * d * d
    S, Sd = np.zeros((3, 3)), np.zeros((3, 3))
    for j in range(3):
        Bd = qd[j] * K + q[j] * Kd
        Cd = skew(Kd @ (I - R) @ I[:, j] - K @ Rd @ I[:, j])
        Ad_ = (Bd + Cd) * d + (q[j] * K + skew(K @ (I - R) @ I[:, j])) * dd
        Sj = R.T @ A[j] @ R
        Sdj = Rd.T @ A[j] @ R + R.T @ Ad_ @ R + R.T @ A[j] @ Rd
        S[:, j] = [Sj[2, 1], Sj[0, 2], Sj[1, 0]]
        Sd[:, j] = [Sdj[2, 1], Sdj[0, 2], Sdj[1, 0]]
    return R, S, Sd


def ref_spherical_exp(q, qd):
    """§2.5.8 as a 6 x 3 joint: Q = (exp([q]), 0), S = (0; S_w), Sdot = (0; Sdot_w)."""
    R, Sw, Sdw = exp_jacobian(q, qd)
    S, Sd = np.zeros((6, 3)), np.zeros((6, 3))
    S[3:], Sd[3:] = Sw, Sdw
    return pin.SE3(R, np.zeros(3)), S, Sd


def ref_free3d_exp(q, qd):
    """§2.5.11 in reverse order: Q = Q_1 Q_2 with Q_1 the exponential-coordinate spherical joint of
    §2.5.8 (R = exp([r]), r = q[:3]) and Q_2 the translational joint (t = q[3:], expressed in the
    rotated frame), so Q = (R, R t): the joint origin is at R t in the parent frame [m].

    S of Eq. 2.65 (notes' order: [[S_w, 0], [-[t] S_w, I]]) and Sdot of Eq. 2.66
    ([[Sdot_w, 0], [-[tdot] S_w - [t] Sdot_w, 0]]), here in Pinocchio's order (linear rows first), with
    S_w, Sdot_w the angular blocks of §2.5.8 (:func:`exp_jacobian`). With qdot = (rdot, tdot) the body
    twist is (tdot + w x t, w), w = S_w rdot the body angular velocity [rad/s]. Equal to the composite
    rule (Eq. 2.53-2.58, :func:`ref_compose`) of the two joints."""
    q, qd = np.asarray(q, float), np.asarray(qd, float)
    t, td = q[3:6], qd[3:6]
    R, Sw, Sdw = exp_jacobian(q[:3], qd[:3])
    S, Sd = np.zeros((6, 6)), np.zeros((6, 6))
    S[:3, :3] = -skew(t) @ Sw
    S[:3, 3:] = np.eye(3)
    S[3:, :3] = Sw
    Sd[:3, :3] = -skew(td) @ Sw - skew(t) @ Sdw
    Sd[3:, :3] = Sdw
    return pin.SE3(R, R @ t), S, Sd


def reparameterize_exp(q, qd, threshold=math.pi):
    """Grassia's reparameterisation (§2.5.8): if ||q|| > threshold, q <- (1 - 2 pi/||q||) q (the same
    rotation, ||q_new|| = 2 pi - ||q||) and qdot <- S(q_new)^-1 S(q) qdot (the same angular velocity).
    ``threshold`` in [pi, 2 pi) (scene key reparam_threshold; pi by default, the RedMax reference uses
    1.5 pi): at or above pi the new norm is below it, so the map is applied once. Returns (q, qdot, changed)."""
    q, qd = np.asarray(q, float), np.asarray(qd, float)
    n = float(np.linalg.norm(q))
    if n <= threshold:
        return q, qd, False
    q2 = (1.0 - 2.0 * math.pi / n) * q
    _, S1, _ = exp_jacobian(q)
    _, S2, _ = exp_jacobian(q2)
    return q2, np.linalg.solve(S2, S1 @ qd), True


def reparameterize_free3d_exp(q, qd, threshold=math.pi):
    """Grassia's reparameterisation of the rotation r = q[:3] of a free3d_exp joint
    (:func:`reparameterize_exp`); the translation t = q[3:] and its rate are unchanged: the rotation R
    and the angular velocity w are the same, so the origin R t and the body twist (tdot + w x t, w)
    are too. Returns (q, qdot, changed)."""
    q, qd = np.asarray(q, float), np.asarray(qd, float)
    r2, rd2, changed = reparameterize_exp(q[:3], qd[:3], threshold)
    if not changed:
        return q, qd, False
    return np.concatenate([r2, q[3:]]), np.concatenate([rd2, qd[3:]]), True


# scene type -> reparameterisation of its exponential coordinates (joint_maps.Maps.reparameterize)
REPARAMETERIZE = {"spherical_exp": reparameterize_exp, "free3d_exp": reparameterize_free3d_exp}


# ----------------------------------------------------------------------------------------------
# Pinocchio joint models


def axis_joint(kind: str, axis) -> pin.JointModel:
    """Revolute / prismatic about/along an axis: the aligned RX..PZ models when possible."""
    axis = np.asarray(axis, float)
    for i, c in enumerate("XYZ"):
        e = np.zeros(3)
        e[i] = 1.0
        if np.allclose(axis, e):
            return getattr(pin, f"JointModel{'R' if kind == 'revolute' else 'P'}{c}")()
    return pin.JointModelRevoluteUnaligned(axis) if kind == "revolute" else pin.JointModelPrismaticUnaligned(axis)


def chart_axes(chart: str) -> np.ndarray:
    return np.array([_AX[c] for c in chart.upper()])


def composite(models_and_placements) -> pin.JointModelComposite:
    jc = pin.JointModelComposite()
    for jm, P in models_and_placements:
        jc.addJoint(jm, P)
    return jc


def pin_joint_model(j) -> pin.JointModel:
    """The Pinocchio joint model of a (validated) scene joint of one of the types handled here."""
    t = j.type
    ex = j.extra
    I = pin.SE3.Identity()
    if t == "planar_translation":
        return composite([(axis_joint("prismatic", j.axes[0]), I), (axis_joint("prismatic", j.axes[1]), I)])
    if t == "translational":
        return pin.JointModelTranslation()
    if t == "spherical_euler":
        return composite([(axis_joint("revolute", a), I) for a in chart_axes(ex["chart"])])
    if t == "free2d":
        return composite([(pin.JointModelPX(), I), (pin.JointModelPY(), I), (pin.JointModelRZ(), I)])
    if t == "free3d":
        return composite([(pin.JointModelTranslation(), I), (pin.JointModelSpherical(), I)])
    if t == "composite":
        return composite([(pin_joint_model(sub) if sub.type in NATIVE_TYPES else core_joint_model(sub),
                           _placement(sub.placement)) for sub in ex["parts"]])
    raise AssertionError(t)


def core_joint_model(j):
    """The Pinocchio joint model of a core scene joint (revolute, prismatic, universal, spherical,
    planar, free)."""
    if j.type in ("revolute", "prismatic"):
        return axis_joint(j.type, j.axes[0])
    if j.type == "universal":
        return pin.JointModelUniversal(j.axes[0], j.axes[1])
    if j.type == "spherical":
        return pin.JointModelSpherical()
    if j.type == "planar":
        return pin.JointModelPlanar()
    if j.type == "free":
        return pin.JointModelFreeFlyer()
    raise AssertionError(j.type)


def _placement(pose):
    return placement(*pose)


def configuration(j, vals) -> np.ndarray:
    """Scene-file joint values (see docs/scenes.md) -> the Pinocchio configuration of that joint."""
    t = j.type
    vals = np.asarray(vals, float)
    if t in ("revolute", "prismatic", "universal", "planar_translation", "translational", "spherical_euler",
             "free2d"):
        return vals.copy()
    if t == "spherical":
        return pin.Quaternion(rpy_matrix(vals)).coeffs().copy()
    if t == "planar":
        x, y, th = vals
        return np.array([x, y, np.cos(th), np.sin(th)])
    if t in ("free", "free3d"):
        return np.concatenate([vals[:3], pin.Quaternion(rpy_matrix(vals[3:])).coeffs()])
    if t == "composite":
        out, k = [], 0
        for sub in j.extra["parts"]:
            n = sub.extra.get("nq0", len(sub.q0))
            out.append(configuration(sub, vals[k:k + n]))
            k += n
        return np.concatenate(out) if out else np.zeros(0)
    raise AssertionError(t)


def dof_q_offsets(jm) -> list:
    """For each velocity DOF of a Pinocchio joint model: the offset of the configuration entry whose
    time derivative it is (None when the DOF is not the derivative of one coordinate, e.g. quaternion
    rotations and body-frame velocities of Planar/FreeFlyer). Used for limits and linear constraints."""
    short = jm.shortname()
    if short == "JointModelComposite":
        jc = jm.extract()
        out, oq = [], 0
        for sub in jc.joints:
            out += [None if o is None else oq + o for o in dof_q_offsets(sub)]
            oq += sub.nq
        return out
    if short in ("JointModelPlanar", "JointModelFreeFlyer", "JointModelSpherical"):
        return [None] * jm.nv
    if jm.nq == jm.nv:
        return list(range(jm.nv))
    return [None] * jm.nv


def q_index(model, dof: int):
    """Configuration index of velocity DOF ``dof`` of the model (see :func:`dof_q_offsets`), or None."""
    for jid in range(1, model.njoints):
        jm = model.joints[jid]
        if jm.idx_v <= dof < jm.idx_v + jm.nv:
            o = dof_q_offsets(jm)[dof - jm.idx_v]
            return None if o is None else jm.idx_q + o
    return None


# types whose Pinocchio model is built here (native Pinocchio joints, possibly composite)
NATIVE_TYPES = {"planar_translation", "translational", "spherical_euler", "free2d", "free3d", "composite"}
# types realised as a coordinate map on a carrier joint (joint_maps.py)
MAPPED_TYPES = {"spherical_exp", "free3d_exp", "spline_curve", "spline_surface"}
