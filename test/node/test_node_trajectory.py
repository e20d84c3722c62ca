"""Position targets on joint_commands and trajectory_msgs/JointTrajectory on joint_trajectory (issue 18,
point 3): the node in-process, lockstep, scene chain (5 revolute joints).

Every published state and required torque is compared bitwise with a core Simulator given the same
prescription (the core's joint trajectory: piecewise-cubic q_p(t) through the waypoints, followed by
the velocity-level law qdot = qdot_p + b (q_p - q)); the tracking error is O(h) (halving h halves
it); replaying the required torques as applied torques on a fresh core reproduces the motion.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from node_fixtures import Client, run_node_in_thread  # noqa: F401  (first: skips without ROS)

from builtin_interfaces.msg import Duration  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from redmax_msgs.msg import Result, SimulationState  # noqa: E402
from redmax_ros.core import Simulator  # noqa: E402

NS = f"/trajectory{os.getpid()}"
H = 1e-3
B = 5.0  # position_gain (the default)
WAYPOINTS = [(0.2, 0.3, 0.0), (0.5, -0.2, -0.5), (0.8, 0.1, 0.0)]  # (time_from_start [s], position [rad], rate)


@pytest.fixture(scope="module")
def client(ros):
    node, shutdown = run_node_in_thread({"scene": "chain", "mode": "lockstep", "marker_rate": 0.0, "tf_rate": 0.0,
                                         "command_timeout": 0.5}, namespace=NS)
    c = Client("trajectory_client", ns=NS)
    c.pub_traj = c.node.create_publisher(JointTrajectory, f"{NS}/joint_trajectory", 10)
    c.wait_ready()
    c.wait_for(lambda: c.pub_traj.get_subscription_count() > 0, what="joint_trajectory subscription")
    yield c
    c.close()
    shutdown()


@pytest.fixture()
def fresh(client):
    assert client.call("get_state").state.state == SimulationState.PAUSED
    n0 = len(client.prescribed)
    assert client.call("release").result.result == Result.OK
    assert client.reset().result.result == Result.OK
    client.wait_for(lambda: len(client.prescribed) >= n0 + 2, what="release and reset acknowledgements")
    client.wait_for(lambda: client.joint_states and client.joint_states[-1].header.stamp.sec == 0
                    and client.joint_states[-1].header.stamp.nanosec == 0, what="reset state")
    client.clear()
    return client


def _dur(t):
    ns = int(round(t * 1e9))
    return Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _trajectory_msg(joint="j0", waypoints=WAYPOINTS, velocities=True):
    m = JointTrajectory(joint_names=[joint])
    for t, q, v in waypoints:
        m.points.append(JointTrajectoryPoint(positions=[q], velocities=[v] if velocities else [],
                                             time_from_start=_dur(t)))
    return m


def _send_and_ack(c, pub, msg, joint):
    with c.lock:
        n0 = len(c.prescribed)
    pub.publish(msg)
    c.wait_for(lambda: len(c.prescribed) > n0 and joint in list(c.prescribed[-1].name), what="acknowledgement")


def _states(c, n):
    c.wait_for(lambda: len(c.joint_states) >= n, what=f"{n} states")
    with c.lock:
        return list(c.joint_states[:n])


def _core_trajectory(dt=None):
    """The core given the trajectory the node builds: from the joint's state at t = 0 through the waypoints."""
    sim = Simulator.load("chain", overrides=[f"dt={dt!r}"] if dt else [])
    q0, v0 = sim.joint_positions()[0], sim.joint_velocities()[0]
    pts = [[0.0, float(q0), float(v0)]] + [[t, q, v] for t, q, v in WAYPOINTS]
    sim.prescribe_joints({"j0": {"position": [{"type": "cubic", "points": pts}], "b": B}})
    return sim


def test_trajectory_followed_with_the_core_torques_and_replayed(fresh):
    c = fresh
    _send_and_ack(c, c.pub_traj, _trajectory_msg(), "j0")  # zero stamp: starts now (t = 0)
    n = 1000
    assert c.step(n).result.result == Result.OK
    got = _states(c, n)
    sim = _core_trajectory()
    traj = sim.joint_trajectories()["j0"]
    err, q_run, effort = [], [], []
    for k in range(n):
        res = sim.step(1)
        js = got[k]
        assert np.array_equal(np.asarray(js.position), res.q) and np.array_equal(np.asarray(js.effort), res.effort), k
        q_run.append(res.q.copy())
        effort.append(res.effort.copy())
        err.append(abs(res.q[0] - traj.position(res.t)[0]))
    # O(h): e ~ h (qdot_p + qddot_p / (2 b)); halving h halves the largest error
    sim2 = _core_trajectory(H / 2)
    traj2 = sim2.joint_trajectories()["j0"]
    err2 = []
    for k in range(2 * n):
        res = sim2.step(1)
        err2.append(abs(res.q[0] - traj2.position(res.t)[0]))
    e1, e2 = max(err), max(err2)
    assert e1 < 0.02 and 1.7 < e1 / e2 < 2.3, (e1, e2)
    assert abs(q_run[-1][0] - 0.1) < 0.02  # held at the last waypoint after 0.8 s
    # replay: the required torque of j0 applied as a torque, no prescription, on a fresh core
    rep = Simulator.load("chain")
    dev = 0.0
    for k in range(n):
        rep.set_joint_torques({"j0": [effort[k][0]]})
        res = rep.step(1)
        dev = max(dev, float(np.max(np.abs(res.q - q_run[k]))))
    assert dev <= 1e-8, dev
    # the trajectory's end, not its arrival, starts the command timeout (0.5 s sim time): held still
    with c.lock:
        last = c.prescribed[-1]
    assert "j0" in list(last.name)


def test_position_target_is_held_with_the_core_torques(fresh):
    c = fresh
    target = 0.4
    _send_and_ack(c, c.pub_joint, JointState(name=["j1"], position=[target]), "j1")
    n = 400  # below command_timeout (0.5 s sim time)
    assert c.step(n).result.result == Result.OK
    got = _states(c, n)
    sim = Simulator.load("chain")
    sim.prescribe_joints({"j1": {"position": [target], "b": B}})
    for k in range(n):
        res = sim.step(1)
        assert np.array_equal(np.asarray(got[k].position), res.q) and np.array_equal(np.asarray(got[k].effort), res.effort)
    q1 = np.asarray(got[-1].position)[1]
    assert abs(q1 - target) < abs(0.0 - target) * np.exp(-B * n * H) * 1.5 + 1e-3


@pytest.mark.parametrize("label,msg,expect", [
    ("position and velocity", JointState(name=["j0"], position=[0.1], velocity=[0.2]), "not both"),
    ("position length", JointState(name=["j0", "j1"], position=[0.1]), "2 name(s) but 1 position"),
])
def test_bad_position_commands_are_rejected(fresh, label, msg, expect):
    c = fresh
    c.pub_joint.publish(msg)
    c.wait_for(lambda: any(expect in e for e in c.errors()), what=f"error for {label}")


def test_bad_trajectories_are_rejected(fresh):
    c = fresh
    cases = {"unknown joint 'nope'": _trajectory_msg("nope"),
             "strictly increasing": _trajectory_msg(waypoints=[(0.2, 0.0, 0.0), (0.2, 0.1, 0.0)])}
    m = _trajectory_msg()
    m.points[1].velocities = []
    cases["every point or for none"] = m
    m = _trajectory_msg()
    m.points[0].positions = [float("nan")]
    cases["non-finite positions"] = m
    for expect, msg in cases.items():
        c.pub_traj.publish(msg)
        c.wait_for(lambda: any(expect in e for e in c.errors()), what=f"error '{expect}'")
    with c.lock:
        assert "j0" not in list(c.prescribed[-1].name)  # nothing applied
