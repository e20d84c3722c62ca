"""Our work-precision runs (redmax_bench/methods.run_ours) are the trajectory a user's single steps give: the
untimed warm-up step leaves no trace (the run restarts from the start state, BDF2 without a history), and the
runs sampled every step (Simulator.step_results in blocks) record what step(1) after step(1) gives, bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

from redmax_bench import accuracy  # noqa: F401 - registers the cases
from redmax_bench import methods as M
from redmax_ros.core import State


def _single_steps(case, extra, T, sample_dt, h):
    """q and E_total every sample_dt from step(1) calls on a fresh problem (no warm-up)."""
    p = M.make_problem(case, T, sample_dt, extra)
    sim = p.sim
    sim.dt = h
    sim.set_state(State(0.0, p.q0.copy(), p.vR0.copy()))
    n_sub = int(round(sample_dt / h))
    Q, E = [], []
    for _ in range(p.n_samples):
        for _ in range(n_sub):
            res = sim.step(1)
        Q.append(res.q.copy())
        E.append(res.diagnostics.E_total)
    return np.array(Q), np.array(E)


@pytest.mark.parametrize("extra, method", [([], "ours (direct)"), (["integrator.scheme=bdf2"], "ours BDF2 (direct)")])
@pytest.mark.parametrize("h", [0.01, 0.005])  # every step a sample (step_results), two steps a sample (step(2))
def test_runs_record_the_single_steps_trajectory(extra, method, h):
    case = M.CASES["mass_springs k=1e+06"]
    T, sample_dt = 0.3, 0.01
    Q, E = _single_steps(case, extra, T, sample_dt, h)
    p = M.make_problem(case, T, sample_dt)
    run = M.METHODS[method].run(p, h)
    assert run.status == "ok" and run.steps == len(Q) * int(round(sample_dt / h))
    assert np.array_equal(np.array(run.q), Q)
    assert np.array_equal(np.array(run.E), E)
    again = M.METHODS[method].run(p, h)  # the same problem again (the timing repeats): the same trajectory
    assert np.array_equal(np.array(again.q), Q)
