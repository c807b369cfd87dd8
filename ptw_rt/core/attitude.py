"""Kinematic attitude filter: roll from the gyros and the accelerometer, no tyre model (jitted, allocation-free).

Why it exists (docs/estimator.md, "Attitude"): roll from the Sharp model depends on the tyres the model
assumes; every real scooter's tyres differ. Rigid-body kinematics do not: the gyros integrate roll, the
accelerometer sees gravity once the motion terms are removed, and two exact constraints pin what the
gyros cannot:

- **Lateral specific force** (100 Hz). In yaw-frame axes (x along the heading, y right, z down), at the
  IMU mounted ``h`` above ground and ``x_i`` ahead of the reference point (the simulator's and the
  chassis' geometry, ``docs/simulator.md``):

      a_y = a_v + u r + x_i r' - h r^2 sin(phi) + h (cos(phi) phi'' - sin(phi) phi'^2)
      a_z = h (sin(phi) phi'' + cos(phi) phi'^2)
      f_y(body) = a_y cos(phi) + (a_z - g) sin(phi) + b_ay

  with ``r`` the ground yaw rate, ``a_v`` = dv_y/dt (a first-order Markov state: sideslip transients
  are short and v_y is bounded) and ``b_ay`` the accelerometer bias. The lever-arm terms need phi''
  and r': they are taken as central differences, so the filter processes each cycle's measurement one
  cycle late (a lagged derivative here costs more than 1 deg of roll in a long turn, tested) and
  predicts the current roll with the gyro.
- **Horizontal rotation axis** (100 Hz): off a pitching road the vehicle turns about the vertical, so
  the body rates satisfy (q - b_q) cos(phi) - (r_b - b_r) sin(phi) = pitch rate ~ 0. In a turn this
  gives roll independently of the accelerometer (d/dphi = -r): it is what separates roll from an
  accelerometer bias, which the lateral force alone cannot.
- **GPS course over ground** (10 Hz, 0.1 s latency): course = psi + v_y / u, which makes the yaw-gyro
  bias observable without a stop.
- **Standstill**: zero rates, zero sideslip (the gyro biases are read directly).

In a steady turn one direction of (phi, b_q, b_r, b_ay) is still unobservable (a roll error with the
matching biases fits every constraint); straights and changes of lean remove it. The biases are random
walks and survive a restart of the dynamic states.

- **A road that is not level**: on a slope (or with the suspension's sag) the gyro's roll axis is pitched, and the
  turn about the vertical leaks into it: roll' = p + tan(pitch) r_ground, heading' = r_ground / cos(pitch). The
  pitch is a state, taught by the turns (the roll drifts by tan(pitch) r_ground where the accelerometer says it does
  not) and seeded by the speed stage's longitudinal offset, g sin(pitch) + b_ax (`speed.OUT_ACCEL_OFFSET`).
- **A road whose grade changes**: the pitch rate is a state the gyros measure and the vertical accelerometer feels
  (u pitch', with its bias b_az), free to move only while both see the chassis pitch.

Extended Kalman filter on x = [phi, psi, b_p, b_q, b_r, b_ay, pitch, b_ax, b_az, pitch rate, v_y, a_v]; innovations
beyond ``gate`` standard deviations are not applied (counted in OUT_REJECTED).

Stage 3 of the estimator (`attitude_stage`, at the end of this module): the filter fed from the inputs and
speed stages' outputs, with standstill detection and the GPS course; `attitude_step` is the filter alone.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import inputs as inp
from ptw_rt.core import speed as spd
from ptw_rt.core.layout import REASON_COUNTER_JUMPS, REASON_DECODE_ERRORS, REASON_OUT_OF_RANGE, REASON_SPEED_LOW
from ptw_rt.core.stage import Layout, Stage, all_finite

# ---- filter state x ----
X_PHI = 0  # rad, roll (SAE: positive leaning right)
X_PSI = 1  # rad, heading (unwrapped)
X_BP = 2  # rad/s, roll-gyro bias
X_BQ = 3  # rad/s, pitch-gyro bias
X_BR = 4  # rad/s, yaw-gyro bias
X_BAY = 5  # m/s^2, lateral accelerometer bias
X_PITCH = 6  # rad, the IMU's pitch off the level (a road's slope, the suspension's sag, a mount not square)
X_BAX = 7  # m/s^2, longitudinal accelerometer bias (what of the speed stage's offset is not g sin(pitch))
X_BAZ = 8  # m/s^2, vertical accelerometer bias
X_PITCH_RATE = 9  # rad/s, the rate the road's grade turns the chassis at (a crest, a dip): the pitch's derivative
X_VY = 10  # m/s, lateral velocity of the reference point
X_AV = 11  # m/s^2, its derivative
N_X = 12
N_BIASES = X_BAZ - X_BP + 1  # the slow states, X_BP .. X_BAZ (contiguous): kept on a restart
N_DYNAMIC_STATES = (X_PHI, X_PSI, X_PITCH_RATE, X_VY, X_AV)  # reset on a restart; the biases are kept

# ---- state buffer layout ----
# inputs of the previous cycle (processed one cycle late), at ST_PREV + PREV_*
PREV_P, PREV_Q, PREV_R, PREV_FY, PREV_U, PREV_U_VAR, PREV_OK, PREV_P2, PREV_RG, PREV_RG2, PREV_RATES_OK = range(11)
PREV_RATES_OK2 = 11  # the rates of the cycle before the previous one were measured (PREV_P2's, PREV_RG2's)
PREV_P3 = 12  # the roll rate three cycles back, and the lateral specific force two and three cycles back: the
PREV_FY2 = 13  # roll-gyro step check's samples (`_roll_gyro_step`)
PREV_FY3 = 14
PREV_FZ = 15  # the vertical specific force
N_PREV = 16
MAX_LATENCY_CYCLES = 32
STATE = Layout(
    "ST_",
    x=N_X,  # the filter state x
    p=N_X * N_X,  # its covariance, row-major
    init=1,  # 1 once initialised (2: restart the dynamic states, biases kept)
    psi_init=1,  # 1 once the heading has been set from a GPS course
    prev=N_PREV,  # inputs of the previous cycle (processed one cycle late)
    psi_hist=MAX_LATENCY_CYCLES,  # heading increments of the last LATENCY_CYCLES cycles (GPS latency)
    # sideslip angles v_y / u of the last cycles (newest first), as the measurements left them: the course describes
    # the vehicle `latency` ago, its sideslip as well as its heading
    beta_hist=MAX_LATENCY_CYCLES,
    psi_head=1,
    rejected=1,  # consecutive rejected lateral-force innovations
    quiet=1,  # consecutive lateral-force innovations applied and within QUIET_NU (when a reopened roll is safe)
    nu=1,  # whitened innovation e / sqrt(s) of the last scalar update (written by `_update`, gated out or not)
    # the stage's consistency monitor (attitude_stage):
    mean_lateral=1,  # running mean of the whitened lateral-force innovations
    mean_pitch=1,  # ... of the rotation-axis constraint's
    mean_course=1,  # ... of the GPS course's (updated per fix)
    inconsistent_for=1,  # s the monitor has still to hold its alarm
    reacquired=1,  # 1 once this alarm has reopened the biases, 2 once it has reopened the roll too (once per alarm)
    course_rejected=1,  # consecutive GPS course fixes gated out
    held=1,  # consecutive cycles that integrated a held rate
    corrupt_run=1,  # cycles with corrupt input in the current burst (clean gaps shorter than BURST_GAP allowed)
    clean_run=1,  # consecutive cycles without corrupt input
    burst_biases=N_BIASES,  # the slow states (b_p .. b_az) as the current burst found them (only updates move them)
    burst_roll_moved=1,  # rad, what the measurement updates have moved the roll by since the burst began
    yaw_accel=1,  # rad/s^2, the ground yaw rate's derivative, low-passed over YAW_ACCEL_TIME (the sideslip's drive)
    imu_fresh_run=1,  # consecutive cycles with new sound samples of the gyros and accelerometer (`_roll_gyro_step`)
    step_ms=1,  # (rad/s)^2, running mean square of the roll-gyro step statistic in healthy riding (its noise)
    step_ms_samples=1,  # statistics that went into step_ms, up to GYRO_STEP_LEARN_CYCLES (kept over a restart)
    standstill_ms=1,  # (rad/s)^2, the gyros' mean square about their biases at standstill (their noise as read)
    standstill_samples=1,  # standstill cycles that went into it, up to STANDSTILL_NOISE_CYCLES
    step_last=1,  # rad/s, that statistic in the previous cycle (0 without one)
    step_candidate=1,  # rad/s, a step the last cycle's statistic found, taken if this cycle's confirms it (else 0)
    step_before=1,  # rad/s, the statistic before that candidate
    pitch_lag=1,  # rad, how far the pitch has turned beyond its running mean over the speed stage's offset window
    pitch_rate_seen=1,  # rad/s, the gyros' pitch rate (q cos(roll) - r sin(roll), bias-corrected), low-passed
    pitch_rate_felt=1,  # rad/s, the pitch rate the vertical accelerometer implies (u pitch'), low-passed
    turn_accel_mean=1,  # m/s^2, what a turn adds along x at the IMU (`turn_accel_along`), over the offset's window
    offset_doubt=1,  # m/s^2, running mean of the longitudinal offset's innovations over OFFSET_DOUBT_TIME
    level_for=1,  # s the road has been seen level, riding (LEVEL_ROAD_TIME)
    # the start's test of a grade's rate (`_grade_start_test`), armed by a start from nothing:
    grade_test_due=1,  # 1 until the test has run (0: run, or the biases were read at standstill first)
    grade_test_seen=1,  # rad/s, sum over its cycles of the gyros' raw pitch rate (no bias taken off) ...
    grade_test_felt=1,  # rad/s, ... of the vertical accelerometer's (no bias taken off) ...
    grade_test_rate=1,  # rad/s, ... of the filter's grade rate ...
    grade_test_cycles=1,  # ... and their count
    grade_found=1,  # 1 once the test gave the start's pitch rate to the grade (the biases re-split)
    level_prior_due=1,  # 1 while the accelerometers' biases still hold the tight prior a level road widens (once)
    tmp=3 * N_X + N_X * N_X,  # scratch: K, H, PH (3 N_X) and an N_X x N_X product
)
(
    ST_X,
    ST_P,
    ST_INIT,
    ST_PSI_INIT,
    ST_PREV,
    ST_PSI_HIST,
    ST_BETA_HIST,
    ST_PSI_HEAD,
    ST_REJECTED,
    ST_QUIET,
    ST_NU,
    ST_MEAN_LATERAL,
    ST_MEAN_PITCH,
    ST_MEAN_COURSE,
    ST_INCONSISTENT_FOR,
    ST_REACQUIRED,
    ST_COURSE_REJECTED,
    ST_HELD,
    ST_CORRUPT_RUN,
    ST_CLEAN_RUN,
    ST_BURST_BIASES,
    ST_BURST_ROLL_MOVED,
    ST_YAW_ACCEL,
    ST_IMU_FRESH_RUN,
    ST_STEP_MS,
    ST_STEP_MS_SAMPLES,
    ST_STANDSTILL_MS,
    ST_STANDSTILL_SAMPLES,
    ST_STEP_LAST,
    ST_STEP_CANDIDATE,
    ST_STEP_BEFORE,
    ST_PITCH_LAG,
    ST_PITCH_RATE_SEEN,
    ST_PITCH_RATE_FELT,
    ST_TURN_ACCEL_MEAN,
    ST_OFFSET_DOUBT,
    ST_LEVEL_FOR,
    ST_GRADE_TEST_DUE,
    ST_GRADE_TEST_SEEN,
    ST_GRADE_TEST_FELT,
    ST_GRADE_TEST_RATE,
    ST_GRADE_TEST_CYCLES,
    ST_GRADE_FOUND,
    ST_LEVEL_PRIOR_DUE,
    ST_TMP,
) = STATE.offsets
STATE_SIZE = STATE.size
# rad/s: what a rate not measured this cycle (held, frozen or corrupt frames) may be, as far as the filter knows
UNMEASURED_RATE_SD = 0.5
# rad/s: the gyros' full scale, IMU_Rates' range in the DBC (tests/test_dbc.py holds the two together). A reading at
# it is a body turning at least that fast: in a fall the roll rate reached 6 rad/s while the gyro read 3.0, and the
# integrated roll ran 5 deg behind, VALID (random set 81, `radius_accel` seed 8539). Such a rate is as unknown as a
# held one (UNMEASURED_RATE_SD), and the roll's and the heading's uncertainty grow alike
GYRO_FULL_SCALE = 3.0
GYRO_SATURATED = GYRO_FULL_SCALE - 1e-3  # one count of the frame's 0.0001 rad/s, and margin
# m/s^2: the most lateral acceleration a tyre can give (~1.2 g); what scales the sideslip's noise is bounded by it,
# so no roll (near 90 deg, tan grows without bound) can blow the covariance up
MAX_LATERAL_ACCEL = 12.0
# s: the low pass of the ground yaw acceleration that drives the sideslip's noise (a central difference of the gyro
# alone is ~0.2 rad/s^2 of noise)
YAW_ACCEL_TIME = 0.1
# The accelerometer's specific force is trusted for the lateral-force and the gravity constraints only while its
# magnitude is one a riding vehicle has (braking at 1 g beside gravity is 1.4 g; a pothole's spike is not a
# measurement of the lean): outside, that cycle's accelerometer is not used (a garbage sample of 4 m/s^2 that
# passed every range check once corrected the roll 6 deg the wrong way with a collapsed uncertainty)
# A burst of corrupt input (out-of-range values, broken counters, undecodable frames: garbage that reached the
# sensors' frames) of at least BURST_CYCLES cycles, with clean gaps shorter than BURST_GAP: whatever of it passed
# every check may have moved the biases along the direction a steady turn cannot observe (a roll error with
# matching biases), so once per burst, when it ends, the biases' and the roll's uncertainty grow by what the
# burst's updates moved them (`_doubt_what_the_burst_moved`): the roll is VALID again only when the data have
# pinned it down again (random garbage bursts into a steady turn: see docs/estimator.md, "Known gaps").
BURST_CYCLES = 10
BURST_GAP = 10
_CORRUPT_INPUT = REASON_OUT_OF_RANGE | REASON_COUNTER_JUMPS | REASON_DECODE_ERRORS
# The roll is reopened after an alarm (`_reacquire_roll`; the biases at once) only once the lateral force has been
# explained for QUIET_CYCLES in a row, each innovation within QUIET_NU of its sd: the roll reopened by its initial
# spread (11 deg) widens the gate of the next lateral-force update, and in a slide, or a wheel unloaded in its
# recovery, the specific force is one no lean explains: it moved the roll 22-44 deg in one cycle (random
# combined-perturbation rides, docs/estimator.md "Attitude consistency"). A bias that stepped shows as a shift of
# 1-3 sd that a white sequence does not have, well within QUIET_NU most cycles, so it is not kept waiting.
QUIET_CYCLES = 20
QUIET_NU = 3.0
ACCEL_TRUSTED_MIN_G = 0.5
ACCEL_TRUSTED_MAX_G = 2.0
# s between GPS fixes: the contract's 10 Hz GPS_Velocity (a slower serial receiver only makes the course's
# running mean in the consistency monitor shorter, in fixes, and so less sensitive, never more)
GPS_FIX_INTERVAL = 0.1
NU_CLIP = 2.0  # standard deviations: bound of each whitened innovation in the consistency monitor's means
# consecutive GPS course fixes gated out after which the heading is taken from the course again: a heading
# that drifted beyond the gate (a long GPS outage on a biased yaw gyro) would otherwise refuse every fix
# for the rest of the ride, and with them the yaw-gyro bias's only reference while riding
COURSE_REINIT_FIXES = 10
INITIAL_VY_SD = 0.5  # m/s: a gripping vehicle's sideslip velocity, a priori
INITIAL_AV_SD = 1.0  # m/s^2: its rate
# Riding straight, a gripping vehicle does not slide: v_y is zero within a tenth of a m/s (road camber, a crosswind).
# The filter's sideslip model (v_y' = a_v - v_y / sideslip_time) lets a steady a_v and a v_y of sideslip_time times it
# hold each other, and the lateral-force measurement reads that a_v as a lateral force: the pair then carries a roll
# error of a_v / g for as long as nothing else contradicts it (a hard braking in a corner left the roll 0.65 deg off
# for 30 s on the straight after it, and the tyres learned on it: docs/estimator.md, "The sideslip on a straight").
# Each cycle of straight riding measures v_y = 0 with a variance such that a second of it says STRAIGHT_SIDESLIP_SD.
STRAIGHT_SIDESLIP_SD = 0.1  # m/s, over STRAIGHT_SIDESLIP_TIME of straight riding
STRAIGHT_SIDESLIP_TIME = 1.0  # s
# straight: a lean, a ground yaw rate and its low-passed rate of change below these (at 50 km/h a yaw rate of 0.03
# rad/s is a curve of 460 m radius and 0.4 m/s^2 of lateral acceleration: its steady sideslip is a few cm/s)
STRAIGHT_MAX_ROLL = 0.05  # rad
STRAIGHT_MAX_YAW_RATE = 0.03  # rad/s
STRAIGHT_MAX_YAW_ACCEL = 0.05  # rad/s^2
# The pitch (docs/estimator.md, "A road that is not level"): roads climb and fall by up to ~6 deg (10 %), and an IMU
# is mounted square to a degree or two. In a turn the vertical the vehicle turns about then has a part along the
# gyro's roll axis, roll' = p + tan(pitch) r_ground: on a 3 deg slope 0.05 r, the roll off by a degree in town.
INITIAL_PITCH_SD = 0.1  # rad, a priori
# What of the pitch's change its rate does not carry. Small: a pitch that may walk on its own lets a false pitch rate
# (a gyro bias learned wrong, in a long corner) run for tens of seconds while the longitudinal accelerometer, which
# sees every degree of pitch as 0.17 m/s^2 against the GPS, says the pitch never moved (0.005 before the rate was a
# state: docs/estimator.md, "The pitch carried by its rate")
PITCH_DRIFT = 0.001  # rad/sqrt(s)
# A road's grade changes: over a crest or through a dip the chassis pitches, at u over the vertical curve's radius
# (a 4 deg swing of the grade every 300 m: 0.0015 / m, 0.015 rad/s at 36 km/h). The gyros measure that rate,
# q cos(roll) - r sin(roll), and a turn on a level road makes none (its axis is vertical), so the pitch rate is a state,
# a first-order Markov process:
PITCH_RATE_SD = 0.015  # rad/s, its stationary spread on a hilly road ...
PITCH_RATE_TIME = 5.0  # s, its correlation time ...
# ... at and below this speed. The rate is the speed times the road's vertical curvature, which keeps over a distance,
# not a time: faster, the same road's spread grows with u and its correlation time shrinks as 1/u (a 4.5 deg swing
# every 240 m at 117 km/h turns the chassis at up to 0.067 rad/s, 4.4 spreads of the 36 km/h process, which lagged it
# and raised the consistency alarm that re-opened the roll: docs/estimator.md, "The grade's rate at speed")
GRADE_REFERENCE_SPEED = 10.0  # m/s
# ... but a level road's turns are where the gyros' split of the turn tells the roll (their pitch rate is zero), and a
# free pitch rate takes part of that: the rate's drive (and its prior) opens only as far as both the gyros' pitch rate
# and the one the vertical accelerometer implies, each low-passed over PITCH_RATE_SEEN_TIME, show one beyond
# PITCH_RATE_LEVEL (drive x seen^2 / (seen^2 + level^2), seen the smaller of the two; docs/estimator.md, "A road
# whose grade changes")
PITCH_RATE_SEEN_TIME = 1.0  # s
PITCH_RATE_LEVEL = 0.003  # rad/s
# The accelerometers' biases a priori. On a straight the lateral one and the roll are one offset, which only corners
# split, in the proportion of their priors until then; what cheap MEMS offsets span (`level_road_accel_bias_sd`,
# 12 mg) leaves the roll less of it than the tight `initial_accel_bias_sd` (5 mg). But a grade that changes from the
# start is one the biases take too (b_q its pitch rate, b_az the u pitch' it adds, b_ay the roll a wrong pitch drifts
# in the turns: a hilly road's roll VALID 2.4 deg off with the wide prior from the start). So the wide prior is
# applied only once both the gyros' and the vertical accelerometer's pitch rates have shown a level road for
# LEVEL_ROAD_TIME (1 s: a handling road's crest, its rate still in b_q, passed for one), and then as if from the start
# (`_widen_prior`). A start on a grade changing at a steady rate looks level to both once b_q and b_az have taken the
# rate; the start's test (`_grade_start_test`, GRADE_TEST_TIME) takes it back where the two raw rates agree beyond
# what their biases span (docs/estimator.md, "The accelerometer's bias a priori, once the road is level" and "The
# start on a changing grade")
LEVEL_ROAD_TIME = 2.0  # s
GRADE_KNOWN_BIAS_SD = 0.0035  # rad/s: a pitch gyro's bias this sure starts the grade's rate open
GRADE_DOUBT_CLOSES = 2.0  # the drive closes as the lateral innovations' running mean nears half the monitor's limit
GRADE_MIN_SPEED = 3.0  # m/s: below it the vertical accelerometer's u pitch' is too small to tell a pitch rate ...
GRADE_MAX_ROLL_COS = 0.5  # ... and leaning beyond 60 deg (a fall) its part along the body's z axis
VERTICAL_ACCEL_NOISE = 0.2  # m/s^2 per cycle (the simulator's; a real engine's vibration is not measured here)
# The speed stage's longitudinal offset, g sin(pitch) + b_ax over its last 3 s against GPS, is a measurement of
# their sum; a turn tells the pitch from the accelerometer's bias (the roll drifts by tan(pitch) r_ground). The
# offset is a running mean (its pitch lags by `pitch_lag`, a turn's part in it by `turn_accel_mean`)
# whose error is correlated over seconds, so each cycle's is taken with this noise (its information over 3 s is that
# of one 0.06 m/s^2 reading; 5 before the lag and the turn's part were modelled, 0.5 - 5 no better since)
ACCEL_OFFSET_NOISE = 1.0  # m/s^2 per cycle
# That offset is the one witness of the pitch no gyro or vertical-accelerometer bias moves. A pitch held wrong while
# the grade turns (from nothing on a changing grade, b_q takes the grade's rate and the rate's gate stays shut)
# leaves its innovations one-signed for as long as the rate is wrong; their running mean over OFFSET_DOUBT_TIME
# (once the offset's own window is full) beyond OFFSET_DOUBT_LEVEL is OUT_PITCH_DOUBT >= 1, and the tyres do not
# learn on the roll rate and lateral force such a pitch bends (docs/estimator.md, "The pitch doubted by the
# longitudinal accelerometer": level roads' 0.008-0.055 m/s^2, hilly starts' 0.08-0.19)
OFFSET_DOUBT_TIME = 3.0  # s
OFFSET_DOUBT_LEVEL = 0.05  # m/s^2
# From nothing at speed on a grade that changes, the level road's prior on the grade's rate gives most of the gyros'
# pitch rate to b_q (and the u pitch' the vertical accelerometer feels to b_az) within the first second, and nothing
# takes it back before the rate changes: the pitch then runs degrees off for tens of seconds and the roll with it
# (`dlc_100` on a 5 deg swing every 210 m: b_q 0.06 rad/s for -0.002, the pitch 3-4.5 deg off). But two sensors' biases
# are independent and a grade's rate is common to both: over the first GRADE_TEST_TIME of riding the gyros' and the
# vertical accelerometer's raw pitch rates (no bias taken off) are averaged and weighed under both hypotheses, biases
# alone (each N(0, its spread): the gyros' prior; the accelerometer's as wide as cheap MEMS offsets span) or a grade's
# rate (N(0, a hilly road's spread), the same in both) beside them
# (`_grade_odds`). Where the grade explains them GRADE_TEST_ODDS times better, the rate is the two readings' common part
# and each bias the rest of its own sensor's, and the pitch is turned by what the rate turned it over the test
# (`_grade_start_test`; docs/estimator.md, "The start on a changing grade"). A level road's biases do not agree like
# that: every matrix ride's figures are the same to the digit. A start at rest reads the biases at standstill instead
GRADE_TEST_TIME = 1.0  # s
GRADE_TEST_ODDS = 20.0
# A step of the roll-rate gyro's bias (a shock, a sensor that restarts on a stale calibration) is a jump of its level
# between two samples that no roll acceleration made; riding straight nothing else tells it from a sideslip within
# the 1 s the roll's tolerance leaves (docs/estimator.md, "A step within one sample"). `_roll_gyro_step` finds it
# from the gyro's change against what the accelerometer, imu_height above the ground, felt:
GYRO_STEP_Z = 6.0  # standard deviations of that comparison's own running noise beyond which a step is a candidate
GYRO_STEP_MIN = 0.02  # rad/s: the smallest step taken, whatever the noise (a roll-acceleration jump of 4 rad/s^2)
GYRO_STEP_NOISE_TIME = 5.0  # s: time constant of the comparison's running mean square
# ... which is learned before any step is taken: the file's sensors are only its prior, and an IMU noisier than the
# file's read as steps as soon as the ride reached the check's speed (`urban` with `imu_noise=5`: a step taken
# 0.2 s after, the roll 3.5 deg off and VALID 2.9 deg off; docs/estimator.md, "The step check learns its noise")
GYRO_STEP_LEARN_CYCLES = 100  # statistics averaged (the prior counting as one) before the check may take a step
GYRO_STEP_SIZE_DOUBT = 0.1  # share of a step taken that its uncertainty adds beyond the comparison's noise ...
GYRO_STEP_SPIKE_DOUBT = 0.4  # ... or, where it may have been a spike, this: the roll's 3 sd then outgrow its drift
GYRO_STEP_MIN_HEIGHT = 0.1  # m: an IMU lower than this sees too little of the roll acceleration to check the gyro
# At rest the gyros' noise about their biases is read as a plain mean over the first STANDSTILL_NOISE_CYCLES, then
# as a running one of weight 1 / (STANDSTILL_NOISE_CYCLES + 1) (1 s at 100 Hz). Not the step check's learner: that
# one clips what it averages once it tests, which a reading at rest, where nothing is tested, has no reason to.
STANDSTILL_NOISE_CYCLES = 100

# ---- parameters (float64 vector: `attitude_params` builds the filter's from the config, `build_params` all) ----
PARAMS = Layout(
    "A_",
    dt=1,
    g=1,
    imu_height=1,  # m above ground
    imu_forward=1,  # m ahead of the reference point
    q_roll=1,  # rad/sqrt(s), roll random walk beyond the gyro (pitch coupling, vibration)
    q_heading=1,  # rad/sqrt(s)
    q_gyro_bias=1,  # rad/s/sqrt(s)
    q_accel_bias=1,  # m/s^2/sqrt(s)
    q_sideslip_accel=1,  # m/s^2/sqrt(s), drive of the Markov a_v
    sideslip_accel_time=1,  # s, correlation time of a_v
    sideslip_time=1,  # s, mean reversion of v_y
    sideslip_accel_ref=1,  # m/s^2: a_v's drive grows as sqrt(1 + (excess / this)^2) (slides near the grip limit)
    sideslip_compliance=1,  # s^2/m: a yaw acceleration r' at speed u drives the sideslip by this x u^2 |r'|
    sideslip_dead_zone=1,  # m/s^2 of g tan(roll) below which the two hard-corner terms stay off (`_corner_excess`)
    course_sideslip_per_accel=1,  # rad/(m/s^2): steady sideslip taken as course noise, per m/s^2 of that excess
    r_lateral=1,  # m/s^2, lateral specific-force noise (sensor + unmodelled)
    r_pitch_rate=1,  # rad/s, pitch rate of the chassis taken as noise
    r_course=1,  # rad, GPS course noise at speed
    course_min_speed=1,  # m/s, below: course not used
    latency=1,  # s, GPS latency (the course's instant to the millisecond: `_course_epoch`)
    gate=1,  # innovation gate [standard deviations]
    r_standstill_rate=1,  # rad/s, gyro noise at standstill (zero-rate update)
    init_roll_sd=1,  # rad
    init_gyro_bias_sd=1,  # rad/s
    init_accel_bias_sd=1,  # m/s^2, the accelerometers' biases a priori until the road has been seen level ...
    level_road_accel_bias_sd=1,  # m/s^2, ... and from then, as if from the start (`_widen_prior`)
    reopen_after=1,  # consecutive rejected cycles after which the roll uncertainty is reopened
    # the stage's (attitude_stage), not the filter's:
    cal_speed=1,  # m/s: below (with a fix, no input fault, rates small), the vehicle stands still
    cal_max_rate=1,  # rad/s: above, the vehicle is moving (rocked) and the gyros are not read as biases
    consistency_time=1,  # s, time constant of the innovations' running means
    consistency_limit=1,  # alarm beyond this many standard deviations of a white sequence's running mean
    consistency_hold=1,  # s an alarm is held after the means are back within half the limit
    course_interval=1,  # s between GPS fixes (the course's running mean moves per fix)
)
(
    A_DT,
    A_G,
    A_IMU_HEIGHT,
    A_IMU_FORWARD,
    A_Q_ROLL,
    A_Q_HEADING,
    A_Q_GYRO_BIAS,
    A_Q_ACCEL_BIAS,
    A_Q_SIDESLIP_ACCEL,
    A_SIDESLIP_ACCEL_TIME,
    A_SIDESLIP_TIME,
    A_SIDESLIP_ACCEL_REF,
    A_SIDESLIP_COMPLIANCE,
    A_SIDESLIP_DEAD_ZONE,
    A_COURSE_SIDESLIP_PER_ACCEL,
    A_R_LATERAL,
    A_R_PITCH_RATE,
    A_R_COURSE,
    A_COURSE_MIN_SPEED,
    A_LATENCY,
    A_GATE,
    A_R_STANDSTILL_RATE,
    A_INIT_ROLL_SD,
    A_INIT_GYRO_BIAS_SD,
    A_INIT_ACCEL_BIAS_SD,
    A_LEVEL_ROAD_ACCEL_BIAS_SD,
    A_REOPEN_AFTER,
    A_CAL_SPEED,
    A_CAL_MAX_RATE,
    A_CONSISTENCY_TIME,
    A_CONSISTENCY_LIMIT,
    A_CONSISTENCY_HOLD,
    A_COURSE_INTERVAL,
) = PARAMS.offsets
PARAM_SIZE = PARAMS.size

# ---- outputs (float64 vector written every cycle) ----
OUTPUTS = Layout(
    "OUT_",
    roll=1,  # rad, at the current cycle
    roll_rate=1,  # rad/s, bias-corrected roll gyro
    yaw_rate=1,  # rad/s, ground yaw rate, bias-corrected
    roll_sd=1,  # rad, standard deviation of the roll estimate
    bp=1,  # rad/s, roll-gyro bias
    bq=1,  # rad/s, pitch-gyro bias
    br=1,  # rad/s, yaw-gyro bias
    bay=1,  # m/s^2, lateral accelerometer bias
    vy=1,  # m/s
    rejected=1,  # 1 if this cycle's lateral-force innovation was gated out
    heading=1,  # rad, wrapped to (-pi, pi]
    nu_lateral=1,  # whitened innovation of this cycle's lateral-force update, gated out or not (0 without one)
    nu_pitch=1,  # whitened innovation of the rotation-axis constraint
    nu_course=1,  # whitened innovation of this cycle's GPS course (0 without a fix)
    course_fix=1,  # 1 if a GPS course fix was compared this cycle (fused or gated out)
    yaw_rate_sd=1,  # rad/s, standard deviation of yaw_rate from the biases' uncertainty (what the tyres learn on)
    bay_sd=1,  # m/s^2, standard deviation of the lateral accelerometer's bias estimate
    roll_correction=1,  # rad, what this cycle's measurement updates moved the roll by (the prediction's move not)
    gyro_step=1,  # rad/s, the roll-gyro bias step found and taken this cycle (0: none; `_roll_gyro_step`)
    pitch=1,  # rad, the IMU's pitch off the level (X_PITCH)
    pitch_doubt=1,  # the longitudinal offset's innovations' running mean over OFFSET_DOUBT_LEVEL (>= 1: doubted)
    # the stage's (attitude_stage), not the filter's:
    ok=1,  # 1: the filter is initialised and every output above is finite
    rejected_run=1,  # consecutive cycles of rejected lateral-force innovations
    consistency=1,  # the larger running mean of the whitened innovations, in standard deviations of a white mean
    inconsistent=1,  # 1: the innovations say the roll (or a gyro) is not what the filter believes
    saturated=1,  # 1: a gyro reads its full scale this cycle (the body turns faster than it can say)
)
(
    OUT_ROLL,
    OUT_ROLL_RATE,
    OUT_YAW_RATE,
    OUT_ROLL_SD,
    OUT_BP,
    OUT_BQ,
    OUT_BR,
    OUT_BAY,
    OUT_VY,
    OUT_REJECTED,
    OUT_HEADING,
    OUT_NU_LATERAL,
    OUT_NU_PITCH,
    OUT_NU_COURSE,
    OUT_COURSE_FIX,
    OUT_YAW_RATE_SD,
    OUT_BAY_SD,
    OUT_ROLL_CORRECTION,
    OUT_GYRO_STEP,
    OUT_PITCH,
    OUT_PITCH_DOUBT,
    OUT_OK,
    OUT_REJECTED_RUN,
    OUT_CONSISTENCY,
    OUT_INCONSISTENT,
    OUT_SATURATED,
) = OUTPUTS.offsets
N_FILTER_OUT = OUT_PITCH_DOUBT + 1  # what `attitude_step` writes
OUT_SIZE = OUTPUTS.size


def new_state() -> np.ndarray:
    return np.zeros(STATE_SIZE)


def attitude_params(
    dt: float,
    g: float,
    imu_height: float,
    imu_forward: float,
    tuning,
    gps_latency: float,
) -> np.ndarray:
    """The parameter vector from the config's `estimator.attitude` section (`AttitudeTuning`).

    The stage's own entries (A_CAL_*) stay 0 (never standing still): `build_params` sets them."""
    prm = np.zeros(PARAM_SIZE)
    prm[A_DT] = dt
    prm[A_G] = g
    prm[A_IMU_HEIGHT] = imu_height
    prm[A_IMU_FORWARD] = imu_forward
    prm[A_Q_ROLL] = tuning.roll_noise
    prm[A_Q_HEADING] = tuning.heading_noise
    prm[A_Q_GYRO_BIAS] = tuning.gyro_bias_rate
    prm[A_Q_ACCEL_BIAS] = tuning.accel_bias_rate
    prm[A_Q_SIDESLIP_ACCEL] = tuning.sideslip_accel_noise
    prm[A_SIDESLIP_ACCEL_TIME] = tuning.sideslip_accel_time
    prm[A_SIDESLIP_TIME] = tuning.sideslip_time
    prm[A_SIDESLIP_ACCEL_REF] = tuning.sideslip_accel_noise_ref
    prm[A_SIDESLIP_COMPLIANCE] = tuning.sideslip_compliance
    prm[A_SIDESLIP_DEAD_ZONE] = tuning.sideslip_dead_zone
    prm[A_COURSE_SIDESLIP_PER_ACCEL] = tuning.course_sideslip_per_accel
    prm[A_R_LATERAL] = tuning.lateral_accel_noise
    prm[A_R_PITCH_RATE] = tuning.pitch_rate_noise
    prm[A_R_COURSE] = math.radians(tuning.course_noise_deg)
    prm[A_COURSE_MIN_SPEED] = tuning.course_min_speed
    prm[A_LATENCY] = gps_latency
    prm[A_GATE] = tuning.innovation_gate
    prm[A_R_STANDSTILL_RATE] = tuning.standstill_rate_noise
    prm[A_INIT_ROLL_SD] = tuning.initial_roll_sd
    prm[A_INIT_GYRO_BIAS_SD] = tuning.initial_gyro_bias_sd
    prm[A_INIT_ACCEL_BIAS_SD] = tuning.initial_accel_bias_sd
    prm[A_LEVEL_ROAD_ACCEL_BIAS_SD] = tuning.level_road_accel_bias_sd
    prm[A_REOPEN_AFTER] = tuning.reopen_after_cycles
    # the stage's consistency monitor's, which the filter's grade rate reads too
    prm[A_CONSISTENCY_TIME] = tuning.consistency_time
    prm[A_CONSISTENCY_LIMIT] = tuning.consistency_limit
    return prm


@njit(cache=True)
def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)  # called six times: inlined, it would add seconds to the cold compile for ~0.04 us
def _update(st: np.ndarray, H: np.ndarray, innovation: float, variance: float, gate: float) -> bool:
    """Scalar EKF update x += K e, P -= K H P (Joseph-free, symmetrised); False if gated out."""
    x = st[ST_X : ST_X + N_X]
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    PH = st[ST_TMP + N_X : ST_TMP + 2 * N_X]
    s = variance
    for i in range(N_X):
        acc = 0.0
        for j in range(N_X):
            acc += P[i, j] * H[j]
        PH[i] = acc
    for i in range(N_X):
        s += H[i] * PH[i]
    if not (s > 0.0 and math.isfinite(innovation)):
        st[ST_NU] = 0.0
        return False
    st[ST_NU] = innovation / math.sqrt(s)
    if innovation * innovation > gate * gate * s:
        # not applied, but still evidence for the consistency monitor (which clips it): counted as 0, the gated
        # peaks of a deep-lean weave (a_y to 10 m/s^2 and back within 0.2 s) left only the troughs in its mean
        return False
    _apply(x, P, PH, s, innovation)
    return True


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _apply(x: np.ndarray, P: np.ndarray, PH: np.ndarray, s: float, innovation: float) -> None:
    """x += PH / s e, P -= PH PH' / s (PH = P H, s its innovation variance), kept symmetric with a positive
    diagonal against round-off."""
    for i in range(N_X):
        x[i] += PH[i] / s * innovation
    for i in range(N_X):
        for j in range(N_X):
            P[i, j] -= PH[i] * PH[j] / s
    for i in range(N_X):
        for j in range(i + 1, N_X):
            m = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = m
            P[j, i] = m
        if P[i, i] < 1e-18:
            P[i, i] = 1e-18


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def pitch_doubted(out: np.ndarray) -> bool:
    """The longitudinal accelerometer doubts the pitch (the stage's OUT_PITCH_DOUBT >= 1): the tyres do not learn
    on what such a pitch bends, and EST_TireConfidence.PitchDoubted says so."""
    return out[OUT_PITCH_DOUBT] >= 1.0


@njit(cache=True)
def turn_accel_along(
    v_y: float, yaw_rate: float, yaw_accel: float, roll: float, roll_rate: float, forward: float, height: float
) -> float:
    """m/s^2: what a turn adds to the IMU's specific force along the body's x axis beyond the speed's rate. In the
    frame that yaws with the vehicle the IMU sits `forward` of the reference point and, leaned, height sin(roll)
    beside it; a point there accelerates along x by -v_y r - forward r^2 - r' height sin(roll) - 2 r height
    cos(roll) roll' (the last two: the lean carries the IMU sideways, and its rate moves it). A 30 km/h slalom makes
    them 0.1-0.15 m/s^2 at 2x its frequency, which integrated as the speed's rate read it 1 % low at every lean
    (docs/estimator.md, "Speed")."""
    return (
        -v_y * yaw_rate
        - forward * yaw_rate * yaw_rate
        - yaw_accel * height * math.sin(roll)
        - 2.0 * yaw_rate * height * math.cos(roll) * roll_rate
    )


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def turn_accel_of(out: np.ndarray, prm: np.ndarray, yaw_accel: float) -> float:
    """`turn_accel_along` at the stage's outputs (its last cycle's), with the ground yaw rate's rate `yaw_accel`
    [rad/s^2]; 0 while the stage has none."""
    if out[OUT_OK] == 0.0:
        return 0.0
    return turn_accel_along(
        out[OUT_VY],
        out[OUT_YAW_RATE],
        yaw_accel,
        out[OUT_ROLL],
        out[OUT_ROLL_RATE],
        prm[A_IMU_FORWARD],
        prm[A_IMU_HEIGHT],
    )


@njit(cache=True)
def _widen_prior(st: np.ndarray, i: int, prior_var: float, wider_var: float) -> None:
    """As if state i's prior (mean 0) had been wider_var, not prior_var, from the start. The narrower prior is the
    wider one plus a pseudo-measurement i = 0 of variance 1 / (1/prior_var - 1/wider_var); that measurement is
    taken out again, an update with its variance negated (s < 0: the covariance grows along what i is correlated
    with, and the estimate moves back to what the data alone say). Exact for a linear filter and a state that
    does not drift; nothing if wider_var is not wider."""
    if not wider_var > prior_var:
        return
    x = st[ST_X : ST_X + N_X]
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    PH = st[ST_TMP + N_X : ST_TMP + 2 * N_X]
    s = P[i, i] - 1.0 / (1.0 / prior_var - 1.0 / wider_var)
    # Without drift, P[i, i] / -s is at most wider_var / prior_var - 1 (no data on i at all). Beyond it i's random walk
    # has since diffused the prior's information, and taking it out exactly divides by almost nothing: a late widening
    # (`urban` from rest, level for 2 s only at 12.7 s) moved b_ay by 1.0 m/s^2 and the roll by 4.6 deg in one cycle,
    # VALID (random set 8147). There, as where the data have not narrowed i that far (an alarm reopened it), the
    # prior's difference is added instead
    if not s < 0.0 or P[i, i] > -s * (wider_var / prior_var - 1.0):
        P[i, i] += wider_var - prior_var
        return
    for k in range(N_X):
        PH[k] = P[k, i]
    _apply(x, P, PH, s, -x[i])


@njit(cache=True)
def _grade_odds(seen: float, felt: float, var_seen: float, var_felt: float, var_rate: float) -> float:
    """Natural log of the odds that two raw pitch rates, seen (gyros) and felt (vertical accelerometer), are a grade's
    rate common to both (variance var_rate) plus each sensor's independent bias and noise (var_seen, var_felt),
    against the biases and noise alone."""
    a, d, w = var_seen, var_felt, var_rate
    level = seen * seen / a + felt * felt / d
    det_grade = (a + w) * (d + w) - w * w
    grade = ((d + w) * seen * seen - 2.0 * w * seen * felt + (a + w) * felt * felt) / det_grade
    return 0.5 * (level - grade) - 0.5 * math.log(det_grade / (a * d))


@njit(cache=True)
def _grade_start_test(
    st: np.ndarray, prm: np.ndarray, u: float, s: float, c: float, q: float, r: float, rate_sd: float, dt: float
) -> None:
    """Once GRADE_TEST_TIME of the start's raw pitch rates is summed: where a grade's rate explains them better than
    two biases (module constants GRADE_TEST_*), re-split them. u: speed [m/s]; s, c: sin and cos of the roll; q, r:
    this cycle's raw pitch and yaw rates [rad/s]; rate_sd: a hilly road's spread of the rate at this speed [rad/s]."""
    n = st[ST_GRADE_TEST_CYCLES]
    if n < GRADE_TEST_TIME / dt or not (u > GRADE_MIN_SPEED and c > GRADE_MAX_ROLL_COS):
        return
    st[ST_GRADE_TEST_DUE] = 0.0
    x = st[ST_X : ST_X + N_X]
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    seen, felt = st[ST_GRADE_TEST_SEEN] / n, st[ST_GRADE_TEST_FELT] / n
    var_seen = prm[A_INIT_GYRO_BIAS_SD] ** 2
    felt_per_baz = 1.0 / (u * c)  # the vertical accelerometer's bias read as a pitch rate
    # the accelerometer's bias as wide as cheap MEMS offsets span, not the filter's tight prior: a b_az of 3-5 times
    # that prior (18-27 mg) alone, the gyros reading no rate, was taken for a grade on level roads
    var_felt = (prm[A_LEVEL_ROAD_ACCEL_BIAS_SD] ** 2 + VERTICAL_ACCEL_NOISE**2 / n) * felt_per_baz**2
    var_rate = rate_sd * rate_sd
    if not _grade_odds(seen, felt, var_seen, var_felt, var_rate) > math.log(GRADE_TEST_ODDS):
        return
    precision = 1.0 / var_rate + 1.0 / var_seen + 1.0 / var_felt
    rate = (seen / var_seen + felt / var_felt) / precision  # the test's mean rate, both sensors' common part
    sd = math.sqrt(1.0 / precision)
    bq = (seen - rate + x[X_BR] * s) / c  # seen = rate + b_q c - b_r s
    baz = (rate - felt) / felt_per_baz  # felt = rate - b_az / (u c)
    # the pitch turned at that rate over the test's cycles, not at the filter's (the offset's running mean, over
    # OFFSET_TIME, took about half of the test's share of it)
    turned = (rate - st[ST_GRADE_TEST_RATE] / n) * n * dt
    x[X_PITCH] += turned
    st[ST_PITCH_LAG] += turned * (1.0 - 0.5 * GRADE_TEST_TIME / spd.OFFSET_TIME)
    _set_uncorrelated(x, P, X_BQ, bq, sd / c)
    _set_uncorrelated(x, P, X_BAZ, baz, sd / felt_per_baz)
    _set_uncorrelated(x, P, X_PITCH_RATE, (q - bq) * c - (r - x[X_BR]) * s, sd)  # this cycle's, by the gyros
    st[ST_GRADE_FOUND] = 1.0


@njit(cache=True)
def _clear_h(H: np.ndarray) -> None:
    for i in range(N_X):
        H[i] = 0.0


@njit(cache=True, inline="always")
def _set_uncorrelated(x: np.ndarray, P: np.ndarray, i: int, value: float, sd: float) -> None:
    """State i to `value` with standard deviation `sd`, uncorrelated with the rest (a prior, or a value known
    from elsewhere: a state file, a GPS course)."""
    for j in range(N_X):
        P[i, j] = 0.0
        P[j, i] = 0.0
    x[i] = value
    P[i, i] = sd * sd


@njit(cache=True, inline="always")
def _restart_sideslip(x: np.ndarray, P: np.ndarray) -> None:
    """v_y and its derivative back to their prior (zero, a gripping vehicle's), uncorrelated with the rest."""
    _set_uncorrelated(x, P, X_VY, 0.0, INITIAL_VY_SD)
    _set_uncorrelated(x, P, X_AV, 0.0, INITIAL_AV_SD)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _roll_gyro_step(
    st: np.ndarray, prm: np.ndarray, prev: np.ndarray, p: float, f_y: float, sound: bool
) -> tuple[float, float]:
    """The roll-gyro bias step [rad/s] that began two samples before this cycle's (0: none; module constants
    GYRO_STEP_*), and the share of it its uncertainty adds. With Dp_k the gyro's change into
    sample k and the trapezoid of the lateral specific force f over the same interval, rho_k = Dp_k - dt (f_k +
    f_{k-1}) / (2 h) is what of the gyro's change the lever arm did not feel, plus slow terms (the turn's u r,
    gravity, the sideslip) that a second difference removes: S_k = rho_k - (rho_{k-1} + rho_{k+1}) / 2. Healthy
    riding makes S its noise; a step b at sample m makes S_{m-1}, S_m, S_{m+1} = -b/2, b, -b/2. A candidate is an S
    beyond the limit whose gyro share is beyond it too (a kick of the accelerometer alone is not the gyro's) and
    that follows an S of the other sign; it is taken a cycle later if its two neighbours' mean is a step's, -S/2
    within a quarter of S (a step of twice the limit makes its -b/2 a candidate first, which its successor b
    does not confirm: that b is the next candidate). A one-sample spike A of the gyro (a glitch, or a garbage frame
    whose counter matched, within the input checks) makes -A/2, 1.5 A, -1.5 A, A/2: its lobes' neighbours' mean is
    -2/3 S, a step's shape within the test's tolerance, but they differ by 2/3 S where a step's are equal.
    Neighbours that differ beyond 4 sd of their noise are a spike's: no step. Nearer the noise (a 0.05 rad/s step is
    9 sd of it) the two cannot be told apart for sure: a step whose neighbours differ by more than a third of it is
    taken with the doubt GYRO_STEP_SPIKE_DOUBT (its uncertainty covers it being no step at all: the roll is not
    VALID until the data have pinned the bias again), else with GYRO_STEP_SIZE_DOUBT. `sound`: this cycle's samples
    are new, sound and riding; four in a row."""
    h = prm[A_IMU_HEIGHT]
    last = st[ST_STEP_LAST]
    candidate = st[ST_STEP_CANDIDATE]
    st[ST_STEP_LAST] = 0.0
    st[ST_STEP_CANDIDATE] = 0.0
    if not sound or h < GYRO_STEP_MIN_HEIGHT:
        st[ST_IMU_FRESH_RUN] = 0.0
        return 0.0, 0.0
    st[ST_IMU_FRESH_RUN] += 1.0
    if st[ST_IMU_FRESH_RUN] < 4.0:
        return 0.0, 0.0
    dt = prm[A_DT]
    if not st[ST_STEP_MS] > 0.0:  # the comparison's noise from the configured sensors' until riding has shown it
        st[ST_STEP_MS] = 5.0 * prm[A_R_STANDSTILL_RATE] ** 2 + (0.5 * dt / h * prm[A_R_LATERAL]) ** 2
    p1, p2, p3 = prev[PREV_P], prev[PREV_P2], prev[PREV_P3]
    f1, f2, f3 = prev[PREV_FY], prev[PREV_FY2], prev[PREV_FY3]
    k = 0.5 * dt / h
    dp_before, dp, dp_after = p2 - p3, p1 - p2, p - p1
    gyro = dp - 0.5 * (dp_before + dp_after)  # the gyro's own share of the statistic
    rho_before, rho, rho_after = dp_before - k * (f2 + f3), dp - k * (f1 + f2), dp_after - k * (f_y + f1)
    stat = rho - 0.5 * (rho_before + rho_after)
    st[ST_STEP_LAST] = stat
    learned = st[ST_STEP_MS_SAMPLES]
    if learned < GYRO_STEP_LEARN_CYCLES:
        st[ST_STEP_MS] += (stat * stat - st[ST_STEP_MS]) / (learned + 2.0)  # the plain mean, the prior one sample
        st[ST_STEP_MS_SAMPLES] = learned + 1.0
        return 0.0, 0.0
    if candidate != 0.0:
        before = st[ST_STEP_BEFORE]
        mean = 0.5 * (before + stat)
        differ = abs(before - stat)
        if 0.25 * candidate * candidate <= -mean * candidate <= 0.75 * candidate * candidate:
            if differ > 4.0 * math.sqrt(2.0 * st[ST_STEP_MS]):
                return 0.0, 0.0  # a spike's neighbours: neither it nor its next lobe (this S) is a step
            return candidate, GYRO_STEP_SPIKE_DOUBT if 3.0 * differ > abs(candidate) else GYRO_STEP_SIZE_DOUBT
        # not a step's shape: the candidate was the -b/2 before a large step's b, which this S may be
    limit = max(GYRO_STEP_Z * math.sqrt(st[ST_STEP_MS]), GYRO_STEP_MIN)
    if abs(stat) > limit and abs(gyro) > limit and gyro * stat > 0.0 and last * stat < 0.0:
        st[ST_STEP_CANDIDATE] = stat
        st[ST_STEP_BEFORE] = last
        return 0.0, 0.0
    if candidate != 0.0:
        return 0.0, 0.0  # what follows a candidate is no noise sample either
    st[ST_STEP_MS] += min(dt / GYRO_STEP_NOISE_TIME, 1.0) * (min(stat * stat, limit * limit) - st[ST_STEP_MS])
    return 0.0, 0.0


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _running_mean_sd(alpha: float) -> float:
    """The sd of an exponential running mean (weight alpha) of a white unit-variance sequence: the consistency
    monitor's unit, which the grade rate's gate reads the lateral innovations' mean in too."""
    return math.sqrt(alpha / (2.0 - alpha))


@njit(cache=True)
def _reset_dynamic(st: np.ndarray, prm: np.ndarray, roll: float) -> None:
    """(Re)start roll, heading, sideslip and the grade's pitch rate; keep the biases and their covariance."""
    x = st[ST_X : ST_X + N_X]
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    keep_biases = st[ST_INIT] != 0.0
    for i in range(N_X):
        for j in range(N_X):
            bias_block = X_BP <= i <= X_BAZ and X_BP <= j <= X_BAZ
            if not (keep_biases and bias_block):
                P[i, j] = 0.0
    x[X_PHI] = roll
    x[X_PSI] = 0.0
    P[X_PHI, X_PHI] = prm[A_INIT_ROLL_SD] ** 2
    P[X_PSI, X_PSI] = 1.0
    _restart_sideslip(x, P)
    x[X_PITCH_RATE] = 0.0
    # with the pitch gyro's bias known (restored from the state file, or learned before a restart) the gyros' pitch
    # rate is the grade's; unknown, a level road's prior is what lets the bias be learned (docs/estimator.md)
    known = keep_biases and P[X_BQ, X_BQ] <= GRADE_KNOWN_BIAS_SD**2
    P[X_PITCH_RATE, X_PITCH_RATE] = PITCH_RATE_SD**2 if known else PITCH_RATE_LEVEL**2
    st[ST_PITCH_LAG] = 0.0
    st[ST_PITCH_RATE_SEEN] = 0.0
    st[ST_PITCH_RATE_FELT] = 0.0
    st[ST_TURN_ACCEL_MEAN] = 0.0
    st[ST_OFFSET_DOUBT] = 0.0
    if not keep_biases:
        for b in (X_BP, X_BQ, X_BR):
            x[b] = 0.0
            P[b, b] = prm[A_INIT_GYRO_BIAS_SD] ** 2
        x[X_BAY] = 0.0
        P[X_BAY, X_BAY] = prm[A_INIT_ACCEL_BIAS_SD] ** 2
        x[X_BAX] = 0.0
        P[X_BAX, X_BAX] = prm[A_INIT_ACCEL_BIAS_SD] ** 2
        x[X_BAZ] = 0.0
        P[X_BAZ, X_BAZ] = prm[A_INIT_ACCEL_BIAS_SD] ** 2
        x[X_PITCH] = 0.0
        P[X_PITCH, X_PITCH] = INITIAL_PITCH_SD**2
        st[ST_LEVEL_PRIOR_DUE] = 1.0
        st[ST_LEVEL_FOR] = 0.0
        st[ST_GRADE_TEST_DUE] = 1.0
        for k in (ST_GRADE_TEST_SEEN, ST_GRADE_TEST_FELT, ST_GRADE_TEST_RATE, ST_GRADE_TEST_CYCLES, ST_GRADE_FOUND):
            st[k] = 0.0
    st[ST_PSI_INIT] = 0.0
    st[ST_REJECTED] = 0.0
    st[ST_QUIET] = 0.0
    st[ST_YAW_ACCEL] = 0.0
    st[ST_IMU_FRESH_RUN] = 0.0
    for k in range(MAX_LATENCY_CYCLES):
        st[ST_PSI_HIST + k] = 0.0
        st[ST_BETA_HIST + k] = 0.0
    st[ST_INIT] = 1.0


@njit(cache=True)
def set_biases(
    st: np.ndarray,
    bp: float,
    bq: float,
    br: float,
    bay: float,
    bax: float,
    baz: float,
    sd_gyro: float,
    sd_accel: float,
    sd_accel_prior: float,
) -> None:
    """Start from biases known from an earlier run (the state file), with their uncertainty; b_ax and b_az NaN: not
    kept (a file written before they were). What is not kept (the pitch always, b_ax and b_az if NaN) starts from
    its prior (sd_accel_prior for the two biases) if the filter has not run yet: the restart that follows keeps
    every slow state as it is, and a state left at zero with no variance would never be learned (a slope's pitch
    read as level all ride)."""
    x = st[ST_X : ST_X + N_X]
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    first = st[ST_INIT] == 0.0
    _set_uncorrelated(x, P, X_BP, bp, sd_gyro)
    _set_uncorrelated(x, P, X_BQ, bq, sd_gyro)
    _set_uncorrelated(x, P, X_BR, br, sd_gyro)
    _set_uncorrelated(x, P, X_BAY, bay, sd_accel)
    st[ST_LEVEL_PRIOR_DUE] = 0.0  # known biases: no prior to widen
    if first:
        _set_uncorrelated(x, P, X_PITCH, 0.0, INITIAL_PITCH_SD)
    for i, kept in ((X_BAX, bax), (X_BAZ, baz)):
        if math.isfinite(kept):
            _set_uncorrelated(x, P, i, kept, sd_accel)
        elif first:
            _set_uncorrelated(x, P, i, 0.0, sd_accel_prior)
    st[ST_INIT] = 2.0  # roll, heading and sideslip start from the next sample's data, these biases kept


@njit(cache=True)
def restart(st: np.ndarray) -> None:
    """Forget roll, heading and sideslip at the next step (a re-initialisation); biases are kept."""
    if st[ST_INIT] != 0.0:
        st[ST_INIT] = 2.0  # 2: initialised before, restart the dynamic states with the biases kept


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _riding_straight(phi: float, yaw_rate: float, yaw_accel: float) -> bool:
    """Lean, ground yaw rate and its low-passed rate of change all small: no steady sideslip to speak of."""
    return (
        abs(phi) < STRAIGHT_MAX_ROLL
        and abs(yaw_rate) < STRAIGHT_MAX_YAW_RATE
        and abs(yaw_accel) < STRAIGHT_MAX_YAW_ACCEL
    )


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _corner_excess(phi: float, prm: np.ndarray) -> float:
    """How much harder than `sideslip_dead_zone` the corner is [m/s^2]: the lateral acceleration g tan(roll) its
    lean balances, bounded at what a tyre can give, less the dead zone (0 below it). From the filter's own roll, a
    state, not from the gyro times the speed: a burst of corrupt rates that the input checks let through after 10
    cycles must not open the sideslip's covariance (tests/test_estimator.py)."""
    a_lat = min(prm[A_G] * abs(math.tan(phi)), MAX_LATERAL_ACCEL)
    return max(a_lat - prm[A_SIDESLIP_DEAD_ZONE], 0.0)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _course_epoch(
    st: np.ndarray, prm: np.ndarray, psi: float, beta: float, fix_older_than_imu: float
) -> tuple[float, float]:
    """The heading and sideslip angle the filter had at the GPS course's epoch: the receiver's latency before its
    frame, which came `fix_older_than_imu` s before the newest IMU frame; the state is the previous IMU sample's (the
    measurements go one cycle late), and the histories hold each cycle's heading increment and sideslip angle.

    Whole cycles alone (the state's instant less the latency, rounded) put the heading 12 ms before the course's
    epoch on the simulator's phases, and the sideslip was today's: in a 30 km/h slalom both errors go with the turn,
    the yaw gyro's bias moved in time with it and the tyres read 4.5 % stiff (`docs/estimator.md`, "The course at
    its own instant")."""
    dt = prm[A_DT]
    delay = (prm[A_LATENCY] - dt + fix_older_than_imu) / dt
    delay = min(max(delay, 0.0), MAX_LATENCY_CYCLES - 2.0)
    j = int(delay)
    frac = delay - j
    delayed_psi = psi
    for k in range(j):
        delayed_psi -= st[ST_PSI_HIST + k]
    delayed_psi -= frac * st[ST_PSI_HIST + j]
    beta_j = beta if j == 0 else st[ST_BETA_HIST + j - 1]
    beta_next = st[ST_BETA_HIST + j]
    return delayed_psi, beta_j + frac * (beta_next - beta_j)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def attitude_step(
    st: np.ndarray,
    out: np.ndarray,
    prm: np.ndarray,
    p: float,
    q: float,
    r: float,
    f_y: float,
    f_z: float,
    u: float,
    u_sd: float,
    rates_ok: bool,
    accel_ok: bool,
    course: float,
    course_new: bool,
    standstill: bool,
    saturated: bool = False,
    rates_trusted: bool = True,
    imu_fresh: bool = False,
    accel_x_offset: float = math.nan,
    accel_x_offset_age: float = 0.0,
    fix_older_than_imu: float = 0.0,
) -> None:
    """One cycle. p, q, r: body rates [rad/s]; f_y, f_z: body specific force [m/s^2]; u: forward speed and
    u_sd its standard deviation [m/s]; course [rad] valid when course_new (a fresh GPS fix at speed);
    standstill: the vehicle is known to stand still (zero rates and sideslip); saturated: a gyro reads its full
    scale (GYRO_FULL_SCALE: the rate integrated is a bound, not the rate); rates_trusted: no burst of corrupt input
    is under way (the rates may be garbage that passed the checks: they must not open the sideslip's covariance);
    imu_fresh: p and f_y are a new sound sample of each sensor (the roll-gyro step check compares consecutive ones);
    accel_x_offset: what the longitudinal accelerometer reads beyond the speed's rate [m/s^2] (the speed stage's,
    learned against GPS; NaN: none), g sin(pitch) + b_ax: with the turns it gives the pitch, which the roll's
    kinematics need (roll' = p + tan(pitch) r_ground: the vehicle turns about the vertical); accel_x_offset_age: s its
    running mean has run since it (re)started (the speed stage's; its innovations are doubted from OFFSET_TIME on)."""
    dt = prm[A_DT]
    g = prm[A_G]
    h = prm[A_IMU_HEIGHT]
    x = st[ST_X : ST_X + N_X]
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    H = st[ST_TMP + 2 * N_X : ST_TMP + 3 * N_X]
    gate = prm[A_GATE]
    prev = st[ST_PREV : ST_PREV + N_PREV]

    if st[ST_INIT] != 1.0:
        if not (rates_ok and accel_ok):
            for k in range(N_FILTER_OUT):
                out[k] = 0.0
            return
        # roll from gravity alone (at rest or riding straight; a turn is corrected within seconds)
        roll0 = math.atan2(-f_y, -f_z) if f_z < -0.5 * g else 0.0
        _reset_dynamic(st, prm, roll0)
        prev[PREV_P] = p
        prev[PREV_P2] = p
        prev[PREV_P3] = p
        prev[PREV_Q] = q
        prev[PREV_R] = r
        prev[PREV_FY] = f_y
        prev[PREV_FY2] = f_y
        prev[PREV_FY3] = f_y
        prev[PREV_FZ] = f_z
        prev[PREV_U] = u
        prev[PREV_U_VAR] = u_sd * u_sd
        prev[PREV_OK] = 0.0
        s0, c0 = math.sin(roll0), math.cos(roll0)
        prev[PREV_RG] = q * s0 + r * c0
        prev[PREV_RG2] = prev[PREV_RG]

    # ---- 0. a step of the roll gyro's bias, taken at once: it began in the sample before the previous one, so
    # this cycle's lever-arm derivative (this sample's less that one's) is already clean; the two before it saw it ----
    sound = imu_fresh and rates_ok and accel_ok and rates_trusted and not saturated
    step, doubt = _roll_gyro_step(st, prm, prev, p, f_y, sound and u >= prm[A_COURSE_MIN_SPEED])
    out[OUT_GYRO_STEP] = step
    if step != 0.0:
        x[X_BP] += step
        x[X_PHI] -= 1.5 * dt * step  # the last two predictions integrated 1.5 cycles of it (the trapezoid)
        P[X_BP, X_BP] += st[ST_STEP_MS] + (doubt * step) ** 2
        P[X_PHI, X_PHI] += (1.5 * dt * step) ** 2

    # ---- 1. measurements of the previous cycle, with central-difference lever-arm derivatives ----
    phi = x[X_PHI]
    phi_predicted = phi
    s, c = math.sin(phi), math.cos(phi)
    bp, bq, br = x[X_BP], x[X_BQ], x[X_BR]
    q1, r1, u1 = prev[PREV_Q] - bq, prev[PREV_R] - br, prev[PREV_U]
    rg1 = q1 * s + r1 * c
    pitch = x[X_PITCH]
    phid1 = prev[PREV_P] - bp + math.tan(pitch) * rg1
    rejected = 0.0
    nu_lateral = 0.0
    nu_pitch = 0.0
    nu_course = 0.0
    course_fix = 0.0
    if rates_ok:
        phidd1 = (p - prev[PREV_P2]) / (2.0 * dt)
        rg_now = (q - bq) * s + (r - br) * c
        rgd1 = (rg_now - prev[PREV_RG2]) / (2.0 * dt)
        if prev[PREV_RATES_OK2] != 0.0 and not saturated and rates_trusted:
            st[ST_YAW_ACCEL] += min(dt / YAW_ACCEL_TIME, 1.0) * (rgd1 - st[ST_YAW_ACCEL])
    else:
        phidd1 = 0.0
        rgd1 = 0.0
    if not rates_trusted:
        st[ST_YAW_ACCEL] = 0.0
    # the accelerometer's constraints need the previous cycle's rates: the turn's u r, the rotation axis, the
    # lever-arm terms; held ones (a frozen or corrupt IMU_Rates frame) would pin the roll to the lean of the moment
    # they froze (`sensor_faults` seeds 3 / 7: 4.8 / 5.8 deg off around a 0.5 s freeze in a corner; integrating the
    # held roll rate alone, at most 0.9 / 1.4 deg), so a held cycle predicts only
    if prev[PREV_OK] != 0.0 and prev[PREV_RATES_OK] != 0.0:
        a_y = x[X_AV] + u1 * rg1 + prm[A_IMU_FORWARD] * rgd1 - h * rg1 * rg1 * s + h * (c * phidd1 - s * phid1 * phid1)
        # a grade that changes curves the path in the vertical plane: u pitch' along the road's normal (a crest
        # lightens the vehicle like less gravity)
        a_z = h * (s * phidd1 + c * phid1 * phid1) - u1 * x[X_PITCH_RATE]
        g_level = g * math.cos(pitch)  # gravity's part in the plane the roll turns in
        # the vertical accelerometer (body z): its prediction from this state, carried linearly to the state the
        # lateral update leaves (the two are one measurement of the specific force's direction and size)
        h_z = st[ST_TMP + 3 * N_X : ST_TMP + 4 * N_X]
        x_before = st[ST_TMP + 4 * N_X : ST_TMP + 5 * N_X]
        predicted_z = -a_y * s + (a_z - g_level) * c + x[X_BAZ]
        for k in range(N_X):
            h_z[k] = 0.0
            x_before[k] = x[k]
        h_z[X_PHI] = -a_y * c - (a_z - g_level) * s
        h_z[X_PITCH] = g * math.sin(pitch) * c
        h_z[X_PITCH_RATE] = -u1 * c
        turn_per_rg = u1 - 2.0 * h * rg1 * s  # d a_y / d r_ground
        h_z[X_BQ] = turn_per_rg * s * s
        h_z[X_BR] = turn_per_rg * s * c
        h_z[X_AV] = -s
        h_z[X_BAZ] = 1.0
        predicted = a_y * c + (a_z - g_level) * s + x[X_BAY]
        _clear_h(H)
        H[X_PHI] = -a_y * s + (a_z - g_level) * c
        H[X_PITCH] = g * math.sin(pitch) * s
        H[X_PITCH_RATE] = -u1 * s
        dud_rg = turn_per_rg * c
        H[X_BQ] = -dud_rg * s
        H[X_BR] = -dud_rg * c
        H[X_BAY] = 1.0
        H[X_AV] = c
        variance = prm[A_R_LATERAL] ** 2 + prev[PREV_U_VAR] * rg1 * rg1
        # lever-arm derivatives (central differences over this cycle and the one before the previous) from a held
        # rate: unknown
        if prev[PREV_RATES_OK2] == 0.0 or not rates_ok:
            variance += (h * UNMEASURED_RATE_SD / dt) ** 2 * 0.01
        accepted = _update(st, H, prev[PREV_FY] - predicted, variance, gate)
        nu_lateral = st[ST_NU]
        st[ST_QUIET] = st[ST_QUIET] + 1.0 if accepted and abs(nu_lateral) <= QUIET_NU else 0.0
        if accepted:
            st[ST_REJECTED] = 0.0
        else:
            rejected = 1.0
            st[ST_REJECTED] += 1.0
            if st[ST_REJECTED] >= prm[A_REOPEN_AFTER]:
                # the data have disagreed for a while: the roll is not what we believe, say so
                P[X_PHI, X_PHI] += prm[A_INIT_ROLL_SD] ** 2
                st[ST_REJECTED] = 0.0
        # the vertical specific force: g cos(pitch) and what the grade's change adds (u pitch'), seen through the roll
        for k in range(N_X):
            predicted_z += h_z[k] * (x[k] - x_before[k])
            H[k] = h_z[k]
        variance = VERTICAL_ACCEL_NOISE**2 + prev[PREV_U_VAR] * rg1 * rg1 * s * s
        if prev[PREV_RATES_OK2] == 0.0 or not rates_ok:
            variance += (h * UNMEASURED_RATE_SD / dt) ** 2 * 0.01
        nu_z = prev[PREV_FZ] - predicted_z
        if u1 > GRADE_MIN_SPEED and c > GRADE_MAX_ROLL_COS:
            felt = x[X_PITCH_RATE] - nu_z / (u1 * c)
            if math.isfinite(felt):
                st[ST_PITCH_RATE_FELT] += dt / PITCH_RATE_SEEN_TIME * (felt - st[ST_PITCH_RATE_FELT])
                if st[ST_GRADE_TEST_DUE] != 0.0:  # the start's raw rates: the biases the filter took added back
                    st[ST_GRADE_TEST_SEEN] += prev[PREV_Q] * c - prev[PREV_R] * s
                    st[ST_GRADE_TEST_FELT] += felt - x[X_BAZ] / (u1 * c)
                    st[ST_GRADE_TEST_RATE] += x[X_PITCH_RATE]
                    st[ST_GRADE_TEST_CYCLES] += 1.0
        _update(st, H, nu_z, variance, gate)
        # the rotation axis is vertical but for the road's grade changing: pitch rate (q cos - r sin) = the state's
        phi = x[X_PHI]
        s, c = math.sin(phi), math.cos(phi)
        bq, br = x[X_BQ], x[X_BR]
        q1, r1 = prev[PREV_Q] - bq, prev[PREV_R] - br
        _clear_h(H)
        H[X_PHI] = -(q1 * s + r1 * c)
        H[X_BQ] = -c
        H[X_BR] = s
        H[X_PITCH_RATE] = -1.0
        _update(st, H, x[X_PITCH_RATE] - (q1 * c - r1 * s), prm[A_R_PITCH_RATE] ** 2, gate)
        nu_pitch = st[ST_NU]

    if math.isfinite(accel_x_offset):
        # the longitudinal accelerometer's offset against GPS: g sin(pitch) + b_ax and a turn's part, a running mean
        # over the speed stage's window: the pitch of that window is this one less what its rate turned it by since
        pitch = x[X_PITCH] - st[ST_PITCH_LAG]
        _clear_h(H)
        H[X_PITCH] = g * math.cos(pitch)
        H[X_BAX] = 1.0
        nu = accel_x_offset - g * math.sin(pitch) - x[X_BAX] - st[ST_TURN_ACCEL_MEAN]
        if accel_x_offset_age >= spd.OFFSET_TIME:  # its window full: the last OFFSET_TIME's mean
            st[ST_OFFSET_DOUBT] += dt / OFFSET_DOUBT_TIME * (nu - st[ST_OFFSET_DOUBT])
        _update(st, H, nu, ACCEL_OFFSET_NOISE**2, gate)

    if standstill and rates_ok:
        st[ST_GRADE_TEST_DUE] = 0.0  # the biases are read here, where no grade turns the vehicle
        # the true rates and the sideslip are zero: the gyros read their biases, with the noise they show here if it is
        # more than the file's (an IMU noisier than the file's read its biases 5x more surely than they were)
        seen = ((p - x[X_BP]) ** 2 + (q - x[X_BQ]) ** 2 + (r - x[X_BR]) ** 2) / 3.0
        n = st[ST_STANDSTILL_SAMPLES]
        st[ST_STANDSTILL_MS] += (seen - st[ST_STANDSTILL_MS]) / (n + 1.0)
        st[ST_STANDSTILL_SAMPLES] = min(n + 1.0, STANDSTILL_NOISE_CYCLES)
        rs = max(prm[A_R_STANDSTILL_RATE] ** 2, st[ST_STANDSTILL_MS])
        for b, m in ((X_BP, p), (X_BQ, q), (X_BR, r)):
            _clear_h(H)
            H[b] = 1.0
            _update(st, H, m - x[b], rs, gate)
        _clear_h(H)
        H[X_VY] = 1.0
        _update(st, H, -x[X_VY], 0.01, gate)
        _clear_h(H)
        H[X_AV] = 1.0
        _update(st, H, -x[X_AV], 0.01, gate)

    if (
        rates_ok
        and rates_trusted
        and not saturated
        and u >= prm[A_COURSE_MIN_SPEED]
        and _riding_straight(x[X_PHI], rg1, st[ST_YAW_ACCEL])
    ):
        # no sideslip riding straight (STRAIGHT_SIDESLIP_SD): what breaks a steady a_v / v_y pair holding the roll off.
        # Gated on what a second of it says, not on one cycle's wide variance: a v_y metres per second off (a slide's)
        # is not pulled back through its correlations with the roll here (2.4 deg), the course's restart takes it
        if x[X_VY] ** 2 <= gate * gate * (P[X_VY, X_VY] + STRAIGHT_SIDESLIP_SD**2):
            _clear_h(H)
            H[X_VY] = 1.0
            _update(st, H, -x[X_VY], STRAIGHT_SIDESLIP_SD**2 * STRAIGHT_SIDESLIP_TIME / dt, gate)

    # ---- 2. GPS course (describes the vehicle `latency` cycles ago) ----
    if course_new and u >= prm[A_COURSE_MIN_SPEED]:
        delayed_psi, delayed_beta = _course_epoch(st, prm, x[X_PSI], x[X_VY] / u, fix_older_than_imu)
        if st[ST_PSI_INIT] == 0.0:
            _set_uncorrelated(x, P, X_PSI, course - delayed_beta + (x[X_PSI] - delayed_psi), prm[A_R_COURSE])
            st[ST_PSI_INIT] = 1.0
            st[ST_COURSE_REJECTED] = 0.0
        else:
            _clear_h(H)
            H[X_PSI] = 1.0
            H[X_VY] = 1.0 / u
            # in a long hard corner the vehicle slides steadily sideways (its rear slip angle); with no tyre model
            # here that sideslip is indistinguishable from a heading error, so beyond the dead zone it is noise
            beta_sd = prm[A_COURSE_SIDESLIP_PER_ACCEL] * _corner_excess(x[X_PHI], prm)
            if _update(st, H, _wrap(course - delayed_psi - delayed_beta), prm[A_R_COURSE] ** 2 + beta_sd**2, gate):
                st[ST_COURSE_REJECTED] = 0.0
            else:
                st[ST_COURSE_REJECTED] += 1.0
                if st[ST_COURSE_REJECTED] >= COURSE_REINIT_FIXES:
                    # heading and sideslip together contradict the GPS: either may be wrong, and a slide can leave
                    # v_y far off (a sideslip of 20 deg kept, and the heading set to match it, then drove the roll
                    # 7 deg off on a straight), so both restart: the sideslip at its prior, the heading from the
                    # next fix
                    _restart_sideslip(x, P)
                    st[ST_PSI_INIT] = 0.0
                    st[ST_COURSE_REJECTED] = 0.0
            nu_course = st[ST_NU]
            course_fix = 1.0

    roll_correction = x[X_PHI] - phi_predicted
    # the sideslip angle of the previous cycle's instant, as its measurements left it (newest first)
    for k in range(MAX_LATENCY_CYCLES - 1, 0, -1):
        st[ST_BETA_HIST + k] = st[ST_BETA_HIST + k - 1]
    st[ST_BETA_HIST] = x[X_VY] / u if u > 0.0 else 0.0

    # ---- 3. predict to this cycle: trapezoidal integration of the previous and this cycle's rates (both are
    # known; the rectangle rule's dt^2 phi''/2 per step adds up to ~0.2 deg in a quick lane change) ----
    phi = x[X_PHI]
    s, c = math.sin(phi), math.cos(phi)
    bp, bq, br = x[X_BP], x[X_BQ], x[X_BR]
    if rates_ok:
        p_mid = 0.5 * (prev[PREV_P] + p)
        q_mid = 0.5 * (prev[PREV_Q] + q)
        r_mid = 0.5 * (prev[PREV_R] + r)
    else:
        p_mid, q_mid, r_mid = prev[PREV_P], prev[PREV_Q], prev[PREV_R]
    x[X_PHI] += dt * (p_mid - bp)
    phi_mid = 0.5 * (phi + x[X_PHI])
    s, c = math.sin(phi_mid), math.cos(phi_mid)
    q1, r1 = q_mid - bq, r_mid - br
    rg1 = q1 * s + r1 * c
    pitch1 = q1 * c - r1 * s
    tan_pitch, cos_pitch = math.tan(x[X_PITCH]), math.cos(x[X_PITCH])
    x[X_PHI] += dt * tan_pitch * rg1
    d_psi = dt * rg1 / cos_pitch
    x[X_PSI] += d_psi
    roll_per_pitch = dt * rg1 / (cos_pitch * cos_pitch)  # d(roll')/d(pitch) dt
    psi_per_pitch = dt * rg1 * tan_pitch / cos_pitch
    ta = prm[A_SIDESLIP_ACCEL_TIME]
    tv = prm[A_SIDESLIP_TIME]
    x[X_VY] += dt * (x[X_AV] - x[X_VY] / tv)
    x[X_AV] *= 1.0 - dt / ta
    x[X_PITCH] += dt * x[X_PITCH_RATE]
    st[ST_PITCH_LAG] += dt * (x[X_PITCH_RATE] - st[ST_PITCH_LAG] / spd.OFFSET_TIME)
    turn_accel = turn_accel_along(
        x[X_VY], rg1, st[ST_YAW_ACCEL], phi_mid, p_mid - bp, prm[A_IMU_FORWARD], prm[A_IMU_HEIGHT]
    )
    st[ST_TURN_ACCEL_MEAN] += dt / spd.OFFSET_TIME * (turn_accel - st[ST_TURN_ACCEL_MEAN])
    faster = u / GRADE_REFERENCE_SPEED if u > GRADE_REFERENCE_SPEED else 1.0  # (a NaN speed: the reference's)
    pitch_rate_decay = dt * faster / PITCH_RATE_TIME
    pitch_rate_drive = 2.0 * (PITCH_RATE_SD * faster) ** 2 * pitch_rate_decay  # the Markov process's, on a hilly road
    x[X_PITCH_RATE] *= 1.0 - pitch_rate_decay
    # P <- F P F' + Q with F = I + dt A, A sparse: [phi,bp]=-1, [psi,phi]=pitch, [psi,bq]=-s, [psi,br]=-c (the
    # psi row over cos(pitch) and tan(pitch) of it added to the phi row), [phi,pitch] = r_g / cos^2(pitch),
    # [psi,pitch] = r_g tan(pitch) / cos(pitch), [vy,vy]=-1/tv, [vy,av]=1, [av,av]=-1/ta, [pitch,pitch rate]=1,
    # [pitch rate,pitch rate]=-1/PITCH_RATE_TIME
    FP = st[ST_TMP + 3 * N_X : ST_TMP + 3 * N_X + N_X * N_X].reshape((N_X, N_X))
    for j in range(N_X):
        for i in range(N_X):
            FP[i, j] = P[i, j]
        turn = dt * (pitch1 * P[X_PHI, j] - s * P[X_BQ, j] - c * P[X_BR, j])
        FP[X_PHI, j] += tan_pitch * turn - dt * P[X_BP, j] + roll_per_pitch * P[X_PITCH, j]
        FP[X_PSI, j] += turn / cos_pitch + psi_per_pitch * P[X_PITCH, j]
        FP[X_VY, j] += dt * (P[X_AV, j] - P[X_VY, j] / tv)
        FP[X_AV, j] -= dt * P[X_AV, j] / ta
        FP[X_PITCH, j] += dt * P[X_PITCH_RATE, j]
        FP[X_PITCH_RATE, j] -= pitch_rate_decay * P[X_PITCH_RATE, j]
    for i in range(N_X):
        for j in range(N_X):
            P[i, j] = FP[i, j]
        turn = dt * (pitch1 * FP[i, X_PHI] - s * FP[i, X_BQ] - c * FP[i, X_BR])
        P[i, X_PHI] += tan_pitch * turn - dt * FP[i, X_BP] + roll_per_pitch * FP[i, X_PITCH]
        P[i, X_PSI] += turn / cos_pitch + psi_per_pitch * FP[i, X_PITCH]
        P[i, X_VY] += dt * (FP[i, X_AV] - FP[i, X_VY] / tv)
        P[i, X_AV] -= dt * FP[i, X_AV] / ta
        P[i, X_PITCH] += dt * FP[i, X_PITCH_RATE]
        P[i, X_PITCH_RATE] -= pitch_rate_decay * FP[i, X_PITCH_RATE]
    P[X_PHI, X_PHI] += prm[A_Q_ROLL] ** 2 * dt
    P[X_PSI, X_PSI] += prm[A_Q_HEADING] ** 2 * dt
    if not rates_ok or saturated:
        # integrated a held (or saturated) rate: its error is the same every such cycle, so the roll's and heading's
        # grow with the run's length (n cycles: n UNMEASURED_RATE_SD dt), not with its square root
        st[ST_HELD] += 1.0
        grow = (2.0 * st[ST_HELD] - 1.0) * (UNMEASURED_RATE_SD * dt) ** 2
        P[X_PHI, X_PHI] += grow
        P[X_PSI, X_PSI] += grow
        # ... and nothing measures the grade's rate: it drives as on a hilly road, whatever the gate said before
        P[X_PITCH_RATE, X_PITCH_RATE] += pitch_rate_drive
    else:
        st[ST_HELD] = 0.0
    qb = prm[A_Q_GYRO_BIAS] ** 2 * dt
    P[X_BP, X_BP] += qb
    P[X_BQ, X_BQ] += qb
    P[X_BR, X_BR] += qb
    P[X_BAY, X_BAY] += prm[A_Q_ACCEL_BIAS] ** 2 * dt
    P[X_BAX, X_BAX] += prm[A_Q_ACCEL_BIAS] ** 2 * dt
    P[X_BAZ, X_BAZ] += prm[A_Q_ACCEL_BIAS] ** 2 * dt
    P[X_PITCH, X_PITCH] += PITCH_DRIFT**2 * dt
    st[ST_PITCH_RATE_SEEN] += dt / PITCH_RATE_SEEN_TIME * (pitch1 - st[ST_PITCH_RATE_SEEN])
    seen2 = min(st[ST_PITCH_RATE_SEEN] ** 2, st[ST_PITCH_RATE_FELT] ** 2)  # the gyros and the accelerometer agree
    # ... and the lateral specific force agrees with the roll: a roll gone wrong (a gyro's fault) makes a pitch rate
    # of the turn's rate times its error, which the grade's rate must not take (closed at half the monitor's limit)
    lateral_sd = _running_mean_sd(min(dt / prm[A_CONSISTENCY_TIME], 1.0))
    lateral_doubt = abs(st[ST_MEAN_LATERAL]) / (lateral_sd * prm[A_CONSISTENCY_LIMIT])
    level = PITCH_RATE_LEVEL * faster  # a level road's vertical curvature, at this speed
    if st[ST_LEVEL_PRIOR_DUE] != 0.0:
        # level: the gyros' and the vertical accelerometer's pitch rates both below a level road's
        seen_level = max(abs(st[ST_PITCH_RATE_SEEN]), abs(st[ST_PITCH_RATE_FELT])) < level
        riding = rates_ok and u >= prm[A_COURSE_MIN_SPEED]
        st[ST_LEVEL_FOR] = st[ST_LEVEL_FOR] + dt if riding and seen_level else 0.0
        if st[ST_LEVEL_FOR] >= LEVEL_ROAD_TIME:
            for b in (X_BAY, X_BAX, X_BAZ):
                _widen_prior(st, b, prm[A_INIT_ACCEL_BIAS_SD] ** 2, prm[A_LEVEL_ROAD_ACCEL_BIAS_SD] ** 2)
            st[ST_LEVEL_PRIOR_DUE] = 0.0
    if st[ST_GRADE_TEST_DUE] != 0.0:
        _grade_start_test(st, prm, u, s, c, q_mid, r_mid, PITCH_RATE_SD * faster, dt)
    opening = seen2 / (seen2 + level * level) * max(1.0 - GRADE_DOUBT_CLOSES * lateral_doubt, 0.0)
    P[X_PITCH_RATE, X_PITCH_RATE] += pitch_rate_drive * opening
    # near the grip limit the tyres' forces, and with them the sideslip, move faster (a slide in a weave)
    lat_ratio = _corner_excess(x[X_PHI], prm) / prm[A_SIDESLIP_ACCEL_REF]
    # ... and in a quick change of yaw at speed: the slip angles follow the forces, v_y' ~ (l_r - u^2 m_r / C_r) r'
    # (the 100 km/h lane change of a heavier rider: a sideslip acceleration of ~2 m/s^2 the Markov model's
    # stationary 0.6 m/s^2 did not allow, read as a bias: docs/estimator.md, "The sideslip in a quick change of yaw")
    yaw_drive = min(prm[A_SIDESLIP_COMPLIANCE] * u * u * abs(st[ST_YAW_ACCEL]), MAX_LATERAL_ACCEL)
    yaw_ratio = yaw_drive / prm[A_SIDESLIP_ACCEL_REF]
    P[X_AV, X_AV] += prm[A_Q_SIDESLIP_ACCEL] ** 2 * (1.0 + lat_ratio * lat_ratio + yaw_ratio * yaw_ratio) * dt
    P[X_VY, X_VY] += 1e-6 * dt
    # heading increments for the GPS latency (newest first)
    for k in range(MAX_LATENCY_CYCLES - 1, 0, -1):
        st[ST_PSI_HIST + k] = st[ST_PSI_HIST + k - 1]
    st[ST_PSI_HIST] = d_psi

    # ---- 4. this cycle's inputs become the previous ones ----
    prev[PREV_P3] = prev[PREV_P2]
    prev[PREV_P2] = prev[PREV_P]
    prev[PREV_RG2] = prev[PREV_RG]
    if rates_ok:
        prev[PREV_P] = p
        prev[PREV_Q] = q
        prev[PREV_R] = r
    phi = x[X_PHI]
    s, c = math.sin(phi), math.cos(phi)
    prev[PREV_RG] = (prev[PREV_Q] - x[X_BQ]) * s + (prev[PREV_R] - x[X_BR]) * c
    prev[PREV_FY3] = prev[PREV_FY2]
    prev[PREV_FY2] = prev[PREV_FY]
    prev[PREV_FY] = f_y
    prev[PREV_FZ] = f_z
    prev[PREV_U] = u
    prev[PREV_U_VAR] = u_sd * u_sd
    prev[PREV_OK] = 1.0 if accel_ok else 0.0
    prev[PREV_RATES_OK2] = prev[PREV_RATES_OK]
    prev[PREV_RATES_OK] = 1.0 if rates_ok else 0.0

    tan_pitch, cos_pitch = math.tan(x[X_PITCH]), math.cos(x[X_PITCH])  # predicted above
    out[OUT_ROLL] = phi
    out[OUT_ROLL_RATE] = prev[PREV_P] - x[X_BP] + tan_pitch * prev[PREV_RG]
    out[OUT_YAW_RATE] = prev[PREV_RG] / cos_pitch
    out[OUT_PITCH] = x[X_PITCH]
    out[OUT_PITCH_DOUBT] = abs(st[ST_OFFSET_DOUBT]) / OFFSET_DOUBT_LEVEL
    out[OUT_ROLL_SD] = math.sqrt(max(P[X_PHI, X_PHI], 0.0))
    out[OUT_BP] = x[X_BP]
    out[OUT_BQ] = x[X_BQ]
    out[OUT_BR] = x[X_BR]
    out[OUT_BAY] = x[X_BAY]
    out[OUT_VY] = x[X_VY]
    out[OUT_REJECTED] = rejected
    out[OUT_HEADING] = _wrap(x[X_PSI])
    out[OUT_NU_LATERAL] = nu_lateral
    out[OUT_NU_PITCH] = nu_pitch
    out[OUT_NU_COURSE] = nu_course
    out[OUT_COURSE_FIX] = course_fix
    # r_ground = (q - b_q) sin(phi) + (r - b_r) cos(phi): its variance from the biases' covariance
    var_r = s * s * P[X_BQ, X_BQ] + c * c * P[X_BR, X_BR] + 2.0 * s * c * P[X_BQ, X_BR]
    out[OUT_YAW_RATE_SD] = math.sqrt(max(var_r, 0.0))
    out[OUT_BAY_SD] = math.sqrt(max(P[X_BAY, X_BAY], 0.0))
    out[OUT_ROLL_CORRECTION] = roll_correction


# ---- the estimator's stage: the filter with its inputs from the inputs and speed stages ----


def build_params(settings, design) -> np.ndarray:
    sens = settings.sensors
    prm = attitude_params(
        float(design.sample_time),
        settings.vehicle.g,
        sens.imu_height,
        sens.imu_forward,
        settings.estimator.attitude,
        sens.gps_latency,
    )
    prm[A_CAL_SPEED] = sens.gyro_calibration_speed
    prm[A_CAL_MAX_RATE] = sens.gyro_calibration_max_rate
    tuning = settings.estimator.attitude
    prm[A_CONSISTENCY_HOLD] = tuning.consistency_hold
    prm[A_COURSE_INTERVAL] = GPS_FIX_INTERVAL
    return prm


@njit(cache=True)
def attitude_stage(st: np.ndarray, prm: np.ndarray, out: np.ndarray, inputs: np.ndarray, speed: np.ndarray) -> None:
    """One cycle from the inputs and speed stages' outputs: standstill detection (the gyros then read their
    biases), the speed's uncertainty (the speed filter dead-reckons on the accelerometer in a GPS dropout),
    the GPS course, and whether the filter's outputs can be used (OUT_OK)."""
    raw = inputs[inp.OUT_RAW : inp.OUT_RAW + inp.N_RAW]
    u = speed[spd.OUT_U]
    speed_known = speed[spd.OUT_KNOWN] != 0.0
    reasons_now = int(inputs[inp.OUT_REASONS])
    # the speed stage's GPS age and loss (no fix taken), never below the inputs stage's (no usable fix): a refused
    # or doubted fix corrects nothing
    standstill = (
        speed_known
        and speed[spd.OUT_GPS_LOST] == 0.0
        and u < prm[A_CAL_SPEED]
        and reasons_now & ~REASON_SPEED_LOW == 0
        and abs(raw[inp.RAW_P] - st[ST_X + X_BP]) < prm[A_CAL_MAX_RATE]
        and abs(raw[inp.RAW_R] - st[ST_X + X_BR]) < prm[A_CAL_MAX_RATE]
    )
    speed_sd = 0.1 + 0.5 * min(speed[spd.OUT_GPS_AGE], 10.0)
    saturated = max(abs(raw[inp.RAW_P]), abs(raw[inp.RAW_Q]), abs(raw[inp.RAW_R])) >= GYRO_SATURATED
    force = math.sqrt(raw[inp.RAW_AX] ** 2 + raw[inp.RAW_AY] ** 2 + raw[inp.RAW_AZ] ** 2)
    accel_plausible = ACCEL_TRUSTED_MIN_G * prm[A_G] <= force <= ACCEL_TRUSTED_MAX_G * prm[A_G]
    corrupt = (reasons_now & _CORRUPT_INPUT) != 0
    in_burst = corrupt or st[ST_CORRUPT_RUN] > 0.0  # its clean gaps and first clean cycle included
    if corrupt and st[ST_CORRUPT_RUN] == 0.0:  # a burst begins: where it found the biases, before its data
        for k in range(N_BIASES):
            st[ST_BURST_BIASES + k] = st[ST_X + X_BP + k]
        st[ST_BURST_ROLL_MOVED] = 0.0
    attitude_step(
        st,
        out,
        prm,
        raw[inp.RAW_P],
        raw[inp.RAW_Q],
        raw[inp.RAW_R],
        raw[inp.RAW_AY],
        raw[inp.RAW_AZ],
        u if speed_known else 0.0,
        speed_sd if speed_known else 30.0,
        inputs[inp.OUT_RATES_OK] != 0.0,
        inputs[inp.OUT_ACCEL_TRUSTED] != 0.0 and accel_plausible,
        inputs[inp.OUT_COURSE],
        inputs[inp.OUT_COURSE_NEW] != 0.0 and speed[spd.OUT_GPS_DOUBTED] == 0.0,  # a doubted receiver's course too
        standstill,
        saturated,
        not in_burst,
        inputs[inp.OUT_IMU_FRESH] != 0.0,
        speed[spd.OUT_ACCEL_OFFSET] if speed_known and speed[spd.OUT_GPS_LOST] == 0.0 else math.nan,
        speed[spd.OUT_ACCEL_OFFSET_AGE],
    )
    if in_burst:
        st[ST_BURST_ROLL_MOVED] += out[OUT_ROLL_CORRECTION]
    if corrupt:
        st[ST_CORRUPT_RUN] += 1.0
        st[ST_CLEAN_RUN] = 0.0
    else:
        st[ST_CLEAN_RUN] += 1.0
        if st[ST_CLEAN_RUN] == 1.0 and st[ST_CORRUPT_RUN] >= BURST_CYCLES:
            _doubt_what_the_burst_moved(st)  # the burst is over (for now): what it left is doubted, once
            st[ST_CORRUPT_RUN] = 0.0
        if st[ST_CLEAN_RUN] >= BURST_GAP:
            st[ST_CORRUPT_RUN] = 0.0
    out[OUT_OK] = 1.0 if st[ST_INIT] == 1.0 and all_finite(out, N_FILTER_OUT) else 0.0
    out[OUT_SATURATED] = 1.0 if saturated else 0.0
    out[OUT_REJECTED_RUN] = st[ST_REJECTED]
    # re-learning the biases is for riding; at a stop the zero-rate calibration reads them, and a rider rocking
    # the scooter there is motion the filter cannot model, not a bias
    riding = speed_known and u >= prm[A_COURSE_MIN_SPEED]
    consistency_monitor(st, prm, out, riding)


@njit(cache=True)
def _reacquire_biases(st: np.ndarray, prm: np.ndarray) -> None:
    """The innovations contradict the biases the filter believes (a gyro whose bias stepped, a scale error):
    reopen the biases' uncertainty by their initial spread so the data can move them again."""
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    for b in (X_BP, X_BQ, X_BR):
        P[b, b] += prm[A_INIT_GYRO_BIAS_SD] ** 2
    P[X_BAY, X_BAY] += prm[A_INIT_ACCEL_BIAS_SD] ** 2


@njit(cache=True)
def _doubt_what_the_burst_moved(st: np.ndarray) -> None:
    """A burst of corrupt input has ended. Whatever of it passed every check moved the estimate by the
    measurement updates it took part in: the biases by how far they are from where the burst found them (only
    updates move them) and the roll by its updates' sum. The filter cannot tell garbage from data, so it doubts
    exactly that much: each variance grows by its move squared. Garbage that moved them along what a steady turn
    cannot observe (a roll error with matching biases) is doubted until the data pin it down again; a burst that
    was dropped (frames refused, rates held, whose uncertainty the prediction already grew) moved nothing and
    leaves the estimate as sure as the clean data made it (docs/estimator.md, "Known gaps")."""
    P = st[ST_P : ST_P + N_X * N_X].reshape((N_X, N_X))
    for k in range(N_BIASES):
        moved = st[ST_X + X_BP + k] - st[ST_BURST_BIASES + k]
        P[X_BP + k, X_BP + k] += moved * moved
    moved = st[ST_BURST_ROLL_MOVED]
    P[X_PHI, X_PHI] += moved * moved


@njit(cache=True)
def _reacquire_roll(st: np.ndarray, prm: np.ndarray) -> None:
    """... and the roll's, which those biases have moved for as long as the filter believed them (QUIET_*)."""
    st[ST_P + X_PHI * N_X + X_PHI] += prm[A_INIT_ROLL_SD] ** 2


@njit(cache=True)
def _clip_nu(nu: float) -> float:
    """A whitened innovation as the running means take it: a burst of large ones of either sign (a slide or a
    weave in a deep corner, which the sideslip state cannot follow) is not a bias, and a bias shows as a
    persistent shift well inside this bound."""
    return min(max(nu, -NU_CLIP), NU_CLIP)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def consistency_monitor(st: np.ndarray, prm: np.ndarray, out: np.ndarray, riding: bool) -> None:
    """Is the filter consistent with its data? A consistent filter's whitened innovations are zero-mean with
    unit variance; a bias that stepped or a gyro scale error biases them for as long as the filter believes
    the wrong thing, which a running mean sees long before the error is large (docs/estimator.md, "Attitude
    consistency"). The statistic is the larger |running mean| of the lateral-force and rotation-axis
    innovations in standard deviations of a white sequence's running mean; beyond the limit the roll is
    flagged (OUT_INCONSISTENT, held while the means stay above half the limit and for the hold time after) and
    the biases' uncertainty is reopened once per alarm while `riding`."""
    dt = prm[A_DT]
    alpha = min(dt / prm[A_CONSISTENCY_TIME], 1.0)
    # the GPS course comes once per fix: its mean moves per fix, by the fix interval's share
    alpha_fix = min(prm[A_COURSE_INTERVAL] / prm[A_CONSISTENCY_TIME], 1.0)
    if out[OUT_OK] == 0.0:
        st[ST_MEAN_LATERAL] = 0.0
        st[ST_MEAN_PITCH] = 0.0
        st[ST_MEAN_COURSE] = 0.0
    else:
        st[ST_MEAN_LATERAL] += alpha * (_clip_nu(out[OUT_NU_LATERAL]) - st[ST_MEAN_LATERAL])
        st[ST_MEAN_PITCH] += alpha * (_clip_nu(out[OUT_NU_PITCH]) - st[ST_MEAN_PITCH])
        if out[OUT_COURSE_FIX] != 0.0:
            st[ST_MEAN_COURSE] += alpha_fix * (_clip_nu(out[OUT_NU_COURSE]) - st[ST_MEAN_COURSE])
    white_sd = _running_mean_sd(alpha)
    white_sd_fix = _running_mean_sd(alpha_fix)
    stat = max(max(abs(st[ST_MEAN_LATERAL]), abs(st[ST_MEAN_PITCH])) / white_sd, abs(st[ST_MEAN_COURSE]) / white_sd_fix)
    limit = prm[A_CONSISTENCY_LIMIT]
    if stat > limit:
        st[ST_INCONSISTENT_FOR] = prm[A_CONSISTENCY_HOLD] + dt
    elif stat > 0.5 * limit and st[ST_INCONSISTENT_FOR] > 0.0:
        st[ST_INCONSISTENT_FOR] = prm[A_CONSISTENCY_HOLD] + dt
    elif st[ST_INCONSISTENT_FOR] > 0.0:
        st[ST_INCONSISTENT_FOR] -= dt
    if st[ST_INCONSISTENT_FOR] <= 0.0:
        st[ST_REACQUIRED] = 0.0
    elif riding:  # an alarm raised at a stop re-learns once riding
        # ... and out of a hard corner: in one a slide moves the innovations as a bias would, and biases reopened
        # there took it (a healthy ride's alarm at 22 deg of lean near the grip: yaw-gyro bias 0.025 rad/s off and
        # the roll 4 deg off after the corner, docs/estimator.md)
        if st[ST_REACQUIRED] == 0.0 and _corner_excess(st[ST_X + X_PHI], prm) == 0.0:
            _reacquire_biases(st, prm)
            st[ST_REACQUIRED] = 1.0
        if st[ST_REACQUIRED] == 1.0 and st[ST_QUIET] >= QUIET_CYCLES:  # the roll once a slide is over
            _reacquire_roll(st, prm)
            st[ST_REACQUIRED] = 2.0
    out[OUT_CONSISTENCY] = stat
    out[OUT_INCONSISTENT] = 1.0 if st[ST_INCONSISTENT_FOR] > 0.0 else 0.0


STAGE = Stage(
    name="attitude",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    reset=lambda state, params: restart(state),  # roll and heading again from the data; the sensor biases are kept
    doc="kinematic EKF: roll, heading, gyro and accelerometer biases, sideslip; standstill and GPS course",
)
