"""Body-twist prescriptions as the scene and the commands give them (issue 13 item 4): the selected
components of a body's twist [omega; v] and their frame. The rows and wrenches are step/body_twist.py.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FRAMES = ("body", "world")


@dataclass
class BodyTwist:
    P: np.ndarray  # (k,6) selected rows of I6 ([angular; linear] order)
    g: np.ndarray  # (k,) prescribed components [rad/s, m/s]
    frame: str  # 'body' | 'world'


def parse(name: str, d, bodies) -> BodyTwist:
    """A BodyTwist from {angular: [3], linear: [3], frame: body|world}; a null component is left free
    (e.g. angular: [null, 2, null] prescribes omega_y only). ValueError naming the problem."""
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
    rows, vals = [], []
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
            try:
                x = float(x)
            except (TypeError, ValueError):
                raise ValueError(f"body '{name}': '{key}'[{c}] is not a number: {x!r}") from None
            if not np.isfinite(x):
                raise ValueError(f"body '{name}': non-finite '{key}'[{c}] = {x}")
            rows.append(off + c)
            vals.append(x)
    if not rows:
        raise ValueError(f"body '{name}': give 'angular' and/or 'linear' (at least one non-null component)")
    return BodyTwist(np.eye(6)[rows], np.array(vals, float), frame)
