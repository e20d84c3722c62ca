"""Cyclic spline curve joints (``cyclic: true``, issue 13 item 6; notes §2.5.12, Eq. 2.71-2.74, Alg. 3):
the control frames wrap around, segment i = floor(s) mod n uses C_i .. C_{i+3} (indices mod n),
Q(s + n) = Q(s) for all real s.

Checked: periodicity; continuity of Q, S and dS/ds across the wrap (s = 0 = n) and at every other
segment join; S and dS/ds against central finite differences of Q and S (1e-7) on both sides of the wrap
and in other periods; the curve equals today's workaround (the first three frames repeated at the end)
on [0, n]; the catalogue scene laps the loop (s passes n several times) with a continuous motion and
the carrier on the curve; SceneErrors.
"""
import numpy as np
import pinocchio as pin
import pytest
import yaml

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.geometry import joints as jt
from redmax_ros.core.geometry.spline_joints import SplineCurve
from redmax_ros.core.scene.loader import scene_from_dict
from redmax_ros.core.spatial import placement
from pathlib import Path

CAT = Path(__file__).resolve().parents[3] / "scenes" / "catalogue"
RAW = yaml.safe_load((CAT / "spline_loop.yaml").read_text())
RNG = np.random.default_rng(11)


def frames(raw=RAW):
    return [placement(np.array(f["pos"], float), np.array(f.get("rpy", [0, 0, 0]), float))
            for f in raw["joints"][0]["control_frames"]]


def curve():
    return SplineCurve(frames(), cyclic=True)


def test_periodic_in_s():
    c, n = curve(), len(RAW["joints"][0]["control_frames"])
    for s in np.r_[RNG.uniform(-20, 20, 20), 0.0, 3.0, n - 1e-9]:
        for p in (-2, 1, 3):
            Q, S, dS = c.eval(s)
            Q2, S2, dS2 = c.eval(s + p * n)
            assert np.abs(Q.homogeneous - Q2.homogeneous).max() < 1e-11
            assert np.abs(S - S2).max() < 1e-10 and np.abs(dS - dS2).max() < 1e-9


@pytest.mark.parametrize("join", [0.0, 1.0, 4.0, 7.0, 8.0, -8.0])
def test_continuity_at_joins_and_the_wrap(join):
    """Q, S, dS/ds continuous (C2: the limits from both sides agree, differences O(eps)) at segment joins;
    8 and 0 are the wrap-around (segment 7 uses frames 7, 0, 1, 2)."""
    c = curve()
    for eps in (1e-6, 1e-8):
        Qa, Sa, dSa = c.eval(join - eps)
        Qb, Sb, dSb = c.eval(join + eps)
        assert np.linalg.norm(jt.log6(Qa.inverse() * Qb)) < 3 * eps * np.abs(Sa).max()
        assert np.abs(Sa - Sb).max() < 3 * eps * np.abs(dSa).max() + 1e-12
        assert np.abs(dSa - dSb).max() < 1e-5  # dS is C0 (its derivative, the third one, jumps)


@pytest.mark.parametrize("s", [-1e-3, 1e-3, 7.999, 8.0, 8.001, 15.5, -3.3, 0.5, 6.7])
def test_S_and_dS_finite_differences(s):
    """S = [Q^-1 dQ/ds] (central differences of log(Q(s)^-1 Q(s +- e))) and dS/ds (central differences
    of S), within 1e-7, on both sides of the wrap and in other periods."""
    c, e = curve(), 1e-5
    Q, S, dS = c.eval(s)
    Sfd = (jt.log6(Q.inverse() * c.eval(s + e)[0]) - jt.log6(Q.inverse() * c.eval(s - e)[0])) / (2 * e)
    dSfd = (c.eval(s + e)[1] - c.eval(s - e)[1]) / (2 * e)
    assert np.abs(S[:, 0] - Sfd).max() < 1e-7 * max(np.abs(S).max(), 1.0), np.abs(S[:, 0] - Sfd).max()
    assert np.abs(dS - dSfd).max() < 1e-7 * max(np.abs(dS).max(), 1.0), np.abs(dS - dSfd).max()


def test_equals_the_repeated_frames_workaround():
    """Today's workaround: the frames C_0..C_{n-1}, C_0, C_1, C_2 (non-cyclic, domain [0, n]) give the
    same Q, S, dS on [0, n] to round-off."""
    Ms = frames()
    c, w = curve(), SplineCurve(Ms + Ms[:3])
    assert w.domain == (0.0, float(len(Ms)))
    for s in np.r_[np.linspace(0, len(Ms), 41), RNG.uniform(0, len(Ms), 20)]:
        a, b = c.eval(s), w.eval(s)
        assert np.abs(a[0].homogeneous - b[0].homogeneous).max() < 1e-12
        assert np.abs(a[1] - b[1]).max() < 1e-11 and np.abs(a[2] - b[2]).max() < 1e-10


def test_scene_laps_the_loop_continuously():
    sim = Simulator.load("catalogue/spline_loop")
    m = sim.mech.extras.maps.items[0]
    geo = sim.spec.joints[0].extra["geometry"]
    assert geo.cyclic and np.isinf(sim.spec.joints[0].lower).all() and np.isinf(sim.spec.joints[0].upper).all()
    h = sim.dt
    x = sim.body_poses()["cart"][0].copy()
    s_prev, big, wraps = float(sim.state.q[m.gq][0]), 0.0, 0
    for _ in range(3000):
        sim.step()
        s = float(sim.state.q[m.gq][0])
        wraps += int(np.floor(s / 8) > np.floor(s_prev / 8))
        x1 = sim.body_poses()["cart"][0].copy()
        speed = np.linalg.norm(geo.eval(s)[1][:3, 0]) * abs(sim.joint_velocities()[m.gv][0])
        big = max(big, np.linalg.norm(x1 - x) / (h * speed))
        Q = geo.eval(s)[0]  # the carrier (the body) sits exactly on Q(s)
        assert np.abs(Q.translation - x1).max() < 1e-9  # body frame = joint frame (no body_placement)
        x, s_prev = x1, s
    assert wraps >= 4, wraps
    assert big < 1.05, big  # per-step displacement ~ |dx/ds| |sdot| h, also at every wrap


def test_bad_cyclic_raises_scene_error():
    with pytest.raises(SceneError, match=r"joints\[0\] 'loop'.*'cyclic' must be true or false"):
        Simulator.load("catalogue/spline_loop", ["joints.loop.cyclic=maybe"])
    d = yaml.safe_load((CAT / "spline_loop.yaml").read_text())
    d["joints"][0]["control_frames"].append(dict(d["joints"][0]["control_frames"][0]))
    with pytest.raises(SceneError, match=r"joints\[0\] 'loop'.*do not repeat the first control frame"):
        scene_from_dict(d, str(CAT / "spline_loop.yaml"), base_dir=CAT)
    with pytest.raises(SceneError, match=r"joints\[0\] 'bowl'.*unknown key.*cyclic"):  # curves only
        Simulator.load("catalogue/spline_surface", ["joints.bowl.cyclic=true"])
