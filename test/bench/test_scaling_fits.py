"""redmax_bench scaling's fits (issue 12 point 8): the largest decade, the fixed cost a of a + b DOF, the
size levels past 10^4 DOF. Arithmetic only, no timing."""
import numpy as np

from redmax_bench.scaling import FLEXY_SCALE, RIGID_SCALE, UMBRELLA_RIBS, linear_fit, slope, top_decade


def test_top_decade_keeps_sizes_within_a_tenth_of_the_largest():
    d, v = top_decade([80, 960, 1280, 2560, 10240], [1, 2, 3, 4, 5])
    assert d == [1280, 2560, 10240] and v == [3, 4, 5]


def test_linear_fit_and_slope_recover_a_plus_b_dof():
    dof = np.array([1000, 2000, 5000, 10000])
    t = 50e-6 + 3e-6 * dof  # 50 us fixed + 3 us per DOF
    fit = linear_fit(list(dof), list(t))
    assert abs(fit["a_us"] - 50.0) < 1e-6 and abs(fit["b_us_per_dof"] - 3.0) < 1e-9
    assert abs(slope([1000, 10000], [1.0, 10.0]) - 1.0) < 1e-12


def test_levels_reach_ten_thousand_dof():
    """Level 7 of every scene has >= 10^4 DOF (builders_large.py: rigid 80 s, flexy 60 s, umbrella
    1 + 16 (ribs + stretchers)); levels 0-4 are Table 2's."""
    rigid = [80 * s for s in RIGID_SCALE]
    flexy = [60 * s for s in FLEXY_SCALE]
    umbrella = [1 + 16 * (r + r // 2) for r in UMBRELLA_RIBS]
    assert rigid[:5] == [80, 160, 320, 640, 1280] and flexy[:5] == [60, 120, 240, 480, 960]
    assert umbrella[:5] == [241, 385, 529, 769, 1105]
    assert min(rigid[7], flexy[7], umbrella[7]) >= 10000


def test_the_small_size_fit_resolves_the_fixed_cost_the_all_size_fit_does_not():
    """100 us fixed + 2 us per DOF with +1 % on the largest size: the fit over all sizes is off by far more than
    the fit over the three smallest, which scaling reports beside it (pcg_per_step_fit_small)."""
    dof = [80, 160, 320, 640, 1280, 2560, 5120, 10240]
    t = [100e-6 + 2e-6 * d for d in dof]
    t[-1] *= 1.01
    a_all = linear_fit(dof, t)["a_us"]
    a_small = linear_fit(dof[:3], t[:3])["a_us"]
    assert abs(a_small - 100.0) < 1e-6 and abs(a_all - 100.0) > 20.0
