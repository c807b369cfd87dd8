"""Seed 000's UIHOSMO on the sensors, wired into the step, and the plausibility monitor it feeds (issue #16).

The published rider torque (the tyre bank's fusion filters) and the UIHOSMO's (model inversion through the
steer angle's second derivative) take structurally different paths from the same sensors; the supervisor
compares them (windowed RMS residual against a threshold per speed band learned from the evaluation matrix's
healthy rides) and drops V_RIDER_TORQUE with REASON_IMPLAUSIBLE when they disagree.
"""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core import layout as L  # noqa: N812
from ptw_rt.eval.evaluate import evaluate_ride
from ptw_rt.sim.ride import parse_perturbations, simulate
from ptw_rt.sim.scenarios import SCENARIOS

FAULT_AT = 20.0


def _ride(scenario: str, perturb: list[str] | None = None):
    ev = evaluate_ride(simulate(scenario, perturbation=parse_perturbations(perturb or [])))
    E = ev.estimates
    flagged = (E[:, L.E_REASONS].astype(int) & L.REASON_IMPLAUSIBLE) != 0
    torque_valid = (E[:, L.E_VALID].astype(int) & L.V_RIDER_TORQUE) != 0
    return ev, flagged, torque_valid


@pytest.mark.slow
@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_the_uihosmo_on_the_sensors_is_within_target_through_the_step(scenario):
    ev, _, _ = _ride(scenario)
    m = ev.mask
    tau = ev.truth["rider_torque"][m]
    rmse = np.sqrt(np.mean((ev.estimates[m, L.E_TORQUE_UIO_SENSORS] - tau) ** 2))
    assert rmse <= 0.25 * np.max(np.abs(tau))  # issue #16: <= 25 % of the ride's peak (11.1-23.7 % here)
    # ... and its roll, its own (core.channel_kinematics, not the published filter's): <= 1.5 deg (0.07-0.78 here)
    roll_rmse = np.sqrt(np.mean((ev.estimates[m, L.E_ROLL_UIO_SENSORS] - ev.truth["roll"][m]) ** 2))
    assert np.degrees(roll_rmse) <= 1.5


@pytest.mark.slow
@pytest.mark.parametrize(
    "scenario, perturb",
    # the healthy cells of the matrix whose residual came closest to its threshold (ratio 0.76-0.77, 2026-11-25)
    [("radius_accel", ["mu_scale=0.85"]), ("mu_drop", ["stiffness=0.7"]), ("slalom_30", ["stiffness=1.3"])],
)
def test_no_false_alarm_on_healthy_rides(scenario, perturb):
    ev, flagged, _ = _ride(scenario, perturb)
    assert not flagged.any()
    assert ev.estimates[:, L.E_PLAUSIBILITY].max() < 1.0
    assert ev.result["alarms"] == {
        "fault_at_s": None,
        "plausibility": {"cycles": 0},
        "attitude_consistency": {"cycles": 0},
        "gyro_step": {"cycles": 0},
    }


@pytest.mark.slow
def test_a_steer_encoder_offset_is_flagged_within_half_a_second():
    """3 counts (1 deg) of encoder offset appearing at speed: the steer angle no longer matches the yaw rate and
    the tyres' slip (the steer-kinematics check, 0.2 s here)."""
    ev, flagged, torque_valid = _ride("handling_40_120", ["steer_offset_step=3", f"fault_at={FAULT_AT}"])
    t = ev.t
    first = t[flagged][0]
    assert FAULT_AT < first <= FAULT_AT + 0.5
    assert not (torque_valid & flagged).any()  # the torque is not VALID while the monitor objects
    assert not flagged[t < FAULT_AT].any()
    # what `ptw-rt evaluate --scenario ... --perturb fault_at=...` reports: the same first alarm, and none of the other
    alarms = ev.result["alarms"]
    assert alarms["fault_at_s"] == FAULT_AT
    assert alarms["plausibility"]["detected_after_s"] == pytest.approx(first - FAULT_AT, abs=0.006)
    assert alarms["attitude_consistency"] == {"cycles": 0, "detected_after_s": None}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("scenario", "offset"),
    [("urban", 3), ("urban", -3), ("slalom_30", 3), ("radius_accel", -3), ("mu_drop", 3), ("mu_drop", -3)],
)
def test_a_steer_encoder_offset_is_flagged_by_the_kinematics_in_town_and_in_corners(scenario, offset):
    """In town the offset moves both torques less than their normal disagreement (it took 17 s), and in a long
    corner a check of the kinematics alone (L r cos(roll) / (u cos(caster)), riding nearly straight) never ran:
    with the tyres' slip difference (from m a_y and I_z r', the learned scale) it runs everywhere and sees the
    offset within 0.5 s (0.2-0.4 s on these rides, 2026-11-25); steer, steer rate and torque are not VALID while
    it objects."""
    ev, flagged, torque_valid = _ride(scenario, [f"steer_offset_step={offset}", f"fault_at={FAULT_AT}"])
    t = ev.t
    first = t[flagged & (t >= FAULT_AT)][0]
    assert first <= FAULT_AT + 0.5
    assert not flagged[t < FAULT_AT].any()
    steer_valid = (ev.estimates[:, L.E_VALID].astype(int) & (L.V_STEER | L.V_STEER_RATE)) != 0
    assert not steer_valid[np.flatnonzero(t == first)[0]]  # the kinematics' alarm: the steer itself is doubted
    assert not (torque_valid & flagged).any()


def test_the_steer_kinematics_check_stays_quiet_on_healthy_town_riding_with_other_tyres():
    for perturb in (["stiffness=0.6"], ["mu_scale=0.8"], ["added_mass=80"]):
        _, flagged, _ = _ride("urban", perturb)
        assert not flagged.any(), perturb


@pytest.mark.slow
def test_the_steer_kinematics_check_is_quiet_in_a_long_corner_with_a_heavy_rider():
    """`radius_accel` with +80 kg of rider (the file's mass, so the forces and the slip are 20 % short) until the
    simulated rider loses the vehicle at 28-29 deg of lean: the slip difference keeps the residual small."""
    ev, flagged, _ = _ride("radius_accel", ["added_mass=80"])
    before = ev.t < (ev.result["crashed_at"] or np.inf) - 1.0
    assert not flagged[before].any()
    assert np.degrees(np.abs(ev.estimates[ev.mask & before, L.E_STEER_RESIDUAL]).max()) < 0.35


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11, 21, 33])
def test_corrupt_frames_are_the_input_checks_business_not_the_torque_monitors(seed):
    """`sensor_faults` seed 11: corrupt IMU_Accel frames at 40 s carry a lateral acceleration of -27 m/s^2 for a
    few cycles (flagged out of range). Both torques chase it; the torque monitor compared them anyway and raised
    110 cycles of REASON_IMPLAUSIBLE on a healthy sensor set (hidden before by seed 000's case 2 blowing up and
    restarting the filters' clock). It now compares only on sound cycles, like the steer check. Seeds 21 and 33:
    once the corrupt frames end, the steer comes back with a step of ~3 deg that the UIHOSMO's differentiator turns
    into a torque spike; compared at once, that raised 187 / 157 cycles of alarm 0.4 s after the fault. The
    residual now waits while the input fault's reason is held (`supervisor.reason_hold_time`, 1 s)."""
    ev = evaluate_ride(simulate("sensor_faults", seed=seed))
    assert ev.result["alarms"]["plausibility"]["cycles"] == 0


@pytest.mark.slow
def test_a_ride_the_simulated_rider_crashes_is_scored_until_just_before_the_fall():
    """`radius_accel` with tyres x0.7 on seed 7: the rider falls at 30 deg of lean (|roll| > 69 deg at 38.2 s). The
    fall and what follows are not a ride: scoring and the alarm count stop CRASH_MARGIN_S before it."""
    from ptw_rt.eval.evaluate import CRASH_MARGIN_S

    ev = evaluate_ride(simulate("radius_accel", seed=7, perturbation=parse_perturbations(["stiffness=0.7"])))
    crash = ev.result["crashed_at"]
    assert crash is not None
    assert not ev.mask[ev.t >= crash - CRASH_MARGIN_S].any() and ev.mask[ev.t < crash - CRASH_MARGIN_S].any()
    assert ev.result["alarms"]["plausibility"]["cycles"] == 0
    assert ev.result["metrics"]["roll_rmse_deg"] < 1.0


@pytest.mark.slow
def test_a_steer_encoder_a_count_off_is_recalibrated_and_the_tyres_are_learned():
    """A zero a count off (0.35 deg, below what the steer check flags) is as large as a steady corner's slip-angle
    difference: the tyre filters' innovations said their model did not fit (windowed NIS ~14), so the stiffness
    was never VALID on `handling_40_120` (before 2026-11-25). Riding straight the conditioning learns the zero
    (0.9 of the second half VALID here, within 2 % of the truth). Since the balance check (2026-12-07) the zero's
    error, a slip on the front alone, read as a front tyre off the file's balance until the zero was learned, and the
    check withheld VALID meanwhile: 0.46 of the second half. Since the zero check learns the zero in corners too
    (docs/estimator.md, "The steer zero the balance rests on"): 0.62, as with the zero right."""
    from ptw_rt.eval.matrix import valid_stiffness_stats

    ev, flagged, _ = _ride("handling_40_120", ["steer_offset=1"])
    E, t = ev.estimates, ev.t
    valid = (E[:, L.E_VALID].astype(int) & L.V_CORNERING) != 0
    stats = valid_stiffness_stats(t, E[:, L.E_C_ALPHA_FRONT], ev.truth["c_alpha_front"], valid, ev.mask)
    assert stats["valid_share_second_half"] >= 0.55
    assert stats["max_abs_err_pct"] <= 10.0
    assert not flagged[t > t[-1] / 2].any()


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["urban", "handling_40_120"])
def test_a_rider_busier_on_the_bar_is_not_a_fault(scenario):
    """Twice the simulator's rider torque noise, healthy sensors: the UIHOSMO's ~70 ms lag behind the quicker
    torque had raised the RMS residual to 1.34 / 1.24 thresholds (565 / 319 cycles of false alarm, before
    2026-11-25). The threshold now grows with lag x the RMS of the published torque's rate (ratio 0.63 / 0.86)."""
    ev, flagged, _ = _ride(scenario, ["rider_noise=2"])
    assert not flagged[ev.mask].any()
    assert ev.estimates[ev.mask, L.E_PLAUSIBILITY].max() < 1.0
