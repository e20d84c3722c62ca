"""redmax_ros/node/robot_model.py without ROS: the URDF of every shipped scene, its kinematics
against the core, the frames the node puts on /tf and /tf_static, mimic tags of couplings, and the
body twists (issue 18, point 2)."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import Simulator, State, list_scenes
from redmax_ros.node.robot_model import BodyPoses, BodyTwists, Frames, quaternions, urdf_text

SCENES = list_scenes()
TREE_1DOF = ["pendulum", "chain", "slider_crank", "catalogue/fixed", "catalogue/composite_body", "bridge",
             "klann_leg", "fourbar", "catalogue/prismatic", "catalogue/gear", "catalogue/trajectory"]


def _stepped(name, n=40):
    sim = Simulator.load(name)
    sim.step(n)
    return sim


def _se3(pose):
    return pin.XYZQUATToSE3(np.r_[pose[0], pose[1]])


@pytest.mark.parametrize("scene", SCENES)
def test_urdf_parses_and_frames_compose_to_the_core_poses(scene):
    sim = _stepped(scene, 5)
    text = urdf_text(sim)
    root = ET.fromstring(text.split("\n", 1)[1])
    links = {e.get("name") for e in root.findall("link")}
    assert set(sim.mech.bodies) | {"world"} <= links
    pin.buildModelFromXML(text)  # a URDF Pinocchio (and so robot_state_publisher's parser family) reads
    fr = Frames(sim)
    poses = sim.body_poses()
    W = {"world": pin.SE3.Identity(), **{b: _se3(poses[b]) for b in fr.moving}}
    for parent, child, p, q in fr.static:  # parents first (tree order)
        W[child] = W[parent] * pin.XYZQUATToSE3(np.r_[p, q])
    assert links <= set(W)  # every URDF link has a frame
    for b, pose in poses.items():
        assert np.max(np.abs(W[b].homogeneous - _se3(pose).homogeneous)) <= 1e-12, b


@pytest.mark.parametrize("scene", TREE_1DOF)
def test_urdf_kinematics_equal_the_core(scene):
    """Revolute, prismatic and fixed joints: the URDF's forward kinematics at the core's joint values
    give the core's body poses (1e-12)."""
    sim = _stepped(scene)
    model = pin.buildModelFromXML(urdf_text(sim))
    data = model.createData()
    q = pin.neutral(model)
    for j in sim.mech.joints:
        jm = model.joints[model.getJointId(j.name)]
        a = sim.state.q[j.idx_q]
        if jm.nq == 2:  # continuous: (cos, sin)
            q[jm.idx_q:jm.idx_q + 2] = [np.cos(a), np.sin(a)]
        else:
            q[jm.idx_q] = a
    pin.framesForwardKinematics(model, data, q)
    for b, pose in sim.body_poses().items():
        assert np.max(np.abs(data.oMf[model.getFrameId(b)].homogeneous - _se3(pose).homogeneous)) <= 1e-12, b


def test_couplings_become_mimic_tags_that_hold():
    sim = _stepped("hand", 200)
    root = ET.fromstring(urdf_text(sim).split("\n", 1)[1])
    mimics = {j.get("name"): j.find("mimic") for j in root.findall("joint") if j.find("mimic") is not None}
    assert set(mimics) == {"index_dip", "middle_dip", "ring_dip", "little_dip"}
    q = dict(zip(sim.describe().position_names, sim.state.q))
    for name, m in mimics.items():
        lead = m.get("joint")
        assert lead == name.replace("dip", "pip")
        assert abs(q[name] - (float(m.get("multiplier")) * q[lead] + float(m.get("offset")))) <= 1e-9


def test_loops_are_noted_and_universal_joints_are_floating():
    text = urdf_text(Simulator.load("klann_leg"))
    assert text.count("<!-- loop closure") == 2
    root = ET.fromstring(urdf_text(Simulator.load("hand")).split("\n", 1)[1])
    types = {j.get("name"): j.get("type") for j in root.findall("joint")}
    assert types["wrist"] == "floating"


def test_floating_bases():
    assert Frames(Simulator.load("klann")).floating == ["chassis"]
    assert Frames(Simulator.load("mass_springs")).floating == ["box0", "box1", "box2"]
    assert Frames(Simulator.load("hand")).floating == []


@pytest.mark.parametrize("scene", ["branching", "hand", "incline", "klann_leg"])
def test_body_twists_match_finite_differences_of_the_poses(scene):
    """World-frame twist of each body frame against central differences of the core's body poses
    along the exact velocity (q +- eps qdot), O(eps^2)."""
    sim = _stepped(scene, 30)
    mech = sim.mech
    q, v = sim.state.q.copy(), sim.joint_velocities()
    R0 = {b: _se3(pose).rotation for b, pose in sim.body_poses().items()}
    tw = BodyTwists(mech)(q, v, list(mech.bodies))
    eps = 1e-6
    qp, qm = pin.integrate(mech.model, q, eps * v), pin.integrate(mech.model, q, -eps * v)
    sim.set_state(State(sim.time, qp, sim.state.v))
    plus = sim.body_poses()
    sim.set_state(State(sim.time, qm, sim.state.v))
    minus = sim.body_poses()
    for b in mech.bodies:
        Xp, Xm = _se3(plus[b]), _se3(minus[b])
        lin = (Xp.translation - Xm.translation) / (2 * eps)
        ang = pin.log3(Xp.rotation @ Xm.rotation.T) / (2 * eps)
        assert np.max(np.abs(lin - tw[b][0])) <= 1e-6 * max(1.0, np.abs(lin).max()), b
        assert np.max(np.abs(ang - tw[b][1])) <= 1e-6 * max(1.0, np.abs(ang).max()), b
        # body-frame components: R^T times the world ones
        assert np.max(np.abs(tw[b][2] - R0[b].T @ tw[b][0])) <= 1e-12, b
        assert np.max(np.abs(tw[b][3] - R0[b].T @ tw[b][1])) <= 1e-12, b


@pytest.mark.parametrize("scene", SCENES)
def test_fast_body_poses_equal_the_core(scene):
    """BodyPoses (what /tf carries) against the core's Simulator.body_poses: 1e-12 (the quaternion up to sign)."""
    sim = _stepped(scene, 20)
    names = list(sim.mech.bodies)
    P, Q = BodyPoses(sim.mech, names)(sim.state.q)
    for b, p, q in zip(names, P, Q):
        p0, q0 = sim.body_poses()[b]
        assert np.max(np.abs(p - p0)) <= 1e-12
        assert min(np.max(np.abs(q - q0)), np.max(np.abs(q + q0))) <= 1e-12


def test_quaternions_of_rotation_matrices():
    rng = np.random.default_rng(0)
    Rs = [pin.exp3(rng.normal(size=3)) for _ in range(200)]
    Rs += [pin.exp3(np.pi * a / np.linalg.norm(a)) for a in rng.normal(size=(20, 3))]  # 180 degrees
    Rs += [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    Q = quaternions(np.array(Rs))
    for R, q in zip(Rs, Q):
        assert np.max(np.abs(pin.Quaternion(q[3], q[0], q[1], q[2]).toRotationMatrix() - R)) <= 1e-14
