"""/tf, /tf_static, robot_description and odom read back from the node (issue 18, point 2).

The node runs in this process (lockstep, logging to MCAP) so its core's body poses can be read
directly while it is paused: every body's world pose, from /tf alone or composed with /tf_static,
equals the core's ``Simulator.body_poses()`` to 1e-12; robot_description is a URDF with a link for
every body; odom (a floating base: scene incline, loaded at run time) carries the base's world
pose and its body-frame twist. Then the log's records of these topics decode with mcap_ros2 and
rosbags (Jazzy typestore).
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from node_fixtures import Client, run_node_in_thread  # noqa: F401  (first: skips without ROS)

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from redmax_msgs.msg import Result  # noqa: E402
from redmax_ros.node.cdr import TFMessageEncoder, serialize_message  # noqa: E402

NS = f"/frames{os.getpid()}"
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
TOL = 1e-12


@pytest.fixture(scope="module")
def logdir(tmp_path_factory):
    return tmp_path_factory.mktemp("frames_logs")


@pytest.fixture(scope="module")
def node(ros, logdir):
    node, shutdown = run_node_in_thread({"scene": "hand", "mode": "lockstep", "marker_rate": 0.0, "tf_rate": 50.0,
                                         "command_timeout": 100.0, "log_path": str(logdir)}, namespace=NS)
    box = {"shutdown": shutdown}
    yield node, box
    if box["shutdown"] is not None:
        box["shutdown"]()


class FrameClient(Client):
    def __init__(self):
        super().__init__("frames_client", ns=NS)
        self.tf, self.tf_static, self.descriptions, self.odom = [], [], [], []
        n = self.node
        n.create_subscription(TFMessage, "/tf", self._store(self.tf), QoSProfile(depth=100,
                                                                                 reliability=ReliabilityPolicy.RELIABLE))
        n.create_subscription(TFMessage, "/tf_static", self._store(self.tf_static), LATCHED)
        n.create_subscription(String, f"{NS}/robot_description", self._store(self.descriptions), LATCHED)
        n.create_subscription(Odometry, f"{NS}/odom", self._store(self.odom), QoSProfile(depth=100))


@pytest.fixture(scope="module")
def client(node):
    c = FrameClient()
    c.wait_ready()
    # the latched topics reach a late joiner some time after discovery
    c.wait_for(lambda: c.tf_static and c.descriptions, what="/tf_static and robot_description")
    yield c
    c.close()


def _se3(tr):
    t, r = tr.translation, tr.rotation
    return pin.XYZQUATToSE3(np.array([t.x, t.y, t.z, r.x, r.y, r.z, r.w]))


def _core_se3(pose):
    p, q = pose
    return pin.XYZQUATToSE3(np.r_[p, q])


def _stamp_ns(h):
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def _world_frames(tf_msg, static_msg):
    """frame -> SE3 in the world: /tf's world poses, then /tf_static composed onto them."""
    W = {"world": pin.SE3.Identity()}
    for tr in tf_msg.transforms:
        assert tr.header.frame_id == "world"
        W[tr.child_frame_id] = _se3(tr.transform)
    pending = list(static_msg.transforms)
    while pending:
        rest = [tr for tr in pending if tr.header.frame_id not in W]
        for tr in pending:
            if tr.header.frame_id in W:
                W[tr.child_frame_id] = W[tr.header.frame_id] * _se3(tr.transform)
        assert len(rest) < len(pending), [tr.header.frame_id for tr in rest]  # every parent known
        pending = rest
    return W


def _latest(c, lst, pred, what):
    c.wait_for(lambda: any(pred(m) for m in lst), what=what)
    with c.lock:
        return [m for m in lst if pred(m)][-1]


def _check_poses(node, c, steps, t_ns):
    r = c.step(steps)
    assert r.result.result == Result.OK, r.result.error_message
    tf = _latest(c, c.tf, lambda m: m.transforms and _stamp_ns(m.transforms[0].header) == t_ns, f"/tf at {t_ns} ns")
    c.wait_for(lambda: c.tf_static, what="/tf_static")
    with c.lock:
        static = c.tf_static[-1]
    core = node.engine.sim.body_poses()  # paused: the state the node published last
    W = _world_frames(tf, static)
    assert set(core) <= set(W)
    err = max(np.max(np.abs(W[b].homogeneous - _core_se3(core[b]).homogeneous)) for b in core)
    assert err <= TOL, err
    for tr in tf.transforms:  # /tf alone: the core's numbers to rounding (the quaternion up to its sign)
        p, q = core[tr.child_frame_id]
        t, rr = tr.transform.translation, tr.transform.rotation
        got = np.array([rr.x, rr.y, rr.z, rr.w])
        assert np.max(np.abs(np.array([t.x, t.y, t.z]) - p)) <= TOL
        assert min(np.max(np.abs(got - q)), np.max(np.abs(got + q))) <= TOL
    return tf, static


def test_tf_and_tf_static_give_every_body_pose(node, client):
    node, _ = node
    c = client
    assert c.reset().result.result == Result.OK
    c.command_joints(["elbow", "wrist[0]", "wrist[1]"], [0.5, 0.2, -0.3])
    tf, static = _check_poses(node, c, 7, 7_000_000)  # fewer steps than tf_rate's period: the last one is published
    info = node.engine.info
    moving = {tr.child_frame_id for tr in tf.transforms}
    assert moving | {tr.child_frame_id for tr in static.transforms} >= set(info.d.bodies)
    # hand: every joint moves, so each body is on /tf; joint-frame links (URDF) on /tf_static
    assert moving == set(info.d.bodies)
    assert all(tr.header.frame_id in info.d.bodies for tr in static.transforms)
    _check_poses(node, c, 45, 52_000_000)  # across tf_rate's decimation (every 20 steps) and the last step


def test_robot_description_is_a_urdf_of_the_tree(node, client):
    node, _ = node
    c = client
    desc = _latest(c, c.descriptions, lambda m: '<robot name="hand">' in m.data, "robot_description").data
    root = ET.fromstring(desc.split("\n", 1)[1])
    links = {e.get("name") for e in root.findall("link")}
    joints = {e.get("name"): e for e in root.findall("joint")}
    info = node.engine.info
    assert set(info.d.bodies) | {"world"} <= links
    for name, jtype in zip(info.d.joint_names, info.d.joint_types):
        assert name in joints
        want = {"revolute": ("revolute", "continuous"), "universal": ("floating",)}[jtype]
        assert joints[name].get("type") in want
        if jtype == "revolute":
            assert joints[name].find("axis") is not None
    # the frames it names are all on /tf or /tf_static
    with c.lock:
        tf, static = c.tf[-1], c.tf_static[-1]
    frames = {tr.child_frame_id for tr in tf.transforms} | {tr.child_frame_id for tr in static.transforms} | {"world"}
    assert links <= frames
    # geometry: the hand's boxes
    assert len(root.findall("link/visual/geometry/box")) == len(info.d.bodies)


def test_fixed_joints_on_tf_static_and_odom_for_a_floating_base(node, client):
    node, _ = node
    c = client
    try:
        r = c.load("catalogue/fixed")
        assert r.result.result == Result.OK, r.result.error_message
        c.wait_for(lambda: c.tf_static and any(tr.child_frame_id == "ball" for tr in c.tf_static[-1].transforms),
                   what="/tf_static of catalogue/fixed")
        with c.lock:
            ball = [tr for tr in c.tf_static[-1].transforms if tr.child_frame_id == "ball"][0]
        assert ball.header.frame_id == "rod"  # welded to the rod: a static transform from it
        tf, _ = _check_poses(node, c, 12, 12_000_000)
        assert "ball" not in {tr.child_frame_id for tr in tf.transforms}

        r = c.load("incline")
        assert r.result.result == Result.OK, r.result.error_message
        assert c.step(30).result.result == Result.OK
        odom = _latest(c, c.odom, lambda m: _stamp_ns(m.header) == 30_000_000, "odom at 30 ms")
        sim = node.engine.sim
        assert odom.child_frame_id == "block" and odom.header.frame_id == "world"
        p, q = sim.body_poses()["block"]
        pp, oo = odom.pose.pose.position, odom.pose.pose.orientation
        assert np.max(np.abs(np.array([pp.x, pp.y, pp.z, oo.x, oo.y, oo.z, oo.w]) - np.r_[p, q])) <= TOL
        v = sim.joint_velocities()  # free joint at the body frame: (linear, angular) in the body frame
        lin, ang = odom.twist.twist.linear, odom.twist.twist.angular
        assert np.max(np.abs(np.array([lin.x, lin.y, lin.z, ang.x, ang.y, ang.z]) - v[:6])) <= TOL
        assert np.linalg.norm(v[:3]) > 1e-3  # it is moving
        _check_poses(node, c, 3, 33_000_000)
    finally:
        assert c.load("hand").result.result == Result.OK


def test_new_topics_decode_from_the_log(node, client, logdir):
    """The log's /tf, /tf_static, robot_description and odom records decode with mcap_ros2 and with
    rosbags (Jazzy typestore: tf2_msgs, nav_msgs and std_msgs are standard there)."""
    node, box = node
    box["shutdown"]()  # finishes the log
    box["shutdown"] = None
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.typesys import Stores, get_typestore

    files = sorted(Path(logdir).rglob("*.mcap"))
    assert len(files) == 1
    topics = {"/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage",
              f"{NS}/robot_description": "std_msgs/msg/String", f"{NS}/odom": "nav_msgs/msg/Odometry"}
    store = get_typestore(Stores.ROS2_JAZZY)
    counts = {t: 0 for t in topics}
    with open(files[0], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            if channel.topic not in topics:
                continue
            assert schema.name == topics[channel.topic]
            msg = store.deserialize_cdr(bytes(message.data), schema.name)
            assert len(bytes(store.serialize_cdr(msg, schema.name))) == len(message.data)
            counts[channel.topic] += 1
            if channel.topic == f"{NS}/odom":
                assert decoded.child_frame_id == msg.child_frame_id == "block"
            if channel.topic == "/tf":
                assert [t.child_frame_id for t in decoded.transforms] == [t.child_frame_id for t in msg.transforms]
    assert all(counts.values()), counts
    assert counts[f"{NS}/robot_description"] >= 4  # hand, catalogue/fixed, incline, hand


def test_tf_encoder_writes_the_serializer_bytes():
    """cdr.TFMessageEncoder (the node's /tf) against the generic serializer of the same message."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
    rng = np.random.default_rng(3)
    for children in (["a"], ["palm", "index_prox_joint", "x" * 13, "ab"], []):
        n = len(children)
        P, Q = rng.normal(size=(n, 3)), rng.normal(size=(n, 4))
        for t in (0.0, 0.123456789, 12345.000000001):
            ns = int(round(t * 1e9))
            stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            msg = TFMessage()
            for c, p, q in zip(children, P, Q):
                m = TransformStamped(child_frame_id=c)
                m.header.stamp, m.header.frame_id = stamp, "world"
                m.transform = Transform(translation=Vector3(x=p[0], y=p[1], z=p[2]),
                                        rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
                msg.transforms.append(m)
            assert TFMessageEncoder("world", children).encode(t, P, Q) == serialize_message(msg)
