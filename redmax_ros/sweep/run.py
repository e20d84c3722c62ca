"""One run of a sweep -> one row of metrics (a dict), computed in the worker that ran it.

The run is redmax_ros.runner's loop (``load_simulator``, ``run``, the same rows as redmax_run's CSV). Every
exception is caught and recorded in the row, so a diverging run never stops a sweep:

* ``status`` ok | failed (StepError: ``reason``, the failing step ``fail_step`` (1-based) and its start time
  ``fail_t`` [s]) | error (scene, command or controller error: ``reason``); the pool adds ``killed`` (the
  worker process died on both attempts) and the ``attempts`` column;
* ``steps``, ``t_end`` [s]: steps completed and the simulated time reached;
* energies [J]: ``E_kin_end``, ``E_pot_end``, ``E_spring_end``, ``E_total_start``, ``E_total_end``,
  ``E_total_max``, ``E_drift`` (end - start);
* ``violation_max`` [m]: largest loop-closure residual over the run;
* required forces of the prescribed joints/sites/bodies (tau:, f:, w: columns of redmax_run's CSV [N m, N]),
  pooled over those columns and the steps: ``effort_mean``, ``effort_mean_abs``, ``effort_rms``,
  ``effort_max_abs``; per column in ``effort_stats`` (JSON {column: {mean, mean_abs, rms, max_abs}});
* ``body`` and the distance its origin travelled [m]: ``body_dx``, ``body_dy``, ``body_dz`` (final - initial,
  world), ``body_path`` (sum of the per-step displacements), ``body_vx`` (body_dx / t_end [m/s], the mean
  forward speed of a walker) and ``body_speed`` (|final - initial| / t_end [m/s]);
* final state: ``q_final``, ``v_final`` (JSON lists, exact float64);
* timing: ``wall_s``, ``cpu_s`` (this run's wall and process CPU time, loading included [s]), ``steps_per_s``
  (steps per wall second of the stepping loop) and ``worker`` (host:pid; for a killed run, how the worker
  died); these and ``attempts`` are the only columns that may differ between two runs of the same sweep
  (TIMING_COLUMNS), the step budget aside (CPU time: docs/sweeps.md).
"""
from __future__ import annotations

import json
import os
import socket
import time

import numpy as np

from redmax_ros import runner
from redmax_ros.core import CommandError, SceneError
from redmax_ros.sweep.spec import RunSpec

METRIC_COLUMNS = ["status", "reason", "fail_step", "fail_t", "attempts", "steps", "t_end",
                  "E_kin_end", "E_pot_end", "E_spring_end", "E_total_start", "E_total_end", "E_total_max", "E_drift",
                  "violation_max", "effort_mean", "effort_mean_abs", "effort_rms", "effort_max_abs",
                  "body", "body_dx", "body_dy", "body_dz", "body_path", "body_vx", "body_speed",
                  "q_final", "v_final", "effort_stats"]
TIMING_COLUMNS = ["wall_s", "cpu_s", "steps_per_s", "worker", "attempts"]


def columns(param_keys) -> list:
    """The table's columns for a sweep over ``param_keys``: run, the keys, the metrics, the timings."""
    return ["run", *param_keys, *METRIC_COLUMNS, *[c for c in TIMING_COLUMNS if c != "attempts"]]


def empty_row(spec: RunSpec) -> dict:
    """A row with the run's index and parameters and every metric None."""
    row = {"run": spec.index, **dict(spec.params)}
    row.update({c: None for c in METRIC_COLUMNS + TIMING_COLUMNS})
    row["body"] = spec.body
    return row


class _BodyTrack:
    """Origin of one body after every step (world [m]): displacement and path length."""

    def __init__(self, sim, body):
        self.body = body
        self.p0 = self.last = np.array(sim.body_poses()[body][0], float)
        self.path = 0.0

    def __call__(self, sim, res):
        p = np.array(sim.body_poses()[self.body][0], float)
        self.path += float(np.linalg.norm(p - self.last))
        self.last = p


def _effort_stats(header, rows) -> tuple:
    cols = [i for i, h in enumerate(header) if h.startswith(("tau:", "f:", "w:"))]
    if not cols or len(rows) < 2:
        return None, {}
    E = rows[1:, cols]
    stats = {header[i]: {"mean": float(np.mean(E[:, j])), "mean_abs": float(np.mean(np.abs(E[:, j]))),
                         "rms": float(np.sqrt(np.mean(E[:, j] ** 2))), "max_abs": float(np.max(np.abs(E[:, j])))}
             for j, i in enumerate(cols)}
    pooled = (float(np.mean(E)), float(np.mean(np.abs(E))), float(np.sqrt(np.mean(E ** 2))), float(np.max(np.abs(E))))
    return pooled, stats


def metrics(row: dict, sim, header, rows, track) -> None:
    """Fill ``row`` with the metrics of a finished (or stopped) run from its trajectory ``rows``."""
    col = {h: i for i, h in enumerate(header)}
    last = rows[-1]
    row["steps"] = len(rows) - 1
    row["t_end"] = float(last[0])
    for k in ("E_kin", "E_pot", "E_spring", "E_total"):
        row[f"{k}_end"] = float(last[col[k]])
    E = rows[:, col["E_total"]]
    row["E_total_start"] = float(E[0])
    row["E_total_max"] = float(np.max(E))
    row["E_drift"] = float(E[-1] - E[0])
    row["violation_max"] = float(np.nanmax(rows[:, col["violation"]]))
    pooled, stats = _effort_stats(header, rows)
    if pooled is not None:
        row["effort_mean"], row["effort_mean_abs"], row["effort_rms"], row["effort_max_abs"] = pooled
    row["effort_stats"] = json.dumps(stats, sort_keys=True)
    row["q_final"] = json.dumps([float(x) for x in sim.state.q])
    row["v_final"] = json.dumps([float(x) for x in sim.joint_velocities()])
    if track is not None:
        d = track.last - track.p0
        row["body_dx"], row["body_dy"], row["body_dz"] = (float(x) for x in d)
        row["body_path"] = track.path
        t = row["t_end"]
        row["body_vx"] = float(d[0] / t) if t > 0 else None
        row["body_speed"] = float(np.linalg.norm(d) / t) if t > 0 else None


def run_one(spec: RunSpec) -> dict:
    """Run ``spec`` (load, step for its duration under its controller) and return its metrics row; never raises
    for a problem of the run itself (see the module docstring)."""
    row = empty_row(spec)
    t0, c0 = time.perf_counter(), time.process_time()
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    sim = track = None
    try:
        sim = runner.load_simulator(spec.scene, spec.overrides, spec.step_budget_ms)
        n = runner.step_count(sim, spec.duration)
        controller = runner.load_controller(spec.controller) if spec.controller else None
        if spec.body is not None:
            if spec.body not in sim.describe().bodies:
                raise ValueError(f"unknown body '{spec.body}' (known: {', '.join(sim.describe().bodies)})")
            track = _BodyTrack(sim, spec.body)
    except (SceneError, CommandError, ValueError) as e:
        row.update(status="error", reason=f"{type(e).__name__}: {e}")
        return _timed(row, t0, c0)
    try:
        header, rows, err, wall = runner.run(sim, n, quiet=True, controller=controller, on_step=track)
    except Exception as e:  # noqa: BLE001 - the controller's own errors end this run only
        row.update(status="error", reason=f"controller: {type(e).__name__}: {e}", fail_t=float(sim.time),
                   fail_step=int(round(sim.time / sim.dt)) + 1)
        return _timed(row, t0, c0)
    metrics(row, sim, header, rows, track)
    if err is not None:
        row.update(status="failed", reason=err.reason, fail_step=row["steps"] + 1, fail_t=row["t_end"])
    else:
        row["status"] = "ok"
    row["steps_per_s"] = row["steps"] / wall if wall > 0 else None
    if spec.csv_path:
        runner.write_csv(spec.csv_path, header, rows)
    return _timed(row, t0, c0)


def _timed(row, t0, c0):
    row["wall_s"] = time.perf_counter() - t0
    row["cpu_s"] = time.process_time() - c0
    return row
