"""A chain of capsules dropped onto the floor and onto itself (self-collision rows of Eq. 5,
docs/collisions.md) ends with no pair penetrating more than 1 % of the link radius."""
import numpy as np

from redmax_ros.core import Simulator, scene_from_dict

R, L, N = 0.01, 0.04, 12  # link radius [m], cylinder length [m], links


def chain_scene():
    bodies, joints = [], []
    for i in range(N):
        bodies.append({"name": f"l{i}", "shape": {"type": "capsule", "radius": R, "length": L}, "density": 1000.0})
        if i == 0:  # free root: the chain folded in a zig-zag rising from 5 cm to 20 cm above the floor
            joints.append({"name": "root", "type": "free", "parent": "world", "child": "l0",
                           "q0": [0, 0, 0.05, 0, 1.5707963267948966, 0]})
        else:  # universal joints (x: vertical fold, y: tilt), damped; the links fall onto each other
            joints.append({"name": f"u{i}", "type": "universal", "parent": f"l{i - 1}", "child": f"l{i}",
                           "axes": ["x", "y"], "placement": {"pos": [0, 0, L / 2 + R]},
                           "body_placement": {"pos": [0, 0, L / 2 + R]},
                           "q0": [2.5 if i % 2 else -2.5, -0.25],
                           "damping": 2e-4})
    return scene_from_dict({"name": "chain_drop", "gravity": [0, 0, -9.81], "dt": 1e-3, "bodies": bodies,
                            "joints": joints,
                            "collision": {"margin": 0.004, "obstacles": [
                                {"name": "floor", "type": "plane", "normal": [0, 0, 1], "offset": 0.0}]}})


def test_chain_dropped_onto_itself_and_floor():
    sim = Simulator(chain_scene())
    worst, self_rows, floor_rows = np.inf, 0, 0
    for k in range(800):
        c = sim.step().diagnostics.solution.contacts
        worst = min(worst, c.min_distance)
        self_rows = max(self_rows, sum(1 for lab in c.labels if "floor" not in lab))
        floor_rows = max(floor_rows, sum(1 for lab in c.labels if "floor" in lab))
    assert floor_rows >= 2 and self_rows >= 1, (floor_rows, self_rows)
    assert c.min_distance > -0.01 * R, c.min_distance  # at the end
    assert worst > -0.01 * R, worst  # and throughout
