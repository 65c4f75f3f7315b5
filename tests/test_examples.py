"""examples/ runs (issue 14): simulated UFF → γ-maps → figure → tracks, on quick sizes."""

from __future__ import annotations

import importlib.util
from pathlib import Path

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "simulate_locate_track.py"


def test_simulate_locate_track_example(tmp_path, capsys) -> None:
    spec = importlib.util.spec_from_file_location("simulate_locate_track", EXAMPLE)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "ex"
    result = mod.main(["--out", str(out), "--frames", "3", "--spacing", "0.5mm"])
    for name in ("frames.uff", "calibration_cylinder1.uff", "tracks.json"):
        assert (out / name).is_file()
    assert (out / "gamma.png").stat().st_size > 10_000
    rows = result["rows"]
    assert [r["frame"] for r in rows] == [0, 1, 2]  # one track, every frame
    assert {r["track"] for r in rows} == {1} and rows[-1]["status"] == "confirmed"
    assert all(r["error_m"] < 1e-3 for r in rows)  # the cylinder, within a millimetre of its truth
    assert "frame 2: track 1 confirmed" in capsys.readouterr().out
