"""The paper's gain law G = C_γ/C_I ∼ N_S N_T (Supplementary S4) in its own setting, stationary white noise, on
targets whose degrees of freedom are known: the measurement `bench/gain_law.py` makes on the spheres."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from gain_law import SplitGain, white_noise_like  # noqa: E402

import fpcore  # noqa: E402
from fpcore.born import born_points  # noqa: E402

BAND = (2.0e6, 3.0e6)


def white_noise_gain(n_points: int, spacing: float = 2e-3) -> tuple[float, float]:
    """G of a row of `n_points` equal point reflectors at 15 mm (resolved: the lateral resolution there is
    ≈ 0.6 mm), the fingerprint their own ungated echo, over three draws of white noise; and its N_S."""
    probe = fpcore.Probe.linear(48, 0.3e-3, 2.5e6, 1.5e6)
    seq = fpcore.PlaneWaveSequence.from_angles(np.linspace(-12, 12, 7))
    r0 = np.array([0.0, 0.0, 15e-3])
    xs = (np.arange(n_points) - (n_points - 1) / 2) * spacing
    pts = np.stack([xs, np.zeros(n_points), np.full(n_points, r0[2])], axis=1)
    echo = born_points(probe, seq, pts, np.ones(n_points), n_t=800)
    imager = fpcore.Imager(fpcore.ImagingConfig(fpcore.Grid.for_acquisition(echo, BAND), band=BAND))
    fp = fpcore.from_calibration(
        echo,
        r0,
        imager.out_sines_for(echo),
        BAND,
        None,
        diameter=0.0,
        gate=False,
        angular_filter=False,
        svd_threshold=0.1,
    )
    split = SplitGain(imager, fp, echo, r0, 0.0)
    g = [split.against(white_noise_like(echo, (1.5e6, 3.5e6), seed=s))["G"] for s in (1, 2, 3)]
    return float(np.mean(g)), fp.n_s


def test_a_point_gains_nothing_over_the_confocal_image() -> None:
    """One point is one degree of freedom (N_S = N_T = 1): the fingerprint is the confocal focus, G = 1."""
    g, n_s = white_noise_gain(1)
    assert n_s == pytest.approx(1.0, abs=0.05)
    assert g == pytest.approx(1.0, abs=0.25)


def test_gain_counts_the_resolved_points() -> None:
    """K resolved equal points: the confocal image's brightest point holds one of them, the fingerprint all K
    (N_S ≈ K): G ≈ K, the law's N_S N_T with N_T = 1."""
    g5, n_s5 = white_noise_gain(5)
    assert n_s5 == pytest.approx(5.0, abs=1.0)
    assert 3.5 < g5 < 6.5


def test_gain_counts_energy_not_modes() -> None:
    """Five points within one resolution cell: the whitened fingerprint keeps two modes, but nearly all the
    energy is in one, which the confocal focus already holds: G ≈ 1, not N_S."""
    g, n_s = white_noise_gain(5, spacing=0.2e-3)
    assert n_s >= 2.0
    assert g == pytest.approx(1.0, abs=0.25)
