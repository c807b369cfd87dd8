"""`ptw-rt evaluate`: simulate a scenario, run the estimator over it exactly as replay does, score it against truth.

The ride's frames are encoded with the DBC and driven through the shared cycle (`drive_log`), so the
figures are those of the daemon's code path. Errors are measured after `SETTLE_S` and only where the
true speed is inside the model's validity (the estimator says "not valid" below it, by design).

Baselines (never published, evaluation only):
- kinematic roll atan(u r / g) from the same conditioned speed and yaw rate;
- a complementary filter of the gyro's roll rate and the kinematic roll, with the same time
  constant as our fusion (so the comparison isolates what the UIHOSMO adds);
- seed 001's direct method and dynamic inversion for the stiffness (ptw_rt.eval.stiffness_baselines);
- seeds 002/003's first-order SMO and super-twisting observer of the tyre forces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptw_rt.core import force_observers as fo
from ptw_rt.core import layout as L  # noqa: N812 - the Estimates index table, used on every line
from ptw_rt.edge.cycle import drive_log, shared_runner
from ptw_rt.errors import UserFacingError
from ptw_rt.output import emit
from ptw_rt.parallel import map_in_processes
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.sim.recording import encode_frames
from ptw_rt.sim.ride import Ride, get_scenario, parse_perturbations, simulate
from ptw_rt.sim.scenarios import SCENARIOS

SETTLE_S = 5.0  # s: observers start, converge (2 s) and the fusion filter forgets its start (2 s)
# s before the simulated rider's crash (|roll| > 69 deg) where scoring stops: the fall from a deep lean takes
# 0.2-0.5 s, and a falling vehicle is not a ride the estimator is meant for (its figures and alarms there would
# be about the fall; other seeds' matrices have such rides)
CRASH_MARGIN_S = 1.0
TRANSIENT_SCENARIOS = ("dlc_50", "dlc_100", "slalom_30")
# the monitors a sensor fault the input checks cannot see should raise (issue #16), by their reason bits
MONITORS = (
    ("plausibility", L.REASON_IMPLAUSIBLE),
    ("attitude_consistency", L.REASON_ATTITUDE_INCONSISTENT),
    ("gyro_step", L.REASON_GYRO_STEP),
)


def before_crash(t: np.ndarray, ride: Ride) -> np.ndarray:
    """The cycles that are still a ride: all of them, or those CRASH_MARGIN_S before the simulated rider's crash."""
    if ride.crashed_at is None:
        return np.ones(t.shape, bool)
    return t < ride.crashed_at - CRASH_MARGIN_S


def monitor_alarms(t: np.ndarray, reasons: np.ndarray, ride: Ride) -> dict:
    """Each monitor's alarms on the ride: cycles raised, and, where the perturbation injects a fault (yaw-gyro
    scale, a gyro bias step, steer-encoder step: `Perturbation.injects_fault`), the time from the fault to its first
    alarm (None: none before the ride ends). On a healthy ride every alarm is a false one; a ride the simulated
    rider crashes counts until CRASH_MARGIN_S before the crash."""
    p = ride.perturbation
    injected = p.injects_fault
    bits = reasons.astype(np.int64)
    riding = before_crash(t, ride)
    out: dict = {"fault_at_s": p.fault_at if injected else None}
    for name, bit in MONITORS:
        raised = ((bits & bit) != 0) & riding
        entry: dict = {"cycles": int(np.count_nonzero(raised))}
        if injected:
            hit = np.flatnonzero(raised & (t >= p.fault_at))
            entry["detected_after_s"] = round(float(t[hit[0]] - p.fault_at), 2) if hit.size else None
        out[name] = entry
    return out


def plausibility_by_band(speed: np.ndarray, residual: np.ndarray, ratio: np.ndarray, band_start_kmh) -> dict:
    """The plausibility monitor on one ride: its largest ratio and its largest windowed torque residual in each
    speed band of `estimator.plausibility` (None where the ride never ran in the band). On healthy rides these
    are what the thresholds are learned from (`ptw_rt.eval.matrix.plausibility_calibration`)."""
    kmh = speed * 3.6
    starts = [float(b) for b in band_start_kmh]
    bands = []
    for i, lo in enumerate(starts):
        hi = starts[i + 1] if i + 1 < len(starts) else math.inf
        r = residual[(kmh >= lo) & (kmh < hi) & np.isfinite(residual)]
        bands.append(_round(float(r.max())) if r.size else None)
    finite = ratio[np.isfinite(ratio)]
    return {
        "band_start_kmh": starts,
        "largest_ratio": _round(float(finite.max())) if finite.size else None,
        "largest_residual_nm": bands,
    }


def alarms_text(alarms: dict) -> str:
    """One line: the first alarm of each monitor after an injected fault, or the alarm count of a healthy ride."""
    if alarms["fault_at_s"] is None:
        return "monitor alarms (a healthy ride: false ones): " + ", ".join(
            f"{name} {alarms[name]['cycles']} cycles" for name, _ in MONITORS
        )
    parts = []
    for name, _ in MONITORS:
        after = alarms[name]["detected_after_s"]
        parts.append(f"{name} " + (f"{after:g} s" if after is not None else "none before the ride ends"))
    return f"fault injected at {alarms['fault_at_s']:g} s; first alarm after: " + ", ".join(parts)


STIFFNESS_KEYS = (
    ("front_cornering", L.E_C_ALPHA_FRONT, "c_alpha_front"),
    ("front_camber", L.E_C_GAMMA_FRONT, "c_gamma_front"),
    ("rear_cornering", L.E_C_ALPHA_REAR, "c_alpha_rear"),
    ("rear_camber", L.E_C_GAMMA_REAR, "c_gamma_rear"),
)


@dataclass
class Evaluation:
    """Everything `report` plots: the ride, the estimates per cycle and the baselines' series."""

    ride: Ride
    t: np.ndarray  # cycle times, ride time [s]
    estimates: np.ndarray  # (N, ESTIMATES_SIZE)
    truth: dict[str, np.ndarray]  # truth interpolated at the cycle times
    mask: np.ndarray  # samples scored
    baselines: dict[str, np.ndarray]
    result: dict
    samples: np.ndarray | None = None  # (N, SAMPLE_SIZE): the Sample each cycle's step received
    roll_tolerance_deg: float | None = None  # what EST_Roll_Valid promises (the config's, as the step ran on it)


def _rms(e: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(e**2))) if e.size else None


def _complementary(rate: np.ndarray, reference: np.ndarray, dt: float, time_constant: float) -> np.ndarray:
    out = np.empty_like(rate)
    pull = 1.0 - math.exp(-dt / time_constant)
    x = reference[0]
    for k in range(rate.shape[0]):
        x += dt * rate[k]
        x += pull * (reference[k] - x)
        out[k] = x
    return out


def _pct(est: float, true: float) -> float | None:
    if est is None or not math.isfinite(est) or true == 0:
        return None
    return round(100.0 * (est - true) / true, 2)


def evaluate_ride(
    ride: Ride,
    config: Path = DEFAULT_CONFIG,
    design_file: Path | None = None,
    initial_stiffness_scale: tuple[float, float] | None = None,
    initial_sensor_biases: tuple[float, ...] | None = None,
) -> Evaluation:
    """Score one ride. `initial_stiffness_scale` = (front, rear): the estimator starts from the nominal
    tyres times these factors (a wrong start), if it offers `set_initial_stiffness_scale(front, rear)`;
    `result["initial_stiffness_scale"]` then says whether it was applied. `initial_sensor_biases` = (b_p, b_q, b_r
    [rad/s], b_ay[, b_ax, b_az] [m/s^2]): the estimator starts from them as the daemon does from its state file."""
    runner = shared_runner(config, design_file)  # a matrix's or a random set's worker loads the files once
    if initial_sensor_biases is not None:
        runner.estimator.restore_sensor_biases(initial_sensor_biases[:4], initial_sensor_biases[4:] or None)
    settings = runner.settings
    applied = None
    if initial_stiffness_scale is not None:
        setter = getattr(runner.estimator, "set_initial_stiffness_scale", None)
        applied = setter is not None
        if setter is not None:
            setter(*initial_stiffness_scale)
    frames = list(encode_frames(ride, runner.codec))
    times: list[float] = []
    rows: list[np.ndarray] = []
    samples: list[np.ndarray] = []

    def keep(now: float, est: np.ndarray) -> None:
        times.append(now)
        rows.append(est.copy())
        samples.append(runner.sample.copy())  # what this cycle's step received (the peer's input)

    drive_log(frames, runner, keep, start=ride.epoch)
    t = np.asarray(times) - ride.epoch
    E = np.vstack(rows)
    truth = {k: np.interp(t, ride.truth["t"], v) for k, v in ride.truth.items() if k != "t"}
    min_speed = settings.estimator.min_valid_speed_kmh / 3.6
    mask = (t >= SETTLE_S) & (truth["speed"] >= min_speed) & before_crash(t, ride)
    dt = runner.sample_time
    g = settings.vehicle.g

    # baselines on the same conditioned signals
    kin = np.arctan(E[:, L.E_SPEED] * E[:, L.E_YAW_RATE] / g)
    comp = _complementary(E[:, L.E_ROLL_RATE_MEASURED], kin, dt, settings.estimator.roll_fusion_time_constant)
    geom = fo.lateral_yaw_constants(settings.vehicle)
    u, r, a_y = E[:, L.E_SPEED], E[:, L.E_YAW_RATE], E[:, L.E_LAT_ACCEL]
    smo = fo.run_smo(u, r, a_y, dt, geom)
    sta = fo.run_sta(u, r, a_y, dt, geom)
    S = np.vstack(samples)
    peer = _ahrs_peer(S, dt, settings.sensors)
    baselines = {
        "ahrs_peer_roll": peer,
        "kinematic_roll": kin,
        "complementary_roll": comp,
        "smo_fy_front": smo[0],
        "smo_fy_rear": smo[1],
        "sta_fy_front": sta[0],
        "sta_fy_rear": sta[1],
    }

    m = mask
    deg = math.degrees
    roll_err = E[m, L.E_ROLL] - truth["roll"][m]
    torque_peak = float(np.max(np.abs(truth["rider_torque"][m]))) if m.any() else None
    metrics = {
        "roll_rmse_deg": _round(deg(_rms(roll_err))) if m.any() else None,
        "roll_max_err_deg": _round(deg(float(np.max(np.abs(roll_err))))) if m.any() else None,
        "torque_rmse_nm": _round(_rms(E[m, L.E_RIDER_TORQUE] - truth["rider_torque"][m])),
        "torque_peak_nm": _round(torque_peak),
        "steer_rate_rmse": _round(_rms(E[m, L.E_STEER_RATE] - truth["steer_rate"][m]), 4),
        "vy_rmse": _round(_rms(E[m, L.E_LAT_VEL] - truth["lat_vel"][m]), 4),
        "fy_front_rmse_n": _round(_rms(E[m, L.E_FY_FRONT] - truth["fy_front"][m])),
        "fy_rear_rmse_n": _round(_rms(E[m, L.E_FY_REAR] - truth["fy_rear"][m])),
        "roll_rmse_pct": _round(100.0 * _rms(roll_err) / _rms(truth["roll"][m]), 2) if m.any() else None,
        "roll_uihosmo_rmse_deg": _round(deg(_rms(E[m, L.E_ROLL_UIHOSMO] - truth["roll"][m]))) if m.any() else None,
        "roll_uio_sensors_rmse_deg": (
            _round(deg(_rms(E[m, L.E_ROLL_UIO_SENSORS] - truth["roll"][m]))) if m.any() else None
        ),
        "stiffness_err_pct": {},
        # None for a ride shorter than the settling time (`demo --duration 2`: numpy's "Mean of empty slice")
        "valid_share": _round(float(np.mean(E[t >= SETTLE_S, L.E_MODE] == L.MODE_VALID)), 3)
        if (t >= SETTLE_S).any()
        else None,
    }
    if torque_peak:
        metrics["torque_rmse_pct_of_peak"] = _round(100.0 * metrics["torque_rmse_nm"] / torque_peak, 1)
    second_half = m & (t >= t[-1] / 2)
    for key, col, tcol in STIFFNESS_KEYS:
        if second_half.any():
            metrics["stiffness_err_pct"][key] = _pct(
                float(np.mean(E[second_half, col])), float(np.mean(truth[tcol][second_half]))
            )
        else:
            metrics["stiffness_err_pct"][key] = None

    base = {
        "ahrs_peer_roll_rmse_deg": (
            _round(deg(_rms(peer[m] - truth["roll"][m]))) if m.any() and peer is not None else None
        ),
        "kinematic_roll_rmse_deg": _round(deg(_rms(kin[m] - truth["roll"][m]))) if m.any() else None,
        "complementary_roll_rmse_deg": _round(deg(_rms(comp[m] - truth["roll"][m]))) if m.any() else None,
        "smo_fy_rmse_n": {
            "front": _round(_rms(smo[0][m] - truth["fy_front"][m])),
            "rear": _round(_rms(smo[1][m] - truth["fy_rear"][m])),
        },
        "sta_fy_rmse_n": {
            "front": _round(_rms(sta[0][m] - truth["fy_front"][m])),
            "rear": _round(_rms(sta[1][m] - truth["fy_rear"][m])),
        },
    }
    base.update(_stiffness_baselines(settings.vehicle, dt, E, truth, second_half))
    result = {
        "scenario": ride.scenario,
        "seed": ride.seed,
        "perturbation": ride.perturbation.as_dict(),
        "metrics": metrics,
        "baselines": base,
        "settle_s": SETTLE_S,
        "duration_s": ride.duration,
        "crashed_at": ride.crashed_at,
        "alarms": monitor_alarms(t, E[:, L.E_REASONS], ride),
        "plausibility": plausibility_by_band(
            E[:, L.E_SPEED],
            E[:, L.E_TORQUE_RESIDUAL],
            E[:, L.E_PLAUSIBILITY],
            settings.estimator.plausibility.band_start_kmh,
        ),
    }
    if initial_stiffness_scale is not None:
        result["initial_stiffness_scale"] = {"front_rear": list(initial_stiffness_scale), "applied": applied}
    return Evaluation(ride, t, E, truth, mask, baselines, result, S, settings.estimator.roll_tolerance_deg)


def _ahrs_peer(samples: np.ndarray, dt: float, sensors: dict) -> np.ndarray | None:
    """Roll of the Fusion AHRS peer per cycle (None without the eval extra)."""
    from ptw_rt.eval import ahrs_peer

    if not ahrs_peer.available():
        return None
    out = ahrs_peer.run_peer(samples, dt, sensors.imu_height, sensors.imu_forward, sensors.gps_latency)
    return out["roll"]


def _stiffness_baselines(vehicle, dt, E, truth, use) -> dict:
    try:
        from ptw_rt.eval import stiffness_baselines as sb
    except ImportError:  # pragma: no cover - module ships with the package
        return {}
    true4 = [float(np.mean(truth[c][use])) if use.any() else float("nan") for _, _, c in STIFFNESS_ORDER]
    y = np.column_stack([E[:, L.E_STEER], E[:, L.E_YAW_RATE], E[:, L.E_ROLL_RATE_MEASURED], E[:, L.E_STEER_RATE]])
    x_hat = np.column_stack(
        [
            E[:, L.E_ROLL],
            E[:, L.E_STEER],
            E[:, L.E_LAT_VEL],
            E[:, L.E_YAW_RATE],
            E[:, L.E_ROLL_RATE_MEASURED],
            E[:, L.E_STEER_RATE],
            E[:, L.E_FY_FRONT],
            E[:, L.E_FY_REAR],
        ]
    )
    u = E[:, L.E_SPEED]
    out = {}
    with np.errstate(all="ignore"):
        direct = sb.direct_method(
            vehicle,
            dt,
            u,
            E[:, L.E_STEER],
            E[:, L.E_LAT_VEL],
            E[:, L.E_YAW_RATE],
            E[:, L.E_ROLL],
            E[:, L.E_STEER_RATE],
            E[:, L.E_LAT_ACCEL],
            use,
        )
        inversion = sb.dynamic_inversion(vehicle, dt, u, y, x_hat, E[:, L.E_RIDER_TORQUE], use)
    out["direct_stiffness_err_pct"] = sb.stiffness_error_pct(direct, true4)
    out["inversion_stiffness_err_pct"] = sb.stiffness_error_pct(inversion, true4)
    return out


# order of seed 001's Theta: C_af, C_gf, C_ar, C_gr
STIFFNESS_ORDER = (STIFFNESS_KEYS[0], STIFFNESS_KEYS[1], STIFFNESS_KEYS[2], STIFFNESS_KEYS[3])


def _round(v, nd: int = 3):
    if v is None or not math.isfinite(v):
        return None
    return round(float(v), nd)


def evaluate_scenario(
    scenario: str,
    seed: int | None = None,
    perturb: list[str] | None = None,
    config: Path = DEFAULT_CONFIG,
    design_file: Path | None = None,
    restored_biases: bool = False,
) -> Evaluation:
    """Simulate and score one ride; `restored_biases`: the estimator starts from the ride's own IMU biases, as the
    daemon does from a state file (`ride_biases`)."""
    ride = simulate(scenario, seed=seed, vehicle=config, perturbation=parse_perturbations(perturb or []))
    biases = ride_biases(ride) if restored_biases else None
    return evaluate_ride(ride, config, design_file, initial_sensor_biases=biases)


def ride_biases(ride: Ride) -> tuple[float, float, float, float, float, float]:
    """(b_p, b_q, b_r [rad/s], b_ay, b_ax, b_az [m/s^2]): the simulated IMU's own biases, what a state file written
    by an earlier ride on this IMU keeps (`Estimator.learned_sensor_biases`, `learned_accel_biases`)."""
    gyro, accel = ride.sensor_meta["gyro_bias"], ride.sensor_meta["accel_bias"]
    return (float(gyro[0]), float(gyro[1]), float(gyro[2]), float(accel[1]), float(accel[0]), float(accel[2]))


def _targets(result: dict) -> dict:
    """Which of the issue's targets this scenario meets (None: not applicable)."""
    m, b = result["metrics"], result["baselines"]
    out = {}
    known = [v for v in (b.get("kinematic_roll_rmse_deg"), b.get("complementary_roll_rmse_deg")) if v is not None]
    if m["roll_rmse_deg"] is not None and known:  # nothing scored (never valid, or ridden below the validity speed)
        best = min(known)
        factor = 0.5 if result["scenario"] in TRANSIENT_SCENARIOS else 1.0
        out["roll_beats_baselines"] = m["roll_rmse_deg"] <= factor * best
    if result["scenario"] == "dlc_100":
        out["roll_rmse_le_1deg"] = m["roll_rmse_deg"] is not None and m["roll_rmse_deg"] <= 1.0
        out["torque_rmse_le_15pct_peak"] = (m.get("torque_rmse_pct_of_peak") or 1e9) <= 15.0
    return out


def _table(results: list[dict]) -> str:
    head = (
        f"{'scenario':<16}{'roll':>7}{'peer':>7}{'uioS':>7}{'uio':>7}{'kin':>7}{'comp':>7}{'tau':>8}{'tau%':>7}"
        f"{'vy':>7}{'Fyf':>7}{'Fyr':>7}{'Caf%':>8}{'Car%':>8}{'Cgf%':>8}{'Cgr%':>8}  targets"
    )
    lines = [head, "-" * len(head)]

    def f(v, w=7, nd=2):
        return f"{'-':>{w}}" if v is None else f"{v:>{w}.{nd}f}"

    for r in results:
        m, b, s = r["metrics"], r["baselines"], r["metrics"]["stiffness_err_pct"]
        met = r.get("targets", {})
        tgt = " ".join(f"{k}={'ok' if v else 'MISS'}" for k, v in met.items())
        lines.append(
            f"{r['scenario']:<16}{f(m['roll_rmse_deg'])}{f(b.get('ahrs_peer_roll_rmse_deg'))}"
            f"{f(m.get('roll_uio_sensors_rmse_deg'))}{f(m['roll_uihosmo_rmse_deg'])}"
            f"{f(b['kinematic_roll_rmse_deg'])}{f(b['complementary_roll_rmse_deg'])}"
            f"{f(m['torque_rmse_nm'], 8)}{f(m.get('torque_rmse_pct_of_peak'), 7, 0)}{f(m['vy_rmse'])}"
            f"{f(m['fy_front_rmse_n'], 7, 0)}{f(m['fy_rear_rmse_n'], 7, 0)}"
            f"{f(s['front_cornering'], 8, 1)}{f(s['rear_cornering'], 8, 1)}{f(s['front_camber'], 8, 1)}"
            f"{f(s['rear_camber'], 8, 1)}  {tgt}"
        )
    lines.append(
        "roll/peer/uioS/uio/kin/comp: roll RMSE [deg] (ours, Fusion AHRS peer, the UIHOSMO on the sensors' own"
    )
    lines.append("roll, seed 000's case 2 alone, kinematic, complementary); tau [N m];")
    lines.append("vy [m/s]; Fy [N]; C%: stiffness error of the second-half mean [%]")
    for r in results:  # the monitors' alarms where there is something to say (a table of healthy rides stays short)
        a = r.get("alarms")
        if a and (len(results) == 1 or a["fault_at_s"] is not None or any(a[n]["cycles"] for n, _ in MONITORS)):
            lines.append(f"{r['scenario']}: {alarms_text(a)}")
    return "\n".join(lines)


def _one(job: tuple) -> dict:
    scenario, seed, perturb, config, design_file, restored_biases = job
    result = evaluate_scenario(scenario, seed, perturb, config, design_file, restored_biases).result
    result["targets"] = _targets(result)
    return result


ROBUSTNESS = (
    ("+20 % mass and inertia", ["mass_inertia=1.2"]),
    ("stiffness x 0.5", ["stiffness=0.5"]),
    ("stiffness x 1.5", ["stiffness=1.5"]),
    ("IMU noise x 2", ["imu_noise=2"]),
)

PAPER_NOTES = """\
### The papers' figures beside ours

| quantity | paper | ours (nominal table above) |
|---|---|---|
| roll RMSE % (seed 001 Tab. II, BikeSim 40-120 km/h) | 6.2 % | `handling_40_120`: {handling_roll_pct} % |
| roll RMSE %, mass -16.5 % / stiffness x0.5 (Tab. II) | 7.9 % / 7.1 % | robustness tables |
| stiffness mean vs nominal (seed 001 Tab. I) | within 1-10 % | `handling_40_120`: {handling_stiff} |
| roll, rider torque (seed 000 figs. 8-12) | plots only, exact sensors, 100 km/h | `ptw-rt report` |

Seed 000 gives no numbers (figures of a noise-free simulation at one speed); seed 001 defines RMSE % without the
normalisation its name implies (its eq. 39); ours is 100 RMSE / RMS(truth).
"""


def _markdown(nominal: list[dict], robustness: list[tuple[str, list[dict]]]) -> str:
    out = [
        "# Estimator results",
        "",
        "Regenerate with `ptw-rt evaluate --all --markdown > docs/results.md` (simulated rides, standard sensor",
        f"noise, errors after {SETTLE_S:g} s and above the model's validity speed). Columns as in `ptw-rt evaluate`.",
        "",
        "## Nominal plant",
        "",
        "```",
        _table(nominal),
        "```",
    ]
    for title, results in robustness:
        diverged = [r["scenario"] for r in results if r["crashed_at"] is not None]
        out += ["", f"## Robustness: {title}", "", "```", _table(results), "```"]
        out.append(f"Rides that crashed in the simulator: {', '.join(diverged) or 'none'}.")
    h = next((r for r in nominal if r["scenario"] == "handling_40_120"), None)
    stiff = h["metrics"]["stiffness_err_pct"] if h else {}
    out += [
        "",
        PAPER_NOTES.format(
            handling_roll_pct=h["metrics"]["roll_rmse_pct"] if h else "-",
            handling_stiff=", ".join(f"{k} {v} %" for k, v in stiff.items()),
        ),
    ]
    return "\n".join(out)


def _run_all(jobs: list[tuple], workers: int | None = None) -> list[dict]:
    """The rides of ``jobs`` on ``--jobs`` processes (default: every usable core), in job order."""
    return map_in_processes(_one, jobs, workers, None, lambda job: job[0])


def run_evaluate(args) -> int:
    for option, one_ride in (
        ("routes", "one route alone: --scenario route_N"),
        ("hills", "one hilly ride: --perturb road_slope_swing=DEG, road_slope_length=M"),
    ):
        if getattr(args, option, False) and getattr(args, "random", None) is None:
            raise UserFacingError(f"--{option} goes with --random N ({one_ride})")
    if getattr(args, "random", None) is not None:  # first: it refuses the options it would ignore, --matrix too
        from ptw_rt.eval.random_rides import run_random_command

        return run_random_command(args)
    if getattr(args, "seeds", None) is not None and not getattr(args, "matrix", False):
        raise UserFacingError("--seeds goes with --matrix (one ride or table on one noise seed: --seed S)")
    if getattr(args, "restored_biases", False) and getattr(args, "matrix", False):
        raise UserFacingError(
            "--restored-biases does not go with --matrix: issue #12's matrix starts from no persisted state"
        )
    if getattr(args, "matrix", False):
        # the matrix is every scenario on its own variants: a scenario, --all or --perturb asked for something else,
        # and the matrix ran in their place, exit 0 (found by fuzzing)
        given = [
            option
            for option, value in (("--scenario", args.scenario), ("--all", args.all), ("--perturb", args.perturb))
            if value
        ]
        if given:
            raise UserFacingError(
                f"{', '.join(given)} does not go with --matrix (every scenario on the matrix's own variants); "
                "one ride or every scenario: --scenario NAME or --all, with --perturb"
            )
        from ptw_rt.eval.matrix import run_matrix_command

        return run_matrix_command(args)
    if not args.all and not args.scenario:
        raise UserFacingError("give --scenario NAME, --all or --matrix")
    if args.scenario:
        get_scenario(args.scenario)  # an unknown name: one line
    names = list(SCENARIOS) if args.all else [args.scenario]
    restored = getattr(args, "restored_biases", False)
    jobs = [(n, args.seed, args.perturb, args.config, args.design_file, restored) for n in names]
    if getattr(args, "markdown", False):
        if not args.all:
            raise UserFacingError("--markdown needs --all")
        workers = getattr(args, "jobs", None)
        results = _run_all(jobs, workers)
        robustness = [
            (title, _run_all([(n, args.seed, pert, args.config, args.design_file, restored) for n in names], workers))
            for title, pert in ROBUSTNESS
        ]
        print(_markdown(results, robustness))
        return 0
    results = _run_all(jobs, getattr(args, "jobs", None))
    if args.all:
        emit({"scenarios": results}, args.json, _table(results))
    else:
        emit(results[0], args.json, _table(results))
    return 0
