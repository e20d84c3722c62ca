"""redmax_sweep: run a scene over a grid (or random samples) of overrides, in parallel, and tabulate metrics.

    redmax_sweep SCENE [--set KEY=VALUE ...] [--grid KEY=V1,V2,... ...] [--random KEY=DIST:A:B --samples N --seed S]
                 [--duration T] [--controller MODULE:FUNCTION] [--body NAME] [--workers N | --ray auto|ADDRESS]
                 [--out DIR] [--metric COLUMN] [--per-run-csv] [--resume]

Writes into --out (default runs/sweep_<scene>): runs.csv (one row per run, appended and flushed as each run
finishes), runs.parquet (the same table sorted by run, at the end), summary.json, and <metric>.png (the metric
against the first swept key). Rows: redmax_ros/sweep/run.py; grid and random syntax: redmax_ros/sweep/spec.py;
local pool and Ray: redmax_ros/sweep/pool.py; docs/sweeps.md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from redmax_ros import runner
from redmax_ros.core import SOLVERS, CommandError, SceneError
from redmax_ros.sweep import chart as chart_mod
from redmax_ros.sweep import spec as sp
from redmax_ros.sweep.pool import TaskFailure, run_tasks
from redmax_ros.sweep.run import columns, empty_row, run_one
from redmax_ros.sweep.table import TableWriter, read_table, write_parquet

SUMMARY_METRICS = ("body_vx", "body_path", "effort_mean", "effort_max_abs", "E_drift", "violation_max", "wall_s", "cpu_s")


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="redmax_sweep", description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="scene name (scenes/) or path to a scene YAML")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override for every run (as redmax_run)")
    ap.add_argument("--grid", action="append", default=[], metavar="KEY=VALUES",
                    help="swept key: V1,V2,... (YAML values), lin:A:B:N or log:A:B:N; several --grid: cartesian product")
    ap.add_argument("--random", action="append", default=[], metavar="KEY=DIST",
                    help="randomly sampled key: uniform:A:B, normal:MU:SIGMA or loguniform:A:B")
    ap.add_argument("--samples", type=int, default=0, help="number of random samples (with --random)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random samples (numpy default_rng)")
    ap.add_argument("--duration", type=float, help="simulated time per run [s] (default: the scene's)")
    ap.add_argument("--dt", type=float, help="time step h [s] (default: the scene's)")
    ap.add_argument("--solver", choices=list(SOLVERS), default=None)
    ap.add_argument("--step-budget-ms", type=float, default=None, metavar="MS", help="as redmax_run")
    ap.add_argument("--controller", default=None, metavar="MODULE:FUNCTION",
                    help="callable (t [s], State) -> commands called before every step (as redmax_run)")
    ap.add_argument("--body", default=None, help="body whose distance travelled is measured (body_* columns)")
    ap.add_argument("--workers", type=int, default=None,
                    help="local worker processes (default: this machine's CPUs; 0: in this process)")
    ap.add_argument("--ray", default=None, metavar="auto|ADDRESS|local",
                    help="run on Ray: 'auto' (the running cluster), an address, or 'local' (start one here)")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: runs/sweep_<scene>)")
    ap.add_argument("--metric", default=None, help="column summarised and charted (default: body_vx with --body, "
                                                   "else E_drift)")
    ap.add_argument("--x", default=None, help="swept key on the chart's x axis (default: the first)")
    ap.add_argument("--label", action="append", default=[], metavar="COLUMN=TEXT",
                    help="axis / legend label of a swept key or metric on the chart")
    ap.add_argument("--per-run-csv", action="store_true", help="also write each run's trajectory (out/per_run/)")
    ap.add_argument("--resume", action="store_true", help="keep the finished rows of out/runs.csv, run the others")
    ap.add_argument("--no-parquet", action="store_true")
    ap.add_argument("--no-chart", action="store_true")
    ap.add_argument("--quiet", action="store_true", help="no progress bar, no table of runs")
    return ap.parse_args(argv)


def sweep(runs, keys, out: Path, workers=None, ray_address=None, resume=False, progress=True, parquet=True,
          info=None):
    """Run ``runs`` (RunSpecs) and stream their rows into ``out``/runs.csv as they finish; returns (rows sorted
    by run, wall time of the sweep [s]). ``resume``: rows already in runs.csv (same run index and
    parameters) are kept and those runs skipped. ``info`` (a dict, optional) receives 'kept' and 'ran'."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cols = columns(keys)
    table = out / "runs.csv"
    done = {}
    if resume and table.exists():
        _, old = read_table(table)
        by_index = {r.index: r for r in runs}
        for r in old:
            i = int(r["run"])
            if i in by_index and all(r.get(k) == v for k, v in by_index[i].params):
                done[i] = r
    todo = [r for r in runs if r.index not in done]
    rows = list(done.values())
    if info is not None:
        info.update(kept=len(done), ran=len(todo))
    t0 = time.perf_counter()
    with TableWriter(table, cols, append=bool(done)) as tw:
        for i, res, attempts in run_tasks(run_one, todo, workers=workers, ray_address=ray_address,
                                          progress=progress, desc="runs"):
            if isinstance(res, TaskFailure):
                row = empty_row(todo[i])
                if res.killed:  # how it died goes to the worker column (it differs between backends)
                    row.update(status="killed", reason=res.reason, worker=f"died: {res.detail}")
                else:
                    row.update(status="error", reason=res.reason.strip().splitlines()[-1])
            else:
                row = res
            row["attempts"] = attempts
            tw.write(row)
            rows.append(row)
    wall = time.perf_counter() - t0
    if parquet:
        typed = [_typed(r, cols) for r in rows]
        write_parquet(out / "runs.parquet", cols, typed)
    return sorted(rows, key=lambda r: int(r["run"])), wall


def _typed(row, cols):
    """A row read back from the CSV (text) with numbers as numbers, for the Parquet file."""
    out = {}
    for c in cols:
        v = row.get(c)
        if isinstance(v, str):
            if v == "":
                v = None
            elif c in ("run", "steps", "fail_step", "attempts"):
                v = int(v)
            elif c not in ("status", "reason", "body", "worker", "q_final", "v_final", "effort_stats"):
                try:
                    v = float(v)
                except ValueError:
                    pass
        out[c] = int(v) if c == "run" else v
    return out


def summarize(rows, keys, metric, wall) -> dict:
    """Counts by status, the CPU time of the runs and the wall time of this invocation [s], and min/mean/max
    over the ok runs of the summary metrics."""
    by = {}
    for r in rows:
        by[r["status"]] = by.get(r["status"], 0) + 1
    ok = [r for r in rows if r["status"] == "ok"]
    stats = {}
    for m in dict.fromkeys((metric,) + SUMMARY_METRICS):
        vals = [float(r[m]) for r in ok if r.get(m) not in (None, "")]
        if vals:
            stats[m] = {"min": min(vals), "mean": sum(vals) / len(vals), "max": max(vals)}
    cpu = sum(float(r["cpu_s"]) for r in rows if r.get("cpu_s") not in (None, ""))
    return {"runs": len(rows), "status": by, "keys": list(keys), "metric": metric, "wall_s": wall,
            "cpu_s_total": cpu, "metrics": stats, "loadavg": list(os.getloadavg())}


def print_summary(summ, rows, keys, metric, quiet):
    print(f"{summ['runs']} runs: " + ", ".join(f"{n} {s}" for s, n in sorted(summ["status"].items()))
          + f"; wall time {summ['wall_s']:.2f} s, CPU time of the runs {summ['cpu_s_total']:.2f} s, "
          + f"load average {summ['loadavg'][0]:.2f}")
    for m, s in summ["metrics"].items():
        print(f"  {m:16s} min {s['min']:.6g}  mean {s['mean']:.6g}  max {s['max']:.6g}")
    if quiet or len(rows) > 60:
        return
    w = [max(len(k), 8) for k in keys]
    print("  " + "  ".join(f"{k:>{n}s}" for k, n in zip(keys, w)) + f"  {'status':>7s}  {metric}")
    for r in rows:
        val = r.get(metric)
        txt = f"{float(val):.6g}" if val not in (None, "") else (r.get("reason") or "")[:70]
        print("  " + "  ".join(f"{str(r[k]):>{n}s}" for k, n in zip(keys, w)) + f"  {r['status']:>7s}  {txt}")


def main(argv=None) -> int:
    a = parse_args(argv)
    try:
        keys, points = sp.expand(a.grid, a.random, a.samples, a.seed)
    except ValueError as e:
        print(f"redmax_sweep: {e}", file=sys.stderr)
        return 2
    if a.ray and a.workers == 0:
        print("redmax_sweep: --ray and --workers 0 exclude each other", file=sys.stderr)
        return 2
    out = a.out or Path("runs") / f"sweep_{Path(a.scene).stem}"
    base = runner.scene_overrides(a.set, a.dt, a.solver)
    runs = sp.build_runs(a.scene, keys, points, base, duration=a.duration, controller=a.controller, body=a.body,
                         step_budget_ms=a.step_budget_ms, csv_dir=str(out / "per_run") if a.per_run_csv else None)
    try:  # the first run's scene, controller and body, checked here once rather than failing in every run
        sim = runner.load_simulator(a.scene, runs[0].overrides, a.step_budget_ms)
        runner.step_count(sim, a.duration)
        if a.controller:
            runner.load_controller(a.controller)
        if a.body and a.body not in sim.describe().bodies:
            raise ValueError(f"unknown body '{a.body}' (known: {', '.join(sim.describe().bodies)})")
    except (SceneError, CommandError, ValueError) as e:
        print(f"redmax_sweep: {e}", file=sys.stderr)
        return 2
    metric = a.metric or ("body_vx" if a.body else "E_drift")
    where = f"Ray ({a.ray})" if a.ray else (f"{a.workers} local workers" if a.workers is not None else "local workers")
    print(f"redmax_sweep: {len(runs)} runs of {a.scene} over {', '.join(keys) or 'no key'} on {where}; table {out / 'runs.csv'}")
    info = {}
    try:
        rows, wall = sweep(runs, keys, out, a.workers, a.ray, a.resume, progress=not a.quiet,
                           parquet=not a.no_parquet, info=info)
    except KeyboardInterrupt:
        print(f"redmax_sweep: interrupted; the finished rows are in {out / 'runs.csv'} (--resume runs the rest)",
              file=sys.stderr)
        return 130
    summ = summarize(rows, keys, metric, wall)
    summ.update(runs_kept=info["kept"], runs_ran=info["ran"], workers=a.workers, ray=a.ray)
    if info["kept"]:
        print(f"  {info['kept']} rows kept from {out / 'runs.csv'}, {info['ran']} runs ran now")
    (out / "summary.json").write_text(json.dumps(summ, indent=2))
    print_summary(summ, rows, keys, metric, a.quiet)
    if not a.no_chart and keys:
        labels = dict(t.split("=", 1) for t in a.label if "=" in t)
        png = chart_mod.chart(out / f"{metric}.png", rows, keys, metric, a.x, title=f"{a.scene}: {metric}",
                              labels=labels)
        if png:
            print(f"  wrote {png}")
    print(f"  wrote {out / 'runs.csv'}" + ("" if a.no_parquet else f", {out / 'runs.parquet'}") + f", {out / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
