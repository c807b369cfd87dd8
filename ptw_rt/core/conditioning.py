"""Stage 4, conditioning: raw values -> the model's measurements, and the published roll (jitted).

Helpers (also used by the simulator's tests and the baselines):

- Steering encoder counts -> steer angle, with the calibration zero and wrap-around
  of a 10-bit absolute encoder (1024 counts per revolution). The zero is refined riding straight
  (`learn_steer_zero`): there the steer angle is the kinematic L r / (u cos caster), so what the encoder
  reads beyond it, averaged over seconds, is its calibration error. A count off (0.35 deg) is as large as
  the slip-angle difference of a steady corner and would read as tyres 25 % off.
- Body-frame IMU -> model frame. The IMU leans with the chassis: with roll phi (and
  negligible pitch) the ground yaw rate is q sin(phi) + r cos(phi), and the
  horizontal lateral acceleration is f_y cos(phi) - f_z sin(phi), which needs no
  gravity compensation.

The stage (`conditioning_stage`) runs after the attitude stage: it takes the attitude filter's roll and
bias-corrected rates (or, while that filter is not running, the raw gyros de-rolled with the last published
roll), the steer angle, the rate derivatives through critically damped tracking filters, and moves a_y from
the IMU to the centre of mass (lever arm: the seed 001 output a_y = (F_yf + F_yr) / M). It also decides whether
the model-based observers run this cycle (core sensors fresh, speed above the model's validity) and makes the
published roll: the attitude filter's, carried from the IMU's sample time to the cycle's with the gyro; without
the attitude filter (IMU missing at start), the gyro integrated and pulled to the kinematic roll atan(u r / g).
(The forward-speed filter is the `speed` stage, `ptw_rt.core.speed`: the attitude stage between the two needs
the speed, and this one needs the attitude.)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import attitude as att
from ptw_rt.core import inputs as inp
from ptw_rt.core import speed as spd
from ptw_rt.core.layout import INPUT_FAULTS, REASON_GPS_LOST, REASON_SPEED_LOW, S_IMU_AGE, S_STEER_AGE
from ptw_rt.core.params import lever_arm_coefficients
from ptw_rt.core.stage import Layout, Stage

TWO_PI = 2.0 * math.pi

# Riding straight, for the steer zero: the kinematic steer L r / u is then a few hundredths of a degree and the
# slip angles' difference (what makes a corner's steer differ from it) is negligible. Over the matrix the running
# mean of the residual on healthy rides stays within 0.1 count (docs/estimator.md, "Steer zero").
STRAIGHT_YAW_RATE = 0.02  # rad/s
STRAIGHT_LAT_ACCEL = 0.5  # m/s^2
STEER_ZERO_MIN_SPEED = 5.0  # m/s: slower, the rider balances with the handlebar
# counts: how well straight riding can tell the zero at best (the residual's running mean above), its sd's floor
STEER_ZERO_FLOOR = 0.1

STATE = Layout(
    "ST_",
    init=1,  # 1 once the derivative filters have been started
    df=4,  # derivative filters: [r_f, r_dot_f, p_f, p_dot_f]
    roll=1,  # rad, the published roll of the last cycle
    steer_zero_shift=1,  # rad, the learned steer-encoder zero error (subtracted from the encoder's angle)
    steer_zero_seconds=1,  # s of straight riding it was learned from (a restored value counts as learned)
    rates_gap=1,  # 1 while the IMU's rates are stale: the derivative filters restart on the first fresh ones
)
ST_INIT, ST_DF, ST_ROLL, ST_STEER_ZERO_SHIFT, ST_STEER_ZERO_SECONDS, ST_RATES_GAP = STATE.offsets

PARAMS = Layout(
    "P_",
    dt=1,
    g=1,
    steer_zero=1,  # encoder count of straight ahead
    steer_cpr=1,  # encoder counts per revolution
    deriv_omega=1,  # rad/s of the critically damped derivative filters
    a_y_r_dot=1,  # lever arm: a_y(CoM) = a_y(IMU) + a_y_r_dot r_dot + a_y_phi_ddot phi_ddot
    a_y_phi_ddot=1,
    min_speed=1,  # m/s: below, the model-based observers are held in reset
    fusion_rate=1,  # 1/s: pull of the fallback roll to the kinematic roll
    max_roll=1,  # rad: a published roll beyond is a divergence
    steer_zero_rate=1,  # share of the straight-riding residual learned per cycle (dt / time constant)
    steer_zero_max_shift=1,  # rad: bound of the learned zero error
    steer_zero_sd=1,  # rad: the configured zero's error a priori (sd)
    steer_zero_floor=1,  # rad: STEER_ZERO_FLOOR
    steer_zero_evidence_sd=1,  # rad: the tyre bank's zero check moves the zero once its sd is within this ...
    steer_zero_evidence_rate=1,  # ... by this share of the error it points to per cycle (dt / time constant)
    wheelbase=1,  # m
    cos_caster=1,
)
(
    P_DT,
    P_G,
    P_STEER_ZERO,
    P_STEER_CPR,
    P_DERIV_OMEGA,
    P_A_Y_R_DOT,
    P_A_Y_PHI_DDOT,
    P_MIN_SPEED,
    P_FUSION_RATE,
    P_MAX_ROLL,
    P_STEER_ZERO_RATE,
    P_STEER_ZERO_MAX_SHIFT,
    P_STEER_ZERO_SD,
    P_STEER_ZERO_FLOOR,
    P_STEER_ZERO_EVIDENCE_SD,
    P_STEER_ZERO_EVIDENCE_RATE,
    P_WHEELBASE,
    P_COS_CASTER,
) = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    deroll=1,  # rad: the roll this cycle's measurements are de-rolled with (attitude filter's, else last published)
    roll_rate=1,  # rad/s: bias-corrected by the attitude filter (raw while it is not running)
    yaw_rate=1,  # rad/s: ground yaw rate, likewise
    steer=1,  # rad
    a_y=1,  # m/s^2: lateral acceleration of the centre of mass in the road plane
    yaw_accel=1,  # rad/s^2: filtered derivative of yaw_rate
    roll_accel=1,  # rad/s^2: filtered derivative of roll_rate
    speed_low=1,  # 1: speed unknown or below the model's validity
    run=1,  # 1: the model-based observers run this cycle (core sensors fresh, speed valid)
    reasons=1,  # REASON_* bits of the cycle's conditions: the inputs' and SPEED_LOW
    roll_kin=1,  # rad: kinematic roll atan(u r / g)
    roll=1,  # rad: the published roll, at the cycle's time
    roll_last=1,  # rad: the published roll of the last cycle
    diverged=1,  # 1: the roll was implausible and replaced (an observer-reset event for the supervisor)
    steer_zero_shift=1,  # rad: the learned steer-encoder zero error, already removed from `steer`
    steer_zero_sd=1,  # rad: how far the zero may still be off (`steer_zero_sd`)
    steer_lead=1,  # s: how much newer the steer reading is than the IMU's (`steer_lead`)
)
(
    OUT_DEROLL,
    OUT_ROLL_RATE,
    OUT_YAW_RATE,
    OUT_STEER,
    OUT_A_Y,
    OUT_YAW_ACCEL,
    OUT_ROLL_ACCEL,
    OUT_SPEED_LOW,
    OUT_RUN,
    OUT_REASONS,
    OUT_ROLL_KIN,
    OUT_ROLL,
    OUT_ROLL_LAST,
    OUT_DIVERGED,
    OUT_STEER_ZERO_SHIFT,
    OUT_STEER_ZERO_SD,
    OUT_STEER_LEAD,
) = OUTPUTS.offsets


def build_params(settings, design) -> np.ndarray:
    est, sens, veh = settings.estimator, settings.sensors, settings.vehicle
    lever = lever_arm_coefficients(veh, sens.imu_forward, sens.imu_height)
    return PARAMS.vector(
        dt=float(design.sample_time),
        g=veh.g,
        steer_zero=sens.steer_zero_count,
        steer_cpr=sens.steer_counts_per_rev,
        deriv_omega=2.0 * math.pi * est.derivative_filter_hz,
        a_y_r_dot=lever[0],
        a_y_phi_ddot=lever[1],
        min_speed=design.min_valid_speed,
        fusion_rate=1.0 / est.roll_fusion_time_constant,
        max_roll=est.max_roll,
        steer_zero_rate=float(design.sample_time) / sens.steer_zero_time_constant,
        steer_zero_max_shift=sens.steer_zero_max_shift * sens.steer_count_rad,
        steer_zero_sd=sens.steer_zero_sd * sens.steer_count_rad,
        steer_zero_floor=STEER_ZERO_FLOOR * sens.steer_count_rad,
        steer_zero_evidence_sd=est.tyre_bank.valid_zero_sd * sens.steer_count_rad,
        steer_zero_evidence_rate=float(design.sample_time) / sens.steer_zero_evidence_time_constant,
        wheelbase=veh.l_f + veh.l_r,
        cos_caster=math.cos(veh.caster),
    )


@njit(cache=True)
def steer_angle(count: float, zero_count: float, counts_per_rev: float) -> float:
    """Angle [rad] of an absolute encoder reading, wrapped to (-pi, pi] around the calibration zero."""
    d = (count - zero_count) % counts_per_rev
    if d > 0.5 * counts_per_rev:
        d -= counts_per_rev
    return d * TWO_PI / counts_per_rev


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def kinematic_steer(wheelbase: float, cos_caster: float, yaw_rate: float, roll: float, u: float) -> float:
    """Steer angle [rad] of a turn at this yaw rate without tyre slip: L r cos(roll) / (u cos(caster))."""
    return wheelbase * yaw_rate * math.cos(roll) / (u * cos_caster)


@njit(cache=True)
def learn_steer_zero(
    st: np.ndarray, prm: np.ndarray, encoder_steer: float, yaw_rate: float, a_y: float, u: float
) -> None:
    """Riding straight (small yaw rate and lateral acceleration, some speed), move the learned zero error
    towards the encoder's angle less the kinematic steer, by `steer_zero_rate`, within +-`steer_zero_max_shift`.
    The caller decides the cycle's inputs are sound."""
    if u < STEER_ZERO_MIN_SPEED or abs(yaw_rate) > STRAIGHT_YAW_RATE or abs(a_y) > STRAIGHT_LAT_ACCEL:
        return
    kinematic = kinematic_steer(prm[P_WHEELBASE], prm[P_COS_CASTER], yaw_rate, 0.0, u)  # riding straight: upright
    shift = st[ST_STEER_ZERO_SHIFT] + prm[P_STEER_ZERO_RATE] * (encoder_steer - kinematic - st[ST_STEER_ZERO_SHIFT])
    bound = prm[P_STEER_ZERO_MAX_SHIFT]
    st[ST_STEER_ZERO_SHIFT] = min(max(shift, -bound), bound)
    st[ST_STEER_ZERO_SECONDS] += prm[P_DT]


@njit(cache=True)
def learn_steer_zero_from_evidence(st: np.ndarray, prm: np.ndarray, error: float, error_sd: float) -> None:
    """Move the learned zero error by `steer_zero_evidence_rate` of the error the tyre bank's zero check points to
    (`error`, rad, beyond this zero), once its sd is within `steer_zero_evidence_sd`; within +-`steer_zero_max_shift`.
    The check sees the zero in corners, where straight riding cannot (a slalom has no straight), apart from the
    front tyre (docs/estimator.md, "The steer zero the balance rests on"); the bank re-centres its evidence on the
    new zero."""
    if not error_sd <= prm[P_STEER_ZERO_EVIDENCE_SD] or not math.isfinite(error):  # also a NaN
        return
    bound = prm[P_STEER_ZERO_MAX_SHIFT]
    shift = st[ST_STEER_ZERO_SHIFT] + prm[P_STEER_ZERO_EVIDENCE_RATE] * error
    st[ST_STEER_ZERO_SHIFT] = min(max(shift, -bound), bound)


@njit(cache=True)
def steer_zero_sd(st: np.ndarray, prm: np.ndarray) -> float:
    """rad: how far the zero may still be off. The learning is a first-order filter of `steer_zero_rate` per cycle
    of straight riding, so of the configured zero's error (sd `steer_zero_sd`) exp(-seconds / time constant) is
    left; straight riding tells it no better than its floor (a restored zero counts a time constant)."""
    left = prm[P_STEER_ZERO_SD] * math.exp(-st[ST_STEER_ZERO_SECONDS] * prm[P_STEER_ZERO_RATE] / prm[P_DT])
    return math.sqrt(left * left + prm[P_STEER_ZERO_FLOOR] ** 2)


@njit(cache=True)
def ground_yaw_rate(q_body: float, r_body: float, roll: float) -> float:
    return q_body * math.sin(roll) + r_body * math.cos(roll)


@njit(cache=True)
def horizontal_lateral_accel(f_y_body: float, f_z_body: float, roll: float) -> float:
    """Lateral acceleration in the road plane from body-frame specific force (no gravity term needed)."""
    return f_y_body * math.cos(roll) - f_z_body * math.sin(roll)


@njit(cache=True)
def lateral_accel_at_com(
    f_y_body: float, f_z_body: float, roll: float, r_dot: float, p_dot: float, c_r_dot: float, c_phi_ddot: float
) -> float:
    """The centre of mass's lateral acceleration in the road plane, from the IMU's body-frame specific force and
    the lever-arm terms c_r_dot r_dot + c_phi_ddot phi_ddot (`core.params.lever_arm_coefficients`)."""
    return horizontal_lateral_accel(f_y_body, f_z_body, roll) + c_r_dot * r_dot + c_phi_ddot * p_dot


@njit(cache=True)
def kinematic_roll(speed: float, yaw_rate_ground: float, g: float) -> float:
    """Roll of a steady coordinated turn, atan(u r / g): the baseline a user would pick."""
    return math.atan(speed * yaw_rate_ground / g)


@njit(cache=True)
def _finite_or(value: float, fallback: float) -> float:
    return value if math.isfinite(value) else fallback


@njit(cache=True)
def derivative_filter(z: np.ndarray, k: int, y: float, omega: float, dt: float) -> float:
    """Critically damped 2nd-order tracking filter, exact ZOH; returns the filtered derivative of y."""
    a = omega * dt
    e = math.exp(-a)
    x0 = z[k] - y
    x1 = z[k + 1]
    z[k] = y + e * ((1.0 + a) * x0 + dt * x1)
    z[k + 1] = e * (-omega * omega * dt * x0 + (1.0 - a) * x1)
    return z[k + 1]


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def steer_lead(imu_age: float, steer_age: float, dt: float) -> float:
    """s by which the steer reading is newer than the IMU's, from their frames' arrival times (within one cycle).

    The encoder and the IMU sample at their own phases, so a cycle's steer and rates describe instants up to a
    cycle apart. The lateral filters take the IMU's instant for all of their measurements and carry the steer back
    to it (`ptw_rt.core.lateral`): on the simulator's phases (the steer 4.6 ms newer) the steer read as if 4.6 ms
    early made the tyres read 4.7 % soft in town (`docs/estimator.md`, "The steer at the IMU's instant")."""
    lead = imu_age - steer_age
    if not math.isfinite(lead):
        return 0.0
    return min(max(lead, -dt), dt)


@njit(cache=True)
def conditioning_stage(
    sample: np.ndarray,
    st: np.ndarray,
    prm: np.ndarray,
    out: np.ndarray,
    inputs: np.ndarray,
    speed: np.ndarray,
    attitude: np.ndarray,
    zero_error_before: float,
    zero_error_sd_before: float,
) -> None:
    """One cycle from the inputs, speed and attitude stages' outputs (and the Sample's IMU age), and the steer zero
    error the tyre bank's check pointed to the cycle before (rad, and its sd: `learn_steer_zero_from_evidence`)."""
    dt = prm[P_DT]
    raw = inputs[inp.OUT_RAW : inp.OUT_RAW + inp.N_RAW]
    u = speed[spd.OUT_U]
    attitude_ok = attitude[att.OUT_OK] != 0.0
    if attitude_ok:
        roll_prev = attitude[att.OUT_ROLL]
        p_rate = attitude[att.OUT_ROLL_RATE]
        r_ground = attitude[att.OUT_YAW_RATE]
    else:
        roll_prev = st[ST_ROLL]
        p_rate = raw[inp.RAW_P]
        r_ground = ground_yaw_rate(raw[inp.RAW_Q], raw[inp.RAW_R], roll_prev)
    delta = steer_angle(raw[inp.RAW_STEER], prm[P_STEER_ZERO], prm[P_STEER_CPR])
    # the derivatives start from the rates' first values, and again from the first new and sound ones after the
    # rates were stale: the step from the held rates to the fresh ones read as a jerk, and its lever-arm term put
    # a 0.3 s spike into a_y (the lateral filters' torque, restarted on it, read 20-50 N m off)
    if inputs[inp.OUT_IMU_OK] == 0.0:
        st[ST_RATES_GAP] = 1.0
    elif st[ST_INIT] == 0.0 or (st[ST_RATES_GAP] != 0.0 and inputs[inp.OUT_RATES_OK] != 0.0):
        st[ST_DF + 0], st[ST_DF + 1] = r_ground, 0.0
        st[ST_DF + 2], st[ST_DF + 3] = p_rate, 0.0
        st[ST_RATES_GAP] = 0.0
    r_dot = derivative_filter(st, ST_DF + 0, r_ground, prm[P_DERIV_OMEGA], dt)
    p_dot = derivative_filter(st, ST_DF + 2, p_rate, prm[P_DERIV_OMEGA], dt)
    a_y = lateral_accel_at_com(
        raw[inp.RAW_AY] - attitude[att.OUT_BAY],
        raw[inp.RAW_AZ],
        roll_prev,
        r_dot,
        p_dot,
        prm[P_A_Y_R_DOT],
        prm[P_A_Y_PHI_DDOT],
    )
    st[ST_INIT] = 1.0

    speed_low = speed[spd.OUT_KNOWN] == 0.0 or u < prm[P_MIN_SPEED]
    reasons = int(inputs[inp.OUT_REASONS])
    if (
        attitude_ok
        and inputs[inp.OUT_CORE_OK] != 0.0
        and inputs[inp.OUT_ACCEL_OK] != 0.0
        and speed[spd.OUT_KNOWN] != 0.0
        and reasons & INPUT_FAULTS == 0
        and math.isfinite(delta + r_ground + a_y + u)
    ):
        learn_steer_zero(st, prm, delta, r_ground, a_y, u)
    learn_steer_zero_from_evidence(st, prm, zero_error_before, zero_error_sd_before)
    delta -= st[ST_STEER_ZERO_SHIFT]
    if speed_low:
        reasons |= REASON_SPEED_LOW
    if speed[spd.OUT_GPS_LOST] != 0.0:  # fixes arrive but none is taken (a doubted receiver): dead reckoning
        reasons |= REASON_GPS_LOST
    run = inputs[inp.OUT_CORE_OK] != 0.0 and not speed_low

    # the published roll: the attitude filter's at every speed (kinematics do not depend on the tyres); without
    # it (IMU missing at start), the gyro integrated and pulled to the kinematic roll
    roll_kin = kinematic_roll(u, r_ground, prm[P_G])
    if attitude_ok:
        # the attitude filter's roll is that of the IMU's sample time: carry it to the cycle's time with the
        # gyro (the sample is up to one cycle old; bounded so a stale stamp cannot extrapolate far)
        age = min(max(sample[S_IMU_AGE], 0.0), 2.0 * dt) if math.isfinite(sample[S_IMU_AGE]) else 0.0
        roll = roll_prev + p_rate * age
    else:
        roll = st[ST_ROLL] + dt * p_rate
        pull = 1.0 - math.exp(-prm[P_FUSION_RATE] * dt)
        roll += pull * (roll_kin - roll)
    diverged = False
    if not math.isfinite(roll) or abs(roll) > prm[P_MAX_ROLL]:
        roll = _finite_or(roll_kin, 0.0)
        if abs(roll) > prm[P_MAX_ROLL]:
            roll = 0.0
        diverged = True
    out[OUT_ROLL_LAST] = st[ST_ROLL]
    st[ST_ROLL] = roll

    out[OUT_DEROLL] = roll_prev
    out[OUT_ROLL_RATE] = p_rate
    out[OUT_YAW_RATE] = r_ground
    out[OUT_STEER] = delta
    out[OUT_A_Y] = a_y
    out[OUT_YAW_ACCEL] = r_dot
    out[OUT_ROLL_ACCEL] = p_dot
    out[OUT_SPEED_LOW] = 1.0 if speed_low else 0.0
    out[OUT_RUN] = 1.0 if run else 0.0
    out[OUT_REASONS] = reasons
    out[OUT_ROLL_KIN] = roll_kin
    out[OUT_ROLL] = roll
    out[OUT_DIVERGED] = 1.0 if diverged else 0.0
    out[OUT_STEER_ZERO_SHIFT] = st[ST_STEER_ZERO_SHIFT]
    out[OUT_STEER_ZERO_SD] = steer_zero_sd(st, prm)
    out[OUT_STEER_LEAD] = steer_lead(sample[S_IMU_AGE], sample[S_STEER_AGE], dt)


def restart(st: np.ndarray) -> None:
    """Filters and the roll from the data again; the learned steer zero is a calibration and is kept."""
    shift, seconds = st[ST_STEER_ZERO_SHIFT], st[ST_STEER_ZERO_SECONDS]
    st[:] = 0.0
    st[ST_STEER_ZERO_SHIFT] = shift
    st[ST_STEER_ZERO_SECONDS] = seconds


STAGE = Stage(
    name="conditioning",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    reset=lambda state, params: restart(state),
    doc="steer angle, roll/yaw rates and their derivatives, a_y at the CoM, observers on/off, the published roll",
)
