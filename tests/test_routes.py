"""Random routes (`ptw_rt/sim/routes.py`): rides nobody tuned on, the same ride for the same number everywhere,
reachable by name from every command and drawn by `ptw-rt evaluate --random N --routes`."""

from __future__ import annotations

import pytest

from ptw_rt.errors import UserFacingError
from ptw_rt.eval import random_rides as rr
from ptw_rt.eval.evaluate import evaluate_ride
from ptw_rt.eval.matrix import cell_metrics
from ptw_rt.sim.ride import get_scenario, simulate
from ptw_rt.sim.routes import MAX_ROUTE, ROUTE_DURATION, route_scenario, route_segments
from ptw_rt.sim.scenarios import SCENARIOS


def test_a_route_is_the_same_ride_for_the_same_number_and_another_for_another():
    assert route_segments(17) == route_segments(17)
    assert route_segments(17) != route_segments(18)
    for n in range(50):
        segs, mu, start = route_segments(n)
        assert sum(s.duration for s in segs) >= ROUTE_DURATION
        assert 0.6 <= mu <= 1.0 and start in (0.0, 20.0, 40.0, 60.0)
        assert all(0.0 <= s.kmh <= 125.0 and abs(s.lat) <= 5.5 * mu for s in segs)


@pytest.mark.parametrize("name", ["route_", "route_-1", "route_1e9", "route_x", "route_1234567890", "route_٣"])
def test_a_route_name_that_is_no_number_is_one_line(name):
    with pytest.raises(UserFacingError, match="unknown scenario.*route_N") as info:
        get_scenario(name)
    assert "\n" not in str(info.value)


def test_route_names_reach_the_simulator():
    assert get_scenario("route_5").name == "route_5"
    assert get_scenario("dlc_50") is SCENARIOS["dlc_50"]
    with pytest.raises(ValueError):
        route_scenario(MAX_ROUTE)


def test_a_route_is_ridden_and_estimated_within_the_promises():
    """One route end to end (the sets measured are in docs/estimator.md, "Random routes")."""
    ev = evaluate_ride(simulate("route_3"))
    m = cell_metrics(ev)
    assert m["roll_rmse_deg"]["ours"] <= m["roll_rmse_deg"]["peer"]
    assert m["roll_valid"]["max_err_deg"] <= m["roll_valid"]["tolerance_deg"]
    for stiffness in m["stiffness_valid"].values():
        assert stiffness["max_abs_err_pct"] is None or stiffness["max_abs_err_pct"] <= 20.0


def test_random_routes_draw_the_same_perturbations_as_the_scenarios_rides():
    for i in range(16):
        scenario, perturb, seed = rr.draw_ride(5, i, routes=True)
        assert scenario.startswith("route_") and get_scenario(scenario).name == scenario
        assert (perturb, seed) == rr.draw_ride(5, i)[1:]
