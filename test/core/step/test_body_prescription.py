"""Body-twist prescriptions (issue 13 item 4): maximal hybrid dynamics, paper Eq. 7 with *G_m the body's
6 x nv twist Jacobian (step/body_twist.py). Selected components of phi = [omega; v] of a body frame,
body or world-aligned axes; the required wrench P^T (-lam / h) is StepResult.body_wrenches.
"""
from __future__ import annotations

import copy

import numpy as np
import pinocchio as pin
import pytest
import yaml

from redmax_ros.core import CommandError, SceneError, Simulator, scene_from_dict
from redmax_ros.core.errors import StepError
from redmax_ros.core.step import body_twist

from pathlib import Path

CAT = Path(__file__).resolve().parents[3] / "scenes" / "catalogue"


def raw(name):
    return yaml.safe_load((CAT / f"{name}.yaml").read_text())


def free_box():
    return Simulator.load("catalogue/free3d", ["joints.free.conserve_momentum=false"])


def body_rotation(sim, body):
    _, quat = sim.body_poses()[body]
    return pin.Quaternion(np.asarray(quat)).toRotationMatrix()  # xyzw coeffs


def twist(sim, body, frame):
    """[omega; v] of the body frame at the current state, from the twist Jacobian."""
    data = sim.data
    pin.computeAllTerms(sim.mech.model, data, sim.state.q, sim.joint_velocities())
    return body_twist.twist_jacobian(sim.mech, data, body, frame) @ sim.joint_velocities()


def test_revolute_body_twist_equals_joint_velocity_prescription():
    """Prescribing omega_y of the rod (body frame) = prescribing the hinge velocity: same motion, same torque."""
    a, b = Simulator.load("catalogue/revolute"), Simulator.load("catalogue/revolute")
    a.prescribe_bodies({"rod": {"angular": [None, 2.0, None]}})
    b.prescribe_joints({"hinge": 2.0})
    m, g = 0.02 * 0.02 * 0.4 * 1000, 9.81
    for _ in range(200):
        ra, rb = a.step(), b.step()
        assert ra.diagnostics.violation_vel < 1e-10
        assert np.abs(ra.q - rb.q).max() < 1e-12
        w = ra.body_wrenches["rod"]
        assert w.shape == (6,)
        assert abs(w[1] - rb.effort[0]) < 1e-9
        assert np.abs(np.delete(w, 1)).max() == 0.0
    # the analytic torque holding the pendulum at constant speed: m g l_c sin(q_k) (gravity at the start of the step)
    q_k = ra.q[0] - 2.0 * a.dt
    assert abs(w[1] - m * g * 0.2 * np.sin(q_k)) < 1e-6 * m * g * 0.2
    assert abs(a.joint_velocities()[0] - 2.0) < 1e-12


def test_free_body_angular_velocity_followed_exactly():
    sim = free_box()
    cmd = [0.3, -0.2, 1.0]
    sim.prescribe_bodies({"box": {"angular": cmd}})
    for _ in range(50):
        r = sim.step()
        assert r.diagnostics.violation_vel < 1e-10
        assert np.abs(twist(sim, "box", "body")[:3] - cmd).max() < 1e-10
    assert set(r.body_wrenches) == {"box"} and np.all(r.body_wrenches["box"][3:] == 0.0)
    # the linear velocity stays free: zero gravity, its initial world velocity is kept
    assert np.allclose(sim.joint_velocities()[:3], [0.5, -0.2, 0.3], atol=1e-12)


def test_free_body_linear_and_angular_world_frame():
    sim = free_box()
    w_cmd, v_cmd = [0.0, 0.0, 0.5], [0.2, 0.0, -0.1]
    sim.prescribe_bodies({"box": {"angular": w_cmd, "linear": v_cmd, "frame": "world"}})
    for _ in range(50):
        r = sim.step()
        assert np.abs(twist(sim, "box", "world") - np.r_[w_cmd, v_cmd]).max() < 1e-10
    assert r.body_wrenches["box"].shape == (6,)


def test_world_and_body_frames_give_the_same_motion():
    """A body-frame command and the world command R(q_k) omega_b of the same rows give the same motion and
    wrenches related by the rotation, step by step."""
    a, b = free_box(), free_box()
    w_b = np.array([0.4, -0.3, 0.8])
    a.prescribe_bodies({"box": {"angular": w_b}})
    for _ in range(40):
        R = body_rotation(b, "box")
        b.prescribe_bodies({"box": {"angular": (R @ w_b).tolist(), "frame": "world"}})
        ra, rb = a.step(), b.step()
        assert np.abs(ra.q - rb.q).max() < 1e-12
        assert np.abs(ra.v - rb.v).max() < 1e-12
        assert np.abs(R @ ra.body_wrenches["box"][:3] - rb.body_wrenches["box"][:3]).max() < 1e-10


def test_over_constraining_raises_step_error_naming_the_body():
    sim = Simulator.load("catalogue/revolute")
    sim.prescribe_bodies({"rod": {"angular": [0.1, 2.0, 0.0]}})  # omega_x: the hinge cannot produce it
    q = sim.state.q.copy()
    with pytest.raises(StepError, match="prescribed body 'rod'"):
        sim.step()
    assert np.array_equal(sim.state.q, q)
    # dependent rows: omega_y and the x velocity of the rod's origin conflict
    sim.prescribe_bodies({"rod": {"angular": [None, 2.0, None], "linear": [0.0, None, None]}})
    with pytest.raises(StepError, match="prescribed body 'rod'"):
        sim.step()


@pytest.mark.parametrize("bodies,match", [
    ({"nope": {"angular": [0, 0, 1]}}, "unknown body 'nope'"),
    ({"box": {"angular": [0, 1]}}, "'angular' needs 3 values"),
    ({"box": {"linear": [0, float("nan"), 1]}}, "non-finite 'linear'"),
    ({"box": {"angular": [0, 0, 1], "frame": "joint"}}, "unknown frame 'joint'"),
    ({"box": {"angula": [0, 0, 1]}}, "unknown key"),
    ({"box": {"frame": "world"}}, "give 'angular' and/or 'linear'"),
    ({"box": {"angular": [0, "x", 1]}}, "not a number"),
])
def test_bad_commands_raise_and_change_nothing(bodies, match):
    sim = free_box()
    sim.prescribe_bodies({"box": {"angular": [1.0, 0.0, 0.0]}})
    before = sim.prescribed_bodies()
    with pytest.raises(CommandError, match=match):
        sim.prescribe_bodies({"box": {"linear": [1.0, 2.0, 3.0]}, **bodies} if "box" not in bodies else bodies)
    after = sim.prescribed_bodies()
    assert after.keys() == before.keys()
    assert np.array_equal(after["box"]["values"], before["box"]["values"])
    assert after["box"]["components"] == ["wx", "wy", "wz"]


def test_release_and_restore():
    sim = free_box()
    sim.prescribe_bodies({"box": {"angular": [0.0, 0.0, 0.0]}})
    sim.step(5)
    assert sim.last.body_wrenches
    sim.release_bodies(["box"])
    assert sim.prescribed_bodies() == {}
    assert sim.step().body_wrenches == {}
    with pytest.raises(CommandError, match="unknown body 'x'"):
        sim.release_bodies(["x"])


def test_scene_prescription_and_errors():
    d = raw("revolute")
    d["prescribed"] = {"bodies": {"rod": {"angular": [None, -1.5, None], "frame": "world"}}}
    sim = Simulator(scene_from_dict(d, str(CAT / "revolute.yaml"), base_dir=CAT))
    r = sim.step(20)
    assert abs(sim.joint_velocities()[0] + 1.5) < 1e-12 and "rod" in r.body_wrenches
    sim.prescribe_bodies({"rod": {"angular": [None, 3.0, None]}})
    sim.restore_prescriptions(bodies=["rod"])
    assert sim.prescribed_bodies()["rod"]["values"].tolist() == [-1.5]
    sim.reset()
    assert sim.prescribed_bodies()["rod"]["frame"] == "world"
    for val, match in [({"angular": [0, 1]}, "needs 3 values"), ({"angular": [0, 1, 2], "frame": "x"}, "unknown frame")]:
        bad = copy.deepcopy(d)
        bad["prescribed"]["bodies"]["rod"] = val
        with pytest.raises(SceneError, match=match) as e:
            scene_from_dict(bad)
        assert "prescribed.bodies.rod" in str(e.value)
    bad = copy.deepcopy(d)
    bad["prescribed"]["bodies"] = {"ghost": {"angular": [0, 1, 2]}}
    with pytest.raises(SceneError, match="unknown body 'ghost'"):
        scene_from_dict(bad)


def test_data_free_path_rejects_body_prescriptions():
    sim = Simulator.load("catalogue/revolute", solver="pcg")
    with pytest.raises(CommandError, match="data-free path"):
        sim.prescribe_bodies({"rod": {"angular": [None, 1.0, None]}})
    assert sim.prescribed_bodies() == {}
    d = raw("revolute")
    d["prescribed"] = {"bodies": {"rod": {"angular": [None, 1.0, None]}}}
    with pytest.raises(SceneError, match="data-free path"):
        Simulator(scene_from_dict(d, str(CAT / "revolute.yaml"), base_dir=CAT), solver="pcg")


def test_catalogue_scene_holds_the_world_angular_velocity():
    """catalogue/body_twist: the lower rod's world omega_y = shoulder + elbow rates = -1 rad/s every step."""
    sim = Simulator.load("catalogue/body_twist")
    for _ in range(300):
        r = sim.step()
        assert r.diagnostics.violation_vel < 1e-10
        assert abs(sim.joint_velocities().sum() + 1.0) < 1e-10
    w = r.body_wrenches["lower"]
    assert np.all(np.delete(w, 1) == 0.0) and np.isfinite(w[1])


# -- timed components (time functions of the scene grammar, evaluated at t_k+1)
A_W, F_W = 2.0, 0.8  # omega_y(t) = A sin(2 pi f t) [rad/s]
OMEGA = {"type": "sine", "amplitude": A_W, "frequency": F_W}


def test_timed_body_twist_equals_the_joint_velocity_law_with_the_same_function():
    """omega_y(t) of the rod (a sine time function) = the hinge following q_p(t) with b = 0, whose row is
    qdot_p(t_k+1) = A sin(2 pi f t_k+1) exactly: the same rows, so the same motion to round-off and the
    wrench's torque equal to the joint's required torque; measured max |dq| 0 and |w_y - effort| < 1e-9."""
    a, b = Simulator.load("catalogue/revolute"), Simulator.load("catalogue/revolute")
    a.prescribe_bodies({"rod": {"angular": [None, OMEGA, None]}})
    w = 2 * np.pi * F_W
    q0 = float(b.state.q[0])
    b.prescribe_joints({"hinge": {"position": {"type": "sine", "amplitude": A_W / w, "frequency": F_W,
                                               "phase": -np.pi / 2, "offset": q0 + A_W / w}, "b": 0.0}})
    for _ in range(600):
        t1 = a.state.time_after(a.dt)
        assert a.prescribed_bodies()["rod"]["values"][0] == pytest.approx(A_W * np.sin(w * t1), abs=1e-15)
        ra, rb = a.step(), b.step()
        assert abs(ra.v[0] - A_W * np.sin(w * ra.t)) < 1e-12
        assert np.abs(ra.q - rb.q).max() < 1e-12
        assert abs(ra.body_wrenches["rod"][1] - rb.effort[0]) < 1e-9


def test_timed_twist_in_a_scene_and_mixed_components():
    """prescribed.bodies.<body> with a time function next to constants: the free box's body omega follows
    [0.5, ramp, 0] exactly (one step's value at t_k+1) and the scene and the API give the same steps."""
    ramp = {"type": "ramp", "start": 0.0, "end": 0.2, "to": 1.5}
    d = raw("free3d")
    d["joints"][0]["conserve_momentum"] = False
    d["prescribed"] = {"bodies": {"box": {"angular": [0.5, ramp, 0.0]}}}
    a = Simulator(scene_from_dict(d, str(CAT / "free3d.yaml"), base_dir=CAT))
    b = free_box()
    b.prescribe_bodies({"box": {"angular": [0.5, ramp, 0.0]}})
    for _ in range(300):
        ra, rb = a.step(), b.step()
        assert np.array_equal(ra.q, rb.q)
        assert np.abs(twist(a, "box", "body")[:3] - [0.5, min(1.5, 7.5 * ra.t), 0.0]).max() < 1e-10
    a.prescribe_bodies({"box": {"linear": [1.0, 0.0, 0.0]}})
    a.restore_prescriptions(bodies=["box"])
    assert a.prescribed_bodies()["box"]["values"].tolist() == [0.5, 1.5, 0.0]


BAD_TF = [({"type": "wobble"}, "'angular\\[1\\]': unknown time function type 'wobble'"),
          ({"type": "sine", "amplitude": float("nan"), "frequency": 1.0}, "'angular\\[1\\].amplitude' must be finite"),
          ({"type": "ramp", "start": 1.0, "end": 0.5, "to": 1.0}, "'angular\\[1\\]': ramp end"),
          ({"type": "sine", "amplitude": 1.0}, "missing 'frequency'")]


@pytest.mark.parametrize("tf,match", BAD_TF, ids=[m for _, m in BAD_TF])
def test_bad_time_function_is_a_command_or_scene_error_naming_body_and_component(tf, match):
    sim = Simulator.load("catalogue/revolute")
    sim.prescribe_bodies({"rod": {"angular": [None, 1.0, None]}})
    before = sim.prescribed_bodies()
    with pytest.raises(CommandError, match="body 'rod'") as e:
        sim.prescribe_bodies({"rod": {"angular": [None, tf, None]}})
    assert e.match(match)
    assert sim.prescribed_bodies()["rod"]["values"].tolist() == before["rod"]["values"].tolist() == [1.0]
    d = raw("revolute")
    d["prescribed"] = {"bodies": {"rod": {"angular": [None, tf, None]}}}
    with pytest.raises(SceneError, match="prescribed.bodies.rod") as e:
        scene_from_dict(d)
    assert e.match(match)
