"""Everything a step needs from the kinematics, without Pinocchio's ``pin.Data``.

In pin 4.1 ``model.createData()`` allocates ~nv^3 memory (second-order derivative tensors:
~10 MB at nv = 50, 63 MB at 100, 475 MB at 200, tens of GB at 1000), so mechanisms with hundreds
of DOFs (the paper's BRIDGE and UMBRELLA) cannot create one at all. This module rebuilds the
Data-dependent parts of a step on the O(n) recursive passes of :mod:`redmax_ros.core.recursive`
(world frame at the world origin, twists (v_o, w), linear first):

* :class:`Context`: per-mechanism constants (topology, site/spring/body index arrays) and the
  recursive :class:`~redmax_ros.core.recursive.Workspace`, with a forward-kinematics cache keyed
  on (q, qdot);
* the RHS of Eq. (2) in O(n + m) (:func:`rhs`): M qdot + h (tau - nle - K_r (q - q_rest)
  + J^T f_m), nle from Newton-Euler wrenches of the world-frame body twists and
  :func:`~redmax_ros.core.recursive.bias_acceleration`, all projected by one J^T pass;
* the LHS pieces for :class:`~redmax_ros.core.pcg.MatrixFreeSystem` (:func:`lhs_terms`: spring
  3x3 stiffness/damping as in forces.spring_terms, body-damping 6x6 blocks);
* a dense LHS (:func:`dense_lhs`) for the data-free direct solver: a CRBA-style numba pass over
  composite inertias (M_m plus the 6x6 diagonal blocks of the maximal stiffness/damping) plus the
  cross-body spring terms, O(n d + sum_s d_a d_b) for tree depth d;
* dense point-Jacobian rows of a few sites (loops, prescriptions), energies, loop residuals,
  loop post-stabilization and initial loop assembly, spring lengths and body poses.

Conventions match the direct pipeline (forces.py, constraints.py, stabilization.py, energy.py);
test/test_matrix_free.py checks each piece against it.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.dynamics.energy import spring_energy
from redmax_ros.core.errors import SceneError
from redmax_ros.core.dynamics.forces import joint_displacement, spring_forces
from redmax_ros.core.jit import njit
from redmax_ros.core.linalg import chol_solve, cholesky
from redmax_ros.core.dynamics.stabilization import check_loop_rank

PIN_DATA_MAX_NV = 100  # above this the direct pipeline's pin.Data is not created (>~50 MB, grows as nv^3)


class Context:
    """Constant index arrays of a Mechanism plus the recursive workspace (not thread-safe)."""

    def __init__(self, mech):
        self.mech = mech
        model = mech.model
        self.topo = rc.build_topology(model)
        self.ws = rc.make_workspace(self.topo)
        self._fk_key = None  # ('q' | 'qv') of the configuration held in ws
        # Universal joints are FALLBACK joints of recursive.py (one Pinocchio JointModel.calc per
        # joint and pass, ~3 us each); here they get a numba kernel (Pinocchio's formulas:
        # R = R(a1, q0) R(a2, q1), S = [0; R(a2, q1)^T a1 | 0; a2], c = (S_0 x a2) qdot0 qdot1).
        uni, a1, a2, other, planar = [], [], [], [], []
        for j, jm, jd in zip(self.topo.fallback, self.topo.fallback_models, self.ws.jdata):
            if jm.shortname() == "JointModelUniversal":
                e = jm.extract()
                uni.append(j)
                a1.append(np.array(e.axis1, float))
                a2.append(np.array(e.axis2, float))
            else:
                other.append((j, jm, jd))
                if jm.shortname() == "JointModelPlanar":
                    planar.append(j)
        self.uni_joints = np.array(uni, dtype=np.int64)
        self.uni_a1 = np.array(a1, dtype=float).reshape(-1, 3)
        self.uni_a2 = np.array(a2, dtype=float).reshape(-1, 3)
        self.other_fallback = other
        # planar joints: their placement from q by a kernel where only placements are needed (loop_phi_at)
        self.planar_joints = np.array(planar, dtype=np.int64)
        self.placement_fallback = [(j, jm, jd) for j, jm, jd in zip(self.topo.fallback, self.topo.fallback_models,
                                                                      self.ws.jdata) if j not in planar and j not in uni]
        nv = mech.nv
        self.site_jid = np.ascontiguousarray(mech.site_jid, dtype=np.int64).reshape(-1)
        self.site_local = np.ascontiguousarray(mech.site_local, dtype=float).reshape(-1, 3)
        js = np.asarray(mech.jac_sites, dtype=np.int64)
        self.jac_sites = js
        self.jac_jid = self.site_jid[js] if len(js) else np.zeros(0, np.int64)
        self.jac_local = self.site_local[js] if len(js) else np.zeros((0, 3))
        sa, sb = mech.spring_ab[:, 0], mech.spring_ab[:, 1]
        self.spring_ja = np.ascontiguousarray(self.site_jid[sa])
        self.spring_jb = np.ascontiguousarray(self.site_jid[sb])
        self.spring_oa = np.ascontiguousarray(self.site_local[sa])
        self.spring_ob = np.ascontiguousarray(self.site_local[sb])
        # body damping D_m = c diag(m I3, I_com) at the COM, per damped body (joint frame data)
        db = np.asarray(mech.damped_bodies, dtype=int)
        self.damp_jid = np.asarray(mech.body_jid, dtype=np.int64)[db] if len(db) else np.zeros(0, np.int64)
        self.damp_com = mech.body_com[db] if len(db) else np.zeros((0, 3))
        self.damp_I = np.array([mech.body_inertia[i] for i in db]).reshape(-1, 3, 3)
        self.damp_m = mech.body_mass[db] if len(db) else np.zeros(0)
        self.damp_c = mech.body_damping[db] if len(db) else np.zeros(0)
        # constant world wrenches at body COMs
        wb = np.asarray(mech.wrench_body, dtype=int)
        self.wrench_jid = np.asarray(mech.body_jid, dtype=np.int64)[wb] if len(wb) else np.zeros(0, np.int64)
        self.wrench_com = mech.body_com[wb] if len(wb) else np.zeros((0, 3))
        self.wrench_fw = np.asarray(mech.wrench_fw, dtype=float).reshape(-1, 6)
        self.gravity = np.array(model.gravity.linear, dtype=float)
        self.armature = self.topo.armature
        self.zero_v = np.zeros(nv)
        self._diag = {}
        # loop rows: selection matrix phi = S (x_a - x_b) over stacked loops
        self.loop_a = np.asarray(mech.loop_rows_ab[:, 0], dtype=int) if len(mech.loop_ab) else np.zeros(0, int)
        self.loop_b = np.asarray(mech.loop_rows_ab[:, 1], dtype=int) if len(mech.loop_ab) else np.zeros(0, int)
        self.loop_axes = [np.asarray(P, float) for P in mech.loop_axes]
        self.n_loop_rows = int(sum(len(P) for P in self.loop_axes))
        # hyper-reduced coordinates: one representative reduced DOF per column of T (v_R from v_r)
        if mech.T is not None:
            T = mech.T
            self.T_rep = np.array([int(np.flatnonzero(T[:, c])[0]) for c in range(T.shape[1])])
            self.T_rep_ratio = T[self.T_rep, np.arange(T.shape[1])]
        else:
            self.T_rep = self.T_rep_ratio = None

    # -- per-h constants
    def reduced_diag(self, h: float) -> np.ndarray:
        """h D_r + h^2 K_r (nv,)."""
        d = self._diag.get(h)
        if d is None:
            m = self.mech
            d = self._diag[h] = h * m.damping + h * h * m.stiffness
        return d

    # -- hyper-reduced coordinates
    def to_hyper(self, v_r: np.ndarray) -> np.ndarray:
        """qdot_R from qdot_r = T qdot_R (exact when qdot_r is in the range of T)."""
        if self.T_rep is None:
            return v_r
        return v_r[self.T_rep] / self.T_rep_ratio

    # -- kinematics
    def fk(self, q: np.ndarray, v: np.ndarray | None = None) -> rc.Workspace:
        """Forward kinematics (and body twists with ``v``) into the workspace; cached on (q, v)."""
        ws = self.ws
        if self._fk_key is not None and np.array_equal(ws.q, q):
            if v is None:
                return ws
            if self._fk_key == "qv" and np.array_equal(ws.v, v):
                return ws
        self._fk_key = None
        self._update_kinematics(q, v)
        self._fk_key = "q" if v is None else "qv"
        return ws

    def _update_kinematics(self, q, v):
        """recursive.update_kinematics with universal joints in numba (same results)."""
        topo, ws = self.topo, self.ws
        if not len(self.uni_joints):
            rc.update_kinematics(topo, ws, q, v)
            return
        q = np.ascontiguousarray(q, dtype=float).reshape(topo.nq)
        ws.q[:] = q
        if v is not None:
            v = np.ascontiguousarray(v, dtype=float).reshape(topo.nv)
        ws.has_bias = v is not None
        _universal_kernel(self.uni_joints, topo.idx_q, topo.idx_v, self.uni_a1, self.uni_a2, q,
                          self.zero_v if v is None else v, v is not None, ws.jR, ws.jp, ws.Sl, ws.c_local)
        for j, jm, jd in self.other_fallback:
            if v is None:
                jm.calc(jd, q)
                ws.c_local[j] = 0.0
            else:
                jm.calc(jd, q, v)
                ws.c_local[j] = jd.c.vector
            ws.jR[j], ws.jp[j] = jd.M.rotation, jd.M.translation
            i0, n = topo.idx_v[j], topo.nv_j[j]
            ws.Sl[i0:i0 + n, :] = np.asarray(jd.S).reshape(6, n).T
        rc.fk_kernel(topo.parents, topo.kind, topo.idx_q, topo.idx_v, topo.nv_j, topo.axis, topo.pitch,
                      topo.place_R, topo.place_p, q, ws.jR, ws.jp, ws.Sl, ws.R, ws.p, ws.St)
        rc.world_inertia_kernel(topo.mass, topo.com, topo.inertia_com, ws.R, ws.p, ws.I)
        if v is None:
            ws.v = None
            ws.ov[:] = 0.0
        else:
            ws.v = v.copy()
            rc.jv_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, v, ws.ov)

    def invalidate(self):
        self._fk_key = None

    def site_positions(self, idx=None) -> np.ndarray:
        """World positions (K,3) of sites ``idx`` (default all) at the configuration in ws."""
        if idx is None:
            return rc.site_positions(self.ws, self.site_jid, self.site_local)
        idx = np.asarray(idx, dtype=int)
        return rc.site_positions(self.ws, self.site_jid[idx], self.site_local[idx])

    def jac_positions(self) -> np.ndarray:
        """Positions of mech.jac_sites (rows as Kinematics.X of the direct pipeline)."""
        return rc.site_positions(self.ws, self.jac_jid, self.jac_local)

    def point_jacobians(self, sites) -> tuple:
        """(X (K,3), J (K,3,nv)) world positions and dense point Jacobians of the sites, O(K d)."""
        sites = np.asarray(sites, dtype=int)
        X = self.site_positions(sites)
        J = np.zeros((len(sites), 3, self.topo.nv))
        t = self.topo
        _point_jac_kernel(t.parents, t.idx_v, t.nv_j, self.ws.St, self.site_jid[sites], X, J)
        return X, J

    # -- loops
    def loop_phi(self, Xjac: np.ndarray | None = None) -> np.ndarray:
        """Loop residuals phi (rows,) [m] at the configuration in ws."""
        if not self.n_loop_rows:
            return np.zeros(0)
        X = self.jac_positions() if Xjac is None else Xjac
        return self.mech.loop_select @ (X[self.loop_a] - X[self.loop_b]).reshape(-1)

    def _fallback_placements(self, q):
        """Joint transforms of the FALLBACK joints at q (placements only; the fk cache is reset)."""
        topo, ws = self.topo, self.ws
        self._fk_key = None
        q = np.ascontiguousarray(q, dtype=float).reshape(topo.nq)
        if len(self.uni_joints):
            _universal_kernel(self.uni_joints, topo.idx_q, topo.idx_v, self.uni_a1, self.uni_a2, q,
                              self.zero_v, False, ws.jR, ws.jp, ws.Sl, ws.c_local)
        if len(self.planar_joints):
            rc.planar_placements(self.planar_joints, topo.idx_q, q, ws.jR, ws.jp)
        for j, jm, jd in self.placement_fallback:
            jm.calc(jd, q)
            ws.jR[j], ws.jp[j] = jd.M.rotation, jd.M.translation
        return q

    def loop_phi_at(self, q: np.ndarray) -> np.ndarray:
        """(phi (rows,) [m], max|phi|) of the loops at q from the joint placements alone: forward
        kinematics, loop-site positions and phi = S (x_a - x_b) in one compiled call (the inner loop of
        :func:`project_chord`). Leaves placements of q in the workspace (the fk cache is reset)."""
        q = self._fallback_placements(q)
        topo, ws = self.topo, self.ws
        return _loop_phi_kernel(topo.parents, topo.kind, topo.idx_q, topo.idx_v, topo.nv_j, topo.axis,
                                topo.pitch, topo.place_R, topo.place_p, q, ws.jR, ws.jp, ws.Sl, ws.R, ws.p,
                                ws.St, self.jac_jid, self.jac_local, self.loop_a, self.loop_b,
                                self.mech.loop_select)

    def site_positions_at(self, q: np.ndarray, jid: np.ndarray, local: np.ndarray) -> np.ndarray:
        """World positions (K,3) [m] at q of sites given as (joint, offset in the joint frame), from the
        joint placements alone in one compiled call (kinematics.site_jacobians for many sites)."""
        q = self._fallback_placements(q)
        topo, ws = self.topo, self.ws
        out = np.empty((len(jid), 3))
        _sites_at_kernel(topo.parents, topo.kind, topo.idx_q, topo.idx_v, topo.nv_j, topo.axis, topo.pitch,
                         topo.place_R, topo.place_p, q, ws.jR, ws.jp, ws.Sl, ws.R, ws.p, ws.St, jid, local, out)
        return out

    def loop_rows(self) -> tuple:
        """(G_r (rows, nv), phi (rows,)) of the loop closures at the configuration in ws."""
        mech = self.mech
        if not self.n_loop_rows:
            return np.zeros((0, self.topo.nv)), np.zeros(0)
        sites = np.unique(np.concatenate([self.jac_sites[self.loop_a], self.jac_sites[self.loop_b]]))
        X, J = self.point_jacobians(sites)
        pos = {int(s): k for k, s in enumerate(sites)}
        Gs, phis = [], []
        for (a, b), P in zip(mech.loop_ab, self.loop_axes):
            ka, kb = pos[int(a)], pos[int(b)]
            Gs.append(P @ (J[ka] - J[kb]))
            phis.append(P @ (X[ka] - X[kb]))
        return np.vstack(Gs), np.concatenate(phis)


def context(mech) -> Context:
    """The (cached) data-free Context of a Mechanism."""
    ctx = mech.__dict__.get("_data_free_ctx")
    if ctx is None:
        ctx = Context(mech)
        mech.__dict__["_data_free_ctx"] = ctx
    return ctx


# ----------------------------------------------------------------------------------------------
# numba kernels


@njit
def _loop_phi_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl, R, p,
                     St, jid, local, a, b, S):
    """recursive.fk_kernel, then phi = S (x_a - x_b) of the loop sites (rows a, b of jid/local)."""
    rc.fk_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl, R, p, St)
    L = a.shape[0]
    d = np.empty(3 * L)
    for l in range(L):
        ja, jb = jid[a[l]], jid[b[l]]
        oa, ob = local[a[l]], local[b[l]]
        for r in range(3):
            xa = p[ja, r] + R[ja, r, 0] * oa[0] + R[ja, r, 1] * oa[1] + R[ja, r, 2] * oa[2]
            xb = p[jb, r] + R[jb, r, 0] * ob[0] + R[jb, r, 1] * ob[1] + R[jb, r, 2] * ob[2]
            d[3 * l + r] = xa - xb
    phi = S @ d
    err = 0.0
    for r in range(phi.shape[0]):
        err = max(err, abs(phi[r]))
    return phi, err


@njit
def _sites_at_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl, R, p,
                     St, jid, local, out):
    """recursive.fk_kernel, then the world positions of sites (joint jid, offset local)."""
    rc.fk_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl, R, p, St)
    rc.site_pos_kernel(R, p, jid, local, out)


@njit
def _universal_kernel(joints, idx_q, idx_v, a1, a2, q, v, use_v, jR, jp, Sl, c_local):
    R1 = np.empty((3, 3))
    R2 = np.empty((3, 3))
    for k in range(joints.shape[0]):
        j = joints[k]
        iq, iv = idx_q[j], idx_v[j]
        rc.axis_rotation(a1[k], np.cos(q[iq]), np.sin(q[iq]), R1)
        rc.axis_rotation(a2[k], np.cos(q[iq + 1]), np.sin(q[iq + 1]), R2)
        for r in range(3):
            for c in range(3):
                jR[j, r, c] = R1[r, 0] * R2[0, c] + R1[r, 1] * R2[1, c] + R1[r, 2] * R2[2, c]
            jp[j, r] = 0.0
        s0 = R2[0, 0] * a1[k, 0] + R2[1, 0] * a1[k, 1] + R2[2, 0] * a1[k, 2]
        s1 = R2[0, 1] * a1[k, 0] + R2[1, 1] * a1[k, 1] + R2[2, 1] * a1[k, 2]
        s2 = R2[0, 2] * a1[k, 0] + R2[1, 2] * a1[k, 1] + R2[2, 2] * a1[k, 2]
        for r in range(3):
            Sl[iv, r] = 0.0
            Sl[iv + 1, r] = 0.0
            Sl[iv + 1, 3 + r] = a2[k, r]
        Sl[iv, 3], Sl[iv, 4], Sl[iv, 5] = s0, s1, s2
        for r in range(6):
            c_local[j, r] = 0.0
        if use_v:
            w = v[iv] * v[iv + 1]
            c_local[j, 3] = (s1 * a2[k, 2] - s2 * a2[k, 1]) * w
            c_local[j, 4] = (s2 * a2[k, 0] - s0 * a2[k, 2]) * w
            c_local[j, 5] = (s0 * a2[k, 1] - s1 * a2[k, 0]) * w


@njit
def _point_jac_kernel(parents, idx_v, nv_j, St, joints, X, J):
    """J[k] (3 x nv): column c = lin(S_c) + ang(S_c) x x_k for the DOFs c supporting joint joints[k]."""
    for k in range(joints.shape[0]):
        j = joints[k]
        x0, x1, x2 = X[k, 0], X[k, 1], X[k, 2]
        while j > 0:
            for c in range(idx_v[j], idx_v[j] + nv_j[j]):
                w0, w1, w2 = St[c, 3], St[c, 4], St[c, 5]
                J[k, 0, c] = St[c, 0] + w1 * x2 - w2 * x1
                J[k, 1, c] = St[c, 1] + w2 * x0 - w0 * x2
                J[k, 2, c] = St[c, 2] + w0 * x1 - w1 * x0
            j = parents[j]


@njit
def _nle_wrench_kernel(I, ov, acc, g, W):
    """Newton-Euler wrenches (world, at the origin) for the quadratic-velocity and gravity terms:
    W_j = I_j (a_j - (g, 0)) + ov_j x* (I_j ov_j), with a_j = Jdot_j qdot (bias acceleration).
    J^T W = nle = -J^T (f_m - M_m Jdot qdot) of Eq. (1)-(2) (Pinocchio's RNEA at zero acceleration)."""
    nj = I.shape[0]
    a = np.empty(6)
    hm = np.empty(6)
    for j in range(1, nj):
        for r in range(6):
            a[r] = acc[j, r]
        a[0] -= g[0]
        a[1] -= g[1]
        a[2] -= g[2]
        for r in range(6):
            s = 0.0
            t = 0.0
            for c in range(6):
                s += I[j, r, c] * a[c]
                t += I[j, r, c] * ov[j, c]
            W[j, r] = s
            hm[r] = t
        rc.add_motion_cross_force(ov[j], hm, W[j])  # W += v x* h (gyroscopic/bias wrench)
    for r in range(6):
        W[0, r] = 0.0


@njit
def _dense_crba_kernel(parents, idx_v, nv_j, St, Ic, A):
    """A += J^T blkdiag(Ic) J by the composite-rigid-body algorithm in the world frame.
    Ic (njoints,6,6) holds each body's 6x6 block on entry and is overwritten by the composites.
    Every column pair (c of joint j, c2 of an ancestor-or-self joint k) gets S_c2^T Ic_j S_c."""
    nj = parents.shape[0]
    for j in range(nj - 1, 0, -1):
        p = parents[j]
        if p > 0:
            for a in range(6):
                for b in range(6):
                    Ic[p, a, b] += Ic[j, a, b]
    F = np.empty(6)
    for j in range(1, nj):
        for c in range(idx_v[j], idx_v[j] + nv_j[j]):
            for a in range(6):
                s = 0.0
                for b in range(6):
                    s += Ic[j, a, b] * St[c, b]
                F[a] = s
            k = j
            while k > 0:
                for c2 in range(idx_v[k], idx_v[k] + nv_j[k]):
                    s = 0.0
                    for a in range(6):
                        s += St[c2, a] * F[a]
                    if c2 == c:
                        A[c, c] += s
                    elif c2 < c or k != j:
                        A[c2, c] += s
                        A[c, c2] += s
                k = parents[k]


@njit
def _spring_cross_kernel(parents, idx_v, nv_j, St, ja, pa, jb, pb, C, A):
    """A -= J_a^T C J_b + J_b^T C J_a for springs between two different moving bodies (the
    off-diagonal blocks of sum_s J_s^T C_s J_s; the diagonal blocks are in the composite inertias)."""
    nv = St.shape[0]
    cols_a = np.empty(nv, np.int64)
    cols_b = np.empty(nv, np.int64)
    Pa = np.empty((nv, 3))
    Pb = np.empty((nv, 3))
    CPb = np.empty((nv, 3))
    for s in range(ja.shape[0]):
        i, k = ja[s], jb[s]
        if i == 0 or k == 0 or i == k:
            continue
        na = 0
        j = i
        while j > 0:
            for c in range(idx_v[j], idx_v[j] + nv_j[j]):
                w0, w1, w2 = St[c, 3], St[c, 4], St[c, 5]
                x = pa[s]
                Pa[na, 0] = St[c, 0] + w1 * x[2] - w2 * x[1]
                Pa[na, 1] = St[c, 1] + w2 * x[0] - w0 * x[2]
                Pa[na, 2] = St[c, 2] + w0 * x[1] - w1 * x[0]
                cols_a[na] = c
                na += 1
            j = parents[j]
        nb = 0
        j = k
        while j > 0:
            for c in range(idx_v[j], idx_v[j] + nv_j[j]):
                w0, w1, w2 = St[c, 3], St[c, 4], St[c, 5]
                x = pb[s]
                Pb[nb, 0] = St[c, 0] + w1 * x[2] - w2 * x[1]
                Pb[nb, 1] = St[c, 1] + w2 * x[0] - w0 * x[2]
                Pb[nb, 2] = St[c, 2] + w0 * x[1] - w1 * x[0]
                cols_b[nb] = c
                nb += 1
            j = parents[j]
        for m in range(nb):
            for a in range(3):
                CPb[m, a] = C[s, a, 0] * Pb[m, 0] + C[s, a, 1] * Pb[m, 1] + C[s, a, 2] * Pb[m, 2]
        for l in range(na):
            ca = cols_a[l]
            for m in range(nb):
                cb = cols_b[m]
                val = Pa[l, 0] * CPb[m, 0] + Pa[l, 1] * CPb[m, 1] + Pa[l, 2] * CPb[m, 2]
                A[ca, cb] -= val
                A[cb, ca] -= val


# ----------------------------------------------------------------------------------------------
# forces (Eq. 2)


_I3 = np.eye(3)[None]


def spring_terms(mech, X: np.ndarray):
    """(f_a, K, D, lengths) of the maximal springs from the positions X of mech.jac_sites
    (forces.spring_forces: one formula for both paths)."""
    return spring_forces(mech, X)


def body_damping_blocks(ctx: Context, h: float) -> np.ndarray | None:
    """Maximal 6x6 blocks h D_m per joint (world twists), D_m = c diag(m I3, R I_com R^T) at the COM."""
    if not len(ctx.damp_jid):
        return None
    ws = ctx.ws
    B = np.zeros((ctx.topo.njoints, 6, 6))
    for j, com, Ic, m, c in zip(ctx.damp_jid, ctx.damp_com, ctx.damp_I, ctx.damp_m, ctx.damp_c):
        R, p = ws.R[j], ws.p[j]
        x = R @ com + p
        Iw = R @ Ic @ R.T
        X = np.zeros((3, 6))  # COM velocity = v_o + w x x = [1, -[x]] (v_o, w)
        X[:, :3] = np.eye(3)
        X[:, 3:] = -pin.skew(x)
        blk = m * X.T @ X
        blk[3:, 3:] += Iw
        B[j] += (h * c) * blk
    return B


def rhs(ctx: Context, q, v_r, tau, h, site_forces=None, springs=None) -> np.ndarray:
    """RHS of Eq. (2) in reduced coordinates, O(n + m), for the (q, v_r) held in ctx.ws:
    b = M v_r + h (tau - nle - K_r (q - q_rest) + J_s^T f_springs + wrenches + J^T site forces).
    ``springs``: (f_a (P,3), positions of mech.jac_sites) from :func:`spring_terms`."""
    mech, topo, ws = ctx.mech, ctx.topo, ctx.ws
    acc = rc.bias_acceleration(topo, ws)
    W = np.empty((topo.njoints, 6))
    _nle_wrench_kernel(ws.I, ws.ov, acc, ctx.gravity, W)
    # W_total = I ov - h W_nle + h W_ext, then one J^T pass
    W *= -h
    W += np.einsum("jab,jb->ja", ws.I, ws.ov)
    ext = np.zeros((topo.njoints, 6))
    if springs is not None and len(mech.spring_ab):
        fs, X = springs
        a, b = mech.spring_rows[:, 0], mech.spring_rows[:, 1]
        rc.accumulate_site_forces(ext, ctx.spring_ja, X[a], fs)
        rc.accumulate_site_forces(ext, ctx.spring_jb, X[b], -fs)
    if len(ctx.wrench_jid):
        for j, com, fw in zip(ctx.wrench_jid, ctx.wrench_com, ctx.wrench_fw):
            if j == 0:
                continue
            x = ws.R[j] @ com + ws.p[j]
            ext[j, :3] += fw[:3]
            ext[j, 3:] += np.cross(x, fw[:3]) + fw[3:]
    if site_forces:
        idx = np.array(list(site_forces), dtype=int)
        F = np.array([site_forces[i] for i in idx], dtype=float).reshape(-1, 3)
        rc.accumulate_site_forces(ext, ctx.site_jid[idx], ctx.site_positions(idx), F)
    ext[0] = 0.0
    W += h * ext
    b = rc.jtw(topo, ws, W)
    b += ctx.armature * v_r
    f_r = np.array(tau, dtype=float)
    if mech.has_stiffness:
        f_r -= mech.stiffness * joint_displacement(mech, q)
    b += h * f_r
    return b


def dense_lhs(ctx: Context, h: float, blocks: np.ndarray, springs_C: np.ndarray | None,
              pa: np.ndarray | None, pb: np.ndarray | None) -> np.ndarray:
    """Dense LHS of Eq. (2) (reduced coordinates, positive-stiffness convention) from the recursive
    workspace: J^T (I + blocks) J by composite inertias, minus the cross-body spring terms, plus
    armature + h D_r + h^2 K_r. ``blocks``: the blkdiag maximal blocks (MatrixFreeSystem's
    preconditioner_blocks), ``springs_C``: (P,3,3) h D_s + h^2 K_s at world points pa, pb."""
    topo, ws = ctx.topo, ctx.ws
    nv = topo.nv
    A = np.zeros((nv, nv))
    Ic = ws.I + blocks
    Ic[0] = 0.0
    _dense_crba_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, Ic, A)
    if springs_C is not None and len(springs_C):
        _spring_cross_kernel(topo.parents, topo.idx_v, topo.nv_j, ws.St, ctx.spring_ja, pa, ctx.spring_jb, pb,
                             springs_C, A)
    A[np.diag_indices(nv)] += ctx.armature + ctx.reduced_diag(h)
    return A


# ----------------------------------------------------------------------------------------------
# diagnostics


def energies(ctx: Context, q, v_r) -> tuple:
    """(E_kin, E_pot, E_spring) [J] at (q, v_r), as energy.energies. Leaves (q, v_r) in ctx.ws."""
    mech, topo = ctx.mech, ctx.topo
    ws = ctx.fk(q, v_r)
    ov = ws.ov[1:]
    ek = 0.5 * float(np.einsum("ja,jab,jb->", ov, ws.I[1:], ov))
    if mech.has_armature:
        ek += 0.5 * float(mech.armature @ (v_r * v_r))
    com = np.einsum("jab,jb->ja", ws.R[1:], topo.com[1:]) + ws.p[1:]
    ep = -float(topo.mass[1:] @ (com @ ctx.gravity))
    es = spring_energy(mech, ctx.jac_positions() if len(mech.spring_ab) else None, q)
    return float(ek), float(ep), es


def loop_violation(ctx: Context, q) -> float:
    """max |phi| [m] of the loop closures at q."""
    if not ctx.n_loop_rows:
        return 0.0
    ctx.fk(q)
    return float(np.abs(ctx.loop_phi()).max())


def body_poses(mech, q) -> dict:
    """Body frames in the world: name -> (position (3,), quaternion xyzw (4,)), without pin.Data."""
    ctx = context(mech)
    ws = ctx.fk(q)
    out = {}
    for name, jid, M in zip(mech.bodies, mech.body_jid, mech.body_placement):
        R = ws.R[int(jid)] @ M.rotation
        p = ws.R[int(jid)] @ M.translation + ws.p[int(jid)]
        out[name] = (p.copy(), pin.Quaternion(R).coeffs().copy())
    return out


def all_site_positions(mech, q) -> np.ndarray:
    """World positions (S,3) of every site at q, without pin.Data."""
    ctx = context(mech)
    ctx.fk(q)
    return ctx.site_positions()


def spring_lengths(mech, q) -> np.ndarray:
    """Lengths (P,) of the maximal springs at q (compile_scene's default rest lengths)."""
    if not len(mech.spring_ab):
        return np.zeros(0)
    x = all_site_positions(mech, q)
    return np.linalg.norm(x[mech.spring_ab[:, 0]] - x[mech.spring_ab[:, 1]], axis=1)


# ----------------------------------------------------------------------------------------------
# loop post-stabilization (as stabilization.py, without pin.Data)

TOL = 1e-10


def _hold_rows(mech, hold_dofs):
    """Rows selecting the held hyper-reduced DOFs (cached per set)."""
    key = ("hold rows", *hold_dofs)
    hold = mech.layout_cache.get(key)
    if hold is None:
        hold = np.zeros((len(hold_dofs), mech.ndof))
        hold[np.arange(len(hold_dofs)), list(hold_dofs)] = 1.0
        mech.layout_cache[key] = hold
    return hold


def _loop_rows_hyper(ctx, q):
    ctx.fk(q)
    G, phi = ctx.loop_rows()
    T = ctx.mech.T
    return phi, (G if T is None else G @ T)


def project(ctx: Context, q, hold_dofs=(), tol=TOL, max_iter=5):
    """Newton projection of q onto phi(q) = 0 (least-norm, hyper-reduced, ``hold_dofs`` fixed),
    as stabilization.project. Returns (q, max|phi|)."""
    mech = ctx.mech
    if not ctx.n_loop_rows:
        return q, 0.0
    hold = _hold_rows(mech, hold_dofs)
    phi, G = _loop_rows_hyper(ctx, q)
    for _ in range(max_iter):
        err = float(np.abs(phi).max())
        if err < tol:
            return q, err
        Gh = np.vstack([G, hold])
        dq, *_ = np.linalg.lstsq(Gh, np.concatenate([-phi, np.zeros(len(hold))]), rcond=None)
        q = pin.integrate(mech.model, q, mech.to_reduced(dq))
        phi, G = _loop_rows_hyper(ctx, q)
    return q, float(np.abs(phi).max())


def project_chord(ctx: Context, q, G, hold_dofs=(), tol=TOL, max_iter=8):
    """Chord-Newton projection reusing the step's loop rows G (hyper-reduced), as
    stabilization.project_chord: each iteration costs one O(n) forward kinematics."""
    mech = ctx.mech
    held = _held_array(mech, hold_dofs)
    G = np.ascontiguousarray(G)
    L, ok = _chord_factor(G, held)
    if not ok:
        return project(ctx, q, hold_dofs, tol)
    T = _NO_T if mech.T is None else mech.T
    for _ in range(max_iter):
        phi, err = ctx.loop_phi_at(q)
        if err < tol:
            return q, err
        q = pin.integrate(mech.model, q, _chord_step(L, G, held, phi, T))
    return project(ctx, q, hold_dofs, tol)


_NO_T = np.zeros((0, 0))


def _held_array(mech, hold_dofs):
    key = ("held array", *hold_dofs)
    a = mech.layout_cache.get(key)
    if a is None:
        a = mech.layout_cache[key] = np.asarray(list(hold_dofs), dtype=np.int64)
    return a


@njit
def _chord_factor(G, held):
    """Cholesky factor of K K^T, K = [G; H] (H selects the held hyper-reduced DOFs):
    K K^T = [[G G^T, G[:, held]], [G[:, held]^T, I]]."""
    m, n, k = G.shape[0], G.shape[1], held.shape[0]
    KK = np.zeros((m + k, m + k))
    for r in range(m):
        for c in range(r + 1):
            s = 0.0
            for i in range(n):
                s += G[r, i] * G[c, i]
            KK[r, c] = s
            KK[c, r] = s
        for j in range(k):
            KK[r, m + j] = G[r, held[j]]
            KK[m + j, r] = G[r, held[j]]
    for j in range(k):
        KK[m + j, m + j] = 1.0
    L = np.empty((m + k, m + k))
    ok = cholesky(KK, L)
    return L, ok


@njit
def _chord_step(L, G, held, phi, T):
    """Least-norm correction dq = -K^T (K K^T)^-1 [phi; 0] (held DOFs fixed), mapped to reduced
    coordinates by J_rR = T (empty T: none)."""
    m, n, k = G.shape[0], G.shape[1], held.shape[0]
    y = np.zeros(m + k)
    y[:m] = phi
    chol_solve(L, y)
    dq = np.zeros(n)
    for r in range(m):
        for i in range(n):
            dq[i] -= G[r, i] * y[r]
    for j in range(k):
        dq[held[j]] -= y[m + j]
    if T.shape[0] == 0:
        return dq
    out = np.zeros(T.shape[0])
    for i in range(T.shape[0]):
        s = 0.0
        for c in range(n):
            s += T[i, c] * dq[c]
        out[i] = s
    return out


def assemble_loops(mech, q):
    """Close the loops at the initial configuration and reject redundant loop rows (SceneError),
    as stabilization.assemble_loops but without pin.Data (for nv > PIN_DATA_MAX_NV)."""
    if not len(mech.loop_ab):
        return q
    ctx = context(mech)
    src = mech.spec.source
    q, err = project(ctx, q, tol=1e-12, max_iter=100)
    if err > 1e-9:
        raise SceneError(src, "loops", f"cannot close the loops from the initial configuration "
                                       f"(residual {err:.3g} m after 100 Newton steps); check q0 and the loop sites")
    _, G = _loop_rows_hyper(ctx, q)
    check_loop_rank(mech, G)
    return q


def compile_helpers(mech, q0):
    """compile_scene's two pin.Data users, data-free when nv > PIN_DATA_MAX_NV:
    returns (q0 with the loops assembled, spring lengths at that q0)."""
    if mech.nv <= PIN_DATA_MAX_NV:
        from redmax_ros.core.dynamics.stabilization import assemble_loops as assemble_pin
        q0 = assemble_pin(mech, q0)
    else:
        q0 = assemble_loops(mech, q0)
    return q0, spring_lengths(mech, q0)
