"""reduction.fill (the reduced coupled system with the attached vertices eliminated, deformable/reduction.py)
against its dense formula on random 3 x 3 block patterns, and build's check of the block pattern it needs."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from redmax_ros.core.deformable import reduction


def block_pattern(rng, n_vertices: int, density: float):
    """A random symmetric A_d (CSR, 3 x 3 vertex blocks, sorted columns, every diagonal block stored)."""
    adj = rng.random((n_vertices, n_vertices)) < density
    adj = adj | adj.T | np.eye(n_vertices, dtype=bool)
    A = sp.kron(sp.csr_matrix(adj.astype(float)), np.ones((3, 3)), format="csr")
    A.sort_indices()
    vals = rng.standard_normal(len(A.indices))
    M = sp.csr_matrix((vals, A.indices, A.indptr), shape=A.shape)
    M = (M + M.T).tocsr()  # same pattern (symmetric), symmetric values
    M.sort_indices()
    return M


def dense_reduced(A_d, b_d, attached, E, t, A_r, b_r):
    """[A_ff, A_fa E; E^T A_af, A_r + E^T A_aa E] and [b_f - A_fa t; b_r + E^T (b_a - A_aa t)] (dense)."""
    N = A_d.shape[0] // 3
    att = (3 * np.asarray(attached)[:, None] + np.arange(3)).ravel()
    free_v = np.setdiff1d(np.arange(N), attached)
    fr = (3 * free_v[:, None] + np.arange(3)).ravel()
    A = A_d.toarray()
    Aff, Afa, Aaa = A[np.ix_(fr, fr)], A[np.ix_(fr, att)], A[np.ix_(att, att)]
    top = np.hstack([Aff, Afa @ E])
    bot = np.hstack([E.T @ Afa.T, A_r + E.T @ Aaa @ E])
    return np.vstack([top, bot]), np.concatenate([b_d[fr] - Afa @ t, b_r + E.T @ (b_d[att] - Aaa @ t)])


@pytest.mark.parametrize("seed", range(6))
def test_fill_equals_the_dense_reduced_system(seed):
    rng = np.random.default_rng(seed)
    N, n_r = int(rng.integers(6, 30)), int(rng.integers(3, 12))
    A_d = block_pattern(rng, N, float(rng.uniform(0.1, 0.5)))
    attached = rng.choice(N, size=int(rng.integers(1, N // 2 + 1)), replace=False)
    support = rng.random((len(attached), n_r)) < 0.6
    support[rng.integers(len(attached))] = False  # a world point: E rows zero
    E = np.where(np.repeat(support, 3, axis=0), rng.standard_normal((3 * len(attached), n_r)), 0.0)
    t = rng.standard_normal(3 * len(attached))
    A_r = rng.standard_normal((n_r, n_r))
    A_r = A_r + A_r.T
    b_d, b_r = rng.standard_normal(3 * N), rng.standard_normal(n_r)
    red = reduction.build(A_d.indptr, A_d.indices, N, attached, n_r, support)
    data, b = np.empty(len(red.indices)), np.empty(red.n)
    reduction.fill(red, A_d.data, b_d, E, t, A_r, b_r, data, b, np.empty(reduction.work_shape(red)))
    A_ref, b_ref = dense_reduced(A_d, b_d, attached, E, t, A_r, b_r)
    A_got = sp.csr_matrix((data, red.indices, red.indptr), shape=(red.n, red.n)).toarray()
    scale = max(1.0, np.abs(A_ref).max())
    assert np.abs(A_got - A_ref).max() <= 1e-12 * scale
    assert np.abs(b - b_ref).max() <= 1e-12 * max(1.0, np.abs(b_ref).max())


def test_build_refuses_a_pattern_that_is_not_made_of_vertex_blocks():
    A_d = sp.kron(sp.eye(8), np.ones((3, 3)), format="lil")  # diagonal blocks, then one lone coupling entry:
    A_d[0, 3 * 7 + 1] = A_d[3 * 7 + 1, 0] = 1.0  # vertex 0's x row on attached vertex 7's y column
    A_d = A_d.tocsr()
    A_d.sort_indices()
    with pytest.raises(ValueError, match="3 x 3 vertex blocks"):
        reduction.build(A_d.indptr, A_d.indices, 8, np.array([7]), 4)
