"""Batched stepping (issue 12, point 4): Simulator.step_batch advances B independent states of one scene in one
call, in parallel over the instances; each instance ends bitwise where stepping it alone ends, hand-offs (an
active joint limit) included, and a failing instance is reported without disturbing the others."""
from __future__ import annotations

import dataclasses

import numpy as np

from redmax_ros.core import Simulator


def _states(sim, B, scale, seed):
    rng = np.random.default_rng(seed)
    s0 = sim.state
    return [dataclasses.replace(s0, v=s0.v + scale * rng.standard_normal(s0.v.shape)) for _ in range(B)]


def _alone(name, state, n, setup=None):
    sim = Simulator.load(name)
    if setup:
        setup(sim)
    sim.set_state(state)
    sim.step(n)
    return sim.state


def test_batch_equals_single_instances_bitwise():
    """8 perturbed fourbar states, 300 steps each: every batch instance bitwise equal to its single run, exact time."""
    sim = Simulator.load("fourbar")
    states = _states(sim, 8, 0.5, 1)
    res = sim.step_batch(states, 300)
    assert res.errors == [None] * 8 and list(res.steps_done) == [300] * 8
    for st, out in zip(states, res.states):
        ref = _alone("fourbar", st, 300)
        assert np.array_equal(out.q, ref.q) and np.array_equal(out.v, ref.v)
        assert out.t == ref.t and out.k == ref.k
    assert sim.state.k == 0  # the simulator's own state untouched


def test_batch_with_active_limits_equals_single_instances():
    """Hand instances pushed into a finger limit (the kernel's active set): still bitwise the single runs."""
    def push(s):
        s.set_joint_torques({"index_pip": [0.5]})

    sim = Simulator.load("hand")
    push(sim)
    states = _states(sim, 4, 0.2, 2)
    res = sim.step_batch(states, 120)
    assert res.errors == [None] * 4
    for st, out in zip(states, res.states):
        ref = _alone("hand", st, 120, push)
        assert np.array_equal(out.q, ref.q) and np.array_equal(out.v, ref.v)


def test_a_failing_instance_is_reported_and_the_others_go_on():
    """One instance with a NaN velocity: its error names it, its state is unchanged; the others take every step."""
    sim = Simulator.load("klann_leg")
    states = _states(sim, 3, 0.0, 3)
    bad = states[1].v.copy()
    bad[0] = np.nan
    states[1] = dataclasses.replace(states[1], v=bad)
    res = sim.step_batch(states, 50)
    assert res.errors[0] is None and res.errors[2] is None and "non-finite velocity" in res.errors[1]
    assert list(res.steps_done) == [50, 0, 50]
    assert res.states[1] is states[1]
