"""The coupled step of articulated and deformable DOFs in one sparse system (Wang et al. 2019 §4, the
equation after Eq. 5; Sueda's notes, deformable coupling): unknowns z = (qdot_r, qdot_d),

    [A_r  0  ] z = [b_r] - G^T lam - C^T mu,     G z = g,     lo <= C z <= hi,
    [0   A_d ]     [b_d]

A_r the dense LHS of Eq. (2) of the skeleton, A_d = M_d + h D_d + h^2 K_d sparse, G the skeleton's rows
(loops, prescriptions; zero on the deformable block) and the attachment rows [G_m J_mr, G_d] (attach.py), C
unilateral rows (joint limits of Eq. 5, the floor rows of vertices). Sign convention as solvers/problem.py.

Solved as one sparse KKT system by SuperLU (scipy.sparse.linalg.splu), with a primal-dual active set over
the unilateral rows (each iteration one factorisation with the working rows as equalities), capped at
4 p + 4 iterations. Why the KKT LU and not a Schur complement onto the reduced DOFs: docs/deformables.md
(measured: the Schur complement needs one A_d solve per attachment row, the KKT LU one factorisation).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from redmax_ros.core.errors import StepError


@dataclass
class CoupledSolution:
    v_r: np.ndarray  # (n_r,) skeleton velocities
    v_d: np.ndarray  # (3N,) vertex velocities
    lam: np.ndarray  # (m,) bilateral multipliers (skeleton rows first, then attachments)
    mu: np.ndarray  # (p,) unilateral multipliers (0 when inactive)
    iterations: int
    violation: float  # max |G z - g|
    active: list = field(default_factory=list)  # unilateral rows active at the solution
    residual: float = 0.0  # |A z + G^T lam + C^T mu - b| / |b| of the coupled KKT system (stationarity)

    @property
    def v(self):
        return self.v_r


def _factor(K, labels):
    try:
        return splu(K.tocsc())
    except RuntimeError as e:  # SuperLU: "Factor is exactly singular"
        raise StepError("the coupled KKT system of the skeleton and the deformables is singular "
                        f"(redundant or conflicting rows among: {', '.join(sorted(set(labels))[:6])}): {e}") from None


def solve(A_r, b_r, A_d, b_d, G, g, labels=(), C=None, lo=None, hi=None, tol=1e-12, warm=()) -> CoupledSolution:
    """The coupled velocity solve. A_r (n_r,n_r) dense, A_d (3N,3N) sparse, G (m, n_r + 3N) sparse with g
    (m,); C (p, n_r + 3N) sparse with bounds lo, hi (+-inf where open) or None; ``warm``: unilateral rows to
    start the active set with (held at lo; the last step's active rows), which usually saves a factorisation.
    CoupledSolution.active lists the rows active at the solution."""
    n_r, nd = len(b_r), len(b_d)
    n = n_r + nd
    A = sp.block_diag([sp.csr_matrix(np.asarray(A_r)), A_d], format="csr")
    b = np.concatenate([b_r, b_d])
    G = sp.csr_matrix(G, shape=(len(g), n))
    m = G.shape[0]
    p = 0 if C is None else C.shape[0]
    active = {int(i): lo[i] for i in warm if p and np.isfinite(lo[i])}  # row -> value it is held at
    mu = np.zeros(p)
    for it in range(1, 4 * p + 6):
        idx = np.fromiter(active, dtype=np.int64, count=len(active))
        W = C[idx] if len(idx) else None
        blocks = [[A, G.T], [G, None]] if W is None else [[A, G.T, W.T], [G, None, None], [W, None, None]]
        if m == 0:  # no bilateral rows
            blocks = [[A]] if W is None else [[A, W.T], [W, None]]
        K = sp.bmat(blocks, format="csc")
        lu = _factor(K, list(labels) + ["unilateral"] * bool(len(idx)))
        rhs = np.concatenate([b, g, [active[i] for i in idx]])
        z = lu.solve(rhs)
        v, lam, muW = z[:n], z[n:n + m], z[n + m:]
        if p == 0:
            return CoupledSolution(v[:n_r], v[n_r:], lam, mu, it, _violation(G, v, g),
                                   residual=_residual(A, b, v, G, lam, C, mu))
        mu = np.zeros(p)
        mu[idx] = muW
        Cv = C @ v
        changed = False
        for k, i in enumerate(idx):  # release rows whose multiplier pulls
            lower = active[i] == lo[i]
            if (lower and muW[k] > tol) or (not lower and muW[k] < -tol):
                del active[i]
                mu[i] = 0.0
                changed = True
        for i in np.nonzero((Cv < lo - 1e-12) | (Cv > hi + 1e-12))[0]:
            if i not in active:
                active[int(i)] = lo[i] if Cv[i] < lo[i] else hi[i]
                changed = True
        if not changed:
            return CoupledSolution(v[:n_r], v[n_r:], lam, mu, it, _violation(G, v, g), sorted(active),
                                   _residual(A, b, v, G, lam, C, mu))
    raise StepError(f"the unilateral rows of the coupled solve did not settle in {4 * p + 5} active-set iterations")


def _violation(G, v, g):
    return float(np.abs(G @ v - g).max()) if len(g) else 0.0


def _residual(A, b, v, G, lam, C, mu):
    r = A @ v - b
    if len(lam):
        r += G.T @ lam
    if C is not None and len(mu):
        r += C.T @ mu
    return float(np.linalg.norm(r) / max(np.linalg.norm(b), 1e-300))
