"""The springs' cross-body LHS terms (dynamics/tree_forces.spring_cross_lower_into, the compiled step's call with
the Data's scratch): against the dense sum over springs of J_a^T C J_b + J_b^T C^T J_a on random trees, and on
reused or garbage-filled scratch bit for bit what the allocating spring_cross_lower_kernel gives."""
from __future__ import annotations

import numpy as np
import pytest

from redmax_ros.core.dynamics.tree_forces import (all_support_runs, spring_cross_iwork_size, spring_cross_lower_into,
                                                  spring_cross_lower_kernel, spring_cross_slots)


def _random_tree(rng, nj):
    """parents, idx_v, nv_j of a random tree in depth-first order (joint 0 the world), 1-3 DOFs a joint."""
    children = {0: []}
    for j in range(1, nj):
        p = int(rng.integers(0, j))
        children.setdefault(p, []).append(j)
        children[j] = []
    order, stack = [], [0]
    while stack:  # depth-first renumbering, as Pinocchio orders joints
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children[j]))
    new = {old: k for k, old in enumerate(order)}
    parents = np.zeros(nj, np.int64)
    for old in order[1:]:
        for c in children[old]:
            parents[new[c]] = new[old]
    nv_j = np.concatenate([[0], rng.integers(1, 4, nj - 1)]).astype(np.int64)
    idx_v = np.concatenate([[0, 0], np.cumsum(nv_j[1:])[:-1]]).astype(np.int64)  # joint 0: the world
    return parents, idx_v, nv_j


def _support(parents, idx_v, nv_j, j):
    cols = []
    while j > 0:
        cols.extend(range(idx_v[j], idx_v[j] + nv_j[j]))
        j = parents[j]
    return cols


def _point_jacobian(parents, idx_v, nv_j, St, j, x):
    """J (3, nv) of a point x (world) on joint j's body: column c = v_c + w_c x x for S_c = (v_c, w_c)."""
    J = np.zeros((3, St.shape[0]))
    for c in _support(parents, idx_v, nv_j, j):
        J[:, c] = St[c, :3] + np.cross(St[c, 3:], x)
    return J


def _springs(rng, nj, P):
    ja, jb = rng.integers(0, nj, P), rng.integers(0, nj, P)
    ja[0], jb[0] = 0, max(1, nj - 1)  # one to the world and one within a body: no cross terms
    ja[1] = jb[1] = max(1, nj // 2)
    return ja.astype(np.int64), rng.standard_normal((P, 3)), jb.astype(np.int64), rng.standard_normal((P, 3)), \
        rng.standard_normal((P, 3, 3))


@pytest.mark.parametrize("seed", range(4))
def test_cross_terms_are_the_dense_sum_over_springs(seed):
    rng = np.random.default_rng(seed)
    nj, P = 9 + seed, 7
    parents, idx_v, nv_j = _random_tree(rng, nj)
    nv = int(nv_j.sum())
    St = rng.standard_normal((nv, 6))
    ja, pa, jb, pb, C = _springs(rng, nj, P)
    A0 = rng.standard_normal((nv, nv))
    N = np.zeros((nv, nv))
    for s in range(P):
        if ja[s] == 0 or jb[s] == 0 or ja[s] == jb[s]:
            continue
        Ja = _point_jacobian(parents, idx_v, nv_j, St, ja[s], pa[s])
        Jb = _point_jacobian(parents, idx_v, nv_j, St, jb[s], pb[s])
        N += Ja.T @ C[s] @ Jb + Jb.T @ C[s].T @ Ja
    A = A0.copy()
    spring_cross_lower_kernel(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A)
    lower = np.tril_indices(nv)
    np.testing.assert_allclose(A[lower], (A0 - N)[lower], rtol=0, atol=1e-12 * (1 + np.abs(N).max()))
    upper = np.triu_indices(nv, 1)
    assert np.array_equal(A[upper], A0[upper])  # only the lower triangle is written


def test_reused_or_garbage_scratch_gives_the_allocating_kernels_bits():
    rng = np.random.default_rng(11)
    nj, P = 14, 9
    parents, idx_v, nv_j = _random_tree(rng, nj)
    nv = int(nv_j.sum())
    St = rng.standard_normal((nv, 6))
    ja, pa, jb, pb, C = _springs(rng, nj, P)
    A0 = rng.standard_normal((nv, nv))
    ref = A0.copy()
    spring_cross_lower_kernel(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, ref)
    ptr, runs = all_support_runs(parents, idx_v, nv_j)
    cap = spring_cross_slots(parents)
    W = np.full((cap, 6, nv), np.nan)
    iwork = np.full(spring_cross_iwork_size(nj, P, cap), -5, np.int64)
    StT, Q = np.full((6, nv), np.nan), np.full((6, 6), np.nan)
    for _ in range(2):  # garbage first, then what the first call left
        A = A0.copy()
        spring_cross_lower_into(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A, ptr, runs, W, iwork, StT, Q)
        assert np.array_equal(A, ref)
