"""Seed 001's two comparison methods for tyre stiffness identification. EVALUATION ONLY.

Offline batch least-squares estimators of ``Theta = [C_af, C_gf, C_ar, C_gr]`` (absolute
stiffness, the order of ``VehicleParameters.nominal_stiffness``), used to compare the
product's adaptive observer against the "direct method" (seed 001 eq. 11-12) and the
"dynamic inversion" (eq. 13). They are never run in the daemon.

All signals are 1-D arrays (or ``N x k`` for ``y`` / ``x_hat``) sampled at a fixed ``dt``;
``use`` is a boolean mask selecting the samples that enter the fit (e.g. the second half
of a ride above 20 km/h). Derivatives are central differences (``np.gradient``); the first
and last samples (whose one-sided differences are less accurate) and samples below
``U_MIN`` are dropped from the fit.

Tyre law (the one ``ptw_rt.model.sharp`` implements, ``regressor`` / ``descriptor``)::

    (sigma/u) F_y' + F_y = -C_a alpha + C_g gamma
    alpha_f = (v_y + l_f r - trail delta_dot) / u - cos(caster) delta,   gamma_f = phi + sin(caster) delta
    alpha_r = (v_y - l_r r) / u,                                          gamma_r = phi

Direct method (eq. 11-12)
-------------------------
The vehicle is reduced to one body: ``M a_y = F_yf + F_yr`` and ``I_z r' = a_f F_yf - a_r F_yr``,
with ``r'`` from central differences (the method's known weakness: ``F_y'`` in the relaxation
rows then needs the second derivative of ``r``). ``a_y`` is the lateral acceleration of the
centre of mass in the road plane. ``M``, ``I_z``, ``a_f``, ``a_r`` are the CoM-referred constants
of ``force_observers.lateral_yaw_constants``: ``I_z = e44 - M x_G^2`` is the yaw inertia of the
whole vehicle (both frames, steer at zero) about its CoM, ``a_f = l_f - x_G``, ``a_r = l_r + x_G``
(the seed writes ``l_f``, ``l_r``; ``x_G`` is 2 cm for the scooter). The one-body yaw balance
ignores the gyroscopic moment ``(i_fy/R_f + i_ry/R_r) u phi_dot`` and the roll/steer inertia
couplings (see ``force_observers``); that modelling error is part of the method. A caller that
can compute some of it passes it as ``yaw_moment`` (``I_z r' = a_f F_yf - a_r F_yr + yaw_moment``).

The four rows of eq. 12 are stacked. Rows 1-2 as printed use the static tyre law (no relaxation),
which contradicts rows 3-4 by the relaxation lag ``sigma/u``; here their right-hand sides carry
the same relaxation terms, so they are exactly ``row3 + row4`` and ``a_f row3 - a_r row4``
(the arms of the force split): a reweighting of rows 3-4, no contradictory information.

Dynamic inversion (eq. 13)
--------------------------
``x' = A(u) x + B tau + D chi(x, u) Theta`` with ``A(u)`` the LPV matrix built with zero stiffness
(``lpv_model(p.scaled(stiffness=0))``), so that ``D chi Theta`` carries the whole stiffness and
``Theta`` is absolute: the tyre rows read ``F' = -(u/sigma) F + chi Theta`` exactly (``D = [0; I2]``).
With the outputs ``y = C x = [delta, r, phi_dot, delta_dot]`` eq. 13 cannot be inverted as
printed: ``Theta`` enters only the tyre-force rows, which are not measured, so ``C D = 0`` and the
seed's own feasibility condition ``rank(CD) = rank(D)`` fails (``y'`` carries no information on
``Theta``). The inversion is therefore taken at the outputs' relative degree with respect to
``Theta``, which is 2::

    y'' = C [A1 u' x + A(u) (A(u) x + B tau) + B tau'] + C A(u) D chi(x, u) Theta

with ``y''`` (and ``u'``, ``tau'``) by central differences of the samples and ``x = x_hat``. Four rows per
sample, solved by least squares for ``Theta``; ``rank(C A D) = 2 = rank(D)``.

Identifiability
---------------
A stiffness is returned as NaN when the data cannot determine it: when the RMS of its angle
(``alpha`` or ``gamma`` of its axle over the fit samples) is below ``min_angle`` (no excitation,
e.g. a straight line), or when it lies in a direction of the column-normalised regressor whose
singular value is below ``rcond`` times the largest (collinear slip and camber, e.g. steady
cornering). The other entries are solved on the remaining well-conditioned subspace.
"""

from __future__ import annotations

import math

import numpy as np

from ptw_rt.core.force_observers import lateral_yaw_constants
from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import DELTA, DELTA_DOT, PHI, PHI_DOT, VY, R, lpv_model, regressor

U_MIN = 1.0  # m/s: below this the slip angles (divided by u) are meaningless
MIN_ANGLE = 1e-4  # rad: RMS slip/camber angle below which a stiffness is declared unidentifiable
RCOND = 1e-4  # relative singular value of the column-normalised regressor below which a direction is dropped
NULL_COMPONENT = 0.1  # an entry whose weight in a dropped direction exceeds this is unidentifiable
OUTPUT_STATES = (DELTA, R, PHI_DOT, DELTA_DOT)  # y = C x (seed 001 eq. 10 without a_y)

# report key -> index in Theta (sharp.THETA_NAMES order)
ERROR_KEYS = {"front_cornering": 0, "rear_cornering": 2, "front_camber": 1, "rear_camber": 3}


def _fit_mask(use: np.ndarray, u: np.ndarray, n: int) -> np.ndarray:
    use = np.asarray(use, dtype=bool)
    if use.shape != (n,):
        raise ValueError(f"use must be a boolean array of length {n}, got shape {use.shape}")
    m = use & np.isfinite(u) & (u > U_MIN)
    m[:1] = False
    m[-1:] = False
    return m


def _angles(p: VehicleParameters, u, delta, v_y, r, phi, delta_dot) -> np.ndarray:
    """``N x 4`` array ``[alpha_f, gamma_f, alpha_r, gamma_r]`` (rad), from ``sharp.regressor``'s definitions."""
    s, c = math.sin(p.caster), math.cos(p.caster)
    alpha_f = (v_y + p.l_f * r - p.trail * delta_dot) / u - c * delta
    gamma_f = phi + s * delta
    alpha_r = (v_y - p.l_r * r) / u
    gamma_r = phi
    return np.column_stack([alpha_f, gamma_f, alpha_r, gamma_r])


def _solve(phi_mat: np.ndarray, rhs: np.ndarray, angle_rms: np.ndarray, min_angle: float, rcond: float) -> np.ndarray:
    """Least squares ``phi_mat theta = rhs`` with NaN for the entries the data cannot determine."""
    theta = np.full(4, np.nan)
    ok = np.isfinite(angle_rms) & (angle_rms > min_angle)
    rows = np.all(np.isfinite(phi_mat), axis=1) & np.isfinite(rhs)
    if not ok.any() or not rows.any():
        return theta
    cols = np.flatnonzero(ok)
    X = phi_mat[np.ix_(rows, cols)]
    b = rhs[rows]
    norms = np.linalg.norm(X, axis=0)
    if np.any(norms == 0.0):
        keep = norms > 0.0
        cols, X, norms = cols[keep], X[:, keep], norms[keep]
        if cols.size == 0:
            return theta
    Xn = X / norms
    U, s, Vt = np.linalg.svd(Xn, full_matrices=False)
    good = s > rcond * s[0]
    bad_dirs = Vt[~good]
    identifiable = np.ones(cols.size, dtype=bool)
    if bad_dirs.size:
        identifiable = np.max(np.abs(bad_dirs), axis=0) <= NULL_COMPONENT
    # truncated-SVD solution: the dropped directions get no weight
    coef = Vt[good].T @ ((U[:, good].T @ b) / s[good])
    est = coef / norms
    theta[cols[identifiable]] = est[identifiable]
    return theta


def direct_method(
    p: VehicleParameters,
    dt: float,
    u,
    delta,
    v_y,
    r,
    phi,
    delta_dot,
    a_y,
    use,
    *,
    yaw_moment=None,
    min_angle: float = MIN_ANGLE,
    rcond: float = RCOND,
) -> np.ndarray:
    """Seed 001 eq. 11-12: one-body forces, then the stacked tyre rows; returns ``[C_af, C_gf, C_ar, C_gr]``."""
    sig = [np.asarray(v, dtype=float) for v in (u, delta, v_y, r, phi, delta_dot, a_y)]
    n = sig[3].size
    u, delta, v_y, r, phi, delta_dot, a_y = (np.broadcast_to(v, (n,)).astype(float) for v in sig)
    M, I_z, a_f, a_r = lateral_yaw_constants(p)
    r_dot = np.gradient(r, dt)
    mz = I_z * r_dot - (0.0 if yaw_moment is None else np.broadcast_to(np.asarray(yaw_moment, float), (n,)))
    S = M * a_y
    F_f = (a_r * S + mz) / (a_f + a_r)
    F_r = (a_f * S - mz) / (a_f + a_r)
    m = _fit_mask(use, u, n)
    if not m.any():
        return np.full(4, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        ang = _angles(p, u, delta, v_y, r, phi, delta_dot)
        rhs_f = p.sigma_f / u * np.gradient(F_f, dt) + F_f
        rhs_r = p.sigma_r / u * np.gradient(F_r, dt) + F_r
    al_f, ga_f, al_r, ga_r = (ang[m, i] for i in range(4))
    z = np.zeros_like(al_f)
    front = np.column_stack([-al_f, ga_f, z, z])
    rear = np.column_stack([z, z, -al_r, ga_r])
    rf, rr = rhs_f[m], rhs_r[m]
    phi_mat = np.vstack([front + rear, a_f * front - a_r * rear, front, rear])
    rhs = np.concatenate([rf + rr, a_f * rf - a_r * rr, rf, rr])
    angle_rms = np.sqrt(np.mean(ang[m] ** 2, axis=0))
    return _solve(phi_mat, rhs, angle_rms, min_angle, rcond)


def dynamic_inversion(
    p: VehicleParameters,
    dt: float,
    u,
    y,
    x_hat,
    tau,
    use,
    *,
    min_angle: float = MIN_ANGLE,
    rcond: float = RCOND,
) -> np.ndarray:
    """Seed 001 eq. 13 at the outputs' relative degree (module docstring); returns ``[C_af, C_gf, C_ar, C_gr]``."""
    x_hat = np.asarray(x_hat, dtype=float)
    n = x_hat.shape[0]
    if x_hat.shape != (n, 8):
        raise ValueError(f"x_hat must be N x 8, got {x_hat.shape}")
    y = np.asarray(y, dtype=float)
    if y.shape != (n, len(OUTPUT_STATES)):
        raise ValueError(f"y must be N x {len(OUTPUT_STATES)}, got {y.shape}")
    u = np.broadcast_to(np.asarray(u, dtype=float), (n,)).astype(float)
    tau = np.broadcast_to(np.asarray(tau, dtype=float), (n,)).astype(float)
    m = _fit_mask(use, u, n)
    m[:2] = False  # the second difference needs two neighbours on each side to be central twice
    m[-2:] = False
    if not m.any():
        return np.full(4, np.nan)
    lpv = lpv_model(p.scaled(stiffness=0.0))
    C = np.zeros((len(OUTPUT_STATES), 8))
    C[np.arange(len(OUTPUT_STATES)), OUTPUT_STATES] = 1.0
    y_dd = np.gradient(np.gradient(y, dt, axis=0), dt, axis=0)
    u_d = np.gradient(u, dt)
    tau_d = np.gradient(tau, dt)
    idx = np.flatnonzero(m)
    phi_rows = np.empty((idx.size, len(OUTPUT_STATES), 4))
    rhs_rows = np.empty((idx.size, len(OUTPUT_STATES)))
    CA1 = C @ lpv.A1
    CB = C @ lpv.B
    for j, k in enumerate(idx):
        uk, xk = u[k], x_hat[k]
        A = lpv.A(uk)
        CA = C @ A
        known = CA1 @ xk * u_d[k] + CA @ (A @ xk + lpv.B * tau[k]) + CB * tau_d[k]
        chi = regressor(xk, uk, lpv.sigma_f, lpv.sigma_r, lpv.l_f, lpv.l_r, lpv.caster, lpv.trail)
        phi_rows[j] = CA @ lpv.D @ chi
        rhs_rows[j] = y_dd[k] - known
    xs = x_hat[m]
    with np.errstate(divide="ignore", invalid="ignore"):
        ang = _angles(p, u[m], xs[:, DELTA], xs[:, VY], xs[:, R], xs[:, PHI], xs[:, DELTA_DOT])
    angle_rms = np.sqrt(np.mean(ang**2, axis=0))
    return _solve(phi_rows.reshape(-1, 4), rhs_rows.reshape(-1), angle_rms, min_angle, rcond)


def stiffness_error_pct(estimate4, truth4) -> dict[str, float | None]:
    """Signed percent error ``100 (estimate - truth) / truth`` per stiffness; NaN (unidentified) -> None."""
    est = np.asarray(estimate4, dtype=float).reshape(4)
    tru = np.asarray(truth4, dtype=float).reshape(4)
    out: dict[str, float | None] = {}
    for key, i in ERROR_KEYS.items():
        e = 100.0 * (est[i] - tru[i]) / tru[i] if tru[i] != 0.0 else math.nan
        out[key] = float(e) if math.isfinite(e) else None
    return out


__all__ = ["direct_method", "dynamic_inversion", "stiffness_error_pct"]
