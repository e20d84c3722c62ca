"""redmax_node: the RedMax simulator as a ROS 2 node (thin rclpy layer over node.engine.Engine).

Run: ``redmax_node --ros-args --params-file config/hand.yaml`` (venv console script) or
``ros2 run redmax_ros redmax_node --ros-args --params-file config/hand.yaml`` (apt ROS install).
Topics, services, the action, parameters and QoS are documented in docs/node.md.

Threads: an rclpy MultiThreadedExecutor runs subscriptions, services and the action; they hand
work to the simulation thread (engine.py) in arrival order. The simulation thread publishes: each
outgoing message is serialized once, the bytes go to the MCAP logger (redmax_ros/logging/
mcap_log.py; a separate writer process writes the file), then to DDS (sender.py: by default in the
calling thread with the GIL released for the write). Commands are served by an EventsExecutor
helper node, step_simulation by a thread of its own without an executor (see _start_inputs).
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Point, Pose, Quaternion, Transform, TransformStamped, Twist, Vector3
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType,
                                SetParametersResult)
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy_impl
from rclpy.signals import SignalHandlerOptions
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState, PointCloud2
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

try:  # optional: an rclpy without the EventsExecutor serves everything from the node's executor
    from rclpy.experimental import EventsExecutor
except ImportError:
    EventsExecutor = None

from redmax_msgs.action import SimulateSteps
from redmax_msgs.msg import BodyTwists as BodyTwistsMsg  # robot_model.BodyTwists is the twist evaluator
from redmax_msgs.msg import (BodyTwistCommand, BodyWrenches, PointForces, PointVelocityCommand, Result,
                             SimulationState, SolverStats)
from redmax_msgs.srv import (DescribeScene, GetSimulationState, LoadScene, ReleaseCommands, ResetSimulation,
                             SetSimulationState, StepSimulation)

from redmax_ros.core import SOLVERS as CORE_SOLVERS, SceneError
from redmax_ros.logging.mcap_log import McapLogger

from . import engine as eng
from . import step_server
from .command_reader import CommandReader
from .cdr import (JointStateEncoder, SolverStatsEncoder, StepRecords, TFMessageEncoder, encode_clock, joint_state_key,
                  serialize_message)
from .convert import (StateMessages, body_prescriptions_msg, description_msg, diagnostics_msg, markers_msg,
                      point_prescriptions_msg)
from .convert import prescriptions_msg, time_msg, vertices_msg
from .robot_model import BodyPoses, BodyTwists, Frames, urdf_text
from .sender import Sender
from .sim_interfaces import StandardInterfaces

# ------------------------------------------------------------------------------------------------
# QoS per topic (documented in docs/node.md)

QOS_STATE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
QOS_COMMAND = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
QOS_CLOCK = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
QOS_MARKERS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
QOS_DIAGNOSTICS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
def service_qos(depth: int) -> QoSProfile:
    """Services and the action: reliable, volatile, a request queue of ``depth`` (parameter
    request_queue_depth). The middleware keeps at most this many unanswered requests per service and
    drops the ones beyond it without telling the client; rclpy's default is 10, which lost 5 of 16
    concurrent step_simulation calls."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth), reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


QOS_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
# /tf and /tf_static as tf2_ros' broadcasters offer them (static: transient local, one message holding
# every static transform, replaced on a scene load)
QOS_TF = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
QOS_TF_STATIC = QOS_LATCHED

MODES = ("free_run", "lockstep")
SOLVERS = ("",) + CORE_SOLVERS


def qos_dict(q: QoSProfile) -> dict:
    """``q`` as a dict for ``logging.mcap_log.qos_profiles_yaml``."""
    return {
        "history": "keep_last" if q.history == HistoryPolicy.KEEP_LAST else "keep_all",
        "depth": q.depth,
        "reliability": "reliable" if q.reliability == ReliabilityPolicy.RELIABLE else "best_effort",
        "durability": "transient_local" if q.durability == DurabilityPolicy.TRANSIENT_LOCAL else "volatile",
    }


def type_name(cls) -> str:
    """``pkg/msg/Type`` of a message class."""
    return f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"


def _d(desc, lo=None, hi=None, read_only=False, integer=False, type_=None, constraints=""):
    p = ParameterDescriptor(description=desc, read_only=read_only, additional_constraints=constraints)
    if type_ is not None:
        p.type = type_
    if lo is not None:
        if integer:
            p.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            p.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return p


# name: (default, descriptor). Defaults double as the documentation in docs/node.md.
PARAMETERS = {
    "scene": ("hand", _d("Scene to load at start: a name in scenes/ or a path to a .yaml file. "
                         "Change at runtime with the load_scene service.", read_only=True)),
    "scene_overrides": (Parameter.Type.STRING_ARRAY,
                        _d("Core overrides applied to every scene load, e.g. ['params.n=20'].", read_only=True)),
    "scene_dirs": (Parameter.Type.STRING_ARRAY,
                   _d("Directories load_scene may read scenes from besides the package's scenes/ (names and "
                      "paths resolve inside them; symlinks leaving them, '..' above them, other paths are "
                      "refused with NOT_FOUND). The start scene ('scene') is not restricted.", read_only=True,
                      constraints="existing directories")),
    "dt": (0.0, _d("Time step h [s]; 0 = the scene's own.", 0.0, 0.1, read_only=True)),
    "solver": ("", _d("Solver: '' (scene default), " + ", ".join(CORE_SOLVERS) + " (docs/solvers.md).", read_only=True,
                      constraints="one of '', " + ", ".join(CORE_SOLVERS))),
    "mode": ("free_run", _d("Start state: free_run (PLAYING, paced by real_time_factor) or lockstep "
                            "(PAUSED, steps only on step_simulation / simulate_steps). At runtime use "
                            "set_simulation_state.", read_only=True, constraints="free_run or lockstep")),
    "real_time_factor": (1.0, _d("Free-run pacing: simulated seconds per wall second; 0 = as fast as possible.",
                                 0.0, 1000.0)),
    "publish_rate": (0.0, _d("joint_states / clock / point_forces / body_wrenches / solver_stats rate in Hz of "
                             "simulated time; "
                             "0 = every step. The last step of a step request is always published.",
                             0.0, 1.0e6)),
    "marker_rate": (30.0, _d("markers rate in Hz of simulated time; 0 = off.", 0.0, 1000.0)),
    "tf_rate": (50.0, _d("/tf (every moving body's world pose) and odom (floating or planar bases) rate in Hz of "
                         "simulated time; 0 = off. The last step of a step request is always published.",
                         0.0, 1.0e6)),
    "status_period": (5.0, _d("Wall seconds between one-line console status reports in free-run (sim time, "
                              "real-time factor, steps/s, step failures); 0 = silent.", 0.0, 3600.0)),
    "position_gain": (5.0, _d("Gain b [1/s] of the velocity-level position law that holds position targets "
                              "(joint_commands position) and follows joint_trajectory: each step prescribes "
                              "qdot = qdot_p + b (q_p - q).", 0.0, 1.0e6)),
    "command_timeout": (0.5, _d("A commanded joint/site/body prescription or joint torque is released to passive "
                                "dynamics when no newer command arrives within this many seconds of simulated "
                                "time (one warning per release); 0 = hold forever.", 0.0, 3600.0)),
    "diagnostics_period": (1.0, _d("Wall seconds between /diagnostics messages.", 0.05, 60.0)),
    "max_steps_per_request": (1_000_000, _d("Largest step count accepted by step_simulation / simulate_steps.",
                                            1, 1_000_000_000, integer=True)),
    "step_budget_ms": (50.0, _d("Work one step may do: CPU milliseconds of its iterative solvers (joint-limit QP, "
                                "friction iterations, PCG; JIT compilation and garbage collection excluded) "
                                "with ProxSuite iteration caps. "
                                "Past it the step fails with 'step budget exceeded', the state stays as it was "
                                "(free-run pauses). 0 = unlimited.", 0.0, 60000.0)),
    "request_queue_depth": (1000, _d("Requests each service (and the simulate_steps action) queues while it "
                                     "serves one: concurrent requests beyond this many are dropped by the "
                                     "middleware, below it every request is answered in arrival order. Also the "
                                     "depth of the action's feedback topic.", 10, 100000, read_only=True,
                                     integer=True)),
    "frame_id": ("world", _d("Frame of joint-state-independent outputs (point forces, markers; the world frame "
                             "of body_wrenches and prescribed_bodies).", read_only=True)),
    "log_path": ("", _d("Directory for MCAP logs ('' = no logging). Each run writes "
                        "<log_path>/<scene>_<date>_<time>/<scene>_<i>.mcap.", read_only=True)),
    "log_topics": (Parameter.Type.STRING_ARRAY,
                   _d("Fully qualified topics to record; empty = every topic the node publishes or "
                      "subscribes.", read_only=True)),
    "log_max_bytes": (0, _d("Roll over to a new MCAP file at this size [bytes]; 0 = never.", 0, 2**62,
                            read_only=True, integer=True)),
    "log_max_duration": (0.0, _d("Roll over to a new MCAP file after this many wall seconds; 0 = never.",
                                 0.0, 1.0e7, read_only=True)),
}
RUNTIME = ("real_time_factor", "publish_rate", "marker_rate", "command_timeout", "diagnostics_period",
           "max_steps_per_request", "step_budget_ms", "tf_rate", "status_period", "position_gain")


def _check_value(name, v):
    """Checks beyond the descriptors' types and ranges; returns a reason or None."""
    if name == "mode" and v not in MODES:
        return f"must be one of {', '.join(MODES)}, got {v!r}"
    if name == "solver" and v not in SOLVERS:
        return f"must be one of {', '.join(SOLVERS[1:])} or '' (scene default), got {v!r}"
    if name == "scene" and not v:
        return "must not be empty"
    if name == "scene_dirs" and not all(d and os.path.isdir(d) for d in v):
        return f"every entry must be an existing directory, got {list(v)!r}"
    if isinstance(v, float) and v != v:
        return "must not be NaN"
    return None


def _helper_node(main: Node, suffix: str) -> Node:
    """``<main name>_<suffix>`` in the main node's namespace: no global remappings (a ``__node``
    remap must not give it the main node's name), no parameter or type-description services, no
    rosout."""
    return Node(f"{main.get_name()}_{suffix}", namespace=main.get_namespace(), context=main.context,
                use_global_arguments=False, start_parameter_services=False, enable_rosout=False,
                parameter_overrides=[Parameter("start_type_description_service", value=False)])


class _StepHelper:
    """``<main name>_step``: step_simulation served by step_server.StepServer (a thread of its own
    waiting on this one service; requests and responses as C structs, no Python message objects,
    no executor). Same interface as _EventsHelper."""

    def __init__(self, main: "RedmaxNode", name: str):
        self.node = _helper_node(main, "step")
        self.server = step_server.StepServer(self.node, name, main._step_request, on_error=main._publish_error,
                                             qos_profile=main.qos_service)

    def start(self):
        self.server.start()

    def close(self):
        for fn in (self.server.close, self.node.destroy_node):
            try:
                fn()
            except Exception:
                pass


class _EventsHelper:
    """A helper node (``<main name>_<suffix>``, the main node's namespace, no global remappings,
    no parameter or type-description services, no rosout) spun by rclpy's EventsExecutor in a
    thread of its own."""

    def __init__(self, main: Node, suffix: str):
        self.node = _helper_node(main, suffix)
        self.executor = EventsExecutor(context=main.context)
        self._context = main.context
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"redmax-{suffix}", daemon=True)

    def start(self):
        self.executor.add_node(self.node)
        self._thread.start()

    def _spin(self):
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception:  # context shut down (SIGINT/SIGTERM): the node is closing
                if self._stop.is_set() or not self._context.ok():
                    break
                raise

    def close(self):
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)
        for fn in (self.executor.shutdown, self.node.destroy_node):
            try:
                fn()
            except Exception:
                pass


class _Run:
    """What RedmaxNode.state / run_states keep while they publish steps: the logger and StepRecords (or
    None), the subscriber counts read at the start, the log records and messages not handed over yet."""
    __slots__ = ("logger", "records", "njs", "nclock", "nstats", "blobs", "sends")

    def __init__(self, logger, records, njs, nclock, nstats):
        self.logger, self.records = logger, records
        self.njs, self.nclock, self.nstats = njs, nclock, nstats
        self.blobs, self.sends = [], []


class RedmaxNode(Node):
    def __init__(self, node_name="redmax", **kw):
        super().__init__(node_name, **kw)
        for name, (default, desc) in PARAMETERS.items():
            self.declare_parameter(name, default, desc)
        self.add_on_set_parameters_callback(self._validate_parameters)
        p = {name: self._param(name) for name in PARAMETERS}
        for name, value in p.items():
            reason = _check_value(name, value)
            if reason:
                raise ValueError(f"parameter {name}: {reason}")
        self.frame_id = p["frame_id"]
        self._logged_errors = set()
        self.quit_event = threading.Event()
        self.logger_mcap = None
        self._desc_cache = (None, None)

        # --- outputs
        self._pubs = {}
        self._topic_names = {}
        self.pub_js = self._pub(JointState, "joint_states", QOS_STATE)
        self.pub_pf = self._pub(PointForces, "point_forces", QOS_STATE)
        self.pub_bw = self._pub(BodyWrenches, "body_wrenches", QOS_STATE)
        self.pub_stats = self._pub(SolverStats, "solver_stats", QOS_STATE)
        self.pub_clock = self._pub(Clock, "/clock", QOS_CLOCK)
        self.pub_markers = self._pub(MarkerArray, "markers", QOS_MARKERS)
        self.pub_vertices = self._pub(PointCloud2, "deformable_vertices", QOS_MARKERS)
        self.pub_diag = self._pub(DiagnosticArray, "/diagnostics", QOS_DIAGNOSTICS)
        self.pub_state = self._pub(SimulationState, "simulation_state", QOS_LATCHED)
        self.pub_pj = self._pub(JointState, "prescribed_joints", QOS_LATCHED)
        self.pub_pp = self._pub(PointVelocityCommand, "prescribed_points", QOS_LATCHED)
        self.pub_pb = self._pub(BodyTwistsMsg, "prescribed_bodies", QOS_LATCHED)
        self.pub_tf = self._pub(TFMessage, "/tf", QOS_TF)
        self.pub_tf_static = self._pub(TFMessage, "/tf_static", QOS_TF_STATIC)
        self.pub_description = self._pub(String, "robot_description", QOS_LATCHED)
        self.pub_odom = self._pub(Odometry, "odom", QOS_STATE)
        self._state_handles = (self.pub_js.handle, self.pub_clock.handle, self.pub_stats.handle)  # state(): counts
        self._model = None  # (Frames, BodyTwists, URDF text, BodyPoses, TFMessageEncoder) of the scene (robot_model)
        self._model_published = False

        # --- inputs (raw: the same bytes are logged and decoded once); subscribed at the end of
        # __init__, when the simulation exists (see _start_inputs)
        self._inputs = {"joint_commands": (JointState, self._on_joint_command),
                        "point_commands": (PointVelocityCommand, self._on_point_command),
                        "body_commands": (BodyTwistCommand, self._on_body_command),
                        "joint_trajectory": (JointTrajectory, self._on_joint_trajectory)}
        self._subs = {self.resolve_topic_name(short): (cls, QOS_COMMAND, None)
                      for short, (cls, _) in self._inputs.items()}
        self._topic_by_short = {short: self.resolve_topic_name(short) for short in self._inputs}
        self._helpers = []

        # --- the simulation (loads the scene; SceneError propagates: the node does not start)
        overrides = list(p["scene_overrides"] or [])
        if p["dt"] > 0:
            overrides.append(f"dt={p['dt']!r}")
        if p["solver"]:
            overrides.append(f"solver={p['solver']}")
        self._last_pf_nonempty = False
        self._last_bw_nonempty = False
        self._publish_errors = set()
        self._sender = Sender(context_ok=self.context.ok, on_error=self._publish_error)
        self.msgs = None
        self.stats_enc = SolverStatsEncoder(self.frame_id)
        self._step_records = None  # (logger, cdr.StepRecords or None when not applicable)
        self._stats_forced = False  # build solver_stats every step even for nobody (benchmark)
        self.engine = eng.Engine(
            self, p["scene"], overrides,
            initial_state=eng.PLAYING if p["mode"] == "free_run" else eng.PAUSED,
            real_time_factor=p["real_time_factor"], publish_rate=p["publish_rate"],
            marker_rate=p["marker_rate"], command_timeout=p["command_timeout"],
            diagnostics_period=p["diagnostics_period"], max_steps_per_request=p["max_steps_per_request"],
            scene_dirs=list(p["scene_dirs"] or []), step_budget_ms=p["step_budget_ms"],
            tf_rate=p["tf_rate"], status_period=p["status_period"], position_gain=p["position_gain"])

        # --- logging
        if p["log_path"]:
            self._start_logging(p)

        # --- services and action (reentrant: a long step request does not block the others)
        g = ReentrantCallbackGroup()
        self._service_group = g
        self.qos_service = sq = service_qos(p["request_queue_depth"])
        self.create_service(ResetSimulation, "reset_simulation", self._srv_reset, callback_group=g, qos_profile=sq)
        self.create_service(GetSimulationState, "get_simulation_state", self._srv_get_state, callback_group=g,
                            qos_profile=sq)
        self.create_service(SetSimulationState, "set_simulation_state", self._srv_set_state, callback_group=g,
                            qos_profile=sq)
        self.create_service(LoadScene, "load_scene", self._srv_load, callback_group=g, qos_profile=sq)
        self.create_service(DescribeScene, "describe_scene", self._srv_describe, callback_group=g, qos_profile=sq)
        self.create_service(ReleaseCommands, "release_commands", self._srv_release, callback_group=g, qos_profile=sq)
        # feedback after every step: a reliable feedback topic as deep as the request queue (clients that
        # want every message subscribe with a depth as large; rclpy's default 10 dropped some)
        self._action = ActionServer(self, SimulateSteps, "simulate_steps", execute_callback=self._act_execute,
                                    goal_callback=lambda goal: GoalResponse.ACCEPT,
                                    cancel_callback=lambda gh: CancelResponse.ACCEPT, callback_group=g,
                                    goal_service_qos_profile=sq, result_service_qos_profile=sq,
                                    cancel_service_qos_profile=sq, feedback_pub_qos_profile=sq)
        # simulation_interfaces (the standard, sim_interfaces.py) under ~/: /<ns>/<name>/step_simulation, ...
        self._standard = StandardInterfaces(self, g, sq)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.engine.start()
        self.engine.call(self._initial_publish)
        self._start_inputs()
        self.get_logger().info(
            f"scene '{self.engine.info.name}' (dt = {self.engine.sim.dt:g} s, {len(self.engine.info.velocity_names)} "
            f"DOFs) {eng.STATE_NAMES[self.engine.state]}; "
            + (f"logging to {self.logger_mcap.directory}" if self.logger_mcap else "not logging"))

    # ------------------------------------------------------------------ helpers
    def _param(self, name):
        try:
            return self.get_parameter(name).value
        except rclpy.exceptions.ParameterUninitializedException:
            return []

    def _pub(self, cls, topic, qos):
        pub = self.create_publisher(cls, topic, qos)
        self._pubs[pub.topic_name] = (cls, qos)
        self._topic_names[pub] = pub.topic_name
        return pub

    def _start_inputs(self):
        """Command subscriptions and step_simulation: the latency-critical inputs.

        By default each group is served by a helper node spun by rclpy's C++ EventsExecutor in a
        thread of its own: ``<name>_commands`` (joint_commands, joint_trajectory, point_commands, body_commands) and
        ``<name>_step``
        (step_simulation). rclpy's Python executors rebuild their wait set over all of this node's
        entities for every callback; measured here (load ~1), a step request waited 1.1-1.5 ms
        between the client's call and our callback under the MultiThreadedExecutor and 0.25-0.3 ms
        under the EventsExecutor (a do-nothing service: 0.9-1.1 vs 0.4-0.5 ms round trip), and the
        command-to-state latency at 1 kHz dropped from ~5.5 to ~2.3 ms (medians). Two helpers, not
        one, so that a long step request (which blocks its executor until done) never holds up
        commands. The helpers ignore global remappings (``__node``/``__ns`` must not give them a
        clashing name); topic and service names are resolved with this node's remappings.
        ``<name>_step`` is not spun by any executor: step_server.StepServer waits on the service in
        a thread of its own and takes/answers requests as C structs through ctypes (no Python
        message objects; measured 60-90 us less per round trip than the EventsExecutor, A/B in one
        run at load ~3); ``REDMAX_STEP_SERVER=events`` (or no librcl reachable through ctypes)
        spins it with an EventsExecutor as before. ``REDMAX_EVENTS_EXECUTOR=0`` (or an rclpy
        without the EventsExecutor) serves everything from this node and its executor."""
        events = EventsExecutor is not None and os.environ.get("REDMAX_EVENTS_EXECUTOR", "1") != "0"
        if not events:
            group = MutuallyExclusiveCallbackGroup()
            for short, (cls, cb) in self._inputs.items():
                self._subscribe(self, short, cls, cb, group)
            self.create_service(StepSimulation, "step_simulation", self._srv_step, callback_group=self._service_group,
                                qos_profile=self.qos_service)
            return
        if os.environ.get("REDMAX_COMMAND_READER", "burst") == "events":
            commands = _EventsHelper(self, "commands")
            for short, (cls, cb) in self._inputs.items():
                self._subscribe(commands.node, self._topic_by_short[short], cls, cb, None)
        else:  # command_reader.CommandReader: one thread, drains in bursts (floods, issue 17)
            cnode = _helper_node(self, "commands")
            subs, cbs = [], []
            for short, (cls, cb) in self._inputs.items():
                subs.append(self._subscribe(cnode, self._topic_by_short[short], cls, cb, None))
                cbs.append(cb)
            keyed = [short == "joint_commands" for short in self._inputs]  # newer same-key commands supersede
            commands = CommandReader(cnode, subs, cbs, on_error=self._publish_error,
                                     keys=[joint_state_key if k else None for k in keyed],
                                     superseded=[self._on_joint_command_superseded if k else None for k in keyed])
        step_name = self.resolve_service_name("step_simulation")
        if os.environ.get("REDMAX_STEP_SERVER", "raw") != "events" and step_server.available():
            step = _StepHelper(self, step_name)
        else:
            step = _EventsHelper(self, "step")
            step.node.create_service(StepSimulation, step_name, self._srv_step, qos_profile=self.qos_service)
        self._helpers = [commands, step]
        for h in self._helpers:
            h.start()

    def _subscribe(self, node, topic, cls, cb, group):
        sub = node.create_subscription(cls, topic, lambda data, _cb=cb: _cb(data), QOS_COMMAND, raw=True,
                                       callback_group=group)
        self._subs[sub.topic_name] = (cls, QOS_COMMAND, sub)
        return sub

    def _start_logging(self, p):
        name = "".join(c if c.isalnum() or c in "-_" else "_" for c in self.engine.info.name)
        stamp = time.strftime("%Y%m%d_%H%M%S")
        directory = os.path.join(p["log_path"], f"{name}_{stamp}")
        n = 1
        while os.path.exists(directory):
            n += 1
            directory = os.path.join(p["log_path"], f"{name}_{stamp}_{n}")
        self.logger_mcap = McapLogger(directory, name, max_bytes=p["log_max_bytes"],
                                      max_duration=p["log_max_duration"], topics=list(p["log_topics"] or []))
        for topic, (cls, qos, *_) in list(self._pubs.items()) + list(self._subs.items()):
            self.logger_mcap.add_topic(topic, type_name(cls), [qos_dict(qos)])

    def _send(self, pub, msg):
        self._send_bytes(pub, serialize_message(msg))

    def _send_bytes(self, pub, data: bytes, wake=True):
        """Log first (a message is never lost from the log), then publish the same bytes (see
        sender.py for how)."""
        lg = self.logger_mcap
        if lg is not None:
            lg.write(self._topic_names[pub], data)
        self._sender.send(pub, data, wake)

    def _publish_error(self, text):
        if text not in self._publish_errors:  # each distinct error once
            if len(self._publish_errors) < 1000:
                self._publish_errors.add(text)
            self.get_logger().error(text)

    def _initial_publish(self):
        self.sim_state(self.engine.state)
        self._model_published = True
        self._publish_model()
        self.engine.publish_current()

    def run_request(self, fn, inline=False):
        """Run a request for another module (sim_interfaces.py) as the node's own services do:
        exceptions become OPERATION_FAILED, what it published is out before it returns; ``inline``:
        publish in this thread (a caller that waits for the states anyway, as step requests)."""
        if inline:
            with self._sender.inline():
                return self._guard(fn)
        return self._guard(fn)

    def scene_changed(self, out):
        """Log the outcome of a scene load (load_scene, load_world)."""
        if out.ok:
            self.get_logger().info(f"loaded scene '{self.engine.info.name}'")
        else:
            self.get_logger().error(f"scene load: {out.message}")

    # ------------------------------------------------------------------ parameters
    def _validate_parameters(self, params) -> SetParametersResult:
        for prm in params:
            reason = _check_value(prm.name, prm.value)
            if reason:
                return SetParametersResult(successful=False, reason=f"{prm.name}: {reason}")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params):
        kw = {prm.name: prm.value for prm in params if prm.name in RUNTIME}
        if kw and hasattr(self, "engine"):
            self.engine.configure_async(**kw)

    # ------------------------------------------------------------------ engine sink (simulation thread)
    def scene_loaded(self, info):
        self.msgs = StateMessages(info, self.frame_id)
        self.js_enc = JointStateEncoder(info.velocity_names, "")
        self._desc_cache = (None, None)

    def state(self, t, q, v, effort, site_forces, diag, step_index, body_wrenches=None):
        """One published step: the messages are serialized once (joint_states, /clock and
        solver_stats by the fast CDR encoders, test_node_cdr.py checks them against rclpy's
        serializer), logged together (one lock, one log time), then published in this order.
        A message on one of these volatile topics is encoded only if it is logged or has a
        subscriber, and handed to DDS only with a subscriber (without one it could reach nobody).
        solver_stats is built only when logged or subscribed (its KKT residual is computed for it).
        When all three are logged by the writer process and no point forces or body wrenches go out,
        the log records are built in one piece (cdr.StepRecords: the same bytes as write_many would
        hand over). ``body_wrenches``: body -> (frame 'body' | 'world', required wrench (6,)
        [torque N m; force N]); body_wrenches goes out while any body is prescribed, plus one empty
        message after the last is released (as point_forces). Free-running as fast as possible, the
        DDS writes overlap the next steps on the publisher thread (Sender mode ``auto``, sender.py);
        otherwise they happen here, each when its step is done."""
        run = self._begin_run()
        try:
            self._step_out(run, t, q, v, effort, site_forces, diag, step_index, body_wrenches)
        finally:
            self._end_run(run)

    def run_states(self, results, first_index, body_wrenches):
        """The steps of a recorded run (Engine._publish_each: StepResults, step indices from
        ``first_index``, ``body_wrenches(result)`` as state's argument), each published as ``state``
        publishes it, with the per-call work done once for the run: the publish mode set, the three
        subscriber counts read, the run's log records handed to the logger in one piece
        (write_records) and only then its messages to the sender, the publisher thread woken once.
        A step that goes the general way (point forces, body wrenches) hands over what the run built
        before it first, so the log and DDS keep the order of the steps."""
        run = self._begin_run()
        try:
            step_out = self._step_out
            for i, r in enumerate(results, first_index):
                step_out(run, r.t, r.q, r.v, r.effort, r.site_forces, r.diagnostics, i, body_wrenches(r))
        finally:
            self._end_run(run)

    def _begin_run(self) -> "_Run":
        e = self.__dict__.get("engine")  # None while the engine is made (its first state)
        self._sender.set_overlap(e is not None and e.state == eng.PLAYING and e.rtf <= 0)
        lg = self.logger_mcap
        rec = None
        if lg is not None:
            rec = self._step_records
            if rec is None or rec[0] is not lg:
                rec = self._step_records = (lg, self._make_step_records(lg))
            rec = rec[1]
        hjs, hclock, hstats = self._state_handles
        return _Run(lg, rec, hjs.get_subscription_count(), hclock.get_subscription_count(),
                    hstats.get_subscription_count())

    def _step_out(self, run, t, q, v, effort, site_forces, diag, step_index, body_wrenches):
        """One step's messages (see ``state``): on the StepRecords path kept in ``run`` (handed over by
        ``_flush_run``), otherwise logged and sent now, after what ``run`` holds."""
        lg, rec = run.logger, run.records
        njs, nclock, nstats = run.njs, run.nclock, run.nstats
        if rec is not None and diag is not None and not (site_forces or self._last_pf_nonempty or body_wrenches
                                                         or self._last_bw_nonempty):
            js = self.js_enc.encode(t, self.msgs.info.positions(q), v, effort)
            blob = rec.build(time.time_ns(), t, js, step_index, diag)
            run.blobs.append(blob)
            if njs:
                run.sends.append((self.pub_js, js, njs))
            if nclock:
                i = rec.clock_at(len(js))
                run.sends.append((self.pub_clock, blob[i:i + 12], nclock))
            if nstats:
                run.sends.append((self.pub_stats, blob[rec.stats_at(len(js)):], nstats))
            return
        self._flush_run(run)
        out = []
        names = self._topic_names
        pub = self.pub_js
        if njs or (lg is not None and lg.logs(names[pub])):
            out.append((pub, self.js_enc.encode(t, self.msgs.info.positions(q), v, effort), njs))
        pub = self.pub_clock
        if nclock or (lg is not None and lg.logs(names[pub])):
            out.append((pub, encode_clock(t), nclock))
        if site_forces or self._last_pf_nonempty:
            out.append((self.pub_pf, serialize_message(self.msgs.point_forces(t, site_forces)), None))
            self._last_pf_nonempty = bool(site_forces)
        if body_wrenches or self._last_bw_nonempty:
            out.append((self.pub_bw, serialize_message(self.msgs.body_wrenches(t, body_wrenches or {})), None))
            self._last_bw_nonempty = bool(body_wrenches)
        pub = self.pub_stats
        if diag is not None and (nstats or self._stats_forced or (lg is not None and lg.logs(names[pub]))):
            out.append((pub, self.stats_enc.encode(t, step_index, diag), nstats))
        if lg is not None and out:
            lg.write_many([(names[p], data) for p, data, _ in out])
        send = self._sender.send
        for p, data, n in out:
            if n is None or n:
                send(p, data, False, n)

    def _flush_run(self, run):
        """Hand what ``run`` holds to the logger (one piece), then its messages to the sender."""
        if run.blobs:
            blobs, run.blobs = run.blobs, []
            run.logger.write_records(blobs[0] if len(blobs) == 1 else b"".join(blobs), 3 * len(blobs))
        if run.sends:
            sends, run.sends = run.sends, []
            send = self._sender.send
            for p, data, n in sends:
                send(p, data, False, n)

    def _end_run(self, run):
        self._flush_run(run)
        self._sender.wake()

    def _make_step_records(self, lg):
        """cdr.StepRecords for ``lg``, or None when that path does not apply (the thread writer, or
        one of joint_states, /clock, solver_stats not logged)."""
        names = self._topic_names
        topics = (names[self.pub_js], names[self.pub_clock], names[self.pub_stats])
        if getattr(lg, "writer", None) != "process" or not all(lg.logs(x) for x in topics):
            return None
        return StepRecords(lg, *topics, self.stats_enc)

    def robot_model(self, sim):
        """A scene was adopted: its frames, twist evaluator and URDF (robot_model.py); published on
        robot_description and /tf_static (both transient local) once the node has started."""
        try:
            frames = Frames(sim, self.frame_id)
            self._model = (frames, BodyTwists(sim.mech), urdf_text(sim, self.frame_id),
                           BodyPoses(sim.mech, frames.moving), TFMessageEncoder(frames.world, frames.moving))
        except Exception as e:  # a model the URDF writer does not understand: no robot model, the rest runs
            self._model = None
            self.get_logger().error(f"robot model of scene '{sim.scene_name}' not built: {type(e).__name__}: {e}")
        if self._model_published:
            self._publish_model()

    def _publish_model(self):
        if self._model is None:
            return
        frames, _, urdf, _, _ = self._model
        self._send(self.pub_description, String(data=urdf))
        tf = TFMessage()
        stamp = time_msg(0.0)
        for parent, child, p, q in frames.static:
            tf.transforms.append(_transform(stamp, parent, child, p, q))
        self._send(self.pub_tf_static, tf)

    def frames(self, t, sim):
        """/tf: every moving body's world pose (robot_model.BodyPoses: Pinocchio forward kinematics,
        the core's body poses to rounding), encoded by cdr.TFMessageEncoder; odom for each floating or
        planar base: pose in the world frame, twist in the body frame. Built only when subscribed or
        logged."""
        if self._model is None:
            return
        frames, twists, _, body_poses, tf_enc = self._model
        names = self._topic_names
        lg = self.logger_mcap
        if self.pub_tf.handle.get_subscription_count() or (lg is not None and lg.logs(names[self.pub_tf])):
            P, Q = body_poses(sim.state.q)
            self._send_bytes(self.pub_tf, tf_enc.encode(t, P, Q))
        if frames.floating and (self.pub_odom.handle.get_subscription_count()
                                or (lg is not None and lg.logs(names[self.pub_odom]))):
            poses = sim.body_poses()
            tw = twists(sim.state.q, sim.joint_velocities(), frames.floating)
            stamp = time_msg(t)
            for b in frames.floating:
                p, q = poses[b]
                m = Odometry(child_frame_id=b)
                m.header.stamp, m.header.frame_id = stamp, frames.world
                m.pose.pose = Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                   orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
                lin, ang = tw[b][2], tw[b][3]
                m.twist.twist = Twist(linear=Vector3(x=float(lin[0]), y=float(lin[1]), z=float(lin[2])),
                                      angular=Vector3(x=float(ang[0]), y=float(ang[1]), z=float(ang[2])))
                self._send(self.pub_odom, m)

    def status(self, text):
        self.get_logger().info(text)

    def markers(self, t, poses, springs, meshes=None, contacts=None, shapes=None):
        self._send(self.pub_markers, markers_msg(t, poses, springs, self.frame_id, meshes=meshes, contacts=contacts,
                                                 shapes=shapes))

    def vertices(self, t, positions):
        self._send(self.pub_vertices, vertices_msg(t, positions, self.frame_id))

    def diagnostics(self, values, ok, message):
        level = DiagnosticStatus.OK if ok else DiagnosticStatus.WARN
        values["publish_backlog"] = self._sender.backlog
        values["publish_waits"] = self._sender.waits
        if self.logger_mcap is not None:
            values["log_backlog"] = self.logger_mcap.backlog
            values["log_messages_written"] = self.logger_mcap.written
            if self.logger_mcap.error is not None:
                level, message = DiagnosticStatus.ERROR, f"MCAP logging failed: {self.logger_mcap.error}"
        stamp = self.get_clock().now().to_msg()
        self._send(self.pub_diag, diagnostics_msg(stamp, self.get_fully_qualified_name(), self.engine.info.name, values, level,
                                                  message))

    def sim_state(self, state):
        self._send(self.pub_state, SimulationState(state=state))

    def prescriptions(self, t, joints, sites, bodies):
        self._send(self.pub_pj, prescriptions_msg(t, joints, self.frame_id))
        self._send(self.pub_pp, point_prescriptions_msg(t, sites, self.frame_id))
        self._send(self.pub_pb, body_prescriptions_msg(t, bodies, self.frame_id))

    def command_error(self, text):
        if text not in self._logged_errors:  # each distinct error once
            if len(self._logged_errors) < 10000:
                self._logged_errors.add(text)
            self.get_logger().error(f"command rejected: {text}")

    def warn(self, text):
        self.get_logger().warning(text)

    def quit(self):
        self.quit_event.set()

    # ------------------------------------------------------------------ subscriptions (executor)
    def _log_in(self, sub_topic, data):
        lg = self.logger_mcap
        if lg is not None:
            lg.write(sub_topic, data)

    def _on_joint_command(self, data):
        self._log_in(self._topic_of("joint_commands"), data)
        self.engine.joint_command(deserialize_message(data, JointState))

    def _on_joint_command_superseded(self, data):
        """A joint command a newer one with the same names and fields followed in one drain
        (command_reader.py): logged as received, counted as coalesced, not read."""
        self._log_in(self._topic_of("joint_commands"), data)
        self.engine.command_superseded()

    def _on_joint_trajectory(self, data):
        self._log_in(self._topic_of("joint_trajectory"), data)
        self.engine.joint_trajectory(deserialize_message(data, JointTrajectory))

    def _on_point_command(self, data):
        self._log_in(self._topic_of("point_commands"), data)
        self.engine.point_command(deserialize_message(data, PointVelocityCommand))

    def _on_body_command(self, data):
        self._log_in(self._topic_of("body_commands"), data)
        self.engine.body_command(deserialize_message(data, BodyTwistCommand))

    def _topic_of(self, short):
        return self._topic_by_short[short]

    # ------------------------------------------------------------------ services (executor)
    @staticmethod
    def _result(out) -> Result:
        return Result(result=int(out.code), error_message=out.message if out.code != eng.OK else "")

    def _step_request(self, steps):
        """step_simulation for step_server.StepServer: (code, error message, completed steps, sim
        time [s]); the same as _srv_step without message objects."""
        with self._sender.inline():  # publish in this thread: the answer waits for the states anyway
            out = self._guard(lambda: self.engine.step(steps))  # drains what other threads queued
        return out.code, (out.message if out.code != eng.OK else ""), out.steps, out.t if out.t else self.engine.sim.time

    def _srv_step(self, req, resp):
        with self._sender.inline():  # publish in this thread: the answer waits for the states anyway
            out = self._guard(lambda: self.engine.step(req.steps))  # drains what other threads queued
        resp.result = self._result(out)
        resp.completed_steps = int(out.steps)
        resp.sim_time = time_msg(out.t if out.t else self.engine.sim.time)
        return resp

    def _srv_reset(self, req, resp):
        resp.result = self._result(self._guard(lambda: self.engine.reset(req.scope)))
        return resp

    def _srv_get_state(self, req, resp):
        resp.state = SimulationState(state=self.engine.state)
        resp.result = Result(result=eng.OK)
        return resp

    def _srv_set_state(self, req, resp):
        resp.result = self._result(self._guard(lambda: self.engine.set_state(req.state.state)))
        return resp

    def _srv_load(self, req, resp):
        out = self._guard(lambda: self.engine.load(req.scene, list(req.overrides)))
        resp.result = self._result(out)
        if out.ok:
            self.get_logger().info(f"loaded scene '{self.engine.info.name}'")
        else:
            self.get_logger().error(f"load_scene {req.scene[:200]!r}: {out.message}")  # repr: the caller's text
        resp.description = self._description()
        return resp

    def _srv_describe(self, req, resp):
        resp.result = Result(result=eng.OK)
        resp.description = self._description()
        return resp

    def _srv_release(self, req, resp):
        resp.result = self._result(self._guard(lambda: self.engine.release(list(req.joints), list(req.sites),
                                                                                list(req.bodies))))
        return resp

    def _description(self):
        info = self.engine.info
        if self._desc_cache[0] is not info:
            self._desc_cache = (info, description_msg(info))
        return self._desc_cache[1]

    def _guard(self, fn):
        """Run a request; any unexpected exception becomes OPERATION_FAILED, the node keeps serving.
        What the request published (states after reset/load/steps, acknowledgements) is handed to
        DDS before the answer goes out, as when publishing was synchronous."""
        try:
            return fn()
        except Exception as e:
            self.get_logger().error(f"request failed: {type(e).__name__}: {e}")
            return eng.Outcome(eng.OPERATION_FAILED, f"{type(e).__name__}: {e}", t=self.engine.sim.time)
        finally:
            self._sender.drain()

    def _act_execute(self, goal_handle):
        n = int(goal_handle.request.steps)
        fb = SimulateSteps.Feedback()

        def feedback(done, total, t):
            fb.completed_steps, fb.remaining_steps, fb.sim_time = done, total - done, time_msg(t)
            goal_handle.publish_feedback(fb)

        out = self._guard(lambda: self.engine.step(n, feedback, lambda: goal_handle.is_cancel_requested))
        res = SimulateSteps.Result()
        res.result = self._result(out)
        res.completed_steps = int(out.steps)
        res.sim_time = time_msg(out.t)
        if out.extra.get("canceled"):
            goal_handle.canceled()
        elif out.ok:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return res

    # ------------------------------------------------------------------ shutdown
    def destroy_node(self):
        self.close()  # the publisher thread (publish mode 'thread') must stop before the publishers go
        super().destroy_node()

    def close(self):
        """Stop the simulation thread, then finish the MCAP file (everything handed over is written).
        Idempotent."""
        if getattr(self, "_closed", False):
            return
        self._closed = True
        if getattr(self, "engine", None) is not None:
            self.engine.stop(timeout=0.0)  # first: a running step request ends at its next step
        for h in getattr(self, "_helpers", []):
            h.close()
        self._helpers = []
        if getattr(self, "engine", None) is not None:
            self.engine.stop()
        if getattr(self, "_sender", None) is not None:
            self._sender.close()
        if getattr(self, "logger_mcap", None) is not None:
            self.logger_mcap.close()
            if self.logger_mcap.error is not None:
                self.get_logger().error(f"MCAP logging failed: {self.logger_mcap.error}")


def _transform(stamp, parent, child, p, q) -> TransformStamped:
    m = TransformStamped(child_frame_id=child)
    m.header.stamp, m.header.frame_id = stamp, parent
    m.transform = Transform(translation=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                            rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
    return m


def main(argv=None):
    """Run the node until SIGINT/SIGTERM or set_simulation_state(QUITTING). The signals only set a flag
    (rclpy's own handlers are not installed: they shut the context down while the simulation thread
    still publishes, which printed RCLError and rosout failures on every Ctrl-C); the loop then stops
    the simulation thread, finishes the MCAP log and shuts rclpy down, in that order."""
    args = sys.argv if argv is None else argv
    # The simulation thread and the executor threads share the GIL; a short switch interval
    # (default 5 ms) bounds how long a command or a service request waits for a running step.
    sys.setswitchinterval(float(os.environ.get("REDMAX_SWITCH_INTERVAL", "0.0005")))
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except _rclpy_impl.RCLError as e:  # e.g. '-p log_path:=' (an empty value is not ROS argument syntax)
        print(f"redmax_node: cannot parse the ROS arguments: {str(e).split(', at ')[0]}. An empty string "
              "parameter is written -p name:=\"''\" (e.g. -p log_path:=\"''\": no log).", file=sys.stderr)
        return 2
    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = executor = None
    try:
        try:
            node = RedmaxNode()
        except (SceneError, ValueError, rclpy.exceptions.InvalidParameterValueException) as e:
            print(f"redmax_node: cannot start: {e}", file=sys.stderr)
            return 2
        if stop.is_set():  # a signal during start-up
            return 0
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        while rclpy.ok() and not stop.is_set() and not node.quit_event.is_set():
            executor.spin_once(timeout_sec=0.1)
        if node.quit_event.is_set() and not stop.is_set():  # let the set_simulation_state(QUITTING) response go out
            end = time.monotonic() + 0.5
            while rclpy.ok() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.05)
        return 0
    except ExternalShutdownException:
        return 0
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.close()
            try:
                node.destroy_node()
            except Exception:
                pass
        if rclpy.ok():
            rclpy.shutdown()
        for s, h in previous.items():
            signal.signal(s, h)


def cli():
    """The ``redmax_node`` console script: main(), then exit without the interpreter's teardown. Once
    main() returned, the simulation thread has stopped, the MCAP log is complete and rclpy is shut
    down; what remained was 3-7 s of C-level teardown (module and DDS/numba/Pinocchio static
    destructors, measured on this machine at load ~9 from the signal to the process end), so the
    process ends at once instead (exit within 1 s of SIGINT/SIGTERM)."""
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    cli()
