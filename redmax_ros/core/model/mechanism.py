"""The compiled model of a scene: :class:`Mechanism`, frozen, and :func:`build_mechanism` (SceneSpec ->
Mechanism, the structural part of step.compile.compile_scene).

Like Pinocchio's Model/Data split (and MJX's Model/Data), a Mechanism never changes after compilation:
it holds no cache, no ``pin.Data`` and no scratch; everything a step writes lives in the workspace the
stepping backend creates from it (step/workspace.py). The Mechanism holds the Pinocchio model of the
kinematic tree (reduced coordinates q_r, velocities qdot_r), the sites (points on bodies), the maximal
springs, loop closures, the hyper-reduced coupling matrix J_rR of Eq. (9) (``T`` here: the constant
one; with configuration-dependent catalogue joint maps, J_rR at q0, the workspace holds the live one),
and the per-DOF arrays of the reduced forces (K_r, D_r, explicit torques, limits). SI units throughout.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from redmax_ros.core.model import joint_maps
from redmax_ros.core.errors import SceneError
from redmax_ros.core.geometry.joints import core_joint_model
from redmax_ros.core.geometry.joints import q_index as _catalogue_q_index
from redmax_ros.core.scene.spec import WORLD, SceneSpec
from redmax_ros.core.spatial import placement, rpy_matrix


@dataclass(frozen=True)
class JointInfo:
    name: str
    type: str
    jid: int  # Pinocchio joint index
    idx_q: int
    nq: int
    idx_v: int
    nv: int


@dataclass(frozen=True)
class Mechanism:
    spec: SceneSpec
    model: pin.Model
    joints: list  # JointInfo for every moving joint, tree order
    bodies: list  # body names
    body_jid: np.ndarray  # (B,) joint index of each body (0 = world)
    body_placement: list  # SE3 of each body frame in its joint frame
    body_com: np.ndarray  # (B,3) COM in the joint frame
    body_mass: np.ndarray  # (B,)
    body_inertia: list  # (3,3) inertia about COM, in the joint frame
    site_names: list
    site_jid: np.ndarray  # (S,) joint of each site's body (0 = world)
    site_local: np.ndarray  # (S,3) site position in its joint frame (world frame for world sites)
    site_support: np.ndarray  # (S,nv) bool: velocity DOFs that move the site
    spring_names: list
    spring_ab: np.ndarray  # (P,2) site indices
    spring_k: np.ndarray  # (P,) N/m
    spring_d: np.ndarray  # (P,) N s/m
    spring_rest: np.ndarray  # (P,) m
    loop_names: list
    loop_ab: np.ndarray  # (L,2) site indices
    loop_axes: list  # (k,3) world directions per loop
    T: np.ndarray | None  # J_rR (nv x ndof), Eq. (9); None when there are no couplings
    coupling_names: list
    stiffness: np.ndarray  # (nv,) K_r
    damping: np.ndarray  # (nv,) D_r
    torque0: np.ndarray  # (nv,) constant explicit joint torques
    lower: np.ndarray  # (nv,) joint limits (reduced velocity DOF space; only where nq == nv)
    upper: np.ndarray
    limited: np.ndarray  # indices of velocity DOFs with a finite limit
    limited_q: np.ndarray  # matching configuration indices
    q0: np.ndarray  # (nq,) initial configuration (loops assembled)
    v0: np.ndarray  # (ndof,) initial hyper-reduced velocity
    q_rest: np.ndarray  # (nq,) rest configuration of the joint springs
    damped_bodies: np.ndarray  # indices of bodies with body damping
    body_damping: np.ndarray  # (B,) body damping coefficient c: D_m = c diag(m_d I3, I_d) (body_damping_mass/inertia)
    body_support: np.ndarray  # (B,nv) bool: velocity DOFs that move each body
    wrench_body: np.ndarray  # (W,) body indices
    wrench_fw: np.ndarray  # (W,6) force, torque (world frame)
    prescribable_joints: list
    prescribable_sites: list
    joint_index: dict = field(default_factory=dict)  # name -> JointInfo
    site_index: dict = field(default_factory=dict)  # name -> site row
    site_fid: list = field(default_factory=list)  # Pinocchio frame of each site (-1 for world sites)
    body_com_fid: list = field(default_factory=list)  # Pinocchio frame at each body's COM
    jac_sites: list = field(default_factory=list)  # sites whose Jacobians every step needs (springs, loops)
    jac_row: dict = field(default_factory=dict)  # site -> row in Kinematics.X/J for jac_sites
    spring_rows: np.ndarray | None = None  # (P,2) rows of spring ends in Kinematics.X/J
    loop_rows_ab: np.ndarray | None = None  # (L,2) rows of loop sites in Kinematics.X/J
    has_stiffness: bool = False
    loop_select: np.ndarray | None = None  # (rows, 3L) block-diagonal loop axes: phi = S (x_a - x_b)
    has_armature: bool = False
    no_rows: np.ndarray | None = None  # (0, ndof): G when there are no bilateral rows
    armature: np.ndarray | None = None  # (nv,)
    limit_rows: np.ndarray | None = None  # (p,ndof) rows of J_rR for the limited DOFs
    limit_labels: list = field(default_factory=list)
    limit_lower: np.ndarray | None = None  # (p,) lower[limited] [rad, m]
    limit_upper: np.ndarray | None = None  # (p,) upper[limited]
    extras: object = None  # catalogue_hooks.Extras (compiled; workspaces run copies): mapped joints, linear joint constraints, force elements (or None)
    friction: object = None  # contact.FrictionModel (ground contact, joint friction) or None
    collision: object = None  # model/collision.CollisionModel (self-collision, obstacles; docs/collisions.md) or None
    joint_support: np.ndarray | None = None  # (njoints, nv) bool: DOFs moving each joint's body (row 0: world)
    scheme: str = "euler"  # integrator.scheme: euler | bdf2 (step/scheme.py)
    coriolis_implicit: bool = False  # integrator.coriolis: implicit (forces.coriolis_jacobian; docs/scenes.md)
    # integrator.spring_stiffness: full (True, default): the springs' K_m includes the lever-arm blocks of
    # springs.geometric_blocks_kernel; gauss_newton (False): J^T K J of the 3x3 point stiffness only
    spring_geometric: bool = True
    loop_baumgarte: float = 0.0  # [1/s] b of Baumgarte loop stabilization (G qdot+ = -b phi); 0: post-stabilization
    maps: object = None  # joint_maps.Maps (spline/exp/Euler-chart joints) as built, or None (compile only)
    # body damping D_m = c diag(m_d I3, I_d) at each body's COM (joint frame; scene/bodies.body_damping):
    # form 'mass': m_d = m, I_d = I_com; form 'twist' (D_m = c I6 on the body twist): m_d = 1, I_d = I3
    body_damping_mass: np.ndarray | None = None  # (B,)
    body_damping_inertia: list = field(default_factory=list)  # (B,) of (3,3)
    spring_explicit: np.ndarray | None = None  # (P,) bool: springs with implicit: false (no K/D in Eq. 2's LHS)

    @property
    def nq(self) -> int:
        return self.model.nq

    @property
    def nv(self) -> int:
        return self.model.nv

    @property
    def ndof(self) -> int:
        return self.nv if self.T is None else self.T.shape[1]

    def to_reduced(self, vR: np.ndarray) -> np.ndarray:
        """qdot_r = J_rR qdot_R (Eq. 8-9) with the compile-time J_rR. Exact for every scene whose J_rR is
        constant (couplings); with catalogue joint maps (configuration-dependent J_rR) a step's J_rR is the
        workspace's: use Workspace.to_reduced (Simulator.joint_velocities does)."""
        return vR if self.T is None else self.T @ vR

    def position_names(self) -> list:
        return [n for j in self.joints for n in _names(j.name, j.nq)]

    def velocity_names(self) -> list:
        return [n for j in self.joints for n in _names(j.name, j.nv)]


def _names(name, n):
    return [name] if n == 1 else [f"{name}[{i}]" for i in range(n)]


# ----------------------------------------------------------------------------------------------


def joint_configuration(jtype: str, vals: np.ndarray) -> np.ndarray:
    """Scene-file joint values (see scene.JOINT_TYPES) -> Pinocchio configuration of that joint."""
    if jtype in ("revolute", "prismatic", "universal"):
        return np.asarray(vals, float)
    if jtype == "spherical":
        return pin.Quaternion(rpy_matrix(vals)).coeffs().copy()
    if jtype == "planar":
        x, y, th = vals
        return np.array([x, y, np.cos(th), np.sin(th)])
    if jtype == "free":
        return np.concatenate([vals[:3], pin.Quaternion(rpy_matrix(vals[3:])).coeffs()])
    raise AssertionError(jtype)


def _spatial_inertia(b):
    return pin.Inertia(b.mass, np.asarray(b.com, float), np.asarray(b.inertia, float))


def _build_tree(spec: SceneSpec):
    """Pinocchio model from the scene's joints/bodies; fixed joints merge bodies into parents."""
    model = pin.Model()
    model.name = spec.name
    bodies = {b.name: b for b in spec.bodies}
    frame_of = {WORLD: (0, pin.SE3.Identity())}  # body -> (joint id, body frame in joint frame)
    q0, rest, joint_specs = [], [], []
    for j in spec.joints:  # parent-first order (validated)
        pj, pM = frame_of[j.parent]
        jM = pM * placement(*j.placement)
        bM = placement(*j.body_placement)
        if j.type == "fixed":
            jid, M = pj, jM * bM
        elif "nv" in j.extra:  # notes §2.5 catalogue joints (joints.py; spline/exp joints: carrier + coordinates)
            jid, added = joint_maps.add_to_model(model, pj, j, jM)
            M = bM
            for js, q_, r_ in added:
                q0.append(q_)
                rest.append(r_)
                joint_specs.append(js)
        else:
            jid = model.addJoint(pj, core_joint_model(j), jM, j.name)
            M = bM
            q0.append(joint_configuration(j.type, j.q0))
            rest.append(joint_configuration(j.type, j.rest))
            joint_specs.append(j)
        model.appendBodyToJoint(jid, _spatial_inertia(bodies[j.child]), M)
        model.addFrame(pin.Frame(j.child, jid, 0, M, pin.FrameType.BODY))
        frame_of[j.child] = (jid, M)
    q0 = np.concatenate(q0) if q0 else np.zeros(0)
    rest = np.concatenate(rest) if rest else np.zeros(0)
    return model, frame_of, q0, rest, joint_specs


def _build_urdf(spec: SceneSpec):
    if spec.urdf_fixed_base:
        model = pin.buildModelFromUrdf(spec.urdf)
    else:
        model = pin.buildModelFromUrdf(spec.urdf, pin.JointModelFreeFlyer())
    frame_of = {WORLD: (0, pin.SE3.Identity())}
    for f in model.frames:
        if f.type == pin.FrameType.BODY:
            frame_of[f.name] = (f.parentJoint, f.placement)
    q0 = pin.neutral(model)
    return model, frame_of, q0, q0.copy(), None


def build_mechanism(spec: SceneSpec) -> Mechanism:
    """The Mechanism of a validated scene (Pinocchio model, sites, forces, constraints, couplings) before
    the compile steps that need the dynamics (step.compile.compile_scene: catalogue hooks, loop assembly,
    spring rest lengths, friction). ``v0`` is still the reduced initial velocity here."""
    src = spec.source
    if spec.urdf:
        model, frame_of, q0, q_rest, jspecs = _build_urdf(spec)
    else:
        model, frame_of, q0, q_rest, jspecs = _build_tree(spec)
    model.gravity = pin.Motion(np.asarray(spec.gravity, float), np.zeros(3))
    nv = model.nv
    joints = []
    for jid in range(1, model.njoints):
        jm = model.joints[jid]
        jtype = jspecs[jid - 1].type if jspecs else _urdf_joint_type(jm.shortname())
        joints.append(JointInfo(model.names[jid], jtype, jid, jm.idx_q, jm.nq, jm.idx_v, jm.nv))
    joint_index = {j.name: j for j in joints}

    stiffness, damping, torque0 = np.zeros(nv), np.zeros(nv), np.zeros(nv)
    lower, upper = np.full(nv, -np.inf), np.full(nv, np.inf)
    v0r = np.zeros(nv)
    if jspecs:
        for js, ji in zip(jspecs, joints):
            sl = slice(ji.idx_v, ji.idx_v + ji.nv)
            stiffness[sl], damping[sl], torque0[sl] = js.stiffness, js.damping, js.torque
            model.armature[sl] = js.armature
            lower[sl], upper[sl] = js.lower, js.upper
            v0r[sl] = js.v0
    else:  # URDF: position limits on 1-DOF joints, <dynamics damping>
        for ji in joints:
            if ji.nq == 1 and ji.nv == 1:
                lo, up = model.lowerPositionLimit[ji.idx_q], model.upperPositionLimit[ji.idx_q]
                if np.isfinite(lo) and np.isfinite(up) and up > lo:
                    lower[ji.idx_v], upper[ji.idx_v] = lo, up
        damping[:] = np.asarray(model.damping)
    limited = np.flatnonzero(np.isfinite(lower) | np.isfinite(upper))
    limited_q = np.array([_catalogue_q_index(model, int(i)) for i in limited], dtype=int)

    # bodies
    body_names = [n for n in frame_of if n != WORLD]
    inertia_of = {b.name: b for b in spec.bodies}
    body_jid = np.array([frame_of[n][0] for n in body_names], dtype=int)
    body_pl = [frame_of[n][1] for n in body_names]
    if spec.urdf:  # inertias are already lumped per joint in the URDF model
        masses = [model.inertias[int(j)].mass for j in body_jid]
        coms = [model.inertias[int(j)].lever.copy() for j in body_jid]
        Is = [model.inertias[int(j)].inertia.copy() for j in body_jid]
    else:
        masses = [inertia_of[n].mass for n in body_names]
        coms = [M.act(np.asarray(inertia_of[n].com)) for n, M in zip(body_names, body_pl)]
        Is = [M.rotation @ inertia_of[n].inertia @ M.rotation.T for n, M in zip(body_names, body_pl)]
    body_damping = np.array([inertia_of[n].damping if n in inertia_of else 0.0 for n in body_names])
    damped = np.flatnonzero(body_damping > 0)
    twist_damped = [n in inertia_of and inertia_of[n].damping_form == "twist" for n in body_names]
    damp_mass = np.array([1.0 if t else m for t, m in zip(twist_damped, masses)], dtype=float)
    damp_inertia = [np.eye(3) if t else np.asarray(I, float) for t, I in zip(twist_damped, Is)]
    support_of = support_table(model)  # (njoints, nv) bool, one pass (model.joints[j] copies are slow)
    body_support = support_of[body_jid].reshape(-1, nv)

    # sites
    site_names = [s.name for s in spec.sites]
    site_jid = np.array([frame_of[s.body][0] for s in spec.sites], dtype=int)
    site_local = np.array([frame_of[s.body][1].act(np.asarray(s.pos, float)) for s in spec.sites]).reshape(-1, 3)
    support = support_of[site_jid].reshape(-1, nv)
    site_index = {n: i for i, n in enumerate(site_names)}

    # couplings: T = J_rR (Eq. 9)
    T, cnames = _coupling_matrix(spec, joint_index, nv, src)
    maps = joint_maps.Maps.build(model, joints, jspecs, T, q0, v0r) if jspecs else None
    if maps is not None:  # spline/exp joints: configuration-dependent J_rR (joint_maps.py)
        T = maps.T0

    # wrenches
    bidx = {n: i for i, n in enumerate(body_names)}
    wrench_body = np.array([bidx[w.body] for w in spec.wrenches], dtype=int)
    wrench_fw = np.array([np.concatenate([w.force, w.torque]) for w in spec.wrenches]).reshape(-1, 6)

    # prescriptions
    movable = [j.name for j in joints if j.type != "carrier"]
    pj = spec.prescribable_joints if spec.prescribable_joints is not None else movable
    for n in pj:
        if n not in joint_index:
            raise SceneError(src, "prescribable.joints", f"unknown joint '{n}'")
    ps = spec.prescribable_sites if spec.prescribable_sites is not None else site_names

    site_fid = []
    for s_, jid, loc in zip(spec.sites, site_jid, site_local):
        if jid == 0:
            site_fid.append(-1)
        else:
            site_fid.append(model.addFrame(pin.Frame(f"site:{s_.name}", int(jid), 0, pin.SE3(np.eye(3), loc),
                                                     pin.FrameType.OP_FRAME)))
    com_fid = []
    for n, jid, c in zip(body_names, body_jid, coms):
        com_fid.append(model.addFrame(pin.Frame(f"com:{n}", int(jid), 0, pin.SE3(np.eye(3), np.asarray(c)),
                                                pin.FrameType.OP_FRAME)) if jid else -1)
    jac_sites = sorted({int(i) for s_ in spec.springs for i in (site_index[s_.a], site_index[s_.b])}
                       | {int(i) for lp in spec.loops for i in (site_index[lp.a], site_index[lp.b])})
    jac_row = {s_: k for k, s_ in enumerate(jac_sites)}

    nrows = sum(len(lp.axes) for lp in spec.loops)
    loop_select = np.zeros((nrows, 3 * len(spec.loops)))
    r = 0
    for i, lp in enumerate(spec.loops):
        loop_select[r:r + len(lp.axes), 3 * i:3 * i + 3] = lp.axes
        r += len(lp.axes)
    armature = np.array(model.armature, dtype=float).reshape(nv)
    limit = {}
    if len(limited):
        Cr = np.zeros((len(limited), nv))
        Cr[np.arange(len(limited)), limited] = 1.0
        names = [n for j in joints for n in _names(j.name, j.nv)]
        limit = dict(limit_rows=Cr if T is None else Cr @ T,
                     limit_labels=[f"limit of joint DOF '{names[i]}'" for i in limited],
                     limit_lower=lower[limited], limit_upper=upper[limited])
    spring_ab = np.array([[site_index[s.a], site_index[s.b]] for s in spec.springs], dtype=int).reshape(-1, 2)
    loop_ab = np.array([[site_index[lp.a], site_index[lp.b]] for lp in spec.loops], dtype=int).reshape(-1, 2)
    for name in spec.prescribed_joints:
        if name not in joint_index:
            raise SceneError(src, "prescribed.joints", f"unknown joint '{name}'")
        if joint_index[name].nv != len(spec.prescribed_joints[name]):
            raise SceneError(src, f"prescribed.joints.{name}",
                             f"needs {joint_index[name].nv} values, got {len(spec.prescribed_joints[name])}")
    ndof = nv if T is None else T.shape[1]
    return Mechanism(
        spec=spec, model=model, joints=joints, bodies=body_names, body_jid=body_jid, body_placement=body_pl,
        body_com=np.array(coms).reshape(-1, 3), body_mass=np.array(masses), body_inertia=Is,
        site_names=site_names, site_jid=site_jid, site_local=site_local, site_support=support,
        spring_names=[s.name for s in spec.springs], spring_ab=spring_ab,
        spring_k=np.array([s.stiffness for s in spec.springs]), spring_d=np.array([s.damping for s in spec.springs]),
        spring_rest=np.zeros(len(spec.springs)),
        loop_names=[lp.name for lp in spec.loops], loop_ab=loop_ab, loop_axes=[lp.axes for lp in spec.loops],
        T=T, coupling_names=cnames, stiffness=stiffness, damping=damping, torque0=torque0, lower=lower, upper=upper,
        limited=limited, limited_q=limited_q, q0=q0, v0=v0r, q_rest=q_rest, damped_bodies=damped,
        body_damping=body_damping, body_support=body_support,
        body_damping_mass=damp_mass, body_damping_inertia=damp_inertia,
        spring_explicit=np.array([not s.implicit for s in spec.springs], dtype=bool),
        wrench_body=wrench_body, wrench_fw=wrench_fw, prescribable_joints=list(pj), prescribable_sites=list(ps),
        joint_index=joint_index, site_index=site_index, site_fid=site_fid, body_com_fid=com_fid,
        jac_sites=jac_sites, jac_row=jac_row, has_stiffness=bool(stiffness.any()),
        loop_select=loop_select, has_armature=bool(armature.any()), no_rows=np.zeros((0, ndof)), armature=armature,
        joint_support=support_of,
        spring_rows=np.array([[jac_row[a], jac_row[b]] for a, b in spring_ab], dtype=int).reshape(-1, 2),
        loop_rows_ab=np.array([[jac_row[a], jac_row[b]] for a, b in loop_ab], dtype=int).reshape(-1, 2),
        coriolis_implicit=spec.coriolis == "implicit", maps=maps, scheme=spec.scheme,
        spring_geometric=spec.spring_stiffness == "full",
        loop_baumgarte=float(spec.baumgarte_b) if spec.stabilization == "baumgarte" else 0.0, **limit,
    )


def _urdf_joint_type(short: str) -> str:
    """Scene vocabulary for a Pinocchio joint model name (URDF scenes)."""
    s = short.replace("JointModel", "")
    if s.startswith(("RU", "R")) and not s.startswith("Rev") or s.startswith("Revolute"):
        return "revolute"
    if s.startswith("P") and not s.startswith("Planar"):
        return "prismatic"
    return {"FreeFlyer": "free", "Spherical": "spherical", "SphericalZYX": "spherical", "Planar": "planar",
            "Universal": "universal", "Translation": "translational"}.get(s, s.lower())


def _q_index(joints, dof):
    for j in joints:
        if j.idx_v <= dof < j.idx_v + j.nv:
            assert j.nq == j.nv
            return j.idx_q + dof - j.idx_v
    raise AssertionError(dof)


def support_table(model):
    """Row j: the velocity DOFs that move joint j's body (j and its ancestors); row 0 (world) empty."""
    nj = model.njoints
    table = np.zeros((nj, model.nv), dtype=bool)
    idx_v, nv_j, parents = model.idx_vs, model.nvs, model.parents
    for j in range(1, nj):
        table[j] = table[int(parents[j])]
        table[j, idx_v[j]:idx_v[j] + nv_j[j]] = True
    return table


def _coupling_matrix(spec, joint_index, nv, src):
    if not spec.couplings:
        return None, []
    owner = {}  # reduced dof -> (coupling index, ratio)
    for ci, c in enumerate(spec.couplings):
        for jn, r in zip(c.joints, c.ratios):
            if jn not in joint_index:
                raise SceneError(src, f"couplings '{c.name}'", f"unknown joint '{jn}'")
            ji = joint_index[jn]
            if ji.nv != 1:
                raise SceneError(src, f"couplings '{c.name}'", f"joint '{jn}' must have one DOF")
            if ji.idx_v in owner:
                raise SceneError(src, f"couplings '{c.name}'", f"joint '{jn}' is already in another coupling")
            owner[ji.idx_v] = (ci, r)
    cols, col_of_coupling = [], {}
    T = np.zeros((nv, nv))
    for d in range(nv):
        if d in owner:
            ci, r = owner[d]
            if ci not in col_of_coupling:
                col_of_coupling[ci] = len(cols)
                cols.append(ci)
            T[d, col_of_coupling[ci]] = r
        else:
            T[d, len(cols)] = 1.0
            cols.append(None)
    return T[:, :len(cols)].copy(), [c.name for c in spec.couplings]


def check_couplings_q0(mech) -> None:
    """SceneError unless the initial configuration of every coupling is proportional to its ratios."""
    spec, src = mech.spec, mech.spec.source
    for c in spec.couplings:
        qs = np.array([mech.q0[mech.joint_index[j].idx_q] for j in c.joints])
        theta = qs / c.ratios
        if np.ptp(theta) > 1e-12 * max(1.0, np.abs(theta).max()):
            raise SceneError(src, f"couplings '{c.name}'",
                             f"initial q0 of {c.joints} ({qs.tolist()}) must be proportional to ratios {c.ratios.tolist()}")


def hyper_reduced_v0(mech, v0r) -> np.ndarray:
    """qdot_R(0) from the scene's reduced initial velocities (SceneError if not in the range of J_rR)."""
    if mech.T is None:
        return v0r.copy()
    vR, *_ = np.linalg.lstsq(mech.T, v0r, rcond=None)
    if np.abs(mech.T @ vR - v0r).max() > 1e-9:
        raise SceneError(mech.spec.source, "couplings", "initial joint velocities v0 are not consistent with the coupling ratios")
    return vR
