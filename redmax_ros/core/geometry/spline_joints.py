"""Spline joints of Lee and Terzopoulos [2008] (Sueda's notes §2.5.12-2.5.13, Alg. 3-4).

Uniform cubic B-splines (basis matrix B of Eq. 2.68). Twists are in Pinocchio's order (linear first);
S is the body Jacobian [Q^-1 dQ/dq] and dS/dq its derivative, so that Sdot = (dS/dq) qdot.

* Spline curve joint (1 DOF, §2.5.12): control frames C_1..C_n in SE(3) (n >= 4). On segment i
  (s in [i, i+1], u = s - i) the joint transform is the cumulative form of Eq. 2.74,
  Q(s) = C_i exp(dC_{i+1} Bt_2(u)) exp(dC_{i+2} Bt_3(u)) exp(dC_{i+3} Bt_4(u)), dC_k = log(C_{k-1}^-1 C_k),
  with the cumulative basis functions Bt (Eq. 2.72). The parameter runs over s in [0, n - 3];
  consecutive segments join with C2 continuity (B-spline property, kept by the cumulative form).
  A *cyclic* curve (``cyclic: true``, issue 13 item 6) wraps the control frames around: segment
  i = floor(s) mod n uses C_i .. C_{i+3} with indices mod n and dC_0 = log(C_{n-1}^-1 C_0), so
  Q(s + n) = Q(s) for every real s (no domain ends). The joins are the same identity as between any
  two segments (C_{i-1} exp(dC_i) = C_i, here also for i = 0), so the closed curve is C2 everywhere.
* Spline surface joint (2 DOF, §2.5.13): a grid of control values (x, y, z, rx, ry, rz) of size
  n1 x n2 (each >= 4); on patch (i, j) each of the six components is the tensor-product B-spline
  f_k(q1, q2) = q1^T B^T C_k B q2 (Eq. 2.75) and Q = prod_k exp(e_k f_k) (Eq. 2.78), translations
  x, y, z first and then rotations about x, y, z (the rotations act as XYZ Euler angles).

S and dS/dq follow Alg. 3 / Alg. 4: for each factor E_k = exp(xi_k b_k(q)) appended on the right,
S <- xi_k b_k' + Ad(E_k^-1) S and dS <- xi_k b_k'' + Ad(E_k^-1) (dS + ad(S) xi_k b_k') (the notes
print the last factor as "a_i dC_i Bt_i(q)"; the derivative of Ad(E_k^-1) gives the first
derivative Bt_i'(q) there, which the finite-difference tests confirm).
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from redmax_ros.core.geometry.joints import Ad, ad, exp6, log6

# Eq. 2.68: x(u) = C B [1 u u^2 u^3]^T
B_MATRIX = np.array([[1.0, -3.0, 3.0, -1.0],
                     [4.0, 0.0, -6.0, 3.0],
                     [1.0, 3.0, 3.0, -3.0],
                     [0.0, 0.0, 0.0, 1.0]]) / 6.0
# cumulative basis (Eq. 2.72): Bt_k = sum_{i >= k} B_i
B_CUM = np.array([B_MATRIX[k:].sum(axis=0) for k in range(4)])


def _powers(u):
    u3 = u ** 3 if abs(u) < 1e100 else u * u * u  # float ** raises OverflowError where * gives inf (a huge q)
    return (np.array([1.0, u, u * u, u3]), np.array([0.0, 1.0, 2 * u, 3 * u * u]),
            np.array([0.0, 0.0, 2.0, 6 * u]))


def _segment(s, n):
    """(first control index, local parameter u) for parameter s on a spline with n control points."""
    if not math.isfinite(s):  # a non-finite configuration: NaN geometry, which the step's checks name
        return 0, math.nan
    i = int(np.clip(np.floor(s), 0, n - 4))
    return i, s - i


class SplineCurve:
    """Spline curve joint geometry: control frames (list of pin.SE3), parameter domain [0, n - 3];
    ``cyclic``: the frames wrap around (period n in s, no domain ends)."""

    def __init__(self, frames, cyclic=False):
        self.C = [pin.SE3(M) for M in frames]
        self.cyclic = bool(cyclic)
        if len(self.C) < 4:
            raise ValueError("a spline curve needs at least 4 control frames")
        n = len(self.C)
        self.dC = [log6(self.C[n - 1].inverse() * self.C[0]) if self.cyclic else None] + \
            [log6(self.C[k - 1].inverse() * self.C[k]) for k in range(1, n)]

    @property
    def domain(self):
        if self.cyclic:
            return -np.inf, np.inf
        return 0.0, float(len(self.C) - 3)

    def eval(self, s):
        """(Q (SE3), S (6,1), dS/ds (6,1)) at parameter s (Alg. 3)."""
        n = len(self.C)
        if self.cyclic and math.isfinite(s):
            f = np.floor(float(s))
            i, u = int(f) % n, float(s) - f
        else:
            i, u = _segment(float(s), n)
        p, dp, ddp = _powers(u)
        b, db, ddb = B_CUM @ p, B_CUM @ dp, B_CUM @ ddp
        xi = self.dC[(i + 1) % n]
        Q = self.C[i] * exp6(xi * b[1])
        S = xi * db[1]
        dS = xi * ddb[1]
        for k in (2, 3):
            xi = self.dC[(i + k) % n]
            E = exp6(xi * b[k])
            Q = Q * E
            A = Ad(E.inverse())
            dS = xi * ddb[k] + A @ (dS + ad(S) @ xi * db[k])
            S = xi * db[k] + A @ S
        return Q, S[:, None], dS[:, None]

    def kinematics(self, q, qd):
        """(Q, S, Sdot) with Sdot = (dS/dq) qdot."""
        Q, S, dS = self.eval(np.atleast_1d(q)[0])
        return Q, S, dS * float(np.atleast_1d(qd)[0])


_E6 = np.eye(6)  # Pinocchio order: e_0..e_2 translations x, y, z; e_3..e_5 rotations x, y, z


class SplineSurface:
    """Spline surface joint geometry: control grid (n1, n2, 6) of (x, y, z, rx, ry, rz)."""

    def __init__(self, grid):
        self.G = np.asarray(grid, float)
        if self.G.ndim != 3 or self.G.shape[2] != 6 or min(self.G.shape[:2]) < 4:
            raise ValueError("a spline surface needs an n1 x n2 grid (n1, n2 >= 4) of 6 values")

    @property
    def domain(self):
        return (0.0, float(self.G.shape[0] - 3)), (0.0, float(self.G.shape[1] - 3))

    def _f(self, q):
        """f_k, df_k/dq_i, d2f_k/dq_i dq_j for the six components (Eq. 2.75-2.76)."""
        i, u = _segment(float(q[0]), self.G.shape[0])
        j, w = _segment(float(q[1]), self.G.shape[1])
        pu = [B_MATRIX @ x for x in _powers(u)]  # B q1, B q1', B q1''
        pw = [B_MATRIX @ x for x in _powers(w)]
        C = self.G[i:i + 4, j:j + 4, :]  # (4, 4, 6)
        f = np.einsum("a,abk,b->k", pu[0], C, pw[0])
        df = np.stack([np.einsum("a,abk,b->k", pu[1], C, pw[0]), np.einsum("a,abk,b->k", pu[0], C, pw[1])])
        d11 = np.einsum("a,abk,b->k", pu[2], C, pw[0])
        d22 = np.einsum("a,abk,b->k", pu[0], C, pw[2])
        d12 = np.einsum("a,abk,b->k", pu[1], C, pw[1])
        ddf = np.array([[d11, d12], [d12, d22]])  # (2, 2, 6)
        return f, df, ddf

    def eval(self, q):
        """(Q, S (6,2), dS (6,2,2) with dS[:, i, j] = dS_i/dq_j) at q (Alg. 4)."""
        f, df, ddf = self._f(q)
        e = _E6[0]
        Q = exp6(e * f[0])
        S = np.stack([e * df[0, 0], e * df[1, 0]], axis=1)
        dS = np.zeros((6, 2, 2))
        for a in range(2):
            for b in range(2):
                dS[:, a, b] = e * ddf[a, b, 0]
        for k in range(1, 6):
            e = _E6[k]
            E = exp6(e * f[k])
            Q = Q * E
            A = Ad(E.inverse())
            newdS = np.zeros_like(dS)
            for a in range(2):
                adS = ad(S[:, a]) @ e
                for b in range(2):
                    newdS[:, a, b] = e * ddf[a, b, k] + A @ (dS[:, a, b] + adS * df[b, k])
            S = np.stack([e * df[0, k] + A @ S[:, 0], e * df[1, k] + A @ S[:, 1]], axis=1)
            dS = newdS
        return Q, S, dS

    def kinematics(self, q, qd):
        Q, S, dS = self.eval(q)
        return Q, S, dS @ np.asarray(qd, float)
