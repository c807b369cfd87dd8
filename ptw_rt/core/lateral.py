"""Stage 6, lateral dynamics and tyres: the tyre bank (`ptw_rt.core.tyre_bank`) of fusion filters (jitted).

One fusion filter (`ptw_rt.core.kalman`) per hypothesis of the tyres' scale, and beside it one whose tyre forces
may stray further from the tyre model; the published states (torque, steer rate, v_y, forces) are the latter's
posterior mixture, so the tyres they run on are the learned ones, and the
scale estimate with its spread and the filters' consistency (NIS) are this stage's outputs (the supervisor
makes the stiffness valid bits from them). The published scale is the small-slip posterior's divided by the mean
slope ratio of the cycles it learned from (`_learn_slope_ratio`: the linear filters measure the tyres' slope where
they work, below the small-slip stiffness once they use a share of a wet road's grip; docs/estimator.md, "The
tyres' slope at their working point"). Learning is allowed only from sound inputs (this cycle's
measurements new and in range), after the filters settled, above `min_learning_speed` and below
`max_learning_roll` (the tyres' linear range); the bank itself also requires excitation.

y = [steer, ground yaw rate, roll rate, a_y, kinematic roll]: the rates come bias-corrected from the attitude
filter, whose roll is the fifth measurement. A measurement that is not there this cycle (accelerometer held,
attitude filter not running) is replaced by the filter's own prediction of it (no innovation). The filter runs
only while the model-based observers run (conditioning's OUT_RUN), and coasts through a short silence of the
steer encoder (`MAX_STEER_COAST`) or of the IMU's rates (`MAX_IMU_COAST`) while the other is there: the silent
sensor's measurements are the filter's own prediction, nothing is learned, the convergence clock restarts (so
nothing it publishes is VALID until it has run on all sensors again) and OUT_RAN says z is the filter's; a
longer silence stops it as before. A blown-up or implausible estimate resets it (OUT_DIVERGED, the supervisor
raises REASON_DIVERGING).

The observers' convergence clock lives here (OUT_RUN_TIME: seconds since the model-based observers last
(re)started; the supervisor's CONVERGING mode and the stiffness stage's permission to adapt use it). Nothing
the diagnostics stage does touches it: its observers are cross-checks, not inputs of these filters.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import inputs as inp
from ptw_rt.core import kalman as kf
from ptw_rt.core import speed as spd
from ptw_rt.core import tyre_bank as tb
from ptw_rt.core.stage import Layout, Stage, all_finite, v1, v2, v3

MAX_HYPOTHESES = tb.MAX_COUNT  # the bank's state is laid out for this many (the design file has `len(tb_scale)`)
# s the inputs must be free of every fault reason before the filters' innovations are evidence about the tyres: in
# a burst of corrupt frames a garbage payload whose 4-bit counter matched passes every check of its own (one in 16),
# and a cycle whose other frames were sound took it as a measurement (`sensor_faults`: a lateral acceleration of
# -15 m/s^2 mid-burst put the tyre filters' NIS at 30 and the stiffness lost VALID for 2.5 s)
INPUT_QUIET_TIME = 0.2

STATE = Layout(
    "ST_",
    bank=tb.state_size(MAX_HYPOTHESES),  # the tyre bank (ptw_rt.core.tyre_bank layout, for its H)
    run_time=1,  # s since the model-based observers last (re)started
    ay_mean=1,  # m/s^2: running mean of a_y (`bias_window`): what a constant steer error biases the slip by
    ay_square=1,  # m^2/s^4: running mean of a_y^2: the slip signal the tyres are learned from
    tyre_evidence=1,  # s of learning cycles behind the tyre estimate, faded with the bank's memories
    slope_sum=1,  # the tyres' slope over their small-slip stiffness, summed over the learning cycles (faded) ...
    slope_weight=1,  # ... and their (faded) count: the mean slope ratio the bank's scale is corrected by
    small_slip_scale=1,  # last cycle's published scale (the peak force of this cycle's slope ratio; 0: none yet)
    long_accel=1,  # m/s^2: the longitudinal accelerometer beyond its offset against GPS, low-passed (LONG_ACCEL_TIME)
    ran=1,  # 1: the filters ran last cycle (a coast only continues a running filter)
    coast_time=1,  # s the filters have coasted through a silent sensor
    input_quiet=1,  # s since the inputs last raised a fault reason (INPUT_QUIET_TIME)
    y=kf.N_Y,  # scratch: this cycle's measurements
    scratch=tb.SCRATCH_SIZE,  # the bank's scratch
    bank_out=tb.OUT_SIZE,  # the bank's outputs
)
(
    ST_BANK,
    ST_RUN_TIME,
    ST_AY_MEAN,
    ST_AY_SQUARE,
    ST_TYRE_EVIDENCE,
    ST_SLOPE_SUM,
    ST_SLOPE_WEIGHT,
    ST_SMALL_SLIP_SCALE,
    ST_LONG_ACCEL,
    ST_RAN,
    ST_COAST_TIME,
    ST_INPUT_QUIET,
    ST_Y,
    ST_SCRATCH,
    ST_BANK_OUT,
) = STATE.offsets

PARAMS = Layout(
    "P_",
    dt=1,
    max_roll=1,  # rad: beyond, the filter has diverged
    max_torque=1,  # N m: likewise
    converge_time=1,  # s after a (re)start before the filters' innovations are evidence
    max_learning_roll=1,  # rad: beyond, the tyres leave their linear range: no learning
    max_learning_long_accel=1,  # m/s^2: beyond, load moves between the axles: no learning
    min_learning_speed=1,  # m/s
    max_learning_bias_share=1,  # no learning while the gyro's and accelerometer's bias spread may move k by more
    steer_per_yaw=1,  # m: wheelbase / cos(caster), the kinematic steer per (yaw rate / speed)
    slip_per_ay=1,  # rad/(m/s^2): |front - rear slip angle| of a steady turn per lateral acceleration (nominal tyres)
    bias_alpha=1,  # share per cycle of the a_y running means (dt / bias_window)
    prior_sd=1,  # sd of log k of the prior around the start value
    restored_sd=1,  # ... around a restored (persisted) value
    nominal=4,  # N/rad: the nominal file's [C_af, C_gf, C_ar, C_gr]
    axle_load=2,  # N: the file's static [front, rear] normal loads
    slip_shape=1,  # C_a of the tyres' saturating law (`_slope_ratio`)
    camber_shape=1,  # C_g
    saturation_friction=1,  # peak force per load of tyres at the file's stiffness (k = 1)
    saturation_uncertainty=1,  # share of the slope correction's log taken as its own sd
    bank=tb.PARAM_SIZE,  # the bank's parameters (ptw_rt.core.tyre_bank B_*)
)
(
    P_DT,
    P_MAX_ROLL,
    P_MAX_TORQUE,
    P_CONVERGE_TIME,
    P_MAX_LEARNING_ROLL,
    P_MAX_LEARNING_LONG_ACCEL,
    P_MIN_LEARNING_SPEED,
    P_MAX_LEARNING_BIAS_SHARE,
    P_STEER_PER_YAW,
    P_SLIP_PER_AY,
    P_BIAS_ALPHA,
    P_PRIOR_SD,
    P_RESTORED_SD,
    P_NOMINAL,
    P_AXLE_LOAD,
    P_SLIP_SHAPE,
    P_CAMBER_SHAPE,
    P_SATURATION_FRICTION,
    P_SATURATION_UNCERTAINTY,
    P_BANK,
) = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    z=kf.N_Z,  # the corrected state [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, tau] (0 while not running)
    run_time=1,  # s since the model-based observers last (re)started
    diverged=1,  # 1: the filter was reset this cycle
    tyre_scale=1,  # k: the tyres' small-slip stiffness over the nominal file's (the bank's over the slope ratio)
    tyre_log_sd=1,  # sd of log k (posterior spread, and the slope correction's own uncertainty)
    tyre_nis=1,  # the most likely hypothesis' windowed mean normalised innovation (consistency; expected kf.N_Y)
    tyre_nis_fast=1,  # ... over the short window
    tyre_learning=1,  # 1: this cycle's evidence moved the estimate
    tyre_evidence=1,  # s of such cycles behind the estimate, faded with the bank's memories (what validity rests on)
    tyre_operating_scale=1,  # k the mixture runs on (evidence at any lean: near saturation, the secant slope)
    tyre_change=1,  # nats: the bank's change statistic (a neighbouring tyre explains the last cycles better)
    tyre_balance_log=1,  # log of the front tyre's factor against the rear's the bank's evidence points to (a check)
    tyre_balance_log_sd=1,  # its sd (inf: no balance between the bank's two balance filters explains the data)
    tyre_zero_error=1,  # rad: the steer zero's error the bank's evidence points to, beyond the conditioning's (a check)
    tyre_zero_error_sd=1,  # rad: its sd
    tyre_stiffness=4,  # N/rad: k x nominal [C_af, C_gf, C_ar, C_gr], what is published
    tyre_slope_ratio=1,  # the mean slope ratio of the cycles learned from (1: small slip; `_slope_ratio`)
    ran=1,  # 1: the filters ran this cycle (z is theirs): on every sensor, or coasting through a silent one
)
(
    OUT_Z,
    OUT_RUN_TIME,
    OUT_DIVERGED,
    OUT_TYRE_SCALE,
    OUT_TYRE_LOG_SD,
    OUT_TYRE_NIS,
    OUT_TYRE_NIS_FAST,
    OUT_TYRE_LEARNING,
    OUT_TYRE_EVIDENCE,
    OUT_TYRE_OPERATING_SCALE,
    OUT_TYRE_CHANGE,
    OUT_TYRE_BALANCE_LOG,
    OUT_TYRE_BALANCE_LOG_SD,
    OUT_TYRE_ZERO_ERROR,
    OUT_TYRE_ZERO_ERROR_SD,
    OUT_TYRE_STIFFNESS,
    OUT_TYRE_SLOPE_RATIO,
    OUT_RAN,
) = OUTPUTS.offsets

# How long the filters coast on their own prediction of a silent sensor while the other is there. The steer is
# the torque's main evidence but its prediction drifts slowly (the rates and a_y still pin the lean and the yaw);
# without the rates the filter has the steer and a_y only, and the roll it runs on drifts within a second.
# Beyond, a restart from the data costs less than the drift (docs/estimator.md, "Coasting through a silent sensor").
MAX_STEER_COAST = 2.0  # s
MAX_IMU_COAST = 0.5  # s

TABLES = (
    ("grid", 1),
    ("tb_scale", 1),
    ("tb_Phi", 3),
    ("tb_K", 3),
    ("kf_C", 2),
    ("tb_Gd", 3),
    ("kf_nonlinear", 1),
    ("tb_Sinv", 3),
    ("tb_logdet", 3),
    ("tb_K_pub", 3),
    ("tb_bal_Phi", 3),
    ("tb_bal_K", 3),
    ("tb_bal_Gd", 3),
    ("tb_bal_Sinv", 3),
    ("tb_bal_logdet", 3),
)
(
    T_GRID,
    T_SCALE,
    T_PHI,
    T_K,
    T_C,
    T_GD,
    T_NONLINEAR,
    T_SINV,
    T_LOGDET,
    T_K_PUB,
    T_BAL_PHI,
    T_BAL_K,
    T_BAL_GD,
    T_BAL_SINV,
    T_BAL_LOGDET,
) = range(len(TABLES))


def steady_slip_difference_per_ay(v) -> float:
    """|alpha_f - alpha_r| per unit lateral acceleration in a steady turn on the nominal tyres [rad/(m/s^2)]: the
    forces m a_y l_r / L and m a_y l_f / L, less the camber forces at the lean a_y / g, over the cornering
    stiffnesses. What a steer (or kinematic-steer) error is compared with: the tyres are learned from it."""
    L = v.l_f + v.l_r
    m = v.mass
    front = (m * v.l_r / L - v.c_gf / v.g) / v.c_af
    rear = (m * v.l_f / L - v.c_gr / v.g) / v.c_ar
    return abs(front - rear)


def build_params(settings, design) -> np.ndarray:
    est = settings.estimator
    tun = est.tyre_bank
    count = len(design.tb_scale)
    if count > MAX_HYPOTHESES:
        raise ValueError(f"the design has {count} tyre hypotheses, at most {MAX_HYPOTHESES} are laid out")
    return PARAMS.vector(
        dt=float(design.sample_time),
        max_roll=est.max_roll,
        max_torque=est.max_rider_torque,
        converge_time=est.converge_time,
        max_learning_roll=tun.max_learning_roll,
        max_learning_long_accel=tun.max_learning_long_accel,
        min_learning_speed=tun.min_learning_speed,
        max_learning_bias_share=tun.max_learning_bias_share,
        steer_per_yaw=(settings.vehicle.l_f + settings.vehicle.l_r) / math.cos(settings.vehicle.caster),
        slip_per_ay=steady_slip_difference_per_ay(settings.vehicle),
        bias_alpha=min(float(design.sample_time) / tun.bias_window, 1.0),
        prior_sd=tun.prior_sd,
        restored_sd=tun.restored_sd,
        nominal=np.array(settings.vehicle.nominal_stiffness()),
        axle_load=np.array([settings.vehicle.front_load, settings.vehicle.rear_load]),
        slip_shape=tun.saturation_slip_shape,
        camber_shape=tun.saturation_camber_shape,
        saturation_friction=tun.saturation_friction,
        saturation_uncertainty=tun.saturation_uncertainty,
        bank=tb.bank_params(count, float(design.sample_time), tun, settings.sensors.steer_count_rad),
    )


@njit(cache=True)
def lateral_stage(
    st: np.ndarray,
    prm: np.ndarray,
    out: np.ndarray,
    tables: np.ndarray,
    tindex: np.ndarray,
    t0: int,
    inputs: np.ndarray,
    speed: np.ndarray,
    attitude: np.ndarray,
    cond: np.ndarray,
) -> None:
    """One cycle. ``tables``/``tindex``: a packed buffer holding TABLES in order from row ``t0``."""
    # a (re)start waits for rates that are this cycle's: after a silence the first frame waits for the next one to
    # confirm it (`ptw_rt.core.inputs`), and filters started on the held rates took up the step as torque
    run = cond[cnd.OUT_RUN] != 0.0 and (st[ST_RAN] != 0.0 or inputs[inp.OUT_RATES_OK] != 0.0)
    coast = _coasting(st, prm, run, inputs, cond)
    st[ST_INPUT_QUIET] = 0.0 if int(inputs[inp.OUT_REASONS]) != 0 else st[ST_INPUT_QUIET] + prm[P_DT]
    filtering = run or coast
    if not run:
        st[ST_RUN_TIME] = 0.0
    else:
        st[ST_RUN_TIME] += prm[P_DT]
    bank = st[ST_BANK : ST_BANK + tb.state_size(MAX_HYPOTHESES)]
    bank_prm = prm[P_BANK : P_BANK + tb.PARAM_SIZE]
    bank_out = st[ST_BANK_OUT : ST_BANK_OUT + tb.OUT_SIZE]
    kf_out = out[OUT_Z : OUT_Z + kf.N_Z]
    diverged = False
    if filtering:
        C = v2(tables, tindex, t0 + T_C)
        delta = cond[cnd.OUT_STEER]
        r_ground = cond[cnd.OUT_YAW_RATE]
        p_rate = cond[cnd.OUT_ROLL_RATE]
        roll_prev = cond[cnd.OUT_DEROLL]
        u = speed[spd.OUT_U]
        y_kf = st[ST_Y : ST_Y + kf.N_Y]
        # a measurement that is not there this cycle (a held accelerometer, a sensor coasted through): the last
        # published state's prediction of it (no innovation to speak of; no evidence about the tyres is taken)
        steer_ok = run or inputs[inp.OUT_STEER_OK] != 0.0
        rates_ok = run or inputs[inp.OUT_IMU_OK] != 0.0
        if steer_ok:
            # every measurement at the IMU's instant: the steer, read up to a cycle later or earlier, is carried
            # back with last cycle's steer rate (conditioning.steer_lead)
            shift = cond[cnd.OUT_STEER_LEAD] * kf_out[kf.DELTA_DOT]
            y_kf[0] = delta - shift if math.isfinite(shift) else delta
        else:
            y_kf[0] = _predicted(C, 0, kf_out)
        y_kf[1] = r_ground if rates_ok else _predicted(C, 1, kf_out)
        y_kf[2] = p_rate if rates_ok else _predicted(C, 2, kf_out)
        accel_trusted = inputs[inp.OUT_ACCEL_TRUSTED] != 0.0
        attitude_ok = attitude[att.OUT_OK] != 0.0 and rates_ok
        y_kf[3] = cond[cnd.OUT_A_Y] if accel_trusted else _predicted(C, 3, kf_out)
        y_kf[4] = roll_prev if attitude_ok else kf_out[kf.PHI]
        observe = (
            run
            and accel_trusted
            and inputs[inp.OUT_STEER_TRUSTED] != 0.0  # a held steer (a frame waiting for confirmation) is no evidence
            and attitude_ok
            and inputs[inp.OUT_RATES_OK] != 0.0
            and st[ST_INPUT_QUIET] >= INPUT_QUIET_TIME - 0.5 * prm[P_DT]  # this cycle's reasons included
            and st[ST_RUN_TIME] >= prm[P_CONVERGE_TIME]
        )
        track = observe and u >= prm[P_MIN_LEARNING_SPEED]
        long_accel = _long_accel(st, prm, inputs, speed)
        bias_share = _bias_share(st, prm, attitude[att.OUT_YAW_RATE_SD], attitude[att.OUT_BAY_SD], y_kf[3], u)
        learn = (
            track
            and abs(roll_prev) < prm[P_MAX_LEARNING_ROLL]
            and abs(long_accel) <= prm[P_MAX_LEARNING_LONG_ACCEL]
            and bias_share <= prm[P_MAX_LEARNING_BIAS_SHARE]
            and not att.pitch_doubted(attitude)
        )
        tb.bank_step(
            bank,
            bank_out,
            st[ST_SCRATCH : ST_SCRATCH + tb.SCRATCH_SIZE],
            bank_prm,
            y_kf,
            u,
            roll_prev,
            observe,
            track,
            learn,
            v1(tables, tindex, t0 + T_GRID),
            v1(tables, tindex, t0 + T_SCALE),
            v3(tables, tindex, t0 + T_PHI),
            v3(tables, tindex, t0 + T_K),
            C,
            v3(tables, tindex, t0 + T_GD),
            v1(tables, tindex, t0 + T_NONLINEAR),
            v3(tables, tindex, t0 + T_SINV),
            v3(tables, tindex, t0 + T_LOGDET),
            v3(tables, tindex, t0 + T_K_PUB),
            v3(tables, tindex, t0 + T_BAL_PHI),
            v3(tables, tindex, t0 + T_BAL_K),
            v3(tables, tindex, t0 + T_BAL_GD),
            v3(tables, tindex, t0 + T_BAL_SINV),
            v3(tables, tindex, t0 + T_BAL_LOGDET),
            cond[cnd.OUT_STEER_ZERO_SHIFT],
            cond[cnd.OUT_STEER_ZERO_SD],
        )
        for k in range(kf.N_Z):
            kf_out[k] = bank_out[tb.OUT_Z + k]
        if (
            not all_finite(kf_out, kf.N_Z)
            or abs(kf_out[kf.PHI]) > prm[P_MAX_ROLL]
            or abs(kf_out[kf.TAU]) > prm[P_MAX_TORQUE]
            or not abs(bank_out[tb.OUT_EVIDENCE_ROLL]) <= prm[P_MAX_ROLL]  # also a NaN
            or not abs(bank_out[tb.OUT_EVIDENCE_TORQUE]) <= prm[P_MAX_TORQUE]
        ):
            tb.restart_filters(bank, bank_prm)
            diverged = True
            for k in range(kf.N_Z):
                kf_out[k] = 0.0
            kf_out[kf.PHI] = cond[cnd.OUT_ROLL_LAST]
            kf_out[kf.DELTA] = delta
            kf_out[kf.R] = r_ground
            kf_out[kf.PHI_DOT] = p_rate
    else:
        tb.restart_filters(bank, bank_prm)
        bank_out[tb.OUT_LEARNING] = 0.0
        for k in range(kf.N_Z):
            kf_out[k] = 0.0
    if bank_out[tb.OUT_SCALE] == 0.0:  # the bank has not run yet: its prior's centre, no claim
        bank_out[tb.OUT_SCALE] = tb.prior_centre(bank, bank_prm)
        bank_out[tb.OUT_LOG_SD] = prm[P_PRIOR_SD]
        bank_out[tb.OUT_MAP_SCALE] = bank_out[tb.OUT_SCALE]
        bank_out[tb.OUT_MAP_NIS] = kf.N_Y
        bank_out[tb.OUT_MAP_NIS_FAST] = kf.N_Y
        bank_out[tb.OUT_OPERATING_SCALE] = bank_out[tb.OUT_SCALE]
    if run and bank_out[tb.OUT_LEARNING] != 0.0:
        _learn_slope_ratio(st, prm, bank_out[tb.OUT_SCALE], kf_out[kf.FYF], kf_out[kf.FYR], kf_out[kf.PHI])
    ratio = st[ST_SLOPE_SUM] / st[ST_SLOPE_WEIGHT] if st[ST_SLOPE_WEIGHT] > 0.0 else 1.0
    scale = bank_out[tb.OUT_SCALE] / ratio
    st[ST_SMALL_SLIP_SCALE] = scale
    correction_sd = prm[P_SATURATION_UNCERTAINTY] * math.log(1.0 / ratio)
    out[OUT_TYRE_SCALE] = scale
    out[OUT_TYRE_LOG_SD] = math.sqrt(bank_out[tb.OUT_LOG_SD] ** 2 + correction_sd * correction_sd)
    out[OUT_TYRE_SLOPE_RATIO] = ratio
    out[OUT_TYRE_NIS] = bank_out[tb.OUT_MAP_NIS]
    out[OUT_TYRE_NIS_FAST] = bank_out[tb.OUT_MAP_NIS_FAST]
    out[OUT_TYRE_LEARNING] = bank_out[tb.OUT_LEARNING]
    out[OUT_TYRE_EVIDENCE] = _count_evidence(st, prm, bank_out[tb.OUT_LEARNING] != 0.0)
    out[OUT_TYRE_OPERATING_SCALE] = bank_out[tb.OUT_OPERATING_SCALE]
    out[OUT_TYRE_CHANGE] = bank_out[tb.OUT_CHANGE]
    # the balance is a check, not applied to the published front: an encoder zero a count off and a payload move it
    # as much as a front tyre 10 % off (docs/estimator.md, "Tyres that differ by axle: the balance check")
    out[OUT_TYRE_BALANCE_LOG] = bank_out[tb.OUT_BALANCE_LOG]
    out[OUT_TYRE_BALANCE_LOG_SD] = bank_out[tb.OUT_BALANCE_LOG_SD]
    out[OUT_TYRE_ZERO_ERROR] = bank_out[tb.OUT_ZERO_ERROR]  # a check too: the balance rests on the steer zero
    out[OUT_TYRE_ZERO_ERROR_SD] = bank_out[tb.OUT_ZERO_ERROR_SD]
    for k in range(4):
        out[OUT_TYRE_STIFFNESS + k] = scale * prm[P_NOMINAL + k]
    out[OUT_RUN_TIME] = st[ST_RUN_TIME]
    out[OUT_DIVERGED] = 1.0 if diverged else 0.0
    out[OUT_RAN] = 1.0 if filtering else 0.0
    st[ST_RAN] = 1.0 if filtering and not diverged else 0.0


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _predicted(C: np.ndarray, row: int, z: np.ndarray) -> float:
    """Measurement ``row`` as the state ``z`` predicts it (y = C z)."""
    acc = 0.0
    for c in range(kf.N_Z):
        acc += C[row, c] * z[c]
    return acc


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _coasting(st: np.ndarray, prm: np.ndarray, run: bool, inputs: np.ndarray, cond: np.ndarray) -> bool:
    """The filters coast this cycle: they ran last cycle and only one of the steer encoder and the IMU's rates
    is silent (above the model's speed), for at most that sensor's MAX_*_COAST. Counts the coast's time."""
    steer_ok = inputs[inp.OUT_STEER_OK] != 0.0
    rates_ok = inputs[inp.OUT_IMU_OK] != 0.0
    if run or st[ST_RAN] == 0.0 or cond[cnd.OUT_SPEED_LOW] != 0.0 or steer_ok == rates_ok:
        st[ST_COAST_TIME] = 0.0
        return False
    st[ST_COAST_TIME] += prm[P_DT]
    limit = MAX_STEER_COAST if rates_ok else MAX_IMU_COAST
    return st[ST_COAST_TIME] < limit + 0.5 * prm[P_DT]  # limit / dt cycles (a sum of dt drifts past the limit)


LONG_ACCEL_TIME = 0.3  # s: the longitudinal acceleration of the learning gate is low-passed over this


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _long_accel(st: np.ndarray, prm: np.ndarray, inputs: np.ndarray, speed: np.ndarray) -> float:
    """The longitudinal acceleration (m/s^2): the accelerometer beyond what it reads at a steady speed (its bias and
    the road's grade, the speed stage's offset against GPS), low-passed over LONG_ACCEL_TIME; held while the
    accelerometer is not there."""
    a_x = inputs[inp.OUT_RAW + inp.RAW_AX] - speed[spd.OUT_ACCEL_OFFSET]
    if inputs[inp.OUT_ACCEL_OK] != 0.0 and math.isfinite(a_x):
        st[ST_LONG_ACCEL] += prm[P_DT] / LONG_ACCEL_TIME * (a_x - st[ST_LONG_ACCEL])
    return st[ST_LONG_ACCEL]


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _bias_share(st: np.ndarray, prm: np.ndarray, yaw_rate_sd: float, a_y_sd: float, a_y: float, u: float) -> float:
    """How far (1 sd, as a share of k) the attitude filter's remaining bias uncertainty can move the learned tyres.
    The slip angles are measured against the kinematic steer L r / (u cos caster): a yaw-rate error b shifts it by
    a constant L b / (u cos caster), which a least-squares fit of slip to force turns into a relative error of k of
    (that shift / slip_per_ay) x mean(a_y) / mean(a_y^2); an accelerometer bias error scales the force by the same
    factor. In a one-way corner that is the shift over the slip difference itself (a 0.01 rad/s bias read tyres
    x1.75 on a wet road's corner at 50 km/h); riding left and right it averages out. Updates the a_y means."""
    a = prm[P_BIAS_ALPHA]
    st[ST_AY_MEAN] += a * (a_y - st[ST_AY_MEAN])
    st[ST_AY_SQUARE] += a * (a_y * a_y - st[ST_AY_SQUARE])
    shift = prm[P_STEER_PER_YAW] * yaw_rate_sd / max(u, 1.0)
    # an accelerometer bias error scales the force the slip is fitted to in the same way: a_y_sd over a_y
    return (shift / prm[P_SLIP_PER_AY] + a_y_sd) * abs(st[ST_AY_MEAN]) / max(st[ST_AY_SQUARE], 1e-6)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _count_evidence(st: np.ndarray, prm: np.ndarray, learning: bool) -> float:
    """Seconds of learning cycles behind the tyre estimate, faded with the bank's own memories (its learning one
    while this cycle's evidence moved the estimate, its idle one otherwise): how much the estimate rests on. A
    posterior that a few tenths of a second of one steady corner made narrow is not a measured tyre (its
    innovations are not white; docs/estimator.md, "Tyres")."""
    if learning:
        st[ST_TYRE_EVIDENCE] = st[ST_TYRE_EVIDENCE] * prm[P_BANK + tb.B_LEARN_FORGET] + prm[P_DT]
    else:
        st[ST_TYRE_EVIDENCE] *= prm[P_BANK + tb.B_IDLE_FORGET]
    return st[ST_TYRE_EVIDENCE]


MAX_UTILISATION = 0.95  # of the peak force: the slope ratio's model holds below the peak
MAX_SLIP_PART = 1.4  # rad, atan(B_a alpha) within (-pi/2, pi/2): a force and lean the law cannot pair stay finite
MIN_SLOPE_RATIO = 0.6  # no cycle corrects the scale by more than 1 / this (a force estimate far off the model's)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _slope_ratio(prm: np.ndarray, axle: int, scale: float, force: float, camber: float) -> float:
    """dF/dalpha over the small-slip stiffness at this cycle's working point, for the tyre law
    F = D sin(C_a atan(B_a alpha) + C_g atan(B_g gamma)) with D = k mu_file F_z, B_a = C_alpha / (C_a F_z) and
    B_g = C_gamma / (C_g F_z) (the file's stiffness: a scale k that is the road's grip scales D and the slope, not
    B). The sine's argument is arcsin(F / D); the camber's part of it is C_g atan(B_g gamma) (gamma: the lean,
    the sign convention of the Sharp model's forces), the rest is the slip's. The slope over its small-slip value
    is cos(arg) / (1 + (B_a alpha)^2)."""
    fz = prm[P_AXLE_LOAD + axle]
    peak = max(scale, 1e-3) * prm[P_SATURATION_FRICTION] * fz
    utilisation = max(min(force / peak, MAX_UTILISATION), -MAX_UTILISATION)
    arg = math.asin(utilisation)
    c_g = prm[P_CAMBER_SHAPE]
    b_g = prm[P_NOMINAL + 2 * axle + 1] / (c_g * fz)
    slip_part = (arg - c_g * math.atan(b_g * camber)) / prm[P_SLIP_SHAPE]
    slip_part = max(min(slip_part, MAX_SLIP_PART), -MAX_SLIP_PART)
    b_alpha = math.tan(slip_part)
    return math.cos(arg) / (1.0 + b_alpha * b_alpha)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _learn_slope_ratio(
    st: np.ndarray, prm: np.ndarray, bank_scale: float, force_front: float, force_rear: float, camber: float
) -> None:
    """Adds this learning cycle's slope ratio (both axles' mean) to the faded mean the bank's scale is divided by.
    The data measure the tyres' slope at their working point (the bank's linear filters fit dF/d(slip)); the
    published scale is the small-slip one. The peak is last cycle's published scale's (the correction's fixed
    point); the mean fades with the bank's learning memory, so a new road's cycles replace an old road's."""
    scale = st[ST_SMALL_SLIP_SCALE] if st[ST_SMALL_SLIP_SCALE] > 0.0 else bank_scale
    ratio = 0.5 * (_slope_ratio(prm, 0, scale, force_front, camber) + _slope_ratio(prm, 1, scale, force_rear, camber))
    if not ratio >= MIN_SLOPE_RATIO:  # also a NaN force
        ratio = MIN_SLOPE_RATIO
    forget = prm[P_BANK + tb.B_LEARN_FORGET]
    st[ST_SLOPE_SUM] = st[ST_SLOPE_SUM] * forget + ratio
    st[ST_SLOPE_WEIGHT] = st[ST_SLOPE_WEIGHT] * forget + 1.0


def _bank(st: np.ndarray) -> np.ndarray:
    return st[ST_BANK : ST_BANK + tb.state_size(MAX_HYPOTHESES)]


def _bank_params(prm: np.ndarray) -> np.ndarray:
    return prm[P_BANK : P_BANK + tb.PARAM_SIZE]


def reset(st: np.ndarray, prm: np.ndarray) -> None:
    """Forget the dynamic states; keep what the bank learned (its evidence and prior). The count of learning
    behind the estimate starts again: after a restart the tyres are valid again only on new learning. The bank's
    layout depends on its number of hypotheses (the design's), so its own restart re-initialises its filters
    (a loop over the laid-out maximum wrote into the evidence of a smaller bank)."""
    st[ST_RUN_TIME] = 0.0
    st[ST_TYRE_EVIDENCE] = 0.0
    st[ST_RAN] = 0.0
    st[ST_COAST_TIME] = 0.0
    tb.restart_filters(_bank(st), _bank_params(prm))


def set_prior(st: np.ndarray, prm: np.ndarray, scales: np.ndarray, centre: float, restored: bool) -> None:
    """Start the tyre estimate from `centre` x nominal (a persisted value, or a test's wrong start)."""
    sd = prm[P_RESTORED_SD] if restored else prm[P_PRIOR_SD]
    tb.set_prior(_bank(st), _bank_params(prm), scales, centre, sd)
    st[ST_SLOPE_SUM] = 0.0  # a new start: no working point learned from yet
    st[ST_SLOPE_WEIGHT] = 0.0
    st[ST_SMALL_SLIP_SCALE] = 0.0
    st[ST_BANK_OUT + tb.OUT_SCALE] = 0.0  # the bank has not run on this prior: report its centre until it does


def scale_estimate(st: np.ndarray, prm: np.ndarray, out: np.ndarray) -> float:
    """The current tyre scale (the bank's posterior estimate; its prior's centre before it ran)."""
    k = out[OUT_TYRE_SCALE]
    if k > 0.0:
        return float(k)
    return float(tb.prior_centre(_bank(st), _bank_params(prm)))


STAGE = Stage(
    name="lateral",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    tables=TABLES,
    reset=reset,
    doc="tyre bank of steady-state Kalman filters on the Sharp model: torque, steer rate, v_y, forces, tyre scale",
)
