"""The velocity rows of joint trajectories whose position functions are all sines or constants on joints whose
positions are their coordinates (trajectory.py's coordinate case), for all joints in one compiled call: per DOF
the same operations as TimeFunction.value_rate and JointTrajectory.rate,

    w = 2 pi f,  a = w t + phase,  g = amplitude w cos(a) + b ((offset + amplitude sin(a)) - q)   (sine)
    g = 0.0 + b (value - q)                                                                         (constant)

(numba's math.sin / math.cos are the C library's, as Python's), instead of ~4 Python calls and a small array a
DOF. A plan (``sine_plan``) is built once per set of trajectories and mechanism and kept while both stand."""
from __future__ import annotations

import math

import numpy as np

from redmax_ros.core.jit import njit

_PLANS = {}  # (id(mech), ((name, id(traj)), ...)) -> SinePlan; the plan keeps both alive, so the ids stay theirs
_MAX_PLANS = 8  # the plans keep their mechanisms alive: a few at most (one per simulator and command set in use)


class SinePlan:
    """Per DOF: coordinate index, sine flag, amplitude, w = 2 pi f, phase, offset (or the constant's value),
    gain b; per joint (name, first DOF, end)."""

    def __init__(self, mech, trajectories, joints):
        self.mech, self.trajectories = mech, dict(trajectories)  # kept alive: the cache key holds their ids
        iq, sine, amp, w, ph, off, b, self.slices = [], [], [], [], [], [], [], []
        for name, traj in self.trajectories.items():
            j = joints[name]
            self.slices.append((name, len(iq), len(iq) + j.nv))
            for i, f in enumerate(traj.positions):
                p = f.p
                iq.append(j.idx_q + i)
                b.append(traj.b)
                if f.kind == "sine":
                    sine.append(True)
                    amp.append(p["amplitude"])
                    w.append(2.0 * math.pi * p["frequency"])
                    ph.append(p["phase"])
                    off.append(p["offset"])
                else:
                    sine.append(False)
                    amp.append(0.0)
                    w.append(0.0)
                    ph.append(0.0)
                    off.append(p["value"])
        self.arrays = (np.asarray(iq, np.int64), np.asarray(sine, np.bool_), np.asarray(amp, float),
                       np.asarray(w, float), np.asarray(ph, float), np.asarray(off, float), np.asarray(b, float))


def sine_plan(mech, trajectories, coordinate_types, manifold_types):
    """The SinePlan of ``trajectories`` (joint name -> JointTrajectory) on mech, or None when a joint is not a
    coordinate joint (``coordinate_types`` with nq = nv, not in ``manifold_types``) or a function is neither a
    sine nor a constant."""
    key = (id(mech), tuple((name, id(traj)) for name, traj in trajectories.items()))
    plan = _PLANS.get(key, False)
    if plan is not False:
        return plan
    plan = None
    joints = {name: mech.joint_index[name] for name in trajectories}
    if all(j.nq == j.nv and j.type in coordinate_types and j.type not in manifold_types
           and traj.nv == j.nv and all(f.kind in ("sine", "constant") for f in traj.positions)
           for j, traj in ((joints[n], t) for n, t in trajectories.items())):
        plan = SinePlan(mech, trajectories, joints)
    if len(_PLANS) >= _MAX_PLANS:
        _PLANS.clear()
    _PLANS[key] = plan
    return plan


def rates(plan: SinePlan, q, t: float) -> dict:
    """joint name -> its velocity row's values (nv,) [rad/s, m/s] at end time t from configuration q (views of
    one array)."""
    out = rates_kernel(*plan.arrays, np.ascontiguousarray(q, dtype=float), float(t))
    return {name: out[s:e] for name, s, e in plan.slices}


@njit
def rates_kernel(iq, sine, amp, w, ph, off, b, q, t):
    n = len(iq)
    out = np.empty(n)
    for i in range(n):
        qi = q[iq[i]]
        if sine[i]:
            a = w[i] * t + ph[i]
            val = off[i] + amp[i] * math.sin(a)
            rate = amp[i] * w[i] * math.cos(a)
        else:
            val = off[i]
            rate = 0.0
        out[i] = rate + b[i] * (val - qi)
    return out
