"""One position number per velocity DOF, for joint_states (and any per-DOF report of q).

A joint whose configuration has as many entries as velocity DOFs (revolute, prismatic, universal,
translational, the Euler charts, free2d, the coordinate joints of spline/exp joints) reports q itself.
The others, where q is not a list of per-DOF coordinates (notes §2.5.5/2.5.8/2.5.11: the rotation is a
unit quaternion and the velocity the body angular velocity), report:

* quaternion rotation (``spherical``, the rotation of ``free``/``free3d``, a ``spherical_exp`` carrier):
  **roll, pitch, yaw** [rad] of the joint rotation, R = Rz(yaw) Ry(pitch) Rx(roll) — the values a scene
  file gives as ``q0`` for these joints, so a freshly loaded scene reports its file's q0. Ranges:
  roll, yaw in [-pi, pi], pitch in [-pi/2, pi/2], exactly Pinocchio's ``rpy.matrixToRpy`` (which also
  decides the split of roll and yaw at gimbal lock, |pitch| = pi/2). These numbers are not integrals of
  the reported velocities (body angular velocity);
* ``planar`` (q = x, y, cos th, sin th): x, y [m], th = atan2(sin, cos) [rad];
* ``free``/``free3d``/FreeFlyer carriers: x, y, z [m] of the joint origin, then roll, pitch, yaw.

Composite joints are handled sub-joint by sub-joint. The plan is built once per scene (from the
Pinocchio model, or from the joint types of a SceneDescription) and applied per message in O(n).
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

_LOCK = 1e-3  # |pitch| within this of pi/2: Pinocchio decides (non-unique roll/yaw split)


class DofPositions:
    """Per-DOF positions of a configuration q: ``plan(q) -> (nv,)``."""

    def __init__(self, nv: int, copy_dst=(), copy_src=(), quat_dst=(), quat_src=(), ang_dst=(), ang_src=()):
        self.nv = nv
        self.copy_dst, self.copy_src = np.array(copy_dst, int), np.array(copy_src, int)
        self.quat_dst, self.quat_src = np.array(quat_dst, int), np.array(quat_src, int)  # first DOF / first q
        self.ang_dst, self.ang_src = np.array(ang_dst, int), np.array(ang_src, int)  # DOF / q index of cos
        self.identity = (len(self.quat_dst) == 0 and len(self.ang_dst) == 0
                         and np.array_equal(self.copy_dst, np.arange(nv)) and np.array_equal(self.copy_src, np.arange(nv)))

    def __call__(self, q) -> np.ndarray:
        q = np.asarray(q, float)
        if self.identity and len(q) == self.nv:
            return q
        out = np.full(self.nv, np.nan)
        out[self.copy_dst] = q[self.copy_src]
        if len(self.ang_dst):
            out[self.ang_dst] = np.arctan2(q[self.ang_src + 1], q[self.ang_src])
        if len(self.quat_dst):
            quats = q[self.quat_src[:, None] + np.arange(4)]
            out[self.quat_dst[:, None] + np.arange(3)] = quat_to_rpy(quats)
        return out

    # -- construction
    @classmethod
    def from_model(cls, model) -> "DofPositions":
        """Plan for a Pinocchio model (every joint, composites recursively)."""
        acc = ([], [], [], [], [], [])
        for jid in range(1, model.njoints):
            jm = model.joints[jid]
            _add_joint(acc, jm, jm.idx_q, jm.idx_v)
        return cls(model.nv, *acc)

    @classmethod
    def from_description(cls, d) -> "DofPositions":
        """Plan from a SceneDescription: its ``dof_positions`` when present (Simulator.describe builds it
        from the model), else from the joint types and sizes (composites with quaternion or planar
        sub-joints then report NaN for those DOFs)."""
        plan = getattr(d, "dof_positions", None)
        if plan is not None:
            return plan
        acc = ([], [], [], [], [], [])
        iq = iv = 0
        for jt, nq, nv in zip(d.joint_types, d.joint_nq, d.joint_nv):
            nq, nv = int(nq), int(nv)
            if nq == nv:
                _copy(acc, iq, iv, nv)
            elif jt == "planar" and (nq, nv) == (4, 3):
                _copy(acc, iq, iv, 2)
                _angle(acc, iq + 2, iv + 2)
            elif (nq, nv) == (4, 3) and jt in ("spherical", "carrier"):
                _quat(acc, iq, iv)
            elif (nq, nv) == (7, 6) and jt in ("free", "free3d", "carrier"):
                _copy(acc, iq, iv, 3)
                _quat(acc, iq + 3, iv + 3)
            iq += nq
            iv += nv
        return cls(iv, *acc)


def quat_to_rpy(quats) -> np.ndarray:
    """(n, 4) quaternions (x, y, z, w; normalised here) -> (n, 3) roll, pitch, yaw [rad] with
    R = Rz(yaw) Ry(pitch) Rx(roll): the values of pinocchio.rpy.matrixToRpy (scalar math, ~1 us per
    quaternion; Pinocchio itself within 1e-3 rad of gimbal lock)."""
    Q = np.asarray(quats, float).reshape(-1, 4)
    out = np.empty((len(Q), 3))
    for i, (x, y, z, w) in enumerate(Q.tolist()):
        n = 1.0 / math.sqrt(x * x + y * y + z * z + w * w)
        x, y, z, w = x * n, y * n, z * n, w * n
        r20, r21, r22 = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
        pitch = math.atan2(-r20, math.hypot(r21, r22))
        if abs(abs(pitch) - math.pi / 2) < _LOCK:  # the roll/yaw split is not unique: Pinocchio's choice
            out[i] = pin.rpy.matrixToRpy(pin.Quaternion(w, x, y, z).matrix())
        else:
            out[i] = (math.atan2(r21, r22), pitch, math.atan2(2 * (x * y + z * w), 1 - 2 * (y * y + z * z)))
    return out


def _copy(acc, iq, iv, n):
    acc[0].extend(range(iv, iv + n))
    acc[1].extend(range(iq, iq + n))


def _quat(acc, iq, iv):
    acc[2].append(iv)
    acc[3].append(iq)


def _angle(acc, iq, iv):
    acc[4].append(iv)
    acc[5].append(iq)


def _add_joint(acc, jm, iq, iv):
    short = jm.shortname()
    if short == "JointModelComposite":
        for sub in jm.extract().joints:
            _add_joint(acc, sub, iq, iv)
            iq += sub.nq
            iv += sub.nv
    elif short == "JointModelSpherical":
        _quat(acc, iq, iv)
    elif short == "JointModelFreeFlyer":
        _copy(acc, iq, iv, 3)
        _quat(acc, iq + 3, iv + 3)
    elif short == "JointModelPlanar":
        _copy(acc, iq, iv, 2)
        _angle(acc, iq + 2, iv + 2)
    elif jm.nq == jm.nv:
        _copy(acc, iq, iv, jm.nv)
    # any other joint with nq != nv: NaN (none is used by the scene loader)
