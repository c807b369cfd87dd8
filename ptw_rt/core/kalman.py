"""Fusion filter step (steady-state Kalman on the torque-augmented Sharp model; design in ptw_rt.design.kalman).

    z+ = z + K(u) (y - C z)      corrector: y = [delta, r, phi_dot, a_y, phi_kinematic]
    z  = Phi(u) z+               predictor: exact ZOH, rider torque held (random walk)

State layout (float64, `new_state`): [0:9] z = [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, tau],
[9] initialised. The rates come bias-corrected (the attitude filter owns the gyro biases).
The corrected z+ is written to `out` (the estimate of this cycle).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ptw_rt.core.schedule import grid_position, lerp

N_Z = 9
N_Y = 5
PHI, DELTA, VY, R, PHI_DOT, DELTA_DOT, FYF, FYR, TAU = range(9)
INIT = 9
STATE_SIZE = 10


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
    """One cycle; `out` (>= N_Z floats) receives the corrected state. `roll_init` seeds phi on (re)start."""
    i, w = grid_position(grid, u)
    z = state[0:N_Z]
    if state[INIT] == 0.0:
        for a in range(N_Z):
            z[a] = 0.0
        z[PHI] = roll_init
        z[DELTA] = y[0]
        z[R] = y[1]
        z[PHI_DOT] = y[2]
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
