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
    ``fs_ptr``, ``fs_col``, ``fs_pos``: per free vertex k, the skeleton columns fs_col[fs_ptr[k]:fs_ptr[k + 1]]
    (ascending) its three DOFs couple to through attached vertices next to it (the supports of those vertices'
    bodies; none for a free vertex with no attached neighbour) and, per such column, fs_pos[., 0:3] the
    positions in the reduced data of the entries (free DOF 3k + c, that skeleton DOF), fs_pos[., 3:6] those of
    their transposes; every other (free DOF, skeleton DOF) entry is structurally zero and not stored;
    ``sk_start``: (n_r,) position of skeleton row k's first skeleton column (the skeleton block is dense)."""
    n_r: int
    n_free: int  # 3 n_f
    dof: np.ndarray
    free: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    pos: np.ndarray
    fs_ptr: np.ndarray
    fs_col: np.ndarray
    fs_pos: np.ndarray
    sk_start: np.ndarray
    att_dof: np.ndarray  # (3a,) the A_d DOF of row r of E
    ad_indptr: np.ndarray  # the A_d pattern it was built for
    ad_indices: np.ndarray
    # ``fill``'s entry lists (each target then sums its terms in the order of a scan of A_d's rows): free-free
    # entries (A_d position, reduced position); per free DOF p its A_d DOF free_ad[p]; per free vertex k (free
    # DOFs 3k..3k+2) its 3 x 3 blocks of A_d on attached vertices, fa_blk[fa_ptr[k]:fa_ptr[k + 1]] (A_d
    # positions, row c, column d) in column order, on the attachments fa_att (E rows 3 fa_att..+2); per
    # attachment k the same blocks of its own rows, aa_ptr / aa_blk / aa_att.
    ff_src: np.ndarray
    ff_dst: np.ndarray
    free_ad: np.ndarray
    fa_ptr: np.ndarray
    fa_blk: np.ndarray
    fa_att: np.ndarray
    aa_ptr: np.ndarray
    aa_blk: np.ndarray
    aa_att: np.ndarray
    e_end: np.ndarray  # (a,) one past the last skeleton column attachment k's rows of E can be nonzero on (``support``)
    y_end: np.ndarray  # (a,) the same for its rows of Y = A_aa E (the largest e_end of the attachments it couples to)

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
    fs_pos = np.full((len(adj), n_r), -1, dtype=np.int64)  # (adjacent free DOF, skeleton DOF) -> reduced position
    sf_pos = np.full((len(adj), n_r), -1, dtype=np.int64)  # its transpose's
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
    ff_src, ff_dst = [], []
    free_ad = np.empty(nf3, dtype=np.int64)
    for i in range(3 * n_vertices):
        p = dof[i]
        if p < 0:
            continue
        free_ad[p] = i  # free DOFs are numbered in A_d's row order
        for e in range(ad_indptr[i], ad_indptr[i + 1]):
            if dof[ad_indices[e]] >= 0:
                ff_src.append(e)
                ff_dst.append(pos[e])
    if len(adj) % 3 or np.any(adj[::3] % 3) or not np.array_equal(adj.reshape(-1, 3), adj[::3, None] + np.arange(3)):
        raise ValueError("A_d's pattern is not made of 3 x 3 vertex blocks")  # fill_kernel: W rows by vertex
    fa_ptr, fa_blk, fa_att = attached_blocks(ad_indptr, ad_indices, dof, free)
    aa_ptr, aa_blk, aa_att = attached_blocks(ad_indptr, ad_indices, dof, attached)
    e_end = np.array([int(np.nonzero(support[k])[0][-1]) + 1 if support[k].any() else 0
                      for k in range(len(attached))], dtype=np.int64)
    y_end = np.array([e_end[aa_att[aa_ptr[k]:aa_ptr[k + 1]]].max(initial=0) for k in range(len(attached))],
                     dtype=np.int64)
    fs_ptr, fs_col, fs_vpos = vertex_skeleton_entries(reach, adj_rank, fs_pos, sf_pos)
    written = np.zeros(len(indices), dtype=bool)  # fill_kernel writes every entry (no zeroing of the data first)
    written[np.asarray(ff_dst, dtype=np.int64)] = True
    written[fs_vpos.ravel()] = True
    written[(sk_start[:, None] + np.arange(n_r)).ravel()] = True
    if not written.all():
        raise ValueError("A_d's pattern does not store every diagonal entry")
    i64 = lambda a: np.asarray(a, dtype=np.int64)
    return Reduction(int(n_r), nf3, dof, free, indptr, indices, pos, fs_ptr, fs_col, fs_vpos, sk_start, att_dof,
                     ad_indptr, ad_indices, i64(ff_src), i64(ff_dst), free_ad, fa_ptr, fa_blk, fa_att, aa_ptr, aa_blk,
                     aa_att, e_end, y_end)


def vertex_skeleton_entries(reach, adj_rank, fs_pos, sf_pos) -> tuple:
    """Reduction.fs_ptr / fs_col / fs_pos from build's per-DOF maps: per free vertex the skeleton columns its DOFs
    reach (the same for its three DOFs: A_d is made of 3 x 3 vertex blocks) and the reduced positions of the
    entries (its DOF c, column) and (column, its DOF c), c = 0, 1, 2."""
    ptr, col, where = [0], [], []
    for v in range(len(reach) // 3):
        p = 3 * v
        cols = np.flatnonzero(reach[p])
        if not np.array_equal(reach[p + 1], reach[p]) or not np.array_equal(reach[p + 2], reach[p]):
            raise ValueError("A_d's pattern is not made of 3 x 3 vertex blocks")
        for k in cols:
            c = adj_rank[p:p + 3]
            col.append(int(k))
            where.append([*fs_pos[c, k], *sf_pos[c, k]])
        ptr.append(len(col))
    i64 = lambda a: np.asarray(a, dtype=np.int64)
    return i64(ptr), i64(col), i64(where).reshape(-1, 6)


def attached_blocks(ad_indptr, ad_indices, dof, vertices):
    """The 3 x 3 blocks of A_d (a pattern of 3 x 3 vertex blocks, columns sorted) in the rows of each vertex of
    ``vertices`` on the attached vertices' columns, in column order: (ptr (len(vertices) + 1,), blk (nb, 3, 3)
    A_d positions [row c, column d], att (nb,) the attachment index k of the columns, E rows 3k..3k+2).
    ``dof``: Reduction.dof (-(3k + d + 1) on attachment k's DOF d)."""
    ptr, blk, att = [0], [], []
    for v in vertices:
        rows = [ad_indices[ad_indptr[3 * v + c]:ad_indptr[3 * v + c + 1]] for c in range(3)]
        n_att = sum(int((dof[r] < 0).sum()) for r in rows)
        for col in rows[0]:
            q = -dof[col] - 1
            if q < 0 or q % 3:  # a free column, or not an attached vertex's first DOF
                continue
            b = np.empty((3, 3), dtype=np.int64)
            for c in range(3):
                want = col + np.arange(3)
                at = np.minimum(np.searchsorted(rows[c], want), len(rows[c]) - 1)
                if np.any(rows[c][at] != want):
                    raise ValueError("A_d's pattern is not made of 3 x 3 vertex blocks")
                b[c] = ad_indptr[3 * v + c] + at
            blk.append(b)
            att.append(q // 3)
        if n_att != 9 * (len(att) - ptr[-1]):
            raise ValueError("A_d's pattern is not made of 3 x 3 vertex blocks")
        ptr.append(len(att))
    return (np.asarray(ptr, dtype=np.int64), np.asarray(blk, dtype=np.int64).reshape(-1, 3, 3),
            np.asarray(att, dtype=np.int64))


def fill(red: Reduction, ad_data, b_d, E, t, A_r, b_r, data_out, b_out, work):
    """One step's reduced matrix values (into ``data_out``, red.indptr/indices layout) and right-hand side
    (into ``b_out``): A_d's CSR values ``ad_data`` and b_d (3N,), E (3a, n_r) the attached points' Jacobians
    (nonzero only on the support ``build`` was given), t (3a,) their offsets (v_a = E qdot_r + t), A_r (n_r,
    n_r), b_r (n_r,); ``work`` (3a + 3, n_r) scratch (``work_shape``)."""
    na = len(red.att_dof)
    fill_kernel(np.asarray(ad_data, float), np.asarray(b_d, float), red.ff_src, red.ff_dst, red.free_ad, red.fa_ptr,
                red.fa_blk, red.fa_att, red.aa_ptr, red.aa_blk, red.aa_att, red.e_end, red.y_end, red.fs_ptr,
                red.fs_col, red.fs_pos, red.sk_start, red.att_dof, red.n_free,
                np.ascontiguousarray(E, dtype=float), np.asarray(t, float), np.ascontiguousarray(A_r, dtype=float),
                np.asarray(b_r, float), data_out, b_out, work[:na], work[na:])


def work_shape(red: Reduction) -> tuple:
    """The shape of ``fill``'s scratch: rows of Y = A_aa E (one per attached DOF) and the three rows of A_fa E of
    the free vertex in hand, n_r columns."""
    return len(red.att_dof) + 3, red.n_r


@njit
def fill_kernel(ad_data, b_d, ff_src, ff_dst, free_ad, fa_ptr, fa_blk, fa_att, aa_ptr, aa_blk, aa_att, e_end, y_end,
                fs_ptr, fs_col, fs_pos, sk_start, att_dof, nf3, E, t, A_r, b_r, data, b, Y, W):
    """The loops of ``fill`` over the Reduction's entry lists (no per-entry test of which block an entry is in):
    the free-free entries copied; the products with E as contiguous rows over the skeleton columns a row of E
    can be nonzero on (e_end: its body's supports end there; the columns past it are exact zeros, so skipping
    them changes no bit) (Y = A_aa E, and W = A_fa E one free vertex at a time: its three rows, scattered into
    the reduced pattern with their transposes E^T A_af = W^T (A_d symmetric) as soon as they are complete, on
    the columns it reaches (fs_ptr / fs_col / fs_pos) only), one 3 x 3 block of A_d (a vertex's three rows on
    an attached vertex's three columns) per pass over the columns; E^T A_aa E = E^T Y, an attached vertex's
    three rows of E per pass, symmetrised. Every sum takes its terms in the order of a scan of A_d's rows (a
    pass adds a block row's three terms left to right, as three entries of that row in turn; E^T Y skips the
    columns where the vertex's three rows of E are zero, and adds the exact zeros of the others, which changes
    no bit but the sign of an exact zero; b_r + E^T (b_a - A_aa t) skips the exact zeros past e_end, the same):
    the numbers of the entry-by-entry loops (measured on the starfish: 174 -> 114 us a fill). Every entry of
    the reduced pattern is written (build checks it), so ``data`` is not zeroed first (a free-free entry is
    0 + A_d's, as it was: -0 becomes +0). The per-vertex scatter, the unzeroed data and the shorter b_r loop:
    67 -> 56 us a fill (starfish, CPU, alternating blocks of 25 calls in one process, medians of 200)."""
    n_r = A_r.shape[0]
    na = E.shape[0]
    Y[:, :] = 0.0
    ta = np.zeros(na)  # A_aa t
    for k in range(len(ff_src)):  # free row, free column (the sum 0 + a of the zeroed data: -0 becomes +0)
        data[ff_dst[k]] = 0.0 + ad_data[ff_src[k]]
    for v in range(nf3 // 3):  # a free vertex's rows, attached columns: A_fa E and -A_fa t
        p = 3 * v
        for i in range(fs_ptr[v], fs_ptr[v + 1]):
            W[0, fs_col[i]] = W[1, fs_col[i]] = W[2, fs_col[i]] = 0.0
        b0, b1, b2 = 0.0 + b_d[free_ad[p]], 0.0 + b_d[free_ad[p + 1]], 0.0 + b_d[free_ad[p + 2]]
        for q in range(fa_ptr[v], fa_ptr[v + 1]):
            s = fa_att[q]
            r = 3 * s
            a00, a01, a02 = ad_data[fa_blk[q, 0, 0]], ad_data[fa_blk[q, 0, 1]], ad_data[fa_blk[q, 0, 2]]
            a10, a11, a12 = ad_data[fa_blk[q, 1, 0]], ad_data[fa_blk[q, 1, 1]], ad_data[fa_blk[q, 1, 2]]
            a20, a21, a22 = ad_data[fa_blk[q, 2, 0]], ad_data[fa_blk[q, 2, 1]], ad_data[fa_blk[q, 2, 2]]
            for l in range(e_end[s]):
                e0, e1, e2 = E[r, l], E[r + 1, l], E[r + 2, l]
                W[0, l] = W[0, l] + a00 * e0 + a01 * e1 + a02 * e2
                W[1, l] = W[1, l] + a10 * e0 + a11 * e1 + a12 * e2
                W[2, l] = W[2, l] + a20 * e0 + a21 * e1 + a22 * e2
            t0, t1, t2 = t[r], t[r + 1], t[r + 2]
            b0 = b0 - a00 * t0 - a01 * t1 - a02 * t2
            b1 = b1 - a10 * t0 - a11 * t1 - a12 * t2
            b2 = b2 - a20 * t0 - a21 * t1 - a22 * t2
        b[p], b[p + 1], b[p + 2] = b0, b1, b2
        for i in range(fs_ptr[v], fs_ptr[v + 1]):  # A_fa E and E^T A_af = (A_fa E)^T
            l = fs_col[i]
            for c in range(3):
                data[fs_pos[i, c]] = W[c, l]
                data[fs_pos[i, 3 + c]] = W[c, l]
    for k in range(n_r):
        b[nf3 + k] = b_r[k]
    for v in range(na // 3):  # an attached vertex's rows and attached columns: Y = A_aa E, A_aa t
        r3 = 3 * v
        ta0 = ta1 = ta2 = 0.0
        for q in range(aa_ptr[v], aa_ptr[v + 1]):
            s = aa_att[q]
            r = 3 * s
            a00, a01, a02 = ad_data[aa_blk[q, 0, 0]], ad_data[aa_blk[q, 0, 1]], ad_data[aa_blk[q, 0, 2]]
            a10, a11, a12 = ad_data[aa_blk[q, 1, 0]], ad_data[aa_blk[q, 1, 1]], ad_data[aa_blk[q, 1, 2]]
            a20, a21, a22 = ad_data[aa_blk[q, 2, 0]], ad_data[aa_blk[q, 2, 1]], ad_data[aa_blk[q, 2, 2]]
            for l in range(e_end[s]):
                e0, e1, e2 = E[r, l], E[r + 1, l], E[r + 2, l]
                Y[r3, l] = Y[r3, l] + a00 * e0 + a01 * e1 + a02 * e2
                Y[r3 + 1, l] = Y[r3 + 1, l] + a10 * e0 + a11 * e1 + a12 * e2
                Y[r3 + 2, l] = Y[r3 + 2, l] + a20 * e0 + a21 * e1 + a22 * e2
            t0, t1, t2 = t[r], t[r + 1], t[r + 2]
            ta0 = ta0 + a00 * t0 + a01 * t1 + a02 * t2
            ta1 = ta1 + a10 * t0 + a11 * t1 + a12 * t2
            ta2 = ta2 + a20 * t0 + a21 * t1 + a22 * t2
        ta[r3], ta[r3 + 1], ta[r3 + 2] = ta0, ta1, ta2
    for r in range(na):  # b_r + E^T (b_a - A_aa t)
        ba = b_d[att_dof[r]] - ta[r]
        for k in range(e_end[r // 3]):
            b[nf3 + k] += E[r, k] * ba
    S = np.zeros((n_r, n_r))  # E^T A_aa E = E^T Y
    for v in range(na // 3):
        r = 3 * v
        for k in range(e_end[v]):
            e0, e1, e2 = E[r, k], E[r + 1, k], E[r + 2, k]
            if e0 != 0.0 or e1 != 0.0 or e2 != 0.0:
                for l in range(y_end[v]):
                    S[k, l] = S[k, l] + e0 * Y[r, l] + e1 * Y[r + 1, l] + e2 * Y[r + 2, l]
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
    return hold_kernel(indptr, indices, diag, tpos, data, b, np.asarray(dofs, dtype=np.int64),
                       np.asarray(vals, dtype=float))


@njit
def hold_kernel(indptr, indices, diag, tpos, data, b, dofs, vals):
    """``hold`` in one call (its outputs allocated here: the numpy calls sizing them cost more than the loops)."""
    total = 0
    for j in dofs:
        total += indptr[j + 1] - indptr[j]
    saved = np.empty(total)
    b_saved = np.empty(len(dofs))
    for i in range(len(dofs)):
        b_saved[i] = b[dofs[i]]
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
    return saved, b_saved


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
