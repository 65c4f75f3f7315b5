"""Contrasts, precision and the false-alarm probability (docs/design.md §4.8–4.10).

The PFA is checked where the answer is known: on target-free maps (the paper's S6 null, i.i.d.
reflection-matrix coefficients) the fraction of maps whose most significant peak reports PFA < α must
stay ≤ α (with the sampling slack of a finite run), and a real target must still be found.
"""

from __future__ import annotations

import numpy as np
import pytest

import fpcore
from fpcore import Grid, contrasts, cramer_rao_precision, detect, paper_pfa
from fpcore.acquisition import PlaneWaveData
from fpcore.cfar import ec_density, max_tail, resels_box
from fpcore.fingerprint import point_fingerprint


def test_paper_pfa_matches_paper_figure_s15() -> None:
    # Paper S6 / Fig. S15: C ≈ 6 and L ≈ 25³ give ≈ 1e-8 — with C the amplitude ratio γ_max/⟨γ⟩ (the paper
    # prints (γ_max/γ_M)², a slip: fed the squared ratio, exp(−π·36²/4) would give ≈ 1e-440).
    assert 3e-9 < paper_pfa(6.0, 25**3) < 3e-8
    assert paper_pfa(6.0, 10**3) < paper_pfa(6.0, 25**3) < paper_pfa(6.0, 100**3)
    assert paper_pfa(3.0, 25**3) > 0.99


def test_random_field_tail_limits() -> None:
    # One resel and no smoothness terms: the maximum's tail is the exponential tail of one cell.
    assert max_tail(5.0, np.array([1.0])) == pytest.approx(-np.expm1(-np.exp(-5.0)), rel=1e-9)
    # More resels, more false alarms; a higher threshold, fewer.
    r1, r2 = resels_box(np.array([10.0, 10.0])), resels_box(np.array([40.0, 40.0]))
    assert max_tail(12.0, r1) < max_tail(12.0, r2)
    assert max_tail(14.0, r2) < max_tail(12.0, r2)
    # Never rising with the threshold, up to where e^{-t} underflows (a PFA of 0, not 1).
    r3 = resels_box(np.array([40.0, 40.0, 80.0]))
    tails = [max_tail(t, r3) for t in np.linspace(0.0, 700.0, 1401)]
    assert all(b <= a for a, b in zip(tails, tails[1:], strict=False))
    assert max_tail(800.0, r3) == 0.0 and max_tail(1.0, r3) == 1.0
    # EC density of a χ²₂ field at d = 0 is the chi-square survival function.
    assert ec_density(10.0, 0) == pytest.approx(np.exp(-5.0), rel=1e-9)


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
    assert all(d.pfa < 1e-6 and d.c_gamma > 5 and d.c_local > 5 for d in dets)


C0, FREQS = 1540.0, np.linspace(1.8e6, 2.6e6, 24)
OUT = np.stack([np.linspace(-0.5, 0.5, 48), np.zeros(48)], axis=1)
IN = np.stack([np.linspace(-0.35, 0.35, 11), np.zeros(11)], axis=1)


def _iid_maps(n: int, seed: int) -> tuple[Grid, list[np.ndarray], fpcore.Fingerprint]:
    rng = np.random.default_rng(seed)
    grid = Grid.centred((0.0, 25e-3), (81, 67), 0.2e-3)
    fp = point_fingerprint(FREQS, OUT, IN, C0, r0=np.array([0.0, 0.0, 25e-3]))
    im = fpcore.Imager(fpcore.ImagingConfig(grid, band=(1.8e6, 2.6e6), n_freq=24))
    maps = []
    for _ in range(n):
        d = (rng.standard_normal((24, 48, 11)) + 1j * rng.standard_normal((24, 48, 11))).astype(np.complex64)
        maps.append(im.gamma(PlaneWaveData(d, FREQS, OUT, IN, C0), fp))
    return grid, maps, fp


def test_pfa_is_calibrated_on_target_free_iid_maps() -> None:
    """The paper's own null (S6): i.i.d. coefficients. Fraction of maps with PFA < α ≤ α (+ slack)."""
    grid, maps, _ = _iid_maps(240, seed=11)
    lam = C0 / 2.2e6
    pfas = np.array([detect(g, grid, lam, 48 * 0.3e-3, 0.8e6, C0, max_pfa=None)[0].pfa for g in maps])
    for alpha, allowed in ((0.5, 0.5), (0.1, 0.1), (0.01, 0.01)):
        rate = float(np.mean(pfas < alpha))
        # Binomial slack: 2.5 standard deviations of the empirical rate at n = 240.
        assert rate <= allowed + 2.5 * np.sqrt(allowed * (1 - allowed) / len(maps)) + 1e-9, (alpha, rate)
    # Not vacuous: the PFA does spread over (0, 1] (a constant 1 would pass the bound above).
    assert 0.2 < float(np.mean(pfas < 0.5)) and np.median(pfas) < 0.9
    # The default decision (PFA < 1e-3) reports nothing on almost every target-free map.
    assert sum(bool(detect(g, grid, lam, 48 * 0.3e-3, 0.8e6, C0)) for g in maps) <= 2


def test_a_point_target_in_noise_is_found_with_a_small_pfa() -> None:
    rng = np.random.default_rng(5)
    grid = Grid.centred((0.0, 25e-3), (81, 67), 0.2e-3)
    r_t = np.array([1.6e-3, 0.0, 26.0e-3])
    fp = point_fingerprint(FREQS, OUT, IN, C0, r0=np.array([0.0, 0.0, 25e-3]))
    target = point_fingerprint(FREQS, OUT, IN, C0, r0=r_t).data
    noise = (rng.standard_normal(target.shape) + 1j * rng.standard_normal(target.shape)).astype(np.complex64)
    data = noise + 0.3 * target * np.sqrt(noise.size / np.vdot(target, target).real)
    im = fpcore.Imager(fpcore.ImagingConfig(grid, band=(1.8e6, 2.6e6), n_freq=24))
    g = im.gamma(PlaneWaveData(data.astype(np.complex64), FREQS, OUT, IN, C0), fp)
    (det,) = detect(g, grid, C0 / 2.2e6, 48 * 0.3e-3, 0.8e6, C0)
    assert np.linalg.norm(np.array(det.position_m) - r_t) < 0.3e-3
    assert det.pfa < 1e-6


def test_tail_scale_fit_recovers_the_scale_of_an_exponential_tail() -> None:
    """fpcore.cfar step 2b: the maximum-likelihood scale of truncated exponential excesses."""
    from fpcore.cfar import fit_tail_scale

    rng = np.random.default_rng(11)
    for beta in (1.0, 1.3, 1.6):
        s = rng.exponential(beta, 400_000)
        got = fit_tail_scale(s, 4.5, 11.0)
        assert abs(got - beta) < 0.05 * beta, (beta, got)
    assert fit_tail_scale(rng.exponential(0.8, 400_000), 4.5, 11.0) == 1.0  # never lighter than speckle
    assert fit_tail_scale(np.array([5.0, 6.0]), 4.5, 11.0) == 1.0  # too few exceedances: speckle law


def test_heavier_than_speckle_null_is_discounted_by_the_maps_own_tail() -> None:
    """A smooth γ-map whose intensity is speckle times a log-normal local level varying below the CFAR
    window's scale (heavier-tailed than Rayleigh, like the simulator's fog): without the map's own tail
    fit its maxima report PFAs that are too small; with it β > 1 is measured and no map reports a
    detection at the default 1e-3."""
    from scipy.ndimage import gaussian_filter

    from fpcore.cfar import null_model

    rng = np.random.default_rng(12)
    grid = Grid.centred((0.0, 30e-3), (300, 300), 0.1e-3)
    res = (0.5e-3, 0.5e-3)
    raw, fitted = [], []
    for _ in range(6):
        field = gaussian_filter(rng.standard_normal(grid.shape), 2.0) + 1j * gaussian_filter(
            rng.standard_normal(grid.shape), 2.0
        )
        log_level = gaussian_filter(rng.standard_normal(grid.shape), 5.0)
        gamma = (np.abs(field) * np.exp(0.1 * log_level / log_level.std())).astype(np.float32)
        for tail_fit, out in ((None, raw), ((4.5, 11.0), fitted)):
            nm = null_model(gamma, grid, res, tail_fit=tail_fit)
            out.append(nm.pfa(float(nm.significance[nm.visible].max())))
            if tail_fit is not None:
                assert nm.tail_scale > 1.1
    assert np.median(fitted) > 3 * np.median(raw)
    assert min(fitted) > 1e-3
