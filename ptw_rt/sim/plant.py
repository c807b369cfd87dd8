"""The simulated scooter: Sharp's structure made nonlinear (the truth the observers never see).

State (12): ``[phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, u, psi, X, Y]`` - the model's
eight lateral states, forward speed ``u``, heading ``psi`` (rad, clockwise from north) and the
position ``X`` (north), ``Y`` (east) of the reference point (ground point under the rear frame CoM).

    E x_dot[:8] = Q(x, tau)        (E = descriptor(p).E, kept at its upright value)

with the generalised forces of Sharp's rows, made nonlinear (see docs/simulator.md):

* lateral: ``-M u r + F_yf cos(Delta) + F_yr + S phi_dot^2 sin(phi)``
* yaw:     ``-M_f k u r + G u phi_dot cos(phi) + G_f sin(eps) u delta_dot + l_f F_yf cos(Delta) - l_r F_yr``
* roll:    ``S g sin(phi) + K_s sin(delta) cos(phi) - (S + G) u r cos(phi) - G_f cos(eps) u delta_dot``
  (+ the low-speed feet/balance support)
* steer:   ``K_s (sin(phi) + sin(eps) sin(delta)) - (M_f e + G_f sin(eps)) u r cos(phi)
  + G_f cos(eps) u phi_dot - K delta_dot - eta F_yf + tau``
* tyres:   ``F_dot = (u_roll / sigma) (F_ss(alpha, gamma, mu) - F)`` with the saturating law of
  tyres.py, exact contact-point slip angles and a low-speed floor ``u_min`` on every denominator.
* longitudinal: ``M_eff u_dot = F_drive - F_brake - F_roll - 0.5 rho CdA u^2 - F_yf sin(Delta) + M_eff v_y r``.

``S = M_f j + M_r h``, ``G = i_fy/R_f + i_ry/R_r``, ``G_f = i_fy/R_f``, ``K_s = M_f e g - eta Z_f``.
Linearised at constant speed every row reduces to ``A0 + u A1`` of ptw_rt.model.sharp exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import descriptor
from ptw_rt.sim.tyres import TyreShape, lateral_force

# ----- full plant state ------------------------------------------------------
PHI, DELTA, VY, R, PHI_DOT, DELTA_DOT, FYF, FYR, U, PSI, XPOS, YPOS = range(12)
NX = 12
STATE_NAMES = ("phi", "delta", "v_y", "r", "phi_dot", "delta_dot", "F_yf", "F_yr", "u", "psi", "x", "y")

# ----- packed plant parameters (indices into the float64 vector given to numba) ---------
(
    P_M,
    P_MEFF,
    P_MFK,
    P_S,
    P_MFE,
    P_G,
    P_GF,
    P_KS,
    P_K,
    P_ETA,
    P_SEPS,
    P_CEPS,
    P_LF,
    P_LR,
    P_SIGF,
    P_SIGR,
    P_GRAV,
    P_CAF,
    P_CGF,
    P_CAR,
    P_CGR,
    P_FZF,
    P_FZR,
    P_SHAPE_A,
    P_SHAPE_G,
    P_MIN_MU,
    P_RHO_CDA,
    P_CRR,
    P_FDRIVE,
    P_PMAX,
    P_FBRAKE,
    P_UMIN,
    P_ULO,
    P_UHI,
    P_KFEET,
    P_DFEET,
    P_KLOW,
    P_USTOP,
    P_HOLD_U,
    P_DELTA_MAX,
) = range(40)
NP = 40

# ----- auxiliary outputs of the right-hand side --------------------------------
(
    AX_ALPHA_F,
    AX_ALPHA_R,
    AX_GAMMA_F,
    AX_GAMMA_R,
    AX_FSS_F,
    AX_FSS_R,
    AX_PEAK_F,
    AX_PEAK_R,
    AX_W,
    AX_FX,
) = range(10)
NAUX = 10


@dataclass(frozen=True)
class Longitudinal:
    """Longitudinal and low-speed constants of the plant (not in the vehicle file). SI units."""

    air_density: float = 1.2  # kg/m^3
    drag_area: float = 0.5  # CdA, m^2 (scooter + upright rider)
    rolling_resistance: float = 0.015  # Crr
    max_drive_force: float = 1500.0  # N at the rear contact (traction/gearing limit)
    max_power: float = 35000.0  # W at the wheel: drive force <= P / u
    max_brake_force: float = 3000.0  # N (both brakes, ~1 g)
    stop_speed: float = 0.3  # m/s: brake and rolling resistance fade to 0 below this (no reversing)


@dataclass(frozen=True)
class LowSpeed:
    """The documented low-speed model: below ``u_high`` the rider's feet/balance take over roll.

    ``w(u)`` = smoothstep from 0 at ``u_low`` to 1 at ``u_high``. The plant adds a roll support moment
    ``-(1-w)(K_feet sin(phi) + D_feet phi_dot)`` and extra tyre-force relaxation ``(1-w) k_low``; slip
    and relaxation use ``max(u_roll, u_min)``. At standstill the vehicle is held upright and still.
    """

    u_min: float = 1.0  # m/s, floor of slip denominators and of the relaxation speed
    u_low: float = 2.0  # m/s: full support below
    u_high: float = 4.0  # m/s: no support above (the free nonlinear plant)
    feet_stiffness: float = 6000.0  # N m/rad (> S g = 1681 N m/rad: stable on the feet)
    feet_damping: float = 1500.0  # N m s/rad
    low_speed_relaxation: float = 20.0  # 1/s added to u/sigma at standstill


@dataclass(frozen=True)
class PlantConfig:
    params: VehicleParameters
    longitudinal: Longitudinal = Longitudinal()
    low_speed: LowSpeed = LowSpeed()
    tyre: TyreShape = TyreShape()
    hold_speed: bool = False  # u_dot = 0 (tests against the constant-speed linear model)
    max_steer: float = 1.0  # rad, mechanical steering lock


def effective_mass(p: VehicleParameters) -> float:
    """Mass plus the wheels' spin inertia reduced to the contact line."""
    return p.mass + p.i_fy / p.r_f**2 + p.i_ry / p.r_r**2


def pack(cfg: PlantConfig) -> tuple[np.ndarray, np.ndarray]:
    """(packed parameter vector, inverse of the 4x4 mass block of E) for the jitted plant."""
    p, lon, ls, ty = cfg.params, cfg.longitudinal, cfg.low_speed, cfg.tyre
    v = np.zeros(NP)
    v[P_M] = p.mass
    v[P_MEFF] = effective_mass(p)
    v[P_MFK] = p.mfk
    v[P_S] = p.roll_moment
    v[P_MFE] = p.mfe
    v[P_G] = p.gyro_total
    v[P_GF] = p.gyro_front
    v[P_KS] = p.steer_stiffness
    v[P_K] = p.damping
    v[P_ETA] = p.trail
    v[P_SEPS] = math.sin(p.caster)
    v[P_CEPS] = math.cos(p.caster)
    v[P_LF] = p.l_f
    v[P_LR] = p.l_r
    v[P_SIGF] = p.sigma_f
    v[P_SIGR] = p.sigma_r
    v[P_GRAV] = p.g
    v[P_CAF] = p.c_af
    v[P_CGF] = p.c_gf
    v[P_CAR] = p.c_ar
    v[P_CGR] = p.c_gr
    v[P_FZF] = p.front_load
    v[P_FZR] = p.rear_load
    v[P_SHAPE_A] = ty.slip_shape
    v[P_SHAPE_G] = ty.camber_shape
    v[P_MIN_MU] = ty.min_mu
    v[P_RHO_CDA] = lon.air_density * lon.drag_area
    v[P_CRR] = lon.rolling_resistance
    v[P_FDRIVE] = lon.max_drive_force
    v[P_PMAX] = lon.max_power
    v[P_FBRAKE] = lon.max_brake_force
    v[P_UMIN] = ls.u_min
    v[P_ULO] = ls.u_low
    v[P_UHI] = ls.u_high
    v[P_KFEET] = ls.feet_stiffness
    v[P_DFEET] = ls.feet_damping
    v[P_KLOW] = ls.low_speed_relaxation
    v[P_USTOP] = lon.stop_speed
    v[P_HOLD_U] = 1.0 if cfg.hold_speed else 0.0
    v[P_DELTA_MAX] = cfg.max_steer
    E = descriptor(p).E
    m4inv = np.linalg.inv(E[2:6, 2:6])
    return v, np.ascontiguousarray(m4inv)


@njit(cache=True)
def support_weight(u, u_low, u_high):
    """0 below u_low (feet down), 1 above u_high (free riding), smoothstep between."""
    if u <= u_low:
        return 0.0
    if u >= u_high:
        return 1.0
    z = (u - u_low) / (u_high - u_low)
    return z * z * (3.0 - 2.0 * z)


@njit(cache=True)
def drive_limits(u, pp):
    """(max drive force, max brake force) available at speed u."""
    fmax = pp[P_FDRIVE]
    if u > 1.0 and pp[P_PMAX] / u < fmax:
        fmax = pp[P_PMAX] / u
    return fmax, pp[P_FBRAKE]


@njit(cache=True)
def rhs(x, tau, fx_cmd, mu, pp, m4inv, dx, aux):
    """dx = f(x, tau, F_x, mu); fills aux (slip, camber, steady-state forces, peaks, w, F_x applied)."""
    phi = x[PHI]
    delta = x[DELTA]
    vy = x[VY]
    r = x[R]
    p = x[PHI_DOT]
    dd = x[DELTA_DOT]
    fyf = x[FYF]
    fyr = x[FYR]
    u = x[U]
    if u < 0.0:
        u = 0.0
    sp = math.sin(phi)
    cp = math.cos(phi)
    if cp < 0.2:
        cp = 0.2  # beyond ~78 deg the vehicle is down anyway; keep the kinematics finite
    se = pp[P_SEPS]
    ce = pp[P_CEPS]
    g = pp[P_GRAV]
    umin = pp[P_UMIN]
    w = support_weight(u, pp[P_ULO], pp[P_UHI])

    # kinematic steer angle in the ground plane (delta cos(eps) when upright, grows as 1/cos(phi))
    dl = delta
    dmax = pp[P_DELTA_MAX]
    if dl > dmax:
        dl = dmax
    elif dl < -dmax:
        dl = -dmax
    big_delta = math.atan(math.tan(dl) * ce / cp)
    sD = math.sin(big_delta)
    cD = math.cos(big_delta)

    # front contact point: velocity in the wheel's own axes -> slip angle
    vlat_f = vy + pp[P_LF] * r - pp[P_ETA] * dd
    vlong_wf = u * cD + vlat_f * sD
    vlat_wf = -u * sD + vlat_f * cD
    roll_f = vlong_wf if vlong_wf > umin else umin
    alpha_f = math.atan(-vlat_wf / roll_f)
    gamma_f = phi + se * delta
    # rear contact point
    vlat_r = vy - pp[P_LR] * r
    roll_r = u if u > umin else umin
    alpha_r = math.atan(-vlat_r / roll_r)
    gamma_r = phi

    fss_f, peak_f = lateral_force(
        alpha_f, gamma_f, mu, pp[P_FZF], pp[P_CAF], pp[P_CGF], pp[P_SHAPE_A], pp[P_SHAPE_G], pp[P_MIN_MU]
    )
    fss_r, peak_r = lateral_force(
        alpha_r, gamma_r, mu, pp[P_FZR], pp[P_CAR], pp[P_CGR], pp[P_SHAPE_A], pp[P_SHAPE_G], pp[P_MIN_MU]
    )
    klow = (1.0 - w) * pp[P_KLOW]
    dx[FYF] = (roll_f / pp[P_SIGF] + klow) * (fss_f - fyf)
    dx[FYR] = (roll_r / pp[P_SIGR] + klow) * (fss_r - fyr)

    S = pp[P_S]
    G = pp[P_G]
    Gf = pp[P_GF]
    Ks = pp[P_KS]
    ur = u * r
    q_lat = -pp[P_M] * ur + fyf * cD + fyr + S * p * p * sp
    q_yaw = -pp[P_MFK] * ur + G * u * p * cp + Gf * se * u * dd + pp[P_LF] * fyf * cD - pp[P_LR] * fyr
    q_roll = S * g * sp + Ks * math.sin(dl) * cp - (S + G) * ur * cp - Gf * ce * u * dd
    q_roll -= (1.0 - w) * (pp[P_KFEET] * sp + pp[P_DFEET] * p)
    q_steer = (
        Ks * (sp + se * math.sin(dl))
        - (pp[P_MFE] + Gf * se) * ur * cp
        + Gf * ce * u * p
        - pp[P_K] * dd
        - pp[P_ETA] * fyf
        + tau
    )
    # steering lock: a stiff end stop beyond +-max_steer
    if delta > dmax:
        q_steer -= 2000.0 * (delta - dmax) + 50.0 * dd
    elif delta < -dmax:
        q_steer -= 2000.0 * (delta + dmax) + 50.0 * dd

    dx[PHI] = p
    dx[DELTA] = dd
    for i in range(4):
        dx[VY + i] = m4inv[i, 0] * q_lat + m4inv[i, 1] * q_yaw + m4inv[i, 2] * q_roll + m4inv[i, 3] * q_steer

    # longitudinal
    fdmax, fbmax = drive_limits(u, pp)
    fdrive = fx_cmd if fx_cmd > 0.0 else 0.0
    if fdrive > fdmax:
        fdrive = fdmax
    fbrake = -fx_cmd if fx_cmd < 0.0 else 0.0
    if fbrake > fbmax:
        fbrake = fbmax
    fade = u / pp[P_USTOP]
    if fade > 1.0:
        fade = 1.0
    resist = pp[P_RHO_CDA] * 0.5 * u * u + (pp[P_CRR] * pp[P_M] * g + fbrake) * fade
    if pp[P_HOLD_U] != 0.0:
        dx[U] = 0.0
    else:
        du = (fdrive - resist - fyf * sD) / pp[P_MEFF] + vy * r
        if x[U] <= 0.0 and du < 0.0:
            du = 0.0
        dx[U] = du
    psi = x[PSI]
    dx[PSI] = r
    dx[XPOS] = u * math.cos(psi) - vy * math.sin(psi)
    dx[YPOS] = u * math.sin(psi) + vy * math.cos(psi)

    aux[AX_ALPHA_F] = alpha_f
    aux[AX_ALPHA_R] = alpha_r
    aux[AX_GAMMA_F] = gamma_f
    aux[AX_GAMMA_R] = gamma_r
    aux[AX_FSS_F] = fss_f
    aux[AX_FSS_R] = fss_r
    aux[AX_PEAK_F] = peak_f
    aux[AX_PEAK_R] = peak_r
    aux[AX_W] = w
    aux[AX_FX] = fdrive - fbrake * fade


@njit(cache=True)
def rk4_step(x, tau, fx_cmd, mu, dt, pp, m4inv, k1, k2, k3, k4, xt, aux, aux_scratch):
    """One classical RK4 step in place (inputs held over the step).

    On return k1 holds f(x) and aux the auxiliary outputs, both at the START of the step.
    """
    rhs(x, tau, fx_cmd, mu, pp, m4inv, k1, aux)
    for i in range(NX):
        xt[i] = x[i] + 0.5 * dt * k1[i]
    rhs(xt, tau, fx_cmd, mu, pp, m4inv, k2, aux_scratch)
    for i in range(NX):
        xt[i] = x[i] + 0.5 * dt * k2[i]
    rhs(xt, tau, fx_cmd, mu, pp, m4inv, k3, aux_scratch)
    for i in range(NX):
        xt[i] = x[i] + dt * k3[i]
    rhs(xt, tau, fx_cmd, mu, pp, m4inv, k4, aux_scratch)
    for i in range(NX):
        x[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    if x[U] < 0.0:
        x[U] = 0.0


@njit(cache=True)
def _open_loop(x0, tau, fx, mu, dt, pp, m4inv, out):
    x = x0.copy()
    k1 = np.zeros(NX)
    k2 = np.zeros(NX)
    k3 = np.zeros(NX)
    k4 = np.zeros(NX)
    xt = np.zeros(NX)
    aux = np.zeros(NAUX)
    aux2 = np.zeros(NAUX)
    out[0, :] = x
    for k in range(tau.shape[0]):
        rk4_step(x, tau[k], fx[k], mu[k], dt, pp, m4inv, k1, k2, k3, k4, xt, aux, aux2)
        out[k + 1, :] = x


def simulate_open_loop(
    cfg: PlantConfig,
    x0: np.ndarray,
    tau: np.ndarray,
    dt: float = 1e-3,
    fx: np.ndarray | None = None,
    mu: np.ndarray | float = 1.0,
) -> np.ndarray:
    """Plant alone under given torque (and drive force, friction) sequences; returns states (n+1, 12)."""
    pp, m4inv = pack(cfg)
    tau = np.ascontiguousarray(tau, dtype=float)
    n = tau.shape[0]
    fx_a = np.zeros(n) if fx is None else np.ascontiguousarray(fx, dtype=float)
    mu_a = np.full(n, float(mu)) if np.isscalar(mu) else np.ascontiguousarray(mu, dtype=float)
    out = np.zeros((n + 1, NX))
    _open_loop(np.asarray(x0, dtype=float), tau, fx_a, mu_a, dt, pp, m4inv, out)
    return out


# ----- linearisation and steady turns of the nonlinear plant (used by the rider's design) -----------


@njit(cache=True)
def lateral_jacobian(x, tau, fx, mu, pp, m4inv, J):
    """J[:, :8] = d f_lat / d x_lat and J[:, 8] = d f_lat / d tau by central differences (8 x 9)."""
    dxp = np.zeros(NX)
    dxm = np.zeros(NX)
    aux = np.zeros(NAUX)
    xp = x.copy()
    for j in range(9):
        h = 1e-6 if j < 6 else (1e-3 if j < 8 else 1e-4)
        if j < 8:
            xp[j] = x[j] + h
            rhs(xp, tau, fx, mu, pp, m4inv, dxp, aux)
            xp[j] = x[j] - h
            rhs(xp, tau, fx, mu, pp, m4inv, dxm, aux)
            xp[j] = x[j]
        else:
            rhs(x, tau + h, fx, mu, pp, m4inv, dxp, aux)
            rhs(x, tau - h, fx, mu, pp, m4inv, dxm, aux)
        for i in range(8):
            J[i, j] = (dxp[i] - dxm[i]) / (2.0 * h)


@njit(cache=True)
def _trim_residual(y, phi, u, mu, pp, m4inv, x, dx, aux, res):
    # y = [delta, v_y, r, F_yf, F_yr, tau]
    x[PHI] = phi
    x[DELTA] = y[0]
    x[VY] = y[1]
    x[R] = y[2]
    x[PHI_DOT] = 0.0
    x[DELTA_DOT] = 0.0
    x[FYF] = y[3]
    x[FYR] = y[4]
    x[U] = u
    rhs(x, y[5], 0.0, mu, pp, m4inv, dx, aux)
    res[0] = dx[VY]
    res[1] = dx[R]
    res[2] = dx[PHI_DOT]
    res[3] = dx[DELTA_DOT]
    res[4] = dx[FYF] / (u / pp[P_SIGF])  # in N: F_ss - F
    res[5] = dx[FYR] / (u / pp[P_SIGR])


@njit(cache=True)
def solve_small(A, b, x):
    """x = A^-1 b by Gaussian elimination with partial pivoting (A, b overwritten); False if singular.

    Hand-written on purpose: numba's np.linalg needs scipy's LAPACK, which the runtime does not have.
    """
    n = b.shape[0]
    scale = 0.0
    for i in range(n):
        for j in range(n):
            if abs(A[i, j]) > scale:
                scale = abs(A[i, j])
    if not scale > 0.0:
        return False
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[p, k]):
                p = i
        if abs(A[p, k]) <= 1e-13 * scale:
            return False
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            b[k], b[p] = b[p], b[k]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= f * A[k, j]
            b[i] -= f * b[k]
    for i in range(n - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, n):
            acc -= A[i, j] * x[j]
        x[i] = acc / A[i, i]
    return True


@njit(cache=True)
def steady_turn_trim(phi, u, mu, pp, m4inv, y):
    """Newton solve of the plant's steady turn at roll phi and speed u; y (6) is the guess and the result.

    Returns True on convergence. y = [delta, v_y, r, F_yf, F_yr, tau]. Speed is held (u_dot ignored).
    """
    x = np.zeros(NX)
    dx = np.zeros(NX)
    aux = np.zeros(NAUX)
    res = np.zeros(6)
    res2 = np.zeros(6)
    Jm = np.zeros((6, 6))
    step = np.zeros(6)
    scale = np.array([1e-4, 1e-4, 1e-4, 1e-1, 1e-1, 1e-2])
    for _ in range(50):
        _trim_residual(y, phi, u, mu, pp, m4inv, x, dx, aux, res)
        if not np.all(np.isfinite(res)):
            return False
        # converged when every residual is tiny against the physical sizes involved
        if abs(res[0]) < 1e-9 and abs(res[1]) < 1e-9 and abs(res[2]) < 1e-9 and abs(res[3]) < 1e-9:
            if abs(res[4]) < 1e-6 and abs(res[5]) < 1e-6:
                return abs(y[0]) < 0.8
        for j in range(6):
            h = scale[j]
            y[j] += h
            _trim_residual(y, phi, u, mu, pp, m4inv, x, dx, aux, res2)
            y[j] -= h
            for i in range(6):
                Jm[i, j] = (res2[i] - res[i]) / h
        for i in range(6):
            res2[i] = -res[i]
        if not solve_small(Jm, res2, step):
            return False
        # damped Newton: never more than ~0.1 rad of steer per iteration
        m = 1.0
        if abs(step[0]) > 0.1:
            m = 0.1 / abs(step[0])
        for j in range(6):
            y[j] += m * step[j]
    return False
