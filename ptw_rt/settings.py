"""The config file (config/scooter.yaml): load, validate, fingerprint; one typed dataclass per section.

Four sections:

* ``vehicle:`` physical parameters (``VehicleParameters``),
* ``estimator:`` the tuning (``EstimatorTuning``),
* ``sensors:`` the calibration of the sensors as mounted (``SensorSettings``),
* ``runtime:`` the daemon's bus, GNSS source, timeouts, state file, logs and real-time settings
  (``RuntimeSettings``).

Only ``vehicle`` and ``estimator`` go into the canonical hash that ties a design file to the configuration it
was computed from: changing the CAN channel or a sensor calibration must not invalidate the design.
Every section is validated by the schema below (``ptw_rt.schema``) before it becomes a dataclass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from ptw_rt.model.parameters import VEHICLE_SCHEMA, VehicleParameters, vehicle_from_mapping
from ptw_rt.schema import ConfigError, Flag, Number, NumberList, Section, Text, canonical_hash, read_yaml, validate
from ptw_rt.untrusted import excerpt

# Kinematic attitude filter (ptw_rt/core/attitude.py): roll from gyros + accelerometer, no tyre model.
ATTITUDE_SCHEMA = Section(
    fields={},
    optional={
        "roll_noise": (Number("rad/sqrt(s)", ge=1e-6, le=1), 1.0e-3),
        "heading_noise": (Number("rad/sqrt(s)", ge=1e-6, le=1), 2.0e-3),
        "gyro_bias_rate": (Number("rad/s/sqrt(s)", ge=1e-8, le=0.1), 3.0e-5),
        "accel_bias_rate": (Number("m/s^2/sqrt(s)", ge=1e-7, le=1), 2.0e-4),
        "sideslip_accel_noise": (Number("m/s^2/sqrt(s)", ge=1e-3, le=100), 2.0),
        "sideslip_accel_time": (Number("s", ge=0.01, le=100), 0.2),
        "sideslip_time": (Number("s", ge=0.01, le=1000), 5.0),
        # in a hard corner (its lean balancing a lateral acceleration g tan(roll) beyond `sideslip_dead_zone`) the
        # sideslip moves faster near the grip limit: the drive of dv_y/dt grows as sqrt(1 + (excess / this)^2)
        "sideslip_accel_noise_ref": (Number("m/s^2", ge=0.01, le=100), 1.0),
        # a yaw acceleration r' at speed u drives the sideslip by about k u^2 |r'| (k: the rear axle's load over its
        # cornering stiffness, 0.006 s^2/m for the file's scooter); the sideslip's noise grows with this x u^2 |r'| as
        # with a hard corner. Half of k: at k the quick lane changes' roll lost 0.02 deg on average (docs/estimator.md,
        # "The sideslip in a quick change of yaw")
        "sideslip_compliance": (Number("s^2/m", ge=0, le=1), 0.003),
        "sideslip_dead_zone": (Number("m/s^2", ge=0), 3.0),
        "lateral_accel_noise": (Number("m/s^2", ge=1e-3, le=10), 0.3),
        "pitch_rate_noise": (Number("rad/s", ge=1e-5, le=1), 0.01),
        "course_noise_deg": (Number("deg", ge=0.01, le=30), 0.5),
        # a long hard corner's steady sideslip (no tyre model here to tell it from heading) enters the course
        # as noise: this many rad per m/s^2 of g tan(roll) beyond `sideslip_dead_zone`
        "course_sideslip_per_accel": (Number("rad/(m/s^2)", ge=0, le=0.1), 0.015),
        "course_min_speed": (Number("m/s", gt=0, le=50), 3.0),
        "innovation_gate": (Number("", gt=1, le=100), 5.0),
        "standstill_rate_noise": (Number("rad/s", ge=1e-5, le=1), 0.003),
        "initial_roll_sd": (Number("rad", ge=1e-3, le=1.5), 0.2),
        "initial_gyro_bias_sd": (Number("rad/s", ge=1e-5, le=1), 0.01),
        # the accelerometers' biases a priori while the road's grade has not been seen level: a grade that changes from
        # the start is one the biases can take (b_az its u pitch', b_ay the roll its pitch error drifts), so tight
        "initial_accel_bias_sd": (Number("m/s^2", ge=1e-4, le=10), 0.05),
        # ... and what cheap MEMS accelerometers' offsets span (10-40 mg), applied as if from the start once the road
        # has been level for a while (docs/estimator.md, "The accelerometer's bias a priori, once the road is level");
        # not above initial_accel_bias_sd: never widened
        "level_road_accel_bias_sd": (Number("m/s^2", ge=1e-4, le=10), 0.12),
        "reopen_after_cycles": (Number("", integer=True, gt=0, le=100_000), 50),
        # consistency monitor (docs/estimator.md, "Attitude consistency"): the running means of the whitened
        # lateral-force and rotation-axis innovations, over this time constant, against this many standard
        # deviations of a white sequence's mean; beyond, the roll is not valid and the biases are re-learned
        "consistency_time": (Number("s", gt=0.05, le=30), 0.5),
        "consistency_limit": (Number("", gt=1, le=100), 4.0),
        "consistency_hold": (Number("s", ge=0, le=60), 1.0),
    },
)

# Plausibility monitor (ptw_rt/core/supervisor.py, docs/estimator.md "Plausibility"): the published rider torque
# against the UIHOSMO on the sensors', windowed RMS of their difference over a threshold per speed band. The
# thresholds are the largest windowed residual of every healthy ride of the evaluation matrix in that band, times
# 1.3 (`ptw-rt evaluate --matrix [--seed S]` prints both; 2026-11-25, over the scenarios' own seeds and seeds 3, 5,
# 7, 11: 3.51, 3.63, 4.76, 5.96 N m, and not below the values learned on the scenarios' own seeds alone).
PLAUSIBILITY_SCHEMA = Section(
    fields={},
    optional={
        "window": (Number("s", gt=0.05, le=30), 1.0),
        "band_start_kmh": (NumberList(Number("km/h", ge=0), min_len=1, max_len=8), (0.0, 30.0, 60.0, 90.0)),
        "torque_residual_nm": (NumberList(Number("N m", gt=0, le=1000), min_len=1, max_len=8), (4.6, 4.8, 6.2, 8.2)),
        "hold": (Number("s", ge=0, le=60), 1.0),
        # the two torques' disagreement that lag alone makes: a threshold sqrt(residual^2 + (lag x RMS of the
        # published torque's rate)^2), so a busy rider's quick torque is not a fault (docs/estimator.md)
        "lag": (Number("s", ge=0, le=1), 0.1),
        # the residual is not taken while the most likely tyre filter's short-window NIS (expected 5) is above
        # this: both torques come from linear-tyre models, and a slide makes them disagree whatever the sensors
        "model_max_nis_fast": (Number("", gt=0, le=1e4), 25.0),
        # s the rider torque stays not VALID after that NIS was last above its limit (a slide's NIS dips under it
        # for a cycle between two peaks)
        "model_hold": (Number("s", ge=0, le=10), 0.2),
        # the UIHOSMO channel's own roll (ptw_rt/core/channel_kinematics.py): a complementary filter, the
        # roll-rate gyro above this crossover, the accelerometer's gravity direction below it; a roll-gyro bias b
        # moves it by b / crossover at most (docs/estimator.md, "The channel's own roll")
        "roll_crossover": (Number("rad/s", gt=0.01, le=100), 1.0),
    },
)

# Tyre bank (ptw_rt/design/tyre_bank.py, ptw_rt/core/tyre_bank.py): the tyres' scale factor k from a bank
# of fusion filters, one per hypothesis of k.
TYRE_BANK_SCHEMA = Section(
    fields={},
    optional={
        "min_scale": (Number("", gt=0, le=1), 0.28),
        "max_scale": (Number("", ge=1, le=5), 1.75),
        "step": (Number("", gt=1.02, le=2), 1.15),
        "learning_memory": (Number("s", ge=0.1, le=3600), 10.0),
        "idle_memory": (Number("s", ge=0.1, le=86400), 120.0),
        "prior_sd": (Number("", ge=0.01, le=2), 0.3),
        "restored_sd": (Number("", ge=0.01, le=2), 0.15),
        "consistency_window": (Number("s", ge=0.05, le=60), 2.0),
        "fast_consistency_window": (Number("s", ge=0.01, le=10), 0.1),
        # the small-slip stiffness learns below this lean: a road of mu 0.5 then uses <= 35 % of its grip, where the
        # slope at the working point corrects the evidence (`lateral._slope_ratio`); 0.15 rad before the correction,
        # 0.175 since it: a changed road followed sooner (docs/estimator.md, "The learning range's end, again")
        "max_learning_roll": (Number("rad", gt=0, le=1.0), 0.175),
        # ... and while the longitudinal acceleration (the accelerometer's beyond its offset against GPS, over 0.3 s)
        # is within this: braking or accelerating moves load between the axles, which the filters' tyres (the
        # file's static loads) do not, and on a wet road the less loaded axle works nearer its grip: braking at
        # 4-6 m/s^2 in a corner read a front x0.81 as the file's balance (random route 963102393, seed 2255: VALID
        # 31.6 % off; docs/estimator.md, "The balance check sure of the wrong balance")
        "max_learning_long_accel": (Number("m/s^2", gt=0, le=50), 3.0),
        # ... but the published tyres count as tested (`valid_untested_time`, `settle_learning_time`) only by learning
        # below this lean: near the learning range's end on a wet road the tyres work at 25-35 % of their grip, where
        # their slope is 9-16 % below the small-slip one, and `mu_drop`'s riders, who never come more upright after
        # the drop, were VALID there 10-18 % off (docs/estimator.md, "A hypothesis that joins the window")
        "valid_test_max_roll": (Number("rad", gt=0, le=1.0), 0.12),
        "valid_log_sd": (Number("", ge=1e-3, le=0.2), 0.05),
        "valid_max_nis": (Number("", ge=0.5, le=1000), 6.0),
        # 10, not 12 (2026-11-26): with `valid_untested_time`, what keeps a road that changes in a corner from being
        # published VALID more than 20 % off (docs/estimator.md, "A road that changes where nothing tests the tyres")
        "valid_max_nis_fast": (Number("", ge=0.5, le=1000), 10.0),
        # s the tyres stay not VALID after a short-window inconsistency (a road that changed shows there first);
        # 0.5, not 2 (2026-11-26): a slalom on soft tyres spikes it for 0.1-0.4 s at every peak, and 2 s after each
        # left `slalom_30` x0.7 VALID for 18-45 % of its second half on four of five noise seeds
        "alarm_hold": (Number("s", ge=0), 0.5),
        "settle_time": (Number("s", ge=0), 2.0),
        # ... within this of where it settled (sd of log k): 0.025, half the valid spread (2026-11-27): with the
        # whole spread, a posterior that a still-converging yaw-gyro bias had collapsed 28 % off was VALID while it
        # walked back 3.7 % in 0.8 s (random routes set 4, docs/estimator.md, "The steer at the IMU's instant")
        "settle_log_sd": (Number("", gt=0, le=0.2), 0.025),
        # ... where it settled follows the estimate with this time constant (0: it stays put), so a walk slower than
        # settle_log_sd / settle_follow_time (0.5 %/s) is not a move: a posterior still converging over its 10 s of
        # memory walked 1.06 -> 1.03 in 8 s on `slalom_30` noise seed 101 and restarted the settle time at every
        # 2.5 %, VALID for 0.47 of the second half; fast moves (3.7 % in 0.8 s, 8 % in a road change) still restart
        # it (2026-11-27, docs/estimator.md, "Settled means held, and tested")
        "settle_follow_time": (Number("s", ge=0, le=600), 5.0),
        # ... of which this much learning: a hypothesis nothing has tested since it became the most likely one (the
        # lean beyond the linear range right after a road change moved the bank half-way) has not settled
        "settle_learning_time": (Number("s", ge=0), 0.5),
        "valid_min_evidence": (Number("s", ge=0), 2.0),
        # s the tyres stay VALID after the last cycle whose data tested them (learning, on data the model explains):
        # in a corner beyond `max_learning_roll`, on a straight road or a steady one nothing tests them, and a road
        # that changes there shows only in the short-window NIS, 0.2-0.4 s and 20-45 % late (docs/estimator.md)
        "valid_untested_time": (Number("s", gt=0, le=3600), 1.0),
        # the change statistic (a CUSUM of how much better a neighbouring tyre explains each cycle than the most
        # likely one, less `change_drift` nats, fading with `change_memory`): above `valid_max_change` the tyres are
        # inconsistent, as with the short-window NIS; a road changing as the lean falls into the learning range
        # fits the old tyre within its NIS (docs/estimator.md, "A road that changes where nothing tests the tyres")
        "change_drift": (Number("", gt=0, le=100), 1.0),
        "change_memory": (Number("s", gt=0, le=60), 0.3),
        "valid_max_change": (Number("", gt=0, le=1e4), 4.0),
        # the front/rear balance check: two more filters beside the most likely one, its front tyre's stiffnesses
        # times 1 / `balance_step` and `balance_step` (the rear's as they are); the one scale cannot say a front that
        # differs from the rear (pressure, wear, another make), and a front x0.8 was VALID 23 % off. How much better
        # each explains the learning cycles (with the bank's memory) is a parabola in the log of the front's factor:
        # its peak is the balance the evidence points to, its curvature with a prior of `balance_prior_sd` (log) its
        # spread. Neither axle is VALID unless that spread is within `valid_balance_log_sd` and the peak within half a
        # step of the file's balance (docs/estimator.md, "Tyres that differ by axle: the balance check")
        "balance_step": (Number("", gt=1.02, le=2), 1.15),
        "balance_prior_sd": (Number("", gt=0, le=2), 0.1),
        "valid_balance_log_sd": (Number("", gt=0, le=1), 0.04),
        # the steer zero check: two more filters beside the most likely one, its steer less a zero error of
        # -`zero_step` and +`zero_step` counts. Neither axle is VALID unless the zero error their evidence points to
        # has a spread within `valid_zero_sd` counts and lies within `zero_inner` counts of the conditioning's zero:
        # the joint fit reads the balance through a zero still being learned, but only to first order (0.5 count left
        # a front x0.81 VALID 20.2 % off while its zero was learned; docs/estimator.md, "The steer zero the balance
        # rests on")
        "zero_step": (Number("count", gt=0, le=2), 0.25),
        "valid_zero_sd": (Number("count", gt=0, le=2), 0.05),
        "zero_inner": (Number("count", gt=0, le=2), 0.05),
        "min_learning_speed": (Number("m/s", gt=0, le=100), 8.0),
        # ... and only once the attitude filter knows the yaw gyro's bias well enough: its uncertainty shifts the
        # kinematic steer the slip angles are measured against; learning waits while that could move k by more
        # than this share (1 sd), judged over `bias_window` of a_y (docs/estimator.md, "Tyres")
        "max_learning_bias_share": (Number("", gt=0, le=1), 0.1),
        # 2 s, not 5 (2026-11-27): the bank's posterior can collapse within one corner, so the shift averages out of
        # the fit only over left and right corners inside this window; over 5 s a town route's alternating corners
        # at 11 m/s let a yaw gyro 0.002-0.006 rad/s off be learned from, VALID 32 % off (docs/estimator.md)
        "bias_window": (Number("s", gt=0, le=60), 2.0),
        "excitation_window": (Number("s", ge=0.1, le=60), 2.0),
        "min_excitation_lateral_accel": (Number("m/s^2", gt=0, le=20), 0.8),
        "min_excitation_yaw_rate": (Number("rad/s", gt=0, le=5), 0.04),
        # filters run each cycle: the most likely tyre and this many on each side (a window of 2 n + 1 that
        # follows the estimate; the bank's cost is per running filter)
        "running_half_width": (Number("", integer=True, ge=1, le=64), 3),
        # no evidence about the tyres while even the best-fitting filter's short-window NIS (expected 5) is above
        # this: data no tyre explains (a faulty sensor within its range, the filters still catching up after a
        # lean beyond the tyres' linear range) would drag the estimate (25 before 2026-11-26, docs/estimator.md)
        "max_evidence_nis_fast": (Number("", gt=0, le=1e4), 10.0),
        # no hypothesis is held more than this (log-likelihood, nats) behind the best one: the most evidence a new
        # road needs to bring back a tyre the old road ruled out (mu_drop on seeds 0/3/5/7/11/13: followed within
        # 10 s on 25 of 30 rides at 30, 22 at 50; docs/estimator.md, "Memory")
        "evidence_floor": (Number("", ge=5, le=200), 30.0),
        # the most likely hypothesis (the running window's centre, where the published peak is read) changes only
        # to one that leads it by more than this (nats): near the floor a held-back tyre can take the lead for a
        # cycle on one phase of a weave and the published scale jumped 15 % for it (docs/estimator.md)
        "map_hysteresis": (Number("", ge=0, le=100), 5.0),
        # The data measure the tyres' slope where they work, which is below the small-slip stiffness once they use a
        # share of their grip (a wet road's riders learn at 25-35 % of it: 7-10 % soft). The published scale is the
        # bank's over the mean slope ratio of the cycles it learned from, for a Magic-Formula tyre
        # F = D sin(C_a atan(B_a alpha) + C_g atan(B_g gamma)) whose peak D = k x `saturation_friction` x F_z
        # falls with k (k read as the road's grip: docs/estimator.md, "The tyres' slope at their working point").
        # C_a, C_g: the tyre's shape factors (>= 1: a lateral Magic Formula's is 1.3-1.6); the correction's own
        # uncertainty, this share of its log, joins the spread the valid bit is judged on.
        "saturation_slip_shape": (Number("", ge=1.0, le=2.0), 1.5),
        "saturation_camber_shape": (Number("", ge=0.5, le=2.0), 1.0),
        "saturation_friction": (Number("", ge=0.2, le=2.0), 1.0),
        "saturation_uncertainty": (Number("", ge=0.0, le=1.0), 0.5),
        # s a hypothesis that joins the running window takes its neighbour's evidence while its filter converges
        # from the neighbour's state: the innovations of that convergence are no evidence about its tyres
        # (docs/estimator.md, "A hypothesis that joins the window")
        "join_settle_time": (Number("s", ge=0, le=10), 0.5),
    },
)

ESTIMATOR_SCHEMA = Section(
    {
        "sample_time": Number("s", ge=0.001, le=0.1),
        "speed_grid": Section(
            {
                "min_kmh": Number("km/h", gt=0, le=250),
                "max_kmh": Number("km/h", gt=0, le=250),
                "step_kmh": Number("km/h", gt=0, le=250),
            }
        ),
        "min_valid_speed_kmh": Number("km/h", gt=0, le=250),
        "uihosmo": Section(
            {
                "decay_rate": Number("1/s", ge=0.1, le=300),
                "output_weight": Number("", ge=1e-6, le=1e3),
                "differentiator_lambda": Number("", ge=0.01, le=1e5),
            }
        ),
        "adaptive": Section(
            {
                "decay_rate": Number("1/s", ge=0, le=100),
                "pole_disk_radius": Number("1/s", ge=1, le=1000),
                "stiffness_deviation_bound": Number("", gt=0, lt=1),
                "adaptation_gain": NumberList(Number("", gt=0, le=1e15), min_len=4, max_len=4),
                "excitation_slip_velocity": Number("m/s", gt=0, le=10),
                "excitation_camber_velocity": Number("m/s rad", gt=0, le=100),
                "excitation_time_constant": Number("s", ge=0.01, le=100),
            }
        ),
        "roll_fusion_time_constant": Number("s", ge=0.01, le=100),
        "fusion_filter": Section(
            {
                "process_noise": Number("1/s", ge=1e-7, le=1),
                "rider_torque_rate": Number("N m/sqrt(s)", ge=0.1, le=1000),
                "steer_noise": Number("rad", ge=1e-5, le=0.1),
                "yaw_rate_noise": Number("rad/s", ge=1e-5, le=1),
                "roll_rate_noise": Number("rad/s", ge=1e-5, le=1),
                "lateral_accel_noise": Number("m/s^2", ge=1e-3, le=10),
                "roll_noise": Number("rad", ge=1e-4, le=0.5),
            },
            optional={
                # the filters whose states are published: factors on the front and rear tyre forces' process noise
                # (their typical magnitude) over the evidence filters' (docs/estimator.md, "Published states")
                "published_force_noise": (NumberList(Number("", ge=1, le=1000), min_len=2, max_len=2), (1.0, 1.0)),
                # ... and a factor on their rider torque's random walk (`rider_torque_rate`)
                "published_torque_noise": (Number("", ge=1, le=100), 1.0),
            },
        ),
        "force_observer_yaw_bound": Number("rad/s^3", ge=0.01, le=1e4),
        "force_observer_lateral_bound": Number("m/s^3", ge=0.01, le=1e4),
        "derivative_filter_hz": Number("Hz", ge=0.1, lt=50),
        "supervisor": Section(
            {
                "converge_time": Number("s", ge=0, le=600),
                "gps_hold_time": Number("s", ge=0, le=60),
                "reason_hold_time": Number("s", ge=0, le=60),
                "stiffness_valid_after": Number("s", ge=0, le=3600),
                "max_roll": Number("rad", gt=0, le=1.5),
                "max_rider_torque": Number("N m", gt=0, le=1e4),
                "max_tyre_force": Number("N", gt=0, le=1e6),
                "max_lateral_velocity": Number("m/s", gt=0, le=100),
                "max_abs_rate": Number("rad/s", gt=0, le=50),
                "max_abs_accel": Number("m/s^2", gt=0, le=500),
                "max_gps_speed": Number("m/s", gt=0, le=150),
                "stiffness_max_residual": Number("m/s^2", gt=0, le=100),
                "adaptation_max_residual": Number("m/s^2", gt=0, le=100),
            },
            # the published roll's valid bit: 3 sigma of its own uncertainty within this. The attitude
            # filter's covariance is conservative (a sustained sideslip acceleration is not separable from
            # a roll offset by kinematics alone): measured RMS errors are 0.1-0.3 deg (docs/results.md)
            optional={"roll_tolerance_deg": (Number("deg", gt=0, le=10), 3.0)},
        ),
    },
    optional={
        "attitude": (ATTITUDE_SCHEMA, ATTITUDE_SCHEMA.check("estimator.attitude", {})),
        "tyre_bank": (TYRE_BANK_SCHEMA, TYRE_BANK_SCHEMA.check("estimator.tyre_bank", {})),
        "plausibility": (PLAUSIBILITY_SCHEMA, PLAUSIBILITY_SCHEMA.check("estimator.plausibility", {})),
    },
)

# Calibration of the sensors as mounted on this vehicle: read by the estimator's
# conditioning every cycle, not by the design, so not part of the design hash.
SENSORS_SCHEMA = Section(
    fields={},
    optional={
        "steer_zero_count": (Number("count", ge=0, lt=1024), 512.0),
        # the DBC's SteerCount is 10 bits: at most 1024 counts a revolution (below 64 a count is beyond 5.6 deg)
        "steer_counts_per_rev": (Number("count", integer=True, ge=64, le=1024), 1024),
        "imu_height": (Number("m", ge=0, le=2), 0.5),
        "imu_forward": (Number("m", ge=-2, le=2), 0.0),
        # the IMU's mount off the chassis axes, measured once at rest, upright on level ground (docs/estimator.md,
        # "A road that is not level"): its vectors are turned back into the chassis axes
        "imu_mount_roll": (Number("deg", ge=-10, le=10), 0.0),
        "imu_mount_pitch": (Number("deg", ge=-10, le=10), 0.0),
        "gps_latency": (Number("s", ge=0, le=1), 0.1),
        "speed_filter_gain": (Number("", gt=0, le=1), 0.3),
        "speed_bias_gain": (Number("", ge=0, le=1), 0.02),
        # at standstill the true body rates are zero: what the gyros read is their bias
        "gyro_calibration_speed": (Number("m/s", ge=0, le=2), 0.3),
        "gyro_calibration_time_constant": (Number("s", ge=0.1, le=3600), 5.0),
        "gyro_calibration_max_rate": (Number("rad/s", gt=0, le=1), 0.05),
        # steer-encoder zero learned riding straight (docs/estimator.md, "Steer zero"): its time constant in
        # seconds of straight riding, and how far from steer_zero_count it may move (a slipped encoder,
        # beyond, stays a fault for the steer check)
        "steer_zero_time_constant": (Number("s", gt=0, le=3600), 10.0),
        "steer_zero_max_shift": (Number("count", ge=0, le=5), 1.25),
        # how far the configured zero may be off before anything is learned (one sd): what the tyre bank's steer
        # zero check assumes of it a priori, less as it is learned (docs/estimator.md, "The steer zero the balance
        # rests on")
        "steer_zero_sd": (Number("count", gt=0, le=5), 1.0),
        # and the time constant by which the zero follows what the tyre bank's zero check sees of it in corners
        "steer_zero_evidence_time_constant": (Number("s", gt=0, le=3600), 3.0),
    },
)


class _Optional:
    """A value of ``spec`` or YAML ``null`` (None)."""

    def __init__(self, spec: Any, doc: str = "") -> None:
        self.spec = spec
        self.doc = doc or getattr(spec, "doc", "")

    def check(self, key: str, value: Any) -> Any:
        return None if value is None else self.spec.check(key, value)


class _CpuList(NumberList):
    """Distinct CPU numbers."""

    def check(self, key: str, value: Any) -> tuple:
        cpus = super().check(key, value)
        if len(set(cpus)) != len(cpus):
            raise ConfigError(f"{key}: CPU numbers must be distinct, got {excerpt(list(value))}")
        return cpus


REALTIME_SCHEMA = Section(
    fields={},
    optional={
        "priority": (
            _Optional(
                Number(
                    integer=True,
                    ge=1,
                    le=99,
                    doc="SCHED_FIFO priority of the loop thread (1..99); null leaves the scheduling to systemd",
                )
            ),
            None,
        ),
        "cpus": (
            _Optional(
                _CpuList(
                    Number(integer=True, ge=0, le=4095),
                    min_len=1,
                    doc="CPUs the loop thread may run on (e.g. [1], an isolated core); null = no change",
                )
            ),
            None,
        ),
        "lock_memory": (Flag(doc="mlockall(MCL_CURRENT|MCL_FUTURE): no page faults in the loop"), False),
    },
    doc="Real-time settings applied by the daemon at start (each one optional, never fatal)",
)

BUS_SCHEMA = Section(
    fields={},
    optional={
        "interface": (Text(doc="python-can interface: socketcan, virtual, ..."), "socketcan"),
        "channel": (Text(doc="e.g. can0, vcan0, or a virtual bus name"), "can0"),
        "bitrate": (Number("bit/s", integer=True, ge=10_000, le=8_000_000), 500000),
        "send_retries": (Number("", integer=True, ge=0, le=10), 1),
    },
)

GPS_SCHEMA = Section(
    fields={},
    optional={
        "source": (
            Text(choices=("can", "serial"), doc="can (GPS_Velocity frames) or serial (NMEA 0183 receiver)"),
            "can",
        ),
        "serial_port": (Text(doc="e.g. /dev/serial/by-id/usb-u-blox_GNSS_receiver-if00", path=True), "/dev/ttyACM0"),
        "serial_baudrate": (Number("baud", integer=True, ge=1200, le=4_000_000), 9600),
    },
)

# The daemon's own section: changing the CAN channel must not invalidate the design file, so it is not hashed.
RUNTIME_SCHEMA = Section(
    fields={},
    optional={
        "bus": (BUS_SCHEMA, BUS_SCHEMA.check("runtime.bus", {})),
        "gps": (GPS_SCHEMA, GPS_SCHEMA.check("runtime.gps", {})),
        # a message is stale after this many of its DBC cycle times without a valid frame
        "stale_after_periods": (Number("", gt=1, le=100), 3.0),
        "state_file": (Text(doc="learned tyre stiffness, saved atomically", path=True), "/var/lib/ptw-rt/state.json"),
        "state_save_interval_s": (Number("s", ge=1, le=86400), 60.0),
        "health_log_interval_s": (Number("s", ge=1, le=86400), 10.0),
        "log_repeat_interval_s": (Number("s", ge=0), 5.0),
        "log_level": (Text(choices=("DEBUG", "INFO", "WARNING", "ERROR")), "INFO"),
        "realtime": (REALTIME_SCHEMA, REALTIME_SCHEMA.check("runtime.realtime", {})),
    },
)

CONFIG_SCHEMA = Section(
    {"vehicle": VEHICLE_SCHEMA, "estimator": ESTIMATOR_SCHEMA},
    optional={
        "sensors": (SENSORS_SCHEMA, SENSORS_SCHEMA.check("sensors", {})),
        "runtime": (RUNTIME_SCHEMA, RUNTIME_SCHEMA.check("runtime", {})),
    },
)
DESIGN_SECTIONS = ("vehicle", "estimator")  # what the design file depends on (the config hash)
# What gives the learned values (tyres, sensor biases, steer zero) their meaning: the design sections but the payload.
# A rider's or a pillion's mass (``vehicle.added_mass``) changes no tyre and no sensor: a state file learned with
# one payload is restored with another (the learned tyres are N/rad of the same tyres), where the config hash,
# which the design needs, differs.
PAYLOAD_KEY = "added_mass"


def learned_state_hash(validated: dict[str, Any]) -> str:
    """The hash of ``validated``'s design sections, the vehicle's payload left out (``Settings.learned_state_hash``)."""
    sections = {k: validated[k] for k in DESIGN_SECTIONS}
    sections["vehicle"] = {k: v for k, v in validated["vehicle"].items() if k != PAYLOAD_KEY}
    return canonical_hash(sections)


@dataclass(frozen=True)
class KalmanTuning:
    """Noise model of the fusion filter (ptw_rt.design.kalman)."""

    process_noise: float  # share of the states' typical magnitude^2 per second: how far the plant strays from the model
    rider_torque_rate: float  # N m / sqrt(s): random-walk intensity of the rider torque
    steer_noise: float  # rad
    yaw_rate_noise: float  # rad/s
    roll_rate_noise: float  # rad/s
    lateral_accel_noise: float  # m/s^2
    roll_noise: float  # rad: error of the kinematic attitude filter's roll, fused as a measurement
    # the publishing filters' tyre forces (front, rear): factors on their process noise, freer of the tyre model
    published_force_noise: tuple[float, float] = (1.0, 1.0)
    published_torque_noise: float = 1.0  # ... and on their rider torque's random walk

    def measurement_sd(self) -> tuple[float, float, float, float, float]:
        """The measurements' standard deviations in the order of `ptw_rt.model.sharp.SENSOR_OUTPUTS`."""
        return (self.steer_noise, self.yaw_rate_noise, self.roll_rate_noise, self.lateral_accel_noise, self.roll_noise)


@dataclass(frozen=True)
class TyreBankTuning:
    """The tyre bank's hypotheses, memory and validity (units in TYRE_BANK_SCHEMA)."""

    min_scale: float
    max_scale: float
    step: float
    learning_memory: float
    idle_memory: float
    prior_sd: float
    restored_sd: float
    consistency_window: float
    fast_consistency_window: float
    max_learning_roll: float
    max_learning_long_accel: float
    valid_test_max_roll: float
    valid_log_sd: float
    valid_max_nis: float
    valid_max_nis_fast: float
    alarm_hold: float
    settle_time: float
    settle_log_sd: float
    settle_follow_time: float
    settle_learning_time: float
    min_learning_speed: float
    max_learning_bias_share: float
    valid_min_evidence: float
    valid_untested_time: float
    change_drift: float
    change_memory: float
    valid_max_change: float
    balance_step: float
    balance_prior_sd: float
    valid_balance_log_sd: float
    zero_step: float  # counts
    valid_zero_sd: float  # counts
    zero_inner: float  # counts
    bias_window: float
    excitation_window: float
    min_excitation_lateral_accel: float
    min_excitation_yaw_rate: float
    running_half_width: int
    max_evidence_nis_fast: float
    evidence_floor: float
    map_hysteresis: float
    join_settle_time: float
    saturation_slip_shape: float
    saturation_camber_shape: float
    saturation_friction: float
    saturation_uncertainty: float

    def scales(self) -> np.ndarray:
        """The hypotheses: powers of `step` from min_scale to max_scale; 1 (the nominal tyres) is always one. The
        design is made on them and a design file's are checked against them (`ptw_rt.design.file`)."""
        ratio = math.log(self.step)
        lo = math.ceil(math.log(self.min_scale) / ratio - 1e-9)
        hi = math.floor(math.log(self.max_scale) / ratio + 1e-9)
        return np.exp(np.arange(lo, hi + 1) * ratio)


@dataclass(frozen=True)
class PlausibilityTuning:
    """The plausibility monitor's window, thresholds per speed band and hold (units in PLAUSIBILITY_SCHEMA)."""

    window: float
    band_start_kmh: tuple[float, ...]
    torque_residual_nm: tuple[float, ...]
    hold: float
    lag: float
    model_max_nis_fast: float
    model_hold: float
    roll_crossover: float

    def __post_init__(self) -> None:
        starts = self.band_start_kmh
        if len(starts) != len(self.torque_residual_nm):
            raise ConfigError(
                "estimator.plausibility: band_start_kmh and torque_residual_nm must have the same length, got "
                f"{len(starts)} and {len(self.torque_residual_nm)}"
            )
        if starts[0] != 0.0 or any(b <= a for a, b in zip(starts, starts[1:], strict=False)):
            raise ConfigError(f"estimator.plausibility.band_start_kmh: must start at 0 and increase, got {starts}")


@dataclass(frozen=True)
class AttitudeTuning:
    """Noise model of the kinematic attitude filter (ptw_rt.core.attitude); units in ATTITUDE_SCHEMA."""

    roll_noise: float
    heading_noise: float
    gyro_bias_rate: float
    accel_bias_rate: float
    sideslip_accel_noise: float
    sideslip_accel_time: float
    sideslip_time: float
    sideslip_accel_noise_ref: float
    sideslip_compliance: float
    sideslip_dead_zone: float
    lateral_accel_noise: float
    pitch_rate_noise: float
    course_noise_deg: float
    course_sideslip_per_accel: float
    course_min_speed: float
    innovation_gate: float
    standstill_rate_noise: float
    initial_roll_sd: float
    initial_gyro_bias_sd: float
    initial_accel_bias_sd: float
    level_road_accel_bias_sd: float
    reopen_after_cycles: int
    consistency_time: float
    consistency_limit: float
    consistency_hold: float


@dataclass(frozen=True)
class EstimatorTuning:
    sample_time: float
    grid_min_kmh: float
    grid_max_kmh: float
    grid_step_kmh: float
    min_valid_speed_kmh: float
    uihosmo_decay_rate: float
    uihosmo_output_weight: float
    differentiator_lambda: float
    decay_rate: float
    pole_disk_radius: float
    stiffness_deviation_bound: float
    adaptation_gain: tuple[float, ...]
    excitation_slip_velocity: float
    excitation_camber_velocity: float
    excitation_time_constant: float
    roll_fusion_time_constant: float
    kalman: KalmanTuning
    attitude: AttitudeTuning
    plausibility: PlausibilityTuning
    tyre_bank: TyreBankTuning
    force_observer_yaw_bound: float
    force_observer_lateral_bound: float
    derivative_filter_hz: float
    converge_time: float
    gps_hold_time: float
    reason_hold_time: float
    stiffness_valid_after: float
    max_roll: float
    max_rider_torque: float
    max_tyre_force: float
    max_lateral_velocity: float
    max_abs_rate: float
    max_abs_accel: float
    max_gps_speed: float
    stiffness_max_residual: float
    adaptation_max_residual: float
    roll_tolerance_deg: float

    def speed_grid_ms(self) -> np.ndarray:
        """Design grid in m/s; the end points are always included."""
        n = int(round((self.grid_max_kmh - self.grid_min_kmh) / self.grid_step_kmh))
        return np.linspace(self.grid_min_kmh, self.grid_max_kmh, n + 1) / 3.6


@dataclass(frozen=True)
class SensorSettings:
    """``sensors:``: calibration of the sensors as mounted on this vehicle (read by the estimator's conditioning)."""

    steer_zero_count: float  # encoder count with the wheel straight ahead
    steer_counts_per_rev: int
    imu_height: float  # m above the ground
    imu_forward: float  # m ahead of the centre of mass
    imu_mount_roll: float  # deg the IMU is mounted rolled (right side down) off the chassis axes
    imu_mount_pitch: float  # deg ... pitched (nose up)
    gps_latency: float  # s
    speed_filter_gain: float
    speed_bias_gain: float
    gyro_calibration_speed: float  # m/s: below it the gyros read their bias
    gyro_calibration_time_constant: float  # s
    gyro_calibration_max_rate: float  # rad/s
    steer_zero_time_constant: float  # s of straight riding
    steer_zero_max_shift: float  # counts
    steer_zero_sd: float  # counts: the configured zero's error a priori (sd)
    steer_zero_evidence_time_constant: float  # s

    @property
    def steer_count_rad(self) -> float:
        """One count of the steering encoder [rad]."""
        return 2.0 * math.pi / self.steer_counts_per_rev


@dataclass(frozen=True)
class BusSettings:
    """``runtime.bus:``"""

    interface: str  # python-can interface
    channel: str
    bitrate: int  # bit/s, for interfaces that set it themselves (not socketcan: ip link does)
    send_retries: int


@dataclass(frozen=True)
class GpsSettings:
    """``runtime.gps:``: where the speed comes from."""

    source: str  # "can" (GPS_Velocity frames) or "serial" (NMEA 0183 RMC/VTG receiver)
    serial_port: str
    serial_baudrate: int


@dataclass(frozen=True)
class RealtimeSettings:
    """``runtime.realtime:``; None/False: leave as it is."""

    priority: int | None  # SCHED_FIFO priority of the loop thread
    cpus: tuple[int, ...] | None  # CPU affinity of the loop thread
    lock_memory: bool


@dataclass(frozen=True)
class RuntimeSettings:
    """``runtime:``: the daemon's own settings (not part of the config hash)."""

    bus: BusSettings
    gps: GpsSettings
    stale_after_periods: float
    state_file: str | None
    state_save_interval_s: float
    health_log_interval_s: float
    log_repeat_interval_s: float
    log_level: str
    realtime: RealtimeSettings


@dataclass(frozen=True)
class Settings:
    source: str
    vehicle: VehicleParameters
    estimator: EstimatorTuning
    config_hash: str
    sensors: SensorSettings
    runtime: RuntimeSettings
    learned_state_hash: str  # the config hash but for the payload: whose learned state this one may restore


def _typed(cls: type, values: dict[str, Any]) -> Any:
    """A section's dataclass from its validated mapping (the schema has checked every key and value)."""
    return cls(**{f.name: values[f.name] for f in fields(cls)})


def sensors_from_mapping(values: dict[str, Any]) -> SensorSettings:
    return _typed(SensorSettings, values)


def runtime_from_mapping(values: dict[str, Any]) -> RuntimeSettings:
    return RuntimeSettings(
        **{
            **{k: v for k, v in values.items() if k not in ("bus", "gps", "realtime")},
            "bus": _typed(BusSettings, values["bus"]),
            "gps": _typed(GpsSettings, values["gps"]),
            "realtime": _typed(RealtimeSettings, values["realtime"]),
        }
    )


def runtime_defaults() -> RuntimeSettings:
    """The ``runtime:`` section of a config file that has none."""
    return runtime_from_mapping(RUNTIME_SCHEMA.check("runtime", {}))


# design speeds a config may ask for (10-130 km/h every 0.5 km/h is 241; the file's default is 49): a step of 0.01
# km/h asked for 12 000 designs, a step of 1e-9 for an array of 894 GiB
MAX_GRID_SPEEDS = 250


def _tuning(est: dict[str, Any], source: str) -> EstimatorTuning:
    grid = est["speed_grid"]
    if grid["max_kmh"] <= grid["min_kmh"]:
        raise ConfigError(f"{source}: estimator.speed_grid.max_kmh must be above min_kmh")
    if grid["step_kmh"] > grid["max_kmh"] - grid["min_kmh"]:
        raise ConfigError(f"{source}: estimator.speed_grid.step_kmh is larger than the grid span")
    speeds = (grid["max_kmh"] - grid["min_kmh"]) / grid["step_kmh"] + 1
    if speeds > MAX_GRID_SPEEDS:
        raise ConfigError(
            f"{source}: estimator.speed_grid gives {speeds:.0f} design speeds, at most {MAX_GRID_SPEEDS}: raise "
            "step_kmh (each speed is a design of every observer, and a table row in the design file the daemon loads)"
        )
    if est["min_valid_speed_kmh"] > grid["max_kmh"]:
        raise ConfigError(
            f"{source}: estimator.min_valid_speed_kmh ({est['min_valid_speed_kmh']}) is above the design grid "
            f"(speed_grid.max_kmh = {grid['max_kmh']}): nothing would ever be valid"
        )
    if est["min_valid_speed_kmh"] < grid["min_kmh"]:
        raise ConfigError(
            f"{source}: estimator.min_valid_speed_kmh ({est['min_valid_speed_kmh']}) is below the design grid "
            f"(speed_grid.min_kmh = {grid['min_kmh']}): there would be no gains for those speeds"
        )
    ad = est["adaptive"]
    return EstimatorTuning(
        sample_time=est["sample_time"],
        grid_min_kmh=grid["min_kmh"],
        grid_max_kmh=grid["max_kmh"],
        grid_step_kmh=grid["step_kmh"],
        min_valid_speed_kmh=est["min_valid_speed_kmh"],
        uihosmo_decay_rate=est["uihosmo"]["decay_rate"],
        uihosmo_output_weight=est["uihosmo"]["output_weight"],
        differentiator_lambda=est["uihosmo"]["differentiator_lambda"],
        decay_rate=ad["decay_rate"],
        pole_disk_radius=ad["pole_disk_radius"],
        stiffness_deviation_bound=ad["stiffness_deviation_bound"],
        adaptation_gain=tuple(ad["adaptation_gain"]),
        excitation_slip_velocity=ad["excitation_slip_velocity"],
        excitation_camber_velocity=ad["excitation_camber_velocity"],
        excitation_time_constant=ad["excitation_time_constant"],
        roll_fusion_time_constant=est["roll_fusion_time_constant"],
        kalman=KalmanTuning(**est["fusion_filter"]),
        attitude=AttitudeTuning(**est["attitude"]),
        plausibility=PlausibilityTuning(**est["plausibility"]),
        tyre_bank=TyreBankTuning(**est["tyre_bank"]),
        force_observer_yaw_bound=est["force_observer_yaw_bound"],
        force_observer_lateral_bound=est["force_observer_lateral_bound"],
        derivative_filter_hz=est["derivative_filter_hz"],
        **est["supervisor"],
    )


def settings_from_mapping(doc: Any, source: str) -> Settings:
    validated = validate(doc, CONFIG_SCHEMA, source)
    vehicle = vehicle_from_mapping(doc["vehicle"], source)
    return Settings(
        source=source,
        vehicle=vehicle,
        estimator=_tuning(validated["estimator"], source),
        config_hash=canonical_hash({k: validated[k] for k in DESIGN_SECTIONS}),
        sensors=_sensors(validated["sensors"], source),
        runtime=runtime_from_mapping(validated["runtime"]),
        learned_state_hash=learned_state_hash(validated),
    )


def _sensors(values: dict[str, Any], source: str) -> SensorSettings:
    if values["steer_zero_count"] >= values["steer_counts_per_rev"]:
        raise ConfigError(
            f"{source}: sensors.steer_zero_count ({values['steer_zero_count']}) must be below steer_counts_per_rev "
            f"({values['steer_counts_per_rev']})"
        )
    return sensors_from_mapping(values)


def load_settings(path: str | Path) -> Settings:
    return settings_from_mapping(read_yaml(path), str(path))
