"""The node as a subprocess with MCAP logging: commands over DDS, SIGINT mid-run, logs read back
with mcap_ros2 AND rosbags and compared with what the client received."""
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from node_fixtures import Client  # noqa: F401  (test/node/node_fixtures.py; first: skips without ROS)

from redmax_msgs.msg import Result, SimulationState  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PID = os.getpid()  # namespace of our own, in case another run shares the ROS domain


def _stamp_ns(st):
    return st.sec * 1_000_000_000 + st.nanosec


@pytest.fixture(scope="module")
def run(tmp_path_factory, ros):
    """Start the node (hand, lockstep, logging), drive it, then SIGINT it while playing."""
    logdir = tmp_path_factory.mktemp("logs")
    cmd = [sys.executable, "-m", "redmax_ros.node.main", "--ros-args", "--params-file",
           str(ROOT / "config" / "hand.yaml"), "-p", "mode:=lockstep", "-p", f"log_path:={logdir}",
           "-p", "command_timeout:=100.0", "-p", "marker_rate:=50.0", "-p", "real_time_factor:=0.0",
           "-p", "diagnostics_period:=0.2", "-r", f"__ns:=/sim{PID}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    client = Client("mcap_test_client", ns=f"/sim{PID}")
    out = {"logdir": logdir}
    try:
        client.wait_ready(timeout=30)
        # lockstep: prescribe joints, step, and read back
        client.command_joints(["elbow", "wrist[0]", "wrist[1]"], [0.4, 0.1, -0.1])
        r = client.step(40)
        assert r.result.result == Result.OK, r.result.error_message
        client.wait_for(lambda: len([j for j in client.joint_states if _stamp_ns(j.header.stamp) > 0]) >= 40,
                        what="40 states")
        out["lockstep_states"] = [j for j in client.joint_states if _stamp_ns(j.header.stamp) > 0][:40]
        # a bad command (logged as received, rejected by the node)
        client.command_joints(["nope"], [1.0], wait_ack=False)
        client.wait_for(lambda: any("unknown joint 'nope'" in e for e in client.errors()), what="error")
        # free-run, then SIGINT mid-run
        assert client.set_state(SimulationState.PLAYING).result.result == Result.OK
        n0 = len(client.joint_states)
        client.wait_for(lambda: len(client.joint_states) > n0 + 300, what="free-run states")
        proc.send_signal(signal.SIGINT)
        out["returncode"] = proc.wait(30)
        time.sleep(0.2)
        with client.lock:
            out["received"] = list(client.joint_states)
    finally:
        if proc.poll() is None:
            proc.kill()
        out["output"] = proc.stdout.read()
        client.close()
    return out


def test_subprocess_prescribed_velocities_match(run):
    names = list(run["lockstep_states"][0].name)
    for js in run["lockstep_states"]:
        assert js.velocity[names.index("elbow")] == pytest.approx(0.4, abs=1e-9)
        assert js.velocity[names.index("wrist[0]")] == pytest.approx(0.1, abs=1e-9)
        assert js.velocity[names.index("wrist[1]")] == pytest.approx(-0.1, abs=1e-9)
    stamps = [_stamp_ns(j.header.stamp) for j in run["lockstep_states"]]
    assert stamps == [k * 1_000_000 for k in range(1, 41)]


def test_sigint_closes_cleanly(run):
    assert run["returncode"] == 0, run["output"]
    files = sorted(Path(run["logdir"]).rglob("*.mcap"))
    assert len(files) == 1
    from mcap.reader import make_reader
    with open(files[0], "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0  # summary + footer written


def _mcap_file(run):
    return sorted(Path(run["logdir"]).rglob("*.mcap"))[0]


def test_log_has_ros2_conventions(run):
    from mcap.reader import make_reader
    from rosbags.rosbag2.metadata import parse_qos

    with open(_mcap_file(run), "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
    assert header.profile == "ros2"
    topics = {c.topic: c for c in summary.channels.values()}
    ns = f"/sim{PID}"
    for t in [f"{ns}/joint_states", "/clock", f"{ns}/point_forces", f"{ns}/solver_stats", f"{ns}/markers",
              "/diagnostics", f"{ns}/simulation_state", f"{ns}/prescribed_joints", f"{ns}/joint_commands"]:
        assert t in topics, t
    for c in summary.channels.values():
        assert c.message_encoding == "cdr"
        schema = summary.schemas[c.schema_id]
        assert schema.encoding == "ros2msg" and "/msg/" in schema.name
        assert parse_qos(c.metadata["offered_qos_profiles"])  # rosbag2 YAML that parses
    js_schema = summary.schemas[topics[f"/sim{PID}/joint_states"].schema_id].data.decode()
    assert "MSG: std_msgs/Header" in js_schema and "MSG: builtin_interfaces/Time" in js_schema
    assert summary.statistics.channel_message_counts[topics[f"/sim{PID}/joint_commands"].id] >= 2


def _decode_mcap_ros2(path, topic):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [m for _, _, _, m in reader.iter_decoded_messages(topics=[topic])]


def _decode_rosbags(path, topic):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out = []
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:  # an empty list would mean "all connections"
            return []
        for conn, _, raw in reader.messages(connections=conns):
            out.append(reader.deserialize(raw, conn.msgtype))
    return out


@pytest.mark.parametrize("decode", [_decode_mcap_ros2, _decode_rosbags], ids=["mcap_ros2", "rosbags"])
def test_logged_joint_states_equal_published(run, decode):
    logged = decode(_mcap_file(run), f"/sim{PID}/joint_states")
    by_stamp = {}
    for m in logged:
        by_stamp.setdefault(_stamp_ns(m.header.stamp), m)
    received = [j for j in run["received"] if _stamp_ns(j.header.stamp) > 0]
    assert len(received) > 300
    for js in received:  # everything the client got is in the log, bit for bit
        m = by_stamp[_stamp_ns(js.header.stamp)]
        assert list(m.name) == list(js.name)
        for field in ("position", "velocity", "effort"):
            assert np.array_equal(np.asarray(getattr(m, field)), np.asarray(getattr(js, field))), field
    # and the log has every published step of the run, in order, none lost
    stamps = sorted(s for s in by_stamp if s > 0)
    assert stamps == [k * 1_000_000 for k in range(1, len(stamps) + 1)]
    assert len(stamps) >= max(_stamp_ns(j.header.stamp) for j in received) // 1_000_000


@pytest.mark.parametrize("decode", [_decode_mcap_ros2, _decode_rosbags], ids=["mcap_ros2", "rosbags"])
def test_logged_commands_equal_sent(run, decode):
    cmds = decode(_mcap_file(run), f"/sim{PID}/joint_commands")
    assert [list(c.name) for c in cmds] == [["elbow", "wrist[0]", "wrist[1]"], ["nope"]]
    assert list(cmds[0].velocity) == [0.4, 0.1, -0.1]
    diags = decode(_mcap_file(run), "/diagnostics")
    assert diags and all(math.isfinite(float(kv.value)) for kv in diags[-1].status[0].values
                         if kv.key == "real_time_factor")


def test_logged_clock_and_solver_stats_follow_joint_states(run):
    """Every logged step has its joint_states, /clock and solver_stats, in this order with one log
    time (the node builds these records in one piece when logging; cdr.StepRecords)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    ns = f"/sim{PID}"
    want = (f"{ns}/joint_states", "/clock", f"{ns}/solver_stats")
    with open(_mcap_file(run), "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        msgs = [(c.topic, m.log_time, d) for _, c, m, d in reader.iter_decoded_messages(topics=list(want),
                                                                                       log_time_order=False)]
    stepped = [i for i, (tp, _, d) in enumerate(msgs) if tp == want[0] and _stamp_ns(d.header.stamp) > 0]
    assert len(stepped) > 300
    for i in stepped:
        (_, t0, js), (tc, t1, clk), (ts, t2, st) = msgs[i:i + 3]
        assert (tc, ts) == want[1:] and t0 == t1 == t2
        stamp = _stamp_ns(js.header.stamp)
        assert _stamp_ns(clk.clock) == stamp and _stamp_ns(st.header.stamp) == stamp
        assert st.step == stamp // 1_000_000 and st.solver and math.isfinite(st.residual)


def test_logged_steps_in_order_with_consecutive_sequences(run):
    """Recorded runs are logged in one piece per run (RedmaxNode.run_states): read back in file order
    (mcap and rosbags), every step's joint_states follows the step before it (stamps strictly
    increasing), log times never go back, and each channel's sequence numbers count up by one."""
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    ns = f"/sim{PID}"
    with open(_mcap_file(run), "rb") as f:
        msgs = [(c.topic, m.sequence, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]
    seqs = {}
    for topic, seq, _, _ in msgs:
        seqs.setdefault(topic, []).append(seq)
    for topic, s in seqs.items():
        assert s == list(range(s[0], s[0] + len(s))), topic
    times = [t for _, _, t, _ in msgs]
    assert times == sorted(times)
    with AnyReader([_mcap_file(run)]) as reader:
        conns = [c for c in reader.connections if c.topic == f"{ns}/joint_states"]
        stamps = [_stamp_ns(reader.deserialize(raw, c.msgtype).header.stamp)
                  for c, _, raw in reader.messages(connections=conns)]
    stepped = [s for s in stamps if s > 0]
    assert len(stepped) > 300 and all(b > a for a, b in zip(stepped, stepped[1:]))
