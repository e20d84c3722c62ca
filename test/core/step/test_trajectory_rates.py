"""step/trajectory_rates.py: the compiled velocity rows of sine and constant trajectories on coordinate joints
equal, bit for bit, those of the per-joint path (trajectory.joint_rate: g = qdot_p(t) + b (q_p(t) - q)), and
the plan is refused where that path must be taken (another kind of time function, a manifold joint)."""
from __future__ import annotations

import numpy as np

from redmax_ros.core import Simulator
from redmax_ros.core.step import trajectory, trajectory_rates

SINE = {"type": "sine", "amplitude": 0.3, "frequency": 0.7, "phase": 0.4, "offset": -0.1}


def _plan(sim):
    return trajectory_rates.sine_plan(sim.mech, sim.commands.joint_trajectories, trajectory.TRAJECTORY_JOINT_TYPES,
                                      trajectory.MANIFOLD_JOINT_TYPES)


def test_rates_equal_the_per_joint_rows_bit_for_bit():
    sim = Simulator.load("hand")  # universal (2 DOF) and revolute joints
    sim.prescribe_joints({"elbow": {"position": SINE, "b": 5.0},
                          "wrist": {"position": [{"type": "constant", "value": 0.2}, SINE], "b": 0.0}})
    plan = _plan(sim)
    assert plan is not None
    rng = np.random.default_rng(7)
    for _ in range(200):
        q = sim.mech.q0 + rng.normal(scale=0.5, size=sim.mech.nq)
        t = float(rng.uniform(0.0, 50.0))
        got = trajectory_rates.rates(plan, q, t)
        for name, traj in sim.commands.joint_trajectories.items():
            want = trajectory.joint_rate(sim.mech, name, traj, q, t)
            assert got[name].tobytes() == np.asarray(want, dtype=float).tobytes(), name


def test_no_plan_for_other_time_functions_or_manifold_joints():
    sim = Simulator.load("hand")
    sim.prescribe_joints({"elbow": {"position": {"type": "ramp", "start": 0.0, "end": 1.0, "to": 0.5}}})
    assert _plan(sim) is None
    ms = Simulator.load("mass_springs")  # free joints: positions are not their coordinates
    ms.prescribe_joints({"free0": {"position": [SINE] * 6}})
    assert _plan(ms) is None
