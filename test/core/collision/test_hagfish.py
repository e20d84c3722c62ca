"""The shipped HAGFISH (scenes/hagfish.yaml, paper §6 Fig. 3): 100 joints alternating Z revolute and XY
universal, self-collision rows of Eq. (5); the tail drive of redmax_bench/hagfish.py keeps every pair
within the penetration tolerance and every joint within its limits, and ties an overhand knot: the centre
line's top view has 3 crossings alternating over/under along the body (a reduced alternating diagram with 3
crossings: the trefoil), checked on a known curve too (docs/collisions.md)."""
import json

import numpy as np

from redmax_bench import hagfish as H
from redmax_ros.core import Simulator


def test_hagfish_structure():
    sim = Simulator.load("hagfish", budget=None)
    m = sim.mech
    kinds = [j.type for j in m.joints]
    assert len(kinds) == 100 and kinds[0::2] == ["revolute"] * 50 and kinds[1::2] == ["universal"] * 50
    assert m.nv == 150 and type(sim.backend).__name__ == "DirectBackend"
    names = {o for o in m.collision.owner}
    assert {"jar", "floor", "head", "seg0", "seg99"} <= names
    assert 0.05 < float(m.body_mass.sum()) < 0.3  # kg: a ~0.5 m Pacific hagfish
    assert m.lower[0] == -0.2 and abs(m.upper[-1] - 0.45) < 1e-12  # limits taper head -> tail


def test_hagfish_driven_tail_no_penetration_within_limits():
    sim = Simulator.load("hagfish", budget=None)
    r = H.run(400, sim=sim)
    tol = 0.01 * 0.004  # 1 % of the tail radius [m]
    assert r["worst_distance_m"] > -tol, r
    assert r["worst_limit_excess_rad"] < 1e-6, r
    assert r["max_active"] >= 1 and r["rows_per_step"] > 0


def test_hagfish_ties_an_overhand_knot():
    """3000 steps (3 s) of the shipped drive: 3 alternating crossings in the top view, no pair penetrating
    more than 1 % of the tail radius, every joint within its limits (about 45 s on the 2-core machine)."""
    sim = Simulator.load("hagfish", budget=None)
    r = H.run(3000, sim=sim)
    assert r["crossings"] >= 3 and r["alternating"], r
    assert r["worst_distance_m"] > -0.01 * 0.004, r
    assert r["worst_limit_excess_rad"] < 1e-6, r


def test_crossing_measure_on_a_trefoil():
    t = np.linspace(0.05, 2 * np.pi - 0.05, 400)  # an open trefoil: its standard diagram has 3 crossings
    X = np.c_[np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)]
    k = H.knot_measures(X)
    assert k["crossings"] == 3 and k["alternating"]
    line = np.c_[np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)]
    assert H.knot_measures(line)["crossings"] == 0


def test_hagfish_benchmark_writes_its_split(tmp_path):
    assert H.main(["--steps", "20", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "hagfish.json").read_text())
    assert {"ms_detect", "ms_qp", "ms_rest", "active_per_step", "steps_per_s", "crossings"} <= set(r)
