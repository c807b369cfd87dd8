"""`ptw-rt evaluate --random N`: reproducible random combined-perturbation rides scored against the promises."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from ptw_rt.eval import random_rides as rr
from ptw_rt.sim.ride import parse_perturbations


def test_a_ride_is_the_same_ride_everywhere_and_every_draw_is_within_its_range():
    assert rr.draw_ride(9, 0) == rr.draw_ride(9, 0)
    assert rr.draw_ride(9, 0) != rr.draw_ride(10, 0)
    ranges = {name: (low, high) for name, low, high in rr.DRAWS + rr.AXLE_DRAWS}
    scenarios = set()
    for i in range(64):
        scenario, perturb, seed = rr.draw_ride(3, i)
        scenarios.add(scenario)
        assert rr.NOISE_SEEDS[0] <= seed < rr.NOISE_SEEDS[1]
        parse_perturbations(list(perturb))  # what `ptw-rt evaluate --perturb` accepts
        for item in perturb:
            name, value = item.split("=")
            low, high = ranges[name]
            assert low <= float(value) <= high, item
            if name in rr.WHOLE_COUNTS:
                assert float(value) == round(float(value))
    assert scenarios == set(rr.SCENARIOS)


def _ride(**kw):
    ride = {
        "scenario": "urban",
        "seed": 42,
        "perturb": ["stiffness=0.800", "steer_offset=0.000"],
        "roll_rmse_deg": 0.2,
        "peer_roll_rmse_deg": 0.5,
        "roll_valid_max_err_deg": 0.6,
        "roll_tolerance_deg": 3.0,
        "torque_pct_of_peak": 10.0,
        "torque_valid_max_mean_err_nm": 2.5,
        "stiffness_valid_max_err_pct": 8.0,
        "stiffness_valid_mean_err_pct": 4.0,
        "alarm_cycles": {"plausibility": 0, "attitude_consistency": 0},
        "steer_zero_counts": 0.0,
        "crashed_at": None,
    }
    ride.update(kw)
    return ride


def test_the_summary_names_a_broken_promise_and_the_command_that_replays_it():
    good = [_ride(), _ride(seed=43, steer_zero_counts=1.0, alarm_cycles={"plausibility": 12})]
    s = rr.summarise(good)
    assert all(s["promises_kept"].values())
    assert s["roll"]["le_peer"] == 2 and s["alarms"]["alarmed_with_zero_a_count_off"] == 1
    assert s["alarms"]["alarmed_with_zero_right"] == 0
    never_valid = _ride(seed=45, stiffness_valid_max_err_pct=None, stiffness_valid_mean_err_pct=None)
    s2 = rr.summarise([*good, _ride(seed=46, stiffness_valid_mean_err_pct=12.0), never_valid])
    assert s2["stiffness"]["rides_valid"] == 3 and s2["stiffness"]["mean_le_10pct"] == 2
    bad = good + [_ride(seed=44, roll_rmse_deg=0.9, roll_valid_max_err_deg=3.4, stiffness_valid_max_err_pct=22.0)]
    s = rr.summarise(bad)
    assert s["promises_kept"] == {"roll_valid_within_tolerance": False, "stiffness_valid_max_le_20pct": False}
    assert s["roll"]["worst_valid_err"][0]["command"] == (
        "ptw-rt evaluate --scenario urban --seed 44 --perturb stiffness=0.800 --perturb steer_offset=0.000"
    )
    assert s["roll"]["worse_than_peer"][0]["roll"] == 0.9
    other = _ride(config="/v/other.yaml", design_file="/v/other.npz")
    assert rr.reproduce_command(other).endswith("--config /v/other.yaml --design-file /v/other.npz")
    restored = _ride(restored_biases=True)  # a set run with --restored-biases replays with it
    assert rr.reproduce_command(restored).endswith("--perturb steer_offset=0.000 --restored-biases")
    text = rr.summary_text({"generator_seed": 0, "workers": 1, "wall_s": 1.0, "summary": s})
    assert text.count("BROKEN") == 2 and "--seed 44" in text


def test_a_ride_whose_rider_fell_is_counted_apart_in_the_torque_figure():
    """A simulated fall 1.6 s into the scoring left a route at 64.9 % of the torque's peak (random routes set 2403):
    the summary says how many rides fell and the largest figure of those that did not."""
    rides = [_ride(), _ride(seed=43, torque_pct_of_peak=12.0), _ride(seed=44, torque_pct_of_peak=64.9, crashed_at=6.6)]
    s = rr.summarise(rides)
    assert s["crashed"] == 1
    assert s["torque"]["largest_pct_of_peak"] == 64.9 and s["torque"]["largest_pct_of_peak_upright"] == 12.0
    text = rr.summary_text({"generator_seed": 0, "workers": 1, "wall_s": 1.0, "summary": s})
    assert s["torque"]["le_15pct_of_peak"] == 2 and s["torque"]["le_15pct_of_peak_upright"] == 2
    assert "largest 64.9 % (of the 2 whose simulated rider did not fall: on 2, largest 12.0 %)" in text
    assert "rides whose simulated rider fell (scored until the fall): 1" in text
    quiet = rr.summary_text({"generator_seed": 0, "workers": 1, "wall_s": 1.0, "summary": rr.summarise(rides[:2])})
    assert "fell" not in quiet and "did not fall" not in quiet


def test_the_command_runs_rides_and_prints_json():
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt", "evaluate", "--random", "2", "--random-seed", "5", "--jobs", "1", "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["summary"]["rides"] == 2 and len(result["rides_detail"]) == 2
    for ride, i in zip(result["rides_detail"], range(2), strict=True):
        scenario, perturb, seed = rr.draw_ride(5, i)
        assert (ride["scenario"], tuple(ride["perturb"]), ride["seed"]) == (scenario, perturb, seed)
        assert ride["roll_rmse_deg"] is not None and ride["roll_tolerance_deg"] == 3.0


def test_the_front_tyre_is_drawn_apart_so_every_other_draw_stays_what_it_was():
    """The front tyre's own factor (AXLE_DRAWS, added 2026-12-07) comes from a stream of its own: a set's rides keep
    the tyres, friction, payload, sensors, rider, seed and road they had before it was added."""
    for i in range(16):
        for hills in (False, True):
            scenario, perturb, seed = rr.draw_ride(7, i, hills=hills)
            rng = np.random.default_rng(1000 + i + 1000 * 7)
            before = rr._drawn(rng, rr.DRAWS)
            assert perturb[: len(rr.DRAWS)] == tuple(before) and seed == int(rng.integers(*rr.NOISE_SEEDS))
            name, value = perturb[-1].split("=")
            assert name == "front_stiffness" and 0.8 <= float(value) <= 1.25


def test_hilly_rides_draw_the_same_rides_on_a_road_whose_grade_is_drawn_within_its_range():
    """`--hills` adds the road (HILL_DRAWS) after every other draw: the set's rides are the same rides on hills."""
    ranges = {name: (low, high) for name, low, high in rr.HILL_DRAWS}
    for i in range(16):
        for routes in (False, True):
            scenario, perturb, seed = rr.draw_ride(5, i, routes=routes, hills=True)
            level = rr.draw_ride(5, i, routes=routes)
            assert (scenario, perturb[: len(rr.DRAWS)], seed) == (level[0], level[1][: len(rr.DRAWS)], level[2])
            road = dict(item.split("=") for item in perturb[len(rr.DRAWS) : len(rr.DRAWS) + len(rr.HILL_DRAWS)])
            assert set(road) == set(ranges)
            for name, value in road.items():
                assert ranges[name][0] <= float(value) <= ranges[name][1]
            ride = parse_perturbations(list(perturb))
            assert ride.road_slope_length == float(road["road_slope_length"])


@pytest.mark.parametrize(
    "args",
    [
        ["--random", "0"],
        ["--random", "-3"],
        ["--random", str(rr.MAX_RIDES + 1)],
        ["--random", "2", "--random-seed", "-5"],
        ["--random", "2", "--random-seed", str(10**30)],
        ["--random", "2", "--scenario", "dlc_50"],
        ["--random", "2", "--matrix"],
        ["--random", "2", "--perturb", "stiffness=0.7"],
        ["--random", "2", "--seed", "3"],
        ["--routes", "--scenario", "dlc_50"],  # --routes goes with --random
        ["--hills", "--scenario", "dlc_50"],  # --hills too
        ["--matrix", "--restored-biases"],  # the matrix starts from no persisted state
    ],
)
def test_a_bad_request_is_one_line_and_exit_2(args):
    """Out of range, or options --random would silently ignore (it draws its own)."""
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt", "evaluate", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
