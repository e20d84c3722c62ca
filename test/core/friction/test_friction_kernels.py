"""The compiled kernels of the staggered solve against their dense NumPy definitions on random data:
condense.spd_inverse (A^-1 from the Cholesky factor, L^-1 by rows, or from the LTL factor of a tree's
mass matrix), condense.fixed_row_weights (over the
rows' nonzeros), condense.condense (sparse products by rows of the transposed factors, lambda map
LamX = S^-1 G A^-1 RX^T) and the joint multipliers and bounds of staggered.staggered_kernel (Eq. 16 as axpys
over the implicit points, four-way sums)."""
import numpy as np
import pytest

from redmax_ros.core.friction.condense import (FIXED_ROW, ancestor_chains, arena_size, condense, condense_into,
                                              dense_spd_inverse, fixed_row_weights,
                                              pattern_of, spd_inverse, tree_inverse)
from redmax_ros.core.friction.bisp import dense_wrench_map
from redmax_ros.core.friction.contact import distinct_operators
from redmax_ros.core.friction.staggered import cone_excess, loop_scratch_size, loop_state, staggered_kernel


def _spd(rng, n):
    B = rng.standard_normal((n, n))
    return B @ B.T + n * np.eye(n)


def _sparse_rows(rng, r, n, per_row):
    R = np.zeros((r, n))
    for i in range(r):
        R[i, rng.choice(n, size=per_row, replace=False)] = rng.standard_normal(per_row)
    return R


@pytest.mark.parametrize("n", [1, 7, 28])
def test_spd_inverse_is_the_inverse(n):
    A = _spd(np.random.default_rng(n), n)
    Ainv, ok = spd_inverse(A)
    assert ok
    assert np.abs(Ainv - np.linalg.inv(A)).max() <= 1e-12 * np.abs(np.linalg.inv(A)).max()
    assert not spd_inverse(-A)[1]


def _tree_mass_matrix(rng, parents):
    """A tree's joint-space inertia in depth-first DOF order: sum over bodies of J_i^T M_i J_i with body i
    moved by its own DOF and its ancestors' (branch-induced sparsity), plus a diagonal (armature)."""
    n = len(parents)
    A = np.diag(rng.uniform(0.1, 1.0, n))
    for i in range(n):
        chain = [i]
        while parents[chain[-1]] >= 0:
            chain.append(parents[chain[-1]])
        J = np.zeros((6, n))
        J[:, chain] = rng.standard_normal((6, len(chain)))
        B = rng.standard_normal((6, 6))
        A += J.T @ (B @ B.T + np.eye(6)) @ J
    return A


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tree_inverse_of_a_tree_mass_matrix_is_the_inverse(seed):
    """A walker-like tree (a 3-DOF root, legs of 1-3 DOFs on it): ancestor_chains finds the tree, the LTL
    inverse (RBDA Table 6.3) equals the inverse to round-off, and spd_inverse takes it."""
    rng = np.random.default_rng(seed)
    parents, k = [-1, 0, 1], 3
    for leg in range(14):
        p = int(rng.integers(0, 3))
        for _ in range(int(rng.integers(1, 4))):
            parents.append(p)
            p = k
            k += 1
    A = _tree_mass_matrix(rng, parents)
    lam, work = ancestor_chains(A)
    assert work >= 0 and 6 * work < len(A) ** 3
    ref = np.linalg.inv(A)
    for inv in (tree_inverse(A, lam), spd_inverse(A), dense_spd_inverse(A)):
        assert inv[1] and np.abs(inv[0] - ref).max() <= 1e-12 * np.abs(ref).max()
    assert not tree_inverse(-A, lam)[1] and not spd_inverse(-A)[1]


def test_a_pattern_off_the_ancestor_chains_takes_the_dense_inverse():
    """A nonzero that is not on its row's chain (a coupling between two branches) is no tree: work -1,
    and spd_inverse still returns the inverse (the dense Cholesky path)."""
    rng = np.random.default_rng(5)
    A = _tree_mass_matrix(rng, [-1, 0, 1, 1, 3])  # DOF 4's chain is 3, 1, 0: 2 is not on it
    A[4, 2] = A[2, 4] = 0.3
    assert ancestor_chains(A)[1] == -1
    Ainv, ok = spd_inverse(A)
    assert ok and np.abs(Ainv - np.linalg.inv(A)).max() <= 1e-12 * np.abs(np.linalg.inv(A)).max()


def test_fixed_row_weights_use_the_unconstrained_mobility_of_fixed_rows_only():
    rng = np.random.default_rng(3)
    n = 12
    A = _spd(rng, n)
    Ainv = np.linalg.inv(A)
    T = _sparse_rows(rng, 6, n, 3)
    u = np.einsum("ia,ac,ic->i", T, Ainv, T)
    wT = np.array([0.0, 1e-20, 0.5 * u[2], u[3], 1e-3 * u[4], FIXED_ROW * u[5] * 0.5])
    out = wT.copy()
    fixed_row_weights(out, T, Ainv, *pattern_of(T))
    fixed = np.array([True, True, False, False, False, True])
    assert np.allclose(out[fixed], u[fixed], rtol=1e-14, atol=0.0)
    assert np.array_equal(out[~fixed], wT[~fixed])


@pytest.mark.parametrize("m", [0, 5])
def test_condense_matches_the_dense_schur_complement(m):
    rng = np.random.default_rng(10 + m)
    n, nu, nf = 14, 3, 9
    A, b = _spd(rng, n), rng.standard_normal(n)
    G, g = _sparse_rows(rng, m, n, 4), rng.standard_normal(m)
    RX = _sparse_rows(rng, nu + nf, n, 3)
    status, v0, PX, W_U, X_UT, X_TU, W_T, U_v0, T_v0, wU, wT, lam0, LamX = condense(A, b, G, g, RX, nu)
    assert status == 0
    Ainv = np.linalg.inv(A)
    if m:
        Y = Ainv @ G.T
        Sinv = np.linalg.inv(G @ Y)
        P = Ainv - Y @ Sinv @ Y.T
        v_ref = P @ b + Y @ (Sinv @ g)
        assert np.allclose(lam0, Sinv @ (Y.T @ b - g), rtol=0, atol=1e-12 * np.abs(lam0).max())
        assert np.allclose(LamX, Sinv @ Y.T @ RX.T, rtol=0, atol=1e-12 * np.abs(LamX).max())
    else:
        P, v_ref = Ainv, Ainv @ b
    W = RX @ P @ RX.T
    U, Tr = RX[:nu], -RX[nu:]

    def close(a, ref):
        return np.abs(a - ref).max() <= 1e-12 * max(1.0, np.abs(ref).max())
    assert close(v0, v_ref) and close(PX, P @ RX.T)
    assert close(W_U, W[:nu, :nu]) and close(W_T, W[nu:, nu:]) and close(X_UT, -W[:nu, nu:])
    assert np.array_equal(X_TU, X_UT.T) and close(U_v0, U @ v0) and close(T_v0, Tr @ v0)


@pytest.mark.parametrize("m", [0, 5])
def test_condense_on_a_reused_or_short_arena_gives_the_same_numbers(m):
    """condense_into (the compiled step's call: every array a view of an arena it is handed each step): on a
    fresh arena, on the same arena again after another system, and on one too short (its takes past the end
    allocate), bit for bit what condense gives."""
    rng = np.random.default_rng(20 + m)
    n, nu, nf = 14, 3, 9
    A, b = _spd(rng, n), rng.standard_normal(n)
    G, g = _sparse_rows(rng, m, n, 4), rng.standard_normal(m)
    RX = _sparse_rows(rng, nu + nf, n, 3)
    ref = condense(A, b, G, g, RX, nu)
    nfl, nin = arena_size(n, m, nu + nf)
    buf, ibuf, off = np.full(nfl, np.nan), np.full(nin, -7, dtype=np.int64), np.zeros(2, dtype=np.int64)

    def same(out):
        assert out[0] == ref[0]
        for a, r in zip(out[1:], ref[1:]):
            assert a.shape == r.shape and np.array_equal(a, r)
    same(condense_into(A, b, G, g, RX, nu, buf, ibuf, off))
    assert off[0] <= nfl and off[1] <= nin  # arena_size bounds what it took
    A2 = _spd(rng, n)
    condense_into(A2, b, G, g, RX, nu, buf, ibuf, off)  # another system on the same arena
    same(condense_into(A, b, G, g, RX, nu, buf, ibuf, off))
    same(condense_into(A, b, G, g, RX, nu, np.empty(nfl // 3), np.empty(nin // 3, dtype=np.int64),
                       np.zeros(2, dtype=np.int64)))


@pytest.mark.parametrize("kmax", [7, 8])
def test_joint_multipliers_and_bounds_of_the_loop_are_eq_16_at_its_last_iterate(kmax):
    """alpha_j = h L_j (W0 + Wx x)_j and the joint bound mu_j sum_k |alpha_jk| at the returned x = [alpha; beta]
    (the loop leaves after the contact and BISP stages, so the returned bounds are those of its iterate)."""
    rng = np.random.default_rng(7)
    nc, nj, h = 2, 5, 1e-3
    nu, nf = nc, 2 * nc + nj
    nx = nu + nf
    R = rng.standard_normal((nx, nx + 4))
    W = R @ R.T / nx
    W_U, W_T = W[:nu, :nu].copy(), W[nu:, nu:].copy()
    X_UT = -W[:nu, nu:].copy()
    U_v0, T_v0 = rng.standard_normal(nu) - 1.0, rng.standard_normal(nf)
    lo_U = np.zeros(nu)
    mu_g, bound_mu = np.full(nc, 0.8), np.full(nj, 0.3)
    a0, Mx = rng.standard_normal(6 * nj) * 50.0, rng.standard_normal((6 * nj, nx)) * 50.0
    L = rng.standard_normal((nj, kmax, 6))
    L[3] = L[1]  # joints of one shape share their operator (contact.distinct_operators)
    ops = distinct_operators(L)
    assert ops["L_ops"].shape == (nj - 1, 6, kmax) and ops["L_of"][3] == ops["L_of"][1]
    assert all(ops["L_ops"][ops["L_of"][j]].T.tobytes() == L[j].tobytes() for j in range(nj))
    wU, wT = np.diag(W_U).copy(), np.diag(W_T).copy()
    sbuf, sint = loop_state(nu, nf, 5, nj * kmax)
    alpha, beta, bound, al, it, conv, resid, paused = staggered_kernel(
        W_U, X_UT, X_UT.T.copy(), U_v0, lo_U, W_T, T_v0, mu_g, a0, dense_wrench_map(Mx), ops["L_ops"], ops["L_of"], h,
        bound_mu, kmax, True, wU, wT, 1e-6, 30,
        5, np.zeros(nu), np.zeros(nf), sbuf, sint, np.inf, np.full(loop_scratch_size(nu, nf, 5, len(a0)), np.nan))
    assert not paused and it >= 2
    # converged: the bounds stopped moving and the impulses lie in them, both to the tolerance in velocity
    assert conv and resid <= 1e-6 and cone_excess(beta, bound, wT) <= 1e-6
    x = np.concatenate([alpha, beta])
    al_ref = h * np.einsum("jkl,jl->jk", L, (a0 + Mx @ x).reshape(nj, 6)).reshape(-1)
    assert np.abs(al - al_ref).max() <= 1e-12 * np.abs(al_ref).max()
    assert np.allclose(bound[:2 * nc], np.repeat(mu_g * alpha, 2), rtol=1e-15, atol=0.0)
    assert np.allclose(bound[2 * nc:], bound_mu * np.abs(al_ref).reshape(nj, kmax).sum(1), rtol=1e-12, atol=0.0)
