"""The compiled step with ground contact and joint friction (step/compiled/friction.py: Staggered Projections /
BISP, paper Alg. 2-3, inside the one-call kernel) against the Pinocchio pipeline, its reference.

The two paths run the same friction kernels on inputs that differ by round-off (the compiled step's A_R, b_R
and rows come from the recursive passes, the reference's from Pinocchio). The staggered loop stops at a
tolerance (friction.tol) and its PGS inner solves and Anderson steps are discontinuous in their inputs, so a
difference of 1e-16 can move an iterate by up to the loop's tolerance; what is held here: one step to 1e-10
relative where the loop takes the same path, trajectories to the loop's tolerance over a few hundred steps,
and, on every step, the physics (bilateral rows, non-penetration, friction cone, the same contact set)."""
from __future__ import annotations

import numpy as np
import pytest

from redmax_ros.core import Simulator, StepBudget, StepError
from redmax_ros.core.errors import SceneError
from redmax_ros.core.friction import staggered

WALKER = ("klann", ["friction.joint_mu=0.4"])
# The walker's leg-pin friction rows have their slip fixed by the prescribed crank: their Delassus diagonal
# W_kk = (T P T^T)_kk is zero up to round-off (+-1e-15 .. 1e-18, its sign set by the rounding), and the PGS
# updates such a row to +-bound when W_kk > 0 and leaves it at its warm start otherwise. Their impulses move no
# velocity but load the drive, so the crank's required torque (Eq. 7) and the friction cache differ between
# two correct implementations by up to ~2e-4 relative (measured at the first step); q and qdot do not.
ZERO_W_NOTE = None


def _rel(a, b):
    return float(np.abs(a - b).max() / max(1.0, float(np.abs(b).max())))


def _pair(name, over, budget=None):
    return (Simulator.load(name, over, solver="reference", budget=budget),
            Simulator.load(name, over, solver="compiled", budget=budget))


def test_the_walker_takes_the_compiled_path():
    sim = Simulator.load(*WALKER)  # the default solver: direct
    assert type(sim.backend).__name__ == "CompiledBackend"
    r = sim.step()
    assert r.diagnostics.solver == "compiled" and not sim.backend.handoffs
    assert r.diagnostics.friction is not None and r.diagnostics.friction.iterations >= 1
    assert set(r.diagnostics.friction.joint_normal) == set(sim.mech.friction.fj_names)


def test_walker_steps_match_the_reference():
    """The first steps (the drop onto the floor) one by one from the same state: the same contact counts, and
    where both loops converged qdot+ equal to the staggered loop's tolerance (friction.tol [m/s]) and q+ to
    h tol (10x margin); at touchdown both can stop at friction.max_iter, reported, their iterates then differ
    by more (1.5e-3 m/s measured at 40 ms). (Not the crank's required torque: see ZERO_W_NOTE.)"""
    ref, comp = _pair(*WALKER)
    tol, h = comp.mech.friction.settings.tol, comp.dt
    for _ in range(40):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled"
        fa, fb = a.diagnostics.friction, b.diagnostics.friction
        assert (fa.contacts, fa.active) == (fb.contacts, fb.active)
        if fa.converged and fb.converged:  # else the loop stopped at friction.max_iter (reported), not at tol
            assert np.abs(a.v - b.v).max() <= 10 * tol and np.abs(a.q - b.q).max() <= 10 * h * tol
        comp.set_state(ref.state)  # the next step from the same state


def test_walker_trajectory_agrees_with_the_reference():
    """300 steps (feet touching down, stance, lift-off): the trajectories agree to the loop's tolerance, and every
    compiled step holds the physics: loops closed, bilateral rows met, feet not sinking, friction in its cone."""
    ref, comp = _pair(*WALKER)
    tol = comp.mech.friction.settings.tol
    worst = 0.0
    for _ in range(300):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled"
        worst = max(worst, _rel(a.q, b.q))
        d, f = b.diagnostics, b.diagnostics.friction
        assert d.violation_pos <= 1e-9 and d.violation_vel <= 1e-9
        assert f.max_penetration <= 1e-3
        assert f.converged or f.iterations == comp.mech.friction.settings.max_iter
    assert worst <= 1e3 * tol, worst
    assert _rel(ref.state.q, comp.state.q) <= 1e3 * tol


def test_ground_impulses_agree_in_stance():
    """A step in stance from the same state: the same active contacts, and the ground friction impulses (the
    cache's ground slots) equal to the loop's tolerance."""
    ref, comp = _pair(*WALKER)
    comp.step(150)
    ref.set_state(comp.state)
    b = comp.step()
    a = ref.step()
    fc, fr = comp.state.friction_cache, ref.state.friction_cache
    n_ground = comp.mech.friction.joint_slot0
    assert np.abs(fc[:n_ground] - fr[:n_ground]).max() <= 10 * comp.mech.friction.settings.tol
    assert b.diagnostics.friction.active >= 1
    assert abs(a.diagnostics.friction.active - b.diagnostics.friction.active) == 0


def test_runs_of_steps_equal_single_steps():
    """Simulator.step(n) (n steps in one kernel call, the cache carried inside) is bitwise n single steps."""
    one = Simulator.load(*WALKER, solver="compiled")
    run = Simulator.load(*WALKER, solver="compiled")
    for _ in range(60):
        one.step()
    run.step(60)
    assert np.array_equal(one.state.q, run.state.q) and np.array_equal(one.state.v, run.state.v)
    assert np.array_equal(one.state.friction_cache, run.state.friction_cache)


def test_a_budgeted_step_past_the_first_work_is_the_references_and_a_failed_one_keeps_the_state(monkeypatch):
    """Under a step budget the kernel's staggered loop stops at staggered.KERNEL_FIRST_WORK and hands the step to
    the reference, which checks the deadline: with a budget that cannot be met the step fails with the budget's
    error and the state is unchanged; the next (unbudgeted) step is the one an unfailed run takes."""
    sim = Simulator.load(*WALKER, solver="compiled")
    sim.step(5)
    before = (sim.state.t, sim.state.q.copy(), sim.state.v.copy(), sim.state.friction_cache.copy())
    monkeypatch.setattr(staggered, "KERNEL_FIRST_WORK", 1.0)
    sim.budget = StepBudget(cpu_time=1e-9)
    with pytest.raises(StepError, match="step budget exceeded: Staggered Projections"):
        sim.step()
    assert sim.backend.handoffs["friction loop beyond its first work budget (step budget)"] == 1
    s = sim.state
    assert s.t == before[0] and np.array_equal(s.q, before[1]) and np.array_equal(s.v, before[2])
    assert np.array_equal(s.friction_cache, before[3])
    monkeypatch.setattr(staggered, "KERNEL_FIRST_WORK", 2.0e6)
    sim.budget = None
    ref = Simulator.load(*WALKER, solver="compiled")
    ref.step(6)
    sim.step()
    assert np.array_equal(sim.state.q, ref.state.q) and np.array_equal(sim.state.friction_cache,
                                                                     ref.state.friction_cache)


def test_the_default_budget_changes_no_compiled_result():
    runs = []
    for budget in (StepBudget(), None):
        sim = Simulator.load(*WALKER, solver="compiled", budget=budget)
        runs.append([sim.step() for _ in range(30)])
    assert all(np.array_equal(a.q, b.q) and np.array_equal(a.v, b.v) for a, b in zip(*runs))


@pytest.mark.parametrize("name,over", [("incline", []), ("friction_chain", []), ("klann", ["friction.joint_mu=0"]),
                                       ("catalogue/prismatic_box_friction", [])])
def test_other_friction_scenes_match_the_reference(name, over):
    """Contact only (incline, the walker without joint friction), joint friction only (the paper's CHAIN, a
    box-section slider): 50 steps each to 1e-8 relative."""
    ref, comp = _pair(name, over)
    for _ in range(50):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled", comp.backend.handoffs
    assert _rel(ref.state.q, comp.state.q) <= 1e-8
    assert _rel(ref.state.v, comp.state.v) <= 1e-8


def test_proxsuite_inner_solves_stay_on_the_reference():
    """friction.qp: proxsuite (the Python loop) is outside the compiled set: direct steps it on the reference
    pipeline, compiled names it."""
    over = ["friction.joint_mu=0.4", "friction.qp=proxsuite"]
    assert type(Simulator.load("klann", over).backend).__name__ != "CompiledBackend"
    with pytest.raises(SceneError, match="friction.qp: proxsuite"):
        Simulator.load("klann", over, solver="compiled")


def test_a_short_step_arena_gives_the_same_walker_bit_for_bit(monkeypatch):
    """friction_solve takes every array of a step from the friction pack's step arena (arena.py), sized by
    step_arena_size for the most rows a step can have; a take past its end allocates instead. The walker on an
    arena a tenth of the size (most takes allocate) and on none steps bit for bit as on the full one, whose
    count bounds what a step took."""
    from redmax_ros.core.step.compiled import friction as cf

    def run(shrink):
        if shrink is not None:
            full = cf.step_arena_size
            monkeypatch.setattr(cf, "step_arena_size", lambda *a: tuple(k // shrink for k in full(*a)))
        sim = Simulator.load(*WALKER, solver="compiled")
        monkeypatch.undo()
        fr = sim.backend.friction
        states = []
        for _ in range(60):
            r = sim.step()
            assert r.diagnostics.solver == "compiled"
            states.append(np.concatenate([r.q, r.v, r.effort]))
            if shrink is None:
                assert fr["step_off"][0] <= fr["step_arena"].shape[0]
                assert fr["step_off"][1] <= fr["step_iarena"].shape[0]
        return np.array(states), fr["step_arena"].shape[0]

    ref, n_full = run(None)
    for shrink in (10, n_full + 1):
        out, n = run(shrink)
        assert n < n_full and np.array_equal(out, ref)
