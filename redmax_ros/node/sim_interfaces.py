"""ROS 2 ``simulation_interfaces`` (the Jazzy line, 1.5.x) served by the node: a translation of the
standard's requests into Engine calls (docs/node.md, "Using it from RViz, Foxglove and
simulation_interfaces clients").

The services and the action are created under the node's private namespace, ``~/<name>`` (e.g.
``/redmax/step_simulation``, as Gazebo serves them under ``/gzserver/``): the node's own names
``step_simulation``, ``reset_simulation``, ``get_simulation_state``, ``set_simulation_state`` and
``simulate_steps`` carry the redmax_msgs versions (with completed steps and sim time in the
answers), and one name cannot carry two types.

Entities are the scene's bodies: pose and twist of the body frame in the world frame (the node's
``frame_id``), the twist as the velocity of the body frame's origin and the angular velocity, both
with world axes; acceleration is not provided (zeros). Worlds are scenes: a scene name (scenes/,
``scene_dirs``) or the path of a scene .yaml file there, as load_scene takes them.
"""
from __future__ import annotations

import os
import re

from geometry_msgs.msg import Accel, Point, Pose, Quaternion, Twist, Vector3
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from std_msgs.msg import Header

from simulation_interfaces.action import SimulateSteps
from simulation_interfaces.msg import (Bounds, EntityState, Resource, Result, SimulationState, SimulatorFeatures,
                                       WorldResource)
from simulation_interfaces.srv import (GetAvailableWorlds, GetCurrentWorld, GetEntities, GetEntitiesStates,
                                       GetEntityState, GetSimulationState, GetSimulatorFeatures, LoadWorld,
                                       ResetSimulation, SetSimulationState, StepSimulation)

from redmax_ros.core import list_scenes

from . import engine as eng
from .convert import time_msg
from .robot_model import BodyTwists

F = SimulatorFeatures
FEATURES = [F.ENTITY_STATE_GETTING, F.SIMULATION_RESET, F.SIMULATION_RESET_TIME, F.SIMULATION_RESET_STATE,
            F.SIMULATION_STATE_GETTING, F.SIMULATION_STATE_SETTING, F.SIMULATION_STATE_PAUSE,
            F.STEP_SIMULATION_SINGLE, F.STEP_SIMULATION_MULTIPLE, F.STEP_SIMULATION_ACTION, F.WORLD_LOADING,
            F.WORLD_INFO_GETTING, F.AVAILABLE_WORLDS]
CUSTOM_INFO = ("redmax_ros (RedMax articulated-body simulator). Entities are the scene's bodies (world-frame pose and "
               "twist; acceleration not provided: zeros). Worlds are scenes: names in scenes/ and scene_dirs, or "
               "paths of scene .yaml files there. Joint commands, point commands and forces, solver statistics and "
               "the scene description are in redmax_msgs and standard topics (joint_commands: velocities, position "
               "targets, torques; joint_trajectory; point_commands, point_forces, solver_stats; service "
               "describe_scene). Services under the node's private namespace (~/).")
SCENE_SUFFIXES = ("", ".yaml", ".yml")


def _result(code, message="") -> Result:
    return Result(result=int(code), error_message="" if code == Result.RESULT_OK else str(message))


def _outcome_result(out, incorrect_state=Result.RESULT_INCORRECT_STATE) -> Result:
    code = out.code
    if code == eng.INCORRECT_STATE:
        code = incorrect_state
    return _result(code, out.message)


def entity_state(t, frame_id, pose, twist) -> EntityState:
    """EntityState of one body: pose (position, quaternion xyzw), twist (linear, angular) world frame."""
    (p, q), (lin, ang) = pose, twist
    return EntityState(
        header=Header(stamp=time_msg(t), frame_id=frame_id),
        pose=Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                  orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))),
        twist=Twist(linear=Vector3(x=float(lin[0]), y=float(lin[1]), z=float(lin[2])),
                    angular=Vector3(x=float(ang[0]), y=float(ang[1]), z=float(ang[2]))),
        acceleration=Accel())


class StandardInterfaces:
    """The simulation_interfaces services and the SimulateSteps action on ``node`` (a RedmaxNode):
    ``node.engine`` does the work, ``node.run_request(fn)`` runs a request (errors become
    OPERATION_FAILED; what it published is out before the answer)."""

    def __init__(self, node, group, qos, prefix="~/"):
        self.node = node
        self._twists = (None, None)  # (mechanism, BodyTwists)
        srv = [(GetSimulatorFeatures, "get_simulator_features", self.features),
               (StepSimulation, "step_simulation", self.step),
               (ResetSimulation, "reset_simulation", self.reset),
               (GetSimulationState, "get_simulation_state", self.get_state),
               (SetSimulationState, "set_simulation_state", self.set_state),
               (GetEntities, "get_entities", self.get_entities),
               (GetEntityState, "get_entity_state", self.get_entity_state),
               (GetEntitiesStates, "get_entities_states", self.get_entities_states),
               (GetCurrentWorld, "get_current_world", self.get_current_world),
               (LoadWorld, "load_world", self.load_world),
               (GetAvailableWorlds, "get_available_worlds", self.get_available_worlds)]
        self.services = [node.create_service(cls, prefix + name, cb, callback_group=group, qos_profile=qos)
                         for cls, name, cb in srv]
        self.action = ActionServer(node, SimulateSteps, prefix + "simulate_steps", execute_callback=self.simulate_steps,
                                   goal_callback=lambda goal: GoalResponse.ACCEPT,
                                   cancel_callback=lambda gh: CancelResponse.ACCEPT, callback_group=group,
                                   goal_service_qos_profile=qos, result_service_qos_profile=qos,
                                   cancel_service_qos_profile=qos, feedback_pub_qos_profile=qos)

    @property
    def engine(self):
        return self.node.engine

    # ------------------------------------------------------------------ simulation control
    def features(self, req, resp):
        resp.features = SimulatorFeatures(features=list(FEATURES), spawn_formats=[], custom_info=CUSTOM_INFO)
        return resp

    def step(self, req, resp):
        """Paused only (otherwise OPERATION_FAILED, as the standard says); returns when done."""
        out = self.node.run_request(lambda: self.engine.step(req.steps), inline=True)
        resp.result = _outcome_result(out, Result.RESULT_OPERATION_FAILED)
        return resp

    def simulate_steps(self, goal_handle):
        n = int(goal_handle.request.steps)
        fb = SimulateSteps.Feedback()

        def feedback(done, total, t):
            fb.completed_steps, fb.remaining_steps = done, total - done
            goal_handle.publish_feedback(fb)

        out = self.node.run_request(lambda: self.engine.step(n, feedback, lambda: goal_handle.is_cancel_requested))
        res = SimulateSteps.Result()
        res.result = _outcome_result(out, Result.RESULT_OPERATION_FAILED)
        if out.extra.get("canceled"):
            res.result = _result(Result.RESULT_OK)
            goal_handle.canceled()
        elif out.ok:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return res

    def reset(self, req, resp):
        """Scopes: DEFAULT/ALL (initial state, t = 0, the scene's prescriptions, no torques), TIME
        (t = 0, state kept), STATE (initial q, v and prescriptions, time kept), SPAWNED (nothing is
        ever spawned: a no-op); combinations as bit fields."""
        resp.result = _outcome_result(self.node.run_request(lambda: self.engine.reset(req.scope)))
        return resp

    def get_state(self, req, resp):
        resp.state = SimulationState(state=self.engine.state)
        resp.result = _result(Result.RESULT_OK)
        return resp

    def set_state(self, req, resp):
        target = int(req.state.state)
        if target == SimulationState.STATE_NO_WORLD:
            resp.result = _result(Result.RESULT_FEATURE_UNSUPPORTED, "a scene is always loaded (no world unloading)")
        elif target == SimulationState.STATE_LOADING_WORLD:
            resp.result = _result(SetSimulationState.Response.INCORRECT_TRANSITION,
                                  "STATE_LOADING_WORLD cannot be requested (use load_world)")
        else:
            resp.result = _outcome_result(self.node.run_request(lambda: self.engine.set_state(target)))
        return resp

    # ------------------------------------------------------------------ entities
    def _match(self, filters):
        """(Result, matching body names) for EntityFilters: the name filter is a regular expression
        searched in each name (Python re; POSIX extended expressions mean the same here); category,
        tag and bounds filters are not supported (FEATURE_UNSUPPORTED)."""
        if len(filters.categories):
            return _result(Result.RESULT_FEATURE_UNSUPPORTED, "entity categories are not supported"), []
        if len(filters.tags.tags):
            return _result(Result.RESULT_FEATURE_UNSUPPORTED, "entity tags are not supported"), []
        if filters.bounds.type != Bounds.TYPE_EMPTY or len(filters.bounds.points):
            return _result(Result.RESULT_FEATURE_UNSUPPORTED, "bounds filters are not supported"), []
        names = list(self.engine.info.d.bodies)
        if filters.filter:
            try:
                rx = re.compile(filters.filter)
            except re.error as e:
                return _result(Result.RESULT_OPERATION_FAILED, f"invalid filter {filters.filter!r}: {e}"), []
            names = [n for n in names if rx.search(n)]
        return _result(Result.RESULT_OK), names

    def _states(self, names):
        """(sim time, {body: EntityState}) of one state, read with exclusive use of the Simulator."""
        frame = self.node.frame_id

        def read(sim):
            mech = sim.mech
            if self._twists[0] is not mech:
                self._twists = (mech, BodyTwists(mech))
            poses = sim.body_poses()
            tw = self._twists[1](sim.state.q, sim.joint_velocities(), names)
            return sim.time, {n: entity_state(sim.time, frame, poses[n], tw[n][:2]) for n in names}

        return self.engine.query(read)

    def get_entities(self, req, resp):
        resp.result, resp.entities = self._match(req.filters)
        return resp

    def get_entity_state(self, req, resp):
        if req.entity not in self.engine.info.d.bodies:
            resp.result = _result(Result.RESULT_NOT_FOUND, f"no entity (body) {req.entity!r} in scene "
                                  f"'{self.engine.info.name}' (bodies: {', '.join(self.engine.info.d.bodies)})")
            return resp
        try:
            _, states = self._states([req.entity])
        except KeyError:  # the scene changed in between
            resp.result = _result(Result.RESULT_NOT_FOUND, f"no entity (body) {req.entity!r}")
            return resp
        resp.state = states[req.entity]
        resp.result = _result(Result.RESULT_OK)
        return resp

    def get_entities_states(self, req, resp):
        result, names = self._match(req.filters)
        resp.result = result
        if result.result != Result.RESULT_OK:
            return resp
        try:
            _, states = self._states(names)
        except KeyError:
            resp.result = _result(Result.RESULT_OPERATION_FAILED, "the scene changed during the request")
            return resp
        resp.entities = names
        resp.states = [states[n] for n in names]
        return resp

    # ------------------------------------------------------------------ worlds (scenes)
    def _world(self) -> WorldResource:
        sim = self.engine.sim
        spec = getattr(sim, "spec", None)
        return WorldResource(name=self.engine.info.name,
                             world_resource=Resource(uri=str(getattr(spec, "source", "") or ""), resource_string=""),
                             description=str(getattr(spec, "description", "") or ""), tags=[])

    def get_current_world(self, req, resp):
        resp.result = _result(Result.RESULT_OK)
        resp.world = self._world()
        return resp

    def load_world(self, req, resp):
        """A scene by name or .yaml path (``file://`` allowed), confined like load_scene; the simulation
        is left STOPPED. resource_string is not supported (FEATURE_UNSUPPORTED)."""
        uri = req.uri
        if not uri:
            if req.resource_string:
                resp.result = _result(Result.RESULT_FEATURE_UNSUPPORTED, "loading a world from resource_string is "
                                      "not supported: give a scene name or .yaml path in uri")
            else:
                resp.result = _result(LoadWorld.Response.NO_RESOURCE, "both uri and resource_string are empty")
            return resp
        if uri.startswith("file://"):
            uri = uri[len("file://"):]
        if os.path.splitext(uri)[1].lower() not in SCENE_SUFFIXES:
            resp.result = _result(LoadWorld.Response.UNSUPPORTED_FORMAT, f"{req.uri!r}: only redmax scene files "
                                  "(.yaml) or scene names are supported")
            return resp
        out = self.node.run_request(lambda: self.engine.load(uri, [], stop=True))
        if out.code == eng.INVALID_SCENE:
            resp.result = _result(LoadWorld.Response.RESOURCE_PARSE_ERROR, out.message)
        else:
            resp.result = _outcome_result(out)
        self.node.scene_changed(out)
        if out.ok:
            resp.world = self._world()
        return resp

    def get_available_worlds(self, req, resp):
        if len(req.additional_sources):
            resp.result = _result(Result.RESULT_FEATURE_UNSUPPORTED, "additional sources are not searched (the "
                                  "node reads scenes from scenes/ and its scene_dirs parameter only)")
            return resp
        if len(req.filter.tags):
            resp.result = _result(Result.RESULT_FEATURE_UNSUPPORTED, "world tags are not supported")
            return resp
        try:
            names = list_scenes(self.engine.scene_dirs)
        except Exception as e:  # a scene directory vanished
            resp.result = _result(Result.RESULT_OPERATION_FAILED, f"{type(e).__name__}: {e}")
            return resp
        resp.worlds = [WorldResource(name=n, world_resource=Resource(uri=n, resource_string=""), description="",
                                     tags=[]) for n in names]
        resp.result = _result(Result.RESULT_OK)
        return resp
