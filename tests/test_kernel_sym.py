"""The full-size frame's fast paths (issue 15, item 6) against their references: the exact lateral path of
PresumTransform (centre-symmetric DFTs, rows without samples skipped, one frequency per thread block) against
the direct sum with a fingerprint-like weight (most output directions at zero weight) and against the NUFFT
lateral path; the compiled separable projection P_θu against the general phase-matrix product; the envelope spectra by
autocorrelation against their FFT."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from fpcore.acquisition import PlaneWaveData, PlaneWaveSequence, Probe, Spectrum, to_plane_waves  # noqa: E402
from fpcore.grid import Grid  # noqa: E402
from fpcore.kernel import direct_sum, wavevectors  # noqa: E402
from fpcore.kernel_presum import PresumTransform  # noqa: E402

C0 = 1540.0
DS = 0.031


def _disc(radius: int, offset: float) -> np.ndarray:
    """Sines on a lattice of step DS (offset in steps) cut to a disc: the output directions' shape."""
    ax = (np.arange(-radius, radius + 1) + offset) * DS
    yy, xx = np.meshgrid(ax, ax, indexing="ij")
    keep = xx.ravel() ** 2 + yy.ravel() ** 2 <= (radius * DS) ** 2
    return np.stack([xx.ravel()[keep], yy.ravel()[keep]], axis=1)


@pytest.mark.parametrize("offset", [0.0, 0.5, 0.3])
def test_exact_path_with_empty_directions_matches_direct_sum(offset: float) -> None:
    """offset 0 / 0.5: a lattice symmetric about 0 (θ_c = 0); 0.3: off-centre (the phase e^{iθ_c p})."""
    so = _disc(5, offset)
    si = np.stack([np.array([-2.0, 0.0, 2.0]) * DS, np.array([0.0, 2.0, 0.0]) * DS], axis=1)
    freqs = np.linspace(3e6, 5e6, 6)
    grid = Grid.centred((0.4e-3, -0.2e-3, 11e-3), (9, 8, 13), 0.1e-3)
    rng = np.random.default_rng(7)
    n = freqs.size * so.shape[0] * si.shape[0]
    w = (rng.standard_normal(n) + 1j * rng.standard_normal(n)).astype(np.complex64).reshape(freqs.size, -1, 3)
    cone = np.hypot(so[:, 0] - 2 * DS, so[:, 1]) < 2.5 * DS  # a fingerprint's angular support, off-centre
    w[:, ~cone] = 0
    w[2] = 0  # a frequency without data
    w = w.ravel()
    K = wavevectors(freqs, so, si, C0, 3)
    ref = direct_sum(w, K, grid.points()).reshape(grid.shape)
    exact = PresumTransform(freqs, so, si, C0, grid, nthreads=2, lateral="exact")
    nufft = PresumTransform(freqs, so, si, C0, grid, nthreads=1, lateral="nufft")
    got = exact(w)
    scale = np.abs(ref).max()
    assert np.abs(got - ref).max() < 1e-4 * scale
    assert np.abs(got - nufft(w)).max() < 1e-4 * scale
    # rows: one map each. Float32 rounding only: threads take frequencies as they free up, so two calls add
    # their per-thread partial maps in different orders (measured up to 1.05e-6 of the maximum under load)
    assert np.abs(exact(np.stack([w, 2 * w]))[1] - 2 * got).max() < 1e-5 * scale
    assert not np.any(exact(np.zeros_like(w)))  # no sample at all: an empty map


def test_separable_projection_matches_the_phase_matrix() -> None:
    """A 6×5 matrix array (x-fastest) and a disc of output sines: the compiled y-then-x projection equals
    Σ_u e^{−ik s·u} R_u (the general branch of to_plane_waves, here written out)."""
    px, py = np.meshgrid(np.arange(6) * 0.3e-3, np.arange(5) * 0.3e-3)
    pos = np.stack([px.ravel() - 0.75e-3, py.ravel() - 0.6e-3, np.zeros(30)], axis=1)
    probe = Probe(positions=pos, pitch=0.3e-3, centre_frequency=4e6, bandwidth=2e6)
    sines = np.array([[-0.1, 0.0], [0.0, 0.0], [0.1, 0.05]])
    seq = PlaneWaveSequence(sines=sines)
    freqs = np.linspace(3e6, 5e6, 7)
    rng = np.random.default_rng(1)
    data = (rng.standard_normal((7, 30, 3)) + 1j * rng.standard_normal((7, 30, 3))).astype(np.complex64)
    out = _disc(4, 0.0)
    pw = to_plane_waves(Spectrum(data, freqs, C0, probe, seq), out)
    assert isinstance(pw, PlaneWaveData) and pw.data.shape == (7, out.shape[0], 3)
    k = 2 * np.pi * freqs / C0
    phase = np.exp(-1j * k[:, None, None] * (out @ pos[:, :2].T)[None])
    ref = np.einsum("fou,fui->foi", phase, data.astype(np.complex128))
    assert np.abs(pw.data - ref).max() < 1e-5 * np.abs(ref).max()


def test_null_power_on_the_fingerprints_directions_equals_the_full_data_side() -> None:
    """NullPower makes the data's envelope spectrum only on the output directions where a fingerprint's side
    is not zero (its angular support), once per frame: P(r) of eq. B1 equals the product with Ê_R made on
    every direction, for two fingerprints with different supports, in either order."""
    from fpcore.background import NullPower
    from fpcore.envelope_loops import envelope_columns
    from fpcore.fingerprint import point_fingerprint

    freqs = np.linspace(1.8e6, 2.6e6, 17)
    out = np.stack([np.linspace(-0.5, 0.5, 21), np.zeros(21)], axis=1)
    inn = np.stack([np.linspace(-0.2, 0.2, 5), np.zeros(5)], axis=1)
    grid = Grid.centred((0.0, 25e-3), (31, 29), 0.25e-3)
    rng = np.random.default_rng(2)
    data = (rng.standard_normal((17, 21, 5)) + 1j * rng.standard_normal((17, 21, 5))).astype(np.complex64)
    pw = PlaneWaveData(data, freqs, out, inn, C0)
    fps = []
    for lo, hi, x in ((0, 8, -1e-3), (6, 15, 1e-3)):  # two angular supports, overlapping
        fp = point_fingerprint(freqs, out, inn, C0, np.array([x, 0.0, 25e-3]))
        fp.data[:, :lo] = 0
        fp.data[:, hi:] = 0
        fps.append(fp)
    full = np.zeros_like(data)  # Ê_R on every direction, by the same autocorrelation (fpcore.envelope_loops)
    envelope_columns(data, np.arange(out.shape[0]), full)
    npow = NullPower(grid)
    for order in (fps, fps[::-1]):
        npow._data = None  # a new frame
        for fp in order:
            kern, nu = npow._kernel(pw)
            t, support = npow._fingerprint_side(pw, fp, nu)
            assert support.size < out.shape[0]
            tf = np.zeros(data.shape, np.complex64)  # the side on every direction (zero off its support)
            tf[:, support] = t
            ref = np.maximum(kern((full * tf).ravel()).real.astype(np.float64), 0.0)
            got = npow.power(pw, fp)
            assert np.abs(got - ref).max() <= 1e-6 * np.abs(ref).max()


@pytest.mark.parametrize("n_freq", [1, 2, 17, 89])
def test_envelope_autocorrelation_equals_the_envelopes_spectrum(n_freq: int) -> None:
    """Ê(m) = Σ_f R_{f+m} R_f* (fpcore.envelope_loops, Wiener–Khinchin) is the rFFT of |a(t)|², a the band's
    analytic signal on 2N_f samples (`envelope_spectrum`), on the directions asked for; the others are left as
    they were."""
    from fpcore.background import envelope_spectrum
    from fpcore.envelope_loops import envelope_columns

    rng = np.random.default_rng(n_freq)
    data = (rng.standard_normal((n_freq, 30, 7)) + 1j * rng.standard_normal((n_freq, 30, 7))).astype(np.complex64)
    cols = np.array([0, 3, 4, 5, 11, 12, 13, 14, 15, 16, 17, 18, 29])
    out = np.full(data.shape, 7 + 7j, np.complex64)
    envelope_columns(data, cols, out)
    ref = envelope_spectrum(data)
    assert np.abs(out[:, cols] - ref[:, cols]).max() <= 2e-6 * np.abs(ref).max()
    rest = np.setdiff1d(np.arange(30), cols)
    assert np.all(out[:, rest] == 7 + 7j)
    assert np.allclose(out[0, cols].imag, 0, atol=1e-6 * np.abs(ref).max())  # Ê(0) = Σ|R_f|² is real


def test_support_product_equals_the_full_product_on_any_sequence_of_supports() -> None:
    """SupportProduct (fpcore.support), kept between calls, equals a ∘ b_full — b zero off its support — for
    supports that change, shrink, grow and cover every direction, in either dtype."""
    from fpcore.support import SupportProduct, angular_support

    rng = np.random.default_rng(5)
    prod = SupportProduct()
    for dtype in (np.complex64, np.complex128):
        a = (rng.standard_normal((6, 20, 3)) + 1j * rng.standard_normal((6, 20, 3))).astype(dtype)
        for cols in ([1, 2, 3, 9], [2, 3, 15, 16, 17], list(range(20)), [0], [4, 5]):
            b_full = np.zeros(a.shape, np.complex64)
            b_full[:, cols] = rng.standard_normal((6, len(cols), 3))
            support = angular_support(b_full)
            assert support.tolist() == cols
            got = prod(a, support, np.ascontiguousarray(b_full[:, support]))
            assert np.array_equal(got, a * b_full)
