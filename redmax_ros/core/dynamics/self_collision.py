"""Self-collision stage: distance queries of this step's configuration -> unilateral rows of the QP of
Eq. (5) (paper §6, HAGFISH: "The collisions are turned into inequality constraints, resulting in a
quadratic program (Eq. (5))"; docs/collisions.md).

    pin.updateGeometryPlacements                     # object placements from the kinematics stage's pin.Data
    pre-filter: |c_a - c_b| < r_a + r_b + margin     # bounding spheres (half-spaces: n . c - offset < r + margin)
    pin.computeDistance(pair)  (coal GJK/EPA)         # signed distance d, witness points p_a, p_b, normal n (a -> b)
    row  n^T (J_b(p_b) - J_a(p_a)) qdot+ >= -(d - offset) / h      for every pair with d < margin

The row is the relative normal velocity of the two witness points (maximal rows through the point
Jacobians J_p = J_lin - [p]x J_ang of Eq. S2.4, notes §2.4, on the WORLD joint Jacobians the kinematics
stage computed), projected to hyper-reduced coordinates by J_rR (Eq. 9, ``ws.T``). To first order it is
d(t_k+1) = d + h n^T (v_b - v_a) >= offset: the position correction of the issue, with no Baumgarte gain.
No friction ("hagfish are slimy"). SI units: m, s.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.kinematics import point_jacobians

HI = 1e6  # m/s: upper bound of a contact row, the divergence limit of step/state.py (ProxSuite reports 1e20 or inf
# bounds on these rows as PROXQP_DUAL_INFEASIBLE: its equilibration scales them with the rows)


@dataclass
class ContactReport:
    """What the collision stage found this step (Diagnostics.solution.contacts)."""
    candidates: int  # pairs past the bounding-sphere pre-filter (narrow-phase queries)
    rows: int  # pairs nearer than the margin: unilateral rows added to Eq. (5)
    labels: list  # "a/b" per row
    distance: np.ndarray  # (rows,) signed distance d [m] (negative: penetration)
    point_a: np.ndarray  # (rows, 3) witness points, world frame [m]
    point_b: np.ndarray  # (rows, 3)
    normal: np.ndarray  # (rows, 3) unit normal from a to b
    t_detect: float  # s: placements, pre-filter and distance queries
    t_rows: float = 0.0  # s: point Jacobians and rows
    t_solve: float = 0.0  # s: the velocity solve (QP when a row or a limit is active), set by the pipeline
    active: int = 0  # rows with a non-zero impulse after the solve (set by the pipeline)
    impulse: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (rows,) contact impulses [N s]
    relaxed: bool = False  # the QP was infeasible with the position correction and was solved without it

    @property
    def min_distance(self) -> float:
        """Smallest signed distance of the rows [m] (inf without rows)."""
        return float(self.distance.min()) if len(self.distance) else float("inf")


def geometry_data(mech, ws) -> pin.GeometryData:
    """The workspace's pin.GeometryData of the collision model (created on first use, cached in ws)."""
    gd = ws.cache.get("collision data")
    if gd is None:
        gd = ws.cache["collision data"] = pin.GeometryData(mech.collision.geom)
        _plane_table(mech, ws)
    return gd


def _plane_table(mech, ws):
    """(O,4) [n, offset] of the half-space objects (NaN rows for the others), cached in ws."""
    key = "collision planes"
    tab = ws.cache.get(key)
    if tab is None:
        cm = mech.collision
        tab = np.full((len(cm.owner), 4), np.nan)
        for i, obj in enumerate(cm.geom.geometryObjects):
            g = obj.geometry
            if type(g).__name__ == "Halfspace":
                tab[i, :3], tab[i, 3] = np.asarray(g.n), float(g.d)
        ws.cache[key] = tab
    return tab


def object_frames(gd) -> tuple:
    """(centres (O,3), local z axes (O,3)) of every collision object in the world, read once per step from
    pin.GeometryData.oMg (one pass: indexing oMg per pair copied an SE3 each time, ~3 ms a step of the
    HAGFISH's 5 ms detection late in the knot)."""
    R = np.array([M.homogeneous for M in gd.oMg]).reshape(-1, 4, 4)
    return np.ascontiguousarray(R[:, :3, 3]), np.ascontiguousarray(R[:, :3, 2])


def candidates(mech, ws, gd, frames=None) -> np.ndarray:
    """Indices of the candidate pairs whose bounding spheres (half-spaces: the sphere against the plane)
    are nearer than the margin. ``frames``: object_frames(gd), if already read."""
    cm = mech.collision
    if not cm.n_pairs:
        return np.zeros(0, dtype=int)
    c = (frames or object_frames(gd))[0]
    planes = _plane_table(mech, ws)
    a, b = cm.pair_a, cm.pair_b
    gap = np.linalg.norm(c[a] - c[b], axis=1) - cm.pair_bound
    for side, other in ((a, b), (b, a)):  # half-space pairs: signed distance of the other's centre
        pl = np.isfinite(planes[side, 3])
        if pl.any():
            o = other[pl]
            gap[pl] = np.einsum("ij,ij->i", c[o], planes[side[pl], :3]) - planes[side[pl], 3] - cm.radius[o] - cm.margin
    return np.flatnonzero(gap < 0.0)


def detect(mech, ws) -> tuple:
    """Distances of this step's candidate pairs (needs forward kinematics in ws.data). Returns
    (pair indices with d < margin, d, p_a, p_b, n, candidates)."""
    cm = mech.collision
    gd = geometry_data(mech, ws)
    pin.updateGeometryPlacements(mech.model, ws.data, cm.geom, gd)
    frames = object_frames(gd)
    cand = candidates(mech, ws, gd, frames)
    keep, d, pa, pb, nn = [], [], [], [], []
    distance, geom, results, margin = pin.computeDistance, cm.geom, gd.distanceResults, cm.margin
    for k in cand.tolist():
        distance(geom, gd, k)
        r = results[k]
        dist = r.min_distance
        if dist < margin:
            keep.append(k)
            d.append(dist)
            pa.append(r.getNearestPoint1())
            pb.append(r.getNearestPoint2())
            nn.append(r.normal)
    if keep:
        _capsule_end_points(mech, ws, frames, keep, d, pa, pb, nn)
    m = len(keep)
    return (np.array(keep, dtype=int), np.array(d, float), np.array(pa, float).reshape(m, 3),
            np.array(pb, float).reshape(m, 3), np.array(nn, float).reshape(m, 3), len(cand))


def _capsule_table(mech, ws):
    """(O,2) [radius, half length] of the capsule objects (NaN rows for the others), cached in ws."""
    tab = ws.cache.get("collision capsules")
    if tab is None:
        tab = np.full((len(mech.collision.owner), 2), np.nan)
        for i, obj in enumerate(mech.collision.geom.geometryObjects):
            g = obj.geometry
            if type(g).__name__ == "Capsule":
                tab[i] = g.radius, g.halfLength
        ws.cache["collision capsules"] = tab
    return tab


def _capsule_end_points(mech, ws, frames, keep, d, pa, pb, nn):
    """A pair gives one witness pair, so a capsule lying along a plane or along another capsule (a line
    contact) could roll its far end through within a step. For every kept pair with a capsule, each end
    centre of its segment adds a point pair (end sphere against the other object: a plane, or the closest
    point of the other capsule's segment) when nearer than the margin and not at the coal witness
    (appended to the lists in place; vectorised over the kept pairs)."""
    cm = mech.collision
    caps, planes = _capsule_table(mech, ws), _plane_table(mech, ws)
    kk = np.asarray(keep, dtype=int)
    wa, wb = np.asarray(pa, float), np.asarray(pb, float)
    for me_all, ot_all, flip in ((cm.pair_a[kk], cm.pair_b[kk], False), (cm.pair_b[kk], cm.pair_a[kk], True)):
        sel = np.flatnonzero(np.isfinite(caps[me_all, 0]) & (np.isfinite(planes[ot_all, 3]) | np.isfinite(caps[ot_all, 0])))
        if not len(sel):
            continue
        me, ot = me_all[sel], ot_all[sel]
        r, half = caps[me, 0], caps[me, 1]
        centres, axes = frames
        Mc, ax = centres[me], axes[me]
        is_plane = np.isfinite(planes[ot, 3])
        Oc, Oax = centres[ot], axes[ot]
        ro = np.where(is_plane, 0.0, np.nan_to_num(caps[ot, 0]))
        ho = np.nan_to_num(caps[ot, 1])
        witness = (wb if flip else wa)[sel]
        for sgn in (-1.0, 1.0):
            e = Mc + (sgn * half)[:, None] * ax
            # against a capsule segment: closest point s, normal from me to other
            tt = np.clip(np.einsum("ij,ij->i", e - Oc, Oax), -ho, ho)
            sp = Oc + tt[:, None] * Oax
            gap = sp - e
            ln = np.linalg.norm(gap, axis=1)
            n_me = gap / np.maximum(ln, 1e-300)[:, None]
            dist = ln - r - ro
            if is_plane.any():  # against a half-space: normal into the solid
                npl, off = planes[ot, :3], planes[ot, 3]
                dpl = np.einsum("ij,ij->i", e, np.nan_to_num(npl)) - np.nan_to_num(off) - r
                n_me = np.where(is_plane[:, None], -np.nan_to_num(npl), n_me)
                dist = np.where(is_plane, dpl, dist)
                ln = np.where(is_plane, 1.0, ln)
            p_me = e + r[:, None] * n_me
            p_ot = np.where(is_plane[:, None], p_me - dist[:, None] * n_me, sp - ro[:, None] * n_me)
            ok = (dist < cm.margin) & (ln > 1e-12) & (np.linalg.norm(p_me - witness, axis=1) >= 0.5 * r)
            for q in np.flatnonzero(ok):
                keep.append(int(kk[sel[q]]))
                d.append(float(dist[q]))
                if flip:  # me is object b: normal from a (other) to b (me)
                    pa.append(p_ot[q]), pb.append(p_me[q]), nn.append(-n_me[q])
                else:
                    pa.append(p_me[q]), pb.append(p_ot[q]), nn.append(n_me[q])


def contact_rows(mech, ws, pairs, pa, pb, n) -> np.ndarray:
    """(rows, nv) n^T (J_b(p_b) - J_a(p_a)) in reduced coordinates, from the WORLD joint Jacobians in
    ws.data (Eq. S2.4)."""
    cm = mech.collision
    nv = mech.nv
    m = len(pairs)
    if not m:
        return np.zeros((0, nv))
    J6 = ws.data.J.reshape(6, nv)
    X = np.vstack([pa, pb])
    jids = np.concatenate([cm.jid[cm.pair_a[pairs]], cm.jid[cm.pair_b[pairs]]])
    support = np.ascontiguousarray(mech.joint_support[jids])
    Jp = point_jacobians(J6, X, support)  # (2m, 3, nv)
    return np.einsum("ij,ijk->ik", n, Jp[m:] - Jp[:m])


def append_rows(mech, ws, cons, h: float, v=None) -> ContactReport:
    """Stage 3': the contact rows of this step appended to the unilateral rows of ``cons`` (after the joint
    limits), lo = -(d - offset)/h, hi = +inf. With ``collision.restitution`` e > 0 and ``v`` (the
    hyper-reduced velocity at t_k), a pair that would pass the offset within this step, d + h v_n < offset
    with v_n = C v < 0, gets lo = max(-(d - offset)/h, -e v_n) (Newton's restitution law on the normal
    velocity). Needs the kinematics stage (pin.Data at q_k). Returns the ContactReport (the pipeline
    completes its solve fields)."""
    t0 = time.perf_counter()
    pairs, d, pa, pb, n, n_cand = detect(mech, ws)
    t1 = time.perf_counter()
    cm = mech.collision
    labels = [f"contact {cm.pair_labels[k]}" for k in pairs]
    if len(pairs):
        C = contact_rows(mech, ws, pairs, pa, pb, n)
        if ws.T is not None:
            C = C @ ws.T
        lo = -(d - cm.offset) / h
        if cm.restitution > 0.0 and v is not None:
            vn = C @ v
            hit = (d + h * vn < cm.offset) & (vn < 0.0)
            lo[hit] = np.maximum(lo[hit], -cm.restitution * vn[hit])
        hi = np.full(len(pairs), HI)
        if cons.C is None:
            cons.C, cons.lo, cons.hi, cons.C_labels = C, lo, hi, labels
        else:
            cons.C = np.vstack([cons.C, C])
            cons.lo = np.concatenate([cons.lo, lo])
            cons.hi = np.concatenate([cons.hi, hi])
            cons.C_labels = list(cons.C_labels) + labels
    return ContactReport(n_cand, len(pairs), labels, d, pa, pb, n, t1 - t0, time.perf_counter() - t1)


def relax_rows(cons, rep: ContactReport) -> bool:
    """When the QP of Eq. (5) fails with contact rows (a body squeezed between obstacles, joint limits and
    other bodies can make the position correction infeasible), drop the correction of the penetrating
    pairs: lo = min(lo, 0) on the contact rows (no further approach, no push-out). True if anything
    changed (the pipeline then solves once more; rep.relaxed counts it)."""
    if not rep.rows:
        return False
    lo = cons.lo[-rep.rows:]
    if not (lo > 0.0).any():
        return False
    cons.lo = np.concatenate([cons.lo[:-rep.rows], np.minimum(lo, 0.0)])
    rep.relaxed = True
    return True


def finish_report(rep: ContactReport, mu: np.ndarray, t_solve: float) -> ContactReport:
    """Fill in the solve's share: the contact multipliers are the last ``rep.rows`` entries of mu (sign:
    A qdot = b - G^T lam - C^T mu, so a pushing contact has mu < 0 at its lower bound)."""
    rep.t_solve = t_solve
    if rep.rows and len(mu) >= rep.rows:
        rep.impulse = -np.asarray(mu[-rep.rows:], float)
        rep.active = int(np.count_nonzero(np.abs(rep.impulse) > 1e-12))
    return rep
