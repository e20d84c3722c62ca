"""Staggered Projections (paper Alg. 2, Eq. 11-12) for ground contact and Bilateral Staggered
Projections (Alg. 3, Eq. 15-18) for joint friction, in one loop, in (hyper-)reduced coordinates.

The step's linear system A qdot = b (Eq. 2) with the bilateral rows G qdot = g (loops, prescriptions)
is condensed once per step (condense.py): with P = A^-1 - A^-1 G^T (G A^-1 G^T)^-1 G A^-1 (the inverse of the
bilaterally constrained mass matrix) every impulse R^T x changes the velocity by P R^T x and
    qdot(alpha, beta) = qdot_0 + P U^T alpha - P T^T beta,     qdot_0 = P b + A^-1 G^T S^-1 g.
(This is the dual / Schur-complement form of the QPs of Eq. 17c/18: their equality rows are
eliminated, which the paper suggests for the small external systems.)
  * CONTACT (Alg. 2 line 9, Eq. 11 in reduced coordinates through Eq. 5): the unilateral rows U =
    [ground normals N; joint-limit rows +-C] with lower bounds lo, dual QP over alpha >= 0:
        min 1/2 alpha^T (U P U^T) alpha + alpha^T (U qdot(0, beta) - lo)      (PGS or ProxSuite)
  * BISP (Alg. 3 lines 8-14): joint reaction forces of the constrained velocity (Eq. 15/17), their
    leaf-to-root distribution (§5.2.2) and the local least squares of Eq. (16) -> joint alphas;
    the wrenches are affine in x = [alpha; beta], W0 + Wx x: the constant part once per step
    (bisp.wrench_map), the linear part at each iterate by one Newton-Euler pass (bisp.apply_wrenches),
    then alpha_j = h L_j (W0 + Wx x)_j; loop pins from lambda (§5.3).
  * CONVERGENCE (Alg. 2 line 12): ||f_alpha - f_alpha^0||_{M^-1} <= eps, measured per contact as the
    velocity change the change of its normal impulse (ground) or of its friction bound (joints) makes,
    max_k W_kk |delta_k| <= tol [m/s] (the diagonal of the Delassus operator stands in for M^-1), and the
    friction impulses inside their bounds in the same measure, max_k W_kk max(|beta_k| - bound_k, 0) <= tol
    (cone_excess: a sliding impulse sits on the bound of the previous friction stage).
  * FRICTION (Eq. 12): box QP over beta with W_T = T P T^T,
        min 1/2 beta^T W_T beta - beta^T T qdot(alpha, 0),  -bound <= beta <= bound   (PGS or ProxSuite)
    bounds: mu alpha on both tangents of a ground contact (four-sided pyramid), mu sum_k |alpha_k| on
    a 1-DOF joint's row, mu |alpha_k| on a spherical joint's tangent rows.
The friction impulses are cached per contact (sphere, plane) and per joint in the returned state and
warm-start the next step [Kaufman et al. 2008]. The loop exits after a CONTACT stage, so the returned
velocity always satisfies the bilateral and unilateral rows (feasible) even when the iteration cap is
reached; that case is reported (FrictionReport.converged = False), never silent.
Per step: bisp.body_frames (kinematics), contact.staggered_rows (detection, rows RX = [U; -T]),
condense.condense, bisp.wrench_map, warm_start, staggered_kernel (with PGS and whole-joint bounds;
_python_loop otherwise), finish: all compiled (numba), a few calls per step. Under a step budget
(solvers/budget.py) the loop checks the step's deadline between iterations (_python_loop) or between
pieces of the resumable compiled loop (_compiled_loop), with bitwise the result of an unbudgeted step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
import proxsuite

from redmax_ros.core.friction import bisp
from redmax_ros.core.friction.arena import empty_arena, take1
from redmax_ros.core.friction.bisp import apply_wrenches, wrench_work
from redmax_ros.core.friction.condense import condense
from redmax_ros.core.friction.contact import staggered_rows
from redmax_ros.core.errors import StepError
from redmax_ros.core.linalg import dot
from redmax_ros.core.solvers.budget import qp_solve
from redmax_ros.core.solvers.problem import LinearSystem
from redmax_ros.core.solvers.direct import Solution
import copy

_INF = 1e20


@dataclass
class FrictionReport:
    iterations: int = 0  # staggered iterations (contact stages) this step
    converged: bool = True
    residual: float = 0.0  # last convergence measure [m/s]
    contacts: int = 0  # ground contacts in the QP (gap < margin)
    active: int = 0  # ground contacts with a positive normal impulse
    max_penetration: float = 0.0  # m, before the step
    sticking: int = 0  # friction rows strictly inside their bound (static friction)
    _jn_names: list = field(default_factory=list, repr=False)
    _jn_values: np.ndarray | None = field(default=None, repr=False)

    @property
    def joint_normal(self) -> dict:
        """joint/loop -> sum_k |alpha_k| / h [N] (built on access)."""
        if self._jn_values is None:
            return {}
        return {name: float(x) for name, x in zip(self._jn_names, self._jn_values)}


@numba.njit(cache=True)
def cone_excess(beta, bound, wT):
    """max_k wT_k max(|beta_k| - bound_k, 0) [m/s]: how far the friction impulses lie outside their bounds,
    measured as the residual is (Alg. 2 line 12): the velocity change that bringing each impulse back to
    its bound would make (wT: the convergence weights of condense). The loop stops when this and the
    change of the bounds are both within the tolerance: a sliding impulse sits on the bound of the
    previous friction stage, which the last contact stage has moved by no more than the tolerance."""
    big = 0.0
    for i in range(beta.shape[0]):
        e = (abs(beta[i]) - bound[i]) * wT[i]
        if e > big:
            big = e
    return big


@numba.njit(cache=True)
def _pgs(W, c, lo, hi, x, tol, max_sweeps):
    """Projected Gauss-Seidel for min 1/2 x^T W x + c^T x, lo <= x <= hi (W symmetric PSD), warm-started
    from x (updated in place). Stops when no coordinate moves the velocity W_ii |dx_i| by more than tol.
    Returns the sweeps used."""
    n = len(c)
    for sweep in range(max_sweeps):
        big = 0.0
        for i in range(n):
            d = W[i, i]
            if d <= 1e-300:
                continue
            r = c[i] + dot(W[i], x)  # four partial sums (linalg.dot): the row product is the sweep's cost
            xi = min(max(x[i] - r / d, lo[i]), hi[i])
            ch = abs(xi - x[i]) * d
            if ch > big:
                big = ch
            x[i] = xi
        if big <= tol:
            return sweep + 1
    return max_sweeps


@numba.njit(cache=True)
def _small_solve(H, r):
    """Gaussian elimination with partial pivoting (k <= Anderson depth), in place: H and r are overwritten (the
    solution in r); returns (r, ok)."""
    k = len(r)
    A = H
    x = r
    for i in range(k):
        p = i
        for j in range(i + 1, k):
            if abs(A[j, i]) > abs(A[p, i]):
                p = j
        if abs(A[p, i]) < 1e-300:
            return x, False
        if p != i:
            for c in range(k):
                A[i, c], A[p, c] = A[p, c], A[i, c]
            x[i], x[p] = x[p], x[i]
        for j in range(i + 1, k):
            f = A[j, i] / A[i, i]
            for c in range(i, k):
                A[j, c] -= f * A[i, c]
            x[j] -= f * x[i]
    for i in range(k - 1, -1, -1):
        sacc = x[i]
        for c in range(i + 1, k):
            sacc -= A[i, c] * x[c]
        x[i] = sacc / A[i, i]
    return x, True


@numba.njit(cache=True)
def _abs_sum(a):
    """sum_k |a_k| in four interleaved partial sums (as linalg.dot)."""
    n = a.shape[0]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    k = 0
    while k + 4 <= n:
        s0 += abs(a[k])
        s1 += abs(a[k + 1])
        s2 += abs(a[k + 2])
        s3 += abs(a[k + 3])
        k += 4
    while k < n:
        s0 += abs(a[k])
        k += 1
    return (s0 + s1) + (s2 + s3)


@numba.njit(cache=True)
def loop_kernel(W_U, X_UT, X_TU, U_v0, lo_U, W_T, T_v0, mu_g, a0, wm, bound_mu, kmax, joint, wU, wT, tol,
                 max_iter, depth, alpha, beta):
    """The staggered loop with the joint multipliers given as alpha = a0 + apply_wrenches(wm, x) (a dense map,
    bisp.dense_wrench_map: redmax_bench/sp_maximal.py), in one call. Returns (alpha, beta, bound, al,
    iterations, converged, residual)."""
    nu, nf = len(U_v0), len(T_v0)
    sbuf, sint = loop_state(nu, nf, depth, len(a0))
    out = staggered_kernel(W_U, X_UT, X_TU, U_v0, lo_U, W_T, T_v0, mu_g, a0, wm, np.zeros((0, 6, kmax)),
                           np.zeros(0, dtype=np.int64), 1.0, bound_mu, kmax, joint, wU, wT, tol, max_iter, depth,
                           alpha, beta, sbuf, sint, np.inf, np.empty(loop_scratch_size(nu, nf, depth, len(a0))))
    return out[0], out[1], out[2], out[3], out[4], out[5], out[6]


@numba.njit(cache=True)
def loop_state(nu, nf, depth, nal):
    """The state of a new staggered loop for staggered_kernel: (float buffer, int buffer), zeros."""
    buf, ibuf, off = empty_arena()
    return loop_state_into(nu, nf, depth, nal, buf, ibuf, off)


@numba.njit(cache=True)
def loop_state_into(nu, nf, depth, nal, buf, ibuf, off):
    """:func:`loop_state` taken from an arena (``buf``, ``ibuf``, ``off``: arena.py), zeroed."""
    sbuf = take1(buf, off, 0, loop_state_size(nu, nf, depth, nal))
    sint = take1(ibuf, off, 1, 3)
    sbuf[:] = 0.0
    sint[:] = 0
    return sbuf, sint


@numba.njit(cache=True)
def loop_state_size(nu, nf, depth, nal):
    """Floats of loop_state's float buffer (its int buffer has 3)."""
    return 5 * nf + nu + nal + 2 * depth * nf + 2


@numba.njit(cache=True)
def _carve(buf, o, k):
    """(buf[o:o + k], o + k): the next view of a buffer laid out field after field."""
    return buf[o:o + k], o + k


@numba.njit(cache=True)
def loop_scratch_size(nu, nf, depth, na0):
    """Floats of staggered_kernel's ``scratch`` (its work vectors, none of them state kept between pieces) for
    nu unilateral and nf friction rows, Anderson depth and a0 of na0 entries (at least this; more is fine)."""
    return na0 + 4 * nu + 6 * nf + depth * depth + depth


KERNEL_FIRST_WORK = 2.0e6  # work units (~ multiply-adds, ~1-2 ms here) of the first call of the compiled loop
KERNEL_SLICE = 2e-3  # s: CPU time of each further call under a budget, between two deadline checks


@numba.njit(cache=True)
def staggered_kernel(W_U, X_UT, X_TU, U_v0, lo_U, W_T, T_v0, mu_g, a0, wm, L_ops, L_of, h, bound_mu, kmax, joint, wU,
                     wT, tol, max_iter, depth, alpha, beta, sbuf, sint, work_cap, scratch):
    """The staggered loop of solve() (same steps, same tests, PGS inner solves, Anderson) compiled:
    used when the friction bounds are whole-joint sums (no spherical joints) and qp = pgs.
    Joint multipliers (Eq. 16): with L_of (J,) given, the joint wrenches are W = a0 + apply_wrenches(wm, x)
    (a0 (6J,) and wm of bisp.wrench_map: one Newton-Euler pass per iterate) and alpha_j = h L_j W_j, L_j^T =
    L_ops[L_of[j]] (contact.distinct_operators); with L_of empty, alpha = a0 + apply_wrenches(wm, x) (a dense map).

    Resumable, so that a step budget can be checked between its pieces (solvers/budget.py): the loop's
    state between iterations lives in ``sbuf``/``sint`` (loop_state(): a new loop) and ``alpha``/``beta``;
    the call returns before an iteration once the work done in this call exceeds ``work_cap`` (work: the
    multiply-adds of the PGS sweeps, rows^2 per sweep, and of the per-iteration products; at least one
    iteration per call), with paused = True. Called again with the same arrays it continues exactly where
    it stopped: the loop run in pieces gives bitwise the result of one call (work_cap = inf).
    Returns (alpha, beta, bound, al, iterations, converged, residual, paused); the work done so far is
    sbuf[-1]. ``scratch`` (loop_scratch_size floats): the work vectors, so the loop allocates nothing."""
    nu, nf, nc = len(U_v0), len(T_v0), len(mu_g)
    nw = L_of.shape[0]
    nal = len(a0) if nw == 0 else nw * kmax
    na0 = len(a0)
    wr = scratch[:na0]
    wr[:] = 0.0
    ng = 2 * nc
    nx = nu + nf
    # the state, views of sbuf (layout of loop_state)
    bound, o = _carve(sbuf, 0, nf)
    prev_u, o = _carve(sbuf, o, nu)
    prev_b, o = _carve(sbuf, o, nf)
    gprev, o = _carve(sbuf, o, nf)
    fprev, o = _carve(sbuf, o, nf)
    nb, o = _carve(sbuf, o, nf)
    al, o = _carve(sbuf, o, nal)
    dX, o = _carve(sbuf, o, depth * nf)
    dF, ir = _carve(sbuf, o, depth * nf)  # sbuf[ir]: the residual, sbuf[ir + 1]: the work done so far
    dX, dF = dX.reshape((depth, nf)), dF.reshape((depth, nf))
    it, k_hist, have_prev = sint[0], sint[1], sint[2] != 0
    resid = np.inf if it == 0 else sbuf[ir]
    work = sbuf[ir + 1]
    work0 = work
    it0 = it
    # the work vectors, views of scratch (after wr)
    zeros_u, o = _carve(scratch, na0, nu)
    inf_u, o = _carve(scratch, o, nu)
    x, o = _carve(scratch, o, nx)
    c, o = _carve(scratch, o, nu)
    cf, o = _carve(scratch, o, nf)
    b_in, o = _carve(scratch, o, nf)  # Anderson's vectors, its matrix and right-hand side
    g, o = _carve(scratch, o, nf)
    f, o = _carve(scratch, o, nf)
    out, o = _carve(scratch, o, nf)
    Hbuf, o = _carve(scratch, o, depth * depth)
    Dfbuf, o = _carve(scratch, o, depth)
    Hbuf = Hbuf.reshape((depth, depth))
    zeros_u[:] = 0.0
    inf_u[:] = 1e20
    x[:] = 0.0
    c[:] = 0.0
    cf[:] = 0.0
    converged = False
    per_it = 2.0 * nu * nf + wrench_work(wm) + depth * (depth + 2) * nf + nx
    while True:
        if it > it0 and work - work0 > work_cap:  # pause: the state is in sbuf/sint, alpha, beta
            sint[0], sint[1], sint[2] = it, k_hist, 1 if have_prev else 0
            sbuf[ir], sbuf[ir + 1] = resid, work
            return alpha, beta, bound, al, it, False, resid, True
        it += 1
        work += per_it
        if nu:
            allpos = True
            for i in range(nu):  # c = U qdot(0, beta) - lo (explicit loops: no small BLAS calls)
                sacc = U_v0[i] - lo_U[i]
                for k in range(nf):
                    sacc -= X_UT[i, k] * beta[k]
                c[i] = sacc
                allpos = allpos and sacc >= 0.0
            if allpos:
                alpha[:] = 0.0
            else:
                for i in range(nu):
                    alpha[i] = max(alpha[i], 0.0)
                work += _pgs(W_U, c, zeros_u, inf_u, alpha, 0.1 * tol, 500) * float(nu * nu)
        for i in range(nc):
            bound[2 * i] = mu_g[i] * alpha[i]
            bound[2 * i + 1] = mu_g[i] * alpha[i]
        if joint:
            x[:nu] = alpha
            x[nu:] = beta
            apply_wrenches(wm, x, wr)  # the joint wrenches' part linear in x (one Newton-Euler pass)
            if nw:  # Eq. (16) per joint: alpha_j = h L_j (W0 + Wx x)_j
                for j in range(nw):
                    o = 6 * j
                    f0, f1, f2 = a0[o] + wr[o], a0[o + 1] + wr[o + 1], a0[o + 2] + wr[o + 2]
                    t0, t1, t2 = a0[o + 3] + wr[o + 3], a0[o + 4] + wr[o + 4], a0[o + 5] + wr[o + 5]
                    aj = al[j * kmax:(j + 1) * kmax]
                    Lt = L_ops[L_of[j]]  # points last: alpha_j = h L_j W_j as six axpys over the points
                    L0, L1, L2, L3, L4, L5 = Lt[0], Lt[1], Lt[2], Lt[3], Lt[4], Lt[5]
                    for kk in range(kmax):
                        aj[kk] = h * (L0[kk] * f0 + L1[kk] * f1 + L2[kk] * f2 + L3[kk] * t0 + L4[kk] * t1
                                      + L5[kk] * t2)
            else:
                for i in range(nal):
                    al[i] = a0[i] + wr[i]
            nj = len(bound_mu)
            for j in range(nj):
                bound[ng + j] = bound_mu[j] * _abs_sum(al[j * kmax:(j + 1) * kmax])
        resid = 0.0
        for i in range(nu):
            resid = max(resid, abs(alpha[i] - prev_u[i]) * wU[i])
        for i in range(nf):
            resid = max(resid, abs(bound[i] - prev_b[i]) * wT[i])
        if resid <= tol and cone_excess(beta, bound, wT) <= tol:
            converged = True
            break
        if it >= max_iter:
            break
        prev_u[:] = alpha
        prev_b[:] = bound
        if nf:
            for i in range(nf):
                sacc = T_v0[i]
                for k in range(nu):
                    sacc += X_TU[i, k] * alpha[k]
                cf[i] = -sacc
            b_in[:] = beta
            for i in range(nf):
                beta[i] = min(max(beta[i], -bound[i]), bound[i])
            for i in range(nf):
                nb[i] = -bound[i]
            work += _pgs(W_T, cf, nb, bound, beta, 0.1 * tol, 500) * float(nf * nf)
            if depth > 0:  # Anderson (see Anderson)
                for i in range(nf):
                    g[i] = beta[i]
                    f[i] = g[i] - b_in[i]
                if have_prev:
                    if k_hist == depth:
                        for r in range(depth - 1):
                            dX[r] = dX[r + 1]
                            dF[r] = dF[r + 1]
                        k_hist -= 1
                    for i in range(nf):
                        dX[k_hist, i] = g[i] - gprev[i]
                        dF[k_hist, i] = f[i] - fprev[i]
                    k_hist += 1
                gprev[:] = g
                fprev[:] = f
                have_prev = True
                if k_hist > 0:
                    D = dF[:k_hist]
                    H = Hbuf[:k_hist, :k_hist]
                    Df = Dfbuf[:k_hist]
                    for r in range(k_hist):
                        for q in range(r + 1):
                            sacc = dot(D[r], D[q])
                            H[r, q] = sacc
                            H[q, r] = sacc
                        Df[r] = dot(D[r], f)
                    tr = 0.0
                    for r in range(k_hist):
                        tr += H[r, r]
                    for r in range(k_hist):
                        H[r, r] += 1e-12 * max(tr, 1e-300)
                    gam, ok = _small_solve(H, Df)
                    out[:] = g
                    for r in range(k_hist):
                        for i in range(nf):
                            out[i] -= gam[r] * dX[r, i]
                    if ok and np.isfinite(out.sum()):
                        for i in range(nf):
                            beta[i] = min(max(out[i], -bound[i]), bound[i])
                    else:
                        k_hist = 0
                        have_prev = False
    sbuf[ir + 1] = work
    return alpha, beta, bound, al, it, converged, resid, False


def box_qp(W, c, lo, hi, x0, tol, solver, deadline=None):
    """min 1/2 x^T W x + c^T x on a box: ProxSuite (dense) or warm-started projected Gauss-Seidel (at most
    500 sweeps). ``deadline``: the step's budget.Deadline for the ProxSuite solve (None: no budget)."""
    if solver == "proxsuite":
        return _qp(W, c, lo, hi, np.clip(x0, lo, hi), 1e-12, deadline)
    x = np.clip(x0, lo, hi)
    _pgs(W, c, lo, hi, x, tol, 500)
    return x


def _qp(H, c, lo, hi, x0, eps, deadline=None):
    n = len(c)
    qp = proxsuite.proxqp.dense.QP(n, 0, n)
    s = qp.settings
    s.eps_abs, s.eps_rel, s.verbose = eps, 0.0, False
    s.initial_guess = proxsuite.proxqp.InitialGuess.WARM_START
    qp.init(H, c, None, None, np.eye(n), lo, hi)
    qp_solve(qp, deadline, "friction/contact QP (Staggered Projections)", x0, None, None)
    x = np.array(qp.results.x)
    if not np.all(np.isfinite(x)):
        raise StepError("friction/contact QP returned non-finite impulses")
    return np.clip(x, lo, hi)


def solve(mech, work, kin, system: LinearSystem, cons, q, v_prev_r, h, cache, site_forces=None, deadline=None,
          jdot_qdot=None):
    """Frictional contact step. Returns (Solution, FrictionReport, new cache). ``cache``: the previous
    step's friction impulses (ndarray of FrictionModel.n_slots, or None); ``work``: the step workspace's
    contact.FrictionWork (the set-up runs on its own kinematics workspace, bisp.body_frames).
    ``deadline``: the step's budget.Deadline (None: no budget), checked between the iterations of the
    Python loop and in its ProxSuite solves, and between the pieces of the compiled loop (_compiled_loop;
    without the checks a diverging walker step ran its friction.max_iter iterations of two 500-sweep PGS
    solves for ~50 ms of CPU time). ``jdot_qdot``: Jdot_rR qdot_R of a configuration-dependent J_rR (catalogue
    joint maps, Eq. 2.89; None without), part of the acceleration of the joint reactions (bisp.wrench_map)."""
    fm = mech.friction
    st = fm.settings
    A, b = system.A, system.b
    n = len(b)
    ws, Z = bisp.body_frames(fm, work, q, v_prev_r)  # placements, subspaces, inertias, twists, Jdot qdot

    # rows: unilateral U (ground normals, limits) and friction T (ground tangents, joints, loops)
    cs, RX, lo_U, nu = staggered_rows(mech, fm, work, h, cons)
    nc = 0 if cs is None else len(cs.gap)
    nf = len(RX) - nu
    ng = 2 * nc
    m = cons.m
    G = cons.G if m else np.zeros((0, n))
    gb = cons.g if m else np.zeros(0)
    status, v0, PX, W_U, X_UT, X_TU, W_T, U_v0, T_v0, wU, wT, lam0, LamX = condense(A, b, G, gb, RX, nu)
    if status == 1:
        raise StepError("the LHS matrix of Eq. (2) is not positive definite (Cholesky failed)")
    if status == 2:
        raise StepError("bilateral constraints are redundant or conflicting (singular Schur complement)")

    # warm start of the friction impulses: one cache slot per (sphere, plane) tangent, joint and loop row
    slots, beta = warm_start(_NO_CACHE if cache is None else cache, cache is not None,
                              cs.sphere if nc else _NO_INDEX, cs.plane if nc else _NO_INDEX, len(fm.plane_n),
                              fm.joint_slot0, nf)
    joint_fric = fm.has_joint_friction
    if joint_fric:  # Eq. (15)-(17) as a function of x = [alpha_U; beta] (bisp.wrench_map)
        W0, wm = bisp.wrench_map(mech, fm, work, kin, ws, Z, h, v0, PX, v_prev_r, lam0, LamX, cs, nu, nf, cons,
                                 site_forces, jdot_qdot)
        kmax = fm.L.shape[1]
    alpha = np.zeros(nu)
    it, converged, resid = 0, False, np.inf
    use_kernel = st.qp == "pgs" and (not joint_fric or fm.bound_mu is not None)
    mu_g = cs.mu if nc else np.zeros(0)
    if use_kernel:  # compiled loop, same steps
        if not joint_fric:
            kmax, w0, L_ops, L_of, bmu = 1, np.zeros(0), np.zeros((0, 6, 1)), np.zeros(0, dtype=np.int64), np.zeros(0)
            wm = bisp.dense_wrench_map(np.zeros((0, nu + nf)))
        else:
            w0, L_ops, L_of, bmu = W0.reshape(-1), fm.L_ops, fm.L_of, fm.bound_mu
        alpha, beta, bound, al, it, converged, resid = _compiled_loop(
            deadline, W_U, X_UT, X_TU, U_v0, lo_U, W_T, T_v0, mu_g, w0, wm, L_ops, L_of, h, bmu, kmax, joint_fric,
            wU, wT, st.tol, st.max_iter, st.anderson, alpha, beta)
    else:
        alpha, beta, bound, al, it, converged, resid = _python_loop(
            fm, st, W_U, X_UT, U_v0, lo_U, W_T, T_v0, mu_g, nc,
            (lambda x: bisp.joint_alphas_at(fm, h, W0, wm, x)) if joint_fric else None, wU, wT, alpha, beta,
            deadline)

    if not joint_fric:
        kmax, al = 1, np.zeros(0)
    v, r, lam, new_cache, active, max_pen, sticking, jn = finish(
        v0, PX, b, RX, lam0, LamX, alpha, beta, bound, al, slots, fm.n_slots, cs.gap if nc else _NO_GAP, kmax, h)
    # velocity of the last contact stage (Alg. 2 line 20); the unilateral rows are in r = b + RX^T x
    sol = Solution(v, lam, _NO_GAP, it, "staggered", LinearSystem(A, r), cons if cons.C is None else _no_unilateral(cons))
    rep = FrictionReport(it, converged, float(resid), nc, active, max_pen, sticking)
    if joint_fric:
        rep._jn_names = fm.fj_names
        rep._jn_values = jn
    return sol, rep, new_cache


_NO_CACHE = np.zeros(0)
_NO_INDEX = np.zeros(0, dtype=np.int64)
_NO_GAP = np.zeros(0)


@numba.njit(cache=True)
def warm_start(cache, has_cache, sphere, plane, n_planes, j0, nf):
    """:func:`warm_start_into` on arrays of its own: (slots, beta)."""
    return warm_start_into(cache, has_cache, sphere, plane, n_planes, j0, np.empty(nf, dtype=np.int64), np.empty(nf))


@numba.njit(cache=True)
def warm_start_into(cache, has_cache, sphere, plane, n_planes, j0, slots, beta):
    """Cache slots of this step's friction rows (2 per (sphere, plane) ground contact, then the joint and
    loop rows from j0) into ``slots`` (nf,) and the warm-start impulses [Kaufman et al. 2008] into ``beta``
    (nf,; zeros without a cache). Returns (slots, beta)."""
    nc = len(sphere)
    nf = len(slots)
    for c in range(nc):
        g0 = 2 * (sphere[c] * n_planes + plane[c])
        slots[2 * c], slots[2 * c + 1] = g0, g0 + 1
    for i in range(nf - 2 * nc):
        slots[2 * nc + i] = j0 + i
    beta[:] = 0.0
    if has_cache:
        for i in range(nf):
            beta[i] = cache[slots[i]]
    return slots, beta


@numba.njit(cache=True)
def finish(v0, PX, b, RX, lam0, LamX, alpha, beta, bound, al, slots, n_slots, gap, kmax, h):
    """:func:`finish_into` on arrays of its own: (v, r, lam, cache, active, max_pen, sticking, jn)."""
    v, r, lam, cache = np.empty(len(v0)), np.empty(len(b)), np.empty(len(lam0)), np.empty(n_slots)
    jn = np.empty(len(al) // kmax)
    scratch = np.empty(finish_scratch_size(len(alpha) + len(beta), len(b), len(lam0)))
    active, max_pen, sticking = finish_into(v0, PX, b, RX, lam0, LamX, alpha, beta, bound, al, slots, gap, kmax, h,
                                            v, r, lam, cache, jn, scratch)
    return v, r, lam, cache, active, max_pen, sticking, jn


@numba.njit(cache=True)
def finish_scratch_size(nx, n, m):
    """Floats of finish_into's ``scratch`` for nx staggered rows, n DOFs and m bilateral rows."""
    return nx + n + m


@numba.njit(cache=True)
def finish_into(v0, PX, b, RX, lam0, LamX, alpha, beta, bound, al, slots, gap, kmax, h, v, r, lam, cache, jn,
                scratch):
    """Outputs of the staggered solve from its last iterate x = [alpha; beta] into the given arrays: velocity
    v = qdot_0 + PX x, generalized impulse RHS r = b + RX^T x, multipliers lam = lambda_0 + LamX x, the new
    warm-start ``cache`` (n_slots,), the joint normal loads jn = sum_k |alpha_k| / h (len(al) // kmax,);
    returns the report's counts (active ground contacts, deepest penetration, sticking friction rows).
    ``scratch``: finish_scratch_size floats (x and the products)."""
    nu, nf = len(alpha), len(beta)
    n, m = len(v0), len(lam0)
    x = scratch[:nu + nf]
    tn = scratch[nu + nf:nu + nf + n]
    tm = scratch[nu + nf + n:nu + nf + n + m]
    x[:nu] = alpha
    x[nu:] = beta
    np.dot(PX, x, tn)  # as v0 + PX @ x
    for i in range(n):
        v[i] = v0[i] + tn[i]
    np.dot(x, RX, tn)  # as b + x @ RX
    for i in range(len(b)):
        r[i] = b[i] + tn[i]
    if m:
        np.dot(LamX, x, tm)
        for i in range(m):
            lam[i] = lam0[i] + tm[i]
    cache[:] = 0.0
    for i in range(nf):
        cache[slots[i]] = beta[i]
    nc = len(gap)
    active = 0
    max_pen = 0.0
    for c in range(nc):
        if alpha[c] > 1e-12:
            active += 1
        max_pen = max(max_pen, -gap[c])
    sticking = 0
    for i in range(nf):
        if bound[i] > 1e-12 and bound[i] - abs(beta[i]) > 1e-9 * max(bound[i], 1e-300):
            sticking += 1
    nj = len(al) // kmax
    for j in range(nj):
        sacc = 0.0
        for k in range(kmax):
            sacc += abs(al[j * kmax + k])
        jn[j] = sacc / h
    return active, max_pen, sticking


def _compiled_loop(deadline, *args):
    """staggered_kernel(*args) in one call without a deadline; with one, in pieces with the deadline checked
    between them (bitwise the same result): a first piece of KERNEL_FIRST_WORK (more than a normal step's
    loop needs), then pieces sized to KERNEL_SLICE of CPU time (or the time left) by the measured CPU time
    per unit of work. Returns (alpha, beta, bound, al, iterations, converged, residual)."""
    W_U, T_v0, a0, L_of, kmax, depth = args[0], args[6], args[8], args[11], args[14], args[20]
    nal = len(a0) if L_of.shape[0] == 0 else L_of.shape[0] * kmax
    sbuf, sint = loop_state(len(W_U), len(T_v0), depth, nal)
    scratch = np.empty(loop_scratch_size(len(W_U), len(T_v0), depth, len(a0)))
    if deadline is None:
        return staggered_kernel(*args, sbuf, sint, math.inf, scratch)[:7]
    deadline.begin()
    cap = KERNEL_FIRST_WORK
    while True:
        out = staggered_kernel(*args, sbuf, sint, cap, scratch)
        if not out[7]:
            return out[:7]
        deadline.check("Staggered Projections (compiled loop)", out[4])
        per_work = deadline.used() / max(sbuf[-1], 1.0)  # s per unit (an upper bound: includes earlier solvers)
        cap = min(KERNEL_SLICE, deadline.remaining()) / per_work if per_work > 0 else KERNEL_FIRST_WORK


def _python_loop(fm, st, W_U, X_UT, U_v0, lo_U, W_T, T_v0, mu_g, nc, alphas, wU, wT, alpha, beta, deadline=None):
    """The staggered loop in Python (ProxSuite inner solves, spherical-joint bounds); same steps as
    staggered_kernel, with the step's deadline checked between iterations. Returns (alpha, beta, bound,
    al, iterations, converged, residual)."""
    if deadline is not None:
        deadline.begin()
    nu, nf, ng = len(U_v0), len(T_v0), 2 * nc
    acc = Anderson(st.anderson)
    prev_u, prev_b = None, None
    bound = np.zeros(nf)
    al = np.zeros(0)
    kmax = fm.L.shape[1]
    it, converged, resid = 0, False, np.inf
    while True:
        if deadline is not None and it:
            deadline.check("Staggered Projections", it)
        it += 1
        # CONTACT (Eq. 11 / 17c)
        if nu:
            c = U_v0 - X_UT @ beta - lo_U
            if np.all(c >= 0):
                alpha = np.zeros(nu)
            else:
                alpha = box_qp(W_U, c, np.zeros(nu), np.full(nu, _INF), alpha, 0.1 * st.tol, st.qp, deadline)
        # BISP (Eq. 15-17): joint alphas -> bounds of the joint friction rows
        if nc:
            bound[:ng] = np.repeat(mu_g * alpha[:nc], 2)
        if alphas is not None:  # x -> the joint multipliers (bisp.joint_alphas_at)
            al = alphas(np.concatenate([alpha, beta]))
            if fm.bound_mu is not None:  # 1-DOF joints and pins: mu_j sum_k |alpha_jk|
                bound[ng:] = fm.bound_mu * np.abs(al).reshape(-1, kmax).sum(1)
            else:
                bound[ng:] = fm.bound_B @ np.abs(al)
        # CONVERGENCE CHECK (Alg. 2 line 12)
        du = np.abs(alpha - (prev_u if prev_u is not None else 0.0)) * wU  # f_alpha^0 = 0 at first
        db = np.abs(bound - (prev_b if prev_b is not None else 0.0)) * wT
        resid = max(du.max(initial=0.0), db.max(initial=0.0))
        if resid <= st.tol and cone_excess(beta, bound, wT) <= st.tol:
            converged = True
            break
        if it >= st.max_iter:
            break
        prev_u, prev_b = alpha.copy(), bound.copy()
        # FRICTION (Eq. 12)
        if nf:
            cf = T_v0 + X_UT.T @ alpha
            b_in = beta
            beta = box_qp(W_T, -cf, -bound, bound, beta, 0.1 * st.tol, st.qp, deadline)
            if st.anderson:
                beta = acc.update(b_in, beta, bound)
    return alpha, beta, bound, al, it, converged, resid


class Anderson:
    """Anderson acceleration (type II, depth m) of the staggered fixed point beta_{k+1} = G(beta_k).

    With joint friction the staggered iteration converges linearly (measured contraction ~0.9 per
    iteration on the walker: joint friction changes the loop forces, which change the joint normal
    forces); extrapolating over the last m iterates cuts the iteration count several-fold. The
    extrapolated impulses are clipped to the current friction bounds; the convergence test of Alg. 2
    is unchanged (it still needs the contact forces to stop changing and beta inside its bounds, both to
    the tolerance)."""

    def __init__(self, m):
        self.m = m
        self.dX, self.dF = [], []  # differences of successive G(beta_k) and residuals
        self.g = self.f = None

    def reset(self):
        self.dX, self.dF = [], []
        self.g = self.f = None

    def update(self, b_in, g, bound):
        f = g - b_in
        if self.f is not None:
            self.dX.append(g - self.g)
            self.dF.append(f - self.f)
            if len(self.dF) > self.m:
                del self.dX[0], self.dF[0]
        self.g, self.f = g, f
        k = len(self.dF)
        if k == 0:
            return g
        dF = np.array(self.dF)  # (k, n)
        H = dF @ dF.T
        H.flat[::k + 1] += 1e-12 * max(float(H.trace()), 1e-300)
        try:
            gam = np.linalg.solve(H, dF @ f)
        except np.linalg.LinAlgError:
            self.reset()
            return g
        out = g - gam @ np.array(self.dX)
        if not math.isfinite(out.sum()):
            self.reset()
            return g
        return np.minimum(np.maximum(out, -bound), bound)


def _no_unilateral(cons):
    c = copy.copy(cons)
    c.C = None
    return c


def _loop_external(mech, fm, kin, ext, fx, lam_loops, beta_loops, h, loop_force):
    """Loop-closure forces -J^T G^T lambda / h (both sites) and loop-pin friction moments as external
    forces of the tree (§5.3); fills loop_force (force on site b of each frictional loop). Used with
    bisp.joint_alphas as the direct (one RNEA per iterate) reference of bisp.linear_alphas (tests)."""
    r = 0
    ab = mech.loop_ab
    rows_ab = mech.loop_rows_ab
    Fb = np.zeros((len(ab), 3))
    for i, P in enumerate(mech.loop_axes):
        k = len(P)
        Fb[i] = P.T @ lam_loops[r:r + k] / h
        r += k
    xa, xb = kin.X[rows_ab[:, 0]], kin.X[rows_ab[:, 1]]
    ext.add(fx, mech.site_jid[ab[:, 0]], -Fb, xa)
    ext.add(fx, mech.site_jid[ab[:, 1]], Fb, xb)
    if len(fm.loop_index):
        li = fm.loop_index
        loop_force[:] = Fb[li]
        Mw = (fm.loop_radius * beta_loops / h)[:, None] * fm.loop_axis
        ext.add(fx, mech.site_jid[ab[li, 0]], np.zeros_like(Mw), None, -Mw)
        ext.add(fx, mech.site_jid[ab[li, 1]], np.zeros_like(Mw), None, Mw)
