"""The design file: every gain the runtime needs, per speed grid point, as one .npz.

Loaded with numpy alone (no scipy, no cvxpy) so the daemon never needs the
design extra. It carries the hash of the configuration it was computed from;
a design that does not match the running configuration is refused.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ptw_rt.errors import UserFacingError

FORMAT_VERSION = 5
REGENERATE_HINT = "regenerate it with: ptw-rt design --config {config} --out {path}"


class DesignFileError(UserFacingError, ValueError):
    """The design file is missing, unreadable, of another format version, or made for another config."""


@dataclass(frozen=True)
class DesignData:
    format_version: int
    config_hash: str
    vehicle_name: str
    sample_time: float
    grid: np.ndarray  # (G,) forward speed [m/s]
    min_valid_speed: float  # [m/s]
    detectability_floor: float  # [m/s], case 2 strongly detectable above
    # UIHOSMO (reduced state [delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr])
    uh_detectable: np.ndarray  # (G,) bool
    uh_Phi: np.ndarray  # (G, 7, 7)
    uh_Gamma: np.ndarray  # (G, 7, 2)
    uh_T: np.ndarray  # (G, 7, 7)
    uh_T_inv: np.ndarray  # (G, 7, 7)
    uh_Abar: np.ndarray  # (G, 2, 7)
    uh_Dbar_inv: np.ndarray  # (G, 2, 2)
    uh_Phi22: np.ndarray  # (G, 4, 4)
    uh_Gamma21: np.ndarray  # (G, 4, 3)
    uh_Ramp_y: np.ndarray  # (G, 7, 2) first-order hold of y
    uh_Ramp21: np.ndarray  # (G, 4, 3) ramp of theta_1
    uh_complement_rows: np.ndarray  # (4,)
    uh_differentiator_lambda: float
    # LPV adaptive observer (state [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr])
    ad_Phi: np.ndarray  # (G, 8, 8)
    ad_B_tau: np.ndarray  # (G, 8)
    ad_B_theta: np.ndarray  # (G, 8, 2), input matrix of chi(x, u) Theta
    ad_B_y: np.ndarray  # (G, 8, 6)
    ad_C: np.ndarray  # (6, 8)
    ad_T: np.ndarray  # (2, 6), output error -> D^T P x_err
    ad_gamma: np.ndarray  # (4,) adaptation gains
    ad_theta_nominal: np.ndarray  # (4,) C_af, C_gf, C_ar, C_gr
    ad_theta_bound: np.ndarray  # (4,) |Theta| bound
    ad_pe_threshold: np.ndarray  # (4,) RMS of each regressor column needed to adapt
    ad_pe_forgetting: float  # per-sample forgetting factor of the excitation mean square
    ad_L_vertices: np.ndarray  # (2, 8, 6)
    ad_speed_vertices: np.ndarray  # (2,)
    ad_lmi_slack: float
    ad_lmi_residual: float
    # regressor constants (seed 001 eq. 8): sigma_f, sigma_r, l_f, l_r, caster, trail
    regressor_constants: np.ndarray  # (6,)
    # fusion filter (steady-state Kalman, state [phi, delta, v_y, r, phi_dot, delta_dot, F_yf, F_yr, tau])
    kf_Phi: np.ndarray  # (G, 11, 11) exact ZOH of the torque- and gyro-bias-augmented model
    kf_K: np.ndarray  # (G, 9, 5) corrector gain for y = [delta, r, phi_dot, a_y, phi]
    kf_C: np.ndarray  # (5, 9)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self)}
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        tmp.replace(path)


def load_design(path: str | Path, expected_hash: str | None = None, config_path: str | Path = "CONFIG") -> DesignData:
    path = Path(path)
    hint = REGENERATE_HINT.format(config=config_path, path=path)
    if not path.exists():
        raise DesignFileError(f"{path}: design file not found; {hint}")
    try:
        with np.load(path, allow_pickle=False) as npz:
            raw = {k: npz[k] for k in npz.files}
    except (OSError, ValueError) as exc:
        raise DesignFileError(f"{path}: not a readable design file ({exc}); {hint}") from None
    version = int(raw.get("format_version", -1))
    if version != FORMAT_VERSION:
        raise DesignFileError(f"{path}: design format version {version}, this ptw-rt reads {FORMAT_VERSION}; {hint}")
    missing = [f.name for f in fields(DesignData) if f.name not in raw]
    if missing:
        raise DesignFileError(f"{path}: design file lacks {', '.join(missing)}; {hint}")
    values = {}
    for f in fields(DesignData):
        v = raw[f.name]
        if v.ndim == 0:
            v = v.item()
        values[f.name] = v
    data = DesignData(**values)
    if expected_hash is not None and data.config_hash != expected_hash:
        raise DesignFileError(
            f"{path}: made for another configuration (design hash {data.config_hash[:12]}, "
            f"config hash {expected_hash[:12]}): the vehicle or tuning changed since; {hint}"
        )
    return data
