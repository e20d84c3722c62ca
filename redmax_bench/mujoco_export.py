"""Export a compiled scene (``Mechanism``) to MuJoCo through MjSpec, for benchmarks only
(the ``bench`` extra; ``redmax_ros.core`` never imports mujoco).

What maps to what:
  * one MuJoCo body per Pinocchio joint, its frame = the Pinocchio joint frame, with the joint's
    lumped inertia (mass, COM, full inertia tensor; fixed children are already merged);
  * revolute -> hinge, prismatic -> slide, universal -> two hinges in one body (MuJoCo composes
    them in order, as Pinocchio's R_a1(q1) R_a2(q2)), spherical -> ball, free -> free,
    planar -> slide x, slide y, hinge z; joint stiffness/rest -> stiffness/springref, damping,
    armature, limits -> range (soft, MuJoCo's default solver parameters);
  * sites -> sites; maximal springs -> spatial tendons through the two sites with stiffness,
    damping and springlength = rest length (MuJoCo applies tendon stiffness explicitly);
  * loops -> ``connect`` equality constraints between the two sites (3 rows; the redundant
    out-of-plane row of a planar loop is absorbed by MuJoCo's soft-constraint regularisation),
    with solref = (2 h, 1), the stiffest MuJoCo recommends, and impedance 0.9999 (HARD_SOLIMP);
  * couplings -> ``joint`` equality constraints q_k = (r_k / r_1) q_1 (same solref/solimp);
  * angles in radians (``compiler.degree = False``: MjSpec's default is degrees for springref and
    ranges);
  * constant joint torques -> qfrc_applied, constant wrenches -> xfrc_applied (at the COM).
Velocities differ only for free joints (MuJoCo: world-frame linear velocity; Pinocchio: local)
and planar joints; ``Export.vel_map(q)`` is the matrix T with qvel = T v_pinocchio, so that
M_pin = T^T M_mj T and g_pin = T^T g_mj.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from redmax_bench.maximal import decode_joint

try:  # benchmark-only dependency
    import mujoco
except ImportError:  # pragma: no cover - exercised when the bench extra is missing
    mujoco = None

# Equality constraints as hard as MuJoCo allows: impedance 0.9999 (MuJoCo's default 0.9-0.95 lets
# the heavy bridge deck sag ~4 cm at its loop and caps the accuracy at 4e-2).
HARD_SOLIMP = [0.9999, 0.9999, 0.001, 0.5, 2.0]
INTEGRATORS = {"euler": "mjINT_EULER", "implicitfast": "mjINT_IMPLICITFAST", "rk4": "mjINT_RK4",
               "discrete": "mjINT_DISCRETE"}  # discrete: MuJoCo 3.13+


def _quat_wxyz(R):
    x, y, z, w = pin.Quaternion(R).coeffs()
    return [w, x, y, z]


@dataclass
class Export:
    mech: object
    model: object  # mujoco.MjModel
    joints: list  # per Pinocchio joint: (kind, idx_q, nq, idx_v, nv, qposadr, dofadr)
    qfrc_applied: np.ndarray
    xfrc_applied: np.ndarray
    notes: list = field(default_factory=list)

    def make_data(self):
        d = mujoco.MjData(self.model)
        d.qfrc_applied[:] = self.qfrc_applied
        d.xfrc_applied[:] = self.xfrc_applied
        return d

    def qpos(self, q):
        out = np.zeros(self.model.nq)
        for kind, iq, nq, iv, nv, qa, da in self.joints:
            qq = q[iq:iq + nq]
            if kind in ("revolute", "prismatic", "universal"):
                out[qa:qa + nq] = qq
            elif kind == "spherical":
                out[qa:qa + 4] = [qq[3], qq[0], qq[1], qq[2]]
            elif kind == "free":
                out[qa:qa + 3] = qq[:3]
                out[qa + 3:qa + 7] = [qq[6], qq[3], qq[4], qq[5]]
            elif kind == "planar":
                out[qa:qa + 3] = [qq[0], qq[1], math.atan2(qq[3], qq[2])]
        return out

    def q(self, qpos):
        """Pinocchio configuration of a MuJoCo qpos (quaternions renormalised)."""
        out = np.zeros(self.mech.nq)
        for kind, iq, nq, iv, nv, qa, da in self.joints:
            qq = qpos[qa:]
            if kind in ("revolute", "prismatic", "universal"):
                out[iq:iq + nq] = qq[:nq]
            elif kind == "spherical":
                u = np.array([qq[1], qq[2], qq[3], qq[0]])
                out[iq:iq + 4] = u / np.linalg.norm(u)
            elif kind == "free":
                u = np.array([qq[4], qq[5], qq[6], qq[3]])
                out[iq:iq + 3] = qq[:3]
                out[iq + 3:iq + 7] = u / np.linalg.norm(u)
            elif kind == "planar":
                out[iq:iq + 4] = [qq[0], qq[1], math.cos(qq[2]), math.sin(qq[2])]
        return out

    def vel_map(self, q) -> np.ndarray:
        """T (nv_mj x nv_pin) with qvel = T v_pin at configuration q (Pinocchio)."""
        T = np.zeros((self.model.nv, self.mech.nv))
        for kind, iq, nq, iv, nv, qa, da in self.joints:
            if kind == "free":
                R = pin.Quaternion(q[iq + 6], q[iq + 3], q[iq + 4], q[iq + 5]).toRotationMatrix()
                T[da:da + 3, iv:iv + 3] = R
                T[da + 3:da + 6, iv + 3:iv + 6] = np.eye(3)
            elif kind == "planar":
                c, s = q[iq + 2], q[iq + 3]
                T[da:da + 2, iv:iv + 2] = [[c, -s], [s, c]]
                T[da + 2, iv + 2] = 1.0
            else:
                T[da:da + nv, iv:iv + nv] = np.eye(nv)
        return T

    def qvel(self, q, v):
        return self.vel_map(q) @ v

    def v(self, q, qvel):
        return np.linalg.lstsq(self.vel_map(q), qvel, rcond=None)[0]

    def mass_matrix_and_gravity(self, q):
        """(M, g) of the MuJoCo model at Pinocchio configuration q, mapped to Pinocchio velocities."""
        d = mujoco.MjData(self.model)
        d.qpos[:] = self.qpos(q)
        d.qvel[:] = 0.0
        mujoco.mj_forward(self.model, d)
        M = np.zeros((self.model.nv, self.model.nv))
        mujoco.mj_fullM(self.model, d, M)
        T = self.vel_map(q)
        return T.T @ M @ T, T.T @ d.qfrc_bias


def _poly(x):
    """MuJoCo 4 stores joint/tendon stiffness and damping as polynomial coefficients (linear first)."""
    return [float(x), 0.0, 0.0]


def available() -> bool:
    return mujoco is not None


def export(mech, h: float = 1e-3, integrator: str = "implicitfast", loop_solref=None) -> Export:
    """Build the MuJoCo model of ``mech`` with time step ``h`` and the named integrator."""
    if mujoco is None:
        raise ImportError("mujoco is not installed (pip install -e .[bench])")
    model = mech.model
    spec = mujoco.MjSpec()
    spec.modelname = mech.spec.name
    spec.compiler.degree = False  # angles (springref, ranges) in radians, as everywhere in the project
    spec.option.timestep = h
    spec.option.gravity = np.asarray(model.gravity.linear, float)
    spec.option.integrator = getattr(mujoco.mjtIntegrator, INTEGRATORS[integrator])
    spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    notes = []
    bodies = {0: spec.worldbody}
    jinfo = []  # (kind, name list, idx_q, nq, idx_v, nv)
    for jid in range(1, model.njoints):
        jm = model.joints[jid]
        kind, axes = decode_joint(jm)
        Mpj = model.jointPlacements[jid]
        parent = bodies[int(model.parents[jid])]
        name = model.names[jid]
        b = parent.add_body(name=f"body:{name}", pos=Mpj.translation.copy(), quat=_quat_wxyz(Mpj.rotation))
        I = model.inertias[jid]
        b.mass = I.mass
        b.ipos = np.asarray(I.lever, float).copy()
        Ic = np.asarray(I.inertia, float)
        b.fullinertia = [Ic[0, 0], Ic[1, 1], Ic[2, 2], Ic[0, 1], Ic[0, 2], Ic[1, 2]]
        b.explicitinertial = True
        iv, nv = jm.idx_v, jm.nv
        k, dmp, arm = mech.stiffness[iv:iv + nv], mech.damping[iv:iv + nv], mech.armature[iv:iv + nv]
        lo, up = mech.lower[iv:iv + nv], mech.upper[iv:iv + nv]
        names = []

        def add(jtype, axis, i, jname):
            j = b.add_joint(name=jname, type=jtype, axis=np.asarray(axis, float))
            j.damping = _poly(dmp[i])
            j.armature = float(arm[i])
            if k[i]:
                j.stiffness = _poly(k[i])
            if np.isfinite(lo[i]) or np.isfinite(up[i]):
                j.limited = mujoco.mjtLimited.mjLIMITED_TRUE
                j.range = [float(lo[i]) if np.isfinite(lo[i]) else -1e10, float(up[i]) if np.isfinite(up[i]) else 1e10]
            names.append(jname)
            return j

        H, S = mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE
        if kind in ("revolute", "prismatic"):
            j = add(H if kind == "revolute" else S, axes[0], 0, name)
            j.springref = float(mech.q_rest[jm.idx_q])
        elif kind == "universal":
            for i in range(2):
                j = add(H, axes[i], i, f"{name}#{i}")
                j.springref = float(mech.q_rest[jm.idx_q + i])
        elif kind == "planar":
            for i, (t, ax) in enumerate(((S, [1, 0, 0]), (S, [0, 1, 0]), (H, [0, 0, 1]))):
                add(t, ax, i, f"{name}#{i}")
            if np.any(k):
                raise NotImplementedError("mujoco export: planar joint stiffness")
        elif kind in ("spherical", "free"):
            if np.any(k) or np.ptp(dmp) or np.ptp(arm) or np.any(np.isfinite(lo)) or np.any(np.isfinite(up)):
                raise NotImplementedError(f"mujoco export: per-DOF stiffness/damping/armature/limits on a {kind} joint")
            jt = mujoco.mjtJoint.mjJNT_BALL if kind == "spherical" else mujoco.mjtJoint.mjJNT_FREE
            j = b.add_joint(name=name, type=jt)
            j.damping, j.armature = _poly(dmp[0]), float(arm[0])
            names.append(name)
        bodies[jid] = b
        jinfo.append((kind, names, jm.idx_q, jm.nq, iv, nv))
    if len(mech.damped_bodies):
        raise NotImplementedError("mujoco export: body damping")
    site_names = []
    for s, (name, jid, loc) in enumerate(zip(mech.site_names, mech.site_jid, mech.site_local)):
        bodies[int(jid)].add_site(name=name, pos=np.asarray(loc, float).copy())
        site_names.append(name)
    for name, (a, b_), k, d, L0 in zip(mech.spring_names, mech.spring_ab, mech.spring_k, mech.spring_d, mech.spring_rest):
        t = spec.add_tendon(name=f"spring:{name}")
        t.stiffness = _poly(k)
        t.damping = _poly(d)
        t.springlength = [float(L0), float(L0)]
        t.wrap_site(site_names[a])
        t.wrap_site(site_names[b_])
    sr = [2.0 * h, 1.0] if loop_solref is None else list(loop_solref)
    si = HARD_SOLIMP
    for name, (a, b_), P in zip(mech.loop_names, mech.loop_ab, mech.loop_axes):
        e = spec.add_equality(name=f"loop:{name}", type=mujoco.mjtEq.mjEQ_CONNECT, objtype=mujoco.mjtObj.mjOBJ_SITE,
                              name1=site_names[a], name2=site_names[b_])
        e.solref, e.solimp = sr, si
        if len(P) < 3:
            notes.append(f"loop '{name}': {len(P)} rows exported as a 3-row connect (redundant row regularised)")
    for c in mech.spec.couplings:
        j1 = c.joints[0]
        for jn, r in zip(c.joints[1:], c.ratios[1:]):
            e = spec.add_equality(name=f"coupling:{c.name}:{jn}", type=mujoco.mjtEq.mjEQ_JOINT,
                                  objtype=mujoco.mjtObj.mjOBJ_JOINT, name1=jn, name2=j1)
            data = np.zeros(len(e.data))
            data[1] = float(r) / float(c.ratios[0])
            e.data = data
            e.solref, e.solimp = sr, si
    mjm = spec.compile()
    joints = []
    for kind, names, iq, nq, iv, nv in jinfo:
        jid0 = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_JOINT, names[0])
        joints.append((kind, iq, nq, iv, nv, int(mjm.jnt_qposadr[jid0]), int(mjm.jnt_dofadr[jid0])))
    ex = Export(mech, mjm, joints, np.zeros(mjm.nv), np.zeros((mjm.nbody, 6)), notes)
    T0 = ex.vel_map(mech.q0)
    if np.any(mech.torque0):
        ex.qfrc_applied = np.linalg.pinv(T0.T) @ mech.torque0  # constant joint torques (1-DOF joints)
    for bi, fw in zip(mech.wrench_body, mech.wrench_fw):
        jid = int(mech.body_jid[bi])
        bid = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_BODY, f"body:{model.names[jid]}")
        ex.xfrc_applied[bid] += fw
    return ex
