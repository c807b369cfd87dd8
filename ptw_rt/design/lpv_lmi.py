"""LMI design of the LPV adaptive observer (seed 001, theorem 2, LMIs 33-34), with cvxpy.

Model  x' = A(u) x + B tau + D chi(x, u) Theta,  y = C x, A(u) affine in u, so the
two speed vertices A_1 = A(u_min), A_2 = A(u_max) describe it exactly.
Measurements y = [delta, r, phi_dot, delta_dot, a_y, y_a] (seed 001 eq. 10 and the
virtual output of eq. 15).

Find P > 0, K_i, T, R such that for i = 1, 2

    [[A_i^T P + P A_i - C^T K_i^T - K_i C + R + 2 alpha P,  P], [P, -Q]] < 0      (34)
    || D^T P - T C || <= slack, slack minimised                                      (33)
    [[-q P, q P + (P A_i - K_i C)^T], [q P + P A_i - K_i C, -q P]] < 0                 (pole disk)
    R >= J_v^T Q J_v for every vertex v of the (u, Theta) box                         (Lipschitz, lemma 1)
    Q > 0 (a decision variable: everything above is linear in it)

where J_v is the Jacobian of D chi(x, u) Theta in x. Gains L_i = P^-1 K_i,
L(u) = eta_1(u) L_1 + eta_2(u) L_2 (eq. 38). Because A(u) and L(u) are both affine
with the same weights, A(u) - L(u) C is the same convex combination of the vertex
matrices: one common P proves stability for every speed in the range, also when
speed varies in time. Everything is solved in scaled coordinates (typical
magnitudes) so the SDP is well conditioned.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.model.sharp import DELTA, DELTA_DOT, FYF, FYR, N_STATES, PHI_DOT, LPVModel, R, lpv_model, regressor

N_Y = 6
OUTPUT_NAMES = ("delta", "r", "phi_dot", "delta_dot", "a_y", "y_a")
# Typical magnitudes: [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr] and the outputs.
STATE_SCALE = np.array([0.1, 0.01, 0.3, 0.1, 0.3, 0.1, 500.0, 500.0])
OUTPUT_SCALE = np.array([0.01, 0.1, 0.3, 0.1, 2.0, 1e5])


def output_matrix(p: VehicleParameters) -> np.ndarray:
    """C of the adaptive observer: four sensors, the lateral acceleration (F_yf + F_yr)/M
    and the virtual output y_a = (M_f k - M l_f) F_yf + (M_f k + M l_r) F_yr (seed 001 eq. 15)."""
    C = np.zeros((N_Y, N_STATES))
    C[0, DELTA] = 1.0
    C[1, R] = 1.0
    C[2, PHI_DOT] = 1.0
    C[3, DELTA_DOT] = 1.0
    C[4, FYF] = C[4, FYR] = 1.0 / p.mass
    C[5, FYF] = p.mfk - p.mass * p.l_f
    C[5, FYR] = p.mfk + p.mass * p.l_r
    return C


def lipschitz_jacobians(model: LPVModel, speeds: tuple[float, float], theta_bound: np.ndarray) -> list[np.ndarray]:
    """Jacobians in x of D chi(x, u) Theta at the vertices of the speed x Theta box (chi is linear in x)."""
    jacobians = []
    for u in speeds:
        # Columns of d chi / d x: chi is linear in x, so evaluate it on unit vectors.
        basis = [
            regressor(
                np.eye(N_STATES)[k], u, model.sigma_f, model.sigma_r, model.l_f, model.l_r, model.caster, model.trail
            )
            for k in range(N_STATES)
        ]
        for signs in itertools.product((-1.0, 1.0), repeat=4):
            theta = theta_bound * np.array(signs)
            J = np.column_stack([model.D @ (chi @ theta) for chi in basis])
            jacobians.append(J)
    return jacobians


@dataclass(frozen=True)
class LmiSolution:
    feasible: bool
    status: str
    slack: float  # optimal value of the slack of (33), scaled coordinates
    residual: float  # ||D^T P - T C||_2, scaled coordinates
    P: np.ndarray  # scaled coordinates
    K: tuple[np.ndarray, np.ndarray]
    T: np.ndarray  # scaled coordinates
    R: np.ndarray
    Q: np.ndarray
    A_vertices: tuple[np.ndarray, np.ndarray]  # scaled
    C: np.ndarray  # scaled
    D: np.ndarray  # scaled
    decay_rate: float
    pole_disk_radius: float
    L_vertices: tuple[np.ndarray, np.ndarray]  # physical units
    T_physical: np.ndarray  # maps a physical output error to D^T P x_err (adaptation law)
    speed_vertices: tuple[float, float]

    def lmi34(self, i: int) -> np.ndarray:
        """The matrix of LMI (34) at vertex i (must be negative definite)."""
        A, K, P = self.A_vertices[i], self.K[i], self.P
        top = A.T @ P + P @ A - self.C.T @ K.T - K @ self.C + self.R + 2 * self.decay_rate * P
        return np.block([[top, P], [P, -self.Q]])

    def disk_lmi(self, i: int) -> np.ndarray:
        """The D-stability LMI at vertex i (must be negative definite)."""
        P, q = self.P, self.pole_disk_radius
        PM = P @ self.A_vertices[i] - self.K[i] @ self.C
        return np.block([[-q * P, q * P + PM.T], [q * P + PM, -q * P]])

    def lmi33(self) -> np.ndarray:
        M = self.D.T @ self.P - self.T @ self.C
        n, m = M.shape
        return np.block([[self.slack * np.eye(n), M], [M.T, self.slack * np.eye(m)]])


def solve_lmis(
    p: VehicleParameters,
    speed_range: tuple[float, float],
    decay_rate: float,
    deviation_bound: float,
    pole_disk_radius: float,
    margin: float = 1e-6,
) -> LmiSolution:
    model = lpv_model(p)
    S, W = np.diag(STATE_SCALE), np.diag(OUTPUT_SCALE)
    S_inv, W_inv = np.linalg.inv(S), np.linalg.inv(W)
    C = output_matrix(p)
    A_s = tuple(S_inv @ model.A(u) @ S for u in speed_range)
    C_s = W_inv @ C @ S
    D_s = S_inv @ model.D
    theta_bound = deviation_bound * np.array(p.nominal_stiffness())
    jac = [S_inv @ J @ S for J in lipschitz_jacobians(model, speed_range, theta_bound)]

    n = N_STATES
    # Q of lemma 1 is a decision variable: (34) and R >= J^T Q J are both linear in it,
    # so the solver picks the Lipschitz weighting instead of a hand-tuned constant.
    Q = cp.Variable((n, n), symmetric=True)
    P = cp.Variable((n, n), symmetric=True)
    R = cp.Variable((n, n), symmetric=True)
    K = [cp.Variable((n, N_Y)) for _ in speed_range]
    T = cp.Variable((2, N_Y))
    slack = cp.Variable(nonneg=True)
    eye = np.eye(n)
    # P >= I normalises the homogeneous problem: with an upper bound instead, the
    # slack is minimised by shrinking the tyre rows of P, which turns adaptation off.
    constraints = [P >> eye, Q >> margin * eye]
    q = pole_disk_radius
    for A_i, K_i in zip(A_s, K, strict=True):
        PM = P @ A_i - K_i @ C_s  # P (A_i - L_i C)
        top = PM + PM.T + R + 2 * decay_rate * P
        block = cp.bmat([[top, P], [P, -Q]])
        constraints.append(0.5 * (block + block.T) << -margin * np.eye(2 * n))
        # D-stability (Chilali-Gahinet): eigenvalues of A_i - L_i C in the disk of centre -q,
        # radius q, i.e. no error pole faster than 2q, which the 100 Hz samples cannot carry.
        disk = cp.bmat([[-q * P, q * P + PM.T], [q * P + PM, -q * P]])
        constraints.append(0.5 * (disk + disk.T) << -margin * np.eye(2 * n))
    for J in jac:
        constraints.append(R >> J.T @ Q @ J)
    mismatch = D_s.T @ P - T @ C_s
    constraints.append(cp.bmat([[slack * np.eye(2), mismatch], [mismatch.T, slack * eye]]) >> 0)
    problem = cp.Problem(cp.Minimize(slack), constraints)
    status = _solve(problem)
    feasible = status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) and P.value is not None
    if not feasible:
        nan = np.full((n, n), np.nan)
        return LmiSolution(
            False,
            status,
            np.nan,
            np.nan,
            nan,
            (nan, nan),
            np.full((2, N_Y), np.nan),
            nan,
            nan,
            A_s,
            C_s,
            D_s,
            decay_rate,
            q,
            (nan, nan),
            np.full((2, N_Y), np.nan),
            speed_range,
        )
    P_v = 0.5 * (P.value + P.value.T)
    K_v = tuple(k.value for k in K)
    T_v = T.value
    L_phys = tuple(S @ np.linalg.solve(P_v, k) @ W_inv for k in K_v)
    residual = float(np.linalg.norm(D_s.T @ P_v - T_v @ C_s, 2))
    # Adaptation law: Theta' = Gamma chi^T (D^T P x_err) with x_err in scaled coordinates;
    # D^T P x_err = T C_s x_err = T W^-1 y_err: T W^-1 acts on the physical output error.
    return LmiSolution(
        feasible=True,
        status=status,
        slack=float(slack.value),
        residual=residual,
        P=P_v,
        K=K_v,
        T=T_v,
        R=0.5 * (R.value + R.value.T),
        Q=0.5 * (Q.value + Q.value.T),
        A_vertices=A_s,
        C=C_s,
        D=D_s,
        decay_rate=decay_rate,
        pole_disk_radius=q,
        L_vertices=L_phys,
        T_physical=T_v @ W_inv,
        speed_vertices=speed_range,
    )


def _solve(problem: cp.Problem) -> str:
    for solver in ("CLARABEL", "SCS"):
        if solver not in cp.installed_solvers():
            continue
        try:
            problem.solve(solver=solver)
        except cp.error.SolverError:
            continue
        if problem.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return problem.status
    return str(problem.status)


def scheduled_gain(sol: LmiSolution, u: float) -> np.ndarray:
    """L(u) = eta_1 L_1 + eta_2 L_2 with the polytopic weights of eq. 35."""
    u_min, u_max = sol.speed_vertices
    eta_2 = float(np.clip((u - u_min) / (u_max - u_min), 0.0, 1.0))
    return (1.0 - eta_2) * sol.L_vertices[0] + eta_2 * sol.L_vertices[1]
