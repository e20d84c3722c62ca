"""The scene as a robot model for ROS tools (no ROS here): a URDF of the kinematic tree, the frames
the node publishes on /tf and /tf_static, the floating bases (odom) and body twists.

Frames (names = body names; the root is the node's ``frame_id``, default ``world``):

* every body whose joint moves gets its world pose on /tf (``BodyPoses``: the core's
  ``Simulator.body_poses()`` to rounding);
* a body attached by a fixed joint gets one constant transform from its parent (its parent's frame
  or the world) on /tf_static: ``placement * body_placement`` of that joint;
* a revolute or prismatic joint whose child body frame is offset from the joint frame
  (``body_placement`` not the identity) has an extra URDF link ``<body>_joint`` at the joint frame
  (URDF puts a child link's frame on its joint axis); its constant transform from the body,
  ``body_placement^-1``, is on /tf_static too.

The URDF (``urdf_text``): links with inertial, visual and collision geometry of the body shapes
(box, sphere, cylinder; a capsule as a cylinder and two spheres; meshes by file; composite bodies
part by part), revolute (``continuous`` without limits) and prismatic joints with their axes and
limits, fixed joints, and ``floating`` joints for what URDF cannot express (universal, spherical,
planar, free, catalogue joints: the real type and axes are in a comment; the node's /tf gives those
links' poses). Couplings between 1-DOF joints become ``mimic`` tags (exact: qdot_i = r_i qdot_c
integrates to q_i = (r_i / r_0) q_0 + offset); loop closures and other couplings are comments.
Scenes built from a URDF file (``urdf:``) publish that file as it is.

Twists (``BodyTwists``): Pinocchio forward kinematics with a ``pin.Data`` of our own at the
current (q, qdot_r): the body frame's origin velocity and angular velocity [m/s, rad/s], in the
world frame and in the body frame.
"""
from __future__ import annotations

import math
import os
from xml.sax.saxutils import escape, quoteattr

import numpy as np
import pinocchio as pin
from numba import njit

from redmax_ros.core import body_frames

ONE_DOF = ("revolute", "prismatic")
FLOATING_BASE = ("free", "planar", "free2d", "free3d", "free3d_exp")  # a body on one of these to the world: odom
_TOL = 1e-12


def _se3(pose) -> pin.SE3:
    pos, rpy = pose
    return pin.SE3(pin.rpy.rpyToMatrix(np.asarray(rpy, float)), np.asarray(pos, float))


def _is_identity(M: pin.SE3) -> bool:
    return bool(np.allclose(M.rotation, np.eye(3), atol=_TOL, rtol=0) and np.allclose(M.translation, 0, atol=_TOL))


def pose_of(M: pin.SE3) -> tuple:
    """(position (3,), quaternion xyzw (4,)) of an SE3."""
    return M.translation.copy(), pin.Quaternion(M.rotation).coeffs().copy()


def _f(x) -> str:
    return repr(float(x))


def _v(xs) -> str:
    return " ".join(_f(x) for x in xs)


def _origin(M: pin.SE3) -> str:
    return f'<origin xyz="{_v(M.translation)}" rpy="{_v(pin.rpy.matrixToRpy(M.rotation))}"/>'


class Frames:
    """Which frames go where for one scene (see the module doc)."""

    def __init__(self, sim, world_frame="world"):
        spec = sim.spec
        self.world = world_frame or "world"
        self.bodies = list(sim.mech.bodies)
        joint_of = {j.child: j for j in spec.joints} if not spec.urdf else {}
        self.static = []  # (parent frame, child frame, position (3,), quaternion xyzw (4,))
        self.moving = []  # bodies whose world pose goes on /tf
        self.joint_links = {}  # body -> name of its extra joint-frame link
        names = set(self.bodies) | {self.world}
        for b in self.bodies:
            j = joint_of.get(b)
            if j is not None and j.type == "fixed":
                parent = self.world if j.parent == "world" else j.parent
                self.static.append((parent, b, *pose_of(_se3(j.placement) * _se3(j.body_placement))))
                continue
            self.moving.append(b)
            if j is not None and j.type in ONE_DOF and not _is_identity(_se3(j.body_placement)):
                link = f"{b}_joint"
                while link in names:
                    link += "_"
                names.add(link)
                self.joint_links[b] = link
                self.static.append((b, link, *pose_of(_se3(j.body_placement).inverse())))
        self.floating = [j.child for j in spec.joints if j.parent == "world" and j.type in FLOATING_BASE] \
            if not spec.urdf else []


# ------------------------------------------------------------------------------------------------
# URDF

def _geometry(shape: dict, base_dir: str):
    """[(geometry xml, SE3 in the shape's frame)] of one primitive or mesh shape (empty if none)."""
    t = shape.get("type") if isinstance(shape, dict) else None
    eye = pin.SE3.Identity()
    if t == "box":
        return [(f'<box size="{_v(shape["size"])}"/>', eye)]
    if t == "sphere":
        return [(f'<sphere radius="{_f(shape["radius"])}"/>', eye)]
    if t == "cylinder":
        return [(f'<cylinder radius="{_f(shape["radius"])}" length="{_f(shape["length"])}"/>', eye)]
    if t == "capsule":  # URDF has no capsule: its cylinder and the two end spheres
        r, h = float(shape["radius"]), float(shape["length"])
        return [(f'<cylinder radius="{_f(r)}" length="{_f(h)}"/>', eye),
                (f'<sphere radius="{_f(r)}"/>', pin.SE3(np.eye(3), np.array([0.0, 0.0, h / 2]))),
                (f'<sphere radius="{_f(r)}"/>', pin.SE3(np.eye(3), np.array([0.0, 0.0, -h / 2])))]
    if t == "mesh":
        path = shape["file"]
        if not os.path.isabs(path):
            path = os.path.join(base_dir, path)
        scale = shape.get("scale", 1.0)
        scale = [float(scale)] * 3 if np.isscalar(scale) else list(scale)
        return [(f'<mesh filename={quoteattr("file://" + os.path.abspath(path))} scale="{_v(scale)}"/>', eye)]
    return []


def _body_geometry(body, base_dir):
    """[(geometry xml, SE3 in the body frame)] of a body's shape (composite bodies part by part)."""
    shape = body.shape if isinstance(body.shape, dict) else {}
    out = []
    if shape.get("type") == "composite":
        for part in shape.get("parts", []):
            M = _se3((part.get("pos", [0, 0, 0]), part.get("rpy", [0, 0, 0])))
            out += [(g, M * G) for g, G in _geometry(part.get("shape"), base_dir)]
    else:
        out = _geometry(shape, base_dir)
    if shape.get("principal_applied"):  # the body frame is the principal frame; shapes are in the design frame
        R, c = shape["principal"]
        Xi = pin.SE3(np.asarray(R, float), np.asarray(c, float)).inverse()
        out = [(g, Xi * G) for g, G in out]
    return out


def _link(name, body=None, base_dir=".") -> list:
    if body is None:
        return [f'  <link name={quoteattr(name)}/>']
    lines = [f'  <link name={quoteattr(name)}>']
    I = np.asarray(body.inertia, float)
    lines += ['    <inertial>', f'      <origin xyz="{_v(body.com)}" rpy="0 0 0"/>',
              f'      <mass value="{_f(body.mass)}"/>',
              f'      <inertia ixx="{_f(I[0, 0])}" ixy="{_f(I[0, 1])}" ixz="{_f(I[0, 2])}" iyy="{_f(I[1, 1])}" '
              f'iyz="{_f(I[1, 2])}" izz="{_f(I[2, 2])}"/>', '    </inertial>']
    rgba = _v(body.rgba) if body.rgba is not None else "0.7 0.7 0.75 1.0"
    for g, M in _body_geometry(body, base_dir):
        lines += ['    <visual>', f'      {_origin(M)}', f'      <geometry>{g}</geometry>',
                  f'      <material name={quoteattr(name + "_material")}><color rgba="{rgba}"/></material>',
                  '    </visual>',
                  '    <collision>', f'      {_origin(M)}', f'      <geometry>{g}</geometry>', '    </collision>']
    lines.append('  </link>')
    return lines


def _limit(j, k=0) -> str:
    lo, hi = float(np.atleast_1d(j.lower)[k]), float(np.atleast_1d(j.upper)[k])
    # the scene has no effort or velocity limits: URDF requires the attributes, these mean "none"
    attrs = 'effort="1e9" velocity="1e9"'
    if math.isfinite(lo) and math.isfinite(hi):
        attrs = f'lower="{_f(lo)}" upper="{_f(hi)}" ' + attrs
    return f'<limit {attrs}/>'


def urdf_text(sim, world_frame="world") -> str:
    """The URDF of ``sim``'s scene (module doc); for a scene built from a URDF file, that file."""
    spec = sim.spec
    if spec.urdf:
        with open(spec.urdf, encoding="utf-8") as f:
            return f.read()
    fr = Frames(sim, world_frame)
    base_dir = os.path.dirname(os.path.abspath(spec.source)) if spec.source else "."
    bodies = {b.name: b for b in spec.bodies}
    lines = ['<?xml version="1.0"?>',
             f'<!-- Generated by redmax_ros from scene {escape(repr(spec.name))} ({escape(str(spec.source))}). '
             'Every link frame is on /tf or /tf_static from the node itself: do not run robot_state_publisher. -->',
             f'<robot name={quoteattr(spec.name)}>', _link(fr.world)[0]]
    mimic = _mimics(sim)
    for j in spec.joints:
        parent = fr.world if j.parent == "world" else j.parent
        child = j.child
        P, B = _se3(j.placement), _se3(j.body_placement)
        lines += _link(child, bodies.get(child), base_dir)
        axes = np.asarray(j.axes, float).reshape(-1, 3) if j.axes is not None and len(j.axes) else np.zeros((0, 3))
        if j.type == "fixed":
            lines += [f'  <joint name={quoteattr(j.name)} type="fixed">', f'    <parent link={quoteattr(parent)}/>',
                      f'    <child link={quoteattr(child)}/>', f'    {_origin(P * B)}', '  </joint>']
        elif j.type in ONE_DOF:
            target = fr.joint_links.get(child, child)
            if target != child:
                lines += _link(target)
            lo, hi = float(np.atleast_1d(j.lower)[0]), float(np.atleast_1d(j.upper)[0])
            kind = j.type if j.type == "prismatic" or (math.isfinite(lo) and math.isfinite(hi)) else "continuous"
            lines += [f'  <joint name={quoteattr(j.name)} type="{kind}">', f'    <parent link={quoteattr(parent)}/>',
                      f'    <child link={quoteattr(target)}/>', f'    {_origin(P)}', f'    <axis xyz="{_v(axes[0])}"/>']
            if kind != "continuous":
                lines.append(f'    {_limit(j)}')
            if j.name in mimic:
                lines.append(f'    {mimic[j.name]}')
            lines.append('  </joint>')
            if target != child:
                lines += [f'  <joint name={quoteattr(j.name + "_body")} type="fixed">',
                          f'    <parent link={quoteattr(target)}/>', f'    <child link={quoteattr(child)}/>',
                          f'    {_origin(B)}', '  </joint>']
        else:
            note = f"{j.type} joint" + (f", axes {escape(str(axes.tolist()))} (joint frame)" if len(axes) else "")
            lines += [f'  <!-- {escape(repr(j.name))}: {note}; URDF cannot express it: floating here, the pose is '
                      'on /tf -->',
                      f'  <joint name={quoteattr(j.name)} type="floating">', f'    <parent link={quoteattr(parent)}/>',
                      f'    <child link={quoteattr(child)}/>', f'    {_origin(P * B)}', '  </joint>']
    for c in spec.couplings:
        if not all(n in mimic or n == c.joints[0] for n in c.joints):
            lines.append(f'  <!-- coupling {escape(repr(c.name))}: qdot of {escape(", ".join(c.joints))} = '
                         f'{escape(str(np.asarray(c.ratios).tolist()))} x qdot_{escape(c.name)} -->')
    sites = {s.name: s.body for s in spec.sites}
    for lp in spec.loops:
        axes = np.asarray(lp.axes, float).tolist()
        lines.append(f'  <!-- loop closure {escape(repr(lp.name))}: site {escape(repr(lp.a))} (on '
                     f'{escape(repr(sites.get(lp.a, "?")))}) and site {escape(repr(lp.b))} (on '
                     f'{escape(repr(sites.get(lp.b, "?")))}) coincide along world axes {escape(str(axes))} -->')
    lines.append('</robot>')
    return "\n".join(lines) + "\n"


def _mimics(sim) -> dict:
    """joint -> <mimic .../> for couplings whose joints are all 1-DOF (revolute, prismatic): q_i =
    (r_i / r_0) q_0 + (q0_i - (r_i / r_0) q0_0), the first joint leading."""
    spec = sim.spec
    joints = {j.name: j for j in spec.joints}
    out = {}
    for c in spec.couplings:
        js = [joints.get(n) for n in c.joints]
        r = np.asarray(c.ratios, float)
        if not js or any(j is None or j.type not in ONE_DOF for j in js) or abs(r[0]) < 1e-300:
            continue
        lead = js[0]
        for j, ri in zip(js[1:], r[1:]):
            m = ri / r[0]
            off = float(np.atleast_1d(j.q0)[0]) - m * float(np.atleast_1d(lead.q0)[0])
            out[j.name] = f'<mimic joint={quoteattr(lead.name)} multiplier="{_f(m)}" offset="{_f(off)}"/>'
    return out


# ------------------------------------------------------------------------------------------------
# twists

def quaternions(R: np.ndarray) -> np.ndarray:
    """Unit quaternions xyzw (n,4) of rotation matrices R (n,3,3) (the largest of w, x, y, z is
    computed from the diagonal, the others from the off-diagonal terms; w >= 0 where w is largest).
    One compiled loop (_quaternions_into): /tf converts every moving body at tf_rate, and the same
    formulas as batched numpy cost ~110 us a call at any n (numpy's fixed cost per operation) against
    ~1 us. It keeps the GIL (no ``nogil``): the caller is the simulation thread, and releasing the GIL for
    ~1 us invites another thread to take it, the simulation thread then waiting to get it back."""
    R = np.ascontiguousarray(R, dtype=float).reshape(-1, 3, 3)
    q = np.empty((len(R), 4))
    _quaternions_into(R, q)
    return q


@njit(cache=True)
def _quaternions_into(R, q):
    for n in range(R.shape[0]):
        r = R[n]
        tr = r[0, 0] + r[1, 1] + r[2, 2]
        case, big = 0, tr  # argmax of (tr, R00, R11, R22), the first on ties
        for c in range(1, 4):
            if r[c - 1, c - 1] > big:
                case, big = c, r[c - 1, c - 1]
        if case == 0:
            s = 2.0 * math.sqrt(1.0 + tr)
            x, y, z, w = (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s
        elif case == 1:
            s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
            x, y, z, w = 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s
        elif case == 2:
            s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
            x, y, z, w = (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s
        else:
            s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
            x, y, z, w = (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s
        nrm = math.sqrt(x * x + y * y + z * z + w * w)
        q[n, 0], q[n, 1], q[n, 2], q[n, 3] = x / nrm, y / nrm, z / nrm, w / nrm


class BodyPoses:
    """World poses of chosen bodies at a configuration, for /tf at its rate. On every joint kind of the
    compiled step: one compiled call (core step/compiled/poses.BodyFrames: the step's own forward
    kinematics, ~2-5 us a call against ~80 us warm and 370-470 us in the node's simulation thread
    through Pinocchio), then one for the quaternions. Otherwise (catalogue joints): Pinocchio forward
    kinematics with a pin.Data of our own and every joint placement read in one call
    (``oMi.tolist()``). Equal to the core's ``body_poses`` to 1e-12 over every shipped scene
    (test/node/test_node_robot_model.py)."""

    def __init__(self, mech, names):
        self._fast = body_frames(mech, names)
        if self._fast is not None:
            return
        self.model = mech.model
        self.data = mech.model.createData()
        idx = {b: i for i, b in enumerate(mech.bodies)}
        sel = [idx[n] for n in names]
        self.jid = np.array([int(mech.body_jid[i]) for i in sel], dtype=np.intp)
        self.MR = np.array([mech.body_placement[i].rotation for i in sel]).reshape(-1, 3, 3)
        self.Mp = np.array([mech.body_placement[i].translation for i in sel]).reshape(-1, 3)

    def __call__(self, q) -> tuple:
        """(positions (n,3) [m], quaternions xyzw (n,4)) in the order of ``names``."""
        if self._fast is not None:
            P, R = self._fast(q)
            return P.copy(), quaternions(R)
        pin.forwardKinematics(self.model, self.data, np.asarray(q, float))
        if not len(self.jid):
            return np.empty((0, 3)), np.empty((0, 4))
        H = np.array([M.np for M in self.data.oMi.tolist()])[self.jid]  # (n, 4, 4) homogeneous matrices
        R = np.ascontiguousarray(H[:, :3, :3])
        p = H[:, :3, 3]
        Rb = R @ self.MR
        pb = np.einsum("nij,nj->ni", R, self.Mp) + p
        return pb, quaternions(Rb)


class BodyTwists:
    """Body twists at a state, with a pin.Data of our own (the stepping backend's is left alone)."""

    def __init__(self, mech):
        self.mech = mech
        self.data = mech.model.createData()
        self.index = {b: i for i, b in enumerate(mech.bodies)}

    def __call__(self, q, v, names) -> dict:
        """body -> (linear (3,), angular (3,)) in the world frame and (linear, angular) in the body
        frame: velocity of the body frame's origin [m/s] and angular velocity [rad/s], at
        configuration q (nq,) and reduced velocity v (nv,)."""
        m = self.mech
        pin.forwardKinematics(m.model, self.data, np.asarray(q, float), np.asarray(v, float))
        out = {}
        for n in names:
            i = self.index[n]
            jid = int(m.body_jid[i])
            M = m.body_placement[i]
            vb = M.actInv(self.data.v[jid])  # body frame, at its origin
            R = (self.data.oMi[jid] * M).rotation
            out[n] = (R @ vb.linear, R @ vb.angular, vb.linear.copy(), vb.angular.copy())
        return out
