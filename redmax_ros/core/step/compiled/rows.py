"""Stage 3 of the compiled step, ``rows(m, d, q, h, gj, sv)``: the bilateral rows G qdot_R = g and the limit
bounds of Eq. (5), hyper-reduced, in the layout of dynamics/constraints.build:

* loop closures: S (J_a - J_b) J_rR, g = 0 (post-stabilization) or -b phi(q_k) (Baumgarte);
* prescribed joints (Eq. 7): the constant rows of J_rR held in d.G_joints, g = the prescribed velocities ``gj``;
* prescribed sites (Eq. 7): P J_site J_rR with the site's axes P (identity: x, y, z), g = P ``sv[k]``;
* limits: (lower - q) / h <= C qdot_R <= (upper - q) / h on the limited DOFs."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import njit, njit_inline
from redmax_ros.core.step.compiled.kinematics import point_jacobian


@njit_inline
def _project_rows(m, Gr, out):
    """out = Gr J_rR (or Gr without couplings), with T's one entry per row (T_col, T_ratio)."""
    if m.T.shape[0] == 0:
        out[:, :] = Gr
        return
    out[:, :] = 0.0
    for r in range(Gr.shape[0]):
        for i in range(Gr.shape[1]):
            out[r, m.T_col[i]] += Gr[r, i] * m.T_ratio[i]


@njit_inline
def loop_phi(m, d):
    """(phi, max|phi|) [m] of the loop closures at the site positions in d: phi = S (x_a - x_b)."""
    L = m.loop_a.shape[0]
    dx = np.empty(3 * L)
    for l in range(L):
        a, b = m.loop_a[l], m.loop_b[l]
        for r in range(3):
            dx[3 * l + r] = d.X[a, r] - d.X[b, r]
    phi = m.loop_select @ dx
    err = 0.0
    for r in range(phi.shape[0]):
        err = max(err, abs(phi[r]))
    return phi, err


@njit_inline
def rows(m, d, q, h, gj, sv):
    """Fill d.G, d.g (and d.lo, d.hi) at the kinematics in d."""
    nl = m.loop_select.shape[0]
    L = m.loop_a.shape[0]
    if L:
        for l in range(L):
            point_jacobian(m, d, m.loop_a[l], d.Jpt[2 * l])
            point_jacobian(m, d, m.loop_b[l], d.Jpt[2 * l + 1])
        nv = d.Gr_loop.shape[1]
        d.Gr_loop[:, :] = 0.0
        for r in range(nl):
            for l in range(L):
                for c in range(3):
                    s = m.loop_select[r, 3 * l + c]
                    if s != 0.0:
                        for i in range(nv):
                            d.Gr_loop[r, i] += s * (d.Jpt[2 * l, c, i] - d.Jpt[2 * l + 1, c, i])
        _project_rows(m, d.Gr_loop, d.G[:nl])
        if m.scalars[0] != 0.0:  # Baumgarte: G qdot = -b phi(q_k)
            phi, _ = loop_phi(m, d)
            for r in range(nl):
                d.g[r] = -m.scalars[0] * phi[r]
        else:
            for r in range(nl):
                d.g[r] = 0.0
    mj = d.G_joints.shape[0]
    for r in range(mj):
        d.G[nl + r, :] = d.G_joints[r]
        d.g[nl + r] = gj[r]
    r0 = nl + mj
    for k in range(d.site_ids.shape[0]):
        J = d.Jpt[k]
        point_jacobian(m, d, d.site_ids[k], J)
        kk = d.site_k[k]
        P = d.site_P[k]
        Gs = d.site_rows[:kk]
        for r in range(kk):
            for i in range(J.shape[1]):
                Gs[r, i] = P[r, 0] * J[0, i] + P[r, 1] * J[1, i] + P[r, 2] * J[2, i]
        _project_rows(m, Gs, d.G[r0:r0 + kk])
        for r in range(kk):
            d.g[r0 + r] = P[r, 0] * sv[k, 0] + P[r, 1] * sv[k, 1] + P[r, 2] * sv[k, 2]
        r0 += kk
    for r in range(m.limited_q.shape[0]):
        ql = q[m.limited_q[r]]
        d.lo[r] = (m.limit_lower[r] - ql) / h
        d.hi[r] = (m.limit_upper[r] - ql) / h
