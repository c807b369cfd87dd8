"""The lateral stage alone: the fusion filter on a straight ride, its convergence clock, reset on a blow-up."""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import inputs as inp
from ptw_rt.core import kalman as kf
from ptw_rt.core import lateral as lat
from ptw_rt.core import layout as lay
from ptw_rt.core import speed as spd
from ptw_rt.core import tyre_bank as tb


def _step(b, cond, accel=1.0, attitude_ok=1.0, rates=1.0, steer_ok=1.0, imu_ok=1.0, steer_trusted=None, reasons=0):
    flags = {"accel_trusted": accel, "rates_ok": rates, "steer_ok": steer_ok, "imu_ok": imu_ok, "core_ok": 1.0}
    flags["steer_trusted"] = steer_ok if steer_trusted is None else steer_trusted
    flags["reasons"] = float(reasons)
    inputs = inp.OUTPUTS.vector(flags, strict=False)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=20.0, known=1.0
    )
    attitude = att.OUTPUTS.vector({"ok": attitude_ok}, strict=False)
    lat.lateral_stage(b.state, b.params, b.outputs, b.tables, b.tindex, 0, inputs, speed, attitude, cond)
    return b.outputs


def test_straight_upright_ride_stays_at_zero_and_the_clock_runs(settings, design):
    b = lat.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0}, strict=False)
    for _ in range(200):
        out = _step(b, cond)
    z = out[lat.OUT_Z : lat.OUT_Z + kf.N_Z]
    np.testing.assert_allclose(z, 0.0, atol=1e-9)
    assert out[lat.OUT_RUN_TIME] == pytest.approx(2.0)
    # no accelerometer, no attitude filter this cycle: their rows predict themselves, nothing moves
    out = _step(b, cond, accel=0.0, attitude_ok=0.0)
    np.testing.assert_allclose(out[lat.OUT_Z : lat.OUT_Z + kf.N_Z], 0.0, atol=1e-9)
    # stopping the observers restarts the clock and zeroes everything (a diagnostic observer's reset does not:
    # the stage does not even see the diagnostics)
    out = _step(b, cnd.OUTPUTS.vector({"run": 0.0}, strict=False))
    assert out[lat.OUT_RUN_TIME] == 0.0 and not np.any(out[lat.OUT_Z : lat.OUT_Z + kf.N_Z])


def test_a_start_waits_for_this_cycles_rates(settings, design):
    """After a silence the first rates frame waits for the next to confirm it (`inputs`): the rates of that cycle
    are the held ones, and filters started on them took the step as torque. The start waits one cycle."""
    b = lat.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0}, strict=False)
    out = _step(b, cond, rates=0.0)
    assert out[lat.OUT_RAN] == 0.0 and out[lat.OUT_RUN_TIME] == 0.0
    out = _step(b, cond)
    assert out[lat.OUT_RAN] == 1.0 and out[lat.OUT_RUN_TIME] == pytest.approx(0.01)
    out = _step(b, cond, rates=0.0)  # running: a cycle without new rates goes on
    assert out[lat.OUT_RAN] == 1.0 and out[lat.OUT_RUN_TIME] == pytest.approx(0.02)


@pytest.mark.parametrize(("silent", "limit"), [("steer", lat.MAX_STEER_COAST), ("imu", lat.MAX_IMU_COAST)])
def test_a_silent_sensor_is_coasted_through_for_its_limit(settings, design, silent, limit):
    """The observers stopped (conditioning's run 0) by one silent sensor while the other is there: the filters
    coast for the sensor's limit (the clock held at 0: nothing VALID), then stop; one cycle of both back restarts
    the clock."""
    b = lat.STAGE.alone(settings, design)
    running = cnd.OUTPUTS.vector({"run": 1.0}, strict=False)
    for _ in range(100):
        _step(b, running)
    flags = {"steer_ok": 0.0} if silent == "steer" else {"imu_ok": 0.0, "rates": 0.0}
    stopped = cnd.OUTPUTS.vector({"run": 0.0}, strict=False)
    n = int(round(limit / 0.01))
    for _ in range(n):
        out = _step(b, stopped, **flags)
        assert out[lat.OUT_RAN] == 1.0 and out[lat.OUT_RUN_TIME] == 0.0
    out = _step(b, stopped, **flags)
    assert out[lat.OUT_RAN] == 0.0 and not np.any(out[lat.OUT_Z : lat.OUT_Z + kf.N_Z])
    out = _step(b, running)
    assert out[lat.OUT_RAN] == 1.0 and out[lat.OUT_RUN_TIME] == pytest.approx(0.01)
    # both silent, or the speed below the model's: no coast
    for stop in ({"steer_ok": 0.0, "imu_ok": 0.0, "rates": 0.0}, {}):
        _step(b, running)
        speed_low = cnd.OUTPUTS.vector({"run": 0.0, "speed_low": 0.0 if stop else 1.0}, strict=False)
        assert _step(b, speed_low, **stop)[lat.OUT_RAN] == 0.0


def test_a_steady_roll_measurement_is_followed(settings, design):
    b = lat.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0, "deroll": 0.05}, strict=False)
    for _ in range(500):
        out = _step(b, cond)
    assert 0.0 < out[lat.OUT_Z + kf.PHI] <= 0.05 + 1e-6


def test_a_blown_up_filter_is_reset_and_says_so(settings, design):
    b = lat.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0, "roll_last": 0.1, "steer": 0.02, "yaw_rate": 0.03}, strict=False)
    _step(b, cond)
    H = len(design.tb_scale)
    for first in (0, tb._published0(H)):  # every evidence filter of the bank, or every publishing one
        state = b.state.copy()
        for h in range(H):
            b.state[lat.ST_BANK + first + h * tb.BLOCK : lat.ST_BANK + first + h * tb.BLOCK + kf.N_Z] = 1e12
        out = _step(b, cond)
        assert out[lat.OUT_DIVERGED] == 1.0
        assert out[lat.OUT_Z + kf.PHI] == 0.1 and out[lat.OUT_Z + kf.DELTA] == 0.02 and out[lat.OUT_Z + kf.TAU] == 0.0
        assert _step(b, cond)[lat.OUT_DIVERGED] == 0.0
        b.state[:] = state


def _share(b, yaw_rate_sd, a_y_of_t, u=14.0, seconds=20.0, a_y_sd=0.0):
    """The bias share over the last 6 s of a ride of `seconds`: its largest value (the phase of a turn where
    learning would wait longest)."""
    st = b.state.copy()
    dt = b.params[lat.P_DT]
    shares = [lat._bias_share(st, b.params, yaw_rate_sd, a_y_sd, a_y_of_t(k * dt), u) for k in range(int(seconds / dt))]
    return max(shares[-int(6.0 / dt) :])


def test_no_tyre_learning_on_a_yaw_gyro_bias_the_attitude_filter_has_not_pinned_down(settings, design):
    """The slip angles are measured against the kinematic steer L r / (u cos caster): in a one-way corner a yaw
    rate 0.01 rad/s off (the attitude filter's spread in its first seconds) moves k by ~30 % per sd (it read a
    wet road's x0.9 as x1.75 and published it VALID); once the bias is known (spread 0.0006 rad/s) it does not;
    riding left and right the shift averages out of the fit, but only over corners within `bias_window` (2 s): the
    bank's posterior can collapse within one corner. Random route 830215172 (noise seed 8639, corners every 3 s at
    11 m/s) learned with the yaw rate 0.0037 rad/s unsure (its gyro 0.002 rad/s off) and was VALID 32 % off with
    the 5 s window."""
    b = lat.STAGE.alone(settings, design)
    limit = b.params[lat.P_MAX_LEARNING_BIAS_SHARE]
    one_way = lambda t: 1.8 + 0.6 * np.sin(2.0 * np.pi * t / 6.0)  # noqa: E731 (mu_drop's weave about a corner)
    assert _share(b, 0.01, one_way) > 2.5 * limit
    assert _share(b, 0.0006, one_way) < limit
    slalom = lambda t: 2.0 * np.sin(2.0 * np.pi * t / 3.6)  # noqa: E731
    assert _share(b, 0.003, slalom, u=8.3) < limit  # in a one-way corner at that speed: 0.15
    assert _share(b, 0.005, slalom, u=8.3) > limit
    route = lambda t: 1.5 * np.sin(2.0 * np.pi * t / 6.0)  # noqa: E731
    assert _share(b, 0.0037, route, u=11.1) > 1.3 * limit  # 0.07 over a 5 s window
    assert _share(b, 0.0015, route, u=11.1) < limit
    # an accelerometer bias the attitude filter is unsure of (0.05 m/s^2) matters in a gentle bend, not a corner
    assert _share(b, 0.0, lambda t: 0.3, a_y_sd=0.05) > limit
    assert _share(b, 0.0, one_way, a_y_sd=0.05) < limit


def test_the_tyre_evidence_count_fades_with_the_banks_memories(settings, design):
    """What the supervisor's tyre validity rests on: seconds of learning cycles, faded with the bank's learning
    memory while it learns (tau (1 - exp(-t / tau))) and with its idle memory otherwise; a restart zeroes it."""
    b = lat.STAGE.alone(settings, design)
    st, dt = b.state.copy(), b.params[lat.P_DT]
    tun = settings.estimator.tyre_bank
    for _ in range(int(round(2.0 / dt))):
        count = lat._count_evidence(st, b.params, True)
    assert count == pytest.approx(tun.learning_memory * (1.0 - np.exp(-2.0 / tun.learning_memory)), rel=1e-3)
    for _ in range(int(round(30.0 / dt))):
        faded = lat._count_evidence(st, b.params, False)
    assert faded == pytest.approx(count * np.exp(-30.0 / tun.idle_memory), rel=1e-3)
    lat.reset(st, b.params)
    assert st[lat.ST_TYRE_EVIDENCE] == 0.0


@pytest.mark.parametrize("axle", [0, 1])
@pytest.mark.parametrize("mu", [1.0, 0.5])
def test_the_slope_ratio_is_the_saturating_tyres_slope_over_its_small_slip_stiffness(settings, design, axle, mu):
    """The simulator's tyre law (a Magic Formula whose peak is mu F_z and whose small-slip slope is mu C): at a
    working point (alpha, gamma), dF/dalpha / (mu C_alpha) is what `_slope_ratio` gives from the force, the lean
    and k = mu alone. That is what the published scale is corrected by (the data measure the slope there)."""
    from ptw_rt.sim.tyres import TyreShape, lateral_force

    b = lat.STAGE.alone(settings, design)
    prm = b.params
    shape = TyreShape()
    fz = prm[lat.P_AXLE_LOAD + axle]
    c_alpha, c_gamma = prm[lat.P_NOMINAL + 2 * axle], prm[lat.P_NOMINAL + 2 * axle + 1]

    def force(alpha, gamma):
        f, _ = lateral_force(alpha, gamma, mu, fz, c_alpha, c_gamma, shape.slip_shape, shape.camber_shape, 0.05)
        return f

    h = 1e-6
    for alpha, gamma in [(0.0, 0.0), (0.004, 0.05), (0.01, 0.14), (-0.01, -0.14), (0.02, 0.1), (-0.005, 0.2)]:
        slope = (force(alpha + h, gamma) - force(alpha - h, gamma)) / (2.0 * h) / (mu * c_alpha)
        got = lat._slope_ratio(prm, axle, mu, force(alpha, gamma), gamma)
        assert got == pytest.approx(slope, abs=1e-4), (alpha, gamma)
    # at a third of a wet road's grip the slope is well below the small-slip stiffness: what the data measure
    assert lat._slope_ratio(prm, axle, 0.5, 0.17 * fz, 0.13) < 0.95


def test_the_published_scale_is_the_banks_over_the_mean_slope_ratio_of_what_it_learned_from(settings, design):
    """The faded mean of the learning cycles' slope ratios divides the bank's scale; its log, times
    `saturation_uncertainty`, joins the published spread. Nothing learned: no correction. A new prior forgets it.
    A force the law cannot produce (a NaN, or beyond the peak) corrects by at most 1 / MIN_SLOPE_RATIO."""
    b = lat.STAGE.alone(settings, design)
    st, prm = b.state, b.params
    fz_f, fz_r = prm[lat.P_AXLE_LOAD], prm[lat.P_AXLE_LOAD + 1]
    assert st[lat.ST_SLOPE_WEIGHT] == 0.0
    for _ in range(300):  # a wet road's working point, k 0.5
        lat._learn_slope_ratio(st, prm, 0.45, 0.15 * fz_f, 0.16 * fz_r, 0.13)
        st[lat.ST_SMALL_SLIP_SCALE] = 0.45 / (st[lat.ST_SLOPE_SUM] / st[lat.ST_SLOPE_WEIGHT])
    ratio = st[lat.ST_SLOPE_SUM] / st[lat.ST_SLOPE_WEIGHT]
    expected = 0.5 * (
        lat._slope_ratio(prm, 0, st[lat.ST_SMALL_SLIP_SCALE], 0.15 * fz_f, 0.13)
        + lat._slope_ratio(prm, 1, st[lat.ST_SMALL_SLIP_SCALE], 0.16 * fz_r, 0.13)
    )
    assert ratio == pytest.approx(expected, rel=1e-3)  # the fixed point: the peak from the published scale
    assert 0.85 < ratio < 0.97
    out = _step(b, cnd.OUTPUTS.vector({"run": 0.0}, strict=False))  # the bank idle: its prior's centre, 1.0
    assert out[lat.OUT_TYRE_SLOPE_RATIO] == pytest.approx(ratio)
    assert out[lat.OUT_TYRE_SCALE] == pytest.approx(1.0 / ratio)
    np.testing.assert_allclose(
        out[lat.OUT_TYRE_STIFFNESS : lat.OUT_TYRE_STIFFNESS + 4], prm[lat.P_NOMINAL : lat.P_NOMINAL + 4] / ratio
    )
    sd = np.hypot(prm[lat.P_PRIOR_SD], prm[lat.P_SATURATION_UNCERTAINTY] * np.log(1.0 / ratio))
    assert out[lat.OUT_TYRE_LOG_SD] == pytest.approx(sd)
    lat.set_prior(st, prm, design.tb_scale, 1.0, restored=False)
    assert st[lat.ST_SLOPE_WEIGHT] == 0.0 and st[lat.ST_SMALL_SLIP_SCALE] == 0.0
    for force in (float("nan"), 5.0 * fz_f):
        lat._learn_slope_ratio(st, prm, 1.0, force, force, 0.0)
    assert st[lat.ST_SLOPE_SUM] / st[lat.ST_SLOPE_WEIGHT] >= lat.MIN_SLOPE_RATIO


def test_the_learning_gates_longitudinal_acceleration_is_the_accelerometers_beyond_its_offset_low_passed(
    settings, design
):
    """`_long_accel`: the accelerometer's x less the speed stage's offset against GPS (its bias and the grade), over
    LONG_ACCEL_TIME; held while the accelerometer is not there (a NaN never enters). Beyond
    `max_learning_long_accel` (3 m/s^2) the tyres do not learn: load moves between the axles."""
    b = lat.STAGE.alone(settings, design)
    st, prm = b.state, b.params
    assert prm[lat.P_MAX_LEARNING_LONG_ACCEL] == pytest.approx(settings.estimator.tyre_bank.max_learning_long_accel)
    speed = spd.OUTPUTS.vector({"u": 20.0, "accel_offset": 0.4}, strict=False)

    def inputs(a_x, ok=1.0):
        v = inp.OUTPUTS.vector({"accel_ok": ok}, strict=False)
        v[inp.OUT_RAW + inp.RAW_AX] = a_x
        return v

    for _ in range(int(round(3.0 / prm[lat.P_DT]))):  # braking at 4 m/s^2 on a grade the offset holds
        a = lat._long_accel(st, prm, inputs(-3.6), speed)
    assert a == pytest.approx(-4.0, abs=1e-3)
    assert lat._long_accel(st, prm, inputs(float("nan")), speed) == pytest.approx(a)
    assert lat._long_accel(st, prm, inputs(5.0, ok=0.0), speed) == pytest.approx(a)
    n = int(round(lat.LONG_ACCEL_TIME / prm[lat.P_DT]))
    for _ in range(n):
        a = lat._long_accel(st, prm, inputs(0.4), speed)
    assert -4.0 * np.exp(-0.9) < a < -4.0 * np.exp(-1.1)  # 1/e of it left after LONG_ACCEL_TIME


def _observed(b, a_y: float, reasons: int = 0, steer_trusted: float = 1.0) -> float:
    """One cycle riding straight at 20 m/s with the lateral acceleration `a_y`; the tyre filters' short-window NIS."""
    cond = cnd.OUTPUTS.vector({"run": 1.0, "a_y": a_y}, strict=False)
    return float(_step(b, cond, steer_trusted=steer_trusted, reasons=reasons)[lat.OUT_TYRE_NIS_FAST])


def test_no_tyre_evidence_within_the_quiet_time_after_an_input_fault_nor_from_a_held_steer(settings, design):
    """In a burst of corrupt frames a garbage payload whose counter matched passes its own checks; a cycle whose
    other frames were sound took it as a measurement (`sensor_faults`: -15 m/s^2 put the tyre filters' NIS at 30
    and the stiffness lost VALID for 2.5 s). The filters' innovations are evidence only INPUT_QUIET_TIME after the
    last input fault, and not while the steer is held."""
    b = lat.STAGE.alone(settings, design)
    for _ in range(400):
        _observed(b, 0.0)
    _observed(b, 0.0, reasons=lay.REASON_COUNTER_JUMPS)
    quiet = int(round(lat.INPUT_QUIET_TIME / b.params[lat.P_DT]))
    for _ in range(quiet - 2):
        calm = _observed(b, 0.0)
    assert _observed(b, -15.0) == calm  # within the quiet time: no evidence
    for _ in range(quiet):
        calm = _observed(b, 0.0)
    assert _observed(b, -15.0, steer_trusted=0.0) == calm  # the steer held: no evidence
    assert _observed(b, -15.0) > 100.0 * max(calm, 1.0)  # after it: the garbage is seen for what it is
