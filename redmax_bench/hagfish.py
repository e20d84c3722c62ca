"""redmax_bench hagfish: the paper's HAGFISH (Fig. 3, §6; scenes/hagfish.yaml) driven by a procedural tail
motion that tries to tie an overhand knot, with self-collision as unilateral rows of the QP of Eq. (5)
(docs/collisions.md). Per-step cost split into collision detection, QP (the velocity solve) and the rest,
active contacts, QP iterations, steps/s at h = 1e-3 (target 200), the knot measures (crossing number of
the centre line in the top view, tail through the loop), the worst penetration and the joint limits.
Writes hagfish.json into --out.

    redmax_bench hagfish [--steps N (default 3000 = 3 s: the knot is tied at 2.9 s)] [--out DIR]

The drive: two body points (sites s19, s39) are held by PD forces [N] at :data:`ANCHORS` (the standing
part, 5 cm above the floor) and the tail tip (site ``tail_tip``) is pulled by a PD force towards a target
moving along :data:`WAYPOINTS` (world frame [m], times [s]): out and back (the loop), over the standing part,
under it into the loop, up and over the loop's outgoing part; then held. Forces, not prescribed
velocities, so the contact rows can always be met (a prescribed point pushed into the body would make the
QP infeasible).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from redmax_ros.core import Simulator
from redmax_bench.common import add_out_argument, write_json

# Two body points (sites s19, s39) are held by PD forces above the floor at ANCHORS: the standing part of
# the knot, a bar along x at z = 0.05 m with room under it. (t [s], target of the tail tip [m]): swing out to
# +y and back, over the bar to -y (crossing 1, over), down and under the bar back to +y, inside the loop
# (crossing 2, under), up and over the tail's outgoing part out of the loop (crossing 3, over), held there.
ANCHORS = {"s19": (0.09, 0.0, 0.05), "s39": (0.18, 0.0, 0.05)}
WAYPOINTS = [(0.0, (0.45, 0.0, 0.03)), (0.8, (0.26, 0.07, 0.06)), (1.3, (0.17, 0.06, 0.10)),
             (1.7, (0.14, -0.05, 0.10)), (2.1, (0.14, -0.05, 0.01)), (2.5, (0.155, 0.03, 0.01)),
             (2.7, (0.16, 0.03, 0.12)), (3.1, (0.24, -0.02, 0.12)), (4.0, (0.24, -0.02, 0.12))]
KP_ANCHOR, KD_ANCHOR = 40.0, 1.0  # N/m, N s/m
KP, KD = 20.0, 0.6  # N/m, N s/m


def target(t: float) -> np.ndarray:
    """Piecewise-linear waypoint target of the tail tip at time t [m]."""
    ts = [w[0] for w in WAYPOINTS]
    ps = np.array([w[1] for w in WAYPOINTS], float)
    return np.array([np.interp(t, ts, ps[:, k]) for k in range(3)])


def centre_line(sim) -> np.ndarray:
    """(n, 3) world positions of the segments' body frames (the centre line) [m]."""
    P = sim.body_poses()
    return np.array([np.asarray(P[b][0], float) for b in sim.mech.bodies if b.startswith("seg")])


def crossings(X: np.ndarray) -> list:
    """Crossings of the polyline X (n,3) in the top view (xy): [(i, j, which is over)] for segments
    i < j - 1 whose xy projections intersect; 'over' is the index of the higher one at the crossing."""
    out = []
    P = X[:, :2]
    n = len(P) - 1
    for i in range(n):
        a, b = P[i], P[i + 1]
        for j in range(i + 2, n):
            c, d = P[j], P[j + 1]
            M = np.array([b - a, c - d]).T
            det = np.linalg.det(M)
            if abs(det) < 1e-14:
                continue
            s, u = np.linalg.solve(M, c - a)
            if 0 <= s <= 1 and 0 <= u <= 1:
                zi = X[i, 2] + s * (X[i + 1, 2] - X[i, 2])
                zj = X[j, 2] + u * (X[j + 1, 2] - X[j, 2])
                out.append((i, j, i if zi > zj else j))
    return out


def knot_measures(X: np.ndarray) -> dict:
    """Crossing number of the top view and whether the crossings alternate over/under along the body
    (an overhand knot's diagram: 3 crossings, alternating)."""
    cr = crossings(X)
    events = sorted([(i, c[2] == c[0]) for c in cr for i in (c[0],)] + [(c[1], c[2] == c[1]) for c in cr])
    alternating = len(events) >= 2 and all(events[k][1] != events[k + 1][1] for k in range(len(events) - 1))
    return {"crossings": len(cr), "alternating": bool(alternating)}


class KnotDrive:
    """The knotting drive: PD forces [N] on the anchor sites (held at :data:`ANCHORS`) and on the tail tip
    (towards :func:`target`), velocities by finite differences of the positions of the previous call (0 at
    the first), for a step of ``h`` [s]."""

    def __init__(self, mech, h: float):
        self.h = h
        self.tip = mech.site_index["tail_tip"]
        self.anchors = {n: mech.site_index[n] for n in ANCHORS}
        self.prev = None  # site positions of the previous call

    def forces(self, t: float, X: np.ndarray) -> dict:
        """{site: world force [N]} at time t [s] for the site positions X (S,3) [m]."""
        prev = X if self.prev is None else self.prev
        self.prev = X
        x = X[self.tip]
        f = {"tail_tip": KP * (target(t) - x) - KD * (x - prev[self.tip]) / self.h}
        for n, i in self.anchors.items():
            f[n] = KP_ANCHOR * (np.asarray(ANCHORS[n]) - X[i]) - KD_ANCHOR * (X[i] - prev[i]) / self.h
        return f


_CONTROLLER = {}


def knot_drive(t, state):
    """The drive as a redmax_run controller: ``redmax_run hagfish --controller redmax_bench.hagfish:knot_drive``
    (site positions from a kinematics-only copy of the scene at ``state``; one drive per process)."""
    if "drive" not in _CONTROLLER:
        kin = Simulator.load("hagfish", budget=None)
        _CONTROLLER.update(kin=kin, drive=KnotDrive(kin.mech, kin.spec.dt))
    kin = _CONTROLLER["kin"]
    kin.set_state(state)
    return {"site_forces": _CONTROLLER["drive"].forces(t, kin.site_positions())}


def run(steps: int, drive: bool = True, sim=None, qp_solver: str = "active-set") -> dict:
    """Step the hagfish ``steps`` times at its dt with the tail drive; the cost split and measures. ``qp``:
    how the contact QP is solved (``qp_solver``: Workspace.contact_qp, 'active-set' or 'proxsuite')."""
    sim = sim or Simulator.load("hagfish", budget=None)  # no step budget: a knot step's QP can take > 50 ms
    sim.workspace.contact_qp = qp_solver
    solvers = {}
    per_step = []  # CPU-wall seconds of each step
    mech = sim.mech
    h = sim.spec.dt
    tip = mech.site_index["tail_tip"]
    knot = KnotDrive(mech, h)
    lo, hi = mech.lower, mech.upper
    det = qp = tot = 0.0
    rows = act = iters = 0
    worst, worst_lim = np.inf, 0.0
    max_active = 0
    for k in range(steps):
        if drive:
            sim.set_site_forces(knot.forces(sim.time, sim.site_positions()))
        t0 = time.perf_counter()
        res = sim.step()
        dt_step = time.perf_counter() - t0
        tot += dt_step
        per_step.append(dt_step)
        c = res.diagnostics.solution.contacts
        det += c.t_detect + c.t_rows
        qp += c.t_solve
        rows += c.rows
        act += c.active
        max_active = max(max_active, c.active)
        iters += res.diagnostics.iterations
        solvers[res.diagnostics.solver] = solvers.get(res.diagnostics.solver, 0) + 1
        worst = min(worst, c.min_distance)
        qr = sim.joint_positions() if hasattr(sim, "joint_positions") else None
        if qr is not None and len(qr) == mech.nv:
            worst_lim = max(worst_lim, float(np.max(np.maximum(qr - hi, lo - qr))))
    X = centre_line(sim)
    out = {"steps": steps, "h": h, "nv": mech.nv, "contact_qp": qp_solver, "solvers": solvers, "steps_per_s": steps / tot,
           "steps_per_s_by_500": [round(len(w) / sum(w), 1) for w in (per_step[i:i + 500] for i in range(0, steps, 500))],
           "ms_per_step": 1e3 * tot / steps, "ms_detect": 1e3 * det / steps, "ms_qp": 1e3 * qp / steps,
           "ms_rest": 1e3 * (tot - det - qp) / steps, "rows_per_step": rows / steps,
           "active_per_step": act / steps, "max_active": max_active, "qp_iterations_per_step": iters / steps,
           "worst_distance_m": worst, "worst_limit_excess_rad": worst_lim, "tip_error_m":
           float(np.linalg.norm(sim.site_positions()[tip] - target(sim.time)))}
    out.update(knot_measures(X))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench hagfish", description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--qp", nargs="+", default=["active-set", "proxsuite"], choices=["active-set", "proxsuite"],
                    help="contact QP solvers to run, side by side (the first is the headline)")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    runs = {qp: run(a.steps, qp_solver=qp) for qp in a.qp}  # the same drive, one after the other in this process
    for k in next(iter(runs.values())):
        print(f"{k:26s} " + "  |  ".join(f"{r[k]}" for r in runs.values()))
    r = dict(runs[a.qp[0]])
    if len(runs) > 1:
        r["by_qp"] = runs
    write_json(a.out, "hagfish", r)
    return 0
