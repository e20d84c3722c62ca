"""Exact simulated time (issue 17): the State counts steps and computes t = t0 + k h with one rounding,
so after a million steps t is the float nearest k h and round(t * 1e9) is exactly k times the step in
nanoseconds; a running sum (what the step did before) is off by 2 ns after 380,910 steps of 1 ms."""
import numpy as np
import pytest

from redmax_ros.core import State, StepError

N = 1_000_000


@pytest.mark.parametrize("h", [1e-3, 2e-4, 5e-5])
def test_a_million_steps_give_exact_nanoseconds(h):
    h_ns = round(h * 1e9)
    q, v = np.zeros(1), np.zeros(1)
    s = State(0.0, q, v)
    naive = 0.0
    worst_naive = 0
    for k in range(1, N + 1):
        s = s.advanced(h, q, v)
        naive += h
        if k % 1000 == 0:  # every 1000th step (all of them: 3 s more per h, the same result)
            assert round(s.t * 1e9) == k * h_ns, k
            worst_naive = max(worst_naive, abs(round(naive * 1e9) - k * h_ns))
    assert s.k == N and s.t == N * h and round(s.t * 1e9) == N * h_ns
    assert worst_naive >= 1  # the running sum drifts by whole nanoseconds: the check has teeth


def test_time_origin_and_count_survive_steps_failures_and_resets(load_sim):
    sim = load_sim("pendulum")
    h = sim.dt
    sim.step(2500)
    assert sim.state.k == 2500 and sim.state.t == 2500 * h and round(sim.time * 1e9) == 2500 * round(h * 1e9)
    before = sim.state
    sim.commands.joint_torques[0] = np.nan
    with pytest.raises(StepError):
        sim.step()
    assert sim.state is before  # a failed step leaves the count and the time as they were
    sim.commands.joint_torques[0] = 0.0
    sim.step(500)
    assert sim.state.t == 3000 * h
    sim.reset()
    assert sim.state.t == 0.0 and sim.state.k == 0
    sim.step(7)
    assert sim.state.t == 7 * h
    # a state set with its own time (t0 = 0.25 s): t = t0 + k h from there
    sim.state = State(0.25, sim.state.q.copy(), sim.state.v.copy())
    sim.step(4000)
    assert sim.state.t == 0.25 + 4000 * h
