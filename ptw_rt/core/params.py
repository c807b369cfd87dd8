"""Coefficients derived from the vehicle parameters that the stages' parameter builders use.

Each stage builds its own parameter vector next to its layout (`build_params(settings, design)` in
`ptw_rt.core.inputs`, `speed`, `attitude`, `conditioning`, `diagnostics`, `kalman`, `adaptive`,
`supervisor`); what they share from the vehicle's geometry is here. Imports no stage.
"""

from __future__ import annotations

import numpy as np

from ptw_rt.model.sharp import descriptor

# rows of the Sharp descriptor model (state order [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr])
_LATERAL, _YAW = 2, 3
_R, _PHI_DOT, _DELTA_DOT = 3, 4, 5


def virtual_output_coefficients(vehicle) -> tuple[float, float, float, float]:
    """y_a of seed 001 eq. 15 in measured terms.

    y_a = c1 r_dot + c2 phi_ddot + c3 delta_ddot + u (c4 phi_dot + c5 delta_dot):

    y_a = (M_f k - M l_f) F_yf + (M_f k + M l_r) F_yr is M_f k (lateral equation) - M (yaw equation): the
    lateral-velocity derivative cancels, what is left are rate derivatives and speed-proportional
    gyroscopic terms. The steer-acceleration term (c3, two orders of magnitude below c1 for this vehicle)
    is dropped: it would need a second derivative of a quantised encoder.
    Returns (c1, c2, c4, c5).
    """
    d = descriptor(vehicle)
    w = np.zeros(d.E.shape[0])
    w[_LATERAL] = vehicle.mfk
    w[_YAW] = -vehicle.mass
    e_row = w @ d.E
    a1_row = w @ d.A1
    return float(e_row[_R]), float(e_row[_PHI_DOT]), float(-a1_row[_PHI_DOT]), float(-a1_row[_DELTA_DOT])


def lever_arm_coefficients(vehicle, imu_forward: float, imu_height: float) -> tuple[float, float]:
    """a_y at the centre of mass = a_y at the IMU + c_r r_dot + c_p phi_ddot (linear rigid-body kinematics).

    The seed 001 output a_y = (F_yf + F_yr) / M is the acceleration of the total centre of mass:
    from the lateral equation, M a_y = M (v_y' + u r) + M_f k r' + (M_f j + M_r h) phi''.
    """
    m = vehicle.mass
    k_cm = vehicle.mfk / m
    h_cm = vehicle.roll_moment / m
    return k_cm - imu_forward, h_cm - imu_height
