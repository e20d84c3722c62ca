"""redmax_bench sweep: what the sweep runner's parallelism buys (issue 19).

    redmax_bench sweep [--runs-duration T] [--no-ray] [--out DIR]

1. Speed-up: the same 40-run sweep (klann, crank rate 8 values x joint friction 5 values, T s each, distance
   of the chassis measured) on 1 and on 2 local workers, --repeats times each, interleaved (1, 2, 1, 2, ...);
   wall time of the whole sweep (worker start-up included), best and median, and the speed-up
   T(1) / T(2) of the best (the least disturbed by the other users of the machine) and of the medians; the
   rows must be identical (checked).
2. Ray per-task overhead: a local Ray with 2 CPUs (started first; its start-up time reported apart); the same
   40-run sweep on it, interleaved with the local ones (1, 2, Ray, 1, 2, Ray, ...; rows checked against
   the local ones), and 1000 no-op tasks on Ray and on the 2-worker local pool: wall time per task from the
   (n/4)-th to the last result (worker start-up left out). Overhead per run = (T(Ray) - T(local, 2
   workers)) / 40, of the best and of the medians. Ray's idle daemons run beside the local sweeps.

Results: sweep.json and sweep.png in --out (default bench/results). The machine's load average is recorded
with every figure (the 2 cores are shared).
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from redmax_bench.common import add_out_argument, results_dir, write_json
from redmax_ros.sweep import spec as sp
from redmax_ros.sweep.pool import run_tasks
from redmax_ros.sweep.run import TIMING_COLUMNS, run_one

GRID = ["prescribed.joints.crank_fwd=lin:-2:-9:8", "friction.joint_mu=0,0.2,0.4,0.6,0.8"]


def noop(x):
    """A task that does nothing (returns its argument): the runner's own cost per task."""
    return x


def build(duration):
    """The 40 RunSpecs of the benchmark sweep."""
    keys, pts = sp.expand(GRID)
    return keys, sp.build_runs("klann", keys, pts, duration=duration, body="chassis")


def timed_sweep(runs, **kw):
    """(rows in run order, wall time [s]) of the runs on run_tasks(**kw)."""
    t0 = time.perf_counter()
    rows = [None] * len(runs)
    for i, row, _ in run_tasks(run_one, runs, progress=True, desc=kw.get("ray_address") or f"{kw.get('workers')} workers",
                               **kw):
        rows[i] = row
    return rows, time.perf_counter() - t0


def same_rows(a, b) -> bool:
    """Rows equal in every column but the timing ones."""
    strip = [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in a]
    return strip == [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in b]


def per_task(n, **kw) -> float:
    """Wall time per no-op task [s] in the steady state: the time from the (n/4)-th to the last of n results
    over the tasks in between, so that the workers' start-up is left out."""
    stamps = [time.perf_counter() for _ in run_tasks(noop, range(n), **kw)]
    k = n // 4
    return (stamps[-1] - stamps[k]) / (n - 1 - k)


def chart(res, out) -> Path | None:
    try:
        import matplotlib  # optional: matplotlib
    except ImportError:
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # optional: matplotlib
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.6))
    names = ["1 worker", "2 workers"] + (["Ray, 2 CPUs"] if "ray" in res else [])
    walls = [res["local"]["1"]["wall_s"], res["local"]["2"]["wall_s"]] + ([res["ray"]["sweep_wall_s"]] if "ray" in res else [])
    a1.bar(names, walls, color=["tab:gray", "tab:blue", "tab:orange"][:len(names)])
    for i, w in enumerate(walls):
        a1.text(i, w, f"{w:.1f} s", ha="center", va="bottom", fontsize=8)
    a1.set_ylabel("wall time of the 40-run sweep [s]")
    a1.set_title(f"klann, 40 runs x {res['duration']:g} s, best of {res['repeats']}: speed-up "
                 f"{res['speedup_2_over_1']:.2f}x", fontsize=9)
    if "ray" in res:
        vals = [res["local_noop_per_task_ms"], res["ray"]["noop_per_task_ms"]]
        a2.bar(["local pool, 2 workers", "Ray, 2 CPUs"], vals, color=["tab:blue", "tab:orange"])
        for i, v in enumerate(vals):
            a2.text(i, v, f"{v:.3f} ms", ha="center", va="bottom", fontsize=8)
        a2.set_ylabel("wall time per no-op task [ms]")
        a2.set_title(f"runner overhead per task; Ray start-up {res['ray']['init_s']:.1f} s;\n40-run sweep on Ray - local: "
                     f"{res['ray']['overhead_per_run_ms']:+.0f} ms per run", fontsize=9)
    fig.suptitle(f"load average at start {res['loadavg_start'][0]:.2f}, end {res['loadavg_end'][0]:.2f} (2 shared cores)",
                 fontsize=8)
    fig.tight_layout()
    path = results_dir(out) / "sweep.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench sweep", description=__doc__.splitlines()[0])
    ap.add_argument("--runs-duration", type=float, default=1.0, help="simulated time per run [s] (default 1)")
    ap.add_argument("--no-ray", action="store_true", help="skip the Ray part")
    ap.add_argument("--noop-tasks", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3, help="sweeps per worker count, interleaved; best and median kept")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    keys, runs = build(a.runs_duration)
    res = {"scene": "klann", "grid": GRID, "runs": len(runs), "duration": a.runs_duration,
           "loadavg_start": list(os.getloadavg()), "repeats": a.repeats}
    run_one(runs[0])  # the kernels in the on-disk cache before any timing
    ray = None
    if not a.no_ray:
        import ray  # optional: pip install .[cluster]
        t0 = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        res["ray"] = {"init_s": time.perf_counter() - t0}
    configs = [("1", {"workers": 1}), ("2", {"workers": 2})] + ([("ray", {"ray_address": "auto"})] if ray else [])
    rows, walls = {}, {k: [] for k, _ in configs}
    tries = {k: [] for k, _ in configs}
    try:
        for rep in range(a.repeats):  # 1, 2, Ray, 1, 2, Ray, ...: all see the same changes of the other users' load
            for name, kw in configs:
                r, wall = timed_sweep(runs, **kw)
                rows.setdefault(name, r)
                if not same_rows(r, rows[name]):
                    raise RuntimeError(f"the rows of repeat {rep} on {name} differ from the first repeat's")
                cpu = sum(x["cpu_s"] for x in r)
                walls[name].append(wall)
                tries[name].append({"wall_s": wall, "cpu_s_runs": cpu, "loadavg": list(os.getloadavg()),
                                    "status": sorted({x["status"] for x in r})})
                print(f"{name:>3s} {'worker(s)' if name != 'ray' else '(2 CPUs)'}: 40 runs in {wall:.2f} s wall "
                      f"(CPU of the runs {cpu:.2f} s), load {os.getloadavg()[0]:.2f}")
        if ray:
            res["ray"]["noop_per_task_ms"] = per_task(a.noop_tasks, ray_address="auto") * 1e3
    finally:
        if ray:
            ray.shutdown()
    res["local_noop_per_task_ms"] = per_task(a.noop_tasks, workers=2) * 1e3
    best = {k: min(v) for k, v in walls.items()}
    med = {k: sorted(v)[len(v) // 2] for k, v in walls.items()}
    res["local"] = {k: {"wall_s": best[k], "wall_s_median": med[k], "tries": tries[k]} for k in ("1", "2")}
    res["rows_identical_1_vs_2"] = same_rows(rows["1"], rows["2"])
    res["speedup_2_over_1"] = best["1"] / best["2"]
    res["speedup_2_over_1_median"] = med["1"] / med["2"]
    res["speedups_per_repeat"] = [t1 / t2 for t1, t2 in zip(walls["1"], walls["2"])]
    print(f"speed-up 2 workers over 1: {res['speedup_2_over_1']:.2f}x best-of-{a.repeats} "
          f"({res['speedup_2_over_1_median']:.2f}x median; per repeat "
          + ", ".join(f"{x:.2f}" for x in res["speedups_per_repeat"]) + f"); rows identical: {res['rows_identical_1_vs_2']}")
    print(f"local pool, 2 workers: {res['local_noop_per_task_ms']:.3f} ms per no-op task")
    if ray:
        over = (best["ray"] - best["2"]) / len(runs) * 1e3
        res["ray"].update(sweep_wall_s=best["ray"], sweep_wall_s_median=med["ray"], tries=tries["ray"],
                          overhead_per_run_ms=over, overhead_per_run_ms_median=(med["ray"] - med["2"]) / len(runs) * 1e3,
                          rows_identical_to_local=same_rows(rows["ray"], rows["2"]))
        print(f"Ray (local, 2 CPUs; start-up {res['ray']['init_s']:.1f} s): {res['ray']['noop_per_task_ms']:.3f} ms per "
              f"no-op task; 40-run sweep {best['ray']:.2f} s best -> {over:+.1f} ms per run over the local pool "
              f"({res['ray']['overhead_per_run_ms_median']:+.1f} ms median); rows identical: "
              f"{res['ray']['rows_identical_to_local']}")
    res["loadavg_end"] = list(os.getloadavg())
    print("wrote", write_json(a.out, "sweep", res))
    png = chart(res, a.out)
    if png:
        print("wrote", png)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
