"""Bounded work per step (issue 17): inputs whose step must diverge are rejected before any solve, naming
the joint or site and the value; every step is held to a budget (CPU time of its iterative solvers,
ProxSuite iteration caps) past which it fails with the budget's StepError; a failed step leaves the state
as it was and the next normal step is the one it would have been; the default budget changes no result of
a normal step and ``budget=None`` is the unlimited step.

The only timing assertions are generous bounds ("returns within 5 s") proving that a step does not run
on: without the budget the 1e12 cases ran ProxSuite's QP for 2-124 s."""
import gc
import re
import time

import numpy as np
import pytest

from redmax_ros.core import CommandError, Simulator, State, StepBudget, StepError
from redmax_ros.core.friction import staggered
from redmax_ros.core.solvers import budget as budget_mod
from redmax_ros.core.step import pipeline

RETURNS_WITHIN = 5.0  # s of wall time: a slow CI machine, far below the 2-124 s of an unbounded QP


def snapshot(sim):
    s = sim.state
    return (s.t, s.q.copy(), s.v.copy(), None if s.friction_cache is None else s.friction_cache.copy())


def unchanged(before, sim):
    t, q, v, fc = before
    s = sim.state
    return (s.t == t and np.array_equal(s.q, q) and np.array_equal(s.v, v)
            and (fc is None) == (s.friction_cache is None) and (fc is None or np.array_equal(s.friction_cache, fc)))


def failing_step(sim, match):
    """The next step: StepError matching ``match``, within RETURNS_WITHIN, state bitwise unchanged."""
    before = snapshot(sim)
    t0 = time.perf_counter()
    with pytest.raises(StepError, match=match) as ei:
        sim.step()
    assert time.perf_counter() - t0 < RETURNS_WITHIN
    assert unchanged(before, sim)
    assert ei.value.steps_done == 0
    return str(ei.value)


def same_result(a, b):
    return (np.array_equal(a.q, b.q) and np.array_equal(a.v, b.v) and np.array_equal(a.effort, b.effort)
            and a.diagnostics.iterations == b.diagnostics.iterations and a.diagnostics.solver == b.diagnostics.solver)


# ------------------------------------------------------------------------------------------------
# up-front rejection: the 1e12 cases measured against the node


def test_elbow_velocity_1e12_is_rejected_before_solving_and_the_next_step_is_unaffected():
    """Was: the QP ran to PROXQP_MAX_ITER_REACHED (90 s in the node). The elbow row needs |qdot| >= 1e12."""
    sim, ref = Simulator.load("hand"), Simulator.load("hand")
    sim.step(5)
    ref.step(5)
    sim.prescribe_joints({"elbow": 1e12})
    msg = failing_step(sim, r"prescribed joint 'elbow'")
    assert "diverged" in msg and "1e+12" in msg and "limit 1e+06" in msg
    sim.prescribe_joints({"elbow": 0.5})  # the next normal step: as if the bad command had never been
    ref.prescribe_joints({"elbow": 0.5})
    assert same_result(sim.step(), ref.step())


def test_wrist_torque_1e12_is_rejected_before_solving():
    """Was: accepted, and a later step ran the joint-limit QP for ~64 s. Its impulse alone would change the
    wrist's velocity by ~6e7 rad/s in one step."""
    sim = Simulator.load("hand")
    sim.step(3)
    sim.set_joint_torques({"wrist": [1e12, 0.0]})
    msg = failing_step(sim, r"applied torque of joint 'wrist'")
    assert "diverged" in msg and "1e+12 N m" in msg and "limit 1e+06" in msg
    sim.set_joint_torques({"wrist": [0.0, 0.0]})
    sim.step(2)


def test_wrist_torque_1e12_then_many_steps_fails_at_once_every_time():
    """The node's case: the command is accepted and free-run keeps stepping. Every step fails at once,
    before solving (steps_done 0), and the state never moves."""
    sim = Simulator.load("hand")
    sim.step(3)
    sim.set_joint_torques({"wrist": [1e12, 0.0]})
    before = snapshot(sim)
    for _ in range(20):
        t0 = time.perf_counter()
        with pytest.raises(StepError, match=r"rejected before solving\): applied torque of joint 'wrist'") as ei:
            sim.step(100)
        assert time.perf_counter() - t0 < RETURNS_WITHIN
        assert ei.value.steps_done == 0 and unchanged(before, sim)


@pytest.mark.parametrize("command", ["elbow velocity", "wrist torque"])
def test_the_same_commands_at_1e6_behave_as_before(command):
    """At 1e6 a step below the divergence limit is possible, so nothing is rejected up front: the step is
    solved and judged by its result, as before the up-front tests (elbow: the first step diverges; wrist:
    a few steps are taken, then one diverges)."""
    sim = Simulator.load("hand")
    sim.step(3)
    if command == "elbow velocity":
        sim.prescribe_joints({"elbow": 1e6})
    else:
        sim.set_joint_torques({"wrist": [1e6, 0.0]})
    with pytest.raises(StepError, match=r"step diverged: max \|qdot\| = [\d.e+]+ \(limit 1e\+06\)") as ei:
        sim.step(100)
    assert "rejected before solving" not in str(ei.value)
    assert (ei.value.steps_done == 0) == (command == "elbow velocity")


@pytest.mark.parametrize("command", ["crank velocity", "knee torque"])
def test_walker_1e12_commands_are_rejected_and_1e6_ones_solved(command):
    """The shipped walker (its crank prescribed at -2 pi rad/s by the scene, joint friction 0.2): 1e12 on
    the crank or a knee fails before the staggered solve, naming the joint; at 1e6 the crank step is
    solved and diverges, the knee torque is stepped (its leg's loops and the floor hold it)."""
    sim = Simulator.load("klann")
    sim.step(3)
    if command == "crank velocity":
        sim.prescribe_joints({"crank_fwd": 1e12})
        failing_step(sim, r"rejected before solving\): prescribed joint 'crank_fwd': velocity 1e\+12")
        sim.prescribe_joints({"crank_fwd": 1e6})
        with pytest.raises(StepError, match=r"step diverged: max \|qdot\|"):
            sim.step()
    else:
        sim.set_joint_torques({"knee_f2": 1e12})
        failing_step(sim, r"rejected before solving\): applied torque of joint 'knee_f2' = 1e\+12 N m")
        sim.set_joint_torques({"knee_f2": 1e6})
        sim.step(5)


@pytest.mark.parametrize("where", ["joint", "site"])
def test_huge_prescribed_velocities_name_the_joint_or_site(where):
    sim = Simulator.load("hand")
    if where == "joint":
        sim.prescribe_joints({"wrist": [0.0, -1e9]})
        failing_step(sim, r"prescribed joint 'wrist': velocity -1e\+09 needs max \|qdot\| >= 1e\+09")
    else:
        sim.prescribe_sites({"index_tip": [0.0, 0.0, 1e12]})
        failing_step(sim, r"prescribed site 'index_tip': velocity 1e\+12")


def test_huge_site_force_names_the_site():
    sim = Simulator.load("hand")
    sim.set_site_forces({"index_tip": [0.0, 0.0, 1e12]})
    failing_step(sim, r"applied force on site 'index_tip'")


def test_walker_crank_1e12_is_rejected_before_the_staggered_solve():
    sim = Simulator.load("klann", ["friction.joint_mu=0.4"])
    sim.step(3)
    sim.prescribe_joints({"crank_fwd": 1e12})
    failing_step(sim, r"prescribed joint 'crank_fwd': velocity 1e\+12")
    sim.prescribe_joints({"crank_fwd": -6.283185307179586})
    sim.step(2)


def test_pcg_scene_huge_commands_fail_fast_and_keep_the_state():
    """PCG solves at any scale in its capped iterations: a 1e12 N m torque ends in the divergence check
    within a few steps; a 1e12 rad/s prescription is rejected before the solve."""
    sim = Simulator.load("bridge", ["params.n_deck=12"], solver="pcg")
    sim.step(2)
    sim.set_joint_torques({"d5": 1e12})
    t0 = time.perf_counter()
    with pytest.raises(StepError, match="diverged"):
        sim.step(10)
    assert time.perf_counter() - t0 < RETURNS_WITHIN
    sim = Simulator.load("bridge", ["params.n_deck=12"], solver="pcg")
    sim.step(2)
    sim.prescribe_joints({"d5": 1e12})
    failing_step(sim, r"prescribed joint 'd5': velocity 1e\+12")


def test_a_state_velocity_beyond_the_limit_is_rejected():
    sim = Simulator.load("hand")
    sim.step(2)
    v = sim.state.v.copy()
    v[3] = 2e6
    sim.set_state(State(sim.state.t, sim.state.q.copy(), v))
    failing_step(sim, r"the state's velocity 2e\+06 \(DOF 3\) is beyond the limit")


def test_large_but_possible_commands_are_not_rejected():
    """The up-front tests reject only what no step below the divergence limit can do: a torque on a
    prescribed joint is taken by its multiplier (the required effort cancels it), a 1 kN m wrist torque
    (1e4 times the hand's scale, far below the ~1.7e7 N m the test needs) is stepped."""
    sim = Simulator.load("hand")  # elbow prescribed at 0 rad/s
    ref = Simulator.load("hand")
    sim.set_joint_torques({"elbow": 1e9})
    res, ref_res = sim.step(3), ref.step(3)
    assert np.allclose(res.v, ref_res.v, atol=1e-6)
    assert res.effort[0] == pytest.approx(ref_res.effort[0], abs=1e-3)
    sim = Simulator.load("hand")
    sim.set_joint_torques({"wrist": [1e3, 0.0]})
    sim.step(3)
    sim.prescribe_joints({"elbow": 1e5})  # a step below 1e6 is possible: solved, then judged by its result
    with pytest.raises(StepError, match=r"step diverged: max \|qdot\|"):
        sim.step(5)


# ------------------------------------------------------------------------------------------------
# the budget: the backstop when an input gets past the up-front tests


@pytest.mark.parametrize("command", ["elbow velocity", "wrist torque"])
def test_without_the_up_front_tests_the_1e12_cases_end_with_the_budget_error(command, monkeypatch):
    """The same 1e12 inputs with the up-front tests switched off: the default budget stops the QP (which
    cannot reach its absolute tolerance at that scale) instead of letting it run on."""
    monkeypatch.setattr(pipeline, "check_rows", lambda *a, **k: None)
    monkeypatch.setattr(pipeline, "check_applied", lambda *a, **k: None)
    sim = Simulator.load("hand")
    sim.step(2)
    if command == "elbow velocity":
        sim.prescribe_joints({"elbow": 1e12})
    else:
        sim.set_joint_torques({"wrist": [1e12, 0.0]})
    msg = failing_step(sim, r"step budget exceeded: joint-limit QP \(Eq. 5\) after \d+ iterations / [\d.]+ ms")
    assert "(budget 50 ms)" in msg or "(budget 1000 QP outer iterations)" in msg


def hand_at_a_joint_limit(budget):
    """The hand with a 1 N m index_pip torque: after 5 steps the finger reaches its limit and the next
    step needs the joint-limit QP of Eq. (5) (ProxSuite, on the reference pipeline: the compiled step's own
    active set is bounded by its 4 p + 4 iterations, test/core/compiled/test_compiled_step.py)."""
    sim = Simulator.load("hand", solver="reference", budget=budget)
    sim.set_joint_torques({"index_pip": 1.0})
    sim.step(5)
    return sim


def test_qp_iteration_budget_fails_the_step_and_keeps_the_state():
    sim = hand_at_a_joint_limit(StepBudget(qp_max_iter=1))
    msg = failing_step(sim, r"step budget exceeded: joint-limit QP \(Eq. 5\) after \d+ iterations")
    assert "(budget 1 QP outer iterations)" in msg
    sim.budget = StepBudget()  # the same step with the default budget: solved, as the unlimited one
    res = sim.step()
    ref = hand_at_a_joint_limit(None).step()
    assert res.diagnostics.solver == "qp" and same_result(res, ref)


def test_time_budget_fails_a_pcg_step_and_keeps_the_state():
    sim = Simulator.load("umbrella", solver="pcg", budget=StepBudget(cpu_time=1e-9))
    failing_step(sim, r"step budget exceeded: lockstep PCG \(Eq. 4\) after \d+ iterations / [\d.]+ ms "
                      r"\(budget 1e-06 ms\)")
    sim.budget = None
    assert sim.step().diagnostics.solver == "pcg"


def test_time_budget_fails_the_compiled_staggered_loop_and_keeps_the_state(monkeypatch):
    """Under a budget the compiled staggered loop of the walker (joint friction and floor contact) runs in
    pieces with the deadline checked between them, and fails with the budget's error, the state unchanged. Its
    first piece (staggered.KERNEL_FIRST_WORK work units) is more than a normal step needs, so it is cut to one
    unit here (the reference pipeline's loop; the compiled step hands such a step to it: test_compiled_friction.py): the step then runs in pieces whatever the machine. (The test used to drive the crank at 1e4 rad/s
    and wait for a step that runs long, ~20 ms at the 7th step on one machine; on another CPU the chaotic
    trajectory's round-off differs and no step of the first 10 ran long: the 11th diverged.)"""
    sim = Simulator.load("klann", solver="reference")
    sim.step(3)
    sim.budget = StepBudget(cpu_time=1e-9)
    monkeypatch.setattr(staggered, "KERNEL_FIRST_WORK", 1.0)
    before = snapshot(sim)
    with pytest.raises(StepError) as e:
        sim.step()
    assert re.search(r"step budget exceeded: Staggered Projections \(compiled loop\) after \d+ "
                     r"iterations / [\d.]+ ms \(budget 1e-06 ms\)", str(e.value)), str(e.value)
    assert unchanged(before, sim)
    monkeypatch.setattr(staggered, "KERNEL_FIRST_WORK", 2.0e6)
    sim.budget = None
    ref = Simulator.load("klann", solver="reference")
    ref.step(4)
    sim.step()  # the failed step changed nothing: it now gives the unbudgeted step
    assert np.array_equal(sim.state.q, ref.state.q)


def test_the_compiled_staggered_loop_in_pieces_is_bitwise_the_loop_in_one_call(monkeypatch):
    """Pieces of one iteration each (a budget without a time limit still runs the loop in pieces): the
    same steps as the unbudgeted loop, bit for bit."""
    calls = []
    kernel = staggered.staggered_kernel
    monkeypatch.setattr(staggered, "KERNEL_FIRST_WORK", 1.0)
    monkeypatch.setattr(staggered, "KERNEL_SLICE", 1e-12)
    monkeypatch.setattr(staggered, "staggered_kernel", lambda *a: calls.append(1) or kernel(*a))
    runs = []
    for budget in (StepBudget(cpu_time=None), None):
        sim = Simulator.load("klann", ["friction.joint_mu=0.6"], solver="reference", budget=budget)
        calls.clear()
        runs.append([sim.step() for _ in range(40)])
        n_calls = len(calls)
        if budget is not None:
            assert n_calls > 2 * 40  # in pieces
        else:
            assert n_calls == 40
    assert all(same_result(a, b) and a.diagnostics.friction.iterations == b.diagnostics.friction.iterations
               for a, b in zip(*runs))


def test_lockstep_pcg_in_slices_is_bitwise_the_solve_in_one_call(monkeypatch):
    """Under a budget the lockstep PCG iterations after the first run in slices sized to the time left
    (Deadline.iterations_left): slices of one iteration each, or of what fits in the default budget, give the
    unbudgeted steps bit for bit."""
    from_budget = {}
    for name, budget, slice_of_one in (("one call", None, False), ("slices of 1", StepBudget(), True),
                                       ("default slices", StepBudget(), False)):
        with monkeypatch.context() as mp:
            if slice_of_one:
                mp.setattr(budget_mod.Deadline, "iterations_left", lambda self, per, cap: 1)
            sim = Simulator.load("umbrella", ["params.ribs=2"], solver="pcg", budget=budget)
            from_budget[name] = [sim.step() for _ in range(10)]
    ref = from_budget["one call"]
    for name in ("slices of 1", "default slices"):
        assert all(same_result(a, b) and a.diagnostics.iterations == b.diagnostics.iterations
                   for a, b in zip(from_budget[name], ref)), name


def test_lockstep_pcg_first_slice_at_the_previous_pace(monkeypatch):
    """After the first budgeted PCG call in a workspace, the first slice of the next one is sized at the pace
    recorded by the last (wall time per column and iteration): under the default budget the umbrella's steps then
    run their lockstep iterations in the one call that starts them (no lockstep_iterate call)."""
    from redmax_ros.core.solvers import lockstep_pcg
    sim = Simulator.load("umbrella", ["params.ribs=2"], solver="pcg", budget=StepBudget())
    sim.step(2)
    calls = []
    real = lockstep_pcg.lockstep_iterate
    monkeypatch.setattr(lockstep_pcg, "lockstep_iterate", lambda *a: calls.append(1) or real(*a))
    most = []
    for _ in range(5):
        assert sim.step().diagnostics.solver == "pcg"
        most.append(max(sim.backend.workspace.tree.last_stats["solves"]))
    assert not calls and max(most) > 1  # a solve of more than one iteration, all in the first call


def test_deadline_iterations_left():
    """The iterations of a given pace that fit before the deadline's limit, between 1 and the cap; the cap
    without a time budget."""
    d = StepBudget(cpu_time=0.05).start()
    assert d.iterations_left(1e-3, 1000) == 1000  # the clock has not started: no limit yet
    d.begin()
    assert 40 <= d.iterations_left(1e-3, 1000) <= 50
    assert d.iterations_left(1e-3, 7) == 7 and d.iterations_left(1.0, 1000) == 1
    assert d.iterations_left(0.0, 9) == 9
    free = StepBudget(cpu_time=None).start()
    free.begin()
    assert free.iterations_left(1e-3, 1000) == 1000


def test_garbage_collection_is_not_the_steps_time():
    """A full collection of a large heap inside the clock's span is left out of ``used`` (it traverses every
    object of the process, whoever made them), as JIT compilation is."""
    junk = [[i] for i in range(3_000_000)]  # ~0.3 s for a full collection here
    d = StepBudget(cpu_time=0.01).start()
    d.begin()
    t0 = time.thread_time()
    gc.collect()
    spent = time.thread_time() - t0
    assert spent > 0.01 and d.used() < 0.1 * spent  # the collection took the whole budget; ~0 of it counted
    d.limit = 0.0  # the wall clock is past the limit: check reads the CPU time
    d.check("test", 1)
    del junk


def test_a_collection_inside_the_walkers_first_iteration_does_not_fail_the_step(monkeypatch):
    """CI's failure: a full collection (a pytest process's heap, up to 264 ms measured) inside the first
    staggered iteration of the walker with ProxSuite inner QPs failed its 50 ms budget "after 1 iterations
    / 238.5 ms". With the collection left out, the step is the unlimited step, bitwise."""
    junk = [[i] for i in range(3_000_000)]
    calls = []
    box_qp = staggered.box_qp

    def collecting_box_qp(*args, **kwargs):
        if not calls:
            gc.collect()
        calls.append(1)
        return box_qp(*args, **kwargs)

    ref = Simulator.load("klann", ["friction.joint_mu=0.4", "friction.qp=proxsuite"], budget=None)
    expected = ref.step()
    sim = Simulator.load("klann", ["friction.joint_mu=0.4", "friction.qp=proxsuite"])
    monkeypatch.setattr(staggered, "box_qp", collecting_box_qp)
    assert same_result(sim.step(), expected) and calls
    del junk


@pytest.mark.parametrize("scene,overrides,solver,setup", [
    ("hand", (), "reference", lambda s: s.set_joint_torques({"index_pip": 1.0})),  # joint-limit QP steps (ProxSuite)
    ("klann", ("friction.joint_mu=0.4",), None, lambda s: None),  # Staggered Projections / BISP
    ("klann", ("friction.joint_mu=0.4", "friction.qp=proxsuite"), None, lambda s: None),  # ProxSuite inner QPs
    ("bridge", ("params.n_deck=12",), "pcg", lambda s: s.set_joint_torques({"d5": 50.0})),  # lockstep PCG
], ids=["hand-qp", "walker-pgs", "walker-proxsuite", "bridge-pcg"])
def test_the_default_budget_changes_no_result_of_normal_steps(scene, overrides, solver, setup):
    runs = []
    for budget in (StepBudget(), None):
        sim = Simulator.load(scene, list(overrides), solver=solver, budget=budget)
        setup(sim)
        runs.append([sim.step() for _ in range(20)])
    assert all(same_result(a, b) for a, b in zip(*runs))
    if scene == "hand":
        assert any(r.diagnostics.solver == "qp" for r in runs[0])


def test_budget_api():
    sim = Simulator.load("pendulum")
    assert sim.budget == StepBudget(cpu_time=0.05, qp_max_iter=1000, qp_max_iter_in=50)
    assert Simulator.load("pendulum", budget=None).budget is None
    assert StepBudget.from_ms(20) == StepBudget(cpu_time=0.02)
    assert StepBudget.from_ms(0) is None and StepBudget.from_ms(None) is None
    assert StepBudget.from_ms(5, qp_max_iter=10).qp_max_iter == 10
    assert StepBudget.from_ms(-1.0) is None and StepBudget.from_ms(np.float64(2.5)).cpu_time == 0.0025
    for bad in (float("nan"), float("inf"), "50", True):
        with pytest.raises(ValueError, match="finite number of milliseconds"):
            StepBudget.from_ms(bad)
    for bad in (dict(cpu_time=-1.0), dict(cpu_time=float("nan")), dict(qp_max_iter=2.5), dict(qp_max_iter_in=-3)):
        with pytest.raises(ValueError):
            StepBudget(**bad)
    with pytest.raises(CommandError, match="StepBudget or None"):
        sim.budget = 0.05
    sim.budget = StepBudget(cpu_time=None, qp_max_iter=None, qp_max_iter_in=None)  # caps off: ProxSuite's own
    sim.step(3)
