"""Kinematics stage of a step: Pinocchio terms and site (point) positions and Jacobians.

J_mr is never formed: J_mr^T M_m J_mr is Pinocchio's CRBA (with armature) and
J_mr^T (f_m - M_m Jdot_mr qdot) (Coriolis, centrifugal and gravity forces with the quadratic
velocity vector of Eq. 1-2) is -nle (RNEA at zero acceleration). Sites are Pinocchio frames;
their point Jacobians (Eq. S2.4, Sueda's notes §2.4) are the linear rows of Pinocchio's
LOCAL_WORLD_ALIGNED frame Jacobian.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from redmax_ros.core.jit import njit

LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


@dataclass
class Kinematics:
    M: np.ndarray  # (nv,nv) reduced mass matrix J^T M_m J + armature [kg m^2]
    nle: np.ndarray  # (nv,) Coriolis + centrifugal + gravity generalized force [N m]
    sites: list  # site indices whose rows are in X, J (static ones first, see Mechanism.jac_sites)
    row: dict  # site index -> row in X, J
    X: np.ndarray  # (K,3) site positions, world frame [m]
    J: np.ndarray  # (K,3,nv) site point Jacobians, world frame
    v: np.ndarray | None = None  # (nv,) the reduced velocity they were computed at


def site_positions(mech, data, idx=None) -> np.ndarray:
    """World positions (K,3) of the sites in ``idx`` (default all). Needs forward kinematics in data."""
    idx = range(len(mech.site_names)) if idx is None else idx
    out = np.empty((len(idx), 3))
    fids, model = mech.site_fid, mech.model
    for k, i in enumerate(idx):
        fid = fids[i]
        out[k] = mech.site_local[i] if fid < 0 else pin.updateFramePlacement(model, data, fid).translation
    return out


def point_jacobians(J6: np.ndarray, X: np.ndarray, support: np.ndarray) -> np.ndarray:
    """(K,3,nv) Jacobians of world points X (K,3) from the WORLD-frame joint Jacobian J6 (6,nv) of
    computeJointJacobians: J_x = J_lin - [x]x J_ang on the DOFs that support each point (Eq. S2.4)."""
    return _point_jacobians(np.ascontiguousarray(J6), np.ascontiguousarray(X, dtype=float), support)


@njit
def _point_jacobians(J6, X, support):
    out = np.zeros((X.shape[0], 3, J6.shape[1]))
    point_jacobians_into(J6, X, support, out)
    return out


@njit
def point_jacobians_into(J6, X, support, out):
    """point_jacobians into ``out`` (K,3,nv): writes the supported entries only (the others keep their values: a
    buffer zeroed once and reused with the same ``support`` holds the whole Jacobians)."""
    K, nv = X.shape[0], J6.shape[1]
    for k in range(K):
        x0, x1, x2 = X[k, 0], X[k, 1], X[k, 2]
        for i in range(nv):
            if support[k, i]:
                a0, a1, a2 = J6[3, i], J6[4, i], J6[5, i]
                out[k, 0, i] = J6[0, i] - (x1 * a2 - x2 * a1)
                out[k, 1, i] = J6[1, i] - (x2 * a0 - x0 * a2)
                out[k, 2, i] = J6[2, i] - (x0 * a1 - x1 * a0)


GATHER_MAX = 8  # sites: up to this many, positions are read from Pinocchio's frames (~1.4 us each)


def _site_set(mech, ws, sites):
    """(frame ids, DOF support (K,nv), joint ids, offsets) of a list of sites, cached per list in ws."""
    key = ("sites", *sites)
    hit = ws.cache.get(key)
    if hit is None:
        idx = list(sites)
        hit = ws.cache[key] = ([int(mech.site_fid[s]) for s in sites],
                                      np.ascontiguousarray(mech.site_support[idx]),
                                      np.ascontiguousarray(np.asarray(mech.site_jid)[idx], dtype=np.int64),
                                      np.ascontiguousarray(mech.site_local[idx], dtype=float))
    return hit


def site_jacobians(mech, ws, sites, q=None):
    """(X (K,3), J (K,3,nv)) for the listed sites. Needs joint Jacobians in ws.data
    (computeJointJacobians) at q. Positions: from Pinocchio's frame placements for a few sites; with q
    given and more than GATHER_MAX sites, from one compiled forward-kinematics pass
    (tree_kinematics.Context.site_positions_at; same numbers to round-off) instead of one frame read per
    site."""
    data = ws.data
    if not len(sites):  # the frame placements as with sites (forces.frame_jacobian reads them), no empty kernel call
        pin.updateFramePlacements(mech.model, data)
        return np.zeros((0, 3)), np.zeros((0, 3, mech.nv))
    fids, support, jid, local = _site_set(mech, ws, sites)
    if q is not None and len(sites) > GATHER_MAX:
        X = ws.tree.site_positions_at(q, jid, local)
    else:
        pin.updateFramePlacements(mech.model, data)
        oMf, loc = data.oMf, mech.site_local
        X = np.array([oMf[f].translation if f >= 0 else loc[s] for f, s in zip(fids, sites)]).reshape(len(sites), 3)
    return X, _point_jacobians(data.J.reshape(6, mech.nv), X, support)


def compute(mech, ws, q, v, extra_sites=()) -> Kinematics:
    """All quantities of the current configuration the step needs (one Pinocchio pass + frames), in the
    workspace's pin.Data."""
    nv = mech.nv
    data = ws.data
    pin.computeAllTerms(mech.model, data, q, v)
    sites, row = mech.jac_sites, mech.jac_row
    if extra_sites:
        key = ("extra", *extra_sites)
        hit = ws.cache.get(key)
        if hit is None:
            s2 = sites + [s for s in dict.fromkeys(extra_sites) if s not in mech.jac_row]
            hit = ws.cache[key] = (s2, {s: k for k, s in enumerate(s2)})
        sites, row = hit
    X, J = site_jacobians(mech, ws, sites, q)
    return Kinematics(M=data.M.reshape(nv, nv), nle=data.nle.reshape(nv), sites=sites, row=row, X=X, J=J, v=v)


def frame_jacobian(mech, data, fid):
    """(position (3,), linear Jacobian (3,nv), angular Jacobian (3,nv), rotation (3,3)) of a frame."""
    Jf = pin.getFrameJacobian(mech.model, data, fid, LWA).reshape(6, mech.nv)
    M = data.oMf[fid]
    return M.translation, Jf[:3], Jf[3:], M.rotation
