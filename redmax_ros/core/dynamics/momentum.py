"""Spatial momentum of a free system (an articulated skeleton on one ``free`` root joint and the point masses
of its deformables), and the momentum projection of the step with deformables (issue 15 point 5).

Momenta are world-frame 6-vectors (linear [kg m/s]; angular about the world origin [kg m^2/s]), inertias
6 x 6 in Pinocchio's order (linear first): a rigid twist (v_O, w) of the whole system, v(p) = v_O + w x p,
has momentum ``locked_inertia @ (v_O, w)``.

Why a projection. The linearly implicit Euler step of Eq. (2) (Wang et al. 2019; the equation after Eq. 5
for the deformable DOFs) changes an isolated system's angular momentum by O(h^2) a step: for the mesh
h^2 sum_i v_i+ x f_i (the elastic force linearised at x_k, with co-rotation: sum_i x_i x K v = -sum_i v x f),
for a spinning skeleton its explicit gyroscopic term and the manifold update. With ``conserve_momentum:
true`` on the skeleton's ``free`` root joint, after each step the velocities get the least change in the
kinetic-energy metric that puts the momentum at its exact balance (:func:`target`). The momentum map of the
system is Phi^T M with Phi the rigid-twist field, so that least change M^-1 A^T lam is itself a rigid twist
of the whole system: a change of the root joint's velocity alone (every body moves with its root) and
v_i += v_O + w x x_i for every vertex. A rigid twist keeps every attachment row and loop closure (they
are invariant under rigid motions of the whole system). The correction is O(h^2), so the step stays first
order; it is a post-step velocity projection (Hairer, Lubich, Wanner, Geometric Numerical Integration,
§IV.4, projection onto the invariant), not part of the paper's integrator, hence opt-in. The catalogue's
``free3d`` joints have the same option on the skeleton alone (catalogue_hooks.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from redmax_ros.core.errors import SceneError, StepError


def skeleton_momentum(model, data, q, v) -> tuple:
    """(momentum (6,), locked inertia (6,6)) of every body of ``model`` at (q, v) (reduced velocity), world
    frame, angular part about the world origin: Pinocchio's centroidal ones (pin.ccrba, about the centre of
    mass) moved to the origin."""
    pin.ccrba(model, data, q, v)
    to_origin = pin.SE3(np.eye(3), data.com[0].copy())
    return to_origin.act(data.hg).vector, to_origin.act(data.Ig).matrix()


def com_of(inertia) -> np.ndarray:
    """Centre of mass [m] of a locked inertia about the origin (its lower-left block is M [c])."""
    return np.array([inertia[5, 1], inertia[3, 2], inertia[4, 0]]) / inertia[0, 0]


def target(h0, inertia0, gravity, dt) -> np.ndarray:
    """The momentum an isolated system under uniform gravity g has dt after it had h0 with locked inertia
    inertia0 (mass M, centre c): P + dt M g, and L_O + dt M c x g + dt^2/2 P x g (the centre moves as
    c + t P/M + t^2 g/2, so the gravity torque about the origin integrates exactly). Zero gravity: h0."""
    M = inertia0[0, 0]
    P, L = h0[:3], h0[3:]
    g = np.asarray(gravity, float)
    c = com_of(inertia0)
    return np.concatenate([P + dt * M * g, L + dt * M * np.cross(c, g) + 0.5 * dt * dt * np.cross(P, g)])


@dataclass(frozen=True)
class FreeRoot:
    """The root joint whose velocity takes the correction: Pinocchio joint id, its reduced velocity slice and
    the hyper-reduced columns equal to it (J_rR is the identity on them)."""
    name: str
    jid: int
    rows: slice
    cols: np.ndarray


class MomentumProjection:
    """The projection of a free skeleton with deformables (module docstring); its own pin.Data."""

    def __init__(self, model, root: FreeRoot, dm):
        self.model, self.root, self.dm = model, root, dm  # dm: deformable.system.Deformables
        self.data = model.createData()

    def check_inputs(self, cmd, tau) -> None:
        """StepError for this step's commands that act from outside the system: prescribed sites, site forces,
        a prescribed root joint or a torque on it (step.state.Commands; tau the applied joint torques)."""
        name = self.root.name
        why = ("prescribed sites" if cmd.site_velocities else "site forces" if cmd.site_forces else
               f"the prescribed root joint '{name}'" if name in cmd.joint_velocities or name in cmd.joint_trajectories
               else f"a torque on the root joint '{name}'" if np.any(tau[self.root.rows] != 0.0) else None)
        if why:
            raise StepError(f"conserve_momentum (joint '{name}'): {why} act from outside the system; the momentum "
                            f"projection balances gravity only")

    def momentum(self, q, v_r, x, v) -> tuple:
        """(momentum (6,), locked inertia (6,6)) of skeleton and vertices."""
        h, inertia = skeleton_momentum(self.model, self.data, q, v_r)
        return h + np.concatenate(self.dm.momentum(x, v)), inertia + self.dm.locked_inertia(x)

    def project(self, before, dt, q, v_hyper, v_r, x, v) -> tuple:
        """The corrected (hyper-reduced velocity, reduced velocity, vertex velocities (N,3)) at (q, x) whose
        momentum is the :func:`target` of ``before`` ((momentum, locked inertia) at the step's start, of
        :meth:`momentum`) after dt, and the twist (v_O, w) added. Inputs are not modified."""
        h, inertia = self.momentum(q, v_r, x, v)
        twist = np.linalg.solve(inertia, target(*before, self.dm.gravity, dt) - h)
        local = self.data.oMi[self.root.jid].actInv(pin.Motion(twist)).vector  # root joint frame
        v_hyper, v_r = v_hyper.copy(), v_r.copy()
        v_hyper[self.root.cols] += local
        v_r[self.root.rows] += local
        return v_hyper, v_r, v + (twist[:3] + np.cross(twist[3:], x)), twist


def build(mech, dm) -> MomentumProjection | None:
    """The projection of a scene with deformables ``dm`` (deformable.system.Deformables) whose ``free`` root
    joint has ``conserve_momentum: true``, or None. Raises SceneError when something in the scene acts from
    outside the system (the momentum balance of :func:`target` has gravity only): a floor, a world
    attachment, mass-proportional Rayleigh damping (alpha), body damping, world wrenches, springs or loop
    closures to world points, a second tree, couplings of the root, or a spring, damper or torque on the
    root joint."""
    roots = [js for js in mech.spec.joints if js.extra.get("conserve_momentum")]
    if not roots:
        return None
    js = roots[0]
    src, entry = mech.spec.source, f"joints.{js.name}.conserve_momentum"

    def no(why):
        raise SceneError(src, entry, f"the momentum projection needs an isolated system (gravity only): {why}")

    if js.type != "free":
        no(f"with deformables it takes a 'free' root joint, not {js.type}")
    ji = mech.joint_index[js.name]
    model = mech.model
    others = [k for k in range(1, model.njoints) if k != ji.jid and model.parents[k] == 0]
    if others:
        no(f"joint '{model.names[others[0]]}' is a second tree on the world")
    rows = slice(ji.idx_v, ji.idx_v + ji.nv)
    if mech.T is None:
        cols = np.arange(ji.idx_v, ji.idx_v + ji.nv)
    else:
        cols = np.flatnonzero(np.any(mech.T[rows] != 0.0, axis=0))
        if (len(cols) != ji.nv or not np.array_equal(mech.T[rows][:, cols], np.eye(ji.nv))
                or np.any(np.delete(mech.T, np.arange(ji.idx_v, ji.idx_v + ji.nv), axis=0)[:, cols])):
            no(f"root joint '{js.name}' is coupled to other joints")
    if any(np.any(a[rows] != 0.0) for a in (mech.stiffness, mech.damping, mech.torque0)):
        no(f"root joint '{js.name}' has a stiffness, damping or torque against the world")
    if dm.floor is not None:
        no("a deformable touches the floor")
    if np.any(dm.attach.body < 0):
        no(f"{dm.attach.labels[int(np.flatnonzero(dm.attach.body < 0)[0])]} holds a vertex to the world")
    for name, e in zip(dm.names, dm.elements):
        if e.alpha != 0.0:
            no(f"deformables.{name} has mass-proportional Rayleigh damping (alpha)")
    if len(mech.damped_bodies):
        no(f"body '{mech.bodies[int(mech.damped_bodies[0])]}' has body damping")
    if len(mech.wrench_body):
        no("a world wrench acts on a body")
    for kind, names, ab in (("spring", mech.spring_names, mech.spring_ab), ("loop", mech.loop_names, mech.loop_ab)):
        for n, (a, b) in zip(names, np.asarray(ab, dtype=int).reshape(-1, 2)):
            if mech.site_jid[a] == 0 or mech.site_jid[b] == 0:
                no(f"{kind} '{n}' ends at a world point")
    return MomentumProjection(model, FreeRoot(js.name, ji.jid, rows, cols), dm)
