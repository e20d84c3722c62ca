"""Stages 5-6 of the compiled step: ``update_configuration`` (q+ = q (+) h J_rR qdot_R+ on the manifold, then the
loop post-stabilization of dynamics/stabilization.project_chord: chord-Newton steps dq = -K^T (K K^T)^-1 [phi; 0]
with the step's loop rows, prescribed joints held, until max|phi| < 1e-10 m) and ``required_forces`` (Eq. 7:
effort = tau - *G_r^T lam / h on the prescribed joints, the world force every prescribed site requires)."""
from __future__ import annotations

from redmax_ros.core.dynamics.stabilization import TOL, chord_factor, chord_step
from redmax_ros.core.jit import njit, njit_inline
from redmax_ros.core.step.compiled.kinematics import placements
from redmax_ros.core.step.compiled.manifold import integrate
from redmax_ros.core.step.compiled.rows import loop_phi

CHORD_MAX_ITER = 8  # as stabilization.project_chord; past it the full Newton projection (the reference) takes over


@njit_inline
def to_reduced(m, vR, out):
    """qdot_r = J_rR qdot_R (Eq. 8-9)."""
    if m.T.shape[0] == 0:
        out[:] = vR
    else:
        for i in range(out.shape[0]):
            out[i] = m.T_ratio[i] * vR[m.T_col[i]]


@njit_inline
def update_configuration(m, d, q, h):
    """q+ into d.q_new, qdot_r+ into d.v_new from d.v_hyper; returns (converged, max loop violation [m])."""
    to_reduced(m, d.v_hyper, d.v_new)
    for i in range(d.v_new.shape[0]):
        d.step_v[i] = h * d.v_new[i]
    integrate(m.kind, m.idx_q, m.idx_v, q, d.step_v, d.q_new)
    nl = m.loop_select.shape[0]
    if nl == 0:
        return True, 0.0
    if m.scalars[0] != 0.0:  # Baumgarte: the rows' RHS did it; report max|phi| at q+
        placements(m, d, d.q_new, False, d.v_new)
        _, err = loop_phi(m, d)
        return True, err
    G = d.G[:nl]
    L, ok = chord_factor(G, d.held)
    if not ok:
        return False, 0.0
    for _ in range(CHORD_MAX_ITER):
        placements(m, d, d.q_new, False, d.v_new)
        phi, err = loop_phi(m, d)
        if err < TOL:
            return True, err
        dq = chord_step(L, G, d.held, phi, m.T)
        d.q_tmp[:] = d.q_new
        integrate(m.kind, m.idx_q, m.idx_v, d.q_tmp, dq, d.q_new)
    return False, 0.0


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
