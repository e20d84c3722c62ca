"""Joint friction geometry (issue 13 item 7; docs/friction.md "Joint friction model"): the box cross-section of
a prismatic joint (8 corners, two face normals each) and BISP friction on exponential-coordinate spherical
joints (spherical_exp, through the carrier's rows and J_rR, Eq. 9-10)."""
import math

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.friction.contact import box_section_axes, implicit_points, ls_operator
from redmax_ros.core.geometry import joints as jt
from redmax_ros.core.scene.contact_schema import JointFrictionSpec
from redmax_ros.core.scene.loader import scene_from_dict

G = 9.81
M = 2.0  # kg, the slider / pendulum bob


def _rail(phi_deg, theta_deg=0.0, mu=0.2, v0=0.0, force=0.0, size=(0.02, 0.03)):
    """A 2 kg ball (COM at the joint origin) on a box-section prismatic rail along the joint frame's x, the
    joint frame turned by roll phi about the rail (the box faces u1 = y, u2 = z at phi to the vertical)
    and pitched by theta (the rail slopes down along +x): in the joint frame gravity is
    g (sin th, -sin phi cos th, -cos phi cos th)."""
    raw = {"bodies": [{"name": "b", "mass": M, "shape": {"type": "sphere", "radius": 0.05}}],
           "joints": [{"name": "rail", "type": "prismatic", "axis": "x", "parent": "world", "child": "b",
                       "placement": {"rpy": [math.radians(phi_deg), math.radians(theta_deg), 0.0]},
                       "v0": v0, "torque": force,
                       "friction": {"mu": mu, "shape": "box", "size": list(size), "length": 0.04}}]}
    return Simulator(scene_from_dict(raw))


def _normal_sum(phi_deg, theta_deg=0.0):
    """N_total = m g cos th (|sin phi| + |cos phi|) [N]: the box carries each face's component of the load."""
    ph, th = math.radians(phi_deg), math.radians(theta_deg)
    return M * G * math.cos(th) * (abs(math.sin(ph)) + abs(math.cos(ph)))


def test_box_section_splits_a_force_over_the_two_faces():
    """Minimum-norm split (Eq. 16, eps -> 0) of a force F1 u1 + F2 u2 through the joint origin over the 16
    normals: F1/8 on each u1 normal, F2/8 on each u2 normal, so sum|alpha| = |F1| + |F2| (1e-6 relative at the
    default eps = 1e-6: measured deficit 2.5e-7 relative, the regularisation's), for the axes x, y, z and an
    oblique one (u1, u2, axis orthonormal)."""
    spec = JointFrictionSpec(0.2, 0.0, 0.04, 0, "box", np.array([0.02, 0.03]))
    for axis in (np.eye(3)[0], np.eye(3)[1], np.eye(3)[2], np.array([1.0, 2.0, 2.0]) / 3):
        u1, u2 = box_section_axes(axis)
        assert np.abs(np.array([u1, u2, axis]) @ np.array([u1, u2, axis]).T - np.eye(3)).max() < 1e-14
        P, Nn, rows = implicit_points("prismatic", axis, spec)
        assert P.shape == (16, 3) and len(rows) == 1 and rows[0][1] == list(range(16))
        L = ls_operator(P, Nn, np.diag([2.0, 2.0, 2.0, 1e-3, 2e-3, 3e-3]), 1e-6)
        for F1, F2 in ((5.0, 0.0), (3.0, -4.0), (-1.0, 2.5)):
            al = L @ np.concatenate([F1 * u1 + F2 * u2, np.zeros(3)])
            assert abs(np.abs(al).sum() - (abs(F1) + abs(F2))) < 1e-6 * (abs(F1) + abs(F2))
            assert np.abs(al[0::2] - F1 / 8 * (Nn[0::2] @ u1)).max() < 1e-6 * (abs(F1) + abs(F2))
            assert np.abs(al[1::2] - F2 / 8 * (Nn[1::2] @ u2)).max() < 1e-6 * (abs(F1) + abs(F2))


@pytest.mark.parametrize("phi", [0.0, 30.0, 45.0])
def test_box_rail_decelerates_at_the_coulomb_rate(phi):
    """Horizontal rail, the box turned by phi about it, the slider launched at 1.5 m/s: it decelerates at
    a = mu N_total / m = mu g (|sin phi| + |cos phi|) (the load along one face normal at phi = 0, on two faces
    otherwise; a cylinder would not depend on phi) until it stops, then stays (within 1 %)."""
    mu, v0 = 0.2, 1.5
    sim = _rail(phi, mu=mu, v0=v0)
    a_an = mu * _normal_sum(phi) / M
    t_stop = v0 / a_an
    n = int(0.9 * t_stop / sim.dt)
    x = np.empty(n)
    for k in range(n):
        r = sim.step()
        assert r.diagnostics.friction.converged
        x[k] = sim.state.q[0]
    t = sim.dt * (np.arange(n) + 1)
    a = -2 * np.polyfit(t, x, 2)[0]
    assert abs(a - a_an) < 0.01 * a_an, (a, a_an)
    sim.step(int(0.3 * t_stop / sim.dt))
    assert abs(sim.state.v[0]) < 1e-8


def test_box_rail_tilted_slides_with_the_incline_rate():
    """Rail pitched 30 deg down, box rolled 30 deg: a = g sin th - mu g cos th (|sin phi| + |cos phi|) (1 %),
    the catalogue scene prismatic_box_friction."""
    sim = Simulator.load("catalogue/prismatic_box_friction")
    mu, th, ph = 0.2, math.radians(30.0), math.radians(30.0)
    a_an = G * (math.sin(th) - mu * math.cos(th) * (math.sin(ph) + math.cos(ph)))
    n = 400
    x = np.empty(n)
    for k in range(n):
        sim.step()
        x[k] = sim.state.q[0]
    a = 2 * np.polyfit(sim.dt * (np.arange(n) + 1), x, 2)[0]
    assert abs(a - a_an) < 0.01 * a_an, (a, a_an)


@pytest.mark.parametrize("phi", [0.0, 30.0])
def test_box_rail_static_threshold(phi):
    """Axial force f on the horizontal rail: at rest at 0.98 mu N_total, sliding at 1.02 mu N_total."""
    f_s = 0.2 * _normal_sum(phi)
    for k, moves in ((0.98, False), (1.02, True)):
        sim = _rail(phi, force=k * f_s)
        for _ in range(100):
            r = sim.step()
        assert r.diagnostics.friction.converged
        assert (abs(sim.state.v[0]) > 1e-6) == moves, (phi, k, sim.state.v)


@pytest.mark.parametrize("friction,msg", [
    ({"mu": 0.2, "shape": "box"}, "missing 'size'"),
    ({"mu": 0.2, "shape": "box", "size": [0.02]}, "'size' must have 2 values"),
    ({"mu": 0.2, "shape": "box", "size": [0.02, -0.01]}, "must be positive"),
    ({"mu": 0.2, "shape": "box", "size": [0.02, 0.02], "radius": 0.01}, "unknown key"),
    ({"mu": 0.2, "shape": "hexagon", "radius": 0.01}, "'shape' must be one of cylinder, box"),
])
def test_bad_box_section_keys_are_named(friction, msg):
    raw = {"bodies": [{"name": "b", "mass": 1.0, "shape": {"type": "sphere", "radius": 0.1}}],
           "joints": [{"name": "rail", "type": "prismatic", "axis": "x", "parent": "world", "child": "b",
                       "friction": friction}]}
    with pytest.raises(SceneError, match=msg) as e:
        scene_from_dict(raw)
    assert "joints[0] 'rail' friction" in str(e.value)


def test_box_section_on_a_revolute_joint_is_named():
    raw = {"bodies": [{"name": "b", "mass": 1.0, "shape": {"type": "sphere", "radius": 0.1}}],
           "joints": [{"name": "pin", "type": "revolute", "axis": "x", "parent": "world", "child": "b",
                       "friction": {"mu": 0.2, "shape": "box", "size": [0.01, 0.01]}}]}
    with pytest.raises(SceneError, match="box cross-section.*prismatic joints, not revolute"):
        scene_from_dict(raw)


# ----------------------------------------------------------------------------------------------
# spherical_exp: the ball of the carrier's angular velocity, rows through J_rR


def _pendulum(jtype, q0, v0, mu=0.3, dt=1e-3):
    raw = {"dt": dt, "bodies": [{"name": "b", "mass": M, "shape": {"type": "box", "size": [0.05, 0.08, 0.3]}}],
           "joints": [{"name": "j", "type": jtype, "parent": "world", "child": "b", "q0": list(q0), "v0": list(v0),
                       "body_placement": {"pos": [0, 0, -0.2]}, "friction": {"mu": mu, "radius": 0.02}}]}
    return Simulator(scene_from_dict(raw))


def _pose_gap(a, b):
    return float(np.abs(np.concatenate(a.body_poses()["b"]) - np.concatenate(b.body_poses()["b"])).max())


def test_spherical_exp_friction_matches_the_quaternion_joint():
    """A frictional ball-joint pendulum (mu 0.3, r 2 cm) released at 0.8 rad about x: the rotation stays about
    x, where exp(g) with g + h gdot is exactly the quaternion update and Sdot gdot = 0, so the two
    coordinates give the same motion: body poses within 1e-8 over 300 steps (measured 5e-16), the same
    joint normal load (1e-8 relative) and the same velocity."""
    a, b = _pendulum("spherical", (0.8, 0, 0), (0, 0, 0)), _pendulum("spherical_exp", (0.8, 0, 0), (0, 0, 0))
    gap = 0.0
    for _ in range(300):
        ra, rb = a.step(), b.step()
        assert ra.diagnostics.friction.converged and rb.diagnostics.friction.converged
        gap = max(gap, _pose_gap(a, b))
    assert gap < 1e-8, gap
    na, nb = ra.diagnostics.friction.joint_normal["j"], rb.diagnostics.friction.joint_normal["j"]
    assert abs(na - nb) < 1e-8 * na and na > 1.0
    assert np.abs(a.state.v - b.state.v).max() < 1e-8  # gdot = w while g stays along x


def test_spherical_exp_friction_three_dimensional_motion_is_first_order_close():
    """A general 3D swing (g0 = (0.5, 0.3, 0.1), gdot0 = (0.5, -1, 2), the quaternion joint started at the same
    rotation and body angular velocity S(g0) gdot0): the two coordinates differ by their O(h) discretisation
    only, also with friction (the reaction includes M Jdot_rR qdot_R, Eq. 2.89): over 0.3 s the largest pose
    difference halves with h (ratio <= 0.55; measured 3.8e-5 -> 1.7e-5; without that term it stayed at 7.8e-3)."""
    g0, gd0 = np.array([0.5, 0.3, 0.1]), np.array([0.5, -1.0, 2.0])
    Q, S, _ = jt.ref_spherical_exp(g0, gd0)
    rpy, w0 = pin.rpy.matrixToRpy(Q.rotation), S[3:] @ gd0
    gaps = []
    for h in (1e-3, 5e-4):
        a, b = _pendulum("spherical", rpy, w0, dt=h), _pendulum("spherical_exp", g0, gd0, dt=h)
        assert _pose_gap(a, b) < 1e-15
        gap = 0.0
        for _ in range(int(round(0.3 / h))):
            a.step()
            b.step()
            gap = max(gap, _pose_gap(a, b))
        gaps.append(gap)
    assert gaps[0] < 1e-4 and gaps[1] <= 0.55 * gaps[0], gaps


def test_spherical_exp_static_friction_threshold():
    """The spherical joint's threshold (test_friction_contact.py) in exponential coordinates: the weight F
    loads the +-z points with |alpha| = F/2; a torque about x (the exp coordinates' generalized force at
    g = 0, and along g = theta x as long as it turns about x) starts it at mu r F: at rest at 0.98, turning at 1.02."""
    mu, r, F = 0.3, 0.01, M * G
    for k, moves in ((0.98, False), (1.02, True)):
        raw = {"bodies": [{"name": "b", "mass": M, "shape": {"type": "sphere", "radius": 0.05}}],
               "joints": [{"name": "j", "type": "spherical_exp", "parent": "world", "child": "b",
                           "torque": [k * mu * r * F, 0.0, 0.0], "friction": {"mu": mu, "radius": r}}]}
        sim = Simulator(scene_from_dict(raw))
        for _ in range(100):
            res = sim.step()
        assert res.diagnostics.friction.converged
        assert (np.abs(sim.state.v).max() > 1e-6) == moves, (k, sim.state.v)
