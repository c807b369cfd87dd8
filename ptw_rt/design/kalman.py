"""Offline design of the fusion filter: a steady-state Kalman filter on the Sharp model, per speed grid point.

Augmented state z = [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, tau]: the rider torque is an
unknown input modelled as a random walk (the classical disturbance-observer augmentation), so the filter
reconstructs it from every measurement, not only from the steer angle.

Measurements y = [delta (10-bit encoder), r (ground yaw rate), phi_dot (roll rate), a_y (lateral
acceleration at the centre of mass), phi (roll of the kinematic attitude filter, ptw_rt.core.attitude)].
The rates come bias-corrected by the attitude filter, which estimates the gyro biases from kinematics
alone; its roll enters as a measurement, so where the tyre model is wrong the kinematics win, and the
model adds what kinematics cannot give (torque, steer rate, lateral states, forces).

Why this filter exists next to the papers' observers: with a
10-bit encoder the steer angle of a 100 km/h lane change stays below one count, so the UIHOSMO's
roll and torque, which come from the second and third derivatives of the steer error, are dominated
by quantisation (docs/estimator.md). The gyro roll rate and the lateral acceleration carry the same
dynamics with 100x less noise; a filter that uses them gets torque 20x closer to truth.

Discretisation: exact zero-order hold of the augmented model at each grid speed (expm), then the
discrete algebraic Riccati equation for the predictor-corrector gain. The runtime interpolates Phi and
K linearly in speed; `check` verifies the error dynamics between grid points.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_are

from ptw_rt.design.discretize import zoh
from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import descriptor, sensor_outputs, state_space
from ptw_rt.settings import KalmanTuning

N_X = 9
N_Y = 5
TAU = 8
# typical magnitudes of the states (the process noise of state i is process_noise * SCALE_i^2 per second)
STATE_SCALE = np.array([0.1, 0.01, 0.3, 0.1, 0.3, 0.1, 500.0, 500.0])
FORCE_STATES = [6, 7]  # F_yf, F_yr


def output_matrix(p: VehicleParameters) -> np.ndarray:
    """The sensors' outputs (`ptw_rt.model.sharp.sensor_outputs`) of the augmented state: the torque reads on none."""
    C = np.zeros((N_Y, N_X))
    C[:, :TAU] = sensor_outputs(p)
    return C


# rows of Sharp's descriptor model that carry generalised forces: lateral, yaw, roll, steer
FORCE_ROWS = (2, 3, 4, 5)
N_D = len(FORCE_ROWS)


def design_point(
    p: VehicleParameters, u: float, dt: float, tuning: KalmanTuning
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Phi, K, Gd) at speed u (see `design_point_with_innovation`)."""
    return design_point_with_innovation(p, u, dt, tuning)[:3]


def design_point_with_innovation(
    p: VehicleParameters,
    u: float,
    dt: float,
    tuning: KalmanTuning,
    force_noise: tuple[float, float] = (1.0, 1.0),
    torque_noise: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(Phi, K, Gd, S) at speed u: z+ = z + K (y - C z); z_next = Phi z+ + Gd d; S = C P C' + R, the
    covariance of the innovation y - C z (what the tyre bank's likelihoods need). `force_noise` scales the
    front and rear tyre forces' process noise (their typical magnitude): the tyre bank's publishing filters
    (`fusion_filter.published_force_noise`) let the forces stray further from the tyre model, and `torque_noise`
    (`published_torque_noise`) their rider torque walk faster.

    d are the generalised forces by which the nonlinear vehicle differs from the linear model on the
    lateral, yaw, roll and steer rows (`ptw_rt.core.kalman.nonlinear_correction`), held over the step:
    a known input, so the filter's error dynamics (and its stability) are those of (Phi, K)."""
    A, B = state_space(p, u)
    Aa = np.zeros((N_X, N_X))
    Aa[:8, :8] = A
    Aa[:8, TAU] = B
    Bd = np.zeros((N_X, N_D))
    Bd[:8, :] = np.linalg.inv(descriptor(p).E)[:, FORCE_ROWS]
    Phi, Gd = zoh(Aa, Bd, dt)
    Q = np.zeros((N_X, N_X))
    scale = STATE_SCALE.copy()
    scale[FORCE_STATES] *= force_noise  # the tyre forces' freedom from the tyre model (front, rear)
    Q[:8, :8] = np.diag(tuning.process_noise * scale**2 * dt)
    Q[TAU, TAU] = (torque_noise * tuning.rider_torque_rate) ** 2 * dt
    R = np.diag(np.square(tuning.measurement_sd()))
    C = output_matrix(p)
    P = solve_discrete_are(Phi.T, C.T, Q, R)
    S = C @ P @ C.T + R
    K = P @ C.T @ np.linalg.inv(S)
    return Phi, K, Gd, S


def design_grid(p: VehicleParameters, grid: np.ndarray, dt: float, tuning: KalmanTuning):
    """(Phi, K, Gd) stacked over the speed grid."""
    points = [design_point(p, float(u), dt, tuning) for u in grid]
    return tuple(np.array([pt[k] for pt in points]) for k in range(3))


def nonlinear_constants(p: VehicleParameters) -> np.ndarray:
    """Constants of `ptw_rt.core.kalman.nonlinear_correction` (layout NL_* there)."""
    return np.array(
        [
            p.roll_moment,
            p.gyro_total,
            p.gyro_front,
            p.steer_stiffness,
            p.mfe,
            p.g,
            np.sin(p.caster),
        ]
    )


def error_dynamics(Phi: np.ndarray, K: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Estimation error propagation of the predictor-corrector: e_next = Phi (I - K C) e."""
    return Phi @ (np.eye(Phi.shape[0]) - K @ C)
