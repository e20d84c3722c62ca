"""The dense active set for the QP of Eq. (5) (solvers/active_set.py): its solution satisfies the KKT
conditions to round-off and equals ProxSuite's to its tolerance on random QPs with many unilateral rows
and few active; duplicated (linearly dependent) rows are left out and still hold; a warm start (right or
wrong) gives the same solution; infeasible rows make it give up (None) for the ProxSuite fallback."""
import numpy as np
import proxsuite
import pytest

from redmax_ros.core.solvers import active_set


def _qp(rng, n=30, m=3, p=60):
    B = rng.normal(size=(n, n))
    A = B @ B.T + n * np.eye(n)
    b = rng.normal(size=n) * 10
    G = rng.normal(size=(m, n))
    g = rng.normal(size=m)
    C = rng.normal(size=(p, n))
    v_free = np.linalg.solve(A, b)
    Cv = C @ v_free
    lo = Cv - rng.uniform(-0.3, 2.0, size=p)  # some rows violated by the free solution
    hi = np.full(p, 1e6)
    return A, b, G, g, C, lo, hi


def _proxsuite(A, b, G, g, C, lo, hi):
    qp = proxsuite.proxqp.dense.QP(len(b), len(g), len(lo))
    qp.settings.eps_abs, qp.settings.eps_rel, qp.settings.verbose = 1e-12, 0.0, False
    qp.init(A, -b, G, g, C, lo, hi)
    qp.solve()
    return np.array(qp.results.x)


def _kkt(A, b, G, g, C, lo, hi, r):
    """(stationarity, primal, dual sign, complementarity) residuals; convention A v = b - G^T lam - C^T mu."""
    stat = np.abs(A @ r.v - b + G.T @ r.lam + C.T @ r.mu).max() / np.abs(b).max()
    Cv = C @ r.v
    primal = max(np.abs(G @ r.v - g).max(), np.maximum(lo - Cv, 0).max(), np.maximum(Cv - hi, 0).max())
    at_lo = np.isclose(Cv, lo, atol=1e-9)
    dual = max(np.maximum(r.mu[at_lo], 0).max(initial=0), np.abs(r.mu[~at_lo & (Cv < hi - 1e-9)]).max(initial=0))
    return stat, primal, dual


@pytest.mark.parametrize("seed", range(8))
def test_solution_meets_kkt_and_matches_proxsuite(seed):
    rng = np.random.default_rng(seed)
    A, b, G, g, C, lo, hi = _qp(rng)
    r = active_set.solve(A, b, G, g, C, lo, hi)
    assert r is not None and len(r.active) > 0
    stat, primal, dual = _kkt(A, b, G, g, C, lo, hi, r)
    assert stat < 1e-12 and primal < 1e-10 and dual < 1e-10
    assert np.abs(r.v - _proxsuite(A, b, G, g, C, lo, hi)).max() < 1e-7


def test_dependent_rows_are_left_out_and_hold():
    """Each row twice (a capsule pair's witness row and its end row): the Schur complement of both would be
    singular; the copy is left out, satisfied at the solution, and the answer is that of the single rows."""
    rng = np.random.default_rng(11)
    A, b, G, g, C, lo, hi = _qp(rng)
    one = active_set.solve(A, b, G, g, C, lo, hi)
    C2, lo2, hi2 = np.vstack([C, C * (1 + 1e-13)]), np.concatenate([lo, lo]), np.concatenate([hi, hi])
    two = active_set.solve(A, b, G, g, C2, lo2, hi2)
    assert two is not None
    assert np.abs(two.v - one.v).max() < 1e-9
    assert (C2 @ two.v >= lo2 - 1e-9).all()


def test_warm_start_gives_the_same_solution():
    rng = np.random.default_rng(5)
    A, b, G, g, C, lo, hi = _qp(rng)
    cold = active_set.solve(A, b, G, g, C, lo, hi)
    right = active_set.solve(A, b, G, g, C, lo, hi, warm=cold.active)
    wrong = active_set.solve(A, b, G, g, C, lo, hi, warm=[(i, True) for i in range(0, len(lo), 3)])
    assert right.iterations == 1
    for r in (right, wrong):
        assert np.abs(r.v - cold.v).max() < 1e-10 and r.active == cold.active


def test_infeasible_rows_give_up():
    """v_0 >= 1 and -v_0 >= 1 cannot both hold: no solution, None (the caller reports ProxSuite's verdict)."""
    n = 4
    C = np.zeros((2, n))
    C[0, 0], C[1, 0] = 1.0, -1.0
    r = active_set.solve(np.eye(n), np.zeros(n), np.zeros((0, n)), np.zeros(0), C, np.ones(2), np.full(2, 1e6))
    assert r is None
