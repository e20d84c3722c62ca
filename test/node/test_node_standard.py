"""The node driven by a ROS 2 ``simulation_interfaces`` client (issue 18, point 1).

The node runs as a subprocess (pendulum, lockstep); the client here uses rclpy and the standard's
types only (simulation_interfaces, plus std_msgs/String for robot_description): no redmax_msgs.
Physics is checked against a core Simulator replaying the same steps in this process (the node's
states are the core's, bitwise): entity poses to 1e-12, twists against v = w x r of the pendulum.
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

if os.environ.get("CI"):
    import rclpy  # noqa: E402
    import simulation_interfaces.srv  # noqa: E402,F401
else:
    rclpy = pytest.importorskip("rclpy")
    pytest.importorskip("simulation_interfaces.srv", reason="simulation_interfaces not built (scripts/setup.sh)")

from rclpy.action import ActionClient  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from simulation_interfaces.action import SimulateSteps  # noqa: E402
from simulation_interfaces.msg import EntityCategory, Result, SimulationState, SimulatorFeatures  # noqa: E402
from simulation_interfaces.srv import (GetAvailableWorlds, GetCurrentWorld, GetEntities,  # noqa: E402
                                       GetEntitiesStates, GetEntityState, GetSimulationState,
                                       GetSimulatorFeatures, LoadWorld, ResetSimulation, SetSimulationState,
                                       StepSimulation)

from redmax_ros.core import Simulator  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
NS = f"/standard{os.getpid()}"
PREFIX = f"{NS}/redmax/"  # the node's private namespace: /<ns>/<node name>/<standard service>
TIMEOUT = 30.0
SERVICES = {"get_simulator_features": GetSimulatorFeatures, "step_simulation": StepSimulation,
            "reset_simulation": ResetSimulation, "get_simulation_state": GetSimulationState,
            "set_simulation_state": SetSimulationState, "get_entities": GetEntities,
            "get_entity_state": GetEntityState, "get_entities_states": GetEntitiesStates,
            "get_current_world": GetCurrentWorld, "load_world": LoadWorld, "get_available_worlds": GetAvailableWorlds}
OK = Result.RESULT_OK


class StandardClient:
    """Services, the action and robot_description of a simulation_interfaces simulator."""

    def __init__(self):
        self.node = Node("standard_client")
        self.cli = {k: self.node.create_client(cls, PREFIX + k) for k, cls in SERVICES.items()}
        # every feedback message: a feedback subscription as deep as the node's feedback topic
        self.action = ActionClient(self.node, SimulateSteps, PREFIX + "simulate_steps",
                                   feedback_sub_qos_profile=QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        self.lock = threading.Lock()
        self.descriptions = []
        self.node.create_subscription(String, f"{NS}/robot_description", self._desc,
                                      QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                                 durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _desc(self, msg):
        with self.lock:
            self.descriptions.append(msg.data)

    def _spin(self):
        while not self._stop and rclpy.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:
                if self._stop or not rclpy.ok():
                    break
                raise

    def close(self):
        self._stop = True
        self._thread.join(5)
        self.action.destroy()
        self.node.destroy_node()

    def wait_ready(self):
        # the first one generously: a node whose numba kernels recompile (a core edit) starts in ~100 s
        assert self.cli["get_simulator_features"].wait_for_service(timeout_sec=300), "the node did not start"
        for name, c in self.cli.items():
            assert c.wait_for_service(timeout_sec=TIMEOUT), f"service {PREFIX}{name} not available"
        assert self.action.wait_for_server(timeout_sec=TIMEOUT), "action simulate_steps not available"

    def call(self, name, req=None, timeout=TIMEOUT):
        c = self.cli[name]
        fut = c.call_async(c.srv_type.Request() if req is None else req)
        end = time.monotonic() + timeout
        while not fut.done():
            assert time.monotonic() < end, f"{name} did not answer"
            time.sleep(0.001)
        return fut.result()

    def set_state(self, state):
        req = SetSimulationState.Request()
        req.state.state = state
        return self.call("set_simulation_state", req).result

    def wait_future(self, fut, timeout=TIMEOUT):
        end = time.monotonic() + timeout
        while not fut.done():
            assert time.monotonic() < end, "future not done"
            time.sleep(0.001)
        return fut.result()


@pytest.fixture(scope="module")
def client(ros):
    cmd = [sys.executable, "-m", "redmax_ros.node.main", "--ros-args", "-p", "scene:=pendulum",
           "-p", "mode:=lockstep", "-p", "marker_rate:=0.0", "-p", "log_path:=''", "-r", f"__ns:={NS}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    c = StandardClient()
    try:
        c.wait_ready()
        yield c
    finally:
        c.close()
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()


@pytest.fixture()
def paused(client):
    """PAUSED and reset to t = 0."""
    if client.call("get_simulation_state").state.state != SimulationState.STATE_PAUSED:
        assert client.set_state(SimulationState.STATE_PAUSED).result == OK
    assert client.call("reset_simulation", ResetSimulation.Request(scope=ResetSimulation.Request.SCOPE_ALL)) \
        .result.result == OK
    return client


def _pose(state):
    p, q = state.pose.position, state.pose.orientation
    return np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])


def _twist(state):
    a, b = state.twist.linear, state.twist.angular
    return np.array([a.x, a.y, a.z]), np.array([b.x, b.y, b.z])


def _stamp(state):
    return state.header.stamp.sec * 1_000_000_000 + state.header.stamp.nanosec


def test_features_are_the_supported_ones(client):
    f = client.call("get_simulator_features").features
    want = {F for F in (SimulatorFeatures.ENTITY_STATE_GETTING, SimulatorFeatures.SIMULATION_RESET,
                        SimulatorFeatures.SIMULATION_RESET_TIME, SimulatorFeatures.SIMULATION_RESET_STATE,
                        SimulatorFeatures.SIMULATION_STATE_GETTING, SimulatorFeatures.SIMULATION_STATE_SETTING,
                        SimulatorFeatures.SIMULATION_STATE_PAUSE, SimulatorFeatures.STEP_SIMULATION_SINGLE,
                        SimulatorFeatures.STEP_SIMULATION_MULTIPLE, SimulatorFeatures.STEP_SIMULATION_ACTION,
                        SimulatorFeatures.WORLD_LOADING, SimulatorFeatures.WORLD_INFO_GETTING,
                        SimulatorFeatures.AVAILABLE_WORLDS)}
    assert set(f.features) == want
    for unsupported in (SimulatorFeatures.SPAWNING, SimulatorFeatures.DELETING, SimulatorFeatures.ENTITY_STATE_SETTING,
                        SimulatorFeatures.SIMULATION_RESET_SPAWNED, SimulatorFeatures.WORLD_RESOURCE_STRING,
                        SimulatorFeatures.ENTITY_TAGS, SimulatorFeatures.ENTITY_CATEGORIES):
        assert unsupported not in f.features
    assert list(f.spawn_formats) == [] and "bodies" in f.custom_info


def test_state_machine_and_step_only_when_paused(paused):
    c = paused
    assert c.call("get_simulation_state").state.state == SimulationState.STATE_PAUSED
    assert c.set_state(SimulationState.STATE_PAUSED).result == SetSimulationState.Response.ALREADY_IN_TARGET_STATE
    assert c.call("step_simulation", StepSimulation.Request(steps=1)).result.result == OK
    assert c.set_state(SimulationState.STATE_PLAYING).result == OK
    r = c.call("step_simulation", StepSimulation.Request(steps=3)).result
    assert r.result == Result.RESULT_OPERATION_FAILED and "paused" in r.error_message
    assert c.set_state(SimulationState.STATE_STOPPED).result == OK
    assert c.call("get_simulation_state").state.state == SimulationState.STATE_STOPPED
    s = c.call("get_entity_state", GetEntityState.Request(entity="link")).state
    assert _stamp(s) == 0  # stopped = paused and reset
    assert c.call("step_simulation", StepSimulation.Request(steps=1)).result.result == Result.RESULT_OPERATION_FAILED
    assert c.set_state(SimulationState.STATE_NO_WORLD).result == Result.RESULT_FEATURE_UNSUPPORTED
    assert c.set_state(SimulationState.STATE_LOADING_WORLD).result == SetSimulationState.Response.INCORRECT_TRANSITION
    assert c.set_state(SimulationState.STATE_PAUSED).result == OK


def test_steps_and_entity_states_match_the_core(paused):
    c = paused
    assert c.call("step_simulation", StepSimulation.Request(steps=1)).result.result == OK
    assert c.call("step_simulation", StepSimulation.Request(steps=29)).result.result == OK
    sim = Simulator.load("pendulum")
    sim.step(30)
    s = c.call("get_entity_state", GetEntityState.Request(entity="link"))
    assert s.result.result == OK
    assert _stamp(s.state) == 30_000_000 and s.state.header.frame_id == "world"
    p, q = _pose(s.state)
    p0, q0 = sim.body_poses()["link"]
    assert np.max(np.abs(p - p0)) <= 1e-12 and np.max(np.abs(q - q0)) <= 1e-12
    # the pendulum turns about the world y axis through the origin: w = qdot y, v = w x p
    w = sim.joint_velocities()[0] * np.array([0.0, 1.0, 0.0])
    lin, ang = _twist(s.state)
    assert np.max(np.abs(ang - w)) <= 1e-12 and np.max(np.abs(lin - np.cross(w, p0))) <= 1e-12
    a = s.state.acceleration
    assert (a.linear.x, a.linear.y, a.linear.z, a.angular.x, a.angular.y, a.angular.z) == (0.0,) * 6
    many = c.call("get_entities_states")
    assert many.result.result == OK and list(many.entities) == ["link"]
    assert np.array_equal(_pose(many.states[0])[0], p)
    missing = c.call("get_entity_state", GetEntityState.Request(entity="no_such_body"))
    assert missing.result.result == Result.RESULT_NOT_FOUND and "link" in missing.result.error_message


def test_get_entities_filters(client):
    assert list(client.call("get_entities").entities) == ["link"]
    req = GetEntities.Request()
    req.filters.filter = "^li"
    r = client.call("get_entities", req)
    assert r.result.result == OK and list(r.entities) == ["link"]
    req.filters.filter = "^x"
    assert list(client.call("get_entities", req).entities) == []
    req.filters.filter = "("
    assert client.call("get_entities", req).result.result == Result.RESULT_OPERATION_FAILED
    req = GetEntities.Request()
    req.filters.categories = [EntityCategory(category=EntityCategory.CATEGORY_ROBOT)]
    assert client.call("get_entities", req).result.result == Result.RESULT_FEATURE_UNSUPPORTED
    req = GetEntitiesStates.Request()
    req.filters.tags.tags = ["a"]
    assert client.call("get_entities_states", req).result.result == Result.RESULT_FEATURE_UNSUPPORTED


def test_simulate_steps_action_feedback_and_result(paused):
    c = paused
    feedback = []
    goal = SimulateSteps.Goal(steps=25)
    handle = c.wait_future(c.action.send_goal_async(goal, feedback_callback=lambda m: feedback.append(m.feedback)))
    assert handle.accepted
    # rclpy's ActionClient drops feedback arriving after the result: ask for the result once it is in
    end = time.monotonic() + TIMEOUT
    while len(feedback) < 25 and time.monotonic() < end:
        time.sleep(0.01)
    res = c.wait_future(handle.get_result_async()).result
    assert res.result.result == OK
    assert [(f.completed_steps, f.remaining_steps) for f in feedback] == [(k, 25 - k) for k in range(1, 26)]
    assert _stamp(c.call("get_entity_state", GetEntityState.Request(entity="link")).state) == 25_000_000
    # not paused: OPERATION_FAILED
    assert c.set_state(SimulationState.STATE_PLAYING).result == OK
    handle = c.wait_future(c.action.send_goal_async(SimulateSteps.Goal(steps=5)))
    res = c.wait_future(handle.get_result_async()).result
    assert res.result.result == Result.RESULT_OPERATION_FAILED
    assert c.set_state(SimulationState.STATE_PAUSED).result == OK


def test_reset_scopes(paused):
    c = paused
    assert c.call("step_simulation", StepSimulation.Request(steps=40)).result.result == OK
    before = c.call("get_entity_state", GetEntityState.Request(entity="link")).state
    R = ResetSimulation.Request
    assert c.call("reset_simulation", R(scope=R.SCOPE_TIME)).result.result == OK
    s = c.call("get_entity_state", GetEntityState.Request(entity="link")).state
    assert _stamp(s) == 0 and np.array_equal(_pose(s)[0], _pose(before)[0])  # time only
    assert c.call("step_simulation", StepSimulation.Request(steps=10)).result.result == OK
    assert c.call("reset_simulation", R(scope=R.SCOPE_STATE)).result.result == OK
    s = c.call("get_entity_state", GetEntityState.Request(entity="link")).state
    initial = Simulator.load("pendulum").body_poses()["link"][0]
    assert _stamp(s) == 10_000_000 and np.max(np.abs(_pose(s)[0] - initial)) <= 1e-12  # state only
    assert c.call("reset_simulation", R(scope=R.SCOPE_SPAWNED)).result.result == OK  # nothing is spawned
    assert c.call("reset_simulation", R(scope=R.SCOPE_DEFAULT)).result.result == OK
    s = c.call("get_entity_state", GetEntityState.Request(entity="link")).state
    assert _stamp(s) == 0 and np.max(np.abs(_pose(s)[0] - initial)) <= 1e-12


def test_worlds_are_scenes(paused):
    c = paused
    w = c.call("get_current_world")
    assert w.result.result == OK and w.world.name == "pendulum"
    assert w.world.world_resource.uri.endswith("pendulum.yaml")
    avail = c.call("get_available_worlds")
    assert avail.result.result == OK and {"pendulum", "hand", "klann"} <= {x.name for x in avail.worlds}
    bad = c.call("load_world", LoadWorld.Request(uri="no_such_scene"))
    assert bad.result.result == Result.RESULT_NOT_FOUND
    assert c.call("load_world", LoadWorld.Request(uri="world.sdf")).result.result == LoadWorld.Response.UNSUPPORTED_FORMAT
    assert c.call("load_world", LoadWorld.Request()).result.result == LoadWorld.Response.NO_RESOURCE
    assert c.call("load_world", LoadWorld.Request(resource_string="name: x")).result.result == \
        Result.RESULT_FEATURE_UNSUPPORTED
    assert c.call("get_current_world").world.name == "pendulum"  # nothing changed
    try:
        r = c.call("load_world", LoadWorld.Request(uri="chain"))
        assert r.result.result == OK, r.result.error_message
        assert r.world.name == "chain"
        assert c.call("get_simulation_state").state.state == SimulationState.STATE_STOPPED  # as the standard says
        names = list(c.call("get_entities").entities)
        assert names == list(Simulator.load("chain").describe().bodies)
        end = time.monotonic() + TIMEOUT
        while time.monotonic() < end:
            with c.lock:
                if c.descriptions and '<robot name="chain">' in c.descriptions[-1]:
                    break
            time.sleep(0.01)
        with c.lock:
            assert c.descriptions and '<robot name="chain">' in c.descriptions[-1]
    finally:
        r = c.call("load_world", LoadWorld.Request(uri="file://" + str(ROOT / "scenes" / "pendulum.yaml")))
        assert r.result.result == OK, r.result.error_message
        assert c.set_state(SimulationState.STATE_PAUSED).result == OK
