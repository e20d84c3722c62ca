"""Time functions for time-dependent loads in scene files (no expression evaluation: a closed set of
standard functions, validated at load time, evaluated with a few floating-point operations).

A time function is a number (constant) or a mapping with a ``type``:

===========  ==========================================================  =============================
type         keys (defaults)                                             value at time t [s]
===========  ==========================================================  =============================
constant     value                                                       value
sine         amplitude, frequency [Hz], phase [rad] (0), offset (0)      offset + amplitude sin(2 pi f t + phase)
step         time [s], before (0), after                                 before if t < time else after
ramp         start [s], end [s], from (0), to                            from, linear to ``to`` on
                                                                         [start, end], then ``to``
table        points: [[t0, v0], [t1, v1], ...] (t increasing)            piecewise linear, held
                                                                         constant outside [t0, tn]
sum          terms: [f1, f2, ...]                                        f1(t) + f2(t) + ...
product      terms: [f1, f2, ...]                                        f1(t) * f2(t) * ...
===========  ==========================================================  =============================

Units are those of the quantity the function drives (N, N m, ...). Loads are explicit (evaluated at
the start of the step, t_k), like the other explicit forces of Eq. (2).
"""
from __future__ import annotations

import math

import numpy as np

KEYS = {
    "constant": ({"value"}, {"value"}),
    "sine": ({"amplitude", "frequency", "phase", "offset"}, {"amplitude", "frequency"}),
    "step": ({"time", "before", "after"}, {"time", "after"}),
    "ramp": ({"start", "end", "from", "to"}, {"start", "end", "to"}),
    "table": ({"points"}, {"points"}),
    "sum": ({"terms"}, {"terms"}),
    "product": ({"terms"}, {"terms"}),
}


class TimeFunction:
    """A validated time function; call it with t [s]."""

    def __init__(self, kind: str, p: dict, terms=()):
        self.kind, self.p, self.terms = kind, p, tuple(terms)
        if kind == "table":
            self.t = np.array([x[0] for x in p["points"]], float)
            self.v = np.array([x[1] for x in p["points"]], float)

    def __call__(self, t: float) -> float:
        k, p = self.kind, self.p
        if k == "constant":
            return p["value"]
        if k == "sine":
            return p["offset"] + p["amplitude"] * math.sin(2.0 * math.pi * p["frequency"] * t + p["phase"])
        if k == "step":
            return p["before"] if t < p["time"] else p["after"]
        if k == "ramp":
            if t <= p["start"]:
                return p["from"]
            if t >= p["end"]:
                return p["to"]
            return p["from"] + (p["to"] - p["from"]) * (t - p["start"]) / (p["end"] - p["start"])
        if k == "table":
            return float(np.interp(t, self.t, self.v))
        if k == "sum":
            return sum(f(t) for f in self.terms)
        if k == "product":
            out = 1.0
            for f in self.terms:
                out *= f(t)
            return out
        raise AssertionError(k)

    @property
    def is_constant(self) -> bool:
        return self.kind == "constant"

    def __repr__(self):
        return f"TimeFunction({self.kind}, {self.p})"


def parse(v, entry: str, key: str, d) -> TimeFunction:
    """Validate a time function (``v``: the scene _Validator, for numbers and error messages)."""
    where = f"{entry} {key}"
    if not isinstance(d, dict):
        return TimeFunction("constant", {"value": v.number(entry, key, d)})
    kind = d.get("type")
    if kind not in KEYS:
        v.err(entry, f"'{key}': unknown time function type {kind!r} (known: {', '.join(KEYS)}, or a number)")
    allowed, required = KEYS[kind]
    v.keys(where, d, allowed | {"type"}, required=tuple(sorted(required)))
    num = lambda k, default=None: v.number(entry, f"{key}.{k}", d.get(k, default))  # noqa: E731
    if kind == "constant":
        return TimeFunction(kind, {"value": num("value")})
    if kind == "sine":
        return TimeFunction(kind, {"amplitude": num("amplitude"), "frequency": num("frequency"),
                                   "phase": num("phase", 0.0), "offset": num("offset", 0.0)})
    if kind == "step":
        return TimeFunction(kind, {"time": num("time"), "before": num("before", 0.0), "after": num("after")})
    if kind == "ramp":
        p = {"start": num("start"), "end": num("end"), "from": num("from", 0.0), "to": num("to")}
        if p["end"] <= p["start"]:
            v.err(entry, f"'{key}': ramp end ({p['end']}) must be after its start ({p['start']})")
        return TimeFunction(kind, p)
    if kind == "table":
        pts = d["points"]
        if not isinstance(pts, list) or len(pts) < 2:
            v.err(entry, f"'{key}.points' must list at least two [t, value] pairs")
        pts = [v.vector(entry, f"{key}.points[{i}]", x, 2).tolist() for i, x in enumerate(pts)]
        ts = [x[0] for x in pts]
        if any(b <= a for a, b in zip(ts, ts[1:])):
            v.err(entry, f"'{key}.points' times must be strictly increasing, got {ts}")
        return TimeFunction(kind, {"points": pts})
    terms = d["terms"]
    if not isinstance(terms, list) or not terms:
        v.err(entry, f"'{key}.terms' must be a non-empty list of time functions")
    return TimeFunction(kind, {}, [parse(v, entry, f"{key}.terms[{i}]", x) for i, x in enumerate(terms)])


def parse_vector(v, entry: str, key: str, d, n: int) -> list:
    """A list of n time functions (numbers or mappings), or a number / single mapping for all n."""
    if isinstance(d, list):
        if len(d) != n:
            v.err(entry, f"'{key}' must have {n} entries, got {len(d)}")
        return [parse(v, entry, f"{key}[{i}]", x) for i, x in enumerate(d)]
    f = parse(v, entry, key, d)
    return [f] * n
