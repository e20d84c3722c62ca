"""The step with deformables (issue 15; Wang et al. 2019 §4, the equation after Eq. 5): the Pinocchio
pipeline's skeleton stages (kinematics.compute, forces.assemble, constraints.build, as
pipeline.pinocchio_velocity) with the deformable DOFs joined to the velocity solve.

    A_r, b_r, G_r, C_r            = skeleton stages 1-3 (Eq. 2, Eq. 5-7)
    A_d, b_d                      = Deformables.fill (M_d + h D_d + h^2 K_d, M_d v_d + h f_d; filled when the
                                    step before ended in this DeformState, else here)
    [J_p, -S_i] z = 0             = attachments (deformable/attach.py): attached vertices eliminated
                                    (deformable/reduction.py); prescribed joint rows held as DOFs
    z_floor >= (floor - z_i) / h  = floor contact per free vertex near the floor, Coulomb friction floor_mu
    z = (qdot_R+, v_d+)           = solvers.coupled.solve (sparse LDL^T, staggered contact loop, Alg. 2)
    q+ = q (+) h qdot_r+          = pipeline.update_configuration (manifold, loops)
    x+ = x + h v_d+, then attached vertices projected onto their points at q+ (post-stabilization)

With ``stabilization: {method: baumgarte, b}`` (mech.loop_baumgarte = b [1/s], 0 for post) the attachment rows
read [J_p, -S_i] z = -b phi(q_k, x_k) (attach.residual: phi = P - x_i for body points, x_i - P for world
points) and no projection follows: the residual at q+, x+ is the reported violation.

The deformable state (deformable.system.DeformState) is State.deform; a state without it starts from the
mesh's rest positions at rest. A failed step raises StepError and leaves the state as it
was (State is immutable).
"""
from __future__ import annotations

import math
import time

import numpy as np
import pinocchio as pin

from redmax_ros.core.deformable import attach, reduction
from redmax_ros.core.deformable.unreduce import unreduce
from redmax_ros.core.deformable.fem import TetFEM
from redmax_ros.core.deformable.string import String
from redmax_ros.core.deformable.system import Attachments, Deformables, DeformState
from redmax_ros.core.dynamics import momentum as system_momentum
from redmax_ros.core.dynamics.energy import energies
from redmax_ros.core.dynamics.kinematics import point_jacobians, point_jacobians_into
from redmax_ros.core.errors import SceneError, StepError
from redmax_ros.core.jit import njit
from redmax_ros.core.solvers import coupled
from redmax_ros.core.solvers.direct import Solution
from redmax_ros.core.step import trajectory
from redmax_ros.core.step.pipeline import VelocitySolve, required_forces, skeleton_stages, update_configuration
from redmax_ros.core.step.state import Diagnostics, StepResult, applied_torques, check_rows, check_speed
from redmax_ros.core.step.workspace import Workspace

LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
FLOOR_MARGIN = 0.01  # [m] vertices this close to the floor (or closer than their step's travel) get a row
cpu_time = time.thread_time  # the clock of the ``timing`` split [s]: CPU time, so the split adds up under load


def inside_shape(shape: dict, p_local: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Which body-frame points (k,3) lie inside a body's marker shape (box, sphere, cylinder, capsule)."""
    t = shape.get("type")
    if t == "box":
        return np.all(np.abs(p_local) <= 0.5 * np.asarray(shape["size"], float) + tol, axis=1)
    if t == "sphere":
        return np.linalg.norm(p_local, axis=1) <= float(shape["radius"]) + tol
    if t in ("cylinder", "capsule"):
        r, L = float(shape["radius"]), float(shape["length"])
        rad = np.linalg.norm(p_local[:, :2], axis=1)
        if t == "cylinder":
            return (rad <= r + tol) & (np.abs(p_local[:, 2]) <= 0.5 * L + tol)
        zc = np.clip(p_local[:, 2], -0.5 * L, 0.5 * L)
        return np.linalg.norm(p_local - np.stack([np.zeros_like(zc), np.zeros_like(zc), zc], 1), axis=1) <= r + tol
    raise ValueError(f"shape type {t!r} has no inside test (box, sphere, cylinder, capsule)")


def build(mech) -> Deformables | None:
    """The scene's deformables (SceneSpec.deformables) as a Deformables, attachments resolved at q0: a
    listed vertex or one inside the body's shape is held at the body point it occupies at q0."""
    specs = getattr(mech.spec, "deformables", None)
    if not specs:
        return None
    src = mech.spec.source
    data = mech.model.createData()
    pin.forwardKinematics(mech.model, data, mech.q0)
    names, elements, offsets = [], [], [0]
    av, ab, al, labels = [], [], [], []
    floors = []
    bodies = {n: i for i, n in enumerate(mech.bodies)}
    shapes = {b.name: b.shape for b in mech.spec.bodies}
    for d in specs:
        entry = f"deformables.{d.name}"
        try:
            e = (String(d.vertices, d.mass, d.stiffness, d.alpha, d.beta) if d.kind == "string" else
                 TetFEM(d.vertices, d.tets, d.young, d.poisson, d.density, d.alpha, d.beta))
        except ValueError as err:
            raise SceneError(src, entry, str(err)) from None
        off = offsets[-1]
        seen = set()
        for a in d.attachments:
            if a.body == "world":
                bi, jid = -1, 0
            elif a.body in bodies:
                bi = bodies[a.body]
                jid = int(mech.body_jid[bi])
            else:
                raise SceneError(src, f"{entry}.attachments", f"unknown body '{a.body}'")
            M = data.oMi[jid]
            if a.inside:
                shape = shapes.get(a.body)
                if not shape:
                    raise SceneError(src, f"{entry}.attachments", f"body '{a.body}' has no shape to find vertices inside")
                Mb = M * mech.body_placement[bi]
                loc = (e.x0 - Mb.translation) @ Mb.rotation
                try:
                    verts = np.nonzero(inside_shape(shape, loc))[0]
                except ValueError as err:
                    raise SceneError(src, f"{entry}.attachments", str(err)) from None
                if not len(verts):
                    raise SceneError(src, f"{entry}.attachments", f"no vertex lies inside body '{a.body}'")
            else:
                verts = np.asarray(a.vertices, dtype=np.int64) % e.n
            for v in verts:
                if int(v) in seen:
                    raise SceneError(src, f"{entry}.attachments", f"vertex {int(v)} is attached twice")
                seen.add(int(v))
                x = e.x0[v]
                av.append(off + int(v))
                ab.append(jid if bi >= 0 else -1)
                al.append(x if bi < 0 else M.rotation.T @ (x - M.translation))
                labels.append(f"{d.name}/vertex {int(v)} -> {a.body}")
        if d.floor is not None:
            floors.append((d.floor, np.arange(off, off + e.n), d.floor_mu))
        names.append(d.name)
        elements.append(e)
        offsets.append(off + e.n)
    att = Attachments(np.asarray(av, dtype=np.int64), np.asarray(ab, dtype=np.int64),
                      np.asarray(al, dtype=float).reshape(-1, 3), labels)
    fl = fv = None
    if floors:  # attached vertices move with their body: a floor row on them could conflict with the attachment
        fl = floors[0][0]
        fv = np.setdiff1d(np.concatenate([f[1] for f in floors]), np.asarray(av, dtype=np.int64))
    return Deformables(names, elements, np.asarray(offsets), att, np.asarray(mech.spec.gravity, float), fl, fv,
                       floors[0][2] if floors else 0.0)


def deform_state(dm: Deformables, state) -> DeformState:
    """The deformable part of a State (State.deform), or the rest state of the scene's deformables."""
    d = state.deform
    return d if isinstance(d, DeformState) else dm.initial()


def attachment_points(mech, data, dm: Deformables, support=None):
    """(world points P (a,3) [m], their Jacobians E (3a, nv) stacked per attached vertex (rows 3k..3k+2; zero
    for world points), or None without ``support`` (attachment_support)) at data's kinematics (forward
    kinematics; the WORLD joint Jacobians of computeJointJacobians for the Jacobians): E_k = J_lin - [P_k]_x J_ang
    on the DOFs supporting the body (kinematics.point_jacobians, Sueda's notes Eq. S2.4). The joint placements
    are read in one pass over data.oMi.tolist() (indexing one element costs ~2.5 us, the pass ~0.8 us per joint) and the
    points formed in one compiled loop (attach.world_points)."""
    att = dm.attach
    P = attach.world_points(np.array([M.homogeneous for M in data.oMi.tolist()]), att.body, att.local)
    if support is None:
        return P, None
    return P, point_jacobians(data.J.reshape(6, mech.nv), P, support).reshape(3 * len(P), mech.nv)


def attachment_points_at(mech, ws, dm, q, support=None):
    """attachment_points at configuration q from the workspace's compiled forward kinematics
    (tree_kinematics.Context.site_positions_at: one compiled call, the same placements as Pinocchio's to
    round-off, ~1e-16 m) instead of reading data.oMi through the bindings (~4 us per joint, two passes a step);
    world points are their stored positions. With ``support``, the Jacobians from data.J (computeJointJacobians
    at q, which the skeleton stages leave in ws.data), written into a buffer zeroed once and kept in ws.cache
    (only the supported entries change; valid until the next call)."""
    att = dm.attach
    jid, local, world = _attach_frames(ws, dm)
    P = ws.tree.site_positions_at(q, jid, local)
    if len(world):
        P[world] = att.local[world]
    if support is None:
        return P, None
    return P, attachment_jacobians(mech, ws, P, support)


def attachment_jacobians(mech, ws, P, support):
    """E (3a, nv) of attachment_points_at for the points P (a,3) at the configuration of ws.data.J, in a buffer
    zeroed once and kept in ws.cache (only the supported entries change; valid until the next call)."""
    J = ws.cache.get("deformable_attach_jacobians")
    if J is None or J.shape != (len(P), 3, mech.nv):
        J = ws.cache["deformable_attach_jacobians"] = np.zeros((len(P), 3, mech.nv))
    point_jacobians_into(np.ascontiguousarray(ws.data.J.reshape(6, mech.nv)), P, support, J)
    return J.reshape(3 * len(P), mech.nv)


_POINTS = "deformable attachment points"  # ws.cache: (q's bytes, the attachment points at q)


def _points_at(mech, ws, dm, q):
    """attachment_points_at(q)'s points, kept in ws.cache for the last q they were computed at (compared bit
    for bit): the post-projection's points at q+ are the next step's at q_k, the same numbers without a second
    forward kinematics. Read-only by convention (the step only reads them)."""
    key = q.tobytes()
    hit = ws.cache.get(_POINTS)
    if hit is not None and hit[0] == key:
        return hit[1]
    P = attachment_points_at(mech, ws, dm, q)[0]
    ws.cache[_POINTS] = (key, P)
    return P


def _attach_frames(ws, dm):
    """(joint ids (world points: 0), offsets, indices of the world points) of the attachments, kept in ws.cache."""
    hit = ws.cache.get("deformable_attach_frames")
    if hit is None:
        att = dm.attach
        hit = ws.cache["deformable_attach_frames"] = (
            np.ascontiguousarray(np.maximum(att.body, 0), dtype=np.int64),
            np.ascontiguousarray(att.local, dtype=float), np.flatnonzero(att.body < 0))
    return hit


def attachment_support(mech, dm):
    """(a, nv) bool: the DOFs that move each attached vertex's body (none for world points)."""
    sup = np.zeros((len(dm.attach.vertex), mech.nv), dtype=bool)
    model = mech.model
    for k, jid in enumerate(dm.attach.body):
        for j in (model.supports[int(jid)] if jid > 0 else ()):
            if j > 0:
                jm = model.joints[j]
                sup[k, jm.idx_v:jm.idx_v + jm.nv] = True
    return sup


def coupled_velocity(mech, ws, dm, state, ds, cmd, tau, h, timing=None):
    """Stages 1-4 with the deformables: (VelocitySolve of the skeleton, vertex velocities (N,3)). The attached
    vertices are eliminated (deformable/reduction.py), the reduced system solved with the skeleton's rows and
    the floor contacts (solvers/coupled.py)."""
    t0 = cpu_time()
    sk = skeleton_stages(mech, ws, state, cmd, tau, h)  # 1-3, as the Pinocchio pipeline
    system, cons = sk.system, sk.cons
    if cons.m:
        check_rows(cons)
    t1 = cpu_time()
    n_r, N = len(system.b), dm.n_vertices
    red, cws, buf = _reduction(mech, ws, dm, n_r)
    filled = ws.cache.get(_PREFILLED)
    if filled is None or filled[0] is not ds or filled[1] != h:  # the last step filled it when it ended in ds
        dm.fill(ds.x, ds.v, h, buf["ad"], buf["bd"])  # 2 of the deformables: A_d, b_d in A_d's fixed pattern
    t2 = cpu_time()
    E, t = _attached_velocity_map(mech, ws, dm, ds, n_r, state.q)
    reduction.fill(red, buf["ad"], buf["bd"], E, t, system.A, system.b, buf["data"], buf["b"], buf["work"])
    t_red = cpu_time()
    contacts = _floor_contacts(dm, ds, red, h)
    C = cons.C if cons.C is not None and len(cons.lo) else None
    G = np.asarray(cons.G).reshape(cons.m, n_r)
    # prescribed joint velocities c qdot_j = g (unit rows of Eq. 7) are held DOFs, not Schur rows
    rows, dofs, coef, rest, G_rest, labels = _held_rows(ws, dm, G, C, cons.labels, red.n_free)
    if len(rows):  # reduction.hold, its arguments already int64 and float
        saved, b_saved = reduction.hold_kernel(red.indptr, red.indices, cws.diag, cws.tpos, buf["data"], buf["b"],
                                               dofs, cons.g[rows] / coef)
    sol = coupled.solve(cws, buf["data"], buf["b"], n_r, G_rest, cons.g[rest],
                        C, cons.lo if C is not None else None, cons.hi if C is not None else None, contacts,
                        _warm_contacts(ws, ds), labels, stats=timing)
    ws.cache[_CONTACTS_FOUND] = sol.contact_state  # step() keys them to the DeformState it ends in, on success
    v_r = sol.z[red.n_free:]
    if not len(rows):
        dofs, rows, saved, b_saved, coef = _NO_INTS, _NO_INTS, _NO_FLOATS, _NO_FLOATS, _NO_FLOATS
    # A z + G^T lam = b on a held DOF: lam = (b_j - (A z)_j) / c
    lam, v_d, held_violation = unreduce(sol.z, red.n_free, buf["free_dof"], red.att_dof, E @ v_r, t, cons.m, rest,
                                        sol.lam, red.indptr, red.indices, dofs, saved, b_saved, coef,
                                        cons.g[rows], rows)
    violation = max(sol.violation, held_violation) if len(rows) else sol.violation
    t3 = cpu_time()
    if timing is not None:
        timing["skeleton"] += t1 - t0
        timing["mesh_assembly"] += t2 - t1
        timing["reduction"] += t_red - t2
        timing["coupled_solve"] += t3 - t_red
        timing["contact_iterations"] = sol.iterations
        timing["contact_converged"] = sol.converged
    s = Solution(v_r, lam, sol.mu, sol.iterations, "coupled", None, None, violation, given_residual=sol.residual)
    vs = VelocitySolve(s, cons.joint_rows, cons.site_rows,
                       cons.G[cons.loop_rows] if len(mech.loop_ab) else None, violation, "coupled", sol.iterations)
    return vs, v_d.reshape(-1, 3)


def _held_rows(ws, dm, G, C, labs, n_free):
    """(rows, their reduced DOFs n_free + columns, coefficients) of reduction.unit_rows(G, C), the other rows
    ``rest``, G[rest] and the labels of the coupled solve's rows (G[rest]'s, then the attachments'): kept in
    ws.cache and reused while G, C and the labels are those of the last step (the skeleton's rows of a prescribed
    joint are the same unit rows every step; only their right-hand side changes; compared bit for bit), so the
    same numbers as computing them afresh."""
    hit = ws.cache.get("deformable_held_rows")
    key = (n_free, G.shape, G.dtype.str, G.tobytes(),
           None if C is None else (np.shape(C), np.asarray(C, dtype=float).tobytes()))
    if hit is not None and hit[0] == key and hit[1] == list(labs):  # the same bits (tobytes: ~1 us, array_equal ~5)
        return hit[2]
    rows, cols, coef = reduction.unit_rows(G, C)
    keep = np.ones(len(G), dtype=bool)
    keep[rows] = False
    rest = np.flatnonzero(keep)
    out = (rows, n_free + cols, np.ascontiguousarray(coef, dtype=float), rest, G[rest],
           [labs[i] for i in rest] + dm.attach.labels)
    ws.cache["deformable_held_rows"] = (key, list(labs), out)
    return out


_NO_FLOATS, _NO_INTS, _NO_POINTS = np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3))  # unreduce's, advance's
_CONTACTS = "deformable contacts"  # ws.cache: (the DeformState they were found for, contact states by vertex)
_CONTACTS_FOUND = "deformable contacts found"  # ws.cache: the running step's, until it succeeds


def _warm_contacts(ws, ds):
    """The floor contacts' states (coupled.solve's warm start) of the step that ended in ``ds``, or None: after
    a reset, a set_state or a load a step solves as a fresh run from that state does."""
    hit = ws.cache.get(_CONTACTS)
    return hit[1] if hit is not None and hit[0] is ds else None


_PREFILLED = "deformable system filled"  # ws.cache: (the DeformState whose A_d, b_d are in the buffers, h)


def _prefill(ws, dm, ds: DeformState, h: float) -> float:
    """Fill A_d, b_d for the next step, from ``ds`` with step h, into the step buffers (kept for that step when
    it starts from this very DeformState with the same h: State and DeformState are immutable) and return the
    elastic energy at ds.x [J], which the fill computes on the way: the step's reported energy at x+ then costs
    no second pass over the elements."""
    buf = ws.cache["deformable_reduction"][2]
    ws.cache.pop(_PREFILLED, None)
    elastic = dm.fill(ds.x, ds.v, h, buf["ad"], buf["bd"])
    ws.cache[_PREFILLED] = (ds, h)
    return elastic


def _reduction(mech, ws, dm, n_r):
    """(Reduction of A_d's fixed pattern, the coupled solve's Workspace for it, the step's buffers), built on
    the first step and kept in ws.cache. The reduced pattern couples a free vertex next to attached ones only to
    the skeleton DOFs that move them (their bodies' supports, through J_rR with couplings)."""
    hit = ws.cache.get("deformable_reduction")
    if hit is None or hit[0].n_r != n_r:
        indptr, indices = dm.csr_pattern()
        support = _support(mech, ws, dm)
        if ws.T is not None:
            support = (support.astype(float) @ np.abs(ws.T)) != 0.0
        red = reduction.build(indptr, indices, dm.n_vertices, dm.attach.vertex, n_r, support)
        buf = {"ad": np.empty(len(indices)), "bd": np.empty(3 * dm.n_vertices), "data": np.empty(len(red.indices)),
               "b": np.empty(red.n), "work": np.empty(reduction.work_shape(red)),
               "free_dof": (3 * red.free[:, None] + np.arange(3)).ravel()}
        hit = ws.cache["deformable_reduction"] = (red, coupled.Workspace(red.indptr, red.indices, red.n), buf)
    return hit


def _support(mech, ws, dm):
    """attachment_support, kept in ws.cache."""
    support = ws.cache.get("deformable_support")
    if support is None:
        support = ws.cache["deformable_support"] = attachment_support(mech, dm)
    return support


def _attached_velocity_map(mech, ws, dm, ds, n_r, q):
    """(E (3a, n_r), t (3a,)) with v_a = E qdot_r + t for every attached vertex: E the body point's Jacobian
    (0 for a world point), t = -g (body point) or +g (world point) of the attachment row's right-hand side g
    (0 with post-stabilization, -b phi with Baumgarte; attach.py's rows [J_p, -S_i] and [0, S_i])."""
    att = dm.attach
    a = len(att.vertex)
    if not a:
        return np.zeros((0, n_r)), np.zeros(0)
    P = _points_at(mech, ws, dm, q)  # at q_k (the skeleton stages' kinematics for the Jacobians)
    J = attachment_jacobians(mech, ws, P, _support(mech, ws, dm))
    E = J if ws.T is None else J @ ws.T
    t = np.zeros(3 * a)
    if mech.loop_baumgarte:  # G z = -b phi(q_k, x_k)
        world = att.body < 0
        sgn = np.repeat(np.where(world, 1.0, -1.0), 3)
        t = sgn * (-mech.loop_baumgarte * attach.residual(P, ds.x[att.vertex], world))
    return E, t


def _floor_contacts(dm, ds, red, h):
    """The free vertices near the floor (within FLOOR_MARGIN or their step's travel) as VertexContacts, with
    the speculative bound v_z >= (floor - z)/h; None without a floor."""
    if dm.floor is None:
        return None
    idx = dm.floor_vertices
    near, dof, lo = np.empty(len(idx), np.int64), np.empty(len(idx), np.int64), np.empty(len(idx))
    c = near_floor(ds.x, ds.v, idx, float(dm.floor), FLOOR_MARGIN, h, float(dm.gravity[2]), red.dof, near, dof, lo)
    return coupled.VertexContacts(dof[:c], lo[:c], float(dm.floor_mu), near[:c])


@njit
def near_floor(x, v, idx, floor, margin, h, gz, red_dof, near, dof, lo):
    """The loop of _floor_contacts: the count of vertices of ``idx`` near the floor, written into near (vertex),
    dof (reduced index of its x DOF) and lo (the bound of v_z [m/s])."""
    c = 0
    for i in idx:
        if x[i, 2] - floor < margin + h * abs(v[i, 2]) + h * h * abs(gz):
            near[c] = i
            dof[c] = red_dof[3 * i]
            lo[c] = (floor - x[i, 2]) / h
            c += 1
    return c


def step(mech, ws, dm, state, cmd, h, timing=None, momentum=None):
    """One step with the deformables. Returns (State, StepResult); StepResult.diagnostics energies include
    the deformables' (kinetic, gravitational, elastic in E_spring); ``violation_pos`` is the largest
    attachment (and loop) residual after the projection; the attachment drift the velocity step left before it
    (O(h^2)) is ``timing["attachment_drift"]``. With Baumgarte (mech.loop_baumgarte > 0) nothing is projected
    and both are the residual max |x_i - P| [m] at q+, x+. ``momentum``: the momentum projection of a free
    system (dynamics/momentum.MomentumProjection, conserve_momentum) or None."""
    t0 = time.perf_counter()
    ds = deform_state(dm, state)
    cmd = trajectory.resolve(mech, state, cmd, h, state.q)  # joint trajectories -> this step's prescribed velocities
    if cmd.body_twists:
        raise StepError("body-twist prescriptions are not supported with deformables")
    tau = applied_torques(mech, state, cmd, h)
    if momentum is not None:
        momentum.check_inputs(cmd, tau)
        before = momentum.momentum(state.q, ws.to_reduced(state.v), ds.x, ds.v)
    vs, v_d = coupled_velocity(mech, ws, dm, state, ds, cmd, tau, h, timing)
    check_speed(vs.sol.v)
    check_speed(v_d.ravel())
    q_new, v_hyper, v_new, viol_loop = update_configuration(mech, ws, state.q, vs, cmd, h)
    effort, site_forces = required_forces(mech, tau, vs, cmd, h)
    # x+ = x + h v_d; post-stabilization: attached vertices onto their points at q+ (Baumgarte: no projection,
    # the residual is the violation; projected, the vertices sit on their points: a second evaluation at q+
    # gave P again)
    P = _points_at(mech, ws, dm, q_new) if len(dm.attach.vertex) else _NO_POINTS
    x_new = np.empty_like(ds.x)
    drift, squares = attach.advance(ds.x, v_d, h, dm.attach.vertex, P, not mech.loop_baumgarte, x_new)
    resid = drift if mech.loop_baumgarte else 0.0
    if timing is not None:
        timing["attachment_drift"] = drift  # what the velocity step left before the projection [m]
    if not math.isfinite(squares):
        raise StepError("non-finite deformable positions after the step")
    if momentum is not None:  # conserve_momentum: a rigid twist of the whole system (dynamics/momentum.py)
        v_hyper, v_new, v_d, _ = momentum.project(before, h, q_new, v_hyper, v_new, x_new, v_d)
    ek, ep, es = energies(mech, ws, q_new, v_new)
    ds_new = DeformState(x_new, v_d)  # both fresh float (N,3) arrays of this step: no copy (DeformState.of)
    t1 = cpu_time()
    dk, dg, de = dm.energies(ds_new.x, ds_new.v, _prefill(ws, dm, ds_new, h))  # the next step's A_d, b_d
    if timing is not None:
        timing["mesh_assembly"] += cpu_time() - t1
    ek, ep, es = ek + dk, ep + dg, es + de
    if not math.isfinite(ek + ep + es):
        raise StepError("non-finite energy after the step")
    diag = Diagnostics(ek, ep, es, ek + ep + es, max(viol_loop or 0.0, resid), vs.violation_vel, vs.iterations,
                       vs.solver, time.perf_counter() - t0, vs.sol, None)
    new = state.advanced(h, q_new, v_hyper, None, deform=ds_new)
    ws.cache[_CONTACTS] = (ds_new, ws.cache.pop(_CONTACTS_FOUND))  # a failed step leaves the last warm start
    return new, StepResult(new.t, q_new, v_new, effort, site_forces, diag)


class DeformableBackend:
    """The Pinocchio reference pipeline with the deformables joined to the velocity solve (this module)."""

    name = "reference+deformable"

    def __init__(self, mech, dm: Deformables):
        if (mech.extras is not None or mech.friction is not None or mech.scheme != "euler"
                or getattr(mech, "collision", None) is not None):
            raise SceneError(mech.spec.source, "deformables",
                             "deformables are not supported with catalogue joints/force elements, contact or joint "
                             "friction, self-collision, or integrator.scheme bdf2 (use the deformables' floor rows "
                             "and scheme euler)")
        self.mech, self.deformables = mech, dm
        self.momentum = system_momentum.build(mech, dm)  # conserve_momentum on the free root, or None
        self.workspace = Workspace(mech, pin_data=True)
        self.timing = {"skeleton": 0.0, "mesh_assembly": 0.0, "reduction": 0.0, "coupled_solve": 0.0,
                       "attachment_drift": 0.0}

    def step(self, state, cmd, h, budget=None):
        return step(self.mech, self.workspace, self.deformables, state, cmd, h, self.timing, self.momentum)

    def at_state(self, q, t):
        self.workspace.at_state(q, t)
