"""The Exudyn peer (redmax_bench/exudyn_planar.py, benchmarks only): the planar export of the pendulum, chain-5 and
the four-bar reproduces RK4 on our reduced dynamics (pin.aba; the four-bar: our step at tiny h) at small h, keeps the
loop closed, and converges at second order (generalized-alpha). Exudyn is part of the ``bench`` extra."""
import numpy as np
import pytest

from redmax_ros.core import Simulator

exudyn = pytest.importorskip("exudyn", reason="exudyn is not installed (pip install -e .[bench])")

from redmax_bench import exudyn_planar  # noqa: E402
from redmax_bench.methods import project_velocity  # noqa: E402


def _exudyn_q(sim, h, T, sample_dt):
    mech = sim.mech
    v0 = project_velocity(mech, sim.state.q, sim.state.v) if len(mech.loop_ab) else sim.state.v
    model = exudyn_planar.PlanarModel(mech, sim.state.q, mech.to_reduced(v0), h, T, sample_dt)
    ok, _, _ = model.solve()
    assert ok
    t, q, v = model.samples()
    return t, q, v, v0


@pytest.mark.parametrize("scene,over", [("pendulum", []), ("chain", ["params.n=5"])])
def test_tree_scenes_match_rk4(scene, over, rk4_aba):
    """At h = 1e-4 over 0.5 s the Exudyn joint angles equal RK4 on pin.aba to 1e-5 rad (the same state at t = 0;
    generalized-alpha is second order: measured 2e-8 on the pendulum, 1.3e-6 on chain-5)."""
    sim = Simulator.load(scene, over)
    t, q, _, _ = _exudyn_q(sim, 1e-4, 0.5, 0.05)
    i = int(np.argmin(np.abs(t - 0.5)))
    assert abs(t[i] - 0.5) < 1e-9
    assert np.abs(q[i] - rk4_aba(sim.mech.model, sim.state.q, sim.joint_velocities(), 0.5)).max() < 1e-5


def test_fourbar_matches_our_step_and_keeps_the_loop_closed():
    """The four-bar at h = 1e-4 over 0.3 s: joint angles equal our BDF2 step at h = 2.5e-5 from the same consistent
    state to 1e-5 rad; the loop residual of the Exudyn state stays below 1e-9 m; successive halving of h gives
    order 2 +- 0.3 (generalized-alpha)."""
    sim = Simulator.load("fourbar")
    t, q, _, v0 = _exudyn_q(sim, 1e-4, 0.3, 0.05)
    ours = Simulator.load("fourbar", ["integrator.scheme=bdf2", "dt=2.5e-5"])
    from redmax_ros.core.step.state import State
    ours.set_state(State(0.0, sim.state.q.copy(), v0))
    ours.step(12000)
    i = int(np.argmin(np.abs(t - 0.3)))
    assert np.abs(q[i] - ours.state.q).max() < 1e-5
    data = sim.mech.model.createData()
    from redmax_bench.methods import loop_residual
    assert max(loop_residual(sim.mech, data, qi) for qi in q) < 1e-9
    finals = []
    for h in (2e-3, 1e-3, 5e-4):
        t, q, _, _ = _exudyn_q(sim, h, 0.3, 0.05)
        finals.append(q[int(np.argmin(np.abs(t - 0.3)))])
    d1, d2 = np.abs(finals[0] - finals[1]).max(), np.abs(finals[1] - finals[2]).max()
    assert abs(np.log2(d1 / d2) - 2.0) < 0.3, (d1, d2)
