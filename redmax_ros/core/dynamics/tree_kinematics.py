"""Kinematics without Pinocchio's ``pin.Data``: the :class:`Context` of a Mechanism on the O(n)
recursive passes of :mod:`redmax_ros.core.solvers.recursive`.

In pin 4.1 ``model.createData()`` allocates ~nv^3 memory (second-order derivative tensors:
~10 MB at nv = 50, 63 MB at 100, 475 MB at 200, tens of GB at 1000), so mechanisms with hundreds
of DOFs (the paper's BRIDGE and UMBRELLA) cannot create one at all. The Context holds per-mechanism
index arrays (sites, springs, damped bodies, wrenches, loops) and the recursive workspace with a
forward-kinematics cache keyed on (q, qdot) (world frame at the world origin, twists (v_o, w), linear
first): site positions, dense point Jacobians of a few sites (loops, prescriptions; Eq. S2.4), loop
residuals from the placements alone, body poses. Every pipeline uses it for the loop projection
(stabilization.py) and the energies (energy.py); the data-free pipeline for everything. One Context
per step workspace (it is scratch, not thread-safe); test/core/step/test_matrix_free.py checks it against
Pinocchio.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.springs import spring_arrays, spring_state_kernel
from redmax_ros.core.jit import njit
from redmax_ros.core.solvers import recursive as rc

PIN_DATA_MAX_NV = 100  # above this the direct pipeline's pin.Data is not created (>~50 MB, grows as nv^3)
_NO_V = np.zeros((0, 3))  # Context.spring_state without explicit dampers
ADDITIVE_KINDS = (rc.REVOLUTE, rc.PRISMATIC, rc.HELICAL, rc.TRANSLATION)  # joints on R^n: pin.integrate is q + v


class Context:
    """Index arrays of a Mechanism plus the recursive workspace and its caches (scratch of one step
    workspace; not thread-safe)."""

    def __init__(self, mech, T=None, cache=None):
        """``T``: the live J_rR of the workspace (default: the Mechanism's constant one); ``cache``: the
        workspace's per-prescription-set cache (a dict)."""
        self.mech = mech
        self.T = mech.T if T is None else T
        self.cache = {} if cache is None else cache
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
        # every joint a vector space (pin.integrate is q + v) placed by the kernels: the loop projection runs in
        # one compiled call (stabilization.chord_project_kernel)
        self.additive = (model.nq == model.nv and not self.placement_fallback and not planar
                         and all(int(k) in ADDITIVE_KINDS or j in uni for j, k in enumerate(self.topo.kind) if j))
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
        self.spring_arrays = spring_arrays(mech)  # the constants of springs.spring_forces
        # body damping D_m = c diag(m_d I3, I_d) at the COM, per damped body (joint frame data);
        # (m_d, I_d) = (m, I_com) for form 'mass', (1, I3) for form 'twist' (D_m = c I6)
        db = np.asarray(mech.damped_bodies, dtype=int)
        self.damp_jid = np.asarray(mech.body_jid, dtype=np.int64)[db] if len(db) else np.zeros(0, np.int64)
        self.damp_com = mech.body_com[db] if len(db) else np.zeros((0, 3))
        self.damp_I = np.array([mech.body_damping_inertia[i] for i in db]).reshape(-1, 3, 3)
        self.damp_m = mech.body_damping_mass[db] if len(db) else np.zeros(0)
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
        self.P = None  # solvers.preconditioner.ProjectedBlockJacobi of the PCG path (refactored per step)
        self.z_cache = None  # (row key, Z rows) warm start of the PCG solves of Eq. (4)
        self.last_stats = {}  # the last data-free step's solver statistics
        # loop rows: selection matrix phi = S (x_a - x_b) over stacked loops
        self.loop_a = np.asarray(mech.loop_rows_ab[:, 0], dtype=int) if len(mech.loop_ab) else np.zeros(0, int)
        self.loop_b = np.asarray(mech.loop_rows_ab[:, 1], dtype=int) if len(mech.loop_ab) else np.zeros(0, int)
        self.loop_axes = [np.asarray(P, float) for P in mech.loop_axes]
        self.n_loop_rows = int(sum(len(P) for P in self.loop_axes))
        # the loops' sites (each once): joints, offsets, and per loop the rows of its ends among them
        sites = np.unique(np.concatenate([self.jac_sites[self.loop_a], self.jac_sites[self.loop_b]])).astype(int)
        pos = {int(s): k for k, s in enumerate(sites)}
        self.loop_site_jid = np.ascontiguousarray(self.site_jid[sites])
        self.loop_site_local = np.ascontiguousarray(self.site_local[sites]).reshape(-1, 3)
        self.loop_ends = [(pos[int(a)], pos[int(b)]) for a, b in mech.loop_ab]
        # per loop row: its ends among those sites and its world direction (row of the loop's axes P)
        self.loop_row_a = np.array([ka for (ka, _), P in zip(self.loop_ends, self.loop_axes) for _ in P], np.int64)
        self.loop_row_b = np.array([kb for (_, kb), P in zip(self.loop_ends, self.loop_axes) for _ in P], np.int64)
        self.loop_row_axis = np.array([r for P in self.loop_axes for r in P], dtype=float).reshape(-1, 3)
        self._loop_X = np.empty((len(sites), 3))  # scratch of loop_jacobian_kernel
        self._loop_J = np.empty((len(sites), 3, nv))
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
        if self._fk_key is not None and same_vector(ws.q, q):
            if v is None:
                return ws
            if self._fk_key == "qv" and same_vector(ws.v, v):
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
        universal_kernel(self.uni_joints, topo.idx_q, topo.idx_v, self.uni_a1, self.uni_a2, q,
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
        rc.kinematics_passes(topo, ws, q, v)

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

    def spring_state(self, h: float, V: np.ndarray | None = None) -> tuple:
        """(X, f, K, D, (pa, pb), C) of the maximal springs at the placements in ws, one compiled call
        (springs.spring_state_kernel): X the positions of mech.jac_sites (as :meth:`jac_positions`), f, K, D
        those of springs.spring_forces, (pa, pb) the end points [m], C = h D + h^2 K. ``V``: the site velocities of
        explicit dampers (springs.spring_forces), None when no spring needs them."""
        sa, P = self.spring_arrays, len(self.spring_ja)
        if V is None:
            if sa.needs_velocities:
                raise ValueError("explicit spring dampers need the site velocities V")
            V = _NO_V
        X = np.empty((len(self.jac_jid), 3))
        f, K, D, C = np.empty((P, 3)), np.empty((P, 3, 3)), np.empty((P, 3, 3)), np.empty((P, 3, 3))
        pa, pb = np.empty((P, 3)), np.empty((P, 3))
        spring_state_kernel(self.ws.R, self.ws.p, self.jac_jid, self.jac_local, sa.a, sa.b, sa.k, sa.d, sa.rest,
                            sa.explicit, np.ascontiguousarray(V, dtype=float), float(h), X, f, K, D, np.empty(P),
                            pa, pb, C)
        return X, f, K, D, (pa, pb), C

    def point_jacobians(self, sites) -> tuple:
        """(X (K,3), J (K,3,nv)) world positions and dense point Jacobians of the sites, O(K d)."""
        sites = np.asarray(sites, dtype=int)
        X = self.site_positions(sites)
        J = np.zeros((len(sites), 3, self.topo.nv))
        t = self.topo
        point_jac_kernel(t.parents, t.idx_v, t.nv_j, self.ws.St, self.site_jid[sites], X, J)
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
            universal_kernel(self.uni_joints, topo.idx_q, topo.idx_v, self.uni_a1, self.uni_a2, q,
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
        return loop_phi_kernel(topo.parents, topo.kind, topo.idx_q, topo.idx_v, topo.nv_j, topo.axis,
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
        if not self.n_loop_rows:
            return np.zeros((0, self.topo.nv)), np.zeros(0)
        X, J = self._loop_site_jacobians()
        G = np.concatenate([P @ (J[ka] - J[kb]) for (ka, kb), P in zip(self.loop_ends, self.loop_axes)])
        return G, np.concatenate([P @ (X[ka] - X[kb]) for (ka, kb), P in zip(self.loop_ends, self.loop_axes)])

    def loop_jacobian(self) -> np.ndarray:
        """G_r (rows, nv) of :meth:`loop_rows` alone."""
        if not self.n_loop_rows:
            return np.zeros((0, self.topo.nv))
        t, ws = self.topo, self.ws
        G = np.empty((self.n_loop_rows, t.nv))
        loop_jacobian_kernel(t.parents, t.idx_v, t.nv_j, ws.St, ws.R, ws.p, self.loop_site_jid, self.loop_site_local,
                             self.loop_row_a, self.loop_row_b, self.loop_row_axis, self._loop_X, self._loop_J, G)
        return G

    def _loop_site_jacobians(self) -> tuple:
        """(X (K,3), J (K,3,nv)) of :meth:`point_jacobians` for the loops' sites (rows of self.loop_ends)."""
        t, ws, jid = self.topo, self.ws, self.loop_site_jid
        X = np.empty((len(jid), 3))
        rc.site_pos_kernel(ws.R, ws.p, jid, self.loop_site_local, X)
        J = np.zeros((len(jid), 3, t.nv))
        point_jac_kernel(t.parents, t.idx_v, t.nv_j, ws.St, jid, X, J)
        return X, J



def same_vector(a: np.ndarray, b) -> bool:
    """np.array_equal(a, b) for the fk cache's 1-D float vector ``a``, the common case (``b`` a 1-D array of the
    same length) in one compiled call (~0.3 us instead of ~1.7 us)."""
    if isinstance(b, np.ndarray) and b.shape == a.shape and b.dtype == a.dtype:
        return _same_values(a, b)
    return np.array_equal(a, b)


@njit
def _same_values(a, b):
    """a[i] == b[i] for every i (equal length): np.array_equal's comparison (0.0 == -0.0, NaN != NaN)."""
    for i in range(a.shape[0]):
        if a[i] != b[i]:
            return False
    return True


@njit
def loop_phi_kernel(parents, kind, idx_q, idx_v, nv_j, axis, pitch, place_R, place_p, q, jR, jp, Sl, R, p,
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
def universal_kernel(joints, idx_q, idx_v, a1, a2, q, v, use_v, jR, jp, Sl, c_local):
    for k in range(joints.shape[0]):
        j = joints[k]
        iq, iv = idx_q[j], idx_v[j]
        R1 = rc.axis_rotation(a1[k], np.cos(q[iq]), np.sin(q[iq]))  # row-major 9-tuples
        R2 = rc.axis_rotation(a2[k], np.cos(q[iq + 1]), np.sin(q[iq + 1]))
        for r in range(3):
            for c in range(3):
                jR[j, r, c] = R1[3 * r] * R2[c] + R1[3 * r + 1] * R2[3 + c] + R1[3 * r + 2] * R2[6 + c]
            jp[j, r] = 0.0
        s0 = R2[0] * a1[k, 0] + R2[3] * a1[k, 1] + R2[6] * a1[k, 2]
        s1 = R2[1] * a1[k, 0] + R2[4] * a1[k, 1] + R2[7] * a1[k, 2]
        s2 = R2[2] * a1[k, 0] + R2[5] * a1[k, 1] + R2[8] * a1[k, 2]
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
def point_jac_kernel(parents, idx_v, nv_j, St, joints, X, J):
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
def loop_jacobian_kernel(parents, idx_v, nv_j, St, R, p, jid, local, row_a, row_b, row_axis, X, J, G):
    """The loop rows of Eq. (4)'s H in reduced coordinates, G[r] = P_r (J_a - J_b) (Wang et al. 2019 §3.1: the
    relative velocity of a loop's two sites along its constrained directions P_r), in one call: the loop sites'
    world positions X (recursive.site_pos_kernel) and point Jacobians J (:func:`point_jac_kernel`, J zeroed
    first; scratch), then per row the direction times the Jacobians' difference (the sums of numpy's P @ (J_a -
    J_b) over the three directions, to round-off)."""
    rc.site_pos_kernel(R, p, jid, local, X)
    J[:] = 0.0
    point_jac_kernel(parents, idx_v, nv_j, St, jid, X, J)
    for r in range(G.shape[0]):
        a, b = row_a[r], row_b[r]
        P0, P1, P2 = row_axis[r, 0], row_axis[r, 1], row_axis[r, 2]
        for c in range(G.shape[1]):
            G[r, c] = P0 * (J[a, 0, c] - J[b, 0, c]) + P1 * (J[a, 1, c] - J[b, 1, c]) + P2 * (J[a, 2, c] - J[b, 2, c])


def body_poses(ctx: Context, q) -> dict:
    """Body frames in the world: name -> (position (3,), quaternion xyzw (4,)), without pin.Data."""
    mech = ctx.mech
    ws = ctx.fk(q)
    out = {}
    for name, jid, M in zip(mech.bodies, mech.body_jid, mech.body_placement):
        R = ws.R[int(jid)] @ M.rotation
        p = ws.R[int(jid)] @ M.translation + ws.p[int(jid)]
        out[name] = (p.copy(), pin.Quaternion(R).coeffs().copy())
    return out


def all_site_positions(ctx: Context, q) -> np.ndarray:
    """World positions (S,3) of every site at q, without pin.Data."""
    ctx.fk(q)
    return ctx.site_positions()


def spring_lengths(ctx: Context, q) -> np.ndarray:
    """Lengths (P,) of the maximal springs at q (compile_scene's default rest lengths)."""
    mech = ctx.mech
    if not len(mech.spring_ab):
        return np.zeros(0)
    x = all_site_positions(ctx, q)
    return np.linalg.norm(x[mech.spring_ab[:, 0]] - x[mech.spring_ab[:, 1]], axis=1)
