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
    X, J: Kinematics.X/J (rows in mech.loop_rows_ab)."""
    if not len(mech.loop_ab):
        return np.zeros((0, mech.nv)), np.zeros(0)
    Gs, phis = [], []
    for (a, b), P in zip(mech.loop_rows_ab, mech.loop_axes):
        Gs.append(P @ (J[a] - J[b]))
        phis.append(P @ (X[a] - X[b]))
    return np.vstack(Gs), np.concatenate(phis)


def build(mech, kin, q, prescribed_joints: dict, prescribed_sites: dict, h: float, site_axes=None) -> Constraints:
    """All constraint rows of this step, in hyper-reduced coordinates. ``site_axes``: {site: (k,3)}
    world directions along which a prescribed site's velocity is imposed (default all three)."""
    T = mech.T
    rows, rhs, spans = [], [], []
    r = 0
    out = Constraints(G=None, g=None, label_spans=spans)
    if len(mech.loop_ab):
        G_loop, _ = loop_rows(mech, kin.X, kin.J)
        spans += [(f"loop '{name}'", len(ax)) for name, ax in zip(mech.loop_names, mech.loop_axes)]
        rows.append(G_loop if T is None else G_loop @ T)
        rhs.append(np.zeros(len(G_loop)))
        r = len(G_loop)
        out.loop_rows = slice(0, r)
    for name, vel in prescribed_joints.items():
        Gj = mech.joint_rows(name)  # constant rows of J_rR (already projected)
        rows.append(Gj)
        rhs.append(vel)
        spans.append((f"prescribed joint '{name}'", len(Gj)))
        out.joint_rows[name] = slice(r, r + len(Gj))
        r += len(Gj)
    if prescribed_sites and not site_axes:
        Js = kin.J[[kin.row[mech.site_index[n]] for n in prescribed_sites]].reshape(-1, mech.nv)
        rows.append(Js if T is None else Js @ T)
        for name, vel in prescribed_sites.items():
            rhs.append(vel)
            spans.append((f"prescribed site '{name}'", 3))
            out.site_rows[name] = slice(r, r + 3)
            r += 3
    elif prescribed_sites:
        for name, vel in prescribed_sites.items():
            Js = kin.J[kin.row[mech.site_index[name]]]
            P = site_axes.get(name)
            if P is not None:
                Js, vel = P @ Js, P @ vel
            rows.append(Js if T is None else Js @ T)
            rhs.append(vel)
            spans.append((f"prescribed site '{name}'", len(Js)))
            out.site_rows[name] = slice(r, r + len(Js))
            r += len(Js)
    if mech.extras is not None and mech.extras.has_rows:  # linear joint constraints, G_r (catalogue.py)
        G_l, g_l, sp = mech.extras.rows(mech)
        rows.append(G_l)
        rhs.append(g_l)
        spans += sp
        r += len(G_l)
    if r:
        out.G = np.vstack(rows) if len(rows) > 1 else rows[0]
        out.g = np.concatenate(rhs) if len(rhs) > 1 else np.asarray(rhs[0], float)
    else:
        out.G, out.g = mech.no_rows, _EMPTY
    if len(mech.limited):
        out.C = mech.limit_rows
        ql = q[mech.limited_q]
        out.lo = (mech.lower[mech.limited] - ql) / h
        out.hi = (mech.upper[mech.limited] - ql) / h
        out.C_labels = mech.limit_labels
    return out


_EMPTY = np.zeros(0)
