"""Sharp's lateral model with tyre relaxation, in descriptor and LPV form.

State  x = [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr]
Input  tau (rider steering torque), scheduling parameter u = forward speed.

    E x_dot = (A0 + u A1) x + Bbar tau

Every entry of the descriptor matrix is affine in u, and E does not depend on
u, so the explicit matrix A(u) = E^-1 (A0 + u A1) is exactly affine as well:
a two-vertex polytope in u is exact (seed 001, eq. 35-36).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ptw_rt.model.parameters import VehicleParameters

STATE_NAMES = ("phi", "delta", "v_y", "r", "phi_dot", "delta_dot", "F_yf", "F_yr")
PHI, DELTA, VY, R, PHI_DOT, DELTA_DOT, FYF, FYR = range(8)
N_STATES = 8
# Order of seed 001's parameter vector Theta (deviations from nominal stiffness).
THETA_NAMES = ("front_cornering", "front_camber", "rear_cornering", "rear_camber")


@dataclass(frozen=True)
class Descriptor:
    """E x_dot = (A0 + u A1) x + B tau."""

    E: np.ndarray
    A0: np.ndarray
    A1: np.ndarray
    B: np.ndarray


def descriptor(p: VehicleParameters) -> Descriptor:
    s, c = math.sin(p.caster), math.cos(p.caster)
    t = p.mass_matrix_terms()
    E = np.eye(N_STATES)
    E[2:6, 2:6] = [
        [t["e33"], t["e34"], t["e35"], t["e36"]],
        [t["e34"], t["e44"], t["e45"], t["e46"]],
        [t["e35"], t["e45"], t["e55"], t["e56"]],
        [t["e36"], t["e46"], t["e56"], t["e66"]],
    ]
    A0 = np.zeros((N_STATES, N_STATES))
    A1 = np.zeros((N_STATES, N_STATES))
    A0[PHI, PHI_DOT] = 1.0
    A0[DELTA, DELTA_DOT] = 1.0
    # lateral force balance
    A1[VY, R] = -p.mass
    A0[VY, FYF] = 1.0
    A0[VY, FYR] = 1.0
    # yaw: gyroscopic coupling and tyre moments
    A1[R, R] = -p.mfk
    A1[R, PHI_DOT] = p.gyro_total
    A1[R, DELTA_DOT] = p.gyro_front * s
    A0[R, FYF] = p.l_f
    A0[R, FYR] = -p.l_r
    # roll: gravity, steer-induced moment, centrifugal and gyroscopic terms
    A0[PHI_DOT, PHI] = p.roll_moment * p.g
    A0[PHI_DOT, DELTA] = p.steer_stiffness
    A1[PHI_DOT, R] = -(p.roll_moment + p.gyro_total)
    A1[PHI_DOT, DELTA_DOT] = -p.gyro_front * c
    # steer: gravity/trail moment, gyroscopic terms, damper, tyre force on the trail
    A0[DELTA_DOT, PHI] = p.steer_stiffness
    A0[DELTA_DOT, DELTA] = p.steer_stiffness * s
    A1[DELTA_DOT, R] = -(p.mfe + p.gyro_front * s)
    A1[DELTA_DOT, PHI_DOT] = p.gyro_front * c
    A0[DELTA_DOT, DELTA_DOT] = -p.damping
    A0[DELTA_DOT, FYF] = -p.trail
    # front tyre, relaxation sigma_f/u: (u/sigma)(-F + C_a(delta cos - (v_y + l_f r)/u + eta delta_dot/u) + C_g gamma)
    kf = 1.0 / p.sigma_f
    A1[FYF, FYF] = -kf
    A1[FYF, DELTA] = kf * (p.c_af * c + p.c_gf * s)
    A0[FYF, VY] = -kf * p.c_af
    A0[FYF, R] = -kf * p.c_af * p.l_f
    A0[FYF, DELTA_DOT] = kf * p.c_af * p.trail
    A1[FYF, PHI] = kf * p.c_gf
    # rear tyre
    kr = 1.0 / p.sigma_r
    A1[FYR, FYR] = -kr
    A0[FYR, VY] = -kr * p.c_ar
    A0[FYR, R] = kr * p.c_ar * p.l_r
    A1[FYR, PHI] = kr * p.c_gr
    B = np.zeros(N_STATES)
    B[DELTA_DOT] = 1.0
    return Descriptor(E, A0, A1, B)


@dataclass(frozen=True)
class LPVModel:
    """x_dot = (A0 + u A1) x + B tau + D chi(x, u) Theta  (seed 001, eq. 6-9)."""

    A0: np.ndarray
    A1: np.ndarray
    B: np.ndarray
    D: np.ndarray
    sigma_f: float
    sigma_r: float
    l_f: float
    l_r: float
    caster: float
    trail: float

    def A(self, u: float) -> np.ndarray:
        return self.A0 + u * self.A1

    def chi(self, x: np.ndarray, u: float) -> np.ndarray:
        """Regressor of the stiffness deviations: the tyre-row terms u*slip/sigma and u*camber/sigma."""
        return regressor(x, u, self.sigma_f, self.sigma_r, self.l_f, self.l_r, self.caster, self.trail)


def regressor(x, u, sigma_f, sigma_r, l_f, l_r, caster, trail) -> np.ndarray:
    s, c = math.sin(caster), math.cos(caster)
    u_alpha_f = x[VY] + l_f * x[R] - u * c * x[DELTA] - trail * x[DELTA_DOT]
    u_gamma_f = u * (x[PHI] + s * x[DELTA])
    u_alpha_r = x[VY] - l_r * x[R]
    u_gamma_r = u * x[PHI]
    chi = np.zeros((2, 4))
    chi[0, 0] = -u_alpha_f / sigma_f
    chi[0, 1] = u_gamma_f / sigma_f
    chi[1, 2] = -u_alpha_r / sigma_r
    chi[1, 3] = u_gamma_r / sigma_r
    return chi


def lpv_model(p: VehicleParameters) -> LPVModel:
    d = descriptor(p)
    Einv = np.linalg.inv(d.E)
    D = Einv @ np.vstack([np.zeros((6, 2)), np.eye(2)])
    return LPVModel(
        A0=Einv @ d.A0,
        A1=Einv @ d.A1,
        B=Einv @ d.B,
        D=D,
        sigma_f=p.sigma_f,
        sigma_r=p.sigma_r,
        l_f=p.l_f,
        l_r=p.l_r,
        caster=p.caster,
        trail=p.trail,
    )


def state_space(p: VehicleParameters, u: float) -> tuple[np.ndarray, np.ndarray]:
    """Explicit (A, B) at forward speed u [m/s]."""
    m = lpv_model(p)
    return m.A(u), m.B.copy()


# what the sensors read of the state, in this order: the encoder's steer, the gyros' yaw and roll rates, the
# lateral acceleration (the tyres' forces over the mass) and the roll (the attitude filter's, fused as a measurement)
SENSOR_OUTPUTS = ("steer", "yaw_rate", "roll_rate", "lat_accel", "roll")


def sensor_outputs(p: VehicleParameters) -> np.ndarray:
    """C (len(SENSOR_OUTPUTS) x N_STATES): y = C x, the fusion filters' measurements of Sharp's state."""
    C = np.zeros((len(SENSOR_OUTPUTS), N_STATES))
    C[0, DELTA] = 1.0
    C[1, R] = 1.0
    C[2, PHI_DOT] = 1.0
    C[3, FYF] = C[3, FYR] = 1.0 / p.mass
    C[4, PHI] = 1.0
    return C


# ----- seed 000's rearranged systems ----------------------------------------
REDUCED_STATE_NAMES = STATE_NAMES[1:]  # phi removed from the state
R_DELTA, R_VY, R_R, R_PHI_DOT, R_DELTA_DOT, R_FYF, R_FYR = range(7)


@dataclass(frozen=True)
class UnknownInputSystem:
    """x_dot = A x + D zeta, y = C x (the unknown inputs zeta are reconstructed, not known)."""

    A: np.ndarray
    D: np.ndarray
    C: np.ndarray


def roll_as_unknown_input(p: VehicleParameters, u: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seed 000 sec. III-A: remove phi from the state; its column becomes an input.

    Returns (A_p, D_p, B_p) on the reduced state [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr].
    """
    A, B = state_space(p, u)
    return A[1:, 1:].copy(), A[1:, PHI].copy(), B[1:].copy()


def case1(p: VehicleParameters, u: float) -> UnknownInputSystem:
    """Unknown input phi, output delta (rider torque treated as known)."""
    A_p, D_p, _ = roll_as_unknown_input(p, u)
    C = np.zeros((1, 7))
    C[0, R_DELTA] = 1.0
    return UnknownInputSystem(A_p, D_p[:, None], C)


def case2(p: VehicleParameters, u: float) -> UnknownInputSystem:
    """Unknown inputs [phi, tau], outputs [delta, r] (seed 000 eq. 10): the design that runs."""
    A_p, D_p, B_p = roll_as_unknown_input(p, u)
    C = np.zeros((2, 7))
    C[0, R_DELTA] = 1.0
    C[1, R_R] = 1.0
    return UnknownInputSystem(A_p, np.column_stack([D_p, B_p]), C)


def full_system(p: VehicleParameters, u: float) -> UnknownInputSystem:
    """Full model, unknown input tau, output delta (seed 000 sec. III-A, non-minimum phase)."""
    A, B = state_space(p, u)
    C = np.zeros((1, N_STATES))
    C[0, DELTA] = 1.0
    return UnknownInputSystem(A, B[:, None], C)


def kmh(speed_kmh: float) -> float:
    return speed_kmh / 3.6
