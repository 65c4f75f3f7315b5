"""`fp locate` on UFF files: positions within 1 mm of the truth, units, and one-line user errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fpcore import Acquisition, PlaneWaveSequence, Probe
from fpcore.born import born_points
from fpcore.io import write_uff
from services.cli import main
from services.units import UnitError, parse_band, parse_length, parse_position


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("loc")
    rng = np.random.default_rng(1)
    probe = Probe.linear(48, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.from_angles(np.linspace(-12, 12, 7))
    offs = rng.uniform(-1.2e-3, 1.2e-3, (10, 3))
    offs[:, 1] = 0.0
    amps = rng.uniform(0.5, 1.0, 10)
    r0 = np.array([0.0, 0.0, 15e-3])
    cal = born_points(probe, seq, r0 + offs, amps, n_t=800)
    cal.truth = {"targets": [{"name": "marker", "position_m": r0.tolist(), "diameter_m": 2.4e-3}]}
    write_uff(d / "cal.uff", cal)
    # Speckle: 3000 weak Born points (≈ 5 per resolution cell: developed speckle, the null hypothesis of
    # the PFA), with the backscattered energy of 300 points of amplitude 0.4. (300 strong points — sparse,
    # each as bright as a marker point — are themselves coherent reflectors that a marker fingerprint
    # partly matches: significant against speckle, not the target.)
    n_sp = 3000
    speckle = np.stack([rng.uniform(-7e-3, 7e-3, n_sp), np.zeros(n_sp), rng.uniform(8e-3, 25e-3, n_sp)], axis=1)
    frames = []
    for k in range(2):
        t = np.array([-1e-3 + k * 1e-3, 0.0, 14e-3 + 2e-3 * k])
        a = born_points(
            probe,
            seq,
            np.concatenate([t + offs, speckle]),
            np.concatenate([amps, 0.4 * np.sqrt(300 / n_sp) * rng.standard_normal(n_sp)]),
            n_t=800,
            frame_index=k,
        )
        a.truth = {"targets": [{"name": "marker", "position_m": t.tolist()}]}
        frames.append(a)
    write_uff(d / "data.uff", frames)
    bad = Acquisition(cal.rf[:, :, ::2].copy(), cal.fs / 2, cal.t0, cal.c0, cal.probe, cal.sequence)
    write_uff(d / "bad_cal.uff", bad)
    return d


def test_locate_finds_targets_within_1mm(files, tmp_path) -> None:
    out = tmp_path / "loc.json"
    png = tmp_path / "loc.png"
    rc = main(
        [
            "locate",
            str(files / "data.uff"),
            "--calibration",
            str(files / "cal.uff"),
            "--z",
            "8mm:24mm",
            "--n-freq",
            "24",
            "--json",
            str(out),
            "--png",
            str(png),
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    assert [f["frame_index"] for f in doc["frames"]] == [0, 1]
    for f in doc["frames"]:
        det = f["detections"][0]
        assert det["truth_error_m"] < 1e-3
        assert 0 < det["gamma_max"] <= 1 and det["pfa"] < 1e-6
        assert set(det) >= {"position_m", "precision_m", "c_gamma", "c_pfa"}
    assert png.stat().st_size > 10_000


def test_mismatched_calibration_is_one_error_line(files, capsys) -> None:
    rc = main(["locate", str(files / "data.uff"), "--calibration", str(files / "bad_cal.uff")])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sampling_frequency" in err[0]


def test_missing_file_and_bad_unit_are_clear(files, capsys) -> None:
    assert main(["locate", str(files / "nope.uff"), "--model", "point"]) == 2
    assert main(["locate", str(files / "data.uff"), "--model", "point", "--z", "8furlong:20mm"]) == 2
    err = capsys.readouterr().err
    assert "nope.uff" in err and "--z" in err and "Traceback" not in err


def test_units() -> None:
    assert parse_length("25mm") == pytest.approx(0.025)
    assert parse_length("0.02") == pytest.approx(0.02)
    assert parse_position("0,25mm") == pytest.approx([0.0, 0.025])
    assert parse_position("1,2,25mm") == pytest.approx([1e-3, 2e-3, 25e-3])
    assert parse_band("1.8:2.6MHz") == pytest.approx((1.8e6, 2.6e6))
    with pytest.raises(UnitError, match="--band"):
        parse_band("2.6MHz:1.8MHz")


def test_velocity_uses_the_motion_aware_fingerprint(tmp_path, capsys) -> None:
    """`fp simulate fast-cylinder` then `fp locate --velocity`: the static fingerprint's best peak (taken at
    any PFA) misplaces the fast target by millimetres, the motion-aware one finds it (at the default
    PFA < 1e-3); data without a PRF is refused."""
    assert main(["simulate", "fast-cylinder", "--quick", "--out", str(tmp_path), "--frames", "1"]) == 0
    errors = {}
    for label, extra in (("static", ["--max-pfa", "1"]), ("moving", ["--velocity", "0.25,0.1"])):
        out = tmp_path / f"{label}.json"
        assert (
            main(
                [
                    "locate",
                    str(tmp_path / "frames.uff"),
                    "--calibration",
                    str(tmp_path / "calibration_cylinder.uff"),
                    "--x=-4mm:2mm",
                    "--z",
                    "22mm:28mm",
                    "--json",
                    str(out),
                    *extra,
                ]
            )
            == 0
        )
        errors[label] = json.loads(out.read_text())["frames"][0]["detections"][0]["truth_error_m"]
    assert errors["moving"] < 0.2e-3 < 1e-3 < errors["static"]
    capsys.readouterr()
    assert (
        main(
            [
                "locate",
                str(tmp_path / "frames.uff"),
                "--calibration",
                str(tmp_path / "calibration_cylinder.uff"),
                "--velocity",
                "fast",
            ]
        )
        == 2
    )
    assert "--velocity: expected VX,VZ[,VY] in m/s" in capsys.readouterr().err


def test_locate_with_the_single_scattering_null(files, tmp_path) -> None:
    """--null-single-scattering (docs/design.md §4.9, eq. B2) runs end to end. The marker is a small
    cluster of Born points (fingerprint gain G ≈ 7) that stands out of the confocal image of a Born speckle:
    exactly what that null describes ("single scatterers as bright as the image shows"), so its PFA rises
    by orders of magnitude — the option's documented price — while it stays among the top peaks."""
    pfas = {}
    for flag in ([], ["--null-single-scattering"]):
        out = tmp_path / f"loc{len(flag)}.json"
        args = ["locate", str(files / "data.uff"), "--calibration", str(files / "cal.uff"), "--z", "8mm:24mm"]
        assert main([*args, "--n-freq", "24", "--max-pfa", "1", "--targets", "3", *flag, "--json", str(out)]) == 0
        frames = json.loads(out.read_text())["frames"]
        on = [[d for d in f["detections"] if d["truth_error_m"] < 1e-3] for f in frames]
        assert all(len(m) == 1 for m in on)  # the marker is one of the three most significant peaks
        pfas[bool(flag)] = [m[0]["pfa"] for m in on]
    assert all(a < 1e-6 for a in pfas[False])
    assert all(b > 1e3 * a for a, b in zip(pfas[False], pfas[True], strict=True)), pfas


def test_locate_with_the_time_weighting(files, tmp_path) -> None:
    """--time-weighting (docs/design.md §4.14, eq. W1) runs end to end: each frame weighted by its own 1/v(t).
    In this speckle, stationary over the marker's depths, the marker stays detected where it is."""
    out = tmp_path / "loc.json"
    args = ["locate", str(files / "data.uff"), "--calibration", str(files / "cal.uff"), "--n-freq", "24"]
    assert main([*args, "--time-weighting", "--json", str(out)]) == 0
    frames = json.loads(out.read_text())["frames"]
    for f in frames:
        (d,) = f["detections"]
        assert d["truth_error_m"] < 1e-3, d
        assert d["pfa"] < 1e-3, d


def test_locate_with_the_union_of_both_statistics(files, tmp_path, capsys) -> None:
    """--union (docs/design.md §4.14, eq. W2) maps each frame as recorded and weighted by 1/v(t) and keeps the more
    significant map's detection at twice its PFA: the marker is found where it is, each frame names the map it
    came from, and its PFA is twice the one that map alone reports."""
    args = ["locate", str(files / "data.uff"), "--calibration", str(files / "cal.uff"), "--n-freq", "24"]
    out, alone = tmp_path / "union.json", {}
    assert main([*args, "--union", "--json", str(out)]) == 0
    assert "statistic: the union" in capsys.readouterr().out
    union = json.loads(out.read_text())["frames"]
    for flag, name in (([], "as recorded"), (["--time-weighting"], "weighted")):
        path = tmp_path / f"{name}.json"
        assert main([*args, *flag, "--max-pfa", "1", "--json", str(path)]) == 0
        alone[name] = json.loads(path.read_text())["frames"]
    for k, f in enumerate(union):
        (d,) = f["detections"]
        assert d["truth_error_m"] < 1e-3, d
        (same,) = alone[f["statistic"]][k]["detections"]
        assert d["position_m"] == same["position_m"]
        assert d["pfa"] == pytest.approx(min(1.0, 2 * same["pfa"]), rel=1e-9)
        other = alone["weighted" if f["statistic"] == "as recorded" else "as recorded"][k]["detections"][0]
        assert same["pfa"] <= other["pfa"]  # the union took the more significant map
    assert main([*args, "--union", "--time-weighting"]) == 2
    assert "--union: maps the frames both as recorded and weighted" in capsys.readouterr().err
