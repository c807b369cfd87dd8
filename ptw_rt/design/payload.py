"""`ptw-rt analyze --payload KG`: can the sensors tell a payload from softer tyres? (docs/estimator.md, "The payload")

Sharp's linear model with the rider's torque unknown, as every filter here has it. Vehicle A (the file with a
payload) drives the sensors' outputs (`ptw_rt.model.sharp.SENSOR_OUTPUTS`) with a rider's torque; vehicle B (the
file, its four stiffnesses times k) explains them with whatever torque history fits them best (least squares over
the whole ride). The residual's chi-square in the fusion filters' own measurement noise is the log-likelihood ratio
(x2) that a filter with an exact model would gather for A against B: what the data say about the mass beyond the
tyres per unit mass (C/m). Its minimum over k, against the chi-square by which the same ride tells the file's tyres
from tyres `VALID_TOLERANCE` softer, measures how well the mass could be learned at best. Offline only (scipy).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from ptw_rt.design.discretize import zoh
from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import SENSOR_OUTPUTS, kmh, sensor_outputs, state_space
from ptw_rt.settings import KalmanTuning

DT = 0.01  # s, the loop's step
DURATION = 10.0  # s of riding compared
RAMP = 2.0  # s over which the manoeuvre's torque fades in (no step at the start)
# the rider's torque: a manoeuvre's tone (a slalom's 0.28 Hz at 30 km/h) and a busy rider's band
MANOEUVRE_NM = 10.0
BUSY_NM = 2.0  # RMS
BUSY_BAND_HZ = (0.1, 3.0)
# (speed km/h, the manoeuvre's frequency Hz): `slalom_30`, `dlc_50`'s pace, `handling_40_120` at speed
RIDES = ((30.0, 0.28), (60.0, 0.5), (100.0, 0.3))
SCALE_SEARCH = (0.6, 1.2)  # the tyre scales k searched for vehicle B
VALID_TOLERANCE = 0.15  # the stiffness VALID's promise (issue #12): the reference tyres are this much softer
# how the payload is built: a point mass at the rear frame's centre of mass (the simulator's `added_mass`: it adds no
# inertia about the model's reference point), or the rear frame, which holds the file's rider, grown (a heavier
# rider of the same build: its roll, yaw and cross inertias times its mass's ratio)
PAYLOAD_MODELS = ("point_mass", "rear_frame_grown")


def markov_parameters(p: VehicleParameters, u: float, n: int) -> np.ndarray:
    """(n, outputs): the outputs k + 1 steps after a unit torque held for one step (zero-order hold, exact)."""
    Ad, Bd = zoh(*state_space(p, u), DT)
    C = sensor_outputs(p)
    h = np.empty((n, C.shape[0]))
    x = Bd.copy()
    for k in range(n):
        h[k] = C @ x
        x = Ad @ x
    return h


def response_matrix(p: VehicleParameters, u: float, n: int, noise: np.ndarray) -> np.ndarray:
    """(n * outputs, n): the whitened outputs of n steps as a linear function of the n torques (from rest)."""
    h = markov_parameters(p, u, n) / noise
    T = np.zeros((n, h.shape[1], n))
    for k in range(n - 1):
        T[k + 1 :, :, k] = h[: n - k - 1]
    return T.reshape(n * h.shape[1], n)


def rider_torque(n: int, frequency_hz: float, seed: int = 0) -> np.ndarray:
    """A manoeuvre's tone faded in over RAMP, plus a busy rider's band-limited torque (N m)."""
    t = np.arange(n) * DT
    busy = np.random.default_rng(seed).standard_normal(n)
    spectrum = np.fft.rfft(busy)
    f = np.fft.rfftfreq(n, DT)
    spectrum[(f < BUSY_BAND_HZ[0]) | (f > BUSY_BAND_HZ[1])] = 0.0
    busy = np.fft.irfft(spectrum, n)
    busy *= BUSY_NM / busy.std()
    return MANOEUVRE_NM * np.sin(2.0 * math.pi * frequency_hz * t) * np.minimum(t / RAMP, 1.0) + busy


def unexplained(y: np.ndarray, T_b: np.ndarray, outputs: int) -> np.ndarray:
    """Per output: the chi-square of what no torque history through T_b explains of the whitened outputs y."""
    torque, *_ = np.linalg.lstsq(T_b, y, rcond=None)
    r = (y - T_b @ torque).reshape(-1, outputs)
    return (r * r).sum(axis=0)


def loaded(p: VehicleParameters, added_mass: float, model: str) -> VehicleParameters:
    """The file's vehicle with a payload, as PAYLOAD_MODELS says it is built."""
    q = p.with_added_mass(added_mass)
    if model == "point_mass":
        return q
    grown = q.m_r / p.m_r  # the rear frame (the file's rider in it) of the same build, heavier
    return replace(q, i_rx=p.i_rx * grown, i_rz=p.i_rz * grown, c_rxz=p.c_rxz * grown)


def compare(
    p: VehicleParameters,
    a: VehicleParameters,
    speed_kmh: float,
    frequency_hz: float,
    noise: np.ndarray,
    duration: float = DURATION,
) -> dict[str, Any]:
    """One ride of vehicle a: its chi-square against the file on the file's tyres and on the best-fitting tyre
    scale, and the reference (the file's tyres against tyres VALID_TOLERANCE softer, on the file's mass)."""
    u = kmh(speed_kmh)
    n = int(round(duration / DT))
    tau = rider_torque(n, frequency_hz)
    outputs = len(SENSOR_OUTPUTS)
    y = response_matrix(a, u, n, noise) @ tau

    def chi2(k: float) -> float:
        return float(unexplained(y, response_matrix(p.scaled(stiffness=k), u, n, noise), outputs).sum())

    best = minimize_scalar(chi2, bounds=SCALE_SEARCH, method="bounded", options={"xatol": 1e-3})
    k = float(best.x)
    parts = unexplained(y, response_matrix(p.scaled(stiffness=k), u, n, noise), outputs)
    T_file = response_matrix(p, u, n, noise)  # the file's tyres: what vehicle a is told from, and the reference's
    T_soft = response_matrix(p.scaled(stiffness=1.0 - VALID_TOLERANCE), u, n, noise)
    reference = float(unexplained(T_file @ tau, T_soft, outputs).sum())
    return {
        "speed_kmh": speed_kmh,
        "manoeuvre_hz": frequency_hz,
        "chi2_file_tyres": round(float(unexplained(y, T_file, outputs).sum()), 1),
        "best_tyre_scale": round(k, 3),
        "chi2_best_tyres": round(float(parts.sum()), 1),
        "chi2_best_tyres_per_output": {name: round(float(v), 1) for name, v in zip(SENSOR_OUTPUTS, parts, strict=True)},
        "chi2_reference": round(reference, 1),
        # the tyre error whose chi-square the payload's signature beyond C/m matches (chi-square ~ error^2)
        "equivalent_tyre_error_pct": round(100.0 * VALID_TOLERANCE * math.sqrt(float(parts.sum()) / reference), 1),
    }


def payload_study(p: VehicleParameters, tuning: KalmanTuning, added_mass: float, rides=RIDES) -> dict[str, Any]:
    noise = np.array(tuning.measurement_sd())
    return {
        "vehicle": p.name,
        "mass_kg": round(p.mass, 2),
        "added_mass_kg": added_mass,
        "duration_s": DURATION,
        "noise": {name: float(v) for name, v in zip(SENSOR_OUTPUTS, noise, strict=True)},
        "reference": f"the file's tyres against tyres x{1.0 - VALID_TOLERANCE:g}, the file's mass",
        "models": {
            model: [compare(p, loaded(p, added_mass, model), v, f, noise) for v, f in rides] for model in PAYLOAD_MODELS
        },
    }


def format_study(result: dict[str, Any]) -> str:
    lines = [
        f"'{result['vehicle']}' ({result['mass_kg']} kg) with {result['added_mass_kg']:+g} kg against the file's mass"
        f" on tyres x k; {result['duration_s']:g} s of riding, the rider's torque unknown; chi-square in the fusion"
        " filters' measurement noise (reference: " + result["reference"] + ")",
    ]
    head = ("km/h", "Hz", "file tyres", "best k", "at best k", "reference", "as tyres")
    for model, rides in result["models"].items():
        lines += [f"payload: {model}", " ".join(f"{h:>10}" for h in head) + "  at best k, per output"]
        for r in rides:
            row = (
                f"{r['speed_kmh']:.0f}",
                f"{r['manoeuvre_hz']:.2f}",
                f"{r['chi2_file_tyres']:.1f}",
                f"{r['best_tyre_scale']:.3f}",
                f"{r['chi2_best_tyres']:.1f}",
                f"{r['chi2_reference']:.1f}",
                f"{r['equivalent_tyre_error_pct']:.1f} %",
            )
            per = ", ".join(f"{k} {v:g}" for k, v in r["chi2_best_tyres_per_output"].items())
            lines.append(" ".join(f"{c:>10}" for c in row) + f"  {per}")
    return "\n".join(lines)


def run_analyze_payload(args) -> int:
    from ptw_rt.errors import UserFacingError
    from ptw_rt.output import emit
    from ptw_rt.settings import load_settings

    settings = load_settings(args.config)
    try:
        result = payload_study(settings.vehicle, settings.estimator.kalman, args.payload)
    except ValueError as exc:  # a payload the vehicle cannot take (`VehicleParameters.with_added_mass`)
        raise UserFacingError(f"{args.config}: --payload {args.payload:g}: {exc}") from None
    emit(result, args.json, format_study(result))
    return 0
