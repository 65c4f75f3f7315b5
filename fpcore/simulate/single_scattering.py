"""Single scattering by the medium's own scatterers (the beads): a continuum reflectivity in the
plane-wave output basis, computed by a non-uniform FFT (docs/design.md §6.3).

Physics. A density n of scatterers of strength t (σ_s = |t|²/(4π) in 3D, |t|²/(4k) in 2D) with
n σ_s = 1/ℓ_s(f) is a random reflectivity η(r) with ⟨η η*⟩ = n|t|² δ(r − r') = (4π/ℓ_s) δ (3D),
(4k/ℓ_s) δ (2D) (independent scattering, Supplementary S1). In the first Born approximation through
the coherent (extinguished) medium, transmit θ (sine a, cosine c_a) and an upgoing output plane wave o
(sine b, cosine c_b; element phase e^{−ik b·u}) see

  A(o, θ, f) = W_b(f) (1 − R²) Σ_m η_m e^{−ik[(a − b)·x_m + (c_a + c_b) z_m]} e^{−d_m (1/c_a + q(z_m))/(2ℓ_ext)} w(x_m)

with d_m = z_m − z_s the depth below the surface and e^{−d(1/c_a + q)/(2ℓ_ext(f))} the extinction of both
oblique legs: the transmit's, of length d/c_a, and the receive's, whose rays fan out over the array's aperture
D: q(z) = ⟨1/cos φ⟩ over the aperture seen from the range z (`geometry.secant_over_aperture`; the plane-wave
output basis cannot carry each output's own 1/c_b through the transform, and the array receives the fan);
w(x − z tan θ) the lateral extent of the transmitted beam, steered with it (the aperture and its
diffraction spread at each depth, a smooth edge, and the amplitude that keeps the beam's power as it spreads,
`beam_half_width`, `beam_gain`)
and W_b the plane-wave (Weyl) weight of the Green function on the output grid of spacing Δs:
e^{−ikR}/(4πR) = (−ik/8π²) ∫ d²b e^{−ik(b·x + c_b|z|)}/c_b, so W_b = −ik Δs²/(8π² c_b) (3D), and
(−i/4)H₀⁽²⁾(kR) = (−i/4π) ∫ db e^{−ik(b x + c_b|z|)}/c_b, W_b = −iΔs/(4π c_b) (2D). The
reflectivity is sampled on a grid that resolves the band's spatial frequencies (lateral k|a − b|,
axial k(c_a + c_b) demodulated about its centre), and the sum is one type-2 NUFFT per sub-band of
frequencies and transmit (each sub-band has its own ℓ_s(f), so the echo is filtered by exp(−2z/ℓ_ext(f));
each transmit has its own beam).

Frames: the beads move by ⟨Δr²⟩^{1/2} between frames; a single-scattering echo (wavevector transfer
≈ 2k) keeps the correlation g₁ = exp(−(2k)²⟨Δr²⟩/6) (3D Brownian displacement), applied as an AR(1)
update of the grid's white noise.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

import finufft
import numpy as np

from ..geometry import cosines, secant_over_aperture
from ..kernel import default_threads
from ..kernel_presum_loops import _jit, nb, pool, split

if TYPE_CHECKING:
    from .medium import ScatteringLayer

__all__ = ["SingleScatteringField"]


class SingleScatteringField:
    """The beads' single-scattering spectrum A(o, θ, f) on an output plane-wave grid (module doc).

    layer: the `ScatteringLayer`; sines (N_θ, 2) transmits; freqs (N_f,) Hz; blend (n_sub, N_f): each
    sub-band's weight per frequency (summing to 1; triangular between the sub-band centres `centres`, so the
    spectrum has no step between sub-bands); aperture (lateral extents of the array, m) and the deepest depth
    below the surface worth simulating `depth_max` (m). The output grid (`s_out`, spacing `ds`, `axes` and
    `keep` over the full square grid, x-major) is the field's own, alias-free (`output_grid`), unless given.
    """

    def __init__(
        self,
        layer: ScatteringLayer,
        sines: np.ndarray,
        freqs: np.ndarray,
        blend: np.ndarray,
        centres: np.ndarray,
        c0: float,
        dim: int,
        aperture: tuple[float, float],
        depth_max: float,
        rng: np.random.Generator,
        rho0: float = 1000.0,
        s_out: np.ndarray | None = None,
        ds: float | None = None,
    ) -> None:
        self.layer, self.c0, self.dim, self.rng = layer, c0, dim, rng
        self.freqs = np.asarray(freqs, dtype=np.float64)
        self.blend, self.centres = np.asarray(blend, dtype=np.float64), np.asarray(centres, dtype=np.float64)
        if self.blend.shape != (self.centres.size, self.freqs.size):
            raise ValueError(f"blend: expected shape {(self.centres.size, self.freqs.size)}, got {self.blend.shape}")
        si = np.asarray(sines, dtype=np.float64)
        z_s = layer.z_surface
        # Lateral extent of one transmitted beam: the aperture D plus its diffraction spread λ z/D at the deepest
        # depth, steered: transmit θ's beam is centred on z tan θ at depth z (a finite-aperture plane wave).
        lam = c0 / float(np.mean(self.freqs))
        z_far = z_s + depth_max
        half = [float(beam_half_width(aperture[d], z_far, lam)) for d in range(2)]
        ci = cosines(si)
        self._tan = si / ci[:, None]  # (N_θ, 2)
        self._sines_in = si
        reach = [1.15 * half[d] + z_far * float(np.abs(self._tan[:, d]).max(initial=0.0)) for d in range(2)]
        self._half = half  # at the deepest depth: the grid's reach
        self._aperture, self._lam = (float(aperture[0]), float(aperture[1])), lam
        self.axes: list[np.ndarray] | None = None
        self.keep: np.ndarray | None = None
        if s_out is None:
            lam_min = c0 / float(self.freqs.max())
            ds, self.axes, self.keep, s_out, taper = output_grid(reach, aperture, z_s, lam_min, dim)
        else:
            taper = np.ones(np.asarray(s_out).shape[0])
        self.taper = taper
        assert ds is not None
        self.ds = ds
        so = np.asarray(s_out, dtype=np.float64)
        self.s_out = so
        self.n_o, self.n_i = so.shape[0], si.shape[0]
        co = cosines(so)
        self._ci = ci
        # Spatial frequencies per (o, θ) in units of k: lateral a − b, axial c_a + c_b.
        self._qx = si[None, :, 0] - so[:, None, 0]
        self._qy = si[None, :, 1] - so[:, None, 1]
        self._qz = ci[None, :] + co[:, None]
        k_max = 2 * np.pi * float(self.freqs.max()) / c0
        k_min = 2 * np.pi * float(self.freqs.min()) / c0
        # Axial: demodulate about the centre of k(c_a + c_b) over the band; Nyquist with a 1.5 margin.
        qz_lo, qz_hi = k_min * float(self._qz.min()), k_max * float(self._qz.max())
        self._kz0 = 0.5 * (qz_lo + qz_hi)
        hz = np.pi / (1.02 * max(0.5 * (qz_hi - qz_lo), 1e-9))
        qx_max = k_max * max(float(np.abs(self._qx).max()), 1e-6)
        hx = np.pi / (1.02 * qx_max)
        self.nz = max(4, int(np.ceil(depth_max / hz)) + 1)
        self.hz = hz
        self.depths = np.arange(self.nz) * hz
        # The receive leg's mean secant over the array's fan of rays at each depth (module doc).
        self._q_out = secant_over_aperture(aperture[: 2 if dim == 3 else 1], z_s + self.depths)
        self.nx = 2 * int(np.ceil(reach[0] / hx)) + 2
        self.ny = 2 * int(np.ceil(reach[1] / hx)) + 2 if dim == 3 else 1
        self.hx = hx
        self._xs = (np.arange(self.nx) - self.nx // 2) * hx
        self._ys = (np.arange(self.ny) - self.ny // 2) * hx
        cell = hx * hz * (hx if dim == 3 else 1.0)
        self._cell = cell
        t_r = 1.0 - layer.reflection(rho0, c0) ** 2
        self._t_r = t_r
        self._co = co
        g = layer.correlation_single(c0, float(np.mean(self.freqs))) if layer.frame_displacement > 0 else None
        self.g1 = g
        self.state: np.ndarray | None = None
        # The focal return of the orders ≥ 2 (`add_focal_return`): its own reflectivity on this grid, summed with the
        # beads' before the NUFFT (one transform for both), with its own depth profile and frame-to-frame g₁.
        self._fr_var: np.ndarray | None = None
        self._fr_light: np.ndarray | None = None
        self._fr_beams: np.ndarray | None = None
        self._fr_g1: np.ndarray | None = None
        self.fr_state: np.ndarray | None = None
        # The focal return as two-point paths (F6, `add_focal_return`'s separations): the joint distribution of the
        # pairs' lateral separations by depth, and, drawn with the first grid, each cell's partner (`pair_cells`).
        self._fr_sep: np.ndarray | None = None
        self._pairs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        # False leaves the focal return alone on the grid, the beads' reflectivity zero (a diagnostic: the focal
        # return's own share of the focused matrix, bench/transport_paths.py --focal-split). Set before the first
        # spectrum.
        self.draw_beads = True
        self._plans: list[tuple] | None = None  # per sub-band, built at the first spectrum
        self._beams: np.ndarray | None = None
        self._plan_lock: threading.Lock | None = None  # made with the plans, shared with them (`prepare`)

    @property
    def beam_aperture(self) -> tuple[float, float]:
        """The transmits' beam aperture per lateral axis (`beam`)."""
        return self._aperture

    @property
    def beam_wavelength(self) -> float:
        """The wavelength of the beams' diffraction spread (`beam`)."""
        return self._lam

    def beam(self, i: int, light: np.ndarray | None = None) -> np.ndarray:
        """Transmit i's beam w(x − z tan θ) on the grid, (nx, ny, nz) float32: flat inside its half-width at each
        depth, cosine edges, its amplitude conserving the beam's power as it spreads (`beam_half_width`); with
        `light` (nz,), each depth lit as at that depth below the surface instead."""
        z = self.layer.z_surface + (self.depths if light is None else light)
        ap, lam = self._aperture, self._lam
        hx = beam_half_width(ap[0], z, lam)[None, :]
        bx = _edge(self._xs[:, None] - z[None, :] * self._tan[i, 0], hx, BEAM_SOFT * hx) * beam_gain(ap[0], z, lam)
        if self.dim == 3:
            hy = beam_half_width(ap[1], z, lam)[None, :]
            by = _edge(self._ys[:, None] - z[None, :] * self._tan[i, 1], hy, BEAM_SOFT * hy) * beam_gain(ap[1], z, lam)
        else:
            by = np.ones((1, z.size))
        return (bx[:, None, :] * by[None, :, :]).astype(np.float32)

    def _white(self) -> np.ndarray:
        shape = (self.nx, self.ny, self.nz)
        out = np.empty(shape, dtype=np.complex64)
        sig = np.float32(np.sqrt(0.5))
        out.real = self.rng.standard_normal(shape, dtype=np.float32) * sig
        out.imag = self.rng.standard_normal(shape, dtype=np.float32) * sig
        return out

    def add_focal_return(
        self,
        variance: np.ndarray,
        g1: np.ndarray | None,
        light: np.ndarray | None = None,
        separations: np.ndarray | None = None,
    ) -> None:
        """A second reflectivity on this grid: the focal return of the orders ≥ 2 (`paths.focal_return`),
        variance (n_sub, nz) per unit volume at each sub-band centre and depth (extinction included), and its g₁
        between frames per depth (nz,), None when frozen; `light` (nz,), the depth below the surface at which each
        depth's focal return is lit by the transmits' beams (its paths' ends, `paths.focal_return`), or None: its own.
        With `separations` (nz, n_y, n_steps) (`paths.focal_pairs`, F6 of docs/design.md §6.6: per depth the joint
        distribution of (|m_y|, |m_x|), n_y = 1 in 2D) the cells are paired, each pair one path whose ends lie that
        many grid steps apart per axis: a cell holds the term received
        at it and transmitted from its partner (each transmit's phase and beam taken at the partner), the partner the
        reversed term, with the same amplitude (√2 × where a cell is its own partner: the ends coincide); the
        variance is then the paths' ν' (`paths.focal_pairs`). Set before the first spectrum."""
        v = np.asarray(variance, dtype=np.float64)
        if v.shape != (self.centres.size, self.nz):
            raise ValueError(f"variance: expected shape {(self.centres.size, self.nz)}, got {v.shape}")
        if self._plans is not None:
            raise ValueError("variance: expected before the first spectrum (the sub-bands' profiles are built then)")
        lit = None if light is None else np.asarray(light, dtype=np.float64)
        if lit is not None and lit.shape != (self.nz,):
            raise ValueError(f"light: expected a depth per grid depth, shape {(self.nz,)}, got {lit.shape}")
        sep = None if separations is None else np.asarray(separations, dtype=np.float64)
        if sep is not None and (
            sep.ndim != 3 or sep.shape[0] != self.nz or (self.dim == 2 and sep.shape[1] != 1) or 0 in sep.shape
        ):
            n_y = "1" if self.dim == 2 else "n_y"
            raise ValueError(f"separations: expected shape ({self.nz}, {n_y}, n_steps), got {sep.shape}")
        if sep is not None and (np.any(sep < 0) or not np.allclose(sep.sum(axis=(1, 2)), 1.0, atol=1e-6)):
            raise ValueError("separations: expected non-negative probabilities summing to 1 per depth")
        self._fr_var = v
        self._fr_light = lit
        self._fr_g1 = None if g1 is None else np.asarray(g1, dtype=np.float32)
        self._fr_sep = sep

    def scale_focal_return(self, factor: np.ndarray) -> None:
        """Multiply the focal return's variance by `factor` (nz,) or (n_sub, nz), ≥ 0 (`diffuse`'s excess, F5 of
        docs/design.md §6.6); the next spectrum takes it (the NUFFT plans do not depend on it)."""
        if self._fr_var is None:
            raise ValueError("factor: expected a focal return to scale (add_focal_return first)")
        fac = np.broadcast_to(np.asarray(factor, dtype=np.float64), self._fr_var.shape)
        if np.any(fac < 0) or not np.all(np.isfinite(fac)):
            raise ValueError("factor: expected finite, non-negative factors")
        self._fr_var = self._fr_var * fac  # a new array: copies made before keep theirs

    def _focal_weights(self, j: int) -> np.ndarray:
        """The focal return's depth profile at sub-band centre j (nz,): √(ν cell) with e^{−i k_z0 d} (`_sub_band`)."""
        assert self._fr_var is not None
        return (np.exp(-1j * self._kz0 * self.depths) * np.sqrt(self._fr_var[j] * self._cell)).astype(np.complex64)

    def advance(self) -> None:
        """Draw the first grid, or move the beads by one frame (AR(1) with g₁; frozen when g₁ is None); the focal
        return's grid likewise with its own g₁ per depth."""
        if self.state is None:
            self.state = self._white()
        elif self.g1 is not None:
            g = np.float32(self.g1)
            self.state *= g
            self.state += self._white() * np.float32(np.sqrt(max(0.0, 1.0 - self.g1**2)))
        if self._fr_var is not None:
            if self.fr_state is None:
                self.fr_state = self._white()
                if self._fr_sep is not None:  # the paths' topology: drawn once, its amplitudes evolve with g₁
                    self._pairs = pair_layout(pair_offsets((self.nx, self.ny, self.nz), self._fr_sep, self.rng))
            elif self._fr_g1 is not None:
                self.fr_state *= self._fr_g1
                self.fr_state += self._white() * np.sqrt(np.maximum(0.0, 1.0 - self._fr_g1**2))

    def _sub_band(
        self, idx: np.ndarray, fc: float
    ) -> tuple[np.ndarray, np.ndarray, int | None, list[tuple[int, int, np.ndarray, list, np.ndarray]]]:
        """What a frame does not change, per sub-band: the depth profile, the transmits' extinction (N_θ, nz), the
        index of the focal return's variance profile (`_focal_weights`; None without one), per depth chunk (i0, i1,
        its output directions, its NUFFT plans per transmit, the factor applied after them) (module doc)."""
        lay = self.layer
        ls, lext = float(lay.ls_at(fc)), float(lay.l_ext_at(fc))
        kc = 2 * np.pi * fc / self.c0
        strength = (4 * np.pi / ls) if self.dim == 3 else (4 * kc / ls)  # n|t|² (module doc)
        # The depth profile: the receive leg's extinction over the aperture's fan of rays, the scattering strength,
        # and e^{−i k_z0 d} (the axial carrier taken out of the NUFFT's spatial frequencies below); the transmit
        # leg's extinction e^{−d/(2 c_θ ℓ_ext)} per transmit (module doc).
        depth_w = np.exp(-self.depths * self._q_out / (2 * lext) - 1j * self._kz0 * self.depths)
        depth_w *= np.sqrt(strength * self._cell) if self.draw_beads else 0.0
        tx_w = np.exp(-self.depths[None, :] / (2 * lext * self._ci[:, None])).astype(np.float32)  # (N_θ, nz)
        fr_j = None if self._fr_var is None else int(np.argmin(np.abs(self.centres - fc)))
        k = 2 * np.pi * self.freqs[idx] / self.c0  # (n_f,)
        kx = k[None, None, :] * self._qx[:, :, None]  # (N_o, N_θ, n_f)
        kz = k[None, None, :] * self._qz[:, :, None]
        # e^{−iK·r}: r = (x, y, z_s + d); d_m = m hz (m ≥ 0) → modes centred: d = (i0 + m' + n/2) hz, finufft's modes
        # m' ∈ [−n/2, n/2) over each chunk of n depths, summed over its own output directions (`_depth_chunks`); the
        # axial frequency is demodulated by k_z0. One plan per chunk and transmit (each transmit has its own steered
        # beam), its points set once.
        if self.dim == 3:
            weyl = (-1j * k[None, :] * self._ds2 / (8 * np.pi**2 * self._co[:, None]))[:, None, :]
        else:
            weyl = (-1j * self._ds2 / (4 * np.pi * self._co[:, None]) * np.ones_like(k)[None, :])[:, None, :]
        chunks = []
        for i0, i1, o_idx, o_taper in self._depth_chunks():
            plans = []
            for i in range(self.n_i):
                pts = [np.ascontiguousarray(kx[o_idx, i] * self.hx, dtype=np.float32).ravel()]
                if self.dim == 3:
                    qy = k[None, :] * self._qy[o_idx, i, None] * self.hx
                    pts.append(np.ascontiguousarray(qy, dtype=np.float32).ravel())
                pts.append(np.ascontiguousarray((kz[o_idx, i] - self._kz0) * self.hz, dtype=np.float32).ravel())
                modes = (self.nx, self.ny, i1 - i0) if self.dim == 3 else (self.nx, i1 - i0)
                plan = finufft.Plan(2, modes, eps=1e-3, isign=-1, dtype="complex64", modeord=0, upsampfac=1.25)
                plan.setpts(*pts)
                plans.append(plan)
            # Phase of the chunk's depth origin (d = i0 hz + (m' + n/2) hz) and of the surface, e^{−i k_z z_s}; Weyl
            # weight; 1 − R²; the output grid's taper and the chunk's.
            kz_o = kz[o_idx]
            ph = np.exp(-1j * ((kz_o - self._kz0) * self.hz * (i0 + (i1 - i0) // 2) + kz_o * self.layer.z_surface))
            taper = self.taper[o_idx] if o_taper is None else self.taper[o_idx] * o_taper
            post = (ph * weyl[o_idx] * self._t_r * taper[:, None, None]).astype(np.complex64)
            chunks.append((i0, i1, o_idx, plans, post))
        return depth_w.astype(np.complex64), tx_w, fr_j, chunks

    def _depth_chunks(self) -> list[tuple[int, int, np.ndarray, np.ndarray | None]]:
        """The grid's depths in chunks [i0, i1), each summed over the output directions that its sources reach:
        (i0, i1, output indices, their taper or None for all ones) (docs/design.md §6.6, the output grid's images).
        The output sines Δs apart repeat every source laterally every λ/Δs; the grid's cut-off s_end hides the images
        from the elements only for a shallow source, so with the focal return in 3-D (its grid reaches the record's
        end) a source at the range R is seen only at |s| < s_X(R), s_X = X/√(X² + R²), X the lateral reach of its
        lit sources plus half the aperture, then a cosine edge CHUNK_EDGE wide (its images come in at
        (λ/Δs − X)/√((λ/Δs − X)² + R²), beyond for a source near the axis). A chunk's s_X spans at most CHUNK_SPAN and
        its cut is its largest. One chunk, every depth and direction, otherwise."""
        every = np.arange(self.n_o)
        full: list[tuple[int, int, np.ndarray, np.ndarray | None]] = [(0, self.nz, every, None)]
        if self.dim != 3 or self._fr_var is None:
            return full
        z_s = self.layer.z_surface
        tan_max = float(np.abs(self._tan).max(initial=0.0))
        ap = max(self._aperture)
        # Where the beads are worth their own beams' reach: their echo down by e^{−12} at the band's longest ℓ_ext
        # (ℓ_ext(f) may grow or fall with f); the focal return's, lit at its light depth.
        d_beads = 6.0 * float(np.max(self.layer.l_ext_at(self.freqs)))
        lit = self.depths if self._fr_light is None else self._fr_light
        z_lit = z_s + lit
        # a beam's cosine edge ends (1 + BEAM_SOFT) half-widths from its steered centre (`beam`)
        reach = z_lit * tan_max + (1 + BEAM_SOFT) * beam_half_width(ap, z_lit, self._lam)
        z_own = z_s + self.depths
        own = z_own * tan_max + (1 + BEAM_SOFT) * beam_half_width(ap, z_own, self._lam)
        x_src = np.where(self.depths <= d_beads, np.maximum(reach, own), reach) + 0.5 * ap
        s_x = x_src / np.hypot(x_src, z_own)  # (nz,)
        s_mag = np.hypot(self.s_out[:, 0], self.s_out[:, 1])
        s_top = float(s_mag.max())
        chunks: list[tuple[int, int, np.ndarray, np.ndarray | None]] = []
        i0 = 0
        while i0 < self.nz:
            i1 = i0 + 1
            while i1 < self.nz and np.ptp(s_x[i0 : i1 + 1]) <= CHUNK_SPAN:
                i1 += 1
            cut = float(s_x[i0:i1].max())
            if cut + CHUNK_EDGE >= s_top:  # every direction
                if chunks and chunks[-1][3] is None:  # and so did the one before: one chunk
                    chunks[-1] = (chunks[-1][0], i1, every, None)
                else:
                    chunks.append((i0, i1, every, None))
            else:
                keep = np.flatnonzero(s_mag < cut + CHUNK_EDGE)
                t = np.clip((s_mag[keep] - cut) / CHUNK_EDGE, 0.0, 1.0)
                chunks.append((i0, i1, keep, (0.5 + 0.5 * np.cos(np.pi * t)).astype(np.float32)))
            i0 = i1
        return chunks

    def prepare(self) -> None:
        """Build what no frame changes (per sub-band depth profiles and NUFFT plans, the transmits' beams),
        once; copies made after share them (`diffuse.DiffuseBackground.fork`), and a lock they share too, so
        that threads run one NUFFT at a time."""
        if self._plans is None:
            self._plan_lock = threading.Lock()
            self._plans = []
            for wts, fc in zip(self.blend, self.centres, strict=True):
                idx = np.flatnonzero(wts > 0)
                if idx.size:
                    depth_w, tx_w, fr_j, chunks = self._sub_band(idx, fc)
                    bw = wts[idx].astype(np.float32)[None, None, :]
                    chunks = [(i0, i1, o, plans, post * bw) for i0, i1, o, plans, post in chunks]
                    self._plans.append((idx, depth_w, tx_w, fr_j, chunks))
        if self._beams is None:
            self._beams = np.stack([self.beam(i) for i in range(self.n_i)])
        if self._fr_light is not None and self._fr_beams is None:
            self._fr_beams = np.stack([self.beam(i, self._fr_light) for i in range(self.n_i)])

    def spectrum(self) -> np.ndarray:
        """A(o, θ, f) (N_o, N_θ, N_f) complex64 for the current grid (module doc)."""
        if self.state is None:
            self.advance()
        assert self.state is not None
        self.prepare()
        assert self._plans is not None and self._beams is not None and self._plan_lock is not None
        out = np.zeros((self.n_o, self.n_i, self.freqs.size), dtype=np.complex64)
        fr_beams = self._beams if self._fr_beams is None else self._fr_beams
        for idx, depth_w, tx_w, fr_j, chunks in self._plans:
            base = self.state * depth_w[None, None, :]
            focal = None
            if fr_j is not None:  # its variance holds its legs' extinction: no transmit factor (module doc)
                assert self.fr_state is not None
                amp = self.fr_state if self._pairs is None else self._paired_amplitudes()
                focal = amp * self._focal_weights(fr_j)[None, None, :]
            phases = None if self._pairs is None or fr_j is None else self._pair_phases(fr_j)
            for i in range(self.n_i):
                if focal is not None and phases is not None and self._pairs is not None:  # (F6): from the partner
                    grid = _paired_grid(base, tx_w[i], self._beams[i], focal, phases[i], self._pairs, fr_beams[i])
                else:
                    grid = base * tx_w[i][None, None, :]
                    grid *= self._beams[i]
                    if focal is not None:  # lit as its ends are (`add_focal_return`'s light), else as the beads
                        grid += focal * fr_beams[i]
                for i0, i1, o_idx, plans, post in chunks:
                    part = np.ascontiguousarray(grid[:, :, i0:i1] if self.dim == 3 else grid[:, 0, i0:i1])
                    with self._plan_lock:
                        vals = plans[i].execute(part).reshape(o_idx.size, idx.size) * post[:, i]
                    if o_idx.size == self.n_o:
                        out[:, i, idx] += vals
                    else:
                        out[o_idx[:, None], i, idx[None, :]] += vals
        return out

    def _paired_amplitudes(self) -> np.ndarray:
        """The focal return's amplitudes with each pair's two cells equal (its primary's white value), √2 × on the
        cells that are their own partner (F6)."""
        assert self._pairs is not None and self.fr_state is not None
        _, primary, _, gain = self._pairs
        return self.fr_state.reshape(-1)[primary].reshape(self.fr_state.shape) * gain

    def _pair_phases(self, j: int) -> np.ndarray:
        """Per transmit, e^{−ik a_θ·δ} over every offset δ = (m_x, m_y) h_x to the partner (the transmit's phase at
        the partner instead of the cell), k at sub-band centre j: (N_θ, (2M + 1)^2) complex64, indexed by
        `_pairs`' offset codes (F6)."""
        k = 2 * np.pi * float(self.centres[j]) / self.c0
        m = np.arange(-PAIR_CODE_STEPS, PAIR_CODE_STEPS + 1) * self.hx
        px = np.exp(-1j * k * self._sines_in[:, 0, None] * m[None, :])
        py = np.exp(-1j * k * self._sines_in[:, 1, None] * m[None, :]) if self.dim == 3 else np.ones_like(px)
        return (px[:, :, None] * py[:, None, :]).reshape(self.n_i, -1).astype(np.complex64)

    @property
    def _ds2(self) -> float:
        return self.ds**2 if self.dim == 3 else self.ds


#: The output directions see a source this far in sine beyond its rays to the elements, a cosine edge; the grid's
#: depths in chunks over which these rays' sine spans at most CHUNK_SPAN (`SingleScatteringField._depth_chunks`).
CHUNK_EDGE, CHUNK_SPAN = 0.1, 0.1

#: Spatial period λ/Δs of the output grid over twice the largest source–element offset (`output_grid`).
PERIOD_MARGIN = 1.5
#: At most this many output directions in 3D (the grid coarsens beyond, and the outermost sources alias).
MAX_DIRECTIONS = 2500


def output_grid(
    reach: list[float], aperture: tuple[float, float], z_s: float, lam_min: float, dim: int
) -> tuple[float, list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """An output plane-wave grid for sources within ±reach (m) of the axis seen by elements within
    ±aperture/2. Its spatial period λ/Δs (the Poisson images of each source, λ-dependent and therefore
    dispersed in time: energy before the surface echo) is PERIOD_MARGIN × twice the largest source–element
    offset X = reach + aperture/2, and it reaches the sine of that offset's ray from the surface, s_X =
    X/√(X² + z_s²), then tapers to 0 by s_X + 0.15 (≤ 0.95), so that the truncated Weyl sum has no endpoint
    term. In 3D the spacing grows if MAX_DIRECTIONS would be exceeded.
    Returns (Δs, axes, keep over the full x-major grid, s_out (N_o, 2), taper (N_o,))."""
    span = [reach[d] + 0.5 * aperture[d] for d in range(2 if dim == 3 else 1)]
    x = max(span)
    s_need = min(x / np.hypot(x, z_s), 0.8)
    s_end = min(s_need + 0.15, 0.95)
    ds = lam_min / (2.0 * PERIOD_MARGIN * x)
    if dim == 3:
        ds = max(ds, s_end * np.sqrt(np.pi / MAX_DIRECTIONS))
    m = int(np.ceil(s_end / ds))
    ax = np.arange(-m, m + 1) * ds
    if dim == 3:
        sx, sy = np.meshgrid(ax, ax, indexing="ij")
        full = np.stack([sx.ravel(), sy.ravel()], axis=1)
        axes = [ax, ax]
    else:
        full = np.stack([ax, np.zeros_like(ax)], axis=1)
        axes = [ax]
    mag = np.hypot(full[:, 0], full[:, 1])
    keep = mag < s_end
    edge = np.clip((mag[keep] - s_need) / (s_end - s_need), 0.0, 1.0)
    return ds, axes, keep, full[keep], 0.5 + 0.5 * np.cos(np.pi * edge)


#: The longest pair offset per axis the phase codes hold (`pair_layout`; `paths.PAIR_MAX_STEPS` rounds to it).
PAIR_CODE_STEPS = 40


def pair_offsets(shape: tuple[int, int, int], separations: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Each cell's offset to its partner (2, nx, ny, nz) int16, in grid steps per lateral axis (F6 of docs/design.md
    §6.6): the cells of every depth paired so that the pairs' separations follow `separations` (nz, n_y, n_steps),
    per depth the joint distribution of (|m_y|, |m_x|) (n_y = 1: none along y): the share separations[z, m_y, m_x]
    of the cells has those offsets (each cell carries the same variance, so this is the share of the paths'
    energy). Each depth is cut along y into strips of height 2m_y (1 for m_y = 0), the share of the cells in strips
    of m_y its marginal; each strip's row pair (rows y and y + m_y, which pair with each other) along x into tiles of
    width 2m_x drawn from the conditional distribution given the strip's m_y, the tile's cell (x, y) paired with
    (x ± m_x, y ± m_y) across its halves: the partner lies in the same row pair, so the partner's partner is the
    cell, and a cell is its own partner only where m_x = m_y = 0. At the grid's edges a tile too wide shrinks to the
    widest that fits (a strip then takes the x-marginal).

    One tiling per row pair, not one per strip (until 2026-12-08): a tiling shared by the strip's 2m_y rows lays
    pairs of one separation side by side over a patch of the grid, a structured reflectivity that no suspension has
    (each bead ends many paths, at every separation) and that made the default detector's γ-maps heavier-tailed than
    their level under the surface (docs/validation.md, tenth session). The shares of the separations are the same."""
    nx, ny, nz = shape
    sep = np.asarray(separations, dtype=np.float64)
    if sep.ndim != 3 or sep.shape[0] != nz:
        raise ValueError(f"separations: expected shape ({nz}, n_y, n_steps), got {sep.shape}")
    if max(sep.shape[1], sep.shape[2]) > PAIR_CODE_STEPS + 1:
        raise ValueError(f"separations: expected at most {PAIR_CODE_STEPS + 1} steps, got {sep.shape[1:]}")
    off = np.zeros((2, nx, ny, nz), dtype=np.int16)

    def tiling(n: int, q: np.ndarray) -> np.ndarray:
        """Offsets along one axis of n cells: tiles of 2m (±m across their halves) or single cells (m = 0), the
        share q(m) of the cells in tiles of m (a tile's probability q(m) over its width)."""
        out = np.zeros(n, dtype=np.int16)
        p = q / np.maximum(2 * np.arange(q.size), 1)
        draws = rng.choice(p.size, size=n, p=p / p.sum())
        cur = 0
        for m in draws:
            if cur >= n:
                break
            m = min(int(m), (n - cur) // 2)
            if m == 0:
                cur += 1
                continue
            out[cur : cur + m], out[cur + m : cur + 2 * m] = m, -m
            cur += 2 * m
        return out

    for z in range(nz):
        q_y = sep[z].sum(axis=1)
        q_x = sep[z].sum(axis=0)
        oy = tiling(ny, q_y)
        y0 = 0
        while y0 < ny:
            m_y = abs(int(oy[y0]))
            height = 2 * m_y if m_y else 1
            given = sep[z, m_y] / q_y[m_y] if m_y < q_y.size and q_y[m_y] > 0 else q_x  # the conditional on m_y
            for j in range(max(m_y, 1)):  # rows y0 + j and y0 + m_y + j pair with each other: one tiling for both
                tiles = tiling(nx, given)
                for row in (y0 + j, y0 + m_y + j) if m_y else (y0,):
                    off[0, :, row, z] = tiles
            off[1, :, y0 : y0 + height, z] = oy[None, y0 : y0 + height]
            y0 += height
    return off


def pair_layout(off: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """From the offsets to the partners (`pair_offsets`, (2, nx, ny, nz)): each cell's partner and its pair's primary
    cell (the lower flat index), flat int32 (nx·ny·nz,); its offset's code into `SingleScatteringField._pair_phases`
    and its amplitude gain (√2 where the cell is its own partner), (nx, ny, nz) int32 and float32."""
    _, nx, ny, nz = off.shape
    ix, iy, iz = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    cell = (ix * ny + iy) * nz + iz
    partner = ((ix + off[0]) * ny + (iy + off[1])) * nz + iz
    primary = np.minimum(cell, partner).ravel().astype(np.int32)
    width = 2 * PAIR_CODE_STEPS + 1
    combo = (off[0].astype(np.int32) + PAIR_CODE_STEPS) * width + off[1] + PAIR_CODE_STEPS
    alone = (off[0] == 0) & (off[1] == 0)
    gain = np.where(alone, np.float32(np.sqrt(2.0)), np.float32(1.0)).astype(np.float32)
    return partner.ravel().astype(np.int32), primary, combo, gain


def _paired_grid(
    base: np.ndarray,
    tx_w: np.ndarray,
    beam: np.ndarray,
    focal: np.ndarray,
    phases: np.ndarray,
    pairs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    fr_beam: np.ndarray,
) -> np.ndarray:
    """One transmit's grid with the pairs (F6): the beads' base × its extinction per depth × its beam, plus the focal
    return × the transmit's phase at each cell's partner (`phases` indexed by the offset codes) × its beam there;
    (nx, ny, nz) complex64. Compiled (one pass, the project's threads) where numba is, NumPy otherwise."""
    partner, _, combo, _ = pairs
    if nb is None:  # pragma: no cover - numba is a dependency; the same sums
        grid = base * tx_w[None, None, :] * beam
        grid += focal * phases[combo] * fr_beam.reshape(-1)[partner].reshape(base.shape)
        return grid
    out = np.empty(base.shape, dtype=np.complex64)
    flat = (base.reshape(-1), tx_w.astype(np.float32), beam.reshape(-1), focal.reshape(-1), phases, combo.reshape(-1))
    args = (*flat, partner, fr_beam.reshape(-1), out.reshape(-1))
    n, parts = out.size, 4 * default_threads()

    def task(slot: int, t: int) -> tuple:
        return (*args, *split(n, parts, t))

    pool(default_threads(), parts, _paired_rows, task)
    return out


if nb is not None:

    @_jit
    def _paired_rows(base, tx_w, beam, focal, phases, combo, partner, fr_beam, out, r0, r1):  # pragma: no cover
        """out[c] = base[c] tx_w[c mod nz] beam[c] + focal[c] phases[combo[c]] fr_beam[partner[c]], r0 ≤ c < r1."""
        nz = tx_w.size
        for c in range(r0, r1):
            out[c] = base[c] * (tx_w[c % nz] * beam[c]) + focal[c] * phases[combo[c]] * fr_beam[partner[c]]


#: The beams' cosine edges, this fraction of the half-width either side of it (`SingleScatteringField.beam`).
BEAM_SOFT = 0.15


def beam_half_width(aperture: float, z: np.ndarray | float, lam: float) -> np.ndarray:
    """Half-width of a plane wave synthesised by an aperture D at the range z from it: D/2 in the near field plus
    the diffraction spread λz/(2D) (the far-field energy width λz/D of a uniform aperture's sinc² pattern)."""
    return 0.5 * aperture + 0.5 * lam * np.asarray(z, dtype=np.float64) / max(aperture, lam)


def beam_gain(aperture: float, z: np.ndarray | float, lam: float) -> np.ndarray:
    """The beam's amplitude per lateral axis at the range z, √(h(0)/h(z)) with h = `beam_half_width`: the power
    the aperture sends through each depth, |w|² × width, stays D. A flat beam of amplitude 1 as wide as its
    spread carries 1 + λz/D² times it per axis: lit by it, the first order of the 3-D Foldy–Lax rig (4 mm array,
    7–12 mm) is +1.8 … +4.5 dB over the same lit by the synthesised transmits, and −0.3 … +1.0 dB with this gain
    (`bench/transport_paths.py --beams`)."""
    return np.sqrt(0.5 * aperture / beam_half_width(aperture, z, lam))


def _edge(x: np.ndarray, half: float | np.ndarray, soft: float | np.ndarray) -> np.ndarray:
    """1 inside |x| < half − soft, a cosine edge down to 0 at |x| = half + soft."""
    t = np.clip((np.abs(x) - (half - soft)) / (2 * soft), 0.0, 1.0)
    return 0.5 + 0.5 * np.cos(np.pi * t)
