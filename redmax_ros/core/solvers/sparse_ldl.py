"""Sparse symmetric LDL^T without pivoting, for a pattern that stays the same from step to step (issue 15's
coupled deformable step: skeleton DOFs + 3 DOFs per free mesh vertex).

    P A P^T = L D L^T,   L unit lower triangular, D diagonal,  P a fill-reducing permutation

``analyse(indptr, indices, n)`` runs once per pattern (compiled; 1.0 ms for 1000 unknowns): the ordering,
the elimination tree and column counts (Davis, "Direct Methods for Sparse Linear Systems", SIAM 2006, §4.1
and his LDL package), the fundamental supernodes and their row structures (Liu, Ng and Peyton, SIAM J.
Matrix Anal. Appl. 14, 1993), where each input entry lands in the factor's storage, and which supernode
updates which, at which target positions. ``factor(sym, data, out)`` (one compiled call, no allocation when
``out`` is given) loads the values and factorises left-looking, supernode by supernode (Davis 2006, §9.1):
each supernode is a dense column-major block, updated by its descendants four target columns and three
source columns per pass, straight into its storage where the source's rows land on consecutive positions
and through a buffer and a scatter otherwise. ``solve(sym, num, b)`` takes b (n,) or (n, k).

No pivoting: the matrix must have nonzero leading pivots in the chosen order; SPD matrices always do, the
occasionally indefinite ones of co-rotated FEM under compression usually do (LDLNumeric.n_negative counts
the negative pivots, the inertia). A pivot with |d_k| <= tiny max|diag A| fails the factorisation with a
StepError naming it. A DOF fixed for a step is expressed by the caller by overwriting its row and column
with the identity in the values (pattern unchanged): its pivot is 1 and the solve returns b there exactly.

Ordering: minimum external degree on the graph compressed by indistinguishable nodes (a mesh vertex's 3
DOFs), with mass elimination, on the explicit elimination graph (George and Liu, "The evolution of the
minimum degree ordering algorithm", SIAM Review 31, 1989; the AMD of Amestoy, Davis and Duff, SIAM J. Matrix
Anal. Appl. 17, 1996, approximates the same degrees on the quotient graph, which only pays at sizes well
above these). Chosen over reverse Cuthill-McKee (scipy.sparse.csgraph) by nnz(L) and factor time, measured
(test/core/solvers/sparse_ldl_matrices.py, docs/solvers.md): STARFISH mesh block 10.7k nonzeros / 62 us
(RCM 12.9k / 70 us, natural 28.4k / 119 us), with a dense 36-DOF skeleton block 22.6k / 121 us (RCM 54.5k /
500 us, natural 51.3k / 264 us), 2-D grid of 3000 41.9k / 459 us (RCM 110k / 2466 us); within 5 % of
SuperLU's MMD(A^T + A) ordering on every test matrix and 7 % below it with the skeleton block.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from redmax_ros.core.errors import StepError
from redmax_ros.core.jit import njit, njit_inline

TINY = 1e-12  # default relative pivot threshold: |d_k| <= TINY max|diag A| fails the factorisation
MIN_RUN = 8  # mean run length (rows with consecutive target positions) from which an update skips the buffer
ORDERINGS = ("mindeg", "rcm", "natural")


# ------------------------------------------------------------------------------------------- ordering

@njit
def symmetric_graph(indptr, indices, n):
    """(xadj, adj): the adjacency (CSR, no diagonal, no duplicates) of the pattern of A + A^T."""
    ptr = np.zeros(n + 1, np.int64)
    for r in range(n):
        for p in range(indptr[r], indptr[r + 1]):
            c = indices[p]
            if c != r:
                ptr[r + 1] += 1
                ptr[c + 1] += 1
    for i in range(n):
        ptr[i + 1] += ptr[i]
    tmp = np.empty(ptr[n], np.int64)
    fill = ptr[:n].copy()
    for r in range(n):
        for p in range(indptr[r], indptr[r + 1]):
            c = indices[p]
            if c != r:
                tmp[fill[r]] = c
                fill[r] += 1
                tmp[fill[c]] = r
                fill[c] += 1
    mark = np.full(n, -1, np.int64)
    xadj = np.zeros(n + 1, np.int64)
    adj = np.empty(ptr[n], np.int64)
    m = 0
    for i in range(n):
        for p in range(ptr[i], ptr[i + 1]):
            c = tmp[p]
            if mark[c] != i:
                mark[c] = i
                adj[m] = c
                m += 1
        xadj[i + 1] = m
    return xadj, adj[:m]


@njit
def indistinguishable(xadj, adj):
    """(n,) the representative (lowest index) of each node's group of indistinguishable nodes: nodes with
    the same closed neighbourhood adj(i) + {i} (e.g. the 3 DOFs of a mesh vertex). Candidates are found by
    a hash (sum of the closed neighbourhood, degree), then compared exactly."""
    n = len(xadj) - 1
    key = np.empty(n, np.int64)
    for i in range(n):
        s = i
        for p in range(xadj[i], xadj[i + 1]):
            s += adj[p]
        key[i] = s * (n + 1) + (xadj[i + 1] - xadj[i])
    order = np.argsort(key, kind="mergesort")
    rep = np.arange(n)
    mark = np.full(n, -1, np.int64)
    a = 0
    while a < n:
        b = a
        while b + 1 < n and key[order[b + 1]] == key[order[a]]:
            b += 1
        for x in range(a, b + 1):
            i = order[x]
            if rep[i] != i:
                continue
            mark[i] = i
            for p in range(xadj[i], xadj[i + 1]):
                mark[adj[p]] = i
            for y in range(x + 1, b + 1):
                j = order[y]
                if rep[j] != j or mark[j] != i:
                    continue
                same = True
                for p in range(xadj[j], xadj[j + 1]):
                    if mark[adj[p]] != i:
                        same = False
                        break
                if same:
                    rep[j] = i
        a = b + 1
    return rep


@njit
def quotient(xadj, adj, rep):
    """The graph of the groups of ``rep``: (group of each node (n,), xadj, adj, weight = nodes per group)."""
    n = len(xadj) - 1
    gid = np.full(n, -1, np.int64)
    ng = 0
    for i in range(n):
        if rep[i] == i:
            gid[i] = ng
            ng += 1
    for i in range(n):
        gid[i] = gid[rep[i]]
    weight = np.zeros(ng, np.int64)
    for i in range(n):
        weight[gid[i]] += 1
    cxadj = np.zeros(ng + 1, np.int64)
    cadj = np.empty(len(adj), np.int64)
    mark = np.full(ng, -1, np.int64)
    m = 0
    for i in range(n):
        if rep[i] != i:
            continue
        g = gid[i]
        mark[g] = g
        for p in range(xadj[i], xadj[i + 1]):
            h = gid[adj[p]]
            if mark[h] != g:
                mark[h] = g
                cadj[m] = h
                m += 1
        cxadj[g + 1] = m
    return gid, cxadj, cadj[:m], weight


@njit
def eliminate(nbr, m, pool, start, length, top, alive, w, deg, hsh, mark, stamp):
    """Make the alive neighbours nbr[:m] of an eliminated node a clique: each one's list becomes its alive
    neighbours plus the others (written at ``top`` of ``pool``), its external degree the sum of their
    weights. Returns (new top, stamp); the caller makes room for sum(length[nbr] + m) entries."""
    for a in range(m):
        u = nbr[a]
        stamp += 1
        mark[u] = stamp
        c = 0
        d = 0
        h = u
        for q in range(start[u], start[u] + length[u]):
            x = pool[q]
            if alive[x] and mark[x] != stamp:
                mark[x] = stamp
                pool[top + c] = x
                c += 1
                d += w[x]
                h += x
        for b in range(m):
            x = nbr[b]
            if mark[x] != stamp:
                mark[x] = stamp
                pool[top + c] = x
                c += 1
                d += w[x]
                h += x
        start[u] = top
        length[u] = c
        top += c
        deg[u] = d
        hsh[u] = h
    return top, stamp


@njit
def mass_eliminate(nbr, m, pool, start, length, alive, w, deg, hsh, merged, mark, stamp):
    """Merge the nodes among nbr[:m] whose closed neighbourhoods became equal (indistinguishable: they
    will be eliminated together) into one supervariable. Returns (nodes merged away, stamp)."""
    gone = 0
    for a in range(m):
        u = nbr[a]
        if not alive[u]:
            continue
        stamp += 1
        marked = False
        for b in range(a + 1, m):
            v = nbr[b]
            if not alive[v] or hsh[v] != hsh[u] or length[v] != length[u]:
                continue
            if not marked:
                mark[u] = stamp
                for q in range(start[u], start[u] + length[u]):
                    mark[pool[q]] = stamp
                marked = True
            same = True
            for q in range(start[v], start[v] + length[v]):
                if mark[pool[q]] != stamp:
                    same = False
                    break
            if same:
                alive[v] = False
                merged[v] = u
                w[u] += w[v]
                deg[u] -= w[v]
                gone += 1
    return gone, stamp


@njit
def compact(pool, start, length, alive, need):
    """A new pool holding the lists of the alive nodes, with room for ``need`` more entries: (pool, top)."""
    live = 0
    for i in range(len(start)):
        if alive[i]:
            live += length[i]
    out = np.empty(2 * (live + need) + 64, np.int64)
    t = 0
    for i in range(len(start)):
        if alive[i]:
            for q in range(length[i]):
                out[t + q] = pool[start[i] + q]
            start[i] = t
            t += length[i]
    return out, t


@njit
def min_degree(xadj, adj, weight):
    """Minimum external degree order of a weighted graph (no self loops) on the explicit elimination graph,
    ties to the lowest index, with mass elimination (George and Liu 1989). Returns (order of the nodes
    that were eliminated, merged: the node each other one was merged into, -1 for none)."""
    n = len(xadj) - 1
    pool = np.empty(4 * len(adj) + 16 * n + 64, np.int64)
    start = xadj[:n].copy()
    length = xadj[1:] - xadj[:n]
    pool[:len(adj)] = adj
    top = len(adj)
    w = weight.copy()
    alive = np.ones(n, np.bool_)
    deg = np.zeros(n, np.int64)
    for i in range(n):
        for p in range(xadj[i], xadj[i + 1]):
            deg[i] += w[adj[p]]
    mark = np.zeros(n, np.int64)
    merged = np.full(n, -1, np.int64)
    nbr = np.empty(n, np.int64)
    hsh = np.zeros(n, np.int64)
    order = np.empty(n, np.int64)
    stamp, no, remaining = 0, 0, n
    while remaining > 0:
        p, best = -1, 1 << 62
        for i in range(n):
            if alive[i] and deg[i] < best:
                best, p = deg[i], i
        order[no] = p
        no += 1
        alive[p] = False
        remaining -= 1
        m = 0
        need = 0
        for q in range(start[p], start[p] + length[p]):
            x = pool[q]
            if alive[x]:
                nbr[m] = x
                m += 1
                need += length[x]
        need += m * m
        if top + need > len(pool):
            pool, top = compact(pool, start, length, alive, need)
        top, stamp = eliminate(nbr, m, pool, start, length, top, alive, w, deg, hsh, mark, stamp)
        gone, stamp = mass_eliminate(nbr, m, pool, start, length, alive, w, deg, hsh, merged, mark, stamp)
        remaining -= gone
    return order[:no], merged


@njit
def expand(order, merged, gid):
    """The permutation (new -> old) of the original nodes: the groups in ``order``, each followed by the
    groups merged into it (depth first), each group's nodes in increasing index."""
    ng = len(merged)
    n = len(gid)
    head = np.full(ng, -1, np.int64)
    nxt = np.full(ng, -1, np.int64)
    for v in range(ng - 1, -1, -1):
        if merged[v] >= 0:
            nxt[v] = head[merged[v]]
            head[merged[v]] = v
    mptr = np.zeros(ng + 1, np.int64)
    for i in range(n):
        mptr[gid[i] + 1] += 1
    for g in range(ng):
        mptr[g + 1] += mptr[g]
    members = np.empty(n, np.int64)
    fill = mptr[:ng].copy()
    for i in range(n):
        members[fill[gid[i]]] = i
        fill[gid[i]] += 1
    perm = np.empty(n, np.int64)
    stack = np.empty(ng, np.int64)
    k = 0
    for a in range(len(order)):
        stack[0] = order[a]
        top = 1
        while top > 0:
            top -= 1
            g = stack[top]
            for q in range(mptr[g], mptr[g + 1]):
                perm[k] = members[q]
                k += 1
            c = head[g]
            while c >= 0:
                stack[top] = c
                top += 1
                c = nxt[c]
    return perm


def minimum_degree(indptr, indices, n) -> np.ndarray:
    """Fill-reducing permutation (new -> old, (n,)) of the symmetric pattern A + A^T: indistinguishable
    nodes grouped, minimum external degree on the groups (``min_degree``), groups expanded."""
    xadj, adj = symmetric_graph(np.asarray(indptr, np.int64), np.asarray(indices, np.int64), n)
    gid, cxadj, cadj, weight = quotient(xadj, adj, indistinguishable(xadj, adj))
    order, merged = min_degree(cxadj, cadj, weight)
    return expand(order, merged, gid)


def cuthill_mckee(indptr, indices, n) -> np.ndarray:
    """Reverse Cuthill-McKee permutation (new -> old) of A + A^T (scipy.sparse.csgraph)."""
    A = sp.csr_matrix((np.ones(len(indices)), np.asarray(indices), np.asarray(indptr)), shape=(n, n))
    return np.asarray(reverse_cuthill_mckee((A + A.T).tocsr(), symmetric_mode=True), np.int64)


# ------------------------------------------------------------------------------------------- symbolic

@njit
def upper_columns(indptr, indices, iperm, n):
    """Strictly upper triangle of the pattern of P (A + A^T) P^T by columns: (ptr, rows); rows unsorted,
    possibly repeated (both triangles given)."""
    ptr = np.zeros(n + 1, np.int64)
    for r in range(n):
        for p in range(indptr[r], indptr[r + 1]):
            a, b = iperm[r], iperm[indices[p]]
            if a != b:
                ptr[max(a, b) + 1] += 1
    for i in range(n):
        ptr[i + 1] += ptr[i]
    rows = np.empty(ptr[n], np.int64)
    fill = ptr[:n].copy()
    for r in range(n):
        for p in range(indptr[r], indptr[r + 1]):
            a, b = iperm[r], iperm[indices[p]]
            if a != b:
                k = max(a, b)
                rows[fill[k]] = min(a, b)
                fill[k] += 1
    return ptr, rows


@njit
def etree_counts(uptr, urows, n):
    """Elimination tree and column counts of L (strictly below the diagonal) by walking each row's subtree
    of the elimination tree (Davis 2006, §4.1 and his LDL package's ldl_symbolic): (parent (-1 at roots),
    lnz). O(nnz(L))."""
    parent = np.full(n, -1, np.int64)
    flag = np.empty(n, np.int64)
    lnz = np.zeros(n, np.int64)
    for k in range(n):
        flag[k] = k
        for p in range(uptr[k], uptr[k + 1]):
            i = urows[p]
            while flag[i] != k:
                if parent[i] == -1:
                    parent[i] = k
                lnz[i] += 1
                flag[i] = k
                i = parent[i]
    return parent, lnz


@njit
def fundamental_supernodes(parent, lnz, n):
    """Column ranges (sptr (ns+1,)) of the fundamental supernodes (Liu, Ng and Peyton, SIAM J. Matrix Anal.
    Appl. 14, 1993): j joins j-1's supernode when j-1's only parent is j, j has no other child and
    column j-1 of L is column j plus its diagonal."""
    nchild = np.zeros(n, np.int64)
    for j in range(n):
        if parent[j] >= 0:
            nchild[parent[j]] += 1
    sptr = np.empty(n + 1, np.int64)
    ns = 0
    for j in range(n):
        if j == 0 or not (parent[j - 1] == j and lnz[j - 1] == lnz[j] + 1 and nchild[j] == 1):
            sptr[ns] = j
            ns += 1
    sptr[ns] = n
    return sptr[:ns + 1]


@njit
def supernode_rows(uptr, urows, parent, lnz, sptr, n):
    """Row structure of each supernode, the pattern of its first column with the diagonal, ascending:
    (rptr (ns+1,), rows), and snode (n,) the supernode of each column."""
    ns = len(sptr) - 1
    snode = np.empty(n, np.int64)
    first = np.full(n, -1, np.int64)
    rptr = np.zeros(ns + 1, np.int64)
    for s in range(ns):
        snode[sptr[s]:sptr[s + 1]] = s
        first[sptr[s]] = s
        rptr[s + 1] = rptr[s] + lnz[sptr[s]] + 1
    rows = np.empty(rptr[ns], np.int64)
    fill = rptr[:ns].copy()
    flag = np.empty(n, np.int64)
    for k in range(n):
        flag[k] = k
        if first[k] >= 0:
            rows[fill[first[k]]] = k
            fill[first[k]] += 1
        for p in range(uptr[k], uptr[k + 1]):
            i = urows[p]
            while flag[i] != k:
                if first[i] >= 0:
                    rows[fill[first[i]]] = k
                    fill[first[i]] += 1
                flag[i] = k
                i = parent[i]
    return rptr, rows, snode


@njit
def value_offsets(sptr, rptr):
    """Offset of each supernode's dense column-major block (rows x columns) in the value array: (ns+1,)."""
    ns = len(sptr) - 1
    voff = np.zeros(ns + 1, np.int64)
    for s in range(ns):
        voff[s + 1] = voff[s] + (rptr[s + 1] - rptr[s]) * (sptr[s + 1] - sptr[s])
    return voff


@njit
def has_entry(indptr, indices, r, c):
    for p in range(indptr[r], indptr[r + 1]):
        if indices[p] == c:
            return True
    return False


@njit
def data_map(indptr, indices, iperm, sptr, rptr, rows, snode, voff):
    """(nnz,) position in the value array where each input entry is added, -1 to ignore it: an entry above
    the diagonal of P A P^T is used only when its transpose is not given (one triangle given)."""
    n = len(iperm)
    out = np.full(indptr[n], -1, np.int64)
    for r in range(n):
        for p in range(indptr[r], indptr[r + 1]):
            c = indices[p]
            a, b = iperm[r], iperm[c]
            if a < b and has_entry(indptr, indices, c, r):
                continue
            k, j = max(a, b), min(a, b)
            s = snode[j]
            lo, hi = rptr[s], rptr[s + 1] - 1
            while lo < hi:
                mid = (lo + hi) // 2
                if rows[mid] < k:
                    lo = mid + 1
                else:
                    hi = mid
            m = rptr[s + 1] - rptr[s]
            out[p] = voff[s] + (j - sptr[s]) * m + (lo - rptr[s])
    return out


@njit
def update_lists(sptr, rptr, rows, snode):
    """Which supernodes update which (left-looking): for target s, entries uptr[s]:uptr[s+1] of (src, a, b):
    rows a:b of supernode src's structure lie in s's columns (rows a: of src then update s)."""
    ns = len(sptr) - 1
    cnt = np.zeros(ns + 1, np.int64)
    for d in range(ns):
        w = sptr[d + 1] - sptr[d]
        i, e = rptr[d] + w, rptr[d + 1]
        while i < e:
            s = snode[rows[i]]
            while i < e and rows[i] < sptr[s + 1]:
                i += 1
            cnt[s + 1] += 1
    for s in range(ns):
        cnt[s + 1] += cnt[s]
    src = np.empty(cnt[ns], np.int64)
    ra = np.empty(cnt[ns], np.int64)
    rb = np.empty(cnt[ns], np.int64)
    fill = cnt[:ns].copy()
    for d in range(ns):
        w = sptr[d + 1] - sptr[d]
        i, e = rptr[d] + w, rptr[d + 1]
        while i < e:
            s = snode[rows[i]]
            a = i
            while i < e and rows[i] < sptr[s + 1]:
                i += 1
            q = fill[s]
            src[q], ra[q], rb[q] = d, a - rptr[d], i - rptr[d]
            fill[s] += 1
    return cnt, src, ra, rb


@njit
def relative_rows(rptr, rows, uptr, usrc, ua, n):
    """For each update q (source d, its structure rows ua[q]:) the local positions of those rows in the
    target's structure: rel[relptr[q]:relptr[q+1]]."""
    ns = len(rptr) - 1
    nu = len(usrc)
    relptr = np.zeros(nu + 1, np.int64)
    for q in range(nu):
        d = usrc[q]
        relptr[q + 1] = relptr[q] + (rptr[d + 1] - rptr[d]) - ua[q]
    rel = np.empty(relptr[nu], np.int64)
    pos = np.empty(n, np.int64)
    for s in range(ns):
        for i in range(rptr[s], rptr[s + 1]):
            pos[rows[i]] = i - rptr[s]
        for q in range(uptr[s], uptr[s + 1]):
            d = usrc[q]
            for i in range(rptr[d] + ua[q], rptr[d + 1]):
                rel[relptr[q] + i - rptr[d] - ua[q]] = pos[rows[i]]
    return relptr, rel


@njit
def row_runs(relptr, rel, ua, min_run):
    """Runs of source rows with consecutive target positions, per update: runs run_ptr[q]:run_ptr[q+1], each
    starting at source row run_row (local to the source's structure) and target position run_pos, ending
    where the next begins (the last at the source's end). An update whose runs average fewer than
    ``min_run`` rows gets none: it goes through the buffer and a scatter."""
    nu = len(ua)
    count = np.zeros(nu, np.int64)
    for q in range(nu):
        nr = 1
        for t in range(relptr[q] + 1, relptr[q + 1]):
            if rel[t] != rel[t - 1] + 1:
                nr += 1
        if (relptr[q + 1] - relptr[q]) >= min_run * nr:
            count[q] = nr
    run_ptr = np.zeros(nu + 1, np.int64)
    for q in range(nu):
        run_ptr[q + 1] = run_ptr[q] + count[q]
    run_row = np.empty(run_ptr[nu], np.int64)
    run_pos = np.empty(run_ptr[nu], np.int64)
    for q in range(nu):
        if count[q] == 0:
            continue
        k = run_ptr[q]
        for t in range(relptr[q], relptr[q + 1]):
            if t == relptr[q] or rel[t] != rel[t - 1] + 1:
                run_row[k] = ua[q] + t - relptr[q]
                run_pos[k] = rel[t]
                k += 1
    return run_ptr, run_row, run_pos


@njit
def scatter_lists(dmap, sptr, rptr, voff):
    """How ``factor`` loads the input, branch-free: (assign_src, assign_dst) the first input entry at each
    position (by position), (add_src, add_dst) any later one there (duplicates), and ``fill`` the positions of
    the supernodes' lower trapezoids that no entry reaches (zeroed). The diagonal blocks' upper triangles
    are never read."""
    nv = voff[-1]
    first = np.full(nv, -1, np.int64)
    nadd = 0
    for p in range(len(dmap)):
        t = dmap[p]
        if t >= 0:
            if first[t] < 0:
                first[t] = p
            else:
                nadd += 1
    add_src = np.empty(nadd, np.int64)
    add_dst = np.empty(nadd, np.int64)
    nadd = 0
    for p in range(len(dmap)):
        t = dmap[p]
        if t >= 0 and first[t] != p:
            add_src[nadd], add_dst[nadd] = p, t
            nadd += 1
    na, nf = 0, 0
    for s in range(len(sptr) - 1):
        m = rptr[s + 1] - rptr[s]
        for c in range(sptr[s + 1] - sptr[s]):
            for i in range(c, m):
                if first[voff[s] + c * m + i] >= 0:
                    na += 1
                else:
                    nf += 1
    assign_src = np.empty(na, np.int64)
    assign_dst = np.empty(na, np.int64)
    fill = np.empty(nf, np.int64)
    na, nf = 0, 0
    for s in range(len(sptr) - 1):
        m = rptr[s + 1] - rptr[s]
        for c in range(sptr[s + 1] - sptr[s]):
            for i in range(c, m):
                t = voff[s] + c * m + i
                if first[t] >= 0:
                    assign_src[na], assign_dst[na] = first[t], t
                    na += 1
                else:
                    fill[nf] = t
                    nf += 1
    return assign_src, assign_dst, add_src, add_dst, fill


@njit
def diagonal_positions(sptr, rptr, voff):
    """(n,) position of D_k in the values."""
    out = np.empty(sptr[-1], np.int64)
    for s in range(len(sptr) - 1):
        m = rptr[s + 1] - rptr[s]
        for c in range(sptr[s + 1] - sptr[s]):
            out[sptr[s] + c] = voff[s] + c * m + c
    return out


@njit
def diagonal_stored(indptr, indices):
    """Every row stores its diagonal entry."""
    for r in range(len(indptr) - 1):
        if not has_entry(indptr, indices, r, r):
            return False
    return True


@dataclass(frozen=True)
class LDLSymbolic:
    """The analysis of one pattern (``analyse``), read-only, shared by every factorisation of the pattern.
    Index arrays are int64; 'permuted' indices are those of P A P^T; positions index LDLNumeric.values."""
    n: int  # unknowns
    ordering: str  # "mindeg", "rcm", "natural" or "given"
    perm: np.ndarray  # (n,) new -> old: row/column k of P A P^T is row/column perm[k] of A
    iperm: np.ndarray  # (n,) old -> new
    parent: np.ndarray  # (n,) elimination tree of P A P^T, -1 at roots
    colcount: np.ndarray  # (n,) nonzeros of each column of L strictly below the diagonal
    sptr: np.ndarray  # (ns+1,) columns sptr[s]:sptr[s+1] form supernode s
    rptr: np.ndarray  # (ns+1,) rows[rptr[s]:rptr[s+1]]: row structure of supernode s, ascending, its columns first
    rows: np.ndarray  # (rptr[ns],)
    voff: np.ndarray  # (ns+1,) supernode s's values: dense column-major (structure rows x columns) at voff[s]
    diag: np.ndarray  # (n,) position of D_k
    data_map: np.ndarray  # (nnz of the input,) position of each input entry data[p]; -1: ignored (its transpose is used)
    assign_src: np.ndarray  # input entries (indices into data) that set a position: values[assign_dst] = data[assign_src]
    assign_dst: np.ndarray
    add_src: np.ndarray  # duplicate input entries, added: values[add_dst] += data[add_src]
    add_dst: np.ndarray
    fill: np.ndarray  # positions no input entry reaches (fill-in of L), zeroed by each factorisation
    uptr: np.ndarray  # (ns+1,) updates of supernode s: entries uptr[s]:uptr[s+1] of usrc, ua, ub, relptr, run_ptr
    usrc: np.ndarray  # source supernode of each update
    ua: np.ndarray  # its structure rows ua:ub lie in the target's columns (local indices)
    ub: np.ndarray
    relptr: np.ndarray  # (updates+1,) rel[relptr[q]:relptr[q+1]]: target positions of update q's source rows ua[q]:
    rel: np.ndarray
    run_ptr: np.ndarray  # (updates+1,) runs of consecutive target positions (row_runs); none: buffer + scatter
    run_row: np.ndarray  # first source row of each run (local to the source's structure)
    run_pos: np.ndarray  # its target position
    nnz_l: int  # nonzeros of L strictly below the diagonal
    max_rows: int  # largest supernode structure (workspace length)

    @property
    def n_supernodes(self) -> int:
        return len(self.sptr) - 1

    @property
    def n_values(self) -> int:
        """Length of LDLNumeric.values: nnz(L) + n plus the unused upper triangles of the supernodes'
        diagonal blocks."""
        return int(self.voff[-1])

    @property
    def madds(self) -> int:
        """Multiply-adds of the factorisation: sum_j c_j (c_j + 1) / 2 over the column counts c_j."""
        c = self.colcount
        return int((c * (c + 1) // 2).sum())


@dataclass
class LDLNumeric:
    """A factorisation of one LDLSymbolic's pattern (``factor``); ``factor(sym, data, out)`` refactorises in
    place."""
    values: np.ndarray  # (sym.n_values,) per supernode dense column-major: L below the diagonal, D on it
    buf: np.ndarray  # (4 sym.max_rows,) workspace of factor and of one-vector solves
    n_negative: int = 0  # negative pivots: D's negative count, the inertia's (when the factorisation succeeded)

    @staticmethod
    def empty(sym: LDLSymbolic) -> "LDLNumeric":
        return LDLNumeric(np.zeros(sym.n_values), np.zeros(4 * max(sym.max_rows, 1)))

    def diagonal(self, sym: LDLSymbolic) -> np.ndarray:
        """D (n,) in the permuted order."""
        return self.values[sym.diag]


def analyse(indptr, indices, n: int, ordering="mindeg") -> LDLSymbolic:
    """The symbolic analysis of the n x n symmetric pattern given in CSR (``indptr`` (n+1,), ``indices``;
    both triangles or one, duplicates allowed, every row storing its diagonal; the pattern analysed is that
    of A + A^T). ``ordering``: "mindeg" (minimum degree, the default), "rcm" (reverse Cuthill-McKee),
    "natural", or a permutation array (new -> old)."""
    indptr = np.ascontiguousarray(indptr, dtype=np.int64)
    indices = np.ascontiguousarray(indices, dtype=np.int64)
    if len(indptr) != n + 1 or (n and not diagonal_stored(indptr, indices)):
        raise ValueError("the pattern must have n + 1 row pointers and store every diagonal entry")
    if isinstance(ordering, str):
        if ordering not in ORDERINGS:
            raise ValueError(f"ordering {ordering!r}: one of {ORDERINGS} or a permutation")
        perm = {"mindeg": minimum_degree, "rcm": cuthill_mckee,
                "natural": lambda *_: np.arange(n, dtype=np.int64)}[ordering](indptr, indices, n)
        name = ordering
    else:
        perm, name = np.asarray(ordering, dtype=np.int64), "given"
    if perm.shape != (n,) or not np.array_equal(np.sort(perm), np.arange(n)):
        raise ValueError(f"ordering {name!r} is not a permutation of range(n)")
    iperm = np.empty(n, np.int64)
    iperm[perm] = np.arange(n)
    uptr, urows = upper_columns(indptr, indices, iperm, n)
    parent, lnz = etree_counts(uptr, urows, n)
    sptr = fundamental_supernodes(parent, lnz, n)
    rptr, rows, snode = supernode_rows(uptr, urows, parent, lnz, sptr, n)
    voff = value_offsets(sptr, rptr)
    dmap = data_map(indptr, indices, iperm, sptr, rptr, rows, snode, voff)
    up, usrc, ua, ub = update_lists(sptr, rptr, rows, snode)
    relptr, rel = relative_rows(rptr, rows, up, usrc, ua, n)
    run_ptr, run_row, run_pos = row_runs(relptr, rel, ua, MIN_RUN)
    return LDLSymbolic(n, name, perm, iperm, parent, lnz, sptr, rptr, rows, voff, diagonal_positions(sptr, rptr, voff),
                       dmap, *scatter_lists(dmap, sptr, rptr, voff), up, usrc, ua, ub, relptr, rel, run_ptr, run_row,
                       run_pos, int(lnz.sum()), int(np.diff(rptr).max(initial=0)))


# ------------------------------------------------------------------------------------------- numeric
# The kernels index the flat value array with unsigned integers (np.uint64, U below): numba wraps negative
# signed indices, and that select keeps LLVM from vectorising the loops (measured: an axpy over a flat
# array at a signed offset 0.7 ns per multiply-add, unsigned 0.1-0.3, three columns fused 0.06-0.09).
# Mixing uint64 with int64 gives float64 in numba: every index is converted with U() first. Array views
# passed to non-inlined functions cost reference counting (measured 50 ns a call): the helpers are inlined.
U = np.uint64


@njit
def scatter_values(assign_src, assign_dst, add_src, add_dst, fill, diag, data, values):
    """values <- the input (scatter_lists), zeros at the fill; returns max|diag A|."""
    for k in range(len(fill)):
        values[U(fill[k])] = 0.0
    for k in range(len(assign_src)):
        values[U(assign_dst[k])] = data[U(assign_src[k])]
    for k in range(len(add_src)):
        values[U(add_dst[k])] += data[U(add_src[k])]
    dmax = 0.0
    for k in range(len(diag)):
        dmax = max(dmax, abs(values[U(diag[k])]))
    return dmax


@njit_inline
def sub_columns(y, yb, values, od, md, c0, c1, jj, i0, ln, assign):
    """y[yb + r] -= sum_{c0 <= c < c1} L(i0 + r, c) D_c L(jj, c) for r < ln, over columns of a factorised
    supernode (values at od, md rows: L below the diagonal, D on it), three columns per pass (a mesh
    vertex's); ``assign``: y = - that sum instead (c1 > c0). Indices uint64."""
    c = c0
    first = assign
    while c < c1:
        x0 = od + c * md
        if c1 - c >= U(3):
            x1 = x0 + md
            x2 = x1 + md
            t0 = values[x0 + jj] * values[x0 + c]
            t1 = values[x1 + jj] * values[x1 + c + U(1)]
            t2 = values[x2 + jj] * values[x2 + c + U(2)]
            x0 += i0
            x1 += i0
            x2 += i0
            if first:
                for r in range(ln):
                    y[yb + r] = -(t0 * values[x0 + r] + t1 * values[x1 + r] + t2 * values[x2 + r])
            else:
                for r in range(ln):
                    y[yb + r] -= t0 * values[x0 + r] + t1 * values[x1 + r] + t2 * values[x2 + r]
            c += U(3)
        else:
            t0 = values[x0 + jj] * values[x0 + c]
            x0 += i0
            if first:
                for r in range(ln):
                    y[yb + r] = -t0 * values[x0 + r]
            else:
                for r in range(ln):
                    y[yb + r] -= t0 * values[x0 + r]
            c += U(1)
        first = False


@njit_inline
def tile_rows(y, y0, y1, y2, y3, values, od, md, c0, c1, jj, i0, ln):
    """Four target columns at once, those of source rows jj..jj+3: y[yk + r] -= sum_{c0 <= c < c1}
    L(i0 + r, c) D_c L(jj + k, c) for r < ln (yk: column k's position of source row i0), three source columns
    per pass: one pass over the rows for 12 multiply-adds each. Indices uint64."""
    c = c0
    while c < c1:
        x0 = od + c * md
        if c1 - c >= U(3):
            x1 = x0 + md
            x2 = x1 + md
            d0, d1, d2 = values[x0 + c], values[x1 + c + U(1)], values[x2 + c + U(2)]
            j0, j1, j2 = x0 + jj, x1 + jj, x2 + jj
            t00, t01, t02 = values[j0] * d0, values[j1] * d1, values[j2] * d2
            t10, t11, t12 = values[j0 + U(1)] * d0, values[j1 + U(1)] * d1, values[j2 + U(1)] * d2
            t20, t21, t22 = values[j0 + U(2)] * d0, values[j1 + U(2)] * d1, values[j2 + U(2)] * d2
            t30, t31, t32 = values[j0 + U(3)] * d0, values[j1 + U(3)] * d1, values[j2 + U(3)] * d2
            x0 += i0
            x1 += i0
            x2 += i0
            for r in range(ln):
                l0, l1, l2 = values[x0 + r], values[x1 + r], values[x2 + r]
                y[y0 + r] -= t00 * l0 + t01 * l1 + t02 * l2
                y[y1 + r] -= t10 * l0 + t11 * l1 + t12 * l2
                y[y2 + r] -= t20 * l0 + t21 * l1 + t22 * l2
                y[y3 + r] -= t30 * l0 + t31 * l1 + t32 * l2
            c += U(3)
        else:
            d0 = values[x0 + c]
            j0 = x0 + jj
            t0, t1, t2, t3 = values[j0] * d0, values[j0 + U(1)] * d0, values[j0 + U(2)] * d0, values[j0 + U(3)] * d0
            x0 += i0
            for r in range(ln):
                l0 = values[x0 + r]
                y[y0 + r] -= t0 * l0
                y[y1 + r] -= t1 * l0
                y[y2 + r] -= t2 * l0
                y[y3 + r] -= t3 * l0
            c += U(1)


@njit_inline
def tile_triangle(y, a00, a10, a20, a11, a21, a22, values, od, md, c0, c1, jj):
    """The part of ``tile_rows``' four columns above source row jj + 3: (row jj + i, column k) for
    k <= i < 3, at y[a_ik], each minus sum_{c0 <= c < c1} L(jj + i, c) D_c L(jj + k, c)."""
    s00 = s10 = s20 = s11 = s21 = s22 = 0.0
    for c in range(c0, c1):
        x = od + c * md
        d = values[x + c]
        l0, l1, l2 = values[x + jj], values[x + jj + U(1)], values[x + jj + U(2)]
        u0, u1, u2 = l0 * d, l1 * d, l2 * d
        s00 += l0 * u0
        s10 += l1 * u0
        s20 += l2 * u0
        s11 += l1 * u1
        s21 += l2 * u1
        s22 += l2 * u2
    y[a00] -= s00
    y[a10] -= s10
    y[a20] -= s20
    y[a11] -= s11
    y[a21] -= s21
    y[a22] -= s22


@njit_inline
def scatter_column(values, tc, rel, r0, buf, b0, ln):
    """values[tc + rel[r0 + i]] += buf[b0 + i] for i < ln (a buffered update column into its target)."""
    for i in range(ln):
        values[tc + U(rel[r0 + i])] += buf[b0 + i]


@njit_inline
def update_runs(values, tc, jj, run_row, run_pos, k0, k1, od, md, wd):
    """One target column (of source row jj, at tc) minus the source's update of its rows i >= jj, run by run
    straight into the target."""
    for k in range(k0, k1):
        i1 = U(run_row[k + 1]) if k + 1 < k1 else md
        s = max(U(run_row[k]), jj)
        if s < i1:
            sub_columns(values, tc + U(run_pos[k]) + s - U(run_row[k]), values, od, md, U(0), wd, jj, s, i1 - s, False)


@njit_inline
def tile_runs(values, tc0, tc1, tc2, tc3, jj, run_row, run_pos, k0, k1, od, md, wd):
    """``tile_rows`` for the source rows i >= jj + 3 of four target columns (at tc0..tc3), run by run."""
    for k in range(k0, k1):
        i1 = U(run_row[k + 1]) if k + 1 < k1 else md
        s = max(U(run_row[k]), jj + U(3))
        if s < i1:
            p = U(run_pos[k]) + s - U(run_row[k])
            tile_rows(values, tc0 + p, tc1 + p, tc2 + p, tc3 + p, values, od, md, U(0), wd, jj, s, i1 - s)


@njit
def apply_update(values, rel, rb, run_row, run_pos, k0, k1, buf, od, md, wd, a, b, ot, mt):
    """Target supernode (values at ot, mt rows) minus the update of a factorised source supernode (values at
    od, md rows, wd columns) through its structure rows a:b: the target column of source row jj (a <= jj < b)
    loses sum_c L(i, c) D_c L(jj, c) at the target positions rel[rb + i - a] of the source rows i >= jj
    (Davis 2006, §9.1, left-looking supernodal). Four target columns per pass, the rest one by one; with
    runs (k0 < k1) straight into the target, else through ``buf`` and a scatter. Indices uint64."""
    jj = a
    while jj + U(4) <= b:
        r = rb + jj - a
        tc0 = ot + U(rel[r]) * mt
        tc1 = ot + U(rel[r + U(1)]) * mt
        tc2 = ot + U(rel[r + U(2)]) * mt
        tc3 = ot + U(rel[r + U(3)]) * mt
        if k0 < k1:
            p0, p1, p2 = U(rel[r]), U(rel[r + U(1)]), U(rel[r + U(2)])
            tile_triangle(values, tc0 + p0, tc0 + p1, tc0 + p2, tc1 + p1, tc1 + p2, tc2 + p2, values, od, md, U(0),
                          wd, jj)
            tile_runs(values, tc0, tc1, tc2, tc3, jj, run_row, run_pos, k0, k1, od, md, wd)
        else:
            ld = md - jj
            for i in range(U(4) * ld):
                buf[i] = 0.0
            tile_triangle(buf, U(0), U(1), U(2), ld + U(1), ld + U(2), U(2) * ld + U(2), values, od, md, U(0), wd, jj)
            tile_rows(buf, U(3), ld + U(3), U(2) * ld + U(3), U(3) * ld + U(3), values, od, md, U(0), wd, jj,
                      jj + U(3), ld - U(3))
            scatter_column(values, tc0, rel, r, buf, U(0), ld)
            scatter_column(values, tc1, rel, r + U(1), buf, ld + U(1), ld - U(1))
            scatter_column(values, tc2, rel, r + U(2), buf, U(2) * ld + U(2), ld - U(2))
            scatter_column(values, tc3, rel, r + U(3), buf, U(3) * ld + U(3), ld - U(3))
        jj += U(4)
    while jj < b:
        r = rb + jj - a
        tc = ot + U(rel[r]) * mt
        if k0 < k1:
            update_runs(values, tc, jj, run_row, run_pos, k0, k1, od, md, wd)
        else:
            sub_columns(buf, U(0), values, od, md, U(0), wd, jj, jj, md - jj, True)
            scatter_column(values, tc, rel, r, buf, U(0), md - jj)
        jj += U(1)


@njit
def factor_block(values, o, m, w, tiny_abs):
    """Dense LDL^T of a supernode (values at o, m rows, w columns; uint64) after all its updates, four
    columns at a time (left-looking inside the block, the update kernels on the block's own columns).
    Returns (failing column or -1, negative pivots)."""
    neg = 0
    c0 = U(0)
    while c0 < w:
        nb = min(w - c0, U(4))
        col0 = o + c0 * m
        if c0 > U(0):
            if nb == U(4):
                tile_triangle(values, col0 + c0, col0 + c0 + U(1), col0 + c0 + U(2), col0 + m + c0 + U(1),
                              col0 + m + c0 + U(2), col0 + U(2) * m + c0 + U(2), values, o, m, U(0), c0, c0)
                tile_rows(values, col0 + c0 + U(3), col0 + m + c0 + U(3), col0 + U(2) * m + c0 + U(3),
                          col0 + U(3) * m + c0 + U(3), values, o, m, U(0), c0, c0, c0 + U(3), m - c0 - U(3))
            else:
                for k in range(nb):
                    sub_columns(values, col0 + k * m + c0 + k, values, o, m, U(0), c0, c0 + k, c0 + k, m - c0 - k,
                                False)
        for k in range(nb):
            c = c0 + k
            col = col0 + k * m
            if k > U(0):
                sub_columns(values, col + c, values, o, m, c0, c, c, c, m - c, False)
            dc = values[col + c]
            if not abs(dc) > tiny_abs:
                return np.int64(c), neg
            if dc < 0.0:
                neg += 1
            inv = 1.0 / dc
            for i in range(c + U(1), m):
                values[col + i] *= inv
        c0 += nb
    return np.int64(-1), neg


@njit
def factor_kernel(sptr, rptr, voff, diag, assign_src, assign_dst, add_src, add_dst, fill, uptr, usrc, ua, ub, relptr,
                  rel, run_ptr, run_row, run_pos, data, values, buf, tiny):
    """Load the input and factorise, supernode by supernode (left-looking). Returns (-1 or the failing
    pivot's permuted index, negative pivots, max|diag A|)."""
    dmax = scatter_values(assign_src, assign_dst, add_src, add_dst, fill, diag, data, values)
    k, neg = factor_loaded(sptr, rptr, voff, uptr, usrc, ua, ub, relptr, rel, run_ptr, run_row, run_pos, values, buf,
                           tiny * dmax)
    return k, neg, dmax


@njit
def factor_loaded(sptr, rptr, voff, uptr, usrc, ua, ub, relptr, rel, run_ptr, run_row, run_pos, values, buf, tiny_abs):
    """The factorisation of ``factor_kernel`` on values already loaded (scatter_values, or a caller's own
    loading): (-1 or the failing pivot's permuted index, negative pivots); a pivot |d| <= tiny_abs fails."""
    neg = 0
    for s in range(len(sptr) - 1):
        ot, w, mt = U(voff[s]), U(sptr[s + 1] - sptr[s]), U(rptr[s + 1] - rptr[s])
        for q in range(uptr[s], uptr[s + 1]):
            d = usrc[q]
            apply_update(values, rel, U(relptr[q]), run_row, run_pos, run_ptr[q], run_ptr[q + 1], buf, U(voff[d]),
                         U(rptr[d + 1] - rptr[d]), U(sptr[d + 1] - sptr[d]), U(ua[q]), U(ub[q]), ot, mt)
        k, ng = factor_block(values, ot, mt, w, tiny_abs)
        neg += ng
        if k >= 0:
            return sptr[s] + k, neg
    return -1, neg


def factor(sym: LDLSymbolic, data, out: LDLNumeric | None = None, tiny: float = TINY) -> LDLNumeric:
    """L D L^T of the matrix whose CSR values are ``data`` (in the order of the analysed ``indices``), into
    ``out`` (no allocation) or a new LDLNumeric. Raises StepError naming the pivot when
    |d_k| <= tiny max|diag A| (singular, or not factorisable without pivoting in this order)."""
    if out is None:
        out = LDLNumeric.empty(sym)
    data = np.asarray(data, dtype=np.float64)
    if data.shape != sym.data_map.shape:
        raise ValueError(f"data has shape {data.shape}, the pattern {sym.data_map.shape[0]} entries")
    k, neg, dmax = factor_kernel(sym.sptr, sym.rptr, sym.voff, sym.diag, sym.assign_src, sym.assign_dst, sym.add_src,
                                 sym.add_dst, sym.fill, sym.uptr, sym.usrc, sym.ua, sym.ub, sym.relptr, sym.rel,
                                 sym.run_ptr, sym.run_row, sym.run_pos, data, out.values, out.buf, tiny)
    out.n_negative = int(neg)
    if k >= 0:
        raise pivot_error(sym, out, k, dmax, tiny)
    return out


def pivot_error(sym: LDLSymbolic, num: LDLNumeric, k: int, dmax: float, tiny: float = TINY) -> StepError:
    """The StepError of a factorisation (factor_kernel) that stopped at pivot k, max|diag A| = dmax."""
    return StepError(f"sparse LDL^T: pivot {k} (row {int(sym.perm[k])} of the matrix) is "
                     f"{num.values[sym.diag[k]]:.3g}, |d| <= {tiny:g} max|diag| = {tiny * dmax:.3g}: the matrix is "
                     "singular, or has no LDL^T without pivoting in this order")


# ------------------------------------------------------------------------------------------- solve

@njit
def solve_vector_kernel(sptr, rptr, rows, voff, diag, values, x, buf):
    """x <- (L D L^T)^-1 x in place (x (n,), permuted order): per supernode, the dense triangle on its own
    columns, then the rows below (forward: each row loses its L row times the columns' entries of x, three
    columns per pass, straight into x for a mesh vertex's 3-column supernode, else summed in ``buf`` and
    scattered once; backward: the rows below gathered into ``buf`` once, then three columns' dot products
    per pass, independent sums that keep the core busy where one sum's chain of dependent additions left
    it waiting). Every entry of x takes its terms in the order of the column-by-column sweep (the passes
    only interleave independent sums), so the numbers are those of the plain sweep (measured on the STARFISH
    reduced system, 474 unknowns: 28-39 -> 20 us a solve, 19 -> 14 us for a unit vector). The forward sweep
    skips a supernode whose entries of x are all zero when it is reached (it would subtract zeros): a
    sparse right-hand side, such as the unit vectors and matrix columns of coupled_kernel's bordered updates,
    then costs the supernodes on its elimination-tree paths only (Gilbert & Peierls 1988; Davis 2006, §3.2).
    The same numbers as the full sweep, up to the sign of an exact zero."""
    ns = len(sptr) - 1
    for s in range(ns):
        o, f, w, m, r0 = U(voff[s]), U(sptr[s]), U(sptr[s + 1] - sptr[s]), U(rptr[s + 1] - rptr[s]), U(rptr[s])
        live = False
        for c in range(w):
            if x[f + c] != 0.0:
                live = True
                break
        if not live:
            continue
        for c in range(w):
            xc = x[f + c]
            col = o + c * m
            for i in range(c + U(1), w):
                x[f + i] -= values[col + i] * xc
        nb = m - w
        if nb == U(0):
            continue
        rb = r0 + w
        if w == U(3):  # a mesh vertex: the three columns' terms straight into x
            c0 = o + w
            c1 = c0 + m
            c2 = c1 + m
            x0, x1, x2 = x[f], x[f + U(1)], x[f + U(2)]
            for i in range(nb):
                x[U(rows[rb + i])] -= values[c0 + i] * x0 + values[c1 + i] * x1 + values[c2 + i] * x2
            continue
        c = U(0)
        while c < w:  # buf[i] = sum_c L(w + i, c) x_c, in column order
            col = o + c * m + w
            if w - c >= U(3):
                c1 = col + m
                c2 = c1 + m
                x0, x1, x2 = x[f + c], x[f + c + U(1)], x[f + c + U(2)]
                if c == U(0):
                    for i in range(nb):
                        buf[i] = values[col + i] * x0 + values[c1 + i] * x1 + values[c2 + i] * x2
                else:
                    for i in range(nb):
                        buf[i] = buf[i] + values[col + i] * x0 + values[c1 + i] * x1 + values[c2 + i] * x2
                c += U(3)
            else:
                x0 = x[f + c]
                if c == U(0):
                    for i in range(nb):
                        buf[i] = values[col + i] * x0
                else:
                    for i in range(nb):
                        buf[i] += values[col + i] * x0
                c += U(1)
        for i in range(nb):
            x[U(rows[rb + i])] -= buf[i]
    for j in range(len(diag)):
        x[j] /= values[U(diag[j])]
    for s in range(ns - 1, -1, -1):
        o, f, w, m, r0 = U(voff[s]), U(sptr[s]), U(sptr[s + 1] - sptr[s]), U(rptr[s + 1] - rptr[s]), U(rptr[s])
        nb = m - w
        if nb > U(0):
            rb = r0 + w
            for i in range(nb):
                buf[i] = x[U(rows[rb + i])]
            c = U(0)
            while c < w:
                c0 = o + c * m + w
                if w - c >= U(3):
                    c1 = c0 + m
                    c2 = c1 + m
                    a0 = a1 = a2 = 0.0
                    for i in range(nb):
                        bi = buf[i]
                        a0 += values[c0 + i] * bi
                        a1 += values[c1 + i] * bi
                        a2 += values[c2 + i] * bi
                    x[f + c] -= a0
                    x[f + c + U(1)] -= a1
                    x[f + c + U(2)] -= a2
                    c += U(3)
                else:
                    acc = 0.0
                    for i in range(nb):
                        acc += values[c0 + i] * buf[i]
                    x[f + c] -= acc
                    c += U(1)
        for cc in range(w):
            c = w - U(1) - cc
            col = o + c * m
            acc = x[f + c]
            for i in range(c + U(1), w):
                acc -= values[col + i] * x[f + i]
            x[f + c] = acc


@njit
def solve_matrix_kernel(sptr, rptr, rows, voff, diag, values, x):
    """x <- (L D L^T)^-1 x in place for k right-hand sides at once (x (n, k) C-ordered, permuted order, flat
    uint64 indexing): per supernode, each row below its columns loses its L row times the columns' rows of x
    (forward), each column's row of x loses the column of L times the rows below (backward), three at a
    time; the inner loops run over the right-hand sides."""
    ns = len(sptr) - 1
    k = U(x.shape[1])
    xf = x.reshape(-1)
    for s in range(ns):
        o, f, w, m, r0 = U(voff[s]), U(sptr[s]), U(sptr[s + 1] - sptr[s]), U(rptr[s + 1] - rptr[s]), U(rptr[s])
        for i in range(U(1), m):
            y = (f + i if i < w else U(rows[r0 + i])) * k
            nc = min(i, w)
            c = U(0)
            while c + U(3) <= nc:
                l0, l1, l2 = values[o + c * m + i], values[o + (c + U(1)) * m + i], values[o + (c + U(2)) * m + i]
                x0 = (f + c) * k
                x1 = x0 + k
                x2 = x1 + k
                for t in range(k):
                    xf[y + t] -= l0 * xf[x0 + t] + l1 * xf[x1 + t] + l2 * xf[x2 + t]
                c += U(3)
            while c < nc:
                l0 = values[o + c * m + i]
                x0 = (f + c) * k
                for t in range(k):
                    xf[y + t] -= l0 * xf[x0 + t]
                c += U(1)
    for j in range(len(diag)):
        inv = 1.0 / values[U(diag[j])]
        y = U(j) * k
        for t in range(k):
            xf[y + t] *= inv
    for s in range(ns - 1, -1, -1):
        o, f, w, m, r0 = U(voff[s]), U(sptr[s]), U(sptr[s + 1] - sptr[s]), U(rptr[s + 1] - rptr[s]), U(rptr[s])
        for cc in range(w):
            c = w - U(1) - cc
            col = o + c * m
            y = (f + c) * k
            i = c + U(1)
            while i + U(3) <= m:
                l0, l1, l2 = values[col + i], values[col + i + U(1)], values[col + i + U(2)]
                x0 = (f + i if i < w else U(rows[r0 + i])) * k
                x1 = (f + i + U(1) if i + U(1) < w else U(rows[r0 + i + U(1)])) * k
                x2 = (f + i + U(2) if i + U(2) < w else U(rows[r0 + i + U(2)])) * k
                for t in range(k):
                    xf[y + t] -= l0 * xf[x0 + t] + l1 * xf[x1 + t] + l2 * xf[x2 + t]
                i += U(3)
            while i < m:
                l0 = values[col + i]
                x0 = (f + i if i < w else U(rows[r0 + i])) * k
                for t in range(k):
                    xf[y + t] -= l0 * xf[x0 + t]
                i += U(1)


def solve(sym: LDLSymbolic, num: LDLNumeric, b) -> np.ndarray:
    """A^-1 b for b (n,) or (n, k): a new array of b's shape."""
    b = np.asarray(b, dtype=np.float64)
    if b.ndim not in (1, 2) or b.shape[0] != sym.n:
        raise ValueError(f"b has shape {b.shape}, expected ({sym.n},) or ({sym.n}, k)")
    x = b[sym.perm]  # a C-ordered copy in the permuted order
    if b.ndim == 1:
        solve_vector_kernel(sym.sptr, sym.rptr, sym.rows, sym.voff, sym.diag, num.values, x, num.buf)
    else:
        solve_matrix_kernel(sym.sptr, sym.rptr, sym.rows, sym.voff, sym.diag, num.values, x)
    out = np.empty_like(x)
    out[sym.perm] = x
    return out
