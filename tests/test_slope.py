"""A road that is not level, through the whole step (docs/estimator.md, "A road that is not level").

On a slope the vehicle still turns about the vertical, so its pitched roll axis sees -r sin(slope) of every turn:
integrated as the roll, a 3 deg slope (5 %) made the published roll drift in each turn. Before the attitude filter
had a pitch, `slalom_30` uphill by 3 deg published a VALID stiffness 75 % off and `urban` downhill by 4 deg a VALID
roll 5.2 deg off (the promise is 3 deg). The simulator's `road_slope` turns the IMU's readings by the slope (the
plant's speed stays the scenario's).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptw_rt.core import layout as L  # noqa: N812
from ptw_rt.eval.evaluate import evaluate_ride
from ptw_rt.sim.ride import parse_perturbations, simulate


@pytest.mark.slow
@pytest.mark.parametrize(
    ("scenario", "slope_deg"),
    [("slalom_30", 3.0), ("urban", -4.0), ("handling_40_120", 3.0)],
)
def test_on_a_slope_the_roll_and_the_valid_stiffness_stay_right(scenario, slope_deg):
    ride = simulate(scenario, perturbation=parse_perturbations([f"road_slope={slope_deg}"]))
    ev = evaluate_ride(ride)
    E, t, truth = ev.estimates, ev.t, ev.truth
    scored = ev.mask
    err_deg = np.degrees(E[:, L.E_ROLL] - truth["roll"])
    assert math.sqrt(float(np.mean(err_deg[scored] ** 2))) < 0.3  # 0.48 / 1.76 / 0.83 deg on the code before the pitch
    roll_valid = scored & ((E[:, L.E_VALID].astype(int) & L.V_ROLL) != 0)
    assert np.abs(err_deg[roll_valid]).max() < 1.0  # 0.79 / 5.22 / 1.61 deg
    cornering_valid = scored & ((E[:, L.E_VALID].astype(int) & L.V_CORNERING) != 0)
    stiffness_err = 100.0 * np.abs(E[:, L.E_C_ALPHA_FRONT] / truth["c_alpha_front"] - 1.0)
    assert cornering_valid.any()
    assert stiffness_err[cornering_valid].max() < 15.0  # 75 / 22.5 / 17.7 %
    assert t[-1] > 20.0
