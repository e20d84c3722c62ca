"""solvers/kkt.kkt_solve_tree_into: the KKT solve on A's tree sparsity (Featherstone's L^T D L, RBDA section 6.5)
equals the dense bordered solve on branching trees (a hand-like wrist with five fingers, random trees), keeps
a dense A on the dense path, and follows a pattern that changes (a spring across two branches fills)."""
from __future__ import annotations

import numpy as np
import pytest

from redmax_ros.core.solvers.kkt import kkt_solve_tree_into, ltdl, tree_structure


def _tree_spd(rng, parent):
    """A symmetric positive definite matrix whose nonzeros are the ancestor pattern of ``parent``."""
    n = len(parent)
    anc = np.eye(n, dtype=bool)
    for k in range(n):
        j = parent[k]
        while j != -1:
            anc[k, j] = anc[j, k] = True
            j = parent[j]
    A = np.where(anc, rng.standard_normal((n, n)), 0.0)
    return (A + A.T) / 2 + 2 * n * np.eye(n), anc


def _hand_parents():
    """3 wrist DOFs in a chain, then four 3-DOF fingers and a 4-DOF thumb hanging from the last wrist DOF."""
    parent = [-1, 0, 1]
    for length in (3, 3, 3, 3, 4):
        parent += [2] + [len(parent) + i for i in range(length - 1)]
    return parent


def _solve(A, b, G, g, par=None, allowed=None):
    n, m = A.shape[0], G.shape[0]
    if par is None:
        par, allowed = np.full(n + 1, -2, np.int64), np.zeros((n, n), np.int64)
    v, lam = np.zeros(n), np.zeros(m)
    out = kkt_solve_tree_into(A, b, G, g, np.zeros((0, n)), np.zeros(0), np.zeros(0), par, allowed,
                              np.zeros((2, n), np.int64), np.zeros((n, n)), np.zeros((n, m)), np.zeros((m, m)), np.zeros((m, m)), np.zeros(n), v, lam)
    return out, v, lam, par, allowed


def _bordered(A, b, G, g):
    n, m = A.shape[0], G.shape[0]
    K = np.block([[A, G.T], [G, np.zeros((m, m))]])
    x = np.linalg.solve(K, np.concatenate([b, g]))
    return x[:n], x[n:]


def _rows_on_chains(rng, parent, tips):
    """Three rows per tip, nonzero on the tip's chain only (a fingertip's site Jacobian), and one joint row."""
    n = len(parent)
    rows = []
    for t in tips:
        chain = []
        j = t
        while j != -1:
            chain.append(j)
            j = parent[j]
        for _ in range(3):
            r = np.zeros(n)
            r[chain] = rng.standard_normal(len(chain))
            rows.append(r)
    e = np.zeros(n)
    e[0] = 1.0
    return np.array(rows + [e])


def test_hand_tree_solve_equals_the_bordered_solve_and_takes_the_tree_path():
    rng = np.random.default_rng(3)
    parent = _hand_parents()
    A, _ = _tree_spd(rng, parent)
    n = len(parent)
    tips = [k for k in range(n) if k not in parent]
    G = _rows_on_chains(rng, parent, tips)
    b, g = rng.standard_normal(n), rng.standard_normal(len(G))
    (status, ratio, viol, ok), v, lam, par, allowed = _solve(A, b, G, g)
    assert status == 0 and ok and par[n] == 1  # the tree path
    assert list(par[:n]) == parent  # no fill: the elimination tree is the kinematic tree
    v0, lam0 = _bordered(A, b, G, g)
    scale = max(np.abs(v0).max(), np.abs(lam0).max())
    assert np.abs(v - v0).max() <= 1e-12 * scale and np.abs(lam - lam0).max() <= 1e-12 * scale
    assert viol <= 1e-12 * scale


@pytest.mark.parametrize("seed", range(20))
def test_random_trees_and_dense_matrices(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 40))
    m = int(rng.integers(0, min(n, 10) + 1))
    if seed % 2:
        parent = [-1] + [int(rng.integers(-1, k)) for k in range(1, n)]
        A, _ = _tree_spd(rng, parent)
    else:
        B = rng.standard_normal((n, n))
        A = B @ B.T + n * np.eye(n)
    G, b, g = rng.standard_normal((m, n)), rng.standard_normal(n), rng.standard_normal(m)
    (status, _, _, _), v, lam, par, _ = _solve(A, b, G, g)
    v0, lam0 = _bordered(A, b, G, g)
    scale = max(np.abs(v0).max(), np.abs(lam0).max(initial=0.0))
    assert status == 0
    assert np.abs(v - v0).max() <= 1e-11 * scale and np.abs(lam - lam0).max(initial=0.0) <= 1e-11 * scale
    if seed % 2 == 0 and n > 4:
        assert par[n] == 0  # a dense matrix keeps the dense Cholesky


def test_a_new_coupling_across_branches_refills_the_structure():
    """A spring between two fingertips couples their chains: the stored structure no longer holds A, is made
    again (with fill), and the solve is still exact."""
    rng = np.random.default_rng(5)
    parent = _hand_parents()
    n = len(parent)
    A, _ = _tree_spd(rng, parent)
    G = np.zeros((0, n))
    b, g = rng.standard_normal(n), np.zeros(0)
    (_, _, _, _), _, _, par, allowed = _solve(A, b, G, g)
    assert par[n] == 1
    tips = [k for k in range(n) if k not in parent]
    A2 = A.copy()
    A2[tips[0], tips[1]] = A2[tips[1], tips[0]] = 0.7
    (status, _, _, _), v, _, par, allowed = _solve(A2, b, G, g, par, allowed)
    assert status == 0 and allowed[tips[1], tips[0]] == 1  # the earlier tip is now on the later one's chain
    assert np.abs(v - np.linalg.solve(A2, b)).max() <= 1e-12 * np.abs(v).max()


def test_ltdl_factor_reproduces_the_matrix_and_rejects_an_indefinite_one():
    rng = np.random.default_rng(9)
    parent = _hand_parents()
    n = len(parent)
    A, anc = _tree_spd(rng, parent)
    par, allowed = np.zeros(n + 1, np.int64), np.zeros((n, n), np.int64)
    tree_structure(A, par, allowed)
    H = np.zeros((n, n))
    assert ltdl(A, par, H)
    L = np.tril(H, -1) * np.tril(anc, -1) + np.eye(n)
    D = np.diag(np.diag(H))
    assert np.abs(L.T @ D @ L - A).max() <= 1e-13 * np.abs(A).max()
    A[n - 1, n - 1] = -1.0
    assert not ltdl(A, par, H)
