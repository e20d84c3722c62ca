"""Constraint stage: the bilateral rows G qdot = g and unilateral rows lo <= C qdot <= hi of Eq. (5),
in hyper-reduced coordinates.

Bilateral rows:
  * loop closures: site a and site b coincide along the listed world directions,
    G = P (J_a - J_b) (maximal constraint G_m J_mr of Eq. 5/6), g = 0; position drift is removed by
    post-stabilization (see stabilization.py), so no Baumgarte term is added here;
  * prescribed joint velocities (hybrid dynamics, Eq. 7): *G_r = selected rows of J_rR, g = *qdot_r;
  * prescribed site (point) velocities (Eq. 7): *G_m J_mr with *G_m a point Jacobian, g = *qdot_m.
Unilateral rows: joint limits lower <= q + h qdot <= upper on each limited DOF.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from redmax_ros.core.jit import njit
from redmax_ros.core.solvers.problem import Constraints


@njit
def _loop_G(J, ab, S):
    """Loop rows S (J_a - J_b) (rows, nv) of loop_rows without the residual, in one compiled call."""
    L, nv = ab.shape[0], J.shape[2]
    D = np.empty((3 * L, nv))
    for l in range(L):
        a, b = ab[l, 0], ab[l, 1]
        for r in range(3):
            for c in range(nv):
                D[3 * l + r, c] = J[a, r, c] - J[b, r, c]
    return S @ D


@dataclass
class RowLayout:
    """Where each bilateral row of a step goes, for one set of prescribed joints and sites (the rows
    change only when the set of prescriptions does; cached per set in the step workspace)."""
    m: int  # rows (without the catalogue's linear joint constraints)
    spans: list  # (label, rows) in row order
    loop_rows: slice
    joint_block: slice  # prescribed joints, contiguous, in command order
    G_joints: np.ndarray  # their constant rows of J_rR (Eq. 7), stacked
    joint_rows: dict  # joint -> slice
    site_block: slice  # prescribed sites
    site_rows: dict  # site -> slice
    site_k: tuple  # rows per prescribed site (3, or the number of its axes)


def prescribed_joint_rows(mech, ws, name: str, hyper: bool = True) -> np.ndarray:
    """Rows *G_r of a prescribed joint (identity on its DOFs, Eq. 7), projected by J_rR unless ``hyper``
    is False (cached in ws)."""
    key = ("joint rows", name, hyper)
    G = ws.cache.get(key)
    if G is None:
        j = mech.joint_index[name]
        G = np.zeros((j.nv, mech.nv))
        G[:, j.idx_v:j.idx_v + j.nv] = np.eye(j.nv)
        G = ws.cache[key] = G if ws.T is None or not hyper else G @ ws.T
    return G


def held_dofs(mech, ws, prescribed_joints) -> list:
    """Hyper-reduced DOFs moved by the prescribed joints (kept fixed by loop stabilization; cached in ws
    per set of joints)."""
    key = ("held", *prescribed_joints)
    hit = ws.cache.get(key)
    if hit is None:
        held = set()
        for name in prescribed_joints:
            j = mech.joint_index[name]
            for d in range(j.idx_v, j.idx_v + j.nv):
                if ws.T is None:
                    held.add(d)
                else:
                    held.update(np.flatnonzero(ws.T[d]).tolist())
        hit = ws.cache[key] = sorted(held)
    return hit


def row_layout(mech, ws, prescribed_joints, prescribed_sites, axes, hyper: bool = True) -> RowLayout:
    """The RowLayout for prescribed joints and sites (names, in order); ``axes`` {site: (k,3)}."""
    key = (tuple(prescribed_joints), tuple(prescribed_sites),
           tuple(3 if axes.get(n) is None else len(axes[n]) for n in prescribed_sites) if axes else None, hyper)
    lay = ws.cache.get(key)
    if lay is not None:
        return lay
    site_counts = [(n, 3 if axes.get(n) is None else len(axes[n])) for n in prescribed_sites]
    spans, joint_rows, site_rows = [], {}, {}
    nl = sum(len(ax) for ax in mech.loop_axes) if len(mech.loop_ab) else 0
    spans += [(f"loop '{name}'", len(ax)) for name, ax in zip(mech.loop_names, mech.loop_axes)] if nl else []
    r = nl
    Gj = [np.zeros((0, mech.ndof if hyper else mech.nv))]
    for name in prescribed_joints:
        G = prescribed_joint_rows(mech, ws, name, hyper)  # constant rows of J_rR (already projected)
        Gj.append(G)
        spans.append((f"prescribed joint '{name}'", len(G)))
        joint_rows[name] = slice(r, r + len(G))
        r += len(G)
    r_sites = r
    for name, k in site_counts:
        spans.append((f"prescribed site '{name}'", k))
        site_rows[name] = slice(r, r + k)
        r += k
    lay = RowLayout(r, spans, slice(0, nl), slice(nl, r_sites), np.vstack(Gj), joint_rows,
                    slice(r_sites, r), site_rows, tuple(k for _, k in site_counts))
    ws.cache[key] = lay
    return lay


def _stack(vals):
    """Concatenate the velocity vectors of a dict's values (scalars allowed)."""
    vals = list(vals)
    if len(vals) == 1:
        return vals[0]
    try:
        return np.concatenate(vals)
    except ValueError:  # scalars among them
        return np.concatenate([np.atleast_1d(np.asarray(x, float)) for x in vals])


def build(mech, ws, G_loop, J_sites, q, prescribed_joints: dict, prescribed_sites: dict, h: float, site_axes=None,
          hyper: bool = True) -> Constraints:
    """All constraint rows of this step. The kinematics come from the backend: ``G_loop`` (rows, nv) the
    loop rows S (J_a - J_b) in reduced coordinates (or None without loops), ``J_sites`` (s, 3, nv) the
    point Jacobians of the prescribed sites in their order (or None). ``site_axes``: {site: (k,3)} world
    directions along which a prescribed site's velocity is imposed (default all three). ``hyper``: rows
    in hyper-reduced coordinates (projected by the workspace's J_rR, ws.T), else in reduced ones (the PCG
    path, which imposes the couplings as rows)."""
    T = ws.T if hyper else None
    axes = site_axes or {}
    lay = row_layout(mech, ws, prescribed_joints, prescribed_sites, axes, hyper)
    G = np.empty((lay.m, mech.nv if T is None else T.shape[1]))
    g = np.empty(lay.m)
    if lay.loop_rows.stop:
        G[lay.loop_rows] = G_loop if T is None else G_loop @ T
        if mech.loop_baumgarte:  # Baumgarte: phi_dot = G qdot = -b phi(q_k), phi decays as (1 - b h)^k
            g[lay.loop_rows] = -mech.loop_baumgarte * ws.tree.loop_phi_at(q)[0]
        else:  # post-stabilization: the velocity-level rows, q+ projected after the step
            g[lay.loop_rows] = 0.0
    if prescribed_joints:
        G[lay.joint_block] = lay.G_joints
        g[lay.joint_block] = _stack(prescribed_joints.values())
    if prescribed_sites:
        if axes:
            for k, (name, vel) in enumerate(prescribed_sites.items()):
                P = axes.get(name)
                sl = lay.site_rows[name]
                rows = J_sites[k] if P is None else P @ J_sites[k]
                G[sl] = rows if T is None else rows @ T
                g[sl] = vel if P is None else P @ vel
        else:  # all three directions
            Js = J_sites.reshape(-1, mech.nv)
            if T is None:
                G[lay.site_block] = Js
            else:
                np.matmul(Js, T, out=G[lay.site_block])
            g[lay.site_block] = _stack(prescribed_sites.values())
    spans = lay.spans
    if ws.extras is not None and ws.extras.has_rows:  # linear joint constraints, G_r (catalogue_hooks.py)
        G_l, g_l, sp = ws.extras.rows(ws)
        G, g, spans = np.vstack([G, G_l]), np.concatenate([g, g_l]), spans + sp
    out = Constraints(G=G, g=g, label_spans=spans, joint_rows=lay.joint_rows, site_rows=lay.site_rows,
                      loop_rows=lay.loop_rows,
                      site_axes={n: axes[n] for n in prescribed_sites if axes.get(n) is not None} if axes else {})
    if len(mech.limited):
        out.C = mech.limit_rows
        ql = q[mech.limited_q]
        out.lo = (mech.limit_lower - ql) / h
        out.hi = (mech.limit_upper - ql) / h
        out.C_labels = mech.limit_labels
    return out


def loop_rows_of(mech, J) -> np.ndarray:
    """Loop rows S (J_a - J_b) (rows, nv) in reduced coordinates from Kinematics.J (rows of the loop sites
    in mech.loop_rows_ab), in one compiled call."""
    return _loop_G(J, mech.loop_rows_ab, mech.loop_select)


_EMPTY = np.zeros(0)
