"""The compiled step's static Model (MJX's ``Model``): every constant of a Mechanism the step needs, as flat
arrays built once (:func:`build_model`), unpacked inside numba by :func:`model_views` into the namedtuple
:data:`Model`. Units SI (m, kg, kg m^2, N/m, N s/m, N m/rad, rad).

:func:`unsupported` says why a Mechanism cannot take the compiled path (then the Pinocchio pipeline, the
reference, steps it): contact or joint friction beyond friction.friction_unsupported's set, catalogue joints and force elements (splines,
exponential coordinates, Euler charts, timed loads...), the implicit Coriolis option, Pinocchio joints
other than revolute, prismatic, helical, spherical, free, translation, universal and planar, or more
than PIN_DATA_MAX_NV DOFs (the dense solve of this path).
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np

from redmax_ros.core.dynamics.springs import needs_velocities
from redmax_ros.core.dynamics.tree_forces import all_support_runs
from redmax_ros.core.dynamics.tree_kinematics import PIN_DATA_MAX_NV, Context
from redmax_ros.core.jit import njit_inline
from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.step.compiled.friction import friction_unsupported
from redmax_ros.core.step.compiled.manifold import PLANAR, UNIVERSAL, joint_kinds
from redmax_ros.core.step.compiled.packing import f1, f2, f3, i1, i2, pack

# (name, 'f' float64 | 'i' int64, ndim), in the order of the Model namedtuple
MODEL_SPEC = (
    # tree (Pinocchio joint order, row 0 = universe): recursive.Topology
    ("parents", "i", 1), ("kind", "i", 1), ("idx_q", "i", 1), ("idx_v", "i", 1), ("nv_j", "i", 1),
    ("axis", "f", 2), ("pitch", "f", 1), ("place_R", "f", 3), ("place_p", "f", 2),
    ("mass", "f", 1), ("com", "f", 2), ("inertia_com", "f", 3), ("Sl0", "f", 2),
    ("uni_joints", "i", 1), ("uni_a1", "f", 2), ("uni_a2", "f", 2), ("planar_joints", "i", 1),
    ("gravity", "f", 1),
    # reduced-coordinate terms (nv,): armature, joint damping D_r, stiffness K_r, rest configuration, torques
    ("armature", "f", 1), ("damping", "f", 1), ("stiffness", "f", 1), ("q_rest", "f", 1),
    # hyper-reduced coordinates (Eq. 9-10): T = J_rR (nv, ndof); (0, 0) without couplings
    ("T", "f", 2), ("T_rep", "i", 1), ("T_rep_ratio", "f", 1),
    # sites
    ("site_jid", "i", 1), ("site_local", "f", 2),
    # maximal point-to-point springs (site indices)
    ("spring_a", "i", 1), ("spring_b", "i", 1), ("spring_k", "f", 1), ("spring_d", "f", 1),
    ("spring_rest", "f", 1), ("spring_explicit", "i", 1),
    # loops: site indices per loop, phi = S (x_a - x_b)
    ("loop_a", "i", 1), ("loop_b", "i", 1), ("loop_select", "f", 2),
    # body damping (per damped body) and constant world wrenches at COMs
    ("damp_jid", "i", 1), ("damp_com", "f", 2), ("damp_I", "f", 3), ("damp_m", "f", 1), ("damp_c", "f", 1),
    ("wrench_jid", "i", 1), ("wrench_com", "f", 2), ("wrench_fw", "f", 2),
    # joint limits (Eq. 5): rows of J_rR of the limited DOFs, their configuration index and bounds
    ("limit_rows", "f", 2), ("limited_q", "i", 1), ("limit_lower", "f", 1), ("limit_upper", "f", 1),
    # scalars: [loop Baumgarte b (0: post-stabilization), has_stiffness, has_armature, explicit spring dampers,
    #           springs' lever-arm stiffness (integrator.spring_stiffness: full)]
    ("scalars", "f", 1),
    # joints carrying each spring end
    ("spring_ja", "i", 1), ("spring_jb", "i", 1),
    # J_rR as one entry per row (a coupled DOF moves with exactly one coupling): qdot_r[i] = T_ratio[i] qdot_R[T_col[i]]
    ("T_col", "i", 1), ("T_ratio", "f", 1),
    # the DOFs supporting each joint's body as runs of consecutive indices (tree_forces.all_support_runs)
    ("support_ptr", "i", 1), ("support_runs", "i", 2),
    # the loop of each loop row (row r of loop_select is zero outside columns 3 l .. 3 l + 2, l = loop_row_loop[r])
    ("loop_row_loop", "i", 1),
)

Model = namedtuple("Model", [n for n, _, _ in MODEL_SPEC])


@njit_inline
def model_views(f, i, t):
    """The Model namedtuple of views into the packed buffers (MODEL_SPEC order)."""
    return Model(i1(i, t, 0), i1(i, t, 1), i1(i, t, 2), i1(i, t, 3), i1(i, t, 4),
                 f2(f, t, 5), f1(f, t, 6), f3(f, t, 7), f2(f, t, 8),
                 f1(f, t, 9), f2(f, t, 10), f3(f, t, 11), f2(f, t, 12),
                 i1(i, t, 13), f2(f, t, 14), f2(f, t, 15), i1(i, t, 16),
                 f1(f, t, 17),
                 f1(f, t, 18), f1(f, t, 19), f1(f, t, 20), f1(f, t, 21),
                 f2(f, t, 22), i1(i, t, 23), f1(f, t, 24),
                 i1(i, t, 25), f2(f, t, 26),
                 i1(i, t, 27), i1(i, t, 28), f1(f, t, 29), f1(f, t, 30), f1(f, t, 31), i1(i, t, 32),
                 i1(i, t, 33), i1(i, t, 34), f2(f, t, 35),
                 i1(i, t, 36), f2(f, t, 37), f3(f, t, 38), f1(f, t, 39), f1(f, t, 40),
                 i1(i, t, 41), f2(f, t, 42), f2(f, t, 43),
                 f2(f, t, 44), i1(i, t, 45), f1(f, t, 46), f1(f, t, 47),
                 f1(f, t, 48),
                 i1(i, t, 49), i1(i, t, 50),
                 i1(i, t, 51), f1(f, t, 52),
                 i1(i, t, 53), i2(i, t, 54), i1(i, t, 55))


SUPPORTED_KINDS = {rc.REVOLUTE, rc.REVOLUTE_UNBOUNDED, rc.PRISMATIC, rc.HELICAL, rc.SPHERICAL, rc.FREEFLYER,
                   rc.TRANSLATION, UNIVERSAL, PLANAR}


def unsupported(mech) -> list:
    """What keeps ``mech`` off the compiled path (empty: supported)."""
    out = []
    out += friction_unsupported(mech)
    if mech.extras is not None:
        out.append("catalogue joints/force elements")
    if mech.coriolis_implicit:
        out.append("integrator.coriolis: implicit")
    if mech.scheme == "bdf2" and mech.loop_baumgarte:
        out.append("integrator.scheme: bdf2 with stabilization: baumgarte")
    if mech.nv > PIN_DATA_MAX_NV:
        out.append(f"more than {PIN_DATA_MAX_NV} DOFs")
    if mech.T is not None and ((np.asarray(mech.T) != 0).sum(1) != 1).any():
        out.append("couplings with a DOF in more than one coupling")
    kinds = joint_kinds(mech.model)
    bad = sorted({mech.model.joints[j].shortname() for j in range(1, len(kinds)) if kinds[j] not in SUPPORTED_KINDS})
    if bad:
        out.append("joint types " + ", ".join(bad))
    return out


def loop_row_loop(select) -> np.ndarray:
    """The loop of every row of the loop selection S (rows, 3 L): each row is one loop's axis, nonzero in that
    loop's three columns only (mechanism.py builds S block by block); a row of zeros is given loop 0."""
    nz = np.asarray(select) != 0.0
    if nz.size == 0:
        return np.zeros(nz.shape[0], dtype=np.int64)
    rows = nz.any(axis=1)
    loops = np.where(rows, np.argmax(nz, axis=1) // 3, 0).astype(np.int64)
    for r in np.flatnonzero(rows):
        cols = np.flatnonzero(nz[r])
        assert (cols // 3 == loops[r]).all(), "a loop row spans two loops"
    return loops


def build_model(mech):
    """Pack the constants of ``mech`` (supported: :func:`unsupported` is empty). Returns a packing.Packed."""
    ctx = Context(mech)
    topo = ctx.topo
    model = mech.model
    kinds = joint_kinds(model)
    nj, nv = topo.njoints, topo.nv
    Sl0 = np.ascontiguousarray(topo.S_const.T).copy()
    uni, a1, a2, planar = [], [], [], []
    for j in range(1, nj):
        jm = model.joints[j]
        if kinds[j] == UNIVERSAL:
            e = jm.extract()
            uni.append(j)
            a1.append(np.array(e.axis1, float))
            a2.append(np.array(e.axis2, float))
        elif kinds[j] == PLANAR:  # constant S: (vx, vy, wz) in the joint frame, zero bias (pin.JointModelPlanar)
            planar.append(j)
            S = np.zeros((6, 3))
            S[0, 0] = S[1, 1] = S[5, 2] = 1.0
            Sl0[jm.idx_v:jm.idx_v + 3] = S.T
    T = np.zeros((0, 0)) if mech.T is None else np.asarray(mech.T, float)
    ndof = mech.ndof
    P = len(mech.spring_ab)
    L = len(mech.loop_ab)
    nlim = len(mech.limited)
    explicit = mech.spring_explicit if mech.spring_explicit is not None else np.zeros(P, bool)
    values = dict(
        parents=topo.parents, kind=kinds, idx_q=topo.idx_q, idx_v=topo.idx_v, nv_j=topo.nv_j,
        axis=topo.axis, pitch=topo.pitch, place_R=topo.place_R, place_p=topo.place_p,
        mass=topo.mass, com=topo.com, inertia_com=topo.inertia_com, Sl0=Sl0,
        uni_joints=np.array(uni, np.int64), uni_a1=np.array(a1).reshape(-1, 3), uni_a2=np.array(a2).reshape(-1, 3),
        planar_joints=np.array(planar, np.int64), gravity=ctx.gravity,
        armature=topo.armature, damping=mech.damping, stiffness=mech.stiffness, q_rest=mech.q_rest,
        T=T, T_rep=np.zeros(0, np.int64) if ctx.T_rep is None else ctx.T_rep,
        T_rep_ratio=np.zeros(0) if ctx.T_rep is None else ctx.T_rep_ratio,
        site_jid=ctx.site_jid, site_local=ctx.site_local.reshape(-1, 3),
        spring_a=mech.spring_ab[:, 0] if P else np.zeros(0), spring_b=mech.spring_ab[:, 1] if P else np.zeros(0),
        spring_k=mech.spring_k.reshape(P), spring_d=mech.spring_d.reshape(P), spring_rest=mech.spring_rest.reshape(P),
        spring_explicit=np.asarray(explicit, np.int64).reshape(P),
        loop_a=mech.loop_ab[:, 0] if L else np.zeros(0), loop_b=mech.loop_ab[:, 1] if L else np.zeros(0),
        loop_select=mech.loop_select if L else np.zeros((0, 0)),
        damp_jid=ctx.damp_jid, damp_com=ctx.damp_com.reshape(-1, 3), damp_I=ctx.damp_I, damp_m=ctx.damp_m,
        damp_c=ctx.damp_c, wrench_jid=ctx.wrench_jid, wrench_com=ctx.wrench_com.reshape(-1, 3),
        wrench_fw=ctx.wrench_fw,
        limit_rows=mech.limit_rows if nlim else np.zeros((0, ndof)),
        limited_q=mech.limited_q if nlim else np.zeros(0), limit_lower=mech.limit_lower if nlim else np.zeros(0),
        limit_upper=mech.limit_upper if nlim else np.zeros(0),
        spring_ja=ctx.spring_ja, spring_jb=ctx.spring_jb,
        T_col=np.zeros(0, np.int64) if mech.T is None else np.argmax(np.abs(T), axis=1),
        T_ratio=np.zeros(0) if mech.T is None else T[np.arange(nv), np.argmax(np.abs(T), axis=1)],
        scalars=np.array([float(mech.loop_baumgarte), float(mech.has_stiffness), float(mech.has_armature),
                          float(needs_velocities(mech)), float(mech.spring_geometric)]),
    )
    values["support_ptr"], values["support_runs"] = all_support_runs(topo.parents, topo.idx_v, topo.nv_j)
    values["loop_row_loop"] = loop_row_loop(values["loop_select"])
    assert nv == mech.nv
    return pack(MODEL_SPEC, values)
