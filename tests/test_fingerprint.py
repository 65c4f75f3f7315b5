"""Fingerprint physics: R = R0 finds r0, the shift follows a moved target, 0 ≤ γ ≤ 1, mirrors' α."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore import (
    Grid,
    Imager,
    ImagingConfig,
    PlaneWaveData,
    from_calibration,
    mirror_fingerprint,
    point_fingerprint,
)
from fpcore.born import born_points
from fpcore.dictionary import Dictionary, mirror_family

BAND = (1.5e6, 3.5e6)
LAM = 1540 / 3.5e6


def _cluster(centre: np.ndarray, radius: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A 'rich' target: scatterers spread over a disc/ball of the given radius (N_S, N_T > 1)."""
    rng = np.random.default_rng(seed)
    offs = rng.uniform(-radius, radius, (9, 3))
    offs[:, 1] *= 0.0 if centre[1] == 0 else 1.0
    offs[0] = [0, 0, -radius]  # the front face, removed by the gate
    return centre + offs, rng.uniform(0.5, 1.0, 9)


@pytest.fixture
def imager_2d() -> Imager:
    grid = Grid.centred((0.0, 15e-3), (72, 72), LAM / 4)
    return Imager(ImagingConfig(grid, BAND, n_freq=32))


def test_calibration_fingerprint_finds_r0_and_follows_a_shift(linear_setup, imager_2d: Imager) -> None:
    probe, seq = linear_setup
    r0 = np.array([0.0, 0.0, 15e-3])
    pts, amps = _cluster(r0, 1.5e-3)
    cal = born_points(probe, seq, pts, amps)
    fp = from_calibration(cal, r0, imager_2d.out_sines_for(cal), BAND, 32, diameter=3e-3)
    assert fp.n_s > 1.0 and fp.provenance == "calibration"
    g = imager_2d.grid
    step = max(g.spacing)
    gam = imager_2d.gamma(imager_2d.plane_waves(cal), fp)
    peak = g.position(np.unravel_index(int(gam.argmax()), gam.shape))
    assert np.linalg.norm(peak - r0) <= step * 1.5
    assert 0.0 <= gam.min() and gam.max() <= 1.0 + 1e-6
    shift = np.array([1.2e-3, 0.0, 2.0e-3])
    moved = born_points(probe, seq, pts + shift, amps)
    gam2 = imager_2d.gamma(imager_2d.plane_waves(moved), fp)
    peak2 = g.position(np.unravel_index(int(gam2.argmax()), gam2.shape))
    assert np.linalg.norm(peak2 - (r0 + shift)) <= step * 1.5


def test_unwhitened_fingerprint_is_the_gated_calibration(linear_setup, imager_2d: Imager) -> None:
    """whiten_modes=False keeps F = R0′ (paper S2, Fig. S7a): the gated calibration matches it exactly at r0
    (γ = 1, Cauchy–Schwarz's equality), where its whitened modes match it less; N_S is counted alike."""
    from fpcore.fingerprint import time_gate

    probe, seq = linear_setup
    r0 = np.array([0.0, 0.0, 15e-3])
    pts, amps = _cluster(r0, 1.5e-3)
    cal = born_points(probe, seq, pts, amps)
    out = imager_2d.out_sines_for(cal)
    kw = dict(diameter=3e-3, angular_filter=False)
    raw = from_calibration(cal, r0, out, BAND, 32, whiten_modes=False, **kw)
    white = from_calibration(cal, r0, out, BAND, 32, **kw)
    assert raw.n_s == white.n_s and raw.state["modes"] != white.state["modes"]
    gated = imager_2d.plane_waves(time_gate(cal, r0, 3e-3, 1.0 / (BAND[1] - BAND[0])))
    node = imager_2d.grid.nearest_index(r0)
    assert np.allclose(imager_2d.grid.position(node), r0)
    g_raw, g_white = imager_2d.gamma(gated, raw)[node], imager_2d.gamma(gated, white)[node]
    assert g_raw == pytest.approx(1.0, abs=1e-4)
    assert g_white < 0.99 * g_raw


def test_calibration_3d_finds_r0(matrix_setup) -> None:
    probe, seq = matrix_setup
    r0 = np.array([0.3e-3, -0.2e-3, 8e-3])
    pts, amps = _cluster(r0, 1.0e-3, seed=4)
    cal = born_points(probe, seq, pts, amps, n_t=400)
    grid = Grid.centred((0.3e-3, -0.2e-3, 8e-3), (20, 20, 24), LAM / 3)
    im = Imager(ImagingConfig(grid, BAND, n_freq=16))
    fp = from_calibration(cal, r0, im.out_sines_for(cal), BAND, 16, diameter=2e-3)
    gam = im.gamma(im.plane_waves(cal), fp)
    peak = grid.position(np.unravel_index(int(gam.argmax()), gam.shape))
    assert np.linalg.norm(peak - r0) <= max(grid.spacing) * 1.5
    assert gam.max() <= 1.0 + 1e-6


def test_gamma_is_one_for_a_perfect_match_and_bounded(imager_2d: Imager) -> None:
    freqs = np.linspace(*BAND, 12)
    so = np.stack([np.linspace(-0.8, 0.8, 24), np.zeros(24)], axis=1)
    si = np.stack([np.linspace(-0.2, 0.2, 5), np.zeros(5)], axis=1)
    r0 = imager_2d.grid.position((40, 38))  # on a node: γ(r0) = 1 exactly there
    fp = mirror_fingerprint(freqs, so, si, 1540.0, 1e-3, 0.2, r0=r0)
    rng = np.random.default_rng(0)
    noise = 0.3 * (rng.standard_normal(fp.data.shape) + 1j * rng.standard_normal(fp.data.shape))
    pw = PlaneWaveData((fp.data + noise).astype(np.complex64), freqs, so, si, 1540.0)
    gam = imager_2d.gamma(pw, fp)
    assert gam.max() <= 1.0 + 1e-6 and gam.min() >= 0.0
    exact = PlaneWaveData(fp.data.copy(), freqs, so, si, 1540.0)
    g1 = imager_2d.gamma(exact, fp)
    assert g1[imager_2d.grid.nearest_index(r0)] == pytest.approx(1.0, abs=2e-3)


def test_point_fingerprint_peaks_at_a_point(linear_setup, imager_2d: Imager) -> None:
    probe, seq = linear_setup
    r = np.array([-1.1e-3, 0.0, 16.3e-3])
    acq = born_points(probe, seq, r[None], np.ones(1))
    pw = imager_2d.plane_waves(acq)
    fp = point_fingerprint(pw.freqs, pw.out_sines, pw.in_sines, pw.c0)
    gam = imager_2d.gamma(pw, fp)
    g = imager_2d.grid
    peak = g.position(np.unravel_index(int(gam.argmax()), gam.shape))
    assert np.linalg.norm(peak - r) <= max(g.spacing) * 1.0001
    conf = imager_2d.confocal(pw)
    assert np.unravel_index(int(conf.argmax()), conf.shape) == np.unravel_index(int(gam.argmax()), gam.shape)


def test_mismatched_geometry_is_a_clear_error(linear_setup, imager_2d: Imager) -> None:
    probe, seq = linear_setup
    acq = born_points(probe, seq, np.array([[0, 0, 15e-3]]), np.ones(1))
    pw = imager_2d.plane_waves(acq)
    fp = point_fingerprint(pw.freqs[:-1], pw.out_sines, pw.in_sines, pw.c0)
    with pytest.raises(ValueError, match="shape"):
        imager_2d.gamma(pw, fp)


@pytest.mark.parametrize("alpha_deg", [10.0, -15.0])
def test_mirror_dictionary_recovers_orientation(linear_setup, imager_2d: Imager, alpha_deg: float) -> None:
    probe, seq = linear_setup
    alpha = np.deg2rad(alpha_deg)
    centre = np.array([0.3e-3, 0.0, 15e-3])
    ls = np.arange(-1e-3, 1e-3 + 1e-9, LAM / 8)
    pts = centre + ls[:, None] * np.array([np.cos(alpha), 0.0, np.sin(alpha)])
    pw = imager_2d.plane_waves(born_points(probe, seq, pts, np.ones(len(pts))))
    dic = Dictionary(family=mirror_family(np.array([1e-3, 2e-3, 3e-3]), np.deg2rad(np.arange(-60, 61, 4))))
    res = dic.evaluate(imager_2d, pw)
    got = np.rad2deg(res.state_map("alpha_rad")[imager_2d.grid.nearest_index(centre)])
    assert abs(got - alpha_deg) <= 5.0


def test_fft_dictionary_equals_exact_nufft(linear_setup, imager_2d: Imager) -> None:
    probe, seq = linear_setup
    rng = np.random.default_rng(2)
    pts = np.stack([rng.uniform(-3e-3, 3e-3, 30), np.zeros(30), rng.uniform(12e-3, 18e-3, 30)], axis=1)
    pw = imager_2d.plane_waves(born_points(probe, seq, pts, rng.uniform(0.2, 1, 30)))
    dic = Dictionary(family=mirror_family(np.array([0.5e-3, 2e-3]), np.deg2rad([-30.0, 0.0, 25.0, 90.0])))
    fast = dic.evaluate(imager_2d, pw, method="fft", keep_all=True)
    ref = dic.evaluate(imager_2d, pw, method="exact", keep_all=True)
    assert np.abs(fast.per_state - ref.per_state).max() <= 1e-3 * ref.per_state.max()


def test_tiled_shift_apodization_keeps_gamma_bounded_and_peaked(linear_setup) -> None:
    import dataclasses

    probe, seq = linear_setup
    r0 = np.array([0.0, 0.0, 15e-3])
    pts, amps = _cluster(r0, 1.5e-3)
    cal = born_points(probe, seq, pts, amps)
    grid = Grid.centred((0.0, 15e-3), (60, 64), LAM / 4)
    plain = Imager(ImagingConfig(grid, BAND, n_freq=24))
    tiled = Imager(dataclasses.replace(plain.config, apodization_tiles=(3, 2)))
    fp = from_calibration(cal, r0, plain.out_sines_for(cal), BAND, 24, diameter=3e-3)
    pw = plain.plane_waves(cal)
    with pytest.raises(ValueError, match="probe"):
        tiled.gamma(pw, fp)
    gam = tiled.gamma(pw, fp, probe)
    assert 0.0 <= gam.min() and gam.max() <= 1.0 + 1e-6
    peak = grid.position(np.unravel_index(int(gam.argmax()), gam.shape))
    assert np.linalg.norm(peak - r0) <= max(grid.spacing) * 1.5
