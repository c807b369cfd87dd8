"""Config + design file -> the estimator's parameter vector: the one place tuning becomes numbers."""

from __future__ import annotations

import math

import numpy as np

from ptw_rt.core import estimator as est_layout
from ptw_rt.core.force_observers import lateral_yaw_constants
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


def build_params(settings, design) -> np.ndarray:
    est = settings.estimator
    sens = settings.sensors
    veh = settings.vehicle
    dt = float(design.sample_time)
    prm = np.zeros(est_layout.PARAM_SIZE)
    prm[est_layout.P_DT] = dt
    prm[est_layout.P_DIFF_L] = design.uh_differentiator_lambda
    prm[est_layout.P_G] = veh.g
    prm[est_layout.P_MIN_SPEED] = design.min_valid_speed
    prm[est_layout.P_STEER_ZERO] = sens.steer_zero_count
    prm[est_layout.P_STEER_CPR] = sens.steer_counts_per_rev
    prm[est_layout.P_SPEED_GAIN] = sens.speed_filter_gain
    prm[est_layout.P_SPEED_BIAS_GAIN] = sens.speed_bias_gain
    prm[est_layout.P_LATENCY_SAMPLES] = round(sens.gps_latency / dt)
    prm[est_layout.P_FUSION_RATE] = 1.0 / est.roll_fusion_time_constant
    prm[est_layout.P_CAL_SPEED] = sens.gyro_calibration_speed
    prm[est_layout.P_CAL_GAIN] = 1.0 - math.exp(-dt / sens.gyro_calibration_time_constant)
    prm[est_layout.P_CAL_MAX_RATE] = sens.gyro_calibration_max_rate
    prm[est_layout.P_DERIV_OMEGA] = 2.0 * math.pi * est.derivative_filter_hz
    prm[est_layout.P_CONVERGE_TIME] = est.converge_time
    prm[est_layout.P_GPS_HOLD] = est.gps_hold_time
    prm[est_layout.P_REASON_HOLD] = est.reason_hold_time
    prm[est_layout.P_STIFF_VALID_AFTER] = est.stiffness_valid_after
    prm[est_layout.P_MAX_ROLL] = est.max_roll
    prm[est_layout.P_MAX_TORQUE] = est.max_rider_torque
    prm[est_layout.P_MAX_FORCE] = est.max_tyre_force
    prm[est_layout.P_MAX_LAT_VEL] = est.max_lateral_velocity
    lever = lever_arm_coefficients(veh, sens.imu_forward, sens.imu_height)
    prm[est_layout.P_A_Y_R_DOT], prm[est_layout.P_A_Y_PHI_DDOT] = lever
    ya = virtual_output_coefficients(veh)
    prm[est_layout.P_YA_R_DOT], prm[est_layout.P_YA_PHI_DDOT] = ya[0], ya[1]
    prm[est_layout.P_YA_PHI_DOT], prm[est_layout.P_YA_DELTA_DOT] = ya[2], ya[3]
    prm[est_layout.P_DIFF_SUBSTEPS] = 1
    prm[est_layout.P_PE_FORGETTING] = design.ad_pe_forgetting
    prm[est_layout.P_MAX_RATE] = est.max_abs_rate
    prm[est_layout.P_MAX_ACCEL] = est.max_abs_accel
    prm[est_layout.P_MAX_GPS_SPEED] = est.max_gps_speed
    prm[est_layout.P_STIFF_MAX_RESIDUAL] = est.stiffness_max_residual
    prm[est_layout.P_ADAPT_MAX_RESIDUAL] = est.adaptation_max_residual
    prm[est_layout.P_ROLL_TOLERANCE] = math.radians(est.roll_tolerance_deg)
    # 3 rad/s of steer rate (the contract's range) at most, in encoder counts per cycle, with one count of margin
    prm[est_layout.P_MAX_STEER_STEP] = 3.0 * dt * sens.steer_counts_per_rev / (2.0 * math.pi) + 1.0
    prm[est_layout.P_STEER_RESYNC] = 10
    prm[est_layout.P_STA_LC_R] = est.force_observer_yaw_bound
    prm[est_layout.P_STA_LC_W] = est.force_observer_lateral_bound
    prm[est_layout.P_GEOM : est_layout.P_GEOM + 4] = lateral_yaw_constants(veh)

    return prm
