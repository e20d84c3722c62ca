"""World frames of chosen bodies at a configuration in one compiled call: the compiled step's placements
(stage 1, :func:`kinematics.placements_of`: every joint kind of the compiled path) and each body's placement
in its joint, R_b = R_j M_R, p_b = R_j M_p + p_j. The node's /tf is built from these at tf_rate; through
Pinocchio (forwardKinematics, then a numpy array of every oMi) the same poses cost ~80 us warm and 370-470 us
in the node's simulation thread (its caches cold after 20 steps and their messages), one call here ~2-5 us.
Equal to the core's ``Simulator.body_poses`` to round-off (test/core/compiled/test_poses.py).

Mechanisms with joints the compiled path does not take (:func:`takes_joints` is False: catalogue joints or a
joint kind outside model.SUPPORTED_KINDS) have no BodyFrames (:func:`body_frames` returns None); the caller
keeps its Pinocchio path for them."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.jit import drop_stale_caches, njit
from redmax_ros.core.step.compiled.kinematics import placements_of
from redmax_ros.core.step.compiled.manifold import joint_kinds
from redmax_ros.core.step.compiled.model import SUPPORTED_KINDS, build_model

# every file compiled into body_frames_into (placements_of inlines the kernels of these)
SOURCES = ("step/compiled/poses.py", "step/compiled/kinematics.py", "solvers/recursive.py",
           "dynamics/tree_kinematics.py", "jit.py")
drop_stale_caches("step/compiled/poses.py", SOURCES)


@njit
def body_frames_into(uni_joints, uni_a1, uni_a2, planar_joints, parents, kind, idx_q, idx_v, nv_j, axis, pitch,
                     place_R, place_p, site_jid, site_local, q, v, jR, jp, Sl, c_local, R, p, St, X, jid, MR, Mp,
                     P, Rb):
    """Placements at q (placements_of, into the scratch jR ... X; v zeros), then P[k] (3,) [m] and Rb[k] (3, 3)
    of body k: its joint jid[k]'s world placement composed with the body's placement (MR[k], Mp[k]) in it."""
    placements_of(uni_joints, uni_a1, uni_a2, planar_joints, parents, kind, idx_q, idx_v, nv_j, axis, pitch,
                  place_R, place_p, site_jid, site_local, q, False, v, jR, jp, Sl, c_local, R, p, St, X)
    for k in range(jid.shape[0]):
        j = jid[k]
        for a in range(3):
            P[k, a] = R[j, a, 0] * Mp[k, 0] + R[j, a, 1] * Mp[k, 1] + R[j, a, 2] * Mp[k, 2] + p[j, a]
            for b in range(3):
                Rb[k, a, b] = R[j, a, 0] * MR[k, 0, b] + R[j, a, 1] * MR[k, 1, b] + R[j, a, 2] * MR[k, 2, b]


class BodyFrames:
    """World frames of the bodies ``names`` of ``mech``: ``frames(q)`` -> (positions (n, 3) [m], rotation
    matrices (n, 3, 3)), arrays of this object's own (overwritten by the next call). Scratch of one caller
    (not thread-safe)."""

    def __init__(self, mech, names):
        idx = {b: i for i, b in enumerate(mech.bodies)}
        sel = [idx[n] for n in names]
        mv = build_model(mech).views
        nj, nv = len(mv["parents"]), mech.nv
        self._model = tuple(mv[k] for k in ("uni_joints", "uni_a1", "uni_a2", "planar_joints", "parents", "kind",
                                            "idx_q", "idx_v", "nv_j", "axis", "pitch", "place_R", "place_p",
                                            "site_jid", "site_local"))
        self._scratch = (np.zeros(nv), np.tile(np.eye(3), (nj, 1, 1)), np.zeros((nj, 3)), mv["Sl0"].copy(),
                         np.zeros((nj, 6)), np.tile(np.eye(3), (nj, 1, 1)), np.zeros((nj, 3)), np.zeros((nv, 6)),
                         np.zeros((len(mv["site_jid"]), 3)))
        self._body = (np.array([int(mech.body_jid[i]) for i in sel], dtype=np.int64),
                      np.array([mech.body_placement[i].rotation for i in sel], dtype=float).reshape(-1, 3, 3),
                      np.array([mech.body_placement[i].translation for i in sel], dtype=float).reshape(-1, 3))
        self.P = np.zeros((len(sel), 3))
        self.R = np.zeros((len(sel), 3, 3))
        self._nq = mech.nq

    def __call__(self, q) -> tuple:
        q = np.ascontiguousarray(q, dtype=float)
        if q.shape != (self._nq,):
            raise ValueError(f"configuration of length {q.shape} for a mechanism with nq = {self._nq}")
        body_frames_into(*self._model, q, *self._scratch, *self._body, self.P, self.R)
        return self.P, self.R


def takes_joints(mech) -> bool:
    """Whether the compiled kinematics cover every joint of ``mech`` (no catalogue joints, every joint kind in
    model.SUPPORTED_KINDS: what model.unsupported checks of the joints)."""
    return mech.extras is None and all(k in SUPPORTED_KINDS for k in joint_kinds(mech.model)[1:])


def body_frames(mech, names):
    """A :class:`BodyFrames` of ``names``, or None when ``mech`` has joints the compiled path does not take."""
    return BodyFrames(mech, names) if takes_joints(mech) else None
