"""Baseline sliding-mode observers of the lateral tyre forces (seeds 002 and 003). EVALUATION ONLY.

These reproduce the published approaches so the product's estimator can be
compared against them; their outputs are never published on the bus.

Sub-model (lateral/yaw split of Sharp's model, seed 002 "model splitting")
-------------------------------------------------------------------------
With ``a_y`` the lateral acceleration of the centre of mass in the road plane
(an IMU reading transported to the CoM, gravity removed, "de-rolled"), ``r``
the yaw rate and ``F_f, F_r`` the lateral tyre forces::

    M a_y      = F_f + F_r                               (lateral balance; exact in the linear model)
    I_z r_dot  = a_f F_f - a_r F_r + m_known + eta       (yaw balance about the CoM)

The constants come from ``VehicleParameters`` (``lateral_yaw_constants``).
Sharp's yaw row is written about the model's reference point; its planar part
is ``e44 r_dot + M_f k (v_y_dot + u r) = l_f F_f - l_r F_r``. The CoM lies
``x_G = M_f k / M`` ahead of that point; moving the balance to the CoM gives
``I_z = e44 - M x_G^2`` (``e44`` is the yaw inertia about the reference point;
the correction is 0.4 % for the scooter), arms ``a_f = l_f - x_G``,
``a_r = l_r + x_G``, and no dependence on ``v_y``. ``eta`` is what
``(u, r, a_y)`` cannot show: the gyroscopic moment
``(i_fy/R_f + i_ry/R_r) u phi_dot`` (dominant: ~40 N m peak in a 100 km/h lane
change, more than the tyre yaw moment itself), ``(i_fy/R_f) sin(eps) u delta_dot``
and the inertia couplings ``e45 phi_ddot + e46 delta_ddot``. Seed 002 treats such
coupling terms as bounded perturbations; ``m_known`` lets a caller add what it
can compute (e.g. the gyroscopic term from the IMU roll rate).

Both observers estimate the two unknown inputs ``S = F_f + F_r`` and
``Mz = a_f F_f - a_r F_r`` on two first-order channels, then split them::

    F_f = (a_r S + Mz) / (a_f + a_r),   F_r = (a_f S - Mz) / (a_f + a_r)

* yaw channel: measured ``r``, ``r_dot = Mz / I_z + m_known / I_z``;
* lateral channel: the scooter has no lateral-velocity sensor (seed 003's
  truck had one), so the measured quantity is the integrated acceleration
  ``w = int a_y dt`` (a lateral pseudo-velocity), ``w_dot = S / M``. The
  observer carries the error ``e_w = w - w_hat`` itself, so nothing drifts.
  Both channels then share the same observer dynamics and ``S`` and ``Mz``
  have matched lag when they are combined.

Between samples the measurements are held (ZOH): ``r`` is constant over the
interval and ``w`` grows by ``a_y dt``.

First-order SMO (seed 002 eq. 23 with the prior force estimate 0; seed 003 sec. 3.2)
------------------------------------------------------------------------------
``x_hat_dot = b + lam sign(x - x_hat)``; the mean ("equivalent") value of the
injection equals the unknown input and is recovered with a low-pass filter
(seed 003 eq. 26, ``Sign_moy``). Default discretisation (``implicit=True``):
the sign is taken implicitly (backward Euler in the set-valued sign, Acary &
Brogliato 2010). With ``p = e + dt c`` the error that the interval would leave
without injection, ``s = sat(p / (lam dt))`` and ``e+ = p - lam dt s``: this is
the exact Filippov solution over the interval (except when the error crosses
zero with ``|c| > lam``), and ``lam s`` is the interval's mean injection. The
filter is the exact ZOH discretisation of ``1 / (T s + 1)``.
``implicit=False`` is forward Euler, the literal discretisation of the seeds:
at 100 Hz the error chatters in a band ``lam dt``, the injection switches
between ``+-lam`` every sample, and no sensible filter recovers the forces
(50-110 % RMSE on the test rides with the default gains, 11-14 % with the
gains and filter tuned down). It is kept only to show that.

Super-twisting observer (seed 003 sec. 3.3; the STA of seed 000)
----------------------------------------------------------------
``x_hat_dot = b + z + k1 |e|^(1/2) sign(e)``, ``z_dot = k2 sign(e)``,
``k1 = 1.5 sqrt(Lc)``, ``k2 = 1.1 Lc`` (Levant's first-order differentiator
gains), ``Lc`` a bound on the rate of change of the unknown input per unit
inertia (or mass). ``z`` is the continuous estimate of the unknown input and is
used unfiltered. Default discretisation (``implicit=True``): implicit in the
sign and the square root (Brogliato, Polyakov, Efimov, "The implicit
discretization of the super-twisting sliding-mode control algorithm", IEEE
TAC 65(8), 2020), solved in closed form per step. It reaches ``e = 0`` exactly
and does not chatter on clean data; with noise ``z`` moves at most ``k2 dt``
per sample. ``implicit=False`` is forward Euler (the Livne-Levant scheme for
order 1): at 100 Hz ``z`` chatters by about ``Lc dt`` and needs ``Lc`` close to
the true bound. ``substeps`` integrates the held sample with ``dt / m``
(comparison only).

Inputs per sample: ``u`` forward speed [m/s] (checked only: the sub-model does
not depend on it), ``r`` [rad/s], ``a_y`` [m/s^2], ``dt`` [s], optional
``m_known`` [N m]. A sample with a non-finite value, ``dt`` outside
``(0, DT_MAX]``, ``|r| > R_MAX``, ``|a_y| > A_Y_MAX`` or
``|m_known| > M_KNOWN_MAX`` holds the state and repeats the last estimate.
The unknown-input estimates are clamped to ``|S/M| <= A_Y_MAX`` and
``|Mz/I_z| <= RDOT_MAX``, so the force outputs are always bounded.

Measured on the lane changes of the tests (noisy, defaults), RMSE as a
fraction of the peak force: SMO 1-6 %, STA 2-4 %. The implicit SMO with its
40 ms filter is the smoothest estimate but lags (5-6 % on the rear force).
The STA is smoother than the SMO's unfiltered equivalent injection and than
the forward-Euler SMO. Without ``m_known`` the error floor (about 3 %) is the
``eta`` moment.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.model.parameters import VehicleParameters

# Geometry vector layout: [M, I_z, a_f, a_r]
G_MASS, G_IZ, G_AF, G_AR = range(4)
# First-order SMO state: [r_hat, e_w, nu_r (filtered Mz/I_z), nu_w (filtered S/M), initialised flag]
SMO_STATE_SIZE = 5
# STA state: [r_hat, z_r (Mz/I_z), e_w, z_w (S/M), initialised flag]
STA_STATE_SIZE = 5

# Plausibility limits of a sample (beyond: the sample is ignored) and of the estimates.
DT_MAX = 1.0  # s
R_MAX = 10.0  # rad/s
A_Y_MAX = 50.0  # m/s^2
M_KNOWN_MAX = 1.0e4  # N m
RDOT_MAX = 100.0  # rad/s^2

# Documented defaults, tuned on the 100 km/h lane change of tests/test_force_observers.py, where the true
# |d a_y/dt| <= 4.6 m/s^3 and |d(Mz/I_z)/dt| <= 3.5 rad/s^3.
SMO_LAMBDA_R = 10.0  # rad/s^2: the largest yaw acceleration the injection can follow
SMO_LAMBDA_W = 15.0  # m/s^2: the largest lateral acceleration the injection can follow
SMO_FILTER_T = 0.04  # s: time constant of the equivalent-injection low-pass filter
STA_LC_R = 10.0  # rad/s^3: bound on |d/dt (Mz / I_z)|
STA_LC_W = 10.0  # m/s^3: bound on |d a_y / dt|


def lateral_yaw_constants(p: VehicleParameters) -> np.ndarray:
    """``[M, I_z, a_f, a_r]`` of the CoM-referred lateral/yaw sub-model (module docstring)."""
    t = p.mass_matrix_terms()
    x_g = t["e34"] / p.mass
    return np.array([p.mass, t["e44"] - p.mass * x_g**2, p.l_f - x_g, p.l_r + x_g])


# ----- jitted kernels ------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _split(s_per_mass: float, mz_per_inertia: float, geom: np.ndarray, out: np.ndarray) -> None:
    S = geom[G_MASS] * s_per_mass
    Mz = geom[G_IZ] * mz_per_inertia
    a_f, a_r = geom[G_AF], geom[G_AR]
    wb = a_f + a_r
    out[0] = (a_r * S + Mz) / wb
    out[1] = (a_f * S - Mz) / wb


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _valid(u: float, r: float, a_y: float, dt: float, m_known: float) -> bool:
    return (
        math.isfinite(u)
        and math.isfinite(dt)
        and 0.0 < dt <= DT_MAX
        and abs(r) <= R_MAX  # also False for NaN
        and abs(a_y) <= A_Y_MAX
        and abs(m_known) <= M_KNOWN_MAX
    )


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _sign(v: float) -> float:
    return 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)


@njit(cache=True)
def _clamp(v: float, lim: float) -> float:
    return min(max(v, -lim), lim)


@njit(cache=True)
def _gain(v: float) -> float:
    """A gain argument: negative or non-finite values count as 0."""
    return v if (math.isfinite(v) and v > 0.0) else 0.0


@njit(cache=True)
def _implicit_sign(p: float, lam_dt: float) -> float:
    """``s`` in ``Sign(p - lam_dt s)``: the projection of ``p / lam_dt`` on ``[-1, 1]``."""
    if lam_dt <= 0.0:
        return 0.0
    return _clamp(p / lam_dt, 1.0)


@njit(cache=True)
def _init(x: np.ndarray, r: float, a_y: float) -> None:
    """Start on the measurement (both layouts): ``r_hat = r``, ``e_w = 0``, yaw input 0, lateral input ``a_y``."""
    x[0] = r
    x[1] = 0.0
    x[2] = 0.0
    x[3] = a_y
    x[4] = 1.0


@njit(cache=True)
def smo_step(
    x: np.ndarray,
    out: np.ndarray,
    u: float,
    r: float,
    a_y: float,
    dt: float,
    geom: np.ndarray,
    lam_r: float,
    lam_w: float,
    t_filter: float,
    m_known: float = 0.0,
    implicit: bool = True,
) -> None:
    """First-order SMO, one sample: updates ``x`` (``SMO_STATE_SIZE``) and writes ``out = [F_yf, F_yr]``."""
    if not _valid(u, r, a_y, dt, m_known):
        _split(x[3], x[2], geom, out)
        return
    if x[4] == 0.0:
        _init(x, r, a_y)
    lam_r = _gain(lam_r)
    lam_w = _gain(lam_w)
    b = m_known / geom[G_IZ]
    # yaw channel: r held over the interval, r_hat_dot = b + lam_r s
    e_r = r - x[0]
    if implicit:
        s_r = _implicit_sign(e_r - dt * b, lam_r * dt)
    else:
        s_r = _sign(e_r)
    x[0] = x[0] + dt * (b + lam_r * s_r)
    # lateral channel: e_w_dot = a_y - lam_w s
    if implicit:
        s_w = _implicit_sign(x[1] + dt * a_y, lam_w * dt)
    else:
        s_w = _sign(x[1])
    x[1] = x[1] + dt * (a_y - lam_w * s_w)
    # equivalent injections through the low-pass filter (exact ZOH discretisation; t_filter <= 0: no filter)
    alpha = 1.0 - math.exp(-dt / t_filter) if t_filter > 0.0 else 1.0
    x[2] = _clamp(x[2] + alpha * (lam_r * s_r - x[2]), RDOT_MAX)
    x[3] = _clamp(x[3] + alpha * (lam_w * s_w - x[3]), A_Y_MAX)
    if not (math.isfinite(x[0]) and math.isfinite(x[1])):
        _init(x, r, a_y)
    _split(x[3], x[2], geom, out)


@njit(cache=True)
def _sta_update(e: float, z: float, c: float, k1: float, k2: float, h: float, implicit: bool):
    """One step of the error-form STA ``e_dot = c - z - k1 |e|^(1/2) sign(e)``, ``z_dot = k2 sign(e)``.

    Implicit: ``e+ = p - s (h^2 k2 + h k1 |e+|^(1/2))``, ``z+ = z + h k2 s``, ``s in Sign(e+)``,
    ``p = e + h (c - z)``; either ``|p| <= h^2 k2`` (then ``e+ = 0``, ``s = p / (h^2 k2)``) or ``sign(e+) = sign(p)``
    and ``|e+|^(1/2)`` is the positive root of a quadratic. Explicit: forward Euler.
    """
    if implicit:
        p = e + h * (c - z)
        h2k2 = h * h * k2
        if abs(p) <= h2k2:
            return 0.0, z + (p / h if h2k2 > 0.0 else 0.0)
        sg = _sign(p)
        hk1 = h * k1
        root = 0.5 * (-hk1 + math.sqrt(hk1 * hk1 + 4.0 * (abs(p) - h2k2)))
        return sg * root * root, z + h * k2 * sg
    sg = _sign(e)
    return e + h * (c - z - k1 * math.sqrt(abs(e)) * sg), z + h * k2 * sg


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def sta_step(
    x: np.ndarray,
    out: np.ndarray,
    u: float,
    r: float,
    a_y: float,
    dt: float,
    geom: np.ndarray,
    lc_r: float,
    lc_w: float,
    m_known: float = 0.0,
    implicit: bool = True,
    substeps: int = 1,
) -> None:
    """Super-twisting observer, one sample: updates ``x`` (``STA_STATE_SIZE``), writes ``out = [F_yf, F_yr]``."""
    if not (_valid(u, r, a_y, dt, m_known) and substeps >= 1):
        _split(x[3], x[1], geom, out)
        return
    if x[4] == 0.0:
        _init(x, r, a_y)
    lc_r = _gain(lc_r)
    lc_w = _gain(lc_w)
    k1r, k2r = 1.5 * math.sqrt(lc_r), 1.1 * lc_r
    k1w, k2w = 1.5 * math.sqrt(lc_w), 1.1 * lc_w
    b = m_known / geom[G_IZ]
    h = dt / substeps
    # yaw: e = r - r_hat, r held => e_dot = -(b + z + injection); lateral: e_w_dot = a_y - (z + injection)
    e_r, z_r, e_w, z_w = r - x[0], x[1], x[2], x[3]
    for _ in range(substeps):
        e_r, z_r = _sta_update(e_r, z_r, -b, k1r, k2r, h, implicit)
        e_w, z_w = _sta_update(e_w, z_w, a_y, k1w, k2w, h, implicit)
    if math.isfinite(e_r) and math.isfinite(z_r) and math.isfinite(e_w) and math.isfinite(z_w):
        x[0] = r - e_r
        x[1] = _clamp(z_r, RDOT_MAX)
        x[2] = e_w
        x[3] = _clamp(z_w, A_Y_MAX)
    else:
        _init(x, r, a_y)
    _split(x[3], x[1], geom, out)


@njit(cache=True)
def _run_smo(u, r, a_y, dt, m_known, geom, lam_r, lam_w, t_filter, implicit):
    n = r.shape[0]
    F = np.empty((n, 2))
    x = np.zeros(SMO_STATE_SIZE)
    out = np.zeros(2)
    for k in range(n):
        smo_step(x, out, u[k], r[k], a_y[k], dt[k], geom, lam_r, lam_w, t_filter, m_known[k], implicit)
        F[k, 0] = out[0]
        F[k, 1] = out[1]
    return F


@njit(cache=True)
def _run_sta(u, r, a_y, dt, m_known, geom, lc_r, lc_w, implicit, substeps):
    n = r.shape[0]
    F = np.empty((n, 2))
    x = np.zeros(STA_STATE_SIZE)
    out = np.zeros(2)
    for k in range(n):
        sta_step(x, out, u[k], r[k], a_y[k], dt[k], geom, lc_r, lc_w, m_known[k], implicit, substeps)
        F[k, 0] = out[0]
        F[k, 1] = out[1]
    return F


# ----- whole-array convenience ---------------------------------------------------------------------------------


def _arrays(u, r, a_y, dt, m_known):
    r = np.ascontiguousarray(r, dtype=np.float64)

    def full(v):
        return np.ascontiguousarray(np.broadcast_to(np.asarray(v, dtype=np.float64), r.shape))

    return full(u), r, full(a_y), full(dt), full(0.0 if m_known is None else m_known)


def run_smo(
    u,
    r,
    a_y,
    dt,
    geom: np.ndarray,
    lam_r: float = SMO_LAMBDA_R,
    lam_w: float = SMO_LAMBDA_W,
    t_filter: float = SMO_FILTER_T,
    m_known=None,
    implicit: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """First-order SMO over whole arrays (scalars broadcast to ``r``'s shape). Returns ``(F_yf, F_yr)``."""
    u, r, a_y, dt, m_known = _arrays(u, r, a_y, dt, m_known)
    geom = np.ascontiguousarray(geom, dtype=np.float64)
    F = _run_smo(u, r, a_y, dt, m_known, geom, float(lam_r), float(lam_w), float(t_filter), bool(implicit))
    return F[:, 0].copy(), F[:, 1].copy()


def run_sta(
    u,
    r,
    a_y,
    dt,
    geom: np.ndarray,
    lc_r: float = STA_LC_R,
    lc_w: float = STA_LC_W,
    m_known=None,
    implicit: bool = True,
    substeps: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Super-twisting observer over whole arrays (scalars broadcast to ``r``'s shape). Returns ``(F_yf, F_yr)``."""
    u, r, a_y, dt, m_known = _arrays(u, r, a_y, dt, m_known)
    geom = np.ascontiguousarray(geom, dtype=np.float64)
    F = _run_sta(u, r, a_y, dt, m_known, geom, float(lc_r), float(lc_w), bool(implicit), int(substeps))
    return F[:, 0].copy(), F[:, 1].copy()
