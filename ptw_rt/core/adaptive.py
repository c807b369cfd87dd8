"""LPV adaptive observer (seed 001, theorem 2) as one jitted, allocation-free step.

    x_hat[k+1] = Phi(u) x_hat + B_tau(u) tau + B_theta(u) chi(x_hat, u) Theta_hat + B_y(u) y     (exact ZOH)
    Theta_hat[k+1] = Proj( Theta_hat + dt Gamma chi^T T (y - C x_hat) )                          (eq. 30)

Adaptation runs per parameter only while that parameter is persistently excited
(seed 001, assumption 2): an exponentially weighted RMS of its regressor column
must exceed a threshold. On a straight road the slip and camber regressors
vanish, so the estimates freeze instead of drifting. The projection keeps each
stiffness within the design's deviation bound around nominal (and positive).

State layout (float64, `new_state`):
  [0:8] x_hat   [8:12] Theta_hat (deviation from nominal)   [12:16] excitation mean squares   [16] initialised
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core.schedule import grid_position, lerp

X0, X1 = 0, 8
TH0, TH1 = 8, 12
PE0, PE1 = 12, 16
INIT = 16
STATE_SIZE = 17

# x_hat indices
PHI, DELTA, VY, R, PHI_DOT, DELTA_DOT, FYF, FYR = range(8)
N_Y = 6


def new_state() -> np.ndarray:
    return np.zeros(STATE_SIZE)


@njit(cache=True)
def regressor_into(chi: np.ndarray, x: np.ndarray, u: float, consts: np.ndarray) -> None:
    """chi (2x4) of seed 001 eq. 8 with the full slip (trail term included); no division by u."""
    sigma_f, sigma_r, l_f, l_r, caster, trail = consts[0], consts[1], consts[2], consts[3], consts[4], consts[5]
    s, c = math.sin(caster), math.cos(caster)
    chi[0, 0] = -(x[VY] + l_f * x[R] - u * c * x[DELTA] - trail * x[DELTA_DOT]) / sigma_f
    chi[0, 1] = u * (x[PHI] + s * x[DELTA]) / sigma_f
    chi[0, 2] = 0.0
    chi[0, 3] = 0.0
    chi[1, 0] = 0.0
    chi[1, 1] = 0.0
    chi[1, 2] = -(x[VY] - l_r * x[R]) / sigma_r
    chi[1, 3] = u * x[PHI] / sigma_r


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def adaptive_step(
    state: np.ndarray,
    chi: np.ndarray,
    scratch: np.ndarray,
    y: np.ndarray,
    tau: float,
    u: float,
    dt: float,
    adapt: bool,
    grid: np.ndarray,
    Phi: np.ndarray,
    B_tau: np.ndarray,
    B_theta: np.ndarray,
    B_y: np.ndarray,
    C: np.ndarray,
    T: np.ndarray,
    gamma: np.ndarray,
    theta_nominal: np.ndarray,
    theta_bound: np.ndarray,
    consts: np.ndarray,
    pe_threshold: np.ndarray,
    pe_forgetting: float,
) -> None:
    """One cycle. `chi` is a preallocated (2, 4) array, `scratch` >= 16 floats.

    `adapt` is the supervisor's permission (speed valid, sensors fresh); excitation
    is checked here per parameter on top of it.
    """
    i, w = grid_position(grid, u)
    x = state[X0:X1]
    theta = state[TH0:TH1]
    pe = state[PE0:PE1]
    if state[INIT] == 0.0:
        x[:] = 0.0
        x[DELTA] = y[0]
        x[R] = y[1]
        x[PHI_DOT] = y[2]
        x[DELTA_DOT] = y[3]
        state[INIT] = 1.0

    regressor_into(chi, x, u, consts)

    # output error and its projection s = T (y - C x_hat) = D^T P x_err (seed 001 eq. 20)
    s0 = 0.0
    s1 = 0.0
    for r in range(N_Y):
        e = y[r]
        for c in range(8):
            e -= C[r, c] * x[c]
        s0 += T[0, r] * e
        s1 += T[1, r] * e

    # excitation: exponentially weighted mean square of each regressor column
    for p in range(4):
        col = chi[0, p] * chi[0, p] + chi[1, p] * chi[1, p]
        pe[p] = pe_forgetting * pe[p] + (1.0 - pe_forgetting) * col

    # state update with the current parameter estimate
    f0 = chi[0, 0] * theta[0] + chi[0, 1] * theta[1]
    f1 = chi[1, 2] * theta[2] + chi[1, 3] * theta[3]
    x_next = scratch[0:8]
    for a in range(8):
        acc = ((1.0 - w) * B_tau[i, a] + w * B_tau[i + 1, a]) * tau
        acc += lerp(B_theta, i, w, a, 0) * f0 + lerp(B_theta, i, w, a, 1) * f1
        for b in range(N_Y):
            acc += lerp(B_y, i, w, a, b) * y[b]
        for b in range(8):
            acc += lerp(Phi, i, w, a, b) * x[b]
        x_next[a] = acc

    # adaptation law (eq. 30), per excited parameter, projected onto the physical bounds
    if adapt:
        for p in range(4):
            if pe[p] > pe_threshold[p] * pe_threshold[p]:
                grad = chi[0, p] * s0 + chi[1, p] * s1
                value = theta[p] + dt * gamma[p] * grad
                lo = -theta_bound[p]
                hi = theta_bound[p]
                if value < lo:
                    value = lo
                elif value > hi:
                    value = hi
                theta[p] = value
    for a in range(8):
        x[a] = x_next[a]
