"""URDF scenes: the tree comes from the URDF through Pinocchio; springs, sites and prescriptions from YAML."""
from pathlib import Path

import numpy as np
import pinocchio as pin

from redmax_ros.core import Simulator

DATA = Path(__file__).parent / "data"


def test_urdf_tree_limits_damping_and_mass_matrix():
    sim = Simulator.load(str(DATA / "urdf_arm.yaml"))
    d = sim.describe()
    assert d.joint_names == ["shoulder", "elbow"] and d.joint_types == ["revolute", "revolute"]
    assert np.allclose(sim.mech.lower, [-2.0, -2.5]) and np.allclose(sim.mech.upper, [2.0, 2.5])
    assert np.allclose(sim.mech.damping, [0.01, 0.0])
    ref = pin.buildModelFromUrdf(str(DATA / "arm.urdf"))
    q = np.array([0.3, -0.7])
    assert np.allclose(pin.crba(sim.mech.model, sim.mech.model.createData(), q), pin.crba(ref, ref.createData(), q),
                       atol=1e-14)


def test_urdf_scene_with_yaml_spring_and_prescription():
    sim = Simulator.load(str(DATA / "urdf_arm.yaml"))
    shoulder = sim.mech.joint_index["shoulder"].idx_v
    for _ in range(300):
        r = sim.step()
        assert abs(r.v[shoulder] - 0.5) < 1e-9  # prescribed in YAML
    assert sim.describe().springs == ["pull"] and abs(r.diagnostics.E_spring) > 0
    assert np.all(np.isfinite(r.effort))
