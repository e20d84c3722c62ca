"""Contact and friction geometry: the constant part (compiled with the Mechanism) and the per-step rows.

Ground contact (paper §5.1, Sueda's notes §1.11): contact primitives on bodies (points, spheres,
capsules = two end spheres, boxes = eight corner points) against world planes n . x = offset.
Every primitive is sampled as spheres (centre on a body, radius r >= 0); a sphere/plane pair whose
gap d = n . c - offset - r is below ``margin`` is a contact with
  * one normal row  N = n^T J_x (J_x the point Jacobian of the contact point x = c - r n, Eq. 1.90-1.91
    written in reduced coordinates through J_mr, i.e. the unilateral rows C_m J_mr of Eq. 5), with the
    velocity bound N qdot >= -d/h when d >= 0 (speculative contact: the body may close the gap this
    step but not cross it; restitution zero) and N qdot >= -erp d / h when d < 0 (penetration is
    removed at the rate erp per step: velocity-level stabilization, Sueda's notes §1.12);
  * two tangent rows T = t_i^T J_x along t_1 (the world x axis, or y, projected onto the plane) and
    t_2 = n x t_1: the four-sided friction pyramid |beta_i| <= mu alpha (Eq. 12, notes Eq. 1.100).

Frictional joints (BISP, paper §5.2, notes §2.12): implicit contact points fixed in the child joint
frame (the pin turns with the child body), on the joint geometry given in the scene file:
  * revolute: ``points`` points on each of the two end circles (radius r, at +-length/2 along the
    axis) of a cylinder around the axis; at each point a radial and an axial normal (together they
    span the 5 constraint directions: forces in 3D and the two moments normal to the axis);
  * prismatic: the same two circles around the sliding axis, with a radial and a circumferential
    normal at each point (forces normal to the axis, all three moments);
  * prismatic with a box cross-section (``shape: box``, full widths w1, w2 along u1, u2 of
    box_section_axes): the 8 corners (+-w1/2 u1 +-w2/2 u2 at +-length/2 along the axis), each with the
    two face normals meeting there, u1 and u2 (the same 5 directions). The minimum-norm split of a
    force F = F1 u1 + F2 u2 through the joint origin puts F1/8 on every u1 normal and F2/8 on every u2
    normal, so sum_k |alpha_k| = h (|F1| + |F2|): a load along one face normal is carried once, a
    diagonal one on both faces;
  * spherical: six points on a ball of radius r (+-x, +-y, +-z), radial normals (the 3 forces);
    ``spherical_exp`` (a coordinate map on a quaternion Spherical carrier, model/joint_maps.py): the same
    ball on the carrier joint, whose angular velocity the friction rows act on; in hyper-reduced
    coordinates a row is r (u x t)^T J_rR(q) (Eq. 9-10), refreshed every step with the live J_rR.
The local least squares of Eq. (16), alpha_i = h (N_i M_i^-1 N_i^T + eps I)^-1 N_i M_i^-1 f_ai, uses
the child body's spatial inertia M_i in the joint frame, so its operator L_i is a constant of the
mechanism (precomputed here, with the projection that removes the joint's motion-subspace part of
the wrench: only the constraint part of the reaction is distributed to the contact points).
Friction in a 1-DOF joint: every implicit point slips at the same rate (r qdot for a revolute, qdot
for a prismatic), so the friction QP row is r e_j (or e_j) with the exact box bound
mu sum_k |alpha_k| ("for 1 DOF joints the cone degenerates into a box", §5.1). Spherical: two tangent
rows per point with the four-sided pyramid bound mu |alpha_k|.
Loop-closing pins (paper §5.3): points around the pin axis (world direction) at the loop's site,
same layout as a revolute joint, unweighted least squares (M_i = I: a loop has no single child body).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numba import njit

from redmax_ros.core.errors import SceneError
from redmax_ros.core.friction.arena import empty_arena, take, take1, take3
from redmax_ros.core.model.joint_maps import ROTATION_TYPES, carrier_name, is_mapped
from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.spatial import rpy_matrix


@dataclass
class FrictionModel:
    settings: object  # contact_schema.FrictionSettings
    plane_n: np.ndarray  # (P,3)
    plane_off: np.ndarray  # (P,)
    plane_mu: np.ndarray  # (P,)
    plane_t: np.ndarray  # (P,2,3) tangent directions
    plane_names: list
    sph_jid: np.ndarray  # (K,) joint of each contact sphere (sampled primitives)
    sph_local: np.ndarray  # (K,3) centre in the joint frame
    sph_radius: np.ndarray  # (K,)
    sph_mu: np.ndarray  # (K,) NaN = the plane's mu
    sph_support: np.ndarray  # (K,nv) bool
    sph_label: list  # "contact 'name'[i]"
    # frictional tree joints and loops: padded implicit-contact operators (Eq. 16)
    fj_names: list  # tree joints then loops
    fj_jid: np.ndarray  # (J,) Pinocchio joint of each frictional tree joint
    n_tree: int
    L: np.ndarray  # (J+Lf, kmax, 6) alpha = h L f (f: joint wrench, local frame / world for loops)
    rows_fixed: np.ndarray  # (F1, ndof) constant friction rows of the tree joints
    bound_B: np.ndarray  # (F1 + Lf, (J+Lf)*kmax) bound = B |alpha| (mu included)
    loop_index: np.ndarray  # (Lf,) indices into mech.loop_names
    loop_axis: np.ndarray  # (Lf,3)
    loop_radius: np.ndarray  # (Lf,)
    loop_rowslices: list  # rows of each frictional loop in the loop block of G
    loop_sites: np.ndarray  # (Lf,2) site indices (a, b)
    bound_mu: np.ndarray | None = None  # (J+Lf,) when every row is a whole joint (no spherical): bound = mu |alpha|_1
    # the distinct operators of L with the points last, and each joint's (distinct_operators): the compiled
    # loop's Eq. (16) reads the few shapes of L (the walker: 8 for 38 joints) instead of one copy per joint
    L_ops: np.ndarray | None = None  # (U, 6, kmax)
    L_of: np.ndarray | None = None  # (J+Lf,) int: L[j] = L_ops[L_of[j]].T
    # constant index maps of the compiled per-step set-up (bisp.wrench_map, detect, warm start)
    topo: object = None  # recursive.Topology of the model
    planar: np.ndarray | None = None  # FALLBACK joints when all are planar (bisp.body_frames fast path)
    gravity: np.ndarray | None = None  # (3,)
    loop_ja: np.ndarray | None = None  # (L,) Pinocchio joint of site a / b of every loop
    loop_jb: np.ndarray | None = None
    pin_ja: np.ndarray | None = None  # (Lf,) the same for the frictional loops
    pin_jb: np.ndarray | None = None
    pin_moment: np.ndarray | None = None  # (Lf,3) r axis: pin friction moment per unit beta (times 1/h)
    loop_sdiff: np.ndarray | None = None  # (Lf,nv) support(a) - support(b) (loop friction rows)
    sph_support_f: np.ndarray | None = None  # (K,nv) float support of the contact spheres
    n_slots: int = 0  # warm-start cache: 2 K P ground tangents, then the joint and loop rows
    loop_xa: np.ndarray | None = None  # (L,) rows of the loops' sites a / b in Kinematics.X
    loop_xb: np.ndarray | None = None
    T_ptr: np.ndarray | None = None  # coupling matrix T (nv, ndof) in CSR form (identity without couplings)
    T_idx: np.ndarray | None = None
    T_val: np.ndarray | None = None
    sel_r: np.ndarray | None = None  # loop selection matrix Sel as (row, column, value) triplets
    sel_c: np.ndarray | None = None
    sel_v: np.ndarray | None = None
    rows_nv: np.ndarray | None = None  # (F1, nv) the tree joint rows before J_rR, when a mapped joint
    # (spherical_exp) has friction: the rows are then rows_nv J_rR(q), every step (joint_rows)

    @property
    def joint_slot0(self) -> int:
        return 2 * len(self.sph_jid) * len(self.plane_n)

    @property
    def has_joint_friction(self) -> bool:
        return len(self.fj_names) > 0


def _perp(a):
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = np.cross(a, e)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


def box_section_axes(axis):
    """(u1, u2) of a prismatic joint's box cross-section, in the joint frame: u1 is the joint-frame axis
    following the sliding axis' largest component in the cycle x -> y -> z -> x, made normal to the axis
    (x axis: u1 = y, u2 = z; y: z, x; z: x, y), and u2 = axis x u1."""
    a = np.asarray(axis, float)
    u = np.eye(3)[(int(np.argmax(np.abs(a))) + 1) % 3]
    u1 = u - (u @ a) * a
    u1 /= np.linalg.norm(u1)
    return u1, np.cross(a, u1)


def implicit_points(jtype: str, axis, spec):
    """(points (k,3), normals (k,3), groups) of the implicit contacts of a joint, in its frame.
    ``groups``: list of (row vector in the joint's DOFs (nv,), normal indices bounding it)."""
    r, L, n = spec.radius, spec.length, spec.points
    P, Nn = [], []
    if jtype == "prismatic" and spec.shape == "box":
        a = np.asarray(axis, float)
        u1, u2 = box_section_axes(a)
        w1, w2 = 0.5 * np.asarray(spec.size, float)
        for s in (-0.5 * L, 0.5 * L):
            for c1 in (-1.0, 1.0):
                for c2 in (-1.0, 1.0):
                    p = s * a + c1 * w1 * u1 + c2 * w2 * u2
                    P += [p, p]
                    Nn += [c1 * u1, c2 * u2]  # the two faces meeting at the corner
        return np.array(P), np.array(Nn), [(np.array([1.0]), list(range(len(P))))]
    if jtype in ("revolute", "prismatic"):
        a = np.asarray(axis, float)
        e1, e2 = _perp(a)
        for s in (-0.5 * L, 0.5 * L):
            for i in range(n):
                th = 2 * np.pi * i / n
                u = np.cos(th) * e1 + np.sin(th) * e2
                p = s * a + r * u
                P += [p, p]
                Nn += [u, a if jtype == "revolute" else np.cross(a, u)]
        rows = [(np.array([r if jtype == "revolute" else 1.0]), list(range(len(P))))]
        return np.array(P), np.array(Nn), rows
    if jtype == "spherical":
        rows = []
        for k, u in enumerate(np.vstack([np.eye(3), -np.eye(3)])):
            P.append(r * u)
            Nn.append(u)
            for t in _perp(u):
                rows.append((r * np.cross(u, t), [k]))  # slip t . (w x r u) = r (u x t) . w
        return np.array(P), np.array(Nn), rows
    raise AssertionError(jtype)


def ls_operator(P, Nn, M, eps):
    """L of Eq. (16) without h: alpha = h L f, L = (N M^-1 N^T + eps I)^-1 N M^-1 (N rows: wrench of a unit
    normal force, Pinocchio order (force, moment))."""
    N = np.hstack([Nn, np.cross(P, Nn)])
    Minv_Nt = np.linalg.solve(M, N.T)
    return np.linalg.solve(N @ Minv_Nt + eps * np.eye(len(N)), Minv_Nt.T)


def compile_friction(mech, fspec) -> FrictionModel | None:
    """Constant contact/friction data of a mechanism (called by step.compile.compile_scene); None when
    the scene has neither contacts nor friction (the step then takes the frictionless path)."""
    src = mech.spec.source
    st = fspec.settings
    model, nv = mech.model, mech.nv
    T = mech.T
    # planes
    pn = np.array([p.normal for p in fspec.planes]).reshape(-1, 3)
    pt = np.zeros((len(pn), 2, 3))
    for i, n in enumerate(pn):
        e = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
        t1 = e - (e @ n) * n
        t1 /= np.linalg.norm(t1)
        pt[i] = t1, np.cross(n, t1)
    # contact spheres
    bidx = {b: i for i, b in enumerate(mech.bodies)}
    jid, loc, rad, mu, lab = [], [], [], [], []
    for c in fspec.contacts:
        bi = bidx[c.body]
        j, M = int(mech.body_jid[bi]), mech.body_placement[bi]
        R = rpy_matrix(c.rpy)
        if c.type in ("point", "sphere"):
            cs, r = [c.pos], c.radius
        elif c.type == "capsule":
            ax = R[:, 2] * 0.5 * c.length
            cs, r = [c.pos - ax, c.pos + ax], c.radius
        else:
            h = 0.5 * c.size
            cs = [c.pos + R @ (h * np.array([sx, sy, sz])) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
            r = 0.0
        if j == 0:
            raise SceneError(src, f"contacts '{c.name}'", "contacts on world-fixed bodies are not needed")
        for k, p in enumerate(cs):
            jid.append(j)
            loc.append(M.act(np.asarray(p, float)))
            rad.append(r)
            mu.append(np.nan if c.mu is None else c.mu)
            lab.append(f"contact '{c.name}'" + (f"[{k}]" if len(cs) > 1 else ""))
    sph_support = mech.joint_support[np.array(jid, dtype=int)].reshape(-1, nv)
    # frictional tree joints
    names, jids, Ls, rows, rows_nv, groups = [], [], [], [], [], []
    mapped = False
    jmu = st.joint_mu
    for name, js in fspec.joints.items():
        if (js.mu if jmu is None else jmu) == 0.0:
            continue  # frictionless: no implicit contacts needed
        if name not in mech.joint_index:
            raise SceneError(src, f"joints '{name}'", "friction on a joint that is not in the model")
        ji = mech.joint_index[name]
        jspec = next(j for j in mech.spec.joints if j.name == name)
        jtype = ji.type
        if is_mapped(jspec):
            if jspec.type not in ROTATION_TYPES:
                raise SceneError(src, f"joints '{name}'", f"joint friction is not supported on {jspec.type} joints")
            ji = mech.joint_index[carrier_name(name)]  # the ball on the carrier (its angular velocity)
            jtype, mapped = "spherical", True
        axis = jspec.axes[0] if len(jspec.axes) else None
        P, Nn, rws = implicit_points(jtype, axis, js)
        Minert = model.inertias[ji.jid].matrix()
        S = np.zeros((6, ji.nv))
        if jtype == "revolute":
            S[3:, 0] = axis
        elif jtype == "prismatic":
            S[:3, 0] = axis
        else:
            S[3:] = np.eye(3)
        Pc = np.eye(6) - S @ S.T
        Ls.append(ls_operator(P, Nn, Minert, st.epsilon) @ Pc)
        names.append(name)
        jids.append(ji.jid)
        for vec, grp in rws:
            row = np.zeros(nv)
            row[ji.idx_v:ji.idx_v + ji.nv] = vec
            rows_nv.append(row)
            rows.append(row if T is None else row @ T)
            groups.append((len(names) - 1, grp, js.mu if jmu is None else jmu))
    n_tree = len(names)
    # frictional loops
    lidx, laxis, lrad, lslices, lsites = [], [], [], [], []
    starts = np.cumsum([0] + [len(a) for a in mech.loop_axes])
    for lname, lf in fspec.loops.items():
        if (lf.friction.mu if jmu is None else jmu) == 0.0:
            continue
        if lname not in mech.loop_names:
            raise SceneError(src, f"loops '{lname}'", "unknown loop")
        i = mech.loop_names.index(lname)
        P, Nn, _ = implicit_points("revolute", lf.axis, lf.friction)
        Ls.append(ls_operator(P, Nn, np.eye(6), st.epsilon))
        names.append(lname)
        lidx.append(i)
        laxis.append(lf.axis)
        lrad.append(lf.friction.radius)
        lslices.append(slice(int(starts[i]), int(starts[i + 1])))
        lsites.append(mech.loop_ab[i])
        groups.append((len(names) - 1, list(range(len(P))), lf.friction.mu if jmu is None else jmu))
    if not names and not (len(jid) and len(pn)):
        return None  # nothing frictional or in contact (e.g. joint_mu = 0, no contacts): plain step
    kmax = max((len(L) for L in Ls), default=0)
    Lpad = np.zeros((len(Ls), kmax, 6))
    for i, L in enumerate(Ls):
        Lpad[i, :len(L)] = L
    B = np.zeros((len(groups), len(Ls) * kmax))
    for r, (j, grp, m) in enumerate(groups):
        B[r, j * kmax + np.asarray(grp)] = m
    return FrictionModel(
        settings=st, plane_n=pn, plane_off=np.array([p.offset for p in fspec.planes]),
        plane_mu=np.array([p.mu for p in fspec.planes]), plane_t=pt, plane_names=[p.name for p in fspec.planes],
        sph_jid=np.array(jid, dtype=int), sph_local=np.array(loc).reshape(-1, 3), sph_radius=np.array(rad),
        sph_mu=np.array(mu), sph_support=sph_support, sph_label=lab,
        fj_names=names, fj_jid=np.array(jids, dtype=int), n_tree=n_tree, L=Lpad, **distinct_operators(Lpad),
        rows_fixed=np.array(rows).reshape(-1, mech.ndof), bound_B=B,
        rows_nv=np.array(rows_nv).reshape(-1, nv) if mapped else None,
        loop_index=np.array(lidx, dtype=int), loop_axis=np.array(laxis).reshape(-1, 3), loop_radius=np.array(lrad),
        loop_rowslices=lslices, loop_sites=np.array(lsites, dtype=int).reshape(-1, 2),
        bound_mu=(np.array([mu_ for _, _, mu_ in groups]) if all(j == r and len(grp) == len(Ls[j])
                  for r, (j, grp, _) in enumerate(groups)) else None),
        **_index_maps(mech, len(jid) * len(pn) * 2 + len(rows) + len(lidx), np.array(lsites, dtype=int).reshape(-1, 2),
                      np.array(laxis).reshape(-1, 3), np.array(lrad), sph_support))


def distinct_operators(L) -> dict:
    """{"L_ops": the distinct operators of L (J, kmax, 6) transposed to (U, 6, kmax), "L_of": (J,) the index of
    each joint's}: joints of one shape (radius, length, friction points) share their operator of Eq. (16)
    exactly (bytes equal), so the per-iterate products alpha_j = h L_j W_j read U operators, not J."""
    ops, of, seen = [], np.zeros(len(L), dtype=np.int64), {}
    for j, Lj in enumerate(L):
        key = np.ascontiguousarray(Lj).tobytes()
        if key not in seen:
            seen[key] = len(ops)
            ops.append(np.ascontiguousarray(Lj.T))
        of[j] = seen[key]
    return {"L_ops": np.array(ops).reshape(len(ops), 6, L.shape[1]), "L_of": of}


def _index_maps(mech, n_slots, lsites, laxis, lrad, sph_support):
    """Constant structure of the per-step set-up, computed once per mechanism."""
    topo = rc.build_topology(mech.model)
    ab = np.asarray(mech.loop_ab, dtype=int).reshape(-1, 2)
    sup = mech.site_support.astype(float).reshape(-1, mech.nv)
    return dict(
        topo=topo, planar=planar_fallbacks(topo),
        gravity=np.array(mech.model.gravity.linear, dtype=float),
        loop_ja=np.ascontiguousarray(mech.site_jid[ab[:, 0]], dtype=np.int64),
        loop_jb=np.ascontiguousarray(mech.site_jid[ab[:, 1]], dtype=np.int64),
        pin_ja=np.ascontiguousarray(mech.site_jid[lsites[:, 0]], dtype=np.int64),
        pin_jb=np.ascontiguousarray(mech.site_jid[lsites[:, 1]], dtype=np.int64),
        pin_moment=lrad[:, None] * laxis,
        loop_sdiff=(sup[lsites[:, 0]] - sup[lsites[:, 1]]) if len(lsites) else np.zeros((0, mech.nv)),
        sph_support_f=np.ascontiguousarray(sph_support, dtype=float), n_slots=int(n_slots),
        loop_xa=np.ascontiguousarray(mech.loop_rows_ab[:, 0], dtype=np.int64),
        loop_xb=np.ascontiguousarray(mech.loop_rows_ab[:, 1], dtype=np.int64),
        **_sparse_maps(mech))


@dataclass
class FrictionWork:
    """Per-workspace scratch of the friction stage (step Workspace.friction): the recursive workspace of
    the BISP map and contact detection (bisp.body_frames), the bias accelerations Z, Pinocchio's
    external-force vector (bisp.joint_alphas, the test reference) and the workspace's J_rR of Eq. (9)
    (``live_T``: refreshed in place every step by catalogue joint maps)."""
    tree: object  # recursive.Workspace
    Z: np.ndarray  # (njoints, 6)
    fext: object  # pin.StdVec_Force
    T: np.ndarray | None
    live_T: bool


def make_work(mech, fm: FrictionModel, T) -> FrictionWork:
    """A FrictionWork for one step workspace; ``T``: that workspace's J_rR (or None)."""
    tree = rc.make_workspace(fm.topo)
    if fm.planar is not None:
        write_planar_subspaces(fm.topo, tree)
    fext = pin.StdVec_Force()
    for _ in range(mech.model.njoints):
        fext.append(pin.Force.Zero())
    return FrictionWork(tree, np.zeros((fm.topo.njoints, 6)), fext, T, mech.extras is not None and T is not None)


def planar_fallbacks(topo):
    """Indices of the FALLBACK joints of recursive.py when all of them are Pinocchio planar joints (q = (x, y,
    cos, sin), S constant, bias zero: body_frames then needs no per-joint Pinocchio call), else None."""
    if not topo.fallback or any(jm.shortname() != "JointModelPlanar" for jm in topo.fallback_models):
        return None
    return np.array(topo.fallback, dtype=np.int64)


def write_planar_subspaces(topo, ws):
    """The constant motion subspaces of planar FALLBACK joints, written into a recursive workspace once."""
    for j in topo.fallback:
        i0 = topo.idx_v[j]
        ws.Sl[i0:i0 + 3, :] = np.array([[1.0, 0, 0, 0, 0, 0], [0, 1.0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 1.0]])
        ws.c_local[j] = 0.0
    ws.has_bias = False


def coupling_csr(fm, work: FrictionWork):
    """The coupling matrix T of Eq. (9) in CSR form (ptr, idx, val): the constant one built with the
    mechanism, or, with catalogue joint maps (a configuration-dependent J_rR refreshed in place every
    step, catalogue_hooks.py), the workspace's current one."""
    if not work.live_T:
        return fm.T_ptr, fm.T_idx, fm.T_val
    return _csr(np.ascontiguousarray(work.T, dtype=float))


@njit(cache=True, nogil=True)
def _csr(T):
    rows, cols = T.shape
    ptr = np.zeros(rows + 1, dtype=np.int64)
    idx = np.empty(rows * cols, dtype=np.int64)
    val = np.empty(rows * cols)
    k = 0
    for i in range(rows):
        for c in range(cols):
            if T[i, c] != 0.0:
                idx[k], val[k] = c, T[i, c]
                k += 1
        ptr[i + 1] = k
    return ptr, idx[:k], val[:k]


def _sparse_maps(mech):
    """The coupling matrix T (Eq. 9; identity when absent) in CSR form and the loop selection matrix
    (phi = Sel (x_a - x_b)) as (row, column, value) triplets, for the compiled BISP map."""
    T = np.eye(mech.nv) if mech.T is None else np.asarray(mech.T, dtype=float)
    ptr, idx, val = [0], [], []
    for row in T:
        nz = np.flatnonzero(row)
        idx += nz.tolist()
        val += row[nz].tolist()
        ptr.append(len(idx))
    nl = len(mech.loop_ab)
    Sel = np.asarray(mech.loop_select, dtype=float).reshape(-1, 3 * nl) if nl else np.zeros((0, 0))
    r, c = np.nonzero(Sel)
    return dict(T_ptr=np.array(ptr, dtype=np.int64), T_idx=np.array(idx, dtype=np.int64), T_val=np.array(val, dtype=float),
                sel_r=r.astype(np.int64), sel_c=c.astype(np.int64), sel_v=Sel[r, c].astype(float))


@dataclass
class ContactSet:
    sphere: np.ndarray  # (c,) contact sphere of each contact
    plane: np.ndarray  # (c,) plane of each contact
    X: np.ndarray  # (c,3) contact points, world
    n: np.ndarray  # (c,3) normals
    t: np.ndarray  # (c,2,3) tangents
    gap: np.ndarray  # (c,) signed gap [m] (negative = penetration)
    mu: np.ndarray  # (c,)
    jid: np.ndarray  # (c,)
    N: np.ndarray  # (c,n) normal rows (hyper-reduced)
    T: np.ndarray  # (2c,n) tangent rows, contact-major
    lo: np.ndarray  # (c,) N qdot >= lo

    @property
    def keys(self) -> list:
        """(sphere, plane) per contact."""
        return list(zip(self.sphere.tolist(), self.plane.tolist()))


@njit(cache=True, nogil=True)
def _detect_kernel(R, p, St, sph_jid, sph_local, sph_radius, sph_support, sph_mu, plane_n, plane_off, plane_t,
                   plane_mu, margin, erp, h, T):
    """:func:`detect_into` on arrays of its own (the reference pipeline's call)."""
    buf, ibuf, off = empty_arena()
    return detect_into(R, p, St, sph_jid, sph_local, sph_radius, sph_support, sph_mu, plane_n, plane_off, plane_t,
                       plane_mu, margin, erp, h, T, buf, ibuf, off)


@njit(cache=True, nogil=True)
def rows_arena_size(K, P, nv, ndof, nlim, F1, Lf):
    """(floats, ints) that :func:`rows_kernel_into` takes from its arena for K spheres, P planes, nv velocity
    DOFs, ndof hyper-reduced DOFs, nlim unilateral limit rows, F1 joint and Lf loop-pin friction rows, with
    every sphere/plane pair in contact (an upper bound: every take counted)."""
    cnt = K * P
    nu = cnt + nlim
    nx = nu + 2 * cnt + F1 + Lf
    floats = 3 * K + K * P + 15 * cnt + 3 * cnt * nv + 3 * cnt * ndof + nx * ndof + nu
    return floats, 3 * cnt


@njit(cache=True, nogil=True)
def detect_into(R, p, St, sph_jid, sph_local, sph_radius, sph_support, sph_mu, plane_n, plane_off, plane_t,
                plane_mu, margin, erp, h, T, buf, ibuf, off):
    """Sphere/plane pairs with gap d = n . c - offset - r < margin (sphere-major, as np.nonzero) and their
    rows: N = n^T J_x, T_k = t_k^T J_x with J_x = J_lin + J_ang x x on the supporting DOFs (Eq. 1.90-1.91,
    J_mr written through the world motion subspaces St), times the coupling matrix T (Eq. 9) if given;
    lo = -d/h (d >= 0, speculative) or -erp d/h (d < 0, stabilisation). Every array is taken from the arena
    (``buf``, ``ibuf``, ``off``: arena.py; not reset here)."""
    K, P, nv = len(sph_jid), len(plane_off), St.shape[0]
    C = take(buf, off, K, 3)
    gap = take(buf, off, K, P)
    cnt = 0
    for k in range(K):
        j = sph_jid[k]
        for a in range(3):
            C[k, a] = p[j, a] + R[j, a, 0] * sph_local[k, 0] + R[j, a, 1] * sph_local[k, 1] \
                + R[j, a, 2] * sph_local[k, 2]
        for q in range(P):
            gap[k, q] = (C[k, 0] * plane_n[q, 0] + C[k, 1] * plane_n[q, 1] + C[k, 2] * plane_n[q, 2]
                         - plane_off[q] - sph_radius[k])
            if gap[k, q] < margin:
                cnt += 1
    ks, ps = take1(ibuf, off, 1, cnt), take1(ibuf, off, 1, cnt)
    X, n, t = take(buf, off, cnt, 3), take(buf, off, cnt, 3), take3(buf, off, cnt, 2, 3)
    d, lo, mu, jid = take1(buf, off, 0, cnt), take1(buf, off, 0, cnt), take1(buf, off, 0, cnt), \
        take1(ibuf, off, 1, cnt)
    Nv, Tv = take(buf, off, cnt, nv), take(buf, off, 2 * cnt, nv)
    Nv[:, :] = 0.0
    Tv[:, :] = 0.0
    i = 0
    for k in range(K):
        for q in range(P):
            if not gap[k, q] < margin:
                continue
            ks[i], ps[i], jid[i] = k, q, sph_jid[k]
            r = sph_radius[k]
            for a in range(3):
                n[i, a] = plane_n[q, a]
                X[i, a] = C[k, a] - r * plane_n[q, a]
                t[i, 0, a] = plane_t[q, 0, a]
                t[i, 1, a] = plane_t[q, 1, a]
            dd = gap[k, q]
            d[i] = dd
            lo[i] = -dd / h if dd >= 0 else -erp * dd / h
            mu[i] = plane_mu[q] if np.isnan(sph_mu[k]) else sph_mu[k]
            x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
            for c in range(nv):
                if sph_support[k, c] == 0.0:
                    continue
                w0, w1, w2 = St[c, 3], St[c, 4], St[c, 5]
                j0 = St[c, 0] + w1 * x2 - w2 * x1
                j1 = St[c, 1] + w2 * x0 - w0 * x2
                j2 = St[c, 2] + w0 * x1 - w1 * x0
                Nv[i, c] = n[i, 0] * j0 + n[i, 1] * j1 + n[i, 2] * j2
                Tv[2 * i, c] = t[i, 0, 0] * j0 + t[i, 0, 1] * j1 + t[i, 0, 2] * j2
                Tv[2 * i + 1, c] = t[i, 1, 0] * j0 + t[i, 1, 1] * j1 + t[i, 1, 2] * j2
            i += 1
    if T.shape[0]:
        NT, TT = take(buf, off, cnt, T.shape[1]), take(buf, off, 2 * cnt, T.shape[1])
        np.dot(Nv, T, NT)  # as Nv @ T
        np.dot(Tv, T, TT)
        Nv, Tv = NT, TT
    return ks, ps, X, n, t, d, mu, jid, Nv, Tv, lo


def detect(mech, fm: FrictionModel, work: FrictionWork, h) -> ContactSet:
    """Sphere/plane pairs closer than the margin, with their rows (compiled, _detect_kernel), from the
    kinematics bisp.body_frames left in ``work.tree`` (world joint placements and motion subspaces)."""
    ws = work.tree
    if len(fm.sph_jid) == 0 or len(fm.plane_n) == 0:
        return None
    st = fm.settings
    out = _detect_kernel(ws.R, ws.p, ws.St, fm.sph_jid, fm.sph_local, fm.sph_radius, fm.sph_support_f, fm.sph_mu,
                         fm.plane_n, fm.plane_off, fm.plane_t, fm.plane_mu, st.margin, st.erp, h,
                         _EMPTY if work.T is None else work.T)
    if len(out[0]) == 0:
        return None
    ks, ps, X, n, t, d, mu, jid, N, Tr, lo = out
    return ContactSet(ks, ps, X, n, t, d, mu, jid, N, Tr, lo)


_EMPTY = np.zeros((0, 0))


@njit(cache=True, nogil=True)
def rows_kernel(R, p, St, sph_jid, sph_local, sph_radius, sph_support, sph_mu, plane_n, plane_off, plane_t, plane_mu,
                 margin, erp, h, T, T_ptr, T_idx, T_val, ndof, rows_fixed, pin_moment, loop_sdiff, CU, lo_CU):
    """:func:`rows_kernel_into` on arrays of its own (the reference pipeline's call)."""
    buf, ibuf, off = empty_arena()
    return rows_kernel_into(R, p, St, sph_jid, sph_local, sph_radius, sph_support, sph_mu, plane_n, plane_off,
                            plane_t, plane_mu, margin, erp, h, T, T_ptr, T_idx, T_val, ndof, rows_fixed, pin_moment,
                            loop_sdiff, CU, lo_CU, buf, ibuf, off)


@njit(cache=True, nogil=True)
def _put_negated(dst, r0, src):
    """dst[r0:r0 + len(src)] = -src (row by row, no temporary)."""
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            dst[r0 + i, j] = -src[i, j]


@njit(cache=True, nogil=True)
def rows_kernel_into(R, p, St, sph_jid, sph_local, sph_radius, sph_support, sph_mu, plane_n, plane_off, plane_t,
                     plane_mu, margin, erp, h, T, T_ptr, T_idx, T_val, ndof, rows_fixed, pin_moment, loop_sdiff, CU,
                     lo_CU, buf, ibuf, off):
    """detect_into plus the stacked rows of the staggered solve, RX = [N; CU; -T_ground; -T_joints;
    -T_loops] (unilateral rows first: ground normals, then the limit rows CU), with the loop-pin rows
    r axis^T (J_w,a - J_w,b) mapped through the coupling matrix (CSR). Every array is taken from the arena
    (``buf``, ``ibuf``, ``off``: arena.py, rows_arena_size; not reset here)."""
    ks, ps, X, n, t, d, mu, jid, N, Tv, lo = detect_into(R, p, St, sph_jid, sph_local, sph_radius, sph_support,
                                                         sph_mu, plane_n, plane_off, plane_t, plane_mu, margin, erp,
                                                         h, T, buf, ibuf, off)
    nc, nlim, F1, Lf, nv = len(ks), CU.shape[0], rows_fixed.shape[0], pin_moment.shape[0], St.shape[0]
    nu = nc + nlim
    RX = take(buf, off, nu + 2 * nc + F1 + Lf, ndof)
    RX[:, :] = 0.0
    RX[:nc] = N
    RX[nc:nu] = CU
    _put_negated(RX, nu, Tv)
    _put_negated(RX, nu + 2 * nc, rows_fixed)
    r0 = nu + 2 * nc + F1
    for q in range(Lf):
        for c in range(nv):
            sd = loop_sdiff[q, c]
            if sd == 0.0:
                continue
            w = sd * (pin_moment[q, 0] * St[c, 3] + pin_moment[q, 1] * St[c, 4] + pin_moment[q, 2] * St[c, 5])
            for e in range(T_ptr[c], T_ptr[c + 1]):
                RX[r0 + q, T_idx[e]] -= w * T_val[e]
    lo_U = take1(buf, off, 0, nu)
    lo_U[:nc] = lo
    lo_U[nc:] = lo_CU
    return ks, ps, X, n, t, d, mu, jid, N, Tv, lo, RX, lo_U, nu


def staggered_rows(mech, fm: FrictionModel, work: FrictionWork, h, cons):
    """Contacts and rows of one staggered step in one compiled call: (ContactSet or None, RX (nx, ndof),
    lo_U, nu) with RX = [U; -T], U = [ground normals; limit rows +-C] (N qdot >= lo_U), T = [ground
    tangents; joint rows; loop-pin rows] (same rows as detect, loop_friction_rows and the joint rows)."""
    if cons.C is not None:
        fin_lo, fin_hi = np.isfinite(cons.lo), np.isfinite(cons.hi)
        CU = np.ascontiguousarray(np.vstack([cons.C[fin_lo], -cons.C[fin_hi]]))
        lo_CU = np.concatenate([cons.lo[fin_lo], -cons.hi[fin_hi]])
    else:
        CU, lo_CU = _NO_ROWS[mech.ndof], _NO_VALUES
    st = fm.settings
    contacts = len(fm.plane_n) > 0
    ws = work.tree
    out = rows_kernel(ws.R, ws.p, ws.St, fm.sph_jid if contacts else _NO_SPHERES, fm.sph_local, fm.sph_radius,
                       fm.sph_support_f, fm.sph_mu, fm.plane_n, fm.plane_off, fm.plane_t, fm.plane_mu, st.margin, st.erp,
                       h, _EMPTY if work.T is None else work.T, *coupling_csr(fm, work), mech.ndof,
                       joint_rows(fm, work), fm.pin_moment, fm.loop_sdiff, CU, lo_CU)
    ks, ps, X, n, t, d, mu, jid, N, Tv, lo, RX, lo_U, nu = out
    cs = ContactSet(ks, ps, X, n, t, d, mu, jid, N, Tv, lo) if len(ks) else None
    return cs, RX, lo_U, nu


class _EmptyRows(dict):
    def __missing__(self, ndof):
        self[ndof] = np.zeros((0, ndof))
        return self[ndof]


_NO_ROWS = _EmptyRows()
_NO_VALUES = np.zeros(0)
_NO_SPHERES = np.zeros(0, dtype=np.int64)


def joint_rows(fm: FrictionModel, work: FrictionWork) -> np.ndarray:
    """(F1, ndof) friction rows of the frictional tree joints: the constant ones, or with a frictional mapped
    joint (spherical_exp) its carrier rows through the workspace's current J_rR (Eq. 9-10), rows_nv J_rR(q)."""
    if fm.rows_nv is None or work.T is None:
        return fm.rows_fixed
    return fm.rows_nv @ work.T


def loop_friction_rows(mech, fm: FrictionModel, work: FrictionWork):
    """(Lf, ndof) friction rows of the loop pins: r axis^T (J_w,a - J_w,b) (relative spin about the pin),
    from the motion subspaces bisp.body_frames left in ``work.tree`` (St = data.J^T)."""
    if not len(fm.loop_index):
        return np.zeros((0, mech.ndof))
    rows = (fm.pin_moment @ work.tree.St[:, 3:].T) * fm.loop_sdiff
    return rows if work.T is None else rows @ work.T
