"""UIHOSMO (seed 000, case 2) as one jitted, allocation-free step per 10 ms sample.

Per cycle, from the measured steer angle delta, ground yaw rate r and speed u:
  1. output errors e1 = delta - z_delta, e2 = r - z_r;
  2. discrete HOSM differentiators (Livne-Levant) of order 3 on e1 and 2 on e2
     give theta_1 = [e1, e1', e2] and the derivatives d/dt xi_12 = e1'', d/dt xi_13 = e2';
  3. x_hat = z + T^-1 [theta_1; theta_2]                                  (eq. 12)
  4. [phi, tau] = Dbar^-1 ([e1'', e2'] - Abar [theta_1; theta_2])         (eq. 15)
  5. z <- Phi z + Gamma y + Ramp_y (y - y_prev)                            (first-order hold of y)
     theta_2 <- Phi22 theta_2 + Gamma21 theta_1 + Ramp21 d/dt theta_1      (ramp hold of theta_1)
Every matrix is interpolated linearly in u between design grid points.

State vector layout (float64, preallocated by `new_state`):
  [0:7] z   [7:11] theta_2   [11:15] steer differentiator   [15:18] yaw differentiator
  [18] initialised   [19:21] previous [delta, r]
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ptw_rt.core.differentiator import hdd_init, hdd_lambda, hdd_step
from ptw_rt.core.schedule import grid_position, lerp

Z0, Z1 = 0, 7
TH0, TH1 = 7, 11
V10, V11 = 11, 15
V20, V21 = 15, 18
INIT = 18
Y_PREV = 19
STATE_SIZE = 21

# reduced-state indices [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr]
X_DELTA, X_VY, X_R, X_PHI_DOT, X_DELTA_DOT, X_FYF, X_FYR = range(7)

# outputs of one step
OUT_PHI, OUT_TAU = 7, 8
OUT_SIZE = 9  # [x_hat (7), phi, tau]

LAMBDA_STEER = hdd_lambda(3)
LAMBDA_YAW = hdd_lambda(2)


def new_state() -> np.ndarray:
    return np.zeros(STATE_SIZE)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def uihosmo_step(
    state: np.ndarray,
    out: np.ndarray,
    scratch: np.ndarray,
    delta: float,
    r: float,
    u: float,
    dt: float,
    diff_lipschitz: float,
    grid: np.ndarray,
    Phi: np.ndarray,
    Gamma: np.ndarray,
    T_inv: np.ndarray,
    Abar: np.ndarray,
    Dbar_inv: np.ndarray,
    Phi22: np.ndarray,
    Gamma21: np.ndarray,
    Ramp_y: np.ndarray,
    Ramp21: np.ndarray,
    lam_steer: np.ndarray,
    lam_yaw: np.ndarray,
    diff_substeps: int,
) -> None:
    """One cycle. `scratch` is a preallocated float64 array of at least 24 entries."""
    i, w = grid_position(grid, u)
    if state[INIT] == 0.0:
        state[Z0:Z1] = 0.0
        state[Z0 + X_DELTA] = delta
        state[Z0 + X_R] = r
        state[TH0:TH1] = 0.0
        hdd_init(state[V10:V11], 0.0)
        hdd_init(state[V20:V21], 0.0)
        state[Y_PREV] = delta
        state[Y_PREV + 1] = r
        state[INIT] = 1.0
    z = state[Z0:Z1]
    th2 = state[TH0:TH1]
    v1 = state[V10:V11]
    v2 = state[V20:V21]

    e1 = delta - z[X_DELTA]
    e2 = r - z[X_R]
    hdd_step(v1, e1, diff_lipschitz, dt, lam_steer, diff_substeps)
    hdd_step(v2, e2, diff_lipschitz, dt, lam_yaw, diff_substeps)

    # theta = [v1_0, v1_1, v2_0, theta_2] in scratch[0:7]
    theta = scratch[0:7]
    theta[0] = v1[0]
    theta[1] = v1[1]
    theta[2] = v2[0]
    for k in range(4):
        theta[3 + k] = th2[k]

    # x_hat = z + T^-1 theta
    for a in range(7):
        acc = z[a]
        for b in range(7):
            acc += lerp(T_inv, i, w, a, b) * theta[b]
        out[a] = acc

    # [phi, tau] = Dbar^-1 ([v1_2, v2_1] - Abar theta)
    rhs0 = v1[2]
    rhs1 = v2[1]
    for b in range(7):
        rhs0 -= lerp(Abar, i, w, 0, b) * theta[b]
        rhs1 -= lerp(Abar, i, w, 1, b) * theta[b]
    out[OUT_PHI] = lerp(Dbar_inv, i, w, 0, 0) * rhs0 + lerp(Dbar_inv, i, w, 0, 1) * rhs1
    out[OUT_TAU] = lerp(Dbar_inv, i, w, 1, 0) * rhs0 + lerp(Dbar_inv, i, w, 1, 1) * rhs1

    # propagate z and theta_2 to the next sample (exact ZOH, inputs held)
    z_next = scratch[7:14]
    d_delta = delta - state[Y_PREV]
    d_r = r - state[Y_PREV + 1]
    for a in range(7):
        acc = lerp(Gamma, i, w, a, 0) * delta + lerp(Gamma, i, w, a, 1) * r
        acc += lerp(Ramp_y, i, w, a, 0) * d_delta + lerp(Ramp_y, i, w, a, 1) * d_r
        for b in range(7):
            acc += lerp(Phi, i, w, a, b) * z[b]
        z_next[a] = acc
    th_next = scratch[14:18]
    for a in range(4):
        acc = 0.0
        for b in range(4):
            acc += lerp(Phi22, i, w, a, b) * th2[b]
        for b in range(3):
            acc += lerp(Gamma21, i, w, a, b) * theta[b]
        # d/dt theta_1 = [e1', e1'', e2'] from the differentiators
        acc += lerp(Ramp21, i, w, a, 0) * v1[1] + lerp(Ramp21, i, w, a, 1) * v1[2]
        acc += lerp(Ramp21, i, w, a, 2) * v2[1]
        th_next[a] = acc
    for a in range(7):
        z[a] = z_next[a]
    for a in range(4):
        th2[a] = th_next[a]
    state[Y_PREV] = delta
    state[Y_PREV + 1] = r
