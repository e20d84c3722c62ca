"""Message conversion without ROS communication: joint_states positions per DOF."""
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("redmax_msgs.msg", reason="redmax_msgs not built (scripts/setup.sh builds msg_defs/)")

from redmax_ros.node.convert import SceneInfo  # noqa: E402


def _desc(types, nq, nv):
    names = [f"j{i}" for i in range(len(types))]
    vnames = [n if v == 1 else f"{n}[{k}]" for n, v in zip(names, nv) for k in range(v)]
    return SimpleNamespace(name="x", dt=1e-3, joint_names=names, joint_types=types, joint_nq=nq, joint_nv=nv,
                           velocity_names=vnames, position_names=[], sites=[], bodies=[], prescribable_joints=[],
                           prescribable_sites=[], nq=sum(nq), nv=sum(nv), ndof=sum(nv))


def test_positions_planar_angle_and_rpy_for_spherical():
    """Planar joints report x, y, angle; quaternion joints roll, pitch, yaw (R = Rz Ry Rx), never NaN."""
    import pinocchio as pin
    info = SceneInfo(_desc(["planar", "revolute", "spherical", "universal", "free"], [4, 1, 4, 2, 7], [3, 1, 3, 2, 6]))
    a, rpy = 0.3, np.array([0.2, -0.4, 1.1])
    quat = pin.Quaternion(pin.rpy.rpyToMatrix(rpy)).coeffs()
    q = np.concatenate([[1.0, 2.0, np.cos(a), np.sin(a), 0.7], quat, [0.1, 0.2, 3.0, 4.0, 5.0], quat])
    p = info.positions(q)
    assert len(p) == 15
    assert np.allclose(p[:3], [1.0, 2.0, a]) and p[3] == 0.7
    assert np.abs(p[4:7] - rpy).max() < 1e-12 and np.array_equal(p[7:9], [0.1, 0.2])
    assert np.array_equal(p[9:12], [3.0, 4.0, 5.0]) and np.abs(p[12:] - rpy).max() < 1e-12
    assert info.dof_index["j2[1]"] == ("j2", 1) and info.dof_index["j1"] == ("j1", 0)


def test_positions_identity_when_nq_equals_nv():
    info = SceneInfo(_desc(["revolute", "universal"], [1, 2], [1, 2]))
    q = np.array([0.1, 0.2, 0.3])
    assert info.positions(q) is q or np.array_equal(info.positions(q), q)


def test_body_command_translation_and_prescribed_bodies_message():
    """BodyTwistCommand -> the core's prescription (NaN = None = free; frame from header.frame_id), and the
    core's prescribed_bodies() -> BodyTwists with NaN where free; errors name the body and the problem."""
    import math

    from geometry_msgs.msg import Twist, Vector3

    from redmax_msgs.msg import BodyTwistCommand
    from redmax_ros.node.convert import CommandRejected, body_command, body_prescriptions_msg

    desc = SimpleNamespace(name="s", bodies=["a", "b"])
    nan = math.nan
    m = BodyTwistCommand(bodies=["b"], twists=[Twist(angular=Vector3(x=nan, y=2.0, z=nan),
                                                     linear=Vector3(x=0.5, y=nan, z=nan))])
    for fid, frame in (("", "world"), ("world", "world"), ("body", "body")):
        m.header.frame_id = fid
        assert body_command(m, desc) == {"b": {"angular": [None, 2.0, None], "linear": [0.5, None, None],
                                               "frame": frame}}
    m.header.frame_id = "b"
    with pytest.raises(CommandRejected, match="frame 'b' is not supported"):
        body_command(m, desc)
    m.header.frame_id = ""
    m.bodies = ["c"]
    with pytest.raises(CommandRejected, match="unknown body 'c' in scene 's'"):
        body_command(m, desc)
    msg = body_prescriptions_msg(1.5, {"a": {"components": ["wz", "vx"], "values": np.array([1.0, -2.0]),
                                             "frame": "body"}}, "map")
    assert list(msg.bodies) == ["a"] and list(msg.frames) == ["body"] and msg.header.frame_id == "map"
    tw = msg.twists[0]
    assert (tw.angular.z, tw.linear.x) == (1.0, -2.0)
    assert all(math.isnan(x) for x in (tw.angular.x, tw.angular.y, tw.linear.y, tw.linear.z))
    assert msg.header.stamp.sec == 1 and msg.header.stamp.nanosec == 500_000_000
