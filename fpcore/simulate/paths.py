"""Multiple scattering as explicit scattering paths: a transport Monte Carlo of the ladder, each path
with its reversed partner (docs/design.md §6.6).

Physics. In a medium of independent point scatterers (density n, strength t, σ_s = n⁻¹/ℓ_s) the
scattering orders n ≥ 2 of the field from a source v to a receiver u are the sums over sequences of
distinct scatterers r₁ … r_n,

    K_n(u, v) = Σ G_c(u, r_n) t G_m(r_n, r_{n−1}) t … t G_c(r₁, v),

with the coherent (extinguished) wave on the legs to and from the array and the mean Green function
G_m = G e^{−d/(2ℓ_ext)} between scatterers (paper Supplementary S1). Averaged over the scatterers'
positions, |K_n|² keeps the sequences paired with themselves (the ladder) and with their reverse
(the most-crossed diagrams: coherent backscattering, reciprocity). The ladder is an integral over
the sequences whose measure is a random walk: in 3-D, n|t|²|G(d)|² e^{−d/ℓ_s} d³r =
(1/ℓ_s) e^{−d/ℓ_s} dd dΩ/(4π) (2-D: dφ/(2π), with the far-field |G|² = 1/(8πkd)), an exponential
step and an isotropic direction. So a walk started at r₁ drawn with density π₁ and weighted by
n|t|²/(N_w π₁) samples the ladder without bias; each of its events r_n (n ≥ 2) ends one path of
internal length L_n = Σ steps. A path contributes, at wavenumber k,

    K(u, v) ∋ (A/√2) [G_c(u, r_n) G_c(r₁, v) + G_c(u, r₁) G_c(r_n, v)],  |A|² = n|t|²/(N_w π₁) w(f),

A's phase e^{−ikL} (the path's own length; distinct paths are then incoherent as in a random medium),
w(f) = (ℓ_ref/ℓ_s(f))^{n−1} e^{−L(1/ℓ_s(f) − 1/ℓ_ref)} e^{−L/ℓ_a} re-weighting walks drawn at ℓ_ref to
the frequency's own ℓ_s(f) and absorption. Summed, ⟨|K|²⟩ is the ladder plus its reversed partner:
twice the ladder where the two ends coincide (coherent backscattering), the ladder elsewhere.

What it gives, without a model of the envelope: the time envelope and frequency correlation of the
walk's path lengths, the halo's lateral spread and the memory effect (explicit end points), reciprocity
and coherent backscattering (reversed partners), and — what a field leaving the surface misses — paths
whose both ends lie at depth, which a focus there collects (the focused matrix's peak of low orders).
What it leaves out: recurrent scattering and the interference between orders of strong (resonant)
scatterers, near-field coupling (d ≲ λ), and every order's fluctuation about the ladder (a finite
number of walks; the first order is the single-scattering field's). Checked against Foldy–Lax in
bench/transport_paths.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import secant_over_aperture, secant_over_sines
from ..kernel import default_threads
from ..kernel_presum_loops import _jit, nb, pool, split
from .single_scattering import BEAM_SOFT, PAIR_CODE_STEPS, _edge, beam_gain, beam_half_width

__all__ = [
    "Paths",
    "PlaneWaveBeams",
    "StraightRays",
    "Synthesised",
    "draw_paths",
    "far_green",
    "focal_overlap",
    "focal_pairs",
    "focal_return",
    "path_spectra",
]


@dataclass(frozen=True)
class Paths:
    """Walks in a medium: the first scattering of each walk, `start` (N_w, 3), and every later event as a
    path end — `walk` (P,) the walk it belongs to (non-decreasing), `end` (P, 3), `order` (P,) n ≥ 2,
    `length` (P,) the internal length L between the first and the last scattering (m). Steps were drawn
    with ℓ_s = `ls_ref`; `start_weight` (N_w,) is 1/(N_w π₁(r₁)), the measure each walk stands for (m³; m² in
    2-D), over first scatterings spread laterally over `start_area` (m²; m in 2-D)."""

    dim: int
    start: np.ndarray
    walk: np.ndarray
    end: np.ndarray
    order: np.ndarray
    length: np.ndarray
    ls_ref: float
    start_weight: np.ndarray
    start_area: float

    @property
    def n_walks(self) -> int:
        return int(self.start.shape[0])

    @property
    def n_paths(self) -> int:
        return int(self.end.shape[0])


def draw_paths(
    rng: np.random.Generator,
    dim: int,
    ls_ref: float,
    n_walks: int,
    l_max: float,
    z_top: float,
    start_half_width: float,
    start_depth: float,
    thickness: float = np.inf,
    half_width: float = np.inf,
    start_decay: float | None = None,
) -> Paths:
    """Walks in the medium z_top < z < z_top + thickness, |x| (and |y|) ≤ half_width (module doc).

    First scatterings uniform over |x|, |y| ≤ start_half_width, and in depth uniform over [0, start_depth]
    below z_top, or, with `start_decay` (m), with density ∝ e^{−d/start_decay} there (importance sampling by
    the incident wave's extinction). A walk ends when it leaves the medium or its internal length exceeds
    l_max (no later arrival is recorded)."""
    if dim not in (2, 3):
        raise ValueError(f"dim: expected 2 or 3, got {dim}")
    for name, v in (("ls_ref", ls_ref), ("l_max", l_max), ("start_half_width", start_half_width)):
        if not v > 0:
            raise ValueError(f"{name}: expected a length > 0, got {v}")
    if not 0 < start_depth <= thickness:
        raise ValueError(f"start_depth: expected a depth in (0, thickness={thickness}], got {start_depth}")
    if n_walks < 1:
        raise ValueError(f"n_walks: expected at least 1, got {n_walks}")
    w = start_half_width
    x = rng.uniform(-w, w, n_walks)
    y = rng.uniform(-w, w, n_walks) if dim == 3 else np.zeros(n_walks)
    area = (2 * w) ** (dim - 1)
    if start_decay is None:
        d = rng.uniform(0.0, start_depth, n_walks)
        density = np.full(n_walks, 1.0 / (area * start_depth))
    else:  # truncated exponential on [0, start_depth]
        mass = -np.expm1(-start_depth / start_decay)
        d = -start_decay * np.log1p(-rng.uniform(0.0, 1.0, n_walks) * mass)
        density = np.exp(-d / start_decay) / (start_decay * mass * area)
    start = np.stack([x, y, z_top + d], axis=1)
    pos, length = start.copy(), np.zeros(n_walks)
    alive = np.arange(n_walks)
    ev_w, ev_p, ev_n, ev_l = [], [], [], []
    order = 1
    while alive.size:
        order += 1
        step = rng.exponential(ls_ref, alive.size)
        if dim == 2:
            phi = rng.uniform(0.0, 2 * np.pi, alive.size)
            u = np.stack([np.cos(phi), np.zeros_like(phi), np.sin(phi)], axis=1)
        else:
            u = rng.standard_normal((alive.size, 3))
            u /= np.linalg.norm(u, axis=1, keepdims=True)
        p = pos[alive] + step[:, None] * u
        lw = length[alive] + step
        inside = (p[:, 2] > z_top) & (p[:, 2] < z_top + thickness) & (lw <= l_max)
        inside &= np.abs(p[:, 0]) <= half_width
        if dim == 3:
            inside &= np.abs(p[:, 1]) <= half_width
        alive = alive[inside]
        pos[alive], length[alive] = p[inside], lw[inside]
        ev_w.append(alive)
        ev_p.append(p[inside])
        ev_n.append(np.full(alive.size, order, dtype=np.int32))
        ev_l.append(lw[inside])
    walk = np.concatenate(ev_w)  # the loop ran at least once (n_walks ≥ 1)
    srt = np.argsort(walk, kind="stable")  # events grouped by walk, in order within each
    return Paths(
        dim,
        start,
        walk[srt],
        np.concatenate(ev_p)[srt],
        np.concatenate(ev_n)[srt],
        np.concatenate(ev_l)[srt],
        float(ls_ref),
        1.0 / (n_walks * density),
        float(area),
    )


#: Amplitude width of a diffraction-limited focus, a = A_W λ/NA for an aperture (or span of sines) NA: the
#: Gaussian e^{−x²/(2a²)} whose |·|² has the FWHM 0.886 λ/NA of the uniform aperture's sinc².
A_W = 0.886 / (2 * np.sqrt(np.log(2)))


def focal_overlap(
    delta: np.ndarray,
    a_t: np.ndarray,
    a_r: np.ndarray,
    dz_first: np.ndarray | None = None,
    dz_last: np.ndarray | None = None,
    k: float | None = None,
) -> np.ndarray:
    """W (N,) of paths whose ends lie Δ⊥ (N, n_axes) apart laterally, relative to half a point scatterer's confocal
    intensity (docs/design.md §6.6, eq. F2): the transmit focus (amplitude width a_t per axis, (n_axes,)) on one end
    and the receive focus (a_r, (N, n_axes)) on the other, ∫|P_T(ρ₁ − ρ)|²|P_R(ρ_n − ρ)|² dρ ∝ e^{−Δ²/(a_t² + a_r²)}
    per axis, and the same with the ends swapped (the reversed path), plus their cross term
    e^{−Δ²(1/a_t² + 1/a_r²)/4}: 2 where the ends coincide in the focal plane, → 0 apart. With the ends' defocus
    `dz_first`, `dz_last` (N,) (the apparent depth less each end's depth) and k, each focus widens as a Gaussian
    beam, ã² = a² + (Δz/(k a))², and its peak falls so that ∫|P|²dρ is kept: each term × √((a_t² + a_r²)/(ã_t² + ã_r²))
    per axis (the cross term at the mean defocus, times each beam's overlap with itself across the ends' defocus
    difference δ, |1 + iδ/(2z_R)|^{−1/2} per axis, z_R = k a²)."""
    d2 = np.asarray(delta, dtype=np.float64) ** 2
    at2 = np.asarray(a_t, dtype=np.float64)[None, :] ** 2
    ar2 = np.asarray(a_r, dtype=np.float64) ** 2
    if dz_first is None or dz_last is None or k is None:
        zero = np.zeros(d2.shape[0])
        dz_first, dz_last, k = zero, zero, 1.0

    def widened(a2: np.ndarray, dz: np.ndarray) -> np.ndarray:
        return a2 + (np.asarray(dz, dtype=np.float64)[:, None] / k) ** 2 / a2

    def term(t2: np.ndarray, r2: np.ndarray, cross: bool) -> np.ndarray:
        peak = np.sqrt((at2 + ar2) / (t2 + r2))
        shape = d2 * (1.0 / t2 + 1.0 / r2) / 4.0 if cross else d2 / (t2 + r2)
        return np.prod(peak * np.exp(-shape), axis=1)

    forward = term(widened(at2, dz_first), widened(ar2, dz_last), False)
    reverse = term(widened(at2, dz_last), widened(ar2, dz_first), False)
    mean = 0.5 * (np.asarray(dz_first) + np.asarray(dz_last))
    # The cross term pairs each focus at one end's defocus with itself at the other's: a Gaussian beam overlaps its
    # own propagation by Δ as |1 + iΔ/(2z_R)|^{−1/2} per axis, z_R = k a².
    gap = (np.asarray(dz_first, dtype=np.float64) - np.asarray(dz_last, dtype=np.float64))[:, None] / k
    coherence = np.prod(((1 + (gap / (2 * at2)) ** 2) * (1 + (gap / (2 * ar2)) ** 2)) ** -0.25, axis=1)
    return 0.5 * (forward + reverse) + coherence * term(widened(at2, mean), widened(ar2, mean), True)


@dataclass(frozen=True)
class FocalRig:
    """The rig's transmits and receive for the discrete focal overlap (`discrete_focal_overlap`, docs/design.md §6.6,
    eq. F2′): the transmits' sines along each lateral axis (a full grid of them: (x, y) pairs over every
    combination), the receive aperture per axis (N_u × pitch), and the transmits' beams — each a plane wave
    confined to `beam_aperture` plus its diffraction spread and steered (`single_scattering`'s beam:
    `beam_half_width`, `beam_gain`, cosine edges over ±`BEAM_SOFT` of the half-width), at the wavelength
    `beam_wavelength` — or unbounded plane waves where `beam_aperture` is None."""

    sines: tuple[np.ndarray, ...]  # per lateral axis, (N_j,)
    aperture: np.ndarray  # (n_axes,)
    beam_aperture: np.ndarray | None = None  # (n_axes,)
    beam_wavelength: float = 0.0

    @property
    def span(self) -> np.ndarray:
        """The span of sines N_j Δs per lateral axis (the transmit focus's aperture in (F2))."""
        return np.array([float(np.ptp(u)) * u.size / max(u.size - 1, 1) for u in self.sines])

    @staticmethod
    def from_grid(
        sines: np.ndarray, aperture: np.ndarray, dim: int, beam_aperture: np.ndarray | None, wavelength: float
    ) -> FocalRig | None:
        """The rig of transmits `sines` (N_θ, 2) if they form a full grid along the lateral axes, else None."""
        si = np.asarray(sines, dtype=np.float64)
        axes = 2 if dim == 3 else 1
        per_axis = tuple(np.unique(np.round(si[:, d], 9)) for d in range(axes))
        n_grid = int(np.prod([u.size for u in per_axis]))
        if si.shape[0] != n_grid or np.unique(np.round(si[:, :axes], 9), axis=0).shape[0] != n_grid:
            return None
        ap = np.resize(np.asarray(aperture, dtype=np.float64), axes)
        beam = None if beam_aperture is None else np.resize(np.asarray(beam_aperture, dtype=np.float64), axes)
        return FocalRig(per_axis, ap, beam, float(wavelength))


def _beam_weights(rig: FocalRig, axis: int, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Each transmit's beam amplitude along one axis at the points (x, range z): (N, N_j); ones if unbounded."""
    s = rig.sines[axis]
    if rig.beam_aperture is None:
        return np.ones((x.size, s.size))
    ap, lam = float(rig.beam_aperture[axis]), rig.beam_wavelength
    hw = beam_half_width(ap, z, lam)[:, None]
    off = x[:, None] - z[:, None] * (s / np.sqrt(1.0 - s**2))[None, :]  # tan θ per axis (paraxial in the other)
    return _edge(off, hw, BEAM_SOFT * hw) * beam_gain(ap, z, lam)[:, None]


def _receive(x_end: np.ndarray, r_end: np.ndarray, r_focus: np.ndarray, k: float, sigma: float) -> tuple:
    """The receive focus at the range r_focus seeing a point at (x_end, r_end), one axis, as the complex Gaussian
    e^{−a x² + b x + c} of the focus position x (Fresnel, Gaussian apodization of rms width σ; amplitude
    r_end^{−1/2} per axis, the leg's spreading)."""
    beta = 1.0 / sigma**2 - 1j * k * (1.0 / r_focus - 1.0 / r_end)
    a = -0.5j * k / r_focus + k**2 / (2 * beta * r_focus**2)
    b = k**2 * x_end / (r_focus * r_end * beta)
    c = (
        -0.5 * np.log(r_end)
        + 0.5 * np.log(2 * np.pi / beta)
        - 0.5j * k * x_end**2 / r_end
        - k**2 * x_end**2 / (2 * beta * r_end**2)
    )
    return a, b, c


def _pair_differences(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct differences s − s' over the pairs of transmits (N_Δ,) and, per pair (i, j), the index of its
    difference s_i − s_j among them (N_s, N_s) (`_overlap_integral` sums each pair's term into its difference)."""
    scale = max(float(np.ptp(s)), 1e-12)
    uniq, inv = np.unique(np.round((s[:, None] - s[None, :]) / scale, 9), return_inverse=True)
    return uniq * scale, np.ascontiguousarray(inv.reshape(s.size, s.size), dtype=np.int64)


def _overlap_integral(
    w_f: np.ndarray, rx_f: tuple, w_g: np.ndarray, rx_g: tuple, k: float, pairs: tuple[np.ndarray, np.ndarray]
) -> np.ndarray:
    """∫ F conj(G) dx over the focus position, F = Σ_s w_f[s] e^{iksx} × receive_f(x) (and G), in closed form: a
    Gaussian integral per pair of transmits, whose exponent depends on the pair through s − s' only (`pairs`:
    `_pair_differences`)."""
    d, lag = pairs
    a = rx_f[0] + np.conj(rx_g[0])
    b = rx_f[1] + np.conj(rx_g[1])
    c = rx_f[2] + np.conj(rx_g[2])
    if nb is not None:  # the same sums, compiled: no (N, N_s²) table of pairs (3.5× faster on the 2-D rig)
        n = a.size
        out = np.empty(n, dtype=np.complex128)
        args = (*(np.ascontiguousarray(x, dtype=np.complex128) for x in (w_f, w_g, a, b, c)), lag, 1j * k * d)
        parts = max(1, min(n // 2000, 4 * default_threads()))

        def task(slot: int, t: int) -> tuple:
            return (*args, *split(n, parts, t), out)

        pool(default_threads(), parts, _overlap_rows, task)
        return out
    q = b[:, None] + 1j * k * d[None, :]
    e = np.exp(q**2 / (4 * a[:, None]) + c[:, None])  # (N, N_Δ)
    pair = (w_f[:, :, None] * np.conj(w_g)[:, None, :]).reshape(w_f.shape[0], -1)
    gather = np.eye(d.size)[lag.ravel()]  # (N_s², N_Δ): each pair's term into its difference
    return np.sqrt(np.pi / a) * np.sum((pair @ gather) * e, axis=1)


def discrete_focal_overlap(
    first: np.ndarray,
    last: np.ndarray,
    r_app: np.ndarray,
    k: float,
    rig: FocalRig,
    light_range: np.ndarray | None = None,
    chunk: int = 20000,
) -> np.ndarray:
    """W (N,) of paths with ends `first`, `last` (N, 3; z the range from the array) seen at the apparent range
    r_app (N,), relative to a point on the array's axis in focus there (docs/design.md §6.6, eq. F2′):

        W = [∫|F|² + ∫|F'|² + 2 Re ∫F F'*] / (2 ∫|P|²),   F(x) = T(x; r₁) R(x; r_n), F' = T(x; r_n) R(x; r₁),

    with the transmit focus T(x; r) = Σ_θ b_θ(r) e^{ik[a_θ·(x − ρ) + c_θ(r_app − z)]} summed over the rig's own
    transmits, each lit by its beam at r (`FocalRig`: the steered beams walk off the axis with depth, so a shallow
    end sees transmits a deep focus no longer gets), and the receive R(x; r) the aperture's Fresnel focus at r_app of
    the spherical wave from r, its amplitude spreading from the end's own range — separable along the lateral axes,
    each integral in closed form (a Gaussian apodization of the receive, the transmits' discrete sum kept: their
    grating lobes λ/Δs apart). 2 where the ends coincide in focus, as (F2). With `light_range` (N,), the point P is
    lit by the beams as at that range (the focal return lit as its ends are, `focal_return`)."""
    p1, pn = np.asarray(first, dtype=np.float64), np.asarray(last, dtype=np.float64)
    ra = np.asarray(r_app, dtype=np.float64)
    rl = ra if light_range is None else np.asarray(light_range, dtype=np.float64)
    out = np.empty(ra.size)
    pairs = [_pair_differences(s) for s in rig.sines]
    for c0 in range(0, ra.size, chunk):
        sl = slice(c0, min(c0 + chunk, ra.size))
        a, b, r, r_light = p1[sl], pn[sl], ra[sl], rl[sl]
        num_f = np.ones(r.size)
        num_r = np.ones(r.size)
        den = np.ones(r.size)
        cross = np.ones(r.size, dtype=np.complex128)
        for j, s in enumerate(rig.sines):
            sigma = float(rig.aperture[j]) / (2 * np.pi * A_W)  # the receive's focus width A_W λ R/D (F2)
            c = np.sqrt(1.0 - s**2)

            def lit(end: np.ndarray, s: np.ndarray = s, c: np.ndarray = c, j: int = j, r: np.ndarray = r) -> np.ndarray:
                phase = (c[None, :] - 1.0) * (r - end[:, 2])[:, None] - s[None, :] * end[:, j : j + 1]
                return _beam_weights(rig, j, end[:, j], end[:, 2]) * np.exp(1j * k * phase)

            w_1, w_n = lit(a), lit(b)
            w_p = _beam_weights(rig, j, np.zeros(r.size), r_light).astype(np.complex128)
            rx_n = _receive(b[:, j], b[:, 2], r, k, sigma)
            rx_1 = _receive(a[:, j], a[:, 2], r, k, sigma)
            rx_p = _receive(np.zeros(r.size), r, r, k, sigma)
            num_f *= _overlap_integral(w_1, rx_n, w_1, rx_n, k, pairs[j]).real
            num_r *= _overlap_integral(w_n, rx_1, w_n, rx_1, k, pairs[j]).real
            cross *= _overlap_integral(w_1, rx_n, w_n, rx_1, k, pairs[j])
            den *= _overlap_integral(w_p, rx_p, w_p, rx_p, k, pairs[j]).real
        out[sl] = (num_f + num_r + 2 * cross.real) / (2 * np.maximum(den, 1e-300))
    return out


def focal_return(
    paths: Paths,
    depths: np.ndarray,
    lengths: np.ndarray,
    freqs: np.ndarray,
    ls: np.ndarray,
    la: float,
    c0: float,
    transmit_span: np.ndarray,
    aperture: np.ndarray,
    z_surface: float,
    rig: FocalRig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The focal return of the orders ≥ 2 (docs/design.md §6.6): the paths' ends that the rig sees as one point.

    Returns ν (N_f, N_z), the reflectivity variance per unit volume (that of the beads' single scattering is
    n|t|² e^{−2d/ℓ_ext}) with which they scatter from the apparent depth d = (d₁ + d_n + L)/2 below the surface
    (`depths`, uniform spacing h),

        ν(d) = (1/(A h)) Σ_{d_app ∈ [d − h/2, d + h/2)} n|t|² sw w_f(n, L) e^{−(q_in d₁ + q_out d_n)/ℓ_ext(f)} W  (F1)

    — each path's intensity |A|² (module doc) with both legs' extinction (d₁ and d_n times the legs' mean obliquity
    1/c: over the span of sines for the transmits, over the aperture seen from the end for the receive), times
    `focal_overlap` W (2 where the ends coincide: the path and its reversed partner add in phase), per unit area A
    of first scatterings — and the share of the ladder's energy that the Gaussian field keeps at each path length
    s = d₁ + L + d_n (`lengths`, uniform), κ(s) = 1 − Σ E W/2 / Σ E over the paths of that length (N_f, N_s),
    E = sw w_f e^{−(q_in d₁ + q_out d_n)/ℓ_ext}: a point-like path's energy moves to the focal return (its reversed
    partner's doubles it there, as in coherent backscattering), a path whose ends lie apart keeps it in the field (F3).
    The rig's foci: the transmits' amplitude width A_W λ/S per lateral axis over the span of sines S =
    `transmit_span` (N_θ Δs per axis), the receive's A_W λ/(2 NA) over the aperture D = `aperture` at the range
    R = z_surface + d, NA = (D/2)/√(R² + D²/4) (A_W λ R/D at small NA); λ at each frequency. ℓ_s(f) = `ls`,
    absorption ℓ_a = `la`.

    With `rig` (the rig's own transmits and beams, `FocalRig`) the focal return is lit as its ends are: the third
    value is the depth below the surface (N_z,) at which each apparent depth's cell is lit — the energy-weighted mean
    of its paths' ends' depths — and ν takes W′ (eq. F2′, `discrete_focal_overlap`, its point lit there) of each path
    moved across so that its midpoint lies on the axis (the grid lights each point where it lies); κ keeps (F2)'s W.
    None without rig."""
    var, kept, light, _ = _focal_sums(
        paths, depths, lengths, freqs, ls, la, c0, transmit_span, aperture, z_surface, rig, None
    )
    return var, kept, light


def focal_pairs(
    paths: Paths,
    depths: np.ndarray,
    lengths: np.ndarray,
    freqs: np.ndarray,
    ls: np.ndarray,
    la: float,
    c0: float,
    transmit_span: np.ndarray,
    aperture: np.ndarray,
    z_surface: float,
    rig: FocalRig,
    spacing: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The focal return drawn as two-point paths (docs/design.md §6.6, F6): each path's ends kept apart laterally
    on the beads' grid, its depths collapsed to the apparent one. Arguments as `focal_return` (`rig` required),
    `spacing` the grid's lateral step. Returns

    - ν' (N_f, N_z), the paths' intensity per unit volume with their defocus,
          ν'(d) = (1/(A h)) Σ n|t|² sw w_f e^{−(q_in d₁ + q_out d_n)/ℓ_ext(f)} D,   D = W′(r̄₁, r̄_n)/2,       (F6)
      D the path's discrete focal overlap (F2′) with both ends moved across onto the axis (r̄: the lateral
      separation removed, the depths kept: the legs' defocus and the receive's spreading from the end's own range),
      1 where the ends coincide in focus — the lateral separation is the grid's to draw;
    - κ (N_f, N_s), the Gaussian field's share by path length: each drawn path moves min(1, D/ρ_R) of its energy,
      ρ_R = ½[(R/R_n)^{d−1} + (R/R₁)^{d−1}] the element energy of its ends against a point at the apparent range
      R (what D counts besides the defocus);
    - the lighting depth (N_z,), as `focal_return`'s;
    - the lateral separations (N_z, n_y, PAIR_MAX_STEPS + 1), n_y = PAIR_MAX_STEPS + 1 in 3D and 1 in 2D: per depth,
      the joint distribution of (|Δy|, |Δx|)/spacing rounded (ν'-weighted at the band's centre, the last bin of each
      axis holding the longer ones), each depth summing to 1 (all at (0, 0) where no path lands). Joint, not per
      axis: the ends of a path lie a distance apart in any direction, so the product of the axes' marginals would
      put pairs at short separations on both axes that no path has."""
    if spacing <= 0:
        raise ValueError(f"spacing: expected the grid's lateral step > 0 m, got {spacing}")
    var, kept, light, sep = _focal_sums(
        paths, depths, lengths, freqs, ls, la, c0, transmit_span, aperture, z_surface, rig, spacing
    )
    assert light is not None and sep is not None
    return var, kept, light, sep


#: The longest lateral separation of a drawn pair, in grid steps per axis (`focal_pairs`; the grid's phase codes).
PAIR_MAX_STEPS = PAIR_CODE_STEPS


def _focal_sums(
    paths: Paths,
    depths: np.ndarray,
    lengths: np.ndarray,
    freqs: np.ndarray,
    ls: np.ndarray,
    la: float,
    c0: float,
    transmit_span: np.ndarray,
    aperture: np.ndarray,
    z_surface: float,
    rig: FocalRig | None,
    pair_spacing: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """`focal_return` (pair_spacing None) and `focal_pairs` (the grid's lateral step): (ν, κ, light, separations)."""
    dep = np.asarray(depths, dtype=np.float64)
    h = float(dep[1] - dep[0]) if dep.size > 1 else 1.0
    s_grid = np.asarray(lengths, dtype=np.float64)
    hs = float(s_grid[1] - s_grid[0]) if s_grid.size > 1 else 1.0
    f = np.asarray(freqs, dtype=np.float64)
    ls = np.broadcast_to(np.asarray(ls, dtype=np.float64), f.shape)
    var, kept = np.zeros((f.size, dep.size)), np.ones((f.size, s_grid.size))
    axes = 2 if paths.dim == 3 else 1
    pairs = pair_spacing is not None
    if pairs and rig is None:
        raise ValueError("rig: expected the rig's foci for the pairs (F6 takes F2′ of the collapsed paths)")
    n_y = PAIR_MAX_STEPS + 1 if axes == 2 else 1
    sep = np.zeros((dep.size, n_y, PAIR_MAX_STEPS + 1)) if pairs else None
    if sep is not None:
        sep[:, 0, 0] = 1.0
    if paths.n_paths == 0:
        return var, kept, (dep.copy() if rig is not None else None), sep
    w = paths.walk
    d1 = paths.start[w, 2] - z_surface
    dn = paths.end[:, 2] - z_surface
    d_app = 0.5 * (d1 + dn + paths.length)
    cell = np.floor((d_app - dep[0]) / h + 0.5).astype(np.int64)
    in_grid = (cell >= 0) & (cell < dep.size)
    age = np.floor((d1 + dn + paths.length - s_grid[0]) / hs + 0.5).astype(np.int64)
    in_ages = (age >= 0) & (age < s_grid.size)
    drawn = in_ages & in_grid  # (F3): a path moves its share out of the Gaussian field only where the grid draws it
    delta = paths.end[:, :axes] - paths.start[w, :axes]
    span = np.broadcast_to(np.asarray(transmit_span, dtype=np.float64), (axes,))
    ap = np.broadcast_to(np.asarray(aperture, dtype=np.float64), (axes,))
    q_in, q_out = leg_obliquities(paths, span, ap, z_surface)

    def path_energy(lf: float) -> np.ndarray:
        return path_energies(paths, lf, la, z_surface, q_in, q_out)

    light = None
    if rig is not None:
        # F2′ of each path moved laterally so that its midpoint lies on the axis: the medium is invariant in x, and
        # the grid's focal return is lit where it lies by the beams themselves (a path off the axis taken as it
        # lies would be darkened by the beams' walk-off twice, in W′ and on the grid: docs/design.md §6.6).
        # (F6) moves both ends onto the axis instead: the grid draws their lateral separation itself.
        first, last = paths.start[w].copy(), paths.end.copy()
        if pairs:  # both ends on the axis, their depths kept
            first[:, :axes], last[:, :axes] = 0.0, 0.0
        else:  # the midpoint on the axis
            mid = 0.5 * (first[:, :axes] + last[:, :axes])
            first[:, :axes] -= mid
            last[:, :axes] -= mid
        r_app = z_surface + d_app
        e_c = path_energy(float(ls[ls.size // 2]))  # the band centre's weights for the lighting depth
        mass = np.bincount(cell[in_grid], weights=e_c[in_grid], minlength=dep.size)
        mean_end = np.bincount(cell[in_grid], weights=(e_c * 0.5 * (d1 + dn))[in_grid], minlength=dep.size)
        light = np.where(mass > 0, mean_end / np.maximum(mass, 1e-300), dep)
        anchors = f if f.size <= 3 else f[[0, f.size // 2, f.size - 1]]
        # (F6): the element energy of the path's two ends against a point at its apparent range
        rho_r = 0.5 * ((r_app / (z_surface + dn)) ** (paths.dim - 1) + (r_app / (z_surface + d1)) ** (paths.dim - 1))
        lit_range = z_surface + light[cell[in_grid]]
        w_anchor = np.stack(
            [
                discrete_focal_overlap(
                    first[in_grid], last[in_grid], r_app[in_grid], 2 * np.pi * fa / c0, rig, lit_range
                )
                for fa in anchors
            ]
        )
    for m in range(f.size):
        lam, lf = c0 / f[m], float(ls[m])
        k = 2 * np.pi / lam
        nt2 = 4 * np.pi / lf if paths.dim == 3 else 4 * k / lf
        energy = path_energy(lf)
        r = (z_surface + d_app)[:, None]
        a_r = A_W * lam * np.sqrt(r**2 + (ap[None, :] / 2) ** 2) / ap[None, :]  # A_W λ/(2 NA), NA = sin of the edge ray
        ov = focal_overlap(delta, A_W * lam / span, a_r, d_app - d1, d_app - dn, k)
        if rig is None:
            weight = nt2 * energy * ov
        else:  # F2′: each path centred on the axis (F6: collapsed onto it), per unit area of first scatterings
            weight = np.zeros_like(energy)
            weight[in_grid] = nt2 * energy[in_grid] * _between(f[m], anchors, w_anchor)
            if pairs:
                weight *= 0.5  # D = W′/2: the pair's two cells carry the factor 2 where its ends coincide
        var[m] = np.bincount(cell[in_grid], weights=weight[in_grid], minlength=dep.size) / h
        total = np.bincount(age[in_ages], weights=energy[in_ages], minlength=s_grid.size)
        if pairs:  # (F6): a pair moves min(1, D/ρ_R) of its energy
            share = np.zeros_like(energy)
            share[in_grid] = _between(f[m], anchors, w_anchor) / (2 * rho_r[in_grid])
            moved_e = energy * np.clip(share, 0.0, 1.0)
        else:
            moved_e = energy * ov / 2
        moved = np.bincount(age[drawn], weights=moved_e[drawn], minlength=s_grid.size)
        kept[m] = np.where(total > 0, np.clip(1.0 - moved / np.maximum(total, 1e-300), 0.0, 1.0), 1.0)
        if sep is not None and pair_spacing is not None and m == f.size // 2:  # weighted by ν' at the band's centre
            steps = np.minimum(np.rint(np.abs(delta) / pair_spacing), PAIR_MAX_STEPS).astype(np.int64)  # (N, axes)
            sy = steps[:, 1] if axes == 2 else np.zeros(steps.shape[0], dtype=np.int64)
            n_x = PAIR_MAX_STEPS + 1
            flat = (cell[in_grid] * n_y + sy[in_grid]) * n_x + steps[in_grid, 0]
            hist = np.bincount(flat, weights=weight[in_grid], minlength=dep.size * n_y * n_x)
            hist = hist.reshape(dep.size, n_y, n_x)
            mass = hist.sum(axis=(1, 2), keepdims=True)
            sep[:] = np.where(mass > 0, hist / np.maximum(mass, 1e-300), sep)
    return var, kept, light, sep


def leg_obliquities(
    paths: Paths, transmit_span: np.ndarray, aperture: np.ndarray, z_surface: float
) -> tuple[float, np.ndarray]:
    """The legs' obliquity (F1): the transmits' ⟨1/c_θ⟩ over the span of sines, and per path the receive rays'
    ⟨1/cos⟩ from its last end's range over the aperture (uniform; tabulated in the range, smooth)."""
    dn = paths.end[:, 2] - z_surface
    q_in = float(secant_over_sines(np.asarray(transmit_span, dtype=np.float64)))
    r_tab = np.linspace(z_surface, z_surface + max(float(dn.max(initial=0.0)), 1e-9), 257)
    return q_in, np.interp(z_surface + dn, r_tab, secant_over_aperture(np.asarray(aperture, dtype=np.float64), r_tab))


def path_energies(
    paths: Paths, lf: float, la: float, z_surface: float, q_in: float | np.ndarray, q_out: float | np.ndarray
) -> np.ndarray:
    """E of (F3) per path at ℓ_s(f) = lf, per unit area of first scatterings: the walk's weight re-weighted to lf
    and ℓ_a, and both legs' extinction over the ends' depths d₁, d_n below the surface with the obliquities q_in (the
    transmits' mean secant) and q_out (the receive rays', per path or one), (docs/design.md §6.6)."""
    w = paths.walk
    d1 = paths.start[w, 2] - z_surface
    dn = paths.end[:, 2] - z_surface
    log_w = (paths.order - 1) * np.log(paths.ls_ref / lf) - paths.length * (1.0 / lf - 1.0 / paths.ls_ref + 1.0 / la)
    per_area = paths.start_weight[w] / paths.start_area
    return per_area * np.exp(log_w - (d1 * q_in + dn * q_out) * (1.0 / lf + 1.0 / la))


def _between(x: float, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Rows ys (n, N) linearly interpolated at x between the abscissae xs (n,), held beyond them."""
    if xs.size == 1:
        return ys[0]
    j = int(np.clip(np.searchsorted(xs, x), 1, xs.size - 1))
    t = float(np.clip((x - xs[j - 1]) / (xs[j] - xs[j - 1]), 0.0, 1.0))
    return (1 - t) * ys[j - 1] + t * ys[j]


def far_green(k: float, d: np.ndarray, dim: int) -> np.ndarray:
    """G(d) for kd ≫ 1: e^{−ikd}/(4πd) (3D, exact), (−i/4)√(2/(πkd)) e^{−i(kd − π/4)}(1 − i/(8kd)) (2D, the
    Hankel function's large-argument form, relative error < 1e-3 for kd > 3)."""
    if dim == 3:
        return np.exp(-1j * k * d) / (4 * np.pi * d)
    x = k * d
    return -0.25j * np.sqrt(2 / (np.pi * x)) * np.exp(-1j * (x - np.pi / 4)) * (1 - 1j / (8 * x))


@dataclass(frozen=True)
class StraightRays:
    """The coherent legs between points in the medium (z > z_surface) and receivers above it (z < z_surface):
    G along the straight ray (`far_green`), times `factor` (the interface's one-way transmission) and the
    extinction e^{−d_b/(2ℓ_ext)} over the ray's length d_b below the surface (paper S1: ⟨ψ⟩ ∝ e^{−d/(2ℓ_ext)})."""

    receivers: np.ndarray  # (N_u, 3)
    z_surface: float
    dim: int
    factor: float = 1.0

    def geometry(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance, length below the surface), each (N, N_u) float32."""
        el = np.asarray(self.receivers, dtype=np.float64)
        diff = np.asarray(points, dtype=np.float64)[:, None, :] - el[None, :, :]
        dist = np.linalg.norm(diff, axis=2) if self.dim == 3 else np.hypot(diff[..., 0], diff[..., 2])
        frac = (diff[..., 2] - (self.z_surface - el[None, :, 2])) / np.maximum(diff[..., 2], 1e-12)
        return dist.astype(np.float32), (dist * np.clip(frac, 0.0, 1.0)).astype(np.float32)

    def values(self, k: float, lext: float, points: np.ndarray) -> np.ndarray:
        """G_c(u, r) (N, N_u) complex64 at one wavenumber."""
        dist, below = self.geometry(points)
        g = far_green(k, dist.astype(np.float64), self.dim) * np.exp(-below / (2 * lext))
        return (self.factor * g).astype(np.complex64)


@dataclass(frozen=True)
class Synthesised:
    """Transmits synthesised by the receivers as the probe fires them: the element v emits with weight
    q_v(θ) = 2ik c_θ p^{d−1} e^{−ik a·v}, a planar monopole layer of density 2ikc radiating the unit plane wave
    e^{−ik(a·ρ + c z)} (bench/foldy_lax_reference.py); the incident field at r is Σ_v G_c(r, v) q_v(θ)."""

    sines: np.ndarray  # (N_θ, 2)
    pitch: float

    def weights(self, k: float, receivers: np.ndarray, dim: int) -> np.ndarray:
        """q (N_u, N_θ) complex64."""
        s = np.asarray(self.sines, dtype=np.float64)
        c = np.sqrt(1.0 - (s**2).sum(axis=1))
        ph = np.asarray(receivers, dtype=np.float64)[:, :2] @ s.T
        return (2j * k * c[None, :] * self.pitch ** (dim - 1) * np.exp(-1j * k * ph)).astype(np.complex64)


@dataclass(frozen=True)
class PlaneWaveBeams:
    """Unit plane waves e^{−ik(a·ρ + c z)} (3-D) confined to a beam: the aperture (side `aperture`) plus its
    diffraction spread λ_c z/(2·aperture) (λ_c = `wavelength`), steered (centred on z tan θ), with cosine edges
    over ±15 % of the half-width and the amplitude that conserves the beam's power as it spreads
    (`single_scattering`'s beam: `beam_half_width`, `beam_gain`); times `factor` (the interface's one-way
    transmission) and the extinction e^{−(z − z_s)/(2 c_θ ℓ_ext)} of the oblique path below the surface."""

    sines: np.ndarray  # (N_θ, 2)
    aperture: float
    z_surface: float
    wavelength: float  # λ_c of the diffraction spread
    factor: float = 1.0


def _amplitudes(
    paths: Paths, lo: int, hi: int, b0: int, k: np.ndarray, ls: np.ndarray, la: float, nt2: np.ndarray
) -> np.ndarray:
    """A (hi − lo, N_f) complex64 of the path ends lo…hi (module doc): √(n|t|² start_weight w(f)/2) e^{−ikL}."""
    n, length = paths.order[lo:hi, None], paths.length[lo:hi, None]
    log_w = (n - 1) * np.log(paths.ls_ref / ls[None, :]) - length * (1.0 / ls[None, :] - 1.0 / paths.ls_ref + 1.0 / la)
    sw = paths.start_weight[paths.walk[lo:hi]][:, None]
    return (np.sqrt(nt2[None, :] * sw / 2.0) * np.exp(0.5 * log_w - 1j * k[None, :] * length)).astype(np.complex64)


#: Frequency bins between exact evaluations in the compiled sums (phase by rotation, extinction by its
#: rate interpolated linearly in between: relative error ≲ 1e-2 where ℓ_ext(f) is steep).
ANCHOR = 8

if nb is not None:

    @_jit
    def _overlap_rows(w_f, w_g, a, b, c, lag, ikd, r0, r1, out):  # pragma: no cover
        """out[n] = √(π/a_n) Σ_{i,j} w_f[n, i] conj(w_g[n, j]) e^{(b_n + ik d_{lag[i, j]})²/(4 a_n) + c_n}, r0 ≤ n < r1
        (`_overlap_integral`: the pairs of transmits summed by their difference first, then one exponential each)."""
        n_s, n_t, n_d = w_f.shape[1], w_g.shape[1], ikd.size
        acc = np.zeros(n_d, dtype=np.complex128)
        for n in range(r0, r1):
            acc[:] = 0
            for i in range(n_s):
                wi = w_f[n, i]
                for j in range(n_t):
                    acc[lag[i, j]] += wi * np.conj(w_g[n, j])
            total = 0j
            for m in range(n_d):
                q = b[n] + ikd[m]
                total += acc[m] * np.exp(q * q / (4 * a[n]) + c[n])
            out[n] = np.sqrt(np.pi / a[n]) * total

    @_jit
    def _ray_sums(dist, below, amp, bounds, s0, s1, k0, dk, h, g0, out):  # pragma: no cover
        """out[s, f, u] += Σ_{p ∈ segment s} amp[p, f] g0 e^{−ik_f d_pu − b_pu h_f}/(4π d_pu), s0 ≤ s < s1 (3-D
        legs, `StraightRays`; k_f = k0 + f dk, h_f = 1/(2ℓ_ext(f)))."""
        n_u = dist.shape[1]
        n_f = amp.shape[1]
        for s in range(s0, s1):
            for p in range(bounds[s], bounds[s + 1]):
                for u in range(n_u):
                    d = dist[p, u]
                    b = below[p, u]
                    zr = np.float32(0.0)
                    zi = np.float32(0.0)
                    sr = np.float32(1.0)
                    si = np.float32(0.0)
                    for f in range(n_f):
                        if f % ANCHOR == 0:
                            mag = g0 / (4 * np.pi * d) * np.exp(-b * h[f])
                            ph = -(k0 + dk * f) * d
                            zr = np.float32(mag * np.cos(ph))
                            zi = np.float32(mag * np.sin(ph))
                            f1 = min(f + ANCHOR, n_f - 1)
                            rate = np.exp(-b * (h[f1] - h[f]) / max(f1 - f, 1))
                            sr = np.float32(rate * np.cos(-dk * d))
                            si = np.float32(rate * np.sin(-dk * d))
                        else:
                            zr, zi = zr * sr - zi * si, zr * si + zi * sr
                        a = amp[p, f]
                        out[s, f, u] += complex(a.real * zr - a.imag * zi, a.real * zi + a.imag * zr)

    @_jit
    def _plane_sums(pts, half, amp, bounds, s0, s1, k0, dk, h, sx, sy, c, soft, zs, g0, out):  # pragma: no cover
        """out[s, f, θ] += Σ_{p ∈ segment s} amp[p, f] g0 beam_θ(r_p) e^{−ik_f(a·ρ + c z) − h_f (z − z_s)/c}
        (`PlaneWaveBeams`; half = the beam's half-width per point)."""
        n_i = sx.size
        n_f = amp.shape[1]
        for s in range(s0, s1):
            for p in range(bounds[s], bounds[s + 1]):
                x, y, z = pts[p, 0], pts[p, 1], pts[p, 2]
                hw = half[p]
                for i in range(n_i):
                    tx, ty = sx[i] / c[i], sy[i] / c[i]
                    beam = 1.0
                    for off in (abs(x - z * tx), abs(y - z * ty)):
                        t = min(max((off - (hw - soft * hw)) / (2 * soft * hw), 0.0), 1.0)
                        beam *= 0.5 + 0.5 * np.cos(np.pi * t)
                    if beam == 0.0:
                        continue
                    path = sx[i] * x + sy[i] * y + c[i] * z
                    depth = max(z - zs, 0.0) / c[i]
                    zr = np.float32(0.0)
                    zi = np.float32(0.0)
                    sr = np.float32(1.0)
                    si = np.float32(0.0)
                    for f in range(n_f):
                        if f % ANCHOR == 0:
                            mag = g0 * beam * np.exp(-depth * h[f])
                            ph = -(k0 + dk * f) * path
                            zr = np.float32(mag * np.cos(ph))
                            zi = np.float32(mag * np.sin(ph))
                            f1 = min(f + ANCHOR, n_f - 1)
                            rate = np.exp(-depth * (h[f1] - h[f]) / max(f1 - f, 1))
                            sr = np.float32(rate * np.cos(-dk * path))
                            si = np.float32(rate * np.sin(-dk * path))
                        else:
                            zr, zi = zr * sr - zi * si, zr * si + zi * sr
                        a = amp[p, f]
                        out[s, f, i] += complex(a.real * zr - a.imag * zi, a.real * zi + a.imag * zr)


def _segment_sums(kind: str, args: tuple, n_seg: int, n_f: int, n_out: int, threads: int) -> np.ndarray:
    """Run `_ray_sums` or `_plane_sums` over n_seg segments on `threads` threads: (n_seg, N_f, n_out)."""
    out = np.zeros((n_seg, n_f, n_out), dtype=np.complex64)
    fn = _ray_sums if kind == "rays" else _plane_sums
    parts = max(1, min(n_seg, 4 * threads))

    def task(slot: int, t: int) -> tuple:
        s0, s1 = split(n_seg, parts, t)
        return (*args[:4], s0, s1, *args[4:], out)

    pool(threads, parts, fn, task)
    return out


def _uniform(freqs: np.ndarray) -> bool:
    d = np.diff(freqs)
    return freqs.size > 1 and bool(np.allclose(d, d[0], rtol=1e-6, atol=0))


#: Walks per block of `path_spectra` (bounds its per-block tables, walks × N_f × N_u complex64).
WALK_BLOCK = 400


def path_spectra(
    paths: Paths,
    freqs: np.ndarray,
    c0: float,
    ls: np.ndarray,
    rays: StraightRays,
    transmits: Synthesised | PlaneWaveBeams,
    la: float = np.inf,
    first_order: bool = False,
    threads: int | None = None,
) -> np.ndarray:
    """K(f, u, θ) (N_f, N_u, N_θ) complex64: the paths' field (module doc) at each frequency, ℓ_s(f) = `ls`
    (N_f,), received along `rays` from the transmits `transmits`. With `first_order`, the walks' starts as
    single scatterers instead (weight n|t|²/(N_w π₁), no reversed partner): the first order in the same
    normalisation (a check). 3-D on a uniform frequency grid runs compiled loops (numba); otherwise numpy."""
    f = np.asarray(freqs, dtype=np.float64)
    ls = np.broadcast_to(np.asarray(ls, dtype=np.float64), f.shape)
    k = 2 * np.pi * f / c0
    lext = 1.0 / (1.0 / ls + 1.0 / la)
    dim = paths.dim
    nt2 = 4 * np.pi / ls if dim == 3 else 4 * k / ls  # n|t|² (module doc)
    n_u = rays.receivers.shape[0]
    n_i = transmits.sines.shape[0]
    out = np.zeros((f.size, n_u, n_i), dtype=np.complex64)
    compiled = nb is not None and dim == 3 and _uniform(f)
    if isinstance(transmits, PlaneWaveBeams) and not compiled:
        raise ValueError("transmits: PlaneWaveBeams needs 3-D paths on a uniform frequency grid (and numba)")
    q = [transmits.weights(float(kk), rays.receivers, dim) for kk in k] if isinstance(transmits, Synthesised) else None
    threads = threads or default_threads()
    for b0 in range(0, paths.n_walks, WALK_BLOCK):
        b1 = min(b0 + WALK_BLOCK, paths.n_walks)
        lo, hi = (int(x) for x in np.searchsorted(paths.walk, [b0, b1]))
        sw = np.sqrt(nt2[None, :] * paths.start_weight[b0:b1, None]).astype(np.complex64)  # (n_w, N_f)
        if compiled:
            e_s, i_s, s_out, s_in = _block_compiled(
                paths, b0, b1, lo, hi, k, lext, ls, la, nt2, rays, transmits, threads
            )
        else:
            e_s = np.stack([rays.values(k[m], lext[m], paths.start[b0:b1]) for m in range(f.size)], axis=1)
            amp = _amplitudes(paths, lo, hi, b0, k, ls, la, nt2)
            s_out = np.zeros((b1 - b0, f.size, n_u), dtype=np.complex64)
            if hi > lo:
                wk = paths.walk[lo:hi] - b0
                first = np.flatnonzero(np.r_[True, wk[1:] != wk[:-1]])
                for m in range(f.size):
                    e_e = rays.values(k[m], lext[m], paths.end[lo:hi]) * amp[:, m, None]
                    s_out[wk[first], m] = np.add.reduceat(e_e, first, axis=0)
            i_s = s_in = None
        for m in range(f.size):
            if q is not None:
                i_m = e_s[:, m] @ q[m]
                s_in_m = s_out[:, m] @ q[m]
            else:
                assert i_s is not None and s_in is not None
                i_m, s_in_m = i_s[:, m], s_in[:, m]
            if first_order:
                out[m] += (e_s[:, m] * sw[:, m, None]).T @ i_m
            else:
                out[m] += s_out[:, m].T @ i_m + e_s[:, m].T @ s_in_m
    return out


def _block_compiled(
    paths: Paths,
    b0: int,
    b1: int,
    lo: int,
    hi: int,
    k: np.ndarray,
    lext: np.ndarray,
    ls: np.ndarray,
    la: float,
    nt2: np.ndarray,
    rays: StraightRays,
    transmits: Synthesised | PlaneWaveBeams,
    threads: int,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None]:
    """One block of walks by the compiled sums: E_s, I_s (None for synthesised transmits), S_out, S_in, each
    (walks, N_f, ·) complex64 (`path_spectra`)."""
    n_f = k.size
    k0, dk = np.float64(k[0]), np.float64(k[1] - k[0])
    h = (0.5 / lext).astype(np.float64)
    n_w = b1 - b0
    starts = paths.start[b0:b1]
    own = np.arange(n_w + 1, dtype=np.int64)
    ones = np.ones((n_w, n_f), dtype=np.complex64)
    amp = _amplitudes(paths, lo, hi, b0, k, ls, la, nt2)
    bounds = np.searchsorted(paths.walk[lo:hi], np.arange(b0, b1 + 1)).astype(np.int64)
    n_u = rays.receivers.shape[0]
    g0 = np.float64(rays.factor)
    d_s, b_s = rays.geometry(starts)
    e_s = _segment_sums("rays", (d_s, b_s, ones, own, k0, dk, h, g0), n_w, n_f, n_u, threads)
    d_e, b_e = rays.geometry(paths.end[lo:hi])
    s_out = _segment_sums("rays", (d_e, b_e, amp, bounds, k0, dk, h, g0), n_w, n_f, n_u, threads)
    if isinstance(transmits, Synthesised):
        return e_s, None, s_out, None
    s = np.asarray(transmits.sines, dtype=np.float64)
    c = np.sqrt(1.0 - (s**2).sum(axis=1))
    ap = transmits.aperture

    def half(pts: np.ndarray) -> np.ndarray:
        return beam_half_width(ap, pts[:, 2], transmits.wavelength)

    def gain(pts: np.ndarray) -> np.ndarray:  # both lateral axes' power-conserving amplitude, per point
        return (beam_gain(ap, pts[:, 2], transmits.wavelength) ** 2).astype(np.float32)[:, None]

    tail = (k0, dk, h, s[:, 0].copy(), s[:, 1].copy(), c, 0.15, transmits.z_surface, np.float64(transmits.factor))
    ends = np.ascontiguousarray(paths.end[lo:hi])
    n_i = s.shape[0]
    i_s = _segment_sums("plane", (starts, half(starts), ones * gain(starts), own, *tail), n_w, n_f, n_i, threads)
    s_in = _segment_sums("plane", (ends, half(ends), amp * gain(ends), bounds, *tail), n_w, n_f, n_i, threads)
    return e_s, i_s, s_out, s_in
