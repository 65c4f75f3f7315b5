"""Acquisition data model: probe, plane-wave sequence, RF frame and its frequency-domain views.

Conventions (docs/design.md §3, §4.1–4.2):

* Element positions are metres, shape (N_u, 3); a linear array has y = 0.
* A plane wave is described by its direction sines (s_x, s_y); the transmit delay on element u is
  τ = (u_x s_x + u_y s_y)/c0 (paper, Methods "Acquisition of the reflection matrix"), with time zero
  when the wavefront crosses the array origin.
* RF data R(u_out, θ_in, t) is real, shape (N_u, N_θ, N_t), sample n at t = t0 + n/fs.
* Spectrum: R(f) = ∫ R(t) e^{-i2πft} dt (paper eq. before Fig. 1; numpy's forward FFT sign).
* Output projection to plane waves: R_θθ(f) = P_θu(f) R_uθ(f), P_θu = exp(-i k s_θ·u) (docs/design.md §4.2).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.fft as sfft

from . import kernel_presum_loops as loops
from .kernel import default_threads
from .truth import Truth

__all__ = [
    "Probe",
    "PlaneWaveSequence",
    "Acquisition",
    "Spectrum",
    "PlaneWaveData",
    "output_sines",
    "to_plane_waves",
]


def _as_sines(sines: np.ndarray) -> np.ndarray:
    s = np.asarray(sines, dtype=np.float64)
    if s.ndim == 1:
        s = np.stack([s, np.zeros_like(s)], axis=1)
    if s.ndim != 2 or s.shape[1] != 2:
        raise ValueError(f"sines: expected shape (N, 2) or (N,), got {s.shape}")
    if np.any(s[:, 0] ** 2 + s[:, 1] ** 2 >= 1.0):
        raise ValueError("sines: every direction must satisfy s_x² + s_y² < 1 (propagating waves)")
    return s


@dataclass(frozen=True)
class Probe:
    """Array of transducers.

    positions: (N_u, 3) element centres in metres (linear arrays have y = 0).
    pitch: element pitch in metres.
    centre_frequency, bandwidth: transducer band in Hz (bandwidth is the full -6 dB width).
    """

    positions: np.ndarray
    pitch: float
    centre_frequency: float
    bandwidth: float

    def __post_init__(self) -> None:
        pos = np.asarray(self.positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"probe.positions: expected shape (N_u, 3), got {pos.shape}")
        object.__setattr__(self, "positions", pos)
        if self.pitch <= 0:
            raise ValueError(f"probe.pitch: expected > 0 m, got {self.pitch}")

    @classmethod
    def linear(cls, n: int, pitch: float, centre_frequency: float, bandwidth: float) -> Probe:
        """Linear array of n elements along x, centred on the origin."""
        x = (np.arange(n) - (n - 1) / 2) * pitch
        return cls(np.stack([x, np.zeros(n), np.zeros(n)], axis=1), pitch, centre_frequency, bandwidth)

    @classmethod
    def matrix(cls, nx: int, ny: int, pitch: float, centre_frequency: float, bandwidth: float) -> Probe:
        """Matrix array nx × ny (x fastest), centred on the origin."""
        x = (np.arange(nx) - (nx - 1) / 2) * pitch
        y = (np.arange(ny) - (ny - 1) / 2) * pitch
        yy, xx = np.meshgrid(y, x, indexing="ij")
        pos = np.stack([xx.ravel(), yy.ravel(), np.zeros(nx * ny)], axis=1)
        return cls(pos, pitch, centre_frequency, bandwidth)

    @property
    def n_elements(self) -> int:
        return self.positions.shape[0]

    @property
    def is_linear(self) -> bool:
        return bool(np.all(self.positions[:, 1] == 0.0))

    @property
    def aperture(self) -> tuple[float, float]:
        """Extent (x, y) of the active surface in metres, one pitch added to the centre span."""
        span = np.ptp(self.positions[:, :2], axis=0)
        ax = float(span[0] + self.pitch)
        ay = float(span[1] + self.pitch) if not self.is_linear else 0.0
        return ax, ay

    def grid_axes(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(x, y) axes if elements form a full regular grid in x-fastest order, else None."""
        return element_grid_axes(self.positions)


def element_grid_axes(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(x, y) axes if element positions (N, 3) form a full regular grid in x-fastest order, else None."""
    pos = np.asarray(positions, dtype=np.float64)
    xs = np.unique(pos[:, 0])
    ys = np.unique(pos[:, 1])
    if xs.size * ys.size != pos.shape[0]:
        return None
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    if np.allclose(pos[:, 0], xx.ravel()) and np.allclose(pos[:, 1], yy.ravel()):
        return xs, ys
    return None


@dataclass(frozen=True)
class PlaneWaveSequence:
    """Transmitted plane waves: direction sines (N_θ, 2) = (s_x, s_y); ``prf`` (Hz, optional): the
    transmits fire in order every 1/prf (needed only for motion-aware fingerprints)."""

    sines: np.ndarray
    prf: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "sines", _as_sines(self.sines))
        if self.prf is not None and not (np.isfinite(self.prf) and self.prf > 0):
            raise ValueError(f"prf: expected a positive pulse repetition frequency in Hz, got {self.prf}")

    def transmit_times(self) -> np.ndarray:
        """Firing time of each transmit relative to the middle of the sequence, (j − (N_θ − 1)/2)/prf (s)."""
        if self.prf is None:
            raise ValueError("prf: the sequence has no pulse repetition frequency (transmit times unknown)")
        return (np.arange(self.n_waves) - (self.n_waves - 1) / 2) / self.prf

    @classmethod
    def from_angles(cls, theta_x_deg: np.ndarray, theta_y_deg: np.ndarray | None = None) -> PlaneWaveSequence:
        """Fan of angles (degrees) in x (and a tensor grid with y if theta_y_deg is given)."""
        sx = np.sin(np.deg2rad(np.asarray(theta_x_deg, dtype=float)))
        if theta_y_deg is None:
            return cls(np.stack([sx, np.zeros_like(sx)], axis=1))
        sy = np.sin(np.deg2rad(np.asarray(theta_y_deg, dtype=float)))
        yy, xx = np.meshgrid(sy, sx, indexing="ij")
        return cls(np.stack([xx.ravel(), yy.ravel()], axis=1))

    @classmethod
    def uniform_sines(cls, n: int, s_max: float, ny: int | None = None) -> PlaneWaveSequence:
        """n (× ny) sines evenly spaced in [-s_max, s_max] (a tensor grid if ny is given)."""
        sx = np.linspace(-s_max, s_max, n) if n > 1 else np.zeros(1)
        if ny is None:
            return cls(np.stack([sx, np.zeros_like(sx)], axis=1))
        sy = np.linspace(-s_max, s_max, ny) if ny > 1 else np.zeros(1)
        yy, xx = np.meshgrid(sy, sx, indexing="ij")
        return cls(np.stack([xx.ravel(), yy.ravel()], axis=1))

    @property
    def n_waves(self) -> int:
        return self.sines.shape[0]

    def transmit_delays(self, probe: Probe, c0: float) -> np.ndarray:
        """τ(θ, u) = (u_x s_x + u_y s_y)/c0, shape (N_θ, N_u) (paper, Methods)."""
        return (self.sines @ probe.positions[:, :2].T) / c0


@dataclass
class Acquisition:
    """One RF frame R(u_out, θ_in, t): real array (N_u, N_θ, N_t), sample n at t0 + n/fs.

    truth: the frame's ground truth as the JSON object it travels as (wire, UFF, JSON; empty if none);
    `ground_truth` is its typed view (`fpcore.truth.Truth`).
    """

    rf: np.ndarray
    fs: float
    t0: float
    c0: float
    probe: Probe
    sequence: PlaneWaveSequence
    frame_index: int = 0
    timestamp: float = 0.0
    truth: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        rf = np.asarray(self.rf)
        expected = (self.probe.n_elements, self.sequence.n_waves)
        if rf.ndim != 3 or rf.shape[:2] != expected:
            raise ValueError(f"rf: expected shape (N_u={expected[0]}, N_theta={expected[1]}, N_t), got {rf.shape}")
        if not np.issubdtype(rf.dtype, np.number) or np.iscomplexobj(rf):
            raise ValueError(f"rf: expected a real numeric array, got dtype {rf.dtype}")
        if not np.all(np.isfinite(rf)):
            raise ValueError("rf: contains NaN or infinite samples")
        if not (self.fs > 0 and np.isfinite(self.fs)):
            raise ValueError(f"fs: expected a positive sampling frequency in Hz, got {self.fs}")
        if not (self.c0 > 0 and np.isfinite(self.c0)):
            raise ValueError(f"c0: expected a positive sound speed in m/s, got {self.c0}")
        self.rf = rf

    @property
    def n_samples(self) -> int:
        return self.rf.shape[2]

    @property
    def times(self) -> np.ndarray:
        return self.t0 + np.arange(self.n_samples) / self.fs

    @property
    def ground_truth(self) -> Truth:
        """The typed view of `truth` (an empty Truth when the frame carries none)."""
        return Truth.from_dict(self.truth) if isinstance(self.truth, Mapping) else Truth()

    def default_band(self) -> tuple[float, float]:
        """The band to image: the truth's ``band_hz`` if the frame carries one (simulated frames), else
        the probe's −6 dB band [f_c − B/2, f_c + B/2] clipped to [0, fs/2]."""
        band = self.ground_truth.band_hz
        if band is not None:
            return float(band[0]), float(band[1])
        fc, bw = self.probe.centre_frequency, self.probe.bandwidth
        return max(fc - bw / 2, 0.0), min(fc + bw / 2, self.fs / 2)

    def spectrum(self, f_min: float, f_max: float, n_freq: int | None = None, pad: int = 2, xp: Any = None) -> Spectrum:
        """Band [f_min, f_max] of R(f) = ∫ R(t) e^{-i2πft} dt (paper eq. 0, docs/design.md §4.1).

        Frequency sampling sets the unambiguous delay window 1/Δf of every map: a fingerprint shifted
        so that its echo ends past the window wraps onto the record's start. With n_freq None the record
        is zero-padded `pad`× (default 2) and every bin of the band is kept (window = pad × record: no wrap
        for pad ≥ 2; pad = 1 gives the record's own DFT bins). With
        n_freq given, n_freq bins evenly spread over the band are kept (window = (n_freq − 1)/band
        width; choose n_freq ≥ band width × (record + target echo duration)). The phase accounts for t0.
        xp: an array module (CuPy: the FFT runs on the GPU and `Spectrum.data` stays there,
        docs/design.md §5); None: numpy/scipy.
        """
        if not (0 <= f_min < f_max <= self.fs / 2):
            raise ValueError(
                f"band: expected 0 <= f_min < f_max <= fs/2 = {self.fs / 2:g} Hz, got [{f_min:g}, {f_max:g}]"
            )
        n_t = self.n_samples
        if pad < 1:
            raise ValueError(f"pad: expected an integer >= 1, got {pad}")
        n_fft = pad * n_t
        if n_freq is not None:
            # Bin spacing fs/n_fft must give at least n_freq bins in the band.
            n_fft = max(n_t, int(np.ceil(n_freq * self.fs / (f_max - f_min))))
        n_fft = sfft.next_fast_len(n_fft, real=True)
        freqs_all = np.fft.rfftfreq(n_fft, 1.0 / self.fs)
        band = np.nonzero((freqs_all >= f_min) & (freqs_all <= f_max))[0]
        if band.size == 0:
            raise ValueError(f"band: no frequency bin in [{f_min:g}, {f_max:g}] Hz")
        if n_freq is not None and band.size > n_freq:
            band = band[np.round(np.linspace(0, band.size - 1, n_freq)).astype(int)]
        f = freqs_all[band]
        # Time origin t0: R(f) = Σ_n R(t0 + n/fs) e^{-i2πf(t0 + n/fs)} / fs.
        phase = (np.exp(-2j * np.pi * f * self.t0) / self.fs).astype(np.complex64)
        if xp is None:
            data = band_spectrum(self.rf, n_fft, band, phase)
        else:  # the RF travels in its own dtype (int16 halves the copy), then float32 on the device
            rf = xp.asarray(self.rf).astype(xp.float32, copy=False)
            spec = xp.fft.rfft(rf, n=n_fft, axis=2)[:, :, xp.asarray(band)]
            data = xp.ascontiguousarray(xp.transpose(spec * xp.asarray(phase), (2, 0, 1))).astype(xp.complex64)
        return Spectrum(data, f, self.c0, self.probe, self.sequence)


_SPECTRUM_CHUNK = 32  # elements per task of `band_spectrum`: 32 × N_θ × (n_fft/2 + 1) bins (≈ 2 MB for 25 × 573)


def band_spectrum(rf: np.ndarray, n_fft: int, band: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """(N_f, N_u, N_θ) complex64: the rFFT bins `band` of rf (N_u, N_θ, N_t) along time (zero-padded to
    n_fft), times `phase` (N_f,) — by chunks of elements on the kernel's threads, each transformed, cut to the
    band and transposed while in cache (no full-record spectrum: 117 MB on a full-size frame)."""
    n_u = rf.shape[0]
    pick: slice | np.ndarray = band
    if band.size and np.all(np.diff(band) == 1):
        pick = slice(int(band[0]), int(band[-1]) + 1)  # a basic slice: no gathered copy
    out = np.empty((band.size, n_u, rf.shape[1]), np.complex64)
    n_chunks = -(-n_u // _SPECTRUM_CHUNK)

    def chunk(c: int) -> None:
        u = slice(c * _SPECTRUM_CHUNK, min(n_u, (c + 1) * _SPECTRUM_CHUNK))
        spec = sfft.rfft(rf[u].astype(np.float32, copy=False), n=n_fft, axis=2, workers=1)[:, :, pick]
        spec *= phase
        out[:, u, :] = spec.transpose(2, 0, 1)

    loops.pool(max(1, min(default_threads(), n_chunks)), n_chunks, chunk, lambda _slot, c: (c,))
    return out


@dataclass
class Spectrum:
    """R(f, u_out, θ_in): complex (N_f, N_u, N_θ) restricted to a band (`data` on the device when built
    with an array module `xp`, `Acquisition.spectrum`)."""

    data: np.ndarray
    freqs: np.ndarray
    c0: float
    probe: Probe
    sequence: PlaneWaveSequence


@dataclass
class PlaneWaveData:
    """R_θθ(f, θ_out, θ_in): complex (N_f, N_o, N_i), both ends in the plane-wave basis."""

    data: np.ndarray
    freqs: np.ndarray
    out_sines: np.ndarray
    in_sines: np.ndarray
    c0: float

    @property
    def wavenumbers(self) -> np.ndarray:
        return 2 * np.pi * self.freqs / self.c0


def _lattice_step(values: np.ndarray) -> float | None:
    """The common step of a set of sines that lie on a uniform lattice (None if not, or a single one)."""
    u = np.unique(np.round(np.asarray(values, float), 12))
    if u.size < 2:
        return None
    d = np.diff(u)
    step = float(d.min())
    if step <= 0 or not np.allclose(d / step, np.round(d / step), atol=1e-6):
        return None
    return step


def output_sines(
    probe: Probe,
    c0: float,
    f_max: float,
    n: int | None = None,
    s_max: float | None = None,
    field_width: tuple[float, float] | float | None = None,
    transmit_sines: np.ndarray | None = None,
) -> np.ndarray:
    """Output directions sampling the array's angular spectrum (docs/design.md §4.2).

    Per lateral dimension, sines evenly spread over [-s_max, s_max], s_max = min(0.95, c0/(2 pitch f_c))
    (the spatial Nyquist limit of the pitch). Their step Δs sets where the receive focus aliases: the
    sum over output directions is periodic in x with period λ/Δs, so
    * with `field_width` (the imaging grid's lateral extent W, per axis), Δs ≤ λ_min/W with
      λ_min = c0/f_max — no alias inside the field of view (docs/design.md §4.2) — and Δs divides the
      transmit sines' own step when `transmit_sines` lie on a lattice (so the structured kernel applies);
      never coarser than one direction per element;
    * else `n` per dimension (default: the elements along it), the aperture's own Nyquist sampling,
      which aliases every λ/Δs ≈ 2 × aperture: fine for a field of view no wider than that.
    Returns (N_o, 2); a matrix probe gives the disc s_x² + s_y² ≤ s_max² of an x-fastest tensor grid.
    """
    if s_max is None:
        s_max = min(0.95, c0 / (2 * probe.pitch * probe.centre_frequency))
    axes = probe.grid_axes()
    if probe.is_linear:
        counts = [probe.n_elements]
    elif axes is not None:
        counts = [axes[0].size, axes[1].size]
    else:
        raise ValueError("probe.positions: output_sines needs a linear or regular matrix array")
    widths = np.broadcast_to(np.asarray(field_width if field_width is not None else np.nan, float), (2,))

    def axis(k: int) -> np.ndarray:
        if n is not None or not np.isfinite(widths[k]) or widths[k] <= 0:
            return np.linspace(-s_max, s_max, n or counts[k])
        step = min(c0 / f_max / widths[k], 2 * s_max / max(counts[k] - 1, 1))
        lattice = _lattice_step(transmit_sines[:, k]) if transmit_sines is not None else None
        if lattice is not None:
            step = lattice / np.ceil(0.98 * lattice / step)  # 2 % slack: no extra halving for round-off
        m = int(np.floor(s_max / step + 1e-9))
        return step * np.arange(-m, m + 1)

    sx = axis(0)
    if probe.is_linear:
        return np.stack([sx, np.zeros(sx.size)], axis=1)
    sy = axis(1)
    yy, xx = np.meshgrid(sy, sx, indexing="ij")
    keep = xx.ravel() ** 2 + yy.ravel() ** 2 < s_max**2 + 1e-12  # drop evanescent corners
    return np.stack([xx.ravel()[keep], yy.ravel()[keep]], axis=1)


def _tensor_axes(sines: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(sx axis, sy axis, flat index of each sine in the x-fastest tensor grid) if the sines are a
    subset of a small tensor grid (e.g. a disc cut from it), else None."""
    sx, ix = np.unique(sines[:, 0], return_inverse=True)
    sy, iy = np.unique(sines[:, 1], return_inverse=True)
    if sx.size * sy.size > 2 * sines.shape[0]:
        return None
    return sx, sy, iy.ravel() * sx.size + ix.ravel()


def _project_separable(data: np.ndarray, px: np.ndarray, py: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """The separable projection (y then x) by the compiled loops (`loops.project_freq`) on the kernel's
    threads, one frequency per task: no BLAS, whose spinning threads fight the kernels' on 2 cores (the same
    products as the matmul path, summed in another order: equal within float32 rounding).
    data (N_f, N_uy·N_ux, N_i); px (N_f, N_sx, N_ux), py (N_f, N_sy, N_uy); flat: each kept sine's index
    s_y·N_sx + s_x. Returns (N_f, flat.size, N_i) complex64."""
    n_f, _, n_i = data.shape
    (_, nsx, nux), (_, nsy, nuy) = px.shape, py.shape
    oidx = np.full(nsy * nsx, -1, dtype=np.int64)
    oidx[flat] = np.arange(flat.size)
    R = np.ascontiguousarray(data, dtype=np.complex64).view(np.float32).reshape(n_f, nuy, nux, n_i, 2)
    out = np.empty((n_f, flat.size, n_i), dtype=np.complex64)
    planes = [np.ascontiguousarray(a, dtype=np.float32) for a in (py.real, py.imag, px.real, px.imag)]
    nt = max(1, min(default_threads(), n_f))
    blk = 512
    work = np.empty((nt, 4, max(nuy * nux, nux * nsy) * n_i), dtype=np.float32)
    acc = np.empty((nt, 2, 4, blk), dtype=np.float32)
    nk = min(n_f, 4 * nt)
    loops.pool(
        nt,
        nk,
        loops.project_freq,
        lambda c, t: (
            R,
            *planes,
            oidx.reshape(nsy, nsx),
            out.view(np.float32).reshape(n_f, -1, n_i, 2),
            *work[c],
            *acc[c],
            blk,
            t,
            nk,
        ),
    )
    return out


def to_plane_waves(spec: Spectrum, out_sines: np.ndarray, xp: Any = None) -> PlaneWaveData:
    """R_θθ(f) = P_θu(f) R_uθ(f), P_θu = exp(-i k s_θ·u) (docs/design.md §4.2, paper Methods).

    For a regular matrix array and a tensor grid of output sines the projection is separable
    (x then y), which costs N_x + N_y instead of N_x N_y per coefficient. xp: the array module of
    `spec.data` (CuPy: the products run on the GPU, the result's `data` stays there); None: numpy.
    """
    xp = np if xp is None else xp
    out = _as_sines(out_sines)
    k = 2 * np.pi * spec.freqs / spec.c0
    pos = spec.probe.positions
    axes = spec.probe.grid_axes()
    s_grid = _tensor_axes(out)
    n_f, n_u, n_i = spec.data.shape
    if axes is not None and s_grid is not None and not spec.probe.is_linear:
        ux, uy = axes
        sx, sy, flat = s_grid
        px = np.exp(-1j * k[:, None, None] * sx[None, :, None] * ux[None, None, :]).astype(np.complex64)
        py = np.exp(-1j * k[:, None, None] * sy[None, :, None] * uy[None, None, :]).astype(np.complex64)
        if xp is np and loops.nb is not None:
            data = _project_separable(np.asarray(spec.data), px, py, flat)
            return PlaneWaveData(data, spec.freqs.copy(), out, spec.sequence.sines.copy(), spec.c0)
        r = spec.data.reshape(n_f, uy.size, ux.size, n_i)
        r = xp.matmul(xp.asarray(px)[:, None], r)  # (f, uy, sx, i)
        r = xp.matmul(xp.asarray(py), r.reshape(n_f, uy.size, sx.size * n_i))  # (f, sy, sx*i)
        data = r.reshape(n_f, sy.size * sx.size, n_i)[:, xp.asarray(flat)]
    else:
        phase = np.exp(-1j * k[:, None, None] * (out @ pos[:, :2].T)[None]).astype(np.complex64)
        data = xp.matmul(xp.asarray(phase), spec.data)
    return PlaneWaveData(
        xp.ascontiguousarray(data, dtype=np.complex64), spec.freqs.copy(), out, spec.sequence.sines.copy(), spec.c0
    )
