"""Inverse-variance time weighting (fpcore.time_weighting, docs/design.md §4.14, eq. W1): the variance it
estimates, the stationary frame it makes, and the matched filter's gain in a background that decays in time."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import fpcore
from fpcore.born import born_points
from fpcore.time_weighting import apply_time_weights, inverse_variance_weighted, time_weights, variance_envelope

BAND = (2.0e6, 3.0e6)
N_T = 1200
FS = 20e6


def _probe_and_sequence() -> tuple[fpcore.Probe, fpcore.PlaneWaveSequence]:
    return fpcore.Probe.linear(48, 0.3e-3, 2.5e6, 1.5e6), fpcore.PlaneWaveSequence.from_angles(np.linspace(-12, 12, 7))


def _noise(like: fpcore.Acquisition, envelope: np.ndarray, seed: int) -> fpcore.Acquisition:
    """Band-limited Gaussian noise of `like`'s shape, unit RMS, times `envelope(t)`."""
    rng = np.random.default_rng(seed)
    spec = np.fft.rfft(rng.standard_normal(like.rf.shape), axis=2)
    f = np.fft.rfftfreq(like.n_samples, 1.0 / like.fs)
    spec[..., (f < 1.5e6) | (f > 3.5e6)] = 0.0
    w = np.fft.irfft(spec, n=like.n_samples, axis=2)
    w /= np.sqrt(np.mean(w**2))
    return replace(like, rf=(w * envelope[None, None, :]).astype(np.float32))


def _decay(acq: fpcore.Acquisition, db: float) -> np.ndarray:
    """An envelope falling by `db` over the record, exponentially (the fog's decay, in amplitude)."""
    t = np.arange(acq.n_samples) / acq.n_samples
    return 10 ** (-db * t / 20)


#: Four resolved point reflectors from 12 to 27 mm: their echoes span 20 µs of the record.
POINTS = np.array([[-2e-3, 0, 12e-3], [1e-3, 0, 17e-3], [-1e-3, 0, 22e-3], [0.0, 0, 27e-3]])


@pytest.fixture(scope="module")
def points() -> tuple[fpcore.Acquisition, np.ndarray]:
    """The echo of POINTS and r0, the deepest."""
    probe, seq = _probe_and_sequence()
    echo = born_points(probe, seq, POINTS, np.ones(len(POINTS)), fs=FS, n_t=N_T)
    return echo, POINTS[-1]


def test_variance_envelope_recovers_the_background_envelope(points) -> None:
    echo, _ = points
    env = _decay(echo, 40.0)
    v = variance_envelope(_noise(echo, env, seed=1))
    inner = slice(100, N_T - 100)  # away from the moving average's ends
    ratio = v[inner] / env[inner] ** 2
    assert np.median(ratio) == pytest.approx(1.0, rel=0.05)
    assert np.all(np.abs(np.log10(ratio)) < 0.1)  # within 26 % everywhere over 40 dB of decay


def test_the_weighted_noise_is_stationary(points) -> None:
    echo, _ = points
    noise = _noise(echo, _decay(echo, 40.0), seed=2)
    weighted = inverse_variance_weighted(noise)
    # R/v has the energy 1/v: flat in 1/√v, the matched filter's whitened frame once divided by √v again
    v_w = variance_envelope(weighted) * variance_envelope(noise)
    inner = slice(100, N_T - 100)
    assert np.ptp(np.log10(v_w[inner] / np.median(v_w[inner]))) < 0.25


def test_a_stationary_background_leaves_gamma_unchanged(points) -> None:
    """A background that rules v(t) and is stationary: the weights are nearly one number, and γ (scale-free)
    hardly moves. (Where a target's own echo rules v(t), the weighting flattens it: docs/design.md §4.14.)"""
    echo, r0 = points
    frame = replace(echo, rf=echo.rf + 0.5 * float(np.abs(echo.rf).max()) * _noise(echo, np.ones(N_T), 3).rf)
    grid = fpcore.Grid.for_acquisition(frame, BAND)
    plain = fpcore.Imager(fpcore.ImagingConfig(grid, band=BAND))
    weighted = fpcore.Imager(fpcore.ImagingConfig(grid, band=BAND, time_weighting=True))
    fp = fpcore.from_calibration(echo, r0, plain.out_sines_for(echo), BAND, None, diameter=0.0, gate=False)
    g0 = plain.gamma(plain.plane_waves(frame), fp)
    g1 = weighted.gamma(weighted.plane_waves(frame), fp)
    assert g1.max() <= 1.0
    assert np.corrcoef(g0.ravel(), g1.ravel())[0, 1] > 0.98
    assert np.unravel_index(np.argmax(g1), g1.shape) == np.unravel_index(np.argmax(g0), g0.shape)


def test_the_imager_option_maps_the_weighted_frame(points) -> None:
    echo, _ = points
    frame = replace(echo, rf=echo.rf + _noise(echo, _decay(echo, 30.0), 4).rf)
    grid = fpcore.Grid.for_acquisition(frame, BAND)
    plain = fpcore.Imager(fpcore.ImagingConfig(grid, band=BAND))
    weighted = fpcore.Imager(fpcore.ImagingConfig(grid, band=BAND, time_weighting=True))
    np.testing.assert_allclose(
        weighted.plane_waves(frame).data, plain.plane_waves(inverse_variance_weighted(frame)).data, rtol=1e-6
    )


def test_the_matched_filter_gains_in_a_decaying_background(points) -> None:
    """Eq. (W1): with a background whose variance falls 40 dB over the record, weighting by 1/v(t) raises the
    fingerprint's F_T/F_M (the target's echo alone at r0 over the background's mean square next to it), with
    the weights the whole frame's (echo and background weighted alike: γ's numerator is linear in R). For
    F = T made of J equal echoes at delays t_j in independent noise of variance v(t), the matched filter's
    gain over the unweighted sum is mean_j v(t_j) · mean_j 1/v(t_j) (Cauchy–Schwarz): 3.0 for these four."""
    echo, r0 = points
    noise = _noise(echo, 30.0 * float(np.abs(echo.rf).max()) * _decay(echo, 40.0), seed=5)
    frame = replace(echo, rf=echo.rf + noise.rf)
    grid = fpcore.Grid.for_acquisition(frame, BAND)
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=BAND))
    fp = fpcore.from_calibration(echo, r0, imager.out_sines_for(echo), BAND, None, diameter=0.0, gate=False)
    it = grid.nearest_index(r0)
    mesh = np.meshgrid(*grid.axes, indexing="ij")
    near = (np.abs(mesh[0] - r0[0]) < 3e-3) & (np.abs(mesh[-1] - r0[2]) < 0.5e-3)

    def rho(weights: np.ndarray) -> float:
        def numerator(acq: fpcore.Acquisition) -> np.ndarray:
            pw = imager.plane_waves(apply_time_weights(acq, weights))
            return imager.gamma(pw, fp).astype(np.float64) * float(np.linalg.norm(pw.data))

        return float(numerator(echo)[it] ** 2 / np.mean(numerator(noise)[near] ** 2))

    plain = rho(np.ones(N_T))
    weighted = rho(time_weights(frame))
    v = _decay(echo, 40.0)[np.round(2 * POINTS[:, 2] / echo.c0 * echo.fs).astype(int)] ** 2
    theory = float(np.mean(v) * np.mean(1 / v))
    assert theory > 2.5  # the setting is one where weighting matters
    assert 0.6 * theory < weighted / plain < 1.2 * theory, (plain, weighted, theory)


def test_bad_frames_and_settings_are_refused(points) -> None:
    echo, _ = points
    with pytest.raises(ValueError, match="rf"):
        inverse_variance_weighted(replace(echo, rf=np.zeros_like(echo.rf)))
    with pytest.raises(ValueError, match="smooth_s"):
        variance_envelope(echo, smooth_s=-1.0)
    with pytest.raises(ValueError, match="weights: expected one per time sample"):
        apply_time_weights(echo, np.ones(N_T + 1))
