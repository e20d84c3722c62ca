"""Stage 1 of the compiled step, ``kinematics(m, d, q, v)``: forward kinematics of every joint kind of the path
(universal and planar joints by their own kernels, the rest in recursive.fk_kernel), world motion subspaces
S (= Pinocchio's data.J), world spatial inertias, body twists J qdot (Sueda's notes Alg. 5), site
positions; and :func:`point_jacobian` (Eq. S2.4). The kernels are those of the data-free pipeline
(solvers/recursive.py, dynamics/tree_kinematics.py), so both paths compute the same numbers."""
from __future__ import annotations

from redmax_ros.core.dynamics.tree_kinematics import universal_kernel
from redmax_ros.core.jit import njit, njit_inline
from redmax_ros.core.solvers.recursive import fk_kernel, jv_kernel, planar_placements, site_pos_kernel, world_inertia_kernel


# A stage gets the Model and Data namedtuples; the helpers it calls more than once get the arrays they use:
# handing a ~100-member namedtuple to an inlined function costs ~3.5 ns per member (reference counting).


@njit_inline
def placements(m, d, q, with_bias, v):
    """Joint transforms, world placements (R, p), motion subspaces St and site positions X at q; with
    ``with_bias`` the universal joints' bias c(q, v) too (needed for Jdot qdot)."""
    placements_of(m.uni_joints, m.uni_a1, m.uni_a2, m.planar_joints, m.parents, m.kind, m.idx_q, m.idx_v, m.nv_j,
                  m.axis, m.pitch, m.place_R, m.place_p, m.site_jid, m.site_local, q, with_bias, v,
                  d.jR, d.jp, d.Sl, d.c_local, d.R, d.p, d.St, d.X)


@njit_inline
def placements_of(uni_joints, uni_a1, uni_a2, planar_joints, parents, kind, idx_q, idx_v, nv_j, axis, pitch,
                  place_R, place_p, site_jid, site_local, q, with_bias, v, jR, jp, Sl, c_local, R, p, St, X):
    """:func:`placements` on explicit arrays (the loop projection calls it every iteration)."""
    if uni_joints.shape[0]:
        universal_kernel(uni_joints, idx_q, idx_v, uni_a1, uni_a2, q, v, with_bias, jR, jp, Sl, c_local)
    if planar_joints.shape[0]:
        planar_placements(planar_joints, idx_q, q, jR, jp)
    fk_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl, R, p, St)
    site_pos_kernel(R, p, site_jid, site_local, X)


@njit_inline
def kinematics(m, d, q, v, warm):
    """Everything of (q, qdot_r) the forces need: placements, inertias I (world, at the origin), twists ov.
    ``warm``: d already holds the placements at q and the twists of v (the previous step of the run left them:
    its energies at its q+, qdot_r+, which are this BDF1 step's q_k, qdot_k bit for bit), so only the universal
    joints' bias c(q, v) and the inertias are computed (the hand: one forward kinematics a step instead of two)."""
    if warm:
        if m.uni_joints.shape[0]:
            universal_kernel(m.uni_joints, m.idx_q, m.idx_v, m.uni_a1, m.uni_a2, q, v, True, d.jR, d.jp, d.Sl,
                             d.c_local)
    else:
        placements(m, d, q, True, v)
    world_inertia_kernel(m.mass, m.com, m.inertia_com, d.R, d.p, d.I)
    if not warm:
        jv_kernel(m.parents, m.idx_v, m.nv_j, d.St, v, d.ov)


@njit_inline
def point_jacobian(parents, idx_v, nv_j, site_jid, St, X, site, J):
    """J (3, nv) = the world point Jacobian of site ``site`` at the placements (St, X) (Eq. S2.4: column c =
    lin(S_c) + ang(S_c) x x_site on the DOFs supporting the site, zero elsewhere)."""
    J[:, :] = 0.0
    x0, x1, x2 = X[site, 0], X[site, 1], X[site, 2]
    j = site_jid[site]
    while j > 0:
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            w0, w1, w2 = St[c, 3], St[c, 4], St[c, 5]
            J[0, c] = St[c, 0] + w1 * x2 - w2 * x1
            J[1, c] = St[c, 1] + w2 * x0 - w0 * x2
            J[2, c] = St[c, 2] + w0 * x1 - w1 * x0
        j = parents[j]
