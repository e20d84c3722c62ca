"""Conversions between ROS messages and the core's Python values (no node, no I/O).

Incoming commands are validated here against the scene description *before* anything reaches the
core, so a bad message changes nothing; every error names the offending field or name.
"""
from __future__ import annotations

import array
import math

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from redmax_msgs.msg import Coupling as CouplingMsg
from redmax_msgs.msg import PointForces, PointVelocityCommand, SceneDescription, SolverStats

from redmax_ros.core import DofPositions

WORLD_FRAMES = ("", "world")


class CommandRejected(ValueError):
    """A command message is malformed or names something the scene does not have."""


# ------------------------------------------------------------------------------------------------
# time

def time_msg(t: float) -> Time:
    """Simulated time [s] -> builtin_interfaces/Time, rounded to the nearest nanosecond."""
    ns = int(round(t * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def time_ns(t: float) -> int:
    return int(round(t * 1e9))


def _darr(x) -> array.array:
    a = array.array("d")
    a.frombytes(np.ascontiguousarray(x, dtype=np.float64).tobytes())
    return a


# ------------------------------------------------------------------------------------------------
# commands in

def _check_names(names, what):
    seen = set()
    for n in names:
        if n in seen:
            raise CommandRejected(f"{what}: name '{n}' appears twice")
        seen.add(n)


def joint_command(msg: JointState, desc) -> tuple[dict, dict]:
    """sensor_msgs/JointState -> (prescribed velocities, applied torques), each joint -> array.

    ``name`` entries are joint names (1-DOF joints) or per-DOF names ``<joint>[i]`` as listed in
    the scene's ``velocity_names``; a multi-DOF joint must be given with all its DOFs. ``velocity``
    (prescription) and ``effort`` (applied torque) are each either empty or as long as ``name``;
    ``position`` must be empty (position commands are not supported)."""
    names = list(msg.name)
    vel, eff = list(msg.velocity), list(msg.effort)
    if not names:
        raise CommandRejected("joint command: no names given")
    _check_names(names, "joint command")
    if len(msg.position):
        raise CommandRejected("joint command: position commands are not supported "
                              "(leave 'position' empty; prescribe velocities)")
    if not vel and not eff:
        raise CommandRejected("joint command: both 'velocity' and 'effort' are empty")
    for field, vals in (("velocity", vel), ("effort", eff)):
        if vals and len(vals) != len(names):
            raise CommandRejected(f"joint command: {len(names)} name(s) but {len(vals)} {field} value(s)")
        for n, x in zip(names, vals):
            if not math.isfinite(x):
                raise CommandRejected(f"joint command: non-finite {field} {x} for '{n}'")
    index = desc.dof_index  # velocity name -> (joint, component)
    parts: dict = {}
    for i, n in enumerate(names):
        if n not in index:
            known = ", ".join(desc.velocity_names)
            raise CommandRejected(f"joint command: unknown joint '{n}' in scene '{desc.name}' (known: {known})")
        joint, comp = index[n]
        parts.setdefault(joint, {})[comp] = i
    velocities, torques = {}, {}
    for joint, comps in parts.items():
        nv = desc.joint_nv[joint]
        if len(comps) != nv:
            need = ", ".join(f"{joint}[{k}]" for k in range(nv))
            raise CommandRejected(f"joint command: joint '{joint}' has {nv} DOFs; give all of {need}")
        order = [comps[k] for k in range(nv)]
        if vel:
            velocities[joint] = np.array([vel[i] for i in order])
        if eff:
            torques[joint] = np.array([eff[i] for i in order])
    bad = [j for j in velocities if j not in desc.prescribable_joints]
    if bad:
        raise CommandRejected(f"joint command: joint '{bad[0]}' cannot be prescribed in scene '{desc.name}' "
                              f"(prescribable: {', '.join(desc.prescribable_joints)})")
    return velocities, torques


def point_command(msg: PointVelocityCommand, desc) -> dict:
    """redmax_msgs/PointVelocityCommand -> site -> (3,) world-frame velocity."""
    if msg.header.frame_id not in WORLD_FRAMES:
        raise CommandRejected(f"point command: frame '{msg.header.frame_id}' is not supported "
                              "(use 'world' or leave frame_id empty)")
    sites = list(msg.sites)
    if not sites:
        raise CommandRejected("point command: no site names given")
    _check_names(sites, "point command")
    if len(msg.velocities) != len(sites):
        raise CommandRejected(f"point command: {len(sites)} site(s) but {len(msg.velocities)} velocity vector(s)")
    out = {}
    for s, v in zip(sites, msg.velocities):
        if s not in desc.sites:
            raise CommandRejected(f"point command: unknown site '{s}' in scene '{desc.name}' "
                                  f"(known: {', '.join(desc.sites)})")
        if s not in desc.prescribable_sites:
            raise CommandRejected(f"point command: site '{s}' cannot be prescribed in scene '{desc.name}' "
                                  f"(prescribable: {', '.join(desc.prescribable_sites)})")
        vec = np.array([v.x, v.y, v.z])
        if not np.all(np.isfinite(vec)):
            raise CommandRejected(f"point command: non-finite velocity {vec.tolist()} for site '{s}'")
        out[s] = vec
    return out


# ------------------------------------------------------------------------------------------------
# description

class SceneInfo:
    """The core's SceneDescription plus lookup tables the node needs on every message."""

    def __init__(self, d, solver: str = ""):
        self.d = d
        self.name = d.name
        self.dt = float(d.dt)
        self.solver = solver
        self.velocity_names = list(d.velocity_names)
        self.position_names = list(d.position_names)
        self.sites = list(d.sites)
        self.prescribable_joints = list(d.prescribable_joints)
        self.prescribable_sites = list(d.prescribable_sites)
        self.joint_names = list(d.joint_names)
        self.joint_nv = {j: int(nv) for j, nv in zip(d.joint_names, d.joint_nv)}
        # DOF name (as in velocity_names) -> (joint, component)
        self.dof_index = {}
        for j, nv in self.joint_nv.items():
            if nv == 1:
                self.dof_index[j] = (j, 0)
            else:
                for k in range(nv):
                    self.dof_index[f"{j}[{k}]"] = (j, k)
        # joint_states positions, one per velocity DOF (core/model/dof_positions.py): q itself when
        # nq == nv; quaternion rotations (spherical, free, free3d) as roll, pitch, yaw; planar as x, y, angle
        self.positions = DofPositions.from_description(d)


def description_msg(info: SceneInfo) -> SceneDescription:
    d = info.d
    return SceneDescription(
        name=d.name, dt=float(d.dt), solver=info.solver, nq=int(d.nq), nv=int(d.nv), ndof=int(d.ndof),
        bodies=list(d.bodies), joint_names=list(d.joint_names), joint_types=list(d.joint_types),
        joint_nq=[int(x) for x in d.joint_nq], joint_nv=[int(x) for x in d.joint_nv],
        position_names=list(d.position_names), velocity_names=list(d.velocity_names),
        sites=list(d.sites), site_bodies=list(d.site_bodies),
        prescribable_joints=list(d.prescribable_joints), prescribable_sites=list(d.prescribable_sites),
        couplings=[CouplingMsg(name=c.name, joints=list(c.joints), ratios=[float(r) for r in c.ratios])
                   for c in d.couplings],
        loops=list(d.loops), springs=list(d.springs),
    )


# ------------------------------------------------------------------------------------------------
# state out (messages are reused per scene: only stamps and arrays change per step)

class StateMessages:
    """Builds the per-step messages for one scene, reusing message objects."""

    def __init__(self, info: SceneInfo, frame_id: str = "world"):
        self.info = info
        self.frame_id = frame_id
        self.js = JointState(check_fields=False)
        self.js.name = list(info.velocity_names)
        self.pf = PointForces(check_fields=False)
        self.pf.header.frame_id = frame_id
        self.clock = Clock(check_fields=False)
        self.stats = SolverStats(check_fields=False)

    def joint_state(self, t, q, v, effort) -> JointState:
        m = self.js
        m.header.stamp = time_msg(t)
        m.position = _darr(self.info.positions(q))
        m.velocity = _darr(v)
        m.effort = _darr(effort)
        return m

    def point_forces(self, t, site_forces: dict) -> PointForces:
        m = self.pf
        m.header.stamp = time_msg(t)
        m.sites = list(site_forces)
        m.forces = [Vector3(x=float(f[0]), y=float(f[1]), z=float(f[2])) for f in site_forces.values()]
        return m

    def clock_msg(self, t) -> Clock:
        self.clock.clock = time_msg(t)
        return self.clock

    def solver_stats(self, t, step_index, diag) -> SolverStats:
        m = self.stats
        m.header.stamp = time_msg(t)
        m.header.frame_id = self.frame_id
        m.step = int(step_index)
        m.solver = str(diag.solver)
        m.iterations = int(diag.iterations)
        m.residual = float(diag.residual)
        m.violation_pos = float(diag.violation_pos)
        m.violation_vel = float(diag.violation_vel)
        m.energy_kinetic = float(diag.E_kin)
        m.energy_potential = float(diag.E_pot)
        m.energy_spring = float(diag.E_spring)
        m.energy_total = float(diag.E_total)
        m.step_wall_time = float(diag.wall_time)
        return m


def prescriptions_msg(t, joints: dict, frame_id="world") -> JointState:
    """Currently prescribed joint velocities as a JointState (names per DOF, velocity only)."""
    m = JointState()
    m.header.stamp = time_msg(t)
    m.header.frame_id = frame_id
    names, vel = [], []
    for j, v in joints.items():
        v = np.atleast_1d(v)
        if len(v) == 1:
            names.append(j)
            vel.append(float(v[0]))
        else:
            for k, x in enumerate(v):
                names.append(f"{j}[{k}]")
                vel.append(float(x))
    m.name = names
    m.velocity = vel
    return m


def point_prescriptions_msg(t, sites: dict, frame_id="world") -> PointVelocityCommand:
    m = PointVelocityCommand()
    m.header.stamp = time_msg(t)
    m.header.frame_id = frame_id
    m.sites = list(sites)
    m.velocities = [Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2])) for v in sites.values()]
    return m


# ------------------------------------------------------------------------------------------------
# markers and diagnostics

_BODY_COLOR = ColorRGBA(r=0.55, g=0.6, b=0.7, a=1.0)
_SPRING_COLOR = ColorRGBA(r=0.9, g=0.5, b=0.1, a=1.0)


def markers_msg(t, poses: dict, springs: list, frame_id="world", scale=0.02) -> MarkerArray:
    """Bodies as small axes-aligned cubes at their frames, springs as line segments."""
    stamp = time_msg(t)
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    out.markers.append(clear)
    for i, (name, (p, quat)) in enumerate(poses.items()):
        m = Marker()
        m.header = Header(stamp=stamp, frame_id=frame_id)
        m.ns, m.id, m.type, m.action = "bodies", i, Marker.CUBE, Marker.ADD
        m.pose = Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                      orientation=Quaternion(x=float(quat[0]), y=float(quat[1]), z=float(quat[2]), w=float(quat[3])))
        m.scale = Vector3(x=scale, y=scale, z=scale)
        m.color = _BODY_COLOR
        m.text = name
        out.markers.append(m)
    if springs:
        m = Marker()
        m.header = Header(stamp=stamp, frame_id=frame_id)
        m.ns, m.id, m.type, m.action = "springs", 0, Marker.LINE_LIST, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = scale / 4
        m.color = _SPRING_COLOR
        for _, a, b in springs:
            m.points.append(Point(x=float(a[0]), y=float(a[1]), z=float(a[2])))
            m.points.append(Point(x=float(b[0]), y=float(b[1]), z=float(b[2])))
        out.markers.append(m)
    return out


def diagnostics_msg(wall_stamp: Time, node_name: str, scene: str, values: dict, level=DiagnosticStatus.OK,
                    message="running") -> DiagnosticArray:
    d = DiagnosticArray()
    d.header.stamp = wall_stamp
    st = DiagnosticStatus(level=level, name=f"{node_name}: simulation", message=message,
                          hardware_id=f"redmax:{scene}")
    st.values = [KeyValue(key=k, value=(f"{v:.6g}" if isinstance(v, float) else str(v))) for k, v in values.items()]
    d.status = [st]
    return d
