"""Stage 6, lateral dynamics: the fusion filter (`ptw_rt.core.kalman`) with its measurements and guards (jitted).

y = [steer, ground yaw rate, roll rate, a_y, kinematic roll]: the rates come bias-corrected from the attitude
filter, whose roll is the fifth measurement. A measurement that is not there this cycle (accelerometer held,
attitude filter not running) is replaced by the filter's own prediction of it (no innovation). The filter runs
only while the model-based observers run (conditioning's OUT_RUN); a blown-up or implausible estimate resets
it (OUT_DIVERGED, the supervisor raises REASON_DIVERGING).

The observers' convergence clock lives here (OUT_RUN_TIME: seconds since the model-based observers last
(re)started; the supervisor's CONVERGING mode and the stiffness stage's permission to adapt use it); a UIHOSMO
reset (diagnostics' OUT_RESET) restarts it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import diagnostics as dia
from ptw_rt.core import inputs as inp
from ptw_rt.core import kalman as kf
from ptw_rt.core import speed as spd
from ptw_rt.core.stage import Layout, Stage, v1, v2, v3

STATE = Layout(
    "ST_",
    kf=kf.STATE_SIZE,  # the fusion filter's state (ptw_rt.core.kalman layout)
    run_time=1,  # s since the model-based observers last (re)started
    y=kf.N_Y,  # scratch: this cycle's measurements
    d=kf.N_D,  # scratch: the nonlinear correction
)
ST_KF, ST_RUN_TIME, ST_Y, ST_D = STATE.offsets

PARAMS = Layout(
    "P_",
    dt=1,
    max_roll=1,  # rad: beyond, the filter has diverged
    max_torque=1,  # N m: likewise
)
P_DT, P_MAX_ROLL, P_MAX_TORQUE = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    z=kf.N_Z,  # the corrected state [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, tau] (0 while not running)
    run_time=1,  # s since the model-based observers last (re)started
    diverged=1,  # 1: the filter was reset this cycle
)
OUT_Z, OUT_RUN_TIME, OUT_DIVERGED = OUTPUTS.offsets

TABLES = (("grid", 1), ("kf_Phi", 3), ("kf_K", 3), ("kf_C", 2), ("kf_Gd", 3), ("kf_nonlinear", 1))
T_GRID, T_PHI, T_K, T_C, T_GD, T_NONLINEAR = range(len(TABLES))


def build_params(settings, design) -> np.ndarray:
    est = settings.estimator
    return PARAMS.vector(dt=float(design.sample_time), max_roll=est.max_roll, max_torque=est.max_rider_torque)


@njit(cache=True)
def _all_finite(v: np.ndarray, n: int) -> bool:
    for i in range(n):
        if not math.isfinite(v[i]):
            return False
    return True


@njit(cache=True)
def lateral_stage(
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
    diag: np.ndarray,
) -> None:
    """One cycle. ``tables``/``tindex``: a packed buffer holding TABLES in order from row ``t0``."""
    run = cond[cnd.OUT_RUN] != 0.0
    if not run:
        st[ST_RUN_TIME] = 0.0
    else:
        st[ST_RUN_TIME] += prm[P_DT]
        if diag[dia.OUT_RESET] != 0.0:
            st[ST_RUN_TIME] = 0.0
    kf_state = st[ST_KF : ST_KF + kf.STATE_SIZE]
    kf_out = out[OUT_Z : OUT_Z + kf.N_Z]
    diverged = False
    if run:
        C = v2(tables, tindex, t0 + T_C)
        delta = cond[cnd.OUT_STEER]
        r_ground = cond[cnd.OUT_YAW_RATE]
        p_rate = cond[cnd.OUT_ROLL_RATE]
        roll_prev = cond[cnd.OUT_DEROLL]
        y_kf = st[ST_Y : ST_Y + kf.N_Y]
        y_kf[0] = delta
        y_kf[1] = r_ground
        y_kf[2] = p_rate
        if inputs[inp.OUT_ACCEL_TRUSTED] != 0.0:
            y_kf[3] = cond[cnd.OUT_A_Y]
        else:  # no accelerometer: no innovation from it (the model's own prediction)
            acc = 0.0
            for c in range(kf.N_Z):
                acc += C[3, c] * kf_state[c]
            y_kf[3] = acc
        # the kinematic roll as a measurement
        if attitude[att.OUT_OK] != 0.0:
            y_kf[4] = roll_prev
        else:  # no kinematic roll: no innovation from it
            acc = 0.0
            for c in range(kf.N_Z):
                acc += C[4, c] * kf_state[c]
            y_kf[4] = acc
        kf.kalman_step(
            kf_state,
            kf_out,
            y_kf,
            speed[spd.OUT_U],
            roll_prev,
            v1(tables, tindex, t0 + T_GRID),
            v3(tables, tindex, t0 + T_PHI),
            v3(tables, tindex, t0 + T_K),
            C,
            v3(tables, tindex, t0 + T_GD),
            v1(tables, tindex, t0 + T_NONLINEAR),
            st[ST_D : ST_D + kf.N_D],
        )
        if (
            not _all_finite(kf_out, kf.N_Z)
            or abs(kf_out[kf.PHI]) > prm[P_MAX_ROLL]
            or abs(kf_out[kf.TAU]) > prm[P_MAX_TORQUE]
        ):
            kf_state[kf.INIT] = 0.0
            diverged = True
            for k in range(kf.N_Z):
                kf_out[k] = 0.0
            kf_out[kf.PHI] = cond[cnd.OUT_ROLL_LAST]
            kf_out[kf.DELTA] = delta
            kf_out[kf.R] = r_ground
            kf_out[kf.PHI_DOT] = p_rate
    else:
        kf_state[kf.INIT] = 0.0
        for k in range(kf.N_Z):
            kf_out[k] = 0.0
    out[OUT_RUN_TIME] = st[ST_RUN_TIME]
    out[OUT_DIVERGED] = 1.0 if diverged else 0.0


STAGE = Stage(
    name="lateral",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    tables=TABLES,
    doc="steady-state Kalman filter on the torque-augmented Sharp model: torque, steer rate, v_y, tyre forces",
)
