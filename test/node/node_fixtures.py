"""Helpers of the ROS tests (test/node/test_node_*.py, test/logging/test_mcap_node.py): real rclpy
over Fast DDS. Plain code, not fixtures: the test modules import it by name.

The private ROS graph (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, RMW_IMPLEMENTATION) is
set before any test module is imported, by test/conftest.py (pytest_configure); its ``ros`` fixture
initialises rclpy per test module. Importing this module skips the importing test module when rclpy
or redmax_msgs is missing (fails instead when CI is set).
"""
from __future__ import annotations

import os
import threading
import time

import pytest

if os.environ.get("CI"):  # in CI a missing ROS environment is a failure, not a skip
    import rclpy  # noqa: E402
    import redmax_msgs.msg  # noqa: E402,F401
else:
    rclpy = pytest.importorskip("rclpy")
    pytest.importorskip("redmax_msgs.msg", reason="redmax_msgs not built (scripts/setup.sh builds msg_defs/)")

from rclpy.action import ActionClient  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rcl_interfaces.msg import Log  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from redmax_msgs.action import SimulateSteps  # noqa: E402
from redmax_msgs.msg import (BodyTwistCommand, BodyTwists, BodyWrenches, PointForces, PointVelocityCommand,  # noqa: E402
                             SimulationState)
from redmax_msgs.srv import (DescribeScene, GetSimulationState, LoadScene, ReleaseCommands,  # noqa: E402
                             ResetSimulation, SetSimulationState, StepSimulation)

TIMEOUT = 20.0
QOS_STATE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
QOS_LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Client:
    """A test client node spun in its own thread; collects what the simulation node publishes."""

    def __init__(self, name="redmax_test_client", ns=""):
        self.node = Node(name)
        n = self.node
        p = (ns.rstrip("/") + "/") if ns else ""
        self.lock = threading.RLock()
        self.joint_states: list = []
        self.point_forces: list = []
        self.body_wrenches: list = []
        self.prescribed: list = []
        self.prescribed_bodies: list = []
        self.states: list = []
        self.rosout: list = []
        n.create_subscription(JointState, p + "joint_states", self._store(self.joint_states), QOS_STATE)
        n.create_subscription(PointForces, p + "point_forces", self._store(self.point_forces), QOS_STATE)
        n.create_subscription(BodyWrenches, p + "body_wrenches", self._store(self.body_wrenches), QOS_STATE)
        n.create_subscription(BodyTwists, p + "prescribed_bodies", self._store(self.prescribed_bodies), QOS_LATCHED)
        n.create_subscription(JointState, p + "prescribed_joints", self._store(self.prescribed), QOS_LATCHED)
        n.create_subscription(SimulationState, p + "simulation_state", self._store(self.states), QOS_LATCHED)
        n.create_subscription(Log, "/rosout", self._store(self.rosout),
                              QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                                         durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.pub_joint = n.create_publisher(JointState, p + "joint_commands", 10)
        self.pub_point = n.create_publisher(PointVelocityCommand, p + "point_commands", 10)
        self.pub_body = n.create_publisher(BodyTwistCommand, p + "body_commands", 10)
        self.cli = {
            "step": n.create_client(StepSimulation, p + "step_simulation"),
            "reset": n.create_client(ResetSimulation, p + "reset_simulation"),
            "get_state": n.create_client(GetSimulationState, p + "get_simulation_state"),
            "set_state": n.create_client(SetSimulationState, p + "set_simulation_state"),
            "load": n.create_client(LoadScene, p + "load_scene"),
            "describe": n.create_client(DescribeScene, p + "describe_scene"),
            "release": n.create_client(ReleaseCommands, p + "release_commands"),
        }
        self.action = ActionClient(n, SimulateSteps, p + "simulate_steps")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(n)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _store(self, lst):
        def cb(msg):
            with self.lock:
                lst.append(msg)
        return cb

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

    # -- waiting
    def wait_for(self, pred, timeout=TIMEOUT, what="condition"):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                if pred():
                    return
            time.sleep(0.005)
        raise AssertionError(f"timed out waiting for {what}")

    def wait_ready(self, timeout=TIMEOUT):
        for name, c in self.cli.items():
            assert c.wait_for_service(timeout_sec=timeout), f"service {name} not available"
        end = time.monotonic() + timeout
        while any(pub.get_subscription_count() == 0 for pub in (self.pub_joint, self.pub_point, self.pub_body)):
            assert time.monotonic() < end, "node's command subscriptions not matched"
            time.sleep(0.01)

    # -- calls
    def call(self, name, req=None, timeout=TIMEOUT):
        c = self.cli[name]
        if req is None:
            req = c.srv_type.Request()
        fut = c.call_async(req)
        end = time.monotonic() + timeout
        while not fut.done():
            assert time.monotonic() < end, f"service {name} did not answer"
            time.sleep(0.001)
        return fut.result()

    def step(self, n):
        return self.call("step", StepSimulation.Request(steps=n))

    def set_state(self, state):
        req = SetSimulationState.Request()
        req.state.state = state
        return self.call("set_state", req)

    def reset(self, scope=0):
        return self.call("reset", ResetSimulation.Request(scope=scope))

    def load(self, scene, overrides=()):
        return self.call("load", LoadScene.Request(scene=scene, overrides=list(overrides)))

    def describe(self):
        return self.call("describe").description

    def last_state(self):
        with self.lock:
            return self.joint_states[-1] if self.joint_states else None

    def clear(self):
        with self.lock:
            self.joint_states.clear()
            self.point_forces.clear()
            self.body_wrenches.clear()

    def command_joints(self, names, velocities=(), efforts=(), wait_ack=True):
        """Publish a joint command; with wait_ack, wait until prescribed_joints reflects it (the
        node's acknowledgement), so a following step request is ordered after it."""
        m = JointState(name=list(names), velocity=[float(v) for v in velocities],
                       effort=[float(e) for e in efforts])
        if wait_ack:
            self.wait_for(lambda: len(self.prescribed) > 0, what="latched prescribed_joints")
        with self.lock:
            n0 = len(self.prescribed)
        self.pub_joint.publish(m)
        if wait_ack:
            want = dict(zip(m.name, m.velocity))

            def acked():
                if len(self.prescribed) <= n0:
                    return False
                last = self.prescribed[-1]
                got = dict(zip(last.name, last.velocity))
                return all(got.get(k) == v for k, v in want.items())
            self.wait_for(acked, what="prescribed_joints acknowledgement")

    def command_points(self, sites, velocities, frame="world", wait_ack=True):
        from geometry_msgs.msg import Vector3
        m = PointVelocityCommand(sites=list(sites), velocities=[Vector3(x=float(v[0]), y=float(v[1]),
                                                                         z=float(v[2])) for v in velocities])
        m.header.frame_id = frame
        if wait_ack:
            self.wait_for(lambda: len(self.prescribed) > 0, what="latched prescribed_joints")
        with self.lock:
            n0 = len(self.prescribed)
        self.pub_point.publish(m)
        if wait_ack:
            self.wait_for(lambda: len(self.prescribed) > n0, what="prescription acknowledgement")

    def command_bodies(self, bodies, twists, frame="world", wait_ack=True):
        """Publish a BodyTwistCommand; ``twists``: per body (angular (3,), linear (3,)) [rad/s, m/s], None or
        NaN for a free component. With wait_ack, wait until prescribed_bodies has a newer message."""
        from geometry_msgs.msg import Twist, Vector3

        def vec(x):
            x = [float("nan") if c is None else float(c) for c in (x if x is not None else (None,) * 3)]
            return Vector3(x=x[0], y=x[1], z=x[2])
        m = BodyTwistCommand(bodies=list(bodies), twists=[Twist(angular=vec(a), linear=vec(lin)) for a, lin in twists])
        m.header.frame_id = frame
        if wait_ack:
            self.wait_for(lambda: len(self.prescribed_bodies) > 0, what="latched prescribed_bodies")
        with self.lock:
            n0 = len(self.prescribed_bodies)
        self.pub_body.publish(m)
        if wait_ack:
            self.wait_for(lambda: len(self.prescribed_bodies) > n0, what="prescribed_bodies acknowledgement")
        return m

    def errors(self):
        with self.lock:
            return [r.msg for r in self.rosout if r.level >= Log.WARN]


def run_node_in_thread(params: dict, name="redmax", namespace=""):
    """Start RedmaxNode in this process with the given parameters; returns (node, stop)."""
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from redmax_ros.node.main import RedmaxNode

    overrides = [Parameter(k, value=v) for k, v in params.items()]
    node = RedmaxNode(name, namespace=namespace, parameter_overrides=overrides)
    ex = MultiThreadedExecutor(num_threads=4)
    ex.add_node(node)
    stop = threading.Event()

    def spin():
        while not stop.is_set() and rclpy.ok():
            try:
                ex.spin_once(timeout_sec=0.05)
            except Exception:
                if stop.is_set() or not rclpy.ok():
                    break
                raise

    th = threading.Thread(target=spin, daemon=True)
    th.start()

    def shutdown():
        stop.set()
        th.join(5)
        node.close()
        ex.remove_node(node)
        node.destroy_node()

    return node, shutdown


def arrays_equal(a, b):
    import numpy as np
    return np.array_equal(np.asarray(a), np.asarray(b))
