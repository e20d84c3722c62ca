"""Exudyn as a second peer (issue 12 point 7): a planar mechanism of revolute joints about y (pendulum, chains, the
four-bar) as Exudyn 2D rigid bodies in maximal coordinates with exact joint and loop constraints (RevoluteJoint2D,
index 3), integrated by Exudyn's implicit generalized-alpha solver (its default, spectral radius 0.9: Arnold &
Bruls 2007). Optional: ``pip install exudyn`` (extra "bench"); the methods say "not applicable" without it.

Mapping (our world x, z to Exudyn's 2D X, Y): a body rotated by Ry(theta) has the 2D angle phi = -theta, and a
body-local vector (a, ., b) is the 2D local vector (a, b). Body states start from our state at t = 0 (COM
positions and velocities, angles and angular velocities from Pinocchio), every engine from the same consistent
state (methods.make_problem projects loop velocities); joint angles are read back as q_j = -(phi_child - phi_parent).
"""
from __future__ import annotations

import time

import numpy as np
import pinocchio as pin


def available() -> bool:
    try:
        import exudyn  # noqa: F401  (optional)
    except ImportError:
        return False
    return True


def applies(mech) -> str | None:
    """Why the mechanism cannot be exported (None: it can): revolute joints about y only, no springs, limits,
    couplings, joint stiffness/damping, armature or applied loads."""
    m = mech.model
    for j in range(1, m.njoints):
        jm = m.joints[j]
        if jm.shortname() != "JointModelRY":
            return f"joint '{m.names[j]}' is {jm.shortname()} (the Exudyn export takes revolute joints about y)"
    if len(mech.spring_ab) or len(mech.limited) or mech.T is not None or mech.has_stiffness:
        return "springs, limits, couplings or joint stiffness are not in the Exudyn export"
    if np.any(mech.damping) or mech.has_armature or np.any(mech.torque0) or len(mech.wrench_body):
        return "joint damping, armature or applied loads are not in the Exudyn export"
    return None


class PlanarModel:
    """The Exudyn system of ``mech`` at (q0, v0) (reduced coordinates), with sensors of every body's angle and
    angular velocity sampled every ``sample_dt``."""

    def __init__(self, mech, q0, v0, h, T, sample_dt):
        import exudyn as exu
        import exudyn.utilities as eu

        self.mech = mech
        m = mech.model
        d = m.createData()
        pin.forwardKinematics(m, d, q0, v0)
        self.sc = exu.SystemContainer()
        mbs = self.mbs = self.sc.AddSystem()
        g = np.asarray(m.gravity.linear)
        ground = mbs.AddObject(eu.ObjectGround())
        self.nodes, self.bodies, self.sensors, self.phi0 = {}, {}, [], {}
        for j in range(1, m.njoints):
            Y = m.inertias[j]
            oMi = d.oMi[j]
            R = oMi.rotation
            theta = float(np.arctan2(R[0, 2], R[0, 0]))
            com = oMi.act(Y.lever)
            vj = d.v[j]  # local twist of the joint frame
            w = float((R @ vj.angular)[1])
            vcom = R @ (vj.linear + np.cross(vj.angular, Y.lever))
            Icom = float(Y.inertia[1, 1])  # about the body's y axis at the COM (revolute about y)
            node = mbs.AddNode(eu.NodeRigidBody2D(referenceCoordinates=[com[0], com[2], -theta],
                                                  initialVelocities=[vcom[0], vcom[2], -w]))
            body = mbs.AddObject(eu.ObjectRigidBody2D(nodeNumber=node, mass=Y.mass, inertia=Icom))
            mk = mbs.AddMarker(eu.MarkerBodyMass(bodyNumber=body))
            mbs.AddLoad(eu.LoadMassProportional(markerNumber=mk, loadVector=[g[0], g[2], 0.0]))
            self.nodes[j], self.bodies[j] = node, body
            self.phi0[j] = -theta  # the node's reference angle (its Coordinates are displacements from it)
            # the joint: child marker at the joint origin (COM -> origin), parent marker at the placement
            lever = Y.lever
            mc = mbs.AddMarker(eu.MarkerBodyPosition(bodyNumber=body, localPosition=[-lever[0], -lever[2], 0.0]))
            parent = m.parents[j]
            pl = m.jointPlacements[j].translation
            if parent == 0:
                mp = mbs.AddMarker(eu.MarkerBodyPosition(bodyNumber=ground, localPosition=[pl[0], pl[2], 0.0]))
            else:
                plev = m.inertias[parent].lever
                mp = mbs.AddMarker(eu.MarkerBodyPosition(bodyNumber=self.bodies[parent],
                                                         localPosition=[pl[0] - plev[0], pl[2] - plev[2], 0.0]))
            mbs.AddObject(eu.RevoluteJoint2D(markerNumbers=[mp, mc]))
            self.sensors.append(mbs.AddSensor(eu.SensorNode(nodeNumber=node, storeInternal=True,
                                                            outputVariableType=exu.OutputVariableType.Coordinates)))
            self.sensors.append(mbs.AddSensor(eu.SensorNode(nodeNumber=node, storeInternal=True,
                                                            outputVariableType=exu.OutputVariableType.Coordinates_t)))
        for (a, b), P in zip(mech.loop_ab, mech.loop_axes):  # loops: the two sites coincide (2D pin)
            markers = []
            for s in (int(a), int(b)):
                fr = m.frames[mech.site_fid[s]]
                jid = fr.parentJoint
                loc = fr.placement.translation - m.inertias[jid].lever
                markers.append(mbs.AddMarker(eu.MarkerBodyPosition(bodyNumber=self.bodies[jid],
                                                                   localPosition=[loc[0], loc[2], 0.0])))
            mbs.AddObject(eu.RevoluteJoint2D(markerNumbers=markers))
        mbs.Assemble()
        ss = self.settings = exu.SimulationSettings()
        ti = ss.timeIntegration
        ti.numberOfSteps = int(round(T / h))
        ti.endTime = T
        ti.verboseMode = 0
        ti.newton.useModifiedNewton = False
        ss.solution.file.write = False
        ss.solution.sensors.writePeriod = sample_dt
        ss.show.statistics = False
        ss.show.computationTime = False
        ss.linearSolver.solverType = exu.LinearSolverType.EXUdense

    def solve(self) -> tuple:
        """Run the whole simulation; returns (success, CPU seconds, wall seconds)."""
        import exudyn as exu
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            ok = exu.SolveDynamic(self.mbs, self.settings, solverType=exu.DynamicSolverType.GeneralizedAlpha,
                                  showHints=False, showCausingItems=False)
        except Exception:  # noqa: BLE001 - Exudyn raises on Newton failure; reported as non-convergence
            ok = False
        return bool(ok), time.process_time() - c0, time.perf_counter() - t0

    def samples(self):
        """(t (S,), q (S, nv), v (S, nv)): the joint angles and rates at the sensor samples."""
        m = self.mech.model
        data = [self.mbs.GetSensorStoredData(s) for s in self.sensors]
        S = min(len(x) for x in data)
        t = data[0][:S, 0]
        phi = {j: self.phi0[j] + data[2 * k][:S, 3] for k, j in enumerate(range(1, m.njoints))}
        om = {j: data[2 * k + 1][:S, 3] for k, j in enumerate(range(1, m.njoints))}
        q = np.empty((S, m.nv))
        v = np.empty((S, m.nv))
        for j in range(1, m.njoints):
            p = m.parents[j]
            iv = m.idx_vs[j]
            q[:, iv] = -(phi[j] - (phi[p] if p else 0.0))
            v[:, iv] = -(om[j] - (om[p] if p else 0.0))
        return t, q, v
