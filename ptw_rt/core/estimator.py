"""The estimator: one Sample in, one Estimates out, every 10 ms, in one jitted call.

Per cycle (`estimator_step`):
  1. inputs: non-finite values are replaced by the last good ones and flagged; a stale
     message's values are held;
  2. conditioning: speed (GPS + accelerometer, latency compensated), steer angle,
     ground yaw rate and horizontal lateral acceleration de-rolled with the previous
     cycle's roll, lateral acceleration moved from the IMU to the centre of mass, and
     the virtual output y_a of seed 001 eq. 15 from filtered derivatives of the rates;
  3. UIHOSMO (seed 000 case 2): roll and rider torque as unknown inputs, published as
     diagnostics; seed 003's super-twisting force observer, also a diagnostic cross-check;
  4. fusion filter (`ptw_rt.core.kalman`): a steady-state Kalman filter on the Sharp model
     with the rider torque as a random-walk state, fed [steer, yaw rate, roll rate, a_y];
     its roll, torque, steer rate, lateral velocity and tyre forces are the published ones
     (`docs/estimator.md`: with a 10-bit encoder the UIHOSMO's derivatives of the steer
     angle are mostly quantisation, the gyros and a_y carry the same dynamics cleanly);
  5. LPV adaptive observer (seed 001): tyre stiffness, driven by the fusion filter's
     torque and steer rate, adapting only when the supervisor allows, the regressor is
     excited and the observer explains a_y;
  6. supervisor: mode, reason bits, per-signal validity; guards against NaN/inf and
     runaway observers by resetting the observer concerned (learned stiffness is kept).

Below the model's validity speed the observers are held in reset: roll is the gyro
integrated and pulled to the kinematic roll, torque and tyre quantities are flagged invalid.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import adaptive as ad
from ptw_rt.core import attitude as att
from ptw_rt.core import kalman as kf
from ptw_rt.core import uihosmo as uh
from ptw_rt.core.adaptive import adaptive_step
from ptw_rt.core.conditioning import (
    ground_yaw_rate,
    horizontal_lateral_accel,
    kinematic_roll,
    new_speed_state,
    speed_step,
    steer_angle,
)
from ptw_rt.core.force_observers import STA_STATE_SIZE, sta_step
from ptw_rt.core.layout import (
    E_C_ALPHA_FRONT,
    E_C_ALPHA_REAR,
    E_C_GAMMA_FRONT,
    E_C_GAMMA_REAR,
    E_EXCITATION,
    E_FY_FRONT,
    E_FY_FRONT_ADAPTIVE,
    E_FY_FRONT_STA,
    E_FY_REAR,
    E_FY_REAR_ADAPTIVE,
    E_FY_REAR_STA,
    E_LAT_ACCEL,
    E_LAT_ACCEL_BIAS,
    E_LAT_VEL,
    E_LAT_VEL_ADAPTIVE,
    E_MODE,
    E_PITCH_GYRO_BIAS,
    E_REASONS,
    E_RIDER_TORQUE,
    E_ROLL,
    E_ROLL_ADAPTIVE,
    E_ROLL_FUSION,
    E_ROLL_GYRO_BIAS,
    E_ROLL_RATE,
    E_ROLL_RATE_MEASURED,
    E_ROLL_SD,
    E_ROLL_UIHOSMO,
    E_SPEED,
    E_STEER,
    E_STEER_RATE,
    E_TORQUE_UIHOSMO,
    E_VALID,
    E_Y_A,
    E_YAW_GYRO_BIAS,
    E_YAW_RATE,
    ESTIMATES_SIZE,
    MODE_CONVERGING,
    MODE_DEGRADED,
    MODE_FAULT,
    MODE_INIT,
    MODE_VALID,
    MSG_GPS,
    MSG_IMU_ACCEL,
    MSG_IMU_RATES,
    MSG_STEER,
    REASON_DIVERGING,
    REASON_GPS_LOST,
    REASON_OUT_OF_RANGE,
    REASON_SPEED_LOW,
    REASON_STALE,
    S_ACCEL_X,
    S_ACCEL_Y,
    S_ACCEL_Z,
    S_FRESH,
    S_GPS_COURSE,
    S_GPS_FIX,
    S_GPS_SPEED,
    S_IMU_AGE,
    S_INPUT_REASONS,
    S_PITCH_RATE_BODY,
    S_ROLL_RATE_BODY,
    S_STALE,
    S_STEER_COUNT,
    S_SUSPECT,
    S_YAW_RATE_BODY,
    V_FY_FRONT,
    V_FY_REAR,
    V_LAT_VEL,
    V_RIDER_TORQUE,
    V_ROLL,
    V_ROLL_RATE,
    V_STEER,
    V_STEER_RATE,
)

# ---- parameter vector (float64), filled once from config + design by `Estimator` ----
P_DT = 0
P_DIFF_L = 1
P_G = 2
P_MIN_SPEED = 3
P_STEER_ZERO = 4
P_STEER_CPR = 5
P_SPEED_GAIN = 6
P_SPEED_BIAS_GAIN = 7
P_LATENCY_SAMPLES = 8
P_FUSION_RATE = 9  # 1/s
P_DERIV_OMEGA = 10  # rad/s of the critically damped derivative filter
P_CONVERGE_TIME = 11
P_GPS_HOLD = 12
P_REASON_HOLD = 13
P_STIFF_VALID_AFTER = 14
P_MAX_ROLL = 15
P_MAX_TORQUE = 16
P_MAX_FORCE = 17
P_MAX_LAT_VEL = 18
P_A_Y_R_DOT = 19  # lever arm: a_y(CoM) = a_y(IMU) + k1 r_dot + k2 phi_ddot
P_A_Y_PHI_DDOT = 20
P_YA_R_DOT = 21  # y_a = c1 r_dot + c2 phi_ddot + u (c3 phi_dot + c4 delta_dot)
P_YA_PHI_DDOT = 22
P_YA_PHI_DOT = 23
P_YA_DELTA_DOT = 24
P_DIFF_SUBSTEPS = 25
P_PE_FORGETTING = 26
# 27, 28: unused (kept so the indices below stay stable)
P_CAL_SPEED = 27  # m/s: zero-rate gyro calibration below this speed
P_CAL_GAIN = 28  # share of the (measured - bias) difference applied per cycle
P_CAL_MAX_RATE = 40  # rad/s: above, the vehicle is moving (rocked) and not calibrated
P_MAX_RATE = 29  # plausibility limits of raw inputs (beyond: treated as missing, flagged)
P_MAX_ACCEL = 30
P_MAX_GPS_SPEED = 31
P_STIFF_MAX_RESIDUAL = 32  # m/s^2: RMS a_y innovation above which the stiffness is not published valid
P_STA_LC_R = 33  # super-twisting force observer (seed 003): bound on |d/dt (M_z / I_z)| [rad/s^3]
P_STA_LC_W = 34  # and on |d a_y / dt| [m/s^3]
P_GEOM = 35  # [M, I_z, a_f, a_r] of the CoM-referred lateral/yaw sub-model (4 entries)
P_ADAPT_MAX_RESIDUAL = 39  # m/s^2: RMS a_y innovation above which adaptation is frozen
P_ROLL_TOLERANCE = 41  # rad: the published roll is valid while 3 sigma of it is within this
P_MAX_STEER_STEP = 42  # counts per cycle: a larger jump of the encoder is not a steering motion
P_STEER_RESYNC = 43  # cycles: after this many implausible jumps in a row the encoder's value is taken as the truth
PARAM_SIZE = 44

# ---- supervisor / glue state (float64) ----
G_INIT = 0  # 1 once the first usable sample has been seen
G_ROLL = 1  # fused roll [rad]
G_RUN_TIME = 2  # s the observers have been running since their last (re)start
G_GPS_AGE = 3  # s since the last usable GPS fix
G_OBSERVERS_ON = 4
G_LAST = 5  # 8 last good raw inputs: p, q, r, ax, ay, az, steer count, gps speed
G_DF = 13  # derivative filters: [r_f, r_dot_f, p_f, p_dot_f]
G_THETA_GOOD = 17  # last finite stiffness deviations (4)
G_EXCITED_TIME = 21  # s of adaptation per parameter (4)
G_REASON_UNTIL = 25  # per reason bit (16): time until which it stays raised
G_TIME = 41  # s since start (sum of dt)
G_RESTORED = 42  # 1 if the stiffness came from a saved state (valid from the start)
G_TAU_FILTERED = 43
G_AY_RESIDUAL_MS = 44  # mean square of the adaptive observer's a_y innovation (consistency of its model)
G_STA = 45  # super-twisting force observer state (STA_STATE_SIZE)
G_KF = G_STA + STA_STATE_SIZE  # fusion filter state (kf.STATE_SIZE)
G_STEER_JUMPS = G_KF + kf.STATE_SIZE  # consecutive implausible steer-encoder jumps
GLUE_SIZE = G_STEER_JUMPS + 1
N_RAW = 8

SCRATCH_SIZE = 112


@njit(cache=True)
def _finite_or(value: float, fallback: float) -> float:
    return value if math.isfinite(value) else fallback


@njit(cache=True)
def _raise(glue: np.ndarray, bits: int, hold: float) -> None:
    t = glue[G_TIME] + hold
    for k in range(16):
        if bits >> k & 1:
            if glue[G_REASON_UNTIL + k] < t:
                glue[G_REASON_UNTIL + k] = t


@njit(cache=True)
def _held_reasons(glue: np.ndarray) -> int:
    """REASON_* bits still held by `_raise` at the current time."""
    bits = 0
    for k in range(16):
        if glue[G_REASON_UNTIL + k] > glue[G_TIME]:
            bits |= 1 << k
    return bits


@njit(cache=True)
def _derivative_filter(z: np.ndarray, k: int, y: float, omega: float, dt: float) -> float:
    """Critically damped 2nd-order tracking filter, exact ZOH; returns the filtered derivative of y."""
    a = omega * dt
    e = math.exp(-a)
    x0 = z[k] - y
    x1 = z[k + 1]
    z[k] = y + e * ((1.0 + a) * x0 + dt * x1)
    z[k + 1] = e * (-omega * omega * dt * x0 + (1.0 - a) * x1)
    return z[k + 1]


@njit(cache=True)
def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def _all_finite(v: np.ndarray, n: int) -> bool:
    for i in range(n):
        if not math.isfinite(v[i]):
            return False
    return True


@njit(cache=True)
def estimator_step(
    sample: np.ndarray,
    est: np.ndarray,
    glue: np.ndarray,
    spd: np.ndarray,
    uh_state: np.ndarray,
    ad_state: np.ndarray,
    scratch: np.ndarray,
    chi: np.ndarray,
    prm: np.ndarray,
    grid: np.ndarray,
    uh_Phi: np.ndarray,
    uh_Gamma: np.ndarray,
    uh_T_inv: np.ndarray,
    uh_Abar: np.ndarray,
    uh_Dbar_inv: np.ndarray,
    uh_Phi22: np.ndarray,
    uh_Gamma21: np.ndarray,
    uh_Ramp_y: np.ndarray,
    uh_Ramp21: np.ndarray,
    lam_steer: np.ndarray,
    lam_yaw: np.ndarray,
    ad_Phi: np.ndarray,
    ad_B_tau: np.ndarray,
    ad_B_theta: np.ndarray,
    ad_B_y: np.ndarray,
    ad_C: np.ndarray,
    ad_T: np.ndarray,
    ad_gamma: np.ndarray,
    theta_nominal: np.ndarray,
    theta_bound: np.ndarray,
    regressor_constants: np.ndarray,
    pe_threshold: np.ndarray,
    kf_Phi: np.ndarray,
    kf_K: np.ndarray,
    kf_C: np.ndarray,
    att_state: np.ndarray,
    att_prm: np.ndarray,
    kf_Gd: np.ndarray,
    kf_nonlinear: np.ndarray,
) -> None:
    dt = prm[P_DT]
    glue[G_TIME] += dt
    fresh = int(sample[S_FRESH])
    stale = int(sample[S_STALE])
    reasons_now = int(sample[S_INPUT_REASONS])

    # ---- 1. inputs: hold the last good value of anything non-finite or stale ----
    raw = scratch[0:N_RAW]
    src = (
        S_ROLL_RATE_BODY,
        S_PITCH_RATE_BODY,
        S_YAW_RATE_BODY,
        S_ACCEL_X,
        S_ACCEL_Y,
        S_ACCEL_Z,
        S_STEER_COUNT,
        S_GPS_SPEED,
    )
    for k in range(N_RAW):
        v = sample[src[k]]
        if k < 3:
            limit = prm[P_MAX_RATE]
        elif k < 6:
            limit = prm[P_MAX_ACCEL]
        elif k == 6:
            limit = prm[P_STEER_CPR]
        else:
            limit = prm[P_MAX_GPS_SPEED]
        plausible = math.isfinite(v) and abs(v) <= limit and (k < 6 or v >= 0.0)
        if plausible:
            raw[k] = v
        else:
            raw[k] = glue[G_LAST + k]
            reasons_now |= REASON_OUT_OF_RANGE
    # a stale message, or one whose rolling counter broke this cycle (its payload may be garbage): held
    held = stale | int(sample[S_SUSPECT])
    if held & MSG_IMU_RATES:
        for k in range(3):
            raw[k] = glue[G_LAST + k]
    if held & MSG_IMU_ACCEL:
        for k in range(3, 6):
            raw[k] = glue[G_LAST + k]
    if held & MSG_STEER:
        raw[6] = glue[G_LAST + 6]
    elif glue[G_INIT] != 0.0:
        # the steering cannot turn more than P_MAX_STEER_STEP counts in one cycle; a bigger jump is a corrupt
        # frame (unless it persists: then the encoder really is there, e.g. after a long silence)
        jump = abs(raw[6] - glue[G_LAST + 6])
        jump = min(jump, prm[P_STEER_CPR] - jump)  # across the wrap
        if jump > prm[P_MAX_STEER_STEP] and glue[G_STEER_JUMPS] < prm[P_STEER_RESYNC]:
            glue[G_STEER_JUMPS] += 1.0
            raw[6] = glue[G_LAST + 6]
            reasons_now |= REASON_OUT_OF_RANGE
        else:
            glue[G_STEER_JUMPS] = 0.0
    for k in range(N_RAW):
        glue[G_LAST + k] = raw[k]
    if stale != 0:
        reasons_now |= REASON_STALE
    core_ok = (stale & (MSG_IMU_RATES | MSG_STEER)) == 0
    accel_ok = (stale & MSG_IMU_ACCEL) == 0
    accel_trusted = (held & MSG_IMU_ACCEL) == 0  # this cycle's accelerometer values are new and sound

    gps_fix = sample[S_GPS_FIX]
    gps_new = (fresh & MSG_GPS) != 0 and (stale & MSG_GPS) == 0
    gps_ok = gps_new and gps_fix >= 2.0 and math.isfinite(sample[S_GPS_SPEED])
    if gps_ok:
        glue[G_GPS_AGE] = 0.0
    else:
        glue[G_GPS_AGE] += dt
    gps_lost = glue[G_GPS_AGE] > prm[P_GPS_HOLD]
    if gps_lost:
        reasons_now |= REASON_GPS_LOST

    # ---- 2. conditioning ----
    accel_x = raw[3] if accel_ok else 0.0
    u = speed_step(
        spd,
        accel_x,
        raw[7],
        gps_ok,
        gps_ok,
        dt,
        prm[P_SPEED_GAIN],
        prm[P_SPEED_BIAS_GAIN],
        int(prm[P_LATENCY_SAMPLES]),
    )
    speed_known = spd[3] != 0.0  # the filter has had its first fix
    rates_ok = (held & MSG_IMU_RATES) == 0

    # attitude (ptw_rt.core.attitude): roll and gyro biases from kinematics alone, no tyre model
    att_out = scratch[96 : 96 + att.OUT_SIZE]
    standstill = (
        speed_known
        and not gps_lost
        and u < prm[P_CAL_SPEED]
        and reasons_now & ~REASON_SPEED_LOW == 0
        and abs(raw[0] - att_state[att.ST_X + att.X_BP]) < prm[P_CAL_MAX_RATE]
        and abs(raw[2] - att_state[att.ST_X + att.X_BR]) < prm[P_CAL_MAX_RATE]
    )
    course_new = gps_ok and sample[S_GPS_FIX] >= 2.0 and math.isfinite(sample[S_GPS_COURSE])
    course = math.radians(sample[S_GPS_COURSE]) if course_new else 0.0
    speed_sd = 0.1 + 0.5 * min(glue[G_GPS_AGE], 10.0)  # the speed filter dead-reckons on the accelerometer
    att.attitude_step(
        att_state,
        att_out,
        att_prm,
        raw[0],
        raw[1],
        raw[2],
        raw[4],
        raw[5],
        u if speed_known else 0.0,
        speed_sd if speed_known else 30.0,
        rates_ok,
        accel_trusted,
        _wrap_pi(course),
        course_new,
        standstill,
    )
    attitude_ok = att_state[att.ST_INIT] == 1.0 and _all_finite(att_out, att.OUT_SIZE)
    if attitude_ok:
        roll_prev = att_out[att.OUT_ROLL]
        p_rate = att_out[att.OUT_ROLL_RATE]
        r_ground = att_out[att.OUT_YAW_RATE]
    else:
        roll_prev = glue[G_ROLL]
        p_rate = raw[0]
        r_ground = ground_yaw_rate(raw[1], raw[2], roll_prev)
    delta = steer_angle(raw[6], prm[P_STEER_ZERO], prm[P_STEER_CPR])
    a_y_imu = horizontal_lateral_accel(raw[4] - att_out[att.OUT_BAY], raw[5], roll_prev)
    if glue[G_INIT] == 0.0:
        glue[G_DF + 0] = r_ground
        glue[G_DF + 2] = p_rate
    r_dot = _derivative_filter(glue, G_DF + 0, r_ground, prm[P_DERIV_OMEGA], dt)
    p_dot = _derivative_filter(glue, G_DF + 2, p_rate, prm[P_DERIV_OMEGA], dt)
    a_y = a_y_imu + prm[P_A_Y_R_DOT] * r_dot + prm[P_A_Y_PHI_DDOT] * p_dot
    glue[G_INIT] = 1.0

    speed_low = (not speed_known) or u < prm[P_MIN_SPEED]
    if speed_low:
        reasons_now |= REASON_SPEED_LOW

    # ---- 3.-5. observers, only where the model holds ----
    run_observers = core_ok and not speed_low
    kf_state = glue[G_KF : G_KF + kf.STATE_SIZE]
    if not run_observers:
        uh_state[uh.INIT] = 0.0
        ad_state[ad.INIT] = 0.0
        glue[G_OBSERVERS_ON] = 0.0
        glue[G_RUN_TIME] = 0.0
    uh_out = scratch[8:17]
    uh_scratch = scratch[24:48]
    ad_scratch = scratch[48:64]
    roll_uio = 0.0
    tau_uio = 0.0
    tau = 0.0
    if run_observers:
        glue[G_OBSERVERS_ON] = 1.0
        glue[G_RUN_TIME] += dt
        uh.uihosmo_step(
            uh_state,
            uh_out,
            uh_scratch,
            delta,
            r_ground,
            u,
            dt,
            prm[P_DIFF_L],
            grid,
            uh_Phi,
            uh_Gamma,
            uh_T_inv,
            uh_Abar,
            uh_Dbar_inv,
            uh_Phi22,
            uh_Gamma21,
            uh_Ramp_y,
            uh_Ramp21,
            lam_steer,
            lam_yaw,
            int(prm[P_DIFF_SUBSTEPS]),
        )
        roll_uio = uh_out[uh.OUT_PHI]
        tau_uio = uh_out[uh.OUT_TAU]
        if (
            not _all_finite(uh_out, uh.OUT_SIZE)
            or not _all_finite(uh_state, uh.STATE_SIZE)
            or abs(roll_uio) > prm[P_MAX_ROLL]
            or abs(tau_uio) > prm[P_MAX_TORQUE]
        ):
            uh_state[uh.INIT] = 0.0
            ad_state[ad.INIT] = 0.0
            glue[G_RUN_TIME] = 0.0
            _raise(glue, REASON_DIVERGING, prm[P_REASON_HOLD])
            roll_uio = glue[G_ROLL]
            tau_uio = 0.0
            for k in range(uh.OUT_SIZE):
                uh_out[k] = 0.0
            uh_out[uh.X_DELTA] = delta
            uh_out[uh.X_R] = r_ground

    # tyre forces: seed 003's super-twisting observer on the lateral/yaw sub-model, from (u, r, a_y) only
    forces = scratch[64:66]
    forces[0] = 0.0
    forces[1] = 0.0
    sta = glue[G_STA : G_STA + STA_STATE_SIZE]
    if run_observers and accel_ok:
        sta_step(sta, forces, u, r_ground, a_y, dt, prm[P_GEOM : P_GEOM + 4], prm[P_STA_LC_R], prm[P_STA_LC_W])
        if not (math.isfinite(forces[0]) and math.isfinite(forces[1])):
            for k in range(STA_STATE_SIZE):
                sta[k] = 0.0
            forces[0] = 0.0
            forces[1] = 0.0
    else:
        for k in range(STA_STATE_SIZE):
            sta[k] = 0.0

    # 4. fusion filter: roll, torque and the lateral states from all four measurements
    kf_out = scratch[72:81]
    roll_kin = kinematic_roll(u, r_ground, prm[P_G])
    if run_observers:
        y_kf = scratch[84:89]
        y_kf[0] = delta
        y_kf[1] = r_ground
        y_kf[2] = p_rate
        if accel_trusted:
            y_kf[3] = a_y
        else:  # no accelerometer: no innovation from it (the model's own prediction)
            acc = 0.0
            for c in range(kf.N_Z):
                acc += kf_C[3, c] * kf_state[c]
            y_kf[3] = acc
        # the kinematic roll as a measurement
        if attitude_ok:
            y_kf[4] = roll_prev
        else:  # no kinematic roll: no innovation from it
            acc = 0.0
            for c in range(kf.N_Z):
                acc += kf_C[4, c] * kf_state[c]
            y_kf[4] = acc
        kf.kalman_step(
            kf_state, kf_out, y_kf, u, roll_prev, grid, kf_Phi, kf_K, kf_C, kf_Gd, kf_nonlinear, scratch[89:93]
        )
        if (
            not _all_finite(kf_out, kf.N_Z)
            or abs(kf_out[kf.PHI]) > prm[P_MAX_ROLL]
            or abs(kf_out[kf.TAU]) > prm[P_MAX_TORQUE]
        ):
            kf_state[kf.INIT] = 0.0
            _raise(glue, REASON_DIVERGING, prm[P_REASON_HOLD])
            for k in range(kf.N_Z):
                kf_out[k] = 0.0
            kf_out[kf.PHI] = glue[G_ROLL]
            kf_out[kf.DELTA] = delta
            kf_out[kf.R] = r_ground
            kf_out[kf.PHI_DOT] = p_rate
    else:
        kf_state[kf.INIT] = 0.0
        for k in range(kf.N_Z):
            kf_out[k] = 0.0

    # roll: the attitude filter's, at every speed (kinematics do not depend on the tyres; the fusion filter
    # fuses it; its own roll is a diagnostic). Without
    # the attitude filter (IMU missing at start), the gyro integrated and pulled to the kinematic roll.
    roll_fusion = kf_out[kf.PHI] if run_observers else 0.0
    if run_observers:
        tau = kf_out[kf.TAU]
    if attitude_ok:
        # the attitude filter's roll is that of the IMU's sample time: carry it to the cycle's time with the
        # gyro (the sample is up to one cycle old; bounded so a stale stamp cannot extrapolate far)
        age = min(max(sample[S_IMU_AGE], 0.0), 2.0 * dt) if math.isfinite(sample[S_IMU_AGE]) else 0.0
        roll = roll_prev + p_rate * age
    else:
        roll = glue[G_ROLL] + dt * p_rate
        pull = 1.0 - math.exp(-prm[P_FUSION_RATE] * dt)
        roll += pull * (roll_kin - roll)
    if not math.isfinite(roll) or abs(roll) > prm[P_MAX_ROLL]:
        roll = _finite_or(roll_kin, 0.0)
        if abs(roll) > prm[P_MAX_ROLL]:
            roll = 0.0
        _raise(glue, REASON_DIVERGING, prm[P_REASON_HOLD])
    glue[G_ROLL] = roll

    # 5. adaptive observer: y = [delta, r, phi_dot, delta_dot, a_y, y_a]
    theta = ad_state[ad.TH0 : ad.TH1]
    adapting_bits = 0
    y_a = 0.0
    if run_observers:
        delta_dot = kf_out[kf.DELTA_DOT]
        y_a = (
            prm[P_YA_R_DOT] * r_dot
            + prm[P_YA_PHI_DDOT] * p_dot
            + u * (prm[P_YA_PHI_DOT] * p_rate + prm[P_YA_DELTA_DOT] * delta_dot)
        )
        y = scratch[17:23]
        y[0] = delta
        y[1] = r_ground  # bias-corrected by the attitude filter
        y[2] = p_rate
        y[3] = delta_dot
        y[4] = a_y
        y[5] = y_a
        first = ad_state[ad.INIT] == 0.0
        if not first:
            innovation = a_y
            for c in range(8):
                innovation -= ad_C[4, c] * ad_state[ad.X0 + c]
            forget = prm[P_PE_FORGETTING]
            glue[G_AY_RESIDUAL_MS] = forget * glue[G_AY_RESIDUAL_MS] + (1.0 - forget) * innovation * innovation
        # learn only from an observer whose model explains what is measured (else the gradient is noise-driven)
        consistent = glue[G_AY_RESIDUAL_MS] < prm[P_ADAPT_MAX_RESIDUAL] * prm[P_ADAPT_MAX_RESIDUAL]
        allow = (
            accel_ok and not gps_lost and glue[G_RUN_TIME] > prm[P_CONVERGE_TIME] and reasons_now == 0 and consistent
        )
        adaptive_step(
            ad_state,
            chi,
            ad_scratch,
            y,
            tau,
            u,
            dt,
            allow,
            grid,
            ad_Phi,
            ad_B_tau,
            ad_B_theta,
            ad_B_y,
            ad_C,
            ad_T,
            ad_gamma,
            theta_nominal,
            theta_bound,
            regressor_constants,
            pe_threshold,
            prm[P_PE_FORGETTING],
        )
        if first:
            ad_state[ad.X0 + ad.PHI] = roll
        if allow:
            for k in range(4):
                if ad_state[ad.PE0 + k] > pe_threshold[k] * pe_threshold[k]:
                    adapting_bits |= 1 << k
                    glue[G_EXCITED_TIME + k] += dt
        x_ad = ad_state[ad.X0 : ad.X1]
        if (
            not _all_finite(ad_state, ad.STATE_SIZE)
            or abs(x_ad[ad.FYF]) > prm[P_MAX_FORCE]
            or abs(x_ad[ad.FYR]) > prm[P_MAX_FORCE]
            or abs(x_ad[ad.VY]) > prm[P_MAX_LAT_VEL]
        ):
            # reset the states, keep what was learned
            ad_state[ad.INIT] = 0.0
            for k in range(4):
                theta[k] = glue[G_THETA_GOOD + k]
            for k in range(4):
                ad_state[ad.PE0 + k] = 0.0
            for k in range(8):
                x_ad[k] = 0.0
            _raise(glue, REASON_DIVERGING, prm[P_REASON_HOLD])
    for k in range(4):
        if math.isfinite(theta[k]):
            glue[G_THETA_GOOD + k] = theta[k]
        else:
            theta[k] = glue[G_THETA_GOOD + k]

    # ---- 6. supervisor ----
    _raise(glue, reasons_now, prm[P_REASON_HOLD])
    # conditions that are states, not events, end as soon as they end
    states = REASON_SPEED_LOW | REASON_GPS_LOST | REASON_STALE
    reasons = (reasons_now & states) | (_held_reasons(glue) & ~states)

    if not speed_known and core_ok:
        mode = MODE_INIT
    elif not core_ok:
        mode = MODE_FAULT
    elif reasons & REASON_DIVERGING and not run_observers:
        mode = MODE_FAULT
    elif reasons != 0:
        mode = MODE_DEGRADED
    elif glue[G_RUN_TIME] < prm[P_CONVERGE_TIME]:
        mode = MODE_CONVERGING
    else:
        mode = MODE_VALID

    valid = 0
    if core_ok:
        valid |= V_ROLL_RATE | V_STEER
    # roll is valid from its own uncertainty: 3 sigma within the documented tolerance, filter consistent
    roll_sd = att_out[att.OUT_ROLL_SD] if attitude_ok else math.inf
    if rates_ok and accel_ok and 3.0 * roll_sd <= prm[P_ROLL_TOLERANCE] and att_state[att.ST_REJECTED] < 10.0:
        valid |= V_ROLL
    observers_settled = run_observers and glue[G_RUN_TIME] >= prm[P_CONVERGE_TIME]
    if observers_settled:
        valid |= V_RIDER_TORQUE | V_STEER_RATE
        valid |= V_LAT_VEL
        if accel_ok:
            valid |= V_FY_FRONT | V_FY_REAR
    # Tyre stiffness is never published VALID by this estimator yet. The timer-and-bound rule it had set
    # the bits on 15 of 40 cells of the evaluation matrix while the values were 20-150 % off (issue #12);
    # a valid bit must come from the learned value's own uncertainty, which the adaptive law does not
    # carry. Until the stiffness learner with a covariance replaces it, V_CORNERING / V_CAMBER stay clear.

    # ---- outputs ----
    x_ad = ad_state[ad.X0 : ad.X1]
    est[E_ROLL] = roll
    est[E_ROLL_RATE] = p_rate
    est[E_RIDER_TORQUE] = tau
    est[E_STEER] = kf_out[kf.DELTA] if run_observers else delta
    est[E_STEER_RATE] = kf_out[kf.DELTA_DOT] if run_observers else 0.0
    # published states from the fusion filter (docs/estimator.md, "What is published from which observer")
    est[E_LAT_VEL] = kf_out[kf.VY] if run_observers else 0.0
    est[E_FY_FRONT] = kf_out[kf.FYF] if run_observers else 0.0
    est[E_FY_REAR] = kf_out[kf.FYR] if run_observers else 0.0
    est[E_C_ALPHA_FRONT] = theta_nominal[0] + theta[0]
    est[E_C_GAMMA_FRONT] = theta_nominal[1] + theta[1]
    est[E_C_ALPHA_REAR] = theta_nominal[2] + theta[2]
    est[E_C_GAMMA_REAR] = theta_nominal[3] + theta[3]
    est[E_SPEED] = u
    est[E_YAW_RATE] = ground_yaw_rate(raw[1], raw[2], roll)  # as measured: the baselines' input
    est[E_ROLL_RATE_MEASURED] = raw[0]
    est[E_YAW_GYRO_BIAS] = att_out[att.OUT_BR]
    est[E_ROLL_GYRO_BIAS] = att_out[att.OUT_BP]
    est[E_PITCH_GYRO_BIAS] = att_out[att.OUT_BQ]
    est[E_LAT_ACCEL_BIAS] = att_out[att.OUT_BAY]
    est[E_ROLL_SD] = roll_sd if math.isfinite(roll_sd) else 10.0
    est[E_ROLL_FUSION] = roll_fusion
    est[E_MODE] = mode
    est[E_REASONS] = reasons
    est[E_VALID] = valid
    est[E_ROLL_UIHOSMO] = roll_uio
    est[E_LAT_ACCEL] = a_y
    est[E_EXCITATION] = adapting_bits
    est[E_ROLL_ADAPTIVE] = x_ad[ad.PHI] if run_observers else 0.0
    est[E_TORQUE_UIHOSMO] = tau_uio
    est[E_FY_FRONT_STA] = forces[0]
    est[E_FY_REAR_STA] = forces[1]
    est[E_LAT_VEL_ADAPTIVE] = x_ad[ad.VY] if run_observers else 0.0
    est[E_FY_FRONT_ADAPTIVE] = x_ad[ad.FYF] if run_observers else 0.0
    est[E_FY_REAR_ADAPTIVE] = x_ad[ad.FYR] if run_observers else 0.0
    est[E_Y_A] = y_a
    # last line of defence: nothing non-finite leaves the step
    for k in range(ESTIMATES_SIZE):
        if not math.isfinite(est[k]):
            est[k] = 0.0


# ---- packed call: numba unboxes every array argument on each call from Python (~0.15 us each); the
# step's 35 arrays cost 5 us of dispatch against ~1 us of arithmetic. The Estimator keeps its state
# and the design tables in two flat buffers and calls `packed_step` with 7 arguments; the views are
# rebuilt inside compiled code, where they cost nothing (no allocation: slices and reshapes of
# contiguous buffers). Index rows: [start, stop, dim0, dim1, dim2].


@njit(cache=True, inline="always")
def _v1(buf: np.ndarray, index: np.ndarray, k: int) -> np.ndarray:
    return buf[index[k, 0] : index[k, 1]]


@njit(cache=True, inline="always")
def _v2(buf: np.ndarray, index: np.ndarray, k: int) -> np.ndarray:
    return buf[index[k, 0] : index[k, 1]].reshape((index[k, 2], index[k, 3]))


@njit(cache=True, inline="always")
def _v3(buf: np.ndarray, index: np.ndarray, k: int) -> np.ndarray:
    return buf[index[k, 0] : index[k, 1]].reshape((index[k, 2], index[k, 3], index[k, 4]))


# order of the state and table buffers (and the dimension each view has); tables are named as in DesignData,
# except the differentiator gains, which are constants of ptw_rt.core.uihosmo
STATE_PARTS = ("glue", "spd", "uh_state", "ad_state", "scratch", "chi", "att_state")
TABLE_PARTS = (
    ("grid", 1),
    ("uh_Phi", 3),
    ("uh_Gamma", 3),
    ("uh_T_inv", 3),
    ("uh_Abar", 3),
    ("uh_Dbar_inv", 3),
    ("uh_Phi22", 3),
    ("uh_Gamma21", 3),
    ("uh_Ramp_y", 3),
    ("uh_Ramp21", 3),
    ("lam_steer", 1),
    ("lam_yaw", 1),
    ("ad_Phi", 3),
    ("ad_B_tau", 2),
    ("ad_B_theta", 3),
    ("ad_B_y", 3),
    ("ad_C", 2),
    ("ad_T", 2),
    ("ad_gamma", 1),
    ("ad_theta_nominal", 1),
    ("ad_theta_bound", 1),
    ("regressor_constants", 1),
    ("ad_pe_threshold", 1),
    ("kf_Phi", 3),
    ("kf_K", 3),
    ("kf_C", 2),
    ("att_prm", 1),
    ("kf_Gd", 3),
    ("kf_nonlinear", 1),
)


@njit(cache=True)
def packed_step(
    sample: np.ndarray,
    est: np.ndarray,
    state: np.ndarray,
    state_index: np.ndarray,
    prm: np.ndarray,
    tables: np.ndarray,
    table_index: np.ndarray,
) -> None:
    """`estimator_step` on views of the two flat buffers (layout: STATE_PARTS, TABLE_PARTS)."""
    s, si, t, ti = state, state_index, tables, table_index
    estimator_step(
        sample,
        est,
        _v1(s, si, 0),
        _v1(s, si, 1),
        _v1(s, si, 2),
        _v1(s, si, 3),
        _v1(s, si, 4),
        _v2(s, si, 5),
        prm,
        _v1(t, ti, 0),
        _v3(t, ti, 1),
        _v3(t, ti, 2),
        _v3(t, ti, 3),
        _v3(t, ti, 4),
        _v3(t, ti, 5),
        _v3(t, ti, 6),
        _v3(t, ti, 7),
        _v3(t, ti, 8),
        _v3(t, ti, 9),
        _v1(t, ti, 10),
        _v1(t, ti, 11),
        _v3(t, ti, 12),
        _v2(t, ti, 13),
        _v3(t, ti, 14),
        _v3(t, ti, 15),
        _v2(t, ti, 16),
        _v2(t, ti, 17),
        _v1(t, ti, 18),
        _v1(t, ti, 19),
        _v1(t, ti, 20),
        _v1(t, ti, 21),
        _v1(t, ti, 22),
        _v3(t, ti, 23),
        _v3(t, ti, 24),
        _v2(t, ti, 25),
        _v1(s, si, 6),
        _v1(t, ti, 26),
        _v3(t, ti, 27),
        _v1(t, ti, 28),
    )


def _pack(arrays) -> tuple[np.ndarray, np.ndarray]:
    """One flat float64 buffer and its index rows [start, stop, dims...] for C-ordered arrays."""
    index = np.zeros((len(arrays), 5), dtype=np.int64)
    start = 0
    for k, a in enumerate(arrays):
        index[k, 0], index[k, 1] = start, start + a.size
        index[k, 2 : 2 + a.ndim] = a.shape
        start += a.size
    buf = np.zeros(start)
    for k, a in enumerate(arrays):
        buf[index[k, 0] : index[k, 1]] = np.ascontiguousarray(a, dtype=np.float64).ravel()
    return buf, index


class Estimator:
    """Owns the preallocated state of one estimator and the bound arguments of its jitted step."""

    def __init__(self, settings, design) -> None:
        from ptw_rt.core.params import build_params  # the one place config becomes numbers

        self.settings = settings
        self.design = design
        self.sample_time = float(design.sample_time)
        self.prm = build_params(settings, design)
        parts = {
            "glue": np.zeros(GLUE_SIZE),
            "spd": new_speed_state(int(self.prm[P_LATENCY_SAMPLES])),
            "uh_state": uh.new_state(),
            "ad_state": ad.new_state(),
            "scratch": np.zeros(SCRATCH_SIZE),
            "chi": np.zeros((2, 4)),
            "att_state": att.new_state(),
        }
        self._state, self._state_index = _pack([parts[name] for name in STATE_PARTS])
        # the named attributes are views into the flat state buffer: writes through them reach the step
        for k, name in enumerate(STATE_PARTS):
            a, b = self._state_index[k, 0], self._state_index[k, 1]
            setattr(self, name, self._state[a:b].reshape(parts[name].shape))
        sens = settings.sensors
        constants = {
            "lam_steer": uh.LAMBDA_STEER,
            "lam_yaw": uh.LAMBDA_YAW,
            "att_prm": att.attitude_params(
                self.sample_time,
                settings.vehicle.g,
                sens.imu_height,
                sens.imu_forward,
                settings.estimator.attitude,
                sens.gps_latency,
            ),
        }
        tables = [np.asarray(constants[n] if n in constants else getattr(design, n)) for n, _ in TABLE_PARTS]
        for (name, ndim), table in zip(TABLE_PARTS, tables, strict=True):
            if table.ndim != ndim:
                raise ValueError(f"design table {name} has {table.ndim} dimensions, expected {ndim}")
        self._tables, self._table_index = _pack(tables)

    def reset(self) -> None:
        """Forget everything but the learned stiffness."""
        theta = self.ad_state[ad.TH0 : ad.TH1].copy()
        restored = self.glue[G_RESTORED]
        for a in (self.glue, self.spd, self.uh_state, self.ad_state, self.scratch):
            a[:] = 0.0
        att.restart(self.att_state)  # roll and heading again from the data; the sensor biases are kept
        self.ad_state[ad.TH0 : ad.TH1] = theta
        self.glue[G_THETA_GOOD : G_THETA_GOOD + 4] = theta
        self.glue[G_RESTORED] = restored

    def step(self, sample: np.ndarray, estimates: np.ndarray) -> None:
        packed_step(sample, estimates, self._state, self._state_index, self.prm, self._tables, self._table_index)

    def learned_stiffness(self) -> np.ndarray:
        """[C_af, C_gf, C_ar, C_gr] in N/rad."""
        return self.design.ad_theta_nominal + self.ad_state[ad.TH0 : ad.TH1]

    def restore_stiffness(self, values) -> None:
        """Start from stiffness learned earlier (clipped to the design's bounds); marks it valid."""
        values = np.asarray(values, dtype=float)
        if values.shape != (4,) or not np.all(np.isfinite(values)):
            raise ValueError("expected four finite stiffness values")
        dev = np.clip(values - self.design.ad_theta_nominal, -self.design.ad_theta_bound, self.design.ad_theta_bound)
        self.ad_state[ad.TH0 : ad.TH1] = dev
        self.glue[G_THETA_GOOD : G_THETA_GOOD + 4] = dev
        self.glue[G_RESTORED] = 1.0
