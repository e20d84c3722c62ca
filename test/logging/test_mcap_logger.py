"""The MCAP logger alone (no node): ROS 2 conventions, both readers, rollover, crash recovery."""
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("redmax_msgs.msg", reason="redmax_msgs not built (scripts/setup.sh builds msg_defs/)")

from geometry_msgs.msg import Vector3  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from redmax_msgs.msg import PointForces  # noqa: E402
from redmax_ros.logging.mcap_log import McapLogger, message_definition, recover  # noqa: E402


def _js(i):
    m = JointState(name=["a", "b[0]"], position=[i * 0.5, -1.0], velocity=[0.25, float(i)], effort=[1e-3, 2.0])
    m.header.stamp.sec, m.header.stamp.nanosec = i // 1000, (i % 1000) * 1_000_000
    return m


def _write(logger, n, start=0):
    sent = []
    for i in range(start, start + n):
        m = _js(i)
        logger.write("/joint_states", serialize_message(m), log_time_ns=1_000_000_000 + i * 1_000_000)
        sent.append(m)
        if i % 10 == 0:
            pf = PointForces(sites=["tip"], forces=[Vector3(x=float(i), y=0.5, z=-2.0)])
            logger.write("/point_forces", serialize_message(pf), log_time_ns=1_000_000_000 + i * 1_000_000)
    return sent


def _read_mcap_ros2(path, topic):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        return [m for _, _, _, m in r.iter_decoded_messages(topics=[topic])]


def _read_rosbags(path, topic):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        conns = [c for c in r.connections if c.topic == topic]
        if not conns:  # an empty list would mean "all connections"
            return []
        return [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]


def _same(a, b):
    return (list(a.name) == list(b.name) and a.header.stamp.sec == b.header.stamp.sec
            and a.header.stamp.nanosec == b.header.stamp.nanosec
            and all(np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
                    for f in ("position", "velocity", "effort")))


def _logger(tmp_path, **kw):
    lg = McapLogger(tmp_path / "run", "t", **kw)
    lg.add_topic("/joint_states", "sensor_msgs/msg/JointState", [{"depth": 100}])
    lg.add_topic("/point_forces", "redmax_msgs/msg/PointForces", [{"depth": 1, "durability": "transient_local"}])
    return lg


def test_message_definition_has_dependencies_once():
    d = message_definition("redmax_msgs/msg/PointForces")
    assert d.startswith("# Forces required")
    for dep in ("std_msgs/Header", "geometry_msgs/Vector3", "builtin_interfaces/Time"):
        assert d.count(f"MSG: {dep}\n") == 1
    with pytest.raises(LookupError):
        message_definition("nope_msgs/msg/Nothing")


@pytest.mark.parametrize("read", [_read_mcap_ros2, _read_rosbags], ids=["mcap_ros2", "rosbags"])
def test_roundtrip_both_readers(tmp_path, read):
    lg = _logger(tmp_path)
    sent = _write(lg, 500)
    lg.close()
    assert lg.error is None and len(lg.files) == 1 and lg.written == lg.handed_over == 550
    got = read(lg.files[0], "/joint_states")
    assert len(got) == 500 and all(_same(a, b) for a, b in zip(got, sent))
    pf = read(lg.files[0], "/point_forces")
    assert [p.forces[0].x for p in pf] == [float(i) for i in range(0, 500, 10)]


def test_summary_statistics_and_qos(tmp_path):
    from mcap.reader import make_reader
    from rosbags.rosbag2.metadata import parse_qos

    lg = _logger(tmp_path)
    _write(lg, 100)
    lg.close()
    with open(lg.files[0], "rb") as f:
        r = make_reader(f)
        assert r.get_header().profile == "ros2"
        s = r.get_summary()
    assert s.statistics.message_count == 110 and s.statistics.channel_count == 2
    qos = {c.topic: parse_qos(c.metadata["offered_qos_profiles"])[0] for c in s.channels.values()}
    assert qos["/joint_states"].depth == 100
    assert qos["/point_forces"].durability.name == "TRANSIENT_LOCAL"


def test_rollover_by_size_loses_nothing(tmp_path):
    lg = _logger(tmp_path, max_bytes=20_000, chunk_size=4_000, compression="none")
    sent = _write(lg, 2000)
    lg.close()
    assert len(lg.files) > 2
    got = [m for f in lg.files for m in _read_rosbags(f, "/joint_states")]
    assert len(got) == 2000 and all(_same(a, b) for a, b in zip(got, sent))
    for f in lg.files:  # every file is complete on its own (channels and schemas repeated)
        assert _read_mcap_ros2(f, "/joint_states")


def test_topic_allow_list(tmp_path):
    lg = McapLogger(tmp_path / "run", "t", topics=["/point_forces"])
    assert not lg.add_topic("/joint_states", "sensor_msgs/msg/JointState")
    assert lg.add_topic("/point_forces", "redmax_msgs/msg/PointForces")
    _write(lg, 100)
    lg.close()
    assert len(_read_rosbags(lg.files[0], "/point_forces")) == 10
    assert _read_rosbags(lg.files[0], "/joint_states") == []


def test_recover_after_hard_kill(tmp_path):
    """A file cut mid-way (no summary, no footer, a torn chunk) is recovered up to the last whole chunk."""
    lg = _logger(tmp_path, chunk_size=8_000)
    sent = _write(lg, 3000)
    lg.flush()
    path = lg.files[0]
    size_flushed = path.stat().st_size
    lg.close()
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: size_flushed - 5000])  # tear the last chunk, lose the summary
    from mcap.reader import make_reader
    with open(cut, "rb") as f, pytest.raises(Exception):
        list(make_reader(f).iter_messages())
    fixed = tmp_path / "fixed.mcap"
    n = recover(cut, fixed)
    got = _read_rosbags(fixed, "/joint_states")
    assert 0 < len(got) < 3000 and n >= len(got)
    assert all(_same(a, b) for a, b in zip(got, sent))  # a prefix, intact
    assert len(_read_mcap_ros2(fixed, "/joint_states")) == len(got)


@pytest.mark.parametrize("writer", ["process", "thread"])
def test_both_writers_roundtrip(tmp_path, writer):
    lg = _logger(tmp_path, writer=writer)
    sent = _write(lg, 300)
    assert lg.flush()
    assert lg.written == lg.handed_over == 330 and lg.backlog == 0
    sent += _write(lg, 200, start=300)
    lg.close()
    assert lg.error is None and lg.written == lg.handed_over == 550
    got = _read_rosbags(lg.files[0], "/joint_states")
    assert len(got) == 500 and all(_same(a, b) for a, b in zip(got, sent))


@pytest.mark.parametrize("writer", ["process", "thread"])
def test_write_many_mixes_with_write(tmp_path, writer):
    """write_many (the node's per-step call): one log time for its messages, per-topic sequence
    numbers continue across write and write_many, unknown topics are skipped."""
    from mcap.reader import make_reader

    lg = _logger(tmp_path, writer=writer)
    sent = []
    for i in range(50):
        m, pf = _js(i), PointForces(sites=["tip"], forces=[Vector3(x=float(i), y=0.0, z=0.0)])
        sent.append(m)
        if i % 2:
            lg.write("/joint_states", serialize_message(m), log_time_ns=10 + i)
        else:
            lg.write_many([("/joint_states", serialize_message(m)), ("/not_logged", b"x"),
                           ("/point_forces", serialize_message(pf))], log_time_ns=10 + i)
    lg.close()
    assert lg.error is None and lg.written == lg.handed_over == 75
    got = _read_rosbags(lg.files[0], "/joint_states")
    assert len(got) == 50 and all(_same(a, b) for a, b in zip(got, sent))
    with open(lg.files[0], "rb") as f:
        msgs = [(c.topic, m.sequence, m.log_time, m.publish_time) for _, c, m in make_reader(f).iter_messages()]
    js = [x for x in msgs if x[0] == "/joint_states"]
    assert [x[1] for x in js] == list(range(1, 51)) and [x[2] for x in js] == [10 + i for i in range(50)]
    pf = [x for x in msgs if x[0] == "/point_forces"]
    assert [x[1] for x in pf] == list(range(1, 26)) and all(x[2] == x[3] for x in pf)
    assert [x[2] for x in pf] == [10 + i for i in range(0, 50, 2)]


def test_writer_process_ignores_sigint_and_sigterm(tmp_path):
    """Ctrl-C / a stop signal to the process group must not cut the log short while the node drains."""
    import signal
    import time

    lg = _logger(tmp_path)
    sent = _write(lg, 200)
    assert lg.flush()
    os.kill(lg._proc.pid, signal.SIGINT)
    os.kill(lg._proc.pid, signal.SIGTERM)
    time.sleep(0.2)
    sent += _write(lg, 200, start=200)
    lg.close()
    assert lg.error is None and lg._proc.returncode == 0
    got = _read_mcap_ros2(lg.files[0], "/joint_states")
    assert len(got) == 400 and all(_same(a, b) for a, b in zip(got, sent))


def test_writer_process_finishes_the_file_when_its_owner_is_killed(tmp_path):
    """SIGKILL of the logging process: everything already handed to the writer process is in a
    complete file (summary and footer), no recovery needed."""
    import subprocess
    import sys
    import time

    code = f"""
import os, signal, sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
from test_mcap_logger import _logger, _write
from pathlib import Path
lg = _logger(Path({str(tmp_path)!r}))
_write(lg, 1000)
assert lg.flush()
print(lg._proc.pid, flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == -9, p.stderr
    writer_pid = int(p.stdout.split()[0])
    end = time.monotonic() + 20
    while time.monotonic() < end:  # the orphaned writer sees EOF, finishes the file and exits
        try:
            os.kill(writer_pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        pytest.fail("the writer process did not exit after its owner was killed")
    path = tmp_path / "run" / "t_0.mcap"
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count == 1100
    got = _read_rosbags(path, "/joint_states")
    assert len(got) == 1000


def test_file_layout_indexes_and_crcs(tmp_path):
    """Our MCAP writer against the spec, record by record: every MessageIndex entry points at a
    message of that channel and log time inside its (decompressed) chunk, every ChunkIndex at its
    Chunk and MessageIndex records, Statistics match, the chunk and summary CRCs hold; and the
    non-seeking reader agrees with the indexed one."""
    import struct
    import zlib

    import zstandard
    from mcap.reader import NonSeekingReader, SeekingReader
    from mcap.records import Chunk, ChunkIndex, Footer, Statistics
    from mcap.stream_reader import StreamReader

    lg = _logger(tmp_path, chunk_size=8_000)
    _write(lg, 700)
    lg.close()
    path = lg.files[0]
    raw = path.read_bytes()
    n_chunks, chunk_indexes, stats, footer = 0, [], None, None
    with open(path, "rb") as f:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                n_chunks += 1
            elif isinstance(rec, ChunkIndex):
                chunk_indexes.append(rec)
            elif isinstance(rec, Statistics):
                stats = rec
            elif isinstance(rec, Footer):
                footer = rec
    assert len(chunk_indexes) == n_chunks > 3 and stats.chunk_count == n_chunks
    n_indexed = 0
    for ci in chunk_indexes:
        op, length = struct.unpack_from("<BQ", raw, ci.chunk_start_offset)
        assert op == 0x06 and 9 + length == ci.chunk_length
        start, end, usize, ucrc = struct.unpack_from("<QQQI", raw, ci.chunk_start_offset + 9)
        clen = struct.unpack_from("<I", raw, ci.chunk_start_offset + 37)[0]
        comp = raw[ci.chunk_start_offset + 41:ci.chunk_start_offset + 41 + clen].decode()
        dlen = struct.unpack_from("<Q", raw, ci.chunk_start_offset + 41 + clen)[0]
        body = raw[ci.chunk_start_offset + 49 + clen:ci.chunk_start_offset + 49 + clen + dlen]
        data = zstandard.ZstdDecompressor().decompress(body, max_output_size=usize) if comp == "zstd" else body
        assert len(data) == usize == ci.uncompressed_size and zlib.crc32(data) == ucrc
        assert (start, end) == (ci.message_start_time, ci.message_end_time)
        assert ci.message_index_offsets
        total = 0
        for cid, off in ci.message_index_offsets.items():
            op, length = struct.unpack_from("<BQ", raw, off)
            ch, rlen = struct.unpack_from("<HI", raw, off + 9)
            assert op == 0x07 and ch == cid and rlen == length - 6
            total += 9 + length
            for k in range(rlen // 16):
                t, o = struct.unpack_from("<QQ", raw, off + 15 + 16 * k)
                mop, _ = struct.unpack_from("<BQ", data, o)
                mch, _, mt = struct.unpack_from("<HIQ", data, o + 9)
                assert mop == 0x05 and mch == cid and mt == t and start <= t <= end
                n_indexed += 1
        assert total == ci.message_index_length
    assert n_indexed == stats.message_count == 770
    # summary CRC as the spec defines it
    summary = raw[footer.summary_start:len(raw) - 8 - 29]
    head = struct.pack("<BQQQ", 0x02, 20, footer.summary_start, footer.summary_offset_start)
    assert zlib.crc32(head, zlib.crc32(summary)) == footer.summary_crc
    with open(path, "rb") as f:
        indexed = [(c.topic, m.log_time, m.data) for _, c, m in SeekingReader(f).iter_messages(log_time_order=False)]
    with open(path, "rb") as f:
        streamed = [(c.topic, m.log_time, m.data) for _, c, m in NonSeekingReader(f).iter_messages()]
    assert len(indexed) == 770 and sorted(indexed) == sorted(streamed)


@pytest.mark.parametrize("chunk_size", [100, 4_096, 256 * 1024])
def test_add_records_writes_what_add_message_writes(chunk_size):
    """The writer process's bulk path (_McapFile.add_records: records indexed one by one, copied as
    one span) gives the file add_message gives for the same messages, byte for byte, whatever the
    chunk size and wherever the reads split the records; a record of an unknown channel stops it
    with an error and leaves the chunk consistent with its index (the records before it in both)."""
    import io
    import random

    from mcap.reader import make_reader

    from redmax_ros.logging.mcap_log import MESSAGE_HEAD, OP_MESSAGE, _McapFile

    rng = random.Random(chunk_size)
    msgs, t = [], 1_000_000_000
    for step in range(600):
        t += rng.randint(1, 200_000)
        for cid, size in ((1, 300), (2, 12), (3, 90)):
            msgs.append((cid, step + 1, t - rng.randint(0, 1000) * (cid == 3), bytes(rng.getrandbits(8) for _ in range(size))))
    records = b"".join(MESSAGE_HEAD.pack(OP_MESSAGE, 22 + len(d), cid, seq, lt, lt) + d for cid, seq, lt, d in msgs)

    def new_file(size=chunk_size):
        f = io.BytesIO()
        w = _McapFile(f, "ros2", "test", size, "")
        for c in (1, 2, 3):
            w.add_channel(f"/t{c}", "cdr", 0, {})
        return f, w

    fa, wa = new_file()
    for cid, seq, lt, d in msgs:
        wa.add_message(cid, seq, lt, lt, d)
    wa.finish()
    fb, wb = new_file()
    pos = 0
    while pos < len(records):
        end = min(len(records), pos + rng.randint(1, 5_000))  # a read: may end inside a record
        while True:
            pos, _, finalized = wb.add_records(records, pos, end, 3)
            if not finalized:
                break
    wb.finish()
    assert fb.getvalue() == fa.getvalue()
    fb.seek(0)
    got = [(c.id, m.sequence, m.log_time, bytes(m.data)) for _, c, m in make_reader(fb).iter_messages(log_time_order=False)]
    assert got == msgs

    fc, wc = new_file(256 * 1024)  # the chunk does not fill before the bad record
    bad = MESSAGE_HEAD.pack(OP_MESSAGE, 22 + 4, 9, 1, t, t) + b"abcd"
    first = records[:len(records) // 600]  # the first step's three records
    with pytest.raises(ValueError, match="unknown channel 9"):
        wc.add_records(first + bad, 0, len(first) + len(bad), 3)
    assert bytes(wc.chunk) == first and sum(len(ix) for ix in wc.index.values()) == 2 * 3
