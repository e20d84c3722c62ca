"""Attachment rows of the deformable coupling (Wang et al. 2019 §4, the equation after Eq. 5:
G_m J_mr qdot_r + G_d qdot_d = 0): a vertex held at a body point p gives three rows
[J_p, -S_i] (qdot_r; qdot_d) = 0 with J_p = J_lin - [p - c]_x J_ang the point Jacobian (Sueda's notes
Eq. S2.4) and S_i the 3 x 3N selector of vertex i; a vertex held at a world point gives [0, S_i] = 0. With Baumgarte
stabilization the right-hand side is -b phi (``residual``) instead of 0.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from redmax_ros.core.jit import njit


def skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def body_point(c, R, local):
    """World point of a body-frame offset ``local`` (frame origin c, rotation R)."""
    return c + R @ local


def world_points(H, body, local) -> np.ndarray:
    """(a,3) world points [m] of the attachments: H (J,4,4) the joint placements (homogeneous, world frame),
    body (a,) the joint of each attachment (-1: a world point), local (a,3) the point in that joint's frame (or
    in the world)."""
    out = np.empty((len(body), 3))
    world_points_kernel(np.ascontiguousarray(H, dtype=float), np.asarray(body, dtype=np.int64),
                        np.ascontiguousarray(local, dtype=float), out)
    return out


@njit
def world_points_kernel(H, body, local, out):
    for k in range(len(body)):
        j = body[k]
        if j < 0:
            for i in range(3):
                out[k, i] = local[k, i]
        else:
            for i in range(3):
                out[k, i] = H[j, i, 3] + H[j, i, 0] * local[k, 0] + H[j, i, 1] * local[k, 1] + H[j, i, 2] * local[k, 2]


def point_jacobian(p, c, J_lin, J_ang):
    """(3,n) Jacobian of the world point p rigidly attached to a frame at c with linear/angular
    Jacobians J_lin, J_ang (LOCAL_WORLD_ALIGNED)."""
    return J_lin - skew(p - c) @ J_ang


def rows(n_r, n_vertices, vertex, J_points):
    """(G_r (3a,n_r) dense, G_d (3a,3N) sparse) of the attachments: J_points (a,3,n_r) (zeros for world
    points) and the vertex selectors with sign -1 for body points, +1 for world points (where
    J_points[i] is None)."""
    a = len(vertex)
    G_r = np.zeros((3 * a, n_r))
    sign = np.empty(3 * a)
    for k, J in enumerate(J_points):
        if J is None:
            sign[3 * k:3 * k + 3] = 1.0
        else:
            G_r[3 * k:3 * k + 3] = J
            sign[3 * k:3 * k + 3] = -1.0
    cols = (3 * np.asarray(vertex, dtype=np.int64)[:, None] + np.arange(3)).ravel()
    G_d = sp.csr_matrix((sign, (np.arange(3 * a), cols)), shape=(3 * a, 3 * n_vertices))
    return G_r, G_d


def residual(P, x, world):
    """(3a,) position residual phi of the attachment rows, row by row, signed so that each row reads
    G z = d/dt phi: for a body point (row [J_p, -S_i], vertex sign -1) J_p qdot_r - v_i = d/dt (P(q) - x_i),
    so phi = P - x_i; for a world point (row [0, S_i], vertex sign +1, P fixed) v_i = d/dt (x_i - P), so
    phi = x_i - P. In short phi = sign_i (x_i - P). P (a,3) the points [m], x (a,3) the attached vertices [m],
    world (a,) True for world points. Baumgarte's rows G z = -b phi(q_k, x_k) make phi decay as (1 - b h)^k."""
    phi = np.asarray(P, dtype=float) - x
    phi[np.asarray(world, dtype=bool)] *= -1.0
    return phi.ravel()


@njit
def advance(x, v, h, vertex, P, project, out):
    """The step's vertex positions in one pass: out (N,3) = x + h v [m]; the attachment drift max |out[vertex] - P|
    [m] (np.max's: a NaN propagates; 0 without attachments); with ``project`` the attached vertices then set onto
    their points P (a,3) (post-stabilization). Returns (drift, sum of out's squares: finite iff every position
    is, short of overflow)."""
    n = x.shape[0]
    for i in range(n):
        for c in range(3):
            out[i, c] = x[i, c] + h * v[i, c]
    drift = 0.0
    for k in range(len(vertex)):
        i = vertex[k]
        for c in range(3):
            d = abs(out[i, c] - P[k, c])
            if d > drift or d != d:
                drift = d
    if project:
        for k in range(len(vertex)):
            i = vertex[k]
            for c in range(3):
                out[i, c] = P[k, c]
    ss = 0.0
    for i in range(n):
        for c in range(3):
            ss += out[i, c] * out[i, c]
    return drift, ss
