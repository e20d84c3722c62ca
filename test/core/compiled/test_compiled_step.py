"""The compiled step (step/compiled/) against the Pinocchio pipeline, its reference (issue 12, point 3): on every
shipped scene it takes, one step from the initial state and from random states to 1e-12 relative, 1000-step
trajectories to 1e-9; prescribed joints and sites with their required torques and forces; runs of steps in one
call bitwise equal to single steps; hand-offs (an active joint limit, bad input) give exactly the reference's
outcome and leave the state as it was."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from redmax_ros.core import Simulator
from redmax_ros.core.errors import SceneError, StepError

TIPS = ["index_tip", "middle_tip", "ring_tip", "little_tip", "thumb_tip"]

# every shipped scene the compiled path takes (scenes/ and scenes/catalogue/), with the overrides used; the
# others (catalogue joints, composite joints, implicit Coriolis) are in test_unsupported_scenes_are_named; the
# frictional scenes are in test_compiled_friction.py
SCENES = [("pendulum", []), ("chain", ["params.n=20"]), ("chain", ["params.n=30", "params.springs=10"]),
          ("fourbar", []), ("klann_leg", []), ("slider_crank", []), ("mass_springs", []), ("hand", []),
          ("branching", []), ("bridge", []), ("umbrella", []), ("catalogue/revolute", []), ("catalogue/prismatic", []), ("catalogue/translational", []),
          ("catalogue/fixed", []), ("catalogue/spring_damper", []), ("catalogue/explicit_spring", []),
          ("catalogue/spherical", ["integrator.coriolis=explicit"]),
          ("catalogue/universal", ["integrator.coriolis=explicit"])]
UNSUPPORTED = {"catalogue/spline_curve": "catalogue",
               "catalogue/free3d": "Composite", "catalogue/limits_multi": "Composite",
               "catalogue/spherical": "coriolis: implicit"}


def _pair(name, over):
    try:
        c = Simulator.load(name, over, solver="compiled")
    except SceneError as e:
        pytest.skip(f"{name}: {e}")
    return Simulator.load(name, over, solver="reference"), c


def _rel(a, b):
    return float(np.abs(a - b).max() / max(1.0, float(np.abs(b).max())))


def _check_step(ref, comp, tol):
    """One step of each; ``tol`` relative, raised to the round-off bound 10 kappa(A) eps of the step's LHS when
    that is larger (two correct implementations of a solve with condition number kappa differ by that much)."""
    a, b = ref.step(), comp.step()
    if b.diagnostics.solver != "compiled":  # handed to the reference (a loop projection needing the full Newton)
        assert set(comp.backend.handoffs) <= {"loop projection (full Newton)"}, comp.backend.handoffs
        assert np.array_equal(a.q, b.q) and np.array_equal(a.v, b.v)
        return a, b
    sol = a.diagnostics.solution
    if getattr(sol, "system", None) is not None:
        tol = max(tol, 10.0 * float(np.linalg.cond(sol.system.A)) * np.finfo(float).eps)
    for x, y in ((a.q, b.q), (a.v, b.v), (a.effort, b.effort), (ref.state.v, comp.state.v)):
        assert _rel(x, y) <= tol
    da, db = a.diagnostics, b.diagnostics
    assert abs(da.E_total - db.E_total) <= tol * max(1.0, abs(da.E_total))
    assert abs(da.violation_pos - db.violation_pos) <= 1e-10
    assert db.residual <= 1e-10
    for n in a.site_forces:
        assert _rel(a.site_forces[n], b.site_forces[n]) <= tol
    return a, b


@pytest.mark.parametrize("name,over", SCENES, ids=[n + ("" if not o else ":" + ",".join(o)) for n, o in SCENES])
def test_one_step_matches_reference(name, over):
    """From the initial state and from three random states (random velocities, perturbed joint angles of
    tree-only scenes): one step equal to the reference to 1e-12 relative."""
    ref, comp = _pair(name, over)
    _check_step(ref, comp, 1e-12)
    rng = np.random.default_rng(7)
    mech = ref.mech
    for _ in range(3):
        st = ref.state
        v = st.v + 0.5 * rng.standard_normal(st.v.shape)
        q = st.q
        if not len(mech.loop_ab) and not len(mech.limited):
            import pinocchio as pin
            q = pin.integrate(mech.model, st.q, 0.3 * rng.standard_normal(mech.nv))
        ref.set_state(dataclasses.replace(st, q=q, v=v))
        comp.set_state(dataclasses.replace(st, q=q, v=v))
        _check_step(ref, comp, 1e-12)


@pytest.mark.parametrize("name,over", [("chain", ["params.n=20"]), ("fourbar", []), ("klann_leg", []),
                                       ("mass_springs", []), ("hand", []), ("slider_crank", [])])
def test_trajectory_matches_reference(name, over):
    """1000 steps: the compiled trajectory stays within 1e-9 of the reference's (relative)."""
    ref, comp = _pair(name, over)
    ra, rb = ref.step(1000), comp.step(1000)
    assert _rel(ra.q, rb.q) <= 1e-9
    assert _rel(ra.v, rb.v) <= 1e-9
    assert set(comp.backend.handoffs) <= {"joint limit active (QP of Eq. 5)"}


def test_hand_prescriptions_and_required_forces():
    """The hand with its elbow and five fingertips prescribed (Eq. 7): positions, required torques and the
    fingertip forces equal the reference's to 1e-12 for 200 steps, the prescribed tip velocities held."""
    ref, comp = _pair("hand", [])
    for s in (ref, comp):
        s.prescribe_joints({"elbow": 0.3})
        s.prescribe_sites({t: [0.0, 0.0, 0.01 * (k + 1)] for k, t in enumerate(TIPS)})
    for _ in range(200):
        a, b = _check_step(ref, comp, 1e-10)
    assert b.diagnostics.violation_vel <= 1e-12
    assert set(b.site_forces) == set(TIPS)
    assert np.abs(b.effort).max() > 0.0


def test_site_axes_prescription():
    """A fingertip prescribed along one world axis only (Eq. 7 with *G_m = P J_site): equal to the reference."""
    ref, comp = _pair("hand", [])
    for s in (ref, comp):
        s.prescribe_sites({"index_tip": [0.0, 0.0, 0.02]}, axes={"index_tip": [[0.0, 0.0, 1.0]]})
    for _ in range(50):
        a, b = _check_step(ref, comp, 1e-10)
    assert b.site_forces["index_tip"].shape == (3,)


def test_runs_of_steps_equal_single_steps():
    """Simulator.step(n) runs the kernel n times in one call: bitwise the state of n single steps, exact time."""
    one = Simulator.load("fourbar", solver="compiled")
    run = Simulator.load("fourbar", solver="compiled")
    for _ in range(500):
        one.step()
    run.step(500)
    assert np.array_equal(one.state.q, run.state.q) and np.array_equal(one.state.v, run.state.v)
    assert one.state.t == run.state.t == 500 * one.dt
    assert np.array_equal(one.last.effort, run.last.effort)


def test_joint_limits_in_kernel_match_the_reference_qp():
    """A finger joint pushed into its limit (0.5 N m on index_pip): the kernel's active set (limits.py) solves
    the QP of Eq. (5) itself, to a relative KKT residual <= 1e-12 on every limit step (measured <= 2.0e-15).
    The reference solves it with ProxSuite (eps_abs 1e-10, KKT residual up to 2.5e-8 here) polished by the
    active set from ProxSuite's active rows (solvers/direct.polish), so both are the exact solution: the 300-step
    trajectories agree to round-off (measured |dq| <= 9.8e-14 rad, |d effort| <= 1.5e-12 N m; before the polish
    8.1e-7 rad and 4.6e-7 N m; asserted 1e-10), the limit holds (q within 1e-9 of its bound) and the
    multipliers are nonzero."""
    ref, comp = _pair("hand", [])
    for s in (ref, comp):
        s.set_joint_torques({"index_pip": [0.5]})
    limit_steps = 0
    for _ in range(300):
        a, b = ref.step(), comp.step()
        assert b.diagnostics.solver == "compiled", comp.backend.handoffs
        assert np.abs(a.q - b.q).max() <= 1e-10 and np.abs(a.effort - b.effort).max() <= 1e-10
        if a.diagnostics.solver == "qp":
            limit_steps += 1
            assert b.diagnostics.iterations >= 2
            mu = b.diagnostics.solution.mu
            assert np.abs(mu).max() > 0.0 and b.diagnostics.residual <= 1e-12
    assert limit_steps > 200
    mech = comp.mech
    k = list(mech.limited).index(mech.joint_index["index_pip"].idx_v)
    q = comp.state.q[mech.limited_q[k]]
    assert min(abs(q - mech.limit_lower[k]), abs(q - mech.limit_upper[k])) <= 1e-9
    assert not comp.backend.handoffs


@pytest.mark.parametrize("bad", ["nan_velocity", "huge_torque", "huge_prescription", "bad_dt"])
def test_bad_input_same_error_state_unchanged(bad):
    """Bad input: the same StepError as the reference (its message names the problem), state unchanged."""
    sims = _pair("hand", [])
    msgs = []
    for s in sims:
        if bad == "nan_velocity":
            v = s.state.v.copy()
            v[0] = np.nan
            s.set_state(dataclasses.replace(s.state, v=v))
        elif bad == "huge_torque":
            s.set_joint_torques({"wrist": [1e30, 0.0]})
        elif bad == "huge_prescription":
            s.prescribe_joints({"elbow": 1e12})
        else:
            s.dt = -1.0
        q0, v0, t0 = s.state.q.copy(), s.state.v.copy(), s.state.t
        with pytest.raises(StepError) as e:
            s.step()
        msgs.append(str(e.value))
        assert np.array_equal(s.state.q, q0, equal_nan=True) and np.array_equal(s.state.v, v0, equal_nan=True)
        assert s.state.t == t0
    assert msgs[0] == msgs[1]


@pytest.mark.parametrize("name,why", sorted(UNSUPPORTED.items()))
def test_unsupported_scenes_are_named(name, why):
    """Scenes outside the compiled path's set are refused with what they use (the reference steps them)."""
    with pytest.raises(SceneError, match=why):
        Simulator.load(name, solver="compiled")


def test_loop_rows_know_their_loop():
    """model.loop_row_loop: the loop of each row of the loop selection S (rows of axes, block by block), which the
    loop residual and the loop rows sum over instead of every column; a row spanning two loops is refused."""
    from redmax_ros.core.step.compiled.model import loop_row_loop
    S = np.zeros((5, 9))
    S[0, 0:3] = [1, 0, 0]
    S[1, 0:3] = [0, 0.6, 0.8]
    S[2, 3:6] = [0, 0, 1]
    S[3, 6:9] = [1, 0, 0]
    S[4, 6:9] = [0, 1, 0]
    assert loop_row_loop(S).tolist() == [0, 0, 1, 2, 2]
    assert loop_row_loop(np.zeros((0, 0))).shape == (0,)
    S[2, 0] = 1.0
    with pytest.raises(AssertionError):
        loop_row_loop(S)
    walker = Simulator.load("klann", solver="compiled")
    Sw = walker.mech.loop_select
    rows = loop_row_loop(Sw)
    for r in range(Sw.shape[0]):  # every nonzero of a row lies in its loop's three columns
        assert set(np.flatnonzero(Sw[r]) // 3) == {rows[r]}
