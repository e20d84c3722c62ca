"""Stage 3 of the compiled step, ``rows(m, d, q, h, gj, sv)``: the bilateral rows G qdot_R = g and the limit
bounds of Eq. (5), hyper-reduced, in the layout of dynamics/constraints.build:

* loop closures: S (J_a - J_b) J_rR, g = 0 (post-stabilization) or -b phi(q_k) (Baumgarte);
* prescribed joints (Eq. 7): the constant rows of J_rR held in d.G_joints, g = the prescribed velocities ``gj``;
* prescribed sites (Eq. 7): P J_site J_rR with the site's axes P (identity: x, y, z), g = P ``sv[k]``;
* limits: (lower - q) / h <= C qdot_R <= (upper - q) / h on the limited DOFs."""
from __future__ import annotations

from redmax_ros.core.jit import njit, njit_inline
from redmax_ros.core.step.compiled.kinematics import point_jacobian


@njit_inline
def project_rows(T_col, T_ratio, Gr, out):
    """out = Gr J_rR with T's one entry per row (T_col, T_ratio), or Gr without couplings (T_col empty)."""
    if T_col.shape[0] == 0:
        out[:, :] = Gr
        return
    out[:, :] = 0.0
    for r in range(Gr.shape[0]):
        for i in range(Gr.shape[1]):
            out[r, T_col[i]] += Gr[r, i] * T_ratio[i]


@njit_inline
def loop_phi(loop_a, loop_b, loop_select, row_loop, X, dx, phi):
    """phi = S (x_a - x_b) [m] of the loop closures at the site positions X (into phi; dx scratch (3L,));
    returns max|phi|. Row r of S is nonzero in the three columns of its loop row_loop[r] only, so its sum runs
    over those (the same nonzero terms in the same order as over every column)."""
    for l in range(loop_a.shape[0]):
        a, b = loop_a[l], loop_b[l]
        for r in range(3):
            dx[3 * l + r] = X[a, r] - X[b, r]
    err = 0.0
    for r in range(phi.shape[0]):
        c0 = 3 * row_loop[r]
        s = 0.0
        for c in range(c0, c0 + 3):
            s += loop_select[r, c] * dx[c]
        phi[r] = s
        err = max(err, abs(s))
    return err


@njit_inline
def rows(m, d, q, h, gj, sv):
    """Fill d.G, d.g (and d.lo, d.hi) at the kinematics in d."""
    nl = m.loop_select.shape[0]
    L = m.loop_a.shape[0]
    if L:
        for l in range(L):
            point_jacobian(m.parents, m.idx_v, m.nv_j, m.site_jid, d.St, d.X, m.loop_a[l], d.Jpt[2 * l])
            point_jacobian(m.parents, m.idx_v, m.nv_j, m.site_jid, d.St, d.X, m.loop_b[l], d.Jpt[2 * l + 1])
        nv = d.Gr_loop.shape[1]
        d.Gr_loop[:, :] = 0.0
        for r in range(nl):
            l = m.loop_row_loop[r]  # the row's loop: S is zero outside its three columns
            for c in range(3):
                s = m.loop_select[r, 3 * l + c]
                if s != 0.0:
                    for i in range(nv):
                        d.Gr_loop[r, i] += s * (d.Jpt[2 * l, c, i] - d.Jpt[2 * l + 1, c, i])
        project_rows(m.T_col, m.T_ratio, d.Gr_loop, d.G[:nl])
        if m.scalars[0] != 0.0:  # Baumgarte: G qdot = -b phi(q_k)
            loop_phi(m.loop_a, m.loop_b, m.loop_select, m.loop_row_loop, d.X, d.dx, d.phi)
            for r in range(nl):
                d.g[r] = -m.scalars[0] * d.phi[r]
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
        point_jacobian(m.parents, m.idx_v, m.nv_j, m.site_jid, d.St, d.X, d.site_ids[k], J)
        kk = d.site_k[k]
        P = d.site_P[k]
        Gs = d.site_rows[:kk]
        for r in range(kk):
            for i in range(J.shape[1]):
                Gs[r, i] = P[r, 0] * J[0, i] + P[r, 1] * J[1, i] + P[r, 2] * J[2, i]
        project_rows(m.T_col, m.T_ratio, Gs, d.G[r0:r0 + kk])
        for r in range(kk):
            d.g[r0 + r] = P[r, 0] * sv[k, 0] + P[r, 1] * sv[k, 1] + P[r, 2] * sv[k, 2]
        r0 += kk
    for r in range(m.limited_q.shape[0]):
        ql = q[m.limited_q[r]]
        d.lo[r] = (m.limit_lower[r] - ql) / h
        d.hi[r] = (m.limit_upper[r] - ql) / h
