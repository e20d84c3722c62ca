"""Force stage: the LHS matrix and RHS vector of Eq. (2) in reduced coordinates.

    (J^T (M_m + h D_m + h^2 K_m) J + h D_r + h^2 K_r) qdot^(k+1)
        = J^T M_m J qdot^(k) + h (f_r + J^T (f_m - M_m Jdot qdot^(k)))          (Eq. 2)

with stiffness written positive here (K = -df/dx). Terms and where they come from:
  * J^T M_m J + armature: Pinocchio CRBA (kinematics.Kinematics.M).
  * J^T (f_m^{coriolis, gravity} - M_m Jdot qdot): -nle (RNEA at zero acceleration).
  * reduced implicit joint springs/dampers K_r, D_r (Sueda's notes §2.6, joint stiffness/damping).
  * maximal implicit point-to-point springs/dampers between sites, projected through the point
    Jacobians (Eq. S2.4), with the full 3x3 spring stiffness including the change of spring direction,
    plus (integrator.spring_stiffness: full, the default) the lever-arm blocks of K_m, the rotation of each
    end's torque about its body's centre of mass at fixed force (notes Eq. 1.32, 1.44, symmetrised;
    springs.geometric_blocks_kernel), as per-body 6x6 blocks J_j^T B_j J_j (:func:`add_geometric_stiffness`).
  * body damping per body (maximal, implicit; notes §1.9.1, f = -D phi): D_m = c diag(m I3, I_com)
    (form 'mass') or D_m = c I6 on the body twist at the COM (form 'twist', the reference's), both as
    c diag(m_d I3, I_d) with mech.body_damping_mass/inertia.
  * explicit joint torques (reduced) and constant world wrenches (maximal).
  * opt-in (integrator.coriolis: implicit): the Coriolis/gyroscopic part of nle linearised about qdot^(k),
    h K_v on the LHS and h K_v qdot^(k) on the RHS with K_v = d nle / d qdot (then A is not symmetric).
Hyper-reduced coordinates (Eq. 9-10) project the result with T = J_rR: T^T A T, T^T b.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.kinematics import Kinematics, frame_jacobian
from redmax_ros.core.jit import njit
from redmax_ros.core.solvers.problem import LinearSystem
from redmax_ros.core.dynamics.springs import (clamp_lever_blocks, geometric_blocks_kernel, joint_displacement,
                                              spring_shift_kernel,
                                              spring_terms)
from redmax_ros.core.dynamics.tree_forces import dense_crba_kernel


def coriolis_jacobian(mech, ws, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """K_v = d(nle)/d(qdot) (nv,nv) at (q, v) (gravity does not depend on qdot).

    The Coriolis/centrifugal part c(q, v) of nle (RNEA at zero acceleration without gravity) is exactly
    quadratic in v, so each column is a central difference that is exact up to round-off:
    K_v e_i = (c(v + s e_i) - c(v - s e_i)) / (2 s) for any s (s = max|v| minimises round-off).
    Pinocchio's computeRNEADerivatives is not used: in pin 4.1 its dtau_dv is wrong for joints with a
    velocity-dependent bias (universal, composite: off by up to 50 %, checked against finite differences;
    spherical, free flyer and translation joints agree to 1e-11). Cost: 2 nv RNEA calls on a zero-gravity
    copy of the model (its own pin.Data, kept in the workspace cache; the step's pin.Data is untouched)."""
    zg = ws.cache.get("coriolis")
    if zg is None:
        model0 = pin.Model(mech.model)
        model0.gravity = pin.Motion.Zero()
        zg = ws.cache["coriolis"] = (model0, model0.createData(), np.zeros(mech.nv))
    model0, d0, a0 = zg
    return quadratic_jacobian(lambda x: pin.rnea(model0, d0, q, x, a0).copy(), v)


def quadratic_jacobian(fn, v: np.ndarray) -> np.ndarray:
    """d fn / d v (n,n) at v of a function fn(v) (n,) that is a quadratic form of v: exact central
    differences (fn(v + s e_i) - fn(v - s e_i)) / (2 s) with s = max|v| (zero at v = 0)."""
    n = len(v)
    K = np.zeros((n, n))
    s = float(np.abs(v).max()) if n else 0.0
    if s == 0.0:
        return K
    e = v.copy()
    for i in range(n):
        e[i] = v[i] + s
        cp = fn(e)
        e[i] = v[i] - s
        K[:, i] = (cp - fn(e)) / (2.0 * s)
        e[i] = v[i]
    return K


def add_geometric_stiffness(ws, A, ja, pa, jb, pb, f, explicit, scale, clamp=True) -> None:
    """A += scale * sum_j J_j^T B_j J_j: the lever-arm blocks B_j of the springs' full maximal stiffness
    (springs.geometric_blocks_kernel: ends of force f (P,3) at world points pa, pb on joints ja, jb; explicit
    springs skipped) through each body's world spatial Jacobian (Pinocchio's WORLD joint Jacobian in ws.data,
    from computeAllTerms), by the composite pass of tree_forces.dense_crba_kernel; each body's block kept above
    minus half its spatial inertia (springs.clamp_lever_blocks). Pinocchio pipeline."""
    topo = ws.tree.topo
    blocks = np.zeros((topo.njoints, 6, 6))
    ja = np.ascontiguousarray(ja, dtype=np.int64)
    jb = np.ascontiguousarray(jb, dtype=np.int64)
    ex = np.zeros(len(ja), dtype=np.int64) if explicit is None else np.asarray(explicit, dtype=np.int64)
    inertia = np.zeros_like(blocks)  # world spatial inertias (v_o, w) of the bodies with a spring end
    model, data = ws.mech.model, ws.data
    for j in set(ja.tolist()) | set(jb.tolist()):
        if j > 0:
            inertia[j] = data.oMi[j].act(model.inertias[j]).matrix()
    geometric_blocks_kernel(ja, np.ascontiguousarray(pa, dtype=float), jb, np.ascontiguousarray(pb, dtype=float),
                            np.ascontiguousarray(f, dtype=float).reshape(-1, 3), ex, float(scale), inertia, blocks)
    if clamp:
        clamp_lever_blocks(inertia, blocks)
    St = np.ascontiguousarray(ws.data.J.reshape(6, -1).T)
    dense_crba_kernel(topo.parents, topo.idx_v, topo.nv_j, St, blocks, A)


def assemble(mech, ws, kin: Kinematics, q, v_r, tau, h, site_forces=None) -> LinearSystem:
    """Eq. (2): returns (A, b) in hyper-reduced coordinates (projected by the workspace's J_rR, ws.T).
    With a BDF2 step (ws.bdf2, step/scheme.py): (q, v_r) are (q*, v*), h is hat h, the joint springs act at q^,
    the maximal springs are linearised about q* (f(q*) + K' (q* (-) q^), springs.spring_shift, plus the turn of
    their lever arms) and the RHS is M v^ + hat h f.

    ``tau`` (nv,) explicit joint torques [N m]; ``site_forces`` {site index: (3,) world force [N]}
    explicit maximal point forces (J_site^T f). Needs ws.data from kinematics.compute.
    """
    data = ws.data
    M = kin.M
    pt = ws.bdf2  # BDF2 (step/scheme.py): (q, v_r) = (q*, v*), h = hat h; joint springs at q^, RHS M v^
    A = None  # maximal and catalogue terms of the LHS, added to M + h D_r + h^2 K_r below
    f = tau - kin.nle  # f_r + J^T (f_m - M_m Jdot qdot)
    if mech.has_stiffness:
        f -= mech.stiffness * joint_displacement(mech, q if pt is None else pt.q_base)
    if len(mech.spring_ab):  # maximal implicit springs: J^T (h D_m + h^2 K_m) J, J^T f_m
        fs, K, D, Jd, _ = spring_terms(mech, kin.X, kin.J, v_r)  # implicit: false springs: K = D = 0, f at step k
        P, nv = Jd.shape[0], Jd.shape[2]
        W = np.matmul(h * D + (h * h) * K, Jd)
        Jf = Jd.reshape(3 * P, nv)
        A = Jf.T @ W.reshape(3 * P, nv)
        f += Jf.T @ fs.reshape(3 * P)
        rows = mech.spring_rows
        pa, pb = kin.X[rows[:, 0]], kin.X[rows[:, 1]]  # the springs' ends
        if pt is not None:  # BDF2: f(q+) ~ f(q*) + K' (q* (-) q^) - K hat h qdot+ (springs.spring_shift)
            corr = np.empty((P, 3))
            ex = np.zeros(P, np.int64) if mech.spring_explicit is None else mech.spring_explicit.astype(np.int64)
            spring_shift_kernel(kin.X, rows[:, 0].copy(), rows[:, 1].copy(), mech.spring_k, mech.spring_rest, ex,
                                kin.J @ pt.back, ws.tree.spring_ja, ws.tree.spring_jb, ws.tree.topo.mass, h * h, corr)
            f += Jf.T @ corr.reshape(3 * P)
            ws.spring_ends = (pa, pb)  # at q*, for the order control (pipeline.spring_miss)
            # ... and the turn of the lever arms, B (q* (-) q^) with the unclamped lever blocks B at q*
            B = np.zeros_like(A)
            add_geometric_stiffness(ws, B, ws.tree.spring_ja, pa, ws.tree.spring_jb, pb, fs, mech.spring_explicit, 1.0,
                                    clamp=False)
            f += B @ pt.back
        if mech.spring_geometric:
            add_geometric_stiffness(ws, A, ws.tree.spring_ja, pa, ws.tree.spring_jb, pb, fs, mech.spring_explicit,
                                    h * h)
    if len(mech.damped_bodies) or mech.extras is not None:
        A = np.zeros_like(M) if A is None else A
    for bi in mech.damped_bodies:  # body damping D_m = c diag(m_d I3, I_d) at the COM, implicit
        _, Jc, Jw, R = frame_jacobian(mech, data, mech.body_com_fid[bi])
        Iw = R @ mech.body_damping_inertia[bi] @ R.T
        A += (h * mech.body_damping[bi]) * (mech.body_damping_mass[bi] * Jc.T @ Jc + Jw.T @ Iw @ Jw)
    for bi, fw in zip(mech.wrench_body, mech.wrench_fw):  # constant world wrenches at the COM
        _, Jc, Jw, _ = frame_jacobian(mech, data, mech.body_com_fid[bi])
        f += Jc.T @ fw[:3] + Jw.T @ fw[3:]
    if site_forces:
        for s, fv in site_forces.items():
            f += kin.J[kin.row[s]].T @ fv
    if ws.extras is not None:  # catalogue force elements; Jdot_rR qdot_R of spline/exp joints (catalogue_hooks.py)
        ws.extras.forces(mech, ws, kin, q, v_r, h, A, f)
    if mech.coriolis_implicit:  # nle(q, qdot+) ~ nle(q, qdot) + K_v (qdot+ - qdot): h K_v on the LHS, h K_v qdot on the RHS
        Kv = coriolis_jacobian(mech, ws, q, v_r)
        if ws.extras is not None and ws.extras.maps is not None:  # M Jdot_rR qdot_R of mapped joints (Eq. 2.89)
            Kv += M @ quadratic_jacobian(lambda x: ws.extras.maps.bias(q, x, mech.nv), v_r)
        A = h * Kv if A is None else A + h * Kv
        f += Kv @ v_r
    A, b = _lhs_rhs(M, ws.tree.reduced_diag(h), _NONE if A is None else A, f, v_r if pt is None else pt.v_mom, h,
                    _NONE if ws.T is None else ws.T)
    return LinearSystem(A, b, not mech.coriolis_implicit)


_NONE = np.zeros((0, 0))


@njit
def _lhs_rhs(M, dvec, A_add, f, v, h, T):
    """A = T^T (M + diag(dvec) + A_add) T and b = T^T (M v + h f) (Eq. 2 projected by J_rR = T, Eq. 9-10;
    an empty A_add / T means none) in one compiled call."""
    n = M.shape[0]
    A = M.copy()
    for i in range(n):
        A[i, i] += dvec[i]
    if A_add.shape[0]:
        A += A_add
    b = h * f
    for i in range(n):
        s = 0.0
        for k in range(n):
            s += M[i, k] * v[k]
        b[i] += s
    if T.shape[0]:
        TA = np.ascontiguousarray(T.T) @ A
        return TA @ T, np.ascontiguousarray(T.T) @ b
    return A, b
