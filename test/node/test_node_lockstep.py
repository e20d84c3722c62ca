"""The node in-process, lockstep (PAUSED): services, commands, physics against the core.

Real rclpy over Fast DDS (private ROS_DOMAIN_ID, localhost discovery: see test/conftest.py).
Every physics check replays the same commands on a separate in-process core Simulator and
compares bitwise: the node must publish exactly the core's state and required torques.
"""
import math
import os
import time

import numpy as np
import pytest

from node_fixtures import Client, arrays_equal, run_node_in_thread  # noqa: F401  (first: skips without ROS)

from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from redmax_msgs.msg import Result, SimulationState  # noqa: E402
from redmax_msgs.srv import ResetSimulation  # noqa: E402
from redmax_ros.core import Simulator  # noqa: E402

H = 1e-3
PARAMS = {"scene": "hand", "mode": "lockstep", "command_timeout": 100.0, "marker_rate": 0.0,
          "diagnostics_period": 0.5}


NS = f"/lockstep{os.getpid()}"  # a namespace of our own, in case another run shares the domain


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """A directory load_scene may read (parameter scene_dirs; docs/node.md, "Security")."""
    return tmp_path_factory.mktemp("scenes")


@pytest.fixture(scope="module")
def node(ros, scene_dir):
    node, shutdown = run_node_in_thread({**PARAMS, "scene_dirs": [str(scene_dir)]}, namespace=NS)
    yield node
    shutdown()


@pytest.fixture(scope="module")
def client(node):
    c = Client(ns=NS)
    c.wait_ready()
    yield c
    c.close()


@pytest.fixture()
def fresh(client):
    """Paused, reset, no commanded prescriptions, collected messages cleared."""
    client.set_state(SimulationState.PAUSED)
    with client.lock:
        n0 = len(client.prescribed)
    r = client.call("release")
    assert r.result.result == Result.OK
    assert client.reset().result.result == Result.OK
    client.wait_for(lambda: client.joint_states and client.joint_states[-1].header.stamp.sec == 0
                    and client.joint_states[-1].header.stamp.nanosec == 0, what="reset state")
    # and the acknowledgements of both on prescribed_joints (one each; another topic than the
    # states, so they may arrive after them)
    client.wait_for(lambda: len(client.prescribed) >= n0 + 2, what="release and reset acknowledgements")
    client.clear()
    return client


def core():
    return Simulator.load("hand")


def stamp(m):
    return m.header.stamp.sec + m.header.stamp.nanosec * 1e-9


def set_param(client, name, value):
    cli = client.node.create_client(SetParameters, f"{NS}/redmax/set_parameters")
    assert cli.wait_for_service(timeout_sec=10)
    fut = cli.call_async(SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()]))
    end = time.monotonic() + 10
    while not fut.done():
        assert time.monotonic() < end
        time.sleep(0.001)
    client.node.destroy_client(cli)
    return fut.result().results[0]


# ------------------------------------------------------------------------------------------------

def test_describe_hand(fresh):
    d = fresh.describe()
    ref = core().describe()
    assert d.name == "hand"
    assert list(d.joint_names) == ref.joint_names
    assert list(d.velocity_names) == ref.velocity_names
    assert d.nv == ref.nv and d.ndof == ref.ndof and abs(d.dt - H) < 1e-15
    assert "index_tip" in d.prescribable_sites and "elbow" in d.prescribable_joints
    assert [c.name for c in d.couplings] == [c.name for c in ref.couplings]


def test_step_n_advances_time_and_matches_core(fresh):
    r = fresh.step(25)
    assert r.result.result == Result.OK, r.result.error_message
    assert r.completed_steps == 25
    assert r.sim_time.sec == 0 and r.sim_time.nanosec == 25_000_000
    fresh.wait_for(lambda: len(fresh.joint_states) >= 25, what="25 joint states")
    sim = core()
    for k, js in enumerate(fresh.joint_states[:25]):
        res = sim.step(1)
        assert round(stamp(js) * 1e9) == round((k + 1) * H * 1e9)
        assert arrays_equal(js.position, res.q) and arrays_equal(js.velocity, res.v)
        assert arrays_equal(js.effort, res.effort)
    assert list(fresh.joint_states[0].name) == sim.describe().velocity_names


def test_step_while_playing_is_incorrect_state(fresh):
    assert fresh.set_state(SimulationState.PLAYING).result.result == Result.OK
    r = fresh.step(1)
    assert r.result.result == Result.INCORRECT_STATE
    assert "paused" in r.result.error_message
    assert fresh.call("get_state").state.state == SimulationState.PLAYING
    assert fresh.set_state(SimulationState.PAUSED).result.result == Result.OK
    again = fresh.set_state(SimulationState.PAUSED)
    assert again.result.result == 101  # ALREADY_IN_TARGET_STATE
    assert fresh.step(1).result.result == Result.OK


def test_stopped_resets_and_refuses_steps(fresh):
    fresh.step(10)
    assert fresh.set_state(SimulationState.STOPPED).result.result == Result.OK
    assert fresh.step(1).result.result == Result.INCORRECT_STATE
    assert fresh.set_state(SimulationState.PAUSED).result.result == Result.OK
    r = fresh.step(1)
    assert r.result.result == Result.OK and r.sim_time.nanosec == 1_000_000  # time restarted at 0


def test_prescribed_joint_velocity_and_required_torque_match_core(fresh):
    fresh.command_joints(["elbow", "wrist[0]", "wrist[1]"], [0.5, -0.2, 0.1])
    assert fresh.step(30).result.result == Result.OK
    fresh.wait_for(lambda: len(fresh.joint_states) >= 30, what="30 states")
    sim = core()
    sim.prescribe_joints({"elbow": 0.5, "wrist": [-0.2, 0.1]})
    names = list(fresh.joint_states[0].name)
    ie, iw0, iw1 = names.index("elbow"), names.index("wrist[0]"), names.index("wrist[1]")
    for js in fresh.joint_states[:30]:
        res = sim.step(1)
        assert js.velocity[ie] == pytest.approx(0.5, abs=1e-9)
        assert js.velocity[iw0] == pytest.approx(-0.2, abs=1e-9)
        assert js.velocity[iw1] == pytest.approx(0.1, abs=1e-9)
        assert arrays_equal(js.effort, res.effort)  # required torques equal the core's
        assert arrays_equal(js.position, res.q)
    assert abs(fresh.joint_states[-1].effort[ie]) > 1e-3  # holding the arm needs torque


def test_applied_torque_command(fresh):
    fresh.command_joints(["index_pip"], efforts=[0.01])
    assert fresh.step(5).result.result == Result.OK
    fresh.wait_for(lambda: len(fresh.joint_states) >= 5, what="5 states")
    sim = core()
    sim.set_joint_torques({"index_pip": 0.01})
    for js in fresh.joint_states[:5]:
        res = sim.step(1)
        assert arrays_equal(js.effort, res.effort) and arrays_equal(js.velocity, res.v)


def test_prescribed_fingertip_follows_commanded_velocity(fresh):
    from redmax_ros.core.dynamics import kinematics

    vel = np.array([0.0, 0.02, 0.03])
    fresh.command_points(["index_tip"], [vel])
    n = 20
    assert fresh.step(n).result.result == Result.OK
    fresh.wait_for(lambda: len(fresh.joint_states) >= n and len(fresh.point_forces) >= n, what="states")
    sim = core()
    sim.prescribe_sites({"index_tip": vel})
    m = sim.mech
    data = m.model.createData()
    i_tip = m.site_index["index_tip"]

    def tip(q):
        import pinocchio as pin
        pin.forwardKinematics(m.model, data, q)
        return kinematics.site_positions(m, data)[i_tip].copy()

    x0 = tip(sim.joint_positions())
    for js, pf in zip(fresh.joint_states[:n], fresh.point_forces[:n]):
        res = sim.step(1)
        assert arrays_equal(js.position, res.q)
        assert list(pf.sites) == ["index_tip"]
        f = pf.forces[0]
        assert arrays_equal([f.x, f.y, f.z], res.site_forces["index_tip"])
    x1 = tip(np.asarray(fresh.joint_states[n - 1].position))
    # the tip moved with the commanded velocity (first-order integration on the manifold)
    assert np.allclose((x1 - x0) / (n * H), vel, atol=2e-3)


def test_command_timeout_releases_joint_with_one_warning(fresh):
    assert set_param(fresh, "command_timeout", 0.005).successful
    try:
        fresh.command_joints(["wrist[0]", "wrist[1]"], [0.3, 0.0])
        assert fresh.step(3).result.result == Result.OK
        assert "wrist[0]" in fresh.prescribed[-1].name
        assert fresh.step(10).result.result == Result.OK
        fresh.wait_for(lambda: "wrist[0]" not in fresh.prescribed[-1].name, what="release")
        fresh.wait_for(lambda: any("command timeout" in e and "wrist" in e for e in fresh.errors()),
                       what="timeout warning")
        assert fresh.step(10).result.result == Result.OK
        time.sleep(0.2)
        assert sum("command timeout" in e and "wrist" in e for e in fresh.errors()) == 1
        # after the release the wrist moves passively: its velocity is no longer held at 0.3
        names = list(fresh.joint_states[-1].name)
        assert fresh.joint_states[-1].velocity[names.index("wrist[0]")] != pytest.approx(0.3, abs=1e-6)
    finally:
        assert set_param(fresh, "command_timeout", 100.0).successful


def test_reset_restores_initial_state_and_time(fresh):
    fresh.command_joints(["elbow"], [1.0])
    fresh.step(50)
    assert fresh.reset(ResetSimulation.Request.SCOPE_ALL).result.result == Result.OK
    fresh.wait_for(lambda: fresh.joint_states and stamp(fresh.joint_states[-1]) == 0.0, what="reset state")
    sim = core()
    js = fresh.joint_states[-1]
    assert arrays_equal(js.position, sim.joint_positions()) and arrays_equal(js.velocity, sim.joint_velocities())
    assert list(fresh.prescribed[-1].name) == ["elbow"] and fresh.prescribed[-1].velocity[0] == 0.0  # scene default
    fresh.clear()
    fresh.step(5)
    fresh.wait_for(lambda: len(fresh.joint_states) >= 5, what="states")
    for js in fresh.joint_states[:5]:
        assert arrays_equal(js.position, sim.step(1).q)


def test_reset_time_scope_keeps_state(fresh):
    fresh.step(20)
    fresh.wait_for(lambda: len(fresh.joint_states) >= 20, what="states")
    q20 = np.asarray(fresh.joint_states[19].position)
    assert fresh.reset(ResetSimulation.Request.SCOPE_TIME).result.result == Result.OK
    fresh.wait_for(lambda: stamp(fresh.joint_states[-1]) == 0.0, what="time reset")
    assert arrays_equal(fresh.joint_states[-1].position, q20)
    assert fresh.reset(77).result.result == Result.FEATURE_UNSUPPORTED


def test_load_scene_changes_description_and_back(fresh):
    r = fresh.load("pendulum")
    assert r.result.result == Result.OK, r.result.error_message
    d = fresh.describe()
    assert d.name == "pendulum" and list(d.joint_names) == ["hinge"] and d.nv == 1
    fresh.wait_for(lambda: list(fresh.joint_states[-1].name) == ["hinge"], what="pendulum state")
    assert fresh.step(3).result.result == Result.OK
    r = fresh.load("hand")
    assert r.result.result == Result.OK
    assert fresh.describe().nv == 23


def test_simulate_steps_action_feedback_and_cancel(fresh):
    from redmax_msgs.action import SimulateSteps

    assert fresh.action.wait_for_server(timeout_sec=10)
    feedback = []
    goal = SimulateSteps.Goal(steps=15)
    fut = fresh.action.send_goal_async(goal, feedback_callback=lambda f: feedback.append(f.feedback))
    fresh.wait_for(lambda: fut.done(), what="goal accepted")
    gh = fut.result()
    assert gh.accepted
    rfut = gh.get_result_async()
    fresh.wait_for(lambda: rfut.done(), what="action result")
    res = rfut.result().result
    assert res.result.result == Result.OK and res.completed_steps == 15
    # one feedback per step (the action's feedback topic keeps the last 10, so a slow client may
    # miss some): what arrives is in order and consistent
    fresh.wait_for(lambda: len(feedback) > 0, what="feedback")
    done = [f.completed_steps for f in feedback]
    assert done == sorted(set(done)) and set(done) <= set(range(1, 16))
    assert all(f.completed_steps + f.remaining_steps == 15 for f in feedback)
    feedback.clear()
    # cancel a long request midway: it stops, reports the steps done, stays paused
    fut = fresh.action.send_goal_async(SimulateSteps.Goal(steps=1_000_000),
                                       feedback_callback=lambda f: feedback.append(f.feedback))
    fresh.wait_for(lambda: fut.done(), what="goal accepted")
    gh = fut.result()
    fresh.wait_for(lambda: len(feedback) > 20, what="progress")
    cfut = gh.cancel_goal_async()
    fresh.wait_for(lambda: cfut.done(), what="cancel response")
    rfut = gh.get_result_async()
    fresh.wait_for(lambda: rfut.done(), what="canceled result")
    res = rfut.result().result
    assert 0 < res.completed_steps < 1_000_000
    assert fresh.call("get_state").state.state == SimulationState.PAUSED
    # an action while playing returns INCORRECT_STATE
    fresh.set_state(SimulationState.PLAYING)
    fut = fresh.action.send_goal_async(SimulateSteps.Goal(steps=3))
    fresh.wait_for(lambda: fut.done(), what="goal accepted")
    rfut = fut.result().get_result_async()
    fresh.wait_for(lambda: rfut.done(), what="result")
    assert rfut.result().result.result.result == Result.INCORRECT_STATE
    fresh.set_state(SimulationState.PAUSED)


# ------------------------------------------------------------------------------------------------
# bad input: a clear error, the node keeps serving, nothing changes

def _bad_joint_commands():
    from sensor_msgs.msg import JointState
    return {
        "unknown joint": (JointState(name=["nope"], velocity=[1.0]), "unknown joint 'nope'"),
        "length mismatch": (JointState(name=["elbow", "wrist[0]"], velocity=[1.0]), "2 name(s) but 1 velocity"),
        "nan": (JointState(name=["elbow"], velocity=[math.nan]), "non-finite velocity"),
        "inf effort": (JointState(name=["elbow"], effort=[math.inf]), "non-finite effort"),
        "partial multi-dof": (JointState(name=["wrist[0]"], velocity=[1.0]), "give all of wrist[0], wrist[1]"),
        "not prescribable": (JointState(name=["index_pip"], velocity=[1.0]), "cannot be prescribed"),
        "duplicate": (JointState(name=["elbow", "elbow"], velocity=[1.0, 2.0]), "appears twice"),
    }


def test_bad_commands_are_rejected_and_change_nothing(fresh):
    from geometry_msgs.msg import Vector3
    from redmax_msgs.msg import PointVelocityCommand

    prescribed_before = fresh.prescribed[-1]
    for label, (msg, expect) in _bad_joint_commands().items():
        fresh.pub_joint.publish(msg)
        fresh.wait_for(lambda: any(expect in e for e in fresh.errors()), what=f"error for {label}")
    points = {
        "unknown site": (PointVelocityCommand(sites=["nope"], velocities=[Vector3()]), "unknown site 'nope'"),
        "site length": (PointVelocityCommand(sites=["index_tip", "thumb_tip"], velocities=[Vector3()]),
                        "2 site(s) but 1 velocity"),
        "site nan": (PointVelocityCommand(sites=["index_tip"], velocities=[Vector3(x=math.nan)]), "non-finite"),
    }
    for label, (msg, expect) in points.items():
        fresh.pub_point.publish(msg)
        fresh.wait_for(lambda: any(expect in e for e in fresh.errors()), what=f"error for {label}")
    bad_frame = PointVelocityCommand(sites=["index_tip"], velocities=[Vector3()])
    bad_frame.header.frame_id = "palm"
    fresh.pub_point.publish(bad_frame)
    fresh.wait_for(lambda: any("frame 'palm'" in e for e in fresh.errors()), what="frame error")
    # nothing changed: no new prescription, and stepping gives exactly the untouched core's states
    assert fresh.prescribed[-1] == prescribed_before
    fresh.clear()
    assert fresh.step(5).result.result == Result.OK
    fresh.wait_for(lambda: len(fresh.joint_states) >= 5, what="states")
    sim = core()
    for js in fresh.joint_states[:5]:
        assert arrays_equal(js.position, sim.step(1).q)
    # each distinct error is logged once even when repeated
    n = sum("unknown joint 'nope'" in e for e in fresh.errors())
    fresh.pub_joint.publish(_bad_joint_commands()["unknown joint"][0])
    fresh.step(1)
    time.sleep(0.2)
    assert sum("unknown joint 'nope'" in e for e in fresh.errors()) == n == 1


def test_bad_requests_return_clear_results(fresh, scene_dir):
    r = fresh.step(0)
    assert r.result.result == Result.OPERATION_FAILED and "steps must be in [1," in r.result.error_message
    r = fresh.step(10**12)
    assert r.result.result == Result.OPERATION_FAILED and "max_steps_per_request" in r.result.error_message
    r = fresh.load("no_such_scene")
    assert r.result.result == Result.NOT_FOUND and "no such scene" in r.result.error_message
    assert r.description.name == "hand"  # old scene kept
    bad = scene_dir / "broken.yaml"
    bad.write_text("name: broken\nbodies: [ {name: x, shape: {type: blob}} ]\njoints: 7\n")
    r = fresh.load(str(bad))
    assert r.result.result == 101 and "broken.yaml" in r.result.error_message  # INVALID_SCENE
    bad.write_text("name: [unclosed\n")
    r = fresh.load(str(bad))
    assert r.result.result == 101 and "YAML" in r.result.error_message
    assert fresh.describe().name == "hand"
    r = fresh.call("release", fresh.cli["release"].srv_type.Request(joints=["nope"]))
    assert r.result.result == Result.NOT_FOUND
    req = fresh.cli["set_state"].srv_type.Request()
    req.state.state = 9
    assert fresh.call("set_state", req).result.result == Result.OPERATION_FAILED
    # out-of-range / invalid parameters are rejected with a reason
    for name, value, expect in [("real_time_factor", -1.0, ""), ("publish_rate", 1e9, ""),
                                ("command_timeout", -0.1, ""), ("max_steps_per_request", 0, ""),
                                ("mode", "fast", "read-only"), ("real_time_factor", "x", "type")]:
        res = set_param(fresh, name, value)
        assert not res.successful and res.reason, (name, value)
        if expect:
            assert expect in res.reason
    # still serving, state consistent with the core
    fresh.clear()
    assert fresh.step(3).result.result == Result.OK
    fresh.wait_for(lambda: len(fresh.joint_states) >= 3, what="states")
    sim = core()
    for js in fresh.joint_states[:3]:
        assert arrays_equal(js.position, sim.step(1).q)


def test_lockstep_is_deterministic(fresh):
    """Same command sequence twice (reset in between): bitwise-identical joint_states."""
    runs = []
    for _ in range(2):
        fresh.reset()
        fresh.wait_for(lambda: fresh.joint_states and stamp(fresh.joint_states[-1]) == 0.0, what="reset")
        fresh.clear()
        for k in range(6):
            fresh.command_joints(["elbow"], [0.3 * math.sin(k)])
            fresh.command_points(["thumb_tip"], [[0.0, 0.01 * k, 0.0]])
            assert fresh.step(4).result.result == Result.OK
        fresh.wait_for(lambda: len(fresh.joint_states) >= 24, what="24 states")
        runs.append([(tuple(js.position), tuple(js.velocity), tuple(js.effort)) for js in fresh.joint_states[:24]])
    assert runs[0] == runs[1]


def test_solver_stats_while_subscribed(client, fresh):
    """solver_stats is built only while someone listens (or it is logged): one per step then."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from redmax_msgs.msg import SolverStats

    c = client
    assert c.step(3).result.result == Result.OK  # nobody listens: nothing to check, nothing breaks
    got = []
    sub = c.node.create_subscription(SolverStats, f"{NS}/solver_stats", got.append,
                                     QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    try:
        pub = [p for p in c.node.get_publishers_info_by_topic(f"{NS}/solver_stats")]
        assert pub, "solver_stats has no publisher"
        end = time.monotonic() + 20
        while c.node.count_subscribers(f"{NS}/solver_stats") == 0 and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(0.2)  # the node's publisher matches us too
        r = c.step(5)
        assert r.result.result == Result.OK
        c.wait_for(lambda: len(got) >= 5, what="5 solver_stats")
        assert [m.step for m in got[-5:]] == [4, 5, 6, 7, 8]
        assert all(m.solver and m.iterations >= 1 and math.isfinite(m.residual) for m in got[-5:])
        assert [m.integration_order for m in got[-5:]] == [1] * 5  # the hand steps Eq. (2) (scheme euler)
        # integrator.scheme bdf2: the order of each step, as the core reports it (Diagnostics.order): the start-up
        # step 1, then BDF2 steps the order control keeps (a smooth pendulum keeps them all)
        r = c.load("pendulum", ["integrator.scheme=bdf2"])
        assert r.result.result == Result.OK, r.result.error_message
        n0 = len(got)
        assert c.step(5).result.result == Result.OK
        c.wait_for(lambda: len(got) >= n0 + 5, what="5 solver_stats under BDF2")
        ref = Simulator.load("pendulum", ["integrator.scheme=bdf2", f"dt={H}"]).rollout(5).order.tolist()
        assert [m.integration_order for m in got[n0:n0 + 5]] == ref == [1, 2, 2, 2, 2]
    finally:
        c.node.destroy_subscription(sub)
        assert c.load("hand").result.result == Result.OK  # the module's scene again
