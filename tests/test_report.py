"""`ptw-rt report`: every figure and the summary are written for a short ride."""

from __future__ import annotations

import pytest

pytest.importorskip("matplotlib")

from ptw_rt.eval.evaluate import evaluate_ride  # noqa: E402
from ptw_rt.eval.report import FIGURES, write_report  # noqa: E402
from ptw_rt.sim.ride import simulate  # noqa: E402


def test_write_report_writes_all_figures_and_summary(tmp_path):
    evaluation = evaluate_ride(simulate("dlc_100", duration=8.0))
    out = tmp_path / "report"
    written = write_report(evaluation, out)

    names = {p.name for p in written}
    for fig in FIGURES:
        assert f"{fig}.png" in names
        png = out / f"{fig}.png"
        assert png.is_file() and png.stat().st_size > 0
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = out / "summary.md"
    assert summary in written and summary.stat().st_size > 0
    text = summary.read_text()
    assert "dlc_100" in text
    rmse = evaluation.result["metrics"]["roll_rmse_deg"]
    assert rmse is not None
    assert f"| roll RMSE | {rmse:g} | deg |" in text
    for fig in FIGURES:
        assert f"({fig}.png)" in text
