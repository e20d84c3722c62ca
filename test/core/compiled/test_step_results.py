"""Simulator.step_results(n): every step's StepResult from runs of steps in one kernel call (the kernels
record each step's outputs, kernel.record_step) must be the results of n single steps, bit for bit: time,
configuration, velocities, required torques and site forces, energies, violations, iterations, KKT residual,
multipliers and the friction report; a run the kernel hands back part-way, trajectories (single steps) and a
rejected step keep that contract."""
from __future__ import annotations

import numpy as np
import pytest

from redmax_ros.core import Simulator
from redmax_ros.core.errors import StepError

TIPS = ["index_tip", "middle_tip", "ring_tip", "little_tip", "thumb_tip"]
WALKER = ("klann", ["friction.joint_mu=0.4"])


def _same(a, b):
    """Two StepResults bitwise equal in everything a single step reports (not its wall time)."""
    assert a.t == b.t
    for x, y in ((a.q, b.q), (a.v, b.v), (a.effort, b.effort)):
        assert np.array_equal(x, y)
    assert set(a.site_forces) == set(b.site_forces)
    for n in a.site_forces:
        assert np.array_equal(a.site_forces[n], b.site_forces[n])
    da, db = a.diagnostics, b.diagnostics
    for f in ("E_kin", "E_pot", "E_spring", "E_total", "violation_pos", "violation_vel", "iterations", "solver",
              "residual"):
        assert getattr(da, f) == getattr(db, f), f
    sa, sb = da.solution, db.solution
    if db.solver == "compiled":
        for f in ("v", "lam", "mu"):
            assert np.array_equal(getattr(sa, f), getattr(sb, f)), f
    if da.friction is not None or db.friction is not None:
        fa, fb = da.friction, db.friction
        for f in ("iterations", "converged", "residual", "contacts", "active", "max_penetration", "sticking"):
            assert getattr(fa, f) == getattr(fb, f), f
        assert fa.joint_normal.keys() == fb.joint_normal.keys()
        assert all(np.array_equal(fa.joint_normal[j], fb.joint_normal[j]) for j in fa.joint_normal)


def _compare(name, over, n, setup=lambda s: None, chunks=(1,)):
    """n single steps against step_results in chunks (each a list of run lengths, cycled)."""
    one = Simulator.load(name, over, solver="compiled")
    many = Simulator.load(name, over, solver="compiled")
    setup(one)
    setup(many)
    singles = [one.step() for _ in range(n)]
    got, c = [], 0
    while len(got) < n:
        k = min(chunks[c % len(chunks)], n - len(got))
        res = many.step_results(k)
        assert len(res) == k
        got += res
        c += 1
    for a, b in zip(singles, got):
        _same(a, b)
    assert np.array_equal(one.state.q, many.state.q) and np.array_equal(one.state.v, many.state.v)
    assert one.state.t == many.state.t and one.state.k == many.state.k
    _same(one.last, many.last)
    return got


def test_hand_with_prescribed_elbow_and_fingertips():
    """The hand with the elbow and five fingertips prescribed (Eq. 7): required torques and fingertip forces of
    every step of 200, in runs of 1, 7 and 64 steps, are those of single steps."""
    def setup(s):
        s.prescribe_joints({"elbow": 0.3})
        s.prescribe_sites({t: [0.0, 0.0, 0.01 * (k + 1)] for k, t in enumerate(TIPS)})
    got = _compare("hand", [], 200, setup, chunks=(1, 7, 64))
    assert set(got[-1].site_forces) == set(TIPS)
    assert np.abs(got[-1].effort).max() > 0.0
    # each result owns its numbers: a later step does not change an earlier one
    first = got[0].q.copy()
    assert np.array_equal(first, got[0].q) and not np.array_equal(got[0].q, got[-1].q)


@pytest.mark.parametrize("name,over", [("fourbar", []), ("mass_springs", ["integrator.scheme=bdf2"]),
                                       ("chain", ["params.n=20"])])
def test_runs_record_the_single_steps(name, over):
    """A loop (post-stabilised), BDF2 with its history, a chain: 300 steps in runs of 300 and of 13."""
    _compare(name, over, 300, chunks=(300,))
    _compare(name, over, 300, chunks=(13,))


def test_joint_limit_steps_inside_a_run():
    """A finger pushed into its limit: the kernel's active-set steps (several KKT solves, multipliers mu) are
    recorded as single steps report them."""
    def setup(s):
        s.set_joint_torques({"index_pip": [0.5]})
    got = _compare("hand", [], 120, setup, chunks=(120,))
    assert max(r.diagnostics.iterations for r in got) > 1
    assert any(np.abs(r.diagnostics.solution.mu).max() > 0.0 for r in got)


def test_walker_with_friction():
    """The Klann walker with joint friction (the friction kernel): every step's friction report too."""
    got = _compare(*WALKER, 60, chunks=(60,))
    assert all(r.diagnostics.friction is not None for r in got)


def test_trajectories_step_one_at_a_time():
    """A joint trajectory changes its rows every step: step_results takes single steps, the same results."""
    def setup(s):
        s.prescribe_joints({"elbow": {"position": {"type": "sine", "amplitude": 0.2, "frequency": 1.0}}})
    _compare("hand", [], 30, setup, chunks=(30,))


def test_a_rejected_step_keeps_the_state_and_reports_no_results():
    """A prescription no step below the divergence limit can meet fails the first step: StepError with
    steps_done 0 and no results, the state as it was."""
    sim = Simulator.load("hand", solver="compiled")
    sim.step_results(5)
    before = sim.state
    sim.prescribe_joints({"elbow": 1e9})
    with pytest.raises(StepError) as e:
        sim.step_results(10)
    assert e.value.steps_done == 0 and e.value.results == []
    assert sim.state is before


@pytest.mark.parametrize("name,over", [WALKER, ("fourbar", []), ("mass_springs", ["integrator.scheme=bdf2"])])
def test_an_unrecorded_run_returns_its_last_step_as_a_single_step_would(name, over):
    """Simulator.step(n) records nothing inside the run (the kernels compute the KKT residual, a diagnostic, for
    the returned step only): its result is the n-th of n single steps, bit for bit, residual included."""
    one = Simulator.load(name, over, solver="compiled")
    run = Simulator.load(name, over, solver="compiled")
    for _ in range(40):
        last = one.step()
    got = run.step(40)
    _same(last, got)
    assert np.isfinite(got.diagnostics.residual) and got.diagnostics.residual < 1e-6
