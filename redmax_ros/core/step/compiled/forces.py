"""Stage 2 of the compiled step, ``assemble(m, d, q, v, tau, h)``: the LHS matrix and RHS vector of Eq. (2),

    (J^T (M_m + h D_m + h^2 K_m) J + h D_r + h^2 K_r) qdot+ = J^T M_m J qdot + h (f_r + J^T (f_m - M_m Jdot qdot))

with the data-free pipeline's formulas and kernels (dynamics/tree_forces.py, springs.spring_kernel; stiffness written
positive, K = -df/dx): the RHS as one J^T pass over the Newton-Euler wrenches (bias accelerations, gravity,
gyroscopic terms), spring forces, constant wrenches; the LHS by the composite-rigid-body pass over the body
inertias plus the maximal 6x6 blocks (body damping, the springs' own blocks), minus the springs' cross-body
terms, plus armature + h D_r + h^2 K_r; then hyper-reduced by T = J_rR (Eq. 9-10): A_R = T^T A T,
b_R = T^T b. Maximal springs: f_a = -k (l - L0) u, K = k [u u^T + max(0, 1 - L0/l)(I - u u^T)], D = c u u^T
(notes §1.9.5, §1.9.9; springs.spring_forces) and their lever-arm blocks (springs.geometric_blocks_kernel, unless
integrator.spring_stiffness: gauss_newton), explicit (implicit: false) springs with K = D = 0 and their
damping force at step k. Joint springs: f = -K_r (q - q_rest) on the manifold (pin.difference)."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.dynamics.springs import clamp_lever_blocks_into, geometric_blocks_kernel, spring_kernel, spring_shift
from redmax_ros.core.dynamics.tree_forces import crba_runs_kernel, nle_wrench_kernel, spring_cross_lower_into
from redmax_ros.core.jit import njit_inline
from redmax_ros.core.linalg import mirror_lower
from redmax_ros.core.solvers.pcg import add_spring_end, spring_blocks_into
from redmax_ros.core.solvers.recursive import add_point_wrench, bias_kernel, jtw_kernel, jv_kernel
from redmax_ros.core.step.compiled.manifold import difference


@njit_inline
def shifted_sites(m, d):
    """BDF2: d.Xf = J (q* (-) q^), the displacements x* - x^ of the sites from q^ to q* (step/scheme.py): the world
    twists of d.back (d.ovb) by one J pass, then v_o + w x x per site."""
    jv_kernel(m.parents, m.idx_v, m.nv_j, d.St, d.back, d.ovb)
    for s in range(d.X.shape[0]):
        y = d.ovb[m.site_jid[s]]
        x = d.X[s]
        d.Xf[s, 0] = y[0] + y[4] * x[2] - y[5] * x[1]
        d.Xf[s, 1] = y[1] + y[5] * x[0] - y[3] * x[2]
        d.Xf[s, 2] = y[2] + y[3] * x[1] - y[4] * x[0]


@njit_inline
def spring_terms(m, d, h, shifted):
    """Per maximal spring (dynamics/springs.spring_kernel, the formulas of every pipeline): force on end a
    (d.spring_f), C = h D + h^2 K (d.spring_C), end positions (d.pa, d.pb); site velocities v_o + w x x first
    when an explicit spring has damping; all at the sites of q* (d.X). ``shifted`` (BDF2): also the sites'
    displacements from q^ (:func:`shifted_sites`), for :func:`rhs`."""
    P = m.spring_a.shape[0]
    if P == 0:
        return
    if m.scalars[3] != 0.0:
        for s in range(d.X.shape[0]):
            y = d.ov[m.site_jid[s]]
            x = d.X[s]
            d.V[s, 0] = y[0] + y[4] * x[2] - y[5] * x[1]
            d.V[s, 1] = y[1] + y[5] * x[0] - y[3] * x[2]
            d.V[s, 2] = y[2] + y[3] * x[1] - y[4] * x[0]
    if shifted:
        shifted_sites(m, d)
    spring_kernel(d.X, m.spring_a, m.spring_b, m.spring_k, m.spring_d, m.spring_rest, m.spring_explicit, d.V,
                  d.spring_f, d.spring_K, d.spring_D, d.spring_l)
    hh = h * h
    for s in range(P):
        a, b = m.spring_a[s], m.spring_b[s]
        for r in range(3):
            d.pa[s, r] = d.X[a, r]
            d.pb[s, r] = d.X[b, r]
            for q in range(3):
                d.spring_C[s, r, q] = h * d.spring_D[s, r, q] + hh * d.spring_K[s, r, q]


@njit_inline
def rhs(m, d, q, v, vm, ovm, tau, h, shifted):
    """b of Eq. (2), reduced coordinates (tree_forces.rhs): J^T (I ovm - h W_nle + h W_ext) + armature vm
    + h (tau - K_r (q - q_rest)), the bias forces of the velocity v (its twists d.ov), the momentum of vm (its
    twists ovm; BDF2's v^, else v and d.ov). ``shifted`` (BDF2): the maximal springs linearised about q*, their
    forces plus K' (x* - x^) (springs.spring_shift) and the lever blocks' B (q* (-) q^) (unclamped, scratch
    d.blocks, which :func:`lhs` rebuilds), as forces.assemble. Needs kinematics and spring_terms."""
    nj = m.parents.shape[0]
    bias_kernel(m.parents, m.idx_v, m.nv_j, d.St, d.ov, v, d.R, d.p, d.c_local, d.acc)
    nle_wrench_kernel(d.I, d.ov, d.acc, m.gravity, d.W)
    d.ext[:, :] = 0.0
    for s in range(m.spring_a.shape[0]):
        add_point_wrench(d.ext, m.spring_ja[s], d.pa[s], d.spring_f[s], 1.0)
        add_point_wrench(d.ext, m.spring_jb[s], d.pb[s], d.spring_f[s], -1.0)
    if shifted and m.spring_a.shape[0]:
        hh = h * h
        for s in range(m.spring_a.shape[0]):
            ja, jb = m.spring_ja[s], m.spring_jb[s]
            ma = np.inf if ja == 0 else m.mass[ja]
            mb = np.inf if jb == 0 else m.mass[jb]
            spring_shift(d.X, m.spring_a, m.spring_b, m.spring_k, m.spring_rest, m.spring_explicit, d.Xf, ma, mb, hh,
                         s, d.x3)
            add_point_wrench(d.ext, ja, d.pa[s], d.x3, 1.0)
            add_point_wrench(d.ext, jb, d.pb[s], d.x3, -1.0)
        d.blocks[:, :, :] = 0.0
        geometric_blocks_kernel(m.spring_ja, d.pa, m.spring_jb, d.pb, d.spring_f, m.spring_explicit, 1.0, d.I,
                                d.blocks)
        for j in range(1, nj):
            for r in range(6):
                t = 0.0
                for c in range(6):
                    t += d.blocks[j, r, c] * d.ovb[j, c]
                d.ext[j, r] += t
    x = d.x3
    for w in range(m.wrench_jid.shape[0]):
        j = m.wrench_jid[w]
        if j == 0:
            continue
        for r in range(3):
            x[r] = d.R[j, r, 0] * m.wrench_com[w, 0] + d.R[j, r, 1] * m.wrench_com[w, 1] + d.R[j, r, 2] * m.wrench_com[w, 2] + d.p[j, r]
        fw = m.wrench_fw[w]
        add_point_wrench(d.ext, j, x, fw, 1.0)
        for r in range(3):
            d.ext[j, 3 + r] += fw[3 + r]
    for j in range(1, nj):
        for r in range(6):
            s = 0.0
            for c in range(6):
                s += d.I[j, r, c] * ovm[j, c]
            d.W[j, r] = (-h * d.W[j, r] + s) + h * d.ext[j, r]
    jtw_kernel(m.parents, m.idx_v, m.nv_j, d.St, d.W, d.F, d.b)
    nv = d.b.shape[0]
    if m.scalars[1] != 0.0:  # joint springs: q - q_rest on the manifold
        difference(m.kind, m.idx_q, m.idx_v, m.q_rest, q, d.dq)
        for i in range(nv):
            d.b[i] += m.armature[i] * vm[i]
        for i in range(nv):
            d.b[i] += h * (tau[i] - m.stiffness[i] * d.dq[i])
    else:
        for i in range(nv):
            d.b[i] += m.armature[i] * vm[i]
        for i in range(nv):
            d.b[i] += h * tau[i]


@njit_inline
def lhs(m, d, h, A):
    """A of Eq. (2), reduced coordinates (tree_forces.dense_lhs): composite inertias of I + blocks, minus the
    springs' cross-body terms, plus armature + h D_r + h^2 K_r, into A (nv, nv); the lower triangle by the
    vectorised row kernels of tree_forces, then mirrored. Needs kinematics and spring_terms."""
    nj = m.parents.shape[0]
    d.blocks[:, :, :] = 0.0
    if m.spring_a.shape[0] and m.scalars[4] != 0.0:  # integrator.spring_stiffness: full: the lever-arm blocks of K_m
        geometric_blocks_kernel(m.spring_ja, d.pa, m.spring_jb, d.pb, d.spring_f, m.spring_explicit, h * h, d.I,
                                d.blocks)
        clamp_lever_blocks_into(d.I, d.blocks, d.m66)
    C3 = d.C33
    C3[:, :] = 0.0
    x = d.x3
    for k in range(m.damp_jid.shape[0]):  # body damping D_m = c diag(m_d I3, R I_d R^T) at the COM
        j = m.damp_jid[k]
        for r in range(3):
            x[r] = d.R[j, r, 0] * m.damp_com[k, 0] + d.R[j, r, 1] * m.damp_com[k, 1] + d.R[j, r, 2] * m.damp_com[k, 2] + d.p[j, r]
        hc = h * m.damp_c[k]
        for r in range(3):
            C3[r, r] = hc * m.damp_m[k]
        add_spring_end(d.blocks, j, 1.0, x[0], x[1], x[2], C3, d.m36)
        for a in range(3):
            for b in range(3):
                s = 0.0
                for e in range(3):
                    for f in range(3):
                        s += d.R[j, a, e] * m.damp_I[k, e, f] * d.R[j, b, f]
                d.blocks[j, 3 + a, 3 + b] += hc * s
    if m.spring_a.shape[0]:
        spring_blocks_into(m.spring_ja, d.pa, m.spring_jb, d.pb, d.spring_C, d.blocks, d.m36)
    for j in range(1, nj):
        for a in range(6):
            for b in range(6):
                d.blocks[j, a, b] += d.I[j, a, b]
    d.blocks[0] = 0.0
    A[:, :] = 0.0
    crba_runs_kernel(m.parents, m.idx_v, m.nv_j, d.St, d.blocks, A, m.support_ptr, m.support_runs, d.StT)
    if m.spring_a.shape[0]:
        spring_cross_lower_into(m.parents, m.idx_v, m.nv_j, d.St, m.spring_ja, d.pa, m.spring_jb, d.pb,
                                d.spring_C, A, m.support_ptr, m.support_runs, d.cross_W, d.cross_i, d.StT, d.m66)
    hh = h * h
    for i in range(A.shape[0]):
        A[i, i] += m.armature[i] + (h * m.damping[i] + hh * m.stiffness[i])
    mirror_lower(A)


@njit_inline
def hyper_reduce(T_col, T_ratio, A, b, AR, bR):
    """A_R = T^T A T, b_R = T^T b (Eq. 9-10) with T's one entry per row (T_col, T_ratio): O(nv^2), no
    allocation; copies without couplings (T_col empty)."""
    if T_col.shape[0] == 0:
        AR[:, :] = A
        bR[:] = b
        return
    nv = A.shape[0]
    AR[:, :] = 0.0
    bR[:] = 0.0
    for i in range(nv):
        ci, ri = T_col[i], T_ratio[i]
        bR[ci] += ri * b[i]
        for k in range(nv):
            AR[ci, T_col[k]] += ri * A[i, k] * T_ratio[k]


@njit_inline
def assemble(m, d, q, v, vm, ovm, tau, h, shifted):
    """Stage 2: d.AR, d.bR of Eq. (2) at the kinematics in d; ``q`` the configuration of the joint springs,
    ``vm``/``ovm`` the momentum's velocity and twists, ``shifted`` the springs linearised about q* from q^ (BDF2,
    :func:`rhs`, :func:`spring_terms`)."""
    spring_terms(m, d, h, shifted)
    rhs(m, d, q, v, vm, ovm, tau, h, shifted)
    coupled = m.T_col.shape[0] != 0
    lhs(m, d, h, d.A if coupled else d.AR)  # without couplings (T = I) straight into A_R
    if coupled:
        hyper_reduce(m.T_col, m.T_ratio, d.A, d.b, d.AR, d.bR)
    else:
        d.bR[:] = d.b
