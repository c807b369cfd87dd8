"""`ptw-rt report`: plots of the estimates against truth and the baselines, with a markdown summary.

Our versions of seed 000's figures 8-12 (roll, rider torque, steer, lateral states, tyre forces) and
seed 001's Tables I-II (stiffness estimates against truth), plus the estimator's mode over time.
The settle time that `evaluate` does not score is shaded grey on every plot.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ptw_rt.core import layout as L  # noqa: N812 - the Estimates index table
from ptw_rt.errors import UserFacingError, output_error
from ptw_rt.eval.evaluate import SETTLE_S, Evaluation, evaluate_scenario
from ptw_rt.untrusted import check_output_file, one_line

DPI = 120
FIGURES = ("roll", "rider_torque", "steer", "states", "forces", "stiffness", "mode")

# (key, label, unit) of the metrics and baselines tables
METRIC_LABELS = {
    "roll_rmse_deg": ("roll RMSE", "deg"),
    "roll_max_err_deg": ("roll max error", "deg"),
    "roll_uihosmo_rmse_deg": ("roll RMSE, UIHOSMO alone (seed 000 case 2)", "deg"),
    "roll_uio_sensors_rmse_deg": ("roll RMSE, the UIHOSMO on the sensors' own roll", "deg"),
    "torque_rmse_nm": ("rider torque RMSE", "N m"),
    "torque_peak_nm": ("rider torque peak", "N m"),
    "torque_rmse_pct_of_peak": ("rider torque RMSE / peak", "%"),
    "steer_rate_rmse": ("steer rate RMSE", "rad/s"),
    "vy_rmse": ("lateral velocity RMSE", "m/s"),
    "fy_front_rmse_n": ("front lateral force RMSE", "N"),
    "fy_rear_rmse_n": ("rear lateral force RMSE", "N"),
    "stiffness_err_pct": ("stiffness error", "%"),
    "valid_share": ("share of time VALID", "-"),
    "ahrs_peer_roll_rmse_deg": ("Fusion AHRS peer roll RMSE", "deg"),
    "kinematic_roll_rmse_deg": ("kinematic roll RMSE", "deg"),
    "complementary_roll_rmse_deg": ("complementary roll RMSE", "deg"),
    "smo_fy_rmse_n": ("SMO lateral force RMSE", "N"),
    "sta_fy_rmse_n": ("STA lateral force RMSE", "N"),
    "direct_stiffness_err_pct": ("direct method stiffness error", "%"),
    "inversion_stiffness_err_pct": ("dynamic inversion stiffness error", "%"),
}


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:g}"
    return str(v)


def _rows(section: dict) -> list[tuple[str, str, str]]:
    """Flatten one level of nesting: ("stiffness error (front_cornering)", "%", "1.2")."""
    rows = []
    for key, value in section.items():
        label, unit = METRIC_LABELS.get(key, (key, ""))
        if isinstance(value, dict):
            for sub, v in value.items():
                rows.append((f"{label} ({sub})", unit, _fmt(v)))
        elif isinstance(value, list | tuple):
            rows.append((label, unit, ", ".join(_fmt(v) for v in value)))
        else:
            rows.append((label, unit, _fmt(value)))
    return rows


def _md_table(section: dict) -> list[str]:
    lines = ["| quantity | value | unit |", "|---|---:|---|"]
    lines += [f"| {label} | {value} | {unit} |" for label, unit, value in _rows(section)]
    return lines


def _summary(evaluation: Evaluation, files: list[Path]) -> str:
    r = evaluation.result
    perturbation = {k: v for k, v in (r.get("perturbation") or {}).items() if v is not None}
    pert = ", ".join(f"{k}={v}" for k, v in perturbation.items()) or "none"
    lines = [
        f"# ptw-rt report: {r.get('scenario')}",
        "",
        f"- scenario: `{r.get('scenario')}`",
        f"- seed: {r.get('seed')}",
        f"- perturbation: {pert}",
        f"- duration: {_fmt(r.get('duration_s'))} s, unscored settle time: {_fmt(r.get('settle_s'))} s",
    ]
    if r.get("crashed_at") is not None:
        lines.append(f"- the ride crashed at t = {_fmt(r['crashed_at'])} s")
    lines += ["", "## Metrics (ours)", ""] + _md_table(r.get("metrics", {}))
    lines += ["", "## Baselines", ""] + _md_table(r.get("baselines", {}))
    lines += ["", "## Figures", ""]
    lines += [f"- [{p.stem}]({p.name})" for p in files]
    lines += [""] + [f"![{p.stem}]({p.name})" for p in files]
    return "\n".join(lines) + "\n"


def _shade(ax, t: np.ndarray, settle: float) -> None:
    if t.size and t[0] < settle:
        ax.axvspan(t[0], min(settle, t[-1]), color="0.85", alpha=0.6, lw=0, label="_nolegend_")


def _finish(fig, axes, t, settle, path: Path) -> Path:
    for ax in axes:
        _shade(ax, t, settle)
        ax.grid(True, alpha=0.3)
        if t.size:
            ax.set_xlim(t[0], t[-1])
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    check_output_file(path)
    fig.savefig(path, dpi=DPI)
    return path


def _limits(*series, margin: float = 0.1) -> tuple[float, float]:
    """y-limits spanning the finite values of the given series (None skipped), plus a margin."""
    vals = [np.asarray(x)[np.isfinite(x)] for x in series if x is not None]
    vals = [v for v in vals if v.size]
    if not vals:
        return -1.0, 1.0
    lo, hi = min(float(v.min()) for v in vals), max(float(v.max()) for v in vals)
    pad = margin * (hi - lo) if hi > lo else 1.0
    return lo - pad, hi + pad


def write_report(evaluation: Evaluation, out_dir: Path) -> list[Path]:
    """Write the PNGs and summary.md of one evaluation into out_dir; return the written paths. One that cannot be
    written: ``OutputError`` (one line, exit code 74)."""
    try:
        return _write_report(evaluation, out_dir)
    except OSError as exc:
        raise output_error(out_dir, exc) from None


def _write_report(evaluation: Evaluation, out_dir: Path) -> list[Path]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise UserFacingError("report needs matplotlib: pip install 'ptw-rt[plot]'") from exc

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t, E, tr, b = evaluation.t, evaluation.estimates, evaluation.truth, evaluation.baselines
    settle = float(evaluation.result.get("settle_s", SETTLE_S))
    deg = np.degrees
    truth_style = {"color": "k", "lw": 1.6, "label": "truth", "zorder": 4}
    ours_style = {"color": "C3", "lw": 1.2, "label": "ours", "zorder": 5}
    files: list[Path] = []

    def figure(rows: int, cols: int = 1, height: float = 3.0):
        fig, axes = plt.subplots(rows, cols, figsize=(9.0 if cols == 1 else 11.0, height * rows), sharex=True)
        return fig, list(np.atleast_1d(axes).ravel())

    def save(fig, axes, name: str) -> None:
        try:
            files.append(_finish(fig, axes, t, settle, out_dir / f"{name}.png"))
        finally:
            plt.close(fig)

    # roll (seed 000 fig. 8): published estimate, truth and the peer on top (y-limits from truth and ours);
    # the UIHOSMO diagnostics in their own panel below: seed 000's case 2 (degrees off on the 10-bit encoder) and the
    # UIHOSMO on the sensors' own roll (issue #16, core.channel_kinematics)
    fig, axes = figure(2, height=3.2)
    ax = axes[0]
    roll_truth = deg(tr["roll"]) if "roll" in tr else None
    roll_ours = deg(E[:, L.E_ROLL])
    if roll_truth is not None:
        ax.plot(t, roll_truth, **truth_style)
    ax.plot(t, roll_ours, **ours_style)
    if b.get("ahrs_peer_roll") is not None:
        ax.plot(t, deg(b["ahrs_peer_roll"]), color="C4", lw=1.0, label="Fusion AHRS peer", zorder=3)
    ax.plot(t, deg(b["kinematic_roll"]), color="C2", lw=0.7, ls=":", alpha=0.7, label="kinematic")
    ax.plot(t, deg(b["complementary_roll"]), color="C1", lw=0.7, ls="-.", alpha=0.7, label="complementary")
    ax.set_ylim(*_limits(roll_ours, roll_truth))
    ax.set_ylabel("roll [deg]")
    ax.set_title(f"Roll angle - {evaluation.result.get('scenario')}")
    ax = axes[1]
    if roll_truth is not None:
        ax.plot(t, roll_truth, **{**truth_style, "lw": 1.0})
    ax.plot(t, deg(E[:, L.E_ROLL_UIHOSMO]), color="C0", lw=0.6, alpha=0.6, label="UIHOSMO case 2 (diagnostic)")
    ax.plot(t, deg(E[:, L.E_ROLL_UIO_SENSORS]), color="C2", lw=0.8, label="UIHOSMO on the sensors, its own roll")
    ax.set_ylabel("roll [deg]")
    save(fig, axes, "roll")

    # rider torque (fig. 9)
    fig, axes = figure(1, height=4.0)
    ax = axes[0]
    if "rider_torque" in tr:
        ax.plot(t, tr["rider_torque"], **truth_style)
    ax.plot(t, E[:, L.E_RIDER_TORQUE], **ours_style)
    # the plausibility monitor's channel, thin and behind the published estimate
    ax.plot(t, E[:, L.E_TORQUE_UIO_SENSORS], color="C2", lw=0.5, alpha=0.6, label="UIHOSMO on the sensors", zorder=1)
    ax.set_ylabel("rider steering torque [N m]")
    ax.set_title("Rider torque (unknown input)")
    save(fig, axes, "rider_torque")

    # steer angle and rate (fig. 10)
    fig, axes = figure(2)
    for ax, col, key, label in (
        (axes[0], L.E_STEER, "steer", "steer angle [deg]"),
        (axes[1], L.E_STEER_RATE, "steer_rate", "steer rate [deg/s]"),
    ):
        if key in tr:
            ax.plot(t, deg(tr[key]), **truth_style)
        ax.plot(t, deg(E[:, col]), **ours_style)
        ax.set_ylabel(label)
    axes[0].set_title("Steering")
    save(fig, axes, "steer")

    # lateral velocity (fig. 11)
    fig, axes = figure(1, height=4.0)
    ax = axes[0]
    if "lat_vel" in tr:
        ax.plot(t, tr["lat_vel"], **truth_style)
    ax.plot(t, E[:, L.E_LAT_VEL], **ours_style)
    ax.set_ylabel("lateral velocity [m/s]")
    ax.set_title("Lateral velocity")
    save(fig, axes, "states")

    # tyre lateral forces (fig. 12)
    fig, axes = figure(2)
    for ax, col, key, side in ((axes[0], L.E_FY_FRONT, "fy_front", "front"), (axes[1], L.E_FY_REAR, "fy_rear", "rear")):
        if key in tr:
            ax.plot(t, tr[key], **truth_style)
        ax.plot(t, E[:, col], **ours_style)
        ax.plot(t, b[f"smo_{key}"], color="C0", lw=0.8, ls="--", label="SMO")
        ax.plot(t, b[f"sta_{key}"], color="C2", lw=0.8, ls=":", label="STA")
        ax.set_ylabel(f"{side} Fy [N]")
    axes[0].set_title("Tyre lateral forces")
    save(fig, axes, "forces")

    # stiffnesses (seed 001 Tables I-II as time histories)
    fig, axes = figure(2, 2)
    panels = (
        (L.E_C_ALPHA_FRONT, "c_alpha_front", "front cornering [N/rad]", L.V_CORNERING),
        (L.E_C_GAMMA_FRONT, "c_gamma_front", "front camber [N/rad]", L.V_CAMBER),
        (L.E_C_ALPHA_REAR, "c_alpha_rear", "rear cornering [N/rad]", L.V_CORNERING),
        (L.E_C_GAMMA_REAR, "c_gamma_rear", "rear camber [N/rad]", L.V_CAMBER),
    )
    valid_bits = E[:, L.E_VALID].astype(np.int64)
    for ax, (col, key, label, bit) in zip(axes, panels, strict=True):
        if key in tr:
            ax.plot(t, tr[key], **truth_style)
        ax.plot(t, E[:, col], **{**ours_style, "lw": 0.6, "alpha": 0.35, "label": "estimate"})
        valid = (valid_bits & bit) != 0
        if valid.any():
            ax.plot(
                t, np.where(valid, E[:, col], np.nan), color="C3", lw=2.2, zorder=6, label="estimate, flagged valid"
            )
            ax.fill_between(
                t,
                0,
                1,
                where=valid,
                transform=ax.get_xaxis_transform(),
                color="C2",
                alpha=0.15,
                lw=0,
                label="valid bit set",
            )
        ax.set_ylabel(label)
    fig.suptitle("Tyre stiffnesses")
    for ax in axes[:2]:
        ax.tick_params(labelbottom=False)
    axes[2].set_xlabel("time [s]")
    save(fig, axes, "stiffness")

    # mode and speed
    fig, axes = figure(2)
    axes[0].step(t, E[:, L.E_MODE], where="post", color="C3", lw=1.2)
    axes[0].set_yticks(range(len(L.MODE_NAMES)), L.MODE_NAMES)
    axes[0].set_ylim(-0.5, len(L.MODE_NAMES) - 0.5)
    axes[0].set_ylabel("mode")
    axes[0].set_title("Estimator mode")
    kmh = 3.6
    if "speed" in tr:
        axes[1].plot(t, kmh * tr["speed"], **truth_style)
    axes[1].plot(t, kmh * E[:, L.E_SPEED], **{**ours_style, "label": "conditioned"})
    axes[1].set_ylabel("speed [km/h]")
    save(fig, axes, "mode")

    summary = out_dir / "summary.md"
    check_output_file(summary)
    summary.write_text(_summary(evaluation, files), encoding="utf-8")
    return [*files, summary]


def run_report(args) -> int:
    evaluation = evaluate_scenario(args.scenario, args.seed, args.perturb, args.config, args.design_file)
    for path in write_report(evaluation, args.out):
        print(one_line(str(path)))
    return 0
