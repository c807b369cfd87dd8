"""Design of the UIHOSMO on a chosen set of the scooter's real sensors (issue #16), over the speed grid.

Seed 000 case 2 (`ptw_rt/design/uihosmo.py`) measures [steer, yaw rate] and reconstructs roll from the
yaw acceleration: phi enters r' through the roll-yaw inertia coupling only (0.91 rad/s^2 per rad), so
0.1 rad/s^2 of error in r' is 6 deg of roll, and it needs e_delta'' from a 10-bit encoder. This module
designs the same observer (seed 000 eq. 11-15: pre-observer, normal form, zero dynamics, eq. 15
reconstruction) for any *square* set of outputs taken from

    steer delta, ground yaw rate r, roll rate phi_dot, lateral acceleration a_y = (F_yf + F_yr) / M

with either the unknown inputs zeta = [phi, tau] (roll removed from the state as in seed 000 sec. III-A)
or zeta = tau with the roll as a *measured* input (the kinematic attitude filter's roll): both on the
reduced state [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr].

    x' = A(u) x + D(u) zeta + B_w(u) w,      y = C x         (w = phi when the roll is measured)
    z' = A z + B_w w + L (y - C z),  e = x - z:  e' = At e + D zeta,   At = A - L C

Normal form: xi_1 = [C_i At^k e, k < rho_i] per output (rho_i its relative degree), xi_2 = T2 e with
T2 D = 0 (the zero dynamics, eigenvalues = the invariant zeros), and eq. 15 with the top row of each
output: zeta = Dbar^-1 ([d/dt xi_1,top] - Abar xi). The differentiator on output i has order rho_i + 1
and supplies e_i ... e_i^(rho_i): the highest derivative of each measured signal the reconstruction
needs is its relative degree (`ptw_rt/design/output_sets.py` tabulates them for every candidate).

Offline only (scipy); the runtime is `ptw_rt/core/uio_sensors.py`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ptw_rt.design.discretize import ramp_response, spectral_radius, zoh
from ptw_rt.design.kalman import FORCE_ROWS
from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import (
    PHI,
    R_DELTA,
    R_FYF,
    R_FYR,
    R_PHI_DOT,
    R_R,
    descriptor,
    state_space,
)

N_X = 7  # reduced state [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr]
MAX_OUT = 2  # square sets of at most 2 outputs (2 unknown inputs)
MAX_XI1 = 4  # sum of relative degrees (each <= 2)

# measured signals: name -> index in the runtime's measurement vector (core.uio_sensors M_*)
OUTPUT_NAMES = ("steer", "yaw_rate", "roll_rate", "lat_accel")
OUTPUT_CODES = {"steer": 0, "yaw_rate": 1, "roll_rate": 2, "lat_accel": 3}
SHORT = {"steer": "delta", "yaw_rate": "r", "roll_rate": "phi_dot", "lat_accel": "a_y"}
# unknown-input configurations
UI_PHI_TAU = "phi_tau"  # zeta = [phi, tau], roll not used as a measurement
UI_TAU = "tau"  # zeta = tau, the roll is a measured input

# The set the product runs (docs/estimator.md, "UIHOSMO on the real sensors"): rider torque as the unknown input,
# roll measured (the kinematic attitude filter), reconstruction from the steer error's second derivative,
# and a pre-observer that injects every output the scooter has.
CHOSEN_OUTPUTS = ("steer",)
CHOSEN_UNKNOWN = UI_TAU
CHOSEN_EXTRA = ("yaw_rate", "roll_rate", "lat_accel")
CHOSEN_LIPSCHITZ = (2.0,)  # rad/s^4 on the steer error (measured best of 1-20 on the evaluation rides)
# The pre-observer's Riccati weights (its own, not case 2's `estimator.uihosmo.output_weight`): how much each
# injected output is trusted, as a typical error per output (a larger one = a smaller gain). Chosen on
# 2026-11-25 over the nominal rides and their x0.7 / mu 0.85 / +50 kg variants (docs/estimator.md, "The chosen
# set"): trusting a_y and the steer more (output weight 0.1 -> 0.01) lets the tyre-force states follow the
# measured lateral acceleration where the linear tyres are wrong; the yaw rate, trusted at 0.1 rad/s, then pulled
# the front/rear split of those forces towards the linear model's in long corners (1 rad/s: barely used).
CHOSEN_OUTPUT_WEIGHT = 0.01
CHOSEN_INJECTION_SCALE = {"steer": 0.01, "yaw_rate": 1.0, "roll_rate": 0.1, "lat_accel": 1.0}

# Typical magnitudes (scaling of the Riccati design and of the condition numbers): state as in uihosmo.py,
# outputs one typical manoeuvre amplitude each.
STATE_SCALE = np.array([0.01, 0.3, 0.1, 0.3, 0.1, 500.0, 500.0])
OUTPUT_SCALE = {"steer": 0.01, "yaw_rate": 0.1, "roll_rate": 0.1, "lat_accel": 1.0}


def output_row(p: VehicleParameters, name: str) -> np.ndarray:
    c = np.zeros(N_X)
    if name == "steer":
        c[R_DELTA] = 1.0
    elif name == "yaw_rate":
        c[R_R] = 1.0
    elif name == "roll_rate":
        c[R_PHI_DOT] = 1.0
    elif name == "lat_accel":
        # total lateral tyre force over the mass: the centre of mass' lateral acceleration (no feedthrough of
        # tau or phi in Sharp's model: the tyre forces are states, relaxed with sigma/u)
        c[R_FYF] = c[R_FYR] = 1.0 / p.mass
    else:
        raise ValueError(f"unknown output {name!r}; choose from {', '.join(OUTPUT_NAMES)}")
    return c


@dataclass(frozen=True)
class SensorSystem:
    """x' = A x + D zeta + Bw w, y = C x on the reduced state."""

    A: np.ndarray
    D: np.ndarray  # (7, m)
    Bw: np.ndarray  # (7,) known input (roll) or zeros
    C: np.ndarray  # (p, 7)
    Bd: np.ndarray  # (7, 4) the nonlinear rows' correction d (core.kalman.nonlinear_correction), a known input


def sensor_system(p: VehicleParameters, u: float, outputs: tuple[str, ...], unknown: str) -> SensorSystem:
    A, B = state_space(p, u)
    A_p, phi_col, tau_col = A[1:, 1:].copy(), A[1:, PHI].copy(), B[1:].copy()
    C = np.array([output_row(p, o) for o in outputs])
    Bd = np.linalg.inv(descriptor(p).E)[1:, FORCE_ROWS]
    if unknown == UI_PHI_TAU:
        return SensorSystem(A_p, np.column_stack([phi_col, tau_col]), np.zeros(N_X), C, Bd)
    if unknown == UI_TAU:
        return SensorSystem(A_p, tau_col[:, None], phi_col, C, Bd)
    raise ValueError(f"unknown inputs must be {UI_PHI_TAU!r} or {UI_TAU!r}, got {unknown!r}")


def relative_degrees(sys: SensorSystem, tol: float = 1e-9) -> list[int]:
    """Relative degree of each output with respect to the whole unknown-input vector (0: none up to n)."""
    out = []
    dn = np.linalg.norm(sys.D)
    for c in sys.C:
        row, deg = c.copy(), 0
        for k in range(1, N_X + 1):
            if np.linalg.norm(row @ sys.D) > tol * np.linalg.norm(row) * dn:
                deg = k
                break
            row = row @ sys.A
        out.append(deg)
    return out


def luenberger_gain(
    sys: SensorSystem, outputs: tuple[str, ...], decay_rate: float, output_weight: float, output_scale=OUTPUT_SCALE
):
    """Shifted-Riccati gain (every error pole left of -decay_rate), as for case 2 (`uihosmo.luenberger_gain`);
    `output_scale`: the typical error of each output (the weights of the outputs relative to each other)."""
    S = np.diag(STATE_SCALE)
    W = np.diag([output_scale[o] for o in outputs])
    A_s = np.linalg.solve(S, sys.A @ S)
    C_s = np.linalg.solve(W, sys.C @ S)
    n, m = A_s.shape[0], C_s.shape[0]
    X = sla.solve_continuous_are((A_s + decay_rate * np.eye(n)).T, C_s.T, np.eye(n), output_weight * np.eye(m))
    return S @ (X @ C_s.T / output_weight) @ np.linalg.inv(W)


def xi1_rows(C: np.ndarray, At: np.ndarray, degrees: list[int]) -> np.ndarray:
    rows = []
    for c, r in zip(C, degrees, strict=True):
        row = c.copy()
        for _ in range(r):
            rows.append(row)
            row = row @ At
    return np.array(rows)


def complement_rows(D: np.ndarray, rows: tuple[int, ...]) -> np.ndarray:
    proj = np.eye(D.shape[0]) - D @ np.linalg.pinv(D)
    return proj[list(rows), :]


def choose_complement_rows(systems: list[SensorSystem], degrees: list[int]) -> tuple[int, ...]:
    """Coordinate rows of T2 giving the best-conditioned T over the grid (fixed per vehicle: continuity)."""
    n2 = N_X - sum(degrees)
    best, best_score = None, np.inf
    for rows in itertools.combinations(range(N_X), n2):
        score = 0.0
        for sys in systems:
            T = np.vstack([xi1_rows(sys.C, sys.A, degrees), complement_rows(sys.D, rows)]) * STATE_SCALE
            T = T / np.linalg.norm(T, axis=1, keepdims=True)
            score = max(score, np.linalg.cond(T))
        if score < best_score:
            best, best_score = rows, score
    if best is None or not np.isfinite(best_score) or best_score > 1e12:
        raise ValueError("no complement of the unknown-input directions gives an invertible transformation")
    return best


def invariant_zeros(sys: SensorSystem, scale: np.ndarray | None = None, largest: float = 1e9) -> np.ndarray:
    """Finite zeros of the square triple (A, D, C), in scaled coordinates (forces are 1e4 x the angles):
    the generalised eigenvalues of the Rosenbrock pencil, those beyond `largest` (infinite zeros) dropped."""
    S = np.diag(STATE_SCALE if scale is None else scale)
    A = np.linalg.solve(S, sys.A @ S)
    D = np.linalg.solve(S, sys.D)
    C = sys.C @ S
    C = C / np.linalg.norm(C, axis=1, keepdims=True)
    n, m = D.shape
    pa = np.block([[A, D], [C, np.zeros((C.shape[0], m))]])
    pb = np.zeros((n + m, n + m))
    pb[:n, :n] = np.eye(n)
    v = sla.eig(pa, pb, right=False)
    v = v[np.isfinite(v) & (np.abs(v) < largest)]
    return v[np.lexsort((v.imag, v.real))]


def detectable_at(p: VehicleParameters, u: float, outputs: tuple[str, ...], unknown: str) -> bool:
    sys = sensor_system(p, u, outputs, unknown)
    z = invariant_zeros(sys)
    return bool(z.size == 0 or np.all(z.real < 0))


def detectability_floor(p, outputs, unknown, lo: float = 0.5, hi: float = 40.0, tol: float = 1e-3) -> float:
    """Lowest speed [m/s] above which the set is strongly detectable (bisection; assumes one crossing)."""
    if not detectable_at(p, hi, outputs, unknown):
        raise ValueError(f"{'+'.join(outputs)} is not strongly detectable at {hi * 3.6:.0f} km/h")
    if detectable_at(p, lo, outputs, unknown):
        return lo
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if detectable_at(p, mid, outputs, unknown) else (mid, hi)
    return hi


def _floor(stable, lo: float, hi: float, tol: float = 1e-3) -> float:
    """Lowest speed in [lo, hi] above which `stable(u)` holds (bisection; one crossing assumed)."""
    if not stable(hi):
        raise ValueError(f"the zero dynamics are unstable at {hi * 3.6:.0f} km/h")
    if stable(lo):
        return lo
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if stable(mid) else (mid, hi)
    return hi


@dataclass(frozen=True)
class SensorUioPoint:
    speed: float
    L: np.ndarray  # (7, p)
    T: np.ndarray  # (7, 7)
    T_inv: np.ndarray
    Abar: np.ndarray  # (m, 7)
    Dbar_inv: np.ndarray  # (m, m)
    A22: np.ndarray
    Phi: np.ndarray  # (7, 7) ZOH of At
    Gamma: np.ndarray  # (7, p + 5): ZOH input matrix of [y, w, d] (columns L, Bw, Bd)
    Ramp: np.ndarray  # (7, p + 5): first-order hold of [y, w, d], times the step's increment / dt
    Phi22: np.ndarray
    Gamma21: np.ndarray  # (n2, n1)
    Ramp21: np.ndarray  # (n2, n1) times d/dt theta_1


def design_point(
    p: VehicleParameters,
    u: float,
    outputs: tuple[str, ...],
    observed: tuple[str, ...],
    unknown: str,
    degrees: list[int],
    rows: tuple[int, ...],
    decay_rate: float,
    output_weight: float,
    dt: float,
    detectable: bool,
    injection_scale=OUTPUT_SCALE,
) -> SensorUioPoint:
    sys = sensor_system(p, u, outputs, unknown)
    obs = sensor_system(p, u, observed, unknown)
    L = luenberger_gain(obs, observed, decay_rate, output_weight, injection_scale)
    At = sys.A - L @ obs.C
    T = np.vstack([xi1_rows(sys.C, At, degrees), complement_rows(sys.D, rows)])
    T_inv = np.linalg.inv(T)
    A_xi = T @ At @ T_inv
    D_xi = T @ sys.D
    tops = list(np.cumsum(degrees) - 1)
    n1 = sum(degrees)
    Abar, Dbar = A_xi[tops, :], D_xi[tops, :]
    A21, A22 = A_xi[n1:, :n1], A_xi[n1:, n1:]
    inputs = np.column_stack([L, sys.Bw, sys.Bd])
    Phi, Gamma = zoh(At, inputs, dt)
    Ramp = ramp_response(At, inputs, dt) / dt
    if detectable:
        Phi22, Gamma21 = zoh(A22, A21, dt)
        Ramp21 = ramp_response(A22, A21, dt)
    else:  # unstable zero dynamics: hold theta_2 at zero (the runtime flags the speed as invalid)
        Phi22, Gamma21, Ramp21 = np.zeros_like(A22), np.zeros_like(A21), np.zeros_like(A21)
    return SensorUioPoint(u, L, T, T_inv, Abar, np.linalg.inv(Dbar), A22, Phi, Gamma, Ramp, Phi22, Gamma21, Ramp21)


@dataclass(frozen=True)
class SensorUioDesign:
    outputs: tuple[str, ...]  # reconstruction outputs (square with the unknown inputs)
    observed: tuple[str, ...]  # all outputs of the pre-observer: `outputs` first, then the extra ones
    unknown: str
    degrees: list[int]
    complement_rows: tuple[int, ...]
    detectability_floor: float  # m/s
    detectable: np.ndarray  # (G,) bool
    points: list[SensorUioPoint]

    @property
    def spectral_radius(self) -> float:
        return max(max(spectral_radius(pt.Phi), spectral_radius(pt.Phi22)) for pt in self.points)


def design_grid(
    p: VehicleParameters,
    speeds: np.ndarray,
    outputs: tuple[str, ...],
    unknown: str,
    decay_rate: float,
    output_weight: float,
    dt: float,
    extra: tuple[str, ...] = (),
    injection_scale=OUTPUT_SCALE,
) -> SensorUioDesign:
    """`extra`: outputs the pre-observer uses beyond the reconstruction outputs (their injection moves the
    zero dynamics: the eigenvalues of A22 are then the zeros of (A - L C_all, D, C), checked per speed);
    `injection_scale`: the typical error of each output in the pre-observer's Riccati design."""
    observed = tuple(outputs) + tuple(o for o in extra if o not in outputs)
    m = 2 if unknown == UI_PHI_TAU else 1
    if len(outputs) != m:
        raise ValueError(f"a square design needs {m} output(s) for unknown inputs {unknown!r}, got {outputs}")
    systems = [sensor_system(p, float(u), outputs, unknown) for u in speeds]
    degrees = relative_degrees(systems[0])
    if any(d == 0 for d in degrees) or sum(degrees) > MAX_XI1:
        raise ValueError(f"relative degrees {degrees} of {outputs} are not supported (1..2 each)")
    for s in systems[1:]:
        if relative_degrees(s) != degrees:
            raise ValueError(f"the relative degrees of {outputs} change with speed")
    rows = choose_complement_rows(systems, degrees)

    def zero_dynamics_stable(u: float) -> bool:
        pt = design_point(
            p, u, outputs, observed, unknown, degrees, rows, decay_rate, output_weight, dt, False, injection_scale
        )
        return bool(np.all(np.linalg.eigvals(pt.A22).real < 0))

    floor = _floor(zero_dynamics_stable, float(speeds[0]), float(speeds[-1]))
    ok = speeds >= floor
    points = [
        design_point(
            p,
            float(u),
            outputs,
            observed,
            unknown,
            degrees,
            rows,
            decay_rate,
            output_weight,
            dt,
            bool(d),
            injection_scale,
        )
        for u, d in zip(speeds, ok, strict=True)
    ]
    return SensorUioDesign(tuple(outputs), observed, unknown, degrees, rows, floor, ok, points)


def design_fields(
    p: VehicleParameters, d: SensorUioDesign, min_valid_speed: float, lipschitz=CHOSEN_LIPSCHITZ
) -> dict[str, object]:
    """The `us_*` fields of `DesignData`."""
    pts = d.points
    return {
        "us_outputs": np.array([OUTPUT_CODES[o] for o in d.outputs], dtype=np.int64),
        "us_observed": np.array([OUTPUT_CODES[o] for o in d.observed], dtype=np.int64),
        "us_degrees": np.array(d.degrees, dtype=np.int64),
        "us_roll_input": int(d.unknown == UI_TAU),
        "us_lipschitz": np.array(lipschitz, dtype=np.float64),
        "us_min_valid_speed": float(max(min_valid_speed, d.detectability_floor)),
        "us_detectability_floor": float(d.detectability_floor),
        "us_mass": float(p.mass),
        "us_C": np.array([output_row(p, o) for o in d.observed]),
        "us_Phi": np.array([pt.Phi for pt in pts]),
        "us_Gamma": np.array([pt.Gamma for pt in pts]),
        "us_Ramp": np.array([pt.Ramp for pt in pts]),
        "us_T_inv": np.array([pt.T_inv for pt in pts]),
        "us_Abar": np.array([pt.Abar for pt in pts]),
        "us_Dbar_inv": np.array([pt.Dbar_inv for pt in pts]),
        "us_Phi22": np.array([pt.Phi22 for pt in pts]),
        "us_Gamma21": np.array([pt.Gamma21 for pt in pts]),
        "us_Ramp21": np.array([pt.Ramp21 for pt in pts]),
    }
