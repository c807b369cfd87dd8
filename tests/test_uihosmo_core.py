"""The jitted UIHOSMO step reconstructs roll and rider torque on the linear model (seed 000 eq. 12-15)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ptw_rt.core.uihosmo import LAMBDA_STEER, LAMBDA_YAW, OUT_PHI, OUT_SIZE, OUT_TAU, new_state, uihosmo_step
from ptw_rt.design.discretize import zoh
from ptw_rt.design.file import load_design
from ptw_rt.model.sharp import kmh, state_space
from ptw_rt.paths import DEFAULT_DESIGN


def torque_pulse(t):
    return 15.0 * np.sin(2 * np.pi * 0.5 * t) * np.exp(-(((t - 3.0) / 1.2) ** 2))


def run(vehicle, design, dt, lipschitz, speed_kmh=100.0, quantum=0.0, duration=8.0, settle=2.0):
    u = kmh(speed_kmh)
    A, B = state_space(vehicle, u)
    h = 0.0005
    Phi, Gam = zoh(A, B[:, None], h)
    stride = int(round(dt / h))
    x = np.zeros(8)
    state, out, scratch = new_state(), np.zeros(OUT_SIZE), np.zeros(24)
    phi_err, tau_err, phi_true = [], [], []
    for k in range(int(duration / h)):
        t = k * h
        tau = torque_pulse(t)
        if k % stride == 0:
            delta = np.round(x[1] / quantum) * quantum if quantum else x[1]
            uihosmo_step(
                state,
                out,
                scratch,
                delta,
                x[3],
                u,
                dt,
                lipschitz,
                design.grid,
                design.uh_Phi,
                design.uh_Gamma,
                design.uh_T_inv,
                design.uh_Abar,
                design.uh_Dbar_inv,
                design.uh_Phi22,
                design.uh_Gamma21,
                design.uh_Ramp_y,
                design.uh_Ramp21,
                LAMBDA_STEER,
                LAMBDA_YAW,
                1,
            )
            assert np.all(np.isfinite(out))
            if t > settle:
                phi_err.append(out[OUT_PHI] - x[0])
                tau_err.append(out[OUT_TAU] - tau)
                phi_true.append(x[0])
        x = Phi @ x + Gam[:, 0] * tau
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    return np.degrees(rms(phi_err)), rms(tau_err), np.degrees(np.max(np.abs(phi_true)))


@pytest.fixture(scope="module")
def design_1khz(settings):
    from ptw_rt.design.build import make_design

    fine = dataclasses.replace(settings, estimator=dataclasses.replace(settings.estimator, sample_time=0.001))
    return make_design(fine)[0]


def test_near_exact_reconstruction_when_sampled_fast(vehicle, design_1khz):
    """At 1 kHz the discrete observer approaches the continuous theory: exact unknown-input reconstruction."""
    phi_rmse_deg, tau_rmse, phi_peak_deg = run(vehicle, design_1khz, 0.001, 50.0)
    assert phi_peak_deg > 5.0
    assert phi_rmse_deg < 0.1
    assert tau_rmse < 0.3


def test_reconstruction_at_100hz_with_the_committed_design(vehicle):
    """At 100 Hz the first-order hold of y and the ramp hold of theta_1 keep the discrete observer close
    to the continuous one; the 10-bit encoder then dominates the error."""
    design = load_design(DEFAULT_DESIGN)
    phi_rmse_deg, tau_rmse, _ = run(vehicle, design, 0.01, 5.0)
    assert phi_rmse_deg < 0.2
    assert tau_rmse < 0.5
    phi_q, tau_q, _ = run(vehicle, design, 0.01, 5.0, quantum=2 * np.pi / 1024)
    assert phi_q < 1.5 and tau_q < 6.0


def test_paper_lipschitz_constant_fails_at_100hz(vehicle):
    """Why L is not the paper's 5000: at 10 ms sampling the differentiator error swamps eq. 15."""
    design = load_design(DEFAULT_DESIGN)
    phi_rmse_deg, _, phi_peak_deg = run(vehicle, design, 0.01, 5000.0)
    assert phi_rmse_deg > phi_peak_deg
