"""``ptw-rt simulate``: run a scenario and write DIR/NAME.log, DIR/NAME.truth.csv (and .meta.json)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ptw_rt.errors import UserFacingError
from ptw_rt.schema import ConfigError
from ptw_rt.sim.ride import NoRiderError, Ride, get_scenario, parse_perturbations, simulate
from ptw_rt.sim.routes import MAX_ROUTE, ROUTE_DURATION, ROUTE_PREFIX
from ptw_rt.sim.scenarios import SCENARIOS
from ptw_rt.untrusted import one_line


def list_scenarios() -> str:
    width = max(len(n) for n in SCENARIOS)
    lines = [f"{'scenario':<{width}}  duration  seed  description"]
    for s in SCENARIOS.values():
        lines.append(f"{s.name:<{width}}  {s.duration:6.0f} s  {s.seed:4d}  {s.description}")
    lines.append(
        f"{ROUTE_PREFIX + 'N':<{width}}  {ROUTE_DURATION:6.0f} s        a random route, N = 0..{MAX_ROUTE - 1}: "
        "segments drawn from N (ptw_rt/sim/routes.py), rides nobody tuned on"
    )
    return "\n".join(lines)


def _bar(label: str):
    def show(frac: float) -> None:
        width = 30
        filled = int(round(frac * width))
        sys.stderr.write(f"\r{label:<24} [{'#' * filled}{'.' * (width - filled)}] {100 * frac:5.1f}%")
        if frac >= 1.0:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UserFacingError(
            "--plot needs matplotlib, which is not installed; install the plot extra: pip install 'ptw-rt[plot]'"
        ) from None
    return plt


def plot_ride(ride: Ride, path: Path) -> None:
    plt = _pyplot()
    T = ride.truth
    t = T["t"]
    fig, ax = plt.subplots(6, 1, figsize=(11, 14), sharex=True)
    ax[0].plot(t, T["speed"] * 3.6, label="speed")
    ax[0].plot(t, T["speed_ref"] * 3.6, "--", label="reference")
    ax[0].set_ylabel("km/h")
    ax[1].plot(t, np.degrees(T["roll"]), label="roll")
    ax[1].plot(t, np.degrees(T["steer"]) * 10, label="steer x10")
    ax[1].set_ylabel("deg")
    ax[2].plot(t, T["rider_torque"], label="rider torque")
    ax[2].set_ylabel("N m")
    ax[3].plot(t, T["fy_front"], label="F_yf")
    ax[3].plot(t, T["fy_rear"], label="F_yr")
    ax[3].set_ylabel("N")
    ax[4].plot(t, T["c_alpha_front"], label="C_af")
    ax[4].plot(t, T["c_alpha_rear"], label="C_ar")
    ax[4].plot(t, T["c_gamma_front"] * 10, label="C_gf x10")
    ax[4].plot(t, T["c_gamma_rear"] * 10, label="C_gr x10")
    ax[4].set_ylabel("N/rad")
    ax[5].plot(t, T["grip_used_front"], label="front")
    ax[5].plot(t, T["grip_used_rear"], label="rear")
    ax[5].set_ylabel("grip used")
    ax[5].set_xlabel("t [s]")
    for a in ax:
        a.legend(loc="upper right", fontsize=8)
        a.grid(alpha=0.3)
    fig.suptitle(f"{ride.scenario} (seed {ride.seed}): {ride.description}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def run_simulate(args) -> int:
    if args.list:
        print(list_scenarios())
        return 0
    if not args.scenario:
        raise UserFacingError(f"give --scenario NAME (or --list); available: {', '.join(SCENARIOS)}")
    sc = get_scenario(args.scenario)
    pert = parse_perturbations(args.perturb)
    if args.plot:
        _pyplot()  # fail before simulating, not after
    if args.duration is not None and not (0.0 < args.duration <= 3600.0):
        raise UserFacingError(f"--duration must be within (0, 3600] s, got {args.duration}")
    config = Path(args.config)  # a missing file, a device, a FIFO: named by the bounded reader below
    from ptw_rt.model.parameters import load_vehicle

    try:
        vehicle = load_vehicle(config)
    except ConfigError as exc:
        raise UserFacingError(str(exc)) from None
    t0 = time.perf_counter()
    try:
        with np.errstate(all="ignore"):  # reported as one line below
            ride = simulate(
                sc, seed=args.seed, duration=args.duration, vehicle=vehicle, perturbation=pert, progress=True
            )
    except NoRiderError as exc:
        # a vehicle the schema's ranges let through may have no rider (a relaxation length of 1e-12 m)
        raise UserFacingError(f"--config {config}: {exc}") from None
    sim_wall = time.perf_counter() - t0
    from ptw_rt.sim.recording import write_ride

    out = Path(args.out)
    paths = write_ride(ride, out, progress=_bar(f"{sc.name}: writing log") if ride.duration >= 20 else None)
    if args.plot:
        png = out / f"{sc.name}.png"
        plot_ride(ride, png)
        paths["plot"] = png
    total_wall = time.perf_counter() - t0
    print(f"scenario {ride.scenario} (seed {ride.seed}, {ride.duration:g} s): {ride.description}")
    nominal = type(ride.perturbation)().as_dict()
    changed = {k: v for k, v in ride.perturbation.as_dict().items() if v != nominal[k]}
    if changed:
        print("perturbation: " + ", ".join(f"{k}={v:g}" for k, v in changed.items()))
    for kind, p in paths.items():
        print(f"wrote {one_line(str(p))}" + (f" ({ride.n_frames()} frames)" if kind == "log" else ""))
    print(
        f"real-time factor {ride.duration / sim_wall:.0f}x simulating, {ride.duration / total_wall:.0f}x including "
        f"the log ({total_wall:.2f} s wall)"
    )
    if ride.crashed_at is not None:
        print(
            f"warning: the rider lost control at t = {ride.crashed_at:.2f} s (|roll| > 69 deg); "
            "the truth holds the last state after that",
            file=sys.stderr,
        )
    return 0
