"""Stage 0 of the compiled step, ``point(m, d, q, vR, qp, vp, hh)``: where the step is linearised and from where
it advances, as step/scheme.bdf2_point computes it (the same operations in the same order; pin.integrate and
pin.difference by manifold.py, bit for bit):

    BDF2 (a history (q_k-1, qdot_k-1) of the same step size):
        d = q_k (-) q_k-1,  q^ = q_k (+) d / 3,  v* = 2 qdot_k - qdot_k-1,  v^ = (4 qdot_k - qdot_k-1) / 3,
        q* = q^ (+) hat h v*  (hat h = 2h/3)
    start-up BDF1 (step/scheme.startup_point): q^ = q_k, v* = v^ = qdot_k, q* = q_k (+) h qdot_k
    BDF1 (Eq. 2; the order control's fallback and the euler scheme): q^ = q* = q_k, v* = v^ = qdot_k.

Outputs: d.q_base (q^), d.q_lin (q*), d.v_r (v*, reduced), d.v_mom (v^, reduced), d.back (q* (-) q^, reduced).

``accepted(m, d, q, hh, placed)``: the order control of step/scheme.accepts on the step's result d.q_new (the same
differences and maxima, and the maximal springs' linearisation miss by the same kernel)."""
from __future__ import annotations

from redmax_ros.core.dynamics.springs import linearisation_miss
from redmax_ros.core.jit import njit_inline
from redmax_ros.core.step.compiled.kinematics import placements
from redmax_ros.core.step.compiled.manifold import difference, integrate
from redmax_ros.core.step.compiled.update import to_reduced
from redmax_ros.core.step.scheme import ORDER_FLOOR, ORDER_RATIO


@njit_inline
def point(m, d, q, vR, qp, vp, hist, hh):
    """Fill the step's points (module docstring); ``hist`` 1: BDF2 from the history (qp, vp), 2: the start-up BDF1
    step about the explicit Euler predictor (``hh`` = h), 0: BDF1 at q_k."""
    if hist != 1:
        d.q_base[:] = q
        to_reduced(m.T_col, m.T_ratio, vR, d.v_r)
        d.v_mom[:] = d.v_r
        if hist == 0:
            d.q_lin[:] = q
            return
        for i in range(d.back.shape[0]):
            d.back[i] = hh * d.v_r[i]
        integrate(m.kind, m.idx_q, m.idx_v, q, d.back, d.q_lin)
        return
    difference(m.kind, m.idx_q, m.idx_v, qp, q, d.bdf_d)
    for i in range(d.bdf_d.shape[0]):
        d.step_v[i] = d.bdf_d[i] / 3.0
    integrate(m.kind, m.idx_q, m.idx_v, q, d.step_v, d.q_base)
    for i in range(vR.shape[0]):
        d.v_lin[i] = 2.0 * vR[i] - vp[i]
        d.v_mom_h[i] = (4.0 * vR[i] - vp[i]) / 3.0
    to_reduced(m.T_col, m.T_ratio, d.v_lin, d.v_r)
    to_reduced(m.T_col, m.T_ratio, d.v_mom_h, d.v_mom)
    for i in range(d.back.shape[0]):
        d.back[i] = hh * d.v_r[i]
    integrate(m.kind, m.idx_q, m.idx_v, d.q_base, d.back, d.q_lin)


@njit_inline
def accepted(m, d, q, hh, placed):
    """Whether the BDF2 step from q = q_k that predicted d.q_lin and reached d.q_new is kept (step/scheme.accepts:
    max |q+ (-) q*| <= ORDER_RATIO max |q+ (-) q_k| + ORDER_FLOOR, and the same bound on the maximal springs'
    linearisation miss, springs.linearisation_miss, from their ends at q* (d.pa, d.pb) and the sites at q+,
    placed into d.X); scratch d.bdf_d, d.step_v. ``hh``: hat h [s]. ``placed``: d holds the placements at q+
    already (the step's energies left them, energy.energies), so the sites are not placed again."""
    difference(m.kind, m.idx_q, m.idx_v, d.q_lin, d.q_new, d.bdf_d)
    difference(m.kind, m.idx_q, m.idx_v, q, d.q_new, d.step_v)
    miss = 0.0
    motion = 0.0
    for i in range(d.bdf_d.shape[0]):
        miss = max(miss, abs(d.bdf_d[i]))
        motion = max(motion, abs(d.step_v[i]))
    bound = ORDER_RATIO * motion + ORDER_FLOOR
    if not miss <= bound:
        return False
    if m.spring_a.shape[0] == 0:
        return True
    if not placed:
        placements(m, d, d.q_new, False, d.v_new)  # the sites at q+ (the next step computes its own kinematics)
    return linearisation_miss(d.pa, d.pb, d.X, m.spring_a, m.spring_b, m.spring_k, m.spring_explicit, m.spring_ja,
                              m.spring_jb, m.mass, hh * hh) <= bound
