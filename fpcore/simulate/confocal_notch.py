"""The Gaussian field kept out of the confocal subspace when the focal return is drawn (docs/design.md §6.6, F4).

With `focal_return` (ScatteringLayer), the orders ≥ 2 are split in two: the paths whose ends the rig cannot tell
apart, drawn as a reflectivity on the beads' grid (the focal return, F1–F3), and the rest, the Gaussian field. Any
component of the Gaussian field that a reflectivity could also produce would add, at every focus, a second copy of
what the focal return already counts (the focal overlap W of F2 holds every path's projection onto the foci). So,
with `confocal_notch`, the field is drawn in the orthogonal complement of that subspace. In the output plane-wave
basis (sine b, cosine c_b; element phase e^{−ik b·u}) a reflectivity ρ(r) gives, for transmit θ (sine a, cosine
c_a), phase only,

    (A ρ)(o, θ, f) = Σ_r ρ(r) e^{−ik[(a − b)·x + (c_a + c_b) z]}                                             (F4)

(the single-scattering model's phases, `single_scattering` module doc), and the field is replaced by
E V − E A ρ̂ with ρ̂ = argmin ‖E V − E A ρ‖²: E maps the plane waves onto the array's elements
(`diffuse.project_plane_waves`), so the notch is taken where the array measures, through its own aperture — a
small array sees only a narrow fan of the field's directions, and a notch in the plane-wave basis alone leaves
its foci untouched. ρ̂ is solved by conjugate gradients on the normal equations (one type-2 and one type-1 NUFFT,
E and its adjoint an iteration); the result is rescaled, time by time, to the envelope it had before the notch
(`keep_envelope`): that envelope is the transport's (the kept paths'), only the field's place in the data space
changes.

The reflectivity lives on a grid that holds every position the data resolve once: laterally one period λ_max/Δs of
the output grid (spacing Δs) about the array's axis, axially from the medium's surface to the record's end (at most
one period 2π/(Δk q_z,min) of the frequency sampling, q_z = c_a + c_b: a reflectivity above the surface would
put the fit's energy before the surface echo, where no path arrives), at the Nyquist spacing of the spatial
frequencies k(a − b) and k q_z (the axial ones demodulated about their centre).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import finufft
import numpy as np
import scipy.fft as sfft

from ..geometry import cosines

__all__ = ["ConfocalNotch"]

#: Conjugate-gradient iterations of the least-squares fit (2-D Foldy–Lax rig: the removed share is 0.199 after 12,
#: 0.201 after 20 and 0.203 after 40). In 3-D the fit does not converge by then (removed share 0.24 / 0.26 after
#: 12 / 24 on the Foldy–Lax deep slab, whose four figures do not move; 0.82 / 0.87 on the quick headline rig, whose
#: fog moves ≤ 0.5 dB), so the count is an early stop: docs/design.md §6, "The notch's fit in 3-D".
NOTCH_ITERATIONS = 12


class ConfocalNotch:
    """V(o, θ, f) → V − A ρ̂, energy kept (module doc, F4), for the output sines `s_out` (N_o, 2) on a regular grid
    of spacings `spacings` (one per lateral axis of the dimension `dim`), transmit sines `sines` (N_θ, 2),
    frequencies `freqs` (Hz, uniform) and a reflectivity grid over the depths `z_range` (m below the array, the
    shallow end the medium's surface: a field that starts there has no reflectivity above it; at most one axial
    period; V's delays are absolute). With a `sensor` (E, E^H), the map of the plane waves onto the array's elements
    and its adjoint, the fit and the notch are made where the array measures, E V − E A ρ̂ (module doc); a
    `constraint` (a projection in that domain: the measured reciprocity, `reciprocity.ElementReciprocity`) applies
    to the notched field before its envelope is restored. The NUFFT plans are built once, on first use, and shared
    by copies behind one lock."""

    def __init__(
        self,
        s_out: np.ndarray,
        spacings: list[float],
        sines: np.ndarray,
        freqs: np.ndarray,
        c0: float,
        dim: int,
        z_range: tuple[float, float],
        iterations: int = NOTCH_ITERATIONS,
        sensor: tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]] | None = None,
        time_grid: tuple[int, int] | None = None,
        constraint: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        so, si = np.asarray(s_out, dtype=np.float64), np.asarray(sines, dtype=np.float64)
        f = np.asarray(freqs, dtype=np.float64)
        if f.size < 2:
            raise ValueError(f"freqs: expected at least 2 frequencies, got {f.size}")
        if len(spacings) != (2 if dim == 3 else 1):
            raise ValueError(f"spacings: expected {2 if dim == 3 else 1} lateral spacings for dim {dim}")
        self.shape = (so.shape[0], si.shape[0], f.size)
        self.dim, self.iterations, self.sensor, self.time_grid = dim, iterations, sensor, time_grid
        self.constraint = constraint
        k = 2 * np.pi * f / c0
        qz = cosines(si)[None, :] + cosines(so)[:, None]  # (N_o, N_θ)
        lateral = [si[None, :, d] - so[:, None, d] for d in range(len(spacings))]
        self._k, self._qz, self._lateral = k, qz, lateral
        # e^{−i k q_z z_c}: the grid's centre depth, taken out of the data before the NUFFTs and put back after
        z_lo, z_hi = float(z_range[0]), float(z_range[1])
        if not z_hi > z_lo:
            raise ValueError(f"z_range: expected (shallow, deep) with deep > shallow, got {z_range}")
        kz_lo, kz_hi = float(k.min() * qz.min()), float(k.max() * qz.max())
        self._kz0 = 0.5 * (kz_lo + kz_hi)
        self.hz = np.pi / (1.02 * max(0.5 * (kz_hi - kz_lo), 1e-9))
        dk = float(np.diff(k).mean())
        depth_period = 2 * np.pi / (dk * float(qz.min()))
        modes = []
        self.h = []
        for d, ds in enumerate(spacings):
            h = np.pi / (1.02 * max(float(k.max() * np.abs(lateral[d]).max()), 1e-9))
            period = 2 * np.pi / (float(k.min()) * ds)  # the output grid's longest lateral period
            modes.append(2 * int(np.ceil(0.5 * period / h)))
            self.h.append(h)
        depth_extent = min(z_hi - z_lo, depth_period)
        modes.append(2 * int(np.ceil(0.5 * depth_extent / self.hz)))
        z_centre = z_lo + 0.5 * depth_extent
        #: the grid's depths below the array (its last axis; laterally, mode m lies at m h about the axis)
        self.depths = z_centre + (np.arange(modes[-1]) - modes[-1] // 2) * self.hz
        self._centre = np.exp(-1j * k[None, None, :] * qz[:, :, None] * z_centre).astype(np.complex64)
        self.modes = tuple(modes)
        self._plans: tuple[finufft.Plan, finufft.Plan] | None = None
        self._lock = threading.Lock()

    def _points(self) -> list[np.ndarray]:
        k = self._k[None, None, :]
        pts = [
            np.ascontiguousarray((q[:, :, None] * k * h).ravel(), dtype=np.float32)
            for q, h in zip(self._lateral, self.h, strict=True)
        ]
        pts.append(np.ascontiguousarray(((self._qz[:, :, None] * k - self._kz0) * self.hz).ravel(), dtype=np.float32))
        return pts

    def prepare(self) -> None:
        """Build the type-2 (A) and type-1 (A^H) plans with their points, once."""
        if self._plans is None:
            pts = self._points()
            kw = {"eps": 1e-3, "dtype": "complex64", "upsampfac": 1.25}
            forward = finufft.Plan(2, self.modes, isign=-1, **kw)
            adjoint = finufft.Plan(1, self.modes, isign=+1, **kw)
            forward.setpts(*pts)
            adjoint.setpts(*pts)
            self._plans = (forward, adjoint)

    def _a(self, x: np.ndarray) -> np.ndarray:
        """A x on the data (N_o, N_θ, N_f), carried to the sensor when one is given."""
        assert self._plans is not None
        v = self._plans[0].execute(x).reshape(self.shape) * self._centre
        return v if self.sensor is None else self.sensor[0](v)

    def _ah(self, y: np.ndarray) -> np.ndarray:
        """A^H y (the reflectivity grid), y on the sensor when one is given."""
        assert self._plans is not None
        v = y if self.sensor is None else self.sensor[1](y)
        return self._plans[1].execute(np.ascontiguousarray((v * self._centre.conj()).ravel(), dtype=np.complex64))

    def adjoint(self, y: np.ndarray) -> np.ndarray:
        """A^H y on the reflectivity grid (`modes`): the matched filter of a reflectivity, y on the sensor when one
        is given (N_f, N_u, N_θ), else the plane waves (N_o, N_θ, N_f)."""
        self.prepare()
        with self._lock:
            return self._ah(y).reshape(self.modes)

    def fit(self, y: np.ndarray) -> np.ndarray:
        """A ρ̂: the least-squares part of `y` that a reflectivity gives (F4), in y's domain (the plane waves
        (N_o, N_θ, N_f), or the sensor's)."""
        if self.sensor is None and y.shape != self.shape:
            raise ValueError(f"y: expected shape {self.shape}, got {y.shape}")
        self.prepare()
        with self._lock:
            r = self._ah(y)
            x = np.zeros_like(r)
            p = r.copy()
            rr = float(np.vdot(r, r).real)
            for _ in range(self.iterations):
                if rr == 0.0:
                    break
                ap = self._ah(self._a(p))
                alpha = rr / float(np.vdot(p, ap).real)
                x += np.complex64(alpha) * p
                r -= np.complex64(alpha) * ap
                rr_new = float(np.vdot(r, r).real)
                p = r + np.complex64(rr_new / rr) * p
                rr = rr_new
            return self._a(x)

    def __call__(self, v: np.ndarray) -> np.ndarray:
        """V − A ρ̂ with V's energy kept (module doc): per time over `time_grid` = (n_t, width) when given — the
        record's baseband samples and the running mean's width in samples —, else in all; on the sensor when
        one is given (V itself is always the plane waves' (N_o, N_θ, N_f))."""
        if v.shape != self.shape:
            raise ValueError(f"v: expected shape {self.shape}, got {v.shape}")
        y = np.asarray(v, dtype=np.complex64) if self.sensor is None else self.sensor[0](v)
        out = y - self.fit(y)
        if self.constraint is not None:
            out = self.constraint(out)
        if self.time_grid is not None:
            return keep_envelope(y, out, 0 if self.sensor is not None else 2, *self.time_grid)
        e0, e1 = float(np.sum(np.abs(y) ** 2)), float(np.sum(np.abs(out) ** 2))
        if e1 > 0.0:
            out *= np.float32(np.sqrt(e0 / e1))
        return out


def keep_envelope(before: np.ndarray, after: np.ndarray, axis: int, n_t: int, width: int) -> np.ndarray:
    """`after` with the time envelope of `before`: both are spectra on contiguous frequency bins along `axis`; on
    the baseband time grid of n_t samples the energy summed over the other axes, averaged over `width` samples
    (periodic), sets a gain g(t) = √(⟨|before|²⟩/⟨|after|²⟩) applied in time to `after`; the spectrum is returned
    on the same bins. The two envelopes are measured through a Hann taper over the bins (as a pulse's spectrum
    would weigh them): the bins' rectangular edges put sinc sidelobes ≈ 35 dB under the peak over the whole
    period, and in the faint tail and before the surface echo those, not the field's own energy, would set the
    gain (docs/design.md §6.6: +3.5 … +7 dB at the record's last 5 µs of the headline rig)."""
    n_f = before.shape[axis]
    if n_t < n_f:
        raise ValueError(f"n_t: expected at least the {n_f} frequency bins, got {n_t}")
    others = tuple(i for i in range(before.ndim) if i != axis)

    def along_axis(v: np.ndarray) -> np.ndarray:
        """A 1-D array v shaped to broadcast along `axis`."""
        return v.reshape([v.size if i == axis else 1 for i in range(before.ndim)])

    taper = along_axis(np.hanning(n_f + 2)[1:-1].astype(np.float32))
    shifts = range(-(width // 2), width - width // 2)  # the running mean's window about each sample

    def smoothed_energy(spec: np.ndarray) -> np.ndarray:
        t = sfft.ifft(spec * taper, n=n_t, axis=axis, workers=-1)
        e = np.sum(np.abs(t).astype(np.float64) ** 2, axis=others)
        # a sum of non-negative terms (a convolution through FFTs leaves −1e-8 of the peak where the field is dark,
        # and a gain against a negative floor is unbounded)
        return sum(np.roll(e, d) for d in shifts) / width

    e0, e1 = smoothed_energy(before), smoothed_energy(after)
    gain = np.sqrt(np.maximum(e0, 0.0) / np.maximum(e1, 1e-30 * max(float(e1.max()), 1e-30)))
    t1 = sfft.ifft(after, n=n_t, axis=axis, workers=-1)  # the gain applies to the field itself, untapered
    spec = sfft.fft(t1 * along_axis(gain.astype(np.float32)), axis=axis, workers=-1)
    return np.ascontiguousarray(np.take(spec, np.arange(n_f), axis=axis), dtype=np.complex64)
