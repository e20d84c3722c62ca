"""redmax_bench step: CPU microseconds per step of the RedMax step beside MuJoCo and Pinocchio, on the
issue's scenes, side by side in one run.

Columns (one function per engine below, ``*_engine``):

* ``ours (reference)``: ``Simulator.load(scene, overrides, solver="reference")``, ``sim.step(k)`` (the
  Pinocchio pipeline);
* ``ours (compiled)``: the same with ``solver="compiled"`` (the default ``direct`` where the scene allows it); n/a (with the reason) where that backend
  does not load;
* ``MuJoCo implicitfast`` / ``discrete`` / ``euler``: the scene exported by ``mujoco_export`` (time step
  = the scene's dt), ``mujoco.mj_step(m, d)`` once per step from a Python loop, so the figure is MuJoCo's
  real per-call cost from Python (binding overhead included); n/a where the export does not carry the
  scene (prescribed motion, contact, joint friction, ...);
* ``SIE on pin.aba``: semi-implicit Euler on ``pin.aba`` for the same Pinocchio model, the tree only
  (no couplings, loops, limits, prescriptions or friction): the cost floor of an explicit
  reduced-coordinate step, not the same problem.

Timing: CPU time of this process (time.process_time), best of --repeats runs of --steps steps, each run
from the scene's initial state (after an untimed warm-up of WARMUP steps: JIT, caches); in each round
every engine of the scene runs once before the next round starts, so load from other processes affects
all engines alike. ``ours`` for the targets is the compiled column when it has a figure, else the
reference one. ``--stages`` adds the per-stage breakdown of the reference pipeline (slow).

    redmax_bench step [--steps N] [--repeats R] [--scenes a,b] [--stages] [--no-chart] [--out DIR]

``--scenes`` takes case labels or scene names (``hand`` selects both hand cases). Writes step.json and
step.png into --out (default bench/results under the current directory).
"""
from __future__ import annotations

import argparse
import os
import re
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pinocchio as pin

from redmax_ros.core import Simulator, Workspace
from redmax_ros.core.step import baselines
from redmax_ros.core.dynamics import constraints
from redmax_ros.core.dynamics import forces
from redmax_ros.core.dynamics import kinematics
from redmax_ros.core.step import pipeline as stepper
from redmax_bench import mujoco_export
from redmax_bench.common import add_out_argument, best_rate, results_dir, write_json

TIPS = ["index_tip", "middle_tip", "ring_tip", "little_tip", "thumb_tip"]
WARMUP = 50  # untimed steps per engine before the timed runs
REF, COMPILED, SIE = "ours (reference)", "ours (compiled)", "SIE on pin.aba"
COMPILED_1 = "ours (compiled, 1 step/call)"  # sim.step() once per step from Python, as paced free-run steps
COMPILED_R = "ours (compiled, results)"  # sim.step_results(k): every step's StepResult, as the node's runs publish
MUJOCO_INTEGRATORS = ("implicitfast", "discrete", "euler")
MJ = {i: f"MuJoCo {i}" for i in MUJOCO_INTEGRATORS}
COLUMNS = [REF, COMPILED, COMPILED_1, COMPILED_R, *MJ.values(), SIE]
RATIOS = {"compiled/MJ implicitfast": COMPILED, "compiled 1 step/call/MJ implicitfast": COMPILED_1,
          "reference/MJ implicitfast": REF}


# ---------------------------------------------------------------------------------------------
# cases


def _free_hand(sim):
    sim.release_joints(["elbow"])  # the scene holds the elbow by default


def _held_hand(sim):
    sim.prescribe_joints({"elbow": 0.0})
    sim.prescribe_sites({t: [0.0, 0.0, 0.0] for t in TIPS})


@dataclass(frozen=True)
class Case:
    label: str
    scene: str
    overrides: tuple = ()
    setup: Callable | None = None  # (Simulator) -> None: commands beyond the scene's defaults
    max_ratio: float | None = None  # target: ours <= max_ratio x MuJoCo implicitfast
    min_rate: float | None = None  # target: ours >= min_rate steps/s
    # MuJoCo steps the mechanism without the scene's prescriptions (the export has none), instead of n/a
    mujoco_unprescribed: bool = False


CASES = [
    Case("hand", "hand", setup=_free_hand, max_ratio=2.0),
    Case("hand 5 tips+elbow", "hand", setup=_held_hand, min_rate=40_000.0),
    Case("chain-20", "chain", ("params.n=20",), max_ratio=2.0),
    Case("chain-100+50 springs", "chain", ("params.n=100", "params.springs=50"), max_ratio=1.0),
    Case("mass_springs", "mass_springs", max_ratio=2.0),
    Case("fourbar", "fourbar", max_ratio=2.0),
    Case("klann_leg", "klann_leg", max_ratio=2.0, mujoco_unprescribed=True),
    Case("klann walker", "klann", ("friction.joint_mu=0.4",), min_rate=10_000.0),
]


def select(names) -> list:
    """The cases whose label or scene name is in ``names`` (None: all); SystemExit on an unknown name."""
    if not names:
        return list(CASES)
    known = {c.label for c in CASES} | {c.scene for c in CASES}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise SystemExit(f"redmax_bench step: unknown scene(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    return [c for c in CASES if c.label in names or c.scene in names]


def load(case: Case, solver: str) -> Simulator:
    sim = Simulator.load(case.scene, list(case.overrides), solver=solver)
    if case.setup is not None:
        case.setup(sim)
    return sim


# ---------------------------------------------------------------------------------------------
# engines: each returns an Engine or raises (the column is then n/a with the error's first line)


@dataclass
class Engine:
    reset: Callable[[], None]  # back to the initial state (not timed)
    run: Callable[[int], None]  # k steps (timed)
    check: Callable[[], str | None] = lambda: None  # after a run: what went wrong in it, or None


def ours_engine(sim: Simulator, per_call: bool = False, results: bool = False) -> Engine:
    """sim.step(k) (a run of k steps: one kernel call on the compiled path), with ``per_call`` k calls of
    sim.step() (the per-step Python cost included, as in the node's paced free run), with ``results``
    sim.step_results(k) (every step's StepResult, recorded in runs: the node's step requests)."""
    s0 = sim.state
    sim.step(WARMUP)

    def one_by_one(k):
        for _ in range(k):
            sim.step()

    run = one_by_one if per_call else (sim.step_results if results else sim.step)
    return Engine(lambda: sim.set_state(s0), run)


def mujoco_engine(case: Case, sim: Simulator, integrator: str) -> Engine:
    import mujoco  # optional: mujoco

    mech = sim.mech
    if mech.friction is not None:
        raise NotImplementedError("contact and joint friction are not exported (the export switches MuJoCo "
                                  "contact off; the pin-joint friction model has no counterpart there)")
    if mech.extras is not None:
        raise NotImplementedError("catalogue joints/force elements are not exported")
    c = sim.commands
    if (c.joint_velocities or c.site_velocities or c.joint_trajectories or c.body_twists) and not case.mujoco_unprescribed:
        raise NotImplementedError("prescribed motion (hybrid dynamics) is not exported to MuJoCo")
    ex = mujoco_export.export(mech, sim.dt, integrator)
    m, d, d0 = ex.model, ex.make_data(), ex.make_data()
    d0.qpos[:] = ex.qpos(mech.q0)
    d0.qvel[:] = ex.qvel(mech.q0, mech.to_reduced(mech.v0))

    def reset():
        mujoco.mj_copyData(d, m, d0)

    def run(k):
        for _ in range(k):
            mujoco.mj_step(m, d)

    def check():
        bad = [w for w in ("mjWARN_BADQPOS", "mjWARN_BADQVEL", "mjWARN_BADQACC")
               if int(d.warning[getattr(mujoco.mjtWarning, w)].number)]
        return f"{', '.join(bad)} (MuJoCo reset the state) in the timed steps" if bad else None

    reset()
    run(WARMUP)
    return Engine(reset, run, check)


def sie_engine(sim: Simulator) -> Engine:
    mech, data = sim.mech, Workspace(sim.mech, pin_data=True)
    q0, v0, h = mech.q0.copy(), mech.to_reduced(mech.v0).copy(), sim.dt

    def run(k):
        q, v = q0, v0
        for _ in range(k):
            a = baselines.acceleration(mech, data, q, v)
            v = v + h * a
            q = pin.integrate(mech.model, q, h * v)

    run(WARMUP)
    return Engine(lambda: None, run)


def engines(case: Case, ref: Simulator) -> tuple:
    """({column: Engine}, {column: why n/a}) for one case; ``ref`` is its reference Simulator."""
    makers = {REF: lambda: ours_engine(ref), COMPILED: lambda: ours_engine(load(case, "compiled")),
              COMPILED_1: lambda: ours_engine(load(case, "compiled"), per_call=True),
              COMPILED_R: lambda: ours_engine(load(case, "compiled"), results=True),
              **{col: (lambda i=i: mujoco_engine(case, ref, i)) for i, col in MJ.items()},
              SIE: lambda: sie_engine(ref)}
    out, na = {}, {}
    for col, make in makers.items():
        try:
            out[col] = make()
        except Exception as e:  # noqa: BLE001 - any failure to build an engine makes its column n/a
            na[col] = _first_line(e)
    return out, na


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}"


def time_interleaved(eng: dict, steps: int, repeats: int, na: dict) -> dict:
    """{column: us of CPU per step}: best of ``repeats`` runs of ``steps`` steps, the engines taking turns
    in each round. An engine whose run raises, or whose check reports a problem, gets None (reason in na)."""
    rate = dict.fromkeys(eng, 0.0)
    for _ in range(repeats):
        for col, e in eng.items():
            if col in na:
                continue
            e.reset()
            try:
                rate[col] = max(rate[col], best_rate(e.run, steps, 1))
                problem = e.check()
            except Exception as exc:  # noqa: BLE001 - e.g. a StepError: no figure for this engine
                problem = _first_line(exc)
            if problem:
                na[col] = problem
    return {col: None if col in na else 1e6 / r for col, r in rate.items()}


# ---------------------------------------------------------------------------------------------
# per-stage breakdown of the reference pipeline (--stages)

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


# ---------------------------------------------------------------------------------------------
# targets, one case


def target(case: Case, us: dict) -> dict:
    """The issue's target of the case: what, against which ours column, and met / missed / n/a."""
    which = COMPILED if us.get(COMPILED) is not None else REF
    ours = us.get(which)
    if case.max_ratio is not None:
        mj = us.get(MJ["implicitfast"])
        value = None if ours is None or mj is None else ours / mj
        ok = None if value is None else value <= case.max_ratio
        what = f"<= {case.max_ratio:g}x MuJoCo implicitfast"
    elif case.min_rate is not None:
        value = None if ours is None else 1e6 / ours
        ok = None if value is None else value >= case.min_rate
        what = f">= {case.min_rate:,.0f} steps/s"
    else:
        return {"what": None, "ours": which, "value": None, "status": None}
    return {"what": what, "ours": which, "value": value, "status": "n/a" if ok is None else ("met" if ok else "missed")}


def target_us(case: Case, us: dict) -> float | None:
    """The case's target as us per step for ours (None: no target, or its MuJoCo figure is n/a)."""
    mj = us.get(MJ["implicitfast"])
    if case.max_ratio is not None:
        return None if mj is None else case.max_ratio * mj
    return None if case.min_rate is None else 1e6 / case.min_rate


def measure(case: Case, steps: int, repeats: int, stages: bool) -> dict:
    ref = load(case, "reference")
    eng, na = engines(case, ref)
    us = time_interleaved(eng, steps, repeats, na)
    us.update({col: None for col in na})
    us = {col: us.get(col) for col in COLUMNS}
    mj = us[MJ["implicitfast"]]
    row = {"case": case.label, "scene": case.scene, "overrides": list(case.overrides), "nv": ref.mech.nv,
           "dof": ref.describe().ndof, "us_per_step": us,
           "steps_per_s": {col: None if v is None else 1e6 / v for col, v in us.items()},
           "ratios": {k: None if us[c] is None or mj is None else us[c] / mj for k, c in RATIOS.items()},
           "na": na, "target": target(case, us)}
    if case.mujoco_unprescribed and mj is not None:
        row["note"] = "MuJoCo steps the mechanism without the scene's prescriptions (not exported); ours has them"
    if stages and us[REF] is not None:
        row["stages_us"] = stage_times(ref, 500)
    return row


# ---------------------------------------------------------------------------------------------
# output


def _fmt(x, spec):
    return "n/a" if x is None else format(x, spec)


def print_table(rows, steps, repeats):
    short = {REF: "ref", COMPILED: "compiled", COMPILED_1: "compiled/1", COMPILED_R: "results", MJ["implicitfast"]: "MJ implfast", MJ["discrete"]: "MJ discrete",
             MJ["euler"]: "MJ euler", SIE: "SIE/aba"}
    print(f"us of CPU per step (best of {repeats} runs of {steps} steps, engines interleaved per scene); "
          f"ratios ours/MuJoCo implicitfast")
    head = f"{'scene':22s} {'nv':>4s} " + " ".join(f"{short[c]:>11s}" for c in COLUMNS)
    head += " " + " ".join(f"{k.split('/')[0] + '/MJ':>12s}" for k in RATIOS)
    print(head)
    for r in rows:
        print(f"{r['case']:22s} {r['nv']:4d} " + " ".join(f"{_fmt(r['us_per_step'][c], '11.1f'):>11s}" for c in COLUMNS)
              + " " + " ".join(f"{_fmt(r['ratios'][k], '12.2f'):>12s}" for k in RATIOS))
    print("\ntargets (ours = the compiled column when it has a figure, else the reference one):")
    for r in rows:
        t = r["target"]
        if t["what"] is None:
            continue
        val = "n/a" if t["value"] is None else (f"{t['value']:.2f}x" if "x MuJoCo" in t["what"] else f"{t['value']:,.0f} steps/s")
        print(f"  {r['case']:22s} {t['what']:32s} {t['ours']:17s} {val:>16s}  {t['status']}")


def collect_notes(rows) -> list:
    """One line per n/a reason (scene paths left out) with the columns and cases it applies to, plus the
    per-case notes. The rows keep each reason as raised."""
    cases = {}  # (column, reason) -> cases
    for r in rows:
        for col, why in r["na"].items():
            cases.setdefault((col, re.sub(r"\S+\.ya?ml: ", "", why)), []).append(r["case"])
    cols = {}  # (reason, cases) -> columns
    for (col, why), cs in cases.items():
        cols.setdefault((why, tuple(cs)), []).append(col)
    everywhere = [r["case"] for r in rows]
    notes = [f"{', '.join(c)}: n/a on {'all cases' if list(cs) == everywhere else ', '.join(cs)}: {why}"
             for (why, cs), c in cols.items()]
    return notes + [f"{r['case']}: {r['note']}" for r in rows if r.get("note")]


def print_stages(rows):
    rows = [r for r in rows if "stages_us" in r]
    if not rows:
        return
    print("\nwhere the time goes, ours (reference) (us CPU per step, each stage measured inside the step):")
    keys = list(rows[0]["stages_us"])
    print(f"{'scene':22s} " + " ".join(f"{k[:12]:>12s}" for k in keys))
    for r in rows:
        print(f"{r['case']:22s} " + " ".join(f"{r['stages_us'][k]:12.1f}" for k in keys))


def chart(rows, path):
    import matplotlib  # optional: matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # optional: matplotlib
    fig, ax = plt.subplots(figsize=(12, 4.8))
    w = 0.8 / len(COLUMNS)
    x = np.arange(len(rows))
    for j, col in enumerate(COLUMNS):
        xs, us = x - 0.4 + (j + 0.5) * w, [r["us_per_step"][col] for r in rows]
        ax.bar(xs, [np.nan if u is None else u for u in us], w, label=col)
        for xi, u in zip(xs, us):
            if u is None:
                ax.text(xi, 0.01, "n/a", transform=ax.get_xaxis_transform(), rotation=90, ha="center",
                        va="bottom", fontsize=7, color="0.4")
    label = "target for ours (at or below)"
    for i, r in enumerate(rows):
        y = target_us(next(c for c in CASES if c.label == r["case"]), r["us_per_step"])
        if y is not None:
            ax.hlines(y, i - 0.45, i + 0.45, colors="k", linestyles="dashed", label=label)
            label = None  # one legend entry
    ax.set_xticks(x, [r["case"] for r in rows], rotation=15)
    ax.set_yscale("log")
    ax.set_ylabel("us of CPU per step (log, lower is faster)")
    ax.set_title("Step cost, engines side by side in one run")
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench step")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes", type=lambda s: [x.strip() for x in s.split(",") if x.strip()], default=None,
                    metavar="A,B", help="case labels or scene names (default: all)")
    ap.add_argument("--stages", action="store_true", help="per-stage breakdown of ours (reference); slow")
    ap.add_argument("--no-chart", action="store_true")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    rows = []
    for case in select(a.scenes):
        try:
            rows.append(measure(case, a.steps, a.repeats, a.stages))
        except Exception as e:  # noqa: BLE001 - the scene itself does not load: skip it, say why
            print(f"{case.label}: skipped ({_first_line(e)})")
    mj_version = mujoco_export.mujoco.__version__ if mujoco_export.available() else None
    notes = [f"MuJoCo {mj_version}: mj_step once per step from a Python loop (its per-call cost from "
             f"Python), timestep = the scene's dt, contact off (mujoco_export)"] + collect_notes(rows)
    print_table(rows, a.steps, a.repeats)
    print("\nnotes:\n" + "\n".join(f"  - {n}" for n in notes))
    print_stages(rows)
    path = write_json(a.out, "step", {
        "steps": a.steps, "repeats": a.repeats, "warmup": WARMUP, "columns": COLUMNS,
        "versions": {"mujoco": mj_version, "pinocchio": pin.__version__, "numpy": np.__version__},
        "load_average": list(os.getloadavg()), "rows": rows, "notes": notes})
    print(f"\nwrote {path}")
    if not a.no_chart:
        png = results_dir(a.out) / "step.png"
        chart(rows, png)
        print(f"wrote {png}")
    return 0
