"""redmax_bench budget: bounded work per step (issue 17): how long an abusive input takes to fail, how far
the failing step runs past its budget, and what the budget's checks cost on normal steps.

    redmax_bench budget [--repeats R] [--steps N] [--out DIR]

Abusive cases (each the command a user or a node client can send, then stepping as free-run does): the
1e12 cases of issue 17 (hand elbow velocity 1e12 rad/s, wrist effort 1e12 N m followed by 100 steps, the
walker's crank at 1e12 rad/s), a 1e12 N m knee torque and a 1e12 N site force, the same commands at 1e6
(solved, then judged by their result), and the cases that really run into the budget: the 1e12 elbow
with the up-front tests switched off (the joint-limit QP of Eq. 5 against the default budget, and
against 1 ms), the walker driven at 1e5 rad/s (its compiled Staggered Projections loop at its caps)
against 10 ms and 1 ms, and the first PCG step of the 529-DOF umbrella against 1 ms. For each: the
budget [ms CPU], the wall and thread CPU time [ms] of the failing step (the call that raised; median and
max of --repeats runs after an untimed warm-up run), the overshoot (that time minus the budget: negative
when the step failed before the budget was used up) and the StepError's text. The budget's clock counts
the CPU time of the iterative solvers only (solvers/budget.py); the step's whole CPU time is reported,
so the overshoot includes the fixed stages (kinematics, assembly, factorisations) before them.

Check cost: steps/s of normal stepping (hand, the hand at a joint limit with joint-limit QP steps, the
walker) with the default budget, with budget=None, and with budget=None and the up-front divergence tests
(step/state.py: check_rows, check_applied) switched off, side by side (interleaved, best of --repeats,
thread CPU time). Writes budget.json into --out (default bench/results under the current directory).
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import time

from redmax_ros.core import Simulator, StepBudget, StepError
from redmax_ros.core.step import data_free_stages, pipeline
from redmax_bench.common import add_out_argument, write_json

DEFAULT = StepBudget()  # the Simulator's default: 50 ms CPU of the iterative solvers, QP caps 1000 / 50


@contextlib.contextmanager
def up_front_tests_off():
    """The up-front divergence tests (step/state.py check_rows, check_applied) switched off in both
    pipelines, so that an input reaches the solvers and only the budget stops it (the backstop)."""
    saved = [(m, n, getattr(m, n)) for m in (pipeline, data_free_stages) for n in ("check_rows", "check_applied")]
    for m, n, _ in saved:
        setattr(m, n, lambda *a, **k: None)
    try:
        yield
    finally:
        for m, n, f in saved:
            setattr(m, n, f)


def _settle(sim):
    """Three normal steps first (the commands then hit a moving mechanism, as in free-run)."""
    sim.step(3)


# (name, command, scene, overrides, solver, budget, prepare(sim), command(sim), steps: max steps until the
#  error, per_call: steps per sim.step call, up-front tests on)
CASES = [
    ("hand elbow 1e12 rad/s", "prescribe_joints({'elbow': 1e12})", "hand", (), None, DEFAULT, _settle,
     lambda s: s.prescribe_joints({"elbow": 1e12}), 1, 1, True),
    ("hand wrist 1e12 N m x100", "set_joint_torques({'wrist': [1e12, 0]}); step(100)", "hand", (), None, DEFAULT,
     _settle, lambda s: s.set_joint_torques({"wrist": [1e12, 0.0]}), 1, 100, True),
    ("hand index_tip 1e12 N", "set_site_forces({'index_tip': [0, 0, 1e12]})", "hand", (), None, DEFAULT, _settle,
     lambda s: s.set_site_forces({"index_tip": [0.0, 0.0, 1e12]}), 1, 1, True),
    ("klann crank 1e12 rad/s", "prescribe_joints({'crank_fwd': 1e12})", "klann", (), None, DEFAULT, _settle,
     lambda s: s.prescribe_joints({"crank_fwd": 1e12}), 1, 1, True),
    ("klann knee 1e12 N m", "set_joint_torques({'knee_f2': 1e12})", "klann", (), None, DEFAULT, _settle,
     lambda s: s.set_joint_torques({"knee_f2": 1e12}), 1, 1, True),
    ("hand elbow 1e6 rad/s", "prescribe_joints({'elbow': 1e6})", "hand", (), None, DEFAULT, _settle,
     lambda s: s.prescribe_joints({"elbow": 1e6}), 100, 1, True),
    ("hand wrist 1e6 N m", "set_joint_torques({'wrist': [1e6, 0]})", "hand", (), None, DEFAULT, _settle,
     lambda s: s.set_joint_torques({"wrist": [1e6, 0.0]}), 100, 1, True),
    ("klann crank 1e6 rad/s", "prescribe_joints({'crank_fwd': 1e6})", "klann", (), None, DEFAULT, _settle,
     lambda s: s.prescribe_joints({"crank_fwd": 1e6}), 100, 1, True),
    ("hand elbow 1e12, no up-front", "elbow 1e12 with check_rows/check_applied off", "hand", (), None, DEFAULT,
     _settle, lambda s: s.prescribe_joints({"elbow": 1e12}), 1, 1, False),
    ("hand elbow 1e12, no up-front", "elbow 1e12 with check_rows/check_applied off", "hand", (), None,
     StepBudget.from_ms(1), _settle, lambda s: s.prescribe_joints({"elbow": 1e12}), 1, 1, False),
    ("hand wrist 1e12, no up-front", "wrist 1e12 N m with check_rows/check_applied off", "hand", (), None, DEFAULT,
     _settle, lambda s: s.set_joint_torques({"wrist": [1e12, 0.0]}), 100, 1, False),
    ("klann crank 1e5 rad/s", "prescribe_joints({'crank_fwd': 1e5}) (staggered loop at its caps)", "klann", (),
     None, StepBudget.from_ms(10), _settle, lambda s: s.prescribe_joints({"crank_fwd": 1e5}), 100, 1, True),
    ("klann crank 1e5 rad/s", "prescribe_joints({'crank_fwd': 1e5}) (staggered loop at its caps)", "klann", (),
     None, StepBudget.from_ms(1), _settle, lambda s: s.prescribe_joints({"crank_fwd": 1e5}), 100, 1, True),
    ("umbrella-529 PCG, first step", "step() (134 PCG iterations)", "umbrella",
     ("params.ribs=22", "params.stretchers=11"), "pcg", StepBudget.from_ms(1), lambda s: None, lambda s: None,
     1, 1, True),
]


def _kind(msg: str) -> str:
    if "rejected before solving" in msg:
        return "rejected up front"
    if "step budget exceeded" in msg:
        return "budget"
    if "diverged" in msg:
        return "diverged"
    return "other" if msg else "none"


def run_case(case, repeats: int) -> dict:
    """One abusive case: an untimed warm-up run, then ``repeats`` timed runs of the failing step."""
    name, command, scene, overrides, solver, budget, prepare, cmd, steps, per_call, up_front = case
    runs = []
    for r in range(repeats + 1):
        sim = Simulator.load(scene, list(overrides), solver=solver, budget=budget)
        prepare(sim)
        cmd(sim)
        msg, wall, cpu, done = "", 0.0, 0.0, 0
        with contextlib.ExitStack() as stack:
            if not up_front:
                stack.enter_context(up_front_tests_off())
            for _ in range(steps):
                before = sim.state
                t0, c0 = time.perf_counter(), time.thread_time()
                try:
                    sim.step(per_call)
                except StepError as e:
                    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
                    msg = str(e)
                    assert sim.state is before, "a failed step changed the state"
                    break
                wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
                done += per_call
        if r:  # r = 0: warm-up (numba's kernels loaded or compiled, caches filled)
            runs.append({"wall_ms": wall * 1e3, "cpu_ms": cpu * 1e3, "steps_before": done, "error": msg})
    b = budget.cpu_time * 1e3 if budget is not None and budget.cpu_time else None
    wall = [x["wall_ms"] for x in runs]
    cpu = [x["cpu_ms"] for x in runs]
    msg = runs[-1]["error"]
    out = {"case": name, "command": command, "scene": scene, "overrides": list(overrides), "solver": solver,
           "up_front_tests": up_front, "budget_ms": b,
           "qp_max_iter": None if budget is None else budget.qp_max_iter,
           "wall_ms_median": statistics.median(wall), "wall_ms_max": max(wall),
           "cpu_ms_median": statistics.median(cpu), "cpu_ms_max": max(cpu),
           "steps_before": runs[-1]["steps_before"], "kind": _kind(msg), "error": msg, "runs": runs}
    if b is not None:
        out["overshoot_wall_ms_max"] = max(wall) - b
        out["overshoot_cpu_ms_max"] = max(cpu) - b
    return out


NORMAL = [  # (name, scene, prepare(sim) after loading)
    ("hand", "hand", lambda s: None),
    ("hand at a joint limit (QP steps)", "hand", lambda s: s.set_joint_torques({"index_pip": 1.0})),
    ("klann walker", "klann", lambda s: None),
]
VARIANTS = [("default budget", DEFAULT, True), ("budget=None", None, True), ("None, no up-front", None, False)]


def check_cost(steps: int, repeats: int) -> list:
    """Per-step thread CPU time of normal stepping, one simulator per variant stepped in lockstep (the same
    trajectory: the budget changes no result; the order rotated every step), each step timed alone. Per variant: steps/s (1 / mean) and
    the median step; the costs are medians of the paired per-step differences (robust to preemption and
    to the state-dependent cost of the steps). ``repeats`` passes of ``steps`` steps from the initial state
    after a warm-up pass."""
    rows = []
    for name, scene, prepare in NORMAL:
        n = steps if scene == "hand" else max(1, steps // 3)
        sims = [Simulator.load(scene, budget=budget) for _, budget, _ in VARIANTS]
        times = [[] for _ in VARIANTS]
        for r in range(repeats + 1):
            for sim in sims:
                sim.reset()
                prepare(sim)
            for k in range(n):
                for j in range(len(VARIANTS)):
                    i = (j + k) % len(VARIANTS)  # rotated: no variant always runs first (caches)
                    sim, up_front = sims[i], VARIANTS[i][2]
                    with contextlib.ExitStack() as stack:
                        if not up_front:
                            stack.enter_context(up_front_tests_off())
                        c0 = time.thread_time()
                        sim.step()
                        dt = time.thread_time() - c0
                    if r:  # r = 0: warm-up
                        times[i].append(dt)
        t = {v: times[i] for i, (v, _, _) in enumerate(VARIANTS)}
        med = lambda a, b: 1e6 * statistics.median(x - y for x, y in zip(t[a], t[b]))  # noqa: E731
        rows.append({"scene": name, "steps": n * repeats,
                     "steps_per_s": {v: len(x) / sum(x) for v, x in t.items()},
                     "median_step_us": {v: 1e6 * statistics.median(x) for v, x in t.items()},
                     "budget_checks_us": med("default budget", "budget=None"),
                     "up_front_tests_us": med("budget=None", "None, no up-front")})
    return rows


def _f(x, fmt="8.2f"):
    return " " * (len(format(0.0, fmt))) if x is None else format(x, fmt)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench budget", description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per case and variant (default 3)")
    ap.add_argument("--steps", type=int, default=1000, help="hand steps per check-cost pass (walker: a third)")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    if a.repeats < 1 or a.steps < 1:
        ap.error("--repeats and --steps must be >= 1")
    t0 = time.perf_counter()
    cases = [run_case(c, a.repeats) for c in CASES]
    print(f"time to failure of abusive inputs (failing step, median / max of {a.repeats}; overshoot = max - budget)")
    print(f"{'case':30s} {'budget':>7s} {'wall':>8s} {'max':>8s} {'CPU':>8s} {'max':>8s} {'over CPU':>9s} "
          f"{'over wall':>9s} {'kind':17s} error")
    for c in cases:
        b = c["budget_ms"]
        print(f"{c['case']:30s} {_f(b, '5.0f') if b is None or b >= 1 else _f(b, '5.1f')} ms "
              f"{c['wall_ms_median']:8.2f} {c['wall_ms_max']:8.2f} {c['cpu_ms_median']:8.2f} {c['cpu_ms_max']:8.2f} "
              f"{_f(c.get('overshoot_cpu_ms_max'), '9.2f')} {_f(c.get('overshoot_wall_ms_max'), '9.2f')} "
              f"{c['kind']:17s} {c['error'].split('failed: ')[-1][:110]}")
    cost = check_cost(a.steps, a.repeats)
    print("\ncost of the checks on normal steps (thread CPU time; steps/s and median step per variant, stepped in "
          "lockstep;\ncosts: median of the paired per-step differences)")
    print(f"{'scene':34s} " + " ".join(f"{v:>24s}" for v, _, _ in VARIANTS)
          + f" {'budget checks':>14s} {'up-front tests':>15s}")
    for r in cost:
        print(f"{r['scene']:34s} " + " ".join(f"{r['steps_per_s'][v]:8.0f}/s {r['median_step_us'][v]:8.1f} us"
                                              for v, _, _ in VARIANTS)
              + f" {r['budget_checks_us']:+11.2f} us {r['up_front_tests_us']:+12.2f} us")
    total = time.perf_counter() - t0
    default = {"cpu_time_s": DEFAULT.cpu_time, "qp_max_iter": DEFAULT.qp_max_iter,
               "qp_max_iter_in": DEFAULT.qp_max_iter_in}
    p = write_json(a.out, "budget", {"default_budget": default, "repeats": a.repeats, "cases": cases,
                                     "check_cost": cost, "total_wall_s": total})
    print(f"\nwrote {p} ({total:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
