"""--grid / --random expansion (redmax_ros/sweep/spec.py): cartesian product, value syntax, seeded sampling."""
import itertools

import numpy as np
import pytest

from redmax_ros.sweep import spec as sp


def test_grid_is_the_cartesian_product_first_key_slowest():
    keys, pts = sp.expand(["params.n=2,3,4", "friction.joint_mu=0,0.2"])
    assert keys == ["params.n", "friction.joint_mu"]
    assert pts == list(itertools.product(["2", "3", "4"], ["0", "0.2"]))
    runs = sp.build_runs("chain", keys, pts, ["dt=0.002"], duration=0.1)
    assert [r.index for r in runs] == list(range(6))
    assert runs[3].overrides == ("dt=0.002", "params.n=3", "friction.joint_mu=0.2")
    assert runs[3].params == (("params.n", "3"), ("friction.joint_mu", "0.2"))


def test_grid_values_keep_brackets_and_ranges():
    assert sp.grid_values("gravity=[0,0,-9.81],[0, 0, -1.62]") == ("gravity", ["[0,0,-9.81]", "[0, 0, -1.62]"])
    k, v = sp.grid_values("params.k=log:1:1000:4")
    assert k == "params.k" and [float(x) for x in v] == pytest.approx([1, 10, 100, 1000])
    assert all("e" not in x for x in v)  # YAML 1.1 reads '1e3' as a string
    _, v = sp.grid_values("dt=lin:0.001:0.002:3")
    assert [float(x) for x in v] == [0.001, 0.0015, 0.002]
    with pytest.raises(ValueError):
        sp.grid_values("dt=")
    with pytest.raises(ValueError):
        sp.grid_values("dt=1,,2")


def test_random_samples_are_reproducible_by_seed_and_in_range():
    args = ["friction.joint_mu=uniform:0:0.8", "params.k=loguniform:10:1e4", "joints.hinge.q0=normal:0.3:0.01"]
    keys, a = sp.expand(random=args, samples=50, seed=7)
    _, b = sp.expand(random=args, samples=50, seed=7)
    _, c = sp.expand(random=args, samples=50, seed=8)
    assert keys == ["friction.joint_mu", "params.k", "joints.hinge.q0"]
    assert a == b and a != c and len(a) == 50
    x = np.array([[float(v) for v in p] for p in a])
    assert np.all((0 <= x[:, 0]) & (x[:, 0] <= 0.8)) and np.all((10 <= x[:, 1]) & (x[:, 1] <= 1e4))
    assert abs(np.mean(x[:, 2]) - 0.3) < 0.01
    # the value texts read back as the sampled float64s
    rng = np.random.default_rng(7)
    assert float(a[0][0]) == rng.uniform(0, 0.8)


def test_grid_times_random_and_errors():
    keys, pts = sp.expand(["params.n=2,3"], ["dt=uniform:0.001:0.002"], samples=3, seed=1)
    assert len(pts) == 6 and keys == ["params.n", "dt"]
    assert [p[1] for p in pts[:3]] == [p[1] for p in pts[3:]]  # the same samples for every grid point
    assert sp.expand() == ([], [()])
    for bad in (dict(random=["dt=uniform:1:2"]), dict(grid=["dt=1", "dt=2"]),
                dict(random=["dt=beta:1:2"], samples=2), dict(random=["dt=loguniform:0:2"], samples=2)):
        with pytest.raises(ValueError):
            sp.expand(**bad)
