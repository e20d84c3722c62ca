"""Body-twist prescriptions over ROS (issue 18 item 3), real rclpy over Fast DDS on the private domain:
body_commands (redmax_msgs/BodyTwistCommand) prescribe components of a body's twist, body_wrenches
(redmax_msgs/BodyWrenches) carry the wrench the core reports for them (StepResult.body_wrenches),
prescribed_bodies (redmax_msgs/BodyTwists, latched) what is in force. Physics checked against the core:
the prescribed components of the body twist after each step (the twist Jacobian times v), and the
published wrenches against a core Simulator given the same commands directly."""
import math

import numpy as np
import pinocchio as pin
import pytest

from node_fixtures import Client, run_node_in_thread  # noqa: F401  (first: skips without ROS)

from geometry_msgs.msg import Twist, Vector3  # noqa: E402

from redmax_msgs.msg import BodyTwistCommand, Result  # noqa: E402
from redmax_msgs.srv import ReleaseCommands  # noqa: E402

from redmax_ros.core import Simulator  # noqa: E402
from redmax_ros.core.step.body_twist import twist_jacobian  # noqa: E402

NS = "/bodytwist"
PARAMS = {"scene": "catalogue/free3d", "mode": "lockstep", "command_timeout": 0.0, "marker_rate": 0.0,
          "publish_rate": 0.0, "tf_rate": 0.0}
FREE = ("catalogue/free3d", ["joints.free.conserve_momentum=false"])  # the plain step (as test/core/step)
NAN = math.nan


@pytest.fixture(scope="module")
def node(ros):
    node, shutdown = run_node_in_thread(PARAMS, namespace=NS)
    yield node
    shutdown()


@pytest.fixture(scope="module")
def client(node):
    c = Client("redmax_bodytwist_client", ns=NS)
    c.wait_ready()
    yield c
    c.close()


def _load(client, scene, overrides=()):
    with client.lock:
        n0 = len(client.prescribed_bodies)
    r = client.load(scene, list(overrides))
    assert r.result.result == Result.OK, r.result.error_message
    client.wait_for(lambda: len(client.prescribed_bodies) > n0, what="prescribed_bodies after the load")
    client.clear()


def _twist(sim, body, frame):
    """[omega; v] of the body frame at the simulator's state: the core's twist Jacobian (own pin.Data) times v."""
    model = sim.mech.model
    data = model.createData()
    v = sim.joint_velocities()
    pin.computeAllTerms(model, data, sim.state.q, v)
    return twist_jacobian(sim.mech, data, body, frame) @ v


def _stamp(m):
    return m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec


def _wrench(w):
    """geometry_msgs/Wrench -> (6,) [torque; force], the core's order."""
    return np.array([w.torque.x, w.torque.y, w.torque.z, w.force.x, w.force.y, w.force.z])


def _wrenches_after(client, t0, n):
    """The n body_wrenches messages stamped after t0 [s], in order."""
    def got():
        return [m for m in client.body_wrenches if _stamp(m) > t0 + 1e-12]
    client.wait_for(lambda: len(got()) >= n, what=f"{n} body_wrenches after t = {t0}")
    with client.lock:
        return got()


def _rel(a, b):
    return np.abs(np.asarray(a) - np.asarray(b)).max() / max(np.abs(np.asarray(b)).max(), 1e-300)


def _twist_of(m, i):
    tw = m.twists[i]
    return [tw.angular.x, tw.angular.y, tw.angular.z, tw.linear.x, tw.linear.y, tw.linear.z]


def _same_nan(a, b):
    return all((math.isnan(x) and math.isnan(y)) or x == y for x, y in zip(a, b))


def test_prescribed_components_met_and_wrenches_equal_the_core(node, client):
    """A body-frame angular velocity, then world-frame components (omega_z, v_x, v_z; the rest free) on the
    free box: after every step the prescribed components of the box's twist are the commanded ones (1e-9),
    the free wrench components are zero, and every published wrench equals the core's
    StepResult.body_wrenches for the same commands run directly on a Simulator (1e-9 relative)."""
    _load(client, *FREE)
    eng = node.engine
    ref = Simulator.load(*FREE)
    assert "box" in client.describe().bodies
    phases = [("body", (0.3, -0.2, 1.0), (None, None, None), [0, 1, 2]),
              ("world", (None, None, 0.5), (0.2, None, -0.1), [2, 3, 5])]
    for frame, ang, lin, rows in phases:
        client.command_bodies(["box"], [(ang, lin)], frame=frame)
        pb = client.prescribed_bodies[-1]
        want = [NAN if x is None else x for x in (*ang, *lin)]
        assert list(pb.bodies) == ["box"] and list(pb.frames) == [frame] and _same_nan(_twist_of(pb, 0), want)
        ref.prescribe_bodies({"box": {"angular": list(ang), "linear": list(lin), "frame": frame}})
        t0 = eng.sim.time
        for _ in range(15):
            assert client.step(1).result.result == Result.OK
            r = ref.step()
            tw = eng.query(lambda sim: _twist(sim, "box", frame))
            assert np.abs(tw[rows] - np.array(want)[rows]).max() < 1e-9, (frame, tw)
            assert np.array_equal(eng.sim.state.q, ref.state.q)  # the node steps what the core steps
        msgs = _wrenches_after(client, t0, 15)
        assert len(msgs) == 15
        free = [k for k in range(6) if k not in rows]
        for m in msgs:
            assert list(m.bodies) == ["box"] and list(m.frames) == [frame] and m.header.frame_id == "world"
            assert all(_wrench(m.wrenches[0])[k] == 0.0 for k in free)
        # the last message is the last step's: same wrench as the direct core run
        assert abs(_stamp(msgs[-1]) - ref.time) < 1e-9
        w = _wrench(msgs[-1].wrenches[0])
        assert np.abs(w).max() > 1e-6  # a real wrench (gyroscopic torque, the linear rows' forces)
        assert _rel(w, r.body_wrenches["box"]) < 1e-9


def test_wrench_sequence_equals_the_core_step_by_step(node, client):
    """20 steps in one request: each of the 20 published wrenches is the core's of that step."""
    _load(client, *FREE)
    eng = node.engine
    ref = Simulator.load(*FREE)
    cmd = {"angular": [0.4, None, -0.8], "linear": [None, 0.1, None], "frame": "body"}
    client.command_bodies(["box"], [(cmd["angular"], cmd["linear"])], frame="body")
    ref.prescribe_bodies({"box": cmd})
    t0 = eng.sim.time
    assert client.step(20).result.result == Result.OK
    want = [ref.step().body_wrenches["box"] for _ in range(20)]
    msgs = _wrenches_after(client, t0, 20)
    assert len(msgs) == 20
    for k, (m, w) in enumerate(zip(msgs, want)):
        assert abs(_stamp(m) - (t0 + (k + 1) * eng.sim.dt)) < 1e-9
        assert _rel(_wrench(m.wrenches[0]), w) < 1e-9, k


def test_release_restores_passive_motion(node, client):
    """release_commands(bodies=[box]): prescribed_bodies empties, one empty body_wrenches message follows,
    then none; the box moves passively (zero gravity: its COM velocity stays what it was at the release)
    exactly as the core's after release_bodies."""
    _load(client, *FREE)
    eng = node.engine
    ref = Simulator.load(*FREE)
    client.command_bodies(["box"], [((None, 0.0, None), (0.2, 0.0, -0.1))], frame="world")
    ref.prescribe_bodies({"box": {"angular": [None, 0.0, None], "linear": [0.2, 0.0, -0.1], "frame": "world"}})
    assert client.step(10).result.result == Result.OK
    ref.step(10)
    assert np.abs(eng.sim.joint_velocities()[:3] - [0.2, 0.0, -0.1]).max() < 1e-9
    # unknown names: NOT_FOUND, nothing released
    r = client.call("release", ReleaseCommands.Request(bodies=["box", "nope"]))
    assert r.result.result == Result.NOT_FOUND and "unknown body 'nope'" in r.result.error_message
    assert list(eng.sim.prescribed_bodies()) == ["box"]
    with client.lock:
        n0 = len(client.prescribed_bodies)
    assert client.call("release", ReleaseCommands.Request(bodies=["box"])).result.result == Result.OK
    client.wait_for(lambda: len(client.prescribed_bodies) > n0, what="release acknowledgement")
    assert list(client.prescribed_bodies[-1].bodies) == [] and len(client.prescribed_bodies[-1].twists) == 0
    held = Simulator.load(*FREE)  # the same run with the prescription kept
    held.set_state(ref.state)
    held.prescribe_bodies({"box": {"angular": [None, 0.0, None], "linear": [0.2, 0.0, -0.1], "frame": "world"}})
    ref.release_bodies(["box"])
    t0, v0 = eng.sim.time, eng.sim.joint_velocities().copy()
    assert client.step(10).result.result == Result.OK
    r = ref.step(10)
    assert r.body_wrenches == {}
    msgs = _wrenches_after(client, t0, 1)
    client.step(1)
    ref.step(1)
    held.step(11)
    client.call("get_state")
    with client.lock:
        after = [m for m in client.body_wrenches if _stamp(m) > t0 + 1e-12]
    assert len(after) == 1 and list(msgs[0].bodies) == [] and len(msgs[0].wrenches) == 0
    assert np.array_equal(eng.sim.state.q, ref.state.q) and np.array_equal(eng.sim.state.v, ref.state.v)
    v = eng.sim.joint_velocities()
    assert np.abs(v[:3] - v0[:3]).max() < 1e-12  # passive: linear momentum kept
    assert np.abs(v - held.joint_velocities()).max() > 1e-6  # not what the prescription would have made


def _snapshot(eng):
    s = eng.sim
    return (s.state.t, eng.step_index, s.state.q.tobytes(), s.state.v.tobytes(),
            {k: (v["components"], v["values"].tobytes(), v["frame"]) for k, v in s.prescribed_bodies().items()},
            {k: v.tobytes() for k, v in s.prescribed_joints().items()})


def _msg(bodies, twists, frame="world"):
    m = BodyTwistCommand(bodies=list(bodies), twists=list(twists))
    m.header.frame_id = frame
    return m


def _tw(wx=NAN, wy=NAN, wz=NAN, vx=NAN, vy=NAN, vz=NAN):
    return Twist(angular=Vector3(x=wx, y=wy, z=wz), linear=Vector3(x=vx, y=vy, z=vz))


BAD = [
    (_msg(["nope"], [_tw(wz=1.0)]), "unknown body 'nope'"),
    (_msg(["box"], []), "1 body(ies) but 0 twist(s)"),
    (_msg(["box"], [_tw(), _tw()]), "1 body(ies) but 2 twist(s)"),
    (_msg(["box"], [_tw()]), "all six twist components of body 'box' are NaN"),
    (_msg(["box"], [_tw(wx=math.inf)]), "non-finite angular.x = inf for body 'box'"),
    (_msg(["box"], [_tw(vz=-math.inf, wx=0.0)]), "non-finite linear.z = -inf for body 'box'"),
    (_msg(["box"], [_tw(wz=1.0)], frame="palm"), "frame 'palm' is not supported"),
    (_msg(["box"], [_tw(wz=1.0)], frame="World"), "frame 'World' is not supported"),
    (_msg(["box", "box"], [_tw(wz=1.0), _tw(wz=2.0)]), "name 'box' appears twice"),
    (_msg([], []), "no body names given"),
]


def test_bad_body_commands_are_rejected_with_the_state_unchanged(node, client):
    """Each bad command is refused (counted, logged with the body and the problem), the node answers at
    once, and time, steps, q, v and prescriptions are bitwise what they were; the prescription in force
    is still met on the next step."""
    _load(client, *FREE)
    eng = node.engine
    client.command_bodies(["box"], [((0.0, 0.0, 1.0), None)], frame="body")
    assert client.step(3).result.result == Result.OK
    before = _snapshot(eng)
    for msg, text in BAD:
        n0 = eng.command_errors
        client.pub_body.publish(msg)
        client.wait_for(lambda: eng.command_errors > n0, what=f"rejection of {text}")
        client.wait_for(lambda: any(text in e for e in client.errors()), what=f"logged: {text}")
        assert client.call("get_state", timeout=10).result.result == Result.OK
        assert _snapshot(eng) == before, text
    assert client.step(1).result.result == Result.OK
    assert np.abs(eng.query(lambda sim: _twist(sim, "box", "body"))[:3] - [0.0, 0.0, 1.0]).max() < 1e-9


def test_data_free_path_rejects_with_the_cores_message(node, client):
    """On a data-free step path (solver pcg) the core refuses body twists; the node rejects the command with
    the core's CommandError text, nothing is prescribed, the node steps on."""
    _load(client, "catalogue/revolute", ["solver=pcg"])
    eng = node.engine
    assert eng.sim.data is None
    before = _snapshot(eng)
    n0 = eng.command_errors
    client.pub_body.publish(_msg(["rod"], [_tw(wy=1.0)], frame="body"))
    client.wait_for(lambda: eng.command_errors > n0, what="rejection on the data-free path")
    client.wait_for(lambda: any("need the Pinocchio pipeline" in e and "data-free path" in e for e in client.errors()),
                    what="the core's message logged")
    assert _snapshot(eng) == before and eng.sim.prescribed_bodies() == {}
    assert client.step(2).result.result == Result.OK


def test_scene_prescription_timeout_reset_and_release_all(node, client):
    """catalogue/body_twist prescribes the lower rod's world omega_y = -1 itself: prescribed_bodies says so
    after the load and body_wrenches equal the core's; a command (-2) holds until command_timeout (sim time),
    then the scene's -1 is back (as for joints and sites); reset also brings it back; release_commands with
    all lists empty releases the body (passive swing, as the core's)."""
    _load(client, "catalogue/body_twist")
    eng = node.engine
    ref = Simulator.load("catalogue/body_twist")
    pb = client.prescribed_bodies[-1]
    assert list(pb.bodies) == ["lower"] and list(pb.frames) == ["world"]
    assert _same_nan(_twist_of(pb, 0), [NAN, -1.0, NAN, NAN, NAN, NAN])
    t0 = eng.sim.time
    assert client.step(5).result.result == Result.OK
    r = ref.step(5)
    m = _wrenches_after(client, t0, 5)[-1]
    assert list(m.bodies) == ["lower"] and list(m.frames) == ["world"]
    assert _rel(_wrench(m.wrenches[0]), r.body_wrenches["lower"]) < 1e-9
    assert abs(eng.sim.joint_velocities().sum() + 1.0) < 1e-9
    try:
        eng.configure(command_timeout=0.01)  # 10 steps of 1 ms
        client.command_bodies(["lower"], [((None, -2.0, None), None)], frame="world")
        assert client.step(5).result.result == Result.OK
        assert abs(eng.sim.joint_velocities().sum() + 2.0) < 1e-9
        assert ("body", "lower") in eng.cmd_times
        with client.lock:
            n0 = len(client.prescribed_bodies)
        assert client.step(10).result.result == Result.OK
        client.wait_for(lambda: len(client.prescribed_bodies) > n0, what="prescribed_bodies after the timeout")
        assert _same_nan(_twist_of(client.prescribed_bodies[-1], 0), [NAN, -1.0, NAN, NAN, NAN, NAN])
        assert abs(eng.sim.joint_velocities().sum() + 1.0) < 1e-9 and ("body", "lower") not in eng.cmd_times
        client.wait_for(lambda: any("returned body 'lower' to the scene's prescription" in e for e in client.errors()),
                        what="the timeout warning")
    finally:
        eng.configure(command_timeout=0.0)
    client.command_bodies(["lower"], [((None, -2.0, None), None)], frame="world")
    with client.lock:
        n0 = len(client.prescribed_bodies)
    assert client.reset().result.result == Result.OK
    client.wait_for(lambda: len(client.prescribed_bodies) > n0, what="prescribed_bodies after the reset")
    assert _same_nan(_twist_of(client.prescribed_bodies[-1], 0), [NAN, -1.0, NAN, NAN, NAN, NAN])
    # release everything (all three lists empty): the scene's own body prescription too
    ref = Simulator.load("catalogue/body_twist")
    with client.lock:
        n0 = len(client.prescribed_bodies)
    assert client.call("release").result.result == Result.OK
    client.wait_for(lambda: len(client.prescribed_bodies) > n0, what="release acknowledgement")
    assert list(client.prescribed_bodies[-1].bodies) == [] and eng.sim.prescribed_bodies() == {}
    ref.release_bodies(["lower"])
    assert client.step(50).result.result == Result.OK
    ref.step(50)
    assert np.array_equal(eng.sim.state.q, ref.state.q) and np.array_equal(eng.sim.state.v, ref.state.v)
    assert abs(eng.sim.joint_velocities().sum() + 1.0) > 1e-3  # no longer held


def test_free_run_command_is_applied_by_the_stepping_thread(node, client):
    """While PLAYING the simulation thread applies the batch before its next step: after the
    acknowledgement and a pause, the box's body-frame angular velocity is the commanded one (1e-9) and
    body_wrenches went out with the free-run states."""
    from redmax_msgs.msg import SimulationState

    _load(client, *FREE)
    eng = node.engine
    assert client.set_state(SimulationState.PLAYING).result.result == Result.OK
    try:
        client.command_bodies(["box"], [((-0.5, 0.25, 0.75), None)], frame="body")
        t0 = eng.sim.time
        _wrenches_after(client, t0, 20)
    finally:
        assert client.set_state(SimulationState.PAUSED).result.result == Result.OK
    assert np.abs(eng.query(lambda sim: _twist(sim, "box", "body"))[:3] - [-0.5, 0.25, 0.75]).max() < 1e-9
    with client.lock:
        assert all(list(m.frames) == ["body"] for m in client.body_wrenches if _stamp(m) > t0 + 1e-12)
