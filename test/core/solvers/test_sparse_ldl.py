"""Sparse LDL^T with a fixed pattern (solvers/sparse_ldl.py) on the STARFISH mesh block, the mesh with a dense
skeleton block, and random SPD grid matrices (sparse_ldl_matrices.py): solutions against SuperLU, inertia of
indefinite matrices, fixed DOFs, singular matrices, several right-hand sides, refactorisation."""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

import sparse_ldl_matrices as mats
from redmax_ros.core.errors import StepError
from redmax_ros.core.solvers import sparse_ldl

MATRICES = {"starfish": mats.starfish_block, "starfish+skeleton": mats.starfish_coupled,
            "starfish reduced": mats.starfish_reduced, "grid 300": lambda: mats.grid_spd(300),
            "grid 1000": lambda: mats.grid_spd(1000), "grid 3000": lambda: mats.grid_spd(3000)}


def factorised(A, ordering="mindeg"):
    sym = sparse_ldl.analyse(A.indptr, A.indices, A.shape[0], ordering)
    return sym, sparse_ldl.factor(sym, A.data)


def rel_residual(A, x, b):
    return np.linalg.norm(A @ x - b) / np.linalg.norm(b)


@pytest.mark.parametrize("name", MATRICES)
def test_solution_matches_superlu(name):
    A = MATRICES[name]()
    b = np.random.default_rng(1).normal(size=A.shape[0])
    sym, num = factorised(A)
    x = sparse_ldl.solve(sym, num, b)
    ref = spsolve(A.tocsc(), b)
    assert rel_residual(A, x, b) <= 1e-12
    assert np.linalg.norm(x - ref) <= 1e-10 * np.linalg.norm(ref)
    assert num.n_negative == 0  # SPD: every pivot positive


@pytest.mark.parametrize("name", ["starfish", "starfish+skeleton", "grid 1000"])
def test_orderings_agree_and_minimum_degree_fills_least(name):
    A = MATRICES[name]()
    b = np.random.default_rng(2).normal(size=A.shape[0])
    out = {o: factorised(A, o) for o in sparse_ldl.ORDERINGS}
    xs = {o: sparse_ldl.solve(*out[o], b) for o in out}
    for o in out:
        assert rel_residual(A, xs[o], b) <= 1e-12
    nnz = {o: out[o][0].nnz_l for o in out}
    assert nnz["mindeg"] <= min(nnz["rcm"], nnz["natural"])


def test_symbolic_structure_is_consistent():
    """Column counts, supernode structures and the value map describe one factor: the pattern of L computed
    from the dense factor of P A P^T (Cholesky, no cancellation in an SPD random-valued matrix) is the
    analysed one."""
    A = mats.grid_spd(300)
    sym, num = factorised(A)
    P = A.toarray()[np.ix_(sym.perm, sym.perm)]
    Ld = np.linalg.cholesky(P)
    pattern = np.abs(np.tril(Ld, -1)) > 1e-14 * np.abs(Ld).max()
    assert np.array_equal(pattern.sum(axis=0), sym.colcount)
    assert sym.nnz_l == int(pattern.sum())
    d = num.diagonal(sym)
    assert np.allclose(d, np.diag(Ld) ** 2, rtol=1e-12)


def test_indefinite_matrix_solves_and_counts_negative_pivots():
    """A_d - s I with s in a gap of the spectrum: symmetric, indefinite, nonsingular; the number of negative
    pivots is the number of eigenvalues below s (Sylvester's law of inertia)."""
    A = mats.starfish_block()
    ev = np.linalg.eigvalsh(A.toarray())
    k = 100 + int(np.argmax(np.diff(ev[100:300])))  # the widest gap among eigenvalues 100-300
    s = 0.5 * (ev[k] + ev[k + 1])
    K = mats.add_diagonal(A, -s)
    b = np.random.default_rng(3).normal(size=A.shape[0])
    sym, num = factorised(K)
    x = sparse_ldl.solve(sym, num, b)
    assert rel_residual(K, x, b) <= 1e-10
    assert num.n_negative == k + 1


def fixed_dofs(A, dofs):
    """A with the rows and columns of ``dofs`` overwritten by the identity (pattern unchanged)."""
    F = sp.csr_matrix(A, copy=True)
    fixed = np.zeros(A.shape[0], bool)
    fixed[dofs] = True
    rows = np.repeat(np.arange(A.shape[0]), np.diff(F.indptr))
    hit = fixed[rows] | fixed[F.indices]
    F.data[hit] = np.where(rows[hit] == F.indices[hit], 1.0, 0.0)
    return F


@pytest.mark.parametrize("name", ["starfish", "starfish reduced"])
def test_identity_rows_give_exactly_the_fixed_values(name):
    """Floor contact: DOFs fixed for a step by the identity in their rows and columns come out exactly as the
    right-hand side gives them; the others solve the system of the free DOFs."""
    A = MATRICES[name]()
    rng = np.random.default_rng(4)
    dofs = rng.choice(A.shape[0] - mats.N_SKELETON, size=40, replace=False)
    F = fixed_dofs(A, dofs)
    b = rng.normal(size=A.shape[0])
    sym = sparse_ldl.analyse(A.indptr, A.indices, A.shape[0])  # the pattern's analysis, shared
    num = sparse_ldl.factor(sym, F.data)
    x = sparse_ldl.solve(sym, num, b)
    assert np.array_equal(x[dofs], b[dofs])
    free = np.setdiff1d(np.arange(A.shape[0]), dofs)
    ref = spsolve(A.tocsr()[free][:, free].tocsc(), b[free])  # the fixed columns are zero in the free rows
    assert np.linalg.norm(x[free] - ref) <= 1e-10 * np.linalg.norm(ref)


def test_zero_pivot_raises_step_error_naming_it():
    A = mats.grid_spd(300)
    dof = 123
    Z = fixed_dofs(A, [dof])
    Z.data[(np.repeat(np.arange(300), np.diff(Z.indptr)) == dof) & (Z.indices == dof)] = 0.0
    sym = sparse_ldl.analyse(A.indptr, A.indices, 300)
    with pytest.raises(StepError, match=rf"pivot {sym.iperm[dof]} \(row {dof} of the matrix\)"):
        sparse_ldl.factor(sym, Z.data)


def test_singular_matrix_raises_step_error():
    """The graph Laplacian of the grid (rows summing to 0) is singular: the last pivot is round-off."""
    A = mats.grid_spd(300)
    L = sp.csr_matrix(A, copy=True)
    rows = np.repeat(np.arange(300), np.diff(L.indptr))
    off = rows != L.indices
    L.data[off] = -1.0
    L.data[~off] = 0.0
    L.data[~off] = -np.asarray(sp.csr_matrix((L.data * off, L.indices, L.indptr)).sum(axis=1)).ravel()
    assert abs(np.linalg.eigvalsh(L.toarray())[0]) < 1e-12
    sym = sparse_ldl.analyse(L.indptr, L.indices, 300)
    with pytest.raises(StepError, match=r"pivot \d+ \(row \d+ of the matrix\)"):
        sparse_ldl.factor(sym, L.data)


@pytest.mark.parametrize("name", ["starfish+skeleton", "grid 1000"])
def test_multiple_right_hand_sides(name):
    A = MATRICES[name]()
    B = np.random.default_rng(5).normal(size=(A.shape[0], 36))
    sym, num = factorised(A)
    X = sparse_ldl.solve(sym, num, B)
    assert X.shape == B.shape
    cols = np.column_stack([sparse_ldl.solve(sym, num, B[:, j]) for j in range(36)])
    assert np.linalg.norm(X - cols) <= 1e-13 * np.linalg.norm(cols)
    assert np.linalg.norm(A @ X - B) <= 1e-12 * np.linalg.norm(B)


def test_refactorisation_in_place_is_consistent():
    """New values on the same pattern, factorised into the same LDLNumeric: the same factor as a fresh one,
    in the same arrays."""
    A = mats.starfish_coupled()
    rng = np.random.default_rng(6)
    A2 = mats.symmetrised(sp.csr_matrix((A.data * rng.uniform(0.9, 1.1, size=A.nnz), A.indices, A.indptr)))
    A2 = mats.add_diagonal(A2, 1.0)
    assert np.array_equal(A2.indices, A.indices) and np.array_equal(A2.indptr, A.indptr)
    sym, num = factorised(A)
    values, buf = num.values, num.buf
    b = rng.normal(size=A.shape[0])
    x1 = sparse_ldl.solve(sym, num, b)
    out = sparse_ldl.factor(sym, A2.data, out=num)
    assert out is num and num.values is values and num.buf is buf
    x2 = sparse_ldl.solve(sym, num, b)
    fresh = sparse_ldl.factor(sym, A2.data)
    assert np.array_equal(num.values[sym.diag], fresh.values[sym.diag])
    assert np.array_equal(x2, sparse_ldl.solve(sym, fresh, b))
    assert rel_residual(A2, x2, b) <= 1e-12 and rel_residual(A, x1, b) <= 1e-12
    sparse_ldl.factor(sym, A.data, out=num)
    assert np.array_equal(sparse_ldl.solve(sym, num, b), x1)


def test_one_triangle_or_duplicates_give_the_same_factor():
    A = mats.starfish_block()
    b = np.random.default_rng(7).normal(size=A.shape[0])
    sym, num = factorised(A)
    x = sparse_ldl.solve(sym, num, b)
    lower = sp.tril(A, format="csr")
    lower.sort_indices()
    sym_l, num_l = factorised(lower)
    assert np.array_equal(sym_l.perm, sym.perm)
    assert np.array_equal(sparse_ldl.solve(sym_l, num_l, b), x)
    C = sp.coo_matrix(A)  # every entry split in two halves: duplicates, summed by the factorisation
    order = np.argsort(np.r_[C.row, C.row], kind="stable")
    D = sp.csr_matrix((np.r_[0.5 * C.data, 0.5 * C.data][order], np.r_[C.col, C.col][order],
                       np.r_[0, np.cumsum(2 * np.diff(A.indptr))]), shape=A.shape)
    assert not D.has_canonical_format
    sym_d, num_d = factorised(D)
    assert np.linalg.norm(sparse_ldl.solve(sym_d, num_d, b) - x) <= 1e-13 * np.linalg.norm(x)


def test_invalid_inputs_are_rejected():
    A = mats.grid_spd(300)
    with pytest.raises(ValueError, match="permutation"):
        sparse_ldl.analyse(A.indptr, A.indices, 300, np.zeros(300, int))
    with pytest.raises(ValueError, match="ordering"):
        sparse_ldl.analyse(A.indptr, A.indices, 300, "amd")
    no_diag = sp.csr_matrix(A - sp.diags(A.diagonal()))
    no_diag.eliminate_zeros()
    with pytest.raises(ValueError, match="diagonal"):
        sparse_ldl.analyse(no_diag.indptr, no_diag.indices, 300)
    sym = sparse_ldl.analyse(A.indptr, A.indices, 300)
    with pytest.raises(ValueError, match="data"):
        sparse_ldl.factor(sym, A.data[:-1])
    num = sparse_ldl.factor(sym, A.data)
    with pytest.raises(ValueError, match="shape"):
        sparse_ldl.solve(sym, num, np.ones(299))
