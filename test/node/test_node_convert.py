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


def test_markers_draw_deformable_surfaces_and_active_contacts():
    """markers_msg: a FEM surface as a TRIANGLE_LIST of its faces' vertices, a string as a LINE_LIST of its
    segments, and only the contact rows with an impulse as points with their normals."""
    from visualization_msgs.msg import Marker

    from redmax_ros.core.dynamics.self_collision import ContactReport
    from redmax_ros.node.convert import markers_msg

    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    segs = np.array([[0, 1], [1, 2]])
    rep = ContactReport(candidates=3, rows=2, labels=["a/b", "c/d"], distance=np.array([0.01, -0.001]),
                        point_a=np.array([[0.0, 0, 0], [1.0, 2.0, 3.0]]), point_b=np.zeros((2, 3)),
                        normal=np.array([[0.0, 0, 1], [1.0, 0, 0]]), t_detect=0.0, active=1,
                        impulse=np.array([0.0, 0.5]))
    out = markers_msg(0.1, {}, [], meshes={"block": (X, faces), "rope": (X, segs)}, contacts=rep, scale=0.02)
    by_ns = {m.ns: m for m in out.markers}
    tri, line = by_ns["deformable/block"], by_ns["deformable/rope"]
    assert tri.type == Marker.TRIANGLE_LIST and line.type == Marker.LINE_LIST
    assert np.array_equal([[p.x, p.y, p.z] for p in tri.points], X[faces.ravel()])
    assert np.array_equal([[p.x, p.y, p.z] for p in line.points], X[segs.ravel()])
    pts, nrm = by_ns["contacts"], by_ns["contact_normals"]
    assert [[p.x, p.y, p.z] for p in pts.points] == [[1.0, 2.0, 3.0]]  # the row with an impulse only
    assert np.allclose([[p.x, p.y, p.z] for p in nrm.points], [[1.0, 2.0, 3.0], [1.04, 2.0, 3.0]])


def test_markers_draw_a_capsule_as_a_cylinder_and_two_end_spheres():
    from visualization_msgs.msg import Marker

    from redmax_ros.core.model.collision import ShapePose
    from redmax_ros.node.convert import markers_msg

    s = 0.5 ** 0.5  # a quarter turn about y: local z along world x
    cap = ShapePose("left", "capsule", (0.1, 0.1, 0.2), np.array([1.0, 2.0, 3.0]), np.array([0.0, s, 0.0, s]))
    box = ShapePose("right", "box", (0.1, 0.2, 0.3), np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    out = markers_msg(0.0, {}, [], shapes=[cap, box])
    ms = [m for m in out.markers if m.ns.startswith("collision/")]
    assert [(m.ns, m.type) for m in ms] == [("collision/left", Marker.CYLINDER), ("collision/left", Marker.SPHERE),
                                            ("collision/left", Marker.SPHERE), ("collision/right", Marker.CUBE)]
    assert len({m.id for m in ms}) == 4
    ends = sorted([m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in ms[1:3])
    assert np.allclose(ends, [[0.9, 2.0, 3.0], [1.1, 2.0, 3.0]])
    assert (ms[0].scale.x, ms[0].scale.z, ms[1].scale.x) == (0.1, 0.2, 0.1)
