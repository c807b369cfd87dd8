"""The tyres' scale from a bank of fusion filters (multiple-model estimation; jitted, allocation-free).

Each hypothesis h is the steady-state fusion filter (ptw_rt.core.kalman) of the vehicle whose four tyre
stiffnesses are k_h times the nominal ones (design: ptw_rt.design.tyre_bank). All of them run every
cycle on the same measurements y = [steer, yaw rate, roll rate, a_y, kinematic roll]. The filter whose
tyres are right explains y best; its innovation e = y - C z is white with covariance S, so

    log L_h += -(e' S^-1 e + log det S) / 2          (only while learning is allowed)

and the posterior weight of h is w_h ~ exp(log L_h). Evidence is forgotten with a time constant
(`learning_memory` while learning, so a new road is followed; `idle_memory` otherwise, so what was
learned fades into the prior spread around the current estimate if nothing confirms it), and the prior
is a Gaussian in log k around the start value (nominal, a persisted value, or a wrong start in tests).

Two posteriors share the filters and their innovations. The **small-slip** one takes evidence only in the
tyres' linear range (`learn`): over the slope ratio of its working points (ptw_rt.core.lateral), it is the
published stiffness. The **operating** one takes it at any lean
(`track`): near saturation the tyres act softer than their small-slip slope, and the published torque,
forces and v_y must come from the tyres the vehicle runs on now (`radius_accel`'s long deep corners: torque
error 17-23 % of the peak with the small-slip weights, 12-14 % with the operating ones).

Only a window of 2 `running_half_width` + 1 filters around the small-slip posterior's most likely
hypothesis runs (the cost is per running filter); one that joins the window starts from its neighbour's
state and evidence, and takes its neighbour's innovations as evidence until its own filter has converged
(`join_settle_time`, `_enter_window`).

Each hypothesis runs two filters on the same measurements: its **evidence** filter, whose innovations are
the likelihoods above, and its **publishing** filter, the same vehicle with the tyre forces' process noise
scaled by `fusion_filter.published_force_noise` (design: ptw_rt.design.tyre_bank). The evidence needs the
tyre model's tight link from slip to force (that is what tells tyres apart); the published torque and forces
are better where the forces follow the measured a_y and yaw when the tyres leave the model (near the grip
limit: `mu_drop` on μ 0.85, torque error 16.4 -> 13.7 % of the peak, docs/estimator.md), and with its rider
torque's random walk ×`fusion_filter.published_torque_noise`: the published torque lags less (its error is mostly
lag), while the evidence filters keep the slower walk that keeps their innovations about the tyres.

Outputs: the operating posterior's mixture of the publishing filters' states (what the lateral-dynamics
filter publishes: the learned tyres are the ones the published torque and forces come from), the scale estimate
k = exp(sum w_h log k_h) (or, for a posterior narrower than the grid, the peak of a parabola through the
log-posterior around the most likely hypothesis: `_sub_grid_peak`), its spread sd(log k), the weight and the
windowed mean normalised innovation
(NIS) of the most likely filter: small spread says the data single out one tyre; a NIS near its
expected value says that tyre explains the data. Both together make the valid bit (the supervisor's).

**The balance check.** The one scale cannot say a front tyre that differs from the rear (pressure, wear, another
make): with the front x0.8 it follows the rear and published the front 23 % off. Two more evidence filters run beside
the most likely hypothesis (at `SC_CHECK_H`), its front tyre's stiffnesses times 1 / `balance_step` and `balance_step`
(design: ptw_rt.design.tyre_bank). Over the learning cycles, with the bank's memory, each accumulates by how much it
explains the data better than the window's filter at that hypothesis:

    Lambda_s = forget Lambda_s + (ll_s - ll_centre)        (s = 0, 1; only while learning)

A parabola through Lambda at -step, 0 and +step in the log of the front's factor, with a prior, gives the balance
the evidence points to and its sd (`check_posterior`: OUT_BALANCE_LOG, OUT_BALANCE_LOG_SD); the supervisor
withholds VALID when it points away from the file's balance. A check only: an encoder zero a count off and a payload
read as a balance too (docs/estimator.md, "Tyres that differ by axle: the balance check"). The filters move with the
estimate (when it is `CHECK_MOVE_STEPS` of a step from theirs), starting from the window's filter there and taking
no evidence for `join_settle_time`, as a hypothesis joining the window does; what they learned stays.

**The steer zero check.** The balance rests on the steer encoder's zero: a count off (0.35 deg) is a front slip as
large as a gentle corner's, and the balance filters read it as a front tyre stiffer or softer (a front x0.82 read
x1.23 with the zero a count off, x0.78 with it right). The conditioning learns the zero riding straight only, and a
slalom has no straight. But the evidence filters see the zero in corners too (a constant steer offset, while the
tyres' slip grows with the lateral acceleration): on `handling_40_120` the filter with the zero a quarter count off
explained the ride 400 nats worse. So three more filters run beside the most likely hypothesis: on the bank's own
tables fed the steer less a zero error of -`zero_step` and +`zero_step` (the conditioning's zero taken as right), and
on the stiffer front's tables with +`zero_step`. Their Lambdas, accumulated as the balance filters', and the balance's
make a quadratic in (balance, zero error) whose cross term says how much the one reads as the other; its peak, with
priors (the zero's: how well the conditioning knows its zero), gives both and their marginal spreads
(`check_posterior`: OUT_BALANCE_LOG, OUT_ZERO_ERROR, rad, and their sds). The supervisor withholds VALID unless they
confirm the file's balance and the conditioning's zero (docs/estimator.md, "The steer zero the balance rests on").
A front x0.82 with the zero a quarter count off passed both checks one at a time (each at the other's centre).

Learning is allowed by the caller only from sound inputs, above the validity speed and below a lean
angle beyond which the plant's tyres leave their linear range (the small-slip stiffness is what we
estimate; a saturated tyre would look softer).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import kalman as kf
from ptw_rt.core.schedule import grid_position

# ---- parameters (float64 vector, `bank_params`) ----
B_COUNT = 0  # hypotheses H
B_LEARN_FORGET = 1  # per-cycle factor of the evidence while learning
B_IDLE_FORGET = 2  # per-cycle factor while not learning
B_PRIOR_SD = 3  # sd of log k of the prior around the start value
B_NIS_ALPHA = 4  # share of each cycle's NIS in the windowed mean
B_FLOOR = 5  # log-likelihoods are kept within this of the best (a hypothesis can always come back: a road changes)
B_NIS_FAST_ALPHA = 6  # the same over a short window: a sudden change of road shows here first
B_EXCITATION_ALPHA = 7  # share of each cycle in the mean squares of a_y and yaw rate (excitation)
B_MIN_AY = 8  # m/s^2: RMS lateral acceleration above which the ride tells tyres apart ...
B_MIN_YAW_RATE = 9  # rad/s: ... or RMS yaw rate
B_HALF_WIDTH = 10  # hypotheses run each cycle: the most likely one and this many on each side (module doc)
B_MAX_EVIDENCE_NIS = 11  # no evidence while even the best-fitting filter's short-window NIS is above this
B_CHANGE_DRIFT = 12  # nats per cycle a neighbour of the most likely tyre must beat it by to count as a change ...
B_CHANGE_LEAK = 13  # ... in the change statistic, which fades by this factor per cycle (`_change_statistic`)
B_JOIN_SETTLE = 14  # cycles a hypothesis that joined the window borrows its neighbour's evidence (`_enter_window`)
B_BALANCE_LOG_STEP = 15  # log of the balance filters' factor on the front tyre (module doc)
B_BALANCE_PRIOR_SD = 16  # sd of the log of the front's factor a priori
B_ZERO_STEP = 17  # rad: the zero check's filters' steer zero error, either side (module doc)
B_MAP_HYSTERESIS = 18  # nats another hypothesis must lead the most likely one by to take its place
PARAM_SIZE = 19

# ---- state layout: H blocks of (z, init), then per-hypothesis vectors (log-likelihood, NIS, prior, fast NIS,
# operating log-likelihood, unclipped log-likelihood, cycles left settling, the neighbour it joined from), then
# scalars, then H blocks of the publishing filters, then the balance check's two filters and the steer zero check's
# two (module doc) ----
BLOCK = kf.STATE_SIZE  # one fusion filter's state
N_VECTORS = 8  # per-hypothesis vectors between the filters' blocks and the scalars


@njit(cache=True)
def state_size(count: int) -> int:
    return count * BLOCK + N_VECTORS * count + N_SCALARS + count * BLOCK + N_CHECKS * BLOCK


@njit(cache=True)
def _logl0(count: int) -> int:
    return count * BLOCK


@njit(cache=True)
def _nis0(count: int) -> int:
    return count * BLOCK + count


@njit(cache=True)
def _prior0(count: int) -> int:
    return count * BLOCK + 2 * count


@njit(cache=True)
def _nis_fast0(count: int) -> int:
    return count * BLOCK + 3 * count


@njit(cache=True)
def _logl_operating0(count: int) -> int:
    return count * BLOCK + 4 * count


@njit(cache=True)
def _logl_raw0(count: int) -> int:
    return count * BLOCK + 5 * count


@njit(cache=True)
def _settle0(count: int) -> int:
    """Cycles left in which a hypothesis that joined the window takes its neighbour's evidence (`_enter_window`)."""
    return count * BLOCK + 6 * count


@njit(cache=True)
def _source0(count: int) -> int:
    """The neighbour a settling hypothesis joined from."""
    return count * BLOCK + 7 * count


@njit(cache=True)
def _scalars0(count: int) -> int:
    return count * BLOCK + N_VECTORS * count


@njit(cache=True)
def _published0(count: int) -> int:
    """Hypothesis h's publishing filter is the block at this + h BLOCK (module doc)."""
    return count * BLOCK + N_VECTORS * count + N_SCALARS


@njit(cache=True)
def _checks0(count: int) -> int:
    """The checks' filter `side` (CHECK_TABLES: the balance check's, then the zero check's) is the block at this +
    side BLOCK (module doc)."""
    return _published0(count) + count * BLOCK


SC_CENTRE = 0  # log k of the prior's centre
SC_INIT = 1  # 1 once the prior is set
SC_MS_AY = 2  # windowed mean square of a_y
SC_MS_R = 3  # windowed mean square of the yaw rate
SC_LOW = 4  # first hypothesis of the running window
SC_MAP = 5  # the small-slip posterior's most likely hypothesis of the last cycle (the window's centre)
SC_CHANGE = 6  # the change statistic (`_change_statistic`)
SC_CHECK_H = 7  # the hypothesis the checks' filters (the balance's and the steer zero's) run at (-1: not started)
SC_CHECK_SETTLE = 8  # cycles left in which they take no evidence (they started from another filter's state)
SC_CHECK_LAMBDA = 9  # Lambda of each of the checks' filters (CHECK_TABLES), module doc
# the checks' filters (module doc), each the most likely hypothesis's with (front's factor, steer zero error):
# (x 1 / balance_step, 0), (x balance_step, 0), (x 1, -zero_step), (x 1, +zero_step), (x balance_step, +zero_step);
# their blocks follow each other from _checks0, their Lambdas from SC_CHECK_LAMBDA
CHECK_TABLES = (0, 1, -1, -1, 1)  # the balance tables' side they run on (-1: the bank's own)
CHECK_ZERO = (0.0, 0.0, -1.0, 1.0, 1.0)  # their steer zero error in zero_steps
N_BALANCE = 2  # the first two: the balance check's
N_CHECKS = len(CHECK_TABLES)
SC_ZERO_SHIFT = SC_CHECK_LAMBDA + N_CHECKS  # rad: the conditioning's steer zero the checks' Lambdas are about
N_SCALARS = SC_ZERO_SHIFT + 1
RECENTRE_STEPS = 1.0  # zero steps over which the checks' evidence fades by 1/e as the zero moves (_recentre_zero)
# the checks' filters (the balance's and the steer zero's) move to the most likely hypothesis once the estimate is
# this many steps of the grid from theirs: comparing the balances at a scale a step off would bias them (a stiffer
# front makes up for tyres too soft overall), while following every flicker of the most likely hypothesis between
# two would keep them settling
CHECK_MOVE_STEPS = 0.75

# ---- outputs ----
OUT_Z = 0  # operating posterior's mixture of the publishing filters' corrected states (kf.N_Z)
OUT_SCALE = kf.N_Z  # k
OUT_LOG_SD = OUT_SCALE + 1  # sd of log k
OUT_MAP_WEIGHT = OUT_SCALE + 2  # weight of the most likely hypothesis
OUT_MAP_NIS = OUT_SCALE + 3  # its windowed mean NIS
OUT_MAP_SCALE = OUT_SCALE + 4  # its k
OUT_MAP_NIS_FAST = OUT_SCALE + 5  # its NIS over the short window
OUT_LEARNING = OUT_SCALE + 6  # 1 if this cycle's evidence moved the estimate
OUT_OPERATING_SCALE = OUT_SCALE + 7  # the operating posterior's scale (what the mixture runs on)
OUT_EVIDENCE_ROLL = OUT_SCALE + 8  # the same mixture of the evidence filters' roll and torque (a blown-up filter
OUT_EVIDENCE_TORQUE = OUT_SCALE + 9  # among them shows here, though its states are not published)
OUT_CHANGE = OUT_SCALE + 10  # nats: how much better a neighbouring tyre explains the last cycles (a road that changed)
OUT_BALANCE = OUT_SCALE + 11  # nats: how much better the better balance filter explains the learning (module doc)
OUT_BALANCE_LOG = OUT_SCALE + 12  # log of the front tyre's factor against the rear's learned (module doc)
OUT_BALANCE_LOG_SD = OUT_SCALE + 13  # its sd
OUT_ZERO_ERROR = OUT_SCALE + 14  # rad: the steer zero's error the evidence points to, beyond the conditioning's zero
OUT_ZERO_ERROR_SD = OUT_SCALE + 15  # rad: its sd
OUT_SIZE = OUT_SCALE + 16

MAX_COUNT = 32  # hypotheses the scratch is laid out for (the design file has `len(tb_scale)`)
# scratch needed by `bank_step`: innovation (N_Y), the evidence and the publishing filters' outputs (N_Z) and
# correction forces (N_D), then per hypothesis its log k and its weights in the two posteriors (each computed once
# per cycle: exp and log are most of the bank's cost beside the filters)
SC_E = 0
SC_ZH = SC_E + kf.N_Y
SC_D = SC_ZH + kf.N_Z
SC_ZH_PUB = SC_D + kf.N_D  # the same two for the publishing filter
SC_D_PUB = SC_ZH_PUB + kf.N_Z
SC_LOG_SCALE = SC_D_PUB + kf.N_D
SC_WEIGHT = SC_LOG_SCALE + MAX_COUNT
SC_WEIGHT_OP = SC_WEIGHT + MAX_COUNT
SC_NIS = SC_WEIGHT_OP + MAX_COUNT  # this cycle's NIS and log det S of each hypothesis
SC_LD = SC_NIS + MAX_COUNT
SC_Y_ZERO = SC_LD + MAX_COUNT  # the measurements as a zero check's filter takes them (its steer less its zero error)
SCRATCH_SIZE = SC_Y_ZERO + kf.N_Y


def bank_params(count: int, dt: float, tuning, steer_count_rad: float) -> np.ndarray:
    """From the config's `estimator.tyre_bank` section (`TyreBankTuning`) and the encoder's count [rad]."""
    prm = np.zeros(PARAM_SIZE)
    prm[B_COUNT] = count
    prm[B_LEARN_FORGET] = math.exp(-dt / tuning.learning_memory)
    prm[B_IDLE_FORGET] = math.exp(-dt / tuning.idle_memory)
    prm[B_PRIOR_SD] = tuning.prior_sd
    prm[B_NIS_ALPHA] = 1.0 - math.exp(-dt / tuning.consistency_window)
    prm[B_FLOOR] = tuning.evidence_floor
    prm[B_NIS_FAST_ALPHA] = 1.0 - math.exp(-dt / tuning.fast_consistency_window)
    prm[B_EXCITATION_ALPHA] = 1.0 - math.exp(-dt / tuning.excitation_window)
    prm[B_MIN_AY] = tuning.min_excitation_lateral_accel
    prm[B_MIN_YAW_RATE] = tuning.min_excitation_yaw_rate
    prm[B_HALF_WIDTH] = tuning.running_half_width
    prm[B_MAX_EVIDENCE_NIS] = tuning.max_evidence_nis_fast
    prm[B_CHANGE_DRIFT] = tuning.change_drift
    prm[B_CHANGE_LEAK] = math.exp(-dt / tuning.change_memory)
    prm[B_JOIN_SETTLE] = round(tuning.join_settle_time / dt)
    prm[B_BALANCE_LOG_STEP] = math.log(tuning.balance_step)
    prm[B_BALANCE_PRIOR_SD] = tuning.balance_prior_sd
    prm[B_ZERO_STEP] = tuning.zero_step * steer_count_rad
    prm[B_MAP_HYSTERESIS] = tuning.map_hysteresis
    return prm


def new_state(count: int) -> np.ndarray:
    return np.zeros(state_size(count))


@njit(cache=True)
def set_prior(st: np.ndarray, prm: np.ndarray, scale: np.ndarray, centre: float, sd: float) -> None:
    """Start from tyres `centre` x nominal, with sd of log k `sd` (forgets all evidence, the balance's too)."""
    H = int(prm[B_COUNT])
    lc = math.log(centre)
    for h in range(H):
        g = (math.log(scale[h]) - lc) / sd
        st[_prior0(H) + h] = -0.5 * g * g
        st[_logl0(H) + h] = st[_prior0(H) + h]
        st[_logl_operating0(H) + h] = st[_prior0(H) + h]
        st[_logl_raw0(H) + h] = st[_prior0(H) + h]
        st[_nis0(H) + h] = kf.N_Y  # its expected value: no claim either way
        st[_nis_fast0(H) + h] = kf.N_Y
        st[_settle0(H) + h] = 0.0
    st[_scalars0(H) + SC_CENTRE] = lc
    st[_scalars0(H) + SC_INIT] = 1.0
    st[_scalars0(H) + SC_CHECK_H] = -1.0  # the checks start afresh beside the new most likely hypothesis
    st[_scalars0(H) + SC_CHECK_SETTLE] = 0.0
    for side in range(N_CHECKS):
        st[_scalars0(H) + SC_CHECK_LAMBDA + side] = 0.0
    best = 0
    for h in range(1, H):
        if abs(math.log(scale[h]) - lc) < abs(math.log(scale[best]) - lc):
            best = h
    st[_scalars0(H) + SC_MAP] = best
    st[_scalars0(H) + SC_LOW] = _window_low(H, best, int(prm[B_HALF_WIDTH]))


@njit(cache=True)
def _window_low(count: int, centre: int, half_width: int) -> int:
    """First hypothesis of the running window around `centre`: 2 half_width + 1 of them, shifted inside the bank
    at its ends (all of them when the bank is not wider)."""
    return max(0, min(centre - half_width, count - 1 - 2 * half_width))


@njit(cache=True)
def _enter_window(st: np.ndarray, count: int, h: int, source: int, settle: float) -> None:
    """Hypothesis h joins the running window next to `source` (the old window's end): it starts from that
    filter's state and evidence, so it is as likely as its neighbour until the data tell them apart. And for
    `settle` cycles it takes its neighbour's evidence, not its own: its filter starts from a state that is not
    its own, and the innovations of its convergence say nothing about its tyres. Taken as evidence, they ruled the
    right tyre out within 0.1 s of joining, 80-335 nats behind, as a road change moved the window (`mu_drop` x1.3,
    seed 37: VALID 24.7 % off for 2.8 s; docs/estimator.md, "A hypothesis that joins the window")."""
    st[_settle0(count) + h] = settle
    st[_source0(count) + h] = source
    for k in range(BLOCK):
        st[h * BLOCK + k] = st[source * BLOCK + k]
        st[_published0(count) + h * BLOCK + k] = st[_published0(count) + source * BLOCK + k]
    st[_logl0(count) + h] = st[_logl0(count) + source]
    st[_logl_operating0(count) + h] = st[_logl_operating0(count) + source]
    st[_logl_raw0(count) + h] = st[_logl_raw0(count) + source]
    st[_nis0(count) + h] = st[_nis0(count) + source]
    st[_nis_fast0(count) + h] = st[_nis_fast0(count) + source]


@njit(cache=True)
def prior_centre(st: np.ndarray, prm: np.ndarray) -> float:
    """The prior's centre (1 before any prior was set)."""
    H = int(prm[B_COUNT])
    if st[_scalars0(H) + SC_INIT] == 0.0:
        return 1.0
    return math.exp(st[_scalars0(H) + SC_CENTRE])


@njit(cache=True)
def restart_filters(st: np.ndarray, prm: np.ndarray) -> None:
    """Re-initialise every filter's dynamic states (evidence and publishing) at the next step; the evidence is
    kept."""
    H = int(prm[B_COUNT])
    for h in range(H):
        st[h * BLOCK + kf.INIT] = 0.0
        st[_published0(H) + h * BLOCK + kf.INIT] = 0.0
    for side in range(N_CHECKS):
        st[_checks0(H) + side * BLOCK + kf.INIT] = 0.0


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _change_statistic(
    st: np.ndarray, prm: np.ndarray, nis_now: np.ndarray, ld_now: np.ndarray, lo: int, hi: int
) -> float:
    """A CUSUM of this cycle's log-likelihood ratio of the better neighbour of the window's centre (the last most
    likely tyre) against the centre, less `B_CHANGE_DRIFT`, fading by `B_CHANGE_LEAK`: a sequential test of "the
    tyres the data show now are another hypothesis than the one published". Unlike the NIS, which measures how badly
    the centre fits, it asks whether a neighbour fits better, which a road that changes shows first: on `mu_drop`
    seed 8512 of random set 35 the short-window NIS stayed at 5.4-6.7 while the error grew from 20 to 66 %
    (docs/estimator.md, "A road that changes where nothing tests the tyres"). Healthy, the centre fits best and the
    ratio's mean is negative; a cycle without a measurement adds nothing."""
    H = int(prm[B_COUNT])
    sc = _scalars0(H)
    centre = int(st[sc + SC_MAP])
    gain = 0.0
    if lo <= centre <= hi and not math.isnan(nis_now[centre]):
        best = -math.inf
        for h in (centre - 1, centre + 1):
            # a neighbour still settling (`_enter_window`) is no evidence of a change either
            if lo <= h <= hi and not math.isnan(nis_now[h]) and not st[_settle0(H) + h] > 0.0:
                best = max(best, 0.5 * (nis_now[centre] + ld_now[centre] - nis_now[h] - ld_now[h]))
        if best > -math.inf:
            gain = best
    value = max(0.0, prm[B_CHANGE_LEAK] * st[sc + SC_CHANGE] + gain - prm[B_CHANGE_DRIFT])
    st[sc + SC_CHANGE] = value
    return value


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _evidence_source(st: np.ndarray, count: int, h: int, lo: int, hi: int) -> int:
    """Whose innovation is hypothesis h's evidence this cycle: its own, or while it settles (`_enter_window`) that
    of the settled neighbour it joined from (through a chain of joins, when the window moved on)."""
    a = h
    for _ in range(count):
        if not st[_settle0(count) + a] > 0.0:
            return a
        s = int(st[_source0(count) + a])
        if not lo <= s <= hi or s == a:
            return h  # the neighbour left the window: no one settled to borrow from
        a = s
    return h


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _evidence(logl: np.ndarray, prior: np.ndarray, h: int, forget: float, take: bool, nis: float, ld: float) -> None:
    """One cycle of hypothesis h's log-likelihood: forget towards the prior, and add this cycle's if `take`."""
    logl[h] = prior[h] + forget * (logl[h] - prior[h])
    if take:
        logl[h] -= 0.5 * (nis + ld)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _normalise(logl: np.ndarray, lo: int, hi: int, floor: float, weight: np.ndarray) -> None:
    """The posterior weights over the window, exp(logl - best) / their sum, into `weight`; every log-likelihood
    kept within `floor` of the best (a hypothesis can always come back: a road can change)."""
    best = logl[lo]
    for h in range(lo + 1, hi + 1):
        if logl[h] > best:
            best = logl[h]
    total = 0.0
    for h in range(lo, hi + 1):
        if not logl[h] >= best - floor:  # also a NaN
            logl[h] = best - floor
        weight[h] = math.exp(logl[h] - best)
        total += weight[h]
    for h in range(lo, hi + 1):
        weight[h] = weight[h] / total


@njit(cache=True)
def _sub_grid_peak(
    logl: np.ndarray, log_scale: np.ndarray, lo: int, hi: int, m: int, mean_log: float, var_log: float
) -> tuple[float, float]:
    """log k of the small-slip estimate and its variance: the posterior's mean `mean_log` and variance `var_log`,
    or where the posterior is narrower than the grid, the peak of the parabola through the log-posterior `logl`
    (the unclipped one: `_normalise`'s floor would make it symmetric) at the most likely hypothesis m and its two
    neighbours, and the variance its curvature gives (if smaller). Why the peak: as evidence accumulates the
    weights collapse onto the one hypothesis nearest the truth and the mean snaps to it: a road of mu 0.5 between
    the x0.43 and x0.50 hypotheses read as -13 %, flagged VALID. The parabola interpolates between them (a
    filter's expected NIS grows quadratically with its tyres' error). Why the curvature: a tyre half-way between
    two hypotheses splits the weights between them, and their variance is then the grid's half step however much
    evidence there is (sd of log k 0.05 against the 0.007 of a tyre on a hypothesis): noise seed 37's `slalom_30`
    x0.7, whose tyre sat between two, was never VALID."""
    if not lo < m < hi:
        return mean_log, var_log
    x0, x1, x2 = log_scale[m - 1], log_scale[m], log_scale[m + 1]
    l0, l1, l2 = logl[m - 1], logl[m], logl[m + 1]
    denom = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (l1 - l0) + x1 * (l0 - l2) + x0 * (l2 - l1)) / denom
    b = (x2 * x2 * (l0 - l1) + x1 * x1 * (l2 - l0) + x0 * x0 * (l1 - l2)) / denom
    if not a < 0.0:
        return mean_log, var_log
    if 1.0 / math.sqrt(-2.0 * a) >= 0.5 * (x2 - x0):  # broader than the grid: the mean represents it
        return mean_log, var_log
    peak = min(max(-b / (2.0 * a), 0.5 * (x0 + x1)), 0.5 * (x1 + x2))
    return peak, min(var_log, -0.5 / a)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _most_likely(logl: np.ndarray, lo: int, hi: int) -> int:
    best = lo
    for h in range(lo + 1, hi + 1):
        if logl[h] > logl[best]:
            best = h
    return best


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def bank_step(
    st: np.ndarray,
    out: np.ndarray,
    scratch: np.ndarray,
    prm: np.ndarray,
    y: np.ndarray,
    u: float,
    roll_init: float,
    observe: bool,
    track: bool,
    learn: bool,
    grid: np.ndarray,
    scale: np.ndarray,
    Phi: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    Gd: np.ndarray,
    nl: np.ndarray,
    Sinv: np.ndarray,
    logdet: np.ndarray,
    K_pub: np.ndarray,
    bal_Phi: np.ndarray,
    bal_K: np.ndarray,
    bal_Gd: np.ndarray,
    bal_Sinv: np.ndarray,
    bal_logdet: np.ndarray,
    zero_shift: float,
    zero_prior_sd: float,
) -> None:
    """One cycle: each filter's innovation, evidence, the two posteriors, then every running filter's step, mixed;
    the balance and steer zero checks' filters beside them (module doc; `zero_shift`, rad: the conditioning's zero
    error removed from the steer; `zero_prior_sd`, rad: how well it knows it).

    observe: this cycle's measurements are sound (the innovations are checked for consistency);
    track: and they may move the operating tyres the published states are mixed from (at any lean: a tyre
    near saturation is what the vehicle runs on);
    learn: and the small-slip stiffness too (linear range of the tyres, see the module doc)."""
    H = int(prm[B_COUNT])
    G = grid.shape[0]
    if st[_scalars0(H) + SC_INIT] == 0.0:
        set_prior(st, prm, scale, 1.0, prm[B_PRIOR_SD])
    i, w = grid_position(grid, u)
    e = scratch[SC_E : SC_E + kf.N_Y]
    zh = scratch[SC_ZH : SC_ZH + kf.N_Z]
    d = scratch[SC_D : SC_D + kf.N_D]
    zp = scratch[SC_ZH_PUB : SC_ZH_PUB + kf.N_Z]
    dp = scratch[SC_D_PUB : SC_D_PUB + kf.N_D]
    log_scale = scratch[SC_LOG_SCALE : SC_LOG_SCALE + H]
    weight = scratch[SC_WEIGHT : SC_WEIGHT + H]
    weight_op = scratch[SC_WEIGHT_OP : SC_WEIGHT_OP + H]
    nis_now = scratch[SC_NIS : SC_NIS + H]
    ld_now = scratch[SC_LD : SC_LD + H]
    logl = st[_logl0(H) : _logl0(H) + H]
    logl_op = st[_logl_operating0(H) : _logl_operating0(H) + H]
    logl_raw = st[_logl_raw0(H) : _logl_raw0(H) + H]
    nisw = st[_nis0(H) : _nis0(H) + H]
    nisf = st[_nis_fast0(H) : _nis_fast0(H) + H]
    prior = st[_prior0(H) : _prior0(H) + H]
    alpha = prm[B_NIS_ALPHA]

    # 0. the running window follows the small-slip posterior's most likely hypothesis (the operating tyres lie
    # within its reach: +-3 steps is x0.66 .. x1.52); the hypotheses that join it start from their neighbour
    sc = _scalars0(H)
    half = int(prm[B_HALF_WIDTH])
    old_lo = int(st[sc + SC_LOW])
    old_hi = min(H - 1, old_lo + 2 * half)
    lo = _window_low(H, int(st[sc + SC_MAP]), half)
    hi = min(H - 1, lo + 2 * half)
    for h in range(lo, hi + 1):
        if h < old_lo:
            _enter_window(st, H, h, old_lo, prm[B_JOIN_SETTLE])
        elif h > old_hi:
            _enter_window(st, H, h, old_hi, prm[B_JOIN_SETTLE])
    st[sc + SC_LOW] = lo

    # 1. evidence: the innovation of each filter's prediction (a filter that just (re)started has none).
    # Only an excited ride tells tyres apart: on a straight road every filter sees the same noise, and
    # the likelihood would only rank how well each one's noise model fits it (tests/test_tyre_bank.py).
    if observe and math.isfinite(y[1]) and math.isfinite(y[3]):
        a = prm[B_EXCITATION_ALPHA]
        st[sc + SC_MS_AY] += a * (y[3] * y[3] - st[sc + SC_MS_AY])
        st[sc + SC_MS_R] += a * (y[1] * y[1] - st[sc + SC_MS_R])
    excited = st[sc + SC_MS_AY] > prm[B_MIN_AY] ** 2 or st[sc + SC_MS_R] > prm[B_MIN_YAW_RATE] ** 2
    best_fit = math.inf  # the best-fitting filter's short-window NIS (with this cycle's)
    for h in range(lo, hi + 1):
        nis_now[h] = math.nan  # no measurement: not observed, the filter (re)starting, or its innovation not finite
        ld_now[h] = 0.0
        if not (observe and st[h * BLOCK + kf.INIT] != 0.0):
            continue
        j = h * G + i
        nis = _nis(st, h * BLOCK, y, 0.0, C, Sinv, j, w, e)
        if math.isfinite(nis):  # a non-finite one (a diverged filter) would stay in the windowed means for good
            nisw[h] += alpha * (nis - nisw[h])
            nisf[h] += prm[B_NIS_FAST_ALPHA] * (nis - nisf[h])
            best_fit = min(best_fit, nisf[h])
            nis_now[h] = nis
            ld_now[h] = (1.0 - w) * logdet[j, 0, 0] + w * logdet[j + 1, 0, 0]
    out[OUT_CHANGE] = _change_statistic(st, prm, nis_now, ld_now, lo, hi)
    # data that no tyre explains (an accelerometer reading what no force causes, a sensor fault the input
    # checks cannot see) are no evidence about the tyres: every filter's innovation is large, and their
    # differences would drag the estimate wherever the garbage points (tests/test_estimator.py)
    track = track and observe and excited and best_fit <= prm[B_MAX_EVIDENCE_NIS]
    learn = learn and track
    forget = prm[B_LEARN_FORGET] if learn else prm[B_IDLE_FORGET]
    forget_op = prm[B_LEARN_FORGET] if track else prm[B_IDLE_FORGET]
    for h in range(lo, hi + 1):
        a = _evidence_source(st, H, h, lo, hi)
        nis, ld = nis_now[a], ld_now[a]
        measured = not math.isnan(nis)
        _evidence(logl, prior, h, forget, measured and learn, nis, ld)
        _evidence(logl_op, prior, h, forget_op, measured and track, nis, ld)
        _evidence(logl_raw, prior, h, forget, measured and learn, nis, ld)
    for h in range(lo, hi + 1):
        if st[_settle0(H) + h] > 0.0:
            st[_settle0(H) + h] -= 1.0
    _recentre_zero(st, H, prm[B_ZERO_STEP], zero_shift)
    _check_evidence(
        st, out, prm, y, i, w, C, Sinv, bal_Sinv, bal_logdet, nis_now, ld_now, lo, hi, learn, forget, e, zero_prior_sd
    )

    # 2. the posteriors over the window: the small-slip one (published stiffness, its spread and consistency)
    # and the operating one (the weights of the published states)
    _normalise(logl, lo, hi, prm[B_FLOOR], weight)
    _normalise(logl_op, lo, hi, prm[B_FLOOR], weight_op)
    mean_log = 0.0
    mean_log_op = 0.0
    for h in range(lo, hi + 1):
        log_scale[h] = math.log(scale[h])
        mean_log += weight[h] * log_scale[h]
        mean_log_op += weight_op[h] * log_scale[h]
    var_log = 0.0
    for h in range(lo, hi + 1):
        dl = log_scale[h] - mean_log
        var_log += weight[h] * dl * dl
    map_h = _most_likely(logl, lo, hi)
    held = int(st[sc + SC_MAP])
    if lo <= held <= hi and not logl[map_h] > logl[held] + prm[B_MAP_HYSTERESIS]:
        map_h = held  # a lead within the hysteresis does not move the window and the peak read (settings)
    mean_log, var_log = _sub_grid_peak(logl_raw, log_scale, lo, hi, map_h, mean_log, var_log)

    # 3. every running filter's step; the published states are the operating posterior's mixture of the
    # publishing filters'
    for k in range(kf.N_Z):
        out[OUT_Z + k] = 0.0
    out[OUT_EVIDENCE_ROLL] = 0.0
    out[OUT_EVIDENCE_TORQUE] = 0.0
    p0 = _published0(H)
    for h in range(lo, hi + 1):
        # filter h's state block and its tables' rows around u (hypothesis h's grid starts at row h G)
        kf.kalman_pair_step_at(
            st, h * BLOCK, p0 + h * BLOCK, zh, zp, y, u, roll_init, h * G + i, w, Phi, K, K_pub, C, Gd, nl, d, dp
        )
        out[OUT_EVIDENCE_ROLL] += weight_op[h] * zh[kf.PHI]
        out[OUT_EVIDENCE_TORQUE] += weight_op[h] * zh[kf.TAU]
        for k in range(kf.N_Z):
            out[OUT_Z + k] += weight_op[h] * zp[k]
    out[OUT_SCALE] = math.exp(mean_log)
    out[OUT_LOG_SD] = math.sqrt(var_log)
    out[OUT_MAP_WEIGHT] = weight[map_h]
    out[OUT_MAP_NIS] = nisw[map_h]
    out[OUT_MAP_SCALE] = scale[map_h]
    out[OUT_MAP_NIS_FAST] = nisf[map_h]
    out[OUT_LEARNING] = 1.0 if learn else 0.0
    out[OUT_OPERATING_SCALE] = math.exp(mean_log_op)
    st[sc + SC_MAP] = map_h
    y_zero = scratch[SC_Y_ZERO : SC_Y_ZERO + kf.N_Y]
    _checks_step(
        st, prm, y, y_zero, u, roll_init, i, w, G, Phi, K, bal_Phi, bal_K, C, Gd, bal_Gd, nl, zh, d, map_h, mean_log,
        scale,
    )  # fmt: skip


@njit(cache=True)
def _nis(
    st: np.ndarray,
    z0: int,
    y: np.ndarray,
    steer_error: float,
    C: np.ndarray,
    Sinv: np.ndarray,
    j: int,
    w: float,
    e: np.ndarray,
) -> float:
    """e' S^-1 e of the filter whose state starts at z0 (indexed, not sliced: a view costs atomic reference
    counting, kf.kalman_pair_step_at), its innovation e = y - C z with the steer less `steer_error`, S^-1
    interpolated between rows j and j + 1 by w."""
    for r in range(kf.N_Y):
        acc = y[r]
        for c in range(kf.N_Z):
            acc -= C[r, c] * st[z0 + c]
        e[r] = acc
    e[0] -= steer_error
    nis = 0.0
    for r in range(kf.N_Y):
        for c in range(kf.N_Y):
            nis += e[r] * ((1.0 - w) * Sinv[j, r, c] + w * Sinv[j + 1, r, c]) * e[c]
    return nis


@njit(cache=True)
def _check_evidence(
    st: np.ndarray,
    out: np.ndarray,
    prm: np.ndarray,
    y: np.ndarray,
    i: int,
    w: float,
    C: np.ndarray,
    Sinv: np.ndarray,
    bal_Sinv: np.ndarray,
    bal_logdet: np.ndarray,
    nis_now: np.ndarray,
    ld_now: np.ndarray,
    lo: int,
    hi: int,
    learn: bool,
    forget: float,
    e: np.ndarray,
    zero_prior_sd: float,
) -> None:
    """This cycle of the balance and steer zero checks (module doc): each side's Lambda forgets like the bank's
    evidence and, while learning, adds by how much that side's filter explains this cycle better than the window's
    filter at the same hypothesis (only if both measured it, neither is settling, and both innovations are finite);
    then the balance and the zero error the evidence points to, and their spreads (`check_posterior`), into `out`."""
    H = int(prm[B_COUNT])
    G = bal_Sinv.shape[0] // (N_BALANCE * H)
    sc = _scalars0(H)
    hb = int(st[sc + SC_CHECK_H])
    take = (
        learn
        and lo <= hb <= hi
        and st[sc + SC_CHECK_SETTLE] <= 0.0
        and not math.isnan(nis_now[hb])
        and not st[_settle0(H) + hb] > 0.0
    )
    largest = -math.inf
    for side in range(N_CHECKS):
        gain = 0.0
        z0 = _checks0(H) + side * BLOCK
        if take and st[z0 + kf.INIT] != 0.0:
            steer_error = CHECK_ZERO[side] * prm[B_ZERO_STEP]
            tables = CHECK_TABLES[side]
            if tables < 0:  # the window's filter's tables
                nis = _nis(st, z0, y, steer_error, C, Sinv, hb * G + i, w, e)
                ld = ld_now[hb]
            else:  # a balance filter's: the front's stiffnesses differ
                j = (tables * H + hb) * G + i
                nis = _nis(st, z0, y, steer_error, C, bal_Sinv, j, w, e)
                ld = (1.0 - w) * bal_logdet[j, 0, 0] + w * bal_logdet[j + 1, 0, 0]
            if math.isfinite(nis):
                gain = 0.5 * (nis_now[hb] + ld_now[hb] - nis - ld)
        value = forget * st[sc + SC_CHECK_LAMBDA + side] + gain
        st[sc + SC_CHECK_LAMBDA + side] = value
        if side < N_BALANCE:
            largest = max(largest, value)
    if st[sc + SC_CHECK_SETTLE] > 0.0:
        st[sc + SC_CHECK_SETTLE] -= 1.0
    out[OUT_BALANCE] = largest
    lam = sc + SC_CHECK_LAMBDA
    balance, balance_sd, zero, zero_sd = check_posterior(
        st[lam], st[lam + 1], st[lam + 2], st[lam + 3], st[lam + 4], prm[B_BALANCE_LOG_STEP], prm[B_ZERO_STEP],
        prm[B_BALANCE_PRIOR_SD], zero_prior_sd,
    )  # fmt: skip
    out[OUT_BALANCE_LOG], out[OUT_BALANCE_LOG_SD] = balance, balance_sd
    out[OUT_ZERO_ERROR], out[OUT_ZERO_ERROR_SD] = zero, zero_sd


@njit(cache=True)
def _recentre_zero(st: np.ndarray, count: int, step: float, zero_shift: float) -> None:
    """The conditioning moved its zero (straight riding, or the checks' own evidence) by s zero steps: what a check's
    filter at zero error z was about, the one at z - s is now. Its quadratic (`_check_quadratic`, without the
    priors) keeps its curvatures and its gradients move by minus them times s; the Lambdas are that quadratic at
    the checks' points again (nats against the new centre), faded by exp(-|s| / RECENTRE_STEPS): the likelihood is a
    quadratic near its centre only (a zero a count off read as a front x1.23 and x1.26 either way), and evidence
    carried over a count without fading claimed the balance within 0.04 while it moved from 1.04 to 1.17 (random
    set 9001)."""
    sc = _scalars0(count)
    s = (zero_shift - st[sc + SC_ZERO_SHIFT]) / step
    st[sc + SC_ZERO_SHIFT] = zero_shift
    if s == 0.0 or not math.isfinite(s):
        return
    lam = sc + SC_CHECK_LAMBDA
    l0, l1, l2, l3, l4 = st[lam], st[lam + 1], st[lam + 2], st[lam + 3], st[lam + 4]
    _, _, _, czz, cbz = _check_quadratic(l0, l1, l2, l3, l4)
    keep = math.exp(-abs(s) / RECENTRE_STEPS)
    st[lam] = keep * (l0 + cbz * s)
    st[lam + 1] = keep * (l1 - cbz * s)
    st[lam + 2] = keep * (l2 + czz * s)
    st[lam + 3] = keep * (l3 - czz * s)
    st[lam + 4] = keep * (l4 - (cbz + czz) * s)


@njit(cache=True)
def _check_quadratic(
    b_lower: float, b_upper: float, z_lower: float, z_upper: float, cross: float
) -> tuple[float, float, float, float, float]:
    """(gb, gz, cbb, czz, cbz), per step: the quadratic gb b + gz z - (cbb b^2 + 2 cbz b z + czz z^2) / 2 through the
    checks' Lambdas at (-+1, 0), (0, -+1) and (1, 1) steps, 0 at (0, 0) (module doc, CHECK_TABLES)."""
    gb, gz = 0.5 * (b_upper - b_lower), 0.5 * (z_upper - z_lower)
    cbb, czz = -(b_lower + b_upper), -(z_lower + z_upper)
    return gb, gz, cbb, czz, gb + gz - 0.5 * cbb - 0.5 * czz - cross


@njit(cache=True)
def check_posterior(
    b_lower: float,
    b_upper: float,
    z_lower: float,
    z_upper: float,
    cross: float,
    b_step: float,
    z_step: float,
    b_prior_sd: float,
    z_prior_sd: float,
) -> tuple[float, float, float, float]:
    """(balance, its sd, zero error, its sd): the peak of the joint log-likelihood in the front's log factor b and
    the steer zero's error z, a quadratic through the checks' Lambdas (nats against the filter at (0, 0)): at
    (-+b_step, 0) `b_lower`, `b_upper`, at (0, -+z_step) `z_lower`, `z_upper`, and at (b_step, z_step) `cross`
    (which gives their correlation: a zero a count off reads as a front tyre), plus Gaussian priors around 0. Each
    sd is the marginal's: what the other may be widens it. Not a peak (a saddle, a NaN): infinite sds."""
    gb, gz, cbb, czz, cbz = _check_quadratic(b_lower, b_upper, z_lower, z_upper, cross)  # per step: to units
    gb, gz = gb / b_step, gz / z_step
    cbb, czz, cbz = cbb / (b_step * b_step), czz / (z_step * z_step), cbz / (b_step * z_step)
    cbb += 1.0 / max(b_prior_sd * b_prior_sd, 1e-300)  # a prior of no spread (a stage alone on zeros): no ZeroDivision
    czz += 1.0 / max(z_prior_sd * z_prior_sd, 1e-300)
    det = cbb * czz - cbz * cbz
    if not (cbb > 0.0 and det > 0.0):  # also a NaN
        return 0.0, math.inf, 0.0, math.inf
    b = (czz * gb - cbz * gz) / det
    z = (cbb * gz - cbz * gb) / det
    return b, math.sqrt(czz / det), z, math.sqrt(cbb / det)


@njit(cache=True)
def _checks_step(
    st: np.ndarray,
    prm: np.ndarray,
    y: np.ndarray,
    y_zero: np.ndarray,
    u: float,
    roll_init: float,
    i: int,
    w: float,
    G: int,
    Phi: np.ndarray,
    K: np.ndarray,
    bal_Phi: np.ndarray,
    bal_K: np.ndarray,
    C: np.ndarray,
    Gd: np.ndarray,
    bal_Gd: np.ndarray,
    nl: np.ndarray,
    z: np.ndarray,
    d: np.ndarray,
    map_h: int,
    mean_log: float,
    scale: np.ndarray,
) -> None:
    """The balance and zero checks' filters' step at their hypothesis (the zero check's on `y_zero`, its steer less
    the side's zero error); then, if the estimate has moved `CHECK_MOVE_STEPS` of a step from it (or they have
    not started), they move to the most likely hypothesis: from the window's evidence filter there (its state for
    the next cycle), taking no evidence while they settle."""
    H = int(prm[B_COUNT])
    sc = _scalars0(H)
    hb = int(st[sc + SC_CHECK_H])
    if hb >= 0:
        for side in range(N_CHECKS):
            for r in range(kf.N_Y):
                y_zero[r] = y[r]
            y_zero[0] -= CHECK_ZERO[side] * prm[B_ZERO_STEP]
            z0 = _checks0(H) + side * BLOCK
            tables = CHECK_TABLES[side]
            if tables < 0:
                kf.kalman_step_at(st, z0, z, y_zero, u, roll_init, hb * G + i, w, Phi, K, C, Gd, nl, d)
            else:
                row = (tables * H + hb) * G + i
                kf.kalman_step_at(st, z0, z, y_zero, u, roll_init, row, w, bal_Phi, bal_K, C, bal_Gd, nl, d)
    step = math.log(scale[1] / scale[0])  # the hypotheses are log-spaced
    if hb < 0 or (hb != map_h and not abs(mean_log - math.log(scale[hb])) <= CHECK_MOVE_STEPS * step):
        for side in range(N_CHECKS):
            for k in range(BLOCK):
                st[_checks0(H) + side * BLOCK + k] = st[map_h * BLOCK + k]
        st[sc + SC_CHECK_H] = map_h
        st[sc + SC_CHECK_SETTLE] = prm[B_JOIN_SETTLE]
