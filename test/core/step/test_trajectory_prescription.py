"""Time-varying joint prescriptions (issue 13 item 3): a joint follows a position trajectory q_p(t) with the
velocity-level law of hybrid dynamics (notes §2.10, Eq. 2.114 with the velocity prescribed; paper Eq. 7:
*G_r qdot_r = *qdot_r) whose right-hand side is qdot_p(t_k+1) + b (q_p(t_k+1) - q_k) each step
(scene/timefunctions.JointTrajectory, step/trajectory.py). The rows, and so the required torques (Eq. 7,
effort = tau - *G_r^T lam / h), are those of velocity prescriptions.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import CommandError, SceneError, Simulator, load_scene, scene_from_dict
from redmax_ros.core.scene import timefunctions
from redmax_ros.core.scene.loader import parse_joint_trajectory

A, F = 0.4, 0.5  # q_p(t) = A sin(2 pi F t) [rad]
W = 2 * math.pi * F
SINE = {"type": "sine", "amplitude": A, "frequency": F}


def pendulum(h, b=5.0, position=SINE, scene="pendulum", joint="hinge", *ov):
    sim = Simulator.load(scene, [f"dt={h}", *ov])
    sim.prescribe_joints({joint: {"position": position, "b": b}})
    return sim


def track(sim, T, dof=0):
    """(t, q, v, effort) of dof after each step up to T."""
    out = []
    for _ in range(int(round(T / sim.dt))):
        r = sim.step()
        out.append((r.t, r.q[dof], r.v[dof], r.effort[dof]))
    return np.array(out).T


@pytest.mark.parametrize("scene,joint,dof,ov", [("pendulum", "hinge", 0, ()), ("chain", "j1", 1, ("params.n=3",))])
def test_sine_tracking_error_is_first_order(scene, joint, dof, ov):
    """b = 5: after the transient (t > 2 s = 10 / b) the position error max|q - q_p| is O(h) and halves with
    h (e' + b e = h (b qdot_p + qddot_p / 2) to leading order: amplitude h A W sqrt(b^2 + W^2 / 4) /
    sqrt(b^2 + W^2) = 1.115 h here); measured max error
    pendulum 2.24e-3, 1.12e-3, 5.67e-4 rad (1.12-1.13 h), chain j1 2.23e-3, 1.12e-3, 5.58e-4 rad at h = 2, 1,
    0.5 ms."""
    errs = []
    for h in (2e-3, 1e-3, 5e-4):
        t, q, _, _ = track(pendulum(h, 5.0, SINE, scene, joint, *ov), 4.0, dof)
        late = t > 2.0
        errs.append(np.abs(q - A * np.sin(W * t))[late].max())
        assert errs[-1] < 2.0 * A * W * h  # bounded by a few h qdot_p
    assert 1.8 < errs[0] / errs[1] < 2.2 and 1.8 < errs[1] / errs[2] < 2.2, errs


def test_data_free_backends_take_the_same_rows():
    """The trajectory only changes the right-hand side of the prescribed rows, so the data-free PCG and dense
    paths (step/data_free_stages.py) step the same motion as the Pinocchio pipeline."""
    runs = {}
    for solver in ("direct", "pcg"):
        sim = Simulator.load("chain", ["dt=0.001", "params.n=3", f"solver={solver}"])
        sim.prescribe_joints({"j1": {"position": SINE, "b": 5.0}})
        runs[solver] = track(sim, 0.5, 1)
    assert sim.backend.name == "pcg"
    assert np.abs(runs["direct"][1] - runs["pcg"][1]).max() < 1e-8
    assert np.abs(runs["direct"][3] - runs["pcg"][3]).max() < 1e-5 * np.abs(runs["direct"][3]).max()


def test_without_feedback_velocity_is_tracked_exactly():
    """b = 0: qdot_k+1 = qdot_p(t_k+1) to round-off at every step (the row is an ordinary velocity row;
    measured 2.2e-16 rad/s); the initial offset q(0) - q_p(0) = 0.3 rad is kept (no position feedback)."""
    t, _, v, _ = track(pendulum(1e-3, 0.0), 2.0)
    assert np.abs(v - A * W * np.cos(W * t)).max() < 1e-10


def test_feedback_removes_an_initial_offset():
    """The pendulum starts at 0.3 rad, q_p(0) = 0: with b = 5 the error decays like (1 - b h)^k to O(h)."""
    t, q, _, _ = track(pendulum(1e-3, 5.0), 3.0)
    e = np.abs(q - A * np.sin(W * t))
    assert e[0] > 0.29 and e[t > 2.5].max() < 2 * A * W * 1e-3


def test_quintic_ramp_ends_at_rest_at_its_end_position():
    """quintic 0.3 -> 1.0 rad over [0, 0.5] s: after it the joint holds 1.0 rad with zero velocity (error
    decays as (1 - b h)^k once q_p is constant); the profile has zero rate at both ends."""
    ramp = {"type": "quintic", "start": 0.0, "end": 0.5, "from": 0.3, "to": 1.0}
    f = timefunctions.parse(_V(), "e", "k", ramp)
    assert f.derivative(0.0) == 0.0 and f.derivative(0.5) == 0.0 and f(0.5) == 1.0
    sim = pendulum(1e-3, 5.0, ramp)
    t, q, v, tau = track(sim, 3.0)
    assert abs(q[-1] - 1.0) < 1e-6 and abs(v[-1]) < 1e-5
    # held against gravity: the required torque is m g l_c sin q at rest (1.25 kg, l_c = 0.25 m)
    assert tau[-1] == pytest.approx(1.25 * 9.81 * 0.25 * math.sin(q[-1]), rel=1e-4)


def test_required_torque_is_inverse_dynamics_of_the_tracked_motion():
    """effort (Eq. 7) = pin.rnea(q_p, qdot_p, qddot_p) of the prescribed motion to O(h) (after the
    transient); measured max difference 1.26e-3, 6.3e-4, 3.2e-4 N m at h = 2, 1, 0.5 ms (0.63 h N m/s),
    torques up to 1.26 N m after the transient."""
    diffs = []
    for h in (2e-3, 1e-3, 5e-4):
        sim = pendulum(h, 5.0)
        model = sim.mech.model
        data = model.createData()
        t, _, _, tau = track(sim, 4.0)
        ref = np.array([pin.rnea(model, data, np.array([A * math.sin(W * s)]), np.array([A * W * math.cos(W * s)]),
                                 np.array([-A * W * W * math.sin(W * s)]))[0] for s in t])
        diffs.append(np.abs(tau - ref)[t > 2.0].max())
    assert diffs[0] < 0.05 and 1.7 < diffs[0] / diffs[1] < 2.3 and 1.7 < diffs[1] / diffs[2] < 2.3, diffs


def test_chain_effort_is_rnea_of_the_simulated_motion():
    """Chain, j1 prescribed, j0 and j2 free: rnea(q_k+1, v_k+1, (v_k+1 - v_k) / h) gives the effort on j1
    and ~0 on the free joints to O(h)."""
    sim = pendulum(1e-3, 5.0, SINE, "chain", "j1", "params.n=3")
    model = sim.mech.model
    data = model.createData()
    v_prev = sim.joint_velocities()
    worst = np.zeros(3)
    for _ in range(1500):
        r = sim.step()
        tau_id = pin.rnea(model, data, r.q, r.v, (r.v - v_prev) / sim.dt)
        v_prev = r.v.copy()
        worst = np.maximum(worst, np.abs(tau_id - r.effort))
    scale = np.abs(r.effort[1]) + 0.1
    assert worst.max() < 0.05 * scale, worst


def test_scene_file_and_api_give_the_same_steps():
    """The scene grammar (prescribed.joints.<name>: {position, b}) and prescribe_joints are one thing."""
    spec = load_scene("pendulum", ["dt=0.001", "prescribed={joints: {hinge: {position: {type: sine, amplitude: 0.4, "
                                                "frequency: 0.5}, b: 5}}}"])
    a = Simulator(spec)
    b = pendulum(1e-3, 5.0)
    for _ in range(200):
        ra, rb = a.step(), b.step()
    assert np.array_equal(ra.q, rb.q) and np.array_equal(ra.effort, rb.effort)
    assert list(a.prescribed_joints()) == ["hinge"]  # the runner's tau:<joint> column
    a.release_joints(["hinge"])
    assert a.prescribed_joints() == {} and a.joint_trajectories() == {}
    a.restore_prescriptions(joints=["hinge"])
    assert list(a.joint_trajectories()) == ["hinge"]
    a.prescribe_joints({"hinge": 0.0})  # a velocity replaces the trajectory, and back
    assert a.joint_trajectories() == {} and a.prescribed_joints()["hinge"] == 0.0
    a.reset()
    assert list(a.joint_trajectories()) == ["hinge"]


def test_shipped_scene_follows_its_waypoints():
    """catalogue/trajectory: the shoulder on C2 cubic waypoints (b = 5) is within O(h) of q_p and at
    rest at 0 after the last waypoint."""
    sim = Simulator.load("catalogue/trajectory")
    tr = sim.joint_trajectories()["shoulder"]
    worst = 0.0
    for _ in range(2000):
        r = sim.step()
        worst = max(worst, abs(r.q[0] - tr.position(r.t)[0]))
    assert worst < 5e-3 and abs(r.q[0]) < 1e-4 and abs(r.v[0]) < 1e-3


class _V:
    """The scene validator's interface for timefunctions.parse, raising SceneError."""

    def err(self, entry, problem):
        raise SceneError("test", entry, problem)

    def number(self, entry, key, value, *, positive=False, nonneg=False):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.err(entry, f"'{key}' bad {value!r}")
        if nonneg and value < 0:
            self.err(entry, f"'{key}' negative")
        return float(value)

    def vector(self, entry, key, value, n, **kw):
        return np.array([self.number(entry, key, x) for x in value])

    def keys(self, entry, d, allowed, required=()):
        assert set(d) <= set(allowed) and set(required) <= set(d)


FUNCS = [SINE, {"type": "ramp", "start": 0.2, "end": 0.9, "from": -1.0, "to": 2.0},
         {"type": "table", "points": [[0, 0], [0.3, 1.0], [1.0, -0.5]]},
         {"type": "sigmoid", "center": 0.5, "width": 0.1, "from": 0.2, "to": 1.2},
         {"type": "quintic", "start": 0.1, "end": 0.8, "to": 1.5},
         {"type": "cubic", "points": [[0, 0], [0.4, 1.0], [0.7, 0.2], [1.2, 0.5]]},
         {"type": "cubic", "points": [[0, 0, 1.0], [0.5, 1.0, 0.0], [1.2, 0.5, -2.0]]},
         {"type": "sum", "terms": [SINE, {"type": "quintic", "start": 0, "end": 1, "to": 1}]},
         {"type": "product", "terms": [SINE, {"type": "sigmoid", "center": 0.5, "width": 0.2, "to": 1}]}]


@pytest.mark.parametrize("d", FUNCS, ids=lambda d: d["type"])
def test_time_function_derivative_matches_finite_differences(d):
    f = timefunctions.parse(_V(), "e", "k", d)
    for t in np.linspace(0.013, 1.17, 41):
        fd = (f(t + 1e-6) - f(t - 1e-6)) / 2e-6
        assert f.derivative(t) == pytest.approx(fd, rel=1e-5, abs=1e-5), t


@pytest.mark.parametrize("d", FUNCS, ids=lambda d: d["type"])
def test_value_rate_is_the_value_and_the_derivative_bit_for_bit(d):
    f = timefunctions.parse(_V(), "e", "k", d)
    for t in np.linspace(-0.2, 1.5, 53):
        assert f.value_rate(t) == (f(t), f.derivative(t)), t


def test_cubic_waypoints_interpolate_with_continuous_acceleration():
    pts = [[0, 0], [0.4, 1.0], [0.7, 0.2], [1.2, 0.5]]
    f = timefunctions.parse(_V(), "e", "k", {"type": "cubic", "points": pts})
    for t, y in pts:
        assert f(t) == pytest.approx(y, abs=1e-12)
    assert f.derivative(0.0) == 0.0 and f.derivative(1.2) == 0.0  # clamped at rest
    acc = lambda t: (f.derivative(t + 1e-7) - f.derivative(t - 1e-7)) / 2e-7  # noqa: E731
    for t in (0.4, 0.7):  # C2 at the interior knots
        left = (f.derivative(t - 1e-7) - f.derivative(t - 2e-7)) / 1e-7
        right = (f.derivative(t + 2e-7) - f.derivative(t + 1e-7)) / 1e-7
        assert left == pytest.approx(right, rel=1e-3, abs=1e-3) and np.isfinite(acc(t))


BAD = [({"position": SINE, "b": -1.0}, "'b'"),
       ({"position": {"type": "sine", "amplitude": float("nan"), "frequency": 1.0}}, "amplitude"),
       ({"position": {"type": "sine", "amplitude": float("inf"), "frequency": 1.0}}, "amplitude"),
       ({"position": {"type": "wobble", "amplitude": 1.0}}, "unknown time function type 'wobble'"),
       ({"position": SINE, "gain": 5}, "unknown key"),
       ({"b": 5}, "missing 'position'"),
       ({"position": {"type": "quintic", "start": 1.0, "end": 0.5, "to": 1.0}}, "must be after"),
       ({"position": {"type": "cubic", "points": [[0, 0], [0, 1]]}}, "strictly increasing"),
       ({"position": [SINE, SINE]}, "must have 1 entries")]


@pytest.mark.parametrize("d,words", BAD, ids=[w for _, w in BAD])
def test_bad_trajectory_command_raises_and_changes_nothing(d, words):
    sim = Simulator.load("catalogue/trajectory")
    sim.step(3)
    before_q, before_p, before_tr = sim.state.q.copy(), sim.prescribed_joints(), sim.joint_trajectories()
    with pytest.raises(CommandError) as e:
        sim.prescribe_joints({"elbow": 0.5, "shoulder": d})  # all-or-nothing: the valid elbow entry is not applied
    assert "shoulder" in str(e.value) and words in str(e.value)
    assert np.array_equal(sim.state.q, before_q) and sim.joint_trajectories() == before_tr
    assert {k: v.tolist() for k, v in sim.prescribed_joints().items()} == {k: v.tolist() for k, v in before_p.items()}


def test_unknown_or_unsuitable_joint_is_a_command_error():
    sim = Simulator.load("catalogue/trajectory")
    with pytest.raises(CommandError, match="unknown joint 'knee'"):
        sim.prescribe_joints({"knee": {"position": SINE}})
    sph = Simulator.load("catalogue/spherical_euler")  # Euler-chart joint: not a trajectory joint
    name = sph.mech.joints[0].name
    with pytest.raises(CommandError, match=f"joint '{name}' .*cannot follow a position trajectory"):
        sph.prescribe_joints({name: {"position": 0.0}})


@pytest.mark.parametrize("d,words", BAD[:5], ids=[w for _, w in BAD[:5]])
def test_bad_trajectory_in_a_scene_is_a_scene_error_naming_the_entry(d, words):
    raw = {"name": "p", "dt": 1e-3, "bodies": [{"name": "rod", "mass": 1.0, "inertia": [0.01, 0.01, 0.01, 0, 0, 0]}],
           "joints": [{"name": "hinge", "type": "revolute", "parent": "world", "child": "rod", "axis": "y"}],
           "prescribed": {"joints": {"hinge": d}}}
    with pytest.raises(SceneError) as e:
        scene_from_dict(raw, "p.yaml")
    assert "prescribed.joints.hinge" in str(e.value) and words in str(e.value)


def test_unknown_joint_in_a_scene_trajectory_is_a_scene_error():
    raw = {"name": "p", "dt": 1e-3, "bodies": [{"name": "rod", "mass": 1.0, "inertia": [0.01, 0.01, 0.01, 0, 0, 0]}],
           "joints": [{"name": "hinge", "type": "revolute", "parent": "world", "child": "rod", "axis": "y"}],
           "prescribed": {"joints": {"knee": {"position": SINE}}}}
    with pytest.raises(SceneError, match="prescribed.joints.*unknown joint 'knee'"):
        Simulator(scene_from_dict(raw, "p.yaml"))


def test_parse_joint_trajectory_default_gain():
    tr = parse_joint_trajectory("e", {"position": 0.5}, 1)
    assert tr.b == timefunctions.DEFAULT_GAIN == 5.0 and tr.position(3.0)[0] == 0.5


def test_redmax_run_reports_the_required_torque(tmp_path):
    """redmax_run takes a trajectory as a scene override and writes its tau:<joint> column (the effort)."""
    from redmax_ros.runner import main
    out = tmp_path / "p.csv"
    rc = main(["pendulum", "--duration", "0.6", "--quiet", "--out", str(out), "--set",
               "prescribed={joints: {hinge: {position: {type: quintic, start: 0, end: 0.5, from: 0.3, to: 1.0}}}}"])
    assert rc == 0
    header = out.read_text().splitlines()[0].split(",")
    rows = np.loadtxt(out, delimiter=",", skiprows=1)
    q, tau = rows[-1, header.index("q:hinge")], rows[-1, header.index("tau:hinge")]
    assert abs(q - 1.0) < 1e-3 and tau == pytest.approx(1.25 * 9.81 * 0.25 * math.sin(q), rel=0.05)


def test_continuous_revolute_follows_a_winding_trajectory(tmp_path):
    """A URDF 'continuous' joint (Pinocchio's unbounded revolute, q = (cos, sin)) follows q_p(t) = 2 pi t
    through several turns: the error q_p - q_k is taken in (-pi, pi] (unwrapped, the row would be ~ b 2 pi k
    after k turns), so the motion settles on the law's fixed point q_k = q_p(t_k + h), qdot = 2 pi."""
    (tmp_path / "wheel.urdf").write_text(
        '<robot name="w"><link name="base"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" '
        'ixy="0" ixz="0" iyz="0"/></inertial></link><link name="wheel"><inertial><origin xyz="0.1 0 0"/><mass value="1"/>'
        '<inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>'
        '<joint name="axle" type="continuous"><parent link="base"/><child link="wheel"/><axis xyz="0 1 0"/></joint></robot>')
    (tmp_path / "wheel.yaml").write_text(
        "name: wheel\nurdf: {file: wheel.urdf}\ndt: 0.001\n"
        "prescribed: {joints: {axle: {position: {type: ramp, start: 0, end: 10, to: 62.83185307179586}, b: 5}}}\n")
    sim = Simulator.load(str(tmp_path / "wheel.yaml"))
    j = sim.mech.joint_index["axle"]
    assert (j.nq, j.nv) == (2, 1)
    for _ in range(2500):  # 2.5 turns
        r = sim.step()
    assert r.v[0] == pytest.approx(2 * math.pi, abs=1e-6)  # (1 - b h)^k decay: 1.1e-7 after 2.5 s
    angle = math.atan2(r.q[j.idx_q + 1], r.q[j.idx_q])
    assert abs((angle - 2 * math.pi * (r.t + sim.dt) + math.pi) % (2 * math.pi) - math.pi) < 1e-6


@pytest.mark.parametrize("scene", ["prismatic", "translational", "universal", "planar_translation"])
def test_other_coordinate_joints_follow_per_dof_trajectories(scene):
    """One time function per DOF (a list) on the other joint types whose positions are coordinates: each
    DOF tracks q0_i + 0.05 sin(2 pi t) to O(h) (measured 2.31e-4 at h = 1 ms on every one: kinematic)."""
    sim = Simulator.load(f"catalogue/{scene}")
    j = next(j for j in sim.mech.joints if j.nv)
    sim.prescribe_joints({j.name: {"position": [{"type": "sine", "amplitude": 0.05, "frequency": 1.0,
                                                 "offset": float(sim.state.q[j.idx_q + i])} for i in range(j.nv)]}})
    tr = sim.joint_trajectories()[j.name]
    worst = 0.0
    for k in range(2000):
        r = sim.step()
        if k > 1000:
            worst = max(worst, np.abs(r.q[j.idx_q:j.idx_q + j.nq] - tr.position(r.t)).max())
    assert worst < 2 * 0.05 * 2 * math.pi * sim.dt
