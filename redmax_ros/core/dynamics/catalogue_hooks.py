"""Runtime of the RedMax catalogue features in a step (hooks called from stepper/forces/constraints/energy).

A Mechanism whose scene uses any of them gets ``mech.extras``, an :class:`Extras` built and checked at
compile time (:func:`attach`) and never changed afterwards; each step workspace holds its own
:meth:`Extras.runtime` copy (``ws.extras``: the joint maps' state, the time of the explicit loads, a
``pin.Data`` for the momentum projection) and the hooks below run on that copy with the workspace's
live J_rR ``ws.T``. Without catalogue features ``mech.extras is None`` and the step pays one ``is None``
test per hook.

* **Mapped joints** (joint_maps.py): J_rR rows of the carriers refreshed at the start of the step,
  the Jdot_rR qdot_R term of Eq. 2.89 in the RHS, coordinates integrated / carriers re-synchronised,
  exponential coordinates reparameterised and Euler charts switched (Eq. 2.40) at the end.
* **Linear equality constraints between joint coordinates** (notes §2.9, reduced constraints G_r,
  Eq. 2.107-2.108): sum_i c_i q_i = value as constant velocity rows G_r qdot_r = 0 in the KKT system,
  alone or with the loop rows. For coordinates that integrate linearly (q+ = q + h qdot) the
  constraint is then kept to round-off without any stabilization; loop post-stabilization (which
  moves the joints along the loop rows only) is followed by a joint projection onto both the loop
  manifold and the linear constraints (least-norm Gauss-Newton, tolerance 1e-12).
* **Momentum projection** (opt-in, ``conserve_momentum: true`` on a ``free3d`` root joint): the
  linearly implicit step of Eq. (2) evaluates the gyroscopic (Coriolis) term explicitly and updates
  the rotation with exp(h w+), so a tumbling body's world angular momentum drifts by O(h^2) per step
  (the world linear momentum of a free3d joint is exact already: its linear velocity is the world
  velocity of the joint origin). With the option, after each step the hyper-reduced velocity of the
  root's subtree is corrected by the least change in the kinetic-energy metric that makes the
  subtree's spatial momentum about the world origin equal to its value before the step plus the
  step's external impulse, J_s^-T [M (qdot+ - qdot) + h C]_root (C: Coriolis/centrifugal forces; the
  root rows of Eq. 2 minus its internal terms). In zero gravity without loads this is exact
  conservation (to round-off) of linear and angular momentum; the correction is O(h^2), so the step
  stays first-order accurate. It is a post-step velocity projection (like the loop
  post-stabilization), not part of the paper's integrator, hence opt-in.
* **Force elements**: spring-damper along a fixed world direction (implicit: K = k d d^T,
  D = c d d^T, projected by the site Jacobians as the point springs of forces.py); world wrench and
  joint torque given by time functions (explicit, evaluated at t_k).
"""
from __future__ import annotations

import copy

import numpy as np
import pinocchio as pin

from redmax_ros.core.errors import SceneError
from redmax_ros.core.geometry.joints import q_index
from redmax_ros.core.dynamics.forces import add_geometric_stiffness, coriolis_jacobian
from redmax_ros.core.dynamics.kinematics import frame_jacobian, site_positions
from redmax_ros.core.dynamics.stabilization import TOL as LOOP_TOL
from redmax_ros.core.dynamics.stabilization import loop_residual
from redmax_ros.core.dynamics.tree_kinematics import Context

TOL = 1e-12  # linear joint constraints [coordinate units]


class Extras:
    def __init__(self, mech, maps, cat):
        self.maps = maps
        self.t = 0.0
        self.jdot_qdot = None  # Jdot_rR qdot_R (Pinocchio velocity space) of the current step's forces, or None
        model, nv = mech.model, mech.nv
        src = mech.spec.source
        # -- linear constraints: rows over Pinocchio velocity DOFs, their configuration indices
        self.lin_names, rows, self.lin_value, qidx = [], [], [], []
        self._lin_value_given = []
        for c in (cat.constraints if cat else []):
            row = np.zeros(nv)
            for jn, dof, coef in c.terms:
                if jn not in mech.joint_index:
                    raise SceneError(src, f"constraints '{c.name}'", f"unknown joint '{jn}'")
                ji = mech.joint_index[jn]
                if maps is not None and any(m.spec.name == jn for m in maps.euler):
                    raise SceneError(src, f"constraints '{c.name}'", f"joint '{jn}' switches Euler charts: its "
                                     "angles jump at a switch and cannot be constrained")
                if not 0 <= dof < ji.nv or q_index(model, ji.idx_v + dof) is None:
                    raise SceneError(src, f"constraints '{c.name}'", f"DOF {dof} of joint '{jn}' is not a coordinate")
                row[ji.idx_v + dof] += coef
            rows.append(row)
            self.lin_names.append(c.name)
            self.lin_value.append(c.value)
        self.G_lin = np.array(rows).reshape(-1, nv)
        self.lin_q = np.array([q_index(model, d) if d is not None else -1 for d in range(nv)]) if rows else None
        self.lin_cols = np.flatnonzero(np.any(self.G_lin != 0, axis=0)) if rows else np.zeros(0, int)
        # -- timed joint torques
        self.torques = []
        for tq in (cat.torques if cat else []):
            if tq.joint not in mech.joint_index:
                raise SceneError(src, f"forces '{tq.name}'", f"unknown joint '{tq.joint}'")
            ji = mech.joint_index[tq.joint]
            if ji.nv != len(tq.torque):
                raise SceneError(src, f"forces '{tq.name}'", f"joint '{tq.joint}' has {ji.nv} DOF(s)")
            self.torques.append((ji.idx_v, tq.torque))
        # -- timed wrenches
        bidx = {n: i for i, n in enumerate(mech.bodies)}
        self.wrenches = []
        for w in (cat.wrenches if cat else []):
            fid = mech.body_com_fid[bidx[w.body]] if w.site is None else mech.site_fid[mech.site_index[w.site]]
            self.wrenches.append((fid, mech.body_com_fid[bidx[w.body]], w.force, w.torque))
        # -- direction springs
        ds = cat.direction_springs if cat else []
        self.ds_names = [s.name for s in ds]
        self.ds_ab = np.array([[mech.site_index[s.a], mech.site_index[s.b]] for s in ds], dtype=int).reshape(-1, 2)
        self.ds_dir = np.array([s.direction for s in ds]).reshape(-1, 3)
        self.ds_k = np.array([s.stiffness for s in ds])
        self.ds_c = np.array([s.damping for s in ds])
        self.ds_rest = np.array([np.nan if s.rest is None else s.rest for s in ds])
        self.ds_implicit = np.array([s.implicit for s in ds], dtype=bool)
        # -- momentum projection roots: (joint id, root velocity slice, subtree joint ids)
        self.momentum_roots = []
        for js in mech.spec.joints:
            if _projects_momentum(mech.spec, js):
                ji = mech.joint_index[js.name]
                sub = [k for k in range(1, model.njoints) if _descends(model, k, ji.jid)]
                self.momentum_roots.append((ji.jid, slice(ji.idx_v, ji.idx_v + ji.nv), sub))
        self._mdata = None  # pin.Data of the momentum projection (runtime copies only)
        self.q0 = None  # the initial configuration after prepare()

    @property
    def has_rows(self) -> bool:
        return len(self.G_lin) > 0

    # ------------------------------------------------------------------------------------------
    # compile time
    def runtime(self, mech):
        """This Extras' copy for one step workspace: its own joint-map state and momentum pin.Data; the
        compiled constants are shared (never written after compile)."""
        rt = copy.copy(self)
        rt.maps = copy.deepcopy(self.maps)
        rt._mdata = mech.model.createData() if self.momentum_roots else None
        rt.t = 0.0
        rt.jdot_qdot = None
        return rt

    def prepare(self, mech):
        """At compile: carriers on their joints, default constraint values, initial projection. Sets
        ``self.q0`` and writes J_rR at q0 into ``mech.T`` (the compile-time array)."""
        ws = _CompileWork(mech)
        q = mech.q0.copy()
        if self.maps is not None:
            self.maps.sync(q)
        if self.has_rows:
            val = self.G_lin[:, self.lin_cols] @ q[self.lin_q[self.lin_cols]]
            self.lin_value = np.array([val[i] if v is None else v for i, v in enumerate(self.lin_value)])
        if len(self.ds_ab):
            data = mech.model.createData()
            pin.forwardKinematics(mech.model, data, q)
            X = site_positions(mech, data)
            s = np.einsum("pi,pi->p", X[self.ds_ab[:, 0]] - X[self.ds_ab[:, 1]], self.ds_dir)
            self.ds_rest = np.where(np.isnan(self.ds_rest), s, self.ds_rest)
        if self.has_rows or (self.maps is not None and len(mech.loop_ab)):
            q, err = self.project(mech, ws, q, (), max_iter=100)
            if err > 1e-9:
                raise SceneError(mech.spec.source, "constraints",
                                 f"cannot satisfy the linear joint constraints (and loops) from the initial "
                                 f"configuration (residual {err:.3g}); check q0 and the constraint values")
            if self.has_rows:
                self._check_rank(mech, ws, q)
        self.q0 = q
        if self.maps is not None:
            self.maps.refresh(mech.T, q)
            self.maps.fill_velocity(q)

    def _check_rank(self, mech, ws, q):
        G = self.G_lin if ws.T is None else self.G_lin @ ws.T
        if len(mech.loop_ab):
            G = np.vstack([loop_residual(ws.tree, q)[1], G])
        sv = np.linalg.svd(G, compute_uv=False)
        if np.sum(sv > 1e-9 * max(sv[0], 1e-300)) < len(G):
            raise SceneError(mech.spec.source, "constraints", "the linear joint constraints are redundant "
                             f"or conflicting ({', '.join(self.lin_names)}), with each other or with the loops; "
                             "remove the dependent ones")

    # ------------------------------------------------------------------------------------------
    # state hooks
    def at_state(self, ws, q, t=0.0):
        """Make the configuration-dependent parts of the workspace those of configuration q at time t
        (called by Simulator.reset/set_state): J_rR = ws.T of the mapped joints (Eq. 2.88) is refreshed in
        place at q, so that ws.to_reduced and everything else reading T between steps sees the state's
        J_rR, not that of the last stepped configuration."""
        self.t = t
        if self.maps is not None:
            self.maps.refresh(ws.T, q)

    # ------------------------------------------------------------------------------------------
    # step hooks
    def begin(self, mech, ws, state):
        """Start of a step: time of the explicit loads; J_rR at the current coordinates."""
        self.t = state.t
        if self.maps is not None:
            self.maps.refresh(ws.T, state.q)
        if self.momentum_roots:
            self._before = self._momentum_state(mech, ws, state.q, ws.to_reduced(state.v))

    def forces(self, mech, ws, kin, q, v_r, h, A, f):
        """Add to the (Pinocchio-space, before the J_rR projection) LHS A and force f of Eq. (2)."""
        if self.maps is not None:  # quadratic velocity term of the configuration-dependent J_rR (Eq. 2.89)
            self.jdot_qdot = self.maps.bias(q, v_r, mech.nv)  # kept for the BISP joint reactions (friction)
            f -= kin.M @ self.jdot_qdot
        t = self.t
        for i0, fns in self.torques:
            for k, fn in enumerate(fns):
                f[i0 + k] += fn(t)
        for fid, com_fid, ff, ft in self.wrenches:
            F = np.array([fn(t) for fn in ff])
            Tq = np.array([fn(t) for fn in ft])
            _, Jc, Jw, _ = frame_jacobian(mech, ws.data, fid)
            f += Jc.T @ F + Jw.T @ Tq
        if len(self.ds_ab):
            ends = []  # (x_a, x_b, f_a) of the implicit ones: the lever-arm blocks of their full K_m
            for (a, b), d, k, c, L0, imp in zip(self.ds_ab, self.ds_dir, self.ds_k, self.ds_c, self.ds_rest,
                                                self.ds_implicit):
                xa, Ja = _site(mech, ws.data, a)
                xb, Jb = _site(mech, ws.data, b)
                Jd = d @ (Ja - Jb)  # (nv,)
                s = float(d @ (xa - xb))
                if imp:  # K = k d d^T, D = c d d^T through the site Jacobians (Eq. 2)
                    A += (h * c + h * h * k) * np.outer(Jd, Jd)
                    f += Jd * (-k * (s - L0))
                    ends.append((xa, xb, -k * (s - L0) * d))
                else:  # implicit: false: the whole force at step k, nothing on the LHS (notes §1.9)
                    f += Jd * (-k * (s - L0) - c * float(Jd @ v_r))
            if ends and mech.spring_geometric:
                imp = self.ds_implicit
                add_geometric_stiffness(ws, A, mech.site_jid[self.ds_ab[imp, 0]], [e[0] for e in ends],
                                        mech.site_jid[self.ds_ab[imp, 1]], [e[1] for e in ends],
                                        [e[2] for e in ends], None, h * h)

    def rows(self, ws):
        """Bilateral rows of the linear constraints in hyper-reduced coordinates (rhs 0)."""
        G = self.G_lin if ws.T is None else self.G_lin @ ws.T
        return G, np.zeros(len(G)), [(f"constraint '{n}'", 1) for n in self.lin_names]

    def end(self, mech, ws, q_new, vR, hold_dofs=(), h=None):
        """End of a step: reparameterise, re-synchronise carriers, project onto the linear constraints
        (with the loops). Returns (q, vR, v_r) with v_r = J_rR(q) vR."""
        vR = vR.copy()
        if self.momentum_roots:
            targets = self._momentum_targets(ws.to_reduced(vR), h)
        if self.maps is not None:
            self.maps.reparameterize(q_new, vR, ws.T)
            self.maps.sync(q_new)
            if self.maps.euler:  # spherical_euler chart switching (Eq. 2.40; euler_charts.py)
                self.maps.switch_charts(q_new, vR, ws.T)
        if self.has_rows or (self.maps is not None and len(mech.loop_ab)):
            if self._needs_projection(mech, ws, q_new):
                q_new, _ = self.project(mech, ws, q_new, hold_dofs)
        if self.maps is not None:
            self.maps.refresh(ws.T, q_new)
        if self.momentum_roots:
            vR = self._project_momentum(mech, ws, q_new, vR, targets)
        return q_new, vR, ws.to_reduced(vR)

    # ------------------------------------------------------------------------------------------
    # momentum projection (free3d roots with conserve_momentum)
    def _momentum_state(self, mech, ws, q, v_r):
        """At the start of the step: per root (H_O (6,), J_s^-T (6,6)), plus M and C (Pinocchio space)."""
        model, d = mech.model, self._mdata
        M = pin.crba(model, d, q).copy()
        M = np.triu(M) + np.triu(M, 1).T
        C = pin.nonLinearEffects(model, d, q, v_r) - pin.computeGeneralizedGravity(model, d, q)
        self._Kv = None
        if mech.coriolis_implicit:  # the step's Coriolis force is C + K_v (qdot+ - qdot) (forces.assemble)
            self._Kv = coriolis_jacobian(mech, ws, q, v_r)
        pin.computeJointJacobians(model, d, q)
        roots = []
        for jid, sl, sub in self.momentum_roots:
            Js = pin.getJointJacobian(model, d, jid, pin.ReferenceFrame.WORLD)[:, sl]
            roots.append((self._subtree_map(mech, d, sub) @ v_r, np.linalg.inv(Js).T))
        return M, C, v_r.copy(), roots

    def _momentum_targets(self, v_r_new, h):
        M, C, v_r, roots = self._before
        imp = M @ (v_r_new - v_r) + h * C  # external generalized impulse of the step (root rows)
        if self._Kv is not None:  # integrator.coriolis: implicit
            imp += h * (self._Kv @ (v_r_new - v_r))
        return [H + JsiT @ imp[sl] for (H, JsiT), (_, sl, _) in zip(roots, self.momentum_roots)]

    def _subtree_map(self, mech, d, sub):
        """A (6, nv): spatial momentum (linear; angular about the world origin, world frame) of the bodies
        on the joints ``sub`` (needs computeJointJacobians at the configuration)."""
        model = mech.model
        A = np.zeros((6, mech.nv))
        for k in sub:
            Iw = d.oMi[k].act(model.inertias[k]).matrix()
            A += Iw @ pin.getJointJacobian(model, d, k, pin.ReferenceFrame.WORLD)
        return A

    def _project_momentum(self, mech, ws, q, vR, targets):
        model, d = mech.model, self._mdata
        T = ws.T if ws.T is not None else np.eye(mech.nv)
        M = pin.crba(model, d, q)
        M = np.triu(M) + np.triu(M, 1).T
        MR = T.T @ M @ T
        pin.computeJointJacobians(model, d, q)
        A = np.vstack([self._subtree_map(mech, d, sub) @ T for _, _, sub in self.momentum_roots])
        r = np.concatenate(targets) - A @ vR
        Y = np.linalg.solve(MR, A.T)
        return vR + Y @ np.linalg.solve(A @ Y, r)

    def energy(self, X) -> float:
        """Energy of the direction springs [J] from the world positions X (S,3) of all sites."""
        if not len(self.ds_ab):
            return 0.0
        e = 0.0
        for (a, b), d, k, L0 in zip(self.ds_ab, self.ds_dir, self.ds_k, self.ds_rest):
            s = float(d @ (X[a] - X[b]))
            e += 0.5 * k * (s - L0) ** 2
        return e

    # ------------------------------------------------------------------------------------------
    # projection onto loops + linear constraints
    def lin_residual(self, q) -> np.ndarray:
        if not self.has_rows:
            return np.zeros(0)
        return self.G_lin[:, self.lin_cols] @ q[self.lin_q[self.lin_cols]] - self.lin_value

    def _needs_projection(self, mech, ws, q):
        r = self.lin_residual(q)
        if len(r) and float(np.abs(r).max()) > TOL:
            return True
        if len(mech.loop_ab):
            return ws.tree.loop_phi_at(q)[1] > LOOP_TOL
        return False

    def project(self, mech, ws, q, hold_dofs=(), tol=TOL, max_iter=10):
        """Least-norm Gauss-Newton onto {loops closed, G_lin q = value}, keeping ``hold_dofs`` fixed."""
        nd = mech.ndof
        hold = np.zeros((len(hold_dofs), nd))
        hold[np.arange(len(hold_dofs)), list(hold_dofs)] = 1.0
        err = np.inf
        for _ in range(max_iter + 1):
            if self.maps is not None:
                self.maps.refresh(ws.T, q)
            res, Gs = [], []
            if len(mech.loop_ab):
                phi, G = loop_residual(ws.tree, q)
                res.append(phi)
                Gs.append(G)
            if self.has_rows:
                res.append(self.lin_residual(q))
                Gs.append(self.G_lin @ ws.T if ws.T is not None else self.G_lin)
            r = np.concatenate(res) if res else np.zeros(0)
            err = float(np.abs(r).max()) if len(r) else 0.0
            if err < tol:
                break
            if len(res) == 2 and float(np.abs(res[1]).max()) < TOL and float(np.abs(res[0]).max()) < LOOP_TOL:
                break
            K = np.vstack(Gs + [hold])
            rhs = np.concatenate([-r, np.zeros(len(hold))])
            dq, *_ = np.linalg.lstsq(K, rhs, rcond=None)
            q = pin.integrate(mech.model, q, ws.to_reduced(dq))
            if self.maps is not None:
                self.maps.sync(q)
        return q, err


def _descends(model, k, root):
    while k > 0:
        if k == root:
            return True
        k = int(model.parents[k])
    return False


def _site(mech, data, s):
    """(position, point Jacobian (3,nv)) of site s (world sites: fixed point, zero Jacobian)."""
    fid = mech.site_fid[s]
    if fid < 0:
        return mech.site_local[s], np.zeros((3, mech.nv))
    x, Jc, _, _ = frame_jacobian(mech, data, fid)
    return x.copy(), Jc


def _projects_momentum(spec, js) -> bool:
    """Whether joint ``js`` is a root of this module's momentum projection: conserve_momentum, and no
    deformables (with them the projection is of the whole system: dynamics/momentum.py)."""
    return bool(js.extra.get("conserve_momentum")) and not getattr(spec, "deformables", None)


def attach(mech, maps):
    """The Extras of a mechanism whose scene uses catalogue features, prepared (``extras.q0``), or None
    (called by step.compile.compile_scene)."""
    cat = mech.spec.catalogue
    if maps is None and cat is None and not any(_projects_momentum(mech.spec, js) for js in mech.spec.joints):
        return None
    extras = Extras(mech, maps, cat)
    extras.prepare(mech)
    return extras


class _CompileWork:
    """The few workspace parts Extras.prepare needs at compile time: the compile-time J_rR (written in
    place), a pin.Data and a recursive kinematics Context."""

    def __init__(self, mech):
        self.T = mech.T
        self.data = mech.model.createData()
        self.tree = Context(mech, self.T)

    def to_reduced(self, vR):
        return vR if self.T is None else self.T @ vR
