"""The tyre bank alone (ptw_rt.core.tyre_bank, design ptw_rt.design.tyre_bank) on the linear model.

A reduced bank (5 hypotheses, 3 grid speeds) keeps the design to a second; the runtime code is the same.
The plant is the linear Sharp model itself (exact ZOH) with its tyres scaled by a known factor and a rider
torque that excites it; the measurements are the fusion filter's y = [steer, yaw rate, roll rate, a_y,
roll] with white noise of the design's size.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from ptw_rt.core import kalman as ck
from ptw_rt.core import tyre_bank as tb
from ptw_rt.design import kalman as dk
from ptw_rt.design import tyre_bank as dtb
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.settings import load_settings

DT = 0.01
U = 20.0
COUNT_RAD = 2.0 * math.pi / 1024  # the encoder's count
ZERO_PRIOR_SD = COUNT_RAD  # the steer zero check's prior: a count


@pytest.fixture(scope="module")
def bank():
    s = load_settings(DEFAULT_CONFIG)
    tuning = replace(s.estimator.tyre_bank, min_scale=0.55, max_scale=1.75, step=1.3)
    grid = np.array([15.0, 20.0, 25.0])
    tables = dtb.design_bank(s.vehicle, grid, DT, s.estimator.kalman, tuning)
    return s, tuning, grid, tables


def _ride(
    s,
    k_true: float,
    seconds: float,
    excite: bool,
    seed: int = 0,
    k_after: float | None = None,
    at: float = 0.0,
    front: float = 1.0,
):
    """y per cycle from the linear model whose tyres are k_true x nominal (no nonlinear terms), its front tyre's times
    `front` besides; `k_after`: the tyres from `at` s on (a road that changes)."""
    p = s.vehicle.scaled(stiffness=k_true, front_stiffness=front)
    Phi, _, _ = dk.design_point(p, U, DT, s.estimator.kalman)
    Phi_after = (
        Phi if k_after is None else dk.design_point(s.vehicle.scaled(stiffness=k_after), U, DT, s.estimator.kalman)[0]
    )
    C = dk.output_matrix(p)
    rng = np.random.default_rng(seed)
    tun = s.estimator.kalman
    noise = np.array([tun.steer_noise, tun.yaw_rate_noise, tun.roll_rate_noise, tun.lateral_accel_noise, 0.002])
    n = int(seconds / DT)
    x = np.zeros(ck.N_Z)
    Y = np.zeros((n, ck.N_Y))
    for k in range(n):
        t = k * DT
        x[ck.TAU] = (9.0 * math.sin(1.3 * t) + 6.0 * math.sin(3.1 * t + 1.0)) if excite else 0.0
        Y[k] = C @ x + noise * rng.standard_normal(ck.N_Y)
        x = (Phi if t < at or k_after is None else Phi_after) @ x
    return Y


def _balance_tables(t) -> tuple:
    """The balance check's tables, in `bank_step`'s order."""
    return t["tb_bal_Phi"], t["tb_bal_K"], t["tb_bal_Gd"], t["tb_bal_Sinv"], t["tb_bal_logdet"]


def _run(
    bank,
    Y,
    start: float = 1.0,
    half_width: int | None = None,
    learn: bool = True,
    published=None,
    tuning=None,
    on_cycle=None,
):
    """The bank over Y: (scale, log sd, NIS) per cycle, the last outputs, the published states per cycle;
    `published`: the publishing filters' gain table (default: the design's); `tuning`: instead of the bank's;
    `on_cycle(k, state)`: called after each cycle's step with the bank's state."""
    s, bank_tuning, grid, t = bank
    tuning = bank_tuning if tuning is None else tuning
    gain_pub = published if published is not None else t["tb_K_pub"]
    if half_width is not None:
        tuning = replace(tuning, running_half_width=half_width)
    H = len(t["tb_scale"])
    prm = tb.bank_params(H, DT, tuning, COUNT_RAD)
    st = tb.new_state(H)
    tb.set_prior(st, prm, t["tb_scale"], start, tuning.prior_sd)
    out = np.zeros(tb.OUT_SIZE)
    scratch = np.zeros(tb.SCRATCH_SIZE)
    C = dk.output_matrix(s.vehicle)
    no_correction = np.zeros(7)  # the plant is linear: no nonlinear correction
    trace = np.zeros((len(Y), 7))
    states = np.zeros((len(Y), ck.N_Z))
    for k, y in enumerate(Y):
        tb.bank_step(
            st, out, scratch, prm, y, U, y[4], True, True, learn, grid, t["tb_scale"], t["tb_Phi"], t["tb_K"], C,
            t["tb_Gd"], no_correction, t["tb_Sinv"], t["tb_logdet"], gain_pub, *_balance_tables(t), 0.0, ZERO_PRIOR_SD,
        )  # fmt: skip
        trace[k, :4] = out[tb.OUT_SCALE], out[tb.OUT_LOG_SD], out[tb.OUT_MAP_NIS], out[tb.OUT_CHANGE]
        trace[k, 4:] = out[tb.OUT_BALANCE], out[tb.OUT_BALANCE_LOG], out[tb.OUT_BALANCE_LOG_SD]
        states[k] = out[tb.OUT_Z : tb.OUT_Z + ck.N_Z]
        if on_cycle is not None:
            on_cycle(k, st)
    return trace, out, states


@pytest.mark.parametrize("k_true", [0.769, 1.0, 1.3])
def test_finds_the_tyres_of_an_excited_ride(bank, k_true):
    trace, out, _ = _run(bank, _ride(bank[0], k_true, 30.0, excite=True))
    assert out[tb.OUT_MAP_SCALE] == pytest.approx(k_true, rel=0.01)
    assert out[tb.OUT_SCALE] == pytest.approx(k_true, rel=0.05)
    assert out[tb.OUT_LOG_SD] < 0.05  # concentrated
    assert out[tb.OUT_MAP_NIS] < 2.0 * ck.N_Y  # and the chosen filter explains the data


def test_converges_from_a_wrong_start(bank):
    trace, _, _ = _run(bank, _ride(bank[0], 1.0, 30.0, excite=True, seed=3), start=1.3)
    outside = np.flatnonzero(np.abs(trace[:, 0] / 1.0 - 1.0) > 0.10)
    settled_from = (outside[-1] + 1) * DT if outside.size else 0.0  # within 10 % from here to the end
    assert settled_from <= 10.0


def test_claims_nothing_without_excitation(bank):
    """A straight road (no torque, no steering): the data cannot tell tyres apart; the spread stays wide."""
    trace, out, _ = _run(bank, _ride(bank[0], 0.769, 30.0, excite=False))
    assert out[tb.OUT_LOG_SD] > 0.15
    assert np.all(trace[:, 1] > 0.15)


def test_a_road_that_changes_is_seen_by_the_change_statistic_before_the_estimate_moves(bank):
    """The tyres x1.0 for 20 s, then x0.769 (one hypothesis down) with nothing learned (a lean beyond the learning
    range): the estimate cannot move, and the change statistic passes `valid_max_change` within 1 s of the change;
    on the ride whose tyres stay, it stays below it after the first 5 s."""
    s, tuning = bank[0], bank[1]
    limit = tuning.valid_max_change
    steady, _, _ = _run(bank, _ride(s, 1.0, 40.0, excite=True, seed=5))
    assert steady[int(5.0 / DT) :, 3].max() < limit
    changed, _, _ = _run(bank, _ride(s, 1.0, 25.0, excite=True, seed=5, k_after=0.769, at=20.0), learn=False)
    assert changed[int(5.0 / DT) : int(20.0 / DT), 3].max() < limit
    assert changed[int(20.0 / DT) : int(21.0 / DT), 3].max() > limit


def test_mixture_is_a_filter_estimate(bank):
    """The published states (the posterior mixture) equal the true hypothesis' filter once it wins."""
    s = bank[0]
    Y = _ride(s, 1.0, 20.0, excite=True, seed=5)
    _, out, _ = _run(bank, Y)
    assert np.all(np.isfinite(out))
    assert abs(out[tb.OUT_Z + ck.PHI] - Y[-1, 4]) < 0.01


def test_running_window_walks_to_far_tyres(bank):
    """Three of the five filters run (the most likely and one on each side): from a start two hypotheses away
    the window follows the evidence to the true tyres, and the hypotheses that join it start from their
    neighbour's state (nothing non-finite, the estimate settles as the full bank's does)."""
    Y = _ride(bank[0], 1.3, 40.0, excite=True, seed=7)
    trace, out, _ = _run(bank, Y, start=0.7, half_width=1)
    full, out_full, _ = _run(bank, Y, start=0.7)
    assert np.all(np.isfinite(trace))
    assert out[tb.OUT_MAP_SCALE] == pytest.approx(1.3, rel=0.1)
    assert out[tb.OUT_SCALE] == pytest.approx(out_full[tb.OUT_SCALE], rel=0.02)
    assert out[tb.OUT_LOG_SD] < 0.05


@pytest.mark.parametrize("lead_share, moves", [(0.4, False), (2.0, True)])
def test_the_most_likely_tyre_changes_only_for_a_lead_beyond_the_hysteresis(bank, lead_share, moves):
    """A neighbour of the most likely hypothesis that leads it by less than `map_hysteresis` nats does not take its
    place (the window's centre and the hypothesis the published peak is read at): near the evidence floor a tyre
    the ride had ruled out took the lead for a cycle on one phase of a weave, and the published scale jumped 15 %
    for it (`mu_drop` mu 0.85, noise seed 419). A lead beyond it does."""
    _, tuning, _, t = bank
    H = len(t["tb_scale"])
    Y = _ride(bank[0], 1.0, 12.0, excite=True, seed=3)
    lead = lead_share * tuning.map_hysteresis
    held = []

    def lift_the_neighbour(k, st):
        if k == len(Y) - 2:
            sc = tb._scalars0(H)
            m = int(st[sc + tb.SC_MAP])
            held.append(m)
            st[tb._logl0(H) + m + 1] = st[tb._logl0(H) + m] + lead

    _, out, _ = _run(bank, Y, on_cycle=lift_the_neighbour)
    m = held[0]
    assert t["tb_scale"][m] == pytest.approx(1.0)
    assert out[tb.OUT_MAP_SCALE] == pytest.approx(t["tb_scale"][m + 1] if moves else t["tb_scale"][m])


@pytest.mark.parametrize("centre, expected", [(0, 0), (1, 0), (6, 3), (10, 7), (13, 7)])
def test_running_window_stays_inside_the_bank(centre, expected):
    assert tb._window_low(14, centre, 3) == expected
    assert tb._window_low(5, centre % 5, 3) == 0  # a bank no wider than the window runs whole


def test_operating_tyres_follow_where_the_small_slip_stiffness_may_not_learn(bank):
    """Beyond the linear range (learn off, track on: a deep corner) the published states run on the tyres the
    data say the vehicle has now (the operating posterior), while the published small-slip stiffness keeps
    what it learned (here: its prior, nominal)."""
    trace, out, _ = _run(bank, _ride(bank[0], 0.769, 30.0, excite=True), learn=False)
    assert out[tb.OUT_OPERATING_SCALE] == pytest.approx(0.769, rel=0.05)
    assert out[tb.OUT_SCALE] == pytest.approx(1.0, rel=0.02)
    assert out[tb.OUT_LOG_SD] > 0.15  # and claims nothing
    assert out[tb.OUT_LEARNING] == 0.0


def test_sub_grid_peak_interpolates_a_narrow_posterior():
    """A log-posterior quadratic in log k peaking between hypotheses: the parabola through the most likely one
    and its neighbours finds the peak, and its curvature the spread (the weights' spread is the grid's half step
    there); a broad one, or one at the window's edge, keeps the posterior's mean and variance."""
    log_scale = np.log(1.15 ** np.arange(-4, 5))
    peak, sd = math.log(1.15**0.5), 0.02
    logl = -0.5 * ((log_scale - peak) / sd) ** 2
    m = int(np.argmax(logl))
    grid_half_step_var = (0.5 * math.log(1.15)) ** 2
    got_peak, got_var = tb._sub_grid_peak(logl, log_scale, 0, 8, m, 99.0, grid_half_step_var)
    assert got_peak == pytest.approx(peak, abs=1e-12)
    assert math.sqrt(got_var) == pytest.approx(sd, rel=1e-9)
    # never wider than the weights say
    assert tb._sub_grid_peak(logl, log_scale, 0, 8, m, 99.0, 1e-8)[1] == 1e-8
    broad = -0.5 * ((log_scale - peak) / 0.5) ** 2
    assert tb._sub_grid_peak(broad, log_scale, 0, 8, int(np.argmax(broad)), 99.0, 7.0) == (99.0, 7.0)
    assert tb._sub_grid_peak(logl, log_scale, m, 8, m, 99.0, 7.0) == (99.0, 7.0)  # no lower neighbour in the window
    flat = np.zeros(9)
    assert tb._sub_grid_peak(flat, log_scale, 0, 8, 4, 99.0, 7.0) == (99.0, 7.0)  # not concave


def test_tyres_between_hypotheses_are_not_snapped_to_one(bank):
    """x1.14 lies between the x1.0 and x1.3 hypotheses of the test bank: the estimate lands between them, not on
    the nearest (a collapsed posterior's mean would read 1.0 or 1.3, 12-14 % off)."""
    trace, out, _ = _run(bank, _ride(bank[0], 1.14, 40.0, excite=True, seed=5))
    assert out[tb.OUT_LOG_SD] < 0.05
    assert out[tb.OUT_SCALE] == pytest.approx(1.14, rel=0.06)
    assert not math.isclose(out[tb.OUT_SCALE], out[tb.OUT_MAP_SCALE], rel_tol=0.02)


def test_a_nan_measurement_poisons_nothing_for_good(bank):
    """A non-finite cycle (a diverged filter; the lateral stage restarts the filters, as here) is no
    measurement: the windowed NIS means, the excitation and the unclipped log-posterior behind the sub-grid
    peak keep no NaN, and the estimate is back between the hypotheses, consistent, afterwards."""
    s, tuning, grid, t = bank
    Y = _ride(s, 1.14, 40.0, excite=True, seed=5)
    Y[1500] = np.nan
    H = len(t["tb_scale"])
    prm = tb.bank_params(H, DT, tuning, COUNT_RAD)
    st = tb.new_state(H)
    tb.set_prior(st, prm, t["tb_scale"], 1.0, tuning.prior_sd)
    out = np.zeros(tb.OUT_SIZE)
    scratch = np.zeros(tb.SCRATCH_SIZE)
    C = dk.output_matrix(s.vehicle)
    for y in Y:
        tb.bank_step(
            st, out, scratch, prm, y, U, y[4], True, True, True, grid, t["tb_scale"], t["tb_Phi"], t["tb_K"], C,
            t["tb_Gd"], np.zeros(7), t["tb_Sinv"], t["tb_logdet"], t["tb_K_pub"], *_balance_tables(t), 0.0,
            ZERO_PRIOR_SD,
        )  # fmt: skip
        if not np.isfinite(out[tb.OUT_Z : tb.OUT_Z + ck.N_Z]).all():
            tb.restart_filters(st, prm)  # what the lateral stage does
    assert np.isfinite(st).all()
    assert np.isfinite(out).all()
    assert out[tb.OUT_SCALE] == pytest.approx(1.14, rel=0.06)
    assert out[tb.OUT_MAP_NIS] < 2.0 * ck.N_Y


def test_the_published_states_come_from_the_publishing_filters_and_the_evidence_does_not(bank):
    """The published states are the mixture of the publishing filters (tyre forces freer of the tyre model);
    what the bank learns comes from the evidence filters alone, so the publishing design cannot move it."""
    s, tuning, grid, t = bank
    Y = _ride(s, 1.3, 20.0, excite=True, seed=5)
    own = t["tb_K"]
    freer = t["tb_K_pub"]
    assert s.estimator.kalman.published_force_noise != (1.0, 1.0)  # the file's publishing filters are freer
    trace_own, _, z_own = _run(bank, Y, published=own)
    trace_freer, _, z_freer = _run(bank, Y, published=freer)
    np.testing.assert_array_equal(trace_own, trace_freer)  # the same evidence, the same tyres learned
    rear = z_freer[:, ck.FYR] - z_own[:, ck.FYR]
    assert np.abs(rear).max() > 1.0  # N: the published rear force is another filter's
    # on the linear model both filters are right: the freer one's rear force stays within its noise
    assert np.sqrt(np.mean(rear[500:] ** 2)) < 50.0
    # and their rider torque walks faster (`published_torque_noise`; the lag it shortens on a simulated ride:
    # `test_the_publishing_filters_faster_torque_follows_a_busy_rider_better`)
    assert s.estimator.kalman.published_torque_noise > 1.0
    assert np.abs(z_freer[:, ck.TAU] - z_own[:, ck.TAU]).max() > 0.05  # N m


@pytest.mark.slow
@pytest.mark.parametrize("seed", [None, 3])
def test_the_published_torque_near_the_grip_limit_is_within_15_percent_of_the_peak(seed):
    """`mu_drop` on a road of 0.85 x its friction (0.43 after the drop; up to 93 % of a tyre's grip): the
    linear tyres of the evidence filters no longer hold there, and a published torque mixed from them was
    16.4 % (own seed) and 16.2 % (seed 3) of the peak off; the publishing filters' forces follow the measured
    a_y and yaw (issue #12's target: 15 %)."""
    from ptw_rt.core import layout as L  # noqa: N812
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.sim.ride import parse_perturbations, simulate

    ev = evaluate_ride(simulate("mu_drop", seed=seed, perturbation=parse_perturbations(["mu_scale=0.85"])))
    m = ev.mask
    err = ev.estimates[m, L.E_RIDER_TORQUE] - ev.truth["rider_torque"][m]
    peak = np.max(np.abs(ev.truth["rider_torque"][m]))
    assert 100.0 * np.sqrt(np.mean(err**2)) / peak <= 15.0


@pytest.mark.slow
@pytest.mark.parametrize(
    ("seed", "perturbation"),
    [
        (None, "stiffness=1.3"),
        (None, "stiffness=1.0"),
        (None, "stiffness=0.7"),
        (None, "mu_scale=0.85"),
        (5, "stiffness=0.7"),
        (419, "stiffness=1.3"),
        (1001, "mu_scale=0.85"),
        (419, "mu_scale=0.85"),
    ],
)
def test_a_changed_road_is_followed_within_10_s(seed, perturbation):
    """`mu_drop`: the road's friction falls from 0.9 to 0.5 at 20 s, and the small-slip stiffness with it.
    Learning waits for the tyres' linear range, and these riders stay beyond it for most of the seconds after
    the drop, so the new road's evidence comes in short bursts. With the old road's hypotheses held up to 50
    nats ahead (the floor before `evidence_floor`), the ×1.3 ride followed after 13.96 s (issue #12: within 10 s).
    The ×0.7 and μ 0.85 rides (and ×0.7 on noise seed 5) read the wet road 9-14 % soft before the slope correction
    (the data measure the tyres' slope at 25-35 % of the grip; `lateral._slope_ratio`) and never came within 10 %;
    now 5.8, 9.0 and 3.3 s. Seed 419 ×1.3 and seed 1001 μ 0.85 rode above the learning range's end of 0.15 rad for
    3-7 s after the drop and followed after 18.4 and 11.4 s; with the end at 0.175 rad (the slope correction takes
    the tyres' working point into account) 1.3 and 6.1 s. Seed 419 μ 0.85 was within 10 % from 23.9 s but
    for its last 0.07 s, where a tyre the ride had ruled out led for a cycle (`map_hysteresis`). The +50 kg ride is
    the next test's."""
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.eval.matrix import MU_DROP_AT, learning_times
    from ptw_rt.sim.ride import parse_perturbations, simulate

    ev = evaluate_ride(simulate("mu_drop", seed=seed, perturbation=parse_perturbations(perturbation.split())))
    for name, times in learning_times(ev, MU_DROP_AT).items():
        assert times["time_s"] is not None and times["time_s"] <= 10.0, name


@pytest.mark.slow
@pytest.mark.parametrize(
    ("seed", "perturbation"),
    [(None, "stiffness=0.7"), (7, "added_mass=50"), (37, "stiffness=1.3"), (3, "mu_scale=0.85")],
)
def test_after_a_changed_road_the_stiffness_moves_to_it_and_is_never_valid_while_off(seed, perturbation):
    """`mu_drop` where the new road's evidence comes only from leans near the learning range's end (25-35 % of the
    new road's grip): there the data show the tyres' slope where they work, 9-16 % below the small-slip one
    (docs/estimator.md, "A hypothesis that joins the window"; the published scale corrects most of it since
    "The tyres' slope at their working point"). The estimate moves to the new road within 10 s (to
    within 25 %: the +50 kg ride adds the payload the sensors cannot see), and no frame is VALID more than 15 % off.
    Seed 37 x1.3 was VALID 24.7 % off for 2.8 s while the hypotheses that joined the window were ruled out by
    their own filters' convergence."""
    from ptw_rt.core import layout as lay
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.eval.matrix import MU_DROP_AT
    from ptw_rt.sim.ride import parse_perturbations, simulate

    ev = evaluate_ride(simulate("mu_drop", seed=seed, perturbation=parse_perturbations([perturbation])))
    err = ev.estimates[:, lay.E_C_ALPHA_FRONT] / ev.truth["c_alpha_front"] - 1.0
    valid = (ev.estimates[:, lay.E_VALID].astype(int) & lay.V_CORNERING) != 0
    assert np.all(np.abs(err[valid & ev.mask]) <= 0.15)
    after = ev.t >= MU_DROP_AT + 10.0
    assert np.all(np.abs(err[after]) <= 0.25)


def test_a_hypothesis_that_joins_the_window_takes_its_neighbours_evidence_while_it_settles(bank):
    """Three filters run (half width 1); the tyres fall from x1.0 to x0.59 (two hypotheses down) at 20 s, so the
    window walks and hypotheses join it from their neighbour's state. For `join_settle_time` each joiner's
    evidence moves with its neighbour's, whatever its own filter's convergence says, and the bank still finds the
    new tyres."""
    s, tuning, grid, t = bank
    tuning = replace(tuning, running_half_width=1, join_settle_time=0.3)
    Y = _ride(s, 1.0, 26.0, excite=True, seed=11, k_after=1.0 / 1.3**2, at=20.0)
    H = len(t["tb_scale"])
    settle = int(tb.bank_params(H, DT, tuning, COUNT_RAD)[tb.B_JOIN_SETTLE])
    assert settle == 30
    raw = slice(tb._logl_raw0(H), tb._logl_raw0(H) + H)
    low = tb._scalars0(H) + tb.SC_LOW
    window_low = [H]  # the window's first hypothesis before the cycle (none before the first)
    joined = []  # (cycle, joiner, source)
    gaps = {}  # (cycle, joiner) -> its log-likelihood less its source's, per cycle after joining

    def watch(k, st):
        lo = int(st[low])
        if lo < window_low[0] and k > 20.0 / DT:
            joined.append((k, lo, int(st[tb._source0(H) + lo])))
        window_low[0] = lo
        for k0, h, src in joined:
            gaps.setdefault((k0, h), []).append(st[raw][h] - st[raw][src])

    _, out, _ = _run(bank, Y, tuning=tuning, on_cycle=watch)
    assert joined, "the window never walked"
    for gap in gaps.values():
        # moved with its neighbour while settling (but for the fading towards their different priors, 1e-3 nats a
        # cycle): its own convergence from the neighbour's state put the true tyres 80-335 nats behind in 0.1 s
        assert np.ptp(gap[:settle]) < 0.1
    assert out[tb.OUT_MAP_SCALE] == pytest.approx(1.0 / 1.3**2, rel=0.01)


@pytest.mark.slow
def test_the_publishing_filters_faster_torque_follows_a_busy_rider_better(tmp_path):
    """`fusion_filter.published_torque_noise` (x1.5): most of the published torque's error is lag (the encoder's
    counts must be averaged over cycles), and a faster random walk in the publishing filters alone shortens it.
    A rider twice as busy as the scenario's on `slalom_30`: 2.88 N m at x1 (the evidence filters' walk), 2.71 at
    x1.5. The roll does not depend on it."""
    from ptw_rt.cli import main
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.sim.ride import parse_perturbations, simulate

    text = DEFAULT_CONFIG.read_text()
    line = next(x for x in text.splitlines() if x.strip().startswith("published_torque_noise:"))
    assert float(line.split(":")[1]) > 1.0
    as_evidence = tmp_path / "as_evidence.yaml"
    as_evidence.write_text(text.replace(line, line.split(":")[0] + ": 1.0"))
    assert main(["design", "--config", str(as_evidence)]) == 0
    ride = simulate("slalom_30", perturbation=parse_perturbations(["rider_noise=2"]))
    runs = [evaluate_ride(ride, config) for config in (DEFAULT_CONFIG, as_evidence)]
    torque = [ev.result["metrics"]["torque_rmse_nm"] for ev in runs]
    assert torque[0] < 0.97 * torque[1]
    assert runs[0].result["metrics"]["roll_rmse_deg"] == runs[1].result["metrics"]["roll_rmse_deg"]


@pytest.mark.parametrize("k_true", [0.769, 1.0, 1.3])
def test_the_balance_is_learned_as_the_files_when_both_axles_differ_alike(bank, k_true):
    """Tyres that differ from the file's by one factor on both axles: the file's balance explains the learning best,
    and the balance learned is 1 within a few percent, its spread narrow enough for VALID."""
    s, tuning = bank[0], bank[1]
    trace, _, _ = _run(bank, _ride(s, k_true, 40.0, excite=True, seed=7))
    assert abs(trace[-1, 5]) < 0.03
    assert trace[-1, 6] <= tuning.valid_balance_log_sd
    assert trace[-1, 4] < 0.0  # both balance filters fit worse than the file's


@pytest.mark.parametrize("front", [0.9, 1.1])
def test_a_front_tyre_within_the_balance_filters_is_learned(bank, front):
    """The front x0.9 (or x1.1) and the rear as the file says: the one scale follows the rear, and the balance
    learned says the front, within 3 %, its spread narrow enough for VALID."""
    s, tuning = bank[0], bank[1]
    trace, _, _ = _run(bank, _ride(s, 1.0, 30.0, excite=True, seed=8, front=front))
    assert trace[-1, 0] == pytest.approx(1.0, rel=0.05)
    assert math.exp(trace[-1, 5]) == pytest.approx(front, rel=0.03)
    assert trace[-1, 6] <= tuning.valid_balance_log_sd


@pytest.mark.parametrize("front", [0.8, 1.25])
def test_a_front_tyre_beyond_the_balance_filters_is_said(bank, front):
    """The front x0.8 (or x1.25): beyond the balance filters (x1/1.15, x1.15), where the parabola would extrapolate;
    within 10 s of excited riding the balance learned lies beyond them (the supervisor then withholds VALID)."""
    s, tuning = bank[0], bank[1]
    trace, _, _ = _run(bank, _ride(s, 1.0, 20.0, excite=True, seed=8, front=front))
    beyond = np.flatnonzero(np.abs(trace[:, 5]) >= math.log(tuning.balance_step))
    assert beyond.size and beyond[0] * DT < 10.0
    assert np.sign(trace[-1, 5]) == np.sign(math.log(front))
    assert abs(trace[-1, 5]) >= math.log(tuning.balance_step)


def test_the_balance_takes_no_evidence_without_learning(bank):
    """Not learning (a lean beyond the linear range, inputs not sound): no evidence either way, the prior's spread."""
    s, tuning = bank[0], bank[1]
    trace, _, _ = _run(bank, _ride(s, 1.0, 10.0, excite=True, seed=8, front=0.8), learn=False)
    assert np.all(trace[:, 4] == 0.0)
    assert np.all(trace[:, 5] == 0.0)
    assert np.allclose(trace[:, 6], tuning.balance_prior_sd)


B_STEP, Z_STEP = math.log(1.15), 0.25 * COUNT_RAD  # the checks' steps: the front's log factor, the steer zero


def _quadratic(b0, z0, sb, sz, rho):
    """A joint log-likelihood in (b, z) peaking at (b0, z0) with marginal sds sb, sz and correlation rho, and the
    checks' Lambdas of it (nats against (0, 0)) in CHECK_TABLES' order."""
    cov = np.array([[sb * sb, rho * sb * sz], [rho * sb * sz, sz * sz]])
    info = np.linalg.inv(cov)

    def ll(b, z):
        d = np.array([b - b0, z - z0])
        return -0.5 * d @ info @ d

    points = [(-B_STEP, 0.0), (B_STEP, 0.0), (0.0, -Z_STEP), (0.0, Z_STEP), (B_STEP, Z_STEP)]
    assert [(x / B_STEP, y / Z_STEP) for x, y in points] == [
        (-1.0 if t == 0 else (1.0 if t == 1 else 0.0), z) for t, z in zip(tb.CHECK_TABLES, tb.CHECK_ZERO, strict=True)
    ]
    return [ll(b, z) - ll(0.0, 0.0) for b, z in points]


@pytest.mark.parametrize("rho", [0.0, 0.9, -0.6])
def test_the_checks_posterior_is_the_joint_peak_and_the_marginal_spreads(rho):
    """The five Lambdas of a quadratic give back its peak and its marginal sds (flat priors), whatever the
    correlation: a zero error that reads as a front tyre widens the balance's spread instead of moving its peak. A
    saddle (both balances better than the centre) is no peak: infinite sds; with no evidence the priors are all."""
    b0, z0, sb, sz = 0.12, -0.6 * Z_STEP, 0.03, 0.2 * Z_STEP
    lam = _quadratic(b0, z0, sb, sz, rho)
    b, b_sd, z, z_sd = tb.check_posterior(*lam, B_STEP, Z_STEP, 1e6, 1e6)
    assert (b, b_sd, z, z_sd) == pytest.approx((b0, sb, z0, sz), rel=1e-6)
    assert tb.check_posterior(5.0, 5.0, 0.0, 0.0, 0.0, B_STEP, Z_STEP, 1e6, 1e6)[1] == math.inf
    assert tb.check_posterior(0.0, 0.0, 0.0, 0.0, 0.0, B_STEP, Z_STEP, 0.1, COUNT_RAD) == pytest.approx(
        (0.0, 0.1, 0.0, COUNT_RAD)
    )


def test_moving_the_zero_recentres_the_checks_evidence_and_fades_it():
    """The conditioning moves its zero by a third of a zero step: the checks' quadratic keeps its peak's balance, its
    zero error is a third of a step less, and the evidence fades by exp(-1/3 / RECENTRE_STEPS) (spreads grow by its
    square root)."""
    H = 14
    st = tb.new_state(H)
    sc = tb._scalars0(H)
    b0, z0, sb, sz = 0.05, 0.4 * Z_STEP, 0.03, 0.2 * Z_STEP
    st[sc + tb.SC_CHECK_LAMBDA : sc + tb.SC_CHECK_LAMBDA + tb.N_CHECKS] = _quadratic(b0, z0, sb, sz, 0.7)
    tb._recentre_zero(st, H, Z_STEP, Z_STEP / 3.0)
    assert st[sc + tb.SC_ZERO_SHIFT] == Z_STEP / 3.0
    lam = st[sc + tb.SC_CHECK_LAMBDA : sc + tb.SC_CHECK_LAMBDA + tb.N_CHECKS]
    b, b_sd, z, z_sd = tb.check_posterior(*lam, B_STEP, Z_STEP, 1e6, 1e6)
    fade = math.exp(-1.0 / 3.0 / tb.RECENTRE_STEPS)
    assert (b, z) == pytest.approx((b0, z0 - Z_STEP / 3.0), rel=1e-6)
    assert (b_sd, z_sd) == pytest.approx((sb / math.sqrt(fade), sz / math.sqrt(fade)), rel=1e-6)
    before = st.copy()
    tb._recentre_zero(st, H, Z_STEP, Z_STEP / 3.0)  # the zero did not move: nothing changes
    assert np.array_equal(st, before)
