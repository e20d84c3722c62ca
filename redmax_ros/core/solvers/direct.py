"""Direct solver for one step: dense Cholesky of the LHS of Eq. (2), bilateral constraints by the
Schur complement of the KKT system (Eq. 6/7), unilateral joint limits by the QP of Eq. (5)
(ProxSuite). Sign convention: A qdot = b - G^T lam - C^T mu, so -G^T lam is the constraint impulse.
With integrator.coriolis: implicit the LHS is not symmetric (LinearSystem.symmetric False): LU instead of
Cholesky (kkt.kkt_solve_lu, numpy's LU above kkt.SMALL_N) and the joint-limit QP as a fixed point of
symmetric QPs (_solve_qp_nonsymmetric). Under a step budget (solvers/budget.py) every ProxSuite solve is
capped and the step's deadline is checked between its slices (budget.qp_solve).
"""
from __future__ import annotations

from dataclasses import dataclass

import eigenpy
import numpy as np
import proxsuite

from redmax_ros.core.solvers.budget import qp_solve
from redmax_ros.core.solvers.problem import Constraints
from redmax_ros.core.errors import StepError
from redmax_ros.core.solvers.problem import LinearSystem
from redmax_ros.core.solvers import active_set
from redmax_ros.core.solvers.kkt import SMALL_N, kkt_residual, kkt_solve, kkt_solve_lu, max_row_residual

_SUCCESS = eigenpy.ComputationInfo.Success


@dataclass
class Solution:
    v: np.ndarray  # new (hyper-reduced) velocity
    lam: np.ndarray  # multipliers of the bilateral rows
    mu: np.ndarray  # multipliers of the unilateral rows (zero when inactive)
    iterations: int  # 1 for a direct solve, QP iterations otherwise
    solver: str
    system: LinearSystem | None = None
    cons: Constraints | None = None
    violation: float = 0.0  # max |G qdot+ - g| of the bilateral rows [m/s, rad/s]
    contacts: object = None  # dynamics/self_collision.ContactReport when the scene has a collision section
    given_residual: float | None = None  # the residual, given by a solver that keeps no system/cons (the coupled solve)

    @property
    def residual(self) -> float:
        """Relative residual |A v - b + G^T lam + C^T mu| / |b| of the KKT stationarity equation
        (computed on demand: the direct solve makes it round-off by construction)."""
        if self.system is None:
            return float("nan") if self.given_residual is None else self.given_residual
        c = self.cons
        C = c.C if len(self.mu) else _NO_ROWS
        return kkt_residual(self.system.A, self.system.b, self.v, c.G, self.lam, C, self.mu)


def _cholesky(A, what):
    llt = eigenpy.LLT(A)
    if llt.info() != _SUCCESS:
        raise StepError(f"{what} is not positive definite (Cholesky failed)")
    return llt


def solve_direct(sys: LinearSystem, cons: Constraints, qp_eps: float = 1e-10, deadline=None, warm=None) -> Solution:
    """Eq. (2) with the bilateral rows of Eq. (6)/(7) (Schur complement) and, when the unconstrained
    solution crosses a joint limit, the QP of Eq. (5). Small systems (n <= kkt.SMALL_N) in one
    compiled call (kkt.py), larger ones with Eigen's LLT. ``deadline``: the step's budget.Deadline (the
    QP's iteration caps and time), None for no budget. ``warm``: None, or the unilateral rows active at the
    previous step, to solve the QP by the dense active set (solvers/active_set.py; many rows, few active:
    self-collision) before falling back on ProxSuite."""
    if not sys.symmetric:
        return _solve_direct_lu(sys, cons, qp_eps, deadline)
    A, b = sys.A, sys.b
    n = len(b)
    if n <= SMALL_N:
        v, lam, viol, limits_ok = _small_kkt(kkt_solve, A, b, cons, check_rank,
                                             "the LHS matrix of Eq. (2) is not positive definite (Cholesky failed)",
                                             "Schur complement not positive definite")
    else:
        llt = _cholesky(A, "the LHS matrix of Eq. (2)")
        v = np.asarray(llt.solve(b)).reshape(n)  # eigenpy may return (1,1) / 1-D shapes for n == 1
        lam = np.zeros(cons.m)
        if cons.m:
            Y = np.asarray(llt.solve(np.ascontiguousarray(cons.G.T))).reshape(n, cons.m)
            S = cons.G @ Y
            lls = eigenpy.LLT(S)
            Ld = lls.matrixL().diagonal() if lls.info() == _SUCCESS else np.zeros(1)
            if Ld.min() <= 1e-6 * Ld.max():  # singular or nearly so: name the rows
                check_rank(S, cons.labels)
            lam = np.asarray(lls.solve(cons.G @ v - cons.g)).reshape(cons.m)
            v = v - Y @ lam
        viol, limits_ok = _violation_and_limits(cons, v)
    if limits_ok:
        return Solution(v, lam, _EMPTY if cons.C is None else np.zeros(len(cons.lo)), 1, "direct", sys, cons, viol)
    if warm is not None:
        r = active_set.solve(A, b, cons.G, cons.g, cons.C, cons.lo, cons.hi, warm)
        if r is not None:
            return Solution(r.v, r.lam, r.mu, r.iterations, "active-set", sys, cons, _violation_and_limits(cons, r.v)[0])
    v, lam, mu, iters = _solve_qp(A, b, cons, qp_eps, deadline)
    return Solution(v, lam, mu, iters, "qp", sys, cons, _violation_and_limits(cons, v)[0])


def _violation_and_limits(cons, v):
    """(max|G v - g|, whether lo - 1e-12 <= C v <= hi + 1e-12) for the NumPy paths."""
    viol = max_row_residual(cons.G, v, cons.g)
    if cons.C is None:
        return viol, True
    Cv = cons.C @ v
    return viol, not ((Cv < cons.lo - 1e-12).any() or (Cv > cons.hi + 1e-12).any())


_EMPTY = np.zeros(0)
_NO_ROWS = np.zeros((0, 0))


def _small_kkt(kernel, A, b, cons, check_rank, lhs_failure, schur_failure):
    """(qdot+, lam, max|G qdot+ - g|, limits_ok) of a small system by one compiled kernel (kkt.kkt_solve
    or kkt.kkt_solve_lu); StepError naming the failure, near-singular rows named by ``check_rank``."""
    no_limits = cons.C is None
    status, v, lam, S, ratio, viol, limits_ok = kernel(
        A, b, cons.G, cons.g, _NO_ROWS if no_limits else cons.C, _EMPTY if no_limits else cons.lo,
        _EMPTY if no_limits else cons.hi)
    if status == 1:
        raise StepError(lhs_failure)
    if status == 2 or ratio <= 1e-6:  # singular or nearly so: name the rows
        check_rank(S, cons.labels)
        if status == 2:
            raise StepError(f"constraints are redundant or conflicting ({schur_failure})")
    return v, lam, viol, limits_ok


def check_rank(S, labels):
    """Redundant or conflicting bilateral rows make the Schur complement singular: name them."""
    d = np.sqrt(np.abs(np.diag(S)))
    if np.any(d == 0):
        i = int(np.argmin(d))
        raise StepError(f"constraint row of {labels[i]} does not act on any DOF (impossible constraint)")
    Sn = S / d[:, None] / d[None, :]
    w, V = np.linalg.eigh(Sn)
    if w[0] < 1e-12:
        involved = sorted({labels[i] for i in np.flatnonzero(np.abs(V[:, 0]) > 1e-3)})
        raise StepError("constraints are redundant or conflicting (over-constrained mechanism): "
                        + ", ".join(involved))


QP_NAME = "joint-limit QP (Eq. 5)"


def _solve_qp(A, b, cons, eps, deadline=None):
    n, m, p = A.shape[0], cons.m, len(cons.lo)
    qp = proxsuite.proxqp.dense.QP(n, m, p)
    qp.settings.eps_abs = eps
    qp.settings.eps_rel = 0.0
    qp.settings.verbose = False
    qp.init(A, -b, cons.G if m else None, cons.g if m else None, cons.C, cons.lo, cons.hi)
    iters = qp_solve(qp, deadline, QP_NAME)
    status = qp.results.info.status
    if status != proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED:
        raise StepError(f"joint-limit QP (Eq. 5) failed: {status.name} (limits conflict with prescriptions?)")
    x = np.array(qp.results.x)
    if not np.all(np.isfinite(x)):
        raise StepError("joint-limit QP (Eq. 5) returned non-finite velocities")
    z = np.array(qp.results.z)
    polished = polish(A, b, cons, z)
    if polished is not None:
        return polished.v, polished.lam, polished.mu, iters
    return x, np.array(qp.results.y), z, iters


POLISH_ACTIVE = 1e-9  # |z_i| above this fraction of max(|z|, 1) marks row i active in ProxSuite's solution


def polish(A, b, cons, z):
    """ProxSuite's solution made exact and reproducible: the rows its multipliers z mark active (z_i > 0 at the
    upper bound, < 0 at the lower one; ProxSuite's sign convention, the same as solvers/problem.py's) start the
    dense active set (solvers/active_set.py), which then solves the equality-constrained KKT system of those rows
    by Cholesky (KKT conditions to round-off instead of eps_abs) and confirms the set, normally in one iteration.

    Why: ProxSuite's iterates depend on the memory alignment of its internal Eigen buffers at the round-off level
    (measured: the same QP solved in fresh QP objects differs by 2.6e-16 between runs), and a chaotic mechanism
    amplifies that, so the same inputs did not give the same trajectory (HAGFISH: two runs apart from step 50
    with ProxSuite as its contact QP, step 149 with the active set falling back to it). The active set's
    LAPACK Cholesky gave identical results at every alignment tried. Returns None (keep ProxSuite's solution)
    when the active set does not settle."""
    if cons.C is None or not len(z):
        return None
    scale = POLISH_ACTIVE * max(1.0, float(np.abs(z).max()))
    rows = np.flatnonzero(np.abs(z) > scale)
    upper = z[rows] > 0
    if len(b) <= SMALL_N:  # small systems: the working set's KKT system in one compiled call, checked here
        r = _confirm_working_set(A, b, cons, rows, upper)
        if r is not None:
            return r
    return active_set.solve(A, b, cons.G, cons.g, cons.C, cons.lo, cons.hi, list(zip(rows.tolist(), upper.tolist())))


def _confirm_working_set(A, b, cons, rows, upper):
    """The QP's solution if the rows ``rows`` (at their upper bound where ``upper``) are exactly its active set:
    the KKT system with them as equalities (kkt.kkt_solve), then every bound held and every multiplier of the
    right sign (active_set.TOL); else None."""
    m = cons.m
    E = np.vstack([cons.G, cons.C[rows]]) if len(rows) else cons.G
    e = np.concatenate([cons.g, np.where(upper, cons.hi[rows], cons.lo[rows])])
    status, v, nu, _, ratio, _, _ = kkt_solve(A, b, np.ascontiguousarray(E), e, _NO_ROWS, _EMPTY, _EMPTY)
    if status != 0 or ratio <= 1e-8:
        return None
    muW = nu[m:]
    if (np.where(upper, -muW, muW) > active_set.TOL).any():  # a row that pulls away from its bound
        return None
    Cv = cons.C @ v
    if (Cv < cons.lo - active_set.TOL).any() or (Cv > cons.hi + active_set.TOL).any():
        return None
    mu = np.zeros(len(cons.lo))
    mu[rows] = muW
    return active_set.ActiveSetResult(v, nu[:m].copy(), mu, 1, sorted(rows.tolist()))


# ------------------------------------------------------------------------------------------------
# non-symmetric LHS (integrator.coriolis: implicit; forces.coriolis_jacobian)


def _solve_direct_lu(sys: LinearSystem, cons: Constraints, qp_eps: float, deadline=None) -> Solution:
    """solve_direct for a non-symmetric A = M + h K_v + ...: the same Schur complement of Eq. (6)/(7)
    with LU factorisations (Y = A^-1 G^T, S = G Y), the joint limits of Eq. (5) by _solve_qp_nonsymmetric."""
    A, b = sys.A, sys.b
    n = len(b)
    if n <= SMALL_N:
        v, lam, viol, limits_ok = _small_kkt(
            kkt_solve_lu, A, b, cons, _check_rank_nonsymmetric,
            "the LHS matrix of Eq. (2) (with the implicit Coriolis term) is singular (LU failed)",
            "Schur complement singular")
    else:
        rhs = np.column_stack([b, cons.G.T]) if cons.m else b[:, None]
        try:
            X = np.linalg.solve(A, rhs)
        except np.linalg.LinAlgError:
            raise StepError("the LHS matrix of Eq. (2) (with the implicit Coriolis term) is singular (LU failed)")
        v, lam = X[:, 0].copy(), np.zeros(cons.m)
        if cons.m:
            Y = X[:, 1:]
            S = cons.G @ Y
            sv = np.linalg.svd(S, compute_uv=False)
            if sv[-1] <= 1e-12 * sv[0]:  # singular or nearly so: name the rows
                _check_rank_nonsymmetric(S, cons.labels)
            lam = np.linalg.solve(S, cons.G @ v - cons.g)
            v = v - Y @ lam
        viol, limits_ok = _violation_and_limits(cons, v)
    if limits_ok:
        return Solution(v, lam, _EMPTY if cons.C is None else np.zeros(len(cons.lo)), 1, "direct", sys, cons, viol)
    v, lam, mu, iters = _solve_qp_nonsymmetric(A, b, cons, qp_eps, v, deadline)
    return Solution(v, lam, mu, iters, "qp", sys, cons, _violation_and_limits(cons, v)[0])


def _check_rank_nonsymmetric(S, labels):
    """check_rank for a non-symmetric Schur complement (SVD instead of eigh; right null vector)."""
    d = np.sqrt(np.abs(np.diag(S)))
    if np.any(d == 0):
        i = int(np.argmin(d))
        raise StepError(f"constraint row of {labels[i]} does not act on any DOF (impossible constraint)")
    _, w, Vt = np.linalg.svd(S / d[:, None] / d[None, :])
    if w[-1] < 1e-12:
        involved = sorted({labels[i] for i in np.flatnonzero(np.abs(Vt[-1]) > 1e-3)})
        raise StepError("constraints are redundant or conflicting (over-constrained mechanism): "
                        + ", ".join(involved))


QP_FIXED_POINT_MAX = 50


def _solve_qp_nonsymmetric(A, b, cons, eps, v, deadline=None):
    """Eq. (5) with a non-symmetric A: the optimality conditions A v = b - G^T lam - C^T mu with the limit
    complementarity are not a QP, but with A = H + K (H symmetric part, K = h skew(K_v) small) they are
    the fixed point of the QPs  min 1/2 v^T H v - (b - K v_k)^T v  (same constraints), which converges
    linearly at the rate |H^-1 K| = O(h |qdot|). Each iterate is one ProxSuite solve; stops when the
    velocity changes by less than the QP tolerance. iterations = total QP iterations; the step's deadline
    is checked between the fixed-point iterations (and inside each QP)."""
    H = 0.5 * (A + A.T)
    K = A - H
    total = 0
    for k in range(QP_FIXED_POINT_MAX):
        if deadline is not None and k:
            deadline.check("joint-limit QP fixed point (implicit Coriolis)", total)
        x, y, z, it = _solve_qp(H, b - K @ v, cons, eps, deadline)
        total += it
        dv = float(np.abs(x - v).max())
        v = x
        if dv <= max(eps, 1e-14 * float(np.abs(x).max())):
            return x, y, z, total
    raise StepError(f"joint-limit QP (Eq. 5) with the implicit Coriolis term did not converge in "
                    f"{QP_FIXED_POINT_MAX} fixed-point iterations (|dv| = {dv:.3g})")
