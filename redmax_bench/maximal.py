"""Maximal-coordinate baseline (STAR §4.4.1): every body has 6 DOF, joints are bilateral
constraints kept by Lagrange multipliers, and the drift the multipliers cannot see is fought with
Baumgarte stabilisation. Benchmark-only; the runtime path never imports this module.

Formulation, per step of size h, with u = (v_1, w_1, ..., v_B, w_B) (COM velocity and angular
velocity of each body, world frame):

    M du/dt = f_ext(x, u) - [0; w x I_w w]  +  J^T lam                (Newton-Euler)
    J du/dt + k(x, u) + 2 alpha C_dot + beta^2 C = 0                    (Eq. 76 + Baumgarte)

solved as one dense KKT system, then semi-implicit Euler: u+ = u + h du/dt, x+ = x + h v+,
R+ = exp(h [w+]) R. ``C`` are the joint constraint functions (point coincidence of the joint
anchor for revolute, universal and spherical joints; two axis-perpendicularity rows for a revolute
axis; one for a universal joint; none for a free joint) and the scene's loop rows. Forces are the
same as the reduced scene's: gravity, maximal point springs/dampers, revolute joint springs/dampers,
constant world wrenches -- all explicit.

Bodies are the Pinocchio joints' lumped bodies (a fixed joint's child is merged into its parent as
in the reduced model), so ``to_reduced`` recovers the Pinocchio configuration q of the same scene
for joint-space error measures.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

_E = np.eye(3)


def decode_joint(jm):
    """(kind, axes) of a Pinocchio joint model: kind in revolute, prismatic, universal, spherical,
    free, planar; axes: list of unit 3-vectors in the joint frame."""
    s = jm.shortname()
    if s in ("JointModelRX", "JointModelRY", "JointModelRZ"):
        return "revolute", [_E["XYZ".index(s[-1])].copy()]
    if s in ("JointModelPX", "JointModelPY", "JointModelPZ"):
        return "prismatic", [_E["XYZ".index(s[-1])].copy()]
    if s == "JointModelRevoluteUnaligned":
        return "revolute", [np.asarray(jm.extract().axis, float).copy()]
    if s == "JointModelPrismaticUnaligned":
        return "prismatic", [np.asarray(jm.extract().axis, float).copy()]
    if s == "JointModelUniversal":
        e = jm.extract()
        return "universal", [np.asarray(e.axis1, float).copy(), np.asarray(e.axis2, float).copy()]
    if s == "JointModelSpherical":
        return "spherical", []
    if s == "JointModelFreeFlyer":
        return "free", []
    if s == "JointModelPlanar":
        return "planar", []
    raise NotImplementedError(f"joint model {s}")


def _cross(a, b):
    """3-vector cross product (np.cross costs ~30 us per call on 3-vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _perp(a):
    """Two unit vectors completing a to an orthonormal basis."""
    t = _E[int(np.argmin(np.abs(a)))]
    n1 = _cross(a, t)
    n1 /= np.linalg.norm(n1)
    return n1, _cross(a, n1)


@dataclass
class PointRow:  # x_A + R_A ra - x_B - R_B rb, projected on rows P (k,3) (world)
    A: int  # body index (-1 = world)
    ra: np.ndarray  # point in body A's frame, relative to its COM (world point if A == -1)
    B: int
    rb: np.ndarray
    P: np.ndarray


@dataclass
class PerpRow:  # (R_A ua) . (R_B wb) = 0
    A: int
    ua: np.ndarray
    B: int
    wb: np.ndarray


@dataclass
class MaxState:
    x: np.ndarray  # (B,3) COM positions
    R: np.ndarray  # (B,3,3) rotations of the body (joint) frames
    v: np.ndarray  # (B,3) COM velocities (world)
    w: np.ndarray  # (B,3) angular velocities (world)

    def copy(self):
        return MaxState(self.x.copy(), self.R.copy(), self.v.copy(), self.w.copy())


class MaximalModel:
    """The scene of a compiled ``Mechanism`` in maximal coordinates, with Baumgarte gains.

    ``omega_b`` [1/s] sets alpha = beta = omega_b (critically damped constraint error); by default
    omega_b = min(100, 0.2 / h) so that h * omega_b stays below the explicit step's stability limit.
    """

    def __init__(self, mech, omega_b: float | None = None):
        if mech.T is not None:
            raise NotImplementedError("maximal baseline: couplings (hyper-reduced coordinates) are not supported")
        model = mech.model
        self.mech, self.model = mech, model
        self.omega_b = omega_b
        nb = model.njoints - 1
        self.nb = nb
        self.mass = np.array([model.inertias[i].mass for i in range(1, nb + 1)])
        self.com = np.array([model.inertias[i].lever for i in range(1, nb + 1)])  # in the joint frame
        self.Ib = np.array([model.inertias[i].inertia for i in range(1, nb + 1)])  # about the COM
        self.parent = np.array([model.parents[i] - 1 for i in range(1, nb + 1)])  # -1 = world
        self.kinds, self.axes, self.placements = [], [], []
        if np.any(np.asarray(model.armature) != 0):
            raise NotImplementedError("maximal baseline: joint armature (a reduced-coordinate term) is not supported")
        if len(mech.damped_bodies):
            raise NotImplementedError("maximal baseline: body damping is not supported")
        rows_point, rows_perp = [], []
        self.joint_springs = []  # (child body, parent body, axis in child frame, k, d, rest angle, placement)
        for i in range(1, nb + 1):
            jm = model.joints[i]
            kind, axes = decode_joint(jm)
            Mpj = model.jointPlacements[i]
            p = self.parent[i - 1]
            c = i - 1
            self.kinds.append(kind)
            self.axes.append(axes)
            self.placements.append(Mpj)
            anchor_p = Mpj.translation - (self.com[p] if p >= 0 else 0.0)
            anchor_c = -self.com[c]
            if kind in ("revolute", "universal", "spherical"):
                rows_point.append(PointRow(p, anchor_p.copy(), c, anchor_c.copy(), np.eye(3)))
            if kind == "revolute":
                a_par = Mpj.rotation @ axes[0]  # in the parent frame
                n1, n2 = _perp(a_par)
                rows_perp += [PerpRow(p, n1, c, axes[0]), PerpRow(p, n2, c, axes[0])]
                sl = slice(jm.idx_v, jm.idx_v + 1)
                k, d = float(mech.stiffness[sl][0]), float(mech.damping[sl][0])
                if k or d or mech.torque0[sl][0]:
                    rest = float(mech.q_rest[jm.idx_q])
                    self.joint_springs.append((c, p, axes[0], k, d, rest, Mpj, float(mech.torque0[sl][0])))
            elif kind == "universal":
                rows_perp.append(PerpRow(p, Mpj.rotation @ axes[0], c, axes[1]))
            elif kind == "spherical":
                pass
            elif kind == "free":
                pass
            else:
                raise NotImplementedError(f"maximal baseline: {kind} joints are not supported")
            sl = slice(jm.idx_v, jm.idx_v + jm.nv)
            if kind != "revolute" and (np.any(mech.stiffness[sl]) or np.any(mech.damping[sl]) or np.any(mech.torque0[sl])):
                raise NotImplementedError(f"maximal baseline: joint springs/dampers/torques on {kind} joints")
        self.n_joint_point = len(rows_point)
        self.n_joint_perp = len(rows_perp)
        # loops: site a and site b coincide along the listed world rows
        for (a, b), P in zip(mech.loop_ab, mech.loop_axes):
            rows_point.append(PointRow(*self._site_body(a), *self._site_body(b), np.asarray(P, float)))
        self.rows_point, self.rows_perp = rows_point, rows_perp
        self.n_loop_rows = sum(len(r.P) for r in rows_point[self.n_joint_point:])
        self.m = sum(len(r.P) for r in rows_point) + len(rows_perp)
        self.springs = [(*self._site_body(a), *self._site_body(b), k, d, L0) for (a, b), k, d, L0 in
                        zip(mech.spring_ab, mech.spring_k, mech.spring_d, mech.spring_rest)]
        self.wrenches = [(int(mech.body_jid[bi]) - 1, fw) for bi, fw in zip(mech.wrench_body, mech.wrench_fw)]
        self.g = np.asarray(model.gravity.linear, float)
        self.n = 6 * nb

    def _site_body(self, s):
        jid = int(self.mech.site_jid[s])
        if jid == 0:
            return -1, np.asarray(self.mech.site_local[s], float).copy()
        return jid - 1, np.asarray(self.mech.site_local[s], float) - self.com[jid - 1]

    # -- conversions --------------------------------------------------------------------------
    def from_reduced(self, q, v) -> MaxState:
        model = self.model
        data = model.createData()
        pin.forwardKinematics(model, data, q, v)
        x, R, lv, w = (np.zeros((self.nb, 3)) for _ in range(4))
        R = np.zeros((self.nb, 3, 3))
        for i in range(1, self.nb + 1):
            M = data.oMi[i]
            R[i - 1] = M.rotation
            x[i - 1] = M.act(self.com[i - 1])
            vi = data.v[i]  # local frame
            w[i - 1] = M.rotation @ vi.angular
            lv[i - 1] = M.rotation @ (vi.linear + _cross(vi.angular, self.com[i - 1]))
        return MaxState(x, R, lv, w)

    def to_reduced(self, s: MaxState, q_prev=None) -> np.ndarray:
        """Pinocchio configuration q of the bodies' poses (joint values from relative transforms).
        Revolute and universal angles are unwrapped to the branch nearest ``q_prev`` (a crank that
        turns keeps counting turns, as Pinocchio's unbounded revolute coordinate does)."""
        q = np.zeros(self.model.nq)
        for i in range(1, self.nb + 1):
            c, p = i - 1, self.parent[i - 1]
            Rc, pc = s.R[c], s.x[c] - s.R[c] @ self.com[c]  # joint frame of the child
            Mpj = self.placements[c]
            if p >= 0:
                Rp, pp = s.R[p], s.x[p] - s.R[p] @ self.com[p]
            else:
                Rp, pp = np.eye(3), np.zeros(3)
            Rj = Rp @ Mpj.rotation  # joint frame at zero configuration
            pj = pp + Rp @ Mpj.translation
            Rrel = Rj.T @ Rc
            trel = Rj.T @ (pc - pj)
            jm = self.model.joints[i]
            iq, kind = jm.idx_q, self.kinds[c]
            if kind == "revolute":
                q[iq] = float(pin.log3(Rrel) @ self.axes[c][0])
            elif kind == "universal":
                a1, a2 = self.axes[c]
                a3 = _cross(a1, a2)
                ra2 = Rrel @ a2
                q1 = math.atan2(ra2 @ a3, ra2 @ a2)
                q2 = float(pin.log3(pin.exp3(-q1 * a1) @ Rrel) @ a2)
                q[iq:iq + 2] = q1, q2
            elif kind == "spherical":
                q[iq:iq + 4] = pin.Quaternion(Rrel).coeffs()
            elif kind == "free":
                q[iq:iq + 3] = trel
                q[iq + 3:iq + 7] = pin.Quaternion(Rrel).coeffs()
        if q_prev is not None:
            for i in range(1, self.nb + 1):
                if self.kinds[i - 1] in ("revolute", "universal"):
                    jm = self.model.joints[i]
                    sl = slice(jm.idx_q, jm.idx_q + jm.nq)
                    q[sl] += 2 * np.pi * np.round((q_prev[sl] - q[sl]) / (2 * np.pi))
        return q

    # -- constraint terms ---------------------------------------------------------------------
    def _world(self, s, A, r):
        """(world point, world lever R r, R) of a point r on body A (A = -1: world point)."""
        if A < 0:
            return r, None
        rw = s.R[A] @ r
        return s.x[A] + rw, rw

    def constraints(self, s: MaxState):
        """(C (m,), J (m, 6B), k (m,)) with J du/dt + k = d^2C/dt^2."""
        m, n = self.m, self.n
        C, J, k = np.zeros(m), np.zeros((m, n)), np.zeros(m)
        r = 0
        for row in self.rows_point:
            pa, ra = self._world(s, row.A, row.ra)
            pb, rb = self._world(s, row.B, row.rb)
            nr = len(row.P)
            C3 = pa - pb
            k3 = np.zeros(3)
            J3 = np.zeros((3, n))
            if row.A >= 0:
                wa = s.w[row.A]
                J3[:, 6 * row.A:6 * row.A + 3] = _E
                J3[:, 6 * row.A + 3:6 * row.A + 6] = -_skew(ra)
                k3 += _cross(wa, _cross(wa, ra))
            if row.B >= 0:
                wb = s.w[row.B]
                J3[:, 6 * row.B:6 * row.B + 3] -= _E
                J3[:, 6 * row.B + 3:6 * row.B + 6] += _skew(rb)
                k3 -= _cross(wb, _cross(wb, rb))
            C[r:r + nr], J[r:r + nr], k[r:r + nr] = row.P @ C3, row.P @ J3, row.P @ k3
            r += nr
        for row in self.rows_perp:
            u = row.ua if row.A < 0 else s.R[row.A] @ row.ua
            wv = s.R[row.B] @ row.wb
            wa = np.zeros(3) if row.A < 0 else s.w[row.A]
            wb = s.w[row.B]
            uxw = _cross(u, wv)
            C[r] = u @ wv
            if row.A >= 0:
                J[r, 6 * row.A + 3:6 * row.A + 6] = uxw
            J[r, 6 * row.B + 3:6 * row.B + 6] -= uxw
            duxw = _cross(_cross(wa, u), wv) + _cross(u, _cross(wb, wv))
            k[r] = duxw @ (wa - wb)
            r += 1
        return C, J, k

    def violation(self, s: MaxState) -> tuple:
        """(max |C| of the joint rows [m or rad], max |C| of the loop rows [m])."""
        C, _, _ = self.constraints(s)
        nj = sum(len(r.P) for r in self.rows_point[:self.n_joint_point])
        joint = np.concatenate([C[:nj], C[nj + self.n_loop_rows:]])
        loop = C[nj:nj + self.n_loop_rows]
        return (float(np.abs(joint).max()) if len(joint) else 0.0,
                float(np.abs(loop).max()) if len(loop) else 0.0)

    # -- forces and energy --------------------------------------------------------------------
    def forces(self, s: MaxState) -> np.ndarray:
        """Generalized force (6B,): gravity, springs, joint springs, wrenches, minus w x I_w w."""
        f = np.zeros((self.nb, 6))
        f[:, :3] = self.mass[:, None] * self.g
        for bi in range(self.nb):
            Iw = s.R[bi] @ self.Ib[bi] @ s.R[bi].T
            f[bi, 3:] -= _cross(s.w[bi], Iw @ s.w[bi])
        for A, ra, B, rb, kk, dd, L0 in self.springs:
            pa, la = self._world(s, A, ra)
            pb, lb = self._world(s, B, rb)
            d = pa - pb
            l = float(np.linalg.norm(d))
            u = d / l if l > 1e-12 else np.zeros(3)
            va = s.v[A] + _cross(s.w[A], la) if A >= 0 else np.zeros(3)
            vb = s.v[B] + _cross(s.w[B], lb) if B >= 0 else np.zeros(3)
            fa = -(kk * (l - L0) + dd * (u @ (va - vb))) * u
            if A >= 0:
                f[A, :3] += fa
                f[A, 3:] += _cross(la, fa)
            if B >= 0:
                f[B, :3] -= fa
                f[B, 3:] -= _cross(lb, fa)
        for c, p, a, kk, dd, rest, Mpj, tau0 in self.joint_springs:
            th, aw, rate = self._revolute_angle(s, c, p, a, Mpj)
            tau = -kk * (th - rest) - dd * rate + tau0
            f[c, 3:] += tau * aw
            if p >= 0:
                f[p, 3:] -= tau * aw
        for bi, fw in self.wrenches:
            f[bi, :3] += fw[:3]
            f[bi, 3:] += fw[3:]
        return f.reshape(-1)

    def _revolute_angle(self, s, c, p, a, Mpj):
        Rp = s.R[p] if p >= 0 else np.eye(3)
        Rj = Rp @ Mpj.rotation
        th = float(pin.log3(Rj.T @ s.R[c]) @ a)
        aw = s.R[c] @ a
        wp = s.w[p] if p >= 0 else np.zeros(3)
        return th, aw, float(aw @ (s.w[c] - wp))

    def energy(self, s: MaxState) -> float:
        e = 0.0
        for bi in range(self.nb):
            Iw = s.R[bi] @ self.Ib[bi] @ s.R[bi].T
            e += 0.5 * self.mass[bi] * s.v[bi] @ s.v[bi] + 0.5 * s.w[bi] @ Iw @ s.w[bi]
            e -= self.mass[bi] * self.g @ s.x[bi]
        for A, ra, B, rb, kk, dd, L0 in self.springs:
            pa, _ = self._world(s, A, ra)
            pb, _ = self._world(s, B, rb)
            e += 0.5 * kk * (np.linalg.norm(pa - pb) - L0) ** 2
        for c, p, a, kk, dd, rest, Mpj, tau0 in self.joint_springs:
            th, _, _ = self._revolute_angle(s, c, p, a, Mpj)
            e += 0.5 * kk * (th - rest) ** 2
        return float(e)

    def mass_matrix(self, s: MaxState) -> np.ndarray:
        M = np.zeros((self.n, self.n))
        for bi in range(self.nb):
            M[6 * bi:6 * bi + 3, 6 * bi:6 * bi + 3] = self.mass[bi] * _E
            M[6 * bi + 3:6 * bi + 6, 6 * bi + 3:6 * bi + 6] = s.R[bi] @ self.Ib[bi] @ s.R[bi].T
        return M

    # -- step ---------------------------------------------------------------------------------
    def step(self, s: MaxState, h: float) -> MaxState:
        """One semi-implicit Euler step of the Baumgarte-stabilised DAE."""
        wb = self.omega_b if self.omega_b is not None else min(100.0, 0.2 / h)
        alpha = beta = wb
        f = self.forces(s)
        u = np.concatenate([s.v, s.w], axis=1).reshape(-1)
        Minv = np.zeros((self.n, self.n))
        for bi in range(self.nb):
            Minv[6 * bi:6 * bi + 3, 6 * bi:6 * bi + 3] = _E / self.mass[bi]
            Minv[6 * bi + 3:6 * bi + 6, 6 * bi + 3:6 * bi + 6] = s.R[bi] @ np.linalg.inv(self.Ib[bi]) @ s.R[bi].T
        a0 = Minv @ f
        if self.m:
            C, J, k = self.constraints(s)
            rhs = -(J @ a0 + k + 2 * alpha * (J @ u) + beta * beta * C)
            S = J @ Minv @ J.T
            lam = np.linalg.solve(S, rhs)
            a = a0 + Minv @ (J.T @ lam)
        else:
            a = a0
        u1 = (u + h * a).reshape(self.nb, 6)
        v1, w1 = u1[:, :3].copy(), u1[:, 3:].copy()
        x1 = s.x + h * v1
        R1 = np.array([pin.exp3(h * w1[bi]) @ s.R[bi] for bi in range(self.nb)])
        return MaxState(x1, R1, v1, w1)
