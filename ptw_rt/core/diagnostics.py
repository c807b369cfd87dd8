"""Stage 5, the seed observers as diagnostics: UIHOSMO (seed 000) and the super-twisting force observer (seed 003),
and the UIHOSMO on the sensors (issue #16) with its own kinematics (`ptw_rt.core.channel_kinematics`: a roll,
rates and a_y from the raw IMU, of the attitude filter only its gyro and accelerometer calibrations), the diverse
channel the supervisor's plausibility monitor checks the published torque against.

Neither is published: the UIHOSMO's roll and rider torque (unknown inputs reconstructed from the second and
third derivatives of the steer-angle error, `ptw_rt.core.uihosmo`; with the contract's 10-bit encoder they are
mostly quantisation, docs/estimator.md) and the super-twisting observer's tyre forces from (u, r, a_y) alone
(`ptw_rt.core.force_observers.sta_step`) are cross-checks in the diagnostics of the Estimates record.

Both run only while the model-based observers run (conditioning's OUT_RUN; the force observer also needs the
accelerometer). A UIHOSMO that blows up (non-finite, or roll or torque beyond the limits) is reset and the
event is an output (OUT_RESET, diagnostic only). Nothing published depends on these observers, so their reset
touches nothing else: until 2026-11-25 it raised REASON_DIVERGING and restarted the fusion filters' clock and
the adaptive observer (carried over from the monolithic step), which kept a ride DEGRADED for 25 s after a
steer-encoder offset (docs/estimator.md, "Plausibility").
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import attitude as att
from ptw_rt.core import channel_kinematics as ck
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import inputs as inp
from ptw_rt.core import speed as spd
from ptw_rt.core import uihosmo as uh
from ptw_rt.core import uio_sensors as cus
from ptw_rt.core.force_observers import STA_STATE_SIZE, lateral_yaw_constants, sta_step
from ptw_rt.core.stage import Layout, Stage, all_finite, v1, v2, v3

STATE = Layout(
    "ST_",
    uh=uh.STATE_SIZE,  # the UIHOSMO's state (ptw_rt.core.uihosmo layout)
    sta=STA_STATE_SIZE,  # the super-twisting observer's state
    uh_tmp=24,  # the UIHOSMO's scratch
    us=cus.STATE_SIZE,  # the UIHOSMO on the sensors (ptw_rt.core.uio_sensors layout)
    ch=ck.STATE_SIZE,  # its own kinematics: roll, rates, a_y (ptw_rt.core.channel_kinematics layout)
)
ST_UH, ST_STA, ST_UH_TMP, ST_US, ST_CH = STATE.offsets

PARAMS = Layout(
    "P_",
    dt=1,
    diff_l=1,  # Lipschitz constant L of the differentiators
    diff_substeps=1,
    max_roll=1,  # rad: beyond, the UIHOSMO has diverged
    max_torque=1,  # N m: likewise
    uh_min_speed=1,  # m/s: the UIHOSMO runs above this (the validity speed, or seed 000 case 2's detectability floor)
    sta_lc_r=1,  # bound on |d/dt (M_z / I_z)| [rad/s^3]
    sta_lc_w=1,  # bound on |d a_y / dt| [m/s^3]
    geom=4,  # [M, I_z, a_f, a_r] of the CoM-referred lateral/yaw sub-model
    us=cus.PARAM_SIZE,  # the UIHOSMO on the sensors' parameters (ptw_rt.core.uio_sensors P_*)
    ch=ck.PARAM_SIZE,  # its own kinematics' parameters (ptw_rt.core.channel_kinematics P_*)
)
(
    P_DT,
    P_DIFF_L,
    P_DIFF_SUBSTEPS,
    P_MAX_ROLL,
    P_MAX_TORQUE,
    P_UH_MIN_SPEED,
    P_STA_LC_R,
    P_STA_LC_W,
    P_GEOM,
    P_US,
    P_CH,
) = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    uh=uh.OUT_SIZE,  # the UIHOSMO's reconstruction (ptw_rt.core.uihosmo OUT layout)
    roll=1,  # rad, the UIHOSMO's roll (0 while not running)
    torque=1,  # N m, the UIHOSMO's rider torque
    fy_front=1,  # N, the super-twisting observer's tyre forces (0 while not running)
    fy_rear=1,
    reset=1,  # 1: the UIHOSMO diverged this cycle and was reset
    us=cus.OUT_SIZE,  # the UIHOSMO on the sensors (ptw_rt.core.uio_sensors OUT layout): torque, valid
    ch=ck.OUT_SIZE,  # its own kinematics (ptw_rt.core.channel_kinematics OUT layout): roll, rates, a_y, valid
)
OUT_UH, OUT_ROLL, OUT_TORQUE, OUT_FY_FRONT, OUT_FY_REAR, OUT_RESET, OUT_US, OUT_CH = OUTPUTS.offsets

# design tables, in the order `diagnostics_stage` reads them from its first table row
TABLES = (
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
    ("us_C", 2),
    ("us_Phi", 3),
    ("us_Gamma", 3),
    ("us_Ramp", 3),
    ("us_T_inv", 3),
    ("us_Abar", 3),
    ("us_Dbar_inv", 3),
    ("us_Phi22", 3),
    ("us_Gamma21", 3),
    ("us_Ramp21", 3),
    ("us_lam", 2),
)
(
    T_GRID,
    T_PHI,
    T_GAMMA,
    T_T_INV,
    T_ABAR,
    T_DBAR_INV,
    T_PHI22,
    T_GAMMA21,
    T_RAMP_Y,
    T_RAMP21,
    T_LAM_STEER,
    T_LAM_YAW,
    T_US_C,
    T_US_PHI,
    T_US_GAMMA,
    T_US_RAMP,
    T_US_T_INV,
    T_US_ABAR,
    T_US_DBAR_INV,
    T_US_PHI22,
    T_US_GAMMA21,
    T_US_RAMP21,
    T_US_LAM,
) = range(len(TABLES))


def build_params(settings, design) -> np.ndarray:
    est = settings.estimator
    return PARAMS.vector(
        dt=float(design.sample_time),
        diff_l=design.uh_differentiator_lambda,
        diff_substeps=1,
        max_roll=est.max_roll,
        max_torque=est.max_rider_torque,
        # below its detectability floor case 2's invariant zeros are unstable: held in reset there (a vehicle whose
        # floor is above the validity speed, a much softer front tyre, still gets every other estimate)
        uh_min_speed=max(float(design.min_valid_speed), float(design.detectability_floor)),
        sta_lc_r=est.force_observer_yaw_bound,
        sta_lc_w=est.force_observer_lateral_bound,
        geom=lateral_yaw_constants(settings.vehicle),
        us=cus.stage_params(design, steer_quantum=settings.sensors.steer_count_rad),
        ch=ck.build_params(settings, design),
    )


@njit(cache=True)
def diagnostics_stage(
    st: np.ndarray,
    prm: np.ndarray,
    out: np.ndarray,
    tables: np.ndarray,
    tindex: np.ndarray,
    t0: int,
    inputs: np.ndarray,
    speed: np.ndarray,
    attitude: np.ndarray,
    cond: np.ndarray,
) -> None:
    """One cycle. ``tables``/``tindex``: a packed buffer holding TABLES in order from row ``t0``."""
    dt = prm[P_DT]
    run = cond[cnd.OUT_RUN] != 0.0
    u = speed[spd.OUT_U]
    delta = cond[cnd.OUT_STEER]
    r_ground = cond[cnd.OUT_YAW_RATE]
    uh_state = st[ST_UH : ST_UH + uh.STATE_SIZE]
    uh_out = out[OUT_UH : OUT_UH + uh.OUT_SIZE]
    run_uh = run and u >= prm[P_UH_MIN_SPEED]
    if not run_uh:
        uh_state[uh.INIT] = 0.0
    roll_uio = 0.0
    tau_uio = 0.0
    reset = False
    if run_uh:
        uh.uihosmo_step(
            uh_state,
            uh_out,
            st[ST_UH_TMP : ST_UH_TMP + 24],
            delta,
            r_ground,
            u,
            dt,
            prm[P_DIFF_L],
            v1(tables, tindex, t0 + T_GRID),
            v3(tables, tindex, t0 + T_PHI),
            v3(tables, tindex, t0 + T_GAMMA),
            v3(tables, tindex, t0 + T_T_INV),
            v3(tables, tindex, t0 + T_ABAR),
            v3(tables, tindex, t0 + T_DBAR_INV),
            v3(tables, tindex, t0 + T_PHI22),
            v3(tables, tindex, t0 + T_GAMMA21),
            v3(tables, tindex, t0 + T_RAMP_Y),
            v3(tables, tindex, t0 + T_RAMP21),
            v1(tables, tindex, t0 + T_LAM_STEER),
            v1(tables, tindex, t0 + T_LAM_YAW),
            int(prm[P_DIFF_SUBSTEPS]),
        )
        roll_uio = uh_out[uh.OUT_PHI]
        tau_uio = uh_out[uh.OUT_TAU]
        if (
            not all_finite(uh_out, uh.OUT_SIZE)
            or not all_finite(uh_state, uh.STATE_SIZE)
            or abs(roll_uio) > prm[P_MAX_ROLL]
            or abs(tau_uio) > prm[P_MAX_TORQUE]
        ):
            uh_state[uh.INIT] = 0.0
            reset = True
            roll_uio = cond[cnd.OUT_ROLL_LAST]
            tau_uio = 0.0
            for k in range(uh.OUT_SIZE):
                uh_out[k] = 0.0
            uh_out[uh.X_DELTA] = delta
            uh_out[uh.X_R] = r_ground

    # tyre forces: seed 003's super-twisting observer on the lateral/yaw sub-model, from (u, r, a_y) only
    forces = out[OUT_FY_FRONT : OUT_FY_REAR + 1]
    forces[0] = 0.0
    forces[1] = 0.0
    sta = st[ST_STA : ST_STA + STA_STATE_SIZE]
    if run and inputs[inp.OUT_ACCEL_OK] != 0.0:
        sta_step(
            sta,
            forces,
            u,
            r_ground,
            cond[cnd.OUT_A_Y],
            dt,
            prm[P_GEOM : P_GEOM + 4],
            prm[P_STA_LC_R],
            prm[P_STA_LC_W],
        )
        if not (math.isfinite(forces[0]) and math.isfinite(forces[1])):
            for k in range(STA_STATE_SIZE):
                sta[k] = 0.0
            forces[0] = 0.0
            forces[1] = 0.0
    else:
        for k in range(STA_STATE_SIZE):
            sta[k] = 0.0
    out[OUT_ROLL] = roll_uio
    out[OUT_TORQUE] = tau_uio
    out[OUT_RESET] = 1.0 if reset else 0.0

    # the UIHOSMO on the sensors (issue #16): rider torque from steer'' with the roll as a measured input, a diverse
    # check of the published torque (the supervisor's plausibility monitor). Its roll, rates and a_y are its own
    # (core.channel_kinematics, from the raw IMU): fed the attitude filter's, it only repeated the published roll
    ch_state = st[ST_CH : ST_CH + ck.STATE_SIZE]
    ch_out = out[OUT_CH : OUT_CH + ck.OUT_SIZE]
    # only on this cycle's own readings: a held gyro value integrated is a roll invented, a held accelerometer
    # value a gravity direction that may be stale
    if inputs[inp.OUT_IMU_OK] != 0.0 and inputs[inp.OUT_RATES_OK] != 0.0:
        raw = inputs[inp.OUT_RAW : inp.OUT_RAW + inp.N_RAW]
        # the pitch and yaw gyros' and the lateral accelerometer's biases are the attitude filter's (calibration
        # constants: a yaw-rate bias times the speed is a lateral acceleration, 0.01 rad/s at 100 km/h is 1.6 deg of
        # roll, and 0.1 m/s^2 of accelerometer bias is 0.6 deg). The roll-rate gyro's is not taken, nor the filter's
        # roll or sideslip: a roll-gyro fault moves this roll by its bias over the crossover, whatever the filter
        # makes of it
        att_ok = attitude[att.OUT_OK] != 0.0
        b_q = attitude[att.OUT_BQ] if att_ok else 0.0
        b_r = attitude[att.OUT_BR] if att_ok else 0.0
        b_ay = attitude[att.OUT_BAY] if att_ok else 0.0
        ck.channel_kinematics_step(
            ch_state,
            prm[P_CH : P_CH + ck.PARAM_SIZE],
            ch_out,
            raw[inp.RAW_P],
            raw[inp.RAW_Q] - b_q,
            raw[inp.RAW_R] - b_r,
            raw[inp.RAW_AY] - b_ay,
            raw[inp.RAW_AZ],
            u,
            inputs[inp.OUT_ACCEL_OK] != 0.0 and inputs[inp.OUT_ACCEL_TRUSTED] != 0.0 and speed[spd.OUT_KNOWN] != 0.0,
        )
    us_state = st[ST_US : ST_US + cus.STATE_SIZE]
    us_out = out[OUT_US : OUT_US + cus.OUT_SIZE]
    if run and ch_out[ck.OUT_VALID] != 0.0:
        cus.uio_sensors_step(
            us_state,
            us_out,
            prm[P_US : P_US + cus.PARAM_SIZE],
            v1(tables, tindex, t0 + T_GRID),
            v2(tables, tindex, t0 + T_US_C),
            v3(tables, tindex, t0 + T_US_PHI),
            v3(tables, tindex, t0 + T_US_GAMMA),
            v3(tables, tindex, t0 + T_US_RAMP),
            v3(tables, tindex, t0 + T_US_T_INV),
            v3(tables, tindex, t0 + T_US_ABAR),
            v3(tables, tindex, t0 + T_US_DBAR_INV),
            v3(tables, tindex, t0 + T_US_PHI22),
            v3(tables, tindex, t0 + T_US_GAMMA21),
            v3(tables, tindex, t0 + T_US_RAMP21),
            v2(tables, tindex, t0 + T_US_LAM),
            delta,
            ch_out[ck.OUT_YAW_RATE],
            ch_out[ck.OUT_ROLL_RATE],
            ch_out[ck.OUT_A_Y],  # nan while the accelerometer is not sound: held, not valid
            ch_out[ck.OUT_ROLL],
            u,
        )
    else:
        cus.uio_sensors_reset(us_state)
        for k in range(cus.OUT_SIZE):
            us_out[k] = 0.0


STAGE = Stage(
    name="diagnostics",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    tables=TABLES,
    constants={
        "lam_steer": uh.LAMBDA_STEER,
        "lam_yaw": uh.LAMBDA_YAW,
        "us_lam": lambda design: cus.stage_lambdas(design.us_degrees),
    },
    doc="seed 000's UIHOSMO (roll, rider torque), seed 003's super-twisting tyre forces, and the UIHOSMO on the "
    "sensors with its own roll (the plausibility monitor's channel)",
)
