"""Fusion filter step (steady-state Kalman on the torque-augmented Sharp model; design in ptw_rt.design.kalman).

    z+ = z + K(u) (y - C z)          corrector: y = [delta, r, phi_dot, a_y, phi_kinematic]
    z  = Phi(u) z+ + Gd(u) d(z+)     predictor: exact ZOH, rider torque held (random walk)

d are the generalised forces by which the vehicle's rows differ from the linear model's (sin and cos of
roll and steer instead of their small-angle forms; see `nonlinear_correction`): a known input computed
from the corrected state, so the filter stays exact in a 30 deg corner where the small-angle steer
row alone would bias the rider torque by 10 N m. phi is the roll angle itself (not tan phi): with d the
roll row is exact, and the tyres' camber is phi.

State layout (float64, `new_state`): [0:9] z = [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, tau],
[9] initialised. The rates come bias-corrected (the attitude filter owns the gyro biases).
The corrected z+ is written to `out` (the estimate of this cycle).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core.schedule import grid_position, lerp

N_Z = 9
N_Y = 5
PHI, DELTA, VY, R, PHI_DOT, DELTA_DOT, FYF, FYR, TAU = range(9)
INIT = 9
STATE_SIZE = 10

# vehicle constants of the nonlinear correction (ptw_rt.design.kalman.nonlinear_constants)
NL_ROLL_MOMENT, NL_GYRO_TOTAL, NL_GYRO_FRONT, NL_STEER_STIFFNESS, NL_MFE, NL_G, NL_SIN_CASTER = range(7)
N_D = 4  # lateral, yaw, roll, steer rows


@njit(cache=True, inline="always")
def nonlinear_correction(d: np.ndarray, z: np.ndarray, u: float, nl: np.ndarray) -> None:
    """d = (nonlinear rows) - (linear rows) at state z, per docs/simulator.md's plant equations:

    lateral  S phi_dot^2 sin(phi)
    yaw      G u phi_dot (cos(phi) - 1)
    roll     S g (sin(phi) - phi) + K_s (sin(delta) cos(phi) - delta) - (S + G) u r (cos(phi) - 1)
    steer    K_s (sin(phi) - phi) + K_s sin(eps) (sin(delta) - delta) - (M_f e + G_f sin(eps)) u r (cos(phi) - 1)
    """
    phi, delta, r, phi_dot = z[PHI], z[DELTA], z[R], z[PHI_DOT]
    sp, cp, sd = math.sin(phi), math.cos(phi), math.sin(delta)
    S, G, Gf, Ks = nl[NL_ROLL_MOMENT], nl[NL_GYRO_TOTAL], nl[NL_GYRO_FRONT], nl[NL_STEER_STIFFNESS]
    se = nl[NL_SIN_CASTER]
    d[0] = S * phi_dot * phi_dot * sp
    d[1] = G * u * phi_dot * (cp - 1.0)
    d[2] = S * nl[NL_G] * (sp - phi) + Ks * (sd * cp - delta) - (S + G) * u * r * (cp - 1.0)
    d[3] = Ks * (sp - phi) + Ks * se * (sd - delta) - (nl[NL_MFE] + Gf * se) * u * r * (cp - 1.0)


# A filter (re)started runs this many steps on its first measurement before its first real one: it starts from
# its own steady response to that measurement (the forces, sideslip and torque of a steady turn at the measured
# steer, yaw rate and lean) instead of zero forces and torque, whose transient the torque's random walk took up
# for 2-3 s (a restart in a slalom read 15-17 N m off). 0.5 s of the filter's time (~0.13 ms of CPU once per
# restart): 2 s settled the same slalom's restarts no better.
SETTLE_STEPS = 50


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
    Gd: np.ndarray,
    nl: np.ndarray,
    d: np.ndarray,
) -> None:
    """One cycle of one filter; `out` (>= N_Z floats) receives the corrected state. `roll_init` seeds phi on
    (re)start. The runtime steps its filters in pairs (`kalman_pair_step_at`, the tyre bank); this runs the same
    code on the filter and a copy of it (tests, offline use: it allocates)."""
    i, w = grid_position(grid, u)
    pair = np.empty(2 * STATE_SIZE)
    pair[:STATE_SIZE] = state
    pair[STATE_SIZE:] = state
    kalman_pair_step_at(
        pair, 0, STATE_SIZE, out, np.empty(N_Z), y, u, roll_init, i, w, Phi, K, K, C, Gd, nl, d, np.empty(N_D)
    )
    state[:] = pair[:STATE_SIZE]


@njit(cache=True, inline="always")
def kalman_pair_step_at(
    st: np.ndarray,
    s0: int,
    s1: int,
    out0: np.ndarray,
    out1: np.ndarray,
    y: np.ndarray,
    u: float,
    roll_init: float,
    j: int,
    w: float,
    Phi: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    C: np.ndarray,
    Gd: np.ndarray,
    nl: np.ndarray,
    d0: np.ndarray,
    d1: np.ndarray,
) -> None:
    """One cycle of two filters of the same vehicle that differ only in their gain (the tyre bank's evidence
    filter, gain K0, state at ``st[s0 : s0 + STATE_SIZE]``, and its publishing filter, K1 at s1), between table rows
    j and j + 1 (their grid position, `grid_position`, found once by the caller; the tyre bank's tables hold every
    hypothesis's grid one after the other). `out0`/`out1` receive the corrected states. Phi and Gd depend on the
    vehicle alone, so each of their entries is interpolated once for both: the tables are most of the bank's
    memory traffic, read afresh each cycle. Every matrix entry is `schedule.lerp`'s. Why offsets instead of
    slices, and inlined: every array view made or passed at run time costs an atomic reference count increment
    and decrement (~6 ns each), which were a third of the bank's time."""
    fresh = st[s0 + INIT] == 0.0 or st[s1 + INIT] == 0.0
    _start(st, s0, y, roll_init)
    _start(st, s1, y, roll_init)
    # a pair just started first settles on this measurement: the same step, `SETTLE_STEPS` more times
    # (both with the evidence filter's gain: the publishing filter's freer torque and forces would settle onto a
    # mid-manoeuvre measurement as if it were a steady turn, farther from the truth)
    settle = SETTLE_STEPS if fresh else 0
    for n in range(1 + settle):
        _correct(st, s0, out0, y, j, w, K0, C)
        _correct(st, s1, out1, y, j, w, K0 if n < settle else K1, C)
        nonlinear_correction(d0, out0, u, nl)
        nonlinear_correction(d1, out1, u, nl)
        for a in range(N_Z):
            acc0 = 0.0
            acc1 = 0.0
            for b in range(N_Z):
                p = lerp(Phi, j, w, a, b)
                acc0 += p * out0[b]
                acc1 += p * out1[b]
            for b in range(N_D):
                g = lerp(Gd, j, w, a, b)
                acc0 += g * d0[b]
                acc1 += g * d1[b]
            st[s0 + a] = acc0
            st[s1 + a] = acc1


@njit(cache=True, inline="always")
def kalman_step_at(
    st: np.ndarray,
    s0: int,
    out: np.ndarray,
    y: np.ndarray,
    u: float,
    roll_init: float,
    j: int,
    w: float,
    Phi: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    Gd: np.ndarray,
    nl: np.ndarray,
    d: np.ndarray,
) -> None:
    """One cycle of one filter whose state is at ``st[s0 : s0 + STATE_SIZE]``, between table rows j and j + 1: a
    filter with tables of its own (the tyre bank's balance check), where `kalman_pair_step_at` steps two that share
    them. The same start, settling and step."""
    fresh = st[s0 + INIT] == 0.0
    _start(st, s0, y, roll_init)
    for _ in range(1 + (SETTLE_STEPS if fresh else 0)):
        _correct(st, s0, out, y, j, w, K, C)
        nonlinear_correction(d, out, u, nl)
        for a in range(N_Z):
            acc = 0.0
            for b in range(N_Z):
                acc += lerp(Phi, j, w, a, b) * out[b]
            for b in range(N_D):
                acc += lerp(Gd, j, w, a, b) * d[b]
            st[s0 + a] = acc


@njit(cache=True, inline="always")
def _start(st: np.ndarray, s0: int, y: np.ndarray, roll_init: float) -> None:
    """A filter that is not initialised starts from the measured steer, yaw and roll rates and `roll_init`."""
    if st[s0 + INIT] == 0.0:
        for a in range(N_Z):
            st[s0 + a] = 0.0
        st[s0 + PHI] = roll_init
        st[s0 + DELTA] = y[0]
        st[s0 + R] = y[1]
        st[s0 + PHI_DOT] = y[2]
        st[s0 + INIT] = 1.0


@njit(cache=True, inline="always")
def _correct(
    st: np.ndarray, s0: int, out: np.ndarray, y: np.ndarray, j: int, w: float, K: np.ndarray, C: np.ndarray
) -> None:
    """out = z + K (y - C z) for the filter whose state z is at s0."""
    for a in range(N_Z):
        out[a] = st[s0 + a]
    for r in range(N_Y):
        e = y[r]
        for c in range(N_Z):
            e -= C[r, c] * st[s0 + c]
        for a in range(N_Z):
            out[a] += lerp(K, j, w, a, r) * e
