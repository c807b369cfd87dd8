"""Strong observability analysis (seed 000 sec. III) and the `analyze` command."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from ptw_rt.analysis.modes import classify_modes
from ptw_rt.analysis.observability import (
    decoupling_matrix,
    invariant_zeros,
    is_strongly_detectable,
    relative_degree,
)
from ptw_rt.analysis.report import analyze
from ptw_rt.model.sharp import UnknownInputSystem, case1, case2, full_system, kmh

SPEEDS = [20, 50, 80, 100, 120]


@pytest.mark.parametrize("speed_kmh", SPEEDS)
def test_case2_relative_degree_and_decoupling(vehicle, speed_kmh):
    sys = case2(vehicle, kmh(speed_kmh))
    degrees = relative_degree(sys)
    assert degrees == [2, 1]
    assert abs(np.linalg.det(decoupling_matrix(sys, degrees))) > 1.0
    assert len(invariant_zeros(sys)) == 7 - 3
    assert is_strongly_detectable(sys)


@pytest.mark.parametrize("speed_kmh", SPEEDS)
def test_full_model_is_not_detectable_below_100(vehicle, speed_kmh):
    sys = full_system(vehicle, kmh(speed_kmh))
    assert relative_degree(sys) == [2]
    assert is_strongly_detectable(sys) == (speed_kmh > 110)


def test_case1_loses_detectability_near_120(vehicle):
    assert is_strongly_detectable(case1(vehicle, kmh(100)))
    assert not is_strongly_detectable(case1(vehicle, kmh(120)))


def test_zeros_of_a_known_system():
    # G(s) = (s + 3) / ((s + 1)(s + 2)) in controllable form: one zero at -3.
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    sys = UnknownInputSystem(A, np.array([[0.0], [1.0]]), np.array([[3.0, 1.0]]))
    assert np.allclose(invariant_zeros(sys), [-3.0])
    assert relative_degree(sys) == [1]


def test_relative_degree_detects_a_chain():
    A = np.diag([1.0, 1.0], k=1)  # triple integrator
    sys = UnknownInputSystem(A, np.array([[0.0], [0.0], [1.0]]), np.array([[1.0, 0.0, 0.0]]))
    assert relative_degree(sys) == [3]
    assert len(invariant_zeros(sys)) == 0


def test_modes_are_named(vehicle):
    result = analyze(vehicle, [20, 100])
    names20 = {m["name"] for m in result["results"][0]["modes"]}
    assert {"wobble", "weave", "capsize"} <= names20
    weave20 = next(m for m in result["results"][0]["modes"] if m["name"] == "weave")
    assert not weave20["stable"] and 0.3 < weave20["frequency_hz"] < 1.0
    wobble100 = next(m for m in result["results"][1]["modes"] if m["name"] == "wobble")
    assert 8.0 < wobble100["frequency_hz"] < 10.0


def test_mode_classification_on_synthetic_spectrum():
    modes = classify_modes(np.array([-10 + 60j, -10 - 60j, -2 + 10j, -2 - 10j, -0.5, -150.0]), 30.0, (0.2, 0.2))
    assert [m.name for m in modes] == ["wobble", "weave", "capsize", "tyre relaxation"]


def test_analyze_cli_json_shape():
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "analyze", "--speeds", "20,50,80,100,120", "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    data = json.loads(proc.stdout)
    assert data["speeds_kmh"] == SPEEDS
    assert len(data["results"]) == 5
    for r in data["results"]:
        assert set(r) >= {"speed_kmh", "eigenvalues", "zeros", "relative_degree_case2", "decoupling_det"}
        assert len(r["eigenvalues"]) == 8 and all(len(e) == 2 for e in r["eigenvalues"])
        assert set(r["zeros"]) == {"full", "case1", "case2"}
        assert r["relative_degree_case2"] == [2, 1]
        assert max(z[0] for z in r["zeros"]["case2"]) < 0


def test_analyze_cli_table():
    proc = subprocess.run([sys.executable, "-m", "ptw_rt.cli", "analyze"], capture_output=True, text=True, check=True)
    assert "wobble" in proc.stdout and "weave" in proc.stdout and "NON-minimum phase" in proc.stdout


def test_bad_speeds_argument():
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "analyze", "--speeds", "fast"], capture_output=True, text=True
    )
    assert proc.returncode == 2 and "comma-separated" in proc.stderr


# ---- the payload against softer tyres (ptw_rt.design.payload; docs/estimator.md, "The payload")

SHORT_RIDE_S = 5.0  # of the study's 10 s: the same shape of answer at a quarter of the cost


def _payload_ride(settings, model: str, added_mass: float) -> dict:
    from ptw_rt.design.payload import compare, loaded

    p = settings.vehicle
    a = loaded(p, added_mass, model)
    return compare(p, a, 30.0, 0.28, np.array(settings.estimator.kalman.measurement_sd()), duration=SHORT_RIDE_S)


def test_the_file_against_itself_leaves_nothing_unexplained(settings):
    r = _payload_ride(settings, "point_mass", 0.0)
    assert abs(r["best_tyre_scale"] - 1.0) < 0.01
    assert r["chi2_best_tyres"] < 1e-3 * r["chi2_reference"]
    assert r["chi2_reference"] > 100.0  # the ride does tell the file's tyres from 15 % softer ones


def test_a_heavier_rider_of_the_same_build_reads_as_tyres_scaled_by_the_mass_ratio(settings):
    """Every force row scales with the mass; where the inertias grow with it too, what is left to tell the mass
    from the tyres is a few per cent of a tyre error (a real rider); a point mass that adds no inertia leaves more
    in the gyros (the simulator's payload)."""
    p = settings.vehicle
    grown = _payload_ride(settings, "rear_frame_grown", 50.0)
    point = _payload_ride(settings, "point_mass", 50.0)
    assert abs(grown["best_tyre_scale"] - p.mass / (p.mass + 50.0)) < 0.03
    assert grown["equivalent_tyre_error_pct"] < 5.0
    assert point["chi2_best_tyres"] > 3.0 * grown["chi2_best_tyres"]
    gyros = point["chi2_best_tyres_per_output"]
    assert gyros["yaw_rate"] + gyros["roll_rate"] > 0.5 * point["chi2_best_tyres"]


def test_analyze_payload_refuses_a_mass_beyond_the_configs_range():
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "analyze", "--payload", "400"], capture_output=True, text=True
    )
    assert proc.returncode == 2 and "[-150, 300] kg" in proc.stderr and "Traceback" not in proc.stderr


def test_analyze_payload_a_vehicle_cannot_take_is_one_line(tmp_path):
    from ptw_rt.paths import DEFAULT_CONFIG

    text = DEFAULT_CONFIG.read_text(encoding="utf-8")
    light = text.replace("    mass: 292.2 ", "    mass: 140.0 ").replace(
        "  front_vertical_load: 1817.7 ", "  front_vertical_load: 700.0 "
    )
    assert light != text and light.count("140.0") == 1 and light.count("700.0 ") == 1
    config = tmp_path / "light.yaml"
    config.write_text(light, encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "analyze", "--payload", "-150", "--config", str(config)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and "too little of rear_frame.mass" in proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
