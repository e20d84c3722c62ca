"""redmax_bench step: steps/s of the RedMax step (direct solver) on the issue's scenes, beside
semi-implicit Euler on pin.aba for the same Pinocchio model (tree only: ABA has no couplings, loops
or prescriptions, so the baseline is the cost floor of an explicit reduced-coordinate step), and a
per-stage breakdown of where one step's time goes. Rates are per CPU second of the benchmark process
(best of --repeats runs of --steps steps; see common.best_rate).

    redmax_bench step [--steps N] [--repeats R] [--no-chart] [--out DIR]

Writes step.json and step.png into --out (default bench/results under the current directory).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import pinocchio as pin

from redmax_ros.core import Simulator, Workspace
from redmax_ros.core.step import baselines
from redmax_ros.core.dynamics import constraints
from redmax_ros.core.dynamics import forces
from redmax_ros.core.dynamics import kinematics
from redmax_ros.core.step import pipeline as stepper
from redmax_bench.common import add_out_argument, best_rate, results_dir, write_json

TIPS = ["index_tip", "middle_tip", "ring_tip", "little_tip", "thumb_tip"]
TARGETS = {"hand": 5000.0, "chain-100+50 springs": 1000.0}


def cases():
    def hand():
        s = Simulator.load("hand")
        s.prescribe_joints({"elbow": 0.0})
        s.prescribe_sites({t: [0.0, 0.0, 0.0] for t in TIPS})
        return s

    out = [
        ("pendulum", lambda: Simulator.load("pendulum")),
        ("chain-20", lambda: Simulator.load("chain", ["params.n=20"])),
        ("chain-100+50 springs", lambda: Simulator.load("chain", ["params.n=100", "params.springs=50"])),
        ("hand", hand),
    ]
    try:
        Simulator.load("klann_leg")
        out.append(("klann_leg", lambda: Simulator.load("klann_leg")))
    except Exception:  # noqa: BLE001 - scene not shipped yet
        pass
    return out


def sie_rate(sim, n, repeats):
    mech, data = sim.mech, Workspace(sim.mech, pin_data=True)
    q0, v0 = sim.state.q.copy(), mech.to_reduced(sim.state.v).copy()

    def run(k):
        q, v = q0, v0
        for _ in range(k):
            a = baselines.acceleration(mech, data, q, v)
            v = v + sim.dt * a
            q = pin.integrate(mech.model, q, sim.dt * v)

    return best_rate(run, n, repeats)


STAGES = [("kinematics", kinematics, "compute"), ("forces (Eq. 2)", forces, "assemble"),
          ("constraints", constraints, "build"), ("solve", stepper, "solve_direct"),
          ("energies", stepper, "energies")]


def _cpu_per_call(f, n, repeats=5) -> float:
    """Best-of-``repeats`` CPU time [us] per call of f (n calls per repeat)."""
    def run(k):
        for _ in range(k):
            f()
    return 1e6 / best_rate(run, n, repeats)


def stage_times(sim, n=2000) -> dict:
    """CPU time [us] of each stage of stepper.step *inside* the step, on the current state: the whole
    step's time minus its time with that stage replaced by its cached result. (Stages timed in
    isolation run about twice as fast as inside the step, where they compete for caches with the
    rest; this measures what removing the stage would save.)"""
    m, ws, st, cmd, h = sim.mech, sim.workspace, sim.state, sim.commands, sim.dt
    vel = stepper.pinocchio_velocity
    whole = _cpu_per_call(lambda: stepper.step(m, ws, st, cmd, h, vel), n)
    out = {}
    for label, mod, fname in STAGES:
        orig, memo = getattr(mod, fname), {}

        def cached(*args, _orig=orig, **kw):
            if "r" not in memo:
                memo["r"] = _orig(*args, **kw)
            return memo["r"]

        setattr(mod, fname, cached)
        try:
            out[label] = max(whole - _cpu_per_call(lambda: stepper.step(m, ws, st, cmd, h, vel), n), 0.0)
        finally:
            setattr(mod, fname, orig)
    out["whole step"] = whole
    out["other (integrate, outputs, checks)"] = max(whole - sum(out[k] for k, _, _ in STAGES), 0.0)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench step")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-chart", action="store_true")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    rows = []
    print(f"{'scene':22s} {'DOF':>4s} {'ours steps/s':>13s} {'SIE/aba steps/s':>16s} {'ours/SIE':>9s} {'target':>7s}")
    for name, make in cases():
        sim = make()
        sim.step(50)
        ours = best_rate(lambda k: sim.step(k), a.steps, a.repeats)
        base = sie_rate(sim, a.steps, a.repeats)
        stages = stage_times(sim, 500)
        tgt = TARGETS.get(name)
        rows.append({"scene": name, "dof": sim.describe().ndof, "nv": sim.mech.nv, "steps_per_s": ours,
                     "sie_aba_steps_per_s": base, "ratio": ours / base, "target": tgt,
                     "meets_target": None if tgt is None else ours >= tgt, "stages_us": stages})
        print(f"{name:22s} {rows[-1]['dof']:4d} {ours:13.0f} {base:16.0f} {ours / base:9.2f} "
              f"{'' if tgt is None else ('%.0f' % tgt):>7s}")
    print("\nwhere the time goes (us CPU per step, each stage measured inside the step):")
    keys = list(rows[0]["stages_us"])
    print(f"{'scene':22s} " + " ".join(f"{k[:12]:>12s}" for k in keys))
    for r in rows:
        print(f"{r['scene']:22s} " + " ".join(f"{r['stages_us'][k]:12.1f}" for k in keys))
    path = write_json(a.out, "step", {"steps": a.steps, "repeats": a.repeats, "rows": rows})
    print(f"\nwrote {path}")
    if not a.no_chart:
        import matplotlib  # optional: matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # optional: matplotlib
        fig, ax = plt.subplots(figsize=(8, 4))
        x = np.arange(len(rows))
        ax.bar(x - 0.2, [r["steps_per_s"] for r in rows], 0.4, label="RedMax step (direct)")
        ax.bar(x + 0.2, [r["sie_aba_steps_per_s"] for r in rows], 0.4, label="semi-implicit Euler on pin.aba")
        for i, r in enumerate(rows):
            if r["target"]:
                ax.hlines(r["target"], i - 0.4, i + 0.4, colors="k", linestyles="dashed")
        ax.set_xticks(x, [r["scene"] for r in rows], rotation=15)
        ax.set_yscale("log")
        ax.set_ylabel("steps / s (log)")
        ax.set_title("Step throughput, measured side by side (dashed: targets)")
        ax.legend()
        fig.tight_layout()
        png = results_dir(a.out) / "step.png"
        fig.savefig(png, dpi=120)
        print(f"wrote {png}")
    return 0
