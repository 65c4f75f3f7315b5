"""The Gaussian field's confocal notch (fpcore/simulate/confocal_notch.py, docs/design.md §6.6, F4)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore.acquisition import PlaneWaveSequence, Probe
from fpcore.geometry import cosines
from fpcore.simulate.confocal_notch import ConfocalNotch
from fpcore.simulate.diffuse import DiffuseBackground
from fpcore.simulate.medium import ScatteringLayer
from fpcore.simulate.reciprocity import ElementReciprocity
from fpcore.simulate.waves import Band, TimeWindow

C0 = 1500.0


def _rig(dim: int) -> tuple[np.ndarray, list[float], np.ndarray, np.ndarray]:
    """A small rig: output sines on a regular grid, a few transmits, a band of uniform frequencies."""
    ds = 0.04
    axis = np.arange(-12, 13) * ds
    if dim == 3:
        sx, sy = np.meshgrid(axis[::2], axis[::2], indexing="ij")
        s_out = np.stack([sx.ravel(), sy.ravel()], axis=1)
        spacings = [2 * ds, 2 * ds]
        t = np.array([-0.1, 0.0, 0.1])
        tx, ty = np.meshgrid(t, t, indexing="ij")
        sines = np.stack([tx.ravel(), ty.ravel()], axis=1)
    else:
        s_out = np.stack([axis, np.zeros_like(axis)], axis=1)
        spacings = [ds]
        sines = np.stack([np.linspace(-0.3, 0.3, 7), np.zeros(7)], axis=1)
    freqs = np.linspace(1.6e6, 2.8e6, 49)
    return s_out, spacings, sines, freqs


def _scatterers(s_out: np.ndarray, sines: np.ndarray, freqs: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Σ_m η_m e^{−ik[(a − b)·x_m + (c_a + c_b) z_m]} by the direct sum (F4), (N_o, N_θ, N_f)."""
    rng = np.random.default_rng(3)
    k = 2 * np.pi * freqs / C0
    qz = cosines(sines)[None, :] + cosines(s_out)[:, None]
    v = np.zeros((s_out.shape[0], sines.shape[0], freqs.size), dtype=np.complex128)
    for x, y, z in points:
        eta = rng.standard_normal() + 1j * rng.standard_normal()
        lat = (sines[None, :, 0] - s_out[:, None, 0]) * x + (sines[None, :, 1] - s_out[:, None, 1]) * y
        v += eta * np.exp(-1j * k[None, None, :] * (lat + qz * z)[:, :, None])
    return v.astype(np.complex64)


def _gated_energy(spec: np.ndarray, n_t: int, gate: int) -> np.ndarray:
    """Energy of a (N_f, …) spectrum on contiguous bins in consecutive time gates of `gate` baseband samples."""
    t = np.fft.ifft(spec, n=n_t, axis=0)
    e = np.sum(np.abs(t.reshape(n_t, -1)) ** 2, axis=1)
    return np.add.reduceat(e, np.arange(0, n_t, gate))


def _share(notch: ConfocalNotch, v: np.ndarray) -> float:
    fit = notch.fit(v)
    return float(np.sum(np.abs(fit) ** 2) / np.sum(np.abs(v) ** 2))


@pytest.mark.parametrize("dim", [2, 3])
def test_a_reflectivity_is_removed_and_noise_keeps_its_energy_outside_the_confocal_subspace(dim: int) -> None:
    """F4: the field of point scatterers (single scattering, phase only) lies in the subspace the notch fits; white
    noise loses only its share of it, and after the notch keeps its energy and has next to nothing left there."""
    s_out, spacings, sines, freqs = _rig(dim)
    notch = ConfocalNotch(s_out, spacings, sines, freqs, C0, dim, (5e-3, 40e-3), iterations=30)
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [
            rng.uniform(-4e-3, 4e-3, 6),
            rng.uniform(-4e-3, 4e-3, 6) if dim == 3 else np.zeros(6),
            rng.uniform(10e-3, 25e-3, 6),
        ]
    )
    echo = _scatterers(s_out, sines, freqs, pts)
    assert _share(notch, echo) > 0.9
    assert float(np.sum(np.abs(notch(echo) - echo) ** 2) / np.sum(np.abs(echo) ** 2)) > 0.5  # it is notched
    shape = (s_out.shape[0], sines.shape[0], freqs.size)
    noise = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    removed = _share(notch, noise)
    assert 0.02 < removed < 0.9
    out = notch(noise)
    np.testing.assert_allclose(np.sum(np.abs(out) ** 2), np.sum(np.abs(noise) ** 2), rtol=1e-3)
    assert _share(notch, out) < 0.1 * removed


def test_the_notch_refuses_a_wrong_shape_and_a_single_frequency() -> None:
    s_out, spacings, sines, freqs = _rig(2)
    notch = ConfocalNotch(s_out, spacings, sines, freqs, C0, 2, (5e-3, 40e-3))
    with pytest.raises(ValueError, match="y: expected shape"):
        notch.fit(np.zeros((3, 3, 3), dtype=np.complex64))
    with pytest.raises(ValueError, match="v: expected shape"):
        notch(np.zeros((3, 3, 3), dtype=np.complex64))
    with pytest.raises(ValueError, match="freqs: expected at least 2"):
        ConfocalNotch(s_out, spacings, sines, freqs[:1], C0, 2, (5e-3, 40e-3))
    with pytest.raises(ValueError, match="z_range: expected"):
        ConfocalNotch(s_out, spacings, sines, freqs, C0, 2, (40e-3, 5e-3))


def _small_background(**layer_kw: object) -> tuple[DiffuseBackground, Probe, PlaneWaveSequence]:
    """A small 2-D rig's background (32 elements, 7 transmits) with the diffusion envelope, the beads' speckle and
    `layer_kw` (the focal return, the notch, cbs…)."""
    probe = Probe.linear(32, 0.34e-3, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(7, 0.2)
    win = TimeWindow.covering(10.4e6, 14e-6, 30e-6, guard=10e-6)
    lay = ScatteringLayer(
        z_surface=10e-3, ls=1.8e-3, la=8e-3, envelope="diffusion", single_scattering="field", **layer_kw
    )
    bg = DiffuseBackground(
        lay,
        probe.positions,
        seq.sines,
        win,
        Band(1.8e6, 2.6e6),
        1500.0,
        2,
        0.5 * probe.aperture[0],
        np.random.default_rng(5),
    )
    return bg, probe, seq


def test_the_focal_return_draws_the_gaussian_field_out_of_the_confocal_subspace() -> None:
    """docs/design.md §6.6: with confocal_notch the background holds a notch taken on the array's elements; its Gaussian
    field carries a share of its energy in the confocal subspace there before the notch and next to none after,
    with the same energy."""

    def build(fr: bool, notch: bool = True) -> DiffuseBackground:
        return _small_background(focal_return=fr, confocal_notch=notch)[0]

    with pytest.raises(ValueError, match="confocal_notch: expected focal_return=True"):
        build(False)
    assert build(True, notch=False)._notch is None
    bg = build(True)
    notch = bg._notch
    assert notch is not None
    assert notch.sensor is not None  # the notch is taken on the array's elements
    bg._advance()
    aw = bg.multiple_spectrum() * bg.weights[:, None, None]
    on_elements = bg._project(aw)
    before = _share(notch, on_elements)
    after = notch(aw)
    assert after.shape == on_elements.shape
    assert before > 0.05
    assert _share(notch, after) < 0.2 * before
    np.testing.assert_allclose(np.sum(np.abs(after) ** 2), np.sum(np.abs(on_elements) ** 2), rtol=1e-2)
    # the transport envelope is kept time by time: in 4 µs gates from the surface echo on, within 5 %; before it
    # (where no path arrives) the fit's band-limited edge adds at most a third to the little there is
    gate = round(4e-6 / bg.dt)
    e_before, e_after = (_gated_energy(x, bg.n_bb, gate) for x in (on_elements, after))
    starts = np.arange(e_before.size) * gate * bg.dt  # absolute delays modulo the period (the spectra's phase)
    t_echo, t_end = 2 * 10e-3 / 1500.0, bg.window.t0 + bg.window.duration - bg.window.period  # the record's end
    after_echo = (starts >= t_echo - 1e-6) & (e_before > 1e-3 * e_before.max())
    np.testing.assert_allclose(e_after[after_echo], e_before[after_echo], rtol=0.05)
    early = (starts >= t_end) & (starts + gate * bg.dt <= t_echo)
    assert np.sum(e_after[early]) <= 1.34 * np.sum(e_before[early])
    multiple, single = bg.fork(np.random.default_rng(6)).next_orders()
    assert single is not None and np.all(np.isfinite(multiple))


@pytest.mark.parametrize("matrix", [False, True])
def test_the_plane_waves_adjoint_is_the_adjoint_of_their_projection_onto_the_elements(matrix: bool) -> None:
    """⟨M, E aw⟩ = ⟨E^H M, aw⟩ for `project_plane_waves` (E) and `adjoint_plane_waves`, on a linear array (the
    frequency recursion) and a matrix array on a masked square grid of sines (the separable path)."""
    from fpcore.simulate.diffuse import adjoint_plane_waves, project_plane_waves

    rng = np.random.default_rng(1)
    freqs = np.linspace(1.5e6, 3.0e6, 5)
    a = np.arange(-5, 6) * 0.05
    axes: list[np.ndarray] | None = None
    keep: np.ndarray | None = None
    if matrix:
        el = Probe.matrix(8, 8, 0.5e-3, 2.2e6, 0.8e6).positions
        sx, sy = np.meshgrid(a, a, indexing="ij")
        grid = np.stack([sx.ravel(), sy.ravel()], axis=1)
        keep = np.hypot(grid[:, 0], grid[:, 1]) < 0.26
        s_out, axes = grid[keep], [a, a]
    else:
        el = Probe.linear(16, 0.3e-3, 2.2e6, 0.8e6).positions
        s_out = np.stack([a, np.zeros_like(a)], axis=1)
    shape = (s_out.shape[0], 3, freqs.size)
    aw = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    m_shape = (freqs.size, el.shape[0], 3)
    m = (rng.standard_normal(m_shape) + 1j * rng.standard_normal(m_shape)).astype(np.complex64)
    lhs = np.vdot(m, project_plane_waves(aw, freqs, C0, el, s_out, axes, keep))
    rhs = np.vdot(adjoint_plane_waves(m, freqs, C0, el, s_out, axes, keep), aw)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-5)


def test_keep_envelope_gives_the_after_field_the_before_fields_time_envelope() -> None:
    """keep_envelope: a band-limited field whose envelope was changed smoothly (by up to 6 dB; the notch takes
    20–30 %) gets its own back within 5 % in every gate, and a field that already has it is left as it is."""
    from fpcore.simulate.confocal_notch import keep_envelope

    rng = np.random.default_rng(2)
    n_f, n_t = 64, 128
    shape = (n_f, 300)
    before = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    t = np.arange(n_t)
    change = 0.75 + 0.25 * np.cos(2 * np.pi * t / n_t)  # 0.5 … 1 in amplitude, smooth and periodic
    after = np.fft.fft(np.fft.ifft(before, n=n_t, axis=0) * change[:, None], axis=0)[:n_f].astype(np.complex64)
    e_a = _gated_energy(after, n_t, 16)
    e_b = _gated_energy(before, n_t, 16)
    assert e_a.min() < 0.4 * e_b.min()  # the change is large
    out = keep_envelope(before, after, 0, n_t, 4)
    np.testing.assert_allclose(_gated_energy(out, n_t, 16), e_b, rtol=0.05)
    same = keep_envelope(before, before, 0, n_t, 4)
    np.testing.assert_allclose(same, before, rtol=1e-4, atol=1e-4 * float(np.abs(before).max()))
    with pytest.raises(ValueError, match="n_t: expected at least"):
        keep_envelope(before, before, 0, n_f - 1, 4)


def test_keep_envelope_follows_a_steep_decay_without_the_band_edges_sidelobes() -> None:
    """keep_envelope on a field that starts sharply and decays by 57 dB over the period (the transport tail),
    the notch having taken 8 dB from its bright start only: measured as a pulse would (a Hann taper over the bins),
    the kept field has the field's own envelope within 1 dB down to 57 dB under the peak. Measured on the bins'
    rectangular band instead, the sinc sidelobes of the bright start set the gain in the tail (+2.2 … +2.9 dB from
    37 dB down, docs/design.md §6.6)."""
    from fpcore.simulate.confocal_notch import keep_envelope

    rng = np.random.default_rng(3)
    n_f, n_t, on, gate = 64, 256, 40, 16
    t = np.arange(n_t)
    amp = np.where(t >= on, np.exp(-(t - on) / 20.0), 0.0)
    x = (rng.standard_normal((n_t, 400)) + 1j * rng.standard_normal((n_t, 400))) * amp[:, None]
    before = np.fft.fft(x, axis=0)[:n_f].astype(np.complex64)
    change = np.convolve(np.pad(np.where(t < on + 40, 0.4, 1.0), 8, mode="edge"), np.ones(17) / 17, mode="valid")
    after = np.fft.fft(np.fft.ifft(before, n=n_t, axis=0) * change[:, None], axis=0)[:n_f].astype(np.complex64)
    hann = np.hanning(n_f + 2)[1:-1][:, None]

    def gated(spec: np.ndarray) -> np.ndarray:
        return np.sum(np.abs(np.fft.ifft(spec * hann, n=n_t, axis=0)) ** 2, axis=1).reshape(-1, gate).sum(axis=1)

    e_b = gated(before)
    level = 10 * np.log10(e_b / e_b.max())
    assert np.max(np.abs(10 * np.log10(gated(after) / e_b))[level > -20]) > 6  # the notch's change is large
    tail = (t[::gate] > on) & (level > -58)
    assert level[tail].min() < -50  # down the tail
    ratio = 10 * np.log10(gated(keep_envelope(before, after, 0, n_t, 4)) / e_b)
    assert np.max(np.abs(ratio[tail])) < 1.0


def test_keep_envelope_stays_bounded_where_the_field_is_dark() -> None:
    """keep_envelope on a field that is dark (exactly zero before its onset, as the beads' speckle before the surface
    echo) and whose changed copy leaks a little there: the running mean's energy is a sum of non-negative terms, so
    the gain stays finite and the kept field has the field's own energy (a convolution through FFTs left −1e-8 of
    the peak in the dark part, and the gain against that floor reached 1e11)."""
    from fpcore.simulate.confocal_notch import keep_envelope

    rng = np.random.default_rng(4)
    n_f, n_t, on = 74, 150, 60
    t = np.arange(n_t)
    amp = np.where(t >= on, np.exp(-(t - on) / 25.0), 0.0)
    x = (rng.standard_normal((n_t, 300)) + 1j * rng.standard_normal((n_t, 300))) * amp[:, None]
    before = np.fft.fft(x, axis=0)[:n_f].astype(np.complex64)
    leak = (rng.standard_normal(before.shape) + 1j * rng.standard_normal(before.shape)).astype(np.complex64)
    after = before * np.float32(0.95) + np.float32(1e-4) * leak
    out = keep_envelope(before, after, 0, n_t, 2)
    assert np.all(np.isfinite(out))
    assert np.sum(np.abs(out) ** 2) == pytest.approx(float(np.sum(np.abs(before) ** 2)), rel=0.02)


def test_the_notched_field_keeps_the_measured_reciprocity() -> None:
    """docs/design.md §6.6: the notch takes a reflectivity's (symmetric) part out of the field and would leave the
    beams' antisymmetric remainder a larger share; with cbs the notched field is projected back onto the measured
    reciprocity (`reciprocity.ElementReciprocity`) before its envelope is restored, so its symmetry through the
    transmits, |Σ S S^T*|/Σ|S|² off the diagonal, is that of a reciprocal medium after the time gain too."""
    bg, probe, seq = _small_background(cbs=True, angular="halo", focal_return=True, confocal_notch=True)
    assert bg._notch is not None and isinstance(bg._notch.constraint, ElementReciprocity)
    symmetry = ElementReciprocity(probe.positions, seq.sines, bg.freqs, 1500.0).symmetry

    bg._advance()
    aw = bg.multiple_spectrum() * bg.weights[:, None, None]
    before = symmetry(bg._project(aw))
    with_constraint = symmetry(bg._notch(aw))
    bg._notch.constraint = None
    without = symmetry(bg._notch(aw))
    assert before > 0.9 and without < before - 0.05  # the notch alone loses the symmetry (0.97 → 0.85 here)
    assert with_constraint > 0.99
