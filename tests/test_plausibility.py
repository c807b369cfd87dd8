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

FAULT_AT = 20.0


def _ride(scenario: str, perturb: list[str] | None = None):
    ev = evaluate_ride(simulate(scenario, perturbation=parse_perturbations(perturb or [])))
    E = ev.estimates
    flagged = (E[:, L.E_REASONS].astype(int) & L.REASON_IMPLAUSIBLE) != 0
    torque_valid = (E[:, L.E_VALID].astype(int) & L.V_RIDER_TORQUE) != 0
    return ev, flagged, torque_valid


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["dlc_50", "dlc_100", "handling_40_120", "slalom_30", "urban"])
def test_the_uihosmo_on_the_sensors_is_within_target_through_the_step(scenario):
    ev, _, _ = _ride(scenario)
    m = ev.mask
    tau = ev.truth["rider_torque"][m]
    rmse = np.sqrt(np.mean((ev.estimates[m, L.E_TORQUE_UIO_SENSORS] - tau) ** 2))
    assert rmse <= 0.25 * np.max(np.abs(tau))  # issue #16: <= 25 % of the ride's peak (11.8-21.4 % here)


@pytest.mark.slow
@pytest.mark.parametrize(
    "scenario, perturb",
    # the three healthy cells of the matrix whose residual came closest to its threshold (ratio 0.77)
    [("sensor_faults", ["stiffness=0.7"]), ("mu_drop", ["stiffness=0.7"]), ("radius_accel", ["mu_scale=0.85"])],
)
def test_no_false_alarm_on_healthy_rides(scenario, perturb):
    ev, flagged, _ = _ride(scenario, perturb)
    assert not flagged.any()
    assert ev.estimates[:, L.E_PLAUSIBILITY].max() < 1.0


@pytest.mark.slow
def test_a_steer_encoder_offset_is_flagged_within_half_a_second():
    """3 counts (1 deg) of encoder offset appearing at speed: the fusion filter and the UIHOSMO read the same wrong
    steer angle but explain it differently, and their torques part within 0.3 s."""
    ev, flagged, torque_valid = _ride("handling_40_120", ["steer_offset_step=3", f"fault_at={FAULT_AT}"])
    t = ev.t
    first = t[flagged][0]
    assert FAULT_AT < first <= FAULT_AT + 0.5
    assert not (torque_valid & flagged).any()  # the torque is not VALID while the monitor objects
    assert not flagged[t < FAULT_AT].any()
