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
from geometry_msgs.msg import Point, Pose, Quaternion, Twist, Vector3, Wrench
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import Marker, MarkerArray

from redmax_msgs.msg import Coupling as CouplingMsg
from redmax_msgs.msg import (BodyTwistCommand, BodyTwists, BodyWrenches, PointForces, PointVelocityCommand,
                             SceneDescription)

from redmax_ros.core import DofPositions

WORLD_FRAMES = ("", "world")
BODY_FRAME = "body"  # BodyTwistCommand header.frame_id: each body's own frame


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


def joint_command(msg: JointState, desc) -> tuple[dict, dict, dict]:
    """sensor_msgs/JointState -> (prescribed velocities, applied torques, position targets), each
    joint -> array.

    ``name`` entries are joint names (1-DOF joints) or per-DOF names ``<joint>[i]`` as listed in
    the scene's ``velocity_names``; a multi-DOF joint must be given with all its DOFs. ``velocity``
    (prescription), ``position`` (a target held by the velocity-level position law, positions per
    DOF as in joint_states) and ``effort`` (applied torque) are each either empty or as long as
    ``name``; ``position`` and ``velocity`` not both."""
    names = list(msg.name)
    vel, eff, pos = list(msg.velocity), list(msg.effort), list(msg.position)
    if not names:
        raise CommandRejected("joint command: no names given")
    _check_names(names, "joint command")
    if pos and vel:
        raise CommandRejected("joint command: give 'position' (a target) or 'velocity' (a prescription), not both")
    if not vel and not eff and not pos:
        raise CommandRejected("joint command: 'position', 'velocity' and 'effort' are all empty")
    for field, vals in (("velocity", vel), ("effort", eff), ("position", pos)):
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
    velocities, torques, positions = {}, {}, {}
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
        if pos:
            positions[joint] = np.array([pos[i] for i in order])
    bad = [j for j in list(velocities) + list(positions) if j not in desc.prescribable_joints]
    if bad:
        raise CommandRejected(f"joint command: joint '{bad[0]}' cannot be prescribed in scene '{desc.name}' "
                              f"(prescribable: {', '.join(desc.prescribable_joints)})")
    _check_position_joints(list(positions), desc, "joint command")
    return velocities, torques, positions


def _check_position_joints(joints, desc, what):
    """Position targets and trajectories need joints whose positions are coordinates (the core's
    trajectory joints: nq = nv, or a continuous revolute joint's (cos, sin))."""
    for j in joints:
        nq, nv = desc.joint_nq[j], desc.joint_nv[j]
        if not (nq == nv or (nq, nv) == (2, 1)):
            raise CommandRejected(f"{what}: joint '{j}' ({desc.joint_types[j]}) cannot follow positions: its "
                                  "positions are not coordinates")


def _duration(d) -> float:
    """builtin_interfaces Duration/Time -> seconds, correctly rounded (0.2 s is 0.2)."""
    return (d.sec * 1_000_000_000 + d.nanosec) / 1e9


class TrajectoryCommand:
    """A validated trajectory_msgs/JointTrajectory for one joint, resolved against the current state
    when it is applied (``prescription``): per DOF the piecewise-cubic (Hermite) q_p(t) through the
    waypoints at times ``start + time_from_start``, ``start`` = the message's stamp in sim time or,
    for a zero stamp, the time it is applied. When the first waypoint lies after the start, the
    joint's position (and, with waypoint velocities, its velocity) at the start is the first point;
    with velocities the curve has them at the waypoints (C1), without it is the C2 cubic spline with
    zero rate at its ends. After the last waypoint the last position is held."""

    def __init__(self, joint: str, start, times, positions, velocities, gain: float):
        self.joint, self.start, self.gain = joint, start, float(gain)
        self.times = np.asarray(times, float)  # (P,) time_from_start [s]
        self.positions = np.asarray(positions, float)  # (P, nv)
        self.velocities = None if velocities is None else np.asarray(velocities, float)  # (P, nv) or None

    def prescription(self, t_now: float, q_now, v_now) -> tuple:
        """(the core's trajectory prescription {position: [...], b}, end time [s])."""
        t0 = t_now if self.start is None else float(self.start)
        ts = t0 + self.times
        pos, vel = self.positions, self.velocities
        begin = max(t0, t_now)
        if ts[0] > begin + 1e-12:  # from where the joint is now
            ts = np.concatenate([[begin], ts])
            pos = np.vstack([np.asarray(q_now, float)[None, :], pos])
            if vel is not None:
                vel = np.vstack([np.asarray(v_now, float)[None, :], vel])
        fns = []
        for k in range(pos.shape[1]):
            if len(ts) == 1:
                fns.append(float(pos[0, k]))
            elif vel is None:
                fns.append({"type": "cubic", "points": [[float(t), float(x)] for t, x in zip(ts, pos[:, k])]})
            else:
                fns.append({"type": "cubic", "points": [[float(t), float(x), float(v)]
                                                        for t, x, v in zip(ts, pos[:, k], vel[:, k])]})
        return {"position": fns, "b": self.gain}, float(ts[-1])


def joint_trajectory(msg: JointTrajectory, desc, gain: float) -> dict:
    """trajectory_msgs/JointTrajectory -> joint -> TrajectoryCommand. ``joint_names`` as joint_commands'
    names (per-DOF names for multi-DOF joints, all DOFs of a joint); every point has one position per
    name, velocities for all points or none (accelerations and effort are not used); time_from_start
    strictly increasing, >= 0. A zero header stamp starts the trajectory when it is applied."""
    names = list(msg.joint_names)
    if not names:
        raise CommandRejected("joint trajectory: no joint_names given")
    _check_names(names, "joint trajectory")
    pts = list(msg.points)
    if not pts:
        raise CommandRejected("joint trajectory: no points given")
    times = [_duration(p.time_from_start) for p in pts]
    if times[0] < 0 or any(b <= a for a, b in zip(times, times[1:])):
        raise CommandRejected(f"joint trajectory: time_from_start must be >= 0 and strictly increasing, got {times}")
    with_vel = [len(p.velocities) > 0 for p in pts]
    if any(with_vel) and not all(with_vel):
        raise CommandRejected("joint trajectory: give velocities for every point or for none")
    for i, p in enumerate(pts):
        for field, vals in (("positions", p.positions), ("velocities", p.velocities)):
            if field == "velocities" and not with_vel[0]:
                continue
            if len(vals) != len(names):
                raise CommandRejected(f"joint trajectory: point {i}: {len(names)} joint name(s) but {len(vals)} "
                                      f"{field}")
            if not all(math.isfinite(x) for x in vals):
                raise CommandRejected(f"joint trajectory: point {i}: non-finite {field}")
    index = desc.dof_index
    parts: dict = {}
    for i, n in enumerate(names):
        if n not in index:
            raise CommandRejected(f"joint trajectory: unknown joint '{n}' in scene '{desc.name}' "
                                  f"(known: {', '.join(desc.velocity_names)})")
        joint, comp = index[n]
        parts.setdefault(joint, {})[comp] = i
    stamp = msg.header.stamp
    start = None if stamp.sec == 0 and stamp.nanosec == 0 else _duration(stamp)
    out = {}
    for joint, comps in parts.items():
        nv = desc.joint_nv[joint]
        if len(comps) != nv:
            need = ", ".join(f"{joint}[{k}]" for k in range(nv))
            raise CommandRejected(f"joint trajectory: joint '{joint}' has {nv} DOFs; give all of {need}")
        if joint not in desc.prescribable_joints:
            raise CommandRejected(f"joint trajectory: joint '{joint}' cannot be prescribed in scene '{desc.name}' "
                                  f"(prescribable: {', '.join(desc.prescribable_joints)})")
        order = [comps[k] for k in range(nv)]
        pos = [[p.positions[i] for i in order] for p in pts]
        vel = [[p.velocities[i] for i in order] for p in pts] if with_vel[0] else None
        out[joint] = TrajectoryCommand(joint, start, times, pos, vel, gain)
    _check_position_joints(list(out), desc, "joint trajectory")
    return out


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


def body_command(msg: BodyTwistCommand, desc) -> dict:
    """redmax_msgs/BodyTwistCommand -> body -> the core's body-twist prescription
    ``{"angular": [wx, wy, wz], "linear": [vx, vy, vz], "frame": "body" | "world"}`` (angular [rad/s],
    linear [m/s] = velocity of the body origin; None = a free component, NaN in the message).
    header.frame_id "" or "world": world-aligned axes at each body's origin; "body": each body's own
    frame. A body with all six components NaN, or any infinite component, is rejected. Whether the
    scene steps on the Pinocchio pipeline is the core's check (Simulator.prescribe_bodies)."""
    fid = msg.header.frame_id
    if fid in WORLD_FRAMES:
        frame = "world"
    elif fid == BODY_FRAME:
        frame = BODY_FRAME
    else:
        raise CommandRejected(f"body command: frame '{fid}' is not supported (use 'world' or empty for "
                              "world-aligned axes at the body origin, 'body' for the body's own frame)")
    bodies = list(msg.bodies)
    if not bodies:
        raise CommandRejected("body command: no body names given")
    _check_names(bodies, "body command")
    if len(msg.twists) != len(bodies):
        raise CommandRejected(f"body command: {len(bodies)} body(ies) but {len(msg.twists)} twist(s)")
    out = {}
    for b, tw in zip(bodies, msg.twists):
        if b not in desc.bodies:
            raise CommandRejected(f"body command: unknown body '{b}' in scene '{desc.name}' "
                                  f"(known: {', '.join(desc.bodies)})")
        presc = {"frame": frame}
        given = 0
        for key, vec in (("angular", tw.angular), ("linear", tw.linear)):
            vals = [vec.x, vec.y, vec.z]
            for c, x in zip("xyz", vals):
                if math.isinf(x):
                    raise CommandRejected(f"body command: non-finite {key}.{c} = {x} for body '{b}' "
                                          "(NaN marks a free component)")
            comps = [None if math.isnan(x) else float(x) for x in vals]
            given += sum(x is not None for x in comps)
            presc[key] = comps
        if not given:
            raise CommandRejected(f"body command: all six twist components of body '{b}' are NaN (free); "
                                  "prescribe at least one (release_commands releases a body)")
        out[b] = presc
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
        self.bodies = list(d.bodies)
        self.prescribable_joints = list(d.prescribable_joints)
        self.prescribable_sites = list(d.prescribable_sites)
        self.joint_names = list(d.joint_names)
        self.joint_nv = {j: int(nv) for j, nv in zip(d.joint_names, d.joint_nv)}
        self.joint_nq = {j: int(nq) for j, nq in zip(d.joint_names, d.joint_nq)}
        self.joint_types = dict(zip(d.joint_names, d.joint_types))
        self.joint_offset = {}  # joint -> index of its first DOF in velocity_names (joint_states order)
        k = 0
        for j, nv in self.joint_nv.items():
            self.joint_offset[j] = k
            k += nv
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
        self.bw = BodyWrenches(check_fields=False)
        self.bw.header.frame_id = frame_id
        self.clock = Clock(check_fields=False)

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

    def body_wrenches(self, t, wrenches: dict) -> BodyWrenches:
        """body -> (frame 'body' | 'world', the core's required wrench (6,) [torque N m; force N])."""
        m = self.bw
        m.header.stamp = time_msg(t)
        m.bodies = list(wrenches)
        m.frames = [f for f, _ in wrenches.values()]
        m.wrenches = [Wrench(force=Vector3(x=float(w[3]), y=float(w[4]), z=float(w[5])),
                             torque=Vector3(x=float(w[0]), y=float(w[1]), z=float(w[2])))
                      for _, w in wrenches.values()]
        return m

    def clock_msg(self, t) -> Clock:
        self.clock.clock = time_msg(t)
        return self.clock


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


_TWIST_COMPONENTS = ("wx", "wy", "wz", "vx", "vy", "vz")  # Simulator.prescribed_bodies' component names


def body_prescriptions_msg(t, bodies: dict, frame_id="world") -> BodyTwists:
    """Simulator.prescribed_bodies() (body -> {components, values, frame}) as redmax_msgs/BodyTwists:
    per body its frame and the twist with NaN for the components not prescribed."""
    m = BodyTwists()
    m.header.stamp = time_msg(t)
    m.header.frame_id = frame_id
    m.bodies = list(bodies)
    m.frames = [str(p["frame"]) for p in bodies.values()]
    twists = []
    for p in bodies.values():
        v = [math.nan] * 6
        for c, x in zip(p["components"], p["values"]):
            v[_TWIST_COMPONENTS.index(c)] = float(x)
        twists.append(Twist(angular=Vector3(x=v[0], y=v[1], z=v[2]), linear=Vector3(x=v[3], y=v[4], z=v[5])))
    m.twists = twists
    return m


# ------------------------------------------------------------------------------------------------
# markers and diagnostics

_BODY_COLOR = ColorRGBA(r=0.55, g=0.6, b=0.7, a=1.0)
_SPRING_COLOR = ColorRGBA(r=0.9, g=0.5, b=0.1, a=1.0)
_DEFORMABLE_COLOR = ColorRGBA(r=0.85, g=0.45, b=0.55, a=0.8)
_CONTACT_COLOR = ColorRGBA(r=0.9, g=0.1, b=0.1, a=1.0)
_COLLISION_COLOR = ColorRGBA(r=0.3, g=0.7, b=0.4, a=0.5)
_VERTEX_DTYPE = np.dtype([("xyz", "<f8", 3), ("deformable", "<u4"), ("pad", "<u4")])  # 32 bytes per point
_VERTEX_FIELDS = [PointField(name="x", offset=0, datatype=PointField.FLOAT64, count=1),
                  PointField(name="y", offset=8, datatype=PointField.FLOAT64, count=1),
                  PointField(name="z", offset=16, datatype=PointField.FLOAT64, count=1),
                  PointField(name="deformable", offset=24, datatype=PointField.UINT32, count=1)]


def markers_msg(t, poses: dict, springs: list, frame_id="world", scale=0.02, meshes=None, contacts=None,
                shapes=None) -> MarkerArray:
    """Bodies as small axes-aligned cubes at their frames, springs as line segments; with ``meshes``
    ({name: (positions (n,3) [m], faces (F,3) or segments (S,2))}) each deformable's surface as a
    TRIANGLE_LIST (FEM) or LINE_LIST (string), namespace ``deformable/<name>``; with ``contacts`` (the
    step's self_collision.ContactReport) the witness points of its active rows (SPHERE_LIST, namespace
    ``contacts``) and their normals (LINE_LIST, ``contact_normals``, 2 scale long); with ``shapes``
    (Simulator.collision_shapes) each collision shape (SPHERE, CUBE, CYLINDER; a capsule as a CYLINDER and
    two SPHEREs), namespace ``collision/<owner>``."""
    stamp = time_msg(t)
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    out.markers.append(clear)
    for i, (name, (p, quat)) in enumerate(poses.items()):
        m = Marker()
        m.header = Header(stamp=stamp, frame_id=frame_id)
        m.ns, m.id, m.type, m.action = name, i, Marker.CUBE, Marker.ADD  # ns: the body name (RViz lists it)
        m.pose = Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                      orientation=Quaternion(x=float(quat[0]), y=float(quat[1]), z=float(quat[2]), w=float(quat[3])))
        m.scale = Vector3(x=scale, y=scale, z=scale)
        m.color = _BODY_COLOR
        m.text = name
        out.markers.append(m)
    if springs:
        m = _world_marker(stamp, frame_id, "springs", 0, Marker.LINE_LIST, Vector3(x=scale / 4), _SPRING_COLOR)
        for _, a, b in springs:
            m.points.append(Point(x=float(a[0]), y=float(a[1]), z=float(a[2])))
            m.points.append(Point(x=float(b[0]), y=float(b[1]), z=float(b[2])))
        out.markers.append(m)
    for k, sp in enumerate(shapes or ()):
        out.markers += _shape_markers(stamp, frame_id, 3 * k, sp)
    for k, (name, (X, elems)) in enumerate((meshes or {}).items()):
        tri = elems.shape[1] == 3
        m = _world_marker(stamp, frame_id, f"deformable/{name}", k, Marker.TRIANGLE_LIST if tri else Marker.LINE_LIST,
                          Vector3(x=1.0, y=1.0, z=1.0) if tri else Vector3(x=scale / 4), _DEFORMABLE_COLOR)
        m.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in np.asarray(X)[np.asarray(elems).ravel()]]
        out.markers.append(m)
    if contacts is not None and contacts.rows:
        act = np.flatnonzero(np.asarray(contacts.impulse) > 0) if len(contacts.impulse) else np.arange(contacts.rows)
        pts = _world_marker(stamp, frame_id, "contacts", 0, Marker.SPHERE_LIST,
                            Vector3(x=scale / 2, y=scale / 2, z=scale / 2), _CONTACT_COLOR)
        nrm = _world_marker(stamp, frame_id, "contact_normals", 0, Marker.LINE_LIST, Vector3(x=scale / 8),
                            _CONTACT_COLOR)
        for i in act:
            a, n = contacts.point_a[i], contacts.normal[i]
            pts.points.append(Point(x=float(a[0]), y=float(a[1]), z=float(a[2])))
            b = a + 2 * scale * n
            nrm.points += [Point(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                           Point(x=float(b[0]), y=float(b[1]), z=float(b[2]))]
        out.markers += [pts, nrm]
    return out


def _world_marker(stamp, frame_id, ns, mid, kind, scale, color) -> Marker:
    """An empty list-type marker (points in ``frame_id``, identity pose)."""
    m = Marker()
    m.header = Header(stamp=stamp, frame_id=frame_id)
    m.ns, m.id, m.type, m.action = ns, mid, kind, Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale = scale
    m.color = color
    return m


def _shape_markers(stamp, frame_id, mid, sp) -> list:
    """Markers of one model.collision.ShapePose (ids mid, mid + 1, mid + 2)."""
    def marker(kind, i, pos, size):
        m = Marker()
        m.header = Header(stamp=stamp, frame_id=frame_id)
        m.ns, m.id, m.type, m.action = f"collision/{sp.owner}", mid + i, kind, Marker.ADD
        q = sp.quaternion
        m.pose = Pose(position=Point(x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
                      orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
        m.scale = Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2]))
        m.color = _COLLISION_COLOR
        return m

    p, s = sp.position, sp.size
    if sp.kind == "sphere":
        return [marker(Marker.SPHERE, 0, p, s)]
    if sp.kind == "box":
        return [marker(Marker.CUBE, 0, p, s)]
    if sp.kind == "cylinder":
        return [marker(Marker.CYLINDER, 0, p, s)]
    axis = quaternion_z_axis(sp.quaternion) * (0.5 * s[2])  # capsule: the end centres +- length/2 along local z
    ball = (s[0], s[0], s[0])
    return [marker(Marker.CYLINDER, 0, p, s), marker(Marker.SPHERE, 1, p + axis, ball),
            marker(Marker.SPHERE, 2, p - axis, ball)]


def quaternion_z_axis(q) -> np.ndarray:
    """Third column of the rotation of a unit quaternion (x, y, z, w): the local z axis in the world."""
    x, y, z, w = (float(c) for c in q)
    return np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def vertices_msg(t, positions: dict, frame_id="world") -> PointCloud2:
    """Every deformable's vertex positions as one sensor_msgs/PointCloud2 (topic deformable_vertices): one
    point per vertex, fields x, y, z (FLOAT64, world frame [m]) and deformable (UINT32: the index of its
    deformable in describe_scene's order), point_step 32 bytes, little-endian, height 1."""
    names = list(positions)
    X = [np.asarray(positions[n], float).reshape(-1, 3) for n in names]
    n = sum(len(x) for x in X)
    rec = np.zeros(n, dtype=_VERTEX_DTYPE)
    if n:
        rec["xyz"] = np.concatenate(X)
        rec["deformable"] = np.concatenate([np.full(len(x), i, np.uint32) for i, x in enumerate(X)])
    msg = PointCloud2(header=Header(stamp=time_msg(t), frame_id=frame_id), height=1, width=n,
                      fields=_VERTEX_FIELDS, is_bigendian=False, point_step=32, row_step=32 * n, is_dense=True)
    msg.data = array.array("B", rec.tobytes())
    return msg


def diagnostics_msg(wall_stamp: Time, node_name: str, scene: str, values: dict, level=DiagnosticStatus.OK,
                    message="running") -> DiagnosticArray:
    d = DiagnosticArray()
    d.header.stamp = wall_stamp
    st = DiagnosticStatus(level=level, name=f"{node_name}: simulation", message=message,
                          hardware_id=f"redmax:{scene}")
    st.values = [KeyValue(key=k, value=(f"{v:.6g}" if isinstance(v, float) else str(v))) for k, v in values.items()]
    d.status = [st]
    return d
