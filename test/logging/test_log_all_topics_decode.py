"""Every topic of a node's log decodes with both mcap_ros2 and rosbags (issue 17).

One node run (subprocess, hand, lockstep, logging) publishes every topic it has - joint_states,
point_forces, body_wrenches, solver_stats, /clock, markers, /diagnostics, simulation_state, prescribed_joints,
prescribed_points, prescribed_bodies, /tf, /tf_static, robot_description (odom: the hand has no floating
base) - and receives the logged inputs (joint_commands, point_commands, body_commands); then every
record of every channel is decoded with mcap_ros2, with rosbags' AnyReader (types from the file's
schemas) and with rosbags' deserializer given the Jazzy typestore plus redmax_msgs from msg_defs/,
and each record must have exactly the CDR length of its message (no trailing bytes: rosbags rejects
more than 3).

The node serializes the messages it publishes itself (redmax_ros/node/cdr.py); the unit tests
below check those bytes against rclpy: equal to what rclpy's publish puts on the wire, and to
``rclpy.serialization.serialize_message`` up to the length of the message. ``serialize_message``
(rmw_fastrtps' rmw_serialize) returns a buffer as long as Fast CDR's *estimated* size, which for
empty float64 sequences (a JointState with names and velocity only, as prescribed_joints) exceeds
the data by 4-12 bytes of uninitialized memory - the trailing bytes rosbags rejected.
"""
from __future__ import annotations

import array
import dataclasses
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from node_fixtures import Client  # noqa: F401  (test/node/node_fixtures.py; first: skips without ROS)

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from redmax_msgs.msg import Result, SimulationState  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PID = os.getpid()
NS = f"/logall{PID}"  # a namespace of our own, in case another run shares the ROS domain

JOINTS = (["elbow", "wrist[0]", "wrist[1]"], [0.4, 0.1, -0.1])
TORQUE = (["index_pip"], [0.01])
SITE, SITE_VEL = "index_tip", (0.0, 0.02, 0.03)
BODY, BODY_WY = "middle_dist", 0.2  # body-frame omega_y of the middle fingertip's link [rad/s]; the rest free

# every topic of the node (docs/node.md, Topics) -> its type
TOPICS = {
    f"{NS}/joint_states": "sensor_msgs/msg/JointState",
    f"{NS}/point_forces": "redmax_msgs/msg/PointForces",
    f"{NS}/body_wrenches": "redmax_msgs/msg/BodyWrenches",
    f"{NS}/solver_stats": "redmax_msgs/msg/SolverStats",
    "/clock": "rosgraph_msgs/msg/Clock",
    f"{NS}/markers": "visualization_msgs/msg/MarkerArray",
    f"{NS}/deformable_vertices": "sensor_msgs/msg/PointCloud2",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    f"{NS}/simulation_state": "redmax_msgs/msg/SimulationState",
    f"{NS}/prescribed_joints": "sensor_msgs/msg/JointState",
    f"{NS}/prescribed_points": "redmax_msgs/msg/PointVelocityCommand",
    f"{NS}/prescribed_bodies": "redmax_msgs/msg/BodyTwists",
    f"{NS}/joint_commands": "sensor_msgs/msg/JointState",
    f"{NS}/point_commands": "redmax_msgs/msg/PointVelocityCommand",
    f"{NS}/body_commands": "redmax_msgs/msg/BodyTwistCommand",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    f"{NS}/robot_description": "std_msgs/msg/String",
    f"{NS}/odom": "nav_msgs/msg/Odometry",
    f"{NS}/joint_trajectory": "trajectory_msgs/msg/JointTrajectory",
}
# channels without records in this run: the hand has no floating base (odom: test/node/test_node_frames.py
# logs and decodes it for one)
NO_RECORDS = {f"{NS}/odom", f"{NS}/joint_trajectory", f"{NS}/deformable_vertices"}  # deformable_vertices: below  # joint_trajectory: test/node/test_node_trajectory.py
INPUTS = {f"{NS}/joint_commands", f"{NS}/point_commands", f"{NS}/body_commands", f"{NS}/joint_trajectory"}  # logged as received (the client's bytes)


def _stamp_ns(st):
    return st.sec * 1_000_000_000 + st.nanosec


# ------------------------------------------------------------------------------------------------
# the node run


@pytest.fixture(scope="module")
def run(tmp_path_factory, ros):
    """The node (hand, lockstep, logging) driven through every topic: joint velocity and torque
    commands, a point command, a body-twist command, steps (states, clock, stats, point forces, body
    wrenches, markers), a release (the empty point_forces and body_wrenches), a reset, play/pause (diagnostics, states), then QUITTING (the log closes)."""
    import subprocess

    logdir = tmp_path_factory.mktemp("logs")
    cmd = [sys.executable, "-m", "redmax_ros.node.main", "--ros-args", "--params-file",
           str(ROOT / "config" / "hand.yaml"), "-p", "mode:=lockstep", "-p", f"log_path:={logdir}",
           "-p", "command_timeout:=100.0", "-p", "marker_rate:=100.0", "-p", "real_time_factor:=1.0",
           "-p", "diagnostics_period:=0.1", "-r", f"__ns:={NS}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    client = Client("log_all_topics_client", ns=NS)
    out = {"logdir": logdir}
    try:
        client.wait_ready(timeout=30)
        assert SITE in client.describe().prescribable_sites
        client.command_joints(*JOINTS)
        n0 = len(client.prescribed)
        client.command_joints(TORQUE[0], efforts=TORQUE[1], wait_ack=False)  # a torque: not in prescribed_joints
        client.wait_for(lambda: len(client.prescribed) > n0, what="torque command acknowledgement")
        client.command_points([SITE], [SITE_VEL])
        client.command_bodies([BODY], [((None, BODY_WY, None), None)], frame="body")
        r = client.step(30)
        assert r.result.result == Result.OK, r.result.error_message
        client.wait_for(lambda: len(client.point_forces) >= 30, what="30 point forces")
        client.wait_for(lambda: len(client.body_wrenches) >= 30, what="30 body wrenches")
        with client.lock:
            out["prescribed_after_commands"] = client.prescribed[-1]
        n0 = len(client.prescribed)
        r = client.call("release", client.cli["release"].srv_type.Request(sites=[SITE], bodies=[BODY]))
        assert r.result.result == Result.OK, r.result.error_message
        client.wait_for(lambda: len(client.prescribed) > n0, what="release acknowledgement")
        assert client.step(5).result.result == Result.OK
        n0 = len(client.prescribed)
        assert client.reset().result.result == Result.OK
        client.wait_for(lambda: len(client.prescribed) > n0, what="reset acknowledgement")
        assert client.step(5).result.result == Result.OK
        assert client.set_state(SimulationState.PLAYING).result.result == Result.OK
        time.sleep(0.5)  # free-run at real time: states, markers and several diagnostics periods
        assert client.set_state(SimulationState.PAUSED).result.result == Result.OK
        assert client.set_state(SimulationState.QUITTING).result.result == Result.OK
        out["returncode"] = proc.wait(30)
        time.sleep(0.2)  # the last messages still in the client's executor
        with client.lock:  # what the client got over DDS (rclpy decoding the node's bytes)
            out["received"] = {"joint_states": list(client.joint_states), "point_forces": list(client.point_forces),
                               "body_wrenches": list(client.body_wrenches),
                               "prescribed_bodies": list(client.prescribed_bodies),
                               "prescribed_joints": list(client.prescribed),
                               "simulation_state": list(client.states)}
    finally:
        if proc.poll() is None:
            proc.kill()
        out["output"] = proc.stdout.read()
        client.close()
    files = sorted(Path(logdir).rglob("*.mcap"))
    assert out["returncode"] == 0 and len(files) == 1, out["output"]
    out["path"] = files[0]
    return out


# ------------------------------------------------------------------------------------------------
# readers


def _raw_records(path):
    """[(topic, schema name, CDR bytes)] of every record, in log order (the mcap reader alone)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(c.topic, s.name, bytes(m.data)) for s, c, m in make_reader(f).iter_messages(log_time_order=True)]


def _mcap_ros2(path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(c.topic, d) for _, c, _, d in reader.iter_decoded_messages(log_time_order=True)]


def _rosbags_anyreader(path):
    """rosbags' AnyReader: the custom types come from the schemas in the file."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        return [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]


def jazzy_typestore():
    """rosbags' Jazzy typestore plus redmax_msgs registered from msg_defs/ (not from the log)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for f in sorted((ROOT / "msg_defs" / "redmax_msgs" / "msg").glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"redmax_msgs/msg/{f.stem}"))
    store.register(types)
    return store


@pytest.fixture(scope="module")
def records(run):
    return _raw_records(run["path"])


def test_every_topic_is_logged_with_records(run, records):
    from mcap.reader import make_reader

    with open(run["path"], "rb") as f:
        summary = make_reader(f).get_summary()
    channels = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert channels == TOPICS
    counts = {t: 0 for t in TOPICS}
    for topic, _, _ in records:
        counts[topic] += 1
    assert all(n for t, n in counts.items() if t not in NO_RECORDS), {t: n for t, n in counts.items() if not n}


def test_every_record_decodes_with_mcap_ros2(run, records):
    decoded = _mcap_ros2(run["path"])
    assert [t for t, _ in decoded] == [t for t, _, _ in records]


def test_every_record_decodes_with_rosbags_anyreader(run, records):
    decoded = _rosbags_anyreader(run["path"])
    assert [t for t, _ in decoded] == [t for t, _, _ in records]


def test_every_record_decodes_with_rosbags_typestore_and_has_its_exact_length(records):
    """rosbags' deserializer with the typestore from msg_defs/; then every record is exactly as
    long as its message's CDR (rosbags' serializer), i.e. no trailing bytes at all, and what the
    node wrote itself is byte for byte the canonical CDR (zero padding: the log holds no stray
    memory)."""
    store = jazzy_typestore()
    failed = {}
    for topic, msgtype, raw in records:
        try:
            msg = store.deserialize_cdr(raw, msgtype)
        except Exception as e:  # collect all, report per topic
            failed.setdefault(topic, f"{len(raw)} bytes: {e}")
            continue
        canon = bytes(store.serialize_cdr(msg, msgtype))
        if len(raw) != len(canon):
            failed.setdefault(topic, f"{len(raw)} bytes, the message has {len(canon)}")
        elif topic not in INPUTS and raw != canon:
            failed.setdefault(topic, f"bytes differ from canonical CDR: {raw.hex()} vs {canon.hex()}")
    assert not failed, failed


def _plain(x):
    """A decoded message (mcap_ros2's or rosbags' classes) as nested dicts/lists of numbers."""
    if dataclasses.is_dataclass(x):  # rosbags (its fields include the constants, upper case, and the type)
        return {f.name: _plain(getattr(x, f.name)) for f in dataclasses.fields(x)
                if f.name != "__msgtype__" and not f.name.isupper()}
    if hasattr(x, "get_fields_and_field_types"):  # rclpy
        return {k: _plain(getattr(x, k)) for k in x.get_fields_and_field_types()}
    if hasattr(x, "__slots__") and not isinstance(x, (str, bytes)):  # mcap_ros2
        return {k: _plain(getattr(x, k)) for k in x.__slots__}
    if isinstance(x, (bytes, bytearray)):
        return list(x)
    if isinstance(x, (list, tuple, np.ndarray, array.array)):
        return [_plain(v) for v in x]
    if isinstance(x, float) and math.isnan(x):
        return "nan"
    if isinstance(x, (np.floating, np.integer)):
        return _plain(x.item())
    return x


def test_both_readers_decode_the_same_values(run, records):
    """mcap_ros2, rosbags' AnyReader (types from the log's schemas) and rosbags with the typestore
    from msg_defs/ decode every record to the same values."""
    a = _mcap_ros2(run["path"])
    b = _rosbags_anyreader(run["path"])
    store = jazzy_typestore()
    assert len(a) == len(b) == len(records)
    for (ta, ma), (tb, mb), (tc, msgtype, raw) in zip(a, b, records):
        assert ta == tb == tc
        pa = _plain(ma)
        assert pa == _plain(mb), ta
        assert pa == _plain(store.deserialize_cdr(raw, msgtype)), ta


def _is_subsequence(part, whole):
    it = iter(whole)
    return all(any(p == w for w in it) for p in part)


@pytest.mark.parametrize("topic", ["joint_states", "point_forces", "body_wrenches", "prescribed_joints",
                                   "prescribed_bodies", "simulation_state"])
def test_logged_values_equal_what_the_client_received(run, topic):
    """What a subscriber got over DDS (rclpy's decoding of the node's bytes) is in the log, in the
    same order, with the same values as both readers decode them."""
    received = [_plain(m) for m in run["received"][topic]]
    assert len(received) >= {"joint_states": 40, "point_forces": 30, "body_wrenches": 30}.get(topic, 2), len(received)
    for decode in (_mcap_ros2, _rosbags_anyreader):
        logged = [_plain(m) for t, m in decode(run["path"]) if t == f"{NS}/{topic}"]
        assert _is_subsequence(received, logged), (decode.__name__, topic)


# ------------------------------------------------------------------------------------------------
# field checks (rosbags, typestore from msg_defs/)


@pytest.fixture(scope="module")
def decoded(records):
    store = jazzy_typestore()
    out = {t: [] for t in TOPICS}
    for topic, msgtype, raw in records:
        out[topic].append(store.deserialize_cdr(raw, msgtype))
    return out


def test_prescribed_joints_are_what_was_commanded(run, decoded):
    pj = decoded[f"{NS}/prescribed_joints"]
    names, vel = JOINTS
    acked = [m for m in pj if all(n in list(m.name) for n in names)]
    assert acked, [list(m.name) for m in pj]
    m = acked[-1]
    got = dict(zip(m.name, m.velocity.tolist()))
    assert {n: got[n] for n in names} == dict(zip(names, vel))
    assert len(m.position) == 0 and len(m.effort) == 0 and len(m.velocity) == len(m.name)
    assert m.header.frame_id == "world"
    # the client's view of the same acknowledgement
    ack = run["prescribed_after_commands"]
    assert list(ack.name) == list(m.name) and list(ack.velocity) == m.velocity.tolist()
    # after the reset: the scene's default (elbow held)
    last = pj[-1]
    assert list(last.name) == ["elbow"] and last.velocity.tolist() == [0.0]


def test_prescribed_points_and_point_forces(decoded):
    pp = decoded[f"{NS}/prescribed_points"]
    with_site = [m for m in pp if list(m.sites) == [SITE]]
    assert with_site, [list(m.sites) for m in pp]
    v = with_site[-1].velocities[0]
    assert (v.x, v.y, v.z) == SITE_VEL
    assert list(pp[-1].sites) == [] and len(pp[-1].velocities) == 0  # released
    pf = decoded[f"{NS}/point_forces"]
    full = [m for m in pf if list(m.sites) == [SITE]]
    assert len(full) >= 30 and all(len(m.forces) == 1 and math.isfinite(m.forces[0].z) for m in full)
    assert any(list(m.sites) == [] and len(m.forces) == 0 for m in pf)  # the empty one on release


def test_prescribed_bodies_and_body_wrenches(decoded):
    pb = decoded[f"{NS}/prescribed_bodies"]
    with_body = [m for m in pb if list(m.bodies) == [BODY]]
    assert with_body, [list(m.bodies) for m in pb]
    m = with_body[-1]
    assert list(m.frames) == ["body"] and m.header.frame_id == "world"
    tw = m.twists[0]
    assert tw.angular.y == BODY_WY and all(math.isnan(x) for x in (tw.angular.x, tw.angular.z, tw.linear.x,
                                                                   tw.linear.y, tw.linear.z))
    assert list(pb[-1].bodies) == [] and len(pb[-1].twists) == 0  # released (the hand prescribes no body)
    bw = decoded[f"{NS}/body_wrenches"]
    full = [m for m in bw if list(m.bodies) == [BODY]]
    assert len(full) >= 30 and all(list(m.frames) == ["body"] and len(m.wrenches) == 1 for m in full)
    for m in full:  # only the prescribed component (torque about the body's y axis) is non-zero
        w = m.wrenches[0]
        assert math.isfinite(w.torque.y) and (w.torque.x, w.torque.z, w.force.x, w.force.y, w.force.z) == (0.0,) * 5
    assert any(abs(m.wrenches[0].torque.y) > 0 for m in full)
    assert any(list(m.bodies) == [] and len(m.wrenches) == 0 for m in bw)  # the empty one on release


def test_commands_are_logged_as_sent(decoded):
    jc = decoded[f"{NS}/joint_commands"]
    assert [list(m.name) for m in jc] == [JOINTS[0], TORQUE[0]]
    assert jc[0].velocity.tolist() == JOINTS[1] and len(jc[0].effort) == 0
    assert jc[1].effort.tolist() == TORQUE[1] and len(jc[1].velocity) == 0
    pc = decoded[f"{NS}/point_commands"]
    assert len(pc) == 1 and list(pc[0].sites) == [SITE]
    assert (pc[0].velocities[0].x, pc[0].velocities[0].y, pc[0].velocities[0].z) == SITE_VEL
    bc = decoded[f"{NS}/body_commands"]
    assert len(bc) == 1 and list(bc[0].bodies) == [BODY] and bc[0].header.frame_id == "body"
    assert bc[0].twists[0].angular.y == BODY_WY and math.isnan(bc[0].twists[0].linear.x)


def test_states_clock_stats_markers_diagnostics(decoded):
    states = [m.state for m in decoded[f"{NS}/simulation_state"]]
    assert states[0] == SimulationState.PAUSED and SimulationState.PLAYING in states
    assert states[-1] == SimulationState.QUITTING
    js = decoded[f"{NS}/joint_states"]
    clock = decoded["/clock"]
    assert len(js) > 40 and len(clock) > 40
    n = len(js[-1].name)
    assert all(len(m.name) == len(m.position) == len(m.velocity) == len(m.effort) == n for m in js)
    assert max(_stamp_ns(m.clock) for m in clock) == max(_stamp_ns(m.header.stamp) for m in js)
    stats = decoded[f"{NS}/solver_stats"]
    assert stats and all(m.solver and m.step > 0 and math.isfinite(m.residual) for m in stats)
    markers = decoded[f"{NS}/markers"]
    assert markers and any(mk.ns == mk.text == "palm" for m in markers for mk in m.markers)  # ns: the body name
    diags = decoded["/diagnostics"]
    assert diags and all(st.name.endswith(": simulation") for m in diags for st in m.status)
    assert any(kv.key == "real_time_factor" for m in diags for st in m.status for kv in st.values)


# ------------------------------------------------------------------------------------------------
# the node's CDR (redmax_ros/node/cdr.py) against rclpy and rosbags


def _messages():
    """Representative messages of every type the node sends or logs, with the empty-array cases."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import Vector3
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CompressedImage, JointState, NavSatFix
    from std_msgs.msg import ByteMultiArray, Empty, Int64MultiArray
    from unique_identifier_msgs.msg import UUID

    from geometry_msgs.msg import Twist, Wrench

    from redmax_msgs.msg import BodyTwistCommand, BodyWrenches, PointForces, SolverStats
    from redmax_ros.node import convert

    def js(names, q=(), v=(), e=(), frame="world", t=0.125):
        m = JointState(name=list(names), position=list(q), velocity=list(v), effort=list(e))
        m.header.stamp, m.header.frame_id = convert.time_msg(t), frame
        return m

    poses = {f"body{i}": (np.array([0.1 * i, -0.2, 0.3]), np.array([0.0, 0.0, math.sin(i), math.cos(i)]))
             for i in range(4)}
    springs = [("s0", np.zeros(3), np.array([0.1, 0.2, 0.3])), ("s1", np.ones(3), -np.ones(3))]
    stats = SolverStats(step=123456789012, solver="direct", iterations=7, residual=2e-16, energy_total=-0.625)
    stats.header.stamp, stats.header.frame_id = convert.time_msg(0.042), "world"
    img = CompressedImage(format="png", data=bytes(range(7)))
    fix = NavSatFix(latitude=1.5, position_covariance=np.arange(9.0))
    return {
        "prescribed_joints": convert.prescriptions_msg(0.5, {"elbow": 0.0}, "world"),  # the 68 bytes
        "prescribed_joints_multi": convert.prescriptions_msg(0.5, {"elbow": 0.4, "wrist": np.array([0.1, -0.1])}),
        "prescribed_joints_none": convert.prescriptions_msg(0.0, {}, "world"),
        "js_names_only": js(["a", "bb", "ccc"]),
        "js_all_empty": js([], frame=""),
        "js_velocity_only_no_frame": js(["elbow"], v=[1.0], frame=""),
        "js_effort_only": js(["index_pip"], e=[0.01]),
        "js_position_only": js(["a"], q=[1.0]),
        "js_full_nan": js(["a", "b"], q=[math.nan, 1.0], v=[2.0, 3.0], e=[4.0, 5.0]),
        "prescribed_points": convert.point_prescriptions_msg(1.0, {"index_tip": np.array([0.0, 0.02, 0.03])}),
        "prescribed_points_none": convert.point_prescriptions_msg(1.0, {}),
        "point_forces": PointForces(sites=["index_tip", "thumb_tip"], forces=[Vector3(x=1.0), Vector3(z=-2.5)]),
        "point_forces_empty": PointForces(),
        "prescribed_bodies_nan": convert.body_prescriptions_msg(
            0.5, {"lower": {"components": ["wy", "vz"], "values": np.array([-1.0, 0.25]), "frame": "world"},
                  "box": {"components": ["wx", "wy", "wz"], "values": np.array([0.1, 0.2, 0.3]), "frame": "body"}}),
        "prescribed_bodies_none": convert.body_prescriptions_msg(0.5, {}),
        "body_wrenches": BodyWrenches(bodies=["lower", "box"], frames=["world", "body"],
                                      wrenches=[Wrench(torque=Vector3(y=-0.5)), Wrench(force=Vector3(x=1.0, z=2.0))]),
        "body_wrenches_empty": BodyWrenches(),
        "body_command_nan": BodyTwistCommand(bodies=["box"], twists=[Twist(angular=Vector3(x=math.nan, y=1.0))]),
        "simulation_state": SimulationState(state=SimulationState.PAUSED),
        "markers": convert.markers_msg(0.25, poses, springs, "world"),
        "markers_no_springs": convert.markers_msg(0.25, poses, [], "world"),
        "diagnostics": convert.diagnostics_msg(Time(sec=5, nanosec=7), "/sim/redmax", "hand",
                                               {"steps_per_s": 1000.5, "failures": 0, "solver": "direct"}),
        "solver_stats": stats,
        "clock": Clock(clock=convert.time_msg(3.999999999)),
        # other shapes the generic encoder meets: empty struct, fixed arrays, uint8[]/octet[]/int64[]
        "empty": Empty(),
        "uuid": UUID(uuid=np.arange(16, dtype=np.uint8)),
        "navsatfix": fix,
        "compressed_image": img,
        "bytes": ByteMultiArray(data=[b"\x01", b"\xff"]),
        "int64s": Int64MultiArray(data=[-1, 2**62]),
    }


MESSAGES = sorted(_messages())


def _rosbags_type(m):
    return f"{type(m).__module__.split('.')[0]}/msg/{type(m).__name__}"


@pytest.mark.parametrize("name", MESSAGES)
def test_serialize_message_is_rclpys_without_the_trailing_bytes(name):
    """cdr.serialize_message = rclpy's serialize_message cut to the message's length (all bytes but
    the alignment padding, which rclpy leaves uninitialized and we zero); rclpy reads it back as the
    same message, and rosbags' serializer writes exactly these bytes."""
    from redmax_ros.node.cdr import padding_of
    from redmax_ros.node.cdr import serialize_message as ours_of

    m = _messages()[name]
    ours, ref, pad = ours_of(m), serialize_message(m), set(padding_of(m))
    assert len(ref) >= len(ours)
    assert [b for i, b in enumerate(ours) if i not in pad] == [b for i, b in enumerate(ref[:len(ours)]) if i not in pad]
    assert all(ours[i] == 0 for i in pad)
    back = deserialize_message(ours, type(m))  # float32 fields round: compare with rclpy's round trip
    assert back == deserialize_message(ref, type(m)) or name.endswith("_nan")  # NaN != NaN
    store = jazzy_typestore()
    t = _rosbags_type(m)
    assert bytes(store.serialize_cdr(store.deserialize_cdr(ours, t), t)) == ours


def test_prescribed_joints_decode_with_rosbags():
    """The issue's record: JointState(name=[elbow], velocity=[0]) in frame world. Its CDR is 64
    bytes; rclpy's serialize_message gave 68 (Fast CDR's size estimate), which rosbags rejects."""
    from redmax_ros.node import convert
    from redmax_ros.node.cdr import serialize_message as ours_of

    m = convert.prescriptions_msg(0.5, {"elbow": 0.0}, "world")
    data = ours_of(m)
    assert len(data) == 64
    got = jazzy_typestore().deserialize_cdr(data, "sensor_msgs/msg/JointState")
    assert list(got.name) == ["elbow"] and got.velocity.tolist() == [0.0]
    assert len(got.position) == 0 and len(got.effort) == 0


def test_fast_encoders_equal_serialize_message():
    """The per-step encoders and serialize_message write the same bytes, padding included (zero)."""
    from types import SimpleNamespace

    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState

    from redmax_msgs.msg import SolverStats
    from redmax_ros.node.cdr import JointStateEncoder, SolverStatsEncoder, encode_clock
    from redmax_ros.node.cdr import serialize_message as ours_of
    from redmax_ros.node.convert import time_msg

    rng = np.random.default_rng(17)
    for names in (["elbow", "wrist[0]", "wrist[1]"], ["hinge"], []):  # [] : a scene without DOFs
        enc = JointStateEncoder(names, "")
        q, v, e = (rng.normal(size=len(names)) for _ in range(3))
        ref = JointState(name=names, position=q.tolist(), velocity=v.tolist(), effort=e.tolist())
        ref.header.stamp = time_msg(1.25)
        assert enc.encode(1.25, q, v, e) == ours_of(ref), names
    empty = JointState()
    empty.header.stamp = time_msg(0.5)
    assert JointStateEncoder([]).encode(0.5, [], [], []) == ours_of(empty)  # lists: the buffer path
    d = SimpleNamespace(E_kin=1.5, E_pot=-2.25, E_spring=0.125, E_total=-0.625, violation_pos=1e-12,
                        violation_vel=3e-15, residual=2e-16, iterations=7, solver="pcg", wall_time=2.5e-4, order=2)
    st = SolverStats(step=42, solver="pcg", iterations=7, residual=2e-16, violation_pos=1e-12, violation_vel=3e-15,
                     energy_kinetic=1.5, energy_potential=-2.25, energy_spring=0.125, energy_total=-0.625,
                     step_wall_time=2.5e-4, integration_order=2)
    st.header.stamp, st.header.frame_id = time_msg(0.042), "world"
    assert SolverStatsEncoder("world").encode(0.042, 42, d) == ours_of(st)
    assert encode_clock(3.5) == ours_of(Clock(clock=time_msg(3.5)))


def test_every_logged_type_has_an_encoder():
    """No type the node logs falls back to rclpy's serializer."""
    import importlib

    from redmax_ros.node.cdr import _encoder

    for t in set(TOPICS.values()):
        pkg, _, name = t.split("/")
        assert _encoder(getattr(importlib.import_module(f"{pkg}.msg"), name)) is not False, t


def test_serialize_message_equals_rclpy_publish_on_the_wire(ros):
    """What a subscriber (a recorder: ros2 bag) gets from rclpy's own publish of the same message:
    the same length and the same bytes but padding."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from redmax_ros.node.cdr import padding_of
    from redmax_ros.node.cdr import serialize_message as ours_of

    node = Node(f"cdr_wire_{PID}")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    try:
        for i, name in enumerate(MESSAGES):
            m = _messages()[name]
            got = []
            topic = f"/cdr_wire_{PID}/t{i}"
            node.create_subscription(type(m), topic, got.append, 10, raw=True)
            pub = node.create_publisher(type(m), topic, 10)
            end = time.monotonic() + 10
            while pub.get_subscription_count() == 0:
                assert time.monotonic() < end, "no match"
                ex.spin_once(timeout_sec=0.01)
            pub.publish(m)
            while not got:
                assert time.monotonic() < end, f"{name}: nothing received"
                ex.spin_once(timeout_sec=0.01)
            ours, pad = ours_of(m), set(padding_of(m))
            wire = bytes(got[0])
            assert len(wire) == len(ours), name
            assert [b for j, b in enumerate(wire) if j not in pad] == [b for j, b in enumerate(ours)
                                                                     if j not in pad], name
    finally:
        ex.remove_node(node)
        node.destroy_node()
