"""The jitted ride loop: rider + plant, fixed-step RK4, everything recorded at the step rate.

One call integrates a whole chunk of the ride without returning to Python (the Python side only
splits long rides into chunks to draw a progress bar).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.sim.plant import (
    AX_ALPHA_F,
    AX_ALPHA_R,
    AX_FSS_F,
    AX_FSS_R,
    AX_FX,
    AX_GAMMA_F,
    AX_GAMMA_R,
    AX_PEAK_F,
    AX_PEAK_R,
    AX_W,
    DELTA,
    DELTA_DOT,
    NAUX,
    NX,
    P_UHI,
    P_ULO,
    PHI,
    PHI_DOT,
    PSI,
    VY,
    XPOS,
    YPOS,
    U,
    drive_limits,
    rk4_step,
    support_weight,
)
from ptw_rt.sim.rider import (
    CS_EPSI,
    CS_EPSI_OFF,
    CS_EY,
    CS_EY_OFF,
    CS_FX,
    CS_IDX,
    CS_INT_V,
    CS_INT_Y,
    CS_PHI_FF,
    CS_TAU,
    CS_TAU_FF,
    RP_CRR_W,
    RP_DC,
    RP_GMIN,
    RP_GSTEP,
    RP_KC,
    RP_KI_V,
    RP_KP_V,
    RP_LAG,
    RP_LEAN_STEP,
    RP_MAX_ROLL,
    RP_MEFF,
    RP_MERGE,
    RP_PREVIEW_DT,
    RP_RHO_CDA,
    RP_TMAX,
    Z_EPSI,
    Z_EY,
    Z_INT,
    Z_TAU,
    _interp2,
    path_errors,
    path_value,
    trim_lean,
)

# ----- recorded channels (one row per plant step, at the START of the step) -------------------
(
    REC_T,
    REC_X0,  # 12 plant states follow
) = (0, 1)
REC_TAU = REC_X0 + NX  # 13: rider torque applied
REC_FX = REC_TAU + 1  # longitudinal force applied (drive - brake)
REC_MU = REC_FX + 1
REC_DVY = REC_MU + 1  # derivatives of v_y, r, phi_dot, delta_dot, u
REC_DR = REC_DVY + 1
REC_DP = REC_DR + 1
REC_DDD = REC_DP + 1
REC_DU = REC_DDD + 1
REC_ALPHA_F = REC_DU + 1
REC_ALPHA_R = REC_ALPHA_F + 1
REC_GAMMA_F = REC_ALPHA_R + 1
REC_GAMMA_R = REC_GAMMA_F + 1
REC_FSS_F = REC_GAMMA_R + 1
REC_FSS_R = REC_FSS_F + 1
REC_PEAK_F = REC_FSS_R + 1
REC_PEAK_R = REC_PEAK_F + 1
REC_W = REC_PEAK_R + 1
REC_PHI_REF = REC_W + 1
REC_EY = REC_PHI_REF + 1
REC_EPSI = REC_EY + 1
REC_VREF = REC_EPSI + 1
NREC = REC_VREF + 1

CRASH_ROLL = 1.2  # rad (69 deg): the ride is over


@njit(cache=True)
def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def _plan_value(arr, t, plan_dt):
    f = t / plan_dt
    n = arr.shape[0]
    if f <= 0.0:
        return arr[0]
    if f >= n - 1:
        return arr[n - 1]
    i = int(f)
    a = f - i
    return (1.0 - a) * arr[i] + a * arr[i + 1]


@njit(cache=True)
def rider_control(
    t,
    x,
    cs,
    dt,
    rp,
    pp,
    gains,
    trims,
    preview,
    xp,
    yp,
    psip,
    kap,
    dkap,
    ds,
    v_ref,
    a_ref,
    noise_tau,
    wander,
    kvec,
    zss,
    pvec,
):
    """Update the rider's internal state; returns the longitudinal force command. Torque is cs[CS_TAU]."""
    u = x[U]
    w = support_weight(u, pp[P_ULO], pp[P_UHI])
    # --- where am I with respect to the line
    i, sidx, ey, hp = path_errors(xp, yp, psip, int(cs[CS_IDX]), x[XPOS], x[YPOS])
    cs[CS_IDX] = i
    ey -= wander
    epsi = _wrap(x[PSI] - hp)
    # on the feet the rider does not steer back to the line; he sets off from where he is and merges
    if w < 1.0:
        cs[CS_EY_OFF] = ey
        cs[CS_EPSI_OFF] = epsi
    else:
        cs[CS_EY_OFF] -= cs[CS_EY_OFF] * dt / rp[RP_MERGE]
        cs[CS_EPSI_OFF] -= cs[CS_EPSI_OFF] * dt / rp[RP_MERGE]
    ey -= cs[CS_EY_OFF]
    epsi -= cs[CS_EPSI_OFF]
    cs[CS_EY] = ey
    cs[CS_EPSI] = epsi
    if w >= 1.0:
        cs[CS_INT_Y] += ey * dt
    else:
        cs[CS_INT_Y] -= (1.0 - w) * cs[CS_INT_Y] * dt
    lim = 3.0
    if cs[CS_INT_Y] > lim:
        cs[CS_INT_Y] = lim
    elif cs[CS_INT_Y] < -lim:
        cs[CS_INT_Y] = -lim

    # --- LQR around the plant's steady turn of the local curvature + optimal preview of the curvature ahead
    kap0 = path_value(kap, sidx)
    gu = (u - rp[RP_GMIN]) / rp[RP_GSTEP]
    lstep = rp[RP_LEAN_STEP]
    _interp2(gains, gu, abs(x[PHI]) / lstep, kvec)
    _interp2(preview, gu, abs(x[PHI]) / lstep, pvec)
    lean = trim_lean(trims, gu, u * abs(kap0), lstep)
    pmax = rp[RP_MAX_ROLL]
    if lean > pmax:
        lean = pmax
    _interp2(trims, gu, lean / lstep, zss)
    sgn = 1.0 if kap0 >= 0.0 else -1.0
    cs[CS_PHI_FF] = sgn * lean
    acc = 0.0
    for k in range(8):
        acc += kvec[k] * (x[k] - sgn * zss[k])
    tau_ss = sgn * zss[8]
    acc += kvec[Z_TAU] * (cs[CS_TAU] - tau_ss)
    acc += kvec[Z_EY] * ey + kvec[Z_EPSI] * (epsi - sgn * zss[9]) + kvec[Z_INT] * cs[CS_INT_Y]
    ff = 0.0
    step = u * rp[RP_PREVIEW_DT] / ds
    for jj in range(pvec.shape[0]):
        ff += pvec[jj] * u * path_value(dkap, sidx + (jj + 0.5) * step)
    cs[CS_TAU_FF] = ff
    tau_cmd = tau_ss - acc + ff
    centre = -rp[RP_KC] * x[DELTA] - rp[RP_DC] * x[DELTA_DOT]
    tau_cmd = w * (tau_cmd + noise_tau) + (1.0 - w) * centre
    tmax = rp[RP_TMAX]
    if tau_cmd > tmax:
        tau_cmd = tmax
    elif tau_cmd < -tmax:
        tau_cmd = -tmax
    cs[CS_TAU] += dt / rp[RP_LAG] * (tau_cmd - cs[CS_TAU])

    # --- speed loop
    ev = v_ref - u
    fade = u / 0.3
    if fade > 1.0:
        fade = 1.0
    fxff = rp[RP_MEFF] * a_ref + 0.5 * rp[RP_RHO_CDA] * u * u + rp[RP_CRR_W] * fade
    fx = fxff + rp[RP_KP_V] * ev + rp[RP_KI_V] * cs[CS_INT_V]
    fdmax, fbmax = drive_limits(u, pp)
    if v_ref < 0.05 and u < 0.2:
        fx = -0.3 * fbmax  # hold the brake at standstill
        cs[CS_INT_V] = 0.0
    else:
        saturated_hi = fx > fdmax and ev > 0.0
        saturated_lo = fx < -fbmax and ev < 0.0
        if not (saturated_hi or saturated_lo):
            cs[CS_INT_V] += ev * dt
    if fx > fdmax:
        fx = fdmax
    elif fx < -fbmax:
        fx = -fbmax
    cs[CS_FX] = fx
    return fx


@njit(cache=True)
def ride_chunk(
    k0,
    k1,
    dt,
    x,
    cs,
    pp,
    m4inv,
    rp,
    gains,
    trims,
    preview,
    xp,
    yp,
    psip,
    kap,
    dkap,
    ds,
    plan_dt,
    v_plan,
    a_plan,
    mu_plan,
    noise_plan,
    wander_plan,
    rec,
):
    """Steps k0..k1-1 (time k*dt) in place; returns the step index of a crash, or -1."""
    k1v = np.zeros(NX)
    k2v = np.zeros(NX)
    k3v = np.zeros(NX)
    k4v = np.zeros(NX)
    xt = np.zeros(NX)
    aux = np.zeros(NAUX)
    aux2 = np.zeros(NAUX)
    kvec = np.zeros(gains.shape[2])
    zss = np.zeros(trims.shape[2])
    pvec = np.zeros(preview.shape[2])
    for k in range(k0, k1):
        t = k * dt
        v_ref = _plan_value(v_plan, t, plan_dt)
        a_ref = _plan_value(a_plan, t, plan_dt)
        mu = _plan_value(mu_plan, t, plan_dt)
        nz = _plan_value(noise_plan, t, plan_dt)
        wd = _plan_value(wander_plan, t, plan_dt)
        tau = cs[CS_TAU]  # the lag state is what the hands apply during this step
        fx = rider_control(
            t,
            x,
            cs,
            dt,
            rp,
            pp,
            gains,
            trims,
            preview,
            xp,
            yp,
            psip,
            kap,
            dkap,
            ds,
            v_ref,
            a_ref,
            nz,
            wd,
            kvec,
            zss,
            pvec,
        )
        row = rec[k]
        row[REC_T] = t
        for i in range(NX):
            row[REC_X0 + i] = x[i]
        rk4_step(x, tau, fx, mu, dt, pp, m4inv, k1v, k2v, k3v, k4v, xt, aux, aux2)
        row[REC_TAU] = tau
        row[REC_FX] = aux[AX_FX]
        row[REC_MU] = mu
        row[REC_DVY] = k1v[VY]
        row[REC_DR] = k1v[VY + 1]
        row[REC_DP] = k1v[PHI_DOT]
        row[REC_DDD] = k1v[DELTA_DOT]
        row[REC_DU] = k1v[U]
        row[REC_ALPHA_F] = aux[AX_ALPHA_F]
        row[REC_ALPHA_R] = aux[AX_ALPHA_R]
        row[REC_GAMMA_F] = aux[AX_GAMMA_F]
        row[REC_GAMMA_R] = aux[AX_GAMMA_R]
        row[REC_FSS_F] = aux[AX_FSS_F]
        row[REC_FSS_R] = aux[AX_FSS_R]
        row[REC_PEAK_F] = aux[AX_PEAK_F]
        row[REC_PEAK_R] = aux[AX_PEAK_R]
        row[REC_W] = aux[AX_W]
        row[REC_PHI_REF] = cs[CS_PHI_FF]
        row[REC_EY] = cs[CS_EY]
        row[REC_EPSI] = cs[CS_EPSI]
        row[REC_VREF] = v_ref
        finite = True
        for i in range(NX):
            if not math.isfinite(x[i]):
                finite = False
        if not finite or abs(x[PHI]) > CRASH_ROLL:
            return k
    return -1
