"""redmax_bench accuracy's reading of a work-precision curve at an error level (cost_at_equal_error): exact on
a power law, never extrapolated past the grid, the measured run when nothing brackets. Arithmetic only."""
import pytest

from redmax_bench.accuracy import TIME_KEY, cost_at, cost_at_equal_error
from redmax_bench.methods import Case

CASE = Case("synthetic", "conservative", "pendulum")
HS = (2e-2, 1e-2, 5e-3, 2e-3, 1e-3, 5e-4)


def _runs(err, cost, hs=HS, status=lambda h: "ok"):
    return [{"h": h, "status": status(h), "state_max": err(h), TIME_KEY: cost(h)} for h in hs]


@pytest.mark.parametrize("order", [1, 2, 4])
def test_a_power_law_is_read_exactly_between_grid_points(order):
    """error = C h^p and cost = c / h are a straight line in log-log: the reading at eps is c / h(eps) with
    h(eps) = (eps / C)^(1/p), between the grid points, where cost_at gives the next grid point below."""
    c, eps = 1e-6, 1e-4
    C = eps / 3e-3 ** order  # the error reaches eps at h = 3 ms, between the grid's 5 and 2 ms
    runs = _runs(lambda h: C * h ** order, lambda h: c / h)
    h_eps = (eps / C) ** (1.0 / order)
    got = cost_at_equal_error(runs, CASE, eps)
    assert got == pytest.approx(c / h_eps, rel=1e-12)
    measured = cost_at(runs, CASE, eps)
    assert measured >= got  # the cheapest measured run under eps costs at least the reading


def test_no_extrapolation_past_the_largest_step():
    """Every run below eps: the reading is the largest step's cost (no line beyond the grid)."""
    runs = _runs(lambda h: 1e-9 * h, lambda h: 1e-6 / h)
    assert cost_at_equal_error(runs, CASE, 1e-3) == cost_at(runs, CASE, 1e-3) == 1e-6 / HS[0]


def test_a_failed_larger_step_gives_the_measured_run():
    """The next larger step blew up: nothing to join, the measured run's cost; nothing below eps: None."""
    runs = _runs(lambda h: 10.0 * h ** 2, lambda h: 1e-6 / h, status=lambda h: "blow-up" if h > 5e-3 else "ok")
    eps = 10.0 * 5e-3 ** 2
    assert cost_at_equal_error(runs, CASE, eps) == 1e-6 / 5e-3
    assert cost_at_equal_error(runs, CASE, 1e-12) is None


def test_another_error_field():
    """``key`` reads another error field of the runs (probe_final: the four-bar's crank angle at 2 s)."""
    runs = [{"h": h, "status": "ok", "state_max": 1.0, "probe_final": 1e-3 * h / 2e-3, TIME_KEY: 1e-6 / h} for h in HS]
    assert cost_at(runs, CASE, 1e-3) is None
    assert cost_at(runs, CASE, 1e-3, "probe_final") == 1e-6 / 2e-3
    assert cost_at_equal_error(runs, CASE, 1e-3, "probe_final") == pytest.approx(1e-6 / 2e-3, rel=1e-12)
