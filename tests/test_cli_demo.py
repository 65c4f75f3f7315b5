"""`fp demo`: publisher → processor → recorder on loopback with the sinking-sphere scenario (issue 4)."""

from __future__ import annotations

import json

from services.cli import main


def test_demo_streams_records_and_finds_both_spheres(tmp_path) -> None:
    rc = main(["demo", "--frames", "2", "--out", str(tmp_path)])
    assert rc == 0
    summary = json.loads((tmp_path / "pipeline_summary.json").read_text())
    assert summary["frames_processed"] == 2 and summary["rejected"] == 0
    for frame in summary["frames"]:
        assert {d["fingerprint"] for d in frame["detections"]} == {"sphere1", "sphere2"}
        for d in frame["detections"]:
            assert d["truth_error_m"] < 1e-3 and d["contrast_c_gamma"] >= 5 and d["pfa"] < 1e-6
    files = summary["recording"]["files"]
    assert files and all(f.endswith(".mcap") for f in files)
    assert (tmp_path / "demo_gamma_over_confocal.png").stat().st_size > 10_000
    assert (tmp_path / "demo_tracks.png").stat().st_size > 10_000


def test_bad_arguments_give_an_error_line(capsys) -> None:
    assert main(["demo", "--frames", "0"]) == 2
    assert "--frames: expected at least 1" in capsys.readouterr().err
