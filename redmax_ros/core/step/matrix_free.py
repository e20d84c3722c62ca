"""Matrix-free RedMax step: PCG with the Projected Block Jacobi Preconditioner (Wang et al. 2019,
§3, Eq. (2)-(4), Alg. 1), and the solver selection (``solver: direct | pcg | auto``).

:func:`step_matrix_free` has the contract of :func:`redmax_ros.core.stepper.step` (same State,
Commands, StepResult and Diagnostics, same sign conventions A qdot = b - G^T lam - C^T mu, required
torques *f_r = *G_r^T lam / h, StepError with the caller's state unchanged) but never creates a
``pin.Data`` (its memory grows as nv^3 in pin 4.1). Per step:

1. O(n) forward kinematics, body twists and bias accelerations (:mod:`.recursive`), cached on (q, qdot);
2. RHS of Eq. (2) in O(n + m) and the LHS as an O(n + m) operator (:class:`.pcg.MatrixFreeSystem`);
3. the Projected Block Jacobi Preconditioner factored once (Alg. 1 lines 1-8, O(n));
4. bilateral rows H (loop closures, prescribed joints and sites, Eq. 7) in reduced coordinates;
   hyper-reduced couplings (Eq. 8-10) are imposed as extra bilateral rows whose null space is the
   range of T = J_rR (the constrained reduced solution is exactly T qdot_R of Eq. 10, with the same
   multipliers for the other rows), so the tree-structured preconditioner still applies;
5. Eq. (4): the l + 1 PCG solves u = A^-1 b (warm-started with the previous velocity) and
   Z = A^-1 H^T (warm-started with the previous step's Z), run together in lockstep (one numba
   call per iteration for all right-hand sides), then the small dense solve
   (H Z) lam = H u - g and qdot = u - Z lam;
6. joint limits (Eq. 5) by a primal active set on the same dual system (limit rows enter as
   equalities at their bound, multipliers checked for sign), with Z columns computed only for
   the rows that become active;
7. if a PCG solve misses its tolerance within its cap (or the preconditioner or the active set
   fails) the step is redone with the data-free direct solver and Diagnostics.solver says
   ``pcg->direct`` (or ``pcg->qp``);
8. configuration update, loop post-stabilization (chord Newton on the step's loop rows),
   energies and violations, all data-free (:mod:`.data_free`).

``solver="direct"`` runs the same pipeline with a dense data-free LHS (:func:`.data_free.dense_lhs`)
and :func:`.solve.solve_direct` (Cholesky / KKT / ProxSuite QP): the direct solver for models too
large for pin.Data, and the fallback of the PCG path.

Diagnostics.iterations of a PCG step is the total number of PCG iterations over all its solves
(l + 1 with l bilateral rows, plus any active limit rows), like the paper's Table 2 counts; the
per-solve counts are in ``Context.last_stats``.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics import data_free as dfm
from redmax_ros.core.dynamics.constraints import Constraints
from redmax_ros.core.dynamics.data_free import PIN_DATA_MAX_NV, Context, context
from redmax_ros.core.errors import SceneError, StepError
from redmax_ros.core.dynamics.forces import LinearSystem
from redmax_ros.core.solvers.pcg import MatrixFreeSystem, PointSprings, lhs_kernel
from redmax_ros.core.solvers.preconditioner import ProjectedBlockJacobi, apply_kernel
from redmax_ros.core.jit import njit
from redmax_ros.core.solvers.direct import check_rank, solve_direct
from redmax_ros.core.step.pipeline import MAX_SPEED, Diagnostics, State, StepResult, check_inputs

DEFAULT_RTOL = 1e-6
MAX_ITER_CAP = 1000  # per PCG solve, whatever n; then the step falls back to the direct solver


# ----------------------------------------------------------------------------------------------
# block (lockstep) PCG


@njit
def _lhs_multi(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, X, active, Y, W, F, OUT):
    for c in range(X.shape[0]):
        if active[c]:
            lhs_kernel(parents, idx_v, nv_j, St, I, blocks, use_blocks, ja, pa, jb, pb, C, diag, X[c], Y, W, F,
                        OUT[c])


@njit
def _pinv_multi(parents, idx_v, nv_j, St, Ut, Psi, X, active, beta, u, acc, OUT):
    for c in range(X.shape[0]):
        if active[c]:
            apply_kernel(parents, idx_v, nv_j, St, Ut, Psi, X[c], OUT[c], beta, u, acc)


class _Ops:
    """Multi-column A and P^-1 products of a MatrixFreeSystem and its factored preconditioner."""

    def __init__(self, system: MatrixFreeSystem, P: ProjectedBlockJacobi):
        self.s, self.P = system, P
        self.t = system.topo

    def A(self, X, active):
        s, t = self.s, self.t
        OUT = np.zeros_like(X)
        blocks = s._noblocks if s.body_blocks is None else s.body_blocks
        sp = s.springs
        _lhs_multi(t.parents, t.idx_v, t.nv_j, s.ws.St, s.ws.I, blocks, s.body_blocks is not None, sp.joint_a,
                   s.pa, sp.joint_b, s.pb, s.C, s._diag, X, active, s._Y, s._W, s._F, OUT)
        return OUT

    def Pinv(self, X, active):
        P, t = self.P, self.t
        OUT = np.zeros_like(X)
        _pinv_multi(t.parents, t.idx_v, t.nv_j, P._St, P._Ut, P._Psi, X, active, P._beta, P._u, P._acc, OUT)
        return OUT


def block_pcg(ops: _Ops, B: np.ndarray, X0: np.ndarray | None, rtol: float, max_iter: int):
    """Independent preconditioned CG solves A x_c = b_c for the rows b_c of B (k, n), run in lockstep.
    Each column stops when ||r_c|| <= rtol ||b_c||. Returns (X, iterations (k,), converged (k,),
    relative residuals (k,))."""
    k, n = B.shape
    X = np.zeros((k, n)) if X0 is None else np.array(X0, dtype=float)
    bn = np.sqrt(np.einsum("ij,ij->i", B, B))
    tol = rtol * bn
    active = bn > 0.0
    X[~active] = 0.0
    R = B - ops.A(X, active) if X0 is not None else B.copy()
    rn = np.sqrt(np.einsum("ij,ij->i", R, R))
    its = np.zeros(k, dtype=int)
    conv = ~active
    done = active & (rn <= tol)
    conv = conv | done
    active = active & ~done
    if not active.any():
        return X, its, conv, np.where(bn > 0, rn / np.where(bn > 0, bn, 1.0), 0.0)
    Z = ops.Pinv(R, active)
    Pd = Z.copy()
    rz = np.einsum("ij,ij->i", R, Z)
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(max_iter):
            AP = ops.A(Pd, active)
            pAp = np.einsum("ij,ij->i", Pd, AP)
            active = active & (pAp > 0.0)  # A not positive definite on p: give up on that column
            alpha = np.where(active, rz / pAp, 0.0)
            X += alpha[:, None] * Pd
            R -= alpha[:, None] * AP
            its += active
            rn = np.sqrt(np.einsum("ij,ij->i", R, R))
            done = active & (rn <= tol)
            conv = conv | done
            active = active & ~done
            if not active.any():
                break
            Z = ops.Pinv(R, active)
            rz_new = np.einsum("ij,ij->i", R, Z)
            beta = np.where(active, rz_new / rz, 0.0)
            Pd = Z + beta[:, None] * Pd
            rz = np.where(active, rz_new, rz)
    rel = np.where(bn > 0, rn / np.where(bn > 0, bn, 1.0), 0.0)
    return X, its, conv, rel


# ----------------------------------------------------------------------------------------------
# constraint rows in reduced coordinates


@dataclasses.dataclass
class _Rows:
    G: np.ndarray  # (m, nv) bilateral rows (loops, prescribed joints, prescribed sites), reduced coords
    g: np.ndarray  # (m,)
    label_spans: list
    joint_rows: dict
    site_rows: dict
    loop_rows: slice
    Gc: np.ndarray  # (c, nv) coupling rows (null space = range of T), for the PCG path only
    C_idx: np.ndarray  # limited reduced DOFs (unilateral rows e_d)
    lo: np.ndarray | None
    hi: np.ndarray | None

    @property
    def m(self):
        return len(self.g)


def _coupling_rows(mech) -> np.ndarray:
    """Rows c with c T = 0 spanning null(T^T): r_i e_first - r_first e_i per coupled joint (normalised)."""
    cached = mech.__dict__.get("_coupling_rows")
    if cached is not None:
        return cached
    T = mech.T
    rows = []
    if T is not None:
        for col in range(T.shape[1]):
            nz = np.flatnonzero(T[:, col])
            if len(nz) < 2:
                continue
            d0, r0 = nz[0], T[nz[0], col]
            for d in nz[1:]:
                row = np.zeros(mech.nv)
                row[d0], row[d] = T[d, col], -r0
                rows.append(row / np.linalg.norm(row))
    out = np.array(rows).reshape(-1, mech.nv)
    mech.__dict__["_coupling_rows"] = out
    return out


def _build_rows(ctx: Context, cmd, q, h) -> _Rows:
    mech = ctx.mech
    nv = mech.nv
    rows, rhs, spans = [], [], []
    joint_rows, site_rows = {}, {}
    r = 0
    loop_sl = slice(0, 0)
    psites = cmd.site_velocities
    site_axes = getattr(cmd, "site_axes", None) or {}
    if ctx.n_loop_rows:
        G_loop, _ = ctx.loop_rows()
        rows.append(G_loop)
        rhs.append(np.zeros(len(G_loop)))
        spans += [(f"loop '{n}'", len(P)) for n, P in zip(mech.loop_names, mech.loop_axes)]
        r = len(G_loop)
        loop_sl = slice(0, r)
    for name, vel in cmd.joint_velocities.items():
        j = mech.joint_index[name]
        Gj = np.zeros((j.nv, nv))
        Gj[:, j.idx_v:j.idx_v + j.nv] = np.eye(j.nv)
        rows.append(Gj)
        rhs.append(np.asarray(vel, float).reshape(j.nv))
        spans.append((f"prescribed joint '{name}'", j.nv))
        joint_rows[name] = slice(r, r + j.nv)
        r += j.nv
    if psites:
        idx = [mech.site_index[n] for n in psites]
        _, J = ctx.point_jacobians(idx)
        for k, (name, vel) in enumerate(psites.items()):
            Js, vel = J[k], np.asarray(vel, float).reshape(3)
            P = site_axes.get(name)
            if P is not None:
                Js, vel = P @ Js, P @ vel
            rows.append(Js)
            rhs.append(vel)
            spans.append((f"prescribed site '{name}'", len(Js)))
            site_rows[name] = slice(r, r + len(Js))
            r += len(Js)
    G = np.vstack(rows) if rows else np.zeros((0, nv))
    g = np.concatenate(rhs) if rhs else np.zeros(0)
    lo = hi = None
    if len(mech.limited):
        ql = q[mech.limited_q]
        lo = (mech.lower[mech.limited] - ql) / h
        hi = (mech.upper[mech.limited] - ql) / h
    return _Rows(G, g, spans, joint_rows, site_rows, loop_sl, _coupling_rows(mech),
                 np.asarray(mech.limited, dtype=int), lo, hi)


# ----------------------------------------------------------------------------------------------
# solutions


class _Fallback(Exception):
    pass


@dataclasses.dataclass
class MFSolution:
    """Solution of one step in hyper-reduced coordinates (the Solution interface of solve.py)."""

    v: np.ndarray  # hyper-reduced velocity
    lam: np.ndarray  # multipliers of the bilateral rows (loops, prescribed joints, prescribed sites)
    mu: np.ndarray  # multipliers of the limit rows (0 when inactive)
    iterations: int
    solver: str
    residual: float  # relative KKT residual |T^T (A v - b + H^T y)| / |T^T b| (true residual, not PCG's)


def _solve_dense(ctx: Context, system: MatrixFreeSystem, b: np.ndarray, rows: _Rows, h: float):
    """Data-free direct solve: dense LHS (CRBA-style pass + spring cross terms), then solve_direct."""
    mech = ctx.mech
    blocks = system.preconditioner_blocks()
    A = dfm.dense_lhs(ctx, h, blocks, system.C, system.pa, system.pb)
    T = mech.T
    if T is not None:
        A, b = T.T @ A @ T, T.T @ b
    G = rows.G if T is None else rows.G @ T
    cons = Constraints(G=G if rows.m else mech.no_rows, g=rows.g, label_spans=rows.label_spans,
                       joint_rows=rows.joint_rows, site_rows=rows.site_rows, loop_rows=rows.loop_rows)
    if len(mech.limited):
        cons.C, cons.lo, cons.hi, cons.C_labels = mech.limit_rows, rows.lo, rows.hi, mech.limit_labels
    return solve_direct(LinearSystem(A, b), cons)


def _spd_solve(S, rhs, labels):
    S = 0.5 * (S + S.T)
    try:
        L = np.linalg.cholesky(S)
        d = np.abs(np.diag(L))
        if d.min() <= 1e-6 * d.max():
            check_rank(S, labels)
        return np.linalg.solve(L.T, np.linalg.solve(L, rhs))
    except np.linalg.LinAlgError:
        check_rank(S, labels)
        return np.linalg.lstsq(S, rhs, rcond=None)[0]


def _solve_pcg(ctx: Context, system: MatrixFreeSystem, b, rows: _Rows, x0, rtol, max_iter, stats):
    """Eq. (4) with lockstep PCG solves, plus the joint-limit active set. Returns (v_r, y_H, mu, iters)."""
    nv = ctx.topo.nv
    try:
        ctx.P = system.preconditioner(getattr(ctx, "P", None))
    except ValueError as e:
        raise _Fallback(f"preconditioner: {e}") from None
    ops = _Ops(system, ctx.P)
    H = np.vstack([rows.G, rows.Gc]) if len(rows.Gc) else rows.G
    gH = np.concatenate([rows.g, np.zeros(len(rows.Gc))]) if len(rows.Gc) else rows.g
    l = len(H)
    labels = [lab for lab, n in rows.label_spans for _ in range(n)] + ["coupling (hyper-reduced coordinates)"] * len(rows.Gc)
    key = tuple(rows.label_spans) + (len(rows.Gc),)
    X0 = np.empty((l + 1, nv))
    X0[0] = x0
    zc = getattr(ctx, "z_cache", None)
    if l:
        if zc is not None and zc[0] == key:
            X0[1:] = zc[1]
        else:
            X0[1:] = 0.0
    B = np.vstack([b[None], H]) if l else b[None]
    X, its, conv, rel = block_pcg(ops, B, X0, rtol, max_iter)
    stats["solves"] = list(its)
    total = int(its.sum())
    if not conv.all():
        bad = int(np.flatnonzero(~conv)[0])
        raise _Fallback(f"PCG did not reach rtol {rtol:g} in {max_iter} iterations "
                        f"(solve {bad}: relative residual {rel[bad]:.2e})", total)
    u = X[0]
    Z = X[1:].T  # (nv, l)
    if l:
        ctx.z_cache = (key, X[1:].copy())
        y = _spd_solve(H @ Z, H @ u - gH, labels)
        v = u - Z @ y
    else:
        y = np.zeros(0)
        v = u
    mu = np.zeros(len(rows.C_idx))
    if len(rows.C_idx):
        v, y, mu, extra = _active_set(ops, rows, H, gH, Z, u, v, y, labels, rtol, max_iter, stats)
        total += extra
    return v, y, mu, total


def _active_set(ops, rows, H, gH, Z, u, v, y, labels, rtol, max_iter, stats):
    """Primal active set for lo <= v[C_idx] <= hi on top of the equality solution (Eq. 5)."""
    idx, lo, hi = rows.C_idx, rows.lo, rows.hi
    tol = 1e-12
    mu = np.zeros(len(idx))
    viol = (v[idx] < lo - tol) | (v[idx] > hi + tol)
    if not viol.any():
        return v, y, mu, 0
    nv = len(u)
    l = len(H)
    zlim = {}  # limit row -> A^-1 e_d
    extra = 0
    active = {}  # limit row -> 'lo' | 'hi'

    def ensure(rws):
        nonlocal extra
        need = [i for i in rws if i not in zlim]
        if need:
            E = np.zeros((len(need), nv))
            E[np.arange(len(need)), idx[need]] = 1.0
            Xc, its, conv, _ = block_pcg(ops, E, None, rtol, max_iter)
            extra += int(its.sum())
            if not conv.all():
                raise _Fallback(f"PCG did not converge on a joint-limit row in {max_iter} iterations", extra)
            for i, x in zip(need, Xc):
                zlim[i] = x

    def worst_violation(v):
        c = v[idx]
        over = np.maximum(lo - c, c - hi)
        for i in active:
            over[i] = -np.inf
        i = int(np.argmax(over))
        return (i, "lo" if lo[i] - c[i] > c[i] - hi[i] else "hi") if over[i] > tol else (None, None)

    i, side = worst_violation(v)
    for _ in range(3 * len(idx) + 10):
        if i is None:
            break
        active[i] = side
        ensure([i])
        act = list(active)
        while True:
            Zw = np.column_stack([Z] + [zlim[a] for a in act]) if l else np.column_stack([zlim[a] for a in act])
            Cw = np.zeros((len(act), nv))
            Cw[np.arange(len(act)), idx[act]] = 1.0
            Hw = np.vstack([H, Cw]) if l else Cw
            bound = np.array([lo[a] if active[a] == "lo" else hi[a] for a in act])
            rhs = Hw @ u - np.concatenate([gH, bound])
            yy = _spd_solve(Hw @ Zw, rhs, labels + [f"joint limit {a}" for a in act])
            mus = yy[l:]
            sgn = np.array([1.0 if active[a] == "hi" else -1.0 for a in act])
            wrong = sgn * mus < -1e-12 * max(1.0, float(np.abs(mus).max()))
            if wrong.any():  # a bound pulls instead of pushing: release the worst one
                k = int(np.argmin(sgn * mus))
                del active[act[k]]
                act = list(active)
                if not act:
                    yy = np.linalg.solve(H @ Z, H @ u - gH) if l else np.zeros(0)
                    mus = np.zeros(0)
                    Zw = Z
                    break
                continue
            break
        v = u - Zw @ yy if len(yy) else u.copy()
        y = yy[:l]
        mu = np.zeros(len(idx))
        mu[act] = mus
        i, side = worst_violation(v)
    else:
        raise _Fallback("joint-limit active set did not settle", extra)
    if i is not None:
        raise _Fallback("joint-limit active set did not settle", extra)
    stats["active_limits"] = len(active)
    return v, y, mu, extra


# ----------------------------------------------------------------------------------------------
# the step




_DIAG_FIELDS = {f.name for f in dataclasses.fields(Diagnostics)}


def _diagnostics(sol, **kw):
    if "solution" in _DIAG_FIELDS:
        kw["solution"] = sol
    if "residual" in _DIAG_FIELDS:
        kw["residual"] = sol.residual
    return Diagnostics(**kw)


def default_max_iter(nv: int) -> int:
    """PCG iteration cap per solve: 2 nv + 10 (exact arithmetic needs <= nv), at most MAX_ITER_CAP."""
    return int(min(2 * nv + 10, MAX_ITER_CAP))


def step_matrix_free(mech, ctx: Context | None, state: State, cmd, h: float, solver: str = "pcg",
                     rtol: float = DEFAULT_RTOL, max_iter: int | None = None) -> tuple:
    """One step of Eq. (2) without pin.Data; ``solver`` 'pcg' (PCG + Eq. 4, direct fallback) or
    'direct' (dense data-free LHS + solve_direct). Returns (State, StepResult); raises StepError
    (the input state is never modified)."""
    t0 = time.perf_counter()
    if not (h > 0 and math.isfinite(h)):
        raise StepError(f"time step must be positive and finite, got {h}")
    if solver not in ("pcg", "direct"):
        raise ValueError(f"solver must be 'pcg' or 'direct', got {solver!r}")
    ctx = context(mech) if ctx is None else ctx
    tau = mech.torque0 if cmd.joint_torques is None else mech.torque0 + cmd.joint_torques
    if not math.isfinite(state.q.sum() + state.v.sum() + tau.sum()):
        check_inputs(state, tau, cmd)
    for f in cmd.site_forces.values():
        if not np.all(np.isfinite(f)):
            check_inputs(state, tau, cmd)
    nv, topo = mech.nv, ctx.topo
    max_iter = default_max_iter(nv) if max_iter is None else int(max_iter)
    stats = {"solver": solver}
    ctx.last_stats = stats

    # 1-2: kinematics, forces (Eq. 2)
    v_r = mech.to_reduced(state.v)
    ws = ctx.fk(state.q, v_r)
    springs = None
    K = D = None
    if len(mech.spring_ab):
        X = ctx.jac_positions()
        fs, K, D, _ = dfm.spring_terms(mech, X)
        springs = (fs, X)
    sf = {mech.site_index[n]: f for n, f in cmd.site_forces.items()} if cmd.site_forces else None
    b = dfm.rhs(ctx, state.q, v_r, tau, h, sf, springs)
    if not math.isfinite(float(b.sum())):
        raise StepError("non-finite right-hand side of Eq. (2) (state or forces out of range)")
    ps = PointSprings(ctx.spring_ja, ctx.spring_oa, ctx.spring_jb, ctx.spring_ob, K, D) if K is not None else None
    system = MatrixFreeSystem(topo, ws, h, ctx.reduced_diag(h), ps, dfm.body_damping_blocks(ctx, h))
    # 3: constraint rows (reduced coordinates)
    rows = _build_rows(ctx, cmd, state.q, h)
    if rows.m and not math.isfinite(rows.g.sum()):
        check_inputs(state, tau, cmd)

    # 4: solve
    label = solver
    sol = None
    if solver == "pcg":
        try:
            v_red, y, mu, iters = _solve_pcg(ctx, system, b, rows, v_r, rtol, max_iter, stats)
            y_rows = y[:rows.m]
            v_hyp = ctx.to_hyper(v_red)
            # true residual of the KKT stationarity equation (one more O(n + m) LHS product)
            r = system.apply(v_red) - b
            H = np.vstack([rows.G, rows.Gc]) if len(rows.Gc) else rows.G
            if len(H):
                r += H.T @ y
            if len(mu):
                r[rows.C_idx] += mu
            bb = b
            if mech.T is not None:
                r, bb = mech.T.T @ r, mech.T.T @ b
            res = math.sqrt(float(r @ r) / max(float(bb @ bb), 1e-300))
            sol = MFSolution(v_hyp, y_rows, mu, iters, "pcg", res)
        except _Fallback as e:
            stats["fallback"] = str(e.args[0])
            label = "pcg->"
            spent = e.args[1] if len(e.args) > 1 else 0
    if sol is None:
        dsol = _solve_dense(ctx, system, b, rows, h)
        sol = dsol
        if label == "pcg->":
            label = "pcg->" + dsol.solver
            iters = spent + dsol.iterations
        else:
            label, iters = dsol.solver, dsol.iterations
    v_new_h = sol.v
    vmax = float(np.abs(v_new_h).max()) if len(v_new_h) else 0.0
    if not vmax <= MAX_SPEED:
        raise StepError(f"step diverged: max |qdot| = {vmax:.3g} (limit {MAX_SPEED:g})")

    # 5: configuration update, loop post-stabilization
    v_new = mech.to_reduced(v_new_h)
    q_new = pin.integrate(mech.model, state.q, h * v_new)
    if ctx.n_loop_rows:
        G_loop = rows.G[rows.loop_rows]
        if mech.T is not None:
            G_loop = G_loop @ mech.T
        q_new, _ = dfm.project_chord(ctx, q_new, G_loop, mech.held_dofs(cmd.joint_velocities))
        if not math.isfinite(q_new.sum()):
            raise StepError("non-finite configuration after loop stabilization")

    # 6: outputs
    effort = tau.copy()
    for name, sl in rows.joint_rows.items():
        j = mech.joint_index[name]
        effort[j.idx_v:j.idx_v + j.nv] -= sol.lam[sl] / h
    site_forces = {}
    axes = getattr(cmd, "site_axes", None) or {}
    for name, sl in rows.site_rows.items():
        f = -sol.lam[sl] / h
        site_forces[name] = axes[name].T @ f if name in axes else f
    ek, ep, es = dfm.energies(ctx, q_new, v_new)  # leaves (q_new, v_new) in the workspace
    viol_pos = float(np.abs(ctx.loop_phi()).max()) if ctx.n_loop_rows else 0.0
    viol_vel = float(np.abs(rows.G @ v_new - rows.g).max()) if rows.m else 0.0
    if not math.isfinite(ek + ep + es):
        raise StepError("non-finite energy after the step")
    stats["iterations"] = int(iters)
    diag = _diagnostics(sol, E_kin=ek, E_pot=ep, E_spring=es, E_total=ek + ep + es, violation_pos=viol_pos,
                        violation_vel=viol_vel, iterations=int(iters), solver=label,
                        wall_time=time.perf_counter() - t0)
    new = State(state.t + h, q_new, v_new_h)
    return new, StepResult(new.t, q_new, v_new, effort, site_forces, diag)


# ----------------------------------------------------------------------------------------------
# solver selection


class DirectBackend:
    """The Pinocchio direct pipeline (stepper.step) with its pin.Data (small models only)."""

    name = "direct"

    def __init__(self, mech):
        from redmax_ros.core.step.pipeline import step
        self.mech, self._step = mech, step
        self.data = mech.model.createData()

    def step(self, state, cmd, h):
        return self._step(self.mech, self.data, state, cmd, h)


class DataFreeBackend:
    """step_matrix_free with solver 'pcg' or 'direct' (dense, data-free)."""

    def __init__(self, mech, solver, rtol=DEFAULT_RTOL, max_iter=None):
        self.mech, self.solver, self.rtol, self.max_iter = mech, solver, rtol, max_iter
        self.name = solver if solver == "pcg" else "direct (data-free)"
        self.ctx = context(mech)
        self.data = None

    def step(self, state, cmd, h):
        return step_matrix_free(self.mech, self.ctx, state, cmd, h, self.solver, self.rtol, self.max_iter)


# The auto rule (docs/solvers.md). Per-step cost models [s], fitted to redmax_bench scaling on the
# project's 2-core benchmark machine (CPU time, single-threaded BLAS); only their ratio matters.
AUTO_DIRECT_NV = 48  # at or below: direct without probing (PCG's fixed per-step Python cost dominates)
AUTO_PROBE_STEPS = 5
PCG_S_PER_STEP = 1.0e-3  # fixed: numpy/Python work of a step (rows, small solves, stabilization)
PCG_S_PER_JOINT_STEP = 1.5e-6  # kinematics, RHS, factorisation, stabilization, energies, per DOF
PCG_S_PER_JOINT_ITER = 1.2e-7  # one LHS product + one P^-1 application, per DOF and iteration
PCG_S_PER_ITER = 3.0e-5  # fixed per-iteration overhead
DENSE_S_PER_STEP = 6.0e-4
DENSE_S_PER_N3 = 2.5e-11  # dense Cholesky (Eigen LLT) + KKT, per nv^3
DENSE_S_PER_N2 = 4.0e-8  # dense assembly per nv^2 (deep chains; less on bushy trees)


def predicted_costs(nv: int, iters_per_step: float) -> tuple:
    """(PCG, direct) predicted seconds per step for nv DOFs and the measured PCG iterations per step
    (summed over the l + 1 solves of Eq. 4)."""
    pcg_t = PCG_S_PER_STEP + PCG_S_PER_JOINT_STEP * nv + iters_per_step * (PCG_S_PER_JOINT_ITER * nv + PCG_S_PER_ITER)
    direct_t = DENSE_S_PER_STEP + PCG_S_PER_JOINT_STEP * nv + DENSE_S_PER_N3 * nv ** 3 + DENSE_S_PER_N2 * nv ** 2
    return pcg_t, direct_t


class AutoBackend:
    """``solver: auto``: direct for nv <= AUTO_DIRECT_NV; otherwise PCG for AUTO_PROBE_STEPS steps,
    then PCG if its predicted cost with the measured iterations per step is below the direct
    solver's (dense Cholesky ~ nv^3), else direct (Pinocchio pipeline when nv <= PIN_DATA_MAX_NV,
    data-free dense otherwise). A PCG fallback during the probe chooses direct."""

    def __init__(self, mech, rtol=DEFAULT_RTOL, max_iter=None):
        self.mech = mech
        self.pcg = DataFreeBackend(mech, "pcg", rtol, max_iter)
        self.choice = None
        self.iters = []
        self.data = None
        self.reason = ""
        if mech.nv <= AUTO_DIRECT_NV:
            self._choose("direct", f"nv = {mech.nv} <= {AUTO_DIRECT_NV}")

    @property
    def name(self):
        return "auto:" + (self.choice if self.choice else "probing")

    def _choose(self, what, reason):
        self.reason = reason
        if what == "pcg":
            self.choice, self.impl = "pcg", self.pcg
            return
        self.choice = "direct"
        self.impl = DirectBackend(self.mech) if self.mech.nv <= PIN_DATA_MAX_NV else DataFreeBackend(self.mech, "direct")
        self.data = getattr(self.impl, "data", None)

    def step(self, state, cmd, h):
        if self.choice is not None:
            return self.impl.step(state, cmd, h)
        new, res = self.pcg.step(state, cmd, h)
        d = res.diagnostics
        if d.solver != "pcg":
            self._choose("direct", f"PCG fell back during the probe ({d.solver})")
            return new, res
        self.iters.append(d.iterations)
        if len(self.iters) >= AUTO_PROBE_STEPS:
            k = float(np.mean(self.iters))
            tp, td = predicted_costs(self.mech.nv, k)
            self._choose("pcg" if tp < td else "direct",
                         f"{k:.1f} PCG iterations/step: predicted {tp * 1e3:.2f} ms (PCG) vs {td * 1e3:.2f} ms (direct)")
        return new, res


def make_backend(mech, solver: str, rtol: float = DEFAULT_RTOL, max_iter: int | None = None):
    """The stepping backend for ``solver`` ('direct' | 'pcg' | 'auto'). 'direct' uses the Pinocchio
    pipeline when nv <= PIN_DATA_MAX_NV (pin.Data fits) and the data-free dense solver above.
    Scenes with contact or joint friction (Mechanism.friction, Staggered Projections / BISP) or catalogue
    joints and force elements (Mechanism.extras) need the Pinocchio pipeline: 'direct' and 'auto' use
    it at any size, 'pcg' is a SceneError."""
    unsupported = [what for what, attr in (("contact or joint friction", "friction"),
                                           ("catalogue joints/force elements", "extras"))
                   if getattr(mech, attr, None) is not None]
    if unsupported:
        if solver == "pcg":
            raise SceneError(mech.spec.source, "solver",
                             f"solver 'pcg' does not support {' and '.join(unsupported)} (use direct or auto)")
        if solver in ("direct", "auto"):
            return DirectBackend(mech)
    if getattr(mech, "coriolis_implicit", False) and (solver != "direct" or mech.nv > PIN_DATA_MAX_NV):
        raise SceneError(mech.spec.source, "integrator.coriolis",
                         f"'implicit' is implemented in the Pinocchio pipeline only (solver 'direct' with at most "
                         f"{PIN_DATA_MAX_NV} DOFs; here solver '{solver}', {mech.nv} DOFs); use coriolis: explicit")
    if solver == "direct":
        return DirectBackend(mech) if mech.nv <= PIN_DATA_MAX_NV else DataFreeBackend(mech, "direct")
    if solver == "pcg":
        return DataFreeBackend(mech, "pcg", rtol, max_iter)
    if solver == "auto":
        return AutoBackend(mech, rtol, max_iter)
    raise SceneError(mech.spec.source, "solver", f"unknown solver '{solver}' (direct, pcg, auto)")
