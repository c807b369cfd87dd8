"""Sensor conditioning: raw sensor values -> the model's measurements (jitted, allocation-free).

- Steering encoder counts -> steer angle, with the calibration zero and wrap-around
  of a 10-bit absolute encoder (1024 counts per revolution).
- Body-frame IMU -> model frame. The IMU leans with the chassis: with roll phi (and
  negligible pitch) the ground yaw rate is q sin(phi) + r cos(phi), and the
  horizontal lateral acceleration is f_y cos(phi) - f_z sin(phi), which needs no
  gravity compensation. The roll used is the estimator's own (previous cycle).
- Forward speed at 100 Hz from 10 Hz GPS and the longitudinal accelerometer: a
  complementary filter whose GPS correction is applied against the prediction made
  when the fix was valid (latency compensation through a ring buffer of past
  predictions). In a GPS dropout the prediction is held (accelerometer only, with a
  slow decay of the correction) and the caller flags it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2.0 * math.pi

# speed filter state layout
SPD_U, SPD_BIAS, SPD_HEAD, SPD_INIT = 0, 1, 2, 3
SPD_RING0 = 4


def new_speed_state(latency_samples: int) -> np.ndarray:
    return np.zeros(SPD_RING0 + max(1, latency_samples) + 1)


@njit(cache=True)
def steer_angle(count: float, zero_count: float, counts_per_rev: float) -> float:
    """Angle [rad] of an absolute encoder reading, wrapped to (-pi, pi] around the calibration zero."""
    d = (count - zero_count) % counts_per_rev
    if d > 0.5 * counts_per_rev:
        d -= counts_per_rev
    return d * TWO_PI / counts_per_rev


@njit(cache=True)
def ground_yaw_rate(q_body: float, r_body: float, roll: float) -> float:
    return q_body * math.sin(roll) + r_body * math.cos(roll)


@njit(cache=True)
def horizontal_lateral_accel(f_y_body: float, f_z_body: float, roll: float) -> float:
    """Lateral acceleration in the road plane from body-frame specific force (no gravity term needed)."""
    return f_y_body * math.cos(roll) - f_z_body * math.sin(roll)


@njit(cache=True)
def kinematic_roll(speed: float, yaw_rate_ground: float, g: float) -> float:
    """Roll of a steady coordinated turn, atan(u r / g): the baseline a user would pick."""
    return math.atan(speed * yaw_rate_ground / g)


@njit(cache=True)
def speed_step(
    state: np.ndarray,
    accel_x: float,
    gps_speed: float,
    gps_new: bool,
    gps_ok: bool,
    dt: float,
    gain: float,
    bias_gain: float,
    latency_samples: int,
) -> float:
    """One 10 ms step of the speed filter; returns the speed estimate [m/s] (never negative).

    `gps_new` marks a fix that arrived this cycle; `gps_ok` that it is usable (2D/3D fix).
    The fix describes the speed `latency_samples` cycles ago: the innovation is taken
    against the prediction stored then and applied to the present estimate.
    """
    n_ring = state.shape[0] - SPD_RING0
    if state[SPD_INIT] == 0.0:
        if not (gps_new and gps_ok and math.isfinite(gps_speed)):
            return 0.0
        state[SPD_U] = gps_speed
        state[SPD_BIAS] = 0.0
        for k in range(n_ring):
            state[SPD_RING0 + k] = gps_speed
        state[SPD_INIT] = 1.0
    a = accel_x if math.isfinite(accel_x) else 0.0
    u = state[SPD_U] + (a - state[SPD_BIAS]) * dt
    head = int(state[SPD_HEAD])
    if gps_new and gps_ok and math.isfinite(gps_speed):
        lag = min(latency_samples, n_ring - 1)
        past = state[SPD_RING0 + (head - lag) % n_ring]
        innovation = gps_speed - past
        u += gain * innovation
        # an accelerometer bias shows up as a persistent innovation of one sign
        state[SPD_BIAS] -= bias_gain * innovation
        # shift the stored predictions too, so the next fix is compared like with like
        for k in range(n_ring):
            state[SPD_RING0 + k] += gain * innovation
    if u < 0.0:
        u = 0.0
    head = (head + 1) % n_ring
    state[SPD_RING0 + head] = u
    state[SPD_HEAD] = head
    state[SPD_U] = u
    return u
