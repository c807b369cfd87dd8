"""Configuration loading: the default file, and a clear message for every kind of error."""

from __future__ import annotations

import copy
import subprocess
import sys

import pytest
import yaml

from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.schema import ConfigError, canonical_hash
from ptw_rt.settings import load_settings

RAW = yaml.safe_load(DEFAULT_CONFIG.read_text())


def write(tmp_path, doc, text=None):
    path = tmp_path / "vehicle.yaml"
    path.write_text(text if text is not None else yaml.safe_dump(doc))
    return path


def mutated(**changes):
    doc = copy.deepcopy(RAW)
    for dotted, value in changes.items():
        *parents, leaf = dotted.split("__")
        node = doc
        for key in parents:
            node = node[key]
        if value is DELETE:
            del node[leaf]
        else:
            node[leaf] = value
    return doc


DELETE = object()


def test_default_config_loads(settings):
    assert settings.vehicle.name == "big-scooter"
    assert settings.vehicle.mass == pytest.approx(303.31)
    assert len(settings.config_hash) == 64


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"vehicle__front_frame__mass": DELETE}, "vehicle.front_frame.mass: missing required key"),
        ({"vehicle__front_frame__mass": -3.0}, "vehicle.front_frame.mass: must be > 0"),
        ({"vehicle__rear_frame__mass": 0}, "vehicle.rear_frame.mass: must be > 0"),
        ({"vehicle__steering__trail": "long"}, "vehicle.steering.trail: expected a number"),
        ({"vehicle__front_tyre__cornering_stiffnes": 1.0}, "unknown key (did you mean 'cornering_stiffness'?)"),
        ({"vehicle__front_tyre__relaxation_length": float("nan")}, "must be finite"),
        ({"vehicle__steering__caster_deg": 75}, "vehicle.steering.caster_deg: must be < 60"),
        ({"vehicle__front_vertical_load": 5000.0}, "more than the whole vehicle's weight"),
        ({"vehicle__rear_frame__inertia_xz": 40.0}, "not positive definite"),
        ({"vehicle__name": 12}, "vehicle.name: expected text"),
        ({"estimator__speed_grid__max_kmh": 5}, "max_kmh must be above min_kmh"),
        ({"estimator__min_valid_speed_kmh": 5}, "below the design grid"),
        ({"estimator__adaptive__adaptation_gain": [1, 2, 3]}, "expected 4..4 items"),
        ({"estimator__adaptive__adaptation_gain": ["2.0e5", 1, 1, 1]}, "write 2.0e+5"),
        ({"estimator": DELETE}, "estimator: missing required key"),
        # nonsense tuning that designed STABLE and ran: a steer noise of 1e-300 rad published the torque VALID at
        # 209 % of the peak with the wrong sign; a validity speed beyond the grid, never valid
        ({"estimator__fusion_filter__steer_noise": 1e-300}, "steer_noise: must be >= 1e-05"),
        ({"estimator__fusion_filter__process_noise": 1e300}, "process_noise: must be <= 1"),
        ({"estimator__uihosmo__differentiator_lambda": 1e300}, "differentiator_lambda: must be <= 100000"),
        ({"estimator__roll_fusion_time_constant": 1e-300}, "roll_fusion_time_constant: must be >= 0.01"),
        ({"estimator__min_valid_speed_kmh": 200}, "above the design grid"),
        ({"sensors": {"steer_counts_per_rev": 1}}, "steer_counts_per_rev: must be >= 64"),
        ({"vehicle__front_tyre__cornering_stiffness": 1e-300}, "cornering_stiffness: must be >= 10"),
        ({"sensors": {"steer_counts_per_rev": 256}}, "steer_zero_count (512.0) must be below steer_counts_per_rev"),
        ({"vehicle__added_mass": 400}, "vehicle.added_mass: must be <= 300"),
        ({"vehicle__added_mass": "heavy"}, "vehicle.added_mass: expected a number"),
        ({"vehicle__added_mass": -140, "vehicle__rear_frame__mass": 150}, "added_mass: -140 kg leaves too little of"),
    ],
)
def test_config_errors_name_the_key(tmp_path, changes, message):
    path = write(tmp_path, mutated(**changes))
    with pytest.raises(ConfigError) as err:
        load_settings(path)
    assert message in str(err.value)
    assert str(path) in str(err.value)


def test_added_mass_is_the_simulators_payload(tmp_path, settings):
    """A rider 50 kg heavier set in the file is the vehicle the simulator rides with `added_mass=50`: one lever rule
    (`VehicleParameters.with_added_mass`); without the key the file is as before (it is optional, 0)."""
    from ptw_rt.sim.ride import parse_perturbations, perturbed_vehicle

    heavy = load_settings(write(tmp_path, mutated(vehicle__added_mass=50))).vehicle
    assert heavy == perturbed_vehicle(settings.vehicle, parse_perturbations(["added_mass=50"]))
    assert heavy.mass == pytest.approx(settings.vehicle.mass + 50)
    assert heavy.front_load > settings.vehicle.front_load and heavy.rear_load > settings.vehicle.rear_load
    assert load_settings(write(tmp_path, mutated(vehicle__added_mass=DELETE))).vehicle == settings.vehicle


def test_a_payload_changes_the_design_but_not_whose_learned_state_is_restored(tmp_path, settings):
    """`learned_state_hash` (the state file's key beside the config hash) leaves the payload out: a pillion's file
    needs its own design but restores what the rider's file learned (the same tyres and sensors). Anything else of
    the vehicle or the tuning changes both, and so does a file that writes the default payload out."""
    pillion = load_settings(write(tmp_path, mutated(vehicle__added_mass=75)))
    assert pillion.config_hash != settings.config_hash
    assert pillion.learned_state_hash == settings.learned_state_hash
    assert load_settings(write(tmp_path, mutated(vehicle__added_mass=DELETE))).learned_state_hash == (
        settings.learned_state_hash
    )
    for change in ({"vehicle__front_tyre__cornering_stiffness": 25000.0}, {"vehicle__rear_frame__mass": 300.0}):
        other = load_settings(write(tmp_path, mutated(**change)))
        assert other.learned_state_hash != settings.learned_state_hash and other.config_hash != settings.config_hash


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="configuration file not found"):
        load_settings(tmp_path / "nope.yaml")


def test_invalid_yaml_reports_the_line(tmp_path):
    path = write(tmp_path, None, text="vehicle:\n  name: x\n   bad: [1, 2\n")
    with pytest.raises(ConfigError, match=r"not valid YAML at line \d+"):
        load_settings(path)


def test_not_a_mapping(tmp_path):
    path = write(tmp_path, None, text="- just\n- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_settings(path)


def test_cli_reports_config_errors_without_traceback(tmp_path):
    path = write(tmp_path, mutated(vehicle__front_frame__mass=-1))
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "analyze", "--config", str(path)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert "vehicle.front_frame.mass: must be > 0" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_hash_ignores_formatting_but_not_values(tmp_path):
    a = load_settings(write(tmp_path, RAW))
    reformatted = tmp_path / "b.yaml"
    reformatted.write_text(yaml.safe_dump(RAW, default_flow_style=True, sort_keys=False))
    assert load_settings(reformatted).config_hash == a.config_hash
    changed = load_settings(write(tmp_path, mutated(vehicle__front_tyre__cornering_stiffness=20000)))
    assert changed.config_hash != a.config_hash
    assert canonical_hash({"a": 1.0, "b": [1, 2]}) == canonical_hash({"b": [1, 2], "a": 1.0})
