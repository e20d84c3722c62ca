"""Joints Pinocchio cannot represent, as configuration-dependent hyper-reduced coordinates.

Pinocchio's joints are a closed set (a boost::variant compiled into the library; no joint can be
added from Python), so the spline curve/surface joints (notes §2.5.12-2.5.13), the
exponential-coordinate spherical joint (§2.5.8), the rotation-first free joint in exponential
coordinates (§2.5.11, Eq. 2.65-2.66, ``free3d_exp``) and the three-angle spherical joint whose chart changes
at run time (§2.5.5, Eq. 2.40, ``switch_charts: true``) cannot be Pinocchio joints. They are realised with
the notes' own tool for chaining Jacobians, hyper-reduced coordinates with a *configuration-
dependent* J_rR (§2.7, Eq. 2.88-2.90):

* the Pinocchio model carries a **carrier** joint that can reach every pose of the joint: a FreeFlyer
  for spline joints and ``free3d_exp`` (body twist (v, w), 6 DOF), a quaternion Spherical for ``spherical_exp`` (body
  angular velocity, 3 DOF); the child body hangs on the carrier;
* the joint's own coordinates g (spline parameter(s), or the exponential coordinates) are stored in
  a **coordinate** joint: a massless leaf (PX, Composite(PX, PY), Translation, or for the 6
  coordinates of ``free3d_exp`` Composite(Translation, Translation)) attached to the
  carrier, named like the scene joint, whose configuration *is* g and whose velocity is gdot; it has
  no inertia, so it adds nothing to the kinetic energy;
* the hyper-reduced velocity holds gdot once: J_rR maps it to the coordinate joint (identity rows)
  and to the carrier (rows S(g), the joint Jacobian of §2.5), so the carrier twist is S(g) gdot
  exactly; the quadratic velocity vector gets the extra term of Eq. 2.89,
  J_rR^T M (Jdot_rR qdot_R) with Jdot_rR qdot_R = Sdot(g, gdot) gdot on the carrier rows;
* after the configuration update the coordinates are integrated as in the notes
  (g+ = g + h gdot+, which pin.integrate does on the coordinate joint) and the carrier is set to
  exactly Q(g+), so the body never leaves the spline/sphere; ``spherical_exp`` coordinates (and the
  rotation coordinates g[:3] of ``free3d_exp``, whose translation is left as it is) are
  reparameterised when ||g|| > the joint's reparam_threshold (default pi; Grassia; joints.reparameterize_exp), which also maps gdot, and a
  switching ``spherical_euler`` joint changes chart when its rotation enters the home chart's
  singular band (euler_charts.select), with g from R and gdot mapped by Eq. 2.40. Its current chart
  is a function of the carrier's rotation, so it is recovered from any configuration (reset,
  set_state) and is set by :meth:`Maps.refresh`.

Cost (per mapped joint): 6 (or 3) carrier DOFs plus k coordinate DOFs in the Pinocchio model
instead of k, so CRBA/RNEA work on a slightly larger tree; the carrier rows of J_rR and the Sdot
term are recomputed every step (Alg. 3/4, a few 6x6 products); the LHS is projected by the dense
J_rR (T^T A T, as for couplings); the configuration is re-synchronised after each step. Only the
direct pipeline (pin.Data, forces.py) supports mapped joints.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from redmax_ros.core.geometry import euler_charts
from redmax_ros.core.geometry import joints as jt
from redmax_ros.core.scene.spec import JointSpec

I6 = pin.SE3.Identity()


ROTATION_TYPES = ("spherical_exp", "spherical_euler")  # mapped joints on a quaternion Spherical carrier
ANALYTIC_TYPES = ROTATION_TYPES + ("free3d_exp",)  # mapped joints whose Q, S, Sdot are closed forms (joints.py)


def is_mapped(j) -> bool:
    """Realised as a coordinate map: spline joints, spherical_exp, and spherical_euler with chart switching
    (``switch_charts: true``; euler_charts.py)."""
    return j.type in jt.MAPPED_TYPES or (j.type == "spherical_euler" and bool(j.extra.get("switch_charts")))


def carrier_name(name: str) -> str:
    """The Pinocchio name of the carrier joint of mapped joint ``name``."""
    return f"{name}/carrier"


def coordinate_count(jtype: str) -> int:
    return {"spherical_exp": 3, "spherical_euler": 3, "free3d_exp": 6, "spline_curve": 1, "spline_surface": 2}[jtype]


def carrier_model(jtype: str):
    return pin.JointModelSpherical() if jtype in ROTATION_TYPES else pin.JointModelFreeFlyer()


def coordinate_model(k: int):
    if k == 1:
        return pin.JointModelPX()
    if k == 2:
        return jt.composite([(pin.JointModelPX(), I6), (pin.JointModelPY(), I6)])
    if k == 6:
        return jt.composite([(pin.JointModelTranslation(), I6), (pin.JointModelTranslation(), I6)])
    return pin.JointModelTranslation()


def joint_kinematics(j, g, gd, chart=None):
    """(Q, S (6,k), Sdot (6,k)) of a mapped scene joint at coordinates g, rates gd (spherical_euler: in
    ``chart``, default its home chart)."""
    if j.type == "spherical_exp":
        return jt.ref_spherical_exp(g, gd)
    if j.type == "free3d_exp":
        return jt.ref_free3d_exp(g, gd)
    if j.type == "spherical_euler":
        return jt.ref_euler(chart or j.extra["chart"], g, gd)
    return j.extra["geometry"].kinematics(g, gd)


def carrier_configuration(jtype: str, Q: pin.SE3) -> np.ndarray:
    if jtype in ROTATION_TYPES:
        return pin.Quaternion(Q.rotation).coeffs().copy()
    return pin.SE3ToXYZQUAT(Q).copy()


def carrier_rows(jtype: str, S: np.ndarray) -> np.ndarray:
    """The carrier's velocity as a function of gdot: FreeFlyer takes the whole body twist, Spherical the
    angular part (the exponential-coordinate joint has no translation)."""
    return S[3:] if jtype in ROTATION_TYPES else S


def carrier_spec(j, nv):
    """Placeholder JointSpec of the carrier of mapped joint j (no forces, limits or initial velocity of
    its own: everything is set on the coordinate joint, which carries the scene joint's name)."""
    z = np.zeros(nv)
    return JointSpec(carrier_name(j.name), "carrier", j.parent, j.child, j.placement, j.body_placement,
                     np.zeros((0, 3)), np.zeros(0), z, np.full(nv, -np.inf), np.full(nv, np.inf), z, np.zeros(0),
                     z, z, z, {"nv": nv, "nq0": 0})


def add_to_model(model, parent_jid, j, jM):
    """Add catalogue joint ``j`` (joints.NATIVE_TYPES or MAPPED_TYPES) under ``parent_jid`` at ``jM``.

    Returns (jid the child body hangs on, [(spec, q0 part, rest part), ...] for each Pinocchio joint
    added, in order: one native joint, or the carrier then the coordinate joint)."""
    if not is_mapped(j):
        jid = model.addJoint(parent_jid, jt.pin_joint_model(j), jM, j.name)
        return jid, [(j, jt.configuration(j, j.q0), jt.configuration(j, j.rest))]
    k = coordinate_count(j.type)
    g0, grest = np.asarray(j.q0, float), np.asarray(j.rest, float)
    cm = carrier_model(j.type)
    cid = model.addJoint(parent_jid, cm, jM, carrier_name(j.name))
    Q0 = joint_kinematics(j, g0, np.zeros(k))[0]
    Qr = joint_kinematics(j, grest, np.zeros(k))[0]
    carrier = carrier_spec(j, cm.nv)
    model.addJoint(cid, coordinate_model(k), I6, j.name)
    return cid, [(carrier, carrier_configuration(j.type, Q0), carrier_configuration(j.type, Qr)),
                 (j, g0.copy(), grest.copy())]


@dataclass
class MappedJoint:
    spec: object  # the scene JointSpec
    k: int  # number of coordinates
    cq: slice  # carrier configuration / velocity indices (Pinocchio)
    cv: slice
    gq: slice  # coordinate-joint configuration / velocity indices
    gv: slice
    chart: str = ""  # spherical_euler with switching: the chart in use (a function of the rotation)
    _key: bytes = b""
    _val: tuple = ()

    def kin(self, q, vg=None):
        """(Q, S, Sdot) at the coordinates in q (Sdot for rates vg, zero if None). Spline evaluations are
        cached on g (the step evaluates the same g for J_rR and for the Jdot_rR term)."""
        g = q[self.gq]
        if self.spec.type in ANALYTIC_TYPES:
            return joint_kinematics(self.spec, g, np.zeros(self.k) if vg is None else vg, self.chart)
        key = g.tobytes()
        if self._key != key:
            self._key, self._val = key, self.spec.extra["geometry"].eval(g if self.k > 1 else g[0])
        Q, S, dS = self._val
        if vg is None:
            return Q, S, np.zeros_like(S)
        return Q, S, (dS * float(vg[0])) if self.k == 1 else dS @ np.asarray(vg, float)


class Maps:
    """Runtime of the mapped joints of one Mechanism (constant index data; T is updated in place)."""

    @classmethod
    def build(cls, model, joint_infos, jspecs, T, q0, v0r):
        """Maps of a compiled tree, or None when it has no mapped joint. Sets ``T0`` (J_rR at q0, carriers
        driven by their coordinates; T: the coupling matrix or None) and fills the carriers' rows of
        the initial reduced velocity v0r (in place) from the coordinate rates."""
        mapped = {js.name: js for js in jspecs if is_mapped(js)}
        if not mapped:
            return None
        maps = cls(model, joint_infos, mapped)
        maps.start_charts(q0, v0r)
        maps.T0 = maps.compose_T(T, model.nv)
        maps.refresh(maps.T0, q0)
        maps.v0r = v0r
        maps.fill_velocity(q0)
        return maps

    def fill_velocity(self, q):
        """Carrier rows of the initial reduced velocity (compile_scene's v0r, in place) at configuration q
        (again after the initial projection onto loops/constraints has moved q0)."""
        for m in self.items:
            _, S, _ = m.kin(q)
            self.v0r[m.cv] = carrier_rows(m.spec.type, S) @ self.v0r[m.gv]

    def __init__(self, model, joint_infos, specs_by_name):
        self.items = []
        info = {ji.name: ji for ji in joint_infos}
        for name, spec in specs_by_name.items():
            c, g = info[carrier_name(name)], info[name]
            self.items.append(MappedJoint(spec, g.nv, slice(c.idx_q, c.idx_q + c.nq), slice(c.idx_v, c.idx_v + c.nv),
                                          slice(g.idx_q, g.idx_q + g.nq), slice(g.idx_v, g.idx_v + g.nv)))
        self.carrier_dofs = sorted(d for m in self.items for d in range(m.cv.start, m.cv.stop))
        self.euler = [m for m in self.items if m.spec.type == "spherical_euler"]
        for m in self.euler:
            m.chart = m.spec.extra["chart"]

    # -- charts of spherical_euler joints with switching (euler_charts.py, Eq. 2.40)
    def start_charts(self, q0, v0r):
        """At compile: q0 (home-chart angles, carriers at Q(q0)) and v0r are rewritten in place into the
        chart the rotation selects (the partner when q0 is within MARGIN of the home chart's singularity)."""
        for m in self.euler:
            home = m.spec.extra["chart"]
            R, _ = euler_charts.rotation_jacobian(home, q0[m.gq])
            c = euler_charts.select(home, R)
            if c != home:
                q0[m.gq], v0r[m.gv] = euler_charts.convert(home, c, q0[m.gq], v0r[m.gv])
            m.chart = c
        self.sync(q0)

    def switch_charts(self, q, vR, T):
        """After the configuration update and sync: switch every joint whose rotation now selects another
        chart; angles from R (Table 3), rates by qdot_new = S_new^-1 S_old qdot_old (Eq. 2.40) through the
        coordinate columns of J_rR; the carrier is re-set to Q(q_new). Returns True if any switched."""
        changed = False
        for m in self.euler:
            c = euler_charts.select(m.spec.extra["chart"], pin.Quaternion(q[m.cq]).matrix())
            if c == m.chart:
                continue
            Tg = T[m.gv]
            cols = [int(np.flatnonzero(Tg[i])[0]) for i in range(m.k)]
            q[m.gq], vR[cols] = euler_charts.convert(m.chart, c, q[m.gq], Tg @ vR)
            m.chart = c
            Q, _, _ = m.kin(q)
            q[m.cq] = carrier_configuration(m.spec.type, Q)
            changed = True
        return changed

    # -- J_rR
    def compose_T(self, T, nv):
        """J_rR with the carrier DOFs driven by their coordinate joints: drop the carriers' own columns
        and fill their rows at the current coordinates with :meth:`refresh`."""
        T = np.eye(nv) if T is None else T.copy()
        keep = [c for c in range(T.shape[1]) if not np.any(T[self.carrier_dofs, c])]
        T = T[:, keep].copy()
        T[self.carrier_dofs] = 0.0
        return T

    def refresh(self, T, q):
        """Carrier rows of J_rR at configuration q: T[carrier] = S_c(g) T[coordinates]. The chart of a
        switching spherical_euler joint is first set from the carrier's rotation in q."""
        for m in self.euler:
            m.chart = euler_charts.select(m.spec.extra["chart"], pin.Quaternion(q[m.cq]).matrix())
        for m in self.items:
            _, S, _ = m.kin(q)
            T[m.cv] = carrier_rows(m.spec.type, S) @ T[m.gv]

    def bias(self, q, v_r, nv):
        """Jdot_rR qdot_R in Pinocchio velocity space: Sdot(g, gdot) gdot on the carrier rows (Eq. 2.89)."""
        out = np.zeros(nv)
        for m in self.items:
            gd = v_r[m.gv]
            _, _, Sd = m.kin(q, gd)
            out[m.cv] = carrier_rows(m.spec.type, Sd) @ gd
        return out

    # -- configuration
    def sync(self, q):
        """Set every carrier to exactly Q(g) of its coordinates (in place; returns q)."""
        for m in self.items:
            Q, _, _ = m.kin(q)
            q[m.cq] = carrier_configuration(m.spec.type, Q)
        return q

    def reparameterize(self, q, vR, T):
        """Grassia's reparameterisation of spherical_exp coordinates (free3d_exp: its rotation
        coordinates) with ||g|| > the joint's reparam_threshold (default pi; notes §2.5.8); maps gdot
        through the hyper-reduced columns of the coordinate joint. Returns True if anything changed."""
        changed = False
        for m in self.items:
            if m.spec.type not in jt.REPARAMETERIZE:
                continue
            Tg = T[m.gv]
            gd = Tg @ vR
            g2, gd2, ch = jt.REPARAMETERIZE[m.spec.type](q[m.gq], gd, m.spec.extra.get("reparam_threshold", math.pi))
            if ch:
                cols = [int(np.flatnonzero(Tg[i])[0]) for i in range(m.k)]
                q[m.gq] = g2
                vR[cols] = gd2  # coordinate rows of J_rR are the identity on these columns
                changed = True
        return changed
