"""`fp demo` runs end to end and finds the target that the confocal image hides (issue 2 foundation)."""

from __future__ import annotations

import json

from services.cli import main


def test_demo_writes_summary_and_figure(tmp_path) -> None:
    rc = main(["demo", "--frames", "2", "--speckle", "300", "--out", str(tmp_path)])
    assert rc == 0
    summary = json.loads((tmp_path / "demo_summary.json").read_text())
    assert len(summary["frames"]) == 2
    assert summary["max_error_m"] < 0.5e-3
    assert all(0 < f["gamma_max"] <= 1 for f in summary["frames"])
    assert (tmp_path / "demo_gamma_over_confocal.png").stat().st_size > 10_000


def test_bad_arguments_give_an_error_line(capsys) -> None:
    assert main(["demo", "--frames", "0"]) == 2
    assert "--frames: expected at least 1" in capsys.readouterr().err
