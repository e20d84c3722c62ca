"""redmax_run: run a scene offline (no ROS) and write a CSV of the trajectory.

    redmax_run SCENE [--dt H] [--duration T] [--solver direct|reference|compiled|pcg|auto] [--set key=value ...] [--out FILE.csv]

CSV columns: t; q:<joint> and v:<joint> (``[i]`` per component of multi-DOF joints); E_kin, E_pot,
E_spring, E_total [J]; violation (max loop-closure residual [m]); tau:<joint> for prescribed joints
(required torque [N m] or force [N]), f:<site>[i] for prescribed sites (required force [N], world) and
w:<body>[i], i = 0..5, for prescribed body twists (required wrench [torque N m; force N] in the
prescription's frame).
Prescriptions, joint trajectories included, are scene values: ``--set 'prescribed={joints: {hinge: {position:
{type: sine, amplitude: 0.4, frequency: 0.5}, b: 5}}}'`` (docs/scenes.md, Constraints).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from redmax_ros.core import SOLVERS, CommandError, SceneError, Simulator, StepBudget, StepError


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="redmax_run", description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="scene name (scenes/) or path to a scene YAML")
    ap.add_argument("--dt", type=float, help="time step h [s] (default: the scene's)")
    ap.add_argument("--duration", type=float, help="simulated time [s] (default: the scene's)")
    ap.add_argument("--solver", choices=list(SOLVERS), default=None,
                    help="linear solver (default: the scene's; see docs/solvers.md)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scene value or builder parameter, e.g. params.n=20, joints.elbow.q0=0.3")
    ap.add_argument("--out", type=Path, help="CSV file to write (default: runs/<scene>.csv)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--step-budget-ms", type=float, default=None, metavar="MS",
                    help="CPU time a step's iterative solvers may take before the step fails (default: the "
                         "core's StepBudget, 50 ms; 0: unlimited, ProxSuite's own iteration caps)")
    return ap.parse_args(argv)


def csv_header(sim: Simulator) -> list:
    d = sim.describe()
    cols = ["t"] + [f"q:{n}" for n in d.position_names] + [f"v:{n}" for n in d.velocity_names]
    cols += ["E_kin", "E_pot", "E_spring", "E_total", "violation"]
    for name in sim.prescribed_joints():
        j = sim.mech.joint_index[name]
        cols += [f"tau:{name}"] if j.nv == 1 else [f"tau:{name}[{i}]" for i in range(j.nv)]
    for name in sim.prescribed_sites():
        cols += [f"f:{name}[{i}]" for i in range(3)]
    for name in sim.prescribed_bodies():
        cols += [f"w:{name}[{i}]" for i in range(6)]
    return cols


def csv_row(sim: Simulator, res) -> np.ndarray:
    dg = res.diagnostics
    parts = [[res.t], res.q, res.v, [dg.E_kin, dg.E_pot, dg.E_spring, dg.E_total, dg.violation_pos]]
    for name in sim.prescribed_joints():
        j = sim.mech.joint_index[name]
        parts.append(res.effort[j.idx_v:j.idx_v + j.nv])
    for name in sim.prescribed_sites():
        parts.append(res.site_forces[name])
    for name in sim.prescribed_bodies():
        parts.append(res.body_wrenches[name])
    return np.concatenate([np.atleast_1d(np.asarray(p, float)) for p in parts])


class Progress:
    """A one-line progress bar on stderr, shown only for runs that last more than ~2 s of wall time."""

    def __init__(self, total: int, quiet: bool):
        self.total, self.quiet = total, quiet
        self.t0 = self.last = time.perf_counter()
        self.shown = False

    def update(self, done: int):
        if self.quiet:
            return
        now = time.perf_counter()
        if now - self.t0 < 2.0 or now - self.last < 0.25:
            return
        self.last, self.shown = now, True
        frac = done / self.total
        eta = (now - self.t0) * (1 - frac) / max(frac, 1e-9)
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\r[{bar:<30}] {100 * frac:5.1f}%  {done}/{self.total} steps  eta {eta:5.1f} s")
        sys.stderr.flush()

    def close(self):
        if self.shown:
            sys.stderr.write("\n")


def run(sim: Simulator, n_steps: int, quiet=False):
    """Step n times; returns (rows (n+1, C) incl. the initial state, error or None, wall time [s])."""
    header = csv_header(sim)
    rows = np.empty((n_steps + 1, len(header)))
    r0 = initial_row(sim)
    rows[0, :len(r0)] = r0
    rows[0, len(r0):] = np.nan  # no required forces before the first step
    bar = Progress(n_steps, quiet)
    err = None
    t0 = time.perf_counter()
    k = 0
    for k in range(1, n_steps + 1):
        try:
            res = sim.step()
        except StepError as e:
            err = e
            k -= 1
            break
        rows[k] = csv_row(sim, res)
        bar.update(k)
    wall = time.perf_counter() - t0
    bar.close()
    return header, rows[:k + 1], err, wall


def initial_row(sim: Simulator) -> np.ndarray:
    v = sim.joint_velocities()
    ek, ep, es = sim.energies()
    return np.concatenate([[sim.time], sim.state.q, v, [ek, ep, es, ek + ep + es, 0.0]])


def summary(sim, header, rows, wall, err) -> str:
    n = len(rows) - 1
    E = rows[:, header.index("E_total")]
    viol = rows[:, header.index("violation")]
    drift = E[-1] - E[0]
    lines = [
        f"scene {sim.scene_name}: {n} steps of h = {sim.dt:g} s ({n * sim.dt:g} s simulated, "
        f"{sim.describe().ndof} DOF)",
        f"  wall time {wall:.3f} s: {n / max(wall, 1e-12):.0f} steps/s, real-time factor {n * sim.dt / max(wall, 1e-12):.2f}",
        f"  energy: start {E[0]:.6g} J, end {E[-1]:.6g} J, drift {drift:+.3e} J"
        + (f" ({drift / abs(E[0]):+.2e} relative)" if abs(E[0]) > 1e-12 else ""),
        f"  max loop-closure violation {np.nanmax(viol):.3e} m",
    ]
    if err is not None:
        lines.append(f"  STOPPED: {err}")
    return "\n".join(lines)


def main(argv=None) -> int:
    a = parse_args(argv)
    overrides = list(a.set)
    if a.dt is not None:
        overrides.append(f"dt={a.dt}")
    if a.solver is not None:
        overrides.append(f"solver={a.solver}")
    try:
        sim = Simulator.load(a.scene, overrides)
        if a.step_budget_ms is not None:
            sim.budget = StepBudget.from_ms(a.step_budget_ms)
    except (SceneError, CommandError) as e:
        print(f"redmax_run: {e}", file=sys.stderr)
        return 2
    duration = a.duration if a.duration is not None else sim.spec.duration
    if not duration > 0:
        print("redmax_run: --duration must be positive", file=sys.stderr)
        return 2
    n = max(1, int(round(duration / sim.dt)))
    header, rows, err, wall = run(sim, n, a.quiet)
    out = a.out or Path("runs") / f"{sim.scene_name}.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(out, rows, delimiter=",", header=",".join(header), comments="", fmt="%.17g")
    print(summary(sim, header, rows, wall, err))
    print(f"  wrote {out} ({len(rows)} rows x {len(header)} columns)")
    return 1 if err is not None else 0


if __name__ == "__main__":
    sys.exit(main())
