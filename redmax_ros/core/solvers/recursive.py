"""O(n) Jacobian products over a Pinocchio kinematic tree, never forming the Jacobian J_mr.

RedMax (Wang et al. 2019) needs products with J_mr, J_mr^T and Jdot_mr to form the RHS of Eq. (2)
and to multiply by its LHS matrix in O(n) (requirements (1)-(2) listed after Eq. (3)). They follow
Sueda's notes §2.11: Alg. 5 (y = J x, z = Jdot x, forward traversal) and Alg. 6 (x = J^T y,
backward traversal).

Frames and ordering (the one convention of this module)
-------------------------------------------------------
Every spatial quantity is expressed in the WORLD frame at the world origin, in Pinocchio's
ordering (linear first, angular second), i.e. Pinocchio's ``pin.WORLD`` reference frame:

* a twist of body j is ``(v_o, w)``: ``w`` the angular velocity and ``v_o`` the velocity of the
  body-fixed point that coincides with the world origin; a point x (world) on the body moves
  with ``v_o + w × x``.
* a wrench is ``(f, tau_o)``: force and torque about the world origin.
* "body j" is the body carried by Pinocchio joint j (rows of the (njoints, 6) arrays); row 0 is
  the universe, whose twist is zero and on which wrenches are ignored (the ground absorbs them).

With this choice the adjoints ``{}^i_p Ad`` of Alg. 5/6 (and of Alg. 1) are identities, so the
recursions reduce to tree prefix sums: (J x)_j = (J x)_parent + S_j x_j, with S_j the joint's motion
subspace in the world frame (Pinocchio's ``data.J`` columns). Sueda's notes order twists
(angular, linear); here we keep Pinocchio's order.

Model constant vs workspace (like Pinocchio's Model/Data)
---------------------------------------------------------
:class:`Topology` is built once per ``pin.Model`` (parents, index ranges, joint types, inertias,
armature). :class:`Workspace` holds the per-configuration arrays, filled by
:func:`update_kinematics` (own forward kinematics, see the note below). No ``pin.Data`` is needed:
in pin 4.1 ``model.createData()`` allocates O(nv^3) memory (~475 MB at nv = 200, tens of GB at
nv = 1000), so large chains cannot use Pinocchio's Data at all.

Forward kinematics runs in a numba kernel for revolute (aligned/unaligned/unbounded), prismatic,
helical, spherical (quaternion), translation and free-flyer joints; any other Pinocchio joint
(SphericalZYX, Universal, Planar, Ellipsoid, Composite) is evaluated by Pinocchio itself through
``model.joints[j].calc`` (a per-joint Python call, only for those joints). Mimic joints are
not supported.

Hot loops are numba kernels (``@njit``): on a chain the tree has one joint per level, so
vectorising by tree level degenerates to one interpreter round trip per joint; measured in
``redmax_bench/passes.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from redmax_ros.core.jit import HAVE_NUMBA, njit  # noqa: F401  (re-exported for the kernels here)

# Joint kinds handled by the forward-kinematics kernel. FALLBACK joints get their transform,
# motion subspace and bias from Pinocchio's own joint model (``JointModel.calc``).
FALLBACK, REVOLUTE, REVOLUTE_UNBOUNDED, PRISMATIC, HELICAL, SPHERICAL, FREEFLYER, TRANSLATION = range(8)

_AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}


# --------------------------------------------------------------------------------------------
# Model constants
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Topology:
    """Constant description of a kinematic tree (build once per model, :func:`build_topology`).

    Joints are numbered as in Pinocchio; ``parents[j] < j`` so increasing index is a forward
    traversal (parents first) and decreasing index a backward traversal (children first).
    """

    njoints: int  # including the universe (index 0)
    nq: int
    nv: int
    parents: np.ndarray  # (njoints,) int64, parents[0] = 0
    idx_q: np.ndarray  # (njoints,) int64
    nq_j: np.ndarray  # (njoints,) int64
    idx_v: np.ndarray  # (njoints,) int64
    nv_j: np.ndarray  # (njoints,) int64
    kind: np.ndarray  # (njoints,) int64, one of REVOLUTE, ..., FALLBACK
    axis: np.ndarray  # (njoints, 3) unit axis of 1-DOF joints (joint frame)
    pitch: np.ndarray  # (njoints,) helical pitch [m/rad]
    place_R: np.ndarray  # (njoints, 3, 3) model.jointPlacements rotations (joint in parent frame)
    place_p: np.ndarray  # (njoints, 3) model.jointPlacements translations [m]
    S_const: np.ndarray  # (6, nv) motion subspace in the joint frame (constant kinds; 0 for FALLBACK)
    mass: np.ndarray  # (njoints,) [kg]
    com: np.ndarray  # (njoints, 3) centre of mass in the joint frame [m]
    inertia_com: np.ndarray  # (njoints, 3, 3) rotational inertia about the COM, joint axes [kg m^2]
    armature: np.ndarray  # (nv,) model.armature [kg m^2 or kg]
    fallback: tuple = field(default=())  # joint indices evaluated through Pinocchio's JointModel.calc
    fallback_models: tuple = field(default=())  # matching pin.JointModel objects (copies)


def _kind_of(jm) -> tuple[int, np.ndarray, float]:
    """Classify a Pinocchio joint model: (kind, axis, pitch)."""
    name = jm.shortname()
    short = name.replace("JointModel", "")
    zero = np.zeros(3)
    if short in ("RX", "RY", "RZ"):
        return REVOLUTE, np.array(_AXES[short[1]]), 0.0
    if short in ("RUBX", "RUBY", "RUBZ"):
        return REVOLUTE_UNBOUNDED, np.array(_AXES[short[3]]), 0.0
    if short in ("PX", "PY", "PZ"):
        return PRISMATIC, np.array(_AXES[short[1]]), 0.0
    if short in ("HX", "HY", "HZ"):
        return HELICAL, np.array(_AXES[short[1]]), float(jm.extract().pitch)
    if short == "RevoluteUnaligned":
        return REVOLUTE, np.array(jm.extract().axis, dtype=float), 0.0
    if short == "RevoluteUnboundedUnaligned":
        return REVOLUTE_UNBOUNDED, np.array(jm.extract().axis, dtype=float), 0.0
    if short == "PrismaticUnaligned":
        return PRISMATIC, np.array(jm.extract().axis, dtype=float), 0.0
    if short == "HelicalUnaligned":
        e = jm.extract()
        return HELICAL, np.array(e.axis, dtype=float), float(e.pitch)
    if short == "Spherical":
        return SPHERICAL, zero, 0.0
    if short == "FreeFlyer":
        return FREEFLYER, zero, 0.0
    if short == "Translation":
        return TRANSLATION, zero, 0.0
    if short == "Mimic" or "Mimic" in name:
        raise NotImplementedError("recursive products do not support Pinocchio mimic joints")
    return FALLBACK, zero, 0.0


def _constant_subspace(kind: int, axis: np.ndarray, pitch: float) -> np.ndarray:
    """Joint-frame motion subspace S (6 x nv_j, [linear; angular]) of a constant-S joint kind."""
    if kind in (REVOLUTE, REVOLUTE_UNBOUNDED):
        return np.concatenate([np.zeros(3), axis])[:, None]
    if kind == PRISMATIC:
        return np.concatenate([axis, np.zeros(3)])[:, None]
    if kind == HELICAL:
        return np.concatenate([pitch * axis, axis])[:, None]
    if kind == SPHERICAL:
        return np.vstack([np.zeros((3, 3)), np.eye(3)])
    if kind == FREEFLYER:
        return np.eye(6)
    if kind == TRANSLATION:
        return np.vstack([np.eye(3), np.zeros((3, 3))])
    raise ValueError(kind)


def build_topology(model: pin.Model) -> Topology:
    """Extract the constant tree description of ``model`` (O(n), once per model)."""
    nj = model.njoints
    parents = np.array([int(p) for p in model.parents], dtype=np.int64)
    parents[0] = 0
    idx_q = np.zeros(nj, dtype=np.int64)
    nq_j = np.zeros(nj, dtype=np.int64)
    idx_v = np.zeros(nj, dtype=np.int64)
    nv_j = np.zeros(nj, dtype=np.int64)
    kind = np.full(nj, FALLBACK, dtype=np.int64)
    axis = np.zeros((nj, 3))
    pitch = np.zeros(nj)
    place_R = np.zeros((nj, 3, 3))
    place_p = np.zeros((nj, 3))
    place_R[0] = np.eye(3)
    S_const = np.zeros((6, model.nv))
    mass = np.zeros(nj)
    com = np.zeros((nj, 3))
    inertia_com = np.zeros((nj, 3, 3))
    fallback, fallback_models = [], []
    for j in range(1, nj):
        jm = model.joints[j]
        idx_q[j], nq_j[j], idx_v[j], nv_j[j] = jm.idx_q, jm.nq, jm.idx_v, jm.nv
        if parents[j] >= j:
            raise ValueError("Pinocchio joints must be ordered parents-first")
        k, a, h = _kind_of(jm)
        kind[j], axis[j], pitch[j] = k, a, h
        if k == FALLBACK:
            fallback.append(j)
            fallback_models.append(pin.JointModel(jm))
        elif jm.nv:
            S_const[:, jm.idx_v:jm.idx_v + jm.nv] = _constant_subspace(k, a, h)
        M = model.jointPlacements[j]
        place_R[j], place_p[j] = M.rotation, M.translation
        Y = model.inertias[j]
        mass[j], com[j], inertia_com[j] = Y.mass, Y.lever, Y.inertia
    return Topology(
        njoints=nj, nq=model.nq, nv=model.nv, parents=parents, idx_q=idx_q, nq_j=nq_j,
        idx_v=idx_v, nv_j=nv_j, kind=kind, axis=axis, pitch=pitch, place_R=place_R,
        place_p=place_p, S_const=S_const, mass=mass, com=com, inertia_com=inertia_com,
        armature=np.array(model.armature, dtype=float).reshape(model.nv),
        fallback=tuple(fallback), fallback_models=tuple(fallback_models))


# --------------------------------------------------------------------------------------------
# Per-configuration workspace
# --------------------------------------------------------------------------------------------
@dataclass(eq=False)
class Workspace:
    """Per-configuration arrays (world frame), filled by :func:`update_kinematics`.

    ``R[j], p[j]`` is ``data.oMi[j]``; ``S`` is ``data.J`` (the joints' motion subspaces in the world
    frame, 6 x nv; stored transposed as ``St`` (nv x 6) so that each column is contiguous for the
    kernels); ``I`` the body spatial inertias at the world origin (``oMi.act(inertia)``);
    ``ov`` the body twists J qdot and ``c_local`` the joint bias ``jdata.c`` (only FALLBACK joints
    with a configuration-dependent S have a nonzero bias).
    """

    q: np.ndarray
    v: np.ndarray | None
    R: np.ndarray  # (njoints, 3, 3)
    p: np.ndarray  # (njoints, 3) [m]
    St: np.ndarray  # (nv, 6) world motion subspaces, row c = column c of data.J
    I: np.ndarray  # (njoints, 6, 6)
    ov: np.ndarray  # (njoints, 6) body twists J v (zeros until a velocity is given)
    c_local: np.ndarray  # (njoints, 6) joint bias in the joint frame
    has_bias: bool
    Sl: np.ndarray  # (nv, 6) joint-frame motion subspaces (constant kinds + FALLBACK joints)
    jR: np.ndarray  # (njoints, 3, 3) joint transforms of FALLBACK joints (scratch)
    jp: np.ndarray  # (njoints, 3)
    tmp6: np.ndarray  # (njoints, 6) scratch for backward passes (a Workspace is not thread-safe)
    jdata: tuple = ()  # pin.JointData of the FALLBACK joints

    @property
    def S(self) -> np.ndarray:
        """(6, nv) view: world motion subspaces, = Pinocchio's data.J."""
        return self.St.T


def make_workspace(topo: Topology) -> Workspace:
    nj, nv = topo.njoints, topo.nv
    R = np.zeros((nj, 3, 3))
    R[:] = np.eye(3)
    return Workspace(
        q=np.zeros(topo.nq), v=None, R=R, p=np.zeros((nj, 3)), St=np.zeros((nv, 6)),
        I=np.zeros((nj, 6, 6)), ov=np.zeros((nj, 6)), c_local=np.zeros((nj, 6)), has_bias=False,
        Sl=np.ascontiguousarray(topo.S_const.T), jR=R.copy(), jp=np.zeros((nj, 3)), tmp6=np.zeros((nj, 6)),
        jdata=tuple(jm.createData() for jm in topo.fallback_models))


# The per-step kernels below allocate nothing: their small temporaries (a joint's rotation, a body's 6-vectors) are
# tuples and scalars, which live in registers (an np.empty in a compiled kernel costs ~40 ns, as much as the
# arithmetic of a body; measured).


@njit
def axis_rotation(a, c, s):
    """Rodrigues: rotation by angle (cos c, sin s) about unit axis a, row-major as a 9-tuple."""
    t = 1.0 - c
    x, y, z = a[0], a[1], a[2]
    return (c + t * x * x, t * x * y - s * z, t * x * z + s * y,
            t * x * y + s * z, c + t * y * y, t * y * z - s * x,
            t * x * z - s * y, t * y * z + s * x, c + t * z * z)


@njit
def _quat_rotation(x, y, z, w):
    """Eigen's Quaternion::toRotationMatrix for coefficients (x, y, z, w) (Pinocchio's q layout), row-major as a
    9-tuple."""
    tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    return (1.0 - (tyy + tzz), txy - twz, txz + twy,
            txy + twz, 1.0 - (txx + tzz), tyz - twx,
            txz - twy, tyz + twx, 1.0 - (txx + tyy))


_EYE3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
_ZERO3 = (0.0, 0.0, 0.0)


@njit
def _joint_motion(k, axis, pitch, q, iq, jR, jp, j):
    """M_joint(q) of joint j of kind k: (rotation, row-major 9-tuple; translation, 3-tuple); FALLBACK joints (and
    universal, planar) read the transform their own kernel left in (jR[j], jp[j])."""
    if k == 1:  # REVOLUTE
        return axis_rotation(axis[j], np.cos(q[iq]), np.sin(q[iq])), _ZERO3
    if k == 2:  # REVOLUTE_UNBOUNDED, q = (cos, sin)
        return axis_rotation(axis[j], q[iq], q[iq + 1]), _ZERO3
    if k == 3:  # PRISMATIC
        x = q[iq]
        return _EYE3, (axis[j, 0] * x, axis[j, 1] * x, axis[j, 2] * x)
    if k == 4:  # HELICAL
        x = pitch[j] * q[iq]
        return axis_rotation(axis[j], np.cos(q[iq]), np.sin(q[iq])), (axis[j, 0] * x, axis[j, 1] * x, axis[j, 2] * x)
    if k == 5:  # SPHERICAL, q = quaternion (x, y, z, w)
        return _quat_rotation(q[iq], q[iq + 1], q[iq + 2], q[iq + 3]), _ZERO3
    if k == 6:  # FREEFLYER, q = (p, quaternion)
        return _quat_rotation(q[iq + 3], q[iq + 4], q[iq + 5], q[iq + 6]), (q[iq], q[iq + 1], q[iq + 2])
    if k == 7:  # TRANSLATION
        return _EYE3, (q[iq], q[iq + 1], q[iq + 2])
    return ((jR[j, 0, 0], jR[j, 0, 1], jR[j, 0, 2], jR[j, 1, 0], jR[j, 1, 1], jR[j, 1, 2],
             jR[j, 2, 0], jR[j, 2, 1], jR[j, 2, 2]), (jp[j, 0], jp[j, 1], jp[j, 2]))


@njit
def fk_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q,
               jR, jp, Sl, R, p, St):
    """Forward kinematics (Sueda's notes §2.1) and world motion subspaces S = oX_j S_local."""
    nj = parents.shape[0]
    for j in range(1, nj):
        Rj, pj = _joint_motion(kind[j], axis, pitch, q, idx_q[j], jR, jp, j)
        # liMi = jointPlacement * M_joint(q), into (R[j], p[j])
        for a in range(3):
            for b in range(3):
                R[j, a, b] = (place_R[j, a, 0] * Rj[b] + place_R[j, a, 1] * Rj[3 + b]
                              + place_R[j, a, 2] * Rj[6 + b])
            p[j, a] = place_p[j, a] + (place_R[j, a, 0] * pj[0] + place_R[j, a, 1] * pj[1]
                                       + place_R[j, a, 2] * pj[2])
        # oMi = oMi[parent] * liMi, in place: a column of liMi (and its translation) read before it is replaced
        par = parents[j]
        for b in range(3):
            l0, l1, l2 = R[j, 0, b], R[j, 1, b], R[j, 2, b]
            for a in range(3):
                R[j, a, b] = R[par, a, 0] * l0 + R[par, a, 1] * l1 + R[par, a, 2] * l2
        l0, l1, l2 = p[j, 0], p[j, 1], p[j, 2]
        for a in range(3):
            p[j, a] = p[par, a] + R[par, a, 0] * l0 + R[par, a, 1] * l1 + R[par, a, 2] * l2
        # world motion subspace columns: S = oX_j S_local (lin' = R lin + p x R ang, ang' = R ang)
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            w0 = R[j, 0, 0] * Sl[c, 3] + R[j, 0, 1] * Sl[c, 4] + R[j, 0, 2] * Sl[c, 5]
            w1 = R[j, 1, 0] * Sl[c, 3] + R[j, 1, 1] * Sl[c, 4] + R[j, 1, 2] * Sl[c, 5]
            w2 = R[j, 2, 0] * Sl[c, 3] + R[j, 2, 1] * Sl[c, 4] + R[j, 2, 2] * Sl[c, 5]
            v0 = R[j, 0, 0] * Sl[c, 0] + R[j, 0, 1] * Sl[c, 1] + R[j, 0, 2] * Sl[c, 2]
            v1 = R[j, 1, 0] * Sl[c, 0] + R[j, 1, 1] * Sl[c, 1] + R[j, 1, 2] * Sl[c, 2]
            v2 = R[j, 2, 0] * Sl[c, 0] + R[j, 2, 1] * Sl[c, 1] + R[j, 2, 2] * Sl[c, 2]
            St[c, 0] = v0 + p[j, 1] * w2 - p[j, 2] * w1
            St[c, 1] = v1 + p[j, 2] * w0 - p[j, 0] * w2
            St[c, 2] = v2 + p[j, 0] * w1 - p[j, 1] * w0
            St[c, 3] = w0
            St[c, 4] = w1
            St[c, 5] = w2


@njit
def world_inertia_kernel(mass, com, inertia_com, R, p, I):
    """Spatial inertia of each body at the world origin ([linear; angular] order):
    [[m 1, -m [c]], [m [c], R I_c R^T - m [c][c]]] with c = R com + p (= oMi.act(inertia).matrix())."""
    nj = mass.shape[0]
    for j in range(1, nj):
        m = mass[j]
        c0 = R[j, 0, 0] * com[j, 0] + R[j, 0, 1] * com[j, 1] + R[j, 0, 2] * com[j, 2] + p[j, 0]
        c1 = R[j, 1, 0] * com[j, 0] + R[j, 1, 1] * com[j, 1] + R[j, 1, 2] * com[j, 2] + p[j, 1]
        c2 = R[j, 2, 0] * com[j, 0] + R[j, 2, 1] * com[j, 1] + R[j, 2, 2] * com[j, 2] + p[j, 2]
        cc = c0 * c0 + c1 * c1 + c2 * c2
        cv = (c0, c1, c2)
        for a in range(3):
            for b in range(3):
                I[j, a, b] = 0.0
            I[j, a, a] = m
            for b in range(3):
                s = 0.0  # (R I_c R^T)[a, b]
                for k in range(3):
                    for l in range(3):
                        s += R[j, a, k] * inertia_com[j, k, l] * R[j, b, l]
                # -m [c][c] = m (|c|^2 1 - c c^T)
                I[j, 3 + a, 3 + b] = s - m * cv[a] * cv[b]
            I[j, 3 + a, 3 + a] += m * cc
        # m [c] (lower-left) and its transpose -m [c] (upper-right)
        I[j, 3, 0], I[j, 3, 1], I[j, 3, 2] = 0.0, -m * c2, m * c1
        I[j, 4, 0], I[j, 4, 1], I[j, 4, 2] = m * c2, 0.0, -m * c0
        I[j, 5, 0], I[j, 5, 1], I[j, 5, 2] = -m * c1, m * c0, 0.0
        for a in range(3):
            for b in range(3):
                I[j, a, 3 + b] = I[j, 3 + b, a]


@njit
def jv_kernel(parents, idx_v, nv_j, St, x, Y):
    """Alg. 5 line 2 & 5 in the world frame: Y_j = Y_parent + S_j x_j (body twists J x)."""
    nj = parents.shape[0]
    Y[0, :] = 0.0
    for j in range(1, nj):
        par = parents[j]
        for a in range(6):
            Y[j, a] = Y[par, a]
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            xc = x[c]
            for a in range(6):
                Y[j, a] += St[c, a] * xc


@njit
def jtw_kernel(parents, idx_v, nv_j, St, W, F, x):
    """Alg. 6 in the world frame: F_j = W_j + sum_children F_c, x_j = S_j^T F_j. F is scratch."""
    nj = parents.shape[0]
    for j in range(nj):
        for a in range(6):
            F[j, a] = W[j, a]
    for j in range(nj - 1, 0, -1):
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            s = 0.0
            for a in range(6):
                s += St[c, a] * F[j, a]
            x[c] = s
        par = parents[j]
        for a in range(6):
            F[par, a] += F[j, a]


@njit
def add_point_wrench(W, j, x, f, sign):
    """W[j] += sign (f, x x f): a point force f at world point x as a wrench at the world origin."""
    W[j, 0] += sign * f[0]
    W[j, 1] += sign * f[1]
    W[j, 2] += sign * f[2]
    W[j, 3] += sign * (x[1] * f[2] - x[2] * f[1])
    W[j, 4] += sign * (x[2] * f[0] - x[0] * f[2])
    W[j, 5] += sign * (x[0] * f[1] - x[1] * f[0])


@njit
def add_motion_cross_force(v, f, out):
    """out += v x* f for a twist v = (linear, angular) and a wrench f = (force, torque), both at the
    world origin: (w x f, v x f + w x n) (Featherstone's cross product for forces)."""
    v0, v1, v2, w0, w1, w2 = v[0], v[1], v[2], v[3], v[4], v[5]
    f0, f1, f2, n0, n1, n2 = f[0], f[1], f[2], f[3], f[4], f[5]
    out[0] += w1 * f2 - w2 * f1
    out[1] += w2 * f0 - w0 * f2
    out[2] += w0 * f1 - w1 * f0
    out[3] += v1 * f2 - v2 * f1 + w1 * n2 - w2 * n1
    out[4] += v2 * f0 - v0 * f2 + w2 * n0 - w0 * n2
    out[5] += v0 * f1 - v1 * f0 + w0 * n1 - w1 * n0


@njit
def _motion_cross(m, u):
    """m x u for twists m = (v, w), u = (v', w'): (w x v' + v x w', w x w'), as a 6-tuple."""
    v0, v1, v2, w0, w1, w2 = m[0], m[1], m[2], m[3], m[4], m[5]
    return (w1 * u[2] - w2 * u[1] + v1 * u[5] - v2 * u[4],
            w2 * u[0] - w0 * u[2] + v2 * u[3] - v0 * u[5],
            w0 * u[1] - w1 * u[0] + v0 * u[4] - v1 * u[3],
            w1 * u[5] - w2 * u[4],
            w2 * u[3] - w0 * u[5],
            w0 * u[4] - w1 * u[3])


@njit
def _joint_twist(idx_v, nv_j, St, x, j):
    """S_j x_j, the twist of joint j's own DOFs, as a 6-tuple."""
    u0 = u1 = u2 = u3 = u4 = u5 = 0.0
    for c in range(idx_v[j], idx_v[j] + nv_j[j]):
        xc = x[c]
        u0 += St[c, 0] * xc
        u1 += St[c, 1] * xc
        u2 += St[c, 2] * xc
        u3 += St[c, 3] * xc
        u4 += St[c, 4] * xc
        u5 += St[c, 5] * xc
    return u0, u1, u2, u3, u4, u5


@njit
def _jdot_kernel(parents, idx_v, nv_j, St, ov, x, Z):
    """Alg. 5 lines 3 & 6 in the world frame. The world-frame derivative of the column block
    S_j = oX_j S_local is ov_j x S_j (+ oX_j dS_local/dt, see :func:`bias_acceleration`), so
    Z_j = Z_parent + ov_j x (S_j x_j)."""
    nj = parents.shape[0]
    Z[0, :] = 0.0
    for j in range(1, nj):
        par = parents[j]
        cr = _motion_cross(ov[j], _joint_twist(idx_v, nv_j, St, x, j))
        for a in range(6):
            Z[j, a] = Z[par, a] + cr[a]


@njit
def bias_kernel(parents, idx_v, nv_j, St, ov, v, R, p, c_local, Z):
    """Z_j = Z_parent + ov_j x (S_j v_j) + oX_j c_j (forward traversal)."""
    nj = parents.shape[0]
    Z[0, :] = 0.0
    for j in range(1, nj):
        par = parents[j]
        cr = _motion_cross(ov[j], _joint_twist(idx_v, nv_j, St, v, j))
        c = c_local[j]
        w3 = R[j, 0, 0] * c[3] + R[j, 0, 1] * c[4] + R[j, 0, 2] * c[5]
        w4 = R[j, 1, 0] * c[3] + R[j, 1, 1] * c[4] + R[j, 1, 2] * c[5]
        w5 = R[j, 2, 0] * c[3] + R[j, 2, 1] * c[4] + R[j, 2, 2] * c[5]
        cw = (R[j, 0, 0] * c[0] + R[j, 0, 1] * c[1] + R[j, 0, 2] * c[2] + p[j, 1] * w5 - p[j, 2] * w4,
              R[j, 1, 0] * c[0] + R[j, 1, 1] * c[1] + R[j, 1, 2] * c[2] + p[j, 2] * w3 - p[j, 0] * w5,
              R[j, 2, 0] * c[0] + R[j, 2, 1] * c[1] + R[j, 2, 2] * c[2] + p[j, 0] * w4 - p[j, 1] * w3,
              w3, w4, w5)
        for a in range(6):
            Z[j, a] = Z[par, a] + cr[a] + cw[a]


@njit
def planar_placements(joints, idx_q, q, jR, jp):
    """Joint transforms of planar joints: rotation about z by (cos, sin) = q[2:4], translation (q0, q1, 0)."""
    for j in joints:
        i = idx_q[j]
        c, s = q[i + 2], q[i + 3]
        jR[j, 0, 0], jR[j, 0, 1], jR[j, 0, 2] = c, -s, 0.0
        jR[j, 1, 0], jR[j, 1, 1], jR[j, 1, 2] = s, c, 0.0
        jR[j, 2, 0], jR[j, 2, 1], jR[j, 2, 2] = 0.0, 0.0, 1.0
        jp[j, 0], jp[j, 1], jp[j, 2] = q[i], q[i + 1], 0.0


def update_kinematics(topo: Topology, ws: Workspace, q: np.ndarray, v: np.ndarray | None = None) -> Workspace:
    """Fill ``ws`` for configuration ``q`` (and velocity ``v``): oMi, world motion subspaces
    (= Pinocchio's data.J), world spatial inertias, and with ``v`` the body twists J v and the
    joint biases needed by :func:`jdot_v` / :func:`bias_acceleration`. O(n)."""
    q = np.ascontiguousarray(q, dtype=float).reshape(topo.nq)
    ws.q[:] = q
    if v is not None:
        v = np.ascontiguousarray(v, dtype=float).reshape(topo.nv)
    ws.has_bias = False
    for j, jm, jd in zip(topo.fallback, topo.fallback_models, ws.jdata):
        if v is None:
            jm.calc(jd, q)
            ws.c_local[j] = 0.0
        else:
            jm.calc(jd, q, v)
            c = jd.c.vector
            ws.c_local[j] = c
            ws.has_bias = ws.has_bias or bool(np.any(c != 0.0))
        ws.jR[j], ws.jp[j] = jd.M.rotation, jd.M.translation
        i0, n = topo.idx_v[j], topo.nv_j[j]
        ws.Sl[i0:i0 + n, :] = np.asarray(jd.S).reshape(6, n).T
    kinematics_passes(topo, ws, q, v)
    return ws


def kinematics_passes(topo: Topology, ws: Workspace, q: np.ndarray, v: np.ndarray | None) -> None:
    """The compiled part of :func:`update_kinematics` (q, v contiguous; the FALLBACK joints' transforms and
    subspaces already in ws): forward kinematics, world inertias and, with ``v``, the body twists (ws.v a copy
    of v), in one call of :func:`kinematics_kernel`."""
    ws.v = None if v is None else v.copy()
    kinematics_kernel(topo.parents, topo.kind, topo.idx_q, topo.idx_v, topo.nv_j, topo.axis, topo.pitch,
                      topo.place_R, topo.place_p, topo.mass, topo.com, topo.inertia_com, q,
                      _NO_VELOCITY if v is None else v, v is not None, ws.jR, ws.jp, ws.Sl, ws.R, ws.p, ws.St,
                      ws.I, ws.ov)


_NO_VELOCITY = np.zeros(0)


@njit
def kinematics_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, mass, com, inertia_com,
                      q, v, use_v, jR, jp, Sl, R, p, St, I, ov):
    """:func:`fk_kernel`, :func:`world_inertia_kernel` and the body twists ov = J v (:func:`jv_kernel`; zero
    without ``use_v``) in one call (Sueda's notes §2.1, Alg. 5)."""
    fk_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl, R, p, St)
    world_inertia_kernel(mass, com, inertia_com, R, p, I)
    if use_v:
        jv_kernel(parents, idx_v, nv_j, St, v, ov)
    else:
        ov[:, :] = 0.0


# --------------------------------------------------------------------------------------------
# Products
# --------------------------------------------------------------------------------------------
def _vec(x, n):
    return np.ascontiguousarray(x, dtype=float).reshape(n)


def jv(topo: Topology, ws: Workspace, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Body twists y = J_mr x, world frame: (njoints, 6), row j = Pinocchio's
    ``getJointJacobian(model, data, j, pin.WORLD) @ x``. Sueda's notes Alg. 5 (forward traversal)."""
    out = np.empty((topo.njoints, 6)) if out is None else out
    jv_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, _vec(x, topo.nv), out)
    return out


def jtw(topo: Topology, ws: Workspace, W: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Generalized force x = J_mr^T w for one world wrench (f, tau_o) per body (njoints, 6);
    row 0 (universe) is ignored. Sueda's notes Alg. 6 (backward traversal)."""
    W = np.ascontiguousarray(W, dtype=float).reshape(topo.njoints, 6)
    out = np.empty(topo.nv) if out is None else out
    jtw_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, W, ws.tmp6, out)
    return out


def jdot_v(topo: Topology, ws: Workspace, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """z = Jdot x (world frame, (njoints, 6)) with Jdot the time variation at the velocity given to
    :func:`update_kinematics`; row j = ``getJointJacobianTimeVariation(model, data, j, pin.WORLD) @ x``.

    Like Pinocchio's ``computeJointJacobiansTimeVariation``, the columns are ov_j x S_j, i.e. the
    derivative of S_local (nonzero only for joints with configuration-dependent subspaces:
    SphericalZYX, Universal, ...) is not included; :func:`bias_acceleration` includes it.
    Sueda's notes Alg. 5 line 3/6."""
    if ws.v is None:
        raise ValueError("jdot_v needs a velocity: call update_kinematics(topo, ws, q, v)")
    out = np.empty((topo.njoints, 6)) if out is None else out
    _jdot_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, ws.ov, _vec(x, topo.nv), out)
    return out


def bias_acceleration(topo: Topology, ws: Workspace, out: np.ndarray | None = None) -> np.ndarray:
    """Exact Jdot_mr qdot (body spatial accelerations at zero joint acceleration, world frame,
    (njoints, 6)) for the qdot given to :func:`update_kinematics`; equals Pinocchio's ``data.oa``
    after ``forwardKinematics(model, data, q, qdot, 0)``. This is the Jdot qdot of the quadratic
    velocity term of Eq. (1)/(2), valid for every joint type."""
    if ws.v is None:
        raise ValueError("bias_acceleration needs a velocity: call update_kinematics(topo, ws, q, v)")
    out = np.empty((topo.njoints, 6)) if out is None else out
    bias_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, ws.ov, ws.v, ws.R, ws.p,
                      ws.c_local, out)
    return out


# --------------------------------------------------------------------------------------------
# Sites (points fixed on bodies): Eq. (S2.4), point Jacobian J_x = J_lin - [x] J_ang
# --------------------------------------------------------------------------------------------
@njit
def site_pos_kernel(R, p, joint, offset, out):
    for s in range(joint.shape[0]):
        j = joint[s]
        for a in range(3):
            out[s, a] = p[j, a] + R[j, a, 0] * offset[s, 0] + R[j, a, 1] * offset[s, 1] + R[j, a, 2] * offset[s, 2]


@njit
def _site_vel_kernel(Y, joint, pos, out):
    """u_s = v_o + w x x_s from the body twist (v_o, w) of the site's body."""
    for s in range(joint.shape[0]):
        y = Y[joint[s]]
        x = pos[s]
        out[s, 0] = y[0] + y[4] * x[2] - y[5] * x[1]
        out[s, 1] = y[1] + y[5] * x[0] - y[3] * x[2]
        out[s, 2] = y[2] + y[3] * x[1] - y[4] * x[0]


@njit
def add_point_force(W, j, x, f0, f1, f2):
    """W[j] += (f, x x f): a point force f at world point x as a wrench at the world origin."""
    W[j, 0] += f0
    W[j, 1] += f1
    W[j, 2] += f2
    W[j, 3] += x[1] * f2 - x[2] * f1
    W[j, 4] += x[2] * f0 - x[0] * f2
    W[j, 5] += x[0] * f1 - x[1] * f0


@njit
def _site_wrench_kernel(joint, pos, f, W):
    """W[body] += (f, x x f) per site (:func:`add_point_force`)."""
    for s in range(joint.shape[0]):
        add_point_force(W, joint[s], pos[s], f[s, 0], f[s, 1], f[s, 2])


@njit
def spring_wrench_kernel(ja, a, jb, b, X, f, W):
    """W += the world-origin wrenches of point springs: f[s] on end a (world point X[a[s]], body ja[s]), then
    -f[s] on end b (X[b[s]], body jb[s]); :func:`accumulate_site_forces` of the a ends and then of the b ends
    with -f, in one call without gathering the points."""
    for s in range(ja.shape[0]):
        add_point_force(W, ja[s], X[a[s]], f[s, 0], f[s, 1], f[s, 2])
    for s in range(jb.shape[0]):
        add_point_force(W, jb[s], X[b[s]], -f[s, 0], -f[s, 1], -f[s, 2])


def site_positions(ws: Workspace, joint: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """World positions (m, 3) [m] of sites given as (joint index, offset in that joint's frame).
    Joint 0 (universe): the offset is the world position."""
    joint = np.ascontiguousarray(joint, dtype=np.int64).reshape(-1)
    offset = np.ascontiguousarray(offset, dtype=float).reshape(len(joint), 3)
    out = np.empty((len(joint), 3))
    site_pos_kernel(ws.R, ws.p, joint, offset, out)
    return out


def site_velocities(Y: np.ndarray, joint: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Point velocities (m, 3), world frame, of world points ``pos`` moving with bodies ``joint``
    whose twists are ``Y`` (from :func:`jv`)."""
    joint = np.ascontiguousarray(joint, dtype=np.int64).reshape(-1)
    out = np.empty((len(joint), 3))
    _site_vel_kernel(Y, joint, np.ascontiguousarray(pos, dtype=float).reshape(len(joint), 3), out)
    return out


def accumulate_site_forces(W: np.ndarray, joint: np.ndarray, pos: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Add point forces f (m, 3) [N] applied at world points ``pos`` of bodies ``joint`` to the
    per-body world wrenches ``W`` (njoints, 6) in place; returns W."""
    joint = np.ascontiguousarray(joint, dtype=np.int64).reshape(-1)
    m = len(joint)
    _site_wrench_kernel(joint, np.ascontiguousarray(pos, dtype=float).reshape(m, 3),
                        np.ascontiguousarray(f, dtype=float).reshape(m, 3), W)
    return W


def site_jv(topo: Topology, ws: Workspace, joint: np.ndarray, pos: np.ndarray, x: np.ndarray) -> np.ndarray:
    """J_site x: world velocities (m, 3) of the sites (bodies ``joint``, world points ``pos`` from
    :func:`site_positions`). Row block s = ``getFrameJacobian(..., LOCAL_WORLD_ALIGNED)[:3] @ x``
    of a frame at the site. O(n + m)."""
    return site_velocities(jv(topo, ws, x), joint, pos)


def site_jtf(topo: Topology, ws: Workspace, joint: np.ndarray, pos: np.ndarray, f: np.ndarray) -> np.ndarray:
    """J_site^T f: generalized force (nv,) of world point forces f (m, 3) [N] at the sites. O(n + m)."""
    W = np.zeros((topo.njoints, 6))
    accumulate_site_forces(W, joint, pos, f)
    return jtw(topo, ws, W)


def point_block(x: np.ndarray, K3: np.ndarray) -> np.ndarray:
    """6x6 maximal block X^T K3 X of a 3x3 point stiffness/damping K3 acting at world point x,
    with X = [1, -[x]] the 3x6 map from a world body twist (v_o, w) to the point velocity
    v_o + w x x. This is how a spring at a site maps into blkdiag(h D_m - h^2 K_m) (Eq. (3))."""
    x = np.asarray(x, dtype=float)
    X = np.zeros((3, 6))
    X[:, :3] = np.eye(3)
    X[:, 3:] = -pin.skew(x)
    return X.T @ np.asarray(K3, dtype=float) @ X


# --------------------------------------------------------------------------------------------
# Frame helpers
# --------------------------------------------------------------------------------------------
def twists_world_to_local(ws: Workspace, Y: np.ndarray) -> np.ndarray:
    """Express world twists Y (njoints, 6) in each body's own frame (Pinocchio's pin.LOCAL):
    w_l = R^T w, v_l = R^T (v_o + w x p)."""
    w = Y[:, 3:]
    vo = Y[:, :3] + np.cross(w, ws.p)
    out = np.empty_like(Y)
    out[:, :3] = np.einsum("jab,ja->jb", ws.R, vo)
    out[:, 3:] = np.einsum("jab,ja->jb", ws.R, w)
    return out


def wrenches_local_to_world(ws: Workspace, Wl: np.ndarray) -> np.ndarray:
    """World wrenches (f, tau_o) of wrenches Wl (njoints, 6) given in each body's frame:
    f = R f_l, tau_o = R tau_l + p x f."""
    f = np.einsum("jab,jb->ja", ws.R, Wl[:, :3])
    out = np.empty_like(Wl)
    out[:, :3] = f
    out[:, 3:] = np.einsum("jab,jb->ja", ws.R, Wl[:, 3:]) + np.cross(ws.p, f)
    return out


def block_to_world(R: np.ndarray, p: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A 6x6 maximal block B given for twists in a frame F with world pose (R, p) (e.g. a body
    damping D_m at the COM) expressed for world twists: Fx^T B Fx with Fx = the motion transform
    world -> F."""
    Xi = pin.SE3(np.asarray(R, dtype=float), np.asarray(p, dtype=float)).inverse().action
    return Xi.T @ np.asarray(B, dtype=float) @ Xi


def mass_matrix_product(topo: Topology, ws: Workspace, x: np.ndarray) -> np.ndarray:
    """M_r x = J^T M_m J x + armature * x (Eq. (1) LHS; equals pin.crba(...) @ x). O(n)."""
    Y = jv(topo, ws, x)
    W = np.einsum("jab,jb->ja", ws.I, Y)
    return jtw(topo, ws, W) + topo.armature * _vec(x, topo.nv)
