"""The simulated rider: steering torque to follow the path, drive/brake force to follow the speed plan.

Lateral: one LQR on the path-augmented lateral model, ``z = [x (8), tau, e_y, e_psi, int e_y]``
(``x`` the model's states, ``tau`` the torque behind the rider's neuromuscular lag
``tau_dot = (tau_cmd - tau) / T_nm``, ``e_y`` the lateral offset from the line, ``e_psi`` the heading
error, ``e_y' = v_y + u e_psi``, ``e_psi' = r - u kappa``), used around the steady turn of the local
path curvature and completed by Sharp's optimal preview of the curvature ahead:

    tau_cmd = tau_ss - K (z - z_ss(kappa)) + sum_j P_j kappa_dot(t + (j + 1/2) dt_p)

Gains are designed with numpy only at start-up (stable invariant subspace of the Hamiltonian for the
Riccati equation, a scaling-and-squaring exponential for the preview) on a (speed, |roll|) grid: at
each node the nonlinear plant's own steady turn is trimmed (Newton) and the plant is linearised there
(central differences of the jitted right-hand side). At zero roll this is exactly the linear model
``state_space(p, u)`` (``design_schedule`` keeps that speed-only variant for reference and tests);
at lean it follows how the saturating tyres and the lean-dependent couplings change the weave.
The feed-forward roll for the local curvature comes from inverting the trims (``roll_ref`` in the truth;
for a coordinated turn it is close to ``atan(u^2 kappa / g)`` with the wheels' gyroscopic share).

Longitudinal: feed-forward (``M_eff a_ref`` + drag + rolling resistance) plus PI on the speed error,
saturated to the plant's drive/brake limits, with anti-windup; brake held at standstill.

Low speed: the rider's torque blends from the LQR to centring the bars over the plant's support range
(``LowSpeed``); on the feet he does not steer back to the line but sets off from where he stopped and
merges back onto it (``merge_time``). Imperfection: coloured torque noise and a slow wander of the line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import DELTA_DOT, PHI, PHI_DOT, VY, R, state_space

NX_PLANT = 12


@dataclass(frozen=True)
class RiderConfig:
    # LQR weights (1 / acceptable excursion^2) on the path-augmented lateral model
    path_error_weight: float = 1.0 / 0.1**2  # lateral offset from the line [m]
    heading_error_weight: float = 1.0 / 0.05**2  # [rad]
    path_integral_weight: float = 1.0 / 1.0**2  # integral of the lateral offset [m s]
    roll_weight: float = 0.0  # roll itself is free: the path decides it
    roll_rate_weight: float = 1.0 / 0.3**2  # [rad/s]
    steer_rate_weight: float = 1.0 / 1.0**2  # [rad/s]
    torque_weight: float = 1.0 / 12.0**2  # R on the commanded torque [N m]
    neuromuscular_lag: float = 0.04  # s
    max_torque: float = 120.0  # N m, rider strength
    # speed grid of the gain schedule [m/s] (linear design) and the (speed, lean) grid actually ridden
    grid_min: float = 2.5
    grid_max: float = 40.0
    grid_step: float = 0.5
    lean_grid_speed_step: float = 1.0  # m/s
    lean_grid_step_deg: float = 7.5
    lean_grid_max_deg: float = 45.0
    min_turn_radius: float = 4.0  # m: no steady turn is trimmed tighter than this
    # feed-forward: steady turn of the local curvature + optimal preview of its future changes
    preview_horizon: float = 2.5  # s
    preview_step: float = 0.05  # s
    max_roll: float = math.radians(48.0)  # the rider never plans more lean than this
    # speed loop
    speed_kp: float = 400.0  # N per m/s
    speed_ki: float = 80.0  # N per m
    # pulling away: the rider starts from where he stopped and merges back onto the line
    merge_time: float = 3.0  # s
    # low speed: bar centring
    centre_stiffness: float = 250.0  # N m/rad (must beat the wheel flop K_s sin(eps) = 69 N m/rad)
    centre_damping: float = 15.0  # N m s/rad
    # imperfection
    torque_noise: float = 0.5  # N m rms (coloured)
    torque_noise_time: float = 0.2  # s correlation time
    line_wander: float = 0.15  # m rms of the followed line's slow offset
    line_wander_time: float = 4.0  # s


# augmented state: [x (8), tau, e_y, e_psi, int(e_y)]
Z_TAU, Z_EY, Z_EPSI, Z_INT = 8, 9, 10, 11
N_AUG = 12


def care(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Continuous algebraic Riccati equation by the stable invariant subspace of the Hamiltonian (numpy)."""
    n = A.shape[0]
    Rinv = np.linalg.inv(R)
    H = np.block([[A, -B @ Rinv @ B.T], [-Q, -A.T]])
    w, V = np.linalg.eig(H)
    stable = np.argsort(w.real)[:n]
    if not np.all(w.real[stable] < 0):
        raise ArithmeticError("Hamiltonian has eigenvalues on the imaginary axis (not stabilisable)")
    U1, U2 = V[:n, stable], V[n:, stable]
    P = np.real(U2 @ np.linalg.inv(U1))
    return 0.5 * (P + P.T)


def augmented(p: VehicleParameters, u: float, lag: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear model + torque lag + path errors: e_y' = v_y + u e_psi, e_psi' = r (- u kappa), int' = e_y."""
    A, B = state_space(p, u)
    Aa = np.zeros((N_AUG, N_AUG))
    Aa[:8, :8] = A
    Aa[:8, Z_TAU] = B
    Aa[Z_TAU, Z_TAU] = -1.0 / lag
    Aa[Z_EY, VY] = 1.0
    Aa[Z_EY, Z_EPSI] = u
    Aa[Z_EPSI, R] = 1.0
    Aa[Z_INT, Z_EY] = 1.0
    Ba = np.zeros((N_AUG, 1))
    Ba[Z_TAU, 0] = 1.0 / lag
    return Aa, Ba


def steady_turn(p: VehicleParameters, u: float) -> tuple[np.ndarray, float]:
    """Linear steady turn per unit roll: (x_ss with phi = 1, tau_ss)."""
    A, B = state_space(p, u)
    M = np.column_stack([A[:, 1:], B])
    sol = np.linalg.solve(M, -A[:, PHI])
    x = np.concatenate([[1.0], sol[:7]])
    return x, float(sol[7])


def expm(A: np.ndarray) -> np.ndarray:
    """Matrix exponential (scaling and squaring, Taylor order 16), numpy only."""
    norm = np.linalg.norm(A, 1)
    s = max(0, int(math.ceil(math.log2(norm))) + 1) if norm > 0 else 0
    As = A / 2.0**s
    E = np.eye(A.shape[0])
    term = np.eye(A.shape[0])
    for k in range(1, 17):
        term = term @ As / k
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


@dataclass(frozen=True)
class RiderSchedule:
    """Gains on the speed grid. Control law (z = [x, tau, e_y, e_psi, int e_y], kappa0 = curvature here):

    tau_cmd = N_tau kappa0 - K (z - N kappa0) + sum_j preview[j] * kappa_dot(t + (j + 1/2) dt_preview)
    """

    speeds: np.ndarray  # (n,)
    gains: np.ndarray  # (n, 12) K
    steady: np.ndarray  # (n, 12) N: steady turn per unit path curvature (z_ss = N kappa)
    preview: np.ndarray  # (n, J) optimal preview gains on the future rate of change of curvature
    preview_dt: float
    closed_loop_max_real: np.ndarray  # (n,) slowest closed-loop pole real part on the linear model


def weights(cfg: RiderConfig) -> tuple[np.ndarray, np.ndarray]:
    Q = np.zeros((N_AUG, N_AUG))
    Q[PHI, PHI] = cfg.roll_weight
    Q[PHI_DOT, PHI_DOT] = cfg.roll_rate_weight
    Q[DELTA_DOT, DELTA_DOT] = cfg.steer_rate_weight
    Q[Z_EY, Z_EY] = cfg.path_error_weight
    Q[Z_EPSI, Z_EPSI] = cfg.heading_error_weight
    Q[Z_INT, Z_INT] = cfg.path_integral_weight
    return Q, np.array([[cfg.torque_weight]])


def steady_per_curvature(p: VehicleParameters, u: float) -> np.ndarray:
    """z_ss per unit path curvature on the augmented state (yaw rate u kappa, on the line)."""
    x1, t1 = steady_turn(p, u)
    scale = u / x1[R]
    N = np.zeros(N_AUG)
    N[:8] = x1 * scale
    N[Z_TAU] = t1 * scale
    N[Z_EPSI] = -N[VY] / u  # the reference point's side slip: heading differs from the path tangent
    return N


def design_schedule(p: VehicleParameters, cfg: RiderConfig = RiderConfig()) -> RiderSchedule:
    """LQR gains, steady turn and optimal preview gains on the speed grid (numpy only).

    Error coordinates around the steady turn of the local curvature, zt = z - N kappa(t), obey
    zt' = A_cl zt + B v - N kappa'(t); the optimal use of the known future kappa' (Sharp's optimal
    preview) is v(t) = R^-1 B' int_0^inf exp(A_cl' s) P N kappa'(t + s) ds, discretised here.
    """
    n = int(round((cfg.grid_max - cfg.grid_min) / cfg.grid_step)) + 1
    speeds = np.linspace(cfg.grid_min, cfg.grid_max, n)
    Q, R_ = weights(cfg)
    Rinv = np.linalg.inv(R_)
    n_prev = max(1, int(round(cfg.preview_horizon / cfg.preview_step)))
    dtp = cfg.preview_step
    gains = np.zeros((n, N_AUG))
    steady = np.zeros((n, N_AUG))
    preview = np.zeros((n, n_prev))
    worst = np.zeros(n)
    for i, u in enumerate(speeds):
        Aa, Ba = augmented(p, float(u), cfg.neuromuscular_lag)
        P = care(Aa, Ba, Q, R_)
        K = (Rinv @ Ba.T @ P)[0]
        gains[i] = K
        Acl = Aa - Ba @ K[None, :]
        worst[i] = np.max(np.linalg.eigvals(Acl).real)
        N = steady_per_curvature(p, float(u))
        steady[i] = N
        step = expm(Acl.T * dtp)
        cur = expm(Acl.T * (0.5 * dtp))
        row = (Rinv @ Ba.T)[0]
        PN = P @ N
        for j in range(n_prev):
            preview[i, j] = row @ (cur @ PN) * dtp
            cur = step @ cur
    return RiderSchedule(speeds, gains, steady, preview, dtp, worst)


# ----- the design actually ridden: LQR on the nonlinear plant linearised at steady turns ------------


@dataclass(frozen=True)
class LeanSchedule:
    """Gains and trims on a (speed, |roll|) grid, linearising the plant at its own steady turns.

    ``trims[i, j]`` = [x (8), tau, e_psi] of the steady turn at speeds[i], leans[j] (odd in roll);
    ``gains[i, j]`` the LQR gain, ``preview[i, j]`` the optimal preview gains on kappa_dot,
    ``feasible[i, j]`` False where no steady turn exists (tyres saturated, or radius < 4 m): there the
    nearest feasible lean's gains are used and the trims are extrapolated.
    """

    speeds: np.ndarray
    leans: np.ndarray
    gains: np.ndarray  # (nu, nl, 12)
    trims: np.ndarray  # (nu, nl, 10)
    preview: np.ndarray  # (nu, nl, J)
    feasible: np.ndarray  # (nu, nl) bool
    preview_dt: float
    closed_loop_max_real: np.ndarray  # (nu, nl)


def _lqr_and_preview(Aa, Ba, Q, R_, N, n_prev, dtp):
    Rinv = np.linalg.inv(R_)
    P = care(Aa, Ba, Q, R_)
    K = (Rinv @ Ba.T @ P)[0]
    Acl = Aa - Ba @ K[None, :]
    step = expm(Acl.T * dtp)
    cur = expm(Acl.T * (0.5 * dtp))
    row = (Rinv @ Ba.T)[0]
    PN = P @ N
    prev = np.zeros(n_prev)
    for j in range(n_prev):
        prev[j] = row @ (cur @ PN) * dtp
        cur = step @ cur
    return K, prev, float(np.max(np.linalg.eigvals(Acl).real))


_LEAN_CACHE: dict = {}


def _trim(phi, u, mu, pp, m4, y) -> bool:
    from ptw_rt.sim.plant import steady_turn_trim

    return bool(steady_turn_trim(phi, u, mu, pp, m4, y))


def design_lean_schedule(plant_cfg, cfg: RiderConfig = RiderConfig(), mu: float = 1.0) -> LeanSchedule:
    """The rider's gains: at each (speed, lean) the plant's steady turn is trimmed (Newton), the plant is
    linearised there (central differences of the jitted right-hand side) and the path-augmented LQR and
    its optimal preview are solved (numpy only). At zero lean this is exactly ``design_schedule`` on the
    linear model. Results are cached per (plant, rider, mu).
    """
    from ptw_rt.sim.plant import PlantConfig, lateral_jacobian, pack

    key = (plant_cfg, cfg, float(mu))
    hit = _LEAN_CACHE.get(key)
    if hit is not None:
        return hit
    assert isinstance(plant_cfg, PlantConfig)
    # the free plant: speed held, no low-speed support (the rider rides it above the support range)
    free = replace(plant_cfg.low_speed, u_low=0.0, u_high=1e-6)
    hold = PlantConfig(plant_cfg.params, plant_cfg.longitudinal, free, plant_cfg.tyre, True)
    pp, m4 = pack(hold)
    nu = int(round((cfg.grid_max - cfg.grid_min) / cfg.lean_grid_speed_step)) + 1
    speeds = np.linspace(cfg.grid_min, cfg.grid_max, nu)
    leans = np.radians(np.arange(0.0, cfg.lean_grid_max_deg + 1e-9, cfg.lean_grid_step_deg))
    nl = len(leans)
    n_prev = max(1, int(round(cfg.preview_horizon / cfg.preview_step)))
    Q, R_ = weights(cfg)
    gains = np.zeros((nu, nl, N_AUG))
    trims = np.zeros((nu, nl, 10))
    preview = np.zeros((nu, nl, n_prev))
    feasible = np.zeros((nu, nl), dtype=bool)
    worst = np.zeros((nu, nl))
    J = np.zeros((8, 9))
    dphi = math.radians(0.25)
    for i, u in enumerate(speeds):
        u = float(u)
        y = np.zeros(6)
        for j, phi in enumerate(leans):
            phi = float(phi)
            ok = math.tan(phi) <= u * u / (cfg.min_turn_radius * plant_cfg.params.g) + 1e-12
            ok = ok and _trim(phi, u, mu, pp, m4, y)
            if ok:
                # neighbouring trims give the steady turn's sensitivity to curvature (kappa = r / u)
                ya, yb = y.copy(), y.copy()
                ok = _trim(phi + dphi, u, mu, pp, m4, ya)
                ok = ok and _trim(max(phi - dphi, -dphi), u, mu, pp, m4, yb)
            if not ok:
                break
            feasible[i, j] = True
            x = np.zeros(NX_PLANT)
            x[PHI], x[1], x[VY], x[R], x[6], x[7], x[8] = phi, y[0], y[1], y[2], y[3], y[4], u
            trims[i, j, :8] = x[:8]
            trims[i, j, 8] = y[5]
            trims[i, j, 9] = -math.atan2(y[1], u)
            lateral_jacobian(x, y[5], 0.0, mu, pp, m4, J)
            Aa, Ba = augmented(plant_cfg.params, u, cfg.neuromuscular_lag)
            Aa[:8, :8] = J[:, :8]
            Aa[:8, Z_TAU] = J[:, 8]
            za = np.concatenate([[phi + dphi], ya[:2], ya[2:3], [0.0, 0.0], ya[3:5], ya[5:6]])
            zb = np.concatenate([[max(phi - dphi, -dphi)], yb[:2], yb[2:3], [0.0, 0.0], yb[3:5], yb[5:6]])
            N = np.zeros(N_AUG)
            N[:9] = (za - zb) / ((ya[2] - yb[2]) / u)
            N[Z_EPSI] = -(math.atan2(ya[1], u) - math.atan2(yb[1], u)) / ((ya[2] - yb[2]) / u)
            K, prev, w = _lqr_and_preview(Aa, Ba, Q, R_, N, n_prev, cfg.preview_step)
            gains[i, j], preview[i, j], worst[i, j] = K, prev, w
        # infeasible leans: nearest feasible gains; trims extrapolated linearly (keeps roll -> yaw monotonic)
        nf = int(feasible[i].sum())
        if nf < 2:
            # no lean can be held on this road at this speed (e.g. mu ~ 0.1): fall back to the linear
            # steady turn so the rider still has a (doomed but well-defined) plan
            x1, t1 = steady_turn(plant_cfg.params, u)
            for j in range(1, nl):
                tl = math.tan(float(leans[j]))
                trims[i, j, :8] = x1 * tl
                trims[i, j, PHI] = leans[j]
                trims[i, j, 8] = t1 * tl
                trims[i, j, 9] = -x1[VY] * tl / u
            nf = 1
        for j in range(nf, nl):
            gains[i, j], preview[i, j], worst[i, j] = gains[i, nf - 1], preview[i, nf - 1], worst[i, nf - 1]
            if not feasible[i, 1]:
                continue
            trims[i, j] = trims[i, j - 1] + (trims[i, j - 1] - trims[i, j - 2])
    sch = LeanSchedule(speeds, leans, gains, trims, preview, feasible, cfg.preview_step, worst)
    if len(_LEAN_CACHE) > 16:
        _LEAN_CACHE.clear()
    _LEAN_CACHE[key] = sch
    return sch


# ----- packed rider parameters for the jitted loop ---------------------------
(
    RP_LAG,
    RP_TMAX,
    RP_GMIN,
    RP_GSTEP,
    RP_PREVIEW_DT,
    RP_MAX_ROLL,
    RP_KP_V,
    RP_KI_V,
    RP_KC,
    RP_DC,
    RP_GYRO_FACTOR,
    RP_MEFF,
    RP_CRR_W,
    RP_RHO_CDA,
    RP_LEAN_STEP,
    RP_MERGE,
) = range(16)
NRP = 16

# controller state layout
CS_TAU, CS_INT_Y, CS_INT_V, CS_PHI_FF, CS_TAU_FF, CS_IDX, CS_FX, CS_EY, CS_EPSI, CS_EY_OFF, CS_EPSI_OFF = range(11)
NCS = 11


def pack_rider(cfg: RiderConfig, p: VehicleParameters, m_eff: float, rho_cda: float, crr: float) -> np.ndarray:
    v = np.zeros(NRP)
    v[RP_LAG] = cfg.neuromuscular_lag
    v[RP_TMAX] = cfg.max_torque
    v[RP_GMIN] = cfg.grid_min
    v[RP_GSTEP] = cfg.lean_grid_speed_step
    v[RP_LEAN_STEP] = math.radians(cfg.lean_grid_step_deg)
    v[RP_MERGE] = cfg.merge_time
    v[RP_PREVIEW_DT] = cfg.preview_step
    v[RP_MAX_ROLL] = cfg.max_roll
    v[RP_KP_V] = cfg.speed_kp
    v[RP_KI_V] = cfg.speed_ki
    v[RP_KC] = cfg.centre_stiffness
    v[RP_DC] = cfg.centre_damping
    v[RP_GYRO_FACTOR] = 1.0 + p.gyro_total / p.roll_moment
    v[RP_MEFF] = m_eff
    v[RP_CRR_W] = crr * p.mass * p.g
    v[RP_RHO_CDA] = rho_cda
    return v


def ou_noise(rng: np.random.Generator, n: int, dt: float, rms: float, corr_time: float) -> np.ndarray:
    """Ornstein-Uhlenbeck (first-order coloured) noise with stationary rms, sampled every dt."""
    a = math.exp(-dt / corr_time)
    e = rng.standard_normal(n) * rms * math.sqrt(1.0 - a * a)
    out = np.empty(n)
    x = rng.standard_normal() * rms
    for i in range(n):
        x = a * x + e[i]
        out[i] = x
    return out


@njit(cache=True)
def _interp2(table, gu, gl, out):
    """Bilinear interpolation of table[i, j, :] at fractional indices (gu, gl), clamped to the grid."""
    nu = table.shape[0]
    nl = table.shape[1]
    if gu < 0.0:
        gu = 0.0
    if gu > nu - 1:
        gu = nu - 1.0
    if gl < 0.0:
        gl = 0.0
    if gl > nl - 1:
        gl = nl - 1.0
    i = min(int(gu), nu - 2) if nu > 1 else 0
    j = min(int(gl), nl - 2) if nl > 1 else 0
    a = gu - i
    b = gl - j
    for k in range(table.shape[2]):
        if nu > 1 and nl > 1:
            out[k] = (1.0 - a) * ((1.0 - b) * table[i, j, k] + b * table[i, j + 1, k]) + a * (
                (1.0 - b) * table[i + 1, j, k] + b * table[i + 1, j + 1, k]
            )
        else:
            out[k] = table[i, j, k]


@njit(cache=True)
def trim_lean(trims, gu, yaw_rate, lean_step):
    """|roll| of the steady turn with |yaw rate| = yaw_rate at fractional speed index gu (trim table inverse)."""
    nu = trims.shape[0]
    nl = trims.shape[1]
    if gu < 0.0:
        gu = 0.0
    if gu > nu - 1:
        gu = nu - 1.0
    i = min(int(gu), nu - 2)
    a = gu - i
    prev = 0.0
    for j in range(1, nl):
        rj = (1.0 - a) * trims[i, j, 3] + a * trims[i + 1, j, 3]
        if yaw_rate <= rj or j == nl - 1:
            d = rj - prev
            f = (yaw_rate - prev) / d if d > 0.0 else 0.0
            if f > 1.0:
                f = 1.0
            return (j - 1 + f) * lean_step
        prev = rj
    return 0.0


@njit(cache=True)
def path_errors(xp, yp, psip, idx0, X, Y):
    """Projection of (X, Y) on the path, searched locally from sample idx0.

    Returns (nearest sample, fractional sample index of the projection, lateral error [m, right of
    the path > 0], path heading there). Heading and position are interpolated between samples, so the
    errors are continuous as the vehicle passes from one sample to the next.
    """
    n = xp.shape[0]
    i = idx0
    if i < 0:
        i = 0
    if i > n - 1:
        i = n - 1
    best = (xp[i] - X) ** 2 + (yp[i] - Y) ** 2
    # walk forward, then backward, while the distance decreases
    while i + 1 < n:
        dn = (xp[i + 1] - X) ** 2 + (yp[i + 1] - Y) ** 2
        if dn <= best:
            best = dn
            i += 1
        else:
            break
    while i - 1 >= 0:
        dp = (xp[i - 1] - X) ** 2 + (yp[i - 1] - Y) ** 2
        if dp < best:
            best = dp
            i -= 1
        else:
            break
    # segment [a, a+1] holding the projection
    along = (X - xp[i]) * math.cos(psip[i]) + (Y - yp[i]) * math.sin(psip[i])
    if along >= 0.0:
        a = i if i < n - 1 else n - 2
    else:
        a = i - 1 if i > 0 else 0
    dx = xp[a + 1] - xp[a]
    dy = yp[a + 1] - yp[a]
    seg2 = dx * dx + dy * dy
    f = ((X - xp[a]) * dx + (Y - yp[a]) * dy) / seg2 if seg2 > 0.0 else 0.0
    if a == n - 2 and f > 1.0:
        fe = f  # beyond the end: extrapolate along the last segment
    elif f < 0.0:
        fe = 0.0 if a > 0 else f
    elif f > 1.0:
        fe = 1.0
    else:
        fe = f
    fh = fe if fe < 1.0 else 1.0
    if fh < 0.0:
        fh = 0.0
    h = psip[a] + fh * (psip[a + 1] - psip[a])
    px = xp[a] + fe * dx
    py = yp[a] + fe * dy
    ey = -(X - px) * math.sin(h) + (Y - py) * math.cos(h)
    return i, a + fe, ey, h


@njit(cache=True)
def path_value(arr, s_idx):
    """Linear interpolation of a path array at a fractional sample index (clamped to the ends)."""
    n = arr.shape[0]
    if s_idx <= 0.0:
        return arr[0]
    if s_idx >= n - 1:
        return arr[n - 1]
    k = int(s_idx)
    f = s_idx - k
    return (1.0 - f) * arr[k] + f * arr[k + 1]
