"""Eq. (5) by a dense active set: min 1/2 v^T A v - b^T v  s.t.  G v = g,  lo <= C v <= hi, for many
unilateral rows of which few are active (self-collision: the HAGFISH has ~135 candidate rows and ~8 active,
docs/collisions.md).

Each iteration solves the equality-constrained problem with the bilateral rows and the working set W (rows
held at the bound they crossed) by the Schur complement of Eq. (6): with A = L L^T,

    Y = A^-1 E^T,  S = E Y,  S nu = E v0 - e,  v = v0 - Y nu      (E = [G; C_W], e = [g; bounds of W])

(the sign convention of solvers/problem.py: A v = b - G^T lam - C^T mu). Then a row of W whose multiplier
pulls (mu > 0 at a lower bound, < 0 at an upper one) is released (the worst one), else every row outside
W that its bounds no longer hold is added; it stops when neither happens: v is then the QP's solution (KKT
conditions exact to round-off, against ProxSuite's eps_abs). Rows enter one at a time, the most violated
first; a row (nearly) linearly dependent on the working rows (a Schur pivot below 1e-9 of its diagonal: two
witness rows of one capsule pair) is left out, and must then hold at the solution. A^-1 C_i^T is solved once
per row that enters.
``warm``: the rows active at the previous step, the starting W (row indices, held at their lower bound, or
(row, at the upper bound) pairs). Returns None when it does not settle within
``max_iter`` iterations or the working rows are degenerate (S not positive definite); the caller then
solves the QP with ProxSuite.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla

TOL = 1e-12  # bound violation [m/s, rad/s] and multiplier sign tolerance [N s]


@dataclass
class ActiveSetResult:
    v: np.ndarray  # (n,) solution
    lam: np.ndarray  # (m,) bilateral multipliers
    mu: np.ndarray  # (p,) unilateral multipliers (0 off the working set)
    iterations: int
    active: list = field(default_factory=list)  # rows of C at a bound at the solution


def solve(A, b, G, g, C, lo, hi, warm=(), max_iter: int | None = None) -> ActiveSetResult | None:
    """The QP of Eq. (5) (module docstring); A symmetric positive definite."""
    n, m, p = len(b), len(g), len(lo)
    try:
        fac = sla.cho_factor(A, lower=True, check_finite=False)
    except (np.linalg.LinAlgError, ValueError):
        return None
    v0 = sla.cho_solve(fac, b, check_finite=False)
    YG = sla.cho_solve(fac, np.ascontiguousarray(G.T), check_finite=False).reshape(n, m) if m else np.zeros((n, 0))
    Yc = {}  # row -> A^-1 C_i^T

    def col(i):
        y = Yc.get(i)
        if y is None:
            y = Yc[i] = sla.cho_solve(fac, C[i], check_finite=False)
        return y

    work = {}  # row -> bound value it is held at (insertion order: the order rows entered)
    dependent = set()  # rows left out: (nearly) linearly dependent on the working rows
    for w in warm:
        i, upper = (int(w[0]), bool(w[1])) if isinstance(w, tuple) else (int(w), False)
        bound = hi[i] if upper else lo[i]
        if 0 <= i < p and np.isfinite(bound):
            work[i] = bound
    max_iter = 4 * p + 10 if max_iter is None else max_iter
    for it in range(1, max_iter + 1):
        idx = np.fromiter(work, dtype=np.int64, count=len(work))
        sf = None
        if m or len(idx):
            E = np.vstack([G, C[idx]]) if len(idx) else G
            e = np.concatenate([g, [work[i] for i in idx]]) if len(idx) else g
            Y = np.hstack([YG] + [col(i)[:, None] for i in idx]) if len(idx) else YG
            S = E @ Y
            try:
                sf = sla.cho_factor(S, lower=True, check_finite=False)
            except (np.linalg.LinAlgError, ValueError):
                if len(idx) and it == 1:  # a degenerate warm start: start cold
                    work.clear()
                    continue
                return None
            d = np.abs(np.diag(sf[0]))
            if d.min() <= 1e-8 * d.max():
                if len(idx) and it == 1:
                    work.clear()
                    continue
                return None
            nu = sla.cho_solve(sf, E @ v0 - e, check_finite=False)
            v = v0 - Y @ nu
        else:
            nu, v = np.zeros(0), v0.copy()
        lam, muW = nu[:m], nu[m:]
        # release the row whose multiplier pulls most
        worst, worst_val = -1, TOL
        for k, i in enumerate(idx):
            pull = muW[k] if work[i] == lo[i] else -muW[k]
            if pull > worst_val:
                worst, worst_val = int(i), pull
        if worst >= 0:
            del work[worst]
            dependent.clear()
            continue
        Cv = C @ v
        excess = np.maximum(lo - Cv, Cv - hi)
        added = False
        for i in np.argsort(-excess):  # the most violated independent row enters
            i = int(i)
            if excess[i] <= TOL:
                break
            if i in work or i in dependent:
                continue
            y = col(i)
            s_ii = float(C[i] @ y)
            if sf is not None:
                c = E @ y
                pivot = s_ii - float(c @ sla.cho_solve(sf, c, check_finite=False))
            else:
                pivot = s_ii
            if pivot <= 1e-9 * s_ii:
                dependent.add(i)
                continue
            work[i] = lo[i] if Cv[i] < lo[i] else hi[i]
            added = True
            break
        if added:
            continue
        if any(excess[i] > 1e-9 for i in dependent):  # a dependent row the working rows do not satisfy
            return None
        mu = np.zeros(p)
        mu[idx] = muW
        return ActiveSetResult(v, lam, mu, it, sorted(work))
    return None
