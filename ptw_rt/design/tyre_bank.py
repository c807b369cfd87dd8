"""Offline design of the tyre bank: one fusion filter per hypothesis of the tyres' scale.

Every real scooter's tyres differ from the nominal file (pressure, temperature, wear, a wet road). We
parametrise the difference by one factor k on all four small-slip stiffnesses (C_af, C_gf, C_ar, C_gr):
it is what the data identify under ordinary riding (docs/estimator.md, "Tyres"), and what a changed road
friction does; and two more filters check the front's factor against the rear's (the balance, below). The bank
holds the steady-state fusion filter (ptw_rt.design.kalman) designed for the vehicle with its tyres scaled by
each k of a log-spaced grid, at every grid speed, plus each filter's innovation covariance S; the runtime
(ptw_rt.core.tyre_bank) weighs the filters by the likelihood of their innovations.

Each hypothesis also has a publishing filter: the same vehicle and measurements, its tyre forces' process
noise scaled by `fusion_filter.published_force_noise` (front, rear), so the published forces and torque
follow the measured a_y and yaw where the tyres leave the linear model (near the grip limit, a payload the
file does not describe), and its rider torque's random walk by `published_torque_noise` (less lag); the evidence
keeps the model's tighter filters, which tell tyres apart.

Tables (H hypotheses, G grid speeds; hypothesis-major, so rows h*G .. h*G+G-1 are hypothesis h):
  tb_scale (H,), tb_Phi (H*G, 9, 9), tb_K (H*G, 9, 5), tb_Gd (H*G, 9, 4), tb_Sinv (H*G, 5, 5),
  tb_logdet (H*G, 1, 1) (log det S, as a 3-D table so it interpolates like the others),
  tb_K_pub: the publishing filters' gain (their Phi and Gd are tb_Phi and tb_Gd: the same vehicle).

The balance check's filters (`balances`): hypothesis h's vehicle with its front tyre's two stiffnesses times
1 / `balance_step` (side 0) and `balance_step` (side 1), the rear's as they are; evidence filters only (no
publishing twin). Rows (side H + h) G + i of tb_bal_Phi (2*H*G, 9, 9), tb_bal_K (2*H*G, 9, 5), tb_bal_Gd (2*H*G, 9, 4),
tb_bal_Sinv (2*H*G, 5, 5), tb_bal_logdet (2*H*G, 1, 1). Their output matrix is the bank's (the tyres do not enter it).
"""

from __future__ import annotations

import numpy as np

from ptw_rt.design import kalman
from ptw_rt.design.stability import spectral_radius
from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.settings import KalmanTuning, TyreBankTuning


def balances(tuning: TyreBankTuning) -> tuple[float, float]:
    """The front tyre's factors of the balance check's two filters (module doc), side 0 and side 1."""
    return 1.0 / tuning.balance_step, tuning.balance_step


def design_bank(
    p: VehicleParameters, grid: np.ndarray, dt: float, kalman_tuning: KalmanTuning, tuning: TyreBankTuning
) -> dict[str, np.ndarray]:
    ks = tuning.scales()
    tables = _EvidenceTables()
    gain_pub = []
    published = kalman_tuning.published_force_noise
    for k in ks:
        pk = p.scaled(stiffness=float(k))
        for u in grid:
            Phi, K, Gd = tables.add(pk, float(u), dt, kalman_tuning)
            Phi_pub, K, Gd_pub, _ = kalman.design_point_with_innovation(
                pk, float(u), dt, kalman_tuning, published, kalman_tuning.published_torque_noise
            )
            # the runtime steps both filters with one Phi and Gd (core.kalman.kalman_pair_step_at): a raise, not an
            # assert, so that `python -O` cannot write a design file whose publishing filters run the wrong model
            if not (np.array_equal(Phi_pub, Phi) and np.array_equal(Gd_pub, Gd)):
                raise ValueError(f"the publishing filter's model differs from the evidence filter's at k={k}, u={u}")
            gain_pub.append(K)
    return {
        "tb_scale": ks,
        **tables.arrays("tb_"),
        "tb_K_pub": np.array(gain_pub),
        **_balance_filters(p, ks, grid, dt, kalman_tuning, tuning),
    }


class _EvidenceTables:
    """An evidence filter's tables, one grid speed at a time: Phi, K, Gd and its innovation's S as S^-1 and
    log det S (what the runtime's likelihoods need)."""

    def __init__(self) -> None:
        self.phi, self.gain, self.gd, self.sinv, self.logdet = [], [], [], [], []

    def add(self, p: VehicleParameters, u: float, dt: float, tuning: KalmanTuning):
        Phi, K, Gd, S = kalman.design_point_with_innovation(p, u, dt, tuning)
        self.phi.append(Phi)
        self.gain.append(K)
        self.gd.append(Gd)
        self.sinv.append(np.linalg.inv(S))
        self.logdet.append(np.linalg.slogdet(S)[1])
        return Phi, K, Gd

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        return {
            prefix + "Phi": np.array(self.phi),
            prefix + "K": np.array(self.gain),
            prefix + "Gd": np.array(self.gd),
            prefix + "Sinv": np.array(self.sinv),
            prefix + "logdet": np.array(self.logdet).reshape(-1, 1, 1),
        }


def _balance_filters(
    p: VehicleParameters,
    ks: np.ndarray,
    grid: np.ndarray,
    dt: float,
    kalman_tuning: KalmanTuning,
    tuning: TyreBankTuning,
) -> dict[str, np.ndarray]:
    """The balance check's evidence filters (module doc), side-major, then hypothesis, then grid speed."""
    tables = _EvidenceTables()
    C = kalman.output_matrix(p)
    for front in balances(tuning):
        for k in ks:
            pk = p.scaled(stiffness=float(k), front_stiffness=front)
            if not np.array_equal(kalman.output_matrix(pk), C):
                raise ValueError("the balance check's filters measure through another output matrix than the bank's")
            for u in grid:
                tables.add(pk, float(u), dt, kalman_tuning)
    return tables.arrays("tb_bal_")


def bank_spectral_radii(data, grid: np.ndarray, between: int) -> tuple[float, float]:
    """Worst spectral radius of every hypothesis' error dynamics (its evidence filter's and its publishing
    filter's) at the grid speeds and `between` speeds inside each interval (linear interpolation, as the
    runtime does)."""
    G = len(grid)
    C = data.kf_C
    at_grid, inside = 0.0, 0.0
    pairs = ((data.tb_Phi, data.tb_K), (data.tb_Phi, data.tb_K_pub), (data.tb_bal_Phi, data.tb_bal_K))
    for Phi_all, K_all in pairs:
        for h in range(Phi_all.shape[0] // G):  # hypotheses (and the balance check's sides x hypotheses)
            Phi, K = Phi_all[h * G : (h + 1) * G], K_all[h * G : (h + 1) * G]
            for i in range(G):
                at_grid = max(at_grid, spectral_radius(kalman.error_dynamics(Phi[i], K[i], C)))
            for i in range(G - 1):
                for w in np.linspace(0.0, 1.0, between + 2)[1:-1]:
                    Pw = (1 - w) * Phi[i] + w * Phi[i + 1]
                    Kw = (1 - w) * K[i] + w * K[i + 1]
                    inside = max(inside, spectral_radius(kalman.error_dynamics(Pw, Kw, C)))
    return at_grid, inside
