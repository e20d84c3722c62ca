"""solvers/kkt.py: the small KKT solve of Eq. (6)/(7) by the Schur complement equals the dense solve of the
bordered system, for random SPD A and full-rank G; S is G A^-1 G^T; dependent rows show in the pivot ratio."""
from __future__ import annotations

import numpy as np
import pytest

from redmax_ros.core.solvers.kkt import kkt_solve

NO_C, NO_B = np.zeros((0, 1)), np.zeros(0)


def _system(rng, n, m):
    B = rng.standard_normal((n, n))
    A = B @ B.T + n * np.eye(n)
    return A, rng.standard_normal(n), rng.standard_normal((m, n)), rng.standard_normal(m)


@pytest.mark.parametrize("n,m", [(1, 0), (3, 2), (23, 16), (40, 39), (64, 20)])
def test_schur_solve_equals_the_bordered_dense_solve(n, m):
    rng = np.random.default_rng(n * 100 + m)
    A, b, G, g = _system(rng, n, m)
    status, v, lam, S, ratio, viol, ok = kkt_solve(A, b, G, g, np.zeros((0, n)), NO_B, NO_B)
    K = np.block([[A, G.T], [G, np.zeros((m, m))]])
    x = np.linalg.solve(K, np.concatenate([b, g]))
    scale = np.abs(x).max()
    assert status == 0 and ok
    assert np.abs(v - x[:n]).max() <= 1e-12 * scale
    assert np.abs(lam - x[n:]).max(initial=0.0) <= 1e-12 * scale
    assert viol <= 1e-12 * scale  # max|G v - g|
    if m:
        S_ref = G @ np.linalg.solve(A, G.T)
        assert np.abs(S - S_ref).max() <= 1e-13 * np.abs(S_ref).max()
        assert 0.0 < ratio <= 1.0


def test_a_repeated_row_shows_as_a_vanishing_pivot_ratio():
    rng = np.random.default_rng(7)
    A, b, G, g = _system(rng, 10, 4)
    G[3] = G[1]
    g[3] = g[1]
    status, *_, ratio, _, _ = kkt_solve(A, b, G, g, np.zeros((0, 10)), NO_B, NO_B)
    assert status == 2 or ratio < 1e-6  # Cholesky of S fails, or its pivot is at round-off
