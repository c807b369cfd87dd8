"""UIHOSMO on the real sensors (issue #16): analysis of the output sets, the design, the jitted stage alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptw_rt.core import uio_sensors as cus
from ptw_rt.design import uio_sensors as dus
from ptw_rt.design.discretize import zoh
from ptw_rt.design.file import load_design
from ptw_rt.design.output_sets import CANDIDATES, analyze_outputs, parse_candidates
from ptw_rt.model.sharp import kmh, state_space
from ptw_rt.paths import DEFAULT_DESIGN


@pytest.fixture(scope="module")
def design():
    return load_design(DEFAULT_DESIGN)


def torque_pulse(t):
    return 15.0 * np.sin(2 * np.pi * 0.5 * t) * np.exp(-(((t - 3.0) / 1.2) ** 2))


def run_linear(vehicle, design, speed_kmh, duration=8.0, settle=2.0):
    """The linear Sharp model at 2 kHz, exact samples of every sensor every 10 ms."""
    u = kmh(speed_kmh)
    A, B = state_space(vehicle, u)
    h = 0.0005
    Phi, Gam = zoh(A, B[:, None], h)
    stride = int(round(design.sample_time / h))
    x = np.zeros(8)
    st, out = cus.new_state(), cus.new_output()
    prm, tables = cus.stage_params(design, nonlinear=False), cus.stage_tables(design)
    err = []
    for k in range(int(duration / h)):
        t = k * h
        tau = torque_pulse(t)
        if k % stride == 0:
            a_y = (x[6] + x[7]) / vehicle.mass
            cus.uio_sensors_step(st, out, prm, *tables, x[1], x[3], x[4], a_y, x[0], u)
            assert np.all(np.isfinite(out)) and out[cus.OUT_VALID] == 1.0
            if t > settle:
                err.append((out[cus.OUT_TORQUE] - tau, out[cus.OUT_ROLL] - x[0]))
        x = Phi @ x + Gam[:, 0] * tau
    e = np.array(err)
    return float(np.sqrt(np.mean(e[:, 0] ** 2))), math.degrees(float(np.sqrt(np.mean(e[:, 1] ** 2))))


@pytest.mark.parametrize("speed_kmh", [30.0, 60.0, 100.0, 125.0])
def test_near_exact_on_the_linear_model(vehicle, design, speed_kmh):
    """Exact samples: the torque of a 15 N m pulse comes back within a few percent."""
    tau_rmse, roll_rmse = run_linear(vehicle, design, speed_kmh)
    assert tau_rmse < 0.5, tau_rmse
    assert roll_rmse < 1e-9  # the roll is the measured input, passed through


def test_layout_and_design_fields(design):
    assert [dus.OUTPUT_NAMES[c] for c in design.us_outputs] == list(dus.CHOSEN_OUTPUTS)
    assert design.us_roll_input == 1
    assert list(design.us_degrees) == [2]
    assert design.us_Phi.shape == (len(design.grid), 7, 7)
    assert design.us_Gamma.shape[2] == len(design.us_observed) + 5
    assert design.us_min_valid_speed >= design.us_detectability_floor
    prm = cus.stage_params(design)
    assert prm.shape == (cus.PARAM_SIZE,) and prm[cus.P_N_OUT] == 1 and prm[cus.P_N_OBS] == 4
    assert cus.STATE_SIZE == cus.ST_TMP + 3 * cus.N_X + cus.MAX_OBS + cus.MAX_OUT + cus.N_D + 5


def test_reset_below_validity_and_hold_on_bad_input(design):
    st, out = cus.new_state(), cus.new_output()
    prm, tables = cus.stage_params(design), cus.stage_tables(design)
    u = 20.0
    for _ in range(5):
        cus.uio_sensors_step(st, out, prm, *tables, 0.01, 0.05, 0.0, 1.0, 0.1, u)
    assert out[cus.OUT_VALID] == 1.0
    before = st.copy()
    cus.uio_sensors_step(st, out, prm, *tables, math.nan, 0.05, 0.0, 1.0, 0.1, u)
    assert out[cus.OUT_VALID] == 0.0
    assert np.array_equal(st[: cus.ST_TMP], before[: cus.ST_TMP])  # held
    cus.uio_sensors_step(st, out, prm, *tables, 0.01, 0.05, 0.0, 1.0, 0.1, 1.0)  # 3.6 km/h
    assert out[cus.OUT_VALID] == 0.0 and st[cus.ST_INIT] == 0.0 and out[cus.OUT_TORQUE] == 0.0


def test_analysis_table(vehicle):
    res = analyze_outputs(vehicle, CANDIDATES, (10, 20, 50, 100, 130))
    by = {("+".join(r["outputs"]), r["unknown_inputs"]): r for r in res["candidates"]}
    case2 = by[("steer+yaw_rate", "phi_tau")]
    assert case2["relative_degrees"] == [2, 1] and case2["not_detectable_at_kmh"] == [10.0]
    assert by[("steer+lat_accel", "phi_tau")]["strongly_detectable"]
    assert by[("roll_rate+lat_accel", "phi_tau")]["strongly_detectable"]
    assert by[("roll_rate+lat_accel", "phi_tau")]["steer_derivative_order"] == 0
    assert not by[("yaw_rate+roll_rate", "phi_tau")]["strongly_detectable"]  # right-half-plane zero near +150
    assert by[("steer", "tau")]["strongly_detectable"] and by[("steer", "tau")]["derivative_orders"] == {"steer": 2}
    assert not any(any(r["feedthrough"]) for r in res["candidates"])  # a_y depends on states only
    # the roll-rate channel carries tau 70 x weaker than the steer channel (eq. 15 gains, N m per unit)
    assert by[("roll_rate", "tau")]["torque_gain_100kmh"][0] > 50 * by[("steer", "tau")]["torque_gain_100kmh"][0]


def test_output_sets_given_by_hand_are_checked_and_analysed_once():
    """`--outputs steer,steer` was analysed as a two-sensor set, and a set repeated (in any order) twice."""
    with pytest.raises(ValueError, match="named twice"):
        parse_candidates("steer,steer", None)
    with pytest.raises(ValueError, match="unknown signal"):
        parse_candidates("steer,speed", None)
    cands = parse_candidates("steer,lat_accel;lat_accel,steer;steer,lat_accel;steer", None)
    assert cands == [(("steer", "lat_accel"), "phi_tau"), (("steer",), "tau"), (("steer",), "tau_state")]


@pytest.mark.slow
def test_within_target_on_the_nonlinear_plant(settings, design):
    """dlc_100 on the realistic plant with the contract's sensors, the roll the channel's own (0.45 deg here)."""
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.eval.uio_sensors import drive_stage, score
    from ptw_rt.sim.ride import simulate

    ev = evaluate_ride(simulate("dlc_100"))
    r = score(ev, drive_stage(ev, design, settings), settings.estimator.min_valid_speed_kmh / 3.6)
    assert r["torque_pct_of_peak"] <= 25.0
    assert r["roll_rmse_deg"] <= 1.5
    assert r["case2_torque_pct_of_peak"] > 50.0  # the old observer on the same ride


def test_a_quantised_steer_is_taken_as_the_cell_it_allows():
    """The encoder rounds: a reading says the steer is within half a count of it, so a prediction inside that cell is
    kept and one outside is moved to the cell's nearer edge."""
    q = 2.0 * math.pi / 1024
    reading = 3 * q
    assert cus._within_reading(reading, reading + 0.3 * q, q) == reading + 0.3 * q
    assert cus._within_reading(reading, reading - 0.49 * q, q) == reading - 0.49 * q
    assert cus._within_reading(reading, reading + 2.0 * q, q) == pytest.approx(reading + 0.5 * q)
    assert cus._within_reading(reading, reading - 2.0 * q, q) == pytest.approx(reading - 0.5 * q)


def test_the_step_is_told_the_encoders_count(settings, design):
    from ptw_rt.core import diagnostics

    prm = diagnostics.build_params(settings, design)
    us = prm[diagnostics.P_US : diagnostics.P_US + cus.PARAM_SIZE]
    assert us[cus.P_STEER_QUANTUM] == pytest.approx(2.0 * math.pi / settings.sensors.steer_counts_per_rev)
    assert cus.stage_params(design)[cus.P_STEER_QUANTUM] == 0.0  # a continuous steer unless told
