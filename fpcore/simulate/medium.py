"""Strongly scattering half-space below a water layer: ballistic extinction, interface echo, and a
statistical multiple-scattering background for large 3D (and 2D) media.

Physics (paper Supplementary S1, S4; docs/design.md §6):

* **Extinction.** The coherent wave decays as ⟨ψ⟩ ∝ exp(ikz − z/(2ℓ_ext)), ℓ_ext = (1/ℓ_s + 1/ℓ_a)^{-1}
  (S1, eqs. ⟨ψ⟩(z, f) and ℓ_ext). A target's echo is multiplied by exp(−L_in/(2ℓ_ext)) on the way in
  (L_in = depth below the surface / c_θ) and by exp(−L_out/(2ℓ_ext)) on the way out (L_out = length of
  the straight ray from the target to the element below the surface), and by the interface
  transmission 1 − R² (pressure, both ways). The depth of an extended target is taken at its front
  face (``attenuation_depth="front"``: the specular cap and the waves that enter and leave through it)
  or at its centre (``"centre"``, the paper's depth convention in eq. (1)).
* **Interface.** The suspension surface z = z_s reflects R = (Z₁ − Z₀)/(Z₁ + Z₀):
  H = R_coh exp(−ik(s·u + 2 z_s c)) (image of the plane wave in the plane), with the coherent
  reflection of a rough surface (rms height σ_h, e.g. the bead radius) reduced by the Kirchhoff
  (Ament) factor R_coh = R exp(−2k²σ_h²c²).
* **Multiple-scattering background M** (S4: R = σ_T R_0 + M with M uncorrelated with the target), a
  Gaussian random field with a physical intensity envelope and the coherence of a diffuse field:

  - *time envelope*: a wave that spent a time τ in the medium (path s = v_E τ) returns the reflected
    flux density ρ(s) per unit path length. Default (``envelope="escape"``): order-of-scattering model
    for isotropic scattering (S1: transport mean free path = ℓ_s) where after each event the wave
    leaves towards the probe with probability 1/2; the n-th event happens after a Gamma(n, ℓ_s) path,
    so ρ(s) = Σ_n 2^{−n} Poisson(n−1; s/ℓ_s)/ℓ_s · e^{−s/ℓ_a} = e^{−s/(2ℓ_s)} e^{−s/ℓ_a}/(2ℓ_s) (total
    reflectance 1 without absorption). Its single-scattering share e^{−s/(2ℓ_s)} = e^{−z/ℓ_s} at
    s = 2z is the single-scattering rate behind the paper's law C_I ∝ exp(−z/ℓ_s) (main text eq. (1),
    Goïcoechea et al. 2024): a ballistic echo (∝ e^{−2z/ℓ_ext}) over this background falls as
    e^{−z/ℓ_s}. All orders, the single one included, are drawn as one Gaussian field (the medium's
    single scattering is then not focused like a speckle image; add Born points for that, as in
    ``lesion-marker``). ``envelope="diffusion"``: the half-space diffusion approximation with an
    extrapolated boundary (Patterson, Chance & Wilson 1989; z_e = 2ℓ_s/3),
    ρ(s) = z₁ (4π D' s³)^{-1/2} exp(−z₁²/(4D's)) e^{−s/ℓ_a}, z₁ = ℓ_s + z_e, D' = ℓ_s/3; its power-law
    tail makes the contrast fall faster than e^{−z/ℓ_s} (bench/validate_simulate.py prints both);
  - *level*: ρ is multiplied by the fraction of the diffuse halo (b² = a² + 4D's) still under the
    insonified aperture (radius a) and by the reception of that Lambertian halo at the array
    (standoff z_s, half-angle θ_d = atan(b/z_s)): the upgoing radiance L = M/π (3D) gives
    ⟨p²⟩/(ρc) = ∫L dΩ = 2(1 − cos θ_d) M (2D: L = M/2, θ_d M). With the exitance M = ρ(s) v_E × (pulse
    energy) and the transmission (1 − R²)² both ways: ⟨M²⟩ = gain · 2(1 − cos θ_d) ρ(s) v_E E_s (1 −
    R²)² (3D); ``gain`` (default 1) calibrates this radiative estimate;
  - *angle–age coupling and spatial speckle*: M is a sum of upgoing plane waves s_o (|s_o| ≲ s_d =
    sin θ_d) with independent random amplitudes; for transmit θ the wave s_o that spent τ in the
    medium reaches the array at t = z_s (c_θ + c_o)/c0 + τ, so obliquely arriving energy is younger
    and the confocal (time, angle) → depth mapping stays consistent with the age of the wave. The
    field on the array is thereby a speckle of grain ≈ λ/(2 s_d); transmits are independent (the
    angular memory effect of a diffusive medium, ~1/(k b), is far below the transmit spacing);
  - *frequency correlation*: each amplitude is white noise shaped by the envelope, so the
    correlation frequency is δf ≈ 1/(envelope duration) and N_f = Δf/δf grains fill the band (S4);
  - *frame-to-frame decorrelation*: the grains move by ⟨Δr²⟩^{1/2} between frames; a path of length s
    keeps the correlation g₁ = exp(−(s/ℓ_s) k_c² ⟨Δr²⟩/3) (diffusing-wave spectroscopy, Pine et
    al. 1988), applied as an AR(1) update of the noise, sample by sample in τ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from ..geometry import cosines
from .waves import Band, TimeWindow

__all__ = ["ScatteringLayer", "DiffuseBackground"]


@dataclass(frozen=True)
class ScatteringLayer:
    """Half-space z > z_surface of a scattering medium under water (the array at z = 0).

    ls, la: scattering and absorption mean free paths (m) at the band centre; density (kg/m³) and
    sound speed (m/s) of the effective medium for the interface echo; energy_velocity (m/s, default
    c0); frame_displacement: rms displacement of the scatterers between frames (m);
    envelope: "escape" (default) or "diffusion" (module doc); gain multiplies the background power.
    """

    z_surface: float
    ls: float
    la: float = np.inf
    density: float = 1000.0
    sound_speed: float = 1500.0
    energy_velocity: float | None = None
    frame_displacement: float = 0.0
    envelope: str = "escape"
    gain: float = 1.0
    attenuation_depth: str = "centre"
    roughness: float = 0.0

    def __post_init__(self) -> None:
        if self.envelope not in ("escape", "diffusion"):
            raise ValueError(f"envelope: expected 'escape' or 'diffusion', got {self.envelope!r}")
        if self.attenuation_depth not in ("centre", "front"):
            raise ValueError(f"attenuation_depth: expected 'centre' or 'front', got {self.attenuation_depth!r}")
        if not (self.ls > 0 and self.la > 0):
            raise ValueError("ls, la: expected positive mean free paths")

    @property
    def l_ext(self) -> float:
        """ℓ_ext = (1/ℓ_s + 1/ℓ_a)^{-1} (Supplementary S1, eq. ls)."""
        return 1.0 / (1.0 / self.ls + 1.0 / self.la)

    def reflection(self, rho0: float = 1000.0, c0: float = 1500.0) -> float:
        z0, z1 = rho0 * c0, self.density * self.sound_speed
        return (z1 - z0) / (z1 + z0)

    # -- ballistic legs --------------------------------------------------------------------------
    def reference_point(self, position: np.ndarray, diameter: float) -> np.ndarray:
        r = np.asarray(position, dtype=np.float64).copy()
        if self.attenuation_depth == "front":
            r[2] -= 0.5 * diameter
        return r

    def attenuation_in(self, ref: np.ndarray, sines: np.ndarray) -> np.ndarray:
        """exp(−L_in/(2ℓ_ext)) per transmit, L_in = (z − z_s)/c_θ (N_θ,)."""
        depth = max(0.0, float(ref[2]) - self.z_surface)
        return np.exp(-depth / cosines(sines) / (2 * self.l_ext))

    def attenuation_out(self, ref: np.ndarray, elements: np.ndarray) -> np.ndarray:
        """exp(−L_out/(2ℓ_ext)) per element, L_out = part of the straight ray below z_s (N_u,)."""
        depth = max(0.0, float(ref[2]) - self.z_surface)
        dist = np.linalg.norm(np.asarray(elements, float) - np.asarray(ref, float)[None, :], axis=1)
        return np.exp(-dist * depth / max(float(ref[2]), 1e-12) / (2 * self.l_ext))

    def attenuate(
        self,
        h: np.ndarray,
        position: np.ndarray,
        diameter: float,
        elements: np.ndarray,
        sines: np.ndarray,
        rho0: float = 1000.0,
        c0: float = 1500.0,
    ) -> np.ndarray:
        """Apply both legs and the interface transmission 1 − R² to a target's H (N_f, N_u, N_θ)."""
        ref = self.reference_point(position, diameter)
        if ref[2] <= self.z_surface:
            return h
        w = np.outer(self.attenuation_out(ref, elements), self.attenuation_in(ref, sines))
        w *= 1.0 - self.reflection(rho0, c0) ** 2
        return h * w.astype(np.float32)[None, :, :]

    # -- interface --------------------------------------------------------------------------------
    def interface_echo(
        self, elements: np.ndarray, sines: np.ndarray, freqs: np.ndarray, c0: float, rho0: float = 1000.0
    ) -> np.ndarray:
        """H = R exp(−ik(s·u + 2 z_s c)) (N_f, N_u, N_θ) complex64."""
        k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
        c = cosines(sines)
        path = np.asarray(elements, float)[:, :2] @ np.asarray(sines, float).T + 2 * self.z_surface * c[None, :]
        r = self.reflection(rho0, c0) * np.exp(-2 * (k[:, None] * self.roughness * cosines(sines)[None, :]) ** 2)
        return (r[:, None, :] * np.exp(-1j * k[:, None, None] * path[None, :, :])).astype(np.complex64)

    # -- multiple-scattering envelope -------------------------------------------------------------
    def reflectance_density(self, s: np.ndarray) -> np.ndarray:
        """ρ(s) per unit path length (1/m) of the multiply scattered flux (module doc)."""
        s = np.maximum(np.asarray(s, dtype=np.float64), 0.0)
        ls, la = self.ls, self.la
        absorb = np.exp(-s / la)
        if self.envelope == "escape":
            return np.exp(-s / (2 * ls)) * absorb / (2 * ls)
        z1 = ls * (1 + 2.0 / 3.0)
        dp = ls / 3.0
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = z1 / np.sqrt(4 * np.pi * dp * s**3) * np.exp(-(z1**2) / (4 * dp * s))
        return np.where(s > 0, rho, 0.0) * absorb

    def halo_radius2(self, s: np.ndarray, aperture_radius: float) -> np.ndarray:
        return aperture_radius**2 + 4 * (self.ls / 3.0) * np.maximum(s, 0.0)

    def intensity(
        self, tau: np.ndarray, c0: float, aperture_radius: float, dim: int, pulse_energy: float
    ) -> np.ndarray:
        """⟨M(t)²⟩ (relative to the incident pulse peak²) τ = t − t_on after the surface echo."""
        v = c0 if self.energy_velocity is None else self.energy_velocity
        s = v * np.maximum(np.asarray(tau, dtype=np.float64), 0.0)
        b2 = self.halo_radius2(s, aperture_radius)
        spread = b2 - aperture_radius**2
        cos_d = self.z_surface / np.sqrt(b2 + self.z_surface**2)  # halo edge seen from the array
        with np.errstate(divide="ignore", invalid="ignore"):
            if dim == 3:
                lateral = np.where(spread > 0, -np.expm1(-(aperture_radius**2) / spread), 1.0)
                reception = 2.0 * (1.0 - cos_d)
            else:
                from scipy.special import erf

                lateral = np.where(spread > 0, erf(aperture_radius / np.sqrt(np.maximum(spread, 1e-30))), 1.0)
                reception = np.arccos(cos_d)
        t_r = 1.0 - self.reflection() ** 2
        out = self.gain * reception * self.reflectance_density(s) * v * pulse_energy * lateral * t_r**2
        return np.where(np.asarray(tau) > 0, out, 0.0)

    def correlation_per_frame(self, tau: np.ndarray, c0: float, f_c: float) -> np.ndarray:
        """g₁ between consecutive frames for waves that spent τ in the medium (DWS, module doc)."""
        v = c0 if self.energy_velocity is None else self.energy_velocity
        s = v * np.maximum(np.asarray(tau, dtype=np.float64), 0.0)
        kc = 2 * np.pi * f_c / c0
        return np.exp(-(s / self.ls) * kc**2 * self.frame_displacement**2 / 3.0)


class DiffuseBackground:
    """Frame generator of the multiple-scattering spectrum V(f, u, θ) (dimensionless, like a target's H).

    The field is built as upgoing plane waves leaving the suspension (module doc), one random
    amplitude A(o, θ, t) per output direction s_o (|s_o| ≲ s_d, on a grid whose spatial period
    λ_min/Δs exceeds the aperture) and transmit θ. A plane wave o launched by transmit θ that spent a
    time τ in the medium arrives at the array at t = z_s (c_θ + c_o)/c0 + τ (lateral phases referred to
    the array centre), so its age — and the envelope √⟨M²⟩(τ) it carries — depends on its direction:
    energy arriving obliquely at a given time is younger. This keeps the confocal mapping
    (time, angle) → depth consistent with the age of the diffuse wave.

    Construction per frame: complex white noise ξ(o, θ, t_n) on a baseband time grid (spacing
    Δ = period/n_bb, E|ξ|² = 1/Δ, i.e. unit spectral density), multiplied by the envelope, Fourier
    transformed onto the band bins, and projected to the elements, M(u, θ, f) = Σ_o w_o A e^{−ik s_o·u}
    (taper w_o, Σ w_o² = 1). Frames evolve by ξ_n = g₁ ξ_{n−1} + √(1 − g₁²) ξ'_n with g₁(τ) (DWS).
    The RF background is S(f)·V(f); it is statistically independent of every target.
    """

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
        b = float(np.sqrt(layer.halo_radius2(np.array(max(mid, 0.0) * v), aperture_radius)))
        self.s_d = b / np.hypot(b, layer.z_surface)
        # Direction grid: spatial period λ_min/Δs ≥ 1.2 × the array extent.
        span = np.ptp(el[:, :2], axis=0) + 1e-12
        lam_min = c0 / band.support[1]
        s_cut = min(1.15 * self.s_d, 0.98)
        axes = []
        for d in range(2 if dim == 3 else 1):
            ds = lam_min / (1.2 * max(span[d], lam_min))
            m = int(np.floor(s_cut / ds))
            axes.append(np.arange(-m, m + 1) * ds)
        if dim == 3:
            sx, sy = np.meshgrid(axes[0], axes[1], indexing="ij")
            so = np.stack([sx.ravel(), sy.ravel()], axis=1)
        else:
            so = np.stack([axes[0], np.zeros_like(axes[0])], axis=1)
        smag = np.hypot(so[:, 0], so[:, 1])
        keep = smag < s_cut
        self.s_out = so[keep]
        self._axes = axes
        self._keep = keep
        self._grid = self._element_grid(el) if dim == 3 else None
        x = np.clip((smag[keep] / self.s_d - 0.85) / 0.3, 0.0, 1.0)
        w = 0.5 + 0.5 * np.cos(np.pi * x)
        self.weights = (w / np.sqrt(np.sum(w**2))).astype(np.float32)
        self.n_o = self.s_out.shape[0]
        c_o = cosines(self.s_out)
        t = window.t0 + np.arange(self.n_bb) * self.dt
        t_on = layer.z_surface * (cosines(s)[None, :] + c_o[:, None]) / c0  # (N_o, N_θ)
        tau = (t[None, None, :] - t_on[:, :, None]).astype(np.float32)
        # ⟨M²⟩ per unit pulse energy: unit-density white noise shaped by this envelope and filtered by
        # S(f) has variance envelope² · E_s = ⟨M²⟩. Tabulated in τ, then interpolated.
        tab = np.linspace(0.0, max(float(tau.max()), 1e-9), 4096)
        rate = layer.intensity(tab, c0, aperture_radius, dim, pulse_energy=1.0)
        self.envelope = np.interp(tau, tab, np.sqrt(rate), left=0.0).astype(np.float32)
        self.g1 = (
            np.interp(tau, tab, layer.correlation_per_frame(tab, c0, band.centre)).astype(np.float32)
            if layer.frame_displacement > 0
            else None
        )
        self.state: np.ndarray | None = None
        self._frozen: np.ndarray | None = None
        self._phase = np.exp(-2j * np.pi * self.freqs * window.t0).astype(np.complex64)

    def _noise(self) -> np.ndarray:
        shape = (self.n_o, self.n_i, self.n_bb)
        sig = np.float32(np.sqrt(0.5 / self.dt))
        xi = self.rng.standard_normal(shape, dtype=np.float32) * sig
        out = np.empty(shape, dtype=np.complex64)
        out.real = xi
        out.imag = self.rng.standard_normal(shape, dtype=np.float32) * sig
        return out

    @staticmethod
    def _element_grid(el: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(x, y) axes if the elements form a full x-fastest grid (separable projection), else None."""
        xs, ys = np.unique(el[:, 0]), np.unique(el[:, 1])
        if xs.size * ys.size != el.shape[0]:
            return None
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        if np.allclose(el[:, 0], xx.ravel()) and np.allclose(el[:, 1], yy.ravel()):
            return xs, ys
        return None

    def _project(self, a: np.ndarray) -> np.ndarray:
        """M(f, u, θ) = Σ_o w_o A(o, θ, f) e^{−ik s_o·u} for A (N_o, N_θ, N_f).

        Separable (x then y) for a regular matrix array, by frequency recursion otherwise.
        """
        k = 2 * np.pi * self.freqs / self.c0
        n_f = self.freqs.size
        aw = a * self.weights[:, None, None]
        if self._grid is not None:
            ux, uy = self._grid
            sx, sy = self._axes
            full = np.zeros((sx.size * sy.size, self.n_i, n_f), dtype=np.complex64)
            full[self._keep] = aw
            full = full.reshape(sx.size, sy.size, self.n_i, n_f)
            px = np.exp(-1j * k[:, None, None] * ux[None, :, None] * sx[None, None, :]).astype(np.complex64)
            py = np.exp(-1j * k[:, None, None] * uy[None, :, None] * sy[None, None, :]).astype(np.complex64)
            g = np.transpose(full, (3, 1, 0, 2))  # (f, sy, sx, θ)
            g = np.matmul(px[:, None], g)  # (f, sy, ux, θ)
            g = np.matmul(py, g.reshape(n_f, sy.size, -1))  # (f, uy, ux·θ)
            return np.ascontiguousarray(g.reshape(n_f, self.n_u, self.n_i), dtype=np.complex64)
        out = np.empty((n_f, self.n_u, self.n_i), dtype=np.complex64)
        phase_u = self.elements[:, :2] @ self.s_out.T  # (N_u, N_o)
        dk = np.diff(k).mean() if n_f > 1 else 0.0
        step = np.exp(-1j * dk * phase_u).astype(np.complex64)
        p = None
        for m in range(n_f):
            if p is None or m % 32 == 0:
                p = np.exp(-1j * k[m] * phase_u).astype(np.complex64)
            out[m] = p @ aw[:, :, m]
            p *= step
        return out

    def next(self) -> np.ndarray:
        """Advance one frame and return V (N_f, N_u, N_θ) complex64 on the band bins.

        A medium with frame_displacement = 0 is frozen: every frame repeats the first realisation.
        """
        if self._frozen is not None:
            return self._frozen
        if self.state is None:
            self.state = self._noise()
        elif self.g1 is not None:
            xi = self._noise()
            xi *= np.sqrt(np.maximum(np.float32(0), np.float32(1) - self.g1 * self.g1))
            self.state *= self.g1
            self.state += xi
        v = self.state * self.envelope
        spec = sfft.fft(v, axis=2, workers=-1)[:, :, : self.freqs.size] * np.float32(self.dt)
        spec *= self._phase[None, None, :]
        out = self._project(spec)
        if self.g1 is None:
            self._frozen, self.state = out, None
        return out
