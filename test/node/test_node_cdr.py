"""The node's fast CDR encoders write the CDR of the message: every byte but the alignment padding
equal to rclpy's serializer, the padding zero, and exactly the message's length.

rclpy's ``serialize_message`` (rmw_fastrtps' ``rmw_serialize``) is not a byte-exact reference: it
leaves alignment padding uninitialized, and its buffer is as long as Fast CDR's size *estimate*,
which for empty float64 sequences exceeds the data by 4-12 bytes of uninitialized memory (an empty
JointState: 44 bytes for a 36-byte message). rosbags rejects a payload with more than 3 bytes after
the message ("CDR message size mismatch"), so the length is checked with rosbags: it must read the
payload and write back exactly the same bytes.
"""
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("redmax_msgs.msg", reason="redmax_msgs not built (scripts/setup.sh builds msg_defs/)")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from redmax_msgs.msg import SolverStats  # noqa: E402
from redmax_ros.node.cdr import JointStateEncoder, SolverStatsEncoder, encode_clock  # noqa: E402
from redmax_ros.node.convert import time_msg  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def store():
    """rosbags' Jazzy typestore plus redmax_msgs from msg_defs/."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for f in sorted((ROOT / "msg_defs" / "redmax_msgs" / "msg").glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"redmax_msgs/msg/{f.stem}"))
    ts.register(types)
    return ts


def check_cdr(ours, ref, padding, store, msgtype):
    """``ours`` is the CDR of the message rclpy serialized as ``ref``: no longer than rclpy's buffer,
    equal to it except at the alignment padding (which rclpy leaves uninitialized; ours is zero),
    and exactly the message's length: rosbags reads it (no more than 3 trailing bytes allowed) and
    its serializer writes back the same bytes, so nothing trails at all."""
    assert ours[:4] == b"\x00\x01\x00\x00"  # CDR_LE
    assert len(ours) <= len(ref), (len(ours), len(ref))
    pad = set(padding)
    assert all(4 <= i < len(ours) for i in pad), sorted(pad)
    assert [i for i in range(len(ours)) if i not in pad and ours[i] != ref[i]] == []
    assert all(ours[i] == 0 for i in pad)
    back = store.deserialize_cdr(ours, msgtype)  # raises "CDR message size mismatch" on > 3 trailing bytes
    assert bytes(store.serialize_cdr(back, msgtype)) == ours
    return back


@pytest.mark.parametrize("names,frame", [(["elbow", "wrist[0]", "wrist[1]", "ab"], ""), (["hinge"], "world"),
                                          ([f"j{i}" for i in range(23)], "x"), ([], "")])
def test_joint_state_bytes(names, frame, store):
    rng = np.random.default_rng(len(names))
    enc = JointStateEncoder(names, frame)
    for t in (0.0, 0.001, 1.2345678901, 12345.000000001):
        q, v, e = (rng.normal(size=len(names)) for _ in range(3))
        if len(names):
            q[0] = math.nan  # NaN positions (joints whose nq != nv) are kept
        ref = JointState(name=names, position=q.tolist(), velocity=v.tolist(), effort=e.tolist())
        ref.header.stamp = time_msg(t)
        ref.header.frame_id = frame
        got = enc.encode(t, q, v, e)
        if len(names):
            back = deserialize_message(got, JointState)
            assert list(back.name) == names and np.array_equal(back.velocity, v)
            q2 = np.asarray(back.position)
            assert math.isnan(q2[0]) and np.array_equal(q2[1:], q[1:])
            q[0] = 0.0
            ref.position = q.tolist()
            got = enc.encode(t, q, v, e)
        back = check_cdr(got, serialize_message(ref), enc.padding, store, "sensor_msgs/msg/JointState")
        assert list(back.name) == names and back.header.frame_id == frame
        assert back.position.tolist() == q.tolist() and back.effort.tolist() == e.tolist()


def test_clock_bytes(store):
    for t in (0.0, 0.001, 3.999999999, 1e6 + 0.5):
        assert encode_clock(t) == serialize_message(Clock(clock=time_msg(t)))  # no padding: all bytes
        check_cdr(encode_clock(t), serialize_message(Clock(clock=time_msg(t))), [], store, "rosgraph_msgs/msg/Clock")


@pytest.mark.parametrize("solver", ["direct", "pcg", "", "a-much-longer-solver-name"])
def test_solver_stats_bytes(solver, store):
    rows, active = (17, 3) if solver == "direct" else (0, 0)  # a step with self-collision rows (docs/collisions.md)
    order = 2 if solver == "pcg" else 1  # a BDF2 step (Diagnostics.order)
    d = SimpleNamespace(E_kin=1.5, E_pot=-2.25, E_spring=0.125, E_total=-0.625, violation_pos=1e-12,
                        violation_vel=3e-15, residual=2e-16, iterations=7, solver=solver, wall_time=2.5e-4,
                        solution=SimpleNamespace(contacts=SimpleNamespace(rows=rows, active=active) if rows else None),
                        order=order)
    enc = SolverStatsEncoder("world")
    ref = SolverStats(step=123456789012, solver=solver, iterations=7, residual=2e-16, violation_pos=1e-12,
                      violation_vel=3e-15, energy_kinetic=1.5, energy_potential=-2.25, energy_spring=0.125,
                      energy_total=-0.625, step_wall_time=2.5e-4, contact_rows=rows, contacts_active=active,
                      integration_order=order)
    ref.header.stamp = time_msg(0.042)
    ref.header.frame_id = "world"
    got = enc.encode(0.042, 123456789012, d)
    back = check_cdr(got, serialize_message(ref), enc.padding, store, "redmax_msgs/msg/SolverStats")
    assert back.solver == solver and back.step == 123456789012 and back.step_wall_time == 2.5e-4
    assert deserialize_message(got, SolverStats) == ref


def test_joint_state_encoder_reuses_no_output_and_checks_lengths():
    """The encoder patches one internal buffer: earlier results must stay intact, wrong lengths fail."""
    enc = JointStateEncoder(["a", "b", "c"])
    first = enc.encode(0.001, np.zeros(3), np.ones(3), np.full(3, 2.0))
    second = enc.encode(0.002, np.ones(3), np.zeros(3), np.zeros(3))
    assert list(deserialize_message(first, JointState).effort) == [2.0, 2.0, 2.0]
    assert deserialize_message(second, JointState).header.stamp.nanosec == 2_000_000
    for bad in (np.zeros(2), np.zeros(4), np.zeros((3, 1))):
        with pytest.raises(ValueError):
            enc.encode(0.0, bad, np.zeros(3), np.zeros(3))


def test_joint_state_encoder_fast_and_buffer_paths_agree():
    """float64 ndarrays take the join path; lists, other dtypes and strided views the buffer path
    or tobytes() of a non-contiguous array: the same bytes either way."""
    rng = np.random.default_rng(3)
    enc = JointStateEncoder([f"j{i}" for i in range(5)], "f")
    q, v, e = (rng.normal(size=5) for _ in range(3))
    ref = enc._encode_buffer(0.25, q, v, e)
    assert enc.encode(0.25, q, v, e) == ref
    assert enc.encode(0.25, q.tolist(), v, e) == ref
    wide = np.stack([e, e]).T  # (5, 2): column 0 is a strided view of e
    assert enc.encode(0.25, q, v, wide[:, 0]) == ref
    assert enc.encode(0.25, q, v, e.astype(np.float32)) == enc._encode_buffer(0.25, q, v, e.astype(np.float32))


def test_step_records_equal_write_many(tmp_path):
    """cdr.StepRecords (the node's per-step log records when logging) hands over exactly the bytes
    write_many would: same records, sequence numbers continuing across both, one log time per
    step; the /clock and solver_stats slices are the encoders' messages."""
    from mcap.reader import make_reader

    from redmax_ros.logging.mcap_log import McapLogger
    from redmax_ros.node.cdr import StepRecords

    names = ["elbow", "wrist[0]", "wrist[1]"]
    topics = ("/ns/joint_states", "/clock", "/ns/solver_stats")
    types = ("sensor_msgs/msg/JointState", "rosgraph_msgs/msg/Clock", "redmax_msgs/msg/SolverStats")
    js_enc, stats_enc = JointStateEncoder(names), SolverStatsEncoder("world")
    rng = np.random.default_rng(3)
    steps = []
    for k in range(1, 41):
        solver = "direct" if k < 30 else "pcg"  # a solver change mid-run: another layout
        d = SimpleNamespace(E_kin=rng.normal(), E_pot=rng.normal(), E_spring=rng.normal(), E_total=rng.normal(),
                            violation_pos=rng.random(), violation_vel=rng.random(), residual=rng.random(),
                            iterations=int(k % 5), solver=solver, wall_time=rng.random(), order=1 + k % 2)
        steps.append((1000 + k, 0.001 * k, js_enc.encode(0.001 * k, *rng.normal(size=(3, 3))), k, d))

    def expected(ns, t, js, k, d):
        return [(topics[0], js), (topics[1], encode_clock(t)), (topics[2], stats_enc.encode(t, k, d))]

    lg = McapLogger(tmp_path / "a", "a")
    for tp, ty in zip(topics, types):
        lg.add_topic(tp, ty)
    rec = StepRecords(lg, *topics, stats_enc)
    for i, (ns, t, js, k, d) in enumerate(steps):
        if i % 3 == 1:
            lg.write_many(expected(ns, t, js, k, d), log_time_ns=ns)
            continue
        blob = rec.build(ns, t, js, k, d)
        c, s = rec.clock_at(len(js)), rec.stats_at(len(js))
        assert blob[c:c + 12] == encode_clock(t) and blob[s:] == stats_enc.encode(t, k, d)
        lg.write_records(blob, 3)
    lg.close()
    assert lg.error is None and lg.written == lg.handed_over == 120
    with open(lg.files[0], "rb") as f:
        got = [(c.topic, m.sequence, m.log_time, m.publish_time, m.data) for _, c, m in make_reader(f).iter_messages()]
    want = [(tp, k, ns, ns, data) for ns, t, js, k, d in steps for tp, data in expected(ns, t, js, k, d)]
    assert got == want
