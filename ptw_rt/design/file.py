"""The design file: every gain the runtime needs, per speed grid point, as one .npz.

Loaded with numpy alone (no scipy, no cvxpy) so the daemon never needs the
design extra. It carries the hash of the configuration it was computed from;
a design that does not match the running configuration is refused.
"""

from __future__ import annotations

import math
import re
import zipfile
import zlib
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ptw_rt.design.stability import spectral_radius
from ptw_rt.errors import UserFacingError
from ptw_rt.paths import DEFAULT_DESIGN, own_design_file
from ptw_rt.untrusted import check_replaceable, excerpt, open_binary, replacing, same_file, short_text

FORMAT_VERSION = 11
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
    kf_Phi: np.ndarray  # (G, 9, 9) exact ZOH of the torque-augmented model
    kf_K: np.ndarray  # (G, 9, 5) corrector gain for y = [delta, r, phi_dot, a_y, phi]
    kf_C: np.ndarray  # (5, 9)
    kf_Gd: np.ndarray  # (G, 9, 4) exact ZOH of the nonlinear correction forces (lateral, yaw, roll, steer rows)
    kf_nonlinear: np.ndarray  # (7,) vehicle constants of the nonlinear correction (core.kalman NL_*)
    # the tyre bank (design/tyre_bank.py): H hypotheses x G grid speeds, hypothesis-major rows
    tb_scale: np.ndarray  # (H,) tyre scale of each hypothesis
    tb_Phi: np.ndarray  # (H*G, 9, 9)
    tb_K: np.ndarray  # (H*G, 9, 5)
    tb_Gd: np.ndarray  # (H*G, 9, 4)
    tb_Sinv: np.ndarray  # (H*G, 5, 5) inverse innovation covariance
    tb_logdet: np.ndarray  # (H*G, 1, 1) log det of the innovation covariance
    # the publishing filter's gain (tyre forces freer of the tyre model); its Phi and Gd are tb_Phi and tb_Gd,
    # which depend on the vehicle alone
    tb_K_pub: np.ndarray  # (H*G, 9, 5)
    # the balance check's evidence filters: hypothesis h with its front tyre x 1 / balance_step (side 0) and
    # x balance_step (side 1), rows (side H + h) G + i (design/tyre_bank.py)
    tb_bal_Phi: np.ndarray  # (2*H*G, 9, 9)
    tb_bal_K: np.ndarray  # (2*H*G, 9, 5)
    tb_bal_Gd: np.ndarray  # (2*H*G, 9, 4)
    tb_bal_Sinv: np.ndarray  # (2*H*G, 5, 5)
    tb_bal_logdet: np.ndarray  # (2*H*G, 1, 1)
    # UIHOSMO on the real sensors (issue #16; design.uio_sensors, runtime core.uio_sensors), reduced state as uh_*
    us_outputs: np.ndarray  # (m,) int, core.uio_sensors M_* codes of the reconstruction outputs
    us_observed: np.ndarray  # (p,) int, M_* codes of the pre-observer's outputs (us_outputs first)
    us_degrees: np.ndarray  # (m,) int, relative degree of each reconstruction output
    us_roll_input: int  # 1: unknown input tau, roll measured (an input); 0: unknown inputs [phi, tau]
    us_lipschitz: np.ndarray  # (m,) differentiator constant L per reconstruction output
    us_min_valid_speed: float  # [m/s] the stage is held in reset below
    us_detectability_floor: float  # [m/s] zero dynamics stable above
    us_mass: float  # [kg] initial tyre forces from a_y
    us_C: np.ndarray  # (p, 7)
    us_Phi: np.ndarray  # (G, 7, 7) exact ZOH of A - L C
    us_Gamma: np.ndarray  # (G, 7, p + 5) ZOH of the inputs [y, roll, d]
    us_Ramp: np.ndarray  # (G, 7, p + 5) first-order hold of the same
    us_T_inv: np.ndarray  # (G, 7, 7)
    us_Abar: np.ndarray  # (G, m, 7)
    us_Dbar_inv: np.ndarray  # (G, m, m)
    us_Phi22: np.ndarray  # (G, n2, n2)
    us_Gamma21: np.ndarray  # (G, n2, n1)
    us_Ramp21: np.ndarray  # (G, n2, n1)

    def save(self, path: str | Path) -> None:
        """Written to a temporary file renamed over ``path`` (a regular file, or none): ``OSError`` if it cannot be,
        nothing left behind."""
        path = Path(path)
        check_replaceable(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self)}
        with replacing(path) as fh:
            np.savez_compressed(fh, **arrays)


# Bounds of what a design file may hold, checked from the zip directory and each member's .npy header BEFORE
# anything is decompressed (a few-MB "zip bomb" .npz can declare gigabytes). Format 6's file: 39 members,
# 174 kB on disk, 217 kB uncompressed, at most 3 dimensions.
MAX_DESIGN_BYTES = 16 << 20  # on disk
MAX_DESIGN_UNCOMPRESSED = 64 << 20  # sum of the members' declared sizes
MAX_MEMBER_HEADER = 4096  # bytes of one .npy header (numpy writes 128)
MAX_NDIM = 4
_MEMBER_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}\.npy")
# dtype kinds allowed per field annotation: no object (pickle), structured, bytes or complex arrays
_KINDS = {"int": "iu", "float": "iuf", "str": "U", "np.ndarray": "biuf"}

# Every table's full shape, in the sizes the file declares: G grid speeds, H tyre hypotheses (HG = H x G rows), m
# reconstruction outputs and p observed outputs of the UIHOSMO on the sensors, n1 + n2 = 7 its reduced split (P5 = p + 5
# inputs). The jitted step has no bounds checks: a table one row short is read past its end, silently.
_SHAPES: dict[str, tuple] = {
    "grid": ("G",),
    "uh_detectable": ("G",),
    "uh_Phi": ("G", 7, 7),
    "uh_Gamma": ("G", 7, 2),
    "uh_T": ("G", 7, 7),
    "uh_T_inv": ("G", 7, 7),
    "uh_Abar": ("G", 2, 7),
    "uh_Dbar_inv": ("G", 2, 2),
    "uh_Phi22": ("G", 4, 4),
    "uh_Gamma21": ("G", 4, 3),
    "uh_Ramp_y": ("G", 7, 2),
    "uh_Ramp21": ("G", 4, 3),
    "uh_complement_rows": (4,),
    "ad_Phi": ("G", 8, 8),
    "ad_B_tau": ("G", 8),
    "ad_B_theta": ("G", 8, 2),
    "ad_B_y": ("G", 8, 6),
    "ad_C": (6, 8),
    "ad_T": (2, 6),
    "ad_gamma": (4,),
    "ad_theta_nominal": (4,),
    "ad_theta_bound": (4,),
    "ad_pe_threshold": (4,),
    "ad_L_vertices": (2, 8, 6),
    "ad_speed_vertices": (2,),
    "regressor_constants": (6,),
    "kf_Phi": ("G", 9, 9),
    "kf_K": ("G", 9, 5),
    "kf_C": (5, 9),
    "kf_Gd": ("G", 9, 4),
    "kf_nonlinear": (7,),
    "tb_scale": ("H",),
    "tb_Phi": ("HG", 9, 9),
    "tb_K": ("HG", 9, 5),
    "tb_Gd": ("HG", 9, 4),
    "tb_Sinv": ("HG", 5, 5),
    "tb_logdet": ("HG", 1, 1),
    "tb_K_pub": ("HG", 9, 5),
    "tb_bal_Phi": ("2HG", 9, 9),
    "tb_bal_K": ("2HG", 9, 5),
    "tb_bal_Gd": ("2HG", 9, 4),
    "tb_bal_Sinv": ("2HG", 5, 5),
    "tb_bal_logdet": ("2HG", 1, 1),
    "us_outputs": ("m",),
    "us_observed": ("p",),
    "us_degrees": ("m",),
    "us_lipschitz": ("m",),
    "us_C": ("p", 7),
    "us_Phi": ("G", 7, 7),
    "us_Gamma": ("G", 7, "P5"),
    "us_Ramp": ("G", 7, "P5"),
    "us_T_inv": ("G", 7, 7),
    "us_Abar": ("G", "m", 7),
    "us_Dbar_inv": ("G", "m", "m"),
    "us_Phi22": ("G", "n2", "n2"),
    "us_Gamma21": ("G", "n2", "n1"),
    "us_Ramp21": ("G", "n2", "n1"),
}
# what the runtime lays out (ptw_rt.core: tyre_bank.MAX_COUNT; uio_sensors MAX_OUT, MAX_OBS, MAX_DIFF - 2 and the
# four measurement codes; tests/test_design_file.py checks they agree): a design beyond them cannot run
MAX_HYPOTHESES = 32
MAX_RECONSTRUCTED = 2
MAX_OBSERVED = 4
MAX_DEGREE = 2
MEASUREMENT_CODES = 4
MAX_GRID_SPEED = 100.0  # m/s


def _check_contents(raw: dict[str, np.ndarray], expected_sample_time: float | None, expected_grid) -> str | None:
    """What the arrays must hold for the step to run on them (any problem: its description): every shape, the grid
    (increasing, positive, the config's), the sample time (the config's), index and count fields within what the
    runtime lays out, and the signs the observers assume. The hash alone proves nothing: a file can keep it."""
    dt = float(raw["sample_time"].item())
    if not 0.001 <= dt <= 0.1:
        return f"sample_time {dt:g} s outside 0.001-0.1 s"
    if expected_sample_time is not None and dt != expected_sample_time:
        return f"sample_time {dt:g} s, the config's estimator.sample_time is {expected_sample_time:g} s"
    grid = raw["grid"].astype(np.float64)
    if grid.ndim != 1 or grid.shape[0] < 2 or grid[0] < 0.0 or grid[-1] > MAX_GRID_SPEED or np.any(np.diff(grid) <= 0):
        return f"grid is not 2 or more increasing speeds within 0-{MAX_GRID_SPEED:g} m/s"
    if expected_grid is not None and (grid.shape != expected_grid.shape or not np.allclose(grid, expected_grid)):
        return "grid is not the config's estimator.speed_grid"
    scale = raw["tb_scale"].astype(np.float64)
    if scale.ndim != 1 or not 2 <= scale.shape[0] <= MAX_HYPOTHESES or scale[0] <= 0 or np.any(np.diff(scale) <= 0):
        return f"tb_scale is not 2 to {MAX_HYPOTHESES} increasing positive tyre scales"
    outputs, observed, degrees = (raw[k].astype(np.int64) for k in ("us_outputs", "us_observed", "us_degrees"))
    m, p = outputs.size, observed.size
    if not (1 <= m <= MAX_RECONSTRUCTED and m <= p <= MAX_OBSERVED):
        return f"us_outputs / us_observed: {m} / {p} outputs (1-{MAX_RECONSTRUCTED} / up to {MAX_OBSERVED})"
    if np.any(observed < 0) or np.any(observed >= MEASUREMENT_CODES) or not np.array_equal(observed[:m], outputs):
        return "us_observed holds unknown measurement codes or does not start with us_outputs"
    if degrees.shape != outputs.shape or np.any(degrees < 1) or np.any(degrees > MAX_DEGREE):
        return f"us_degrees outside 1-{MAX_DEGREE}"
    n2 = raw["us_Phi22"].shape[1] if raw["us_Phi22"].ndim == 3 else 0
    sizes = {"G": grid.shape[0], "H": scale.shape[0], "HG": scale.shape[0] * grid.shape[0], "m": m, "p": p}
    sizes["2HG"] = 2 * sizes["HG"]
    sizes.update(P5=p + 5, n2=n2, n1=7 - n2)
    if not 1 <= n2 <= 6:
        return f"us_Phi22 splits the reduced state {7 - n2} + {n2}"
    for name, spec in _SHAPES.items():
        want = tuple(sizes[d] if isinstance(d, str) else d for d in spec)
        if raw[name].shape != want:
            return f"{name} has shape {excerpt(raw[name].shape, 40)}, expected {want}"
    rows = raw["uh_complement_rows"].astype(np.int64)
    if np.any(rows < 0) or np.any(rows > 6) or np.unique(rows).size != rows.size:
        return "uh_complement_rows are not distinct rows 0-6"
    if int(raw["us_roll_input"].item()) not in (0, 1):
        return "us_roll_input is not 0 or 1"
    positive = ("uh_differentiator_lambda", "us_mass", "ad_theta_nominal", "ad_theta_bound", "us_lipschitz")
    for name in positive:
        if np.any(raw[name] <= 0):
            return f"{name} must be positive"
    for name in ("min_valid_speed", "detectability_floor", "us_min_valid_speed", "us_detectability_floor"):
        if raw[name].item() < 0:
            return f"{name} must not be negative"
    for name in ("ad_gamma", "ad_pe_threshold"):
        if np.any(raw[name] < 0):
            return f"{name} must not be negative"
    if not 0.0 < raw["ad_pe_forgetting"].item() <= 1.0:
        return "ad_pe_forgetting outside (0, 1]"
    if np.any(raw["regressor_constants"][2:4] <= 0):
        return "regressor_constants: the axle distances must be positive"
    return None


def _field_kinds() -> dict[str, str]:
    """Field name -> the DesignData annotation ("float", "np.ndarray", ...), the data-driven part of the checks."""
    return {f.name: str(f.type) for f in fields(DesignData)}


def _read_members(path: Path, hint: str) -> dict[str, np.ndarray]:
    """The arrays of the .npz at ``path`` named like DesignData fields; every check before any decompression."""
    known = _field_kinds()

    def refuse(problem: str) -> DesignFileError:
        return DesignFileError(f"{path}: not a readable design file ({problem}); {hint}")

    fh = open_binary(path, max_bytes=MAX_DESIGN_BYTES, what="design file", error=DesignFileError)
    arrays: dict[str, np.ndarray] = {}
    try:
        with fh, zipfile.ZipFile(fh) as zf:
            infos = zf.infolist()
            if len(infos) > 4 * len(known):
                raise refuse(f"{len(infos)} members, a design file has {len(known)}")
            names = [info.filename for info in infos]
            if len(set(names)) != len(names):
                raise refuse("duplicate members")
            total = 0
            wanted = []
            for info in infos:
                if not _MEMBER_NAME.fullmatch(info.filename):
                    raise refuse(f"unexpected member {excerpt(info.filename, 40)}")
                if info.flag_bits & 0x1 or info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                    raise refuse(f"member {info.filename} is encrypted or uses an unsupported compression")
                total += info.file_size
                if total > MAX_DESIGN_UNCOMPRESSED:
                    raise refuse(f"members would decompress to more than {MAX_DESIGN_UNCOMPRESSED >> 20} MiB")
                if info.filename[:-4] in known:
                    wanted.append(info)
            for info in wanted:
                name = info.filename[:-4]
                with zf.open(info) as member:
                    arrays[name] = _read_member(member, info, name, known[name], refuse)
    except DesignFileError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
        raise refuse(short_text(str(exc), 80)) from None
    return arrays


def _read_member(member, info: zipfile.ZipInfo, name: str, annotation: str, refuse) -> np.ndarray:
    """One .npy member: header checked (dtype, shape, declared size = size in the zip directory), then read."""
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        header = np.lib.format.read_array_header_1_0
    elif version in ((2, 0), (3, 0)):
        header = np.lib.format.read_array_header_2_0
    else:
        raise refuse(f"{name}: .npy format version {version}")
    shape, fortran, dtype = header(member, max_header_size=MAX_MEMBER_HEADER)
    kinds = _KINDS.get(annotation, "biufU")
    if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in kinds:
        raise refuse(f"{name}: dtype {excerpt(str(dtype), 30)} not allowed (expected kind {kinds})")
    scalar = annotation in ("int", "float", "str")
    if scalar and shape != ():
        raise refuse(f"{name}: expected a single value, got shape {excerpt(shape, 40)}")
    if not scalar and not 1 <= len(shape) <= MAX_NDIM:
        raise refuse(f"{name}: expected an array of 1 to {MAX_NDIM} dimensions, got shape {excerpt(shape, 40)}")
    nbytes = math.prod(shape) * dtype.itemsize
    if member.tell() + nbytes != info.file_size:
        raise refuse(f"{name}: shape {excerpt(shape, 40)} does not match its size in the archive")
    data = member.read(nbytes)
    if len(data) != nbytes:
        raise refuse(f"{name}: truncated")
    array = np.frombuffer(bytearray(data), dtype=dtype)
    return array.reshape(shape, order="F" if fortran else "C")


def _printable(text: str) -> str:
    return "".join(c if c.isascii() and c.isalnum() else "?" for c in text)


def load_design(
    path: str | Path,
    expected_hash: str | None = None,
    config_path: str | Path = "CONFIG",
    expected_sample_time: float | None = None,
    expected_grid: np.ndarray | None = None,
) -> DesignData:
    """Read and check a design file (any problem: one-line ``DesignFileError``). The file is untrusted: a
    regular file of at most ``MAX_DESIGN_BYTES``; members, dtypes, shapes and sizes checked before decompressing;
    no pickles; every table's full shape, the grid, the sample time (the config's, when given) and the index
    fields checked (`_check_contents`)."""
    path = Path(path)
    # the shipped design read for a file of one's own (it has none yet): its own is what to write, not the shipped
    out = path
    if config_path != "CONFIG" and same_file(path, DEFAULT_DESIGN):
        out = own_design_file(config_path)
    hint = REGENERATE_HINT.format(config=config_path, path=out)
    try:
        raw = _read_members(path, hint)
    except DesignFileError as exc:
        if str(exc).endswith("not found"):
            raise DesignFileError(f"{exc}; {hint}") from None
        raise
    version = int(raw["format_version"].item()) if "format_version" in raw else -1
    if version != FORMAT_VERSION:
        raise DesignFileError(f"{path}: design format version {version}, this ptw-rt reads {FORMAT_VERSION}; {hint}")
    missing = [f.name for f in fields(DesignData) if f.name not in raw]
    if missing:
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        raise DesignFileError(f"{path}: design file lacks {shown}; {hint}")
    for name in sorted(raw):
        # a table with a NaN loads and runs, every cycle DEGRADED with nothing said (a tampered or damaged file)
        if raw[name].dtype.kind in "fc" and not np.all(np.isfinite(raw[name])):
            raise DesignFileError(f"{path}: {name} holds values that are not finite (NaN or infinity); {hint}")
    problem = _check_contents(raw, expected_sample_time, expected_grid)
    if problem is not None:
        raise DesignFileError(f"{path}: {problem}; {hint}")
    values = {}
    for f in fields(DesignData):
        v = raw[f.name]
        if v.ndim == 0:
            v = v.item()
        values[f.name] = v
    data = DesignData(**values)
    if expected_hash is not None and data.config_hash != expected_hash:
        raise DesignFileError(
            f"{path}: made for another configuration (design hash {_printable(data.config_hash[:12])}, "
            f"config hash {expected_hash[:12]}): the vehicle or tuning changed since; {hint}"
        )
    return data


def load_design_for(settings, path: str | Path, config_path: str | Path = "CONFIG") -> DesignData:
    """`load_design` checked against the running configuration: its hash, sample time and speed grid, and the
    values a restored state file is bounded by (`_check_bounds`)."""
    est = settings.estimator
    design = load_design(path, settings.config_hash, config_path, est.sample_time, est.speed_grid_ms())
    _check_bounds(design, settings, path, config_path)
    _check_stable(design, path, config_path)
    return design


def error_dynamics_radii(design: DesignData) -> dict[str, float]:
    """The largest spectral radius of each observer's discrete error dynamics at the grid speeds: the UIHOSMO
    (diagnostics and on the sensors: pre-observer and zero dynamics), the adaptive observer, the fusion filter
    and every tyre hypothesis's evidence and publishing filters (e = Phi (I - K C) e). numpy alone, batched."""
    C = design.kf_C
    rho = spectral_radius

    def fusion(Phi: np.ndarray, K: np.ndarray) -> np.ndarray:
        return Phi @ (np.eye(Phi.shape[-1]) - K @ C)

    return {
        "uihosmo": max(rho(design.uh_Phi), rho(design.uh_Phi22)),
        "uio_sensors": max(rho(design.us_Phi), rho(design.us_Phi22)),
        "adaptive": rho(design.ad_Phi),
        "fusion": rho(fusion(design.kf_Phi, design.kf_K)),
        "tyre_bank": max(
            rho(fusion(design.tb_Phi, design.tb_K)),
            rho(fusion(design.tb_Phi, design.tb_K_pub)),
            rho(fusion(design.tb_bal_Phi, design.tb_bal_K)),
        ),
    }


def _check_stable(design: DesignData, path: str | Path, config_path: str | Path) -> None:
    """Every observer stable at every grid speed (``error_dynamics_radii`` below 1; ``ptw-rt design --check`` also
    checks between them): a design file with the configuration's hash and bounds but gains edited (finite: x1000)
    passed every check, and the estimator ran on filters that diverge."""
    radii = error_dynamics_radii(design)
    unstable = {name: r for name, r in radii.items() if not r < 1.0}
    if unstable:
        hint = REGENERATE_HINT.format(config=config_path, path=path)
        what = ", ".join(f"{name} {r:.4g}" for name, r in unstable.items())
        raise DesignFileError(
            f"{path}: unstable error dynamics at a grid speed (spectral radius {what}; a designed file's are below 1): "
            f"edited or corrupt; {hint}"
        )


def _check_bounds(design: DesignData, settings, path: str | Path, config_path: str | Path) -> None:
    """The design's nominal stiffness, its deviation bound and the tyre hypotheses, recomputed from the
    configuration: they bound what a state file may restore (`ptw_rt.io.state_file`), and a design file whose
    config hash is right but whose values are not (edited, or garbage that kept the hash) let the daemon restore
    a learned stiffness ten times the file's."""
    nominal = np.array(settings.vehicle.nominal_stiffness())
    expected = {
        "ad_theta_nominal": nominal,
        "ad_theta_bound": settings.estimator.stiffness_deviation_bound * nominal,
        "tb_scale": settings.estimator.tyre_bank.scales(),
    }
    for name, want in expected.items():
        have = getattr(design, name)
        if have.shape != want.shape or not np.allclose(have, want, rtol=1e-9, atol=0.0):
            hint = REGENERATE_HINT.format(config=config_path, path=path)
            raise DesignFileError(
                f"{path}: its {name} {excerpt(have.tolist())} is not what the configuration makes "
                f"({excerpt(want.tolist())}); {hint}"
            )
