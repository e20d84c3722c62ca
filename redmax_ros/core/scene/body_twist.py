"""Body-twist prescriptions as the scene and the commands give them (issue 13 item 4): the selected
components of a body's twist [omega; v] and their frame. The rows and wrenches are step/body_twist.py.

A component is a number (constant), null (free) or a time function of the scene grammar
(scene/timefunctions.py: sine, ramp, quintic, cubic, ...), evaluated at the end time t_k+1 of each step
(like the right-hand side of a joint trajectory's row: hybrid dynamics, paper Eq. 7, *G_m qdot = g(t_k+1)).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FRAMES = ("body", "world")


@dataclass
class BodyTwist:
    P: np.ndarray  # (k,6) selected rows of I6 ([angular; linear] order)
    g: np.ndarray  # (k,) prescribed components [rad/s, m/s] (the constant ones; timed rows: value at t = 0)
    frame: str  # 'body' | 'world'
    timed: tuple = ()  # (row, TimeFunction) of the components given as time functions

    def at(self, t: float) -> "BodyTwist":
        """The prescription with its timed components evaluated at t [s] (itself when none is timed)."""
        if not self.timed:
            return self
        g = self.g.copy()
        for r, f in self.timed:
            g[r] = f(t)
        return BodyTwist(self.P, g, self.frame)


def parse(name: str, d, bodies, time_function=None) -> BodyTwist:
    """A BodyTwist from {angular: [3], linear: [3], frame: body|world}; a null component is left free
    (e.g. angular: [null, 2, null] prescribes omega_y only). ValueError naming the problem.
    ``time_function(key, value)``: parses a mapping component (e.g. key "angular[1]") into a
    scene.timefunctions.TimeFunction, raising for a bad one; None: mappings are refused."""
    if name not in bodies:
        raise ValueError(f"unknown body '{name}' (known: {', '.join(bodies)})")
    if not isinstance(d, dict):
        raise ValueError(f"body '{name}': expected {{angular: [wx, wy, wz], linear: [vx, vy, vz], frame: body|world}}")
    extra = set(d) - {"angular", "linear", "frame"}
    if extra:
        raise ValueError(f"body '{name}': unknown key(s) {', '.join(sorted(map(str, extra)))} (angular, linear, frame)")
    frame = d.get("frame", "body")
    if frame not in FRAMES:
        raise ValueError(f"body '{name}': unknown frame {frame!r} (body, world)")
    rows, vals, timed = [], [], []
    for off, key in ((0, "angular"), (3, "linear")):
        if key not in d:
            continue
        val = d[key]
        if not isinstance(val, (list, tuple, np.ndarray)) or len(val) != 3:
            raise ValueError(f"body '{name}': '{key}' needs 3 values (a number, or null for a free component), "
                             f"got {val!r}")
        for c, x in enumerate(val):
            if x is None:  # this component is not prescribed
                continue
            if isinstance(x, dict) and time_function is not None:  # a time function of t_k+1
                f = time_function(f"{key}[{c}]", x)
                timed.append((len(rows), f))
                rows.append(off + c)
                vals.append(f(0.0))
                continue
            try:
                x = float(x)
            except (TypeError, ValueError):
                raise ValueError(f"body '{name}': '{key}'[{c}] is not a number (or null, or a time function): {x!r}") from None
            if not np.isfinite(x):
                raise ValueError(f"body '{name}': non-finite '{key}'[{c}] = {x}")
            rows.append(off + c)
            vals.append(x)
    if not rows:
        raise ValueError(f"body '{name}': give 'angular' and/or 'linear' (at least one non-null component)")
    return BodyTwist(np.eye(6)[rows], np.array(vals, float), frame, tuple(timed))
