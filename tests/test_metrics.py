"""Contrast, PFA and precision formulas against the paper's figures (docs/design.md §4.8–4.10)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore import Grid, contrasts, cramer_rao_precision, detect, pfa


def test_pfa_matches_paper_figure_s15() -> None:
    # Paper S6: C = (γ_max/γ_M)² ≈ 6 and L ≈ 25³ give a false-alarm probability ≈ 1e-8.
    assert 3e-9 < pfa(6.0, 25**3) < 3e-8
    # Monotonic: more grains, more false alarms; more contrast, fewer.
    assert pfa(6.0, 10**3) < pfa(6.0, 25**3) < pfa(6.0, 100**3)
    assert pfa(3.0, 25**3) > 0.99
    assert pfa(np.array([4.0, 5.0, 6.0]), 1e4).shape == (3,)


def test_contrasts_on_a_known_map() -> None:
    grid = Grid.centred((0.0, 10e-3), (41, 41), 1e-4)
    gam = np.full(grid.shape, 0.1, dtype=np.float32)
    gam[20, 20] = 0.8
    c_gamma, c = contrasts(gam, grid, grid.position((20, 20)), 3e-4)
    assert c_gamma == pytest.approx(8.0, rel=1e-5)
    assert c == pytest.approx(64.0, rel=1e-5)


def test_precision_is_dimensionally_consistent() -> None:
    lam = 1500 / 2.2e6
    lat, ax = cramer_rao_precision(lam, lam, 4.0)
    assert lat == pytest.approx(lam / 2)
    assert ax == pytest.approx(lam / (4 * np.sqrt(2) * np.pi * 2))
    # Scaling with wavelength (a length): both precisions scale linearly.
    lat2, ax2 = cramer_rao_precision(2 * lam, 2 * lam, 4.0)
    assert lat2 == pytest.approx(2 * lat) and ax2 == pytest.approx(2 * ax)


def test_detect_finds_two_peaks_with_low_pfa() -> None:
    grid = Grid.centred((0.0, 20e-3), (80, 80), 1.5e-4)
    rng = np.random.default_rng(0)
    gam = np.abs(rng.standard_normal(grid.shape) + 1j * rng.standard_normal(grid.shape)).astype(np.float32) * 0.05
    gam[20, 30] = 1.0
    gam[60, 50] = 0.8
    dets = detect(gam, grid, wavelength=0.7e-3, aperture=20e-3, bandwidth=0.8e6, c0=1500, n_peaks=2)
    assert [d.index for d in dets] == [[20, 30], [60, 50]]
    assert all(d.pfa < 1e-6 and d.c_gamma > 5 for d in dets)
