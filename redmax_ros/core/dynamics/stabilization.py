"""Loop-closure drift: post-stabilization by projection (Gauss-Newton, least-norm correction).

The velocity-level constraint G qdot = 0 (Eq. 5/6) leaves O(h^2) position drift per step. After
each configuration update q is projected back onto the loop manifold phi(q) = 0 with least-norm
Newton steps in hyper-reduced coordinates, dq = -G^+ phi, keeping prescribed joints fixed, until
max |phi| < ``tol`` (default 1e-10 m). Velocities are not projected (the next step's velocity
constraint acts on them). This replaces Baumgarte's stabilization [Baumgarte 1972], which the paper
uses, because it needs no tuning and removes the drift to solver precision; see docs/architecture.md.

One implementation for every pipeline, on the recursive kinematics Context (tree_kinematics.py):
:func:`project_chord` (the step's: chord Newton reusing the step's loop rows, each iteration one
compiled forward-kinematics + loop-residual call, all of them one call when the configuration is a vector
space), :func:`project` (full Newton, its fallback and the
initial assembly), :func:`assemble_loops` and :func:`check_loop_rank` (compile time),
:func:`loop_violation` (diagnostics).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.tree_kinematics import Context, loop_phi_kernel, universal_kernel
from redmax_ros.core.errors import SceneError
from redmax_ros.core.jit import njit
from redmax_ros.core.linalg import chol_solve, cholesky

TOL = 1e-10  # loop closure [m]


def loop_violation(ctx: Context, q) -> float:
    """max |phi| [m] of the loop closures at q."""
    if not ctx.n_loop_rows:
        return 0.0
    ctx.fk(q)
    return float(np.abs(ctx.loop_phi()).max())


def _hold_rows(ctx, hold_dofs):
    """Rows selecting the held hyper-reduced DOFs (cached per set in the workspace)."""
    key = ("hold rows", *hold_dofs)
    hold = ctx.cache.get(key)
    if hold is None:
        hold = np.zeros((len(hold_dofs), ctx.mech.ndof))
        hold[np.arange(len(hold_dofs)), list(hold_dofs)] = 1.0
        ctx.cache[key] = hold
    return hold


def loop_residual(ctx: Context, q):
    """(phi (rows,) [m], G_R (rows, ndof)): the loop residual and loop rows in hyper-reduced
    coordinates (G_r J_rR with the workspace's live J_rR) at q."""
    ctx.fk(q)
    G, phi = ctx.loop_rows()
    T = ctx.T
    return phi, (G if T is None else G @ T)


def project(ctx: Context, q, hold_dofs=(), tol=TOL, max_iter=5):
    """Newton projection of q onto phi(q) = 0 (least-norm, hyper-reduced, ``hold_dofs`` fixed).
    Returns (q, max|phi|)."""
    mech = ctx.mech
    if not ctx.n_loop_rows:
        return q, 0.0
    hold = _hold_rows(ctx, hold_dofs)
    phi, G = loop_residual(ctx, q)
    for _ in range(max_iter):
        err = float(np.abs(phi).max())
        if err < tol:
            return q, err
        Gh = np.vstack([G, hold])
        dq, *_ = np.linalg.lstsq(Gh, np.concatenate([-phi, np.zeros(len(hold))]), rcond=None)
        q = pin.integrate(mech.model, q, dq if ctx.T is None else ctx.T @ dq)
        phi, G = loop_residual(ctx, q)
    return q, float(np.abs(phi).max())


def project_chord(ctx: Context, q, G, hold_dofs=(), tol=TOL, max_iter=8):
    """Chord-Newton projection reusing the step's loop rows G (hyper-reduced, at q_k): each iteration costs one compiled call (forward kinematics of the placements, loop-site positions,
    phi = S (x_a - x_b), max|phi|). The chord converges at a rate O(h |qdot|) (the change of G over one
    step); if it has not converged in ``max_iter`` iterations the full Newton projection takes over.
    Returns (q, max|phi|) at the returned q."""
    mech = ctx.mech
    held = _held_array(ctx, hold_dofs)
    G = np.ascontiguousarray(G)
    T = _NO_T if ctx.T is None else ctx.T
    if ctx.additive:  # the iterations below in one compiled call
        t, ws = ctx.topo, ctx.ws
        ctx.invalidate()
        q_out, err, status = chord_project_kernel(
            t.parents, t.kind, t.idx_q, t.idx_v, t.nv_j, t.axis, t.pitch, t.place_R, t.place_p, ctx.uni_joints,
            ctx.uni_a1, ctx.uni_a2, ctx.zero_v, ws.jR, ws.jp, ws.Sl, ws.c_local, ws.R, ws.p, ws.St, ctx.jac_jid,
            ctx.jac_local, ctx.loop_a, ctx.loop_b, mech.loop_select, G, held, T,
            np.ascontiguousarray(q, dtype=float), tol, max_iter)
        if status == CHORD_CONVERGED:
            return q_out, err
        return project(ctx, q if status == CHORD_SINGULAR else q_out, hold_dofs, tol)
    L, ok = chord_factor(G, held)
    if not ok:
        return project(ctx, q, hold_dofs, tol)
    for _ in range(max_iter):
        phi, err = ctx.loop_phi_at(q)
        if err < tol:
            return q, err
        q = pin.integrate(mech.model, q, chord_step(L, G, held, phi, T))
    return project(ctx, q, hold_dofs, tol)


_NO_T = np.zeros((0, 0))
CHORD_CONVERGED, CHORD_SINGULAR, CHORD_UNCONVERGED = range(3)  # chord_project_kernel's status


@njit
def chord_project_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, uni, uni_a1, uni_a2,
                         zero_v, jR, jp, Sl, c_local, R, p, St, jid, local, a, b, S, G, held, T, q, tol, max_iter):
    """The chord-Newton iterations of :func:`project_chord` in one call, for a model whose configuration is a
    vector space (Context.additive: q (+) dq = q + dq, as pin.integrate): the factor of K K^T
    (:func:`chord_factor_into`), then per iteration the universal joints' placements
    (tree_kinematics.universal_kernel), forward kinematics and phi = S (x_a - x_b) of the loop sites
    (tree_kinematics.loop_phi_kernel) and, while max|phi| >= tol [m], q <- q + dq (:func:`chord_step_into`,
    into one of two buffers allocated once; q itself is not written). Returns (q, max|phi| at q, status):
    CHORD_CONVERGED, CHORD_SINGULAR (K K^T not positive definite; q the input) or CHORD_UNCONVERGED (q after
    max_iter steps, phi there not evaluated).
    Leaves placements of the last q evaluated in (jR, jp, Sl, R, p, St)."""
    m, n, k = G.shape[0], G.shape[1], held.shape[0]
    L = np.empty((m + k, m + k))
    if not chord_factor_into(G, held, np.zeros((m + k, m + k)), L, np.empty(n, dtype=np.int64)):
        return q, 0.0, CHORD_SINGULAR
    y, dq, step = np.empty(m + k), np.empty(n), np.empty(n if T.shape[0] == 0 else T.shape[0])
    bufs = np.empty((2, q.shape[0]))  # the iterates, alternately (the input q is never written)
    for it in range(max_iter):
        if uni.shape[0]:
            universal_kernel(uni, idx_q, idx_v, uni_a1, uni_a2, q, zero_v, False, jR, jp, Sl, c_local)
        phi, err = loop_phi_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl,
                                   R, p, St, jid, local, a, b, S)
        if err < tol:
            return q, err, CHORD_CONVERGED
        chord_step_into(L, G, held, phi, T, y, dq, step)
        q_next = bufs[it % 2]
        for i in range(q.shape[0]):
            q_next[i] = q[i] + step[i]
        q = q_next
    return q, 0.0, CHORD_UNCONVERGED


def _held_array(ctx, hold_dofs):
    key = ("held array", *hold_dofs)
    a = ctx.cache.get(key)
    if a is None:
        a = ctx.cache[key] = np.asarray(list(hold_dofs), dtype=np.int64)
    return a


@njit
def chord_factor(G, held):
    """Cholesky factor of K K^T, K = [G; H] (H selects the held hyper-reduced DOFs):
    K K^T = [[G G^T, G[:, held]], [G[:, held]^T, I]]. Returns (L, ok)."""
    n = G.shape[0] + held.shape[0]
    L = np.empty((n, n))
    ok = chord_factor_into(G, held, np.zeros((n, n)), L, np.empty(G.shape[1], dtype=np.int64))
    return L, ok


@njit
def chord_factor_into(G, held, KK, L, nz):
    """chord_factor into given arrays: K K^T into KK, its factor into L ((m + k) square); returns ok. The
    products G_r . G_c run over the nonzeros of row r (a loop row touches the DOFs of its two chains only),
    in increasing column order: the same sums as over every column. ``nz``: int scratch (n,), the columns of
    row r's nonzeros."""
    m, n, k = G.shape[0], G.shape[1], held.shape[0]
    KK[:, :] = 0.0
    for r in range(m):
        Gr = G[r]
        cnt = 0
        for i in range(n):
            if Gr[i] != 0.0:
                nz[cnt] = i
                cnt += 1
        for c in range(r + 1):
            Gc = G[c]
            s = 0.0
            for p in range(cnt):
                i = nz[p]
                s += Gr[i] * Gc[i]
            KK[r, c] = s
            KK[c, r] = s
        for j in range(k):
            KK[r, m + j] = G[r, held[j]]
            KK[m + j, r] = G[r, held[j]]
    for j in range(k):
        KK[m + j, m + j] = 1.0
    return cholesky(KK, L)


@njit
def chord_step(L, G, held, phi, T):
    """Least-norm correction dq = -K^T (K K^T)^-1 [phi; 0] (held DOFs fixed), mapped to reduced
    coordinates by J_rR = T (empty T: none)."""
    m, n, k = G.shape[0], G.shape[1], held.shape[0]
    out = np.empty(n if T.shape[0] == 0 else T.shape[0])
    chord_step_into(L, G, held, phi, T, np.empty(m + k), np.empty(n), out)
    return out


@njit
def chord_direction_into(L, G, held, phi, y, dq):
    """The least-norm correction dq = -K^T (K K^T)^-1 [phi; 0] in hyper-reduced coordinates (held DOFs fixed),
    into dq (n,); scratch y (m + k,)."""
    m, n, k = G.shape[0], G.shape[1], held.shape[0]
    y[:] = 0.0
    y[:m] = phi
    chol_solve(L, y)
    dq[:] = 0.0
    for r in range(m):
        for i in range(n):
            dq[i] -= G[r, i] * y[r]
    for j in range(k):
        dq[held[j]] -= y[m + j]


@njit
def chord_step_into(L, G, held, phi, T, y, dq, out):
    """chord_step without allocation: scratch y (m + k,), dq (n,); the correction into out (reduced)."""
    chord_direction_into(L, G, held, phi, y, dq)
    n = G.shape[1]
    if T.shape[0] == 0:
        out[:] = dq
        return
    for i in range(T.shape[0]):
        s = 0.0
        for c in range(n):
            s += T[i, c] * dq[c]
        out[i] = s


def assemble_loops(ctx: Context, q):
    """Close the loops at the initial configuration (Newton, tolerance 1e-12 m) and reject redundant
    loop rows (SceneError): compile time."""
    mech = ctx.mech
    if not len(mech.loop_ab):
        return q
    src = mech.spec.source
    q, err = project(ctx, q, tol=1e-12, max_iter=100)
    if err > 1e-9:
        raise SceneError(src, "loops", f"cannot close the loops from the initial configuration "
                                       f"(residual {err:.3g} m after 100 Newton steps); check q0 and the loop sites")
    _, G = loop_residual(ctx, q)
    check_loop_rank(mech, G)
    return q



def check_loop_rank(mech, G) -> None:
    """Reject loops whose rows are redundant with the joints (SceneError naming the first such loop).
    G: the loop rows (hyper-reduced) at the assembled configuration, loop by loop in mech order."""
    r0 = 0
    for name, P in zip(mech.loop_names, mech.loop_axes):
        r1 = r0 + len(P)
        sv = np.linalg.svd(G[:r1], compute_uv=False)
        rank = int(np.sum(sv > 1e-9 * max(sv[0], 1e-300)))
        if rank < r1:
            raise SceneError(mech.spec.source, f"loops '{name}'",
                             f"over-constrains the mechanism: its rows are redundant with the joints "
                             f"(rank {rank} < {r1} rows); keep only the rows the mechanism needs (e.g. rows: [x, y] "
                             f"for a planar loop)")
        r0 = r1
