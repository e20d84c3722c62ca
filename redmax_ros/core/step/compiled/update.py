"""Stages 5-6 of the compiled step: ``update_configuration`` (q+ = q (+) h J_rR qdot_R+ on the manifold, then the
loop post-stabilization of dynamics/stabilization.project_chord: chord-Newton steps dq = -K^T (K K^T)^-1 [phi; 0]
with the step's loop rows, prescribed joints held, until max|phi| < 1e-10 m) and ``required_forces`` (Eq. 7:
effort = tau - *G_r^T lam / h on the prescribed joints, the world force every prescribed site requires)."""
from __future__ import annotations

from redmax_ros.core.dynamics.stabilization import TOL, chord_direction_into, chord_factor_into
from redmax_ros.core.jit import njit_inline
from redmax_ros.core.step.compiled.kinematics import placements_of
from redmax_ros.core.step.compiled.manifold import integrate
from redmax_ros.core.step.compiled.rows import loop_phi

CHORD_MAX_ITER = 8  # as stabilization.project_chord; past it the full Newton projection (the reference) takes over


@njit_inline
def to_reduced(T_col, T_ratio, vR, out):
    """qdot_r = J_rR qdot_R (Eq. 8-9) with T's one entry per row (T_col empty: no couplings)."""
    if T_col.shape[0] == 0:
        out[:] = vR
    else:
        for i in range(out.shape[0]):
            out[i] = T_ratio[i] * vR[T_col[i]]


@njit_inline
def loop_error_at(m, d, q):
    """max|phi| [m] of the loops at q (the placements of q, as kinematics.placements without the bias, left in d)."""
    placements_of(m.uni_joints, m.uni_a1, m.uni_a2, m.planar_joints, m.parents, m.kind, m.idx_q, m.idx_v, m.nv_j,
                  m.axis, m.pitch, m.place_R, m.place_p, m.site_jid, m.site_local, q, False, d.v_new,
                  d.jR, d.jp, d.Sl, d.c_local, d.R, d.p, d.St, d.X)
    return loop_phi(m.loop_a, m.loop_b, m.loop_select, m.loop_row_loop, d.X, d.dx, d.phi)


@njit_inline
def update_configuration(m, d, q, h):
    """q+ into d.q_new, qdot_r+ into d.v_new from d.v_hyper; returns (converged, max loop violation [m], placed):
    ``placed``, d holds the placements at q+ (left by the last loop-residual evaluation), which the energies
    then reuse instead of computing them again (bit for bit the same: the same call at the same q)."""
    to_reduced(m.T_col, m.T_ratio, d.v_hyper, d.v_new)
    for i in range(d.v_new.shape[0]):
        d.step_v[i] = h * d.v_new[i]
    integrate(m.kind, m.idx_q, m.idx_v, q, d.step_v, d.q_new)
    nl = m.loop_select.shape[0]
    if nl == 0:
        return True, 0.0, False
    if m.scalars[0] != 0.0:  # Baumgarte: the rows' RHS did it; report max|phi| at q+
        return True, loop_error_at(m, d, d.q_new), True
    G = d.G[:nl]
    if not chord_factor_into(G, d.held, d.chord_KK, d.chord_L, d.chord_nz):
        return False, 0.0, False
    for _ in range(CHORD_MAX_ITER):
        err = loop_error_at(m, d, d.q_new)
        if err < TOL:
            return True, err, True
        chord_direction_into(d.chord_L, G, d.held, d.phi, d.chord_y, d.chord_dq)
        to_reduced(m.T_col, m.T_ratio, d.chord_dq, d.chord_out)  # J_rR dq (stabilization.chord_step_into)
        d.q_tmp[:] = d.q_new
        integrate(m.kind, m.idx_q, m.idx_v, d.q_tmp, d.chord_out, d.q_new)
    return False, 0.0, False


@njit_inline
def required_forces(m, d, tau, h):
    """Eq. 7: d.effort = tau - lam_joint / h on the prescribed DOFs; d.site_force[k] = P^T (-lam_site / h)."""
    d.effort[:] = tau
    nl = m.loop_select.shape[0]
    for r in range(d.joint_dofs.shape[0]):
        d.effort[d.joint_dofs[r]] -= d.lam[nl + r] / h
    r0 = nl + d.joint_dofs.shape[0]
    for k in range(d.site_ids.shape[0]):
        kk = d.site_k[k]
        for c in range(3):
            s = 0.0
            for r in range(kk):
                s += d.site_P[k, r, c] * (d.lam[r0 + r] * (-1.0 / h))
            d.site_force[k, c] = s
        r0 += kk
