"""Frequency-domain engine: band, RF synthesis ⇄ Acquisition.spectrum, point radiation vs direct sum,
time of flight of echoes with the docs/design.md §3 transmit-delay convention, interface echo."""

from __future__ import annotations

import numpy as np
import scipy.special as sp

from fpcore.acquisition import Acquisition, PlaneWaveSequence, Probe
from fpcore.simulate import Band, ScatteringLayer, TimeWindow, incident_phase, radiate_points


def test_band_pulse_is_normalised() -> None:
    band = Band(1.8e6, 2.6e6)
    f = np.linspace(0, 5e6, 200001)
    s = band.spectrum(f)
    df = f[1] - f[0]
    assert abs(2 * s.sum() * df - 1) < 1e-4  # s(0) = ∫ S over ±f
    assert abs(2 * (s**2).sum() * df - band.pulse_energy()) < 1e-3 * band.pulse_energy()
    peak = band.spectrum(np.array([band.centre]))[0]
    np.testing.assert_allclose(band.spectrum(np.array([1.8e6, 2.6e6])) / peak, 0.5, rtol=1e-9)


def test_synthesis_is_the_inverse_of_acquisition_spectrum() -> None:
    probe = Probe.linear(3, 0.3e-3, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(2, 0.1)
    band = Band(1.8e6, 2.6e6)
    win = TimeWindow(10.4e6, 17e-6, 512, 512)
    bins = win.band_bins(band)
    rng = np.random.default_rng(0)
    x = (rng.standard_normal((bins.size, 3, 2)) + 1j * rng.standard_normal((bins.size, 3, 2))) * 1e-7
    rf = win.synthesize(x.astype(np.complex64), bins)
    acq = Acquisition(rf, win.fs, win.t0, 1500.0, probe, seq)
    spec = acq.spectrum(win.freqs()[bins[0]] - 1.0, win.freqs()[bins[-1]] + 1.0, pad=1)
    np.testing.assert_allclose(spec.data, x, rtol=2e-4, atol=2e-4 * np.abs(x).max())
    np.testing.assert_allclose(win.analyse(rf, bins), x, rtol=2e-4, atol=2e-4 * np.abs(x).max())


def test_radiate_points_matches_direct_sum() -> None:
    rng = np.random.default_rng(0)
    el = np.stack([np.linspace(-5e-3, 5e-3, 7), np.zeros(7), np.zeros(7)], 1)
    pts = np.stack([rng.uniform(-3e-3, 3e-3, 20), np.zeros(20), rng.uniform(10e-3, 20e-3, 20)], 1)
    t = rng.standard_normal(20) + 1j * rng.standard_normal(20)
    sines = np.array([[0.0, 0.0], [0.2, 0.0], [-0.1, 0.0]])
    f = np.linspace(2e6, 3e6, 70)
    c0 = 1500.0
    for dim, tol in ((3, 1e-5), (2, 5e-4)):
        h = radiate_points(pts, t, el, sines, f, c0, dim)
        ref = np.empty_like(h)
        for m, ff in enumerate(f):
            k = 2 * np.pi * ff / c0
            if dim == 3:
                d = np.linalg.norm(el[:, None, :] - pts[None], axis=2)
                g = np.exp(-1j * k * d) / (4 * np.pi * d)
            else:
                d = np.hypot(el[:, None, 0] - pts[None, :, 0], el[:, None, 2] - pts[None, :, 2])
                g = -0.25j * sp.hankel2(0, k * d)
            ref[m] = g @ (t[:, None] * incident_phase(k, sines, pts))
        assert np.abs(h - ref).max() < tol * np.abs(ref).max()


def test_echo_arrives_at_the_time_of_flight() -> None:
    """RF peak of a point at r on element u for plane wave s: t = (x s_x + y s_y + z c)/c0 + |u − r|/c0."""
    probe = Probe.matrix(4, 4, 0.5e-3, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence(np.array([[0.15, -0.1]]))
    band = Band(1.8e6, 2.6e6)
    win = TimeWindow.covering(40e6, 20e-6, 40e-6)
    bins = win.band_bins(band)
    r = np.array([1e-3, 2e-3, 20e-3])
    h = radiate_points(r[None, :], np.array([1.0]), probe.positions, seq.sines, win.freqs()[bins], 1500.0, 3)
    rf = win.synthesize(h * band.spectrum(win.freqs()[bins])[:, None, None].astype(np.float32), bins)
    s = seq.sines[0]
    expected = (r[0] * s[0] + r[1] * s[1] + r[2] * np.sqrt(1 - s @ s)) / 1500.0 + np.linalg.norm(
        probe.positions - r, axis=1
    ) / 1500.0
    measured = win.times()[np.argmax(np.abs(rf[:, 0, :]), axis=1)]
    assert np.max(np.abs(measured - expected)) < 1.0 / win.fs


def test_interface_echo_time_and_rough_reduction() -> None:
    probe = Probe.linear(5, 1e-3, 2.2e6, 0.8e6)
    sines = np.array([[0.0, 0.0], [0.2, 0.0]])
    f = np.array([2.0e6, 2.001e6])
    smooth = ScatteringLayer(z_surface=16e-3, ls=1.8e-3, density=1900.0, sound_speed=1600.0)
    rough = ScatteringLayer(z_surface=16e-3, ls=1.8e-3, density=1900.0, sound_speed=1600.0, roughness=0.1e-3)
    h = smooth.interface_echo(probe.positions, sines, f, 1500.0)
    np.testing.assert_allclose(np.abs(h), smooth.reflection(), rtol=1e-6)
    delay = -np.angle(h[1] / h[0]) / (2 * np.pi * (f[1] - f[0]))
    c = np.sqrt(1 - sines[:, 0] ** 2)
    expected = (probe.positions[:, :1] * sines[None, :, 0] + 2 * 16e-3 * c[None, :]) / 1500.0
    period = 1 / (f[1] - f[0])
    np.testing.assert_allclose(np.mod(delay - expected + period / 2, period) - period / 2, 0, atol=1e-9)
    k = 2 * np.pi * f[0] / 1500.0
    ratio = np.abs(rough.interface_echo(probe.positions, sines, f, 1500.0)[0, 0, 0]) / smooth.reflection()
    np.testing.assert_allclose(ratio, np.exp(-2 * (k * 0.1e-3) ** 2), rtol=1e-6)
