"""`ptw-rt` command line: argparse subcommands that hand over to the module doing the work."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ptw_rt.errors import UserFacingError
from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN


def _speeds(text: str) -> list[float]:
    try:
        values = [float(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated speeds in km/h, got {text!r}") from None
    if not values or any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError("speeds must be positive km/h values")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ptw-rt",
        description="Real-time roll, rider-torque and tyre-stiffness estimator for powered two-wheelers.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser(
        "analyze",
        help="eigenvalues, invariant zeros and relative degree of the lateral model over speed",
        description="Modal and strong-observability analysis of the vehicle model (seed 000, sec. III).",
    )
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="vehicle YAML (default: %(default)s)")
    p.add_argument("--speeds", type=_speeds, default=[20, 50, 80, 100, 120], help="km/h, comma-separated")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(handler="ptw_rt.analysis.report:run_analyze")

    p = sub.add_parser(
        "design",
        help="offline observer design over the speed grid (UIHOSMO + LPV adaptive), writes the design file",
        description="Computes gains, transformations and their exact 100 Hz discretisation over the speed grid.",
    )
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="vehicle + estimator YAML")
    p.add_argument("--out", type=Path, default=None, help=f"design file to write (default: {DEFAULT_DESIGN})")
    p.add_argument("--check", action="store_true", help="verify stability of the design instead of writing it")
    p.add_argument("--design-file", type=Path, default=None, help="with --check: check this file, not a fresh design")
    p.add_argument("--json", action="store_true", help="with --check: print one JSON object")
    p.set_defaults(handler="ptw_rt.design.build:run_design")

    p = sub.add_parser(
        "simulate",
        help="simulate a ride (nonlinear plant, rider, sensors) and write it as a candump log with truth",
        description="Writes DIR/NAME.log (candump -L, frames from the DBC) and DIR/NAME.truth.csv (100 Hz, SI).",
    )
    p.add_argument("--scenario", help="scenario name (see --list)")
    p.add_argument("--list", action="store_true", help="list scenarios with a description and exit")
    p.add_argument("--out", type=Path, default=Path("out"), help="output directory (default: %(default)s)")
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
    p.set_defaults(handler="ptw_rt.sim.run:run_simulate")

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
    p.add_argument("--jobs", type=int, default=None, help="with --matrix: worker processes (default: all cores)")
    p.add_argument("--seed", type=int, default=None, help="noise/bias seed (default: the scenario's own)")
    p.add_argument("--perturb", action="append", default=[], metavar="KEY=VALUE", help="plant perturbation")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="vehicle + estimator YAML")
    p.add_argument("--design-file", type=Path, default=None, help=f"design file (default: {DEFAULT_DESIGN})")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--markdown",
        action="store_true",
        help="with --matrix (or --all): the results document, e.g. `--matrix --markdown > docs/results.md`",
    )
    p.set_defaults(handler="ptw_rt.eval.evaluate:run_evaluate")

    p = sub.add_parser(
        "report",
        help="plots of estimates vs truth (and baselines) for a scenario, with a markdown summary",
    )
    p.add_argument("--scenario", required=True, help="scenario name")
    p.add_argument("--out", type=Path, required=True, help="directory for the PNGs and summary.md")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--perturb", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    p.add_argument("--design-file", type=Path, default=None)
    p.set_defaults(handler="ptw_rt.eval.report:run_report")

    p = sub.add_parser(
        "run",
        help="the daemon: 100 Hz loop on a CAN bus, estimates published as DBC frames",
    )
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="config YAML (vehicle, estimator, runtime)")
    p.add_argument("--design-file", type=Path, default=None, help=f"design file (default: {DEFAULT_DESIGN})")
    p.add_argument("--interface", default=None, help="override runtime.bus.interface")
    p.add_argument("--channel", default=None, help="override runtime.bus.channel")
    p.add_argument("--state-file", type=Path, default=None, help="override runtime.state_file")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: run forever)")
    p.add_argument("--check-config", action="store_true", help="validate config and design file, then exit")
    p.set_defaults(handler="ptw_rt.runtime.daemon:run_daemon")

    p = sub.add_parser(
        "replay",
        help="offline replay of candump logs through the same cycle as the daemon",
    )
    p.add_argument("logs", nargs="+", type=Path, help="candump -L logs or directories of them")
    p.add_argument("--out", type=Path, required=True, help="output log (one input) or directory (several)")
    p.add_argument("--csv", type=Path, default=None, help="also write the decoded estimates as CSV (file or dir)")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    p.add_argument("--design-file", type=Path, default=None)
    p.add_argument("--jobs", type=int, default=None, help="parallel processes (default: all cores)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(handler="ptw_rt.runtime.replay:run_replay")

    p = sub.add_parser(
        "monitor",
        help="live decoder of the estimator's frames: counters, CRCs, frozen or corrupted estimator",
    )
    p.add_argument("--interface", default="socketcan")
    p.add_argument("--channel", default="can0")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--json", action="store_true", help="one JSON line per status period")
    p.set_defaults(handler="ptw_rt.runtime.monitor:run_monitor")

    p = sub.add_parser(
        "demo",
        help="no hardware needed: a simulated ride played on a virtual CAN bus into the real daemon loop",
    )
    p.add_argument("--scenario", default="dlc_100")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed (1 = real time)")
    p.add_argument("--duration", type=float, default=None, help="ride seconds (default: the scenario's, at most 25)")
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="where the logs and report go")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    p.set_defaults(handler="ptw_rt.runtime.demo:run_demo")

    p = sub.add_parser("bench", help="speed figures of the step, the cycle, the loop and replay (JSON)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--quick", action="store_true", help="shorter runs (figures less stable)")
    p.set_defaults(handler="ptw_rt.bench:run_bench")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    module_name, func_name = args.handler.split(":")
    import importlib

    handler = getattr(importlib.import_module(module_name), func_name)
    try:
        return int(handler(args) or 0)
    except UserFacingError as exc:
        print(f"ptw-rt {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # `ptw-rt ... | head`: the reader left; not an error of ours.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
