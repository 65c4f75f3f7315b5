"""Frequency-domain building blocks: transducer band, time window, RF synthesis, Green functions,
plane-wave incidence and the point-cloud radiation engine.

Conventions (docs/design.md §3–4): R(f) = ∫ R(t) e^{-i2πft} dt; an incident plane wave of direction sines
(s_x, s_y), cosine c = √(1 − s_x² − s_y²), fired with delays τ = (u_x s_x + u_y s_y)/c0, is
p_inc(r, f) = exp(−ik(x s_x + y s_y + z c)) (time zero when the wavefront crosses the array origin);
outgoing waves are e^{-ikr}:

    G_3D(d) = e^{−ikd} / (4πd),         G_2D(d) = (−i/4) H_0^{(2)}(kd)

(both solve ∇²G + k²G = −δ; they are the complex conjugates of the paper's Methods eq. for G with
its e^{+ikr} convention). Transfer functions H(u, θ, f) are dimensionless pressures at element u
relative to the incident plane-wave amplitude; the recorded spectrum is X(f) = S(f) H(f) with S the
two-way transducer band (`Band`), and the RF follows by an inverse rFFT with the t0 phase
(`TimeWindow.synthesize`), the exact inverse of `Acquisition.spectrum`.

Elements are ideal points (omnidirectional) and transmits are ideal, laterally infinite plane waves;
the finite aperture enters through where the elements are, as in the paper's own shift model
(Methods, "Virtual shift of the target").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from ..geometry import cosines
from .special import hankel2_0

__all__ = [
    "Band",
    "TimeWindow",
    "cosines",
    "green",
    "incident_phase",
    "radiate_points",
]


@dataclass(frozen=True)
class Band:
    """Two-way transducer response S(f): a Hann (cos²) bump, −6 dB at f_min and f_max.

    S(f) = cos²(π (f − f_c)/(2W)) / (2W) for |f − f_c| < W, W = f_max − f_min, so its support is
    [f_c − W, f_c + W] and the pulse s(t) = ∫ S(f) e^{i2πft} df (two-sided) has s(0) = 1: RF amplitudes
    are pressures relative to the incident pulse's peak. (The paper's COMSOL model also used a Hann
    spectral window, Supplementary Table S1.)
    """

    f_min: float
    f_max: float

    def __post_init__(self) -> None:
        if not (0 < self.f_min < self.f_max):
            raise ValueError(f"band: expected 0 < f_min < f_max, got [{self.f_min}, {self.f_max}]")
        if self.f_max - self.f_min >= 0.5 * (self.f_min + self.f_max):
            raise ValueError("band: the Hann support f_c ± (f_max − f_min) must stay above 0 Hz")

    @property
    def centre(self) -> float:
        return 0.5 * (self.f_min + self.f_max)

    @property
    def width(self) -> float:
        return self.f_max - self.f_min

    @property
    def support(self) -> tuple[float, float]:
        return self.centre - self.width, self.centre + self.width

    def spectrum(self, f: np.ndarray) -> np.ndarray:
        """S(f) in 1/Hz (real, ≥ 0)."""
        x = (np.asarray(f, dtype=np.float64) - self.centre) / self.width
        return np.where(np.abs(x) < 1.0, np.cos(0.5 * np.pi * x) ** 2, 0.0) / (2 * self.width)

    def pulse_energy(self) -> float:
        """E_s = ∫ s(t)² dt = 2 ∫_0^∞ S(f)² df = 3/(8W) (seconds)."""
        return 3.0 / (8.0 * self.width)


@dataclass(frozen=True)
class TimeWindow:
    """Recorded samples t = t0 + n/fs, n < n_samples; spectra live on an rFFT grid of n_fft ≥ n_samples
    points (period n_fft/fs) so that echoes a little outside the window do not wrap into it."""

    fs: float
    t0: float
    n_samples: int
    n_fft: int

    @classmethod
    def covering(cls, fs: float, t_start: float, t_end: float, guard: float = 15e-6) -> TimeWindow:
        n = int(np.ceil((t_end - t_start) * fs))
        n_fft = sfft.next_fast_len(int(np.ceil((t_end - t_start + guard) * fs)), real=True)
        return cls(fs, t_start, n, max(n_fft, n))

    @property
    def duration(self) -> float:
        return self.n_samples / self.fs

    @property
    def period(self) -> float:
        return self.n_fft / self.fs

    def freqs(self) -> np.ndarray:
        return np.fft.rfftfreq(self.n_fft, 1.0 / self.fs)

    def band_bins(self, band: Band) -> np.ndarray:
        """Indices of the rFFT bins inside the band's support (where S > 0)."""
        f = self.freqs()
        lo, hi = band.support
        idx = np.nonzero((f > lo) & (f < hi))[0]
        if idx.size == 0 or hi >= self.fs / 2:
            raise ValueError(f"window: fs = {self.fs:g} Hz does not resolve the band support [{lo:g}, {hi:g}]")
        return idx

    def times(self) -> np.ndarray:
        return self.t0 + np.arange(self.n_samples) / self.fs

    def synthesize(self, spectrum: np.ndarray, bins: np.ndarray) -> np.ndarray:
        """RF (N_u, N_θ, n_samples) float32 from X(f) on `bins`, given as (N_f, N_u, N_θ).

        Inverse of `Acquisition.spectrum`: X(f) = Σ_n r(t0 + n/fs) e^{−i2πf(t0+n/fs)}/fs, hence
        r = irfft(fs · X(f) · e^{i2πf t0}) (docs/design.md §4.1).
        """
        n_f, n_u, n_i = spectrum.shape
        f = self.freqs()[bins]
        full = np.zeros((n_u, n_i, self.n_fft // 2 + 1), dtype=np.complex64)
        ph = (self.fs * np.exp(2j * np.pi * f * self.t0)).astype(np.complex64)
        full[:, :, bins] = np.transpose(spectrum * ph[:, None, None], (1, 2, 0))
        rf = sfft.irfft(full, n=self.n_fft, axis=2, workers=-1)[:, :, : self.n_samples]
        return np.ascontiguousarray(rf, dtype=np.float32)

    def analyse(self, signal: np.ndarray, bins: np.ndarray) -> np.ndarray:
        """X(f) on `bins` of a time signal (N_u, N_θ, n_fft) sampled from t0: (N_f, N_u, N_θ) complex64."""
        spec = sfft.rfft(signal, n=self.n_fft, axis=2, workers=-1)[:, :, bins]
        f = self.freqs()[bins]
        ph = (np.exp(-2j * np.pi * f * self.t0) / self.fs).astype(np.complex64)
        return np.ascontiguousarray(np.transpose(spec * ph, (2, 0, 1)), dtype=np.complex64)


def green(k: float, d: np.ndarray, dim: int) -> np.ndarray:
    """Outgoing Green function G(d) for the e^{-i2πft} spectra: e^{-ikd}/(4πd) (3D), (−i/4)H_0^{(2)}(kd) (2D)."""
    d = np.asarray(d, dtype=np.float64)
    if dim == 3:
        return np.exp(-1j * k * d) / (4 * np.pi * d)
    if dim == 2:
        return -0.25j * hankel2_0(k * d)
    raise ValueError(f"dim: expected 2 or 3, got {dim}")


def incident_phase(k: float, sines: np.ndarray, points: np.ndarray) -> np.ndarray:
    """exp(−ik(x s_x + y s_y + z c)), shape (N_points, N_θ) (docs/design.md §3, paper Methods P(θ, r, f))."""
    return np.exp(-1j * k * _path_in(sines, points))


def _path_in(sines: np.ndarray, points: np.ndarray) -> np.ndarray:
    s = np.asarray(sines, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    return p[:, 0:1] * s[None, :, 0] + p[:, 1:2] * s[None, :, 1] + p[:, 2:3] * cosines(s)[None, :]


def _uniform_step(freqs: np.ndarray) -> float | None:
    if freqs.size < 2:
        return None
    df = np.diff(freqs)
    return float(df[0]) if np.allclose(df, df[0], rtol=1e-9, atol=0) else None


def radiate_points(
    points: np.ndarray,
    strength: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    freqs: np.ndarray,
    c0: float,
    dim: int,
    *,
    excitation: Callable[[int], np.ndarray] | None = None,
    att_in: np.ndarray | None = None,
    att_out: np.ndarray | None = None,
    spectral: np.ndarray | None = None,
    chunk: int = 4096,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """H(f, u, θ) = Σ_j G(u, r_j; k_f) t_j(f) ψ_j(θ, f) for point scatterers (Born or Foldy–Lax).

    points (N_s, 3); strength t_j: (N_s,) or (N_s, N_f) complex (scattered field t ψ G, docs/design.md §6);
    ψ_j = exp(−ik(s·ρ_j + c z_j)) (the incident plane wave) unless `excitation(m)` returns the
    exciting field (N_s, N_θ) at frequency index m (Foldy–Lax). att_in (N_s, N_θ) and att_out
    (N_u, N_s) multiply the incoming and outgoing legs (ballistic extinction, `medium`); `spectral`
    (N_f,) is a common frequency factor of all strengths (e.g. 2ik for Born mirrors).

    Per frequency this is one complex64 matrix product (N_u × N_s)·(N_s × N_θ); the propagators are
    advanced from one frequency bin to the next by multiplication with e^{−iΔk d} (re-anchored every
    32 bins), so no transcendental is evaluated per (u, j, f). The 2D Green function uses its
    large-argument form (−i/4)√(2/(πkd)) e^{−i(kd − π/4)} (1 + i/(8kd)) with the 1/(8kd) correction
    taken at the band centre: relative error ≲ 1/(8 kd)·Δk/k + 9/(128 (kd)²) (< 1e-4 for kd > 30).
    Returns complex64 (N_f, N_u, N_θ) (added into `out` if given).
    """
    pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
    el = np.asarray(elements, dtype=np.float64)
    freqs = np.asarray(freqs, dtype=np.float64)
    n_s, n_u, n_i, n_f = pts.shape[0], el.shape[0], sines.shape[0], freqs.size
    if out is None:
        out = np.zeros((n_f, n_u, n_i), dtype=np.complex64)
    if n_s == 0:
        return out
    if dim not in (2, 3):
        raise ValueError(f"dim: expected 2 or 3, got {dim}")
    strength = np.asarray(strength)
    per_f = strength.ndim == 2
    k = 2 * np.pi * freqs / c0
    kc = float(np.mean(k))
    df = _uniform_step(freqs)
    dk = 2 * np.pi * df / c0 if df is not None else None
    # Frequency-dependent scalar in front of every propagator.
    if dim == 3:
        scal = np.full(n_f, 1.0 / (4 * np.pi), dtype=np.complex128)
    else:
        scal = -0.25j * np.exp(0.25j * np.pi) * np.sqrt(2.0 / (np.pi * k))
    if spectral is not None:
        scal = scal * np.asarray(spectral)
    for a in range(0, n_s, chunk):
        sl = slice(a, min(a + chunk, n_s))
        p = pts[sl]
        if dim == 2:
            d = np.hypot(el[:, None, 0] - p[None, :, 0], el[:, None, 2] - p[None, :, 2])
        else:
            d = np.linalg.norm(el[:, None, :] - p[None, :, :], axis=2)
        d = np.maximum(d, 1e-9)
        amp_out = 1.0 / d if dim == 3 else d**-0.5 * (1.0 + 1j / (8 * kc * d))
        if att_out is not None:
            amp_out = amp_out * att_out[:, sl]
        phin = _path_in(sines, p)
        amp_in: np.ndarray | None = None if per_f else np.asarray(strength[sl], dtype=np.complex128)[:, None]
        if att_in is not None:
            amp_in = (1.0 if amp_in is None else amp_in) * att_in[sl]
        e_out: np.ndarray  # set at m = 0 (and every 32 frequencies, or each one when they are not uniform)
        e_in: np.ndarray
        step_out: np.ndarray  # set when the frequencies are uniform (dk), the only case they are used
        step_in: np.ndarray
        for m in range(n_f):
            if dk is None or m % 32 == 0:
                e_out = (amp_out * np.exp(-1j * k[m] * d)).astype(np.complex64)
                e_in = np.exp(-1j * k[m] * phin)
                if amp_in is not None and excitation is None:
                    e_in = e_in * amp_in
                if dk is not None:
                    step_out = np.exp(-1j * dk * d).astype(np.complex64)
                    step_in = np.exp(-1j * dk * phin)
            if excitation is None:
                amat = e_in if not per_f else e_in * strength[sl, m][:, None]
            else:
                t = strength[sl, m] if per_f else strength[sl]
                amat = excitation(m)[sl] * t[:, None]
                if att_in is not None:
                    amat = amat * att_in[sl]
            prod = e_out @ amat.astype(np.complex64)
            prod *= np.complex64(scal[m])
            out[m] += prod
            if dk is not None:
                e_out *= step_out
                if excitation is None:
                    e_in = e_in * step_in
    return out
