"""`ptw-rt` command line: argparse subcommands that hand over to the module doing the work.

Each subcommand's handler below imports the one function that serves it (imported when the command runs, not
before: `ptw-rt --help` stays quick and the daemon never loads the offline design code). A command that needs an
optional extra which is not installed says so in one line (exit code 2).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from importlib import metadata
from pathlib import Path

from ptw_rt import _deferred_imports
from ptw_rt.errors import UserFacingError
from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN

DESIGN_FILE_HELP = (
    f"design file (default: the config's own, NAME.design.npz beside it, if there is one; else {DEFAULT_DESIGN})"
)

# optional extras of pyproject.toml: top-level module -> extra that installs it
EXTRA_OF_MODULE = {
    "scipy": "design",
    "cvxpy": "design",
    "clarabel": "design",
    "scs": "design",
    "matplotlib": "plot",
    "pynmea2": "gnss",
    "asammdf": "mf4",
    "dask": "fleet",
    "distributed": "fleet",
}


def _version() -> str:
    try:
        return metadata.version("ptw-rt")
    except metadata.PackageNotFoundError:  # run from a source tree that was not installed
        return "unknown (not installed)"


# ---------------------------------------------------------------------- the command handlers


def _analyze(args) -> int:
    if getattr(args, "payload", None) is not None:
        from ptw_rt.design.payload import run_analyze_payload

        return run_analyze_payload(args)
    if getattr(args, "outputs", None):
        from ptw_rt.design.output_sets import run_analyze_outputs

        return run_analyze_outputs(args)
    from ptw_rt.analysis.report import run_analyze

    return run_analyze(args)


MAX_WORKERS = 1024


def _worker_count(text: str) -> int:
    """--jobs: a count of worker processes, 1 .. MAX_WORKERS (argparse prints the error as one line, exit 2)."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 1 <= n <= MAX_WORKERS:
        raise argparse.ArgumentTypeError(f"a number of worker processes, 1 to {MAX_WORKERS}, not {text!r}")
    return n


MAX_SEEDS = 64
MAX_SEED = 2**32 - 1


def _seed_list(text: str) -> list[int | None]:
    """--seeds: comma-separated noise seeds, `own` for each scenario's own (argparse prints the error, exit 2)."""
    items = text.split(",")
    if not 1 <= len(items) <= MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"1 to {MAX_SEEDS} comma-separated noise seeds, not {len(items)}")
    seeds: list[int | None] = []
    for item in items:
        item = item.strip()
        if item == "own":
            seed = None
        else:
            try:
                seed = int(item)
            except ValueError:
                seed = -1
            if not 0 <= seed <= MAX_SEED:
                raise argparse.ArgumentTypeError(
                    f"a noise seed is `own` or a whole number 0 to {MAX_SEED}, not {item[:40]!r}"
                )
        if seed in seeds:
            raise argparse.ArgumentTypeError(f"noise seed {item!r} listed twice")
        seeds.append(seed)
    return seeds


def _design(args) -> int:
    from ptw_rt.design.build import run_design

    return run_design(args)


def _simulate(args) -> int:
    from ptw_rt.sim.run import run_simulate

    return run_simulate(args)


def _evaluate(args) -> int:
    from ptw_rt.eval.evaluate import run_evaluate

    return run_evaluate(args)


def _report(args) -> int:
    from ptw_rt.eval.report import run_report

    return run_report(args)


def _run(args) -> int:
    from ptw_rt.service.daemon import run_daemon

    return run_daemon(args)


def _replay(args) -> int:
    from ptw_rt.apps.replay import run_replay

    return run_replay(args)


def _monitor(args) -> int:
    from ptw_rt.apps.monitor import run_monitor

    return run_monitor(args)


def _demo(args) -> int:
    from ptw_rt.apps.demo import run_demo

    return run_demo(args)


def _bench(args) -> int:
    from ptw_rt.apps.bench import run_bench

    return run_bench(args)


def _directory(text: str) -> Path:
    if not text.strip():  # Path("") is the current directory: `simulate --out ''` wrote the ride there
        raise argparse.ArgumentTypeError("expected a directory, got an empty name")
    return Path(text)


def _speeds(text: str) -> list[float]:
    try:
        values = [float(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated speeds in km/h, got {text!r}") from None
    if not values or not all(0.0 < v <= 400.0 for v in values):  # nan and inf included (the analysis needs numbers)
        raise argparse.ArgumentTypeError("speeds must be km/h values within (0, 400]")
    return values


def _payload_kg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a mass in kg, got {text!r}") from None
    if not -150.0 <= value <= 300.0:  # nan included; the range of the config's vehicle.added_mass
        raise argparse.ArgumentTypeError("the payload must be within [-150, 300] kg")
    return value


def _file_name(text: str) -> Path:
    """A file name argument held to the rule of ``runtime.state_file`` (``schema.check_path_text``): ``--state-file ""``
    was the current directory (warned about as a directory the daemon could not read), a NUL a traceback."""
    from ptw_rt.schema import ConfigError, check_path_text  # only when the option is given: yaml is slow to import

    try:
        return Path(check_path_text("--state-file", text))  # the rule runtime.state_file is held to
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--state-file: ")) from None


class _Parser(argparse.ArgumentParser):
    """argparse with its errors as one line (the usage block is what --help is for): like every other refusal of
    the command line, one line on stderr and exit 2."""

    def error(self, message: str):  # noqa: ANN201 - argparse's signature; never returns
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="ptw-rt",
        description="Real-time roll, rider-torque and tyre-stiffness estimator for powered two-wheelers.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser(
        "analyze",
        help="eigenvalues, invariant zeros and relative degree of the lateral model over speed",
        description="Modal and strong-observability analysis of the vehicle model (seed 000, sec. III).",
    )
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="vehicle YAML (default: %(default)s)")
    p.add_argument(
        "--speeds",
        type=_speeds,
        default=None,
        help="km/h, comma-separated (default: 20,50,80,100,120; with --outputs 10,15,...,130)",
    )
    p.add_argument(
        "--outputs",
        nargs="?",
        const="all",
        default=None,
        help="strong detectability of sensor output sets (issue #16): 'all' (the default candidates) or "
        "'steer,lat_accel;roll_rate' (signals: steer, yaw_rate, roll_rate, lat_accel); speeds default 10-130 km/h",
    )
    p.add_argument(
        "--unknown",
        choices=("phi_tau", "tau", "tau_state"),
        default=None,
        help="with --outputs: unknown inputs [phi, tau] (roll removed), tau (roll measured), tau_state (roll a state)",
    )
    p.add_argument(
        "--payload",
        type=_payload_kg,
        default=None,
        metavar="KG",
        help="can the sensors tell a payload of KG from softer tyres? chi-square of the linear model with the rider's "
        "torque unknown (docs/estimator.md, 'The payload')",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(handler=_analyze)

    p = sub.add_parser(
        "design",
        help="offline observer design over the speed grid (UIHOSMO + LPV adaptive), writes the design file",
        description="Computes gains, transformations and their exact 100 Hz discretisation over the speed grid.",
    )
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="vehicle + estimator YAML")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="design file to write (default: the config's own, NAME.design.npz beside it)",
    )
    p.add_argument("--check", action="store_true", help="verify stability of the design instead of writing it")
    p.add_argument("--design-file", type=Path, default=None, help="with --check: check this file, not a fresh design")
    p.add_argument("--json", action="store_true", help="with --check: print one JSON object")
    p.set_defaults(handler=_design)

    p = sub.add_parser(
        "simulate",
        help="simulate a ride (nonlinear plant, rider, sensors) and write it as a candump log with truth",
        description="Writes DIR/NAME.log (candump -L, frames from the DBC) and DIR/NAME.truth.csv (100 Hz, SI).",
    )
    p.add_argument("--scenario", help="scenario name (see --list)")
    p.add_argument("--list", action="store_true", help="list scenarios with a description and exit")
    p.add_argument("--out", type=_directory, default=Path("out"), help="output directory (default: %(default)s)")
    p.add_argument("--seed", type=int, default=None, help="noise/bias seed (default: the scenario's own)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's own)")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="vehicle YAML")
    p.add_argument(
        "--perturb",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="plant perturbation, e.g. mass_inertia=1.2, stiffness=0.5, imu_noise=2",
    )
    p.add_argument("--plot", action="store_true", help="also draw the truth (needs the plot extra)")
    p.set_defaults(handler=_simulate)

    p = sub.add_parser(
        "evaluate",
        help="simulate a scenario, run the estimator over it and score it (and the baselines) against truth",
        description="Same code path as replay: frames -> Sample -> jitted step -> Estimates, errors after settle_s.",
    )
    p.add_argument("--scenario", help="scenario name (see `ptw-rt simulate --list`)")
    p.add_argument("--all", action="store_true", help="every scenario, one table")
    p.add_argument(
        "--matrix",
        action="store_true",
        help="issue #12's matrix: every scenario x {nominal, tyres x0.7, x1.3, mu 0.85, mass +50 kg}, in parallel",
    )
    p.add_argument(
        "--random",
        type=int,
        default=None,
        metavar="N",
        help="N rides with every perturbation drawn at once (tyres, friction, payload, IMU, encoder zero, rider),"
        " scored against the promises, in parallel; each worst ride printed with the command that replays it",
    )
    p.add_argument(
        "--random-seed", type=int, default=0, metavar="G", help="with --random: which set of rides (default 0)"
    )
    p.add_argument(
        "--routes",
        action="store_true",
        help="with --random: each ride a random route (route_N: segments nobody tuned on) instead of the scenarios",
    )
    p.add_argument(
        "--hills",
        action="store_true",
        help="with --random: each ride on a hilly road (a grade of -4..4 deg swinging by up to 6 deg over 200-1000 m)",
    )
    p.add_argument(
        "--restored-biases",
        action="store_true",
        help="with --scenario, --all or --random: the estimator starts from the ride's own IMU biases, as the daemon"
        " does from a state file an earlier ride wrote (the matrix starts from nothing)",
    )
    p.add_argument(
        "--jobs",
        type=_worker_count,
        default=None,
        help="with --matrix or --random: worker processes (default: every core this process may use)",
    )
    p.add_argument("--seed", type=int, default=None, help="noise/bias seed (default: the scenario's own)")
    p.add_argument(
        "--seeds",
        type=_seed_list,
        default=None,
        metavar="S,S,...",
        help="with --matrix: the matrix once per noise seed (own: each scenario's own), every ride in one pool,"
        " and what each seed misses; with --markdown the first seed's document and the others' summary",
    )
    p.add_argument("--perturb", action="append", default=[], metavar="KEY=VALUE", help="plant perturbation")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="vehicle + estimator YAML")
    p.add_argument("--design-file", type=Path, default=None, help=DESIGN_FILE_HELP)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--markdown",
        action="store_true",
        help="with --matrix (or --all): the results document, e.g. `--matrix --markdown > docs/results.md`",
    )
    p.set_defaults(handler=_evaluate)

    p = sub.add_parser(
        "report",
        help="plots of estimates vs truth (and baselines) for a scenario, with a markdown summary",
    )
    p.add_argument("--scenario", required=True, help="scenario name (see `ptw-rt simulate --list`)")
    p.add_argument("--out", type=Path, required=True, help="directory for the PNGs and summary.md")
    p.add_argument("--seed", type=int, default=None, help="noise/bias seed (default: the scenario's own)")
    p.add_argument(
        "--perturb", action="append", default=[], metavar="KEY=VALUE", help="plant perturbation, e.g. stiffness=0.5"
    )
    p.add_argument(
        "--config", type=Path, default=DEFAULT_CONFIG, help="vehicle + estimator YAML (default: %(default)s)"
    )
    p.add_argument("--design-file", type=Path, default=None, help=DESIGN_FILE_HELP)
    p.set_defaults(handler=_report)

    p = sub.add_parser(
        "run",
        help="the daemon: 100 Hz loop on a CAN bus, estimates published as DBC frames",
    )
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="config YAML (vehicle, estimator, runtime)")
    p.add_argument("--design-file", type=Path, default=None, help=DESIGN_FILE_HELP)
    p.add_argument("--interface", default=None, help="override runtime.bus.interface")
    p.add_argument("--channel", default=None, help="override runtime.bus.channel")
    p.add_argument("--state-file", type=_file_name, default=None, help="override runtime.state_file")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: run forever)")
    p.add_argument("--check-config", action="store_true", help="validate config and design file, then exit")
    p.set_defaults(handler=_run)

    p = sub.add_parser(
        "replay",
        help="offline replay of CAN logs (candump, ASC, BLF, TRC, CSV, MF4) through the same cycle as the daemon",
        description="Input format from the extension and the content; output format from --out's extension "
        "(.log or none: candump -L; .asc, .blf, .trc, .csv, .mf4). Exit code 2: not a CAN log, empty, unreadable.",
    )
    p.add_argument("logs", nargs="*", type=Path, help="CAN logs or directories of them (searched recursively)")
    p.add_argument("--list", type=Path, default=None, metavar="FILE", help="a file naming one log per line")
    p.add_argument(
        "--dask",
        default=None,
        metavar="ADDRESS",
        help="run the logs on a Dask cluster (tcp://scheduler:8786), or 'local' for a LocalCluster of --jobs "
        "workers (the 'fleet' extra)",
    )
    p.add_argument(
        "--out", type=Path, required=True, help="output log (one input; format from its extension) or directory"
    )
    p.add_argument("--csv", type=Path, default=None, help="also write the decoded estimates as CSV (file or dir)")
    p.add_argument(
        "--config", type=Path, default=DEFAULT_CONFIG, help="vehicle + estimator YAML (default: %(default)s)"
    )
    p.add_argument("--design-file", type=Path, default=None, help=DESIGN_FILE_HELP)
    p.add_argument("--jobs", type=_worker_count, default=None, help="parallel processes (default: all cores)")
    p.add_argument(
        "--max-gap",
        type=float,
        default=None,
        metavar="S",
        help="a gap in a log's time stamps longer than this ends a segment; the next starts from reset inputs "
        "(0.1-60 s, default: 5 s)",
    )
    p.add_argument(
        "--channel",
        default=None,
        metavar="NAME",
        help="in a log of several buses, the one to read, as the log names it (candump: can0; ASC, BLF: 0, 1 ...); "
        "default: the bus with the most input frames among the first. Frames on the others are skipped and counted",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar or progress lines on stderr")
    p.set_defaults(handler=_replay)

    p = sub.add_parser(
        "monitor",
        help="live decoder of the estimator's frames: counters, CRCs, frozen or corrupted estimator",
    )
    p.add_argument("--interface", default="socketcan", help="python-can interface (default: %(default)s)")
    p.add_argument("--channel", default="can0", help="CAN channel (default: %(default)s)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--json", action="store_true", help="one JSON line per status period")
    p.set_defaults(handler=_monitor)

    p = sub.add_parser(
        "demo",
        help="no hardware needed: a simulated ride played on a virtual CAN bus into the real daemon loop",
    )
    p.add_argument("--scenario", default="dlc_100", help="scenario name (default: %(default)s)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed (1 = real time)")
    p.add_argument("--duration", type=float, default=None, help="ride seconds (default: the scenario's, at most 25)")
    p.add_argument(
        "--out", type=Path, default=Path("out/demo"), help="where the logs and report go (default: %(default)s)"
    )
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="config YAML (default: %(default)s)")
    p.set_defaults(handler=_demo)

    p = sub.add_parser("bench", help="speed figures of the step, the cycle, the loop and replay (JSON)")
    p.add_argument("--json", action="store_true", help="one JSON object on one line (default: indented)")
    p.add_argument("--quick", action="store_true", help="shorter runs (figures less stable)")
    p.set_defaults(handler=_bench)
    return parser


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The one-line message for a missing optional dependency, None if ``exc`` is not one."""
    module = (exc.name or "").split(".")[0]
    extra = EXTRA_OF_MODULE.get(module)
    if extra is None:
        return None
    return f"needs the '{extra}' extra ({module} is not installed): pip install 'ptw-rt[{extra}]'"


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001 - warnings' API
    """A library's warning (scipy's LinAlgWarning on an ill-conditioned vehicle, numpy's on an empty mean) as one
    line, not Python's two with a source line: a refusal stays readable."""
    text = " ".join(str(message).split())
    print(f"ptw-rt: warning: {category.__name__}: {text[:200]}", file=file or sys.stderr)


def main(argv: list[str] | None = None) -> int:
    _deferred_imports.install()  # python-can's MF4 support (asammdf, pandas) only when a log needs it
    warnings.showwarning = _warning_line
    parser = build_parser()
    args = parser.parse_args(argv)
    from ptw_rt.service.logs import setup_command_logging
    from ptw_rt.untrusted import one_line

    setup_command_logging()
    try:
        return int(args.handler(args) or 0)
    except UserFacingError as exc:
        print(f"ptw-rt {args.command}: {one_line(str(exc))}", file=sys.stderr)
        return int(getattr(exc, "exit_code", 2))
    except ModuleNotFoundError as exc:
        message = missing_extra(exc)
        if message is None:
            raise
        print(f"ptw-rt {args.command}: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # `ptw-rt ... | head`: the reader left; not an error of ours.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
