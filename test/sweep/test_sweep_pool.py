"""redmax_sweep's runs on the local pool: identical rows for any worker count, failures isolated.

The scene is the compound pendulum (scenes/pendulum.yaml) over 0.1 s, under a PD controller given as a file
(``ctl.py:pd``) so every run goes through the controller path; each run is short, the cost is the workers'
start-up (~3 s each).
"""
import json
import subprocess
import sys

import numpy as np

from redmax_ros.core import Simulator
from redmax_ros.sweep import spec as sp
from redmax_ros.sweep.cli import sweep
from redmax_ros.sweep.run import TIMING_COLUMNS
from redmax_ros.sweep.table import read_table

KP, KD = 20.0, 2.0
CONTROLLER = f'''
import os
from pathlib import Path
HERE = Path(__file__).parent

def pd(t, state):
    """PD torque driving the hinge to 0 [N m]."""
    return {{"joint_torques": {{"hinge": -{KP} * state.q[0] - {KD} * state.v[0]}}}}

def kill_at_q0(t, state):
    """Kill the worker at the start of the run released at q0 = 0.2 rad (every attempt); q0 = 0.3 rad: the
    first attempt only (a marker file remembers it)."""
    if t == 0.0 and state.q[0] == 0.2:
        os._exit(3)
    marker = HERE / "killed_once"
    if t == 0.0 and state.q[0] == 0.3 and not marker.exists():
        marker.write_text("x")
        os._exit(4)
    return pd(t, state)
'''


def _runs(tmp_path, fn="pd", grid=("joints.hinge.q0=0.1,0.2,0.3,0.4",), duration=0.1):
    ctl = tmp_path / "ctl.py"
    ctl.write_text(CONTROLLER)
    keys, pts = sp.expand(list(grid))
    return keys, sp.build_runs("pendulum", keys, pts, duration=duration, controller=f"{ctl}:{fn}", body="link")


def _comparable(path):
    cols, rows = read_table(path)
    keep = [c for c in cols if c not in TIMING_COLUMNS]
    return sorted(tuple(r[c] for c in keep) for r in rows), keep


def test_identical_rows_for_one_and_two_workers(tmp_path):
    keys, runs = _runs(tmp_path)
    rows1, _ = sweep(runs, keys, tmp_path / "w1", workers=1, progress=False)
    rows2, _ = sweep(runs, keys, tmp_path / "w2", workers=2, progress=False)
    a, cols = _comparable(tmp_path / "w1" / "runs.csv")
    b, _ = _comparable(tmp_path / "w2" / "runs.csv")
    assert a == b  # bitwise: floats are written with repr
    assert len({r["worker"] for r in rows2}) == 2 and len({r["worker"] for r in rows1}) == 1
    assert all(r["status"] == "ok" and r["attempts"] == 1 for r in rows2)
    # each row is the run itself: the final state equals stepping the Simulator under the same PD torque
    sim = Simulator.load("pendulum", ["joints.hinge.q0=0.3"])
    for _ in range(100):
        sim.set_joint_torques({"hinge": -KP * sim.state.q[0] - KD * sim.state.v[0]})
        sim.step()
    row = rows2[2]
    assert json.loads(row["q_final"]) == sim.state.q.tolist() and row["steps"] == 100
    # physics: the PD law is a spring KP (its energy KP q^2 / 2) and a damper KD: the total of the mechanical
    # and the spring energy drops; the link swings towards 0
    for r in rows2:
        q0, q1 = float(r["joints.hinge.q0"]), json.loads(r["q_final"])[0]
        assert r["E_total_end"] + KP * q1 ** 2 / 2 < r["E_total_start"] + KP * q0 ** 2 / 2
        assert abs(q1) < q0
        assert r["body_path"] >= np.hypot(r["body_dx"], r["body_dz"]) > 0 and r["body_dy"] == 0.0
        assert r["effort_max_abs"] is None  # nothing prescribed: no required torques


def test_diverging_run_records_its_step_error_and_the_sweep_goes_on(tmp_path):
    keys, pts = sp.expand(["gravity=[0,0,-9.81],[0,0,-1e200],[0,0,-1.62]"])
    runs = sp.build_runs("pendulum", keys, pts, duration=0.05)
    rows, _ = sweep(runs, keys, tmp_path, workers=2, progress=False)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    bad = rows[1]
    assert "diverged" in bad["reason"] and bad["fail_step"] == 1 and bad["fail_t"] == 0.0 and bad["steps"] == 0
    assert rows[0]["steps"] == rows[2]["steps"] == 50
    _, table = read_table(tmp_path / "runs.csv")
    assert sorted(r["status"] for r in table) == ["failed", "ok", "ok"]


def test_killed_worker_is_retried_once_then_recorded(tmp_path):
    keys, runs = _runs(tmp_path, "kill_at_q0")
    rows, _ = sweep(runs, keys, tmp_path / "out", workers=2, progress=False)
    by = {r["joints.hinge.q0"]: r for r in rows}
    assert by["0.2"]["status"] == "killed" and by["0.2"]["attempts"] == 2
    assert by["0.2"]["reason"] == "worker died on each of 2 attempts" and by["0.2"]["worker"] == "died: exit code 3"
    assert by["0.2"]["q_final"] is None
    assert by["0.3"]["status"] == "ok" and by["0.3"]["attempts"] == 2  # died once, then ran
    assert by["0.1"]["status"] == by["0.4"]["status"] == "ok"
    assert by["0.1"]["attempts"] == by["0.4"]["attempts"] == 1
    # the rerun is the same run: its row equals the one of a sweep where nothing died
    _, ref = _runs(tmp_path, "pd")
    ref_rows, _ = sweep(ref, keys, tmp_path / "ref", workers=1, progress=False)
    assert by["0.3"]["q_final"] == ref_rows[2]["q_final"]


def test_streamed_table_keeps_finished_rows_after_a_crash_and_resumes(tmp_path):
    """The sweep process itself dies (inline runs, --workers 0, a controller that calls os._exit in the
    third run): the table holds the two finished rows; --resume runs only the other two."""
    ctl = tmp_path / "ctl.py"
    ctl.write_text(CONTROLLER + '''
def crash_third(t, state):
    if state.q[0] == 0.3 and not (HERE / "crashed").exists():
        (HERE / "crashed").write_text("x")
        os._exit(9)
    return pd(t, state)
''')
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "redmax_ros.sweep.cli", "pendulum", "--grid", "joints.hinge.q0=0.1,0.2,0.3,0.4",
           "--duration", "0.05", "--controller", f"{ctl}:crash_third", "--out", str(out), "--workers", "0",
           "--quiet", "--no-chart"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p.returncode == 9, p.stderr
    _, rows = read_table(out / "runs.csv")
    assert [(r["run"], r["status"]) for r in rows] == [("0", "ok"), ("1", "ok")]
    first = (out / "runs.csv").read_text()
    p = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    text = (out / "runs.csv").read_text()
    assert text.startswith(first)  # the finished rows were kept as they were
    _, rows = read_table(out / "runs.csv")
    assert [(r["run"], r["status"]) for r in rows] == [("0", "ok"), ("1", "ok"), ("2", "ok"), ("3", "ok")]
    assert (out / "runs.parquet").exists() and "4 runs: 4 ok" in p.stdout
