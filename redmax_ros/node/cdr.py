"""Fast CDR encoders for the per-step messages (joint_states, /clock, solver_stats).

rclpy's message objects and ``serialize_message`` cost ~30-50 us per message in Python, which at
1 kHz is a large share of a step. These encoders write the same bytes (plain little-endian CDR as
rmw_fastrtps_cpp produces: 4-byte encapsulation header 00 01 00 00, alignment relative to the end
of that header, doubles aligned to 8) from a per-scene template, patching only the numbers.
test/test_node_cdr.py checks them byte for byte against ``rclpy.serialization``.
"""
from __future__ import annotations

import struct

import numpy as np
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

from redmax_ros.logging.mcap_log import MESSAGE_HEAD, OP_MESSAGE

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE


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
        self.align(8)  # Fast CDR aligns even an empty sequence
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
_F8 = np.dtype("<f8")


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
                and position.dtype == _F8 and velocity.dtype == _F8 and effort.dtype == _F8 and self.n):
            ns = int(round(t * 1e9))
            enc, mid, sep1, sep2 = self._pieces
            return b"".join((enc, _STAMP.pack(ns // 1_000_000_000, ns % 1_000_000_000), mid, position.tobytes(),
                             sep1, velocity.tobytes(), sep2, effort.tobytes()))
        return self._encode_buffer(t, position, velocity, effort)

    def _encode_buffer(self, t, position, velocity, effort) -> bytes:
        if self.n == 0:  # Fast CDR pads empty double sequences lazily: let rclpy do this rare case
            m = JointState()
            m.header.stamp.sec, m.header.stamp.nanosec = _split_time(t)
            m.header.frame_id = self.frame_id
            return serialize_message(m)
        n = self.n
        for view, arr in zip(self._views, (position, velocity, effort)):
            if len(arr) != n or np.ndim(arr) != 1:
                raise ValueError(f"expected {n} values, got shape {np.shape(arr)}")
            view[:] = arr
        _STAMP.pack_into(self._buf, 4, *_split_time(t))
        return self._buf.tobytes()


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
            b = bytes(w.b)
            # encapsulation, sec, nanosec, [frame_id + padding], step, [solver + padding], iterations,
            # [padding], 8 doubles
            fmt = f"<4siI{off_step - 12}sQ{off_it - off_step - 8}sI{off_d - off_it - 4}s8d"
            tpl = (b, off_step, off_it, off_d, struct.Struct(fmt),
                   (b[12:off_step], b[off_step + 8:off_it], b[off_it + 4:off_d]))
            assert tpl[4].size == len(b)
            self.padding = list(w.padding)
            self._cache[solver] = tpl
        return tpl

    def layout(self, solver):
        """(Struct, (frame_id piece, solver piece, padding piece)) of the message for ``solver``:
        ``Struct.pack(ENCAPSULATION, sec, nanosec, piece0, step, piece1, iterations, piece2, residual,
        violation_pos, violation_vel, E_kin, E_pot, E_spring, E_total, wall_time)``."""
        tpl = self._template(solver)
        return tpl[4], tpl[5]

    def encode(self, t, step, diag) -> bytes:
        tpl = self._cache.get(diag.solver) if type(diag.solver) is str else None
        if tpl is None:
            tpl = self._template(str(diag.solver))
        st, (p0, p1, p2) = tpl[4], tpl[5]
        ns = int(round(t * 1e9))
        return st.pack(ENCAPSULATION, ns // 1_000_000_000, ns % 1_000_000_000, p0, int(step), p1,
                       int(diag.iterations), p2, float(diag.residual), float(diag.violation_pos),
                       float(diag.violation_vel), float(diag.E_kin), float(diag.E_pot), float(diag.E_spring),
                       float(diag.E_total), float(diag.wall_time))


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
        rest = st.pack(op, 34, hc.index + 1, sc, log_ns, log_ns, ENCAPSULATION, sec, nsec,
                       op, 22 + n, hs.index + 1, ss, log_ns, log_ns, ENCAPSULATION, sec, nsec, p0, int(step), p1,
                       int(diag.iterations), p2, float(diag.residual), float(diag.violation_pos),
                       float(diag.violation_vel), float(diag.E_kin), float(diag.E_pot), float(diag.E_spring),
                       float(diag.E_total), float(diag.wall_time))
        return b"".join((self._head.pack(op, 22 + len(js), hj.index + 1, sj, log_ns, log_ns), js, rest))
