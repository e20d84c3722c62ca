"""A failed step raises StepError saying why and leaves the state exactly as it was; bad commands
raise CommandError and change nothing."""
import numpy as np
import pytest

from redmax_ros.core import CommandError, Simulator, StepError
from redmax_ros.core import State


def snapshot(sim):
    return sim.state.t, sim.state.q.copy(), sim.state.v.copy(), {k: v.copy() for k, v in sim.prescribed_joints().items()}


def same(a, b):
    return (a[0] == b[0] and np.array_equal(a[1], b[1], equal_nan=True) and np.array_equal(a[2], b[2], equal_nan=True)
            and a[3].keys() == b[3].keys())


def test_non_finite_state_raises_and_keeps_state(load_sim):
    sim = load_sim("chain")
    sim.step(10)
    bad = State(sim.state.t, sim.state.q.copy(), sim.state.v.copy())
    bad.v[2] = np.nan
    sim.set_state(bad)
    before = snapshot(sim)
    with pytest.raises(StepError, match="non-finite velocity"):
        sim.step()
    assert same(before, snapshot(sim))


def test_non_finite_torque_bypassing_validation_raises_and_keeps_state(load_sim):
    sim = load_sim("hand")
    sim.step(5)
    before = snapshot(sim)
    sim.commands.joint_torques[3] = np.inf  # bypasses the command API on purpose
    with pytest.raises(StepError, match="non-finite joint torques"):
        sim.step()
    assert same(before, snapshot(sim))


def test_diverging_step_raises_and_keeps_state(load_sim):
    sim = load_sim("pendulum")
    sim.set_joint_torques({"hinge": 1e12})
    before = snapshot(sim)
    with pytest.raises(StepError, match="diverged"):
        sim.step()
    assert same(before, snapshot(sim))


def test_over_constraining_prescriptions_name_the_constraints(load_sim):
    """The four-bar has 1 DOF: prescribing both crank and rocker is redundant/conflicting; the step
    names the constraints involved and changes nothing."""
    sim = load_sim("fourbar")
    sim.prescribe_joints({"crank_joint": 1.0, "rocker_joint": 0.5})
    before = snapshot(sim)
    with pytest.raises(StepError, match="redundant or conflicting") as ei:
        sim.step()
    for name in ("crank_joint", "rocker_joint"):
        assert name in str(ei.value)
    assert same(before, snapshot(sim))


def test_impossible_point_prescription_names_the_site(load_sim):
    """A hinge about y cannot move its tip along y: the row of that site acts on no DOF."""
    sim = load_sim("pendulum")
    sim.prescribe_sites({"tip": [0.0, 0.1, 0.0]})
    before = snapshot(sim)
    with pytest.raises(StepError, match="prescribed site 'tip' does not act on any DOF"):
        sim.step()
    assert same(before, snapshot(sim))


def test_multi_step_failure_reports_steps_done(load_sim):
    sim = load_sim("pendulum")
    sim.step(3)
    sim.commands.joint_torques[0] = np.nan
    with pytest.raises(StepError) as ei:
        sim.step(5)
    assert ei.value.steps_done == 0 and sim.state.t == pytest.approx(3 * sim.dt)


@pytest.mark.parametrize("call, text", [
    (lambda s: s.prescribe_joints({"knee": 1.0}), "unknown joint 'knee'"),
    (lambda s: s.prescribe_joints({"wrist": 1.0}), "needs 2 value"),
    (lambda s: s.prescribe_joints({"elbow": float("nan")}), "non-finite"),
    (lambda s: s.prescribe_joints({"index_pip": 1.0}), "not prescribable"),
    (lambda s: s.prescribe_sites({"nose": [0, 0, 0]}), "unknown site 'nose'"),
    (lambda s: s.prescribe_sites({"index_tip": [0, 0]}), "needs 3 values"),
    (lambda s: s.prescribe_sites({"index_tip": [0, np.inf, 0]}), "non-finite"),
    (lambda s: s.set_joint_torques({"elbow": [1, 2]}), "needs 1 value"),
    (lambda s: s.prescribe_sites({"index_tip": [0, 0, 0]}, axes={"index_tip": ["w"]}), "axes of site 'index_tip'"),
    (lambda s: s.prescribe_sites({"index_tip": [0, 0, 0]}, axes={"index_tip": ["x", "x"]}), "linearly independent"),
    (lambda s: s.prescribe_sites({}, axes={"index_tip": ["x"]}), "without a velocity"),
    (lambda s: s.step(0), "positive integer"),
])
def test_bad_commands_raise_and_change_nothing(call, text, load_sim):
    sim = load_sim("hand")
    sim.prescribe_joints({"elbow": 0.2})
    before = snapshot(sim)
    tau = sim.commands.joint_torques.copy()
    with pytest.raises(CommandError, match=text):
        call(sim)
    assert same(before, snapshot(sim))
    assert np.array_equal(tau, sim.commands.joint_torques)
    assert sim.prescribed_joints()["elbow"][0] == 0.2


# ------------------------------------------------------------------------------------------------
# Found by fuzzing the facade: arguments of the wrong type or shape are CommandErrors that change nothing
# (before: TypeError, ValueError, AttributeError, OverflowError, a hang in the kernel for a 2-d q).

from dataclasses import replace


@pytest.mark.parametrize("call", [
    lambda s: s.set_joint_torques({"hinge": "abc"}),
    lambda s: s.set_joint_torques({"hinge": {}}),
    lambda s: s.set_joint_torques({None: 1.0}),
    lambda s: s.set_joint_torques([1, 2]),
    lambda s: s.set_site_forces({"tip": None}),
    lambda s: s.set_site_forces("tip"),
    lambda s: s.prescribe_joints({"hinge": 1j}),
    lambda s: s.prescribe_joints(None),
    lambda s: s.prescribe_sites({"tip": "abc"}),
    lambda s: s.prescribe_sites({"tip": [0, 0, 0]}, axes=5),
    lambda s: s.prescribe_bodies(5),
    lambda s: s.release_joints(None),
    lambda s: s.release_sites(5),
    lambda s: s.release_bodies([None]),
    lambda s: s.restore_prescriptions(joints=5),
], ids=lambda c: "")
def test_commands_of_the_wrong_type_are_command_errors(load_sim, call):
    sim = load_sim("pendulum")
    sim.step(3)
    before = snapshot(sim)
    with pytest.raises(CommandError):
        call(sim)
    assert same(before, snapshot(sim))
    sim.step(2)  # still steps


@pytest.mark.parametrize("n", [float("nan"), float("inf"), None, 1e300, 1.5, 0, True, [1], 1j])
@pytest.mark.parametrize("method", ["step", "step_results", "step_batch"])
def test_bad_step_counts_are_command_errors(load_sim, method, n):
    sim = load_sim("pendulum")
    before = snapshot(sim)
    with pytest.raises(CommandError, match="step count must be a positive integer"):
        if method == "step_batch":
            sim.step_batch([sim.state], n)
        else:
            getattr(sim, method)(n)
    assert same(before, snapshot(sim))


@pytest.mark.parametrize("change, text", [
    (lambda st: replace(st, q=st.q[:-1]), r"state.q must be 3 numbers for scene 'fourbar'"),
    (lambda st: replace(st, q=st.q[None, :]), r"state.q must be \d+ numbers"),
    (lambda st: replace(st, v=np.concatenate([st.v, [0.0]])), r"state.v must be \d+ numbers"),
    (lambda st: replace(st, q="abc"), r"state.q must be \d+ numbers"),
    (lambda st: replace(st, t=float("nan")), "state.t must be a finite number"),
    (lambda st: replace(st, k=-1), "state.k must be a step count"),
    (lambda st: None, "state must be a State"),
])
def test_set_state_of_the_wrong_shape_is_a_command_error(load_sim, change, text):
    sim = load_sim("fourbar")
    sim.step(3)
    before = snapshot(sim)
    with pytest.raises(CommandError, match=text):
        sim.set_state(change(sim.state))
    assert same(before, snapshot(sim))
    with pytest.raises(CommandError, match=text.replace("state", r"states\[0\]", 1)):
        sim.step_batch([change(sim.state)], 2)
    sim.step(2)


def test_set_state_converts_integer_arrays(load_sim):
    sim = load_sim("pendulum")
    sim.set_state(replace(sim.state, q=np.zeros(1, dtype=np.int64)))
    assert sim.state.q.dtype == float
    sim.step(2)


def test_linear_algebra_failure_from_huge_scene_values_is_a_step_error(load_sim):
    """dt 1e308 made the compiled kernel's factorisation raise numpy's LinAlgError out of step()."""
    sim = load_sim("catalogue/spring_damper", ["dt=1e308"])
    before = snapshot(sim)
    with pytest.raises(StepError, match="failed"):
        sim.step()
    assert same(before, snapshot(sim))
    with pytest.raises(StepError, match="failed") as ei:
        sim.step_results(2)
    assert ei.value.results == [] and same(before, snapshot(sim))


def test_step_batch_of_no_states_and_of_overflowing_states(load_sim):
    """[] raised IndexError; a state of 1e308 positions raised numpy's LinAlgError out of the batch."""
    sim = load_sim("mass_springs")
    out = sim.step_batch([], 3)
    assert out.states == [] and len(out.steps_done) == 0 and out.errors == []
    before = snapshot(sim)
    huge = replace(sim.state, q=np.full_like(sim.state.q, 1e308))
    try:
        out = sim.step_batch([huge], 2)
    except StepError:
        pass
    else:
        assert out.errors[0] is not None and out.steps_done[0] == 0
    assert same(before, snapshot(sim))


def test_sine_trajectory_with_an_overflowing_phase_is_a_step_error():
    """A sine of frequency 1e308 (found by fuzzing): its phase 2 pi f t overflows to inf and math.sin raised a
    bare ValueError out of the step; the time function now gives NaN and the step names the non-finite
    prescribed velocity, leaving the state as it was."""
    sim = Simulator.load("pendulum")
    sim.prescribe_joints({"hinge": {"position": {"type": "sine", "amplitude": 1.0, "frequency": 1e308}}})
    before = sim.state
    with pytest.raises(StepError):
        sim.step()
    assert sim.state is before
