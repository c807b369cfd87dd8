"""Design of the unknown-input HOSM observer, seed 000 case 2, over the speed grid.

System (roll removed from the state): x' = A(u) x + D(u) zeta,  y = [delta, r] = C x,
zeta = [phi, tau]. Vector relative degree [2, 1], four stable invariant zeros.

Observer (eq. 12):  z' = A z + L (y - C z);  e = x - z obeys e' = At e + D zeta with At = A - L C.
Coordinates xi = T e separate what the unknown inputs reach (eq. 11):

    xi_1 = [C1 e, C1 At e, C2 e]      output error and its derivatives (exactly estimable)
    xi_2 = T2 e,  T2 D = 0            zero dynamics, driven only by xi_1: xi_2' = A21 xi_1 + A22 xi_2

The eigenvalues of A22 are the invariant zeros. T2 is the projection of
fixed coordinate rows onto the left null space of D, which varies continuously
with speed, so the observer state theta_2 keeps its meaning when the gains
are interpolated between grid points (a basis from an SVD would flip and
rotate from one grid point to the next).

Reconstruction (eq. 15): [phi, tau] = Dbar^-1 ([d/dt xi_12, d/dt xi_13] - Abar theta).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ptw_rt.analysis.observability import invariant_zeros
from ptw_rt.design.discretize import ramp_response, spectral_radius, zoh
from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import UnknownInputSystem, case2

N_X = 7  # reduced state [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr]
N_XI1 = 3  # r1 + r2
N_XI2 = N_X - N_XI1

# Typical magnitudes of the reduced state and of the outputs in a brisk manoeuvre.
# They condition the numerics (in SI units tyre forces are 1e4 times the angles)
# and are the Riccati weights: an error of one typical magnitude costs the same in
# every state.
STATE_SCALE = np.array([0.01, 0.3, 0.1, 0.3, 0.1, 500.0, 500.0])
OUTPUT_SCALE = np.array([0.01, 0.1])


@dataclass(frozen=True)
class UihosmoPoint:
    """Everything the runtime needs at one grid speed (continuous and discrete)."""

    speed: float
    L: np.ndarray  # (7, 2) Luenberger gain
    T: np.ndarray  # (7, 7) xi = T e
    T_inv: np.ndarray
    A_xi: np.ndarray  # (7, 7) T At T^-1
    Abar: np.ndarray  # (2, 7) rows of A_xi driving xi_12 and xi_13
    Dbar: np.ndarray  # (2, 2) decoupling matrix in xi coordinates
    Dbar_inv: np.ndarray
    A21: np.ndarray  # (4, 3)
    A22: np.ndarray  # (4, 4)
    Phi: np.ndarray  # (7, 7) ZOH of At
    Gamma: np.ndarray  # (7, 2) ZOH input matrix of L y
    Phi22: np.ndarray  # (4, 4) ZOH of A22
    Gamma21: np.ndarray  # (4, 3) ZOH input matrix of theta_1
    Ramp_y: np.ndarray  # (7, 2) first-order hold of y: times (y[k] - y[k-1])
    Ramp21: np.ndarray  # (4, 3) ramp of theta_1 within the step: times d/dt theta_1

    @property
    def spectral_radius(self) -> float:
        return max(spectral_radius(self.Phi), spectral_radius(self.Phi22))


def luenberger_gain(sys: UnknownInputSystem, decay_rate: float, output_weight: float) -> np.ndarray:
    """Observer gain with every error pole left of -decay_rate: the shifted-Riccati (LQE) gain.

    Why not the paper's pole placement: with two outputs the placing gain is not
    unique, and both KNV and Tits-Yang jump between solution branches as speed
    changes (measured: 400 % gain change between 76 and 76.5 km/h), so gains
    interpolated between grid points would be meaningless. The stabilising
    Riccati solution is unique and analytic in speed; the shift keeps the
    paper's slowest error pole (-15 1/s) as a bound, and the open-loop fast
    tyre modes are left where they are instead of being pushed beyond 1/dt.
    Solved in scaled coordinates with identity state weight.
    """
    S, W = np.diag(STATE_SCALE), np.diag(OUTPUT_SCALE)
    A_s = np.linalg.solve(S, sys.A @ S)
    C_s = np.linalg.solve(W, sys.C @ S)
    n, m = A_s.shape[0], C_s.shape[0]
    X = sla.solve_continuous_are((A_s + decay_rate * np.eye(n)).T, C_s.T, np.eye(n), output_weight * np.eye(m))
    return S @ (X @ C_s.T / output_weight) @ np.linalg.inv(W)


def complement_rows(D: np.ndarray, rows: tuple[int, ...]) -> np.ndarray:
    """T2: the chosen unit rows projected onto the left null space of D (so T2 D = 0)."""
    proj = np.eye(D.shape[0]) - D @ np.linalg.pinv(D)
    return proj[list(rows), :]


def transformation(sys: UnknownInputSystem, L: np.ndarray, rows: tuple[int, ...]) -> np.ndarray:
    At = sys.A - L @ sys.C
    c1, c2 = sys.C[0], sys.C[1]
    return np.vstack([c1, c1 @ At, c2, complement_rows(sys.D, rows)])


TIE_RTOL = 1e-9  # choose_complement_rows: condition numbers closer than this are a tie


def choose_complement_rows(systems: list[UnknownInputSystem]) -> tuple[int, ...]:
    """The 4 coordinate rows giving the best-conditioned T over the whole grid (decided once per vehicle)."""
    best, best_score = None, np.inf
    for rows in itertools.combinations(range(N_X), N_XI2):
        score = 0.0
        for sys in systems:
            # Conditioning of T does not depend on L's contribution to row 2 enough to matter
            # for the choice; use the open-loop rows.
            T = np.vstack([sys.C[0], sys.C[0] @ sys.A, sys.C[1], complement_rows(sys.D, rows)])
            T = T * STATE_SCALE
            scale = np.linalg.norm(T, axis=1, keepdims=True)
            score = max(score, np.linalg.cond(T / scale))
        # `<=` within TIE_RTOL: complements conditioned alike to the last digits (rows 5 and 6 of the scooter
        # are) are equivalent, and the last in enumeration order is kept, so that the choice (and the design
        # file) does not hang on the last bit LAPACK returns, which differs between library versions
        if score <= best_score * (1.0 + TIE_RTOL):
            best, best_score = rows, min(score, best_score)
    if best is None or not np.isfinite(best_score):
        raise ValueError("no complement of the unknown-input directions gives an invertible transformation")
    return best


# the floor of a vehicle for which case 2 is not strongly detectable at any speed a scooter rides: beyond every
# speed (the runtime never runs it), and finite, as every number of the design file is
NEVER_DETECTABLE = 1000.0  # m/s


def detectability_floor(p: VehicleParameters, lo: float = 0.5, hi: float = 40.0, tol: float = 1e-3) -> float:
    """Lowest speed [m/s] above which case 2 has only stable invariant zeros (bisection); NEVER_DETECTABLE if
    it is not strongly detectable even at `hi`.

    Below it the UIHOSMO is not strongly detectable: its zero dynamics are unstable and
    no gain can fix that, so the runtime must not rely on it there.
    """

    def detectable(u: float) -> bool:
        return bool(np.all(invariant_zeros(case2(p, u)).real < 0))

    if not detectable(hi):
        return NEVER_DETECTABLE
    if detectable(lo):
        return lo
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if detectable(mid) else (mid, hi)
    return hi


def design_point(
    p: VehicleParameters,
    speed: float,
    decay_rate: float,
    output_weight: float,
    rows: tuple[int, ...],
    dt: float,
    detectable: bool,
) -> UihosmoPoint:
    """The observer at one speed. Where case 2 is not strongly detectable the zero-dynamics
    state is held at zero (Phi22 = 0): its true dynamics are unstable there, and the runtime
    flags the speed as outside the model's validity."""
    sys = case2(p, speed)
    L = luenberger_gain(sys, decay_rate, output_weight)
    At = sys.A - L @ sys.C
    T = transformation(sys, L, rows)
    T_inv = np.linalg.inv(T)
    A_xi = T @ At @ T_inv
    D_xi = T @ sys.D
    Abar = A_xi[[1, 2], :]
    Dbar = D_xi[[1, 2], :]
    A21 = A_xi[N_XI1:, :N_XI1]
    A22 = A_xi[N_XI1:, N_XI1:]
    # Inputs are not constant over 10 ms: theta_2 reacts to theta_1 through zeros as fast
    # as -500 1/s. Holding theta_1 for a step costs ~1 deg of roll RMS on a lane change;
    # a ramp hold (the differentiator supplies d/dt theta_1) and a first-order hold of
    # y in the pre-observer bring the discrete observer back to the continuous one.
    Phi, Gamma = zoh(At, L, dt)
    Ramp_y = ramp_response(At, L, dt) / dt
    if detectable:
        Phi22, Gamma21 = zoh(A22, A21, dt)
        Ramp21 = ramp_response(A22, A21, dt)
    else:
        Phi22, Gamma21, Ramp21 = np.zeros_like(A22), np.zeros_like(A21), np.zeros_like(A21)
    return UihosmoPoint(
        speed=speed,
        L=L,
        T=T,
        T_inv=T_inv,
        A_xi=A_xi,
        Abar=Abar,
        Dbar=Dbar,
        Dbar_inv=np.linalg.inv(Dbar),
        A21=A21,
        A22=A22,
        Phi=Phi,
        Gamma=Gamma,
        Phi22=Phi22,
        Gamma21=Gamma21,
        Ramp_y=Ramp_y,
        Ramp21=Ramp21,
    )


@dataclass(frozen=True)
class UihosmoDesign:
    points: list[UihosmoPoint]
    complement_rows: tuple[int, ...]
    detectability_floor: float  # m/s
    detectable: np.ndarray  # per grid point


def design_grid(
    p: VehicleParameters, speeds: np.ndarray, decay_rate: float, output_weight: float, dt: float
) -> UihosmoDesign:
    floor = detectability_floor(p)
    # the transformation's rows are chosen where it is detectable; for a vehicle where it never is (the runtime
    # never runs it), at every grid speed, so that the design file keeps its shape
    systems = [case2(p, u) for u in speeds if u >= floor] or [case2(p, u) for u in speeds]
    rows = choose_complement_rows(systems)
    detectable = speeds >= floor
    points = [
        design_point(p, u, decay_rate, output_weight, rows, dt, bool(ok))
        for u, ok in zip(speeds, detectable, strict=True)
    ]
    return UihosmoDesign(points, rows, floor, detectable)
