"""Detection figures: contrasts, a calibrated false-alarm probability, Cramér–Rao precision, gain
(docs/design.md §4.8–4.11).

Contrasts, named apart (docs/design.md §4.8):
* ``c_gamma`` = γ(target) / mean(γ outside the target) — the paper's main-text figure (Fig. 2);
* ``c_pfa`` = (γ_max/γ_M)², γ_M = √⟨γ²⟩ outside — the quantity the paper's S6 writes as C;
* ``c_local`` = γ/γ_M(r), against the *local* null level of γ at the peak (fpcore.cfar): the amplitude
  contrast the false-alarm probability is computed from.

False alarm (docs/design.md §4.9). ``pfa`` of a detection is calibrated: the probability that the
maximum of target-free γ over the searched region reaches the observed local contrast, from a local
null level (physics: fpcore.background; CFAR: fpcore.cfar) and random-field theory for the maximum —
checked on target-free maps (tests/test_metrics.py, bench/validate_pfa.py). `paper_pfa` keeps the
paper's S6 formula for reference, with its slip corrected: the paper writes C = (γ_max/γ_M)² inside
exp(−π C²/4), but its own figure (C ≈ 6, L = 25³ → 1e−8) is the amplitude ratio C_γ = γ_max/⟨γ⟩, and the
Rayleigh tail it starts from is exp(−(γ/γ_M)²) = exp(−(π/4)(γ/⟨γ⟩)²). Fed the squared ratio, the formula
made target-free frames report PFA ≈ 1e−37 (measured); even with the amplitude ratio, a global mean and
a formula for L do not give an honest probability on non-stationary maps.

Precision (paper eq. loc and S5): lateral δρ_L = δρ_D/√C_γ with δρ_D = λ/(2 sin α); axial
δz_L = λ/(4√2 π √C_γ). The paper prints the axial form (eq. axial2) and Quazi's σ_t (eq. Quazi) with
c·f_c where c/f_c = λ is meant; we use the dimensionally consistent form (docs/design.md §4.10).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .cfar import DEFAULT_CFAR, NullModel, cfar_null_model
from .grid import Grid

__all__ = [
    "DEFAULT_MAX_PFA",
    "paper_pfa",
    "contrasts",
    "diffraction_resolution",
    "cramer_rao_precision",
    "resolution_cell",
    "Detection",
    "detect",
    "refine_peak",
    "border_band",
    "interior_peaks",
]


DEFAULT_MAX_PFA = 1e-3  # a detection is reported only below this calibrated PFA (docs/design.md §4.9)


def paper_pfa(c: float | np.ndarray, n_grains: float) -> np.ndarray | float:
    """The paper's S6 figure: PFA = 1 − [1 − exp(−π C²/4)]^L with C the *amplitude* contrast γ_max/⟨γ⟩
    (the paper prints C = (γ_max/γ_M)²: a slip, module doc) and L independent Rayleigh cells. For
    reference only: detections report the calibrated PFA of fpcore.cfar."""
    c = np.asarray(c, dtype=float)
    p_pixel = np.exp(-np.pi * c**2 / 4)
    out = -np.expm1(n_grains * np.log1p(-np.minimum(p_pixel, 1 - 1e-300)))
    return float(out) if out.ndim == 0 else out


def _mesh(grid: Grid) -> list[np.ndarray]:
    return list(np.meshgrid(*grid.axes, indexing="ij"))


def _outside_mask(grid: Grid, centre: np.ndarray, radius: float, mesh: list[np.ndarray] | None = None) -> np.ndarray:
    c = (centre[0], centre[2]) if grid.ndim == 2 else (centre[0], centre[1], centre[2])
    d2 = sum((m - ci) ** 2 for m, ci in zip(mesh or _mesh(grid), c, strict=True))
    return d2 > radius**2


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


def contrasts(
    gamma: np.ndarray, grid: Grid, target: np.ndarray, exclusion_radius: float, value: float | None = None
) -> tuple[float, float]:
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


def resolution_cell(
    wavelength: float, aperture: float, bandwidth: float, c0: float, depth: float
) -> tuple[float, float]:
    """(δρ_D at `depth`, c0/(2Δf)): the lateral and axial resolution cells (paper, main text after eq. G)."""
    return diffraction_resolution(wavelength, aperture, max(depth, wavelength)), c0 / (2 * bandwidth)


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


def _gamma_peak_near(
    gamma: np.ndarray, grid: Grid, index: tuple[int, ...], resolution: tuple[float, float]
) -> tuple[int, ...]:
    """The node of largest γ within half a resolution cell of `index`: the significance peaks where γ
    stands out most from its local level, the position estimate is γ's own peak (paper eq. loc)."""
    cells = [resolution[0]] * (grid.ndim - 1) + [resolution[1]]
    half = [max(1, int(round(0.5 * c / d))) for c, d in zip(cells, grid.spacing, strict=True)]
    box = tuple(slice(max(i - h, 0), i + h + 1) for i, h in zip(index, half, strict=True))
    sub = np.unravel_index(int(np.argmax(gamma[box])), gamma[box].shape)
    return tuple(int(b.start + j) for b, j in zip(box, sub, strict=True))


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
    c_local: float = 0.0  # γ/γ_M(r) against the local null level (module doc)
    significance: float = 0.0  # S = −ln P(T > T(r)) per node under the local null law (fpcore.cfar)

    def as_dict(self) -> dict:
        return asdict(self)


def detect(
    gamma: np.ndarray,
    grid: Grid,
    wavelength: float,
    aperture: float,
    bandwidth: float,
    c0: float,
    name: str = "target",
    exclusion_radius: float | None = None,
    n_peaks: int = 1,
    interior: bool = False,
    level: np.ndarray | None = None,
    visible: np.ndarray | None = None,
    max_pfa: float | None = DEFAULT_MAX_PFA,
    null: NullModel | None = None,
) -> list[Detection]:
    """The n_peaks most significant maxima of a γ-map with contrasts, calibrated PFA and Cramér–Rao precision.

    The map is searched on its local significance S (fpcore.cfar): γ² against a local null level —
    `level` (fpcore.background.NullLevel: the data's energy in the fingerprint's time support times the
    aperture factor) corrected by a censored cell-averaging CFAR, or the CFAR alone — so that a maximum
    under a bright interface and one in a dim, deep region are judged on the same scale, over the whole
    record, with no depth window to pick; nodes already decided (S ≥ 30) are ranked by γ itself
    (`NullModel.ranking`: the likelihood, not a target's own lobes' ratio to the level, picks the position).
    `visible` restricts the search (nodes where the fingerprint can be tested). Peaks are separated by
    exclusion_radius (default 2 δρ_D at the peak depth); `c_gamma` is taken against the map outside every
    accepted peak's exclusion ball. A peak is kept only when its calibrated PFA is below `max_pfa` (default
    1e-3; None keeps every peak, e.g. for figures).
    ``interior=True`` also drops maxima within δρ_D of the grid's border (`interior_peaks`, a heuristic
    kept as an option: the default does not need it).
    """
    g = np.asarray(gamma, dtype=np.float32)
    mid = 0.5 * (grid.z[0] + grid.z[-1])
    res_mid, axial_res = resolution_cell(wavelength, aperture, bandwidth, c0, mid)
    nm = (
        null
        if null is not None
        else cfar_null_model(DEFAULT_CFAR, g, grid, (res_mid, axial_res), level=level, visible=visible)
    )
    sig = nm.significance
    work = np.where(nm.visible, nm.ranking(g, nm.decided(max_pfa)), -np.inf).astype(np.float64)
    mesh = _mesh(grid)
    if interior:
        work[~interior_peaks(g, grid, res_mid, mesh)] = -np.inf
    found: list[tuple[tuple[tuple[int, ...], tuple[int, ...]], np.ndarray, float, float]] = []
    while len(found) < n_peaks:
        top = tuple(int(i) for i in np.unravel_index(int(np.argmax(work)), work.shape))
        if not np.isfinite(work[top]):
            break
        idx = _gamma_peak_near(g, grid, top, (res_mid, axial_res))
        pos, val = refine_peak(g, grid, idx)
        res = diffraction_resolution(wavelength, aperture, max(pos[2], wavelength))
        rad = exclusion_radius if exclusion_radius is not None else 2 * res
        work[~_outside_mask(grid, pos, rad, mesh)] = -np.inf
        work[top] = -np.inf  # even if refinement moved the peak farther than rad
        found.append(((top, idx), pos, val, rad))
    if not found:
        return []
    outside = np.ones(g.shape, dtype=bool)
    for _, pos, _, rad in found:
        outside &= _outside_mask(grid, pos, rad, mesh)
    g_out = g[outside] if outside.any() else g.ravel()
    mean = float(g_out.mean())
    g_m = float(np.sqrt(np.mean(g_out.astype(np.float64) ** 2)))
    dets = []
    for (top, idx), pos, val, _ in found:
        res = diffraction_resolution(wavelength, aperture, max(pos[2], wavelength))
        c_gamma = val / mean if mean > 0 else np.inf
        c = (val / g_m) ** 2 if g_m > 0 else np.inf
        s = float(sig[top])
        p = nm.pfa(s)
        if max_pfa is not None and not p < max_pfa:
            continue
        dets.append(
            Detection(
                name,
                [float(v) for v in pos],
                float(val),
                float(c_gamma),
                float(c),
                float(p),
                [float(v) for v in cramer_rao_precision(wavelength, res, c_gamma)],
                [int(i) for i in idx],
                float(np.sqrt(max(float(nm.statistic[top]), 0.0))),
                s,
            )
        )
    return dets
