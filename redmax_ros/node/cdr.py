"""CDR for every message the node sends: fast encoders for the per-step messages (joint_states,
/clock, solver_stats) and ``serialize_message`` for any other message.

rclpy's message objects and ``serialize_message`` cost ~30-50 us per message in Python, which at
1 kHz is a large share of a step. These encoders write the same bytes (plain little-endian CDR as
rmw_fastrtps_cpp produces: 4-byte encapsulation header 00 01 00 00, alignment relative to the end
of that header, doubles aligned to 8, zero padding) from a per-scene template, patching only the
numbers. test/node/test_node_cdr.py checks every byte but the padding against
``rclpy.serialization`` and the exact length with rosbags (no trailing bytes).

``serialize_message`` here replaces rclpy's for the node's other messages: rclpy's (rmw_fastrtps'
``rmw_serialize``) returns a buffer as long as Fast CDR's *estimated* size, not the serialized
data, and the estimate counts 8-byte alignment for empty float64 sequences that Fast CDR does not
write. A JointState with names and velocities only (prescribed_joints) came out 4-12 bytes longer
than its CDR, the tail uninitialized memory, which rosbags rejects ("CDR message size mismatch": it
allows at most 3 trailing bytes); rclpy also leaves alignment padding uninitialized. Ours writes
exactly the bytes rclpy's ``publish`` puts on the wire (Fast CDR, XCDRv1) with zero padding;
test/logging/test_log_all_topics_decode.py checks it against rclpy's wire bytes and serializer,
rosbags, and a whole node log with mcap_ros2 and rosbags.

One decoder for what the node receives: :func:`joint_state_key` reads only the names and which arrays
are filled of a serialized sensor_msgs/JointState (~2 us instead of ~15 us for rclpy's
``deserialize_message``), so that the command reader can drop, unread, a joint command superseded by a
newer one in the same burst (command_reader.py).
"""
from __future__ import annotations

import array
import importlib
import struct
import sys
from itertools import chain
from operator import attrgetter

import numpy as np
from numba import njit
from rclpy.serialization import serialize_message as _rclpy_serialize_message
from rosidl_parser import definition as idl

from redmax_ros.logging.mcap_log import MESSAGE_HEAD, OP_MESSAGE

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE
_U32 = struct.Struct("<I")


class _W:
    """Minimal CDR writer used to build templates."""

    def __init__(self):
        self.b = bytearray(ENCAPSULATION)
        self.padding = []  # byte offsets of alignment padding (content unspecified in CDR)

    def align(self, n):
        pad = (-(len(self.b) - 4)) % n
        self.padding.extend(range(len(self.b), len(self.b) + pad))
        self.b += b"\x00" * pad

    def u32(self, v):
        self.align(4)
        self.b += struct.pack("<I", v)

    def i32(self, v):
        self.align(4)
        self.b += struct.pack("<i", v)

    def u8(self, v):
        self.b += struct.pack("<B", v)

    def u64(self, v):
        self.align(8)
        self.b += struct.pack("<Q", v)

    def f64(self, v):
        self.align(8)
        self.b += struct.pack("<d", v)

    def string(self, s):
        data = s.encode() + b"\x00"
        self.u32(len(data))
        self.b += data

    def strings(self, seq):
        self.u32(len(seq))
        for s in seq:
            self.string(s)

    def f64_seq(self, n) -> int:
        """Writes a length and n zero doubles; returns the offset of the first double."""
        self.u32(n)
        if n:  # Fast CDR aligns a sequence's first element: an empty sequence has no padding
            self.align(8)
        off = len(self.b)
        self.b += b"\x00" * (8 * n)
        return off


def _split_time(t: float):
    ns = int(round(t * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_8D = struct.Struct("<8d")
_F8 = np.dtype("<f8")  # float64 arrays carry this very instance on a little-endian machine (encode tries `is` first)


class JointStateEncoder:
    """sensor_msgs/JointState with fixed names and n = len(names) position/velocity/effort.

    Encoding patches a per-scene buffer in place (stamp by struct, the three arrays through
    float64 views) and copies it out once (~4 us for the hand's 23 DOFs vs ~10 us building a
    bytearray per message). Not thread-safe: one encoder per publishing thread."""

    def __init__(self, names, frame_id=""):
        self.frame_id = frame_id
        w = _W()
        w.i32(0)
        w.u32(0)  # stamp
        w.string(frame_id)
        w.strings(list(names))
        n = len(names)
        self.n = n
        self.off = [w.f64_seq(n), 0, 0]
        self.off[1] = w.f64_seq(n)
        self.off[2] = w.f64_seq(n)
        self.template = bytes(w.b)
        self.padding = list(w.padding)
        self._buf = np.frombuffer(bytearray(self.template), dtype=np.uint8)
        self._views = [self._buf[o:o + 8 * n].view("<f8") for o in self.off]
        # the fast path joins constant pieces of the template with the arrays' bytes
        o0, o1, o2 = self.off
        self._pieces = (self.template[:4], self.template[12:o0], self.template[o0 + 8 * n:o1],
                        self.template[o1 + 8 * n:o2])
        self._shape = (n,)

    def encode(self, t, position, velocity, effort) -> bytes:
        """One join of template pieces and ``tobytes()`` of the three arrays (~2 us for the
        hand) when all three are 1-D float64 ndarrays of length n; anything else (lists, other
        dtypes) goes through the patched buffer, which also checks the lengths."""
        shape = self._shape
        if (type(position) is np.ndarray and type(velocity) is np.ndarray and type(effort) is np.ndarray
                and position.shape == shape and velocity.shape == shape and effort.shape == shape
                and (position.dtype is _F8 or position.dtype == _F8) and (velocity.dtype is _F8 or velocity.dtype == _F8)
                and (effort.dtype is _F8 or effort.dtype == _F8) and self.n):
            ns = int(round(t * 1e9))
            enc, mid, sep1, sep2 = self._pieces
            return b"".join((enc, _STAMP.pack(ns // 1_000_000_000, ns % 1_000_000_000), mid, position.tobytes(),
                             sep1, velocity.tobytes(), sep2, effort.tobytes()))
        return self._encode_buffer(t, position, velocity, effort)

    def _encode_buffer(self, t, position, velocity, effort) -> bytes:
        n = self.n
        for view, arr in zip(self._views, (position, velocity, effort)):
            if len(arr) != n or np.ndim(arr) != 1:
                raise ValueError(f"expected {n} values, got shape {np.shape(arr)}")
            view[:] = arr
        _STAMP.pack_into(self._buf, 4, *_split_time(t))
        return self._buf.tobytes()


class TFMessageEncoder:
    """tf2_msgs/TFMessage of one transform per child frame, all from ``parent``, with one stamp.

    The layout depends only on the frame names, so the per-scene template is patched in place by one
    compiled loop (_put_transforms) through two views of one buffer: every stamp's (sec, nsec)
    through a uint32 view, every transform's 7 doubles (translation, rotation xyzw; 8-aligned in the
    CDR, so 4 bytes past a multiple of 8 in the buffer) through a float64 view (~4 us for the hand's
    17 frames; numpy's byte-wise scatter of the same values took ~27 us, rclpy message objects and a
    generic serializer ~700 us). test/node/test_node_frames.py checks it against
    ``serialize_message``."""

    def __init__(self, parent, children):
        w = _W()
        w.u32(len(children))
        self.stamps, self.values = [], []
        for c in children:
            w.i32(0)
            self.stamps.append(len(w.b))
            w.u32(0)  # stamp (sec at stamps[i] - 4)
            w.string(parent)
            w.string(c)
            w.align(8)
            self.values.append(len(w.b))
            w.b += b"\x00" * 56
        self.template = bytes(w.b)
        self.n = len(children)
        size = len(self.template)
        self._buf = bytearray(self.template + bytes(-size % 8 + 4))  # room for both views to the end
        self._out = memoryview(self._buf)[:size]
        # uint32 index of every sec (nsec follows), float64 index (from byte 4) of every transform's first double
        self._stamp_idx = (np.array(self.stamps, np.int64) - 4) // 4
        self._vals_idx = (np.array(self.values, np.int64) - 4) // 8
        self._u32 = np.frombuffer(self._buf, dtype=np.uint32)
        self._f64 = np.frombuffer(self._buf, dtype=np.float64, offset=4)
        if sys.byteorder != "little":  # CDR little endian (the encapsulation header says so)
            raise NotImplementedError("TFMessageEncoder writes through native views: little-endian hosts only")

    def encode(self, t, positions, quaternions) -> bytes:
        """``positions`` (n,3) [m], ``quaternions`` (n,4) xyzw, in ``children`` order."""
        if self.n:
            sec, nsec = _split_time(t)
            _put_transforms(self._u32, self._f64, self._stamp_idx, self._vals_idx, sec & 0xFFFFFFFF, nsec,
                            np.asarray(positions, dtype=np.float64), np.asarray(quaternions, dtype=np.float64))
        return bytes(self._out)


@njit(cache=True)
def _put_transforms(u32, f64, stamp_idx, vals_idx, sec, nsec, P, Q):
    """TFMessageEncoder's patch: stamp i at u32[stamp_idx[i]:+2], (P[i], Q[i]) at f64[vals_idx[i]:+7]."""
    for i in range(len(stamp_idx)):
        u32[stamp_idx[i]] = sec
        u32[stamp_idx[i] + 1] = nsec
        k = vals_idx[i]
        for j in range(3):
            f64[k + j] = P[i, j]
        for j in range(4):
            f64[k + 3 + j] = Q[i, j]


def encode_clock(t: float) -> bytes:
    """rosgraph_msgs/Clock."""
    return ENCAPSULATION + struct.pack("<iI", *_split_time(t))


class SolverStatsEncoder:
    """redmax_msgs/SolverStats; one ``struct.Struct`` per solver name (built on first use) packs the
    whole message in one call: the constant parts (encapsulation, frame_id, solver name, padding)
    as byte strings, the numbers in place (~1 us; patching a template copy took ~2-3 us)."""

    def __init__(self, frame_id="world"):
        self.frame_id = frame_id
        self._cache = {}

    def _template(self, solver):
        tpl = self._cache.get(solver)
        if tpl is None:
            w = _W()
            w.i32(0)
            w.u32(0)
            w.string(self.frame_id)
            w.u64(0)
            off_step = len(w.b) - 8
            w.string(solver)
            w.u32(0)
            off_it = len(w.b) - 4
            w.f64(0.0)
            off_d = len(w.b) - 8
            for _ in range(7):  # residual .. step_wall_time: 8 doubles in all
                w.f64(0.0)
            w.u32(0)  # contact_rows
            w.u32(0)  # contacts_active
            w.u8(0)  # integration_order
            b = bytes(w.b)
            # encapsulation, sec, nanosec, [frame_id + padding], step, [solver + padding], iterations,
            # [padding], 8 doubles, 2 uint32, 1 uint8
            fmt = f"<4siI{off_step - 12}sQ{off_it - off_step - 8}sI{off_d - off_it - 4}s8dIIB"
            tpl = (b, off_step, off_it, off_d, struct.Struct(fmt),
                   (b[12:off_step], b[off_step + 8:off_it], b[off_it + 4:off_d]))
            assert tpl[4].size == len(b)
            self.padding = list(w.padding)
            self._cache[solver] = tpl
        return tpl

    def layout(self, solver):
        """(Struct, (frame_id piece, solver piece, padding piece)) of the message for ``solver``:
        ``Struct.pack(ENCAPSULATION, sec, nanosec, piece0, step, piece1, iterations, piece2, residual,
        violation_pos, violation_vel, E_kin, E_pot, E_spring, E_total, wall_time, contact_rows,
        contacts_active, integration_order)``."""
        tpl = self._template(solver)
        return tpl[4], tpl[5]

    def encode(self, t, step, diag) -> bytes:
        tpl = self._cache.get(diag.solver) if type(diag.solver) is str else None
        if tpl is None:
            tpl = self._template(str(diag.solver))
        st, (p0, p1, p2) = tpl[4], tpl[5]
        ns = int(round(t * 1e9))
        rows, active = contact_counts(diag)
        return st.pack(ENCAPSULATION, ns // 1_000_000_000, ns % 1_000_000_000, p0, int(step), p1,
                       int(diag.iterations), p2, float(diag.residual), float(diag.violation_pos),
                       float(diag.violation_vel), float(diag.E_kin), float(diag.E_pot), float(diag.E_spring),
                       float(diag.E_total), float(diag.wall_time), rows, active, integration_order(diag))


def integration_order(diag) -> int:
    """SolverStats.integration_order of a step's Diagnostics: its ``order`` (2 a BDF2 step, 1 a step of Eq. 2)."""
    return int(diag.order)


def contact_counts(diag) -> tuple:
    """(contact_rows, contacts_active) of a step's Diagnostics: its self-collision report's, (0, 0) without."""
    c = getattr(getattr(diag, "solution", None), "contacts", None)
    return (0, 0) if c is None else (int(c.rows), int(c.active))


class StepRecords:
    """The MCAP Message records of one published step without point forces - joint_states, /clock,
    solver_stats, in this order, with one log (= publish) time - exactly as
    ``McapLogger.write_many`` would build them from the encoded messages, for
    ``McapLogger.write_records`` (one lock, one append). The /clock and solver_stats records,
    heads included, come from one ``struct.Struct`` per solver name; joint_states is the
    encoder's bytes behind a packed head. Made for one logger (its topic handles and sequence
    counters); the caller must be the only writer of the three topics.
    ``clock_at(len(js))`` / ``stats_at(len(js))``: where the /clock CDR (12 bytes) and the
    solver_stats CDR (to the end) start in the result."""

    def __init__(self, logger, js_topic, clock_topic, stats_topic, stats_enc):
        self.logger = logger
        self.handles = tuple(logger.handle(t) for t in (js_topic, clock_topic, stats_topic))
        if any(h is None for h in self.handles):
            raise ValueError("all three topics must be logged")
        self.stats_enc = stats_enc
        self._head = MESSAGE_HEAD
        self._op = OP_MESSAGE
        self._cache = {}

    @staticmethod
    def clock_at(js_len):
        return 31 + js_len + 31

    @staticmethod
    def stats_at(js_len):
        return 31 + js_len + 31 + 12 + 31

    def _layout(self, solver):
        lay = self._cache.get(solver)
        if lay is None:
            st, pieces = self.stats_enc.layout(solver)
            lay = self._cache[solver] = (struct.Struct("<BQHIQQ4siIBQHIQQ" + st.format.lstrip("<")), st.size,
                                         *pieces)
        return lay

    def build(self, log_ns, t, js, step, diag) -> bytes:
        hj, hc, hs = self.handles
        hj.seq = sj = (hj.seq + 1) & 0xFFFFFFFF
        hc.seq = sc = (hc.seq + 1) & 0xFFFFFFFF
        hs.seq = ss = (hs.seq + 1) & 0xFFFFFFFF
        lay = self._cache.get(diag.solver) if type(diag.solver) is str else None
        if lay is None:
            lay = self._layout(str(diag.solver))
        st, n, p0, p1, p2 = lay
        ns = int(round(t * 1e9))
        sec, nsec = ns // 1_000_000_000, ns % 1_000_000_000
        op = self._op
        rows, active = contact_counts(diag)
        rest = st.pack(op, 34, hc.index + 1, sc, log_ns, log_ns, ENCAPSULATION, sec, nsec,
                       op, 22 + n, hs.index + 1, ss, log_ns, log_ns, ENCAPSULATION, sec, nsec, p0, int(step), p1,
                       int(diag.iterations), p2, diag.residual, diag.violation_pos,  # 'd' packs any float-like
                       diag.violation_vel, diag.E_kin, diag.E_pot, diag.E_spring, diag.E_total, diag.wall_time,
                       rows, active, integration_order(diag))
        return b"".join((self._head.pack(op, 22 + len(js), hj.index + 1, sj, log_ns, log_ns), js, rest))


# ------------------------------------------------------------------------------------------------
# any message: serialize_message

_BASIC = {  # rosidl BasicType.typename -> struct code (char/wchar/long double: not supported)
    "boolean": "?", "octet": "c", "uint8": "B", "int8": "b", "uint16": "H", "int16": "h", "uint32": "I",
    "int32": "i", "uint64": "Q", "int64": "q", "float": "f", "double": "d", "short": "h", "unsigned short": "H",
    "long": "i", "unsigned long": "I", "long long": "q", "unsigned long long": "Q",
}
# array.array typecodes whose tobytes() are the CDR of a sequence of that struct code (+ itemsize)
_ARRAY_CODES = {"B": "B", "b": "b", "H": "H", "h": "h", "I": "IL", "i": "il", "Q": "QL", "q": "ql", "f": "f", "d": "d"}
_LITTLE = sys.byteorder == "little"
_ZEROS = [bytes(n) for n in range(8)]


class _Unsupported(Exception):
    pass


def _align(b, n, pad):
    """Zero padding to a multiple of n (1, 2, 4, 8) from the end of the encapsulation header."""
    k = (4 - len(b)) % n
    if k:
        if pad is not None:
            pad.extend(range(len(b), len(b) + k))
        b += _ZEROS[k]


def _prim_bytes(v, code, size, n):
    """The n primitives of v (array.array, numpy array, list, bytes) in little-endian."""
    if _LITTLE and type(v) is array.array and v.typecode in _ARRAY_CODES.get(code, "") and v.itemsize == size:
        return v.tobytes()
    if isinstance(v, np.ndarray) and code != "c":
        return np.ascontiguousarray(v, dtype=np.dtype(code).newbyteorder("<")).tobytes()
    if code == "c":  # octet: bytes objects of length 1 (or one bytes object)
        return bytes(v) if isinstance(v, (bytes, bytearray)) else b"".join(v)
    if isinstance(v, (bytes, bytearray)) and code in "Bb":
        return bytes(v)
    return struct.pack(f"<{n}{code}", *v)


def _message_class(t):
    return getattr(importlib.import_module(".".join(t.namespaces)), t.name)


def _leaves(cls, prefix=""):
    """The fields of cls, nested messages flattened (CDR gives a nested struct no alignment of its
    own): ("p", path, code) for a primitive, ("x", path, type) for anything else."""
    names = list(cls.get_fields_and_field_types())
    if not names:  # an empty message: rosidl's structure_needs_at_least_one_member, a uint8
        yield ("p", None, "B")
        return
    for name, t in zip(names, cls.SLOT_TYPES):
        path = prefix + name
        if isinstance(t, idl.BasicType):
            if t.typename not in _BASIC:
                raise _Unsupported(t.typename)
            yield ("p", path, _BASIC[t.typename])
        elif isinstance(t, idl.NamespacedType):
            yield from _leaves(_message_class(t), path + ".")
        else:
            yield ("x", path, t)


def _run(paths, codes):
    """Consecutive primitives as one struct.pack: one Struct per offset mod 8 (padding as 'x')."""
    variants = []
    for mod in range(8):
        fmt, pos, pads = "<", mod, []
        for c in codes:
            size = struct.calcsize(c)
            k = (-pos) % size
            pads.extend(range(pos - mod, pos - mod + k))
            fmt += "x" * k + c
            pos += k + size
        variants.append((struct.Struct(fmt), pads))
    if None in paths:  # with the member of an empty message (always 0)
        getters = [(lambda m: 0) if p is None else attrgetter(p) for p in paths]
        get = lambda m: tuple(g(m) for g in getters)  # noqa: E731
    elif len(paths) == 1:
        one = attrgetter(paths[0])
        get = lambda m: (one(m),)  # noqa: E731
    else:
        get = attrgetter(*paths)

    def enc(m, b, pad):
        st, pads = variants[(len(b) - 4) & 7]
        if pad is not None:
            pad.extend(len(b) + p for p in pads)
        b += st.pack(*get(m))
    enc.codes = codes
    enc.get = get
    return enc


def _string(b, s, pad):
    data = s.encode()
    _align(b, 4, pad)
    b += _U32.pack(len(data) + 1)
    b += data
    b.append(0)


def _strings(seq, b, pad):
    for s in seq:
        _string(b, s, pad)


def _compile(cls):
    """The encoder of message class cls: enc(msg, bytearray, padding list or None)."""
    ops, prims = [], []

    def flush():
        if prims:
            ops.append(_run([p for p, _ in prims], [c for _, c in prims]))
            prims.clear()

    for kind, path, t in _leaves(cls):
        if kind == "p":
            prims.append((path, t))
            continue
        flush()
        get = attrgetter(path)
        if isinstance(t, idl.AbstractWString):
            raise _Unsupported("wstring")
        if isinstance(t, idl.AbstractString):
            ops.append(lambda m, b, pad, get=get: _string(b, get(m), pad))
            continue
        fixed = isinstance(t, idl.Array)
        vt = t.value_type
        if isinstance(vt, idl.AbstractWString):
            raise _Unsupported("wstring")
        if isinstance(vt, idl.BasicType):
            if vt.typename not in _BASIC:
                raise _Unsupported(vt.typename)
            ops.append(_prim_seq(get, _BASIC[vt.typename], t.size if fixed else None))
        elif isinstance(vt, idl.AbstractString):
            ops.append(_seq(get, _strings, t.size if fixed else None))
        else:
            ops.append(_msg_seq(get, _message_class(vt), t.size if fixed else None))
    flush()
    if len(ops) == 1:
        return ops[0]

    def enc(m, b, pad):
        for op in ops:
            op(m, b, pad)
    return enc


def _count(b, n, fixed, pad):
    if fixed is None:
        _align(b, 4, pad)
        b += _U32.pack(n)
    elif n != fixed:
        raise ValueError(f"expected {fixed} elements, got {n}")


def _prim_seq(get, code, fixed):
    size = struct.calcsize(code)

    def enc(m, b, pad):
        v = get(m)
        n = len(v)
        _count(b, n, fixed, pad)
        if n:  # Fast CDR aligns the first element only: nothing for an empty sequence
            _align(b, size, pad)
            b += _prim_bytes(v, code, size, n)
    return enc


def _seq(get, write, fixed):
    def enc(m, b, pad):
        v = get(m)
        _count(b, len(v), fixed, pad)
        write(v, b, pad)
    return enc


def _msg_seq(get, cls, fixed):
    el = _encoder(cls)
    if el is False:
        raise _Unsupported(cls.__name__)
    codes = getattr(el, "codes", None)
    if codes and len({struct.calcsize(c) for c in codes}) == 1:
        # elements of primitives of one size (Vector3, Point, ColorRGBA, Time, ...): no padding
        # after the first, so one pack for the whole sequence
        size, fmt, el_get = struct.calcsize(codes[0]), "".join(codes), el.get

        def enc(m, b, pad):
            v = get(m)
            n = len(v)
            _count(b, n, fixed, pad)
            if n:
                _align(b, size, pad)
                b += struct.pack("<" + fmt * n, *chain.from_iterable(map(el_get, v)))
        return enc

    def enc(m, b, pad):
        v = get(m)
        _count(b, len(v), fixed, pad)
        for x in v:
            el(x, b, pad)
    return enc


_ENCODERS: dict = {}


def _encoder(cls):
    enc = _ENCODERS.get(cls)
    if enc is None:
        try:
            enc = _compile(cls)
        except _Unsupported:
            enc = False
        _ENCODERS[cls] = enc
    return enc


def serialize_message(msg) -> bytes:
    """``rclpy.serialization.serialize_message`` without its trailing bytes: the CDR of any ROS 2
    message exactly as rclpy's publish puts it on the wire over rmw_fastrtps_cpp (encapsulation
    CDR_LE, XCDRv1 alignment, zero padding). Encoders are built per message class from rosidl's
    introspection on first use. Message types with wstring, char or long double fields (none that
    the node sends) fall back to rclpy's serializer."""
    enc = _ENCODERS.get(type(msg))
    if enc is None:
        enc = _encoder(type(msg))
    if enc is False:
        return _rclpy_serialize_message(msg)
    b = bytearray(ENCAPSULATION)
    enc(msg, b, None)
    return bytes(b)


def padding_of(msg) -> list:
    """Offsets of the alignment padding in ``serialize_message(msg)`` (rclpy leaves those bytes
    uninitialized: the tests compare everything else)."""
    enc = _encoder(type(msg))
    if enc is False:
        raise TypeError(f"{type(msg).__name__} is not supported")
    pad = []
    enc(msg, bytearray(ENCAPSULATION), pad)
    return pad


def joint_state_key(data: bytes):
    """(names, has positions, has velocities, has efforts) of a serialized sensor_msgs/JointState (little-
    endian CDR: header stamp, frame_id, then the name, position, velocity and effort sequences), or None
    when ``data`` is not one that this reads (the message is then processed as usual, and rejected there
    if it is malformed). Two commands with the same key set the same prescriptions, so the newer one
    supersedes the older."""
    try:
        if data[:4] != ENCAPSULATION:
            return None
        end = len(data)
        o = 12  # 4 encapsulation + stamp (int32 sec, uint32 nanosec); alignment is relative to byte 4
        n = _U32.unpack_from(data, o)[0]
        o += 4 + n
        o = 4 + ((o - 1) & ~3)  # align 4 (o - 4 rounded up to a multiple of 4)
        count = _U32.unpack_from(data, o)[0]
        o += 4
        if count > end:
            return None
        names = []
        for _ in range(count):
            o = 4 + ((o - 1) & ~3)
            n = _U32.unpack_from(data, o)[0]
            if n == 0 or o + 4 + n > end:
                return None
            names.append(data[o + 4:o + 3 + n])
            o += 4 + n
        filled = []
        for _ in range(3):  # position, velocity, effort: uint32 count, doubles aligned to 8
            o = 4 + ((o - 1) & ~3)
            n = _U32.unpack_from(data, o)[0]
            o += 4
            if n:
                o = 4 + ((o + 3) & ~7) + 8 * n
                if o > end:
                    return None
            filled.append(n > 0)
        return (tuple(names), *filled)
    except (struct.error, IndexError, TypeError):
        return None
