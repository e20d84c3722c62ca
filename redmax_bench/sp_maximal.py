"""Baseline for `redmax_bench friction`: Staggered Projections in MAXIMAL coordinates (paper §5.1, the
comparison of §6 CHAIN), for trees of revolute joints with point loop closures and joint friction.

Every body has 6 DOFs (COM velocity, world angular velocity), mass matrix diag(m I, I_w), gravity and
the gyroscopic force -w x I_w w (explicit). Each revolute joint is 5 bilateral rows (anchor points
coincide, 3 rows; the two axes stay aligned, 2 rows) and each loop its point rows, all with
Baumgarte stabilization G qdot = -(erp/h) phi (Sueda's notes §1.12, Eq. 1.97; STAR §4.4.1), solved by
the KKT Schur complement. Joint friction as in BISP: the joint's reaction wrench (here: its Lagrange
multipliers) is distributed over the same implicit contact points by the same Eq. (16) operator
(contact.compile_friction), friction rows r k . (w_child - w_parent), box QP with bound
mu sum|alpha|, the same staggered iteration, convergence test, inner solver and acceleration as the
reduced solver (staggered.py; with ``compiled`` the same compiled loop, the joint multipliers as an
affine map of beta), so the measured ratio is that of the coordinates only.
The scene's constant joint torques (``torque``) act on the child (+tau k) and the parent (-tau k), and a
prescribed joint velocity (``prescribed.joints``) is one more bilateral row k . (w_child - w_parent) = v
(no Baumgarte term) whose required torque -lambda/h (Eq. 7) is ``effort[name]`` after a step.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.friction.bisp import dense_wrench_map
from redmax_ros.core.friction.condense import fixed_row_weights, pattern_of
from redmax_ros.core.friction.staggered import Anderson, box_qp, cone_excess, loop_kernel


def _skew(a):
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


class MaximalSP:
    def __init__(self, mech, erp=0.2, compiled=True):
        self.mech, self.fm, self.erp, self.compiled = mech, mech.friction, erp, compiled
        model = mech.model
        self.nb = model.njoints - 1
        data = model.createData()
        q0 = mech.q0
        v0 = mech.to_reduced(mech.v0)
        pin.forwardKinematics(model, data, q0, v0)
        self.m = np.array([model.inertias[i].mass for i in range(1, model.njoints)])
        self.c = np.array([model.inertias[i].lever for i in range(1, model.njoints)])
        self.Ic = [model.inertias[i].inertia.copy() for i in range(1, model.njoints)]
        self.R = np.array([data.oMi[i].rotation for i in range(1, model.njoints)])
        self.x = np.array([data.oMi[i].act(self.c[i - 1]) for i in range(1, model.njoints)])
        self.v = np.zeros(6 * self.nb)
        for i in range(1, model.njoints):
            vl = data.v[i]
            R = self.R[i - 1]
            w = R @ vl.angular
            self.v[6 * (i - 1):6 * i] = np.r_[R @ vl.linear + np.cross(w, R @ self.c[i - 1]), w]
        self.parent = [int(model.parents[i]) - 1 for i in range(1, model.njoints)]  # -1: world
        self.place = [model.jointPlacements[i] for i in range(1, model.njoints)]
        self.axis = []
        for j in mech.joints:
            js = next(s for s in mech.spec.joints if s.name == j.name)
            assert j.type == "revolute", "the maximal baseline supports revolute joints only"
            self.axis.append(np.asarray(js.axes[0], float))
        names = [j.name for j in mech.joints]
        self.tau = np.array([float(np.asarray(s.torque).reshape(-1)[0]) for s in
                             sorted(mech.spec.joints, key=lambda s: names.index(s.name))])
        self.prescribed = {names.index(k): float(np.asarray(v).reshape(-1)[0])
                           for k, v in mech.spec.prescribed_joints.items()}
        self.names = names
        self.effort = {}
        self.g = np.asarray(mech.model.gravity.linear)
        self.beta = None
        self.iterations = []

    def _lever(self, b, p_local):
        """World lever from body b's COM to the point p_local (joint frame of b)."""
        return self.R[b] @ (p_local - self.c[b])

    def step(self, h):
        nb, fm, st = self.nb, self.fm, self.fm.settings
        n = 6 * nb
        Mdiag = np.zeros((n, n))
        f = np.zeros(n)
        for b in range(nb):
            Iw = self.R[b] @ self.Ic[b] @ self.R[b].T
            Mdiag[6 * b:6 * b + 3, 6 * b:6 * b + 3] = self.m[b] * np.eye(3)
            Mdiag[6 * b + 3:6 * b + 6, 6 * b + 3:6 * b + 6] = Iw
            w = self.v[6 * b + 3:6 * b + 6]
            f[6 * b:6 * b + 3] = self.m[b] * self.g
            f[6 * b + 3:6 * b + 6] = -np.cross(w, Iw @ w)
        for b in range(nb):  # constant joint torques: +tau k on the child, -tau k on the parent
            kc = self.tau[b] * (self.R[b] @ self.axis[b])
            f[6 * b + 3:6 * b + 6] += kc
            if self.parent[b] >= 0:
                f[6 * self.parent[b] + 3:6 * self.parent[b] + 6] -= kc
        rows, rhs, jrows, frows = [], [], [], []
        k = 0
        for b in range(nb):  # revolute joint of body b
            p = self.parent[b]
            ac = self._lever(b, np.zeros(3))
            kc = self.R[b] @ self.axis[b]
            if p >= 0:
                ap = self._lever(p, self.place[b].translation)
                xp = self.x[p] + ap
                kp = self.R[p] @ (self.place[b].rotation @ self.axis[b])
            else:
                xp = self.place[b].translation
                kp = self.place[b].rotation @ self.axis[b]
            phi = self.x[b] + ac - xp
            G = np.zeros((5, n))
            G[:3, 6 * b:6 * b + 3] = np.eye(3)
            G[:3, 6 * b + 3:6 * b + 6] = -_skew(ac)
            e = np.eye(3)[int(np.argmin(np.abs(kp)))]
            e1 = np.cross(kp, e)
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(kp, e1)
            G[3, 6 * b + 3:6 * b + 6], G[4, 6 * b + 3:6 * b + 6] = e1, e2
            cr = np.cross(kp, kc)
            if p >= 0:
                G[:3, 6 * p:6 * p + 3] = -np.eye(3)
                G[:3, 6 * p + 3:6 * p + 6] = _skew(ap)
                G[3, 6 * p + 3:6 * p + 6], G[4, 6 * p + 3:6 * p + 6] = -e1, -e2
            rows.append(G)
            rhs.append(-(self.erp / h) * np.r_[phi, e1 @ cr, e2 @ cr])
            jrows.append((k, b, e1, e2))
            k += 5
        mech = self.mech
        lrows = []
        for li, ((sa, sb), P) in enumerate(zip(mech.loop_ab, mech.loop_axes)):
            ba, bb = int(mech.site_jid[sa]) - 1, int(mech.site_jid[sb]) - 1
            la, lb = self._lever(ba, mech.site_local[sa]), self._lever(bb, mech.site_local[sb])
            G = np.zeros((len(P), n))
            G[:, 6 * ba:6 * ba + 3] = P
            G[:, 6 * ba + 3:6 * ba + 6] = -P @ _skew(la)
            G[:, 6 * bb:6 * bb + 3] -= P
            G[:, 6 * bb + 3:6 * bb + 6] += P @ _skew(lb)
            rows.append(G)
            rhs.append(-(self.erp / h) * P @ (self.x[ba] + la - self.x[bb] - lb))
            lrows.append((k, len(P), P, ba, bb))
            k += len(P)
        prows = []
        for b, vel in self.prescribed.items():  # Eq. 7: k . (w_child - w_parent) = v
            G = np.zeros((1, n))
            kc = self.R[b] @ self.axis[b]
            G[0, 6 * b + 3:6 * b + 6] = kc
            if self.parent[b] >= 0:
                G[0, 6 * self.parent[b] + 3:6 * self.parent[b] + 6] = -kc
            rows.append(G)
            rhs.append(np.array([vel]))
            prows.append((k, b))
            k += 1
        G = np.vstack(rows)
        g = np.concatenate(rhs)
        # friction rows: tree joints (fm order), loop pins
        jid_to_b = {int(j): int(j) - 1 for j in fm.fj_jid}
        for j, name in zip(fm.fj_jid, fm.fj_names[:fm.n_tree]):
            b = jid_to_b[int(j)]
            p = self.parent[b]
            r = self._radius(name)
            T = np.zeros(n)
            kc = self.R[b] @ self.axis[b]
            T[6 * b + 3:6 * b + 6] = r * kc
            if p >= 0:
                T[6 * p + 3:6 * p + 6] = -r * kc
            frows.append(T)
        for li, ax, rad in zip(fm.loop_index, fm.loop_axis, fm.loop_radius):
            sa, sb = mech.loop_ab[li]
            ba, bb = int(mech.site_jid[sa]) - 1, int(mech.site_jid[sb]) - 1
            T = np.zeros(n)
            T[6 * ba + 3:6 * ba + 6] += rad * ax
            T[6 * bb + 3:6 * bb + 6] -= rad * ax
            frows.append(T)
        Tr = np.array(frows).reshape(-1, n)
        A = Mdiag
        b_ = Mdiag @ self.v + h * f
        Ainv = np.linalg.inv(A)
        Y = Ainv @ G.T
        Sinv = np.linalg.inv(G @ Y)
        P_ = Ainv - Y @ Sinv @ Y.T
        v0 = P_ @ b_ + Y @ (Sinv @ g)
        PT = P_ @ Tr.T
        W = Tr @ PT
        wT = np.maximum(np.diag(W), 0)
        fixed_row_weights(wT, Tr, Ainv, *pattern_of(Tr))  # rows whose slip the prescriptions fix (condense.py)
        nf = len(Tr)
        beta = np.zeros(nf) if self.beta is None else self.beta
        kmax = fm.L.shape[1]
        if self.compiled and fm.bound_mu is not None:
            # the joint wrenches are linear in lambda = lambda0 + Lam beta: alpha = a0 + Mx beta, then the
            # same compiled staggered loop as the reduced solver (staggered.loop_kernel, no contact rows)
            lam0 = Sinv @ (Y.T @ b_ - g)
            Lam = -Sinv @ (Y.T @ Tr.T)
            Q = np.zeros((len(fm.fj_names), 6, len(g)))
            for (k0, b, e1, e2), name in zip(jrows, fm.fj_names[:fm.n_tree]):
                j = fm.fj_names.index(name)
                Rt = self.R[b].T / h
                Q[j, :3, k0:k0 + 3] = Rt
                Q[j, 3:, k0 + 3] = Rt @ e1
                Q[j, 3:, k0 + 4] = Rt @ e2
            for q, li in enumerate(fm.loop_index):
                k0, kk, P, _, _ = lrows[li]
                Q[fm.n_tree + q, :3, k0:k0 + kk] = P.T / h
            HLQ = h * np.matmul(fm.L, Q)  # (J, kmax, m)
            a0 = (HLQ @ lam0).reshape(-1)
            Mx = np.ascontiguousarray((HLQ @ Lam).reshape(-1, nf))
            e0, e2_ = np.zeros(0), np.zeros((0, nf))
            _, beta, _, _, it, _, _ = loop_kernel(
                np.zeros((0, 0)), e2_, np.zeros((nf, 0)), e0, e0, W, Tr @ v0, e0, a0, dense_wrench_map(Mx), fm.bound_mu, kmax,
                True, e0, wT, st.tol, st.max_iter, st.anderson, e0, np.ascontiguousarray(beta))
            self.iterations.append(it)
            self._efforts(prows, lam0 + Lam @ beta, h)
            self._finish(beta, v0, PT, h)
            return
        acc = Anderson(st.anderson)
        prev = None
        for it in range(1, st.max_iter + 1):
            r_ = b_ - Tr.T @ beta
            lam = Sinv @ (Y.T @ r_ - g)
            W6 = np.zeros((len(fm.fj_names), 6))
            for (k0, b, e1, e2), name in zip(jrows, fm.fj_names[:fm.n_tree]):
                Rb = self.R[b]
                F, Mw = lam[k0:k0 + 3] / h, (lam[k0 + 3] * e1 + lam[k0 + 4] * e2) / h
                W6[fm.fj_names.index(name)] = np.r_[Rb.T @ F, Rb.T @ Mw]
            for q, li in enumerate(fm.loop_index):
                k0, kk, P, _, _ = lrows[li]
                W6[fm.n_tree + q, :3] = P.T @ lam[k0:k0 + kk] / h
            al = h * np.einsum("jkl,jl->jk", fm.L, W6)
            bound = fm.bound_B @ np.abs(al).reshape(-1)
            if prev is not None:
                res = float((np.abs(bound - prev) * wT).max(initial=0.0))
                if res <= st.tol and cone_excess(beta, bound, wT) <= st.tol:
                    break
            prev = bound
            c = Tr @ v0  # slip velocity without friction (joint reactions are in v0 through G)
            b_in = beta
            beta = box_qp(W, -c, -bound, bound, beta, 0.1 * st.tol, st.qp)
            if st.anderson:
                beta = acc.update(b_in, beta, bound)
        self.iterations.append(it)
        self._efforts(prows, Sinv @ (Y.T @ (b_ - Tr.T @ beta) - g), h)
        self._finish(beta, v0, PT, h)

    def _efforts(self, prows, lam, h):
        """Required torques of the prescribed joints: A qdot = b - G^T lambda, so the row's torque about
        the joint axis on the child is -lambda / h (Eq. 7)."""
        self.effort = {self.names[b]: float(-lam[k] / h) for k, b in prows}

    def _finish(self, beta, v0, PT, h):
        nb = self.nb
        self.beta = beta
        v = v0 - PT @ beta
        self.v = v
        for b in range(nb):
            self.x[b] = self.x[b] + h * v[6 * b:6 * b + 3]
            self.R[b] = pin.exp3(h * v[6 * b + 3:6 * b + 6]) @ self.R[b]

    def _radius(self, name):
        fs = self.mech.spec.friction
        return fs.joints[name].radius

    def com_positions(self):
        return self.x.copy()
