"""The background measurements of bench/background_metrics.py on synthetic data with a known answer."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import background_metrics as bm  # noqa: E402

from fpcore.simulate.waves import Band, radiate_points  # noqa: E402

DF = 10e3
F0 = 1.5e6


def _decaying_noise(rng: np.random.Generator, tau: float, t_on: float, n_f: int = 128, n_ch: int = 24) -> np.ndarray:
    """Spectra (1, n_f, n_ch, n_ch) of complex white noise with intensity e^{−(t − t_on)/τ} after t_on."""
    t = np.arange(n_f) / (n_f * DF)
    env = np.where(t >= t_on, np.exp(-(t - t_on) / (2 * tau)), 0.0)
    x = (rng.standard_normal((1, n_f, n_ch, n_ch)) + 1j * rng.standard_normal((1, n_f, n_ch, n_ch))) * env[
        None, :, None, None
    ]
    return np.fft.fft(x, axis=1)  # V(f_n) = Σ_j x_j e^{−i2πnj/N}: arrival times t_j


@pytest.mark.parametrize("tau", [2.5e-6, 5e-6])
def test_frequency_correlation_width_of_an_exponential_envelope(tau: float) -> None:
    """|C(Δf)| = (1 + (2πΔfτ)²)^{−1/2} ⇒ δf_½ = √3/(2πτ) (69 kHz at 4 µs, 55 kHz at 5 µs)."""
    v = _decaying_noise(np.random.default_rng(1), tau, t_on=10e-6)
    freqs = F0 + DF * np.arange(v.shape[1])
    got = bm.frequency_correlation_width(v, freqs, gate=(10e-6, 90e-6), taper=0.5e-6)
    assert got["width"] == pytest.approx(np.sqrt(3) / (2 * np.pi * tau), rel=0.12)


def test_time_envelope_of_a_delayed_pulse_and_of_a_decay() -> None:
    """A unit echo delayed by t1 through the band S(f): peak mean-square ½ (carrier-averaged unit pulse) at t1;
    a decaying noise: ln⟨r²⟩ falls at 1/τ."""
    band = Band(1.8e6, 2.6e6)
    freqs = np.arange(1.41e6, 2.99e6, DF)
    t1 = 30e-6
    v = np.exp(-2j * np.pi * freqs * t1)[None, :, None, None]
    t, inten = bm.time_envelope(v, freqs, band)
    assert t[np.argmax(inten)] == pytest.approx(t1, abs=0.3e-6)
    assert inten.max() == pytest.approx(0.5, rel=0.02)
    tau = 4e-6
    vn = _decaying_noise(np.random.default_rng(2), tau, t_on=10e-6, n_f=freqs.size)
    t, inten = bm.time_envelope(vn, freqs, band)
    sel = (t > 14e-6) & (t < 40e-6)
    slope = np.polyfit(t[sel], np.log(inten[sel]), 1)[0]
    assert -1 / slope == pytest.approx(tau, rel=0.1)


def test_energy_before_a_delayed_echo_is_its_pulse_tail_only() -> None:
    """A unit echo at t1: its pulse's tail holds < 1 % of the energy a microsecond before it, < 0.01 % two
    microseconds before; half by t1, all after;
    a mismatched envelope is refused naming the field."""
    band = Band(1.8e6, 2.6e6)
    freqs = np.arange(1.41e6, 2.99e6, DF)
    t1 = 30e-6
    v = np.exp(-2j * np.pi * freqs * t1)[None, :, None, None]
    t, inten = bm.time_envelope(v, freqs, band)
    assert bm.energy_before(t, inten, t1 - 1e-6) < 1e-2
    assert bm.energy_before(t, inten, t1 - 2e-6) < 1e-4
    assert bm.energy_before(t, inten, t1) == pytest.approx(0.5, abs=0.05)
    assert bm.energy_before(t, inten, t1 + 2e-6) > 0.999
    with pytest.raises(ValueError, match="env"):
        bm.energy_before(t, inten[:-1], t1)


def test_precursor_lead_is_the_edge_elements_firing_and_a_pulse() -> None:
    """The most oblique transmit's earliest element fires (D/2)|s|/c0 before the centre (per lateral axis in
    3-D); the lead adds the pulse length 1/B; a normal transmit alone leads by the pulse only."""
    import foldy_lax_reference as flr
    import validate_background as vb

    for dim in (2, 3):
        s = flr.setup_for(dim, quick=True)
        half = np.abs(s.elements()[:, 0]).max()
        sines = vb.transmit_sines(dim)
        per_axis = half * np.abs(sines[:, 0]).max() / s.c0
        want = per_axis * (dim - 1) + 1.0 / (s.band_hi - s.band_lo)
        assert vb.precursor_lead(s, sines) == pytest.approx(want, rel=1e-9)
        assert vb.precursor_lead(s, np.zeros((1, 2))) == pytest.approx(1.0 / (s.band_hi - s.band_lo))


def test_memory_correlation_one_for_a_shift_invariant_matrix_small_for_independent_entries() -> None:
    """R(b, a) = g(b − a) keeps its value under a common tilt (perfect memory effect): C = 1; independent
    entries: C ≈ 0; a lattice on which no partner exists leaves the step out; a wrong shape names r."""
    rng = np.random.default_rng(5)
    x = np.linspace(-0.3, 0.3, 13)
    sines = np.stack([x, np.zeros_like(x)], axis=1)
    g = rng.standard_normal(2 * x.size) + 1j * rng.standard_normal(2 * x.size)
    i = np.arange(x.size)
    shift_inv = g[(i[:, None] - i[None, :]) + x.size][None, None]  # (1, 1, N_b, N_a)
    got = bm.memory_correlation(shift_inv, sines, (1, 3))
    assert got[1] == pytest.approx(1.0, abs=1e-9) and got[3] == pytest.approx(1.0, abs=1e-9)
    noise = rng.standard_normal((8, 4, x.size, x.size)) + 1j * rng.standard_normal((8, 4, x.size, x.size))
    assert bm.memory_correlation(noise, sines, (1,))[1] < 0.1
    assert 20 not in bm.memory_correlation(noise, sines, (20,))
    with pytest.raises(ValueError, match="r"):
        bm.memory_correlation(noise[:, :, :-1], sines)


def _array_data(symmetric: bool, n_real: int = 24, seed: int = 3) -> tuple[np.ndarray, ...]:
    """V(f, u, a) = c_a Σ_v K(u, v) e^{−ik a·v} from random element matrices K (symmetric or not)."""
    rng = np.random.default_rng(seed)
    c0, fc = 1500.0, 2.2e6
    n_u = 32
    x = (np.arange(n_u) - (n_u - 1) / 2) * c0 / fc / 2
    el = np.stack([x, np.zeros(n_u), np.zeros(n_u)], axis=1)
    sines = np.stack([np.linspace(-0.3, 0.3, 11), np.zeros(11)], axis=1)
    freqs = fc + DF * np.arange(-2, 3)
    k = 2 * np.pi * freqs / c0
    shape = (n_real, freqs.size, n_u, n_u)
    kk = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    if symmetric:
        kk = (kk + np.swapaxes(kk, 2, 3)) / np.sqrt(2)
    c = np.sqrt(1 - sines[:, 0] ** 2)
    q = c[None, None, :] * np.exp(-1j * k[:, None, None] * (el[:, 0:1] @ sines[:, 0:1].T)[None])
    v = np.matmul(kk, q[None])
    return v, freqs, el, sines, c0


def test_cbs_enhancement_two_for_a_reciprocal_matrix_one_without() -> None:
    v, freqs, el, sines, c0 = _array_data(symmetric=True)
    rec = bm.cbs_enhancement(v, freqs, el, sines, c0, dim=2)
    assert rec["enhancement"] == pytest.approx(2.0, rel=0.1)
    assert rec["reciprocity"] > 0.99
    assert rec["profile"][-1] == pytest.approx(1.0, rel=0.15)  # flat outside the cone
    assert rec["flatness"] < 0.1
    v, freqs, el, sines, c0 = _array_data(symmetric=False)
    non = bm.cbs_enhancement(v, freqs, el, sines, c0, dim=2)
    assert non["enhancement"] == pytest.approx(1.0, rel=0.1)
    assert non["reciprocity"] < 0.2


def test_cbs_enhancement_jackknife_error_is_the_spread_over_independent_sets() -> None:
    """The jackknife standard error of one set of realisations predicts how far the enhancement of another,
    independent set falls from it: the spread over 8 sets of 12 within a factor 2 of the mean error."""
    got = [bm.cbs_enhancement(*_array_data(True, n_real=12, seed=40 + i), dim=2) for i in range(8)]
    spread = float(np.std([g["enhancement"] for g in got], ddof=1))
    se = float(np.mean([g["enhancement_se"] for g in got]))
    assert 0.5 < spread / se < 2.0
    assert all(np.isfinite(g["enhancement_ladder_se"]) for g in got)
    few = bm.cbs_enhancement(*_array_data(True, n_real=2), dim=2)
    assert np.isnan(few["enhancement_se"])


def test_confocal_contrast_slope_of_an_attenuated_speckle() -> None:
    """Born speckle whose scatterers' amplitude falls as e^{−(z − z0)/L} has I_M ∝ e^{−2z/L}; with an echo
    ∝ e^{−4z/L} the contrast falls as e^{−2z/L}: slope −2/L."""
    rng = np.random.default_rng(4)
    c0, fc = 1500.0, 2.2e6
    n_u = 32
    x = (np.arange(n_u) - (n_u - 1) / 2) * c0 / fc / 2
    el = np.stack([x, np.zeros(n_u), np.zeros(n_u)], axis=1)
    sines = np.stack([np.linspace(-0.2, 0.2, 5), np.zeros(5)], axis=1)
    freqs = np.arange(1.6e6, 2.8e6, 20e3)
    z0, ell = 5e-3, 4e-3
    v = []
    for _ in range(4):
        n = 1500
        pts = np.stack([rng.uniform(-12e-3, 12e-3, n), np.zeros(n), rng.uniform(z0, z0 + 14e-3, n)], axis=1)
        amp = rng.standard_normal(n) * np.exp(-(pts[:, 2] - z0) / ell)
        v.append(radiate_points(pts, amp.astype(np.complex128), el, sines, freqs, c0, 2))
    z = np.linspace(z0 + 2e-3, z0 + 11e-3, 16)
    got = bm.confocal_contrast_slope(
        np.stack(v), freqs, el, sines, c0, 2, z, np.exp(-4 * z / ell), fit=(z[0], z[-1]), half_width=3e-3
    )
    assert got["slope"] == pytest.approx(-2 / ell, rel=0.15)
    assert 0 < got["slope_se"] < 0.15 * 2 / ell  # the jackknife error over 4 realisations: finite, and small here
    # refitted over the same depths, slope_over is the slope; over a sub-range, the same law within its error
    assert bm.slope_over(got, (z[0], z[-1])) == pytest.approx((got["slope"], got["slope_se"]), rel=1e-12)
    part, part_se = bm.slope_over(got, (z[0], z[9]))
    assert part == pytest.approx(-2 / ell, rel=0.25) and part_se > 0
    with pytest.raises(ValueError, match="fit: expected at least 3 depths"):
        bm.slope_over(got, (z[0], z[1]))


def test_bad_input_names_the_field() -> None:
    with pytest.raises(ValueError, match="V: expected shape"):
        bm.time_envelope(np.zeros((3, 4, 5)), np.arange(4.0))
    with pytest.raises(ValueError, match="freqs: expected a uniform"):
        bm.time_envelope(np.zeros((1, 3, 1, 1)), np.array([1.0, 2.0, 4.0]))


def test_focused_profile_of_a_point_echo_peaks_at_zero_separation_and_equals_the_confocal_image() -> None:
    """A point reflector's echo V(f, u, a) = e^{−ik(|u − r₀| + a·ρ₀ + c_a z₀)} is focused at r₀ in and out: the
    focused matrix at its depth peaks at Δx = 0, where it is the confocal image, and falls by more than half
    a few wavelengths off; mismatched point sets are refused by name."""
    c0, n_u = 1500.0, 48
    freqs = np.linspace(1.8e6, 2.6e6, 24)
    lam = c0 / 2.2e6
    x = (np.arange(n_u) - (n_u - 1) / 2) * lam / 2
    el = np.stack([x, np.zeros(n_u), np.zeros(n_u)], axis=1)
    s = np.linspace(-0.3, 0.3, 15)
    sines = np.stack([s, np.zeros_like(s)], axis=1)
    r0 = np.array([0.0, 0.0, 10e-3])
    k = 2 * np.pi * freqs / c0
    d_out = np.hypot(el[:, 0] - r0[0], el[:, 2] - r0[2])
    d_in = s * r0[0] + np.sqrt(1 - s**2) * r0[2]
    v = np.exp(-1j * k[:, None, None] * (d_out[None, :, None] + d_in[None, None, :]))[None]
    seps = np.array([0.0, 0.5, 1.0, 3.0, 6.0]) * lam
    prof = bm.focused_profile(v, freqs, el, sines, c0, 2, r0[2], seps, 0.0, n_lateral=1)
    assert np.argmax(prof) == 0 and prof[-1] < 0.5 * prof[0] and prof[-2] < 0.5 * prof[0]
    conf = bm.confocal_background(v, freqs, el, sines, c0, 2, r0[None])
    assert prof[0] == pytest.approx(float(conf[0]), rel=1e-6)
    with pytest.raises(ValueError, match="points_out"):
        bm.focused_background(v, freqs, el, sines, c0, 2, r0[None], np.stack([r0, r0]))
