"""The coupled solve's staggered floor-contact loop (solvers/coupled.py: paper Alg. 2, Eq. 11-12 as primal
active sets on the vertex DOFs of the reduced system) as one compiled call on the step's arrays: the friction
stage, the normal stage, the joint-limit working set, and the held system on the reduced matrix's LDL^T
(sparse_ldl's factor and solve kernels, compiled into this module's cache, which jit.drop_stale_caches drops
when either file changes) with the bordered (capacitance) updates of its held set
(Golub & Van Loan §2.1.4). The algorithm and its notation are coupled.py's module docstring; ``staggered``
reads and writes the contact state (normal, stick, sign, alpha, known) in place and returns its counters in
``info`` (INFO_*). Before it, each sub-problem solve cost ~100-200 us of numpy calls in Python around a
~30 us LDL^T solve.

The held system: the reduced system with a set H of DOFs held at given velocities and the skeleton rows
W = [G; active limit rows], W z_r = w, by multipliers. One LDL^T per *base* held set H0 (identity rows and
columns, ``held_factor``); a held set H that differs from H0 by a few DOFs (added: held now, free in H0;
released: free now, held in H0) is solved on the base factor by a small capacitance system, with A~0 the base
matrix:

    z = z0 - Y0 lam + sum_a w_a mu_a + sum_j u_j y_j,    z0 = A~0^-1 f0,  Y0 = A~0^-1 W^T,
    w_a = A~0^-1 e_a (a added, mu_a its reaction),    u_j = e_j - A~0^-1 P0 A e_j (j released, y_j = z_j - v_j),

P0 the projection off H0, and the multipliers from W z_r = w, z_a = v_a, (A z)_j = rhs_j (``border``): one
base solve per changed DOF, kept while the base stands. The base is refactorised when more than
``max_changes`` DOFs differ (0: on every change, so the solution is that of the final held set's own
factorisation whatever the path, as on a frictionless floor, where a restarted run then equals a continuing
one bit for bit)."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import drop_stale_caches, njit
from redmax_ros.core.solvers.sparse_ldl import (U, factor_kernel, factor_loaded, scatter_values, solve_matrix_kernel,
                                                solve_vector_kernel)

# the kernels below carry sparse_ldl's factor and solve kernels: an edit of either file recompiles them
drop_stale_caches("solvers/coupled_kernel.py", ("solvers/coupled_kernel.py", "solvers/sparse_ldl.py", "jit.py"))

# info (int64) slots written by ``staggered``
INFO_ITER, INFO_FACTORS, INFO_STATUS, INFO_NFIXED, INFO_CONVERGED, INFO_PIVOT, INFO_NORMAL, INFO_STUCK, INFO_NSTATE = \
    range(9)
INFO_LEN = 9
FINFO_DMAX, FINFO_RESIDUAL, FINFO_VIOLATION = range(3)  # finfo (float64) slots
FINFO_LEN = 3
OK, FACTOR_FAILED, BORDER_SINGULAR = 0, 1, 2  # INFO_STATUS


@njit
def csr_matvec(indptr, indices, data, x, out):
    """out <- A x, three rows per pass (``csr_rows3_dot``)."""
    n = len(indptr) - 1
    i = 0
    while i + 3 <= n:
        out[i], out[i + 1], out[i + 2] = csr_rows3_dot(indptr, indices, data, i, x)
        i += 3
    while i < n:
        out[i] = csr_row_dot(indptr, indices, data, i, x)
        i += 1


@njit
def held_columns(indptr, indices, tpos, data, dofs, vals, out):
    """out <- A[:, dofs] vals of the symmetric CSR matrix (``dofs`` ascending), reading row j's entries' transposes
    data[tpos[e]] = A[indices[e], j]: nnz of the held rows instead of a product with the whole matrix. Bit for bit
    the csr_matvec of the vector with vals on dofs (the nonzero terms of each out[i] are added in the same
    ascending column order; the skipped terms are exact zeros)."""
    for i in range(len(out)):
        out[i] = 0.0
    for q in range(len(dofs)):
        j = dofs[q]
        v = vals[q]
        for e in range(U(indptr[j]), U(indptr[j + 1])):
            out[U(indices[e])] += data[U(tpos[e])] * v


@njit
def csr_row_dot(indptr, indices, data, j, x):
    """(A x)_j (indices uint64, as sparse_ldl's kernels: no wrap-around test on each gather)."""
    acc = 0.0
    for e in range(U(indptr[j]), U(indptr[j + 1])):
        acc += data[e] * x[U(indices[e])]
    return acc


@njit
def csr_rows3_dot(indptr, indices, data, j, x):
    """((A x)_j, (A x)_j+1, (A x)_j+2): the three rows' sums interleaved (a mesh vertex's rows have the same
    length), each adding its terms in its row's order, so the numbers of ``csr_row_dot``; three independent
    chains of additions keep the core busy where one chain left it waiting, and the uint64 indices spare the
    wrap-around tests (the STARFISH's A x, 474 rows, 16140 entries: 31 -> 15 us)."""
    s0, s1, s2 = U(indptr[j]), U(indptr[j + 1]), U(indptr[j + 2])
    l0, l1, l2 = s1 - s0, s2 - s1, U(indptr[j + 3]) - s2
    m = min(l0, l1, l2)
    a0 = a1 = a2 = 0.0
    for q in range(m):
        a0 += data[s0 + q] * x[U(indices[s0 + q])]
        a1 += data[s1 + q] * x[U(indices[s1 + q])]
        a2 += data[s2 + q] * x[U(indices[s2 + q])]
    for q in range(m, l0):
        a0 += data[s0 + q] * x[U(indices[s0 + q])]
    for q in range(m, l1):
        a1 += data[s1 + q] * x[U(indices[s1 + q])]
    for q in range(m, l2):
        a2 += data[s2 + q] * x[U(indices[s2 + q])]
    return a0, a1, a2


@njit
def ldl_solve(ss, values, lbuf, rhs, out, tmp):
    """out <- A^-1 rhs on the factor in ``values`` (ss = (sptr, rptr, rows, voff, diag, perm) of the analysis)."""
    sptr, rptr, rows, voff, sdiag, perm = ss
    for i in range(len(perm)):
        tmp[i] = rhs[U(perm[i])]
    solve_vector_kernel(sptr, rptr, rows, voff, sdiag, values, tmp, lbuf)
    for i in range(len(perm)):
        out[U(perm[i])] = tmp[i]


@njit
def ldl_factor(fs, values, lbuf, data, tiny):
    """(failing pivot or -1, max|diag A|): the LDL^T of ``data`` into ``values`` (fs: the analysis' arrays in
    factor_kernel's order)."""
    k, _, dmax = factor_kernel(fs[0], fs[1], fs[2], fs[3], fs[4], fs[5], fs[6], fs[7], fs[8], fs[9], fs[10],
                               fs[11], fs[12], fs[13], fs[14], fs[15], fs[16], fs[17], data, values, lbuf, tiny)
    return k, dmax


@njit
def held_factor(fs, values, lbuf, data, dmap, indptr, tpos, adiag, dofs, tiny):
    """ldl_factor of the held matrix (``data`` with the rows and columns of ``dofs`` replaced by the identity,
    same CSR pattern) without forming it: ``data`` loaded into the factor's storage, then the positions there of
    the held rows' and columns' entries set to 0 and of their diagonals to 1 (dmap: sparse_ldl's data_map,
    each entry's position or -1). A position holds one entry (or the sum of duplicates of one entry, all held or
    none), so the loaded values, max|diag| and the factor are those of the held matrix, bit for bit; the
    matrix's copy (16140 values on the starfish) is not written and read back: coupled_solve 135.9 -> 129.2 us
    (CPU, the inputs of step 301, alternating blocks of 20 calls in one process, medians of 150)."""
    scatter_values(fs[4], fs[5], fs[6], fs[7], fs[8], fs[3], data, values)
    for j in dofs:
        for e in range(U(indptr[j]), U(indptr[j + 1])):
            d = dmap[e]
            if d >= 0:
                values[U(d)] = 0.0
            d = dmap[U(tpos[e])]
            if d >= 0:
                values[U(d)] = 0.0
    for j in dofs:
        values[U(dmap[U(adiag[j])])] = 1.0
    diag = fs[3]
    dmax = 0.0
    for k in range(len(diag)):
        dmax = max(dmax, abs(values[U(diag[k])]))
    k, _ = factor_loaded(fs[0], fs[1], fs[2], fs[9], fs[10], fs[11], fs[12], fs[13], fs[14], fs[15], fs[16], fs[17],
                         values, lbuf, tiny * dmax)
    return k, dmax


@njit
def same_prefix(a, b, n):
    """a[:n] == b[:n] elementwise."""
    for j in range(n):
        if a[j] != b[j]:
            return False
    return True


@njit
def fixed_set(dof, clo, normal, stick, fixed, vals):
    """Number of held DOFs, written sorted into fixed / vals: v_z = lo for a held normal, v_x / v_y = 0 for
    a sticking tangent of a held contact (``stick`` flat, slot 2 i + c)."""
    k = len(dof)
    d = np.empty(3 * k, np.int64)
    v = np.empty(3 * k)
    cnt = 0
    for i in range(k):
        if normal[i]:
            d[cnt] = dof[i] + 2
            v[cnt] = clo[i]
            cnt += 1
    for i in range(k):
        if normal[i]:
            for c in range(2):
                if stick[2 * i + c]:
                    d[cnt] = dof[i] + c
                    v[cnt] = 0.0
                    cnt += 1
    o = np.argsort(d[:cnt])
    for j in range(cnt):
        fixed[j] = d[o[j]]
        vals[j] = v[o[j]]
    return cnt


@njit
def staggered(indptr, indices, adiag, tpos, data, b, dmap, fs, ss, values, lbuf, tiny, nf, G, g, C, lo, hi,
              dof, clo, fric, normal, stick, sign, alpha, known, tol_imp, max_iter, max_changes, tol_v, stick_v,
              z, F, lam, mu_lim, fixed, info, imp, finfo):
    """The staggered contact loop of coupled.solve on the reduced system (values ``data`` in the CSR pattern
    indptr / indices, diagonal positions ``adiag``, transpose positions ``tpos``; ``dmap`` each entry's
    position in the factor's values, sparse_ldl's data_map), right-hand side b, skeleton rows G z_r = g and joint-limit rows lo <= C z_r <= hi (z_r = z[nf:]),
    contacts of the free vertices (x DOF ``dof``, v_z >= ``clo``, friction coefficient ``fric``) with their
    warm state. Writes z, F (friction impulses of the sliding tangents), lam (G's multipliers), mu_lim, the
    final held DOFs fixed[:info[INFO_NFIXED]], info, and, when converged, the floor impulses ``imp`` (k, 3)
    (beta_x, beta_y, alpha) [N s] and finfo[FINFO_RESIDUAL] = |A z + G^T lam + C^T mu - b - F - R| / |b|,
    finfo[FINFO_VIOLATION] = max |G z_r - g|. A failed factorisation (INFO_PIVOT, finfo[FINFO_DMAX]) or a
    singular bordered system returns at once with its INFO_STATUS."""
    n = len(b)
    m = len(g)
    p = len(lo)
    k = len(dof)
    nwmax = m + p
    tdof = np.empty(2 * k, np.int64)
    ndof = np.empty(k, np.int64)
    local = np.full(n, -1, np.int64)  # DOF -> contact-local slot 3 i + c
    dg = np.empty(k)  # A_xx of each contact vertex: impulse -> velocity
    for i in range(k):
        tdof[2 * i] = dof[i]
        tdof[2 * i + 1] = dof[i] + 1
        ndof[i] = dof[i] + 2
        for c in range(3):
            local[dof[i] + c] = 3 * i + c
        dg[i] = data[adiag[dof[i]]]
    tmp = np.empty(n)
    # the held system: base held set H0 (factorised), its bordered updates
    in_h0 = np.zeros(n, np.bool_)
    in_h = np.zeros(n, np.bool_)
    h0 = np.empty(3 * k, np.int64)
    v0 = np.empty(3 * k)
    nh0 = 0
    au = np.zeros(n)
    has_au = False
    have_base = False
    col_add = np.full(3 * k, -1, np.int64)
    col_rel = np.full(3 * k, -1, np.int64)
    cols = np.empty((6 * k, n))
    ncols = 0
    key_valid = False
    key_fixed = np.empty(3 * k, np.int64)
    key_nfix = 0
    key_w = np.empty(p, np.int64)
    key_nw = 0
    schur_valid = False
    schur_w = np.empty(p, np.int64)
    schur_nw = 0
    Wrows = np.empty((nwmax, n - nf))
    Y = np.empty((n, nwmax))
    add = np.empty(3 * k, np.int64)
    v_add = np.empty(3 * k)
    rel = np.empty(3 * k, np.int64)
    na = 0
    nr = 0
    nw = m
    Z = np.empty((n, 0))
    Kinv = np.empty((0, 0))
    factorisations = 0
    # the loop's state
    vals = np.empty(3 * k)
    nfix = 0
    rhs = np.empty(n)
    zs = np.empty(n)
    z0 = np.empty(n)
    f0 = np.empty(n)
    muW = np.zeros(p)
    act_idx = np.empty(p, np.int64)  # active limit rows in the order they became active
    act_val = np.empty(p)  # the bound each active row is held at (by row)
    is_act = np.zeros(p, np.bool_)
    nact = 0
    wvals = np.empty(p)
    have_z = False
    slide = np.zeros(2 * k, np.bool_)
    bound = np.empty(2 * k)
    releasable = np.zeros(2 * k, np.bool_)
    wrong = np.zeros(2 * k, np.bool_)
    tj = np.empty(2 * k)
    rc = np.zeros((k, 3))
    a_new = np.empty(k)
    nxt = np.empty(k)
    res_k = np.empty(k)
    keep = np.zeros(k, np.bool_)
    off = np.zeros(k, np.bool_)
    on = np.zeros(k, np.bool_)
    hist_valid = False
    hist_a = np.empty(k)
    hist_r = np.empty(k)
    hist_face = 0
    hist_keep = np.zeros(k, np.bool_)
    dirty = True
    face = 0
    converged = False
    it = 0
    info[INFO_STATUS] = OK
    for j in range(n):
        F[j] = 0.0
    while it < max_iter:
        # friction stage (Eq. 12 with alpha fixed; normal working set and limit rows held)
        for j in range(2 * k):
            bound[j] = fric * alpha[j // 2]
            releasable[j] = normal[j // 2] and known[j // 2]
        done = False
        while it < max_iter:
            it += 1
            if k:
                if dirty:
                    nfix = fixed_set(dof, clo, normal, stick, fixed, vals)
                    if fric > 0:
                        for j in range(2 * k):
                            slide[j] = normal[j // 2] and not stick[j]
                    dirty = False
                for j in range(2 * k):
                    F[tdof[j]] = sign[j] * bound[j] if slide[j] else 0.0
            for j in range(n):
                rhs[j] = b[j] + F[j]
            # ---- the held system: z with z[fixed] = vals, G z_r = g, active limit rows at their bounds
            same = (have_base and key_valid and key_nfix == nfix and key_nw == nact
                    and same_prefix(key_fixed, fixed, nfix) and same_prefix(key_w, act_idx, nact))
            if not same:
                rebase = not have_base
                if have_base:
                    for j in range(nfix):
                        in_h[fixed[j]] = True
                    na = 0
                    for j in range(nfix):
                        if not in_h0[fixed[j]]:
                            add[na] = fixed[j]
                            v_add[na] = vals[j]
                            na += 1
                    nr = 0
                    for j in range(nh0):
                        if not in_h[h0[j]]:
                            rel[nr] = h0[j]
                            nr += 1
                    for j in range(nfix):
                        in_h[fixed[j]] = False
                    rebase = na + nr > max_changes
                if rebase:
                    if nfix:
                        piv, dmax = held_factor(fs, values, lbuf, data, dmap, indptr, tpos, adiag, fixed[:nfix], tiny)
                    else:
                        piv, dmax = ldl_factor(fs, values, lbuf, data, tiny)
                    if piv >= 0:
                        info[INFO_STATUS] = FACTOR_FAILED
                        info[INFO_PIVOT] = piv
                        info[INFO_ITER] = it
                        info[INFO_FACTORS] = factorisations
                        finfo[FINFO_DMAX] = dmax
                        return
                    factorisations += 1
                    have_base = True
                    for j in range(nh0):
                        in_h0[h0[j]] = False
                    nh0 = nfix
                    for j in range(nfix):
                        h0[j] = fixed[j]
                        v0[j] = vals[j]
                        in_h0[fixed[j]] = True
                    has_au = nfix > 0
                    if has_au:  # A[:, H0] v0 by the held rows (A symmetric: A[i, j] = data[tpos[e]])
                        held_columns(indptr, indices, tpos, data, fixed[:nfix], vals[:nfix], au)
                    col_add[:] = -1
                    col_rel[:] = -1
                    ncols = 0
                    schur_valid = False
                    na = 0
                    nr = 0
                nw = m + nact
                if not (schur_valid and schur_nw == nact and same_prefix(schur_w, act_idx, nact)):
                    Wrows = np.empty((nw, n - nf))
                    Wrows[:m] = G
                    for j in range(nact):
                        Wrows[m + j] = C[act_idx[j]]
                    Y = np.zeros((n, nw))
                    if nw:  # Y = A~0^-1 [0; W^T], in the factor's permuted order
                        X = np.zeros((n, nw))
                        perm = ss[5]
                        for i in range(n):
                            if perm[i] >= nf:
                                for c in range(nw):
                                    X[i, c] = Wrows[c, perm[i] - nf]
                        solve_matrix_kernel(ss[0], ss[1], ss[2], ss[3], ss[4], values, X)
                        for i in range(n):
                            for c in range(nw):
                                Y[perm[i], c] = X[i, c]
                    schur_valid = True
                    schur_nw = nact
                    for j in range(nact):
                        schur_w[j] = act_idx[j]
                nc = nw + na + nr
                if nc:
                    Z = np.empty((n, nc))
                    for i in range(n):
                        for c in range(nw):
                            Z[i, c] = -Y[i, c]
                    for q in range(na + nr):
                        isadd = q < na
                        d = add[q] if isadd else rel[q - na]
                        s = local[d]
                        slot = col_add[s] if isadd else col_rel[s]
                        if slot < 0:
                            slot = ncols
                            ncols += 1
                            if isadd:  # w_a = A~0^-1 e_a
                                for i in range(n):
                                    f0[i] = 0.0
                                f0[d] = 1.0
                                ldl_solve(ss, values, lbuf, f0, cols[slot], tmp)
                                col_add[s] = slot
                            else:  # u_j = e_j - A~0^-1 (A e_j off H0)
                                for i in range(n):
                                    z0[i] = 0.0
                                for e in range(indptr[d], indptr[d + 1]):
                                    z0[indices[e]] = data[e]
                                for i in range(n):
                                    if in_h0[i]:
                                        z0[i] = 0.0
                                ldl_solve(ss, values, lbuf, z0, cols[slot], tmp)
                                for i in range(n):
                                    cols[slot, i] = -cols[slot, i]
                                cols[slot, d] += 1.0
                                col_rel[s] = slot
                        for i in range(n):
                            Z[i, nw + q] = cols[slot, i]
                    K = np.empty((nc, nc))
                    border(Z, Wrows, nf, add, na, rel, nr, indptr, indices, data, K)
                    try:
                        Kinv = np.ascontiguousarray(np.linalg.inv(K))
                    except Exception:
                        info[INFO_STATUS] = BORDER_SINGULAR
                        info[INFO_ITER] = it
                        info[INFO_FACTORS] = factorisations
                        return
                key_valid = True
                key_nfix = nfix
                for j in range(nfix):
                    key_fixed[j] = fixed[j]
                key_nw = nact
                for j in range(nact):
                    key_w[j] = act_idx[j]
                    wvals[j] = act_val[act_idx[j]]
            for j in range(n):
                f0[j] = rhs[j] - au[j] if has_au else rhs[j]
            for j in range(nh0):
                f0[h0[j]] = v0[j]
            ldl_solve(ss, values, lbuf, f0, z0, tmp)
            nc = nw + na + nr
            if nc == 0:
                for j in range(n):
                    zs[j] = z0[j]
            else:
                beta = np.empty(nc)
                for j in range(m):
                    beta[j] = g[j]
                for j in range(nact):
                    beta[m + j] = wvals[j]
                for j in range(na):
                    beta[nw + j] = v_add[j]
                for j in range(nr):
                    beta[nw + na + j] = rhs[rel[j]]
                bz = np.empty((nc, 1))
                border(z0.reshape(n, 1), Wrows, nf, add, na, rel, nr, indptr, indices, data, bz)
                cc = Kinv @ (beta - bz[:, 0])
                zc = Z @ cc
                for j in range(n):
                    zs[j] = z0[j] + zc[j]
                for j in range(m):
                    lam[j] = cc[j]
                for j in range(nact):
                    muW[j] = cc[m + j]
            # ---- end of the held system's solve
            if not k:
                for j in range(n):
                    z[j] = zs[j]
                done = True
                break
            anyw = False
            for j in range(2 * k):
                wrong[j] = slide[j] and zs[tdof[j]] * sign[j] > 0
                anyw = anyw or wrong[j]
            if not have_z:  # first solve: the warm state's face; a wrong-way slider sticks (z_j = 0)
                have_z = True
                for j in range(n):
                    z[j] = zs[j]
                if anyw:
                    for j in range(2 * k):
                        if wrong[j]:
                            stick[j] = True
                            z[tdof[j]] = 0.0
                    dirty = True
                    face += 1
                    continue
            elif anyw:  # exact line search to zs, stopping at the first slider that reaches 0
                tb = np.inf
                for j in range(2 * k):
                    tj[j] = np.inf
                    if wrong[j]:
                        zt, zt_s = z[tdof[j]], zs[tdof[j]]
                        tj[j] = min(max(zt / (zt - zt_s), 0.0), 1.0)  # zt sign <= 0 < zt_s sign
                    tb = min(tb, tj[j])
                for j in range(n):
                    z[j] += tb * (zs[j] - z[j])
                for j in range(2 * k):
                    if wrong[j] and (tj[j] <= tb or abs(z[tdof[j]]) <= stick_v):
                        stick[j] = True
                        z[tdof[j]] = 0.0
                dirty = True
                face += 1
                continue
            else:
                for j in range(n):
                    z[j] = zs[j]
            for i in range(k):  # reactions A z - b - F on the contact vertices' DOFs
                d = dof[i]
                r0, r1, r2 = csr_rows3_dot(indptr, indices, data, d, z)
                rc[i, 0] = r0 - b[d] - F[d]
                rc[i, 1] = r1 - b[d + 1] - F[d + 1]
                rc[i, 2] = r2 - b[d + 2] - F[d + 2]
            if fric > 0:
                jbest = -1
                ebest = -np.inf
                for j in range(2 * k):  # the stuck tangent whose reaction most exceeds its bound slides
                    if stick[j] and releasable[j]:
                        ex = abs(rc[j // 2, j % 2]) - bound[j]
                        if ex > ebest:
                            ebest = ex
                            jbest = j
                if jbest >= 0 and ebest > tol_imp:
                    stick[jbest] = False
                    sign[jbest] = np.sign(rc[jbest // 2, jbest % 2])
                    dirty = True
                    face += 1
                    continue
            done = True
            break
        if not done:
            break
        # normal stage (Alg. 2 line 9, the friction impulses fixed): v_z >= lo with alpha >= 0; joint limits
        changed = False
        if p:
            for i in range(p):
                mu_lim[i] = 0.0
            for j in range(nact):
                mu_lim[act_idx[j]] = muW[j]
            kept = 0
            for j in range(nact):  # release rows whose multiplier pulls
                i = act_idx[j]
                lower = act_val[i] == lo[i]
                if (lower and muW[j] > tol_imp) or (not lower and muW[j] < -tol_imp):
                    is_act[i] = False
                    mu_lim[i] = 0.0
                    changed = True
                else:
                    act_idx[kept] = i
                    kept += 1
            nact = kept
            Cv = C @ z[nf:]
            for i in range(p):  # hold violated ones
                if (Cv[i] < lo[i] - 1e-12 or Cv[i] > hi[i] + 1e-12) and not is_act[i]:
                    is_act[i] = True
                    act_val[i] = lo[i] if Cv[i] < lo[i] else hi[i]
                    act_idx[nact] = i
                    nact += 1
                    changed = True
        moved = 0.0
        if k:
            anyoff = False
            anyon = False
            for i in range(k):
                ai = rc[i, 2]
                off[i] = normal[i] and ai < -tol_imp  # the floor would pull: released
                on[i] = not normal[i] and z[ndof[i]] < clo[i] - 1e-12  # below the floor's bound: held
                keep[i] = normal[i] and not off[i]
                a_new[i] = max(ai, 0.0)
                anyoff = anyoff or off[i]
                anyon = anyon or on[i]
            if fric > 0:  # Alg. 2 line 12: the velocity change the bound's change makes on the sliding tangents
                ex = -np.inf
                for i in range(k):
                    if keep[i] and not (stick[2 * i] and stick[2 * i + 1]):
                        moved = max(moved, fric * abs(a_new[i] - alpha[i]) / dg[i])
                    for c in range(2):  # a stuck tangent: unaffected by its bound unless it no longer holds it
                        if stick[2 * i + c] and keep[i]:
                            ex = max(ex, abs(rc[i, c]) - fric * a_new[i])
                if ex > tol_imp:
                    changed = True
            for i in range(k):
                nxt[i] = a_new[i]
            if fric > 0 and not anyoff and not anyon:  # Anderson(1) on the fixed point alpha = G(alpha)
                for i in range(k):
                    res_k[i] = fric * (a_new[i] - alpha[i]) / dg[i]  # its residual as velocities [m/s]
                same_keep = hist_valid and hist_face == face
                if same_keep:
                    for i in range(k):
                        if hist_keep[i] != keep[i]:
                            same_keep = False
                            break
                if same_keep:
                    dd = 0.0
                    rd = 0.0
                    for i in range(k):
                        dr = res_k[i] - hist_r[i]
                        dd += dr * dr
                        rd += res_k[i] * dr
                    if dd > 0.0:
                        for i in range(k):
                            nxt[i] = max(a_new[i] - (rd / dd) * (a_new[i] - hist_a[i]), 0.0)
                hist_valid = True
                hist_face = face
                for i in range(k):
                    hist_a[i] = a_new[i]
                    hist_r[i] = res_k[i]
                    hist_keep[i] = keep[i]
            else:
                hist_valid = False
            for i in range(k):
                if keep[i]:
                    alpha[i] = nxt[i]
                    known[i] = True
            if anyoff:
                for i in range(k):
                    if off[i]:
                        normal[i] = False
                        stick[2 * i] = stick[2 * i + 1] = False
                        sign[2 * i] = sign[2 * i + 1] = 0.0
                        alpha[i] = 0.0
                        known[i] = False
                changed = True
            if anyon:  # new contacts slide along their tangential velocity (stick if it is ~0)
                for i in range(k):
                    if on[i]:
                        normal[i] = True
                        z[ndof[i]] = clo[i]
                        for c in range(2):
                            zt = z[dof[i] + c]
                            st = abs(zt) <= stick_v and fric > 0
                            stick[2 * i + c] = st
                            sign[2 * i + c] = 0.0 if st else -np.sign(zt)
                            if st:
                                z[dof[i] + c] = 0.0
                        alpha[i] = 0.0
                        known[i] = False
                changed = True
            dirty = dirty or changed
        if not changed and moved <= tol_v:
            converged = True
            break
    if k and dirty:
        nfix = fixed_set(dof, clo, normal, stick, fixed, vals)
    info[INFO_ITER] = it
    info[INFO_FACTORS] = factorisations
    info[INFO_NFIXED] = nfix
    info[INFO_CONVERGED] = 1 if converged else 0
    if converged:
        finish(indptr, indices, data, b, F, z, nf, G, g, lam, C, mu_lim, dof, normal, stick, fixed[:nfix], imp, finfo)


@njit
def finish(indptr, indices, data, b, F, z, nf, G, g, lam, C, mu_lim, dof, normal, stick, fixed, imp, finfo):
    """The converged solve's floor impulses and residuals (``staggered``): r = A z - b - F; a held contact's
    alpha = r_z, a stuck tangent's beta = r_t, a sliding one's the friction impulse F_t; the stationarity
    residual with the held DOFs' reactions removed."""
    n = len(b)
    r = np.empty(n)
    csr_matvec(indptr, indices, data, z, r)
    for j in range(n):
        r[j] = r[j] - b[j] - F[j]
    for i in range(len(dof)):
        imp[i, 2] = r[dof[i] + 2] if normal[i] else 0.0
        for c in range(2):
            imp[i, c] = (r[dof[i] + c] if stick[2 * i + c] else F[dof[i] + c]) if normal[i] else 0.0
    for j in fixed:
        r[j] = 0.0
    viol = 0.0
    for j in range(len(g)):
        gz = 0.0
        for c in range(n - nf):
            gz += G[j, c] * z[nf + c]
            r[nf + c] += G[j, c] * lam[j]
        viol = max(viol, abs(gz - g[j]))
    for j in range(len(mu_lim)):
        for c in range(n - nf):
            r[nf + c] += C[j, c] * mu_lim[j]
    rr = 0.0
    bb = 0.0
    for j in range(n):
        rr += r[j] * r[j]
        bb += b[j] * b[j]
    finfo[FINFO_RESIDUAL] = np.sqrt(rr) / max(np.sqrt(bb), 1e-300)
    finfo[FINFO_VIOLATION] = viol


@njit
def border(X, Wrows, nf, add, na, rel, nr, indptr, indices, data, out):
    """The bordered rows applied to the columns of X (n, c): W X_r (W = [G; active limit rows]), X on the
    added DOFs, A X on the released ones, into out (nw + na + nr, c)."""
    nw = Wrows.shape[0]
    nrr = Wrows.shape[1]
    for c in range(X.shape[1]):
        for r in range(nw):
            acc = 0.0
            for i in range(nrr):
                acc += Wrows[r, i] * X[nf + i, c]
            out[r, c] = acc
        for q in range(na):
            out[nw + q, c] = X[add[q], c]
        for q in range(nr):
            j = rel[q]
            acc = 0.0
            for e in range(indptr[j], indptr[j + 1]):
                acc += data[e] * X[indices[e], c]
            out[nw + na + q, c] = acc


@njit
def warm_start(cvert, wvert, wrows, fric, normal, stick, sign, alpha, known, prev):
    """The contact state of the contacts ``cvert`` (k,) from the last step's states (vertices ``wvert``, rows
    ``wrows`` (c, 6): stick_x, stick_y, sign_x, sign_y, alpha, the step before's alpha or NaN): held, the
    stick/slide state (no stuck tangent without friction), alpha extrapolated from the last two steps' when
    both had the contact."""
    if len(wvert):
        o = np.argsort(wvert)
        sv = wvert[o]
        for i in range(len(cvert)):
            at = np.searchsorted(sv, cvert[i])
            if at < len(sv) and sv[at] == cvert[i]:
                w = wrows[o[at]]
                normal[i] = known[i] = True
                stick[2 * i], stick[2 * i + 1] = w[0] > 0, w[1] > 0
                sign[2 * i], sign[2 * i + 1] = w[2], w[3]
                alpha[i] = w[4] if np.isnan(w[5]) else max(2.0 * w[4] - w[5], 0.0)
                prev[i] = w[4]
    if fric <= 0:
        stick[:] = False


@njit
def contact_states(cvert, normal, stick, sign, imp, prev, svert, srows):
    """The held contacts' states (the next step's ``warm_start``), ascending by vertex, into svert / srows;
    returns their count."""
    o = np.argsort(cvert)
    c = 0
    for i in o:
        if normal[i]:
            svert[c] = cvert[i]
            srows[c, 0] = 1.0 if stick[2 * i] else 0.0
            srows[c, 1] = 1.0 if stick[2 * i + 1] else 0.0
            srows[c, 2], srows[c, 3] = sign[2 * i], sign[2 * i + 1]
            srows[c, 4], srows[c, 5] = max(imp[i, 2], 0.0), prev[i]
            c += 1
    return c


@njit
def coupled_solve(indptr, indices, adiag, tpos, data, b, dmap, fs, ss, values, lbuf, tiny, nf, G, g, C, lo, hi,
                  dof, clo, cvert, wvert, wrows, fric, tol, max_iter, max_changes, tol_v, stick_v,
                  z, F, lam, mu_lim, imp, svert, srows, ctol, info, finfo):
    """coupled.solve in one call: the warm start, ``staggered`` (tolerance tol (1 + max|b|) on the impulses),
    the contacts' states (svert[:info[INFO_NSTATE]], srows) and ctol = tol_v A_jj (k,) [N s]."""
    k = len(dof)
    normal = np.zeros(k, np.bool_)  # v_z = lo held (alpha >= 0)
    stick = np.zeros(2 * k, np.bool_)  # tangent held at 0 (|beta| <= mu alpha); slot 2 i + c, world axis c
    sign = np.zeros(2 * k)  # sign of a sliding tangent's friction impulse (its velocity has the other sign)
    alpha = np.zeros(k)  # the normal impulse the friction bound mu alpha uses [N s]
    known = np.zeros(k, np.bool_)  # alpha computed (this step or the last): stuck tangents may be released
    prev = np.full(k, np.nan)  # the last step's normal impulse of the contacts it had
    if k:
        warm_start(cvert, wvert, wrows, fric, normal, stick, sign, alpha, known, prev)
    scale = 1.0
    if len(b):
        scale = 1.0 + np.abs(b).max()
    fixed = np.empty(3 * k, np.int64)
    staggered(indptr, indices, adiag, tpos, data, b, dmap, fs, ss, values, lbuf, tiny, nf, G, g, C, lo, hi, dof, clo,
              fric, normal, stick, sign, alpha, known, tol * scale, max_iter, max_changes, tol_v, stick_v, z, F, lam,
              mu_lim, fixed, info, imp, finfo)
    info[INFO_NORMAL] = normal.sum()
    info[INFO_STUCK] = stick.sum()
    for i in range(k):
        ctol[i] = tol_v * data[adiag[dof[i]]]
    info[INFO_NSTATE] = 0
    if info[INFO_STATUS] == OK and info[INFO_CONVERGED]:
        info[INFO_NSTATE] = contact_states(cvert, normal, stick, sign, imp, prev, svert, srows)
