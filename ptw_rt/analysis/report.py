"""`ptw-rt analyze`: modes, invariant zeros and relative degree over forward speed."""

from __future__ import annotations

from typing import Any

import numpy as np

from ptw_rt.analysis.modes import classify_modes
from ptw_rt.analysis.observability import decoupling_matrix, invariant_zeros, relative_degree
from ptw_rt.model.parameters import VehicleParameters, load_vehicle
from ptw_rt.model.sharp import case1, case2, full_system, kmh, state_space
from ptw_rt.output import emit


def _pairs(values: np.ndarray) -> list[list[float]]:
    return [[float(v.real), float(v.imag)] for v in values]


def analyze_speed(p: VehicleParameters, speed_kmh: float) -> dict[str, Any]:
    u = kmh(speed_kmh)
    A, _ = state_space(p, u)
    eigenvalues = np.linalg.eigvals(A)
    eigenvalues = eigenvalues[np.lexsort((eigenvalues.imag, eigenvalues.real))]
    sys2 = case2(p, u)
    degrees = relative_degree(sys2)
    modes = classify_modes(eigenvalues, u, (p.sigma_f, p.sigma_r))
    return {
        "speed_kmh": speed_kmh,
        "eigenvalues": _pairs(eigenvalues),
        "modes": [
            {
                "name": m.name,
                "eigenvalue": [m.eigenvalue.real, m.eigenvalue.imag],
                "frequency_hz": m.frequency_hz,
                "damping_ratio": m.damping_ratio,
                "stable": m.stable,
            }
            for m in modes
        ],
        "zeros": {
            "full": _pairs(invariant_zeros(full_system(p, u))),
            "case1": _pairs(invariant_zeros(case1(p, u))),
            "case2": _pairs(invariant_zeros(sys2)),
        },
        "relative_degree_case2": degrees,
        "decoupling_det": float(np.linalg.det(decoupling_matrix(sys2, degrees))),
    }


def analyze(p: VehicleParameters, speeds_kmh: list[float]) -> dict[str, Any]:
    return {"speeds_kmh": list(speeds_kmh), "results": [analyze_speed(p, v) for v in speeds_kmh]}


def _fmt(v: list[float]) -> str:
    re, im = v
    return f"{re:8.2f}" if abs(im) < 1e-9 else f"{re:7.2f}±{abs(im):.2f}j"


def format_table(result: dict[str, Any]) -> str:
    lines = []
    for r in result["results"]:
        lines.append(f"== {r['speed_kmh']:g} km/h ==")
        lines.append(f"  {'mode':<16} {'eigenvalue [1/s]':>20} {'freq [Hz]':>10} {'damping':>8}  stability")
        for m in sorted(r["modes"], key=lambda m: -m["frequency_hz"]):
            lines.append(
                f"  {m['name']:<16} {_fmt(m['eigenvalue']):>20} {m['frequency_hz']:10.2f} {m['damping_ratio']:8.3f}  "
                + ("stable" if m["stable"] else "UNSTABLE")
            )
        for key, label in (
            ("full", "zeros full (y=delta, d=tau)"),
            ("case1", "zeros case 1 (d=phi)"),
            ("case2", "zeros case 2 (d=[phi,tau], y=[delta,r])"),
        ):
            zs = r["zeros"][key]
            worst = max(z[0] for z in zs) if zs else float("nan")
            verdict = "minimum phase" if worst < 0 else "NON-minimum phase"
            zeros_text = ", ".join(_fmt(z).strip() for z in zs if z[1] >= 0)
            lines.append(f"  {label:<40} max Re {worst:7.2f} ({verdict}): {zeros_text}")
        lines.append(f"  case 2 relative degree {r['relative_degree_case2']}, decoupling det {r['decoupling_det']:.4g}")
    return "\n".join(lines)


def run_analyze(args) -> int:
    p = load_vehicle(args.config)
    result = analyze(p, args.speeds or [20, 50, 80, 100, 120])
    emit(result, args.json, f"Lateral model of '{p.name}' ({args.config})\n" + format_table(result))
    return 0
