"""The stability claims of docs/benchmarks.md on small instances (issue 6).

* At (k, h) inside our stable region and outside the explicit methods' region, the RedMax step
  stays bounded while semi-implicit Euler and RK4 on pin.aba blow up: stiff maximal springs
  (mass_springs) and stiff joint springs (chain).
* Maximal coordinates with Baumgarte stabilisation (STAR §4.4.1) drift beyond the violation
  threshold of the stability maps where reduced coordinates hold the constraints exactly (joints by
  construction, the four-bar's loop to round-off by post-stabilisation).
"""
import math

import numpy as np
import pytest

from redmax_bench import methods as M
from redmax_bench.accuracy import BLOWUP_ENERGY, VIOLATION_MAX, classify
from redmax_ros.core import Workspace
from redmax_ros.core.step import baselines


def _problem(scene, overrides, T, sample_dt=0.05):
    case = M.Case(f"{scene} {overrides}", "test", scene, overrides, T=T)
    p = M.make_problem(case, T=T, sample_dt=sample_dt)
    m = p.mech
    data = Workspace(m, pin_data=True)
    E0 = baselines.mechanical_energy(m, data, p.q0, m.to_reduced(p.vR0))
    q_eq, _ = M.static_equilibrium(m, p.q0)
    S = E0 - baselines.mechanical_energy(m, data, q_eq, np.zeros(m.nv))
    assert S > 0
    return p, E0, S


STIFF = [
    # (scene, overrides, h): h is 3-4x above the explicit limit ~ 2 / omega_max
    ("mass_springs", ["params.n=1", "params.k=1000000.0"], 5e-3),  # omega ~ 1.4e3 rad/s -> explicit h < 1.4e-3
    ("chain", ["params.n=2", "params.joint_stiffness=1000.0"], 5e-3),  # omega ~ 5e3 rad/s -> explicit h < 4e-4
]


@pytest.mark.parametrize("scene,overrides,h", STIFF, ids=["spring k=1e6", "joint k=1e3"])
def test_ours_bounded_where_explicit_blow_up(scene, overrides, h):
    p, E0, S = _problem(scene, overrides, T=0.5)
    cap = E0 + BLOWUP_ENERGY * S
    ours = M.run_ours(p, h, energy_cap=cap)
    status, reason = classify(ours, E0, S)
    assert status == "stable", reason
    assert max(ours.E) <= E0 + 1e-9 * max(1.0, abs(E0))  # the implicit step never gains energy here
    for scheme in ("sie", "rk4"):
        r = M.run_explicit(p, h, scheme, energy_cap=cap)
        status, reason = classify(r, E0, S)
        assert status == "blow-up", f"{scheme}: {status} ({reason})"


def test_explicit_stable_below_their_limit():
    """Sanity of the claim's other side: the same scene at h below the explicit limit is stable."""
    p, E0, S = _problem("mass_springs", ["params.n=1", "params.k=1000000.0"], T=0.2, sample_dt=0.01)
    for scheme in ("sie", "rk4"):
        r = M.run_explicit(p, 2e-4, scheme, energy_cap=E0 + BLOWUP_ENERGY * S)
        assert classify(r, E0, S)[0] == "stable", r.reason


def test_maximal_baumgarte_drifts_where_reduced_holds_constraints():
    case = M.Case("fourbar", "loop", "fourbar", T=1.0)
    p = M.make_problem(case, sample_dt=0.05)
    h = 5e-3
    ours = M.run_ours(p, h)
    assert ours.status == "ok"
    assert max(ours.viol) < 1e-8  # loop rows closed to round-off; joints exact by construction
    mx = M.run_maximal(p, h)
    assert mx.status == "ok", mx.reason
    assert max(mx.viol) > VIOLATION_MAX  # joint/loop drift above the stability maps' threshold
    # the tree joints alone also drift in maximal coordinates (zero in reduced coordinates)
    chain = M.make_problem(M.Case("chain", "x", "chain", ["params.n=3"], T=1.0), sample_dt=0.05)
    mc = M.run_maximal(chain, 1e-2)
    assert max(mc.viol) > VIOLATION_MAX


def test_maximal_baseline_matches_reduced_dynamics_at_small_h():
    """The maximal baseline is a correct (first-order) integrator of the same mechanics."""
    case = M.Case("chain", "x", "chain", ["params.n=3"], T=0.2)
    p = M.make_problem(case, sample_dt=0.05)
    ref = M.run_explicit(p, 1e-4, "rk4")
    errs = [max(M.errors(p, M.Reference(0, 0, np.array(ref.t), np.array(ref.q), np.array(ref.E), None, ref.E[0],
                                        "", 0), M.run_maximal(p, h))["state_max"], 1e-300) for h in (2e-3, 1e-3)]
    assert errs[1] < 5e-3
    assert 1.5 < errs[0] / errs[1] < 2.6  # first order
    assert math.isfinite(errs[0])
