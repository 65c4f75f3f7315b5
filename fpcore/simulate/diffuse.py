"""Frame generator of the multiple-scattering background V(f, u, θ) (docs/design.md §6.3); the physics
of its envelope, level and frame-to-frame decorrelation is in `medium` (module doc there).

The field is built as upgoing plane waves leaving the suspension, one random amplitude A(o, θ, t) per
output direction s_o (|s_o| ≲ s_d, on a grid whose spatial period λ_min/Δs exceeds the aperture) and
transmit θ. A plane wave o launched by transmit θ that spent a time τ in the medium arrives at the
array at t = z_s (c_θ + c_o)/c0 + τ (lateral phases referred to the array centre), so its age — and the
envelope √⟨M²⟩(τ) it carries — depends on its direction: energy arriving obliquely at a given time is
younger. This keeps the confocal mapping (time, angle) → depth consistent with the age of the wave.
With angular="halo" (`HaloGeometry`) each direction sees instead the part of the halo where its ray
through the array lands, at that ray's delay, with its own level.

Transport additions (issue: the paper's regime), each switched by the `ScatteringLayer`:

* **ℓ_s(f).** A dispersive medium (ls_exponent ≠ 0) is simulated in sub-bands, each with the envelope of
  its own ℓ_s(f_j), from the same white noise; the spectra are blended with triangular weights in f.
* **Reciprocity and coherent backscattering** (cbs=True). Reciprocity of the medium's plane-wave matrix
  is T(o, a) = T(−a, −o) (transmit a → upgoing o equals transmit −o → upgoing −a). The output grid is
  aligned with the transmit sines (its spacing divides their lattice) and the outputs carry the Weyl
  factor 1/c_o of a point source's plane-wave spectrum. A transmit synthesised by the array is its
  angular spectrum about s_θ, so the outputs that mirror the transmits' main lobes come from one
  symmetric noise T_ij = T_ji over the lobes' inputs and mirrored outputs, mixed by the array factor
  (`reciprocity.ReciprocalBlock`): then the element-basis matrix is symmetric through the array's own
  beams, R̃(−s_θ', θ)/c_θ = R̃(−s_θ, θ')/c_θ', and the reversed paths give coherent backscattering of height 2
  over the beams' cone; the exactly retro-reflected plane wave, its own partner, has twice the ladder.
  The other outputs keep independent noise with the intensity cone 1 + exp(−k²|s_o + s_θ|² D's
  a_g²/(a_g² + 4D's)) (negligible there). Until 2026-12-02 only the plane-wave pairs on the transmit
  lattice shared their noise, and a receive beam, mixing independent neighbours, saw the cone diluted
  (3-D Foldy–Lax check: 1.43 against 2.14; symmetry 0.15 against 0.997).
* **The angular memory effect** (memory=True; `memory`, docs/design.md §6.5): the main grid's noise correlated
  along (o + L, θ + 1) and the block's along its common tilts, as exp(−k²δ²D_eff(τ)); the block's envelopes
  divided by √G(t) so that the elements receive the envelope's energy (`memory.block_energy_gain`).
* **Single scattering by the beads** (single_scattering="field"): the first order is a continuum
  reflectivity focused like a speckle image (`single_scattering.SingleScatteringField`, on its own output
  grid, projected separately), and the Gaussian field carries the orders ≥ 2 only; "envelope" keeps all
  orders in the Gaussian field.

Construction per frame: complex white noise ξ(o, θ, t_n) on a baseband time grid (spacing
Δ = period/n_bb, E|ξ|² = 1/Δ, i.e. unit spectral density), multiplied by the envelope, Fourier
transformed onto the band bins, and projected to the elements, M(u, θ, f) = Σ_o w_o A e^{−ik s_o·u}
(taper w_o, Σ w_o² = 1). Frames evolve by ξ_n = g₁ ξ_{n−1} + √(1 − g₁²) ξ'_n with g₁(τ) (DWS).
The RF background is S(f)·V(f); it is statistically independent of every target.
"""

from __future__ import annotations

import copy
import hashlib
import pickle
from collections import OrderedDict
from typing import TYPE_CHECKING

import numpy as np
import scipy.fft as sfft

from ..acquisition import element_grid_axes
from ..geometry import cosines
from .confocal_notch import ConfocalNotch, keep_envelope
from .memory import MemoryKernel, block_energy_gain, block_kernel, effective_spread, grid_kernel, lattice_steps
from .paths import FocalRig, Paths, draw_paths, focal_pairs, focal_return
from .reciprocity import ElementReciprocity, ReciprocalBlock
from .single_scattering import SingleScatteringField
from .waves import Band, TimeWindow

if TYPE_CHECKING:
    from .medium import ScatteringLayer

__all__ = ["DiffuseBackground", "HaloGeometry", "aligned_spacing", "project_plane_waves", "reciprocal_pairs"]

#: Sub-bands for a dispersive medium: enough that ℓ_s changes by at most SUB_BAND_LS_RATIO between neighbouring
#: centres, and at most N_SUB_BANDS of them.
N_SUB_BANDS = 8
SUB_BAND_LS_RATIO = 1.25

#: At most this many backgrounds' tables (geometry and envelopes, a few hundred MB each) kept for reuse by
#: `DiffuseBackground.cached`, the least recently used dropped first.
CACHED_BACKGROUNDS = 2
_CACHE: OrderedDict[str, DiffuseBackground] = OrderedDict()


def aligned_spacing(ds_max: float, values: np.ndarray, tol: float = 1e-9) -> float | None:
    """The largest spacing ≤ ds_max of which every value is an integer multiple, or None (irregular)."""
    v = np.asarray(values, dtype=np.float64)
    nz = np.abs(v[np.abs(v) > tol])
    if nz.size == 0:
        return ds_max
    base = float(nz.min())
    for j in range(1, 400):
        g = base / j
        if g > ds_max * (1 + 1e-12):
            continue
        if np.all(np.abs(v / g - np.round(v / g)) < 1e-6):
            return g
        break
    return None


def reciprocal_pairs(s_out: np.ndarray, sines: np.ndarray, tol: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays (o, θ) → partner (o', θ') with s_out[o'] = −s_θ and s_θ' = −s_out[o]; −1 where absent."""
    so, si = np.asarray(s_out, float), np.asarray(sines, float)
    d_o = np.linalg.norm(so[:, None, :] + si[None, :, :], axis=2)  # (N_o, N_θ): |s_o + s_θ|
    o_of_theta = np.where(d_o.min(axis=0) < tol, d_o.argmin(axis=0), -1)  # o' with s_o' = −s_θ
    theta_of_o = np.where(d_o.min(axis=1) < tol, d_o.argmin(axis=1), -1)  # θ' with s_θ' = −s_o
    po = np.broadcast_to(o_of_theta[None, :], d_o.shape)
    pt = np.broadcast_to(theta_of_o[:, None], d_o.shape)
    ok = (po >= 0) & (pt >= 0)
    return np.where(ok, po, -1), np.where(ok, pt, -1)


def landing(z_s: float, sines: np.ndarray) -> np.ndarray:
    """Where a plane wave of these sines from the array's centre meets the surface z_s: z_s s/c, (N, 2)."""
    si = np.asarray(sines, dtype=np.float64)
    return z_s * si / cosines(si)[:, None]


def halo_reach(z_s: float, sines: np.ndarray, aperture_radius: float, spread: float) -> float:
    """The sine out to which a halo of lateral spread 4D's = `spread` is seen from the array's centre: its
    width w (w² = 2a_g² + 4D's, `HaloGeometry`) times 1.5 beyond the farthest transmit's landing."""
    r = float(np.max(np.linalg.norm(landing(z_s, sines), axis=1), initial=0.0))
    r += 1.5 * np.sqrt(2 * a_g2(aperture_radius) + spread)
    return r / np.hypot(r, z_s)


def _pair_axes(paired: bool) -> tuple[slice | None, ...]:
    """The index that lays a per-input array out against per-output columns: (None, :) gives every pair
    (o, θ) as an (N_o, N_θ) table; (:, None), with paired, only the pairs (s_out[n], sines[n]) as (n, 1)."""
    return (slice(None), None) if paired else (None, slice(None))


def a_g2(aperture_radius: float) -> float:
    """a_g² = 2a²/3: the Gaussian e^{−x²/a_g²} with the variance a²/3 of a uniform aperture |x| < a."""
    return 2.0 * aperture_radius**2 / 3.0


class HaloGeometry:
    """Where and when each upgoing plane wave s_o sees the diffuse halo of transmit s_θ (angular="halo").

    Per lateral axis the aperture (half-width a) is the Gaussian e^{−x²/a_g²} of the same variance, a_g² =
    2a²/3, with the flux factor F = 2a/(√π a_g). Transmit θ lands centred on ρ_θ = z_s s_θ/c_θ; the halo it
    leaves after a path s is (a_g²/b²)^{1/2} e^{−|ρ − ρ_θ|²/b²} per axis, b² = a_g² + 4D's. Output s_o sees,
    through the aperture, the surface around ρ_o = −z_s s_o/c_o (its ray through the array's centre), so
    its share of the halo is F (a_g²/w²)^{1/2} e^{−|ρ_o − ρ_θ|²/w²} per axis, w² = a_g² + b². Exit and entry
    points are centred on ρ_m = (1 − u) ρ_θ + u ρ_o and ρ'_m = u ρ_θ + (1 − u) ρ_o, u = b²/w², and the wave
    arrives at t = [z_s (c_θ + c_o) + s_θ·ρ'_m − s_o·ρ_m]/c0 + τ: the specular delay 2 z_s c at u = ½ and
    the rays' z_s (1/c_θ + 1/c_o) once the halo outgrows the aperture (u → 1); exact retro-reflection keeps
    2 z_s/c throughout. The received intensity is the Lambertian radiance M/π (2D: M/2) over the solid angle
    d²s/c_o of each direction, and the incident flux density is c_θ per unit intensity. Every factor is
    symmetric under (o, θ) ↔ (−θ, −o), so reciprocity (`reciprocal_pairs`, `reciprocity`) holds (docs/design.md §6.3).
    Coherent backscattering between beams: the reversed path's phase k q·(ρ₁ − ρ₂), q = s_o + s_θ, is
    averaged over endpoint separations weighted by the diffusion kernel e^{−Δ²/(4D's)} and by both beams'
    footprints e^{−Δ²/a_g²}, so the cone is e^{−k²q² D's a_g²/(a_g² + 4D's)}: the plane waves' e^{−k²q²D's}
    while the halo is narrower than the aperture, the beams' width ~2/(k a_g) once it is wider.
    """

    def __init__(
        self,
        layer: ScatteringLayer,
        s_out: np.ndarray,
        sines: np.ndarray,
        aperture_radius: float,
        dim: int,
        c0: float,
        paired: bool = False,
    ) -> None:
        self.dim, self.c0, self.z_s = dim, c0, layer.z_surface
        self.v = c0 if layer.energy_velocity is None else layer.energy_velocity
        self.a_g2 = a_g2(aperture_radius)
        self.flux = (2.0 * aperture_radius / np.sqrt(np.pi * self.a_g2)) ** (dim - 1)
        so, si = np.asarray(s_out, float), np.asarray(sines, float)
        if paired and so.shape != si.shape:
            raise ValueError(f"sines: expected {so.shape[0]} directions, one per s_out (paired), got {si.shape[0]}")
        self._at_i = _pair_axes(paired)
        c_o, c_i = cosines(so), cosines(si)
        rho_o = -landing(self.z_s, so)  # an output's ray through the array, traced back to the surface
        rho_i = landing(self.z_s, si)
        self.sep2 = np.sum((rho_o[:, None, :] - rho_i[self._at_i]) ** 2, axis=2)  # |ρ_o − ρ_θ|², (N_o, N_θ)
        self.rho_o, self.rho_i = rho_o, rho_i
        # A medium of finite width: absorbing walls at ±X, X = width/2 + z_e, per lateral axis (side_losses).
        self.wall = 0.5 * layer.width + layer.diffusion_constants(dim)[1] if np.isfinite(layer.width) else None
        self.c_o, self.c_i = c_o, c_i
        # t − τ = (A − C) + u (B + C), B + C ≥ 0 (module doc): the specular part and the rays' extra path.
        ci, oi = c_i[self._at_i], (si**2).sum(1)[self._at_i]
        a = self.z_s * (ci + c_o[:, None])
        b = self.z_s * (oi / ci + (so**2).sum(1)[:, None] / c_o[:, None])
        dot = np.sum(so * si, axis=1)[:, None] if paired else so @ si.T
        c = self.z_s * dot * (1.0 / c_o[:, None] + 1.0 / ci)
        self.t_spec = ((a - c) / c0).astype(np.float32)
        self.t_rays = np.maximum((b + c) / c0, 0.0).astype(np.float32)

    def spread_rate(self, ls: float) -> float:
        """4D's per unit age: 4 (ℓ_s/d) v."""
        return 4.0 * ls / self.dim * self.v

    def spread(self, tau: np.ndarray, ls: float) -> np.ndarray:
        """4D's for the age τ (D' = ℓ_s/d)."""
        return self.spread_rate(ls) * np.maximum(tau, 0.0)

    def age(self, t: np.ndarray, ls: float, iterations: int = 12, tol: float = 1e-10) -> np.ndarray:
        """τ (N_o, N_θ, N_t) float32 with t = t_spec + u(τ) t_rays + τ, by Newton from the left (the map is
        increasing and concave in τ, so the iterates rise monotonically to the root; stopped once no step
        exceeds `tol` seconds); τ ≤ 0 before the wave."""
        target = np.asarray(t, np.float32)[None, None, :] - self.t_spec[:, :, None]
        g = self.t_rays[:, :, None]
        tau = target - g
        k = np.float32(self.spread_rate(ls))
        a2 = np.float32(self.a_g2)
        for _ in range(iterations):
            den = np.maximum(tau, 0.0)
            den *= k
            den += 2 * a2  # 2a_g² + 4D's
            resid = a2 / den  # 1 − u
            np.subtract(1.0, resid, out=resid)
            resid *= g
            resid += tau
            resid -= target  # τ + g u − t'
            slope = np.square(den, out=den)
            np.divide(k * a2, slope, out=slope)
            slope[tau <= 0] = 0.0
            slope *= g
            slope += 1.0  # 1 + g du/dτ
            resid /= slope
            tau -= resid
            if float(np.abs(resid).max(initial=0.0)) < tol:
                break
        return tau

    def share(self, tau: np.ndarray, ls: float, spacing: float, cbs: bool) -> np.ndarray:
        """The intensity factor of each (o, θ, τ) for the noise's envelope, weights (`weights`) divided out:
        F (a_g²/w²)^{(d−1)/2} e^{−|ρ_o − ρ_θ|²/w²} × c_θ × Δs^{d−1}/(N_Ω c_o), with N_Ω = π (3D) or 2 (2D) and
        Δs^{d−1} the directions' cell, times c_o² where the weights carry the Weyl factor 1/c_o (cbs)."""
        w2 = 2 * np.float32(self.a_g2) + self.spread(tau, ls).astype(np.float32)
        n_omega = np.pi if self.dim == 3 else 2.0
        per_dir = self.c_i[self._at_i] * spacing / n_omega * (self.c_o[:, None] if cbs else 1.0 / self.c_o[:, None])
        if self.wall is None:
            out = np.exp(-self.sep2.astype(np.float32)[:, :, None] / w2)
        else:  # per axis, the image series Σ_n (−1)ⁿ e^{−(x_o − x_n)²/w²}, x_n = 2nX + (−1)ⁿ x_θ (Carslaw & Jaeger)
            x_wall = self.wall
            m = int(np.ceil(3 * float(np.sqrt(w2.max())) / (2 * x_wall))) + 1
            out = np.ones_like(w2)
            for d in range(self.dim - 1):
                axis = np.zeros_like(w2)
                for n in range(-m, m + 1):
                    x_n = 2 * n * x_wall + (-1) ** abs(n) * self.rho_i[:, d]
                    gap = (self.rho_o[:, None, d] - x_n[self._at_i]).astype(np.float32)
                    axis += np.float32((-1) ** abs(n)) * np.exp(-(gap**2)[:, :, None] / w2)
                out *= np.maximum(axis, 0.0)
        out *= (np.float32(self.a_g2) / w2) ** np.float32(0.5 * (self.dim - 1))
        out *= (self.flux * per_dir).astype(np.float32)[:, :, None]
        return out


class DiffuseBackground:
    """Frame generator of the multiple-scattering spectrum V(f, u, θ) (dimensionless, like a target's H)."""

    def __init__(
        self,
        layer: ScatteringLayer,
        elements: np.ndarray,
        sines: np.ndarray,
        window: TimeWindow,
        band: Band,
        c0: float,
        dim: int,
        aperture_radius: float,
        rng: np.random.Generator,
    ) -> None:
        self.layer, self.window, self.band, self.c0, self.dim = layer, window, band, c0, dim
        self.rng = rng
        self.bins = window.band_bins(band)
        self.freqs = window.freqs()[self.bins]
        el = np.asarray(elements, dtype=np.float64)
        s = np.asarray(sines, dtype=np.float64)
        self.n_u, self.n_i = el.shape[0], s.shape[0]
        self.elements = el
        n_f = self.bins.size
        self.n_bb = int(sfft.next_fast_len(2 * n_f))
        self.dt = window.period / self.n_bb
        v = c0 if layer.energy_velocity is None else layer.energy_velocity
        # Angular spread of the halo seen from the array at the middle of the window.
        mid = window.t0 + 0.5 * window.duration - 2 * layer.z_surface / c0
        halo = layer.angular == "halo"
        if halo:  # the halo at the window's middle (docs/design.md §6.3: ≤ 0.4 dB lost at its end)
            spread = 4 * float(layer.ls_at(band.centre)) / dim * v * max(mid, 0.0)
            self.s_d = halo_reach(layer.z_surface, s, aperture_radius, spread)
        else:
            b = float(np.sqrt(layer.halo_radius2(np.array(max(mid, 0.0) * v), aperture_radius, dim)))
            self.s_d = b / np.hypot(b, layer.z_surface)
        # Direction grid: spatial period λ_min/Δs ≥ 1.2 × the array extent; aligned with the transmits'
        # lattice when reciprocity is asked for (module doc).
        span = np.ptp(el[:, :2], axis=0) + 1e-12
        lam_min = c0 / band.support[1]
        s_cut = min(1.15 * self.s_d, 0.98)
        axes, spacings = [], []
        for d in range(2 if dim == 3 else 1):
            ds = lam_min / (1.2 * max(span[d], lam_min))
            if layer.cbs:
                ds = aligned_spacing(ds, s[:, d]) or ds
            m = int(np.floor(s_cut / ds))
            axes.append(np.arange(-m, m + 1) * ds)
            spacings.append(ds)
        if dim == 3:
            sx, sy = np.meshgrid(axes[0], axes[1], indexing="ij")
            so = np.stack([sx.ravel(), sy.ravel()], axis=1)
        else:
            so = np.stack([axes[0], np.zeros_like(axes[0])], axis=1)
        smag = np.hypot(so[:, 0], so[:, 1])
        keep = smag < s_cut
        self.s_out = so[keep]
        self._axes, self._spacings = axes, spacings
        self._keep = keep
        self.sines = s
        x = np.clip((smag[keep] / self.s_d - 0.85) / 0.3, 0.0, 1.0)
        c_o = cosines(self.s_out)
        # Taper × the plane-wave (Weyl) weight 1/c_o of a point source's spectrum, so that a reciprocal noise
        # pair gives R(b, a) W_a = R(−a, −b) W_b: a symmetric matrix in the element basis (module doc).
        w = (0.5 + 0.5 * np.cos(np.pi * x)) / (c_o if layer.cbs else 1.0)
        norm2 = float(np.sum(w**2))
        self.weights = (w / np.sqrt(norm2)).astype(np.float32)
        self.n_o = self.s_out.shape[0]
        self._t = window.t0 + np.arange(self.n_bb) * self.dt
        self._aperture_radius, self._v = aperture_radius, v
        self._cell = float(np.prod(spacings))  # Δs^{d−1}, the sine area of one direction
        self._norm2 = norm2
        # Sub-bands (one for a non-dispersive medium) and their triangular blending weights in f.
        ls_span = layer.ls_at(np.array([self.freqs[0], self.freqs[-1]]))
        n_sub = 1 + int(np.ceil(np.log(float(ls_span.max() / ls_span.min())) / np.log(SUB_BAND_LS_RATIO) - 1e-9))
        n_sub = 1 if layer.ls_exponent == 0.0 else min(N_SUB_BANDS, n_f, max(n_sub, 2))
        self.centres = np.linspace(self.freqs[0], self.freqs[-1], n_sub) if n_sub > 1 else np.array([band.centre])
        self.blend = _triangles(self.freqs, self.centres)  # (n_sub, N_f)
        # The beads' single scattering (its generator is the background generator's first draw) and the focal
        # return of the orders ≥ 2 on its grid, whose energy the Gaussian field's envelopes then leave out.
        self.single: SingleScatteringField | None = None
        self._fr_kept: tuple[np.ndarray, np.ndarray] | None = None
        fr_kept = self._fr_kept
        if layer.single_scattering == "field":
            ss_rng = _beads_stream(rng)
            t_end = window.t0 + window.period
            # Deep enough that the echo at the band's lower −6 dB edge has fallen by e^{−12} in intensity; with the
            # focal return, to the record's end (its apparent depths reach it: docs/design.md §6.6), unless it is
            # drawn on the beads' own depths only (focal_return_shallow).
            depth_max = max(min(0.5 * c0 * t_end - layer.z_surface, 6.0 * float(layer.l_ext_at(band.f_min))), 1e-3)
            if layer.focal_return and not (layer.focal_return_shallow or layer.focal_return_excess):
                depth_max = max(depth_max, 0.5 * c0 * (window.t0 + window.duration) - layer.z_surface)
            self.single = SingleScatteringField(
                layer,
                s,
                self.freqs,
                self.blend,
                self.centres,
                c0,
                dim,
                (float(span[0]), float(span[1]) if dim == 3 else 0.0),
                depth_max,
                ss_rng,
            )
            if layer.focal_return:
                var, g1, self._fr_kept, light, sep = focal_return_tables(
                    layer, self.single, el, s, self.centres, c0, dim, window
                )
                self.single.add_focal_return(var, g1, light, sep)
                if layer.focal_return_excess:  # the Gaussian field whole until the excess is measured (F5)
                    fr_kept, self._fr_kept = self._fr_kept, None
        self.envelopes, self.g1 = self._envelopes(self.s_out, s, cone=layer.cbs)
        self.envelope = self.envelopes[len(self.envelopes) // 2]  # the band-centre one (tests, diagnostics)
        # Reciprocity and coherent backscattering between the transmits' beams (`reciprocity`): the main
        # lobes' block of reversed-path pairs, with its own symmetric noise; outside it, independent noise.
        self.block: ReciprocalBlock | None = None
        self._block_env: list[np.ndarray] = []
        self._block_g1: np.ndarray | None = None
        if layer.cbs:
            try:
                self.block = ReciprocalBlock(self.s_out, spacings, s, w, el, self.freqs, c0)
            except ValueError:  # transmits off the grid (irregular sines): no reciprocal partners
                self.block = None
        self._block_gain: np.ndarray | None = None
        # The angular memory effect (`memory`, eq. M1): the noise correlated under a common tilt of input and
        # output, D_eff at the age of a normally incident path at each time sample, k at the band's centre.
        self._memory: MemoryKernel | None = None
        self._memory_block: MemoryKernel | None = None
        if layer.memory:
            kc2 = (2 * np.pi * band.centre / c0) ** 2
            d_eff = effective_spread(
                self._t - 2 * layer.z_surface / c0, float(layer.ls_at(band.centre)), v, dim, a_g2(aperture_radius)
            )

            def beta(delta: float) -> np.ndarray:
                return kc2 * delta**2 * d_eff

            steps = lattice_steps(s, spacings)
            self._memory = grid_kernel(axes, keep, spacings, s, steps, beta)
            if self.block is not None:
                self._memory_block = block_kernel(self.block.m_inputs, spacings, steps, beta)
                self._block_gain = block_energy_gain(el, spacings, self.block.m_inputs, steps, beta, np.sqrt(kc2))
        self._block_envelopes()
        # With the confocal notch, the Gaussian field is drawn out of the confocal subspace the focal return fills,
        # on the array's elements (`confocal_notch`, docs/design.md §6.6, F4).
        self._notch: ConfocalNotch | None = None
        # The measured reciprocity (R1–R2): the beams' sidelobes see outputs outside the block, whose noise is
        # independent, and break the symmetry the array measures; the field is projected back onto it.
        self._reciprocity: ElementReciprocity | None = None
        if layer.cbs and (layer.measured_reciprocity or layer.confocal_notch):
            self._reciprocity = ElementReciprocity(el, s, self.freqs, c0)
        self._envelope_width = max(1, round(KEPT_ENVELOPE_WINDOW / self.dt))
        if layer.confocal_notch:
            # from the surface to a normally incident echo at the period's end
            z_range = (layer.z_surface, 0.5 * c0 * (window.t0 + window.period))
            self._notch = ConfocalNotch(
                self.s_out,
                spacings,
                s,
                self.freqs,
                c0,
                dim,
                z_range,
                sensor=(self._project, self._adjoint),
                time_grid=(self.n_bb, self._envelope_width),
                # The notch takes a symmetric part (a reflectivity's) out of the field and raises the share of the
                # antisymmetric remainder: the notched field is projected back onto the measured reciprocity.
                constraint=self._reciprocity,
            )
        self.state: np.ndarray | None = None
        self.block_state: np.ndarray | None = None
        self._frozen: tuple[np.ndarray, np.ndarray | None] | None = None
        self._phase = np.exp(-2j * np.pi * self.freqs * window.t0).astype(np.complex64)
        if layer.focal_return and layer.focal_return_excess:
            assert self.single is not None
            share = self._excess_share()
            self.single.scale_focal_return(share[None, :])
            # (F3) with the excess: a path's apparent depth is half its length, s = 2d, so the share it moves out of
            # the Gaussian field is scaled by the excess at that depth
            assert fr_kept is not None
            s_grid, kept = fr_kept
            at_s = np.interp(0.5 * s_grid, self.single.depths, share, right=1.0)
            self._fr_kept = (s_grid, 1.0 - at_s[None, :] * (1.0 - kept))
            self.envelopes, self.g1 = self._envelopes(self.s_out, s, cone=layer.cbs)
            self.envelope = self.envelopes[len(self.envelopes) // 2]
            self._block_envelopes()

    def _block_envelopes(self) -> None:
        """The reciprocal block's envelopes over its pairs (and their g₁), with the memory effect's energy gain."""
        if self.block is None:
            return
        blk = self.block
        i, j = blk.pairs  # the pair (o_i, a_j), i ≤ j, stands for its reversed path (o_j, a_i) too
        env_b, self._block_g1 = self._envelopes(self.s_out[blk.rows[i]], blk.inputs[j], cone=False, paired=True)
        self._block_env = blk.envelopes(env_b)  # (n_pairs, 1, n_bb): T_ij = T_ji
        if self._block_gain is not None:
            self._block_env = [e / np.sqrt(self._block_gain).astype(np.float32) for e in self._block_env]

    def _excess_share(self) -> np.ndarray:
        """Per depth of the beads' grid, the share of the focal return that the Gaussian field does not already carry
        at the foci (docs/design.md §6.6, F5): e(d) = 1 − I_G(d)/I_F(d), clipped to [0, 1], I the mean confocal
        intensity (the matched filter of a reflectivity on the elements, F4's A^H, under the aperture) of the
        Gaussian field as drawn without the focal return and of the focal return alone, over EXCESS_DRAWS independent
        frames from fixed seeds (a table of the rig), smoothed over EXCESS_SMOOTH in depth."""
        assert self.single is not None
        ss, layer = self.single, self.layer
        z_s = layer.z_surface
        imager = ConfocalNotch(
            self.s_out,
            self._spacings,
            self.sines,
            self.freqs,
            self.c0,
            self.dim,
            (z_s, z_s + float(ss.depths[-1]) + ss.hz),
            sensor=(self._project, self._adjoint),
        )
        imager.prepare()
        under = self._under_aperture(imager)
        gauss, focal = np.zeros(imager.modes[-1]), np.zeros(imager.modes[-1])
        for n in range(EXCESS_DRAWS):  # independent draws (a frozen or slowly moving medium repeats its frames)
            probe = self.fork(np.random.default_rng(EXCESS_SEED + n))
            assert probe.single is not None
            probe._advance()
            aw = probe.multiple_spectrum() * self.weights[:, None, None]
            gauss += _depth_profile(imager, probe._reciprocal(self._project(aw)), under)
            assert probe.single.state is not None
            probe.single.state[...] = 0  # the focal return alone
            fr = project_plane_waves(
                probe.single.spectrum(), self.freqs, self.c0, self.elements, ss.s_out, ss.axes, ss.keep
            )
            focal += _depth_profile(imager, probe._reciprocal(fr), under)
        z = imager.depths - z_s
        width = max(1, round(EXCESS_SMOOTH / imager.hz))
        kernel = np.ones(width) / width
        gauss_s = np.convolve(gauss, kernel, mode="same")
        focal_s = np.convolve(focal, kernel, mode="same")
        share = np.clip(1.0 - gauss_s / np.maximum(focal_s, 1e-300), 0.0, 1.0)
        return np.interp(ss.depths, z, share)

    def _under_aperture(self, imager: ConfocalNotch) -> np.ndarray:
        """The imager's lateral pixels under the array's aperture (a boolean mask over its lateral modes)."""
        axes = []
        for d, h in enumerate(imager.h):
            n = imager.modes[d]
            x = (np.arange(n) - n // 2) * h
            half = 0.5 * float(np.ptp(self.elements[:, d]))
            axes.append(np.abs(x) <= half)
        if self.dim == 3:
            return axes[0][:, None] & axes[1][None, :]
        return axes[0]

    @classmethod
    def cached(
        cls,
        layer: ScatteringLayer,
        elements: np.ndarray,
        sines: np.ndarray,
        window: TimeWindow,
        band: Band,
        c0: float,
        dim: int,
        aperture_radius: float,
        rng: np.random.Generator,
    ) -> DiffuseBackground:
        """As the constructor, but the tables (which do not depend on `rng`) are shared with an earlier
        background of the same medium, rig, window and band when one is kept (`CACHED_BACKGROUNDS`):
        the frames are those a freshly built background would give with `rng`."""
        el, s = np.asarray(elements, dtype=np.float64), np.asarray(sines, dtype=np.float64)
        rig = (layer, el, s, window, band, float(c0), dim, float(aperture_radius))
        key = hashlib.sha256(pickle.dumps(rig)).hexdigest()
        tpl = _CACHE.get(key)
        if tpl is None:
            tpl = _CACHE[key] = cls(*rig, np.random.default_rng(0))
            while len(_CACHE) > CACHED_BACKGROUNDS:
                _CACHE.popitem(last=False)
        _CACHE.move_to_end(key)
        return tpl.fork(rng)

    def fork(self, rng: np.random.Generator) -> DiffuseBackground:
        """A background sharing this one's tables (read-only) with its own draws from `rng` (`restart`); the
        copies share the beads' NUFFT plans behind one lock (`SingleScatteringField.prepare`)."""
        new = copy.copy(self)
        if self.single is not None:
            self.single.prepare()
            new.single = copy.copy(self.single)
        if self._notch is not None:
            self._notch.prepare()
        new.restart(rng)
        return new

    def restart(self, rng: np.random.Generator) -> None:
        """Start the frames again from `rng` (as a background built with it), keeping the geometry and the
        envelopes, which do not depend on the draws."""
        self.rng = rng
        if self.single is not None:
            self.single.rng, self.single.state, self.single.fr_state = _beads_stream(rng), None, None
        self.state = self.block_state = self._frozen = None

    def _envelopes(
        self, s_out: np.ndarray, sines: np.ndarray, cone: bool, paired: bool = False
    ) -> tuple[list[np.ndarray], np.ndarray | None]:
        """Per sub-band, the noise's envelope √⟨M²⟩ of every pair (s_out[o], sines[θ]) on the baseband time
        grid (N_o, N_θ, n_bb) float32 — each direction's share of the halo and the weights' normalisation
        included, times √(1 + cone) when `cone` — and the frame-to-frame correlation g₁ (None if frozen).
        `paired`: only the pairs (s_out[n], sines[n]), (n, 1, n_bb)."""
        layer, dim, c0, t = self.layer, self.dim, self.c0, self._t
        band = self.band
        at_i = _pair_axes(paired)
        geo = None
        if layer.angular == "halo":
            geo = HaloGeometry(layer, s_out, sines, self._aperture_radius, dim, c0, paired=paired)
            tau = geo.age(t, float(layer.ls_at(band.centre)))
        else:
            t_on = layer.z_surface * (cosines(sines)[at_i] + cosines(s_out)[:, None]) / c0  # (N_o, N_θ)
            tau = (t[None, None, :] - t_on[:, :, None]).astype(np.float32)
        orders_from = 2 if layer.single_scattering == "field" else 1
        tab = np.linspace(0.0, max(float(tau.max()), 1e-9), 4096)
        sep2 = np.sum((s_out[:, None, :] + sines[at_i]) ** 2, axis=2)  # |s_o + s_θ|², (N_o, N_θ)
        envelopes: list[np.ndarray] = []
        for fc in self.centres:
            lay = layer.at_frequency(float(fc))
            # ⟨M²⟩ per unit pulse energy: unit-density white noise shaped by this envelope and filtered by
            # S(f) has variance envelope² · E_s = ⟨M²⟩. Tabulated in τ, then interpolated.
            if geo is None:
                rate = lay.intensity(tab, c0, self._aperture_radius, dim, pulse_energy=1.0, orders_from=orders_from)
            else:
                rate = lay.exitance(tab, c0, self._aperture_radius, dim, orders_from=orders_from)
            if self._fr_kept is not None:  # the focal return's share of the energy left out (F3)
                s_grid, kept = self._fr_kept
                rate = rate * np.interp(self._v * tab, s_grid, kept[len(envelopes)])
            env = np.interp(tau, tab, np.sqrt(np.maximum(rate, 0.0)), left=0.0).astype(np.float32)
            if geo is not None:  # each direction's share of the halo, the weights' normalisation divided out
                env *= np.sqrt(geo.share(tau, lay.ls, self._cell, layer.cbs) * np.float32(self._norm2))
            if cone:
                kc = 2 * np.pi * fc / c0
                dps = (lay.ls / dim) * self._v * np.maximum(tau, 0.0)  # D's
                if geo is not None:  # beams of the aperture bound the endpoints' separation (HaloGeometry)
                    dps = dps * np.float32(geo.a_g2) / (np.float32(geo.a_g2) + 4 * dps)
                env *= np.sqrt(1.0 + np.exp(-(kc**2) * sep2[:, :, None] * dps)).astype(np.float32)
            envelopes.append(env)
        g1 = None
        if layer.frame_displacement > 0:
            corr = layer.at_frequency(band.centre).correlation_per_frame(tab, c0, band.centre)
            g1 = np.interp(tau, tab, corr).astype(np.float32)
        return envelopes, g1

    def _white(self, shape: tuple[int, ...]) -> np.ndarray:
        """Complex white noise of unit spectral density on the baseband grid (E|ξ|² = 1/Δ)."""
        sig = np.float32(np.sqrt(0.5 / self.dt))
        out = np.empty(shape, dtype=np.complex64)
        out.real = self.rng.standard_normal(shape, dtype=np.float32) * sig
        out.imag = self.rng.standard_normal(shape, dtype=np.float32) * sig
        return out

    def _noise(self) -> np.ndarray:
        """The outputs' noise (N_o, N_θ, n_bb): independent, or correlated under common tilts (`memory`)."""
        if self._memory is not None:
            return self._memory.draw(lambda shape: self._white(shape + (self.n_bb,)))
        return self._white((self.n_o, self.n_i, self.n_bb))

    def _block_noise(self) -> np.ndarray:
        """The reciprocal block's noise over its pairs i ≤ j (n_pairs, 1, n_bb): T_ji is T_ij (`reciprocity`);
        with the memory effect T_ij = (X_ij + X_ji)/√2 off the diagonal and X_ii on it (unit variance, as the
        independent draw, so that the envelopes' √2 there is the retro-reflected wave's doubling in both cases),
        X correlated along common tilts (`memory`)."""
        assert self.block is not None
        if self._memory_block is not None:
            x = self._memory_block.draw(lambda shape: self._white(shape + (self.n_bb,)))
            i, j = self.block.pairs
            packed = (x[i, j] + x[j, i]) * np.float32(np.sqrt(0.5))
            packed[self.block.diagonal] *= np.float32(np.sqrt(0.5))  # (2 X_ii)/√2 → X_ii
            return packed[:, None, :]
        return self._white((self.block.n_pairs, 1, self.n_bb))

    def _project(self, aw: np.ndarray) -> np.ndarray:
        """M(f, u, θ) = Σ_o aw(o, θ, f) e^{−ik s_o·u} on the multiple-scattering grid."""
        return project_plane_waves(aw, self.freqs, self.c0, self.elements, self.s_out, self._axes, self._keep)

    def _adjoint(self, m: np.ndarray) -> np.ndarray:
        """The adjoint of `_project`: aw(o, θ, f) = Σ_u M(f, u, θ) e^{+ik s_o·u}."""
        return adjoint_plane_waves(m, self.freqs, self.c0, self.elements, self.s_out, self._axes, self._keep)

    def _shaped(self, state: np.ndarray, envelopes: list[np.ndarray]) -> np.ndarray:
        """Envelope-shaped noise, Fourier-transformed onto the band bins, sub-bands blended."""
        spec = np.zeros(state.shape[:2] + (self.freqs.size,), dtype=np.complex64)
        for env, wts in zip(envelopes, self.blend, strict=True):
            used = wts > 0
            part = sfft.fft(state * env, axis=2, workers=-1)[:, :, : self.freqs.size]
            spec[:, :, used] += part[:, :, used] * (wts[used] * self.dt).astype(np.float32)
        spec *= self._phase[None, None, :]
        return spec

    def multiple_spectrum(self) -> np.ndarray:
        """A_MS(o, θ, f) of the current noise state (`_advance`); the reciprocal block's outputs mix their
        lobes' pairs (`reciprocity.ReciprocalBlock.mix`)."""
        assert self.state is not None
        spec = self._shaped(self.state, self.envelopes)
        if self.block is not None:
            assert self.block_state is not None
            spec[self.block.rows] = self.block.mix(self._shaped(self.block_state, self._block_env))
        return spec

    @staticmethod
    def _evolve(state: np.ndarray, g1: np.ndarray, fresh: np.ndarray) -> np.ndarray:
        """ξ_n = g₁ ξ_{n−1} + √(1 − g₁²) ξ'_n, in place."""
        fresh *= np.sqrt(np.maximum(np.float32(0), np.float32(1) - g1 * g1))
        state *= g1
        state += fresh
        return state

    def _advance(self) -> None:
        """Draw the first noise state, or evolve it by one frame (the block's and the beads' alike)."""
        if self.state is None:
            self.state = self._noise()
        elif self.g1 is not None:
            self.state = self._evolve(self.state, self.g1, self._noise())
            if self.block_state is not None and self._block_g1 is not None:
                self.block_state = self._evolve(self.block_state, self._block_g1, self._block_noise())
        if self.block is not None and self.block_state is None:
            self.block_state = self._block_noise()
        if self.single is not None:
            self.single.advance()

    def skip(self) -> None:
        """Advance one frame without computing it: the same random draws as `next`, so the frames after
        are those of a sequential run (a frozen medium computes its one realisation)."""
        if self.g1 is None:
            self.next()
        else:
            self._advance()

    def _reciprocal(self, m: np.ndarray) -> np.ndarray:
        """One order on the elements (N_f, N_u, N_θ) projected onto the measured reciprocity (R1–R2) with its time
        envelope kept (`keep_envelope`: only its place in the data space changes); as it is without the projection."""
        if self._reciprocity is None:
            return m
        return keep_envelope(m, self._reciprocity(m), 0, self.n_bb, self._envelope_width)

    def next(self) -> np.ndarray:
        """Advance one frame and return V (N_f, N_u, N_θ) complex64 on the band bins: `next_orders` summed.

        A medium with frame_displacement = 0 is frozen: every frame repeats the first realisation.
        """
        multiple, single = self.next_orders()
        return multiple + single if single is not None else multiple.copy()

    def next_orders(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Advance one frame and return its two parts apart, each (N_f, N_u, N_θ) complex64: the Gaussian field
        (the orders it carries) and the beads' single scattering (None without single_scattering="field")."""
        if self._frozen is not None:
            return self._frozen
        self._advance()
        aw = self.multiple_spectrum() * self.weights[:, None, None]
        # the notch applies the measured reciprocity itself, before restoring the field's envelope
        multiple = self._notch(aw) if self._notch is not None else self._reciprocal(self._project(aw))
        single = None
        if self.single is not None:  # on its own, finer grid (single_scattering.output_grid)
            ss = self.single
            single = project_plane_waves(ss.spectrum(), self.freqs, self.c0, self.elements, ss.s_out, ss.axes, ss.keep)
            single = self._reciprocal(single)  # the first order's model (its beams) is not exactly reciprocal either
        if self.g1 is None:
            self._frozen, self.state, self.block_state = (multiple, single), None, None
        return multiple, single


#: The confocal notch, and the measured reciprocity without it, keep the Gaussian field's energy per time, averaged
#: over this window (s; about a pulse length: the transport envelope varies over microseconds; docs/design.md §6.6).
KEPT_ENVELOPE_WINDOW = 0.5e-6

#: The focal return's excess (`focal_return_excess`, F5): frames drawn from a fixed seed to measure it, and the depth
#: over which it is smoothed (m; about a pulse length).
EXCESS_DRAWS = 2
EXCESS_SEED = 20261207
EXCESS_SMOOTH = 1e-3


def _depth_profile(imager: ConfocalNotch, y: np.ndarray, under: np.ndarray) -> np.ndarray:
    """The mean confocal intensity by depth of the imager's grid of y on the elements (N_f, N_u, N_θ): |A^H y|²
    (F4's matched filter) averaged over the lateral pixels `under`."""
    image = np.abs(imager.adjoint(y)) ** 2
    return image[under].mean(axis=0)


#: Walks drawn for the focal return's depth profile (`focal_return_tables`), from a fixed seed: a table of the
#: rig, not a draw of the frame (its Monte-Carlo scatter is a few % per depth cell; docs/design.md §6.6).
FOCAL_WALKS = 40000
FOCAL_SEED = 20261205
#: Path-length bins of the Gaussian field's kept energy share (`focal_return_tables`).
FOCAL_LENGTH_BINS = 400


def focal_return_tables(
    layer: ScatteringLayer,
    single: SingleScatteringField,
    elements: np.ndarray,
    sines: np.ndarray,
    centres: np.ndarray,
    c0: float,
    dim: int,
    window: TimeWindow,
) -> tuple[np.ndarray, np.ndarray | None, tuple[np.ndarray, np.ndarray], np.ndarray | None, np.ndarray | None]:
    """The focal return on the beads' grid (docs/design.md §6.6): its variance (n_sub, nz), g₁ per depth (None if
    frozen; a path of length 2d, DWS), the share of the energy the Gaussian field keeps by path length (s grid,
    (n_sub, N_s)), the lighting depth per grid depth (None without the rig's grid of sines) and, with
    focal_return_pairs, the pairs' joint lateral separations by depth (`paths.focal_pairs`, F6; else None). The
    walks and the rig's foci of `focal_walks`, summed by `paths.focal_return` (or `paths.focal_pairs`)."""
    walks, s_grid, rig, span, aperture = focal_walks(layer, single, elements, sines, centres, c0, dim, window)
    args = (walks, single.depths, s_grid, centres, layer.ls_at(centres), layer.la, c0, span)
    sep: np.ndarray | None = None
    light: np.ndarray | None
    if layer.focal_return_pairs:
        if rig is None:
            raise ValueError("focal_return_pairs: expected transmits on a full grid of sines (the rig's foci, F2′)")
        var, kept, light, sep = focal_pairs(*args, aperture, layer.z_surface, rig, single.hx)
    else:
        var, kept, light = focal_return(*args, aperture, layer.z_surface, rig)
    g1 = None
    if layer.frame_displacement > 0:
        v = c0 if layer.energy_velocity is None else layer.energy_velocity
        g1 = layer.correlation_per_frame(2 * single.depths / v, c0, float(np.mean(centres))).astype(np.float32)
    return var, g1, (s_grid, kept), light, sep


def focal_walks(
    layer: ScatteringLayer,
    single: SingleScatteringField,
    elements: np.ndarray,
    sines: np.ndarray,
    centres: np.ndarray,
    c0: float,
    dim: int,
    window: TimeWindow,
) -> tuple[Paths, np.ndarray, FocalRig | None, np.ndarray, np.ndarray]:
    """What the focal return's tables sum (`focal_return_tables`): the walks in the layer (`paths.draw_paths`, first
    scatterings weighted by the incident extinction, FOCAL_WALKS from FOCAL_SEED), the path-length grid, the rig's
    foci (`FocalRig.from_grid`: None unless the sines form a grid), and per lateral axis the transmits' span of sines
    and the array's aperture (a focus needs ≥ 2 transmits along each)."""
    axes = 2 if dim == 3 else 1
    el, si = np.asarray(elements, dtype=np.float64), np.asarray(sines, dtype=np.float64)
    span, aperture = [], []
    for d in range(axes):
        u = np.unique(np.round(si[:, d], 9))
        if u.size < 2:
            raise ValueError(f"focal_return: expected at least 2 transmits along axis {'xy'[d]}, got {u.size}")
        span.append(float(np.ptp(u)) * u.size / (u.size - 1))  # N_θ Δs
        x = np.unique(np.round(el[:, d], 9))
        aperture.append(float(np.ptp(x)) * x.size / max(x.size - 1, 1))  # N_u × pitch
    depth_end = float(single.depths[-1])
    v = c0 if layer.energy_velocity is None else layer.energy_velocity
    s_end = max(v * (window.t0 + window.duration) - 2 * layer.z_surface * v / c0, 2 * depth_end)
    f_c = float(np.mean(centres))
    lext_c = float(layer.l_ext_at(f_c))
    walks = draw_paths(
        np.random.default_rng(FOCAL_SEED),
        dim,
        float(layer.ls_at(f_c)),
        FOCAL_WALKS,
        l_max=s_end,
        z_top=layer.z_surface,
        start_half_width=0.5 * layer.width if np.isfinite(layer.width) else 5e-3,
        start_depth=min(depth_end, layer.thickness),
        thickness=layer.thickness,
        half_width=0.5 * layer.width,
        start_decay=lext_c,
    )
    s_grid = np.linspace(0.0, s_end, FOCAL_LENGTH_BINS)
    # The rig's own transmits and beams (eq. F2′): the focal return lit as its ends are, where the sines form a grid.
    rig = FocalRig.from_grid(si, np.array(aperture), dim, np.array(single.beam_aperture), single.beam_wavelength)
    return walks, s_grid, rig, np.array(span), np.array(aperture)


def _beads_stream(rng: np.random.Generator) -> np.random.Generator:
    """The beads' single-scattering field's own generator: the background generator's first draw."""
    return np.random.default_rng(rng.integers(2**63))


def _separable_phases(
    k: np.ndarray, el: np.ndarray, axes: list[np.ndarray] | None, keep: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-axis phases e^{−ik u_x s_x} (f, ux, sx) and e^{−ik u_y s_y} (f, uy, sy) of a regular matrix array and an
    output grid given by its `axes` and `keep` mask, or None where the map is not separable."""
    grid = element_grid_axes(el) if axes is not None and len(axes) == 2 else None
    if grid is None or axes is None or keep is None:
        return None
    (ux, uy), (sx, sy) = grid, axes
    px = np.exp(-1j * k[:, None, None] * ux[None, :, None] * sx[None, None, :]).astype(np.complex64)
    py = np.exp(-1j * k[:, None, None] * uy[None, :, None] * sy[None, None, :]).astype(np.complex64)
    return px, py


def project_plane_waves(
    aw: np.ndarray,
    freqs: np.ndarray,
    c0: float,
    elements: np.ndarray,
    s_out: np.ndarray,
    axes: list[np.ndarray] | None = None,
    keep: np.ndarray | None = None,
) -> np.ndarray:
    """M(f, u, θ) = Σ_o aw(o, θ, f) e^{−ik s_o·u} for weighted amplitudes aw (N_o, N_θ, N_f), complex64.

    Separable (x then y) for a regular matrix array and an output grid given by its `axes` and `keep` mask
    (x-major), by frequency recursion otherwise.
    """
    k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
    n_f, n_i = k.size, aw.shape[1]
    el = np.asarray(elements, dtype=np.float64)
    phases = _separable_phases(k, el, axes, keep)
    if phases is not None and axes is not None:
        px, py = phases
        sx, sy = axes
        flat = np.zeros((sx.size * sy.size, n_i, n_f), dtype=np.complex64)
        flat[keep] = aw
        full = flat.reshape(sx.size, sy.size, n_i, n_f)
        g = np.transpose(full, (3, 1, 0, 2))  # (f, sy, sx, θ)
        g = np.matmul(px[:, None], g)  # (f, sy, ux, θ)
        g = np.matmul(py, g.reshape(n_f, sy.size, -1))  # (f, uy, ux·θ)
        return np.ascontiguousarray(g.reshape(n_f, el.shape[0], n_i), dtype=np.complex64)
    out = np.empty((n_f, el.shape[0], n_i), dtype=np.complex64)
    phase_u = el[:, :2] @ np.asarray(s_out, dtype=np.float64).T  # (N_u, N_o)
    dk = np.diff(k).mean() if n_f > 1 else 0.0
    step = np.exp(-1j * dk * phase_u).astype(np.complex64)
    p = None
    for m in range(n_f):
        if p is None or m % 32 == 0:
            p = np.exp(-1j * k[m] * phase_u).astype(np.complex64)
        out[m] = p @ aw[:, :, m]
        p *= step
    return out


def adjoint_plane_waves(
    m: np.ndarray,
    freqs: np.ndarray,
    c0: float,
    elements: np.ndarray,
    s_out: np.ndarray,
    axes: list[np.ndarray] | None = None,
    keep: np.ndarray | None = None,
) -> np.ndarray:
    """The adjoint of `project_plane_waves`: aw(o, θ, f) = Σ_u M(f, u, θ) e^{+ik s_o·u}, (N_o, N_θ, N_f) complex64."""
    k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
    n_f, n_u, n_i = m.shape
    el = np.asarray(elements, dtype=np.float64)
    phases = _separable_phases(k, el, axes, keep)
    if phases is not None and axes is not None:
        px, py = phases
        sx, sy = axes
        n_ux, n_uy = px.shape[1], py.shape[1]
        h = np.matmul(np.conj(np.transpose(py, (0, 2, 1))), m.reshape(n_f, n_uy, n_ux * n_i))  # (f, sy, ux·θ)
        h = np.matmul(np.conj(np.transpose(px, (0, 2, 1)))[:, None], h.reshape(n_f, sy.size, n_ux, n_i))
        full = np.transpose(h, (2, 1, 3, 0)).reshape(sx.size * sy.size, n_i, n_f)  # (sx·sy, θ, f)
        return np.ascontiguousarray(full[keep], dtype=np.complex64)
    out = np.empty((np.asarray(s_out).shape[0], n_i, n_f), dtype=np.complex64)
    phase_u = el[:, :2] @ np.asarray(s_out, dtype=np.float64).T  # (N_u, N_o)
    for j in range(n_f):
        out[:, :, j] = np.exp(1j * k[j] * phase_u).T.astype(np.complex64) @ m[j]
    return out


def _triangles(freqs: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Triangular (linear-interpolation) weights of each frequency between neighbouring centres; sum 1."""
    if centres.size == 1:
        return np.ones((1, freqs.size))
    w = np.zeros((centres.size, freqs.size))
    for j in range(centres.size):
        e = np.zeros(centres.size)
        e[j] = 1.0
        w[j] = np.interp(freqs, centres, e)
    return w
