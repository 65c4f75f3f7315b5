"""Detection figures: contrasts, false-alarm probability, Cramér–Rao precision, gain (docs/design.md §4.8–4.11).

Two contrasts, named apart (docs/design.md §4.8):
* ``c_gamma`` = γ(target) / mean(γ outside the target) — the paper's main-text figure (Fig. 2);
* ``c_pfa`` = (γ_max/γ_M)², γ_M = √⟨γ²⟩ outside — the contrast of the false-alarm section (S6).

False alarm (paper Supplementary S6, eq. FR): PFA = 1 − [1 − exp(−π C²/4)]^L with C = c_pfa and L the
number of independent speckle grains in the field of view. Check: C = 6, L = 25³ gives ≈ 1e-8.

Precision (paper eq. loc and S5): lateral δρ_L = δρ_D/√C_γ with δρ_D = λ/(2 sin α); axial
δz_L = λ/(4√2 π √C_γ). The paper prints the axial form (eq. axial2) and Quazi's σ_t (eq. Quazi) with
c·f_c where c/f_c = λ is meant; we use the dimensionally consistent form (docs/design.md §4.10).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .grid import Grid

__all__ = [
    "pfa",
    "contrasts",
    "diffraction_resolution",
    "cramer_rao_precision",
    "speckle_grains",
    "Detection",
    "detect",
    "refine_peak",
    "border_band",
    "interior_peaks",
]


def pfa(c: float | np.ndarray, n_grains: float) -> np.ndarray | float:
    """PFA = 1 − [1 − exp(−π C²/4)]^L (paper S6, eq. FR with C = (γ_max/γ_M)²), computed stably."""
    c = np.asarray(c, dtype=float)
    p_pixel = np.exp(-np.pi * c ** 2 / 4)
    out = -np.expm1(n_grains * np.log1p(-np.minimum(p_pixel, 1 - 1e-300)))
    return float(out) if out.ndim == 0 else out


def _mesh(grid: Grid) -> list[np.ndarray]:
    return np.meshgrid(*grid.axes, indexing="ij")


def _outside_mask(grid: Grid, centre: np.ndarray, radius: float, mesh: list[np.ndarray] | None = None) -> np.ndarray:
    c = (centre[0], centre[2]) if grid.ndim == 2 else (centre[0], centre[1], centre[2])
    d2 = sum((m - ci) ** 2 for m, ci in zip(mesh or _mesh(grid), c, strict=True))
    return d2 > radius ** 2


def border_band(grid: Grid, margin: float, mesh: list[np.ndarray] | None = None) -> np.ndarray:
    """Nodes closer than `margin` to the grid's border, on each axis with more than 2 nodes that spans
    more than 2·margin (a thinner axis has no interior: it is left alone)."""
    band = np.zeros(grid.shape, dtype=bool)
    for m, a in zip(mesh or _mesh(grid), grid.axes, strict=True):
        if a.size > 2 and a[-1] - a[0] > 2 * margin:
            band |= (m - a[0] < margin) | (a[-1] - m < margin)
    return band


def interior_peaks(gamma: np.ndarray, grid: Grid, margin: float, mesh: list[np.ndarray] | None = None) -> np.ndarray:
    """Nodes that are local maxima of γ (over their 3^d neighbourhood) and not in the border band: the
    candidates of a peak inside the region of interest. γ rising towards the border (e.g. under a
    scattering layer's surface) has its maxima on the border or in the band, not here."""
    from scipy.ndimage import maximum_filter

    local = gamma >= maximum_filter(gamma, size=3, mode="nearest")
    return local & ~border_band(grid, margin, mesh)


def contrasts(gamma: np.ndarray, grid: Grid, target: np.ndarray, exclusion_radius: float,
              value: float | None = None) -> tuple[float, float]:
    """(C_γ, C) for the target at position `target` (metres): C_γ = γ_t/mean(γ_out), C = (γ_t/γ_M)².

    γ_t is `value` if given (e.g. a sub-pixel peak), else γ at the nearest node; "outside" excludes a
    ball of exclusion_radius around the target (docs/design.md §4.8).
    """
    out = _outside_mask(grid, np.asarray(target, float), exclusion_radius)
    if not out.any():
        raise ValueError("exclusion_radius: covers the whole grid; nothing left outside the target")
    g_out = gamma[out]
    g_t = float(gamma[grid.nearest_index(target)]) if value is None else float(value)
    mean = float(g_out.mean())
    g_m = float(np.sqrt(np.mean(g_out.astype(np.float64) ** 2)))
    return g_t / mean, (g_t / g_m) ** 2


def diffraction_resolution(wavelength: float, aperture: float, depth: float) -> float:
    """δρ_D = λ/(2 sin α), α the half-angle under which the array aperture is seen from depth z
    (paper, main text after eq. G)."""
    sin_a = (aperture / 2) / np.hypot(aperture / 2, depth)
    return wavelength / (2 * sin_a)


def cramer_rao_precision(wavelength: float, resolution: float, c_gamma: float) -> tuple[float, float]:
    """(δρ_L, δz_L) = (δρ_D/√C_γ, λ/(4√2 π √C_γ)) (paper eq. loc; docs/design.md §4.10 axial form)."""
    c = max(float(c_gamma), 1e-12)
    return resolution / np.sqrt(c), wavelength / (4 * np.sqrt(2) * np.pi * np.sqrt(c))


def speckle_grains(grid: Grid, resolution: float, axial_resolution: float) -> float:
    """L = field-of-view volume / speckle-grain volume (δρ_D² δz in 3D, δρ_D δz in 2D) (paper S6)."""
    extent = [max(float(np.ptp(a)), s) for a, s in zip(grid.axes, grid.spacing, strict=True)]
    vol = float(np.prod(extent))
    grain = resolution * axial_resolution if grid.ndim == 2 else resolution ** 2 * axial_resolution
    return max(vol / grain, 1.0)


def refine_peak(gamma: np.ndarray, grid: Grid, index: tuple[int, ...]) -> tuple[np.ndarray, float]:
    """Sub-grid peak by a 3-point parabola along each axis; returns (position (x, y, z), value)."""
    pos = []
    val = float(gamma[index])
    for ax, (a, i) in enumerate(zip(grid.axes, index, strict=True)):
        off = 0.0
        if 0 < i < a.size - 1:
            lo = list(index)
            hi = list(index)
            lo[ax] -= 1
            hi[ax] += 1
            ym, y0, yp = float(gamma[tuple(lo)]), val, float(gamma[tuple(hi)])
            den = ym - 2 * y0 + yp
            if den < 0:
                off = float(np.clip(0.5 * (ym - yp) / den, -0.5, 0.5))
        step = a[1] - a[0] if a.size > 1 else 0.0
        pos.append(a[i] + off * step)
    p = np.array([pos[0], 0.0, pos[1]]) if grid.ndim == 2 else np.array(pos)
    return p, val


@dataclass
class Detection:
    """One detected target on one γ-map (SI units; the unit is in the name)."""

    fingerprint: str
    position_m: list[float]
    gamma_max: float
    c_gamma: float
    c_pfa: float
    pfa: float
    precision_m: list[float]  # [lateral δρ_L, axial δz_L]
    index: list[int]

    def as_dict(self) -> dict:
        return asdict(self)


def detect(gamma: np.ndarray, grid: Grid, wavelength: float, aperture: float, bandwidth: float, c0: float,
           name: str = "target", exclusion_radius: float | None = None, n_peaks: int = 1,
           n_grains: float | None = None, interior: bool = False) -> list[Detection]:
    """The n_peaks strongest maxima of a γ-map with contrasts, PFA and Cramér–Rao precision.

    Peaks are separated by exclusion_radius (default 2 δρ_D at the peak depth); each contrast is
    taken against the map outside every accepted peak's exclusion ball. ``interior=True`` keeps only
    local maxima of γ farther than δρ_D (at the grid's middle depth) from the border
    (`interior_peaks`): a maximum on or next to the border is, most often, the flank of something
    outside the region of interest — e.g. γ rising towards a scattering layer's surface — not a peak
    inside it (a heuristic: a real target within δρ_D of the border is missed too).
    """
    g = np.asarray(gamma, dtype=np.float32)
    work = g.copy()
    mesh = _mesh(grid)
    if interior:
        mid = 0.5 * (grid.z[0] + grid.z[-1])
        work[~interior_peaks(g, grid, diffraction_resolution(wavelength, aperture, max(mid, wavelength)),
                             mesh)] = -np.inf
    found: list[tuple[tuple[int, ...], np.ndarray, float, float]] = []
    axial_res = c0 / (2 * bandwidth)
    while len(found) < n_peaks:
        idx = np.unravel_index(int(np.argmax(work)), work.shape)
        if not np.isfinite(work[idx]) or work[idx] <= 0:
            break
        pos, val = refine_peak(g, grid, idx)
        res = diffraction_resolution(wavelength, aperture, max(pos[2], wavelength))
        rad = exclusion_radius if exclusion_radius is not None else 2 * res
        work[~_outside_mask(grid, pos, rad, mesh)] = -np.inf
        work[idx] = -np.inf  # even if refinement moved the peak farther than rad
        found.append((idx, pos, val, rad))
    if not found:
        return []
    outside = np.ones(g.shape, dtype=bool)
    for _, pos, _, rad in found:
        outside &= _outside_mask(grid, pos, rad, mesh)
    g_out = g[outside] if outside.any() else g.ravel()
    mean = float(g_out.mean())
    g_m = float(np.sqrt(np.mean(g_out.astype(np.float64) ** 2)))
    dets = []
    for idx, pos, val, _ in found:
        res = diffraction_resolution(wavelength, aperture, max(pos[2], wavelength))
        c_gamma = val / mean if mean > 0 else np.inf
        c = (val / g_m) ** 2 if g_m > 0 else np.inf
        L = n_grains if n_grains is not None else speckle_grains(grid, res, axial_res)
        dets.append(Detection(name, [float(v) for v in pos], float(val), float(c_gamma), float(c),
                              float(pfa(c, L)), [float(v) for v in cramer_rao_precision(wavelength, res, c_gamma)],
                              [int(i) for i in idx]))
    return dets
