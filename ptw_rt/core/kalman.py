"""Fusion filter step (steady-state Kalman on the torque-augmented Sharp model; design in ptw_rt.design.kalman).

    z+ = z + K(u) (y - C z)      corrector: y = [delta, r, phi_dot, a_y]
    z  = Phi(u) z+               predictor: exact ZOH, rider torque held (random walk)

State layout (float64, `new_state`): [0:11] z = [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, tau,
b_r, b_p] (the last two: yaw- and roll-gyro biases), [11] initialised.
A (re)start keeps the gyro biases: they are a property of the sensor, not of the ride, and take minutes to learn.
The corrected z+ is written to `out` (the estimate of this cycle).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ptw_rt.core.schedule import grid_position, lerp

N_Z = 11
N_Y = 4
PHI, DELTA, VY, R, PHI_DOT, DELTA_DOT, FYF, FYR, TAU, YAW_BIAS, ROLL_BIAS = range(11)
N_DYNAMIC = 9  # states reset on a (re)start; the biases are kept
INIT = 11
STATE_SIZE = 12


def new_state() -> np.ndarray:
    return np.zeros(STATE_SIZE)


@njit(cache=True)
def kalman_step(
    state: np.ndarray,
    out: np.ndarray,
    y: np.ndarray,
    u: float,
    roll_init: float,
    grid: np.ndarray,
    Phi: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
) -> None:
    """One cycle; `out` (>= 11 floats) receives the corrected state. `roll_init` seeds phi on (re)start."""
    i, w = grid_position(grid, u)
    z = state[0:N_Z]
    if state[INIT] == 0.0:
        for a in range(N_DYNAMIC):
            z[a] = 0.0
        z[PHI] = roll_init
        z[DELTA] = y[0]
        z[R] = y[1] - z[YAW_BIAS]
        z[PHI_DOT] = y[2] - z[ROLL_BIAS]
        state[INIT] = 1.0
    for a in range(N_Z):
        out[a] = z[a]
    for r in range(N_Y):
        e = y[r]
        for c in range(N_Z):
            e -= C[r, c] * z[c]
        for a in range(N_Z):
            out[a] += lerp(K, i, w, a, r) * e
    for a in range(N_Z):
        acc = 0.0
        for b in range(N_Z):
            acc += lerp(Phi, i, w, a, b) * out[b]
        z[a] = acc
