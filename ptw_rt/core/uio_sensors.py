"""UIHOSMO on the scooter's real sensors (issue #16) as one jitted, allocation-free stage per 10 ms cycle.

The observer designed by `ptw_rt/design/uio_sensors.py` for a square output set chosen from
[steer, yaw rate, roll rate, lateral acceleration] (the design file's `us_outputs`), with the unknown
inputs [phi, tau] (roll not used as a measurement) or tau alone (the roll is a measured input). Per cycle:

  1. output errors e_j = y_j - C_j z;
  2. Livne-Levant discrete differentiator of order rho_j + 1 on each e_j (rho_j: the output's relative
     degree, 1 or 2): theta_1 = [e_j, ..., e_j^(rho_j - 1)], and e_j^(rho_j) for eq. 15;
  3. x_hat = z + T^-1 [theta_1; theta_2];
  4. zeta = Dbar^-1 ([e_j^(rho_j)] - Abar [theta_1; theta_2])                       (seed 000 eq. 15)
  5. z <- Phi z + Gamma [y; w] + Ramp ([y; w] - [y; w]_prev)         (exact ZOH + first-order hold)
     theta_2 <- Phi22 theta_2 + Gamma21 theta_1 + Ramp21 d/dt theta_1             (ramp hold)
Every matrix is interpolated linearly in the speed between design grid points (`core.schedule`).

Below the design's validity speed (`P_MIN_SPEED`, at least the set's detectability floor) the stage is
held in reset and says so (`OUT_VALID` = 0); a non-finite input holds the state for that cycle.

Layouts (float64 vectors, named indices below): state `ST_*` (`new_state()`), parameters `P_*`
(`stage_params(design)`), outputs `OUT_*`. Tables: `stage_tables(design)` gives them in the order of
`uio_sensors_step`'s arguments.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import kalman
from ptw_rt.core.differentiator import hdd_init, hdd_lambda, hdd_step
from ptw_rt.core.schedule import grid_position, lerp

N_X = 7  # reduced state [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr]
X_DELTA, X_VY, X_R, X_PHI_DOT, X_DELTA_DOT, X_FYF, X_FYR = range(N_X)
MAX_OUT = 2  # reconstruction outputs (= unknown inputs)
MAX_OBS = 4  # outputs of the pre-observer (the reconstruction outputs first)
MAX_DIFF = 4  # differentiator of order <= 3
N_D = kalman.N_D  # lateral, yaw, roll and steer rows of the nonlinear correction

# ---- measurement codes (design file `us_outputs`): which signal output j is ----
M_STEER, M_YAW_RATE, M_ROLL_RATE, M_LAT_ACCEL = range(4)

# ---- state buffer ----
ST_Z = 0  # pre-observer state z (N_X)
ST_TH2 = ST_Z + N_X  # zero-dynamics state theta_2 (up to N_X - 1)
ST_DIFF = ST_TH2 + N_X - 1  # MAX_OUT differentiators of MAX_DIFF entries each
ST_Y_PREV = ST_DIFF + MAX_OUT * MAX_DIFF  # observed outputs of the previous cycle (first-order hold)
ST_W_PREV = ST_Y_PREV + MAX_OBS  # measured roll of the previous cycle
ST_D_PREV = ST_W_PREV + 1  # nonlinear correction d of the previous cycle (N_D)
ST_ROLL_HAT = ST_D_PREV + N_D  # rad, the previous cycle's roll estimate (the correction's roll when phi is unknown)
ST_INIT = ST_ROLL_HAT + 1  # 1 once initialised
ST_TMP = ST_INIT + 1  # scratch: theta, z_next, theta_2 next (N_X each), y (MAX_OBS), rhs (MAX_OUT), d (N_D), kz (5)
STATE_SIZE = ST_TMP + 3 * N_X + MAX_OBS + MAX_OUT + N_D + 5

# ---- parameters (`stage_params`) ----
P_DT = 0
P_MIN_SPEED = 1  # m/s: below, held in reset, OUT_VALID = 0
P_N_OUT = 2  # number of outputs = number of unknown inputs (1 or 2)
P_ROLL_INPUT = 3  # 1: zeta = tau and the roll is a measured input; 0: zeta = [phi, tau]
P_OUT0 = 4  # M_* code of output 0
P_OUT1 = 5
P_DEG0 = 6  # relative degree of output 0 (1 or 2)
P_DEG1 = 7
P_LIPSCHITZ0 = 8  # differentiator constant L of output 0, in its units / s^(rho + 2)
P_LIPSCHITZ1 = 9
P_MASS = 10  # kg, for the initial tyre forces from a_y
P_NONLINEAR = 11  # 1: apply the nonlinear rows' correction d as a known input (as the fusion filter does)
P_NL = 12  # the correction's vehicle constants (core.kalman NL_*, 7 entries)
P_N_OBS = P_NL + 7  # number of pre-observer outputs (>= P_N_OUT)
P_OBS = P_N_OBS + 1  # M_* codes of the pre-observer outputs (MAX_OBS entries; the first P_N_OUT are P_OUT*)
P_STEER_QUANTUM = P_OBS + MAX_OBS  # rad, one count of the steer encoder (0: a continuous steer signal)
PARAM_SIZE = P_STEER_QUANTUM + 1

# ---- outputs ----
OUT_ROLL = 0  # rad (the measured roll passed through when it is an input)
OUT_TORQUE = 1  # N m, rider steering torque
OUT_X = 2  # reduced state estimate [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr] (N_X entries)
OUT_VALID = OUT_X + N_X  # 1 when above the validity speed and initialised
OUT_SIZE = OUT_VALID + 1


def new_state() -> np.ndarray:
    return np.zeros(STATE_SIZE)


def new_output() -> np.ndarray:
    return np.zeros(OUT_SIZE)


def stage_lambdas(degrees) -> np.ndarray:
    """(MAX_OUT, MAX_DIFF) differentiator gains, row j for order degrees[j] + 1 (zero-padded)."""
    lam = np.zeros((MAX_OUT, MAX_DIFF))
    for j, d in enumerate(degrees):
        lam[j, : d + 2] = hdd_lambda(d + 1)
    return lam


def stage_params(design, lipschitz=None, nonlinear: bool = True, steer_quantum: float = 0.0) -> np.ndarray:
    """The parameter vector from a `DesignData` (its `us_*` fields); `lipschitz` overrides `us_lipschitz`;
    `steer_quantum` [rad]: one count of the steer encoder that quantises the steer fed to the stage."""
    outs = np.asarray(design.us_outputs, dtype=np.int64)
    degs = np.asarray(design.us_degrees, dtype=np.int64)
    lip = np.asarray(design.us_lipschitz if lipschitz is None else lipschitz, dtype=np.float64)
    prm = np.zeros(PARAM_SIZE)
    prm[P_DT] = design.sample_time
    prm[P_MIN_SPEED] = design.us_min_valid_speed
    prm[P_N_OUT] = outs.shape[0]
    prm[P_ROLL_INPUT] = float(design.us_roll_input)
    for j in range(outs.shape[0]):
        prm[P_OUT0 + j] = outs[j]
        prm[P_DEG0 + j] = degs[j]
        prm[P_LIPSCHITZ0 + j] = lip[j]
    prm[P_MASS] = design.us_mass
    prm[P_NONLINEAR] = 1.0 if nonlinear else 0.0
    prm[P_NL : P_NL + 7] = design.kf_nonlinear
    obs = np.asarray(design.us_observed, dtype=np.int64)
    prm[P_N_OBS] = obs.shape[0]
    for j in range(obs.shape[0]):
        prm[P_OBS + j] = obs[j]
    prm[P_STEER_QUANTUM] = steer_quantum
    return prm


def stage_tables(design) -> tuple[np.ndarray, ...]:
    """(grid, C, Phi, Gamma, Ramp, T_inv, Abar, Dbar_inv, Phi22, Gamma21, Ramp21, lam) for `uio_sensors_step`."""
    return (
        np.ascontiguousarray(design.grid, dtype=np.float64),
        np.ascontiguousarray(design.us_C, dtype=np.float64),
        np.ascontiguousarray(design.us_Phi),
        np.ascontiguousarray(design.us_Gamma),
        np.ascontiguousarray(design.us_Ramp),
        np.ascontiguousarray(design.us_T_inv),
        np.ascontiguousarray(design.us_Abar),
        np.ascontiguousarray(design.us_Dbar_inv),
        np.ascontiguousarray(design.us_Phi22),
        np.ascontiguousarray(design.us_Gamma21),
        np.ascontiguousarray(design.us_Ramp21),
        stage_lambdas(np.asarray(design.us_degrees, dtype=np.int64)),
    )


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _measurement(code: int, steer: float, yaw_rate: float, roll_rate: float, lat_accel: float) -> float:
    if code == M_STEER:
        return steer
    if code == M_YAW_RATE:
        return yaw_rate
    if code == M_ROLL_RATE:
        return roll_rate
    return lat_accel


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _within_reading(reading: float, predicted: float, quantum: float) -> float:
    """The steer nearest to the pre-observer's prediction that the encoder's reading allows.

    A reading of n counts says only that the steer lies within half a count of n counts (the encoder rounds).
    Taken as the steer itself, every crossing of a count steps the steer error that the torque is reconstructed
    from: deep in a 100 km/h corner, where the steer sits near zero and the pre-observer's linear tyres put its
    predicted steer a fraction of a count from the truth, one crossing moved the torque by 2-4 N m. Inside the
    reading's cell the prediction is kept (no error to reconstruct from); outside, the error counts from the
    cell's nearer edge. Measured (docs/estimator.md, "The steer's quantisation"): on the realistic plant every
    ride gains (`radius_accel` 27.3 -> 23.7 % of the peak); on the linear model with every other sensor exact,
    where the prediction is already right, holding it within a cell costs accuracy at speed."""
    half = 0.5 * quantum
    if predicted > reading + half:
        return reading + half
    if predicted < reading - half:
        return reading - half
    return predicted


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def uio_sensors_reset(state: np.ndarray) -> None:
    """Forget everything (next step re-initialises on its measurements)."""
    for k in range(STATE_SIZE):
        state[k] = 0.0


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _finite_state(state: np.ndarray) -> bool:
    for k in range(ST_TMP):
        if not math.isfinite(state[k]):
            return False
    return True


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def uio_sensors_step(
    state: np.ndarray,
    out: np.ndarray,
    prm: np.ndarray,
    grid: np.ndarray,
    C: np.ndarray,
    Phi: np.ndarray,
    Gamma: np.ndarray,
    Ramp: np.ndarray,
    T_inv: np.ndarray,
    Abar: np.ndarray,
    Dbar_inv: np.ndarray,
    Phi22: np.ndarray,
    Gamma21: np.ndarray,
    Ramp21: np.ndarray,
    lam: np.ndarray,
    steer: float,
    yaw_rate: float,
    roll_rate: float,
    lat_accel: float,
    roll: float,
    speed: float,
) -> None:
    """One cycle: steer [rad], ground yaw rate [rad/s], roll rate [rad/s], lateral acceleration at the centre
    of mass [m/s^2], measured roll [rad] (used only when P_ROLL_INPUT = 1), forward speed [m/s]."""
    n_out = int(prm[P_N_OUT])
    n_obs = int(prm[P_N_OBS])
    roll_input = prm[P_ROLL_INPUT] != 0.0
    dt = prm[P_DT]
    out[OUT_VALID] = 0.0
    if not (math.isfinite(speed) and speed >= prm[P_MIN_SPEED]):
        uio_sensors_reset(state)
        out[OUT_ROLL] = roll if roll_input else 0.0
        out[OUT_TORQUE] = 0.0
        for a in range(N_X):
            out[OUT_X + a] = 0.0
        return
    y = state[ST_TMP + 3 * N_X : ST_TMP + 3 * N_X + MAX_OBS]
    for j in range(n_obs):
        y[j] = _measurement(int(prm[P_OBS + j]), steer, yaw_rate, roll_rate, lat_accel)
        if not math.isfinite(y[j]):
            return  # hold: keep the previous estimates, not valid this cycle
    w = roll if roll_input else 0.0
    if not math.isfinite(w):
        return
    i, wg = grid_position(grid, speed)
    z = state[ST_Z : ST_Z + N_X]
    first = state[ST_INIT] == 0.0
    if first:
        for a in range(N_X):
            z[a] = 0.0
        z[X_DELTA] = steer if math.isfinite(steer) else 0.0
        z[X_R] = yaw_rate if math.isfinite(yaw_rate) else 0.0
        z[X_PHI_DOT] = roll_rate if math.isfinite(roll_rate) else 0.0
        if math.isfinite(lat_accel):
            z[X_FYF] = 0.5 * prm[P_MASS] * lat_accel
            z[X_FYR] = 0.5 * prm[P_MASS] * lat_accel
        for k in range(ST_TH2, ST_Y_PREV):
            state[k] = 0.0
        for j in range(n_out):
            v = state[ST_DIFF + MAX_DIFF * j : ST_DIFF + MAX_DIFF * j + int(prm[P_DEG0 + j]) + 2]
            acc = y[j]
            for a in range(N_X):
                acc -= C[j, a] * z[a]
            hdd_init(v, acc)
        for j in range(n_obs):
            state[ST_Y_PREV + j] = y[j]
        state[ST_W_PREV] = w
        state[ST_ROLL_HAT] = w
        state[ST_INIT] = 1.0
    if prm[P_STEER_QUANTUM] > 0.0:
        for j in range(n_obs):
            if int(prm[P_OBS + j]) == M_STEER:
                predicted = 0.0
                for a in range(N_X):
                    predicted += C[j, a] * z[a]
                y[j] = _within_reading(y[j], predicted, prm[P_STEER_QUANTUM])
    n2 = Phi22.shape[1]
    n1 = N_X - n2
    th2 = state[ST_TH2 : ST_TH2 + n2]
    theta = state[ST_TMP : ST_TMP + N_X]
    base_tmp = ST_TMP + 3 * N_X + MAX_OBS
    rhs = state[base_tmp : base_tmp + MAX_OUT]
    dnl = state[base_tmp + MAX_OUT : base_tmp + MAX_OUT + N_D]
    kz = state[base_tmp + MAX_OUT + N_D : STATE_SIZE]
    # nonlinear rows' correction at the measured steer and rates and the measured (or last estimated) roll
    for a in range(N_D):
        dnl[a] = 0.0
    if prm[P_NONLINEAR] != 0.0:
        kz[kalman.PHI] = w if roll_input else state[ST_ROLL_HAT]
        kz[kalman.DELTA] = steer if math.isfinite(steer) else z[X_DELTA]
        kz[kalman.R] = yaw_rate if math.isfinite(yaw_rate) else z[X_R]
        kz[kalman.PHI_DOT] = roll_rate if math.isfinite(roll_rate) else z[X_PHI_DOT]
        kalman.nonlinear_correction(dnl, kz, speed, prm[P_NL : P_NL + 7])
    if first:
        for a in range(N_D):
            state[ST_D_PREV + a] = dnl[a]

    # output errors through the differentiators; theta_1 and the top derivatives
    k1 = 0
    for j in range(n_out):
        deg = int(prm[P_DEG0 + j])
        v = state[ST_DIFF + MAX_DIFF * j : ST_DIFF + MAX_DIFF * j + deg + 2]
        e = y[j]
        for a in range(N_X):
            e -= C[j, a] * z[a]
        hdd_step(v, e, prm[P_LIPSCHITZ0 + j], dt, lam[j, : deg + 2], 1)
        for q in range(deg):
            theta[k1 + q] = v[q]
        rhs[j] = v[deg]
        k1 += deg
    for a in range(n2):
        theta[n1 + a] = th2[a]

    # x_hat = z + T^-1 theta
    for a in range(N_X):
        acc = z[a]
        for b in range(N_X):
            acc += lerp(T_inv, i, wg, a, b) * theta[b]
        out[OUT_X + a] = acc
    # zeta = Dbar^-1 (rhs - Abar theta)
    for j in range(n_out):
        acc = rhs[j]
        for b in range(N_X):
            acc -= lerp(Abar, i, wg, j, b) * theta[b]
        rhs[j] = acc
    z0 = 0.0
    z1 = 0.0
    for j in range(n_out):
        z0 += lerp(Dbar_inv, i, wg, 0, j) * rhs[j]
        if n_out > 1:
            z1 += lerp(Dbar_inv, i, wg, 1, j) * rhs[j]
    if roll_input:
        out[OUT_ROLL] = w
        out[OUT_TORQUE] = z0
    else:
        out[OUT_ROLL] = z0
        out[OUT_TORQUE] = z1

    # propagate z (ZOH + first-order hold of [y; w]) and theta_2 (ramp hold of theta_1)
    z_next = state[ST_TMP + N_X : ST_TMP + 2 * N_X]
    for a in range(N_X):
        acc = 0.0
        for b in range(N_X):
            acc += lerp(Phi, i, wg, a, b) * z[b]
        for j in range(n_obs):
            acc += lerp(Gamma, i, wg, a, j) * y[j] + lerp(Ramp, i, wg, a, j) * (y[j] - state[ST_Y_PREV + j])
        acc += lerp(Gamma, i, wg, a, n_obs) * w + lerp(Ramp, i, wg, a, n_obs) * (w - state[ST_W_PREV])
        for b in range(N_D):
            acc += lerp(Gamma, i, wg, a, n_obs + 1 + b) * dnl[b]
            acc += lerp(Ramp, i, wg, a, n_obs + 1 + b) * (dnl[b] - state[ST_D_PREV + b])
        z_next[a] = acc
    th_next = state[ST_TMP + 2 * N_X : ST_TMP + 3 * N_X]
    for a in range(n2):
        acc = 0.0
        for b in range(n2):
            acc += lerp(Phi22, i, wg, a, b) * th2[b]
        k1 = 0
        for j in range(n_out):
            deg = int(prm[P_DEG0 + j])
            base = ST_DIFF + MAX_DIFF * j
            for q in range(deg):
                acc += lerp(Gamma21, i, wg, a, k1 + q) * state[base + q]
                acc += lerp(Ramp21, i, wg, a, k1 + q) * state[base + q + 1]
            k1 += deg
        th_next[a] = acc
    for a in range(N_X):
        z[a] = z_next[a]
    for a in range(n2):
        th2[a] = th_next[a]
    for j in range(n_obs):
        state[ST_Y_PREV + j] = y[j]
    state[ST_W_PREV] = w
    for b in range(N_D):
        state[ST_D_PREV + b] = dnl[b]
    state[ST_ROLL_HAT] = out[OUT_ROLL]
    if not _finite_state(state):
        uio_sensors_reset(state)
        return
    out[OUT_VALID] = 1.0
