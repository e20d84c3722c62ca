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
sigmoid      center [s], width [s] (> 0), from (0), to                   from + (to - from) / (1 + exp(-(t - center)
                                                                         / width)) (smooth ramp, C-infinity)
quintic      start [s], end [s], from (0), to                            from, then from + (to - from) (10 u^3 -
                                                                         15 u^4 + 6 u^5), u = (t - start) / (end -
                                                                         start), then ``to``: zero velocity and
                                                                         acceleration at both ends
cubic        points: [[t0, v0], ...] or [[t0, v0, dv0], ...]             piecewise-cubic waypoints (Hermite): with
                                                                         the rates dv_i given, C1 through them;
                                                                         without, the C2 cubic spline with zero
                                                                         rate at t0 and tn; held outside [t0, tn]
===========  ==========================================================  =============================

Units are those of the quantity the function drives (N, N m, rad, m, ...). Loads are explicit (evaluated
at the start of the step, t_k), like the other explicit forces of Eq. (2).

Every function also has its time derivative (``derivative(t)``, exact, piecewise where the function is
piecewise; 0 where it jumps, as ``step``): the rate qdot_p(t) of a joint trajectory
(:class:`JointTrajectory`), which prescribes the velocity-level row of hybrid dynamics (notes §2.10,
Eq. 2.114 with the velocity prescribed; paper Eq. 7)

    *G_r qdot_r^(k+1) = qdot_p(t_k+1) + b (q_p(t_k+1) - q_k),     b >= 0 [1/s] (RedMax's reference: b = 5)

so that a joint follows a position trajectory q_p(t): with b = 0 the velocity is tracked exactly and the
position drifts with the integration error; with 0 < b h < 2 the position error e_k = q_k - q_p(t_k)
obeys e_k+1 = (1 - b h) e_k + h^2 (b qdot_p + qddot_p / 2) + O(h^3) and settles at O(h): to leading order
e' + b e = h (b qdot_p + qddot_p / 2), e = h qdot_p for slow trajectories (the law leads q_p by one step).
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
    "sigmoid": ({"center", "width", "from", "to"}, {"center", "width", "to"}),
    "quintic": ({"start", "end", "from", "to"}, {"start", "end", "to"}),
    "cubic": ({"points"}, {"points"}),
}
TRAJECTORY_KEYS = {"position", "b"}
DEFAULT_GAIN = 5.0  # b [1/s] of a joint trajectory when the scene or command gives none (RedMax's reference)


def _spline_slopes(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Knot rates m_i of the C2 cubic spline through (t_i, y_i) with m_0 = m_n = 0 (clamped at rest):
    continuity of the second derivative at the interior knots,
    m_i-1 / h_i-1 + 2 m_i (1 / h_i-1 + 1 / h_i) + m_i+1 / h_i = 3 (d_i-1 / h_i-1 + d_i / h_i)."""
    n = len(t)
    m = np.zeros(n)
    if n <= 2:
        return m
    h = np.diff(t)
    d = np.diff(y) / h
    A = np.zeros((n - 2, n - 2))
    r = np.empty(n - 2)
    for i in range(1, n - 1):
        k = i - 1
        A[k, k] = 2.0 * (1.0 / h[i - 1] + 1.0 / h[i])
        if k > 0:
            A[k, k - 1] = 1.0 / h[i - 1]
        if k < n - 3:
            A[k, k + 1] = 1.0 / h[i]
        r[k] = 3.0 * (d[i - 1] / h[i - 1] + d[i] / h[i])
    m[1:-1] = np.linalg.solve(A, r)
    return m


def _sin(a: float) -> float:
    """sin(a), NaN for an infinite phase (a huge frequency or time overflows it; math.sin would raise), which
    the step's input checks then name."""
    return math.sin(a) if math.isfinite(a) else math.nan


def _cos(a: float) -> float:
    """cos(a), NaN for an infinite phase (see _sin)."""
    return math.cos(a) if math.isfinite(a) else math.nan


def _logistic(x: float) -> float:
    if x >= 0.0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


class TimeFunction:
    """A validated time function; call it with t [s]."""

    def __init__(self, kind: str, p: dict, terms=()):
        self.kind, self.p, self.terms = kind, p, tuple(terms)
        if kind in ("table", "cubic"):
            self.t = np.array([x[0] for x in p["points"]], float)
            self.v = np.array([x[1] for x in p["points"]], float)
        if kind == "cubic":
            pts = p["points"]
            self.m = (np.array([x[2] for x in pts], float) if len(pts[0]) == 3 else _spline_slopes(self.t, self.v))

    def __call__(self, t: float) -> float:
        k, p = self.kind, self.p
        if k == "constant":
            return p["value"]
        if k == "sine":
            return p["offset"] + p["amplitude"] * _sin(2.0 * math.pi * p["frequency"] * t + p["phase"])
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
        if k == "sigmoid":
            return p["from"] + (p["to"] - p["from"]) * _logistic((t - p["center"]) / p["width"])
        if k == "quintic":
            u = min(1.0, max(0.0, (t - p["start"]) / (p["end"] - p["start"])))
            return p["from"] + (p["to"] - p["from"]) * u * u * u * (10.0 + u * (-15.0 + 6.0 * u))
        if k == "cubic":
            return self._hermite(t)[0]
        raise AssertionError(k)

    def _hermite(self, t: float) -> tuple:
        """(value, rate) of the piecewise-cubic Hermite interpolant (held outside [t0, tn])."""
        ts = self.t
        if t <= ts[0]:
            return float(self.v[0]), 0.0
        if t >= ts[-1]:
            return float(self.v[-1]), 0.0
        i = min(int(np.searchsorted(ts, t, side="right")) - 1, len(ts) - 2)
        h = ts[i + 1] - ts[i]
        s = (t - ts[i]) / h
        y0, y1, m0, m1 = self.v[i], self.v[i + 1], self.m[i] * h, self.m[i + 1] * h
        s2, s3 = s * s, s * s * s
        val = (2 * s3 - 3 * s2 + 1) * y0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * y1 + (s3 - s2) * m1
        rate = ((6 * s2 - 6 * s) * y0 + (3 * s2 - 4 * s + 1) * m0 + (-6 * s2 + 6 * s) * y1 + (3 * s2 - 2 * s) * m1) / h
        return float(val), float(rate)

    def derivative(self, t: float) -> float:
        """d/dt of the function at t (exact; one-sided on the right at the breakpoints of the piecewise
        kinds; 0 across the jump of ``step``)."""
        k, p = self.kind, self.p
        if k in ("constant", "step"):
            return 0.0
        if k == "sine":
            w = 2.0 * math.pi * p["frequency"]
            return p["amplitude"] * w * _cos(w * t + p["phase"])
        if k == "ramp":
            if t < p["start"] or t >= p["end"]:
                return 0.0
            return (p["to"] - p["from"]) / (p["end"] - p["start"])
        if k == "table":
            ts = self.t
            if t < ts[0] or t >= ts[-1]:
                return 0.0
            i = int(np.searchsorted(ts, t, side="right")) - 1
            return float((self.v[i + 1] - self.v[i]) / (ts[i + 1] - ts[i]))
        if k == "sum":
            return sum(f.derivative(t) for f in self.terms)
        if k == "product":
            vals = [f(t) for f in self.terms]
            out = 0.0
            for i, f in enumerate(self.terms):
                d = f.derivative(t)
                for j, x in enumerate(vals):
                    if j != i:
                        d *= x
                out += d
            return out
        if k == "sigmoid":
            s = _logistic((t - p["center"]) / p["width"])
            return (p["to"] - p["from"]) * s * (1.0 - s) / p["width"]
        if k == "quintic":
            T = p["end"] - p["start"]
            u = (t - p["start"]) / T
            if u <= 0.0 or u >= 1.0:
                return 0.0
            return (p["to"] - p["from"]) * 30.0 * u * u * (1.0 - u) * (1.0 - u) / T
        if k == "cubic":
            return self._hermite(t)[1]
        raise AssertionError(k)

    def value_rate(self, t: float) -> tuple:
        """(value, derivative) at t: ``self(t)``, ``self.derivative(t)``, the same numbers; a sine evaluates its
        phase once (one call instead of two: a prescribed joint's velocity row needs both every step)."""
        if self.kind == "sine":
            p = self.p
            w = 2.0 * math.pi * p["frequency"]
            a = w * t + p["phase"]  # the argument of both (self(t) forms 2 pi f t + phase, the same operations)
            return p["offset"] + p["amplitude"] * _sin(a), p["amplitude"] * w * _cos(a)
        if self.kind == "constant":  # self(t), self.derivative(t) without their dispatch on the kind
            return self.p["value"], 0.0
        return self(t), self.derivative(t)

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
    if not isinstance(kind, str) or kind not in KEYS:
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
    if kind == "sigmoid":
        p = {"center": num("center"), "width": num("width"), "from": num("from", 0.0), "to": num("to")}
        if p["width"] <= 0:
            v.err(entry, f"'{key}': sigmoid width must be positive, got {p['width']}")
        return TimeFunction(kind, p)
    if kind == "quintic":
        p = {"start": num("start"), "end": num("end"), "from": num("from", 0.0), "to": num("to")}
        if p["end"] <= p["start"]:
            v.err(entry, f"'{key}': quintic end ({p['end']}) must be after its start ({p['start']})")
        return TimeFunction(kind, p)
    if kind == "cubic":
        pts = d["points"]
        if not isinstance(pts, list) or len(pts) < 2:
            v.err(entry, f"'{key}.points' must list at least two [t, value] or [t, value, rate] waypoints")
        width = len(pts[0]) if isinstance(pts[0], list) else 0
        if width not in (2, 3):
            v.err(entry, f"'{key}.points' must be [t, value] or [t, value, rate] lists")
        pts = [v.vector(entry, f"{key}.points[{i}]", x, width).tolist() for i, x in enumerate(pts)]
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


class JointTrajectory:
    """A joint's prescribed position trajectory q_p(t) (one time function per velocity DOF) and the gain b
    [1/s] of the velocity-level law (notes §2.10, hybrid dynamics; paper Eq. 7: the row *G_r qdot_r = g
    of a prescribed joint with g below):

        g = qdot_p(t_k+1) + b (q_p(t_k+1) - q_k)

    ``rate(t, q)``: g for the step ending at t from the joint's positions q (per DOF; ``wrap``: the
    position is an angle and the error is taken in (-pi, pi], for continuous revolute joints)."""

    def __init__(self, positions, b: float = DEFAULT_GAIN):
        self.positions, self.b = tuple(positions), float(b)

    @property
    def nv(self) -> int:
        return len(self.positions)

    def position(self, t: float) -> np.ndarray:
        return np.array([f(t) for f in self.positions])

    def velocity(self, t: float) -> np.ndarray:
        return np.array([f.derivative(t) for f in self.positions])

    def rate(self, t: float, q, wrap: bool = False) -> np.ndarray:
        if wrap:
            e = self.position(t) - np.asarray(q, float)
            e = (e + math.pi) % (2.0 * math.pi) - math.pi
            return self.velocity(t) + self.b * e
        # per DOF in Python floats: the same operations as the array form above (v + b (q_p - q)), without its
        # four small arrays (~13 -> ~4 us a joint; the starfish has five trajectories, called every step); q's
        # floats by one tolist(), the result by one np.array
        qs = q.tolist() if isinstance(q, np.ndarray) else [float(x) for x in q]
        b, out = self.b, []
        for f, qi in zip(self.positions, qs):
            val, rate = f.value_rate(t)
            out.append(rate + b * (val - qi))
        return np.array(out, dtype=float)

    def __repr__(self):
        return f"JointTrajectory({list(self.positions)}, b={self.b})"


def parse_trajectory(v, entry: str, d, n: int) -> JointTrajectory:
    """``{position: <time function, or a list of n>, b: 5}`` (b >= 0 [1/s], default DEFAULT_GAIN) of a joint
    with n velocity DOFs; ``v``: the scene _Validator (its errors name ``entry``)."""
    v.keys(entry, d, TRAJECTORY_KEYS, required=("position",))
    b = v.number(entry, "b", d.get("b", DEFAULT_GAIN), nonneg=True)
    return JointTrajectory(parse_vector(v, entry, "position", d["position"], n), b)
