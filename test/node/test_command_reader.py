"""The command reader drops, unread, a joint command that a newer one with the same names and filled
fields supersedes within one drain (node/command_reader.py); it reads those keys straight from the CDR
(node/cdr.joint_state_key). Checked against rclpy's serializer on random messages, on truncated and
foreign bytes, and on the supersession rule itself. The latest command winning under a real flood over
Fast DDS is test_node_abuse.test_flood_of_commands_is_coalesced_and_the_latest_wins."""
import numpy as np
import pytest

pytest.importorskip("rclpy", reason="rclpy not installed (scripts/setup.sh)")

from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from redmax_ros.node.cdr import joint_state_key  # noqa: E402
from redmax_ros.node.command_reader import CommandReader  # noqa: E402


def _random_state(rng):
    n = int(rng.integers(0, 5))
    names = ["".join(rng.choice(list("abcxyz[]_0123"), size=int(rng.integers(1, 12)))) for _ in range(n)]
    msg = JointState(name=names)
    msg.header.frame_id = "f" * int(rng.integers(0, 10))
    msg.header.stamp.sec = int(rng.integers(0, 2**31 - 1))
    for field in ("position", "velocity", "effort"):
        k = int(rng.integers(0, 3))
        if k:  # filled: as many as names, or a wrong length (the key does not judge validity)
            setattr(msg, field, rng.normal(size=n if k == 1 else int(rng.integers(1, 6))).tolist())
    return msg


def test_key_matches_the_message_for_random_states():
    rng = np.random.default_rng(7)
    for _ in range(300):
        msg = _random_state(rng)
        key = joint_state_key(serialize_message(msg))
        assert key == (tuple(s.encode() for s in msg.name), len(msg.position) > 0, len(msg.velocity) > 0,
                       len(msg.effort) > 0)


def test_key_of_truncated_or_foreign_bytes_is_none_or_exact():
    """Cut anywhere, the bytes give no key or (when only trailing padding was cut) the same key; never an
    exception nor a wrong key."""
    rng = np.random.default_rng(8)
    for _ in range(40):
        raw = serialize_message(_random_state(rng))
        full = joint_state_key(raw)
        for cut in range(len(raw)):
            k = joint_state_key(raw[:cut])
            assert k is None or k == full
    assert joint_state_key(b"") is None
    assert joint_state_key(b"\x01\x00\x00\x00" + bytes(64)) is None  # big-endian CDR: not read here
    assert joint_state_key(b"\x00\x01\x00\x00" + b"\xff" * 64) is None  # counts beyond the data


def test_only_a_newer_message_with_the_same_key_supersedes():
    key = {b"a1": "A", b"b1": "B", b"a2": "A", b"x": None, b"a3": "A", b"b2": "B"}.get
    msgs = [b"a1", b"b1", b"a2", b"x", b"a3", b"x"]
    assert CommandReader._stale(msgs, key) == {0, 2}  # a1, a2 superseded by a3; b1 is the newest B
    assert CommandReader._stale(msgs + [b"b2"], key) == {0, 1, 2}
    assert CommandReader._stale([b"x", b"x"], key) == set()  # unreadable messages are all processed
