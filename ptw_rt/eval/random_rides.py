"""Random combined-perturbation rides: what the matrix does not show (``ptw-rt evaluate --random N``).

The matrix varies one thing at a time. A real scooter varies everything at once, so each ride here draws, from
its own generator, every perturbation of ``DRAWS`` at once (tyres, friction, payload, IMU noise and biases, an
encoder zero up to a count off, the rider's activity) and a noise seed; the scenarios are taken
in turn. ``--random-seed G`` picks the set: ride ``i`` of set ``G`` is always the same ride, and its line carries
the ``ptw-rt evaluate --scenario ... --seed ... --perturb ...`` command that replays it alone.

Scored against the promises, not against tuning goals: roll never worse than the Fusion AHRS peer and within
1 deg; the roll never VALID beyond its documented tolerance; the tyre stiffness never VALID beyond 20 % (within
10 % on average); the rider torque within 15 % of its peak; and which rides raised a monitor's alarm (none was
injected: on a ride whose encoder zero is right, an alarm is a false one; a zero a count off is below what the
steer check is meant to flag, but may be).
"""

from __future__ import annotations

import shlex
import time
from pathlib import Path

import numpy as np

from ptw_rt.eval.matrix import (
    ROLL_MAX_DEG,
    STIFFNESS_VALID_MAX_PCT,
    STIFFNESS_VALID_MEAN_PCT,
    TORQUE_MAX_PCT_OF_PEAK,
    run_cell,
)
from ptw_rt.output import emit
from ptw_rt.parallel import map_in_processes, worker_count
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.progress import Progress
from ptw_rt.sim.routes import MAX_ROUTE, ROUTE_PREFIX

# the scenarios in turn (ride i is SCENARIOS[i % 8]); fixed here rather than taken from the simulator's registry:
# a scenario added there must not change which ride is ride i of set G
SCENARIOS = (
    "handling_40_120",
    "urban",
    "slalom_30",
    "radius_accel",
    "mu_drop",
    "dlc_50",
    "dlc_100",
    "sensor_faults",
)
# drawn in this order (the order is part of what makes ride i of set G the same ride everywhere), uniformly
# within (low, high); the encoder zero in whole counts
DRAWS = (
    ("stiffness", 0.6, 1.4),  # tyres: pressure, wear, temperature
    ("mu_scale", 0.7, 1.0),  # the road's friction, a factor on the scenario's
    ("added_mass", -40.0, 40.0),  # kg: rider and luggage against the file's
    ("imu_noise", 1.0, 2.0),
    ("imu_bias", 1.0, 2.0),
    ("steer_offset", -1, 1),  # counts: the encoder's zero
    ("rider_noise", 1.0, 2.0),  # a busier rider
)
WHOLE_COUNTS = ("steer_offset",)
# with --hills, the road under the ride, drawn after everything else (so a set's other draws stay the same): a mean
# grade, how far it swings about it, and over how many metres (crests and dips; docs/estimator.md, "Hills on
# other seeds")
HILL_DRAWS = (
    ("road_slope", -4.0, 4.0),  # deg, uphill positive
    ("road_slope_swing", 0.0, 6.0),  # deg
    ("road_slope_length", 200.0, 1000.0),  # m ridden over one swing
)
# and the front tyre against the rear (a pressure or a wear of its own): from a generator of its own (`_axle_rng`), so a
# set's other draws are the ones it had before this draw was added (2026-12-07), and a route's ride is drawn the same
AXLE_DRAWS = (("front_stiffness", 0.8, 1.25),)
NOISE_SEEDS = (20, 10000)  # the rides' noise seeds are drawn from [20, 10000): not the scenarios' own
MAX_RIDES = 100_000
MAX_GENERATOR_SEED = 10**9  # sets: ride i of set G draws from a generator seeded 1000 + i + 1000 G
WORST_SHOWN = 5
TORQUE_KEY = "torque_valid_max_mean_err_nm"


def draw_ride(
    generator_seed: int, index: int, routes: bool = False, hills: bool = False
) -> tuple[str, tuple[str, ...], int]:
    """(scenario, perturbations, noise seed) of ride `index` of set `generator_seed`; with `routes`, the ride is a
    random route (``route_N``, ``ptw_rt.sim.routes``), and with `hills` its road's grade (HILL_DRAWS), each drawn
    after the rest, so the other draws are the same as without; last, the front tyre's own factor (AXLE_DRAWS)."""
    rng = np.random.default_rng(1000 + index + 1000 * generator_seed)
    perturb = _drawn(rng, DRAWS)
    seed = int(rng.integers(*NOISE_SEEDS))
    scenario = f"{ROUTE_PREFIX}{int(rng.integers(0, MAX_ROUTE))}" if routes else SCENARIOS[index % len(SCENARIOS)]
    if hills:
        perturb += _drawn(rng, HILL_DRAWS)
    perturb += _drawn(_axle_rng(generator_seed, index), AXLE_DRAWS)
    return scenario, tuple(perturb), seed


def _axle_rng(generator_seed: int, index: int) -> np.random.Generator:
    """Ride `index` of set `generator_seed`'s own stream for AXLE_DRAWS (beside the ride's generator, not after it)."""
    return np.random.default_rng([1000 + index + 1000 * generator_seed, 1])


def _drawn(rng: np.random.Generator, draws: tuple) -> list[str]:
    """`--perturb` items, each (name, low, high) of `draws` drawn in order (whole counts for WHOLE_COUNTS)."""
    items = []
    for name, low, high in draws:
        value = float(rng.integers(low, high + 1)) if name in WHOLE_COUNTS else float(rng.uniform(low, high))
        items.append(f"{name}={value:.3f}")
    return items


def reproduce_command(ride: dict) -> str:
    args = ["ptw-rt", "evaluate", "--scenario", ride["scenario"], "--seed", str(ride["seed"])]
    for p in ride["perturb"]:
        args += ["--perturb", p]
    for flag in ("config", "design_file"):  # a ride on another file replays only on it
        if ride.get(flag) is not None:
            args += ["--" + flag.replace("_", "-"), str(ride[flag])]
    if ride.get("restored_biases"):
        args.append("--restored-biases")
    return shlex.join(args)


def _summary_of_cell(cell: dict, seed: int) -> dict:
    m = cell["metrics"]
    stiff = [s for s in m["stiffness_valid"].values() if s["valid_frames"]]
    steer_zero = next((float(p.split("=")[1]) for p in cell["perturb"] if p.startswith("steer_offset=")), 0.0)
    return {
        "scenario": cell["scenario"],
        "seed": seed,
        "perturb": cell["perturb"],
        "roll_rmse_deg": m["roll_rmse_deg"]["ours"],
        "peer_roll_rmse_deg": m["roll_rmse_deg"]["peer"],
        "roll_valid_max_err_deg": m["roll_valid"]["max_err_deg"],
        "roll_tolerance_deg": m["roll_valid"]["tolerance_deg"],
        "torque_pct_of_peak": m["torque"]["pct_of_peak"],
        "torque_valid_max_mean_err_nm": m["torque_valid"]["max_mean_err_nm"],
        "stiffness_valid_max_err_pct": max((s["max_abs_err_pct"] for s in stiff), default=None),
        "stiffness_valid_mean_err_pct": max((s["mean_abs_err_pct"] for s in stiff), default=None),
        "alarm_cycles": m["alarm_cycles"],
        "steer_zero_counts": steer_zero,
        "crashed_at": cell["result"]["crashed_at"],  # s: the simulated rider fell (scored until then), or None
    }


def _ride_job(job: tuple) -> dict:
    scenario, perturb, seed, config, design_file, restored_biases = job
    cell = run_cell((scenario, "random", perturb, seed, config, design_file, restored_biases))
    ride = _summary_of_cell(cell, seed)
    if restored_biases:
        ride["restored_biases"] = True
    if Path(config) != DEFAULT_CONFIG:
        ride["config"] = str(config)
    if design_file is not None:
        ride["design_file"] = str(design_file)
    return ride


def _gt(value, limit) -> bool:
    return value is not None and limit is not None and value > limit


def summarise(rides: list[dict]) -> dict:
    """The promises over the rides: counts, the largest figures, and the rides that broke or came nearest."""

    def worst(key: str) -> list[dict]:
        ranked = sorted((r for r in rides if r[key] is not None), key=lambda r: -r[key])
        return [{key: r[key], "command": reproduce_command(r)} for r in ranked[:WORST_SHOWN]]

    def largest(key: str, among: list[dict] = rides):
        values = [r[key] for r in among if r[key] is not None]
        return max(values) if values else None

    # a ride whose simulated rider fell is scored until the fall: its torque RMSE then says more about the fall
    # than about the estimator (random routes set 2403: 64.9 % of the peak, the rider down 1.6 s into the scoring)
    upright = [r for r in rides if r["crashed_at"] is None]

    def torque_within(among: list[dict]) -> int:
        return sum(
            r["torque_pct_of_peak"] is not None and r["torque_pct_of_peak"] <= TORQUE_MAX_PCT_OF_PEAK for r in among
        )

    roll_scored = [r for r in rides if r["roll_rmse_deg"] is not None and r["peer_roll_rmse_deg"] is not None]
    alarmed = [any(r["alarm_cycles"].values()) for r in rides]
    zero_right = [r["steer_zero_counts"] == 0.0 for r in rides]
    promises = {
        "roll_valid_within_tolerance": not any(
            _gt(r["roll_valid_max_err_deg"], r["roll_tolerance_deg"]) for r in rides
        ),
        "stiffness_valid_max_le_20pct": not any(
            _gt(r["stiffness_valid_max_err_pct"], STIFFNESS_VALID_MAX_PCT) for r in rides
        ),
    }
    return {
        "rides": len(rides),
        "crashed": len(rides) - len(upright),
        "promises_kept": promises,
        "roll": {
            "le_peer": sum(r["roll_rmse_deg"] <= r["peer_roll_rmse_deg"] for r in roll_scored),
            "scored": len(roll_scored),
            "le_1deg": sum(r["roll_rmse_deg"] <= ROLL_MAX_DEG for r in roll_scored),
            "largest_rmse_deg": largest("roll_rmse_deg"),
            "largest_valid_err_deg": largest("roll_valid_max_err_deg"),
            "worst_rmse": worst("roll_rmse_deg"),
            "worst_valid_err": worst("roll_valid_max_err_deg"),
            "worse_than_peer": [
                {"roll": r["roll_rmse_deg"], "peer": r["peer_roll_rmse_deg"], "command": reproduce_command(r)}
                for r in roll_scored
                if r["roll_rmse_deg"] > r["peer_roll_rmse_deg"]
            ],
        },
        "stiffness": {
            "rides_valid": sum(r["stiffness_valid_max_err_pct"] is not None for r in rides),
            "largest_valid_err_pct": largest("stiffness_valid_max_err_pct"),
            "largest_valid_mean_err_pct": largest("stiffness_valid_mean_err_pct"),
            # of the rides VALID at some time: the mean error over their VALID frames
            "mean_le_10pct": sum(
                r["stiffness_valid_mean_err_pct"] is not None
                and r["stiffness_valid_mean_err_pct"] <= STIFFNESS_VALID_MEAN_PCT
                for r in rides
            ),
            "worst_valid_err": worst("stiffness_valid_max_err_pct"),
        },
        "torque": {
            "le_15pct_of_peak": torque_within(rides),
            "largest_pct_of_peak": largest("torque_pct_of_peak"),
            "largest_pct_of_peak_upright": largest("torque_pct_of_peak", upright),
            "le_15pct_of_peak_upright": torque_within(upright),
            "largest_valid_mean_err_nm": largest("torque_valid_max_mean_err_nm"),
            "worst_valid_mean_err": worst("torque_valid_max_mean_err_nm"),
        },
        "alarms": {
            "rides_with_zero_right": sum(zero_right),
            "alarmed_with_zero_right": sum(a and z for a, z in zip(alarmed, zero_right, strict=True)),
            "rides_with_zero_a_count_off": len(rides) - sum(zero_right),
            "alarmed_with_zero_a_count_off": sum(a and not z for a, z in zip(alarmed, zero_right, strict=True)),
        },
    }


def run_random(
    count: int,
    generator_seed: int = 0,
    *,
    config: Path = DEFAULT_CONFIG,
    design_file: Path | None = None,
    workers: int | None = None,
    progress: bool = True,
    routes: bool = False,
    hills: bool = False,
    restored_biases: bool = False,
) -> dict:
    jobs = []
    for i in range(count):
        scenario, perturb, seed = draw_ride(generator_seed, i, routes, hills)
        jobs.append((scenario, perturb, seed, config, design_file, restored_biases))
    bar = Progress(len(jobs), label="random rides") if progress else None
    t0 = time.perf_counter()
    rides = map_in_processes(_ride_job, jobs, workers, bar, lambda j: f"{j[0]} {j[2]}")
    if bar is not None:
        bar.finish()
    return {
        "generator_seed": generator_seed,
        "routes": routes,
        "hills": hills,
        "restored_biases": restored_biases,
        "summary": summarise(rides),
        "rides_detail": rides,
        "wall_s": round(time.perf_counter() - t0, 1),
        "workers": worker_count(workers, len(jobs)),
    }


def summary_text(result: dict) -> str:
    s = result["summary"]
    roll, st, tq, al = s["roll"], s["stiffness"], s["torque"], s["alarms"]
    n = s["rides"]

    def kept(name: str) -> str:
        return "kept" if s["promises_kept"][name] else "BROKEN"

    lines = [
        f"{n} random rides (set {result['generator_seed']}{', random routes' if result.get('routes') else ''}"
        f"{', hilly roads' if result.get('hills') else ''}"
        f"{', biases restored as from a state file' if result.get('restored_biases') else ''}) on"
        f" {result['workers']} processes in {result['wall_s']} s",
        f"roll: <= the peer on {roll['le_peer']} of {roll['scored']}, <= {ROLL_MAX_DEG:g} deg on {roll['le_1deg']};"
        f" largest RMSE {roll['largest_rmse_deg']} deg",
        f"roll while VALID: largest error {roll['largest_valid_err_deg']} deg"
        f" (promise: within the documented tolerance, {kept('roll_valid_within_tolerance')})",
        f"stiffness while VALID: on {st['rides_valid']} rides, largest error {st['largest_valid_err_pct']} %"
        f" (promise: <= {STIFFNESS_VALID_MAX_PCT:g} %, {kept('stiffness_valid_max_le_20pct')}), largest mean"
        f" {st['largest_valid_mean_err_pct']} %, mean <= {STIFFNESS_VALID_MEAN_PCT:g} % on {st['mean_le_10pct']} of"
        f" those {st['rides_valid']}",
        f"torque: <= {TORQUE_MAX_PCT_OF_PEAK:g} % of the peak on {tq['le_15pct_of_peak']}, largest"
        f" {tq['largest_pct_of_peak']} %"
        + (
            f" (of the {n - s['crashed']} whose simulated rider did not fall: on {tq['le_15pct_of_peak_upright']},"
            f" largest {tq['largest_pct_of_peak_upright']} %)"
            if s["crashed"]
            else ""
        )
        + f"; while VALID, its 0.2 s trailing mean at most {tq['largest_valid_mean_err_nm']} N m off",
        f"alarms (none injected): {al['alarmed_with_zero_right']} of {al['rides_with_zero_right']} rides with the"
        f" encoder zero right, {al['alarmed_with_zero_a_count_off']} of {al['rides_with_zero_a_count_off']} with it"
        " a count off",
    ]
    for title, items, key in (
        ("largest roll error while VALID [deg]", roll["worst_valid_err"], "roll_valid_max_err_deg"),
        ("largest roll RMSE [deg]", roll["worst_rmse"], "roll_rmse_deg"),
        ("largest stiffness error while VALID [%]", st["worst_valid_err"], "stiffness_valid_max_err_pct"),
        (
            "largest torque error (0.2 s trailing mean) while VALID [N m]",
            tq["worst_valid_mean_err"],
            "torque_valid_max_mean_err_nm",
        ),
    ):
        lines.append(f"{title}:")
        lines += [f"  {item[key]:>7}  {item['command']}" for item in items]
    if s["crashed"]:
        lines.append(f"rides whose simulated rider fell (scored until the fall): {s['crashed']}")
    if roll["worse_than_peer"]:
        lines.append("roll worse than the peer (ours / peer [deg]):")
        lines += [f"  {w['roll']} / {w['peer']}  {w['command']}" for w in roll["worse_than_peer"]]
    return "\n".join(lines)


def run_random_command(args) -> int:
    from ptw_rt.errors import UserFacingError

    count = args.random
    if not 1 <= count <= MAX_RIDES:
        raise UserFacingError(f"--random takes a number of rides, 1 to {MAX_RIDES}, not {count}")
    if not 0 <= args.random_seed <= MAX_GENERATOR_SEED:
        raise UserFacingError(f"--random-seed takes a set number, 0 to {MAX_GENERATOR_SEED}, not {args.random_seed}")
    given = [
        flag
        for flag, value in (
            ("--scenario", getattr(args, "scenario", None)),
            ("--all", getattr(args, "all", False)),
            ("--matrix", getattr(args, "matrix", False)),
            ("--seed", getattr(args, "seed", None)),
            ("--seeds", getattr(args, "seeds", None)),
            ("--perturb", getattr(args, "perturb", None)),
            ("--markdown", getattr(args, "markdown", False)),
        )
        if value
    ]
    if given:
        raise UserFacingError(
            f"--random draws its own scenarios, noise seeds and perturbations: drop {', '.join(given)} "
            "(replay one ride with the command its line prints)"
        )
    result = run_random(
        count,
        args.random_seed,
        config=args.config,
        design_file=args.design_file,
        workers=getattr(args, "jobs", None),
        routes=getattr(args, "routes", False),
        hills=getattr(args, "hills", False),
        restored_biases=getattr(args, "restored_biases", False),
    )
    emit(result, args.json, summary_text(result) if not args.json else "")
    return 0
