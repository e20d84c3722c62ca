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

from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.jit import njit


@dataclass
class Constraints:
    G: np.ndarray  # (m,n) bilateral rows
    g: np.ndarray  # (m,)
    label_spans: list  # (label, number of rows) in row order; labels are built only for error messages
    joint_rows: dict = field(default_factory=dict)  # prescribed joint -> slice of rows
    site_rows: dict = field(default_factory=dict)  # prescribed site -> slice of rows
    loop_rows: slice = field(default_factory=lambda: slice(0, 0))
    C: np.ndarray | None = None  # (p,n) unilateral rows
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    C_labels: list = field(default_factory=list)

    @property
    def m(self) -> int:
        return len(self.g)

    @property
    def labels(self) -> list:
        """One label per bilateral row (for error messages)."""
        return [lab for lab, n in self.label_spans for _ in range(n)]


def loop_rows(mech, X, J):
    """(G_r, phi): loop-closure rows in reduced coordinates and their position residual [m].
    X, J: Kinematics.X/J (rows in mech.loop_rows_ab); phi = S (x_a - x_b) with S = mech.loop_select."""
    if not len(mech.loop_ab):
        return np.zeros((0, mech.nv)), np.zeros(0)
    A, B = mech.loop_rows_ab[:, 0], mech.loop_rows_ab[:, 1]
    S = mech.loop_select
    return S @ (J[A] - J[B]).reshape(-1, J.shape[2]), S @ (X[A] - X[B]).reshape(-1)


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
    change only when the set of prescriptions does; cached per set in Mechanism.layout_cache)."""
    m: int  # rows (without the catalogue's linear joint constraints)
    spans: list  # (label, rows) in row order
    loop_rows: slice
    joint_block: slice  # prescribed joints, contiguous, in command order
    G_joints: np.ndarray  # their constant rows of J_rR (Eq. 7), stacked
    joint_rows: dict  # joint -> slice
    site_block: slice  # prescribed sites
    site_rows: dict  # site -> slice
    site_k: tuple  # rows per prescribed site (3, or the number of its axes)
    site_J_rows: np.ndarray | None = None  # rows of Kinematics.J (flattened (3K,nv)) of the sites, set on first use


def row_layout(mech, prescribed_joints, prescribed_sites, axes) -> RowLayout:
    """The RowLayout for prescribed joints and sites (names, in order); ``axes`` {site: (k,3)}."""
    key = (tuple(prescribed_joints), tuple(prescribed_sites),
           tuple(3 if axes.get(n) is None else len(axes[n]) for n in prescribed_sites) if axes else None)
    lay = mech.layout_cache.get(key)
    if lay is not None:
        return lay
    site_counts = [(n, 3 if axes.get(n) is None else len(axes[n])) for n in prescribed_sites]
    spans, joint_rows, site_rows = [], {}, {}
    nl = sum(len(ax) for ax in mech.loop_axes) if len(mech.loop_ab) else 0
    spans += [(f"loop '{name}'", len(ax)) for name, ax in zip(mech.loop_names, mech.loop_axes)] if nl else []
    r = nl
    Gj = [np.zeros((0, mech.ndof))]
    for name in prescribed_joints:
        G = mech.joint_rows(name)  # constant rows of J_rR (already projected)
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
    mech.layout_cache[key] = lay
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


def build(mech, kin, q, prescribed_joints: dict, prescribed_sites: dict, h: float, site_axes=None) -> Constraints:
    """All constraint rows of this step, in hyper-reduced coordinates. ``site_axes``: {site: (k,3)}
    world directions along which a prescribed site's velocity is imposed (default all three)."""
    T = mech.T
    axes = site_axes or {}
    lay = row_layout(mech, prescribed_joints, prescribed_sites, axes)
    G = np.empty((lay.m, mech.ndof))
    g = np.empty(lay.m)
    if lay.loop_rows.stop:
        G_loop = _loop_G(kin.J, mech.loop_rows_ab, mech.loop_select)
        G[lay.loop_rows] = G_loop if T is None else G_loop @ T
        g[lay.loop_rows] = 0.0
    if prescribed_joints:
        G[lay.joint_block] = lay.G_joints
        g[lay.joint_block] = _stack(prescribed_joints.values())
    if prescribed_sites:
        if axes:
            Js = kin.J[[kin.row[mech.site_index[n]] for n in prescribed_sites]]  # (s,3,nv)
            for k, (name, vel) in enumerate(prescribed_sites.items()):
                P = axes.get(name)
                sl = lay.site_rows[name]
                rows = Js[k] if P is None else P @ Js[k]
                G[sl] = rows if T is None else rows @ T
                g[sl] = vel if P is None else P @ vel
        else:  # all three directions: the sites' rows of J (their order in kin is fixed per site set)
            if lay.site_J_rows is None:
                rows = np.array([kin.row[mech.site_index[n]] for n in prescribed_sites])
                lay.site_J_rows = (3 * rows[:, None] + np.arange(3)).reshape(-1)
            Js = kin.J.reshape(-1, mech.nv)[lay.site_J_rows]
            if T is None:
                G[lay.site_block] = Js
            else:
                np.matmul(Js, T, out=G[lay.site_block])
            g[lay.site_block] = _stack(prescribed_sites.values())
    spans = lay.spans
    if mech.extras is not None and mech.extras.has_rows:  # linear joint constraints, G_r (catalogue.py)
        G_l, g_l, sp = mech.extras.rows(mech)
        G, g, spans = np.vstack([G, G_l]), np.concatenate([g, g_l]), spans + sp
    out = Constraints(G=G, g=g, label_spans=spans, joint_rows=lay.joint_rows, site_rows=lay.site_rows,
                      loop_rows=lay.loop_rows)
    if len(mech.limited):
        out.C = mech.limit_rows
        lower, upper = _limit_bounds(mech)
        ql = q[mech.limited_q]
        out.lo = (lower - ql) / h
        out.hi = (upper - ql) / h
        out.C_labels = mech.limit_labels
    return out


def _limit_bounds(mech):
    """(lower, upper) of the limited DOFs [rad, m] (constant; cached)."""
    b = mech.layout_cache.get("limit bounds")
    if b is None:
        b = mech.layout_cache["limit bounds"] = (mech.lower[mech.limited], mech.upper[mech.limited])
    return b


_EMPTY = np.zeros(0)
