"""integrator.scheme: bdf2 on the compiled path (step/compiled/scheme.py, issue 14 point 2): the compiled BDF2 step
against the Pinocchio pipeline's, runs of steps in one call (the history kept inside the kernel) bitwise equal
to single steps, batches bitwise equal to single instances, and the State's history as the pipeline keeps it."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from redmax_bench.accuracy import slow_kick
from redmax_ros.core import Simulator
from redmax_ros.core.step.backends import make_backend
from redmax_ros.core.step.compiled.data import OUT_ORDER
from redmax_ros.core.step.state import State

BDF2 = "integrator.scheme=bdf2"
# (scene, overrides, steps): mass_springs is chaotic under BDF2 (less numerical dissipation than BDF1: a
# 1e-13 perturbation of q grows to 2.3e-8 in 1000 steps), so it is compared over 300 steps
SCENES = [("pendulum", [], 1000), ("chain", ["params.n=20"], 1000), ("chain", ["params.n=30", "params.springs=10"], 1000),
          ("fourbar", [], 1000), ("slider_crank", [], 1000), ("klann_leg", [], 1000), ("hand", [], 1000),
          ("branching", [], 1000), ("mass_springs", [], 300)]


def _rel(a, b):
    return float(np.abs(a - b).max() / max(1.0, float(np.abs(b).max())))


@pytest.mark.parametrize("name,over,n", SCENES, ids=[n + ("" if not o else ":" + ",".join(o)) for n, o, _ in SCENES])
def test_compiled_bdf2_matches_the_reference(name, over, n):
    """The start-up (BDF1) and the first BDF2 step to 1e-12 relative (raised to the round-off bound 10 kappa(A) eps
    of the step's LHS where that is larger, as test_compiled_step does), the trajectory of n steps to 1e-9, the
    required torques of the last step to 1e-9 relative (measured: 1000 steps within 2e-12 on every scene but
    mass_springs)."""
    ref = Simulator.load(name, [BDF2, *over], solver="reference")
    comp = Simulator.load(name, [BDF2, *over], solver="compiled")
    for _ in range(2):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled"
        tol = max(1e-12, 10.0 * float(np.linalg.cond(a.diagnostics.solution.system.A)) * np.finfo(float).eps)
        assert _rel(a.q, b.q) <= tol and _rel(a.v, b.v) <= tol and _rel(a.effort, b.effort) <= tol
    ref.step(n - 3)
    comp.step(n - 3)
    a, b = ref.step(), comp.step()
    assert _rel(ref.state.q, comp.state.q) <= 1e-9 and _rel(a.effort, b.effort) <= 1e-9
    assert comp.state.history is not None and comp.state.history.h == ref.state.history.h


def test_runs_of_steps_equal_single_steps_under_bdf2():
    """Simulator.step(n) keeps BDF2's history inside the kernel: bitwise the state of n single steps (history too)."""
    one = Simulator.load("hand", [BDF2], solver="compiled")
    run = Simulator.load("hand", [BDF2], solver="compiled")
    for _ in range(300):
        one.step()
    run.step(300)
    for x, y in ((one.state.q, run.state.q), (one.state.v, run.state.v),
                 (one.state.history.q, run.state.history.q), (one.state.history.v, run.state.history.v)):
        assert np.array_equal(x, y)
    assert one.state.t == run.state.t


def test_batch_equals_single_instances_under_bdf2():
    """4 perturbed four-bar states (no history: each starts with the BDF1 step), 200 steps: bitwise the single runs."""
    sim = Simulator.load("fourbar", [BDF2])
    rng = np.random.default_rng(3)
    s0 = sim.state
    states = [dataclasses.replace(s0, v=s0.v + 0.3 * rng.standard_normal(s0.v.shape)) for _ in range(4)]
    res = sim.step_batch(states, 200)
    assert res.errors == [None] * 4
    for st, out in zip(states, res.states):
        alone = Simulator.load("fourbar", [BDF2])
        alone.set_state(st)
        alone.step(200)
        assert np.array_equal(out.q, alone.state.q) and np.array_equal(out.v, alone.state.v)
        assert np.array_equal(out.history.q, alone.state.history.q)


def test_trajectory_under_bdf2_matches_the_reference():
    """A position trajectory on the elbow (its rows aim from q^, step/trajectory.py): compiled and reference agree
    to 1e-10 over 300 steps, required elbow torque included."""
    traj = {"elbow": {"position": {"type": "sine", "amplitude": 0.3, "frequency": 1.0}, "b": 20.0}}
    ref = Simulator.load("hand", [BDF2], solver="reference")
    comp = Simulator.load("hand", [BDF2], solver="compiled")
    for s in (ref, comp):
        s.prescribe_joints(traj)
    for _ in range(300):
        a, b = ref.step(), comp.step()
    assert _rel(a.q, b.q) <= 1e-10 and _rel(a.effort, b.effort) <= 1e-10


@pytest.mark.parametrize("h,k", [(1e-2, "1e6"), (5e-3, "1e4")])
def test_compiled_order_control_redoes_the_same_steps_as_bdf1(h, k):
    """mass_springs with corner springs, where the order control (step/scheme.accepts, compiled/scheme.accepted)
    redoes steps as BDF1: the compiled step takes the same order on every step as the Pinocchio pipeline and
    agrees with it over 100 steps to 1e-9 relative, in single steps and in one run of steps."""
    over = [BDF2, f"dt={h}", f"params.k={k}", "params.attach=corners"]
    ref = Simulator.load("mass_springs", over, solver="reference")
    comp = Simulator.load("mass_springs", over, solver="compiled")
    run = Simulator.load("mass_springs", over, solver="compiled")
    for _ in range(100):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled"
        assert _rel(a.q, b.q) <= 1e-9 and _rel(a.v, b.v) <= 1e-9
    run.step(100)
    assert _rel(run.state.q, comp.state.q) <= 1e-12 and _rel(run.state.v, comp.state.v) <= 1e-12


def test_stiffly_compressed_springs_match_the_reference():
    """mass_springs with k = 1e8 N/m at h = 1e-2, its ties compressed 7 % at rest: springs.spring_shift takes their
    exact Jacobian (the stiff branch). Compiled and reference agree to 1e-7 relative over 100 steps (measured 8.5e-9
    in q, 2.1e-8 in v: the LHS's condition number is 2e7, and the BDF1 start-up step already differs by 1.1e-9 in
    v)."""
    over = [BDF2, "params.k=100000000.", "dt=1e-2"]
    ref = Simulator.load("mass_springs", over, solver="reference")
    comp = Simulator.load("mass_springs", over, solver="compiled")
    for _ in range(100):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled"
    assert _rel(a.q, b.q) <= 1e-7 and _rel(a.v, b.v) <= 1e-7


def test_slow_kick_stiff_springs_match_the_reference():
    """redmax_bench accuracy's 'mass_springs k=1e+06' (springs unloaded at the initial pose, static equilibrium,
    0.5 m/s sideways kick) at h = 1e-2: the maximal springs linearised about q* with the ties' soft negative
    transverse stiffness left to the LHS's K (springs.spring_shift, the soft branch): compiled and reference agree
    to 1e-9 relative over 100 steps, every step of both a BDF2 step after the start-up."""
    sims = []
    for solver in ("reference", "compiled"):
        sim = Simulator.load("mass_springs", [BDF2, "dt=1e-2", "params.k=1000000."], solver=solver)
        q, v = slow_kick(0.5)(sim.mech, sim.mech.q0.copy(), None)
        sim.backend = make_backend(sim.mech, solver)  # the compiled Model packs the rest lengths when it is made
        sim.set_state(State(0.0, q, v))
        sims.append(sim)
    ref, comp = sims
    for i in range(100):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled"
        d = next(iter(comp.backend._data.values()))  # the step's Data (no commands: one)
        assert d["out"][OUT_ORDER] == (1.0 if i == 0 else 2.0)
        assert _rel(a.q, b.q) <= 1e-9 and _rel(a.v, b.v) <= 1e-9
