"""Small SE(3) helpers (SI units: metres, radians)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin


def rpy_matrix(rpy) -> np.ndarray:
    """Rotation matrix from roll-pitch-yaw [rad] (R = Rz(yaw) Ry(pitch) Rx(roll), URDF convention)."""
    return pin.rpy.rpyToMatrix(np.asarray(rpy, dtype=float))


def placement(pos=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0)) -> pin.SE3:
    """SE(3) placement from a position [m] and roll-pitch-yaw [rad]."""
    return pin.SE3(rpy_matrix(rpy), np.asarray(pos, dtype=float))


def skew(x: np.ndarray) -> np.ndarray:
    """[x]× such that skew(x) @ y = x × y."""
    return np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix."""
    return pin.Quaternion(R).coeffs().copy()
