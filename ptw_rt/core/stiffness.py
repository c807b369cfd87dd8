"""Stage 7, tyre stiffness: seed 001's LPV adaptive observer (`ptw_rt.core.adaptive`) and its guards (jitted).

y = [delta, r, phi_dot, delta_dot, a_y, y_a] with the fusion filter's steer rate and rider torque as the
observer's input; y_a is seed 001's virtual output (eq. 15) from the filtered rate derivatives. The observer
learns only while the supervisor's conditions allow it (accelerometer, GPS, no input reason, the observers
settled) and while its model explains what is measured: an exponentially weighted mean square of its a_y
innovation below ``adapt_max_residual``. Per parameter, adaptation also needs excitation (the observer's own
test). A blown-up or implausible observer is reset, keeping the last finite stiffness (OUT_DIVERGED).

The learned values are the deviations Theta from the design's nominal stiffness, in the observer's state
(ST_AD + adaptive.TH0); ``learned``, ``restore``, ``start_from_scale`` and ``reset`` are what the Estimator
calls from Python. Nothing here sets a stiffness valid bit (the supervisor's docstring says why).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import adaptive as ad
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import inputs as inp
from ptw_rt.core import kalman as kf
from ptw_rt.core import lateral as lat
from ptw_rt.core import speed as spd
from ptw_rt.core.params import virtual_output_coefficients
from ptw_rt.core.stage import Layout, Stage, all_finite, v1, v2, v3

N_THETA = 4  # [C_af, C_gf, C_ar, C_gr]

STATE = Layout(
    "ST_",
    ad=ad.STATE_SIZE,  # the adaptive observer's state (ptw_rt.core.adaptive layout; Theta at ST_AD + ad.TH0)
    theta_good=N_THETA,  # last finite Theta (what a reset of the observer keeps)
    excited_time=N_THETA,  # s of adaptation per parameter
    ay_residual_ms=1,  # mean square of the observer's a_y innovation (consistency of its model)
    restored=1,  # 1 if the stiffness came from a saved state
    chi=2 * N_THETA,  # scratch: the regressor (2 x 4)
    tmp=16,  # scratch of adaptive_step
    y=ad.N_Y,  # scratch: this cycle's measurements
)
ST_AD, ST_THETA_GOOD, ST_EXCITED_TIME, ST_AY_RESIDUAL_MS, ST_RESTORED, ST_CHI, ST_TMP, ST_Y = STATE.offsets

PARAMS = Layout(
    "P_",
    dt=1,
    pe_forgetting=1,  # forgetting factor of the excitation and residual mean squares
    adapt_max_residual=1,  # m/s^2: RMS a_y innovation above which adaptation is frozen
    converge_time=1,  # s the observers run before adaptation may start
    max_force=1,  # N: a tyre force beyond is a divergence
    max_lat_vel=1,  # m/s: a lateral velocity beyond is a divergence
    ya_r_dot=1,  # y_a = ya_r_dot r_dot + ya_phi_ddot phi_ddot + u (ya_phi_dot phi_dot + ya_delta_dot delta_dot)
    ya_phi_ddot=1,
    ya_phi_dot=1,
    ya_delta_dot=1,
)
(
    P_DT,
    P_PE_FORGETTING,
    P_ADAPT_MAX_RESIDUAL,
    P_CONVERGE_TIME,
    P_MAX_FORCE,
    P_MAX_LAT_VEL,
    P_YA_R_DOT,
    P_YA_PHI_DDOT,
    P_YA_PHI_DOT,
    P_YA_DELTA_DOT,
) = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    stiffness=N_THETA,  # N/rad: [C_af, C_gf, C_ar, C_gr], nominal + learned deviation
    excitation=1,  # bits 0..3: stiffness k currently excited (adapting)
    y_a=1,  # virtual output y_a as measured (0 while not running)
    roll=1,  # rad, the observer's roll state (0 while not running)
    lat_vel=1,  # m/s, its lateral velocity
    fy_front=1,  # N, its tyre forces
    fy_rear=1,
    diverged=1,  # 1: the observer was reset this cycle
)
OUT_STIFFNESS, OUT_EXCITATION, OUT_Y_A, OUT_ROLL, OUT_LAT_VEL, OUT_FY_FRONT, OUT_FY_REAR, OUT_DIVERGED = OUTPUTS.offsets

TABLES = (
    ("grid", 1),
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
)
(
    T_GRID,
    T_PHI,
    T_B_TAU,
    T_B_THETA,
    T_B_Y,
    T_C,
    T_T,
    T_GAMMA,
    T_THETA_NOMINAL,
    T_THETA_BOUND,
    T_REGRESSOR_CONSTANTS,
    T_PE_THRESHOLD,
) = range(len(TABLES))


def build_params(settings, design) -> np.ndarray:
    est = settings.estimator
    ya = virtual_output_coefficients(settings.vehicle)
    return PARAMS.vector(
        dt=float(design.sample_time),
        pe_forgetting=design.ad_pe_forgetting,
        adapt_max_residual=est.adaptation_max_residual,
        converge_time=est.converge_time,
        max_force=est.max_tyre_force,
        max_lat_vel=est.max_lateral_velocity,
        ya_r_dot=ya[0],
        ya_phi_ddot=ya[1],
        ya_phi_dot=ya[2],
        ya_delta_dot=ya[3],
    )


@njit(cache=True)
def stiffness_stage(
    st: np.ndarray,
    prm: np.ndarray,
    out: np.ndarray,
    tables: np.ndarray,
    tindex: np.ndarray,
    t0: int,
    inputs: np.ndarray,
    speed: np.ndarray,
    cond: np.ndarray,
    lateral: np.ndarray,
) -> None:
    """One cycle. ``tables``/``tindex``: a packed buffer holding TABLES in order from row ``t0``."""
    dt = prm[P_DT]
    run = cond[cnd.OUT_RUN] != 0.0
    ad_state = st[ST_AD : ST_AD + ad.STATE_SIZE]
    if not run:
        ad_state[ad.INIT] = 0.0
    ad_C = v2(tables, tindex, t0 + T_C)
    theta_nominal = v1(tables, tindex, t0 + T_THETA_NOMINAL)
    pe_threshold = v1(tables, tindex, t0 + T_PE_THRESHOLD)
    theta = ad_state[ad.TH0 : ad.TH1]
    adapting_bits = 0
    y_a = 0.0
    diverged = False
    if run:
        u = speed[spd.OUT_U]
        r_ground = cond[cnd.OUT_YAW_RATE]
        p_rate = cond[cnd.OUT_ROLL_RATE]
        a_y = cond[cnd.OUT_A_Y]
        delta_dot = lateral[lat.OUT_Z + kf.DELTA_DOT]
        y_a = (
            prm[P_YA_R_DOT] * cond[cnd.OUT_YAW_ACCEL]
            + prm[P_YA_PHI_DDOT] * cond[cnd.OUT_ROLL_ACCEL]
            + u * (prm[P_YA_PHI_DOT] * p_rate + prm[P_YA_DELTA_DOT] * delta_dot)
        )
        y = st[ST_Y : ST_Y + ad.N_Y]
        y[0] = cond[cnd.OUT_STEER]
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
            st[ST_AY_RESIDUAL_MS] = forget * st[ST_AY_RESIDUAL_MS] + (1.0 - forget) * innovation * innovation
        # learn only from an observer whose model explains what is measured (else the gradient is noise-driven)
        consistent = st[ST_AY_RESIDUAL_MS] < prm[P_ADAPT_MAX_RESIDUAL] * prm[P_ADAPT_MAX_RESIDUAL]
        allow = (
            inputs[inp.OUT_ACCEL_OK] != 0.0
            and speed[spd.OUT_GPS_LOST] == 0.0  # no fix taken for the hold time (none usable, or none believed)
            and lateral[lat.OUT_RUN_TIME] > prm[P_CONVERGE_TIME]
            and int(cond[cnd.OUT_REASONS]) == 0
            and consistent
        )
        ad.adaptive_step(
            ad_state,
            st[ST_CHI : ST_CHI + 2 * N_THETA].reshape((2, N_THETA)),
            st[ST_TMP : ST_TMP + 16],
            y,
            lateral[lat.OUT_Z + kf.TAU],
            u,
            dt,
            allow,
            v1(tables, tindex, t0 + T_GRID),
            v3(tables, tindex, t0 + T_PHI),
            v2(tables, tindex, t0 + T_B_TAU),
            v3(tables, tindex, t0 + T_B_THETA),
            v3(tables, tindex, t0 + T_B_Y),
            ad_C,
            v2(tables, tindex, t0 + T_T),
            v1(tables, tindex, t0 + T_GAMMA),
            theta_nominal,
            v1(tables, tindex, t0 + T_THETA_BOUND),
            v1(tables, tindex, t0 + T_REGRESSOR_CONSTANTS),
            pe_threshold,
            prm[P_PE_FORGETTING],
        )
        if first:
            ad_state[ad.X0 + ad.PHI] = cond[cnd.OUT_ROLL]
        if allow:
            for k in range(N_THETA):
                if ad_state[ad.PE0 + k] > pe_threshold[k] * pe_threshold[k]:
                    adapting_bits |= 1 << k
                    st[ST_EXCITED_TIME + k] += dt
        x_ad = ad_state[ad.X0 : ad.X1]
        if (
            not all_finite(ad_state, ad.STATE_SIZE)
            or abs(x_ad[ad.FYF]) > prm[P_MAX_FORCE]
            or abs(x_ad[ad.FYR]) > prm[P_MAX_FORCE]
            or abs(x_ad[ad.VY]) > prm[P_MAX_LAT_VEL]
        ):
            # reset the states, keep what was learned
            ad_state[ad.INIT] = 0.0
            for k in range(N_THETA):
                theta[k] = st[ST_THETA_GOOD + k]
            for k in range(N_THETA):
                ad_state[ad.PE0 + k] = 0.0
            for k in range(8):
                x_ad[k] = 0.0
            diverged = True
    for k in range(N_THETA):
        if math.isfinite(theta[k]):
            st[ST_THETA_GOOD + k] = theta[k]
        else:
            theta[k] = st[ST_THETA_GOOD + k]

    for k in range(N_THETA):
        out[OUT_STIFFNESS + k] = theta_nominal[k] + theta[k]
    out[OUT_EXCITATION] = adapting_bits
    out[OUT_Y_A] = y_a
    out[OUT_ROLL] = ad_state[ad.X0 + ad.PHI] if run else 0.0
    out[OUT_LAT_VEL] = ad_state[ad.X0 + ad.VY] if run else 0.0
    out[OUT_FY_FRONT] = ad_state[ad.X0 + ad.FYF] if run else 0.0
    out[OUT_FY_REAR] = ad_state[ad.X0 + ad.FYR] if run else 0.0
    out[OUT_DIVERGED] = 1.0 if diverged else 0.0


# ---- from Python (the Estimator): the learned values ----


def learned(st: np.ndarray, design) -> np.ndarray:
    """[C_af, C_gf, C_ar, C_gr] in N/rad."""
    return design.ad_theta_nominal + st[ST_AD + ad.TH0 : ST_AD + ad.TH1]


def _start_from(st: np.ndarray, values: np.ndarray, design, restored: bool) -> None:
    dev = np.clip(values - design.ad_theta_nominal, -design.ad_theta_bound, design.ad_theta_bound)
    st[ST_AD + ad.TH0 : ST_AD + ad.TH1] = dev
    st[ST_THETA_GOOD : ST_THETA_GOOD + N_THETA] = dev
    if restored:
        st[ST_RESTORED] = 1.0


def restore(st: np.ndarray, values, design) -> None:
    """Start from stiffness learned earlier (clipped to the design's bounds); marks it restored."""
    values = np.asarray(values, dtype=float)
    if values.shape != (N_THETA,) or not np.all(np.isfinite(values)):
        raise ValueError("expected four finite stiffness values")
    _start_from(st, values, design, restored=True)


def start_from_scale(st: np.ndarray, front: float, rear: float, design) -> None:
    """Start from the nominal tyres times `front` (C_af, C_gf) and `rear` (C_ar, C_gr), clipped to the
    design's bounds; not marked restored (a wrong start, not something learned)."""
    front, rear = float(front), float(rear)
    if not (math.isfinite(front) and math.isfinite(rear) and front > 0.0 and rear > 0.0):
        raise ValueError(f"stiffness scales must be finite and > 0, got front {front}, rear {rear}")
    scale = np.array([front, front, rear, rear])
    _start_from(st, design.ad_theta_nominal * scale, design, restored=False)


def reset(st: np.ndarray) -> None:
    """Forget everything but the learned stiffness (and whether it was restored)."""
    theta = st[ST_AD + ad.TH0 : ST_AD + ad.TH1].copy()
    restored = st[ST_RESTORED]
    st[:] = 0.0
    st[ST_AD + ad.TH0 : ST_AD + ad.TH1] = theta
    st[ST_THETA_GOOD : ST_THETA_GOOD + N_THETA] = theta
    st[ST_RESTORED] = restored


STAGE = Stage(
    name="stiffness",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    tables=TABLES,
    reset=lambda state, params: reset(state),
    doc="seed 001's LPV adaptive observer: the four tyre stiffnesses, frozen when unexcited or inconsistent",
)
