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
