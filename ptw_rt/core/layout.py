"""The two fixed-layout records that cross between I/O and the math: Sample in, Estimates out.

Both are flat float64 arrays with named indices, so the jitted step takes them
without Python objects. The I/O edge (daemon, replay, evaluation) fills one
Sample per 10 ms cycle from the newest frame of each input and reads one
Estimates back. Bit fields are stored as exact small integers in float64.
"""

from __future__ import annotations

import numpy as np

# ---- Sample: raw sensor values of one cycle, in the CAN contract's units ----
S_TIME = 0  # s, the cycle's time stamp (monotonic clock or log time)
S_ROLL_RATE_BODY = 1  # rad/s, IMU body x
S_PITCH_RATE_BODY = 2  # rad/s, IMU body y
S_YAW_RATE_BODY = 3  # rad/s, IMU body z
S_ACCEL_X = 4  # m/s^2, specific force, body axes
S_ACCEL_Y = 5
S_ACCEL_Z = 6
S_STEER_COUNT = 7  # raw encoder count 0..1023
S_GPS_SPEED = 8  # m/s over ground
S_GPS_FIX = 9  # 0 none, 1 dead reckoning, 2 2D, 3 3D
S_FRESH = 10  # MSG_* bits: a frame of that message arrived since the previous cycle
S_STALE = 11  # MSG_* bits: no valid frame of that message within its timeout
S_INPUT_REASONS = 12  # REASON_* bits raised by the I/O edge (decode errors, range, counters, overrun, send)
S_GPS_COURSE = 13  # deg, course over ground (0..360, clockwise from north)
S_IMU_AGE = 14  # s from the newest IMU_Rates frame's arrival to the cycle's time (latency compensation)
S_SUSPECT = 15  # MSG_* bits: a frame of that message came with a broken rolling counter this cycle (not trusted)
S_STEER_AGE = 16  # s from the newest Steer_Encoder frame's arrival to the cycle's time (aligned with the IMU's)
S_GPS_AGE = 17  # s from the newest GPS_Velocity frame's (or serial fix's) arrival to the cycle's time
SAMPLE_SIZE = 18

# input messages, bit order of EST_Status.SensorTimeouts
MSG_IMU_RATES = 1
MSG_IMU_ACCEL = 2
MSG_STEER = 4
MSG_GPS = 8
INPUT_MESSAGE_BITS = {
    "IMU_Rates": MSG_IMU_RATES,
    "IMU_Accel": MSG_IMU_ACCEL,
    "Steer_Encoder": MSG_STEER,
    "GPS_Velocity": MSG_GPS,
}

# EST_Status.ReasonBits
REASON_SPEED_LOW = 1 << 0
REASON_GPS_LOST = 1 << 1
REASON_STALE = 1 << 2
REASON_DIVERGING = 1 << 3
REASON_OUT_OF_RANGE = 1 << 4
REASON_DECODE_ERRORS = 1 << 5
REASON_COUNTER_JUMPS = 1 << 6
REASON_OVERRUN = 1 << 7
REASON_SEND_FAILURE = 1 << 8
REASON_IMPLAUSIBLE = 1 << 9  # the published channel and the UIHOSMO on the sensors disagree (diagnostics)
REASON_ATTITUDE_INCONSISTENT = 1 << 10  # the attitude filter's innovations contradict it (a gyro fault)
REASON_GYRO_STEP = 1 << 11  # the roll gyro's bias stepped within a sample, and the attitude filter took the step
# the input checks' bits: this cycle's value of some sensor is a held or doubtful one (stale, out of range, a broken
# rolling counter, an undecodable frame). What learns or compares on the cycle's values skips such a cycle.
INPUT_FAULTS = REASON_STALE | REASON_OUT_OF_RANGE | REASON_COUNTER_JUMPS | REASON_DECODE_ERRORS
REASON_NAMES = (
    "speed_low",
    "gps_lost",
    "sensor_stale",
    "observer_reset",
    "out_of_range",
    "decode_errors",
    "counter_jumps",
    "overrun",
    "send_failure",
    "implausible",
    "attitude_inconsistent",
    "gyro_step",
)

# EST_Status.Mode
MODE_INIT = 0
MODE_CONVERGING = 1
MODE_VALID = 2
MODE_DEGRADED = 3
MODE_FAULT = 4
MODE_NAMES = ("INIT", "CONVERGING", "VALID", "DEGRADED", "FAULT")

# ---- Estimates: what the estimator publishes (SI units, SAE signs) plus diagnostics ----
E_ROLL = 0  # rad
E_ROLL_RATE = 1  # rad/s
E_RIDER_TORQUE = 2  # N m
E_STEER = 3  # rad
E_STEER_RATE = 4  # rad/s
E_LAT_VEL = 5  # m/s
E_FY_FRONT = 6  # N
E_FY_REAR = 7  # N
E_C_ALPHA_FRONT = 8  # N/rad
E_C_GAMMA_FRONT = 9
E_C_ALPHA_REAR = 10
E_C_GAMMA_REAR = 11
E_SPEED = 12  # m/s, conditioned forward speed
E_YAW_RATE = 13  # rad/s, ground frame, as measured (before the fusion filter's bias correction)
E_MODE = 14  # MODE_*
E_REASONS = 15  # REASON_* bits
E_VALID = 16  # V_* bits
E_ROLL_UIHOSMO = 17  # rad, the UIHOSMO's unknown-input roll before fusion (diagnostic)
E_LAT_ACCEL = 18  # m/s^2, conditioned lateral acceleration at the centre of mass (diagnostic)
E_EXCITATION = 19  # bits 0..3: stiffness i currently excited (adapting)
E_ROLL_ADAPTIVE = 20  # rad, the adaptive observer's roll state (diagnostic)
E_LAT_VEL_ADAPTIVE = 21  # m/s, the adaptive observer's lateral states (diagnostic)
E_FY_FRONT_ADAPTIVE = 22  # N
E_FY_REAR_ADAPTIVE = 23  # N
E_Y_A = 24  # virtual output y_a of seed 001 eq. 15 as measured (diagnostic)
E_TORQUE_UIHOSMO = 25  # N m, the UIHOSMO's unknown-input torque (diagnostic)
E_FY_FRONT_STA = 26  # N, seed 003's super-twisting force observer (independent cross-check)
E_FY_REAR_STA = 27
E_ROLL_RATE_MEASURED = 28  # rad/s, the conditioned roll-rate gyro before bias correction (what baselines use)
E_YAW_GYRO_BIAS = 29  # rad/s, the fusion filter's estimate of the yaw-gyro bias (diagnostic)
E_ROLL_GYRO_BIAS = 30  # rad/s, ... of the roll-gyro bias
E_ROLL_SD = 31  # rad, standard deviation of the published roll (the attitude filter's covariance)
E_ROLL_FUSION = 32  # rad, the Sharp-model fusion filter's roll after it fused the kinematic roll (diagnostic)
E_PITCH_GYRO_BIAS = 33  # rad/s, the attitude filter's pitch-gyro bias estimate
E_LAT_ACCEL_BIAS = 34  # m/s^2, the attitude filter's lateral-accelerometer bias estimate
E_TYRE_SCALE = 35  # the tyres' scale k (published stiffness = k x nominal; the tyre bank's estimate)
E_TYRE_LOG_SD = 36  # its posterior spread, sd of log k
E_TYRE_NIS = 37  # the most likely tyre filter's windowed normalised innovation (consistency, expected 5)
E_TYRE_LEARNING = 38  # 1 while the ride's evidence moves the tyre estimate
E_C_ALPHA_FRONT_SEED001 = 39  # N/rad, seed 001's adaptive observer (the seed's method, evaluated beside ours)
E_C_GAMMA_FRONT_SEED001 = 40
E_C_ALPHA_REAR_SEED001 = 41
E_C_GAMMA_REAR_SEED001 = 42
E_TORQUE_UIO_SENSORS = 43  # N m, the UIHOSMO on the sensors' rider torque (issue #16; 0 while it is not valid)
E_TORQUE_RESIDUAL = 44  # N m, windowed RMS of published - E_TORQUE_UIO_SENSORS (the plausibility monitor's)
E_PLAUSIBILITY = 45  # that residual over its speed-dependent threshold: > 1 raises REASON_IMPLAUSIBLE
E_STEER_RESIDUAL = 46  # rad, running mean of steer - kinematic steer riding nearly straight (> 0.5 deg: implausible)
E_TYRE_CHANGE = 47  # nats, the tyre bank's change statistic (a neighbouring tyre explains the last cycles better)
E_ROLL_UIO_SENSORS = 48  # rad, the UIHOSMO channel's own roll (raw IMU and speed, no attitude filter; 0 until started)
E_PITCH_DOUBTED = 49  # 1 while the longitudinal accelerometer against GPS doubts the attitude's pitch: no tyre learning
E_TYRE_BALANCE = 50  # the front tyre's stiffness factor against the rear's the tyre bank's check points to (not applied
# to the published front; 1 = the file's balance)
E_TYRE_BALANCE_DOUBTED = 51  # 1 while it does not confirm the file's balance: neither axle's stiffness VALID
E_STEER_ZERO_ERROR = 52  # rad, the steer zero's error the tyre bank's check points to, beyond the conditioning's zero
E_STEER_ZERO_DOUBTED = 53  # 1 while it does not confirm the conditioning's zero (then E_TYRE_BALANCE_DOUBTED too)
E_TYRE_BALANCE_LOG_SD = 54  # sd of the log of E_TYRE_BALANCE (the check's marginal: what the steer zero may be too)
E_STEER_ZERO_ERROR_SD = 55  # rad, sd of E_STEER_ZERO_ERROR
ESTIMATES_SIZE = 56

# per-signal validity bits (E_VALID), one per published signal group
V_ROLL = 1 << 0
V_ROLL_RATE = 1 << 1
V_RIDER_TORQUE = 1 << 2
V_STEER = 1 << 3
V_STEER_RATE = 1 << 4
V_LAT_VEL = 1 << 5
V_FY_FRONT = 1 << 6
V_FY_REAR = 1 << 7
V_CORNERING = 1 << 8
V_CAMBER = 1 << 9

ESTIMATE_NAMES = (
    "roll",
    "roll_rate",
    "rider_torque",
    "steer",
    "steer_rate",
    "lat_vel",
    "fy_front",
    "fy_rear",
    "c_alpha_front",
    "c_gamma_front",
    "c_alpha_rear",
    "c_gamma_rear",
    "speed",
    "yaw_rate",
    "mode",
    "reasons",
    "valid",
    "roll_uihosmo",
    "lat_accel",
    "excitation",
    "roll_adaptive",
    "lat_vel_adaptive",
    "fy_front_adaptive",
    "fy_rear_adaptive",
    "y_a",
    "torque_uihosmo",
    "fy_front_sta",
    "fy_rear_sta",
    "roll_rate_measured",
    "yaw_gyro_bias",
    "roll_gyro_bias",
    "roll_sd",
    "roll_fusion",
    "pitch_gyro_bias",
    "lat_accel_bias",
    "tyre_scale",
    "tyre_log_sd",
    "tyre_nis",
    "tyre_learning",
    "c_alpha_front_seed001",
    "c_gamma_front_seed001",
    "c_alpha_rear_seed001",
    "c_gamma_rear_seed001",
    "torque_uio_sensors",
    "torque_residual",
    "plausibility",
    "steer_residual",
    "tyre_change",
    "roll_uio_sensors",
    "pitch_doubted",
    "tyre_balance",
    "tyre_balance_doubted",
    "steer_zero_error",
    "steer_zero_doubted",
    "tyre_balance_log_sd",
    "steer_zero_error_sd",
)
assert len(ESTIMATE_NAMES) == ESTIMATES_SIZE


def new_sample() -> np.ndarray:
    return np.zeros(SAMPLE_SIZE)


def new_estimates() -> np.ndarray:
    return np.zeros(ESTIMATES_SIZE)


def reason_names(bits: int) -> list[str]:
    return [name for k, name in enumerate(REASON_NAMES) if int(bits) >> k & 1]
