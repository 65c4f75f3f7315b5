"""Single-scattering (first Born) plane-wave acquisitions of point reflectors — a small exact model.

R(u, θ, f) = Σ_p a_p S(f) e^{-i2πf(τ_in(θ, r_p) + |u − r_p|/c0 − t0)} / √|u − r_p|

with the plane-wave transmit delay τ_in = (x s_x + y s_y + z c)/c0 (paper, Methods "Acquisition of the
reflection matrix"), the outgoing return path and the numpy FFT sign (docs/design.md §4.1); S(f) is a
Gaussian transducer band. Only the band's bins are computed. It is the reference for sign and position
tests and the engine of the quick offline demo; `fpcore.simulate` holds the full physical simulator.
"""

from __future__ import annotations

import numpy as np

from .acquisition import Acquisition, PlaneWaveSequence, Probe
from .geometry import cosines

__all__ = ["born_points"]


def born_points(
    probe: Probe,
    seq: PlaneWaveSequence,
    points: np.ndarray,
    amps: np.ndarray,
    fs: float = 20e6,
    n_t: int = 640,
    c0: float = 1540.0,
    t0: float = 0.0,
    fc: float | None = None,
    bw: float | None = None,
    frame_index: int = 0,
    timestamp: float = 0.0,
) -> Acquisition:
    """RF frame (N_u, N_θ, n_t) of point reflectors at `points` (P, 3) with amplitudes `amps` (P,)."""
    fc = probe.centre_frequency if fc is None else fc
    bw = probe.bandwidth if bw is None else bw
    f_all = np.fft.rfftfreq(n_t, 1 / fs)
    pulse_all = np.exp(-(((f_all - fc) / (0.6 * bw)) ** 2))
    band = np.nonzero(pulse_all > 1e-6)[0]
    f, pulse = f_all[band], pulse_all[band]
    s = seq.sines
    c = cosines(s)
    spec = np.zeros((probe.n_elements, seq.n_waves, f.size), np.complex128)
    w = -2j * np.pi * f
    for r, a in zip(np.atleast_2d(points), np.atleast_1d(amps), strict=True):
        tin = (r[0] * s[:, 0] + r[1] * s[:, 1] + r[2] * c) / c0
        d = np.linalg.norm(probe.positions - r[None, :], axis=1)
        e_out = np.exp(w[None, :] * (d[:, None] / c0 - t0)) * (a / np.sqrt(d))[:, None]  # (u, f)
        e_in = np.exp(w[None, :] * tin[:, None])  # (θ, f)
        spec += e_out[:, None, :] * e_in[None, :, :]
    full = np.zeros((probe.n_elements, seq.n_waves, f_all.size), np.complex128)
    full[:, :, band] = spec * pulse * fs
    rf = np.fft.irfft(full, n=n_t, axis=2).astype(np.float32)
    return Acquisition(rf, fs, t0, c0, probe, seq, frame_index=frame_index, timestamp=timestamp)
