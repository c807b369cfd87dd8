"""The jitted LPV adaptive observer (seed 001): stiffness identification and freezing without excitation."""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core.adaptive import PHI, TH0, TH1, adaptive_step, new_state
from ptw_rt.design.discretize import zoh
from ptw_rt.design.file import load_design
from ptw_rt.design.lpv_lmi import output_matrix
from ptw_rt.model.sharp import kmh, state_space
from ptw_rt.paths import DEFAULT_DESIGN


@pytest.fixture(scope="module")
def design():
    return load_design(DEFAULT_DESIGN)


def ride(vehicle, design, true_vehicle, torque, duration, speed_kmh=80.0, adapt=True, noise=0.0, seed=0):
    """Linear plant with the true stiffness; the observer knows only the nominal one."""
    u = kmh(speed_kmh)
    A, B = state_space(true_vehicle, u)
    h = 0.001
    Phi, Gam = zoh(A, B[:, None], h)
    C = output_matrix(vehicle)
    rng = np.random.default_rng(seed)
    x, state = np.zeros(8), new_state()
    chi, scratch = np.zeros((2, 4)), np.zeros(16)
    roll_err = []
    for k in range(int(duration / h)):
        tau = torque(k * h)
        if k % 10 == 0:
            y = C @ x + noise * rng.normal(size=6) * np.array([1e-3, 2e-3, 2e-3, 2e-2, 3e-2, 0.0])
            adaptive_step(
                state,
                chi,
                scratch,
                y,
                tau,
                u,
                0.01,
                adapt,
                design.grid,
                design.ad_Phi,
                design.ad_B_tau,
                design.ad_B_theta,
                design.ad_B_y,
                design.ad_C,
                design.ad_T,
                design.ad_gamma,
                design.ad_theta_nominal,
                design.ad_theta_bound,
                design.regressor_constants,
                design.ad_pe_threshold,
                design.ad_pe_forgetting,
            )
            assert np.all(np.isfinite(state))
            roll_err.append(state[PHI] - x[0])
        x = Phi @ x + Gam[:, 0] * tau
    return design.ad_theta_nominal + state[TH0:TH1], np.array(roll_err)


def rich_torque(t):
    return 10 * np.sin(2 * np.pi * 0.4 * t) + 6 * np.sin(2 * np.pi * 1.1 * t)


def test_stiffness_converges_on_the_linear_model(vehicle, design):
    true = vehicle.scaled(stiffness=0.8)
    estimate, roll_err = ride(vehicle, design, true, rich_torque, 60.0)
    truth = np.array(true.nominal_stiffness())
    error = np.abs(estimate - truth) / truth
    start = np.abs(design.ad_theta_nominal - truth) / truth
    assert np.all(error < 0.5 * start)  # every parameter at least halves its error
    assert error[0] < 0.05 and error[2] < 0.08  # cornering stiffness within a few percent
    assert np.degrees(np.sqrt(np.mean(roll_err[500:] ** 2))) < 0.1


def test_no_drift_without_excitation(vehicle, design):
    """Straight running with sensor noise: the regressors stay small and the estimates freeze."""
    estimate, _ = ride(vehicle, design, vehicle.scaled(stiffness=0.8), lambda t: 0.0, 30.0, noise=1.0)
    assert np.array_equal(estimate, design.ad_theta_nominal)


def test_no_adaptation_when_not_permitted(vehicle, design):
    estimate, _ = ride(vehicle, design, vehicle.scaled(stiffness=0.8), rich_torque, 10.0, adapt=False)
    assert np.array_equal(estimate, design.ad_theta_nominal)


def test_estimates_stay_within_physical_bounds(vehicle, design):
    estimate, _ = ride(vehicle, design, vehicle.scaled(stiffness=0.3), rich_torque, 30.0)
    assert np.all(estimate >= design.ad_theta_nominal - design.ad_theta_bound - 1e-9)
    assert np.all(estimate <= design.ad_theta_nominal + design.ad_theta_bound + 1e-9)
