"""The UIHOSMO channel's own kinematics (issue #16): roll, ground yaw rate, roll rate and the centre of mass's
lateral acceleration from the raw IMU and the speed, without the attitude filter.

Why a second roll: the UIHOSMO on the sensors takes the roll as a measured input. Fed the attitude filter's roll
(and rates and a_y turned into the road plane with it) the channel only repeated the published roll, faults
included. This roll has no bias or sideslip state and a fixed crossover; the caller (the diagnostics stage) removes
the attitude filter's calibrations of the pitch and yaw gyros and the lateral accelerometer, never its roll or the
roll-rate gyro's bias. What that buys and costs is in docs/estimator.md ("The channel's own roll").

A complementary filter with a fixed crossover w_c: above w_c the roll-rate gyro integrated, below it the
roll at which the accelerometer sees gravity once the motion is removed. With h the IMU's height above the
ground, x_i its forward offset from the reference point (`ptw_rt/sim/sensors.py` derives the same kinematics,
body axes, z down), the specific force is

    f_y = A cos(phi) - g sin(phi) + h phi_ddot,    f_z = -A sin(phi) - g cos(phi) + h phi_dot^2,
    A   = v_y_dot + u r + x_i r_dot - r^2 h sin(phi)       (the horizontal lateral acceleration)

so phi = atan2(A, g) - atan2(f_y - h phi_ddot, -(f_z - h phi_dot^2)). The kinematics give all of A but
v_y_dot, which is left out: a lateral velocity that changes (a quick lane change on soft tyres) is this roll's
error, ~v_y_dot / g, which the crossover filters. A roll-gyro bias b moves the roll by b / w_c at most.

The ground yaw rate is the body rates turned with this roll, and a_y (the centre of mass's lateral
acceleration in the road plane, what the UIHOSMO's pre-observer injects) the specific force turned with it plus
the lever-arm terms of `core.params.lever_arm_coefficients`.

Layouts (float64 vectors): state `ST_*`, parameters `P_*` (`build_params`), outputs `OUT_*`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core.conditioning import derivative_filter, ground_yaw_rate, lateral_accel_at_com
from ptw_rt.core.params import lever_arm_coefficients
from ptw_rt.core.stage import Layout

# a specific force whose size is further than this share of g from what the motion and gravity give (sqrt(A^2 +
# g^2)) says nothing about the roll this cycle: a bump, a dead accelerometer reading zero (whose direction would
# be a roll of 180 deg), a knock on the mount. The gyro alone carries the roll through it (Fusion AHRS's
# acceleration rejection, by magnitude)
ACCEL_REJECT_SHARE = 0.25

STATE = Layout(
    "ST_",
    init=1,  # 1 once started (the roll from the accelerometer alone, the derivative filters on the rates)
    roll=1,  # rad
    df=4,  # derivative filters: [p_f, p_dot_f, r_f, r_dot_f]
)
ST_INIT, ST_ROLL, ST_DF = STATE.offsets
STATE_SIZE = STATE.size

PARAMS = Layout(
    "P_",
    dt=1,
    g=1,
    pull=1,  # share of the accelerometer's roll taken per cycle, 1 - exp(-w_c dt)
    # rad/s of the critically damped derivative filters (the conditioning stage's bandwidth, not its filters: those
    # differentiate the attitude filter's bias-corrected rates)
    deriv_omega=1,
    imu_height=1,  # m above the ground
    imu_forward=1,  # m ahead of the reference point
    a_y_r_dot=1,  # lever arm to the centre of mass: a_y(CoM) = a_y(IMU) + a_y_r_dot r_dot + a_y_phi_ddot phi_ddot
    a_y_phi_ddot=1,
    max_roll=1,  # rad: beyond, the roll is no lean a rider survives (the gyro alone for too long): restarted
)
P_DT, P_G, P_PULL, P_DERIV_OMEGA, P_IMU_HEIGHT, P_IMU_FORWARD, P_A_Y_R_DOT, P_A_Y_PHI_DDOT, P_MAX_ROLL = PARAMS.offsets
PARAM_SIZE = PARAMS.size

OUTPUTS = Layout(
    "OUT_",
    roll=1,  # rad
    yaw_rate=1,  # rad/s, ground frame (the body rates turned with this roll)
    roll_rate=1,  # rad/s, the gyro's, no bias removed
    a_y=1,  # m/s^2, the centre of mass's lateral acceleration in the road plane (nan: the accelerometer not sound)
    valid=1,  # 1 once started
)
OUT_ROLL, OUT_YAW_RATE, OUT_ROLL_RATE, OUT_A_Y, OUT_VALID = OUTPUTS.offsets
OUT_SIZE = OUTPUTS.size


def build_params(settings, design) -> np.ndarray:
    est, sens, veh = settings.estimator, settings.sensors, settings.vehicle
    dt = float(design.sample_time)
    lever = lever_arm_coefficients(veh, sens.imu_forward, sens.imu_height)
    return PARAMS.vector(
        dt=dt,
        g=veh.g,
        pull=1.0 - math.exp(-est.plausibility.roll_crossover * dt),
        deriv_omega=2.0 * math.pi * est.derivative_filter_hz,
        imu_height=sens.imu_height,
        imu_forward=sens.imu_forward,
        a_y_r_dot=lever[0],
        a_y_phi_ddot=lever[1],
        max_roll=est.max_roll,
    )


@njit(cache=True)
def gravity_roll(f_y: float, f_z: float, lateral: float, p: float, p_dot: float, h: float, g: float) -> float:
    """The roll at which the accelerometer sees gravity, given the horizontal lateral acceleration (module doc);
    nan where the specific force's size is not what the motion and gravity give (ACCEL_REJECT_SHARE)."""
    y = f_y - h * p_dot
    z = -(f_z - h * p * p)
    if abs(math.hypot(y, z) - math.hypot(lateral, g)) > ACCEL_REJECT_SHARE * g:
        return math.nan
    return math.atan2(lateral, g) - math.atan2(y, z)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def channel_kinematics_step(
    st: np.ndarray,
    prm: np.ndarray,
    out: np.ndarray,
    p: float,
    q: float,
    r: float,
    f_y: float,
    f_z: float,
    u: float,
    accel_sound: bool,
) -> None:
    """One cycle from the body rates p, q, r [rad/s], the specific force f_y, f_z [m/s^2] and the speed u [m/s].
    ``accel_sound``: the accelerometer's reading is fresh and in range (otherwise the gyro alone carries the roll
    and a_y is nan). A non-finite input holds the outputs for the cycle."""
    if not math.isfinite(p + q + r + u) or (accel_sound and not math.isfinite(f_y + f_z)):
        return
    dt, g, h = prm[P_DT], prm[P_G], prm[P_IMU_HEIGHT]
    started = st[ST_INIT] != 0.0
    roll = st[ST_ROLL]
    yaw_rate = ground_yaw_rate(q, r, roll)
    if not started:
        st[ST_DF + 0] = p
        st[ST_DF + 1] = 0.0
        st[ST_DF + 2] = yaw_rate
        st[ST_DF + 3] = 0.0
    p_dot = derivative_filter(st, ST_DF + 0, p, prm[P_DERIV_OMEGA], dt)
    r_dot = derivative_filter(st, ST_DF + 2, yaw_rate, prm[P_DERIV_OMEGA], dt)
    measured = math.nan
    if accel_sound:
        lateral = u * yaw_rate + prm[P_IMU_FORWARD] * r_dot - yaw_rate * yaw_rate * h * math.sin(roll)
        measured = gravity_roll(f_y, f_z, lateral, p, p_dot, h, g)
    if started:
        roll += dt * p
        if math.isfinite(measured):
            roll += prm[P_PULL] * (measured - roll)
    elif math.isfinite(measured):
        roll = measured
        st[ST_INIT] = 1.0
    if abs(roll) > prm[P_MAX_ROLL]:  # the gyro alone ran away (an accelerometer rejected for long): start again
        roll = 0.0
        st[ST_INIT] = 0.0
    st[ST_ROLL] = roll
    out[OUT_ROLL] = roll
    out[OUT_YAW_RATE] = yaw_rate
    out[OUT_ROLL_RATE] = p
    if accel_sound:
        a_y = lateral_accel_at_com(f_y, f_z, roll, r_dot, p_dot, prm[P_A_Y_R_DOT], prm[P_A_Y_PHI_DDOT])
    else:
        a_y = math.nan
    out[OUT_A_Y] = a_y
    out[OUT_VALID] = st[ST_INIT]
