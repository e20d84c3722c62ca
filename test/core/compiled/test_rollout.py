"""Simulator.rollout(n, every): the outputs of every every-th step stacked in arrays. Row i must be, bit for bit,
what the single step (i + 1) every reports (time, configuration, velocities, required torques and site forces,
energies, violations, iterations), on the compiled kernels (which record only those steps and, under BDF2,
compute only their energies) and on the other backends; a run the kernel starts part-way into a stride (its
``phase``), trajectories (single steps) and a rejected step keep that contract."""
from __future__ import annotations

import numpy as np
import pytest

import redmax_ros.core.simulator as simulator
from redmax_ros.core import Rollout, Simulator
from redmax_ros.core.errors import CommandError, StepError

TIPS = ["index_tip", "middle_tip", "ring_tip", "little_tip", "thumb_tip"]


def _row_is(ro: Rollout, i: int, res):
    """Row i of a Rollout bitwise equal to the StepResult ``res``."""
    assert ro.t[i] == res.t
    for x, y in ((ro.q[i], res.q), (ro.v[i], res.v), (ro.effort[i], res.effort)):
        assert np.array_equal(x, y)
    assert set(ro.site_forces) == set(res.site_forces)
    for n in res.site_forces:
        assert np.array_equal(ro.site_forces[n][i], res.site_forces[n])
    d = res.diagnostics
    for f in ("E_kin", "E_pot", "E_spring", "E_total", "violation_pos", "violation_vel", "iterations"):
        assert getattr(ro, f)[i] == getattr(d, f), f
    assert ro.solver[i] == d.solver


def _singles(name, over, n, setup, solver="compiled"):
    sim = Simulator.load(name, over, solver=solver)
    setup(sim)
    return sim, [sim.step() for _ in range(n)]


def _prescribed_hand(s):
    s.prescribe_joints({"elbow": 0.3})
    s.prescribe_sites({t: [0.0, 0.0, 0.01 * (k + 1)] for k, t in enumerate(TIPS)})


CASES = [("chain", ["params.n=5", "integrator.scheme=bdf2"], lambda s: None),
         ("mass_springs", ["integrator.scheme=bdf2"], lambda s: None),
         ("fourbar", ["integrator.scheme=bdf2"], lambda s: None),
         ("fourbar", [], lambda s: None),
         ("klann", ["friction.joint_mu=0.4"], lambda s: None),
         ("hand", [], _prescribed_hand)]


@pytest.mark.parametrize("every", [1, 4])
@pytest.mark.parametrize("name,over,setup", CASES, ids=[f"{c[0]}{'-' + c[1][-1] if c[1] else ''}" for c in CASES])
def test_rows_are_the_single_steps(name, over, setup, every, monkeypatch):
    """BDF2 (energies of the recorded steps only), loops, friction, prescribed joints and sites: 12 rows of every
    ``every``-th step, in kernel runs of at most 5 rows (RECORD_ROWS), against 12 every single steps; the
    state after them and ``last`` too."""
    monkeypatch.setattr(simulator, "RECORD_ROWS", 5)
    one, singles = _singles(name, over, 12 * every, setup)
    sim = Simulator.load(name, over, solver="compiled")
    setup(sim)
    ro = sim.rollout(12, every)
    assert len(ro) == 12 and ro.q.flags.c_contiguous
    for i in range(12):
        _row_is(ro, i, singles[(i + 1) * every - 1])
    assert np.array_equal(sim.state.q, one.state.q) and np.array_equal(sim.state.v, one.state.v)
    assert sim.state.t == one.state.t and sim.state.k == one.state.k
    _row_is(ro, 11, sim.last)
    assert sim.last.diagnostics.residual == singles[-1].diagnostics.residual


def test_a_run_that_starts_inside_a_stride():
    """The kernel's phase: a run from 2 steps into a stride of 3 records the run's steps 1, 4, 7 (the 3rd, 6th and
    9th of the stride count), as single steps report them."""
    name, over = "mass_springs", ["integrator.scheme=bdf2"]
    one, singles = _singles(name, over, 8, lambda s: None)
    sim = Simulator.load(name, over, solver="compiled")
    state, ro, k = sim.backend.rollout_run(sim.state, sim.commands, sim.dt, 8, 3, 2)
    assert k == 8 and len(ro) == 3
    for i, step in enumerate((1, 4, 7)):
        _row_is(ro, i, singles[step - 1])
    assert np.array_equal(state.q, one.state.q)


@pytest.mark.parametrize("solver", ["direct", "pcg"])
def test_other_backends_give_the_same_rows(solver):
    """Without the compiled kernels the rows come from single steps: the chain under BDF2, every 3rd of 15."""
    over = ["params.n=5", "integrator.scheme=bdf2"]
    _, singles = _singles("chain", over, 15, lambda s: None, solver)
    sim = Simulator.load("chain", over, solver=solver)
    ro = sim.rollout(5, 3)
    for i in range(5):
        _row_is(ro, i, singles[3 * i + 2])


def test_trajectories_step_one_at_a_time():
    """A joint trajectory changes its rows every step: single steps (through the phase), the same rows."""
    def setup(s):
        s.prescribe_joints({"elbow": {"position": {"type": "sine", "amplitude": 0.2, "frequency": 1.0}}})
    _, singles = _singles("hand", [], 12, setup)
    sim = Simulator.load("hand", solver="compiled")
    setup(sim)
    ro = sim.rollout(4, 3)
    for i in range(4):
        _row_is(ro, i, singles[3 * i + 2])


def test_a_rejected_step_keeps_the_state_and_the_rows_before_it():
    """A prescription no step below the divergence limit can meet: StepError with the rows recorded before the
    failing step (none here), the state as it was."""
    sim = Simulator.load("hand", solver="compiled")
    sim.rollout(2, 2)
    before = sim.state
    sim.prescribe_joints({"elbow": 1e9})
    with pytest.raises(StepError) as e:
        sim.rollout(5, 2)
    assert e.value.steps_done == 0 and e.value.rollout is None
    assert sim.state is before


@pytest.mark.parametrize("n,every", [(0, 1), (3, 0), (2.5, 1), (3, float("nan")), (3, -2)])
def test_bad_counts_are_refused_by_name(n, every):
    """A row count or stride that is not a positive integer: CommandError naming it, nothing stepped."""
    sim = Simulator.load("chain", ["params.n=3"], solver="compiled")
    before = sim.state
    with pytest.raises(CommandError, match="every" if n == 3 else "step count"):
        sim.rollout(n, every)
    assert sim.state is before
