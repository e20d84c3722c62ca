"""Body-twist prescriptions (maximal hybrid dynamics, Eq. 7 with *G_m on one body's six maximal DOFs).

A prescription selects components of the twist phi = [omega; v] of a body frame (angular first, then
the linear velocity of the body origin), in the body frame ('body') or with world-aligned axes
('world', Pinocchio's LOCAL_WORLD_ALIGNED): rows P J_b qdot_r = g with J_b the body's 6 x nv twist
Jacobian and P the selected rows of I6. The required wrench [torque N m; force N] in the prescription's
frame is P^T (-lam / h) (StepResult.body_wrenches). Pinocchio pipeline only: the data-free backends
(solver 'pcg', or 'direct' beyond pin.Data's size) reject them. Components given as time functions
(scene/body_twist.py) are evaluated at the step's end time t_k+1 by :func:`resolve`, before the rows.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin

from redmax_ros.core.scene.body_twist import FRAMES, BodyTwist, parse  # noqa: F401  (re-exported)

_LOCAL = pin.ReferenceFrame.LOCAL


def resolve(cmd, t_next: float):
    """Commands with every timed body-twist component evaluated at t_next = t_k+1 [s] (a new Commands;
    ``cmd`` itself when no component is timed)."""
    if not any(bt.timed for bt in cmd.body_twists.values()):
        return cmd
    return dataclasses.replace(cmd, body_twists={n: bt.at(t_next) for n, bt in cmd.body_twists.items()})


def twist_jacobian(mech, data, name: str, frame: str) -> np.ndarray:
    """(6,nv) [angular; linear] twist Jacobian of body ``name``'s frame (needs the joint Jacobians and
    forward kinematics in ``data``, e.g. pin.computeAllTerms)."""
    i = mech.bodies.index(name)
    jid, M = int(mech.body_jid[i]), mech.body_placement[i]
    Jj = pin.getJointJacobian(mech.model, data, jid, _LOCAL).reshape(6, mech.nv)  # joint frame, [linear; angular]
    Jb = M.toActionMatrixInverse() @ Jj  # body frame
    J = np.vstack([Jb[3:], Jb[:3]])
    if frame == "world":
        R = data.oMi[jid].rotation @ M.rotation
        J = np.vstack([R @ J[:3], R @ J[3:]])
    return J


def append_rows(mech, ws, data, cons, body_twists: dict) -> dict:
    """Append the rows of every prescribed body to ``cons`` (hyper-reduced via ws.T); returns body -> slice."""
    T = ws.T
    G, g, spans, out = [cons.G], [cons.g], list(cons.label_spans), {}
    r = cons.m
    for name, bt in body_twists.items():
        rows = bt.P @ twist_jacobian(mech, data, name, bt.frame)
        G.append(rows if T is None else rows @ T)
        g.append(bt.g)
        spans.append((f"prescribed body '{name}'", len(bt.g)))
        out[name] = slice(r, r + len(bt.g))
        r += len(bt.g)
    cons.G, cons.g, cons.label_spans = np.vstack(G), np.concatenate(g), spans
    return out


def wrenches(lam, body_rows: dict, body_twists: dict, h: float) -> dict:
    """Required wrench (6,) [torque; force] of every prescribed body in its prescription's frame."""
    return {n: body_twists[n].P.T @ (lam[sl] * (-1.0 / h)) for n, sl in body_rows.items()}
