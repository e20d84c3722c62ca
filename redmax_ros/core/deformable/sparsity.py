"""The fixed sparsity pattern of a deformable's step matrix A_d = M_d + h D_d + h^2 K_d (system.py) and the
compiled scatter of element blocks into its CSR ``data`` array.

Every element (tetrahedron, string segment) couples its k vertices with dense 3 x 3 blocks, and every vertex
has its diagonal block (the lumped mass), so A_d is a block matrix of 3 x 3 blocks whose block pattern is
fixed by the mesh: computed once (``block_pattern``), stored as a scalar CSR of shape (3n, 3n) with sorted
column indices. Row 3i + c of that CSR holds the blocks of vertex row i in increasing block column, 3 entries
each, so the entry (3i + c, 3j + d) of block k (row i, column j) sits at ``start[k] + c * stride[i] + d`` with
``stride[i] = 3 * (blocks in row i)``. Per step the element kernels (fem_kernels.py, string.py) add into
``data`` in place through these offsets: no COO triplets, no sort (Saad, Iterative Methods for Sparse Linear
Systems, 2nd ed. 2003, §3.4: CSR; the scatter is the usual finite-element assembly into a fixed pattern).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from redmax_ros.core.jit import njit_inline


@dataclass(frozen=True)
class BlockPattern:
    """The CSR pattern of a (3n, 3n) matrix of dense 3 x 3 blocks and the scatter offsets of its elements.

    indptr (3n + 1,) int32 and indices (nnz,) int32: scipy's CSR arrays (column indices sorted per row).
    blk (E, k, k) int64: data offset of entry (0, 0) of the block (row vertex elems[e, a], column vertex
    elems[e, b]) of element e. diag (n,) int64: data offset of entry (0, 0) of vertex i's diagonal block.
    stride (n,) int64: distance in ``data`` between the rows 3i + c and 3i + c + 1 of a block of vertex row i.
    """
    n: int
    indptr: np.ndarray
    indices: np.ndarray
    blk: np.ndarray
    diag: np.ndarray
    stride: np.ndarray

    @property
    def nnz(self) -> int:
        return len(self.indices)


def block_pattern(n: int, elems) -> BlockPattern:
    """The BlockPattern of n vertices coupled by the elements ``elems`` (E, k) (vertex indices): block (i, j)
    is present when i and j share an element or i == j."""
    elems = np.asarray(elems, dtype=np.int64).reshape(len(elems), -1)
    k = elems.shape[1]
    bi = np.repeat(elems, k, axis=1).ravel()  # row vertex of element block (a, b), a-major
    bj = np.tile(elems, (1, k)).ravel()
    keys = np.unique(np.concatenate([bi * n + bj, np.arange(n, dtype=np.int64) * (n + 1)]))
    rows, cols = keys // n, keys % n
    deg = np.bincount(rows, minlength=n)
    bptr = np.concatenate([[0], np.cumsum(deg)])
    stride = 3 * deg
    start = 9 * bptr[rows] + 3 * (np.arange(len(keys)) - bptr[rows])
    three = np.arange(3)
    at = start[:, None, None] + three[None, :, None] * stride[rows][:, None, None] + three[None, None, :]
    indices = np.empty(9 * len(keys), dtype=np.int32)
    indices[at.ravel()] = np.broadcast_to(3 * cols[:, None, None] + three[None, None, :], at.shape).ravel()
    indptr = np.append((9 * bptr[:-1, None] + three[None, :] * stride[:, None]).ravel(), 9 * len(keys))
    blk = start[np.searchsorted(keys, bi * n + bj)].reshape(len(elems), k, k)
    diag = start[np.searchsorted(keys, np.arange(n, dtype=np.int64) * (n + 1))]
    return BlockPattern(n, indptr.astype(np.int32), indices, blk, diag, stride.astype(np.int64))


def stack(patterns) -> tuple:
    """(indptr, indices, data offsets (P + 1,)) of the block-diagonal CSR of several BlockPatterns (vertex
    blocks of distinct deformables, in order): pattern p's data is data[offsets[p]:offsets[p + 1]]."""
    nnz = np.concatenate([[0], np.cumsum([p.nnz for p in patterns])]).astype(np.int64)
    first = np.concatenate([[0], np.cumsum([3 * p.n for p in patterns])])
    indptr = np.concatenate([p.indptr[:-1] + nnz[i] for i, p in enumerate(patterns)] + [[nnz[-1]]])
    indices = np.concatenate([p.indices + first[i] for i, p in enumerate(patterns)])
    return indptr.astype(np.int32), indices.astype(np.int32), nnz


@njit_inline
def add_block(data, start, stride, scale, K):
    """data[start + c * stride + d] += scale * K[c, d] for a 3 x 3 block K (C-contiguous; ``add_block_strided``)."""
    add_block_strided(data, start, stride, scale, K.reshape(9), 0, 1)


@njit_inline
def add_block_strided(data, start, stride, scale, K, at, step):
    """data[start + c * stride + d] += scale * K[at + (3 c + d) step]: a 3 x 3 block stored row-major in a flat
    array with entries ``step`` apart (start, stride >= 0; the positions unsigned, without numba's wrap-around
    test of each signed index: the starfish's fem_add 195 -> 183 us)."""
    for c in range(3):
        row = np.uint64(start) + np.uint64(c) * np.uint64(stride)
        k = np.uint64(at) + np.uint64(3 * c) * np.uint64(step)
        data[row] += scale * K[k]
        data[row + np.uint64(1)] += scale * K[k + np.uint64(step)]
        data[row + np.uint64(2)] += scale * K[k + np.uint64(2 * step)]


@njit_inline
def start_system(mass, v, h, gravity, cm, diag, stride, data, b):
    """Zero ``data``, put cm * m_i on the diagonal of every vertex block, and b = M v + h M g: the parts of
    A_d = cm M + ... and b_d = M v + h (f + M g) that need no element (mass [kg], v (n,3) [m/s], h [s],
    gravity (3,) [m/s^2], b (3n,) [N s])."""
    data[:] = 0.0
    for i in range(len(mass)):
        for c in range(3):
            data[diag[i] + c * stride[i] + c] = cm * mass[i]
            b[3 * i + c] = mass[i] * (v[i, c] + h * gravity[c])


class PatternElement:
    """Base of the deformable elements (fem.TetFEM, string.String): energy, force and stiffness from the one
    compiled accumulation of the subclass, ``add(x, ck, hf, data, f) -> energy`` (x (n,3) [m]; f (n,3) +=
    hf * elastic forces [N]; ``data`` of ``pattern`` += ck * K [N/m]; returns the elastic energy [J]), over its
    fixed BlockPattern ``pattern`` of the ``n`` vertices and the ``cells`` (E, k) (tetrahedra, segments)."""

    n: int
    cells: np.ndarray

    @cached_property
    def pattern(self) -> BlockPattern:
        """The fixed CSR pattern of the (3n,3n) stiffness and step matrix (computed on first use)."""
        return block_pattern(self.n, self.cells)

    def energy(self, x) -> float:
        """Elastic energy [J] at x (n,3) [m]."""
        return float(self.add(x, 0.0, 0.0, np.empty(0), np.empty((0, 3))))

    def force(self, x) -> np.ndarray:
        """(n,3) elastic forces -dE/dx [N]."""
        f = np.zeros((self.n, 3))
        self.add(x, 0.0, 1.0, np.empty(0), f)
        return f

    def stiffness(self, x) -> sp.csr_matrix:
        """(3n,3n) K = -df/dx [N/m] (the energy's Hessian), sparse CSR on ``pattern``."""
        p = self.pattern
        data = np.zeros(p.nnz)
        self.add(x, 1.0, 0.0, data, np.empty((0, 3)))
        return sp.csr_matrix((data, p.indices, p.indptr), shape=(3 * self.n, 3 * self.n))
