"""MCAP logging with ROS 2 conventions, off the caller's hot path.

Files follow what rosbag2's MCAP storage plugin writes, so ``ros2 bag info/play`` and Foxglove
open them: profile ``ros2``, message encoding ``cdr``, schemas encoded ``ros2msg`` holding the
full definition with its dependencies (``====`` + ``MSG: pkg/Type`` blocks), channel metadata
``offered_qos_profiles`` (YAML as rosbag2 writes it), and a summary with a Statistics record.

The caller hands over *already serialized* CDR bytes (the node serializes once and publishes the
same bytes), so this module needs no rclpy: ``write`` only puts a tuple on a queue; a background
thread builds chunks, compresses and writes. Files roll over by size or by duration; ``close``
drains the queue, so nothing handed to ``write`` before ``close`` is lost.

Crash safety: chunks are finalized every ``flush_interval`` seconds (and whenever a chunk reaches
``chunk_size``), so after a hard kill everything but the last unfinished chunk is on disk; the file
then lacks its summary and footer, and :func:`recover` (``python -m redmax_ros.logging.mcap_log
recover in.mcap out.mcap``) or ``mcap recover`` rewrites the readable part into a valid file.
"""
from __future__ import annotations

import os
import queue
import re
import sys
import threading
import time
from pathlib import Path

from mcap.writer import CompressionType, Writer

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
# the logger

_CLOSE = object()
_FLUSH = object()
_REGISTER = object()


class _Topic:
    __slots__ = ("topic", "type_name", "definition", "qos_yaml", "index")

    def __init__(self, topic, type_name, definition, qos_yaml, index):
        self.topic, self.type_name, self.definition = topic, type_name, definition
        self.qos_yaml, self.index = qos_yaml, index


class McapLogger:
    """Background MCAP writer.

    ``directory``: where files go (created); files are ``<basename>_<i>.mcap``, i = 0, 1, ...
    ``max_bytes`` / ``max_duration`` [s]: roll over to the next file when the current one reaches
    that size (checked at chunk granularity) or age (0 = unlimited).
    ``flush_interval`` [s]: finalize the open chunk at least this often (bounds what a hard kill
    can lose). ``topics``: optional allow-list; ``write`` for other topics is a no-op.

    Thread-safe: ``add_topic`` and ``write`` may be called from any thread; records keep the order
    in which they were handed over.
    """

    def __init__(self, directory, basename="redmax", *, max_bytes=0, max_duration=0.0,
                 chunk_size=256 * 1024, compression="zstd", flush_interval=1.0, topics=None):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.basename = basename
        self.max_bytes = int(max_bytes)
        self.max_duration = float(max_duration)
        self.chunk_size = int(chunk_size)
        self.compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                            "none": CompressionType.NONE, "": CompressionType.NONE}[compression]
        self.flush_interval = float(flush_interval)
        self.allow = None if topics is None or len(topics) == 0 else set(topics)
        self.files: list[Path] = []
        self._topics: dict[str, _Topic] = {}
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._closed = False
        self.error: BaseException | None = None
        self.handed_over = 0  # messages accepted by write()
        self.written = 0  # messages written by the background thread
        self._thread = threading.Thread(target=self._run, name="mcap-logger", daemon=True)
        self._thread.start()

    # -- caller side
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
            t = _Topic(topic, type_name, definition, qos_profiles_yaml(qos_profiles or [{}]), len(self._topics))
            self._topics[topic] = t
        self._q.put((_REGISTER, t))  # channels exist in the file even before their first message
        return True

    def write(self, topic: str, data: bytes, log_time_ns: int | None = None, publish_time_ns: int | None = None):
        """Hand over one serialized (CDR) message; returns immediately."""
        t = self._topics.get(topic)
        if t is None or self._closed:
            return
        if log_time_ns is None:
            log_time_ns = time.time_ns()
        self.handed_over += 1
        self._q.put((t, log_time_ns, data, publish_time_ns if publish_time_ns is not None else log_time_ns))

    def flush(self, timeout=10.0):
        """Block until everything handed over so far is written and the open chunk finalized."""
        ev = threading.Event()
        self._q.put((_FLUSH, ev))
        ev.wait(timeout)

    def close(self, timeout=30.0):
        """Write everything handed over, finish the file (summary, statistics, footer)."""
        if self._closed:
            return
        self._closed = True
        self._q.put((_CLOSE, None))
        self._thread.join(timeout)

    @property
    def backlog(self) -> int:
        return self._q.qsize()

    @property
    def topics(self):
        return dict(self._topics)

    # -- background thread
    def _open(self):
        path = self.directory / f"{self.basename}_{len(self.files)}.mcap"
        f = open(path, "wb")
        w = Writer(f, chunk_size=self.chunk_size, compression=self.compression)
        w.start(profile="ros2", library=LIBRARY)
        self.files.append(path)
        chans = {}
        with self._lock:
            known = list(self._topics.values())
        for t in known:
            self._channel(w, chans, t)
        return f, w, chans, time.monotonic()

    def _channel(self, w, chans, t: _Topic):
        cid = chans.get(t.topic)
        if cid is None:
            sid = w.register_schema(name=t.type_name, encoding="ros2msg", data=t.definition.encode())
            cid = w.register_channel(topic=t.topic, message_encoding="cdr", schema_id=sid,
                                     metadata={"offered_qos_profiles": t.qos_yaml})
            chans[t.topic] = cid
        return cid

    def _run(self):
        f = w = None
        chans: dict = {}
        opened = 0.0
        last_flush = time.monotonic()
        seq = {}
        try:
            f, w, chans, opened = self._open()
            while True:
                try:
                    item = self._q.get(timeout=self.flush_interval)
                except queue.Empty:
                    item = None
                now = time.monotonic()
                if item is not None and item[0] is _CLOSE:
                    break
                if item is not None and item[0] is _REGISTER:
                    self._channel(w, chans, item[1])
                    continue
                if item is not None and item[0] is _FLUSH:
                    w.flush()
                    last_flush = now
                    item[1].set()
                    continue
                if item is not None:
                    t, log_time, data, pub_time = item
                    cid = self._channel(w, chans, t)
                    s = seq.get(t.topic, 0) + 1
                    seq[t.topic] = s
                    w.add_message(cid, log_time=log_time, data=data, publish_time=pub_time, sequence=s)
                    self.written += 1
                if now - last_flush >= self.flush_interval:
                    w.flush()
                    last_flush = now
                if ((self.max_bytes and f.tell() >= self.max_bytes)
                        or (self.max_duration and now - opened >= self.max_duration)):
                    w.finish()
                    f.close()
                    f, w, chans, opened = self._open()
        except BaseException as e:  # keep the error for the owner; never die silently
            self.error = e
        finally:
            if w is not None:
                try:
                    w.finish()
                finally:
                    f.close()


# ------------------------------------------------------------------------------------------------
# recovery of a file cut short by a hard kill

def recover(src, dst) -> int:
    """Copy every readable record of a (possibly truncated) MCAP file into a valid new file.
    Returns the number of messages recovered. Messages in the unfinished last chunk are lost."""
    from mcap.records import Channel, Header, Message, Schema
    from mcap.stream_reader import StreamReader

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
    import argparse

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
