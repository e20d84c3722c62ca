"""The engine steps a lockstep request in runs (Simulator.step(k), engine._advance): the states, the
published steps, command timeouts and a failure's step count must be those of stepping one step at a
time (an action's feedback makes every run one step, so the same engine gives the reference)."""
import numpy as np
import pytest

from redmax_ros.node import engine as eng
import time

from redmax_ros.core import Simulator
from redmax_ros.node.engine import PAUSED, PLAYING, Engine, NullSink


class Recorder(NullSink):
    def __init__(self):
        self.states, self.warnings = [], []

    def state(self, t, q, v, effort, site_forces, diag, step_index, body_wrenches):
        self.states.append((step_index, t, q.copy(), v.copy(), np.asarray(effort).copy()))

    def warn(self, text):
        self.warnings.append(text)


def _engine(scene, overrides=(), initial_state=PAUSED, **kw):
    sink = Recorder()
    e = Engine(sink, scene, overrides, initial_state=initial_state, **kw)
    e.start()
    return e, sink


def _run(scene, n, per_step, overrides=(), before=None, **kw):
    """(Outcome, sink, engine) of one lockstep request of n steps; ``per_step``: with an action's feedback
    (runs of one step), else plain runs."""
    e, sink = _engine(scene, overrides, **kw)
    try:
        if before is not None:
            before(e)
        fb = (lambda done, total, t: None) if per_step else None
        out = e.step(n, fb)
        return out, sink, e
    finally:
        e.stop()


@pytest.mark.parametrize("scene", ["hand", "klann_leg"])
def test_runs_publish_the_same_states_at_the_same_steps_bitwise(scene):
    n = 1234  # h = 1 ms, published at 20 Hz of sim time: steps 50, 100, ..., 1200 and the last
    a, ra, ea = _run(scene, n, per_step=True, publish_rate=20.0)
    b, rb, eb = _run(scene, n, per_step=False, publish_rate=20.0)
    assert a.ok and b.ok and a.steps == b.steps == n
    assert [s[0] for s in rb.states] == [s[0] for s in ra.states] == list(range(50, n, 50)) + [n]
    for sa, sb in zip(ra.states, rb.states):
        assert sa[1] == sb[1]
        for xa, xb in zip(sa[2:], sb[2:]):
            assert np.array_equal(xa, xb)
    assert eb._run_cap > 1  # the runs did take more than one step
    assert ea.sim.state.k == eb.sim.state.k == n


@pytest.mark.parametrize("scene,overrides", [("hand", ()), ("klann", ("friction.joint_mu=0.4",))])
def test_runs_publishing_every_step_record_the_single_steps_bitwise(scene, overrides):
    """joint_states every step (publish_rate 0): a run records each step's result in its one kernel call
    (Simulator.step_results) and the engine publishes them all: the same states at the same steps as
    stepping one at a time (the action's feedback path), with markers and frames still ending the runs."""
    n = 345
    a, ra, ea = _run(scene, n, True, overrides, publish_rate=0.0)
    b, rb, eb = _run(scene, n, False, overrides, publish_rate=0.0)
    assert a.ok and b.ok and a.steps == b.steps == n
    assert [s[0] for s in rb.states] == [s[0] for s in ra.states] == list(range(1, n + 1))
    for sa, sb in zip(ra.states, rb.states):
        assert sa[1] == sb[1]
        for xa, xb in zip(sa[2:], sb[2:]):
            assert np.array_equal(xa, xb)
    assert eb._run_cap > 1 and eb.step_index == n
    assert ea.sim.state.k == eb.sim.state.k == n


def test_a_command_times_out_at_the_same_step_in_runs():
    """A held torque with command_timeout 0.0375 s sim time goes back to zero at the same step either way."""
    from sensor_msgs.msg import JointState

    def command(e):
        msg = JointState()
        msg.name = ["hinge"]
        msg.effort = [0.5]
        e.joint_command(msg)

    n = 200
    a, ra, ea = _run("pendulum", n, True, before=command, command_timeout=0.0375, publish_rate=100.0)
    b, rb, eb = _run("pendulum", n, False, before=command, command_timeout=0.0375, publish_rate=100.0)
    assert a.ok and b.ok
    assert [w for w in ra.warnings if "timeout" in w] == [w for w in rb.warnings if "timeout" in w] != []
    assert np.array_equal(ea.sim.state.q, eb.sim.state.q) and np.array_equal(ea.sim.state.v, eb.sim.state.v)
    for sa, sb in zip(ra.states, rb.states):
        assert sa[0] == sb[0] and np.array_equal(sa[4], sb[4])


def test_a_failing_step_inside_a_run_reports_the_steps_before_it():
    """A free body under 1e7 m/s^2 passes the divergence limit (1e6 m/s) at its 101st step: the request
    says so, 100 steps were taken, and the state is that after them, as stepping one at a time."""
    ov = ["gravity=[0,0,-1e7]"]
    a, _, ea = _run("catalogue/free3d", 500, True, ov, publish_rate=10.0)
    b, _, eb = _run("catalogue/free3d", 500, False, ov, publish_rate=10.0)
    assert a.code == b.code == eng.OPERATION_FAILED
    assert a.steps == b.steps == 100 and "step 101 of 500 failed" in b.message and "diverged" in b.message
    assert a.message == b.message
    assert eb.step_index == 100 and eb.failures == 1
    assert np.array_equal(ea.sim.state.q, eb.sim.state.q) and np.array_equal(ea.sim.state.v, eb.sim.state.v)


@pytest.mark.parametrize("scene,g", [("catalogue/free3d", 1e7), ("mass_springs", 5e7)])
def test_a_failing_step_inside_a_recorded_run_publishes_the_steps_before_it(scene, g):
    """Publishing every step, bodies under huge gravity pass the divergence limit part-way (free3d at its 101st
    step; mass_springs, on its springs, at about its 22nd): the run's steps before it are published (bitwise
    those of single steps) and the request reports them (mass_springs: the compiled kernel's run, its failing
    step handed to the reference)."""
    ov = [f"gravity=[0,0,{-g}]"]
    a, ra, ea = _run(scene, 500, True, ov, publish_rate=0.0)
    b, rb, eb = _run(scene, 500, False, ov, publish_rate=0.0)
    assert a.code == b.code == eng.OPERATION_FAILED and a.message == b.message
    assert a.steps == b.steps == eb.step_index
    assert 10 < b.steps < 500
    assert [s[0] for s in rb.states] == [s[0] for s in ra.states] == list(range(1, b.steps + 1))
    for sa, sb in zip(ra.states, rb.states):
        assert sa[1] == sb[1] and np.array_equal(sa[2], sb[2]) and np.array_equal(sa[4], sb[4])


def test_free_run_in_runs_publishes_the_core_states_at_every_tenth_step():
    """Free-run as fast as possible, publishing at 100 Hz of sim time (h = 1 ms): the steps due go in
    runs that end at every 10th step, and each published state is bitwise the core's, stepped one at a time."""
    e, sink = _engine("hand", initial_state=PLAYING, publish_rate=100.0, real_time_factor=0.0)
    time.sleep(1.0)
    e.stop()
    got = sink.states
    assert len(got) >= 5 and e._run_cap > 1
    assert all(idx % 10 == 0 for idx, *_ in got)
    sim = Simulator.load("hand")
    k = 0
    for idx, t, q, v, _ in got[:50]:
        while k < idx:
            sim.step()
            k += 1
        assert sim.time == t and np.array_equal(sim.state.q, q)


def test_free_run_as_fast_as_possible_publishes_every_recorded_step():
    """Free-run at real_time_factor 0 publishing every step: runs record every step (Simulator.step_results)
    and each is published, with contiguous step indices and states bitwise the core's one step at a time."""
    e, sink = _engine("hand", initial_state=PLAYING, publish_rate=0.0, real_time_factor=0.0)
    time.sleep(1.0)
    e.stop()
    got = sink.states
    assert len(got) >= 50 and e._run_cap > 1
    assert [idx for idx, *_ in got] == list(range(got[0][0], got[0][0] + len(got)))
    sim = Simulator.load("hand")
    k = 0
    for idx, t, q, v, eff in got[:300]:
        while k < idx:
            res = sim.step()
            k += 1
        assert sim.time == t and np.array_equal(sim.state.q, q) and np.array_equal(res.effort, eff)


def test_run_cap_grows_for_cheap_steps_and_halves_for_slow_ones():
    cap = 1
    for _ in range(20):
        cap = eng._next_cap(cap, cap, 1e-5)
    assert cap == eng.RUN_CAP_MAX
    assert eng._next_cap(cap, 10, 1e-5) == cap  # a run cut short (a publish point) says nothing
    assert eng._next_cap(64, 64, 3 * eng.RUN_WALL) == 32
    assert eng._next_cap(1, 1, 1.0) == 1


def test_diagnostics_report_the_last_steps_integration_order():
    """/diagnostics carries the last step's Diagnostics.order: 1 under the euler scheme; under bdf2, 1 after the
    start-up step and 2 after a BDF2 step (a smooth pendulum keeps them)."""
    class Diag(NullSink):
        def __init__(self):
            self.values = []

        def diagnostics(self, values, ok, message):
            self.values.append(values)

    for overrides, n, want in (((), 3, 1), (("integrator.scheme=bdf2",), 1, 1), (("integrator.scheme=bdf2",), 3, 2)):
        sink = Diag()
        e = Engine(sink, "pendulum", list(overrides), initial_state=PAUSED, diagnostics_period=0.02)
        e.start()
        try:
            assert e.step(n, None).steps == n
            end = time.monotonic() + 10.0  # the engine's thread reports every diagnostics_period, paused too
            while not any(v.get("steps") == n for v in list(sink.values)) and time.monotonic() < end:
                time.sleep(0.01)
        finally:
            e.stop()
        last = [v for v in sink.values if v.get("steps") == n][-1]
        assert last["integration_order"] == want, (overrides, n, last)
