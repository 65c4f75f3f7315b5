"""The angular memory effect of the multiple-scattering background (fpcore.simulate.memory, docs/design.md §6.5):
noise correlated under a common tilt of input and output as exp(−k²δ²D_eff) (eq. M1), uncorrelated between
distinct paths, with the energy the array receives unchanged and the reciprocal block still symmetric."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore.acquisition import PlaneWaveSequence, Probe
from fpcore.simulate.diffuse import DiffuseBackground, a_g2
from fpcore.simulate.medium import ScatteringLayer
from fpcore.simulate.memory import block_energy_gain, correlate_lines, effective_spread, gaussian_roots, lattice_steps
from fpcore.simulate.waves import Band, TimeWindow

C0 = 1500.0


def _white(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return ((rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2)).astype(np.complex64)


def test_roots_square_to_the_gaussian_correlation() -> None:
    beta = np.array([0.0, 0.3, 2.0])
    r = gaussian_roots(beta, 7)
    lag = np.arange(7)[:, None] - np.arange(7)[None, :]
    np.testing.assert_allclose(r @ r, np.exp(-beta[:, None, None] * lag[None] ** 2), atol=2e-6)
    np.testing.assert_allclose(r, np.swapaxes(r, 1, 2), atol=1e-6)


def test_lines_correlate_along_a_common_tilt_only() -> None:
    """Entries n steps apart on one line u = c + L v correlate as exp(−β n²); other entries do not; every entry
    keeps unit variance; with a stride, entries an odd number of steps apart are independent."""
    rng = np.random.default_rng(0)
    beta = np.array([0.0, 0.15, 1.0])
    n_u, n_v, n_s, slope = 24, 6, 3000, 3
    x = _white(rng, (n_u, n_s, n_v, beta.size))
    roots = [gaussian_roots(beta, n) for n in range(n_v + 1)]
    y = correlate_lines(x, 0, 2, slope, roots)

    def corr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.abs(np.mean(a * np.conj(b), axis=0))

    np.testing.assert_allclose(np.mean(np.abs(y) ** 2, axis=1), 1.0, atol=0.08)
    for n in (1, 2):
        np.testing.assert_allclose(corr(y[4, :, 1], y[4 + n * slope, :, 1 + n]), np.exp(-beta * n**2), atol=0.06)
    assert np.all(corr(y[4, :, 1], y[5, :, 2]) < 0.06)  # another line
    assert np.all(corr(y[4, :, 1], y[4, :, 2]) < 0.06)  # same output, next transmit
    strided = correlate_lines(x, 0, 2, slope, [gaussian_roots(beta, n) for n in range(4)], stride=2)
    assert np.all(corr(strided[4, :, 1], strided[4 + slope, :, 2]) < 0.06)
    np.testing.assert_allclose(corr(strided[4, :, 1], strided[4 + 2 * slope, :, 3]), np.exp(-beta), atol=0.06)


def test_effective_spread_is_the_diffusion_spread_bounded_by_the_beams() -> None:
    tau = np.array([-1e-6, 0.0, 1e-8, 1.0])
    d = effective_spread(tau, 1.8e-3, C0, 2, 60e-6)
    assert d[0] == 0.0 and d[1] == 0.0
    assert d[2] == pytest.approx(0.9e-3 * C0 * 1e-8, rel=1e-3)  # D's while the halo is small
    assert d[3] == pytest.approx(60e-6 / 4, rel=1e-3)  # a_g²/4 once it outgrows the aperture


def _rig(memory: bool, seed: int = 3) -> DiffuseBackground:
    probe = Probe.linear(48, C0 / 2.2e6 / 2, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(9, 0.2)
    win = TimeWindow.covering(10.4e6, 16e-6, 40e-6, guard=20e-6)
    lay = ScatteringLayer(z_surface=10e-3, ls=1.8e-3, la=8e-3, cbs=True, angular="halo", memory=memory)
    return DiffuseBackground(
        lay, probe.positions, seq.sines, win, Band(1.8e6, 2.6e6), C0, 2, 0.5 * probe.aperture[0],
        np.random.default_rng(seed),
    )  # fmt: skip


def test_background_noise_follows_the_memory_law() -> None:
    """The main grid's noise: (o + L, θ + 1) against (o, θ) correlates as exp(−k_c²δ²D_eff(τ)) (eq. M1) at each
    time sample, δ one transmit step; (o + 1, θ + 1) is another path and does not correlate."""
    bg = _rig(True)
    sines = bg.s_out[:, 0]
    step = int(round(0.05 / (sines[1] - sines[0])))  # 9 transmits in ±0.2: 0.05 apart
    draws = np.stack([bg._noise() for _ in range(6)])  # (n, N_o, N_θ, n_bb)
    t = bg._t - 2 * bg.layer.z_surface / C0
    kc = 2 * np.pi * bg.band.centre / C0
    want = np.exp(-(kc**2) * 0.05**2 * effective_spread(t, 1.8e-3, C0, 2, a_g2(bg._aperture_radius)))
    a, b, c = draws[:, :-step, :-1], draws[:, step:, 1:], draws[:, 1 : 1 + bg.n_o - step, 1:]
    var = np.mean(np.abs(a) ** 2, axis=(0, 1, 2))
    got = np.abs(np.mean(b * np.conj(a), axis=(0, 1, 2))) / var
    for gate in ((0, 30), (60, 90), (110, 140)):  # young, middle, late samples (n_bb = 150)
        sl = slice(*gate)
        assert np.mean(got[sl]) == pytest.approx(np.mean(want[sl]), abs=0.05)
    other = np.abs(np.mean(c * np.conj(a), axis=(0, 1, 2))) / var
    assert np.mean(other) < 0.05


def test_memory_keeps_the_block_symmetric_the_retro_doubled_and_the_energy() -> None:
    """With the memory effect the block's noise is still T_ij = T_ji (packed), the exactly retro-reflected
    plane wave still carries twice the ladder (noise times the block's envelope factor), and the elements
    receive the same energy (`block_energy_gain` divides out the redistribution within a transmit's beam)
    within 0.5 dB over a few realisations."""
    bg = _rig(True)
    blk = bg.block
    assert blk is not None
    doubling = blk.envelopes([np.ones((blk.n_pairs, 1, 1), np.float32)])[0][:, 0]  # the block's factor on a ladder
    x = np.stack([bg._block_noise()[:, 0] * doubling for _ in range(8)])  # (n, n_pairs, n_bb)
    i, j = blk.pairs
    p = np.mean(np.abs(x) ** 2, axis=(0, 2))
    far = np.abs(blk.inputs[j, 0] - blk.inputs[i, 0]) > 0.15  # well outside the plane-wave cone
    assert np.mean(p[blk.diagonal]) / np.mean(p[far]) == pytest.approx(2.0, abs=0.15)
    energy = {}
    for memory in (False, True):
        e = []
        for seed in range(4):
            e.append(np.mean(np.abs(_rig(memory, seed).next()) ** 2))
        energy[memory] = np.mean(e)
    assert abs(10 * np.log10(energy[True] / energy[False])) < 0.5


def test_energy_gain_is_one_without_correlation_and_the_beam_overlap_with_full_correlation() -> None:
    """G(t) = Σ_n B(nΔs) ρ_B(n) C(n) (`block_energy_gain`): 1 where (M1) has decayed (only n = 0 is left),
    and above 1 where every tilt is correlated and the transmit's beam spans several grid steps (L = 1)."""
    n_el, pitch = 12, C0 / 2.2e6 / 2
    el = np.zeros((n_el, 3))
    el[:, 0] = (np.arange(n_el) - (n_el - 1) / 2) * pitch
    ds = 0.05
    sines = np.stack([np.arange(-3, 4) * ds, np.zeros(7)], axis=1)  # on every grid step: L = 1
    m = np.stack([np.arange(-5, 6), np.zeros(11, dtype=int)], axis=1)
    k = 2 * np.pi * 2.2e6 / C0
    assert lattice_steps(sines, [ds]) == [1]
    g = block_energy_gain(el, [ds], m, lattice_steps(sines, [ds]), lambda d: np.array([1e6, 0.0]), k)
    assert g[0] == pytest.approx(1.0, abs=1e-9)
    assert g[1] > 1.5


def test_memory_without_reciprocity_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="memory"):
        ScatteringLayer(z_surface=5e-3, ls=1.8e-3, memory=True)
