"""Stage 4' of the compiled step: the joint limits of Eq. (5) by a primal active set inside the kernel.

    min 1/2 qdot^T A qdot - b^T qdot   s.t.   G qdot = g,   lo <= C qdot <= hi      (A = A_R, C = limit rows)

the QP whose optimality conditions are A qdot = b - G^T lam - C^T mu with mu <= 0 on a row at its lower
bound, mu >= 0 at its upper bound and mu = 0 off its bounds (the sign convention of solvers/direct.py and of
ProxSuite's box multipliers). Starting from the solution with no limit active, each iteration adds the most
violated limit row (at the bound it crosses) or, when every row is within its bounds, drops the active row
whose multiplier has the wrong sign, and solves the KKT system of Eq. (6) with the working rows as equalities
(kkt_solve_tree_into). Few rows change per step, so it converges in a handful of iterations; if it does not within
4 p + 4 iterations, or a KKT solve fails, the step is handed to the reference (ProxSuite, solvers/direct.py)."""
from __future__ import annotations

from redmax_ros.core.jit import njit_inline
from redmax_ros.core.solvers.kkt import kkt_solve_tree_into, max_row_residual

FEAS_TOL = 1e-12  # as kkt._limits_ok: lo - 1e-12 <= C qdot <= hi + 1e-12
MU_TOL = 1e-13  # a multiplier within this (relative to the largest) of zero has the right sign


@njit_inline
def _solve_working_set(m, d):
    """KKT solve with the bilateral rows and the working limit rows as equalities; returns status."""
    mrows = d.g.shape[0]
    ndof = d.AR.shape[0]
    r = mrows
    for i in range(mrows):
        d.Gx[i, :] = d.G[i]
        d.gx[i] = d.g[i]
    for k in range(d.wset.shape[0]):
        if d.wset[k] != 0.0:
            d.Gx[r, :] = m.limit_rows[k]
            d.gx[r] = d.lo[k] if d.wset[k] < 0.0 else d.hi[k]
            r += 1
    status, ratio, viol, ok = kkt_solve_tree_into(d.AR, d.bR, d.Gx[:r], d.gx[:r], m.limit_rows[:0], d.lo[:0], d.hi[:0],
                                                  d.kkt_par, d.kkt_allowed, d.kkt_span, d.kkt_L, d.kkt_Yx[:ndof, :r],
                                                  d.kkt_Sx[:r, :r], d.kkt_LSx[:r, :r], d.kkt_y, d.v_hyper, d.lamx[:r])
    if status != 0 or ratio <= 1e-6:
        return 1
    # multipliers back to their rows
    for i in range(mrows):
        d.lam[i] = d.lamx[i]
    r = mrows
    for k in range(d.wset.shape[0]):
        if d.wset[k] != 0.0:
            d.mu[k] = d.lamx[r]
            r += 1
        else:
            d.mu[k] = 0.0
    return 0


@njit_inline
def active_set(m, d):
    """Joint limits of Eq. (5) from d.v_hyper (the solution without limits); returns (ok, iterations); on ok the
    solution, lam and mu are in d.v_hyper, d.lam, d.mu."""
    p = d.wset.shape[0]
    d.wset[:] = 0.0
    d.mu[:] = 0.0
    C = m.limit_rows
    for it in range(4 * p + 4):
        worst, side, excess = -1, 0.0, FEAS_TOL
        for k in range(p):
            if d.wset[k] != 0.0:
                continue
            s = 0.0
            for c in range(C.shape[1]):
                s += C[k, c] * d.v_hyper[c]
            if d.lo[k] - s > excess:
                worst, side, excess = k, -1.0, d.lo[k] - s
            elif s - d.hi[k] > excess:
                worst, side, excess = k, 1.0, s - d.hi[k]
        if worst < 0:  # feasible: drop the active row whose multiplier pulls the wrong way, if any
            mmax = 0.0
            for k in range(p):
                mmax = max(mmax, abs(d.mu[k]))
            wrong, wval = -1, MU_TOL * mmax
            for k in range(p):
                w = d.wset[k] * d.mu[k]  # > 0 is right: lower (-1) with mu <= 0, upper (+1) with mu >= 0
                if w < -wval:
                    wrong, wval = k, -w
            if wrong < 0:
                return True, it
            d.wset[wrong] = 0.0
        else:
            d.wset[worst] = side
        if _solve_working_set(m, d) != 0:
            return False, it
    return False, 4 * p + 4


@njit_inline
def bilateral_violation(d):
    """max |G qdot+ - g| of the bilateral rows only (the limit rows are not in it, as in solvers/direct.py)."""
    return max_row_residual(d.G, d.v_hyper, d.g)
