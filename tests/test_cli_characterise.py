"""`fp characterise`: mirror-dictionary orientation maps from a UFF file, checked against fibre truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fpcore import PlaneWaveSequence, Probe
from fpcore.born import born_points
from fpcore.io import write_uff
from services.cli import main


@pytest.mark.parametrize("flags", [[], ["--time-weighting"]])
def test_characterise_recovers_fibre_orientation(tmp_path, flags: list[str]) -> None:
    """Two Born fibres, noiseless: their orientation within 5°. With each frame weighted by its own 1/v(t)
    (docs/design.md §4.14) the fibres' echoes are the frame's whole energy, which the weighting takes for
    background: 8° measured against 0.5° unweighted, bounded at 10° (the option's cost where targets rule the
    frame; README, "With the time weighting")."""
    probe = Probe.linear(48, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.from_angles(np.linspace(-12, 12, 7))
    lam = 1540 / 3.5e6
    fibres, pts = [], []
    for x, alpha in ((-2.5e-3, np.deg2rad(12.0)), (2.5e-3, np.deg2rad(-10.0))):
        c = np.array([x, 0.0, 15e-3])
        ls = np.arange(-1e-3, 1e-3 + 1e-9, lam / 8)
        pts.append(c + ls[:, None] * np.array([np.cos(alpha), 0.0, np.sin(alpha)]))
        fibres.append({"position_m": c.tolist(), "alpha_rad": float(alpha), "length_m": 2e-3})
    pts = np.concatenate(pts)
    acq = born_points(probe, seq, pts, np.ones(len(pts)), n_t=700)
    acq.truth = {"fibres": fibres}
    write_uff(tmp_path / "f.uff", acq)
    out = tmp_path / "c.json"
    rc = main(
        [
            "characterise",
            str(tmp_path / "f.uff"),
            "--angles=-30:30:3",
            "--lengths",
            "1mm:3mm:3",
            "--x=-6mm:6mm",
            "--z",
            "11mm:19mm",
            "--json",
            str(out),
            "--npz",
            str(tmp_path / "c.npz"),
            "--png",
            str(tmp_path / "c.png"),
            *flags,
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["truth_fibres_compared"] == 2
    assert np.rad2deg(doc["truth_alpha_error_rad_median"]) <= (10.0 if flags else 5.0)
    maps = np.load(tmp_path / "c.npz")
    assert maps["alpha_rad"].shape == maps["gamma_max"].shape
    assert (tmp_path / "c.png").stat().st_size > 10_000


def test_bad_angles_are_one_error_line(tmp_path, capsys) -> None:
    assert main(["characterise", str(tmp_path / "none.uff"), "--angles=10:-10:5"]) == 2
    assert "--angles" in capsys.readouterr().err
