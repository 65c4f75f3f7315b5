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
    extrapolated boundary (Patterson, Chance & Wilson 1989; z_e = 2ℓ_s/3 in 3-D, πℓ_s/4 in 2-D),
    ρ(s) = z₁ (4π D' s³)^{-1/2} exp(−z₁²/(4D's)) e^{−s/ℓ_a}, z₁ = ℓ_s + z_e, D' = ℓ_s/d in d dimensions
    (a slab of finite ``thickness`` adds the images of its bottom, `reflectance_density`); its power-law
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
    angular memory effect, ~1/(k × the halo's width), is neglected — measured against Foldy–Lax it is not
    negligible: a common tilt of 1 transmit step (0.03) keeps a correlation of 0.5–0.8 over the first 25 µs
    in 2-D, and the confocal background comes out ≈ 2.5 dB low; README, docs/design.md §6.4; ``memory=True``
    adds it, `memory`, §6.5: it reproduces Foldy–Lax's correlation in 2-D and closes 0.5 dB of that). This is
    ``angular="uniform"``; ``angular="halo"`` gives each direction the share of the halo that its ray
    through the array sees, at that ray's delay, and the level there (`diffuse.HaloGeometry`; the
    sinking scenarios' default, validated against Foldy–Lax: docs/design.md §6.3);
  - *frequency correlation*: each amplitude is white noise shaped by the envelope, so the
    correlation frequency is δf ≈ 1/(envelope duration) and N_f = Δf/δf grains fill the band (S4);
  - *frame-to-frame decorrelation*: the grains move by ⟨Δr²⟩^{1/2} between frames; a path of length s
    keeps the correlation g₁ = exp(−(s/ℓ_s) k_c² ⟨Δr²⟩/3) (diffusing-wave spectroscopy, Pine et
    al. 1988), applied as an AR(1) update of the noise, sample by sample in τ.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..geometry import cosines

__all__ = ["ScatteringLayer", "DiffuseBackground"]


def first_order_reflectance(s: np.ndarray, ls: float, dim: int) -> np.ndarray:
    """ρ₁(s) = κ_d e^{−s/ℓ_s}/ℓ_s: the single-scattering flux per unit path of a normally incident plane wave
    on a lossless half-space of isotropic scatterers (`ScatteringLayer.reflectance_density`); its integral
    κ₃ = (1 − ln 2)/2 (3D), κ₂ = (π − 2)/(2π) (2D) is the first order's share of the reflected flux."""
    kappa = (1.0 - np.log(2.0)) / 2.0 if dim == 3 else (np.pi - 2.0) / (2.0 * np.pi)
    return kappa * np.exp(-np.asarray(s, dtype=np.float64) / ls) / ls


@dataclass(frozen=True)
class ScatteringLayer:
    """Half-space z > z_surface of a scattering medium under water (the array at z = 0).

    ls, la: scattering and absorption mean free paths (m) at the band centre; density (kg/m³) and
    sound speed (m/s) of the effective medium for the interface echo; energy_velocity (m/s, default
    c0); frame_displacement: rms displacement of the scatterers between frames (m);
    envelope: "escape" (default) or "diffusion" (module doc); gain multiplies the background power.
    Transport additions (`diffuse` module doc, docs/design.md §6.3): ls_exponent, f_ref, f_cross give
    ℓ_s(f) (`ls_at`); single_scattering "envelope" (all orders in the Gaussian field) or "field" (the first
    order as a focused speckle, `single_scattering`); cbs: reciprocity and coherent backscattering;
    thickness: the medium's thickness below the surface (m; inf: a half-space), which bounds the diffusion
    envelope (`reflectance_density`); width: its lateral extent (m; |x|, |y| ≤ width/2 about the array's
    axis; inf: unbounded), whose sides let the diffuse halo out (`side_losses`); angular: "uniform" (every
    output direction carries the same envelope, timed at the array's centre) or "halo" (each direction sees
    the halo where its ray through the array meets the surface, at that ray's delay: `diffuse` module doc);
    focal_return: the orders ≥ 2 whose ends the rig sees as one point, drawn as a second reflectivity on the beads'
    grid at their apparent depth (`paths.focal_return`, docs/design.md §6.6; needs single_scattering="field");
    confocal_notch: with the focal return, the Gaussian field drawn out of the confocal subspace on the array's
    elements, where the focal return already counts every path's share (`confocal_notch`, F4; docs/design.md §6.6);
    focal_return_shallow: with the focal return, draw it only down to the beads' own depth (their echo down by e^{−12};
    docs/design.md §6.6), the deeper orders left whole in the Gaussian field — no grid to the record's end;
    focal_return_excess: with the focal return, on the beads' own depths as focal_return_shallow, draw only the part of
    its confocal return that the Gaussian field does not already carry at the foci (measured once per rig, F5 of
    docs/design.md §6.6), the Gaussian field left whole otherwise, no notch;
    focal_return_pairs: with the focal return, draw it as two-point paths (F6 of docs/design.md §6.6): each path's
    ends kept apart laterally on the beads' grid (its depths collapsed to the apparent one), its reversed partner in
    phase, its defocus in the variance; the Gaussian field keeps the paths' share the pairs do not carry; no notch,
    no excess;
    measured_reciprocity: with cbs, the background (both orders) projected onto the fields whose element-basis matrix
    is symmetric as the transmits measure it (`reciprocity.ElementReciprocity`, R1–R2; default since 2026-12-06,
    False keeps the earlier background; always on with the notch).
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
    ls_exponent: float = 0.0
    f_ref: float = 0.0
    f_cross: float = 0.0
    single_scattering: str = "envelope"
    cbs: bool = False
    thickness: float = np.inf
    width: float = np.inf
    angular: str = "uniform"
    memory: bool = False
    focal_return: bool = False
    confocal_notch: bool = False
    measured_reciprocity: bool = True
    focal_return_shallow: bool = False
    focal_return_excess: bool = False
    focal_return_pairs: bool = False

    def __post_init__(self) -> None:
        if self.angular not in ("uniform", "halo"):
            raise ValueError(f"angular: expected 'uniform' or 'halo', got {self.angular!r}")
        if self.memory and not self.cbs:
            raise ValueError(
                "memory: expected cbs=True as well (the memory effect needs the output grid aligned with the transmits)"
            )
        if self.focal_return and self.single_scattering != "field":
            raise ValueError(
                "focal_return: expected single_scattering='field' as well (it is drawn on the beads' grid)"
            )
        if self.focal_return_shallow and not self.focal_return:
            raise ValueError("focal_return_shallow: expected focal_return=True as well (it bounds the focal return)")
        if self.focal_return_excess and not self.focal_return:
            raise ValueError("focal_return_excess: expected focal_return=True as well (it bounds the focal return)")
        if self.focal_return_excess and self.confocal_notch:
            raise ValueError(
                "focal_return_excess: expected confocal_notch=False (the excess is what the un-notched field lacks)"
            )
        if self.focal_return_pairs and not self.focal_return:
            raise ValueError("focal_return_pairs: expected focal_return=True as well (the pairs draw the focal return)")
        if self.focal_return_pairs and (self.confocal_notch or self.focal_return_excess):
            raise ValueError(
                "focal_return_pairs: expected confocal_notch=False and focal_return_excess=False (the pairs carry "
                "the paths' confocal return themselves)"
            )
        if self.confocal_notch and not self.focal_return:
            raise ValueError(
                "confocal_notch: expected focal_return=True as well (the notch leaves the focus to the focal return)"
            )
        if self.single_scattering not in ("envelope", "field"):
            raise ValueError(f"single_scattering: expected 'envelope' or 'field', got {self.single_scattering!r}")
        if self.ls_exponent != 0.0 and not self.f_ref > 0:
            raise ValueError("f_ref: expected the frequency (Hz, > 0) at which ls is given when ls_exponent ≠ 0")
        if self.envelope not in ("escape", "diffusion"):
            raise ValueError(f"envelope: expected 'escape' or 'diffusion', got {self.envelope!r}")
        if self.attenuation_depth not in ("centre", "front"):
            raise ValueError(f"attenuation_depth: expected 'centre' or 'front', got {self.attenuation_depth!r}")
        if not (self.ls > 0 and self.la > 0):
            raise ValueError("ls, la: expected positive mean free paths")
        if not self.thickness > 0:
            raise ValueError(f"thickness: expected a positive slab thickness in m (or inf), got {self.thickness!r}")
        if not self.width > 0:
            raise ValueError(f"width: expected a positive lateral extent in m (or inf), got {self.width!r}")

    @property
    def l_ext(self) -> float:
        """ℓ_ext = (1/ℓ_s + 1/ℓ_a)^{-1} (Supplementary S1, eq. ls) at the reference frequency."""
        return 1.0 / (1.0 / self.ls + 1.0 / self.la)

    def ls_at(self, f: np.ndarray | float) -> np.ndarray:
        """ℓ_s(f) = ℓ_s h(f)/h(f_ref) (ℓ_s given at f_ref). Without a crossover, h(f) = f^(−p), p = ls_exponent:
        p = 4 is the Rayleigh law that Supplementary S1 measures at low frequency (k a ≪ 1). With f_cross > 0,
        h(f) = 1 + (f_cross/f)^p: Rayleigh below f_cross, saturating towards a geometric (frequency-
        independent) cross-section above it, where the scatterers' k a passes 1 (docs/design.md §6.3)."""
        f = np.asarray(f, dtype=np.float64)
        if self.ls_exponent == 0.0:
            return np.full(f.shape, self.ls)
        p = self.ls_exponent
        if self.f_cross > 0:
            return self.ls * (1 + (self.f_cross / f) ** p) / (1 + (self.f_cross / self.f_ref) ** p)
        return self.ls * (f / self.f_ref) ** (-p)

    def l_ext_at(self, f: np.ndarray | float) -> np.ndarray:
        """ℓ_ext(f) = (1/ℓ_s(f) + 1/ℓ_a)^{-1} (Supplementary S1, eq. ls; ℓ_a independent of f, as there)."""
        return 1.0 / (1.0 / self.ls_at(f) + 1.0 / self.la)

    def at_frequency(self, f: float) -> ScatteringLayer:
        """This layer with ℓ_s fixed at its value at f (a sub-band of a dispersive medium)."""
        return replace(self, ls=float(self.ls_at(f)), ls_exponent=0.0)

    def reflection(self, rho0: float = 1000.0, c0: float = 1500.0) -> float:
        z0, z1 = rho0 * c0, self.density * self.sound_speed
        return (z1 - z0) / (z1 + z0)

    # -- ballistic legs --------------------------------------------------------------------------
    def reference_point(self, position: np.ndarray, diameter: float) -> np.ndarray:
        r = np.asarray(position, dtype=np.float64).copy()
        if self.attenuation_depth == "front":
            r[2] -= 0.5 * diameter
        return r

    def _l_ext(self, freqs: np.ndarray | None) -> np.ndarray:
        return np.array(self.l_ext) if freqs is None else self.l_ext_at(freqs)[:, None]

    def attenuation_in(self, ref: np.ndarray, sines: np.ndarray, freqs: np.ndarray | None = None) -> np.ndarray:
        """exp(−L_in/(2ℓ_ext)) per transmit, L_in = (z − z_s)/c_θ: (N_θ,), or (N_f, N_θ) with ℓ_ext(f)."""
        depth = max(0.0, float(ref[2]) - self.z_surface)
        out = np.exp(-depth / cosines(sines)[None, :] / (2 * self._l_ext(freqs)))
        return out[0] if freqs is None else out

    def attenuation_out(self, ref: np.ndarray, elements: np.ndarray, freqs: np.ndarray | None = None) -> np.ndarray:
        """exp(−L_out/(2ℓ_ext)) per element, L_out = part of the straight ray below z_s: (N_u,) or (N_f, N_u)."""
        depth = max(0.0, float(ref[2]) - self.z_surface)
        dist = np.linalg.norm(np.asarray(elements, float) - np.asarray(ref, float)[None, :], axis=1)
        out = np.exp(-dist[None, :] * depth / max(float(ref[2]), 1e-12) / (2 * self._l_ext(freqs)))
        return out[0] if freqs is None else out

    def attenuate(
        self,
        h: np.ndarray,
        position: np.ndarray,
        diameter: float,
        elements: np.ndarray,
        sines: np.ndarray,
        rho0: float = 1000.0,
        c0: float = 1500.0,
        freqs: np.ndarray | None = None,
    ) -> np.ndarray:
        """Apply both legs and the interface transmission 1 − R² to a target's H (N_f, N_u, N_θ); with
        `freqs`, each frequency with its own ℓ_ext(f) (the ballistic echo's spectral filtering, S1)."""
        ref = self.reference_point(position, diameter)
        if ref[2] <= self.z_surface:
            return h
        t_r = np.float32(1.0 - self.reflection(rho0, c0) ** 2)
        if freqs is None:
            w = np.outer(self.attenuation_out(ref, elements), self.attenuation_in(ref, sines)) * t_r
            return h * w.astype(np.float32)[None, :, :]
        w_out = self.attenuation_out(ref, elements, freqs).astype(np.float32)
        w_in = self.attenuation_in(ref, sines, freqs).astype(np.float32)
        return h * (w_out[:, :, None] * w_in[:, None, :] * t_r)

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
    def diffusion_constants(self, dim: int = 3) -> tuple[float, float]:
        """(D', z_e): the diffusion constant per unit path, D' = ℓ_s/d (D = v ℓ_t/d, isotropic scattering:
        ℓ_t = ℓ_s), and the extrapolation length, z_e = 2ℓ_s/3 in 3-D and πℓ_s/4 in 2-D (index-matched
        boundary; Ishimaru 1978; Akkermans & Montambaux 2007, ch. 5; docs/design.md §6.3). The escape
        envelope, an order-of-scattering model kept for the legacy conventions, keeps the 3-D values."""
        ls = self.ls
        if dim == 3 or self.envelope == "escape":  # the escape model keeps its 3-D spread (legacy rig)
            return ls / 3.0, 2.0 * ls / 3.0
        return ls / 2.0, np.pi * ls / 4.0

    def reflectance_density(self, s: np.ndarray, orders_from: int = 1, dim: int = 3) -> np.ndarray:
        """ρ(s) per unit path length (1/m) of the multiply scattered flux (module doc); orders_from=2
        drops the single-scattering order (escape: its n = 1 term e^{−s/ℓ_s}/(2ℓ_s); diffusion: the exact
        first order of a normally incident plane wave on isotropic scatterers, ρ₁(s) = κ_d e^{−s/ℓ_s}/ℓ_s —
        every single-scattering path from depth z out at direction cosine μ has s = z(1 + 1/μ), so the
        extinction is e^{−s/ℓ_s} whatever μ, and κ₃ = ∫₀¹ (dμ/2) μ/(1 + μ) = (1 − ln 2)/2, κ₂ = (π − 2)/(2π) —
        is subtracted and the rest clipped at 0, `first_order_reflectance`). Diffusion in `dim` dimensions: the
        flux through the extrapolated boundary of a source at z₁ = ℓ_s + z_e; for a slab (finite
        `thickness` L) the images of both extrapolated boundaries, 2m(L + 2z_e) apart (Patterson, Chance &
        Wilson 1989; Contini, Martelli & Zaccanti 1997):
        ρ(s) = Σ_m (z₁ + 2mL') (4πD's³)^{-1/2} exp(−(z₁ + 2mL')²/(4D's)), L' = L + 2z_e, m ∈ ℤ."""
        s = np.maximum(np.asarray(s, dtype=np.float64), 0.0)
        ls, la = self.ls, self.la
        absorb = np.exp(-s / la)
        if self.envelope == "escape":
            rho = np.exp(-s / (2 * ls)) * absorb / (2 * ls)
            if orders_from >= 2:
                rho = rho - np.exp(-s / ls) * absorb / (2 * ls)
            return rho
        dp, z_e = self.diffusion_constants(dim)
        z1 = ls + z_e
        span = self.thickness + 2 * z_e
        orders: range | tuple[int, ...] = (0,)
        if np.isfinite(span):  # images out to 6.3 diffusion lengths √(4D's) beyond the longest path
            m_max = int(np.ceil(np.sqrt(40 * dp * float(s.max(initial=0.0))) / (2 * span))) + 1
            orders = range(-m_max, m_max + 1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            rho = np.zeros_like(s)
            for m in orders:
                zm = z1 + 2 * m * span if m else z1
                rho = rho + zm / np.sqrt(4 * np.pi * dp * s**3) * np.exp(-(zm**2) / (4 * dp * s))
        rho = np.where(s > 0, np.nan_to_num(rho), 0.0)
        if orders_from >= 2:
            rho = np.maximum(rho - first_order_reflectance(s, ls, dim), 0.0)
        return rho * absorb

    def halo_radius2(self, s: np.ndarray, aperture_radius: float, dim: int = 3) -> np.ndarray:
        """b² = a² + 4D's: the diffuse halo's squared radius after a path s (module doc)."""
        return aperture_radius**2 + 4 * self.diffusion_constants(dim)[0] * np.maximum(s, 0.0)

    def side_losses(self, b2: np.ndarray, aperture_radius: float, dim: int = 3) -> np.ndarray:
        """The share of the halo under the aperture that a medium of finite `width` keeps, per lateral axis
        to the power dim − 1: its sides, extrapolated by z_e, absorb the diffusing energy (the lateral
        analogue of the bottom's images, `reflectance_density`). Per axis the halo is a Gaussian of variance
        σ² = b²/2 centred on the axis; with absorbing walls at ±X, X = width/2 + z_e, its density is the image
        series Σ_n (−1)ⁿ g(x − 2nX), so the share within |x| < a is Σ_n (−1)ⁿ ½[erf((a − 2nX)/√(2σ²)) +
        erf((a + 2nX)/√(2σ²))] over the free one, erf(a/√(2σ²)) (Carslaw & Jaeger 1959, §2.2)."""
        b2 = np.asarray(b2, dtype=np.float64)
        if not np.isfinite(self.width):
            return np.ones_like(b2)
        from scipy.special import erf

        x_wall = 0.5 * self.width + self.diffusion_constants(dim)[1]
        root = np.sqrt(np.maximum(b2, 1e-30))  # √(2σ²)
        a = aperture_radius
        m_max = int(np.ceil(3 * float(root.max(initial=0.0)) / (2 * x_wall))) + 1
        kept = np.zeros_like(b2)
        for n in range(-m_max, m_max + 1):
            kept += (-1) ** abs(n) * 0.5 * (erf((a - 2 * n * x_wall) / root) + erf((a + 2 * n * x_wall) / root))
        ratio = np.clip(kept / np.maximum(erf(a / root), 1e-300), 0.0, 1.0)
        return ratio ** (dim - 1)

    def intensity(
        self, tau: np.ndarray, c0: float, aperture_radius: float, dim: int, pulse_energy: float, orders_from: int = 1
    ) -> np.ndarray:
        """⟨M(t)²⟩ (relative to the incident pulse peak²) τ = t − t_on after the surface echo."""
        v = c0 if self.energy_velocity is None else self.energy_velocity
        s = v * np.maximum(np.asarray(tau, dtype=np.float64), 0.0)
        b2 = self.halo_radius2(s, aperture_radius, dim)
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
        rho = self.reflectance_density(s, orders_from, dim)
        lateral = lateral * self.side_losses(b2, aperture_radius, dim)
        out = self.gain * reception * rho * v * pulse_energy * lateral * t_r**2
        return np.where(np.asarray(tau) > 0, out, 0.0)

    def exitance(
        self, tau: np.ndarray, c0: float, aperture_radius: float, dim: int, orders_from: int = 1
    ) -> np.ndarray:
        """M(τ)/E_s: the diffuse flux density leaving the surface per unit path, v ρ(s) (1 − R²)² × gain, for an
        infinitely wide insonification (the aperture's share, the reception and a finite width's walls are
        the `halo` geometry's, `diffuse.HaloGeometry`)."""
        v = c0 if self.energy_velocity is None else self.energy_velocity
        s = v * np.maximum(np.asarray(tau, dtype=np.float64), 0.0)
        t_r = 1.0 - self.reflection() ** 2
        out = self.gain * self.reflectance_density(s, orders_from, dim) * v * t_r**2
        return np.where(np.asarray(tau) > 0, out, 0.0)

    def correlation_per_frame(self, tau: np.ndarray, c0: float, f_c: float) -> np.ndarray:
        """g₁ between consecutive frames for waves that spent τ in the medium (DWS, module doc)."""
        v = c0 if self.energy_velocity is None else self.energy_velocity
        s = v * np.maximum(np.asarray(tau, dtype=np.float64), 0.0)
        kc = 2 * np.pi * f_c / c0
        return np.exp(-(s / self.ls) * kc**2 * self.frame_displacement**2 / 3.0)

    def correlation_single(self, c0: float, f_c: float) -> float:
        """g₁ between frames of a single-scattering echo: exp(−(2k)²⟨Δr²⟩/6) (3D Brownian step)."""
        kc = 2 * np.pi * f_c / c0
        return float(np.exp(-((2 * kc) ** 2) * self.frame_displacement**2 / 6.0))


from .diffuse import DiffuseBackground  # noqa: E402  (the frame generator lives in its own module)
