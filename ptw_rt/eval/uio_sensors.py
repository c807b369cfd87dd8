"""Offline figures of the UIHOSMO-on-sensors stage (issue #16) against the old case-2 observer, per scenario.

The stage is driven here as the step drives it, from the ride's samples: steer from the 10-bit encoder count,
and the channel's own kinematics (`ptw_rt.core.channel_kinematics`: roll, ground yaw rate, roll rate and the
centre of mass's lateral acceleration from the raw IMU, the pitch and yaw gyros and the lateral accelerometer less
the attitude filter's bias estimates as in the step) with the estimator's conditioned speed. Offline there
are no input checks: a frame the step would hold (`sensor_faults`) is taken as it comes. Errors are scored as
`ptw-rt evaluate` does (after 5 s, above the validity speed). The old case-2 figures are the estimator's own
diagnostics (E_ROLL_UIHOSMO, E_TORQUE_UIHOSMO) on the same ride.

    python -m ptw_rt.eval.uio_sensors [SCENARIO ...]
"""

from __future__ import annotations

import math
import sys

import numpy as np

from ptw_rt.core import channel_kinematics as ck
from ptw_rt.core import layout as L  # noqa: N812
from ptw_rt.core import uio_sensors as cus
from ptw_rt.core.conditioning import steer_angle
from ptw_rt.eval.evaluate import SETTLE_S, Evaluation, evaluate_ride


def drive_stage(ev: Evaluation, design, settings):
    """(N, OUT_SIZE) outputs of the stage over the evaluation's cycles."""
    E, S = ev.estimates, ev.samples
    st, out = cus.new_state(), cus.new_output()
    ch_st, ch_prm, ch = np.zeros(ck.STATE_SIZE), ck.build_params(settings, design), np.zeros(ck.OUT_SIZE)
    zero, cpr = settings.sensors.steer_zero_count, settings.sensors.steer_counts_per_rev
    prm, tables = cus.stage_params(design, steer_quantum=settings.sensors.steer_count_rad), cus.stage_tables(design)
    R = np.zeros((len(ev.t), cus.OUT_SIZE))
    for k in range(len(ev.t)):
        ck.channel_kinematics_step(
            ch_st,
            ch_prm,
            ch,
            S[k, L.S_ROLL_RATE_BODY],
            S[k, L.S_PITCH_RATE_BODY] - E[k, L.E_PITCH_GYRO_BIAS],  # as the step: the attitude filter's calibrations
            S[k, L.S_YAW_RATE_BODY] - E[k, L.E_YAW_GYRO_BIAS],
            S[k, L.S_ACCEL_Y] - E[k, L.E_LAT_ACCEL_BIAS],
            S[k, L.S_ACCEL_Z],
            E[k, L.E_SPEED],
            True,
        )
        if ch[ck.OUT_VALID] == 0.0:
            continue
        cus.uio_sensors_step(
            st,
            out,
            prm,
            *tables,
            steer_angle(S[k, L.S_STEER_COUNT], zero, cpr),
            ch[ck.OUT_YAW_RATE],
            ch[ck.OUT_ROLL_RATE],
            ch[ck.OUT_A_Y],
            ch[ck.OUT_ROLL],
            E[k, L.E_SPEED],
        )
        R[k] = out
    return R


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


def score(ev: Evaluation, R: np.ndarray, min_speed: float) -> dict[str, float]:
    m = (ev.t >= SETTLE_S) & (ev.truth["speed"] >= min_speed)
    roll, tau = ev.truth["roll"][m], ev.truth["rider_torque"][m]
    peak = float(np.max(np.abs(tau)))
    E = ev.estimates[m]
    return {
        "roll_rmse_deg": math.degrees(_rms(R[m, cus.OUT_ROLL] - roll)),
        "torque_rmse_nm": _rms(R[m, cus.OUT_TORQUE] - tau),
        "torque_peak_nm": peak,
        "torque_pct_of_peak": 100.0 * _rms(R[m, cus.OUT_TORQUE] - tau) / peak,
        "case2_roll_rmse_deg": math.degrees(_rms(E[:, L.E_ROLL_UIHOSMO] - roll)),
        "case2_torque_pct_of_peak": 100.0 * _rms(E[:, L.E_TORQUE_UIHOSMO] - tau) / peak,
        "fusion_torque_pct_of_peak": 100.0 * _rms(E[:, L.E_RIDER_TORQUE] - tau) / peak,
    }


def evaluate_scenario(name: str) -> dict[str, float]:
    from ptw_rt.design.file import load_design_for
    from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN
    from ptw_rt.settings import load_settings
    from ptw_rt.sim.ride import simulate

    settings = load_settings(DEFAULT_CONFIG)
    design = load_design_for(settings, DEFAULT_DESIGN, DEFAULT_CONFIG)
    ev = evaluate_ride(simulate(name))
    R = drive_stage(ev, design, settings)
    return score(ev, R, settings.estimator.min_valid_speed_kmh / 3.6)


def main(argv: list[str]) -> int:
    from ptw_rt.sim.scenarios import SCENARIOS

    names = argv or list(SCENARIOS)
    print(
        f"{'scenario':<16} {'roll':>6} {'tau':>6} {'tau%pk':>7} {'peak':>6} | {'case2 roll':>10} {'tau%pk':>7} | "
        "fusion tau%pk"
    )
    for name in names:
        r = evaluate_scenario(name)
        print(
            f"{name:<16} {r['roll_rmse_deg']:6.2f} {r['torque_rmse_nm']:6.2f} {r['torque_pct_of_peak']:7.1f} "
            f"{r['torque_peak_nm']:6.1f} | {r['case2_roll_rmse_deg']:10.2f} {r['case2_torque_pct_of_peak']:7.0f} | "
            f"{r['fusion_torque_pct_of_peak']:6.1f}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
