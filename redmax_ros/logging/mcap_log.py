"""MCAP logging with ROS 2 conventions, off the caller's interpreter.

Files follow what rosbag2's MCAP storage plugin writes, so ``ros2 bag info/play`` and Foxglove
open them: profile ``ros2``, message encoding ``cdr``, schemas encoded ``ros2msg`` holding the
full definition with its dependencies (``====`` + ``MSG: pkg/Type`` blocks), channel metadata
``offered_qos_profiles`` (YAML as rosbag2 writes it), and a summary with a Statistics record.

The caller hands over *already serialized* CDR bytes (the node serializes once and publishes the
same bytes), so this module needs no rclpy. By default the MCAP work (chunks, indexes, zstd,
file I/O) runs in a separate writer process (``writer_process.py``) fed through a pipe: ``write``
appends the bytes as a finished MCAP Message record to a buffer (~1 us), a sender thread hands
the buffer over every ``batch_interval``, and the process copies the records into chunks
(:class:`_McapFile`, ~2-3 us a message). The interpreter that steps the simulation pays almost
nothing (measured in docs/node.md). Files roll
over by size or by duration; ``close`` drains everything, so nothing handed to ``write`` before
``close`` is lost; if the calling process dies without ``close``, the writer still finishes the
file (only the last ``batch_interval`` of messages, not yet handed over, is lost).

Crash safety when the writer itself is killed (SIGKILL of the process group, power loss): chunks
are finalized every ``flush_interval`` seconds (and whenever a chunk reaches ``chunk_size``), so
everything but the last unfinished chunk is on disk; the file then lacks its summary and footer,
and :func:`recover` (``python -m redmax_ros.logging.mcap_log recover in.mcap out.mcap``) or
``mcap recover`` rewrites the readable part into a valid file.
"""
from __future__ import annotations

import argparse
import fcntl
import json
import os
import queue
import re
import struct
import subprocess
import sys
import threading
import time
import zlib
from array import array
from pathlib import Path

from mcap.records import Channel, Header, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

__all__ = ["McapLogger", "message_definition", "qos_profiles_yaml", "recover"]

LIBRARY = "redmax_ros.logging.mcap_log"

_PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
}
_SEPARATOR = "=" * 80


# ------------------------------------------------------------------------------------------------
# message definitions (ros2msg schema text with dependencies)

def _share_dirs():
    seen = []
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) + [sys.prefix]:
        if prefix and prefix not in seen:
            seen.append(prefix)
    return [Path(p) / "share" for p in seen]


def _find_msg_file(pkg: str, name: str) -> Path:
    for share in _share_dirs():
        cand = share / pkg / "msg" / f"{name}.msg"
        if cand.is_file():
            return cand
    raise LookupError(f"message definition {pkg}/msg/{name}.msg not found under AMENT_PREFIX_PATH "
                      f"or {sys.prefix}/share")


def _split_type(type_name: str):
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f"not a message type name: {type_name!r} (expected pkg/msg/Type)")


def _dependencies(pkg: str, text: str):
    deps = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        ftype = line.split()[0]
        if "=" in ftype:  # e.g. "uint8 A=1" written without spaces is a constant, no dependency
            continue
        base = re.sub(r"\[.*\]$", "", ftype)  # arrays
        base = re.sub(r"<=\d+$", "", base)  # bounded strings
        if base in _PRIMITIVES:
            continue
        if base == "Header":
            deps.append(("std_msgs", "Header"))
        elif "/" in base:
            dp, dn = _split_type(base)
            deps.append((dp, dn))
        else:
            deps.append((pkg, base))
    return deps


_DEF_CACHE: dict = {}


def message_definition(type_name: str) -> str:
    """Full ros2msg definition of ``pkg/msg/Type`` with every dependency appended once, in the
    layout rosbag2 uses (``====`` separator line, ``MSG: pkg/Type``)."""
    if type_name in _DEF_CACHE:
        return _DEF_CACHE[type_name]
    pkg, name = _split_type(type_name)
    main = _find_msg_file(pkg, name).read_text()
    parts, done, todo = [main.rstrip("\n")], set(), list(_dependencies(pkg, main))
    while todo:
        dp, dn = todo.pop(0)
        if (dp, dn) in done:
            continue
        done.add((dp, dn))
        text = _find_msg_file(dp, dn).read_text()
        parts.append(f"{_SEPARATOR}\nMSG: {dp}/{dn}\n{text.rstrip(chr(10))}")
        todo.extend(_dependencies(dp, text))
    out = "\n".join(parts) + "\n"
    _DEF_CACHE[type_name] = out
    return out


# ------------------------------------------------------------------------------------------------
# QoS metadata

_INFINITE = {"sec": 9223372036, "nsec": 854775807}  # RMW_DURATION_INFINITE


def qos_profiles_yaml(profiles) -> str:
    """``offered_qos_profiles`` channel metadata as rosbag2 (Jazzy) writes it.

    ``profiles``: list of dicts with keys history ("keep_last"/"keep_all"), depth, reliability
    ("reliable"/"best_effort"), durability ("volatile"/"transient_local"); missing keys take ROS
    defaults, durations are written as infinite."""
    lines = []
    for p in profiles:
        lines += [
            f"- history: {p.get('history', 'keep_last')}",
            f"  depth: {int(p.get('depth', 10))}",
            f"  reliability: {p.get('reliability', 'reliable')}",
            f"  durability: {p.get('durability', 'volatile')}",
            "  deadline:", f"    sec: {_INFINITE['sec']}", f"    nsec: {_INFINITE['nsec']}",
            "  lifespan:", f"    sec: {_INFINITE['sec']}", f"    nsec: {_INFINITE['nsec']}",
            f"  liveliness: {p.get('liveliness', 'automatic')}",
            "  liveliness_lease_duration:", f"    sec: {_INFINITE['sec']}", f"    nsec: {_INFINITE['nsec']}",
            "  avoid_ros_namespace_conventions: false",
        ]
    return "\n".join(lines) + ("\n" if lines else "")


# ------------------------------------------------------------------------------------------------
# a lean MCAP writer (the hot loop of the writer process)

MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_OP_MESSAGE_INDEX, _OP_CHUNK_INDEX, _OP_STATISTICS, _OP_SUMMARY_OFFSET, _OP_DATA_END = 0x07, 0x08, 0x0B, 0x0E, 0x0F
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel id, sequence, log time, publish time
MESSAGE_HEAD, OP_MESSAGE = _MESSAGE_HEAD, _OP_MESSAGE  # for callers building records (McapLogger.write_records)
_RECORD_HEAD = struct.Struct("<BQ")
_CHANNEL_TIME = struct.Struct("<H4xQ")  # channel id and log time of a Message record's content


def _s(text: str) -> bytes:
    b = text.encode()
    return struct.pack("<I", len(b)) + b


def _record(op: int, content: bytes) -> bytes:
    return struct.pack("<BQ", op, len(content)) + content


class _McapFile:
    """Writes the same MCAP layout as ``mcap.writer.Writer`` (chunked, message indexes, a summary
    with schemas, channels, Statistics and chunk indexes, summary offsets, summary CRC) with one
    struct.pack per message; ``mcap.writer.Writer`` builds every record field by field and cost
    ~11 us a message in the writer process, this ~2 us. Schemas and channels are written in the
    data section outside chunks, so a torn last chunk never takes them along. The format is
    checked by the tests with three readers (mcap, mcap_ros2, rosbags)."""

    def __init__(self, f, profile: str, library: str, chunk_size: int, compression: str):
        self.f = f
        self.chunk_size = chunk_size
        self.compression = compression  # "zstd", "lz4" or ""
        if compression == "zstd":
            import zstandard  # optional: zstd compression (the default); lz4 and none work without it
            self._compress = zstandard.ZstdCompressor(level=1).compress
        elif compression == "lz4":
            import lz4.frame  # optional: only for compression="lz4"
            self._compress = lz4.frame.compress
        else:
            self._compress = None
        self.schemas: list[bytes] = []
        self.channels: list[bytes] = []
        self.chunk_indexes: list[bytes] = []
        self.counts: dict[int, int] = {}
        self.message_count = 0
        self.start_time = self.end_time = None
        self.chunk_count = 0
        self._reset_chunk()
        f.write(MAGIC)
        f.write(_record(_OP_HEADER, _s(profile) + _s(library)))

    def _reset_chunk(self):
        self.chunk = bytearray()
        self.index: dict[int, array] = {}
        self.chunk_start = self.chunk_end = None

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self.schemas) + 1
        rec = _record(_OP_SCHEMA, struct.pack("<H", sid) + _s(name) + _s(encoding) + struct.pack("<I", len(data)) + data)
        self.schemas.append(rec)
        self.f.write(rec)
        return sid

    def add_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: dict) -> int:
        cid = len(self.channels) + 1
        meta = b"".join(_s(k) + _s(v) for k, v in metadata.items())
        rec = _record(_OP_CHANNEL, struct.pack("<HH", cid, schema_id) + _s(topic) + _s(message_encoding)
                      + struct.pack("<I", len(meta)) + meta)
        self.channels.append(rec)
        self.f.write(rec)
        return cid

    def add_message(self, cid: int, sequence: int, log_time: int, publish_time: int, data):
        chunk = self.chunk
        off = len(chunk)
        chunk += _MESSAGE_HEAD.pack(_OP_MESSAGE, 22 + len(data), cid, sequence & 0xFFFFFFFF, log_time, publish_time)
        chunk += data
        idx = self.index.get(cid)
        if idx is None:
            idx = self.index[cid] = array("Q")
        idx.append(log_time)
        idx.append(off)
        if self.chunk_start is None:
            self.chunk_start = self.chunk_end = log_time
        elif log_time < self.chunk_start:
            self.chunk_start = log_time
        elif log_time > self.chunk_end:
            self.chunk_end = log_time
        if len(chunk) > self.chunk_size:
            self.finalize_chunk()

    def add_records(self, buf, pos: int, end: int, max_channel: int):
        """Copy the complete Message records in ``buf[pos:end]`` into the open chunk, up to the
        first other record, an incomplete one, or the chunk becoming full (then finalized).
        Returns (new position, messages copied, whether a chunk was finalized). The records are
        indexed one by one and copied as one span (one bytearray extend, not one per record)."""
        chunk, index, head, cid_time = self.chunk, self.index, _RECORD_HEAD, _CHANNEL_TIME
        start, stop_time = self.chunk_start, self.chunk_end
        span = pos
        base = len(chunk) - span  # a record at buf[p] lands at chunk[base + p]
        full = self.chunk_size - base  # a record ending past buf[full] makes the chunk exceed chunk_size
        n = 0
        finalized = False
        while end - pos >= 31:
            op, length = head.unpack_from(buf, pos)
            if op != _OP_MESSAGE:
                break
            stop = pos + 9 + length
            if stop > end:
                break
            cid, log_time = cid_time.unpack_from(buf, pos + 9)
            if not 0 < cid <= max_channel:
                chunk += memoryview(buf)[span:pos]  # what is indexed is in the chunk
                self.chunk_start, self.chunk_end = start, stop_time
                raise ValueError(f"message record for unknown channel {cid}")
            idx = index.get(cid)
            if idx is None:
                idx = index[cid] = array("Q")
            idx.append(log_time)
            idx.append(base + pos)
            if start is None:
                start = stop_time = log_time
            elif log_time < start:
                start = log_time
            elif log_time > stop_time:
                stop_time = log_time
            n += 1
            pos = stop
            if pos > full:
                finalized = True
                break
        if pos > span:
            with memoryview(buf) as mv:
                chunk += mv[span:pos]
        self.chunk_start, self.chunk_end = start, stop_time
        if finalized:
            self.finalize_chunk()
        return pos, n, finalized

    def finalize_chunk(self):
        if self.chunk_start is None:
            return
        data = bytes(self.chunk)
        packed = self._compress(data) if self._compress is not None else data
        f = self.f
        chunk_offset = f.tell()
        content = (struct.pack("<QQQI", self.chunk_start, self.chunk_end, len(data), zlib.crc32(data))
                   + _s(self.compression) + struct.pack("<Q", len(packed)))
        f.write(struct.pack("<BQ", _OP_CHUNK, len(content) + len(packed)))
        f.write(content)
        f.write(packed)
        chunk_length = 9 + len(content) + len(packed)
        index_offsets = []
        index_start = pos = chunk_offset + chunk_length
        for cid in sorted(self.index):
            entries = self.index[cid]
            if sys.byteorder != "little":
                entries.byteswap()
            body = entries.tobytes()
            rec = struct.pack("<BQHI", _OP_MESSAGE_INDEX, 6 + len(body), cid, len(body)) + body
            f.write(rec)
            index_offsets.append(struct.pack("<HQ", cid, pos))
            pos += len(rec)
            n = len(entries) // 2
            self.counts[cid] = self.counts.get(cid, 0) + n
            self.message_count += n
        offsets = b"".join(index_offsets)
        self.chunk_indexes.append(_record(_OP_CHUNK_INDEX, struct.pack("<QQQQ", self.chunk_start, self.chunk_end,
                                                                        chunk_offset, chunk_length)
                                          + struct.pack("<I", len(offsets)) + offsets
                                          + struct.pack("<Q", pos - index_start) + _s(self.compression)
                                          + struct.pack("<QQ", len(packed), len(data))))
        if self.start_time is None:
            self.start_time, self.end_time = self.chunk_start, self.chunk_end
        else:
            self.start_time = min(self.start_time, self.chunk_start)
            self.end_time = max(self.end_time, self.chunk_end)
        self.chunk_count += 1
        self._reset_chunk()

    def flush(self):
        self.finalize_chunk()
        self.f.flush()

    def finish(self):
        """Last chunk, DataEnd, summary (schemas, channels, Statistics, chunk indexes), summary
        offsets, footer, magic."""
        self.finalize_chunk()
        f = self.f
        f.write(_record(_OP_DATA_END, struct.pack("<I", 0)))
        summary_start = f.tell()
        groups = []
        parts = []
        pos = summary_start
        counts = b"".join(struct.pack("<HQ", cid, n) for cid, n in sorted(self.counts.items()))
        stats = _record(_OP_STATISTICS, struct.pack("<QHIIIIQQ", self.message_count, len(self.schemas),
                                                     len(self.channels), 0, 0, self.chunk_count,
                                                     self.start_time or 0, self.end_time or 0)
                        + struct.pack("<I", len(counts)) + counts)
        for op, recs in ((_OP_SCHEMA, self.schemas), (_OP_CHANNEL, self.channels), (_OP_STATISTICS, [stats]),
                         (_OP_CHUNK_INDEX, self.chunk_indexes)):
            if not recs:
                continue
            blob = b"".join(recs)
            groups.append(_record(_OP_SUMMARY_OFFSET, struct.pack("<BQQ", op, pos, len(blob))))
            parts.append(blob)
            pos += len(blob)
        summary_offset_start = pos
        summary = b"".join(parts) + b"".join(groups)
        footer_head = struct.pack("<BQQQ", _OP_FOOTER, 20, summary_start, summary_offset_start)
        crc = zlib.crc32(footer_head, zlib.crc32(summary))
        f.write(summary)
        f.write(footer_head + struct.pack("<I", crc))
        f.write(MAGIC)
        f.flush()


# ------------------------------------------------------------------------------------------------
# the file side: one MCAP file after another (used by the writer process, or by a thread)

class Topic:
    __slots__ = ("topic", "type_name", "definition", "qos_yaml", "index", "seq")

    def __init__(self, topic, type_name, definition, qos_yaml, index):
        self.topic, self.type_name, self.definition = topic, type_name, definition
        self.qos_yaml, self.index = qos_yaml, index
        self.seq = 0  # last sequence number handed out (writer side)

    def to_json(self) -> bytes:
        return json.dumps({"topic": self.topic, "type": self.type_name, "definition": self.definition,
                           "qos": self.qos_yaml, "index": self.index}).encode()

    @classmethod
    def from_json(cls, data) -> "Topic":
        d = json.loads(bytes(data))
        return cls(d["topic"], d["type"], d["definition"], d["qos"], int(d["index"]))


_COMPRESSION = {"zstd": "zstd", "lz4": "lz4", "none": "", "": ""}


class FileSession:
    """Writes messages into ``<directory>/<basename>_<i>.mcap``, i = 0, 1, ...: schemas and channels
    registered in every file, chunks finalized at ``chunk_size`` and at least every
    ``flush_interval`` s (:meth:`tick`), rollover by size (checked at chunk granularity) or age.
    Single-threaded; ``on_open(path)`` is called for every new file."""

    def __init__(self, directory, basename, *, max_bytes=0, max_duration=0.0, chunk_size=256 * 1024,
                 compression="zstd", flush_interval=1.0, on_open=None):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.basename = basename
        self.max_bytes = int(max_bytes)
        self.max_duration = float(max_duration)
        self.chunk_size = int(chunk_size)
        self.compression = _COMPRESSION[compression]
        self.flush_interval = float(flush_interval)
        self.on_open = on_open
        self.files: list[Path] = []
        self.topics: dict[int, Topic] = {}
        self.seq: dict[int, int] = {}
        self.written = 0
        self.f = self.w = None
        self._open()

    def _open(self):
        path = self.directory / f"{self.basename}_{len(self.files)}.mcap"
        self.f = open(path, "wb")
        self.w = _McapFile(self.f, "ros2", LIBRARY, self.chunk_size, self.compression)
        self.files.append(path)
        self.chans: dict[int, int] = {}
        for t in self.topics.values():
            self._channel(t)
        self.opened = self.last_flush = time.monotonic()
        if self.on_open is not None:
            self.on_open(path)

    def _channel(self, t: Topic) -> int:
        cid = self.chans.get(t.index)
        if cid is None:
            sid = self.w.add_schema(t.type_name, "ros2msg", t.definition.encode())
            cid = self.w.add_channel(t.topic, "cdr", sid, {"offered_qos_profiles": t.qos_yaml})
            if cid != t.index + 1:  # callers write Message records with channel id = topic index + 1
                raise RuntimeError(f"channel {cid} for topic index {t.index}: topics registered out of order")
            self.chans[t.index] = cid
        return cid

    def register(self, t: Topic):
        """Channels exist in the file even before their first message."""
        self.topics[t.index] = t
        self._channel(t)

    def add(self, index: int, log_time: int, data, publish_time: int):
        cid = self.chans.get(index)
        if cid is None:
            cid = self._channel(self.topics[index])
        s = self.seq.get(index, 0) + 1
        self.seq[index] = s
        self.w.add_message(cid, s, log_time, publish_time, data)
        self.written += 1
        if self.max_bytes and self.f.tell() >= self.max_bytes:
            self._rollover()

    def add_records(self, buf, pos: int, end: int) -> int:
        """Copy ready-made Message records (see McapLogger.write) from ``buf[pos:end]`` into the
        file; returns the position of the first record that is not a complete Message."""
        while True:
            pos, n, finalized = self.w.add_records(buf, pos, end, len(self.topics))
            self.written += n
            if not finalized:
                return pos
            if self.max_bytes and self.f.tell() >= self.max_bytes:
                self._rollover()

    def next_deadline(self) -> float:
        """monotonic time of the next :meth:`tick` duty (chunk flush or rollover by age)."""
        due = self.last_flush + self.flush_interval
        if self.max_duration:
            due = min(due, self.opened + self.max_duration)
        return due

    def tick(self):
        now = time.monotonic()
        if now - self.last_flush >= self.flush_interval:
            self.flush()
        if self.max_duration and now - self.opened >= self.max_duration:
            self._rollover()

    def flush(self):
        """Finalize the open chunk and write it out (what a hard kill can no longer take)."""
        self.w.flush()
        self.last_flush = time.monotonic()

    def _rollover(self):
        self.w.finish()
        self.f.close()
        self._open()

    def finish(self):
        """Summary (schemas, channels, Statistics, chunk indexes) and footer; idempotent."""
        w, self.w = self.w, None
        if w is not None:
            try:
                w.finish()
            finally:
                self.f.close()


# ------------------------------------------------------------------------------------------------
# the logger (caller side)

# The caller -> writer-process stream is a sequence of records shaped like MCAP records,
# [opcode u8][content length u64][content]: messages are written by the caller as finished MCAP
# Message records (channel id = topic index + 1, per-topic sequence, log and publish time), which
# the writer process copies into chunks as they are; control records use opcodes MCAP reserves
# for private use (>= 0x80): a topic registration (JSON), a flush request (u64 token), close.
FRAME = struct.Struct("<BQ")
K_MESSAGE = _OP_MESSAGE
K_TOPIC, K_FLUSH, K_CLOSE = 0x81, 0x83, 0x84

_CLOSE = object()
_FLUSH = object()
_REGISTER = object()


class McapLogger:
    """MCAP writer that costs the caller almost nothing.

    ``directory``: where files go (created); files are ``<basename>_<i>.mcap``, i = 0, 1, ...
    ``max_bytes`` / ``max_duration`` [s]: roll over to the next file when the current one reaches
    that size (checked at chunk granularity) or age (0 = unlimited).
    ``flush_interval`` [s]: finalize the open chunk at least this often (bounds what a hard kill
    can lose). ``topics``: optional allow-list; ``write`` for other topics is a no-op.

    ``writer="process"`` (default): the MCAP work (records, chunks, zstd, file I/O) runs in a
    separate Python process (``redmax_ros.logging.writer_process``), so it takes no GIL time from
    the caller's interpreter. ``write`` appends the message with a 23-byte frame header to a
    buffer under a lock (~1-2 us); a sender thread hands the buffer to the process through a pipe
    every ``batch_interval`` s (the pipe write releases the GIL). The process ignores SIGINT,
    SIGTERM and SIGHUP and finishes the file when told to close or when the pipe reaches EOF, so
    the file is completed even if this process dies (then only the last ``batch_interval`` of
    messages not yet handed over is lost). ``writer="thread"``: the previous design, an
    in-process thread fed by a queue (kept for comparison; costs ~25 us of GIL time a message).

    Thread-safe: ``add_topic`` and ``write`` may be called from any thread; records keep the order
    in which they were handed over.
    """

    def __init__(self, directory, basename="redmax", *, max_bytes=0, max_duration=0.0,
                 chunk_size=256 * 1024, compression="zstd", flush_interval=1.0, topics=None,
                 writer="process", batch_interval=0.02):
        if writer not in ("process", "thread"):
            raise ValueError(f"writer must be 'process' or 'thread', got {writer!r}")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {', '.join(k for k in _COMPRESSION if k)}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.basename = basename
        self.writer = writer
        self.batch_interval = float(batch_interval)
        self.allow = None if topics is None or len(topics) == 0 else set(topics)
        self._config = {"directory": str(self.directory), "basename": basename, "max_bytes": int(max_bytes),
                        "max_duration": float(max_duration), "chunk_size": int(chunk_size),
                        "compression": compression, "flush_interval": float(flush_interval)}
        self.files: list[Path] = []
        self._topics: dict[str, Topic] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._failed = False
        self.error: BaseException | None = None
        self.handed_over = 0  # messages accepted by write()
        self.written = 0  # messages written to files (as last reported by the writer)
        if writer == "thread":
            self._start_thread()
        else:
            self._start_process()

    # ------------------------------------------------------------------ caller side
    def add_topic(self, topic: str, type_name: str, qos_profiles=None) -> bool:
        """Declare a topic before writing to it. Returns False if the topic is filtered out.
        ``type_name``: "pkg/msg/Type"; ``qos_profiles``: list of dicts for qos_profiles_yaml."""
        if self.allow is not None and topic not in self.allow:
            return False
        definition = message_definition(type_name)
        with self._lock:
            if topic in self._topics:
                if self._topics[topic].type_name != type_name:
                    raise ValueError(f"topic {topic} already logged with type {self._topics[topic].type_name}")
                return True
            t = Topic(topic, type_name, definition, qos_profiles_yaml(qos_profiles or [{}]), len(self._topics))
            self._topics[topic] = t
            if self.writer == "thread":
                self._q.put((_REGISTER, t))
            else:
                payload = t.to_json()
                self._buf += FRAME.pack(K_TOPIC, len(payload))
                self._buf += payload
        if self.writer != "thread":
            self._wake.set()
        return True

    def write(self, topic: str, data: bytes, log_time_ns: int | None = None, publish_time_ns: int | None = None):
        """Hand over one serialized (CDR) message; returns immediately."""
        t = self._topics.get(topic)
        if t is None or self._closed or self._failed:
            return
        if log_time_ns is None:
            log_time_ns = time.time_ns()
        if publish_time_ns is None:
            publish_time_ns = log_time_ns
        if self.writer == "thread":
            self.handed_over += 1
            self._q.put((t, log_time_ns, data, publish_time_ns))
            return
        with self._lock:
            t.seq = seq = (t.seq + 1) & 0xFFFFFFFF
            self._buf += _MESSAGE_HEAD.pack(_OP_MESSAGE, 22 + len(data), t.index + 1, seq, log_time_ns,
                                            publish_time_ns)
            self._buf += data
            self.handed_over += 1

    def write_many(self, items, log_time_ns: int | None = None):
        """``write`` for several (topic, data) messages with one log time (= publish time) and one
        lock: the messages of one simulation step."""
        if self._closed or self._failed:
            return
        if log_time_ns is None:
            log_time_ns = time.time_ns()
        if self.writer == "thread":
            for topic, data in items:
                self.write(topic, data, log_time_ns)
            return
        topics, head = self._topics, _MESSAGE_HEAD.pack
        with self._lock:
            buf = self._buf
            for topic, data in items:
                t = topics.get(topic)
                if t is None:
                    continue
                t.seq = seq = (t.seq + 1) & 0xFFFFFFFF
                buf += head(_OP_MESSAGE, 22 + len(data), t.index + 1, seq, log_time_ns, log_time_ns)
                buf += data
                self.handed_over += 1

    def handle(self, topic: str):
        """The logger's record of a logged topic (None if not logged), for callers that build
        Message records themselves (``write_records``): channel id = ``handle.index + 1``, and the
        caller advances ``handle.seq`` (``(seq + 1) & 0xFFFFFFFF``) for every record it builds, so
        it must be the topic's only writer."""
        return self._topics.get(topic)

    def write_records(self, records, count: int):
        """Hand over ``count`` finished MCAP Message records (``MESSAGE_HEAD`` + CDR each, built
        with ``handle``) in one piece: one lock, one append. Writer process only (the thread
        writer takes messages, not records)."""
        if self._closed or self._failed:
            return
        if self.writer == "thread":
            raise ValueError("write_records needs writer='process'")
        with self._lock:
            self._buf += records
            self.handed_over += count

    def flush(self, timeout=10.0) -> bool:
        """Block until everything handed over so far is written and the open chunk finalized."""
        if self._closed:
            return True
        ev = threading.Event()
        if self.writer == "thread":
            self._q.put((_FLUSH, ev))
            return ev.wait(timeout)
        with self._lock:
            self._token += 1
            token = self._token
            self._flush_waiters[token] = ev
            self._buf += FRAME.pack(K_FLUSH, 8) + struct.pack("<Q", token)
        self._wake.set()
        return ev.wait(timeout) or self._failed

    def close(self, timeout=30.0):
        """Write everything handed over, finish the file (summary, statistics, footer)."""
        if self._closed:
            return
        self._closed = True
        if self.writer == "thread":
            self._q.put((_CLOSE, None))
            self._thread.join(timeout)
            self.written = self._session.written if self._session is not None else self.written
            return
        with self._lock:
            self._buf += FRAME.pack(K_CLOSE, 0)
            self._closing = True
        self._wake.set()
        self._sender.join(timeout)
        self._reader.join(timeout)
        try:
            self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
            self._set_error(RuntimeError(f"MCAP writer process did not finish within {timeout} s; killed"))

    @property
    def backlog(self) -> int:
        """Messages handed over but not yet written."""
        if self.writer == "thread":
            return self._q.qsize()
        return max(0, self.handed_over - self.written)

    @property
    def topics(self):
        return dict(self._topics)

    def logs(self, topic: str) -> bool:
        """Whether messages written for ``topic`` are recorded (declared and allowed)."""
        return topic in self._topics

    def _set_error(self, e: BaseException):
        if self.error is None:
            self.error = e
        self._failed = True
        for ev in list(getattr(self, "_flush_waiters", {}).values()):
            ev.set()

    # ------------------------------------------------------------------ process backend
    def _start_process(self):
        self._buf = bytearray()
        self._closing = False
        self._wake = threading.Event()
        self._token = 0
        self._flush_waiters: dict[int, threading.Event] = {}
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[2])  # so the child imports this redmax_ros
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "redmax_ros.logging.writer_process", json.dumps(self._config)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, close_fds=True, env=env)
        try:  # a larger pipe absorbs bursts without blocking the sender (Linux; best effort)
            fcntl.fcntl(self._proc.stdin.fileno(), getattr(fcntl, "F_SETPIPE_SZ", 1031), 1 << 20)
        except OSError:
            pass
        self._opened = threading.Event()
        self._reader = threading.Thread(target=self._read_status, name="mcap-status", daemon=True)
        self._reader.start()
        self._sender = threading.Thread(target=self._send_loop, name="mcap-sender", daemon=True)
        self._sender.start()
        self._opened.wait(30.0)  # the first file exists when the constructor returns
        if self.error is not None:
            raise RuntimeError(f"MCAP writer process failed to start: {self.error}")

    def _send_loop(self):
        fd = self._proc.stdin.fileno()
        try:
            while True:
                self._wake.wait(self.batch_interval)
                self._wake.clear()
                with self._lock:
                    buf, self._buf = self._buf, bytearray()
                    closing = self._closing
                if buf and not self._failed:
                    try:
                        view = memoryview(buf)
                        while view:
                            view = view[os.write(fd, view):]
                    except OSError as e:  # the process died: keep the reason, stop sending
                        self._set_error(RuntimeError(f"MCAP writer process gone: {e}"))
                if closing:
                    break
        finally:
            try:
                self._proc.stdin.close()  # EOF: the process finishes the file
            except OSError:
                pass

    def _read_status(self):
        closed = False
        try:
            for line in self._proc.stdout:
                try:
                    msg = json.loads(line)
                except ValueError:
                    continue
                if "opened" in msg:
                    self.files.append(Path(msg["opened"]))
                    self._opened.set()
                if "written" in msg:
                    self.written = int(msg["written"])
                if "error" in msg:
                    self._set_error(RuntimeError(msg["error"]))
                if "flushed" in msg:
                    ev = self._flush_waiters.pop(int(msg["flushed"]), None)
                    if ev is not None:
                        ev.set()
                if msg.get("closed"):
                    closed = True
        except (OSError, ValueError):
            pass
        if not closed:
            rc = self._proc.wait()
            self._set_error(RuntimeError(f"MCAP writer process exited unexpectedly (exit code {rc})"))
        self._opened.set()

    # ------------------------------------------------------------------ thread backend (previous design)
    def _start_thread(self):
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._session = FileSession(**self._config)
        self.files = self._session.files
        self._thread = threading.Thread(target=self._run, name="mcap-logger", daemon=True)
        self._thread.start()

    def _run(self):
        s = self._session
        try:
            while True:
                try:
                    item = self._q.get(timeout=max(1e-3, s.next_deadline() - time.monotonic()))
                except queue.Empty:
                    item = None
                if item is not None:
                    if item[0] is _CLOSE:
                        break
                    if item[0] is _REGISTER:
                        s.register(item[1])
                    elif item[0] is _FLUSH:
                        s.flush()
                        item[1].set()
                    else:
                        t, log_time, data, pub_time = item
                        s.add(t.index, log_time, data, pub_time)
                        self.written = s.written
                s.tick()
        except BaseException as e:  # keep the error for the owner; never die silently
            self._set_error(e)
        finally:
            s.finish()
            self.written = s.written


# ------------------------------------------------------------------------------------------------
# recovery of a file cut short by a hard kill

def recover(src, dst) -> int:
    """Copy every readable record of a (possibly truncated) MCAP file into a valid new file.
    Returns the number of messages recovered. Messages in the unfinished last chunk are lost."""
    n = 0
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        w = None
        schema_map, chan_map = {}, {}
        reader = StreamReader(fin, emit_chunks=False)
        try:
            for rec in reader.records:
                if isinstance(rec, Header):
                    w = Writer(fout)
                    w.start(profile=rec.profile, library=rec.library)
                elif isinstance(rec, Schema) and rec.id not in schema_map:
                    schema_map[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel) and rec.id not in chan_map:
                    chan_map[rec.id] = w.register_channel(rec.topic, rec.message_encoding,
                                                          schema_map.get(rec.schema_id, 0), rec.metadata)
                elif isinstance(rec, Message) and rec.channel_id in chan_map:
                    w.add_message(chan_map[rec.channel_id], rec.log_time, rec.data, rec.publish_time,
                                  rec.sequence)
                    n += 1
        except Exception:  # truncated record / chunk: stop at the last complete one
            pass
        if w is None:
            raise ValueError(f"{src}: no MCAP header, nothing to recover")
        w.finish()
    return n


def _main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m redmax_ros.logging.mcap_log")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("recover", help="rewrite the readable part of a truncated MCAP file")
    r.add_argument("src")
    r.add_argument("dst")
    a = ap.parse_args(argv)
    n = recover(a.src, a.dst)
    print(f"recovered {n} messages into {a.dst}")
    return 0


if __name__ == "__main__":
    sys.exit(_main())
