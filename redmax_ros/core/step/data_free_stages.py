"""The data-free backend's velocity stages (stages 1-4 of step.pipeline.step without ``pin.Data``, whose
memory grows as nv^3 in pin 4.1): Wang et al. 2019 §3, Eq. (2)-(4), Alg. 1.

1. O(n) forward kinematics, body twists and bias accelerations (tree_kinematics.Context, cached on
   (q, qdot));
2. the RHS of Eq. (2) in O(n + m) and the LHS as an O(n + m) operator (solvers.pcg.MatrixFreeSystem);
3. the bilateral rows H (loop closures, prescribed joints and sites, Eq. 7) in reduced coordinates by
   constraints.build; hyper-reduced couplings (Eq. 8-10) are imposed as extra bilateral rows whose null
   space is the range of T = J_rR (the constrained reduced solution is exactly T qdot_R of Eq. 10, with
   the same multipliers for the other rows), so the tree-structured preconditioner still applies;
4. ``solver='pcg'``: the Projected Block Jacobi Preconditioner factored once (Alg. 1 lines 1-8, O(n)),
   Eq. (4) as l + 1 lockstep PCG solves (solvers.lockstep_pcg: u = A^-1 b warm-started with the
   previous velocity, Z = A^-1 H^T warm-started with the previous step's Z), the small dense solve
   (H Z) lam = H u - g and qdot = u - Z lam, and the joint limits (Eq. 5) by the active set; if a PCG
   solve misses its tolerance within its cap (or the preconditioner or the active set fails) the step
   is redone with the direct solver and Diagnostics.solver says ``pcg->direct`` (or ``pcg->qp``).
   ``solver='direct'``: a dense data-free LHS (tree_forces.dense_lhs) and solvers.direct.solve_direct
   (Cholesky / KKT / ProxSuite QP): the direct solver for models too large for pin.Data.

Diagnostics.iterations of a PCG step is the total number of PCG iterations over all its solves
(l + 1 with l bilateral rows, plus any active limit rows), like the paper's Table 2 counts; the
per-solve counts are in ``ws.tree.last_stats``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from redmax_ros.core.dynamics import constraints
from redmax_ros.core.dynamics import tree_forces as tf
from redmax_ros.core.solvers.problem import Constraints
from redmax_ros.core.solvers.problem import LinearSystem
from redmax_ros.core.dynamics.springs import geometric_blocks_kernel, spring_shift_kernel
from redmax_ros.core.errors import StepError
from redmax_ros.core.linalg import all_finite
from redmax_ros.core.solvers.direct import solve_direct
from redmax_ros.core.solvers.lockstep_kernel import kkt_residual_kernel
from redmax_ros.core.solvers.lockstep_pcg import DEFAULT_RTOL, Fallback, Ops, active_set, block_pcg, default_max_iter, dual_solve
from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.solvers.pcg import MatrixFreeSystem, PointSprings
from redmax_ros.core.step.pipeline import VelocitySolve
from redmax_ros.core.step.state import check_applied, check_inputs, check_rows


@dataclasses.dataclass
class MFSolution:
    """Solution of one step in hyper-reduced coordinates (the Solution interface of solvers/direct.py)."""

    v: np.ndarray  # hyper-reduced velocity
    lam: np.ndarray  # multipliers of the bilateral rows (loops, prescribed joints, prescribed sites)
    mu: np.ndarray  # multipliers of the limit rows (0 when inactive)
    iterations: int
    solver: str
    residual: float  # relative KKT residual |T^T (A v - b + H^T y)| / |T^T b| (true residual, not PCG's)


def coupling_rows(mech, ws) -> np.ndarray:
    """Rows c with c T = 0 spanning null(T^T): r_i e_first - r_first e_i per coupled joint (normalised;
    cached in the workspace)."""
    cached = ws.cache.get("coupling rows")
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
    out = ws.cache["coupling rows"] = np.array(rows).reshape(-1, mech.nv)
    return out


def coupling_scale(mech, ws) -> float:
    """max_i sum_j |T_ij| (1 without couplings): max |qdot_r| <= it x max |qdot_R| (cached in ws); the scale of
    state.check_rows for the PCG path's reduced-coordinate rows."""
    s = ws.cache.get("coupling scale")
    if s is None:
        s = ws.cache["coupling scale"] = 1.0 if mech.T is None else float(np.abs(mech.T).sum(1).max())
    return s


def lhs_system(ws, rws, h: float, springs: PointSprings | None, blocks: np.ndarray | None,
               ends: tuple | None = None, C: np.ndarray | None = None) -> MatrixFreeSystem:
    """This step's LHS of Eq. (2) as an O(n + m) operator: the workspace's MatrixFreeSystem (made at its first
    step, kept in ws.cache) renewed for the kinematics ``rws``, h, the springs (world end points ``ends``, their
    h D + h^2 K ``C``) and the maximal blocks."""
    ctx = ws.tree
    system = ws.cache.get(_SYSTEM_KEY)
    if system is None:
        system = ws.cache[_SYSTEM_KEY] = MatrixFreeSystem(ctx.topo, rws, h, ctx.reduced_diag(h), springs, blocks)
        return system
    return system.renew(rws, h, ctx.reduced_diag(h), springs, blocks, ends, C)


def point_springs(ws, K: np.ndarray, D: np.ndarray) -> PointSprings:
    """The maximal springs of the LHS with this step's stiffness K and damping D ((P, 3, 3) arrays of
    springs.spring_forces): one PointSprings per workspace (ws.cache; its ends from the Context), whose K
    and D are replaced each step."""
    ps = ws.cache.get(_SPRINGS_KEY)
    if ps is None:
        ctx = ws.tree
        ps = ws.cache[_SPRINGS_KEY] = PointSprings(ctx.spring_ja, ctx.spring_oa, ctx.spring_jb, ctx.spring_ob, K, D)
    else:
        ps.stiffness, ps.damping = K, D
    return ps


_SYSTEM_KEY = "matrix-free LHS"  # ws.cache: the data-free step's MatrixFreeSystem
_SPRINGS_KEY = "matrix-free springs"  # ws.cache: its PointSprings


def build_rows(mech, ws, cmd, q, h, hyper: bool) -> Constraints:
    """Stage 3 on the recursive kinematics: loop rows and prescribed-site Jacobians from the Context,
    then constraints.build (reduced coordinates for PCG, hyper-reduced for the dense direct solver)."""
    ctx = ws.tree
    G_loop = ctx.loop_jacobian() if ctx.n_loop_rows else None
    psites = cmd.site_velocities
    J_sites = ctx.point_jacobians([mech.site_index[n] for n in psites])[1] if psites else None
    return constraints.build(mech, ws, G_loop, J_sites, q, cmd.joint_velocities, psites, h, cmd.site_axes, hyper)


def solve_dense(mech, ws, system: MatrixFreeSystem, b: np.ndarray, cons: Constraints, h: float, tau=None,
                cmd=None):
    """Data-free direct solve: dense LHS (CRBA-style pass + spring cross terms), then solve_direct.
    ``cons`` in hyper-reduced coordinates. With ``tau`` and ``cmd`` the applied torques and site forces are
    checked against the divergence limit on the dense LHS first (state.check_applied)."""
    blocks = system.preconditioner_blocks()
    A = tf.dense_lhs(ws.tree, h, blocks, system.C, system.pa, system.pb)
    T = mech.T
    if T is not None:
        A, b = T.T @ A @ T, T.T @ b
    if tau is not None:
        terms = ()
        if cmd.site_forces:
            names = list(cmd.site_forces)
            J = ws.tree.point_jacobians([mech.site_index[n] for n in names])[1]
            terms = [(n, J[k].T @ cmd.site_forces[n]) for k, n in enumerate(names)]
        check_applied(mech, ws, A, tau, h, cmd, terms)
    if not cons.m:
        cons.G = mech.no_rows
    return solve_direct(LinearSystem(A, b), cons, deadline=ws.deadline)


def solve_pcg(mech, ws, system: MatrixFreeSystem, b, cons: Constraints, x0, rtol, max_iter, stats):
    """Eq. (4) with lockstep PCG solves, plus the joint-limit active set. ``cons`` in reduced coordinates.
    Returns (v_r, y_H, mu, iters, H) with H the bilateral rows (cons's, then the couplings'). The step's
    deadline (ws.deadline) is checked every PCG iteration."""
    ctx = ws.tree
    nv = ctx.topo.nv
    try:
        ctx.P = system.preconditioner(ctx.P)
    except ValueError as e:
        raise Fallback(f"preconditioner: {e}") from None
    ops = Ops(system, ctx.P, ws.cache.setdefault("lockstep scratch", {}))
    Gc = coupling_rows(mech, ws)
    H = np.ascontiguousarray(np.vstack([cons.G, Gc]) if len(Gc) else cons.G, dtype=float)
    gH = np.ascontiguousarray(np.concatenate([cons.g, np.zeros(len(Gc))]) if len(Gc) else cons.g, dtype=float)
    l = len(H)
    key = tuple(cons.label_spans) + (len(Gc),)
    labels = ws.cache.get(("row labels", key))
    if labels is None:  # per set of rows, kept
        labels = ws.cache[("row labels", key)] = ([lab for lab, n in cons.label_spans for _ in range(n)]
                                                  + ["coupling (hyper-reduced coordinates)"] * len(Gc))
    X0 = np.empty((l + 1, nv))
    X0[0] = x0
    zc = ctx.z_cache
    if l:
        if zc is not None and zc[0] == key:
            X0[1:] = zc[1]
        else:
            X0[1:] = 0.0
    if l:
        B = np.empty((l + 1, nv))
        B[0] = b
        B[1:] = H
    else:
        B = b[None]
    X, its, conv, rel = block_pcg(ops, B, X0, rtol, max_iter, ws.deadline)
    stats["solves"] = its.tolist()
    total = sum(stats["solves"])
    if not all(conv.tolist()):  # (conv.all(): ~1 us more)
        bad = int(np.flatnonzero(~conv)[0])
        raise Fallback(f"PCG did not reach rtol {rtol:g} in {max_iter} iterations "
                       f"(solve {bad}: relative residual {rel[bad]:.2e})", total)
    u = X[0]
    Z = X[1:].T  # (nv, l)
    if l:
        ctx.z_cache = (key, X[1:].copy())
        y, v = dual_solve(H, X, gH, labels)
    else:
        y = np.zeros(0)
        v = u
    mu = _NO_LIMITS
    if len(mech.limited):
        limits = _LimitRows(np.asarray(mech.limited, dtype=int), cons.lo, cons.hi)
        v, y, mu, extra = active_set(ops, limits, H, gH, Z, u, v, y, labels, rtol, max_iter, stats, ws.deadline)
        total += extra
    return v, y, mu, total, H


_NO_LIMITS = np.zeros(0)  # mu without limit rows
_NO_DOFS = np.zeros(0, dtype=np.int64)  # limited DOFs of kkt_residual_kernel without limit rows


def limited_dofs(mech, ws) -> np.ndarray:
    """mech.limited as an int64 array (cached in ws)."""
    d = ws.cache.get("limited dofs")
    if d is None:
        d = ws.cache["limited dofs"] = np.asarray(mech.limited, dtype=np.int64).reshape(-1)
    return d


@dataclasses.dataclass
class _LimitRows:
    C_idx: np.ndarray  # limited reduced DOFs (unilateral rows e_d)
    lo: np.ndarray | None
    hi: np.ndarray | None


def data_free_velocity(mech, ws, state, cmd, tau, h, solver="pcg", rtol=DEFAULT_RTOL, max_iter=None):
    """Stages 1-4 without pin.Data (module docstring); the velocity argument of step.pipeline.step."""
    if cmd.body_twists:  # body-twist prescriptions are implemented in the Pinocchio pipeline only
        raise StepError(f"body-twist prescriptions ({', '.join(cmd.body_twists)}) are not supported by the data-free "
                        f"path (solver '{solver}' without pin.Data); use solver 'direct' (at most 100 DOFs)")
    ctx = ws.tree
    nv = mech.nv
    max_iter = default_max_iter(nv) if max_iter is None else int(max_iter)
    stats = {"solver": solver}
    ctx.last_stats = stats

    # 1-2: kinematics, forces (Eq. 2); BDF2 (ws.bdf2, step/scheme.py): (q, v) = (q*, v*), h = hat h
    pt = ws.bdf2
    q_base = state.q if pt is None else pt.q_base  # joint springs and joint limits act from q^
    v_r = ws.to_reduced(state.v)
    rws = ctx.fk(state.q, v_r)
    springs = rhs_springs = None
    K = D = C = ends = None
    if len(mech.spring_ab):
        V = None
        if ctx.spring_arrays.needs_velocities:  # site velocities v_o + w x x of explicit dampers (implicit: false)
            ov = rws.ov[ctx.jac_jid]
            V = ov[:, :3] + np.cross(ov[:, 3:], ctx.jac_positions())
        # at q*: where the spring forces act (X, their Jacobians' points), their forces, K, D, ends and C of the LHS
        X, fs, K, D, ends, C = ctx.spring_state(h, V)
        springs = rhs_springs = (fs, X)
        if pt is not None:  # BDF2: f(q+) ~ f(q*) + K' (q* (-) q^) - K hat h qdot+ (springs.spring_shift), O(n + m)
            rows = mech.spring_rows
            corr = np.empty_like(fs)
            ex = ctx.spring_arrays.explicit
            spring_shift_kernel(X, rows[:, 0].copy(), rows[:, 1].copy(), mech.spring_k, mech.spring_rest, ex,
                                rc.site_jv(ctx.topo, rws, ctx.jac_jid, X, pt.back), ctx.spring_ja, ctx.spring_jb,
                                ctx.topo.mass, h * h, corr)
            rhs_springs = (fs + corr, X)
            ws.spring_ends = ends  # (pa, pb) at q*, for the order control (pipeline.spring_miss)
    sf = {mech.site_index[n]: f for n, f in cmd.site_forces.items()} if cmd.site_forces else None
    b = tf.rhs(ctx, q_base, v_r, tau, h, sf, rhs_springs)
    if pt is not None:  # RHS M v^ + hat h f: the momentum of v^ instead of v*
        b += rc.mass_matrix_product(ctx.topo, rws, pt.v_mom - v_r)
        if springs is not None:  # ... and the turn of the lever arms, B (q* (-) q^), unclamped lever blocks at q*
            B = np.zeros((ctx.topo.njoints, 6, 6))
            geometric_blocks_kernel(ctx.spring_ja, np.ascontiguousarray(X[rows[:, 0]]), ctx.spring_jb,
                                    np.ascontiguousarray(X[rows[:, 1]]), np.ascontiguousarray(fs),
                                    ex, 1.0, rws.I, B)
            b += h * rc.jtw(ctx.topo, rws, np.einsum("jab,jb->ja", B, rc.jv(ctx.topo, rws, pt.back)))
    if not all_finite(b):
        raise StepError("non-finite right-hand side of Eq. (2) (state or forces out of range)")
    ps = None if K is None else point_springs(ws, K, D)
    system = lhs_system(ws, rws, h, ps, tf.maximal_blocks(ctx, h, springs, ends), ends, C)
    # 3: constraint rows (reduced coordinates for PCG)
    cons = build_rows(mech, ws, cmd, q_base, h, hyper=solver != "pcg")
    if cons.m:
        if not all_finite(cons.g):
            check_inputs(state, tau, cmd)
        check_rows(cons, 1.0 if solver != "pcg" else coupling_scale(mech, ws))  # before any solve

    # 4: solve
    label = solver
    sol = viol_vel = None
    if solver == "pcg":
        try:
            v_red, y, mu, iters, H = solve_pcg(mech, ws, system, b, cons, v_r, rtol, max_iter, stats)
            y_rows = y[:cons.m]
            v_hyp = ctx.to_hyper(v_red)
            # true residual of the KKT stationarity equation (one more O(n + m) LHS product) and the rows' velocity
            # violation, one compiled call
            r = np.empty(nv)
            rr, bb, viol = kkt_residual_kernel(*system.lhs_args(), *system.lhs_scratch(), v_red, b, H, y,
                                               limited_dofs(mech, ws) if len(mu) else _NO_DOFS, mu, cons.m,
                                               np.ascontiguousarray(cons.g, dtype=float), r)
            if ws.T is None:  # else the violation of the hyper-reduced velocity's T qdot_R below
                viol_vel = viol
            if mech.T is not None:
                r, bb = mech.T.T @ r, mech.T.T @ b
                rr, bb = float(r @ r), float(bb @ bb)
            res = math.sqrt(rr / max(bb, 1e-300))
            sol = MFSolution(v_hyp, y_rows, mu, iters, "pcg", res)
        except Fallback as e:
            stats["fallback"] = str(e.args[0])
            label = "pcg->"
            spent = e.args[1] if len(e.args) > 1 else 0
            cons = build_rows(mech, ws, cmd, q_base, h, hyper=True)
    if sol is None:
        dsol = solve_dense(mech, ws, system, b, cons, h, tau, cmd)
        sol = dsol
        if label == "pcg->":
            label = "pcg->" + dsol.solver
            iters = spent + dsol.iterations
        else:
            label, iters = dsol.solver, dsol.iterations
    stats["iterations"] = int(iters)
    G_loop = None
    if ctx.n_loop_rows:  # hyper-reduced loop rows for the post-stabilization
        G_loop = cons.G[cons.loop_rows]
        if mech.T is not None and cons.G.shape[1] == nv:
            G_loop = G_loop @ mech.T
    v_new = ws.to_reduced(sol.v)
    if viol_vel is None or not cons.m:
        viol_vel = float(np.abs(cons.G @ (v_new if cons.G.shape[1] == nv else sol.v) - cons.g).max()) if cons.m else 0.0
    return VelocitySolve(sol, cons.joint_rows, cons.site_rows, G_loop, viol_vel, label, int(iters))
