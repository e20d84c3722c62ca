"""The reparameterisation threshold of exponential-coordinate joints (issue 13 item 6; notes §2.5.8,
Grassia 1998): q <- (1 - 2 pi/||q||) q, qdot <- S(q_new)^-1 S(q) qdot when ||q|| > reparam_threshold
(default pi; the RedMax reference uses 1.5 pi), a joint key of spherical_exp in [pi, 2 pi).

Checked on catalogue/spherical_exp (a top spinning at 8 rad/s): the coordinates reach the given
threshold and never pass it; each reparameterisation happens at the first step whose norm would exceed
it (the norm before the map, 2 pi - ||q_new||, lies between the threshold and the previous norm plus one
step); the rotation and the angular velocity S(q) qdot are continuous across it (their jumps no larger than
an ordinary step's change); the motion agrees with the default threshold's to O(h); SceneErrors.
"""
import math

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.geometry import joints as jt

THR = 1.5 * math.pi


def run(thr, h=1e-3, T=2.0):
    ov = [f"dt={h}"] + ([] if thr is None else [f"joints.ball.reparam_threshold={thr!r}"])
    sim = Simulator.load("catalogue/spherical_exp", ov)
    m = sim.mech.extras.maps.items[0]
    G, W, R = [], [], []
    for _ in range(int(round(T / h))):
        sim.step()
        g = sim.state.q[m.gq].copy()
        v = sim.joint_velocities()
        gd = v[m.gv].copy()
        Rg, Sw, _ = jt.exp_jacobian(g)
        G.append(g)
        W.append(Sw @ gd)  # body angular velocity S(q) qdot (Eq. 2.49)
        assert np.abs(W[-1] - v[m.cv]).max() < 1e-9 * max(np.abs(W[-1]).max(), 1.0)  # = the carrier's
        R.append(Rg)
        assert np.abs(Rg - pin.Quaternion(sim.state.q[m.cq]).matrix()).max() < 1e-12  # carrier = exp(q)
    return np.array(G), np.array(W), np.array(R), sim


def angle(Ra, Rb):
    return float(np.linalg.norm(pin.log3(Ra.T @ Rb)))


def test_reparameterisation_at_the_threshold_and_continuous():
    h = 1e-3
    G, W, R, sim = run(THR, h)
    assert sim.spec.joints[0].extra["reparam_threshold"] == THR
    n = np.linalg.norm(G, axis=1)
    dn = np.abs(np.diff(n))
    jumps = np.flatnonzero(np.linalg.norm(np.diff(G, axis=0), axis=1) > 1.0) + 1
    ordinary = np.setdiff1d(np.arange(1, len(G)), jumps)
    step = dn[ordinary - 1].max()  # the largest change of ||q|| in an ordinary step
    assert len(jumps) >= 2, len(jumps)
    assert n.max() <= THR + 1e-12 and n.max() > THR - 1.01 * step and n.max() > math.pi + 1.0, (n.max(), step)
    for k in jumps:
        pre = 2 * math.pi - n[k]  # ||q|| before the map (||q_new|| = 2 pi - ||q||)
        assert THR < pre <= n[k - 1] + 1.01 * step, (k, pre, n[k - 1])
    rot = np.array([angle(R[k - 1], R[k]) for k in range(1, len(R))])
    dw = np.linalg.norm(np.diff(W, axis=0), axis=1)
    assert rot[jumps - 1].max() <= 1.01 * rot[ordinary - 1].max(), (rot[jumps - 1], rot[ordinary - 1].max())
    assert dw[jumps - 1].max() <= 1.01 * dw[ordinary - 1].max(), (dw[jumps - 1], dw[ordinary - 1].max())
    assert np.linalg.norm(run(None, h, 0.5)[0], axis=1).max() <= math.pi + 1e-12  # default: at pi


def test_threshold_changes_the_motion_only_at_order_h():
    diffs = []
    for h in (2e-3, 1e-3):
        _, _, R1, _ = run(THR, h, 1.0)
        _, _, R0, _ = run(None, h, 1.0)
        diffs.append(max(angle(a, b) for a, b in zip(R0, R1)))
    assert diffs[1] < 1e-2 and diffs[1] < 0.6 * diffs[0], diffs


@pytest.mark.parametrize("value,msg", [("3.0", r"'reparam_threshold' must be in \[pi, 2 pi\)"),
                                       ("6.2832", r"'reparam_threshold' must be in \[pi, 2 pi\)"),
                                       ("fast", r"'reparam_threshold' must be a number")])
def test_bad_threshold_raises_scene_error(value, msg):
    with pytest.raises(SceneError, match=r"joints\[0\] 'ball'.*" + msg):
        Simulator.load("catalogue/spherical_exp", [f"joints.ball.reparam_threshold={value}"])


def test_threshold_only_on_exponential_coordinates():
    with pytest.raises(SceneError, match=r"joints\[0\] 'ball'.*unknown key.*reparam_threshold"):
        Simulator.load("catalogue/spherical_euler", ["joints.ball.reparam_threshold=4.7"])
