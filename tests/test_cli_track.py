"""`fp track` (offline tracking with the processor's pipeline) and the calibration safeguards of
`fp locate`/`fp track`: --r0 against the recorded position, negative coordinates, --gate."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.cli import join_negative_values, main


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("track")
    # The 2-D analogue in its legacy conventions (calibrations at the true initial positions, shallower, a
    # background gain): in the paper's conventions this implementation does not find the cylinders (README).
    args = ["simulate", "sinking-cylinder", "--quick", "--out", str(d), "--frames", "4", "--conventions", "legacy"]
    assert main(args) == 0
    return d


def test_track_writes_locate_layout_with_tracks(sim, tmp_path) -> None:
    out, png = tmp_path / "t.json", tmp_path / "t.png"
    assert (
        main(
            [
                "track",
                str(sim / "frames.uff"),
                "--calibration",
                str(sim / "calibration_cylinder2.uff"),
                "--json",
                str(out),
                "--png",
                str(png),
            ]
        )
        == 0
    )
    doc = json.loads(out.read_text())
    assert doc["fingerprint"] == "cylinder2"  # named after the target the calibration records
    assert [f["frame_index"] for f in doc["frames"]] == [0, 1, 2, 3]
    truth = np.array(json.loads((sim / "truth.json").read_text())["frames"][0]["targets"][1]["position_m"])
    seen = set()
    for f in doc["frames"]:
        assert isinstance(f["detections"], list)
        for det in f["detections"]:
            assert det["pfa"] < 1e-3 and np.linalg.norm(np.array(det["position_m"]) - truth) < 1e-3
        for tr in f["tracks"]:
            assert set(tr) >= {"id", "position_m", "velocity_m_s", "pfa", "status"}
            assert tr["status"] in ("tentative", "confirmed", "coasting", "lost")
            assert tr["truth_error_m"] < 1e-3
            seen.add(tr["id"])
    assert len(seen) == 1  # one target, one track id
    assert doc["frames"][-1]["tracks"][0]["status"] in ("confirmed", "coasting")
    assert png.stat().st_size > 10_000


def test_negative_values_are_joined_to_their_option() -> None:
    assert join_negative_values(["locate", "d.uff", "--r0", "-1.5mm,11mm", "--x", "-4mm:4mm", "--targets", "2"]) == [
        "locate",
        "d.uff",
        "--r0=-1.5mm,11mm",
        "--x=-4mm:4mm",
        "--targets",
        "2",
    ]
    assert join_negative_values(["--velocity", "-.2,0.1", "-h"]) == ["--velocity=-.2,0.1", "-h"]
    assert join_negative_values(["--json", "-"]) == ["--json", "-"]  # not a number: left alone


def test_r0_far_from_the_recorded_position_is_refused_unless_forced(sim, tmp_path, capsys) -> None:
    data, cal = str(sim / "frames.uff"), str(sim / "calibration_cylinder2.uff")  # recorded r0 (4.75, 0, 23.5) mm
    assert main(["locate", data, "--calibration", cal, "--r0", "-4.75mm,23.5mm", "--frames", "0"]) == 2
    err = capsys.readouterr().err
    assert "--r0" in err and "9.50 mm laterally" in err and "--force" in err and "Traceback" not in err
    out = tmp_path / "forced.json"
    assert (
        main(
            [
                "locate",
                data,
                "--calibration",
                cal,
                "--r0",
                "-4.75mm,23.5mm",
                "--frames",
                "0",
                "--force",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    assert "warning" in capsys.readouterr().out
    # Within one resolution cell of the recorded position: accepted silently.
    assert main(["locate", data, "--calibration", cal, "--r0", "4.8mm,23.5mm", "--frames", "0"]) == 0
    assert "warning" not in capsys.readouterr().out


def test_gate_none_and_measured_diameter(sim, tmp_path, capsys) -> None:
    data, cal = str(sim / "frames.uff"), str(sim / "calibration_cylinder1.uff")
    out = tmp_path / "g.json"
    assert main(["locate", data, "--calibration", cal, "--gate", "none", "--frames", "0", "--json", str(out)]) == 0
    assert "no gate" in capsys.readouterr().out
    assert isinstance(json.loads(out.read_text())["frames"][0]["detections"], list)


def test_no_whitening_keeps_the_gated_calibration(sim, tmp_path, capsys) -> None:
    """--no-whitening: F = R0′ (paper S2, Fig. S7a); said on screen, and the run still locates."""
    data, cal = str(sim / "frames.uff"), str(sim / "calibration_cylinder1.uff")
    out = tmp_path / "w.json"
    assert main(["locate", data, "--calibration", cal, "--no-whitening", "--frames", "0", "--json", str(out)]) == 0
    assert "F = R0′ (not whitened)" in capsys.readouterr().out
    assert isinstance(json.loads(out.read_text())["frames"][0]["detections"], list)


def test_no_whitening_needs_a_calibration(sim, capsys) -> None:
    """A model has no modes to whiten: --no-whitening with --model is a clear error, not ignored."""
    assert main(["locate", str(sim / "frames.uff"), "--model", "point", "--no-whitening", "--frames", "0"]) == 2
    assert "--no-whitening: applies to a --calibration" in capsys.readouterr().err


def test_track_with_the_union_names_each_frames_map(sim, tmp_path, capsys) -> None:
    """`fp track --union` (docs/design.md §4.14, eq. W2): each frame's row names the map kept, and its detections'
    PFA is twice that map's own: never below what the same map reports alone."""
    out = {}
    for flag in ("--union", "--time-weighting", None):
        path = tmp_path / f"{flag}.json"
        args = ["track", str(sim / "frames.uff"), "--calibration", str(sim / "calibration_cylinder2.uff")]
        assert main([*args, "--json", str(path), *([flag] if flag else [])]) == 0
        out[flag] = json.loads(path.read_text())["frames"]
    assert "eq. W2: PFA × 2" in capsys.readouterr().out
    for u, w, p in zip(out["--union"], out["--time-weighting"], out[None], strict=True):
        assert u["statistic"] in ("as recorded", "weighted") and "statistic" not in p
        alone = {"as recorded": p, "weighted": w}[u["statistic"]]
        for d, a in zip(u["detections"], alone["detections"], strict=False):
            assert d["pfa"] == pytest.approx(min(1.0, 2 * a["pfa"]), rel=1e-3)
        assert u["detections"] and u["tracks"]
