"""Shared test fixtures: a tiny single-scattering (Born) forward model for point reflectors.

R(u, θ, f) = Σ_p a_p S(f) e^{-i2πf(τ_in(θ, r_p) + |u − r_p|/c0)} / √|u − r_p| — the plane-wave
transmit delay τ_in = (x s_x + y s_y + z c)/c0 (paper, Methods) and the outgoing return path, with
the numpy FFT sign (DESIGN.md §4.1). Small and exact: it is the reference for sign and position tests.
"""

from __future__ import annotations

import numpy as np
import pytest

from fpcore import Acquisition, PlaneWaveSequence, Probe


def born_points(probe: Probe, seq: PlaneWaveSequence, points: np.ndarray, amps: np.ndarray,
                fs: float = 20e6, n_t: int = 640, c0: float = 1540.0, t0: float = 0.0,
                fc: float | None = None, bw: float | None = None) -> Acquisition:
    fc = probe.centre_frequency if fc is None else fc
    bw = probe.bandwidth if bw is None else bw
    f = np.fft.rfftfreq(n_t, 1 / fs)
    pulse = np.exp(-(((f - fc) / (0.6 * bw)) ** 2))
    s = seq.sines
    c = np.sqrt(1 - s[:, 0] ** 2 - s[:, 1] ** 2)
    spec = np.zeros((probe.n_elements, seq.n_waves, f.size), complex)
    for r, a in zip(np.atleast_2d(points), np.atleast_1d(amps), strict=True):
        tin = (r[0] * s[:, 0] + r[1] * s[:, 1] + r[2] * c) / c0
        d = np.linalg.norm(probe.positions - r[None, :], axis=1)
        delay = tin[None, :, None] + d[:, None, None] / c0 - t0
        spec += a * np.exp(-2j * np.pi * f[None, None, :] * delay) / np.sqrt(d)[:, None, None]
    rf = np.fft.irfft(spec * pulse * fs, n=n_t, axis=2).astype(np.float32)
    return Acquisition(rf, fs, t0, c0, probe, seq)


@pytest.fixture
def linear_setup() -> tuple[Probe, PlaneWaveSequence]:
    return Probe.linear(48, 0.3e-3, 2.5e6, 1.5e6), PlaneWaveSequence.from_angles(np.linspace(-12, 12, 7))


@pytest.fixture
def matrix_setup() -> tuple[Probe, PlaneWaveSequence]:
    probe = Probe.matrix(12, 12, 0.3e-3, 2.5e6, 1.5e6)
    return probe, PlaneWaveSequence.from_angles(np.linspace(-8, 8, 3), np.linspace(-8, 8, 3))
