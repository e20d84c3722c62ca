"""Test matrices of solvers/sparse_ldl.py (test_sparse_ldl.py; run this file to print the measured figures of
docs/solvers.md, "Sparse LDL^T for the coupled deformable step"):

(a) ``starfish_block``: A_d = M_d + h D_d + h^2 K_d of the STARFISH mesh (222 vertices, 666 DOFs) at rest;
(b) ``starfish_coupled``: (a) with a dense 36 x 36 skeleton block appended last and dense coupling between
    those 36 DOFs and the 3 DOFs of 40 random vertices, made SPD by a multiple of the identity;
    ``starfish_reduced``: the shape issue 15's restructured step will have (474 unknowns): the 76 attached
    vertices removed, the 36 skeleton DOFs last, coupled densely to the vertices next to attached ones;
(c) ``grid_spd``: random SPD matrices with the pattern of a 2-D grid Laplacian (5-point stencil).
All returned as scipy CSR with both triangles stored, symmetric to round-off (exactly symmetric values).
"""
from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp

N_SKELETON = 36  # skeleton DOFs of the STARFISH (free core 6 + 5 arms x 6)


@functools.lru_cache(maxsize=1)
def _starfish():
    from redmax_ros.core.simulator import Simulator  # heavy: loaded once, on first use
    from redmax_ros.core.step.deformable_stages import deform_state

    sim = Simulator.load("starfish")
    dm = sim.deformables
    ds = deform_state(dm, sim.state)
    x = ds.x + np.random.default_rng(7).normal(scale=1e-3, size=ds.x.shape)  # generic values (none exactly 0)
    A, _ = dm.assemble(x, ds.v, sim.dt)
    return vertex_pattern(sp.csr_matrix(A)), np.asarray(dm.attach.vertex)


def vertex_pattern(A) -> sp.csr_matrix:
    """A with the full 3 x 3 block of every pair of vertices that share an element stored (explicit zeros
    where A's value is 0): the pattern of A_d at any deformation."""
    rows, cols = np.nonzero((abs(A) + abs(A).T).toarray().reshape(A.shape[0] // 3, 3, -1, 3).any(axis=(1, 3)))
    r = (3 * rows[:, None, None] + np.arange(3)[None, :, None] + 0 * np.arange(3)[None, None, :]).ravel()
    c = (3 * cols[:, None, None] + 0 * np.arange(3)[None, :, None] + np.arange(3)[None, None, :]).ravel()
    return coo_to_csr(r, c, np.asarray(A[r, c]).ravel(), A.shape[0])


def coo_to_csr(r, c, v, n) -> sp.csr_matrix:
    """CSR (n,n) of (r, c, v) triplets, duplicates summed, explicit zeros kept, indices sorted."""
    S = sp.coo_matrix((v, (r, c)), shape=(n, n)).tocsr()
    S.sum_duplicates()
    S.sort_indices()
    return S


def symmetrised(A) -> sp.csr_matrix:
    """(A + A^T)/2 in CSR with sorted indices (the values exactly symmetric, the pattern that of A + A^T,
    explicit zeros kept)."""
    A = sp.coo_matrix(A)
    return coo_to_csr(np.r_[A.row, A.col], np.r_[A.col, A.row], np.r_[A.data, A.data] * 0.5, A.shape[0])


def add_diagonal(A, d) -> sp.csr_matrix:
    """A + diag(d) (every diagonal entry of A stored), pattern unchanged."""
    A = sp.csr_matrix(A, copy=True)
    n = A.shape[0]
    for i in range(n):
        p = A.indptr[i] + np.flatnonzero(A.indices[A.indptr[i]:A.indptr[i + 1]] == i)[0]
        A.data[p] += d[i] if np.ndim(d) else d
    return A


def starfish_block() -> sp.csr_matrix:
    """(a) the STARFISH mesh's A_d (666 x 666, SPD)."""
    return symmetrised(_starfish()[0])


def with_skeleton(A, coupled_dofs, rng, n_skel=N_SKELETON) -> sp.csr_matrix:
    """A with ``n_skel`` DOFs appended last: a dense random block among them and dense random coupling to
    the DOFs ``coupled_dofs`` of A, then shifted by s I so that its smallest eigenvalue is A's (SPD)."""
    n = A.shape[0]
    scale = float(np.abs(A.diagonal()).max())
    S = rng.normal(size=(n_skel, n_skel)) * scale
    S = 0.5 * (S + S.T)
    C = np.zeros((n_skel, n))
    C[:, coupled_dofs] = rng.normal(size=(n_skel, len(coupled_dofs))) * scale
    A = sp.coo_matrix(A)
    cr, cc = np.nonzero(C)
    sr, sc = np.nonzero(np.ones_like(S))
    B = coo_to_csr(np.r_[A.row, n + cr, cc, n + sr], np.r_[A.col, cc, n + cr, n + sc],
                   np.r_[A.data, C[cr, cc], C[cr, cc], S[sr, sc]], n + n_skel)
    shift = np.linalg.eigvalsh(A.toarray())[0] - np.linalg.eigvalsh(B.toarray())[0]
    return add_diagonal(B, max(shift, 0.0))


def vertex_dofs(vertices) -> np.ndarray:
    return (3 * np.asarray(vertices, dtype=np.int64)[:, None] + np.arange(3)).ravel()


def starfish_coupled(seed=0, n_vertices=40) -> sp.csr_matrix:
    """(b) (a) + a dense 36 x 36 block last + dense coupling to ``n_vertices`` random vertices (702 x 702)."""
    A, _ = _starfish()
    rng = np.random.default_rng(seed)
    verts = rng.choice(A.shape[0] // 3, size=n_vertices, replace=False)
    return with_skeleton(symmetrised(A), vertex_dofs(verts), rng)


def starfish_reduced(seed=0) -> sp.csr_matrix:
    """The restructured step's shape: free vertices only (146 x 3 DOFs) + 36 skeleton DOFs last, coupled
    densely to every free vertex that shares an element with an attached one (474 x 474)."""
    A, attached = _starfish()
    nv = A.shape[0] // 3
    free = np.setdiff1d(np.arange(nv), attached)
    Av = sp.csr_matrix(A[vertex_dofs(attached)][:, vertex_dofs(free)])
    near = np.unique(Av.indices // 3)  # positions in ``free`` of vertices next to attached ones
    Af = symmetrised(A[vertex_dofs(free)][:, vertex_dofs(free)])
    return with_skeleton(Af, vertex_dofs(near), np.random.default_rng(seed))


def grid_spd(n, seed=0) -> sp.csr_matrix:
    """(c) an SPD matrix with the pattern of the 5-point Laplacian of an m1 x m2 grid (m1 m2 = n, m1 the
    largest divisor of n not above sqrt(n)): random off-diagonal values, the diagonal their absolute row
    sums plus a random positive margin (strictly diagonally dominant)."""
    m1 = max(d for d in range(1, int(np.sqrt(n)) + 1) if n % d == 0)
    m2 = n // m1
    rng = np.random.default_rng(seed)
    idx = np.arange(n).reshape(m1, m2)
    rows = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    cols = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    vals = rng.normal(size=len(rows))
    L = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    L = L + L.T
    d = np.asarray(abs(L).sum(axis=1)).ravel() + rng.uniform(0.1, 1.0, size=n)
    return add_diagonal(symmetrised(L + sp.diags(d)), 0.0)


def all_matrices() -> dict:
    """name -> CSR of every test matrix."""
    return {"a starfish A_d": starfish_block(), "b starfish + skeleton": starfish_coupled(),
            "b' starfish reduced": starfish_reduced(), "c grid 300": grid_spd(300),
            "c grid 1000": grid_spd(1000), "c grid 3000": grid_spd(3000)}


def cpu_time(f, repeats, inner=1) -> float:
    """Smallest CPU time (time.process_time) of ``inner`` calls of f over ``repeats`` runs, per call [s]."""
    import time

    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        for _ in range(inner):
            f()
        best = min(best, (time.process_time() - t) / inner)
    return best


def superlu_mmd(A) -> np.ndarray:
    """SuperLU's MMD(A^T + A) column ordering (new -> old), to compare minimum degree against."""
    from scipy.sparse.linalg import splu

    lu = splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    perm = np.empty(A.shape[0], np.int64)
    perm[lu.perm_c] = np.arange(A.shape[0])
    return perm


def measure():
    """The figures of docs/solvers.md: per test matrix and ordering nnz(L), multiply-adds, the analysis, the
    factorisation, one solve, factorisation + one solve, a solve with 36 right-hand sides (CPU time, the
    smallest of many runs) and SuperLU's factorisation (scipy splu, default options)."""
    from scipy.sparse.linalg import splu

    from redmax_ros.core.solvers import sparse_ldl

    rng = np.random.default_rng(1)
    for name, A in all_matrices().items():
        n = A.shape[0]
        b, B = rng.normal(size=n), rng.normal(size=(n, N_SKELETON))
        reps, inner = (30, 1) if n > 1500 else (300, 5)
        for ordering in (*sparse_ldl.ORDERINGS, superlu_mmd(A)):
            sym = sparse_ldl.analyse(A.indptr, A.indices, n, ordering)
            ta = cpu_time(lambda: sparse_ldl.analyse(A.indptr, A.indices, n, ordering), 5)
            num = sparse_ldl.factor(sym, A.data)
            tf = cpu_time(lambda: sparse_ldl.factor(sym, A.data, num), reps, inner)
            ts = cpu_time(lambda: sparse_ldl.solve(sym, num, b), reps, inner)
            tfs = cpu_time(lambda: (sparse_ldl.factor(sym, A.data, num), sparse_ldl.solve(sym, num, b)), reps, inner)
            tm = cpu_time(lambda: sparse_ldl.solve(sym, num, B), reps // 3)
            label = sym.ordering if sym.ordering != "given" else "SuperLU MMD"
            print(f"{name:22s} n={n:5d} nnz(A)={A.nnz:6d} {label:11s} nnz(L)={sym.nnz_l:7d} madds={sym.madds:8d} "
                  f"supernodes={sym.n_supernodes:5d} analyse {ta * 1e3:5.1f} ms  factor {tf * 1e6:7.1f} us  "
                  f"solve {ts * 1e6:6.1f} us  factor+solve {tfs * 1e6:7.1f} us  36 rhs {tm * 1e6:7.1f} us", flush=True)
        tl = cpu_time(lambda: splu(A.tocsc()), 5 if n > 1500 else 20)
        print(f"{name:22s} scipy splu (SuperLU, default options) factorisation {tl * 1e6:.0f} us", flush=True)


if __name__ == "__main__":
    measure()
