"""step/compiled/poses.BodyFrames (what the node's /tf is built from): every body's world frame at a configuration
in one compiled call, against the core's Simulator.body_poses (Pinocchio-free recursive kinematics, quaternions
by Pinocchio) on every shipped scene, at the initial state and at a random configuration; scenes with joints
the compiled path does not take get none."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import BodyFrames, Simulator, State, body_frames, list_scenes
from redmax_ros.core.step.compiled.model import unsupported

SCENES = [s for s in list_scenes() if s != "umbrella"]  # umbrella: ~1 s of load, the bridge's joints


def _rotation(quat_xyzw):
    x, y, z, w = quat_xyzw
    return pin.Quaternion(w, x, y, z).toRotationMatrix()


@pytest.mark.parametrize("scene", SCENES)
def test_body_frames_equal_the_core_poses(scene):
    sim = Simulator.load(scene)
    names = list(sim.mech.bodies)
    frames = body_frames(sim.mech, names)
    if frames is None:  # joints outside the compiled path: the caller keeps Pinocchio
        assert sim.mech.extras is not None or any(w.startswith("joint types") for w in unsupported(sim.mech))
        return
    rng = np.random.default_rng(7)
    q_random = pin.integrate(sim.mech.model, sim.state.q, 0.7 * rng.standard_normal(sim.mech.nv))
    for q in (sim.state.q, q_random):
        sim.set_state(State(sim.state.t, q, np.zeros(sim.mech.ndof)))
        P, R = frames(q)
        core = sim.body_poses()
        for k, b in enumerate(names):
            p0, q0 = core[b]
            assert np.max(np.abs(P[k] - p0)) <= 1e-12, (scene, b)
            assert np.max(np.abs(R[k] - _rotation(q0))) <= 1e-12, (scene, b)
            assert np.max(np.abs(R[k] @ R[k].T - np.eye(3))) <= 1e-12, (scene, b)


def test_catalogue_joints_have_no_body_frames_and_bad_lengths_are_named():
    """A spline joint (catalogue, outside the compiled path): None. A configuration of the wrong length: ValueError."""
    assert body_frames(Simulator.load("catalogue/spline_curve").mech, []) is None
    sim = Simulator.load("hand")
    frames = BodyFrames(sim.mech, list(sim.mech.bodies)[:3])
    with pytest.raises(ValueError, match="nq"):
        frames(np.zeros(sim.mech.nq + 1))
