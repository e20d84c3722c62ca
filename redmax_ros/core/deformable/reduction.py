"""Elimination of the attached vertices from the coupled step (Wang et al. 2019 §4, the equation after Eq. 5).

An attachment row G_m J_mr qdot_r + G_d qdot_d = g holds a vertex's velocity to a body point's,
v_i = J_p qdot_r - g_i (attach.py: rows [J_p, -S_i], right-hand side g_i, 0 without Baumgarte), or to a world
point, v_i = g_i. Substituting these into the step's quadratic form 1/2 z^T A z - b^T z (A = blockdiag(A_r, A_d))
is the null-space method for those rows (Nocedal & Wright, Numerical Optimization, §16.2): with v_d = E qdot_r + t
on the attached vertices (E the stacked J_p, 0 for world points; t = -g_i or +g_i) and the free vertices' v_f
left as unknowns, the reduced unknowns z = (v_f, qdot_r) (free DOFs first, skeleton last) solve

    [ A_ff          A_fa E            ] [v_f   ]   [ b_f - A_fa t                  ]
    [ E^T A_af      A_r + E^T A_aa E  ] [qdot_r] = [ b_r + E^T (b_a - A_aa t)      ]

with the skeleton's rows (loops, prescriptions, joint limits) on qdot_r unchanged, so their multipliers are the
coupled KKT system's. The attachment rows hold exactly (v_a = E qdot_r + t), and the system is symmetric and
half the size of the KKT matrix with its 3a attachment rows.

The reduced matrix's pattern is fixed by the mesh topology and the skeleton's chains (a Reduction, built once
per A_d pattern): free-free entries of A_d; for every free DOF next to an attached vertex (the "adjacent" DOFs) a
row segment over the skeleton DOFs that move those vertices (their bodies' supports); and the dense skeleton
block. ``fill`` writes one step's values into it in one compiled
call.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from redmax_ros.core.jit import njit


@dataclass(frozen=True)
class Reduction:
    """Index maps of the reduced system of one A_d pattern (3N DOFs) and attachment set.

    ``dof``: (3N,) reduced index of every free vertex DOF, or -(r + 1) for the attached DOF of row r of E;
    ``free``: (n_f,) free vertex indices, in order (free DOF p = 3 k + c of free vertex free[k]);
    ``indptr``, ``indices``: the reduced CSR pattern (n = 3 n_f + n_r, columns sorted, the skeleton last);
    ``pos``: (nnz(A_d),) position in the reduced data of every free-free entry of A_d, -1 otherwise;
    ``adj_rank``: (3 n_f,) rank of a free DOF among the adjacent ones (free DOFs coupled by A_d to an attached
    vertex), -1 where not adjacent;
    ``fs_pos``, ``sf_pos``: (n_adj, n_r) positions in the reduced data of the entries (adjacent free DOF,
    skeleton DOF k) and (skeleton DOF k, adjacent free DOF), -1 where k moves none of the attached vertices
    next to that free DOF (the entry is structurally zero and not stored);
    ``sk_start``: (n_r,) position of skeleton row k's first skeleton column (the skeleton block is dense)."""
    n_r: int
    n_free: int  # 3 n_f
    dof: np.ndarray
    free: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    pos: np.ndarray
    adj_rank: np.ndarray
    fs_pos: np.ndarray
    sf_pos: np.ndarray
    sk_start: np.ndarray
    att_dof: np.ndarray  # (3a,) the A_d DOF of row r of E
    ad_indptr: np.ndarray  # the A_d pattern it was built for
    ad_indices: np.ndarray
    # ``fill``'s entry lists, in A_d's row order (each target then sums its terms in the order of a row scan):
    # free-free entries (A_d position, reduced position); per free DOF p the A_d DOF free_ad[p] and its
    # attached-column entries fa_src[fa_ptr[p]:fa_ptr[p + 1]] with their E rows fa_row; per attached row r its
    # attached-column entries aa_src[aa_ptr[r]:aa_ptr[r + 1]] with their E rows aa_row.
    ff_src: np.ndarray
    ff_dst: np.ndarray
    free_ad: np.ndarray
    fa_ptr: np.ndarray
    fa_src: np.ndarray
    fa_row: np.ndarray
    aa_ptr: np.ndarray
    aa_src: np.ndarray
    aa_row: np.ndarray
    e_end: np.ndarray  # (3a,) one past the last skeleton column E's row r can be nonzero on (from ``support``)
    y_end: np.ndarray  # (3a,) the same for row r of Y = A_aa E (the largest e_end of its attached columns)

    @property
    def n(self) -> int:
        return self.n_free + self.n_r


def build(ad_indptr, ad_indices, n_vertices: int, attached, n_r: int, support=None) -> Reduction:
    """The Reduction of an A_d CSR pattern (3N x 3N, sorted column indices) with the ``attached`` vertices
    (their order = the attachment order: vertex attached[k] is rows 3k..3k+2 of E) and n_r skeleton DOFs.
    ``support`` (a, n_r) bool: the skeleton DOFs that can move each attached vertex (the nonzero columns of its
    rows of E); a free DOF next to attached vertices then couples to the union of their supports only (the
    skeleton's chains), which keeps the factor of the reduced system sparse. None: every skeleton DOF."""
    ad_indptr = np.asarray(ad_indptr, dtype=np.int64)
    ad_indices = np.asarray(ad_indices, dtype=np.int64)
    attached = np.asarray(attached, dtype=np.int64)
    support = (np.ones((len(attached), n_r), dtype=bool) if support is None
               else np.asarray(support, dtype=bool).reshape(len(attached), n_r))
    dof = np.empty(3 * n_vertices, dtype=np.int64)
    is_att = np.zeros(n_vertices, dtype=bool)
    is_att[attached] = True
    free = np.nonzero(~is_att)[0]
    for k, v in enumerate(free):
        dof[3 * v:3 * v + 3] = 3 * k + np.arange(3)
    for k, v in enumerate(attached):
        dof[3 * v:3 * v + 3] = -(3 * k + np.arange(3) + 1)
    nf3 = 3 * len(free)
    reach = np.zeros((nf3, n_r), dtype=bool)  # skeleton DOFs coupled to each free DOF through attached ones
    adjacent = np.zeros(nf3, dtype=bool)
    rows = [[] for _ in range(nf3)]
    for i in range(3 * n_vertices):
        p = dof[i]
        for e in range(ad_indptr[i], ad_indptr[i + 1]):
            q = dof[ad_indices[e]]
            if p >= 0 and q >= 0:
                rows[p].append(q)
            elif p >= 0 > q:
                adjacent[p] = True
                reach[p] |= support[(-q - 1) // 3]
    adj = np.nonzero(adjacent)[0]
    adj_rank = np.full(nf3, -1, dtype=np.int64)
    adj_rank[adj] = np.arange(len(adj))
    fs_pos = np.full((len(adj), n_r), -1, dtype=np.int64)
    sf_pos = np.full((len(adj), n_r), -1, dtype=np.int64)
    sk_start = np.zeros(n_r, dtype=np.int64)
    indptr = [0]
    indices = []
    for p in range(nf3):
        indices += sorted(set(rows[p]) | {p})
        if adjacent[p]:
            for k in np.nonzero(reach[p])[0]:
                fs_pos[adj_rank[p], k] = len(indices)
                indices.append(nf3 + int(k))
        indptr.append(len(indices))
    for k in range(n_r):
        for p in adj[reach[adj, k]]:
            sf_pos[adj_rank[p], k] = len(indices)
            indices.append(int(p))
        sk_start[k] = len(indices)
        indices += list(nf3 + np.arange(n_r))
        indptr.append(len(indices))
    indptr = np.asarray(indptr, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    pos = np.full(len(ad_indices), -1, dtype=np.int64)
    for i in range(3 * n_vertices):
        p = dof[i]
        if p < 0:
            continue
        row = indices[indptr[p]:indptr[p + 1]]
        for e in range(ad_indptr[i], ad_indptr[i + 1]):
            q = dof[ad_indices[e]]
            if q >= 0:
                pos[e] = indptr[p] + int(np.searchsorted(row, q))
    att_dof = (3 * attached[:, None] + np.arange(3)).ravel()
    na = len(att_dof)
    ends = np.array([int(np.nonzero(support[k])[0][-1]) + 1 if support[k].any() else 0 for k in range(len(attached))],
                    dtype=np.int64)
    e_end = np.repeat(ends, 3)
    ff_src, ff_dst, fa_src, fa_row = [], [], [], []
    aa_rows = [[] for _ in range(na)]  # per attached row r (E's row order, not A_d's): (A_d position, E row)
    free_ad = np.empty(nf3, dtype=np.int64)
    fa_ptr = np.zeros(nf3 + 1, dtype=np.int64)
    y_end = np.zeros(na, dtype=np.int64)
    for i in range(3 * n_vertices):
        p = dof[i]
        for e in range(ad_indptr[i], ad_indptr[i + 1]):
            q = dof[ad_indices[e]]
            if p >= 0 and q >= 0:
                ff_src.append(e)
                ff_dst.append(pos[e])
            elif p >= 0:
                fa_src.append(e)
                fa_row.append(-q - 1)
            elif q < 0:
                aa_rows[-p - 1].append((e, -q - 1))
                y_end[-p - 1] = max(y_end[-p - 1], e_end[-q - 1])
        if p >= 0:  # free DOFs are numbered in A_d's row order
            free_ad[p] = i
            fa_ptr[p + 1] = len(fa_src)
    aa_ptr = np.concatenate([[0], np.cumsum([len(r) for r in aa_rows])]).astype(np.int64)
    aa_src = [e for r in aa_rows for e, _ in r]
    aa_row = [s for r in aa_rows for _, s in r]
    i64 = lambda a: np.asarray(a, dtype=np.int64)
    return Reduction(int(n_r), nf3, dof, free, indptr, indices, pos, adj_rank, fs_pos, sf_pos, sk_start, att_dof,
                     ad_indptr, ad_indices, i64(ff_src), i64(ff_dst), free_ad, fa_ptr, i64(fa_src), i64(fa_row),
                     aa_ptr, i64(aa_src), i64(aa_row), e_end, y_end)


def fill(red: Reduction, ad_data, b_d, E, t, A_r, b_r, data_out, b_out, work):
    """One step's reduced matrix values (into ``data_out``, red.indptr/indices layout) and right-hand side
    (into ``b_out``): A_d's CSR values ``ad_data`` and b_d (3N,), E (3a, n_r) the attached points' Jacobians
    (nonzero only on the support ``build`` was given), t (3a,) their offsets (v_a = E qdot_r + t), A_r (n_r,
    n_r), b_r (n_r,); ``work`` (3a + n_adj, n_r) scratch (``work_shape``)."""
    na = len(red.att_dof)
    fill_kernel(np.asarray(ad_data, float), np.asarray(b_d, float), red.ff_src, red.ff_dst, red.free_ad, red.fa_ptr,
                red.fa_src, red.fa_row, red.aa_ptr, red.aa_src, red.aa_row, red.e_end, red.y_end, red.adj_rank,
                red.fs_pos, red.sf_pos, red.sk_start, red.att_dof, red.n_free,
                np.ascontiguousarray(E, dtype=float), np.asarray(t, float), np.ascontiguousarray(A_r, dtype=float),
                np.asarray(b_r, float), data_out, b_out, work[:na], work[na:])


def work_shape(red: Reduction) -> tuple:
    """The shape of ``fill``'s scratch: rows of Y = A_aa E (one per attached DOF) and of A_fa E (one per
    adjacent free DOF), n_r columns."""
    return len(red.att_dof) + red.fs_pos.shape[0], red.n_r


@njit
def fill_kernel(ad_data, b_d, ff_src, ff_dst, free_ad, fa_ptr, fa_src, fa_row, aa_ptr, aa_src, aa_row, e_end, y_end,
                adj_rank, fs_pos, sf_pos, sk_start, att_dof, nf3, E, t, A_r, b_r, data, b, Y, W):
    """The loops of ``fill`` over the Reduction's entry lists (no per-entry test of which block an entry is in):
    the free-free entries copied; the products with E as contiguous rows over the skeleton columns a row of E
    can be nonzero on (e_end: its body's supports end there; the columns past it are exact zeros, so skipping
    them changes no bit) (Y = A_aa E, W = A_fa E), scattered into the reduced pattern once at the end;
    E^T A_af = W^T (A_d symmetric); E^T A_aa E symmetrised. Every sum takes its terms in the order of a scan of
    A_d's rows."""
    n_r = A_r.shape[0]
    na = E.shape[0]
    data[:] = 0.0
    Y[:, :] = 0.0
    W[:, :] = 0.0
    ta = np.zeros(na)  # A_aa t
    for k in range(len(ff_src)):  # free row, free column
        data[ff_dst[k]] += ad_data[ff_src[k]]
    for p in range(nf3):  # free row, attached column: A_fa E and -A_fa t
        b[p] = 0.0
        b[p] += b_d[free_ad[p]]
        c = adj_rank[p]
        for k in range(fa_ptr[p], fa_ptr[p + 1]):
            a = ad_data[fa_src[k]]
            r = fa_row[k]
            for l in range(e_end[r]):
                W[c, l] += a * E[r, l]
            b[p] -= a * t[r]
    for k in range(n_r):
        b[nf3 + k] = b_r[k]
    for r in range(na):  # attached row and column: Y = A_aa E
        for k in range(aa_ptr[r], aa_ptr[r + 1]):
            a = ad_data[aa_src[k]]
            s = aa_row[k]
            for l in range(e_end[s]):
                Y[r, l] += a * E[s, l]
            ta[r] += a * t[s]
    for c in range(fs_pos.shape[0]):  # A_fa E and E^T A_af = (A_fa E)^T
        for k in range(n_r):
            f = fs_pos[c, k]
            if f >= 0:
                data[f] = W[c, k]
                data[sf_pos[c, k]] = W[c, k]
    for r in range(na):  # b_r + E^T (b_a - A_aa t)
        ba = b_d[att_dof[r]] - ta[r]
        for k in range(n_r):
            b[nf3 + k] += E[r, k] * ba
    S = np.zeros((n_r, n_r))  # E^T A_aa E = E^T Y
    for r in range(na):
        for k in range(e_end[r]):
            erk = E[r, k]
            if erk != 0.0:
                for l in range(y_end[r]):
                    S[k, l] += erk * Y[r, l]
    for k in range(n_r):  # + A_r: the dense skeleton block
        s = sk_start[k]
        for l in range(n_r):
            data[s + l] = 0.5 * (S[k, l] + S[l, k]) + A_r[k, l]


def unit_rows(G, C=None):
    """(rows, columns, coefficients) of the rows of G (m, n_r) with exactly one nonzero c on a column no other
    row of G or C touches: the prescribed joint velocities of Eq. (7) without couplings, c qdot_j = g_i. Such a
    row is imposed by holding the DOF (``hold``) instead of by a Schur complement (one solve per row)."""
    G = np.ascontiguousarray(G, dtype=float)
    C = np.zeros((0, G.shape[1])) if C is None else np.ascontiguousarray(C, dtype=float)
    rows, cols = np.empty(len(G), np.int64), np.empty(len(G), np.int64)
    cnt = unit_rows_kernel(G, C, rows, cols)
    rows, cols = rows[:cnt], cols[:cnt]
    return rows, cols, G[rows, cols]


@njit
def unit_rows_kernel(G, C, rows, cols):
    """The loops of ``unit_rows``: their count, written into rows / cols."""
    n = G.shape[1]
    touched = np.zeros(n, np.int64)
    for i in range(G.shape[0]):
        for j in range(n):
            if G[i, j] != 0.0:
                touched[j] += 1
    for i in range(C.shape[0]):
        for j in range(n):
            if C[i, j] != 0.0:
                touched[j] += 1
    cnt = 0
    for i in range(G.shape[0]):
        first, nz = -1, 0
        for j in range(n):
            if G[i, j] != 0.0:
                nz += 1
                if first < 0:
                    first = j
        if nz == 1 and touched[first] == 1:
            rows[cnt] = i
            cols[cnt] = first
            cnt += 1
    return cnt


def hold(indptr, indices, diag, tpos, data, b, dofs, vals):
    """Impose z[dofs] = vals on the symmetric system (CSR values ``data`` in the pattern indptr/indices,
    right-hand side b, both modified in place): b -= A[:, dofs] vals, then the rows and columns of ``dofs``
    become identity rows with b[dofs] = vals (the pattern, hence the symbolic factorisation, is unchanged).
    ``diag`` (n,) is each row's diagonal position, ``tpos`` (nnz,) each entry's transpose position. Returns the
    held rows' original values (concatenated, in ``dofs`` order) and b[dofs], for their reactions
    (``reactions``)."""
    dofs = np.asarray(dofs, dtype=np.int64)
    lens = indptr[dofs + 1] - indptr[dofs]
    saved = np.empty(int(lens.sum()))
    b_saved = b[dofs].copy()
    hold_kernel(indptr, indices, diag, tpos, data, b, dofs, np.asarray(vals, dtype=float), saved)
    return saved, b_saved


@njit
def hold_kernel(indptr, indices, diag, tpos, data, b, dofs, vals, saved):
    k = 0
    for i in range(len(dofs)):  # b -= A[:, j] v_j, A symmetric: the column is the row
        j = dofs[i]
        for e in range(indptr[j], indptr[j + 1]):
            saved[k] = data[e]
            k += 1
            b[indices[e]] -= data[e] * vals[i]
    for i in range(len(dofs)):
        j = dofs[i]
        for e in range(indptr[j], indptr[j + 1]):
            data[e] = 0.0
            data[tpos[e]] = 0.0
        data[diag[j]] = 1.0
        b[j] = vals[i]


def reactions(indptr, indices, dofs, saved, b_saved, z):
    """(A z - b)[dofs] with the held rows' original values ``saved`` and right-hand sides ``b_saved`` (``hold``):
    the reaction each held DOF needs (the multiplier of its row, up to the row's coefficient)."""
    out = np.empty(len(dofs))
    reactions_kernel(indptr, indices, np.asarray(dofs, dtype=np.int64), saved, b_saved, z, out)
    return out


@njit
def reactions_kernel(indptr, indices, dofs, saved, b_saved, z, out):
    k = 0
    for i in range(len(dofs)):
        j = dofs[i]
        acc = -b_saved[i]
        for e in range(indptr[j], indptr[j + 1]):
            acc += saved[k] * z[indices[e]]
            k += 1
        out[i] = acc
