"""`ptw-rt analyze --outputs`: strong detectability of the output sets the scooter has (issue #16).

For each candidate (outputs from steer delta, ground yaw rate r, roll rate phi_dot, lateral acceleration
a_y = (F_yf + F_yr) / M; unknown inputs [phi, tau] with roll removed from the state as in seed 000
sec. III-A, tau with the roll measured as an input, or tau with the roll kept as an unmeasured state):

- invariant zeros over the speeds (max real part per speed; strongly detectable = all in the open left
  half-plane, and where not, the speeds where it fails);
- relative degree of each output w.r.t. the unknown inputs, and whether an output has a direct
  feedthrough of an unknown input (then that part of the reconstruction is algebraic);
- the highest derivative of each measured signal the reconstruction needs (= its relative degree);
- the torque gain of eq. 15 (N m per unit of the highest derivative of the output that carries tau, at
  100 km/h), which says how a derivative's noise becomes torque noise: 0.6 N m per rad/s^2 of steer
  acceleration, 41 N m per rad/s^2 of roll acceleration.

Offline (scipy), never imported by the runtime.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ptw_rt.design import uio_sensors as us
from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import N_STATES, state_space

UI_TAU_STATE = "tau_state"  # tau unknown, roll kept as an (unmeasured) state of the full model
UNKNOWN_LABEL = {
    us.UI_PHI_TAU: "[phi, tau], roll removed from the state",
    us.UI_TAU: "tau, roll measured (attitude filter) as an input",
    UI_TAU_STATE: "tau, roll an unmeasured state",
}
# Default candidates: seed 000's case 2 first, then every pair / single output that is square with its inputs.
CANDIDATES: tuple[tuple[tuple[str, ...], str], ...] = (
    (("steer", "yaw_rate"), us.UI_PHI_TAU),
    (("steer", "roll_rate"), us.UI_PHI_TAU),
    (("steer", "lat_accel"), us.UI_PHI_TAU),
    (("yaw_rate", "roll_rate"), us.UI_PHI_TAU),
    (("yaw_rate", "lat_accel"), us.UI_PHI_TAU),
    (("roll_rate", "lat_accel"), us.UI_PHI_TAU),
    (("steer",), us.UI_TAU),
    (("yaw_rate",), us.UI_TAU),
    (("roll_rate",), us.UI_TAU),
    (("lat_accel",), us.UI_TAU),
    (("steer",), UI_TAU_STATE),
    (("roll_rate",), UI_TAU_STATE),
    (("lat_accel",), UI_TAU_STATE),
)
DEFAULT_SPEEDS_KMH = (10, 15, 20, 30, 50, 70, 90, 100, 110, 120, 130)


def _full_system(p: VehicleParameters, u: float, outputs: tuple[str, ...]) -> us.SensorSystem:
    A, B = state_space(p, u)
    C = np.array([np.r_[0.0, us.output_row(p, o)] for o in outputs])
    return us.SensorSystem(A, B[:, None], np.zeros(N_STATES), C, np.zeros((N_STATES, 4)))


def system(p: VehicleParameters, u: float, outputs: tuple[str, ...], unknown: str) -> us.SensorSystem:
    if unknown == UI_TAU_STATE:
        return _full_system(p, u, outputs)
    return us.sensor_system(p, u, outputs, unknown)


def zeros(sys: us.SensorSystem) -> np.ndarray:
    """Invariant zeros of the square triple (A, D, C), scaled (tyre forces are 1e4 x the angles)."""
    scale = us.STATE_SCALE if sys.A.shape[0] == us.N_X else np.r_[0.05, us.STATE_SCALE]
    return us.invariant_zeros(sys, scale, largest=1e6)


def _relative_degrees(sys: us.SensorSystem) -> list[int]:
    out = []
    dn = np.linalg.norm(sys.D)
    for c in sys.C:
        row, deg = c.copy(), 0
        for k in range(1, sys.A.shape[0] + 1):
            if np.linalg.norm(row @ sys.D) > 1e-9 * np.linalg.norm(row) * dn:
                deg = k
                break
            row = row @ sys.A
        out.append(deg)
    return out


def torque_gain(sys: us.SensorSystem, degrees: list[int]) -> list[float] | None:
    """|d tau / d y_j^(rho_j)| per output: N m per unit of each top derivative in eq. 15."""
    if 0 in degrees:
        return None
    Dbar = np.array([c @ np.linalg.matrix_power(sys.A, r - 1) @ sys.D for c, r in zip(sys.C, degrees, strict=True)])
    if abs(np.linalg.det(Dbar)) < 1e-14:
        return None
    return [float(abs(g)) for g in np.linalg.inv(Dbar)[-1]]


def analyze_candidate(p: VehicleParameters, outputs: tuple[str, ...], unknown: str, speeds_kmh) -> dict[str, Any]:
    per_speed = []
    for v in speeds_kmh:
        z = zeros(system(p, v / 3.6, outputs, unknown))
        per_speed.append(
            {
                "speed_kmh": float(v),
                "max_real_zero": float(z.real.max()) if z.size else None,
                "zeros": [[float(x.real), float(x.imag)] for x in z if x.imag >= 0],
            }
        )
    bad = [s["speed_kmh"] for s in per_speed if s["max_real_zero"] is not None and s["max_real_zero"] >= 0]
    ref = system(p, 100 / 3.6, outputs, unknown)
    degrees = _relative_degrees(ref)
    feedthrough = [False for _ in outputs]  # C has no D-term in Sharp's model: a_y = (F_yf + F_yr) / M
    derivs = {o: d for o, d in zip(outputs, degrees, strict=True)}
    return {
        "outputs": list(outputs),
        "unknown_inputs": unknown,
        "unknown_label": UNKNOWN_LABEL[unknown],
        "relative_degrees": degrees,
        "feedthrough": feedthrough,
        "derivative_orders": derivs,
        "steer_derivative_order": derivs.get("steer", 0),
        "torque_gain_100kmh": torque_gain(ref, degrees),
        "strongly_detectable": not bad,
        "not_detectable_at_kmh": bad,
        "per_speed": per_speed,
    }


def analyze_outputs(p: VehicleParameters, candidates, speeds_kmh) -> dict[str, Any]:
    rows = [analyze_candidate(p, tuple(o), u, speeds_kmh) for o, u in candidates]
    ok = [r for r in rows if r["strongly_detectable"]]
    fewest = min(r["steer_derivative_order"] for r in ok) if ok else None
    return {
        "speeds_kmh": [float(v) for v in speeds_kmh],
        "candidates": rows,
        "fewest_steer_derivatives_detectable": [
            "+".join(r["outputs"]) + f" ({r['unknown_inputs']})" for r in ok if r["steer_derivative_order"] == fewest
        ],
        "chosen": {
            "outputs": list(us.CHOSEN_OUTPUTS),
            "unknown_inputs": us.CHOSEN_UNKNOWN,
            "pre_observer_extra_outputs": list(us.CHOSEN_EXTRA),
        },
    }


def _zero_text(v: float | None) -> str:
    if v is None:
        return f"{'none':>6}"
    return f"{v:6.3f}" if abs(v) < 0.1 else f"{v:6.2f}"


def format_outputs_table(result: dict[str, Any]) -> str:
    speeds = result["speeds_kmh"]
    head = f"{'outputs':<15} {'unknown':<9} {'rel.deg':<7} {'derivatives needed':<24} {'tau gain per deriv.':<19}  "
    head += " ".join(f"{v:>6g}" for v in speeds) + "  strongly detectable"
    lines = [head, "-" * len(head)]
    for r in result["candidates"]:
        der = ", ".join(f"{us.SHORT[o]}^({d})" for o, d in r["derivative_orders"].items())
        g = r["torque_gain_100kmh"]
        gain = "-" if g is None else "/".join(f"{x:.3g}" for x in g)
        zs = " ".join(_zero_text(s["max_real_zero"]) for s in r["per_speed"])
        bad = ",".join(f"{v:g}" for v in r["not_detectable_at_kmh"])
        verdict = "yes" if r["strongly_detectable"] else "NO at " + bad
        lines.append(
            f"{'+'.join(us.SHORT[o] for o in r['outputs']):<15} {r['unknown_inputs']:<9} "
            f"{str(r['relative_degrees']):<7} {der:<24} {gain:<19}  {zs}  {verdict}"
        )
    c = result["chosen"]
    lines += [
        "",
        "columns per speed [km/h]: max real part of the invariant zeros (>= 0: not strongly detectable there)",
        "unknown inputs: phi_tau = [phi, tau] with roll removed from the state (seed 000 III-A); tau = rider torque "
        "with the roll measured as an input; tau_state = rider torque, roll an unmeasured state (full model)",
        "feedthrough: none in any candidate (a_y = (F_yf + F_yr)/M depends on states only), so no part of the "
        "reconstruction is algebraic; derivatives needed = relative degree of each output",
        "tau gain per deriv.: N m of torque per unit of each output's top derivative in eq. 15 at 100 km/h "
        "(per output, in the order listed): how that derivative's noise and model error become torque error",
        "strongly detectable with the fewest steer derivatives: "
        + "; ".join(result["fewest_steer_derivatives_detectable"]),
        f"chosen (docs/estimator.md): reconstruction from {'+'.join(c['outputs'])}, unknown input "
        f"{c['unknown_inputs']}, pre-observer also injecting {'+'.join(c['pre_observer_extra_outputs'])}",
    ]
    return "\n".join(lines)


def parse_candidates(outputs: str | None, unknown: str | None):
    """`--outputs a,b[;c,d]` and `--unknown`: the candidates to analyse (default: all of CANDIDATES)."""
    if not outputs:
        return list(CANDIDATES)
    cands = []
    seen = set()  # (the set of signals, unknown inputs): the same system whatever the order, analysed once
    for group in outputs.split(";"):
        outs = tuple(x.strip() for x in group.split(",") if x.strip())
        for o in outs:
            if o not in us.OUTPUT_NAMES:
                raise ValueError(f"--outputs: unknown signal {o!r}; choose from {', '.join(us.OUTPUT_NAMES)}")
        if len(set(outs)) != len(outs):  # a signal twice is a rank-deficient output matrix, not a sensor set
            raise ValueError(f"--outputs {group}: a signal named twice")
        kinds = [unknown] if unknown else ([us.UI_PHI_TAU] if len(outs) == 2 else [us.UI_TAU, UI_TAU_STATE])
        for k in kinds:
            need = 2 if k == us.UI_PHI_TAU else 1
            if len(outs) != need:
                raise ValueError(f"--outputs {group}: unknown inputs {k} need {need} output(s) (square system)")
            if (frozenset(outs), k) not in seen:
                seen.add((frozenset(outs), k))
                cands.append((outs, k))
    return cands


def run_analyze_outputs(args) -> int:
    """`ptw-rt analyze --outputs ...`: the table of candidate output sets."""
    from ptw_rt.errors import UserFacingError
    from ptw_rt.model.parameters import load_vehicle
    from ptw_rt.output import emit

    p = load_vehicle(args.config)
    try:
        cands = parse_candidates(None if args.outputs == "all" else args.outputs, args.unknown)
    except ValueError as exc:
        raise UserFacingError(str(exc)) from None
    result = analyze_outputs(p, cands, args.speeds or list(DEFAULT_SPEEDS_KMH))
    title = f"Output sets of '{p.name}' ({args.config}): strong detectability, relative degree, derivatives\n"
    emit(result, args.json, title + format_outputs_table(result))
    return 0
