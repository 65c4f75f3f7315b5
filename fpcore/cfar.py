"""A calibrated false-alarm probability for γ-maps: local background, measured smoothness, random-field
tail (docs/design.md §4.9).

Why not the paper's formula as printed. Under the null hypothesis (paper Supplementary S6: the
reflection-matrix coefficients are i.i.d.) the numerator of γ is a linear form of R, hence circular
complex Gaussian, so γ is Rayleigh: P(γ > g) = exp(−g²/γ_M²), γ_M² = ⟨γ²⟩. The paper's S6 writes
C = (γ_max/γ_M)² inside exp(−π C²/4): a notational slip — its own figure (C ≈ 6, L = 25³ → 1e−8) is the
amplitude ratio; the exponent that follows from its Rayleigh law is (γ/γ_M)². Two further facts make
any single global formula dishonest on real maps (measured on the simulator's fog, docs/design.md §4.9):

* the background is not stationary: γ's level rises under strong interfaces and falls with depth, so
  the scale γ_M must be estimated *locally*;
* the pixels are not independent: a γ-map is a smooth random field whose grains are the resolution
  cell, so "L independent cells" is not a count of pixels, nor a formula of the resolution alone.

What this module does (cell-averaging CFAR in the radar sense, Rohling 1983, with random-field theory
for the maximum, Worsley et al. 1996):

1. **Local scale** (`NullModel.power`): γ² is first divided by a physical null level when one is given
   (fpcore.background: the data's energy in the fingerprint's time support × the aperture factor);
   what remains is averaged over a training window of ± `window_cells` resolution cells around each
   node (± 6 lateral × ± 3 axial), censoring nodes that stand out (T > `censor` against a robust
   per-depth median) together with a guard region of one resolution cell: a censored cell-averaging
   CFAR. The **compact** setting, the default (`CFAR_SETTINGS["compact"]`, `DEFAULT_CFAR`), trains on ± 1
   axial cell by ± 10 lateral cells in 2-D, ± 2 in 3-D (`COMPACT_WINDOW_CELLS`), leaves the cell under
   test's ± 0.5 cell out of its own level (`cut_guard`) and censors the nodes 30× above the window's median
   (`local_median`, one node per resolution cell; `censor_reference="median"`): it follows the
   single-scattering level's peak under the surface and its lateral concentration, which the physical level
   does not carry, and is calibrated on the focused speckle where "wide" is not (docs/design.md §4.9,
   measured). The median is the reference because half the window may be a target's own main lobe and
   sidelobes without raising it: in water, where those lobes are the whole background, a reference that
   they raise (the window's mean) left them in the training and masked the target. "wide" (± 6 × ± 3 cells,
   censoring at 8× the per-depth median, the node in its own level) is the earlier default, kept as an
   option; `cfar_null_model("both", …)` takes the greater of the two levels. Optionally (`greatest_of`,
   off by default) the level is the greater of the window's mean and the means of its two halves along each
   lateral axis (GO-CFAR, Hansen & Sawyers 1980), so that a level edge — the border of the insonified
   region — is not averaged into its bright side; it halved the false alarms on the 2-D diffusion fog
   under the previous window but loses targets whose own sidelobes fill one half (docs/design.md §4.9).
   Nodes outside `visible` neither train nor are searched.
2. **Statistic**: T(r) = γ²(r)/γ_M²(r), exponentially distributed (χ²₂/2) under the null. The level is
   estimated from n(r) independent training cells, counted per node (a node's own guard region,
   ± `own_guard` cells, not counted as missing), so the tail is the CA-CFAR law (1 + T/n)^(−n) = e^{−S},
   S = n ln(1 + T/n): `NullModel.significance`. (Optionally, `heavy_tails=True`, a K law of shape ν
   fitted to the training window's log-moments first; off by default — see step 2b.)
2b. **The map's own tail** (an empirical null in Efron's sense, 2004): S is exponential under the
   speckle law, but measured on the simulator's fog its pooled tail is heavier — P(S > s)/e^{−s} = 1.0
   at s = 6, 2.2 at 10, 8 at 14 (480 2-D fog maps, worst under the surface) — from structure at
   scales below the training window, which a local K law cannot see (its log-moment estimator has a
   standard deviation of ≈ 0.13 on ~100 cells, while Rayleigh and ν = 10 differ by 0.05; where it does
   fire it is mostly on a target's own sidelobes, costing power). So each map's tail scale β is fitted
   on its own visible nodes: the maximum-likelihood scale of the excesses S − u of the nodes with
   u < S < U (`tail_fit`, default (4.5, 11): above the bulk, below where targets live; an exponential
   truncated at U), floored at 1 (never lighter than speckle), and S ← u + (S − u)/β above u. On
   speckle (i.i.d. data) β = 1 and nothing changes. Peaks already decided (S ≥ `SURE_SIGNIFICANCE` =
   30, PFA < 1e-3 on our largest grids even at β = 1.5) and their ± 2-cell guard are left out of the
   fit, so a strong target's sidelobes do not discount the rest of its map; the fog never reached
   S = 21 in 720 target-free maps, so this costs the null nothing. Maps of fewer than
   `MIN_FIT_RESELS` = 1000 resels (a few mm² in 2-D) keep β = 1: at ≈ 1 % of speckle above u they hold
   too few independent exceedances, and a target's own skirt would dominate the fit.
3. **Smoothness** (`NullModel.fwhm`): the roughness of the underlying Gaussian field per axis from the
   lag-one autocorrelation ρ₁ of T (ρ_T = |μ|², so for a Gaussian-shaped correlation λ = −ln ρ₁/h²),
   as FWHM = √(4 ln 2/λ) — measured on the map itself, not taken from a formula.
4. **Maximum**: the probability that the maximum of the null field over a region exceeds t is the
   expected Euler characteristic of the excursion set (Worsley's χ² field with ν = 2 degrees of
   freedom), E[EC] = Σ_d R_d ρ_d(2 S_eff), with R_d the resel counts of the region (its intrinsic
   volumes in FWHM units); PFA = 1 − exp(−E[EC]). For a box of N independent-looking resels this is
   ≈ N e^{−t} times a factor t^{D/2} that the "L independent cells" model misses — which is why that
   model, even with the right exponent, under-reports false alarms in the tail.
5. **Search order** (`NullModel.ranking`; fpcore.metrics.detect, the tracker's gates): the maxima of S,
   except among decided nodes (S ≥ `SURE_SIGNIFICANCE`, PFA ≈ 3e-6 over a 76×76×143 grid; `detect` uses its
   own threshold's S when `max_pfa` is stricter), which are ranked by γ itself. There the PFA is far
   below the detection threshold, and the ratio to a local level is shaped by the
   target's own lobes (in water they are the whole background: the compact window put the Born marker's
   most significant node on a lobe 0.95 mm off); γ, the likelihood (paper eq. loc), picks the position.

The calibration of this PFA is checked on target-free maps (i.i.d. noise, and the simulator's 2-D and
3-D fog) in `tests/test_metrics.py` and `bench/validate_pfa.py`: the fraction of maps whose maximum
reports PFA < α stays ≤ α (measured figures: README, docs/design.md §4.9).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from math import gamma as gamma_fn
from math import log, pi
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import uniform_filter, uniform_filter1d
from scipy.special import digamma, gammaln, kve

from .grid import Grid

__all__ = [
    "NullModel",
    "null_model",
    "COMPACT_WINDOW_CELLS",
    "CFAR_SETTINGS",
    "CFAR_NAMES",
    "DEFAULT_CFAR",
    "check_cfar",
    "cfar_null_model",
    "greater_level",
    "ec_density",
    "max_tail",
    "resels_box",
    "resels_ellipsoid",
    "fit_tail_scale",
]

_FOUR_LN2 = 4 * log(2)
#: The compact training window's half-widths (lateral, axial) in resolution cells, by the map's dimension
#: (``CFAR_SETTINGS["compact"]``; docs/design.md §4.9): ± 1 axial cell, where the level changes fastest (the
#: beads' single-scattering peak under the surface, attenuation), and about 20–25 lateral cells, a line in
#: 2-D, a square in 3-D, narrow enough to follow the single-scattering level's lateral concentration.
COMPACT_WINDOW_CELLS: dict[int, tuple[float, float]] = {2: (10.0, 1.0), 3: (2.0, 1.0)}
#: Named CFAR settings (`cfar_null_model`; docs/design.md §4.9): "compact", the default — the compact window,
#: the cell under test's ± 0.5 cell left out of its own level, censoring the nodes 30× above the window's
#: median (calibrated on the focused single-scattering speckle, where "wide" is not, and keeps a target's
#: own lobes out of its level in water); "wide" — ± 6 × ± 3 cells, censoring at 8× the per-depth median, the
#: node in its own training (`null_model`'s defaults; the earlier default); "both" — the greater of the two.
CFAR_SETTINGS: dict[str, dict[str, Any]] = {
    "wide": {},
    "compact": {"window_cells": "compact", "censor": 30.0, "censor_reference": "median", "cut_guard": 0.5},
}
CFAR_NAMES: tuple[str, ...] = (*CFAR_SETTINGS, "both")
DEFAULT_CFAR = "compact"


def check_cfar(name: str, field: str = "cfar") -> str:
    """`name` if it is a CFAR setting (`CFAR_NAMES`), else a ValueError naming `field` and the choices."""
    if name not in CFAR_NAMES:
        raise ValueError(f"{field}: expected one of {', '.join(CFAR_NAMES)}, got {name!r}")
    return name


SURE_SIGNIFICANCE = 30.0  # S of a decided peak, left out of the map's own tail fit (module doc, step 2b)
MIN_FIT_RESELS = 1000.0  # maps with fewer resels keep the speckle law (β = 1): too few exceedances to fit


def ec_density(u: float, d: int, nu: int = 2) -> float:
    """ρ_d(u): Euler-characteristic density of a χ² field with ν degrees of freedom at level u, in
    resel units (Worsley 1994, Table 2; d = 0…3)."""
    if u <= 0:
        return 1.0 if d == 0 else 0.0
    from scipy.stats import chi2

    if d == 0:
        return float(chi2.sf(u, nu))
    base = u ** ((nu - d) / 2) * np.exp(-u / 2) / (2 ** ((nu - 2) / 2) * gamma_fn(nu / 2))
    c = (_FOUR_LN2 / (2 * pi)) ** (d / 2)
    if d == 1:
        poly = 1.0
    elif d == 2:
        poly = u - (nu - 1)
    elif d == 3:
        poly = u**2 - (2 * nu - 1) * u + (nu - 1) * (nu - 2)
    else:
        raise ValueError(f"d: expected 0…3, got {d}")
    return float(c * base * poly)


def resels_box(sides: np.ndarray) -> np.ndarray:
    """Resel counts (R_0, …, R_D) of a box whose sides are given in FWHM units (intrinsic volumes)."""
    a = np.asarray(sides, float)
    if a.size == 1:
        return np.array([1.0, a[0]])
    if a.size == 2:
        return np.array([1.0, a.sum(), a.prod()])
    return np.array([1.0, a.sum(), a[0] * a[1] + a[1] * a[2] + a[0] * a[2], a.prod()])


def resels_ellipsoid(semi_axes: np.ndarray) -> np.ndarray:
    """Resel counts of an ellipsoid (semi-axes in FWHM units), through the ball of equal volume."""
    a = np.asarray(semi_axes, float)
    r = float(np.prod(a) ** (1 / a.size))
    if a.size == 2:
        return np.array([1.0, pi * r, pi * r**2])
    return np.array([1.0, 4 * r, 2 * pi * r**2, 4 / 3 * pi * r**3])


def max_tail(t: float, resels: np.ndarray) -> float:
    """P(max of the null field over a region with these resel counts > t), t on the exponential scale
    (the significance S_eff of `NullModel`, which already carries the CA-CFAR law).

    E[EC] of the excursion set at u = 2t (χ² field, ν = 2; Worsley 1994); PFA = 1 − exp(−E[EC]), and 1
    where E[EC] ≤ 0 at low thresholds (t ≤ 5, where the expansion fails and the maximum exceeds t almost
    surely). Above, every density is positive and carries e^{−u/2}: E[EC] = 0 there is its underflow
    (t ≳ 700), a PFA below the smallest double, returned as 0.
    """
    if not np.isfinite(t) or t <= 0:
        return 0.0 if t > 0 else 1.0
    u = 2 * float(t)
    ec = sum(float(r) * ec_density(u, d) for d, r in enumerate(resels))
    if ec <= 0:
        return 0.0 if t > 5.0 else 1.0
    return float(-np.expm1(-ec))


@dataclass
class NullModel:
    """The local null model of one γ-map (see the module doc).

    power: γ_M²(r), the local mean of γ² under the null, on the grid;
    fwhm: FWHM of the underlying Gaussian field per grid axis, in nodes; train_cells: independent cells
    behind each node's level estimate; statistic: T = γ²/γ_M² on the grid; n_maps: the number of statistics'
    maps this one was chosen from (fpcore.locate.union_of): every PFA it reports is n_maps × its own, capped at
    1 (docs/design.md §4.14, eq. W2, the Bonferroni bound), and `threshold` inverts that.
    """

    grid: Grid
    power: np.ndarray
    fwhm: np.ndarray
    train_cells: np.ndarray
    statistic: np.ndarray
    shape: np.ndarray  # K-distribution shape ν per node (inf: Rayleigh speckle)
    visible: np.ndarray  # nodes searched (and counted as cells)
    tail_fit: tuple[float, float] | None = (4.5, 11.0)  # (u, U) of the map's own tail fit (step 2b)
    guard_nodes: tuple[int, ...] = (1, 1, 1)  # ± nodes per axis of two resolution cells (step 2b's guard)
    n_maps: int = 1  # maps this one was chosen from (eq. W2): its PFAs are n_maps × its own, capped at 1

    _significance: np.ndarray | None = None
    _tail_scale: float = 1.0

    @property
    def significance(self) -> np.ndarray:
        """S(r) = −ln P(T > T(r)) under the local law: the statistic on the exponential scale (equal to T
        where the background is Rayleigh speckle); detections are the maxima of S."""
        if self._significance is None:
            # S ≤ T for the K law (heavier tail); below T = 4 (PFA ≈ 1 over any region of a few resels)
            # the exact value decides nothing, so the law is evaluated only above it.
            sig = self.statistic.astype(np.float64, copy=True)
            hot = (sig > 4.0) & np.isfinite(self.shape)
            if hot.any():
                sig[hot] = -np.log(np.maximum(k_tail(self.statistic[hot], self.shape[hot]), 1e-300))
            # CA-CFAR: a level estimated from n independent cells turns the tail e^{−t} into
            # (1 + t/n)^{−n} = e^{−n ln(1 + t/n)}; n is local (fewer training cells near the grid's edges).
            n = np.maximum(np.asarray(self.train_cells, np.float64), 2.0)
            sig = n * np.log1p(sig / n)
            if self.tail_fit is not None and self.resels()[-1] >= MIN_FIT_RESELS:
                u, upper = self.tail_fit
                fit = self.visible
                sure = (sig >= SURE_SIGNIFICANCE) & self.visible
                if sure.any():  # a decided peak's own skirt is not evidence about the null's tail
                    near = uniform_filter(
                        sure.astype(np.float32), [2 * r + 1 for r in self.guard_nodes], mode="constant"
                    )
                    fit = fit & ~(near > 1e-6)
                self._tail_scale = fit_tail_scale(sig[fit], u, upper)
                above = sig > u
                sig[above] = u + (sig[above] - u) / self._tail_scale
            self._significance = sig.astype(np.float32)
        return self._significance

    def ranking(self, gamma: np.ndarray, sure: float = SURE_SIGNIFICANCE) -> np.ndarray:
        """The order in which nodes are searched: S below `sure` (default `SURE_SIGNIFICANCE`); at or above
        it, where a peak is decided (PFA ≈ 3e-6 over a 76×76×143 grid at S = 30, far below the default
        threshold), sure + γ/max γ — among decided nodes the likelihood (paper eq. loc), not the ratio to a
        local level that a target's own lobes shape, picks the position. Pass a higher `sure` (`threshold`)
        when the detection threshold is stricter than that."""
        sig = self.significance.astype(np.float64)
        g = np.asarray(gamma, np.float64)
        seen = np.isfinite(g) & self.visible
        top = float(g[seen].max()) if seen.any() else 0.0
        score = sure + np.nan_to_num(g, nan=0.0) / max(top, 1e-300)
        return np.where(sig >= sure, score, sig)

    def threshold(self, pfa: float) -> float:
        """The significance S whose calibrated PFA over the visible nodes is `pfa` (bisection on `max_tail`;
        with `n_maps` > 1, the S where n_maps × max_tail reaches it, eq. W2)."""
        resels = self.resels()
        lo, hi = 0.0, 800.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self._union(max_tail(mid, resels)) > pfa else (lo, mid)
        return hi

    def decided(self, max_pfa: float | None) -> float:
        """The S above which `ranking` orders by γ for a search kept below `max_pfa`: `SURE_SIGNIFICANCE`, or
        the threshold's own S where `max_pfa` is stricter than the PFA at S = 30 (None: no threshold)."""
        if max_pfa is None or self.pfa(SURE_SIGNIFICANCE) < max_pfa:
            return SURE_SIGNIFICANCE
        return max(SURE_SIGNIFICANCE, self.threshold(max_pfa))

    @property
    def tail_scale(self) -> float:
        """β, the map's own tail scale on the significance scale (module doc, step 2b; 1: speckle)."""
        _ = self.significance
        return self._tail_scale

    def resels(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Resel counts of the nodes in `mask` (default: the visible ones), through their volume and the
        grid box's shape: R_D scaled by the fraction of nodes, lower orders by its power d/D."""
        mask = self.visible if mask is None else mask
        shape = np.array(self.grid.shape, float)
        keep = shape > 1
        sides = shape[keep] / self.fwhm[keep]
        r = resels_box(sides)
        frac = float(np.count_nonzero(mask)) / mask.size
        dim = len(r) - 1
        return np.array([1.0] + [r[d] * frac ** (d / dim) for d in range(1, dim + 1)])

    def pfa(self, value: float, mask: np.ndarray | None = None, resels: np.ndarray | None = None) -> float:
        """Calibrated false-alarm probability of a maximum S = `value` (`significance`) over `mask`
        (default: the visible nodes); × `n_maps` (eq. W2)."""
        return self._union(max_tail(value, self.resels(mask) if resels is None else resels))

    def gate_pfa(self, value: float, radius_nodes: np.ndarray) -> float:
        """PFA of a maximum S = `value` found in an ellipsoidal gate with these semi-axes (nodes); × `n_maps`
        (eq. W2)."""
        keep = np.array(self.grid.shape) > 1
        semi = np.asarray(radius_nodes, float)[keep] / self.fwhm[keep]
        return self._union(max_tail(value, resels_ellipsoid(np.maximum(semi, 1e-6))))

    def _union(self, pfa: float) -> float:
        """Eq. (W2): a PFA of this map, chosen among `n_maps` statistics' maps: n_maps × its own, capped at 1."""
        return min(1.0, int(self.n_maps) * pfa)


def _lag1_fwhm(t: np.ndarray, valid: np.ndarray, axis: int) -> float:
    """FWHM (nodes) along `axis` from the lag-one autocorrelation of T over valid pairs."""
    if t.shape[axis] < 3:
        return 1.0
    a = np.moveaxis(t, axis, -1)
    v = np.moveaxis(valid, axis, -1)
    pair = v[..., 1:] & v[..., :-1]
    if pair.sum() < 16:
        return 1.0
    x, y = a[..., :-1][pair], a[..., 1:][pair]
    x = x - x.mean()
    y = y - y.mean()
    rho = float((x * y).mean() / max(np.sqrt((x * x).mean() * (y * y).mean()), 1e-30))
    rho = min(max(rho, 1e-6), 1 - 1e-9)
    lam = -np.log(rho)  # per node²
    return float(np.sqrt(_FOUR_LN2 / lam))


def fit_tail_scale(s: np.ndarray, u: float, upper: float, min_nodes: int = 20) -> float:
    """β ≥ 1: maximum-likelihood scale of the excesses y = s − u of the values in (u, upper), for an
    exponential law truncated at w = upper − u (module doc, step 2b). The likelihood equation
    ⟨y⟩ = β − w/(e^{w/β} − 1) is solved for β by bisection (⟨y⟩ grows with β, from 0 to w/2)."""
    v = np.asarray(s, np.float64)
    y = v[(v > u) & (v < upper)] - u
    if y.size < min_nodes:
        return 1.0
    w = upper - u
    m = float(y.mean())

    def mean_excess(beta: float) -> float:
        return beta - w / np.expm1(w / beta)

    if m <= mean_excess(1.0):
        return 1.0
    if m >= 0.5 * w * (1 - 1e-9):
        return 1e3
    lo, hi = 1.0, 2.0
    while mean_excess(hi) < m and hi < 1e3:
        lo, hi = hi, 2 * hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mean_excess(mid) < m else (lo, mid)
    return 0.5 * (lo + hi)


def k_tail(t: np.ndarray | float, nu: np.ndarray | float) -> np.ndarray:
    """P(T > t) for a unit-mean K-distributed intensity of shape ν (Jakeman & Pusey 1976):
    2/Γ(ν) (ν t)^{ν/2} K_ν(2√(ν t)); ν → ∞ is the exponential law e^{−t} of Rayleigh speckle."""
    tv: np.ndarray = np.maximum(np.asarray(t, float), 0.0)
    nv = np.broadcast_to(np.asarray(nu, float), tv.shape)
    out = np.exp(-tv)
    fin = np.isfinite(nv) & (nv < 200) & (tv > 0)
    if fin.any():
        n, tt = nv[fin], tv[fin]
        x = 2 * np.sqrt(n * tt)
        log_p = np.log(2) - gammaln(n) + 0.5 * n * np.log(n * tt) + np.log(kve(n, x)) - x
        out = out.copy()
        out[fin] = np.exp(np.minimum(log_p, 0.0))
    return out


def k_shape(log_moment: np.ndarray) -> np.ndarray:
    """ν of a K-distribution from Δ = ⟨ln T⟩ − ln⟨T⟩ = ψ(ν) − ln ν − γ_E (the log-moment estimator);
    Δ ≥ −γ_E − 1e-3 (as light-tailed as Rayleigh or lighter) gives ν = ∞."""
    target = np.asarray(log_moment, float) + np.euler_gamma
    grid_nu = np.logspace(-1, 2.3, 400)
    f = digamma(grid_nu) - np.log(grid_nu)
    nu = np.interp(target, f, grid_nu, left=grid_nu[0], right=np.inf)
    return np.where(target >= f[-1], np.inf, nu)


def null_model(
    gamma: np.ndarray,
    grid: Grid,
    resolution: tuple[float, float],
    level: np.ndarray | None = None,
    visible: np.ndarray | None = None,
    window_cells: tuple[float, float] | str | None = None,
    censor: float = 8.0,
    heavy_tails: bool = False,
    own_guard: float = 2.0,
    tail_fit: tuple[float, float] | None = (4.5, 11.0),
    greatest_of: bool = False,
    cut_guard: float = 0.0,
    censor_reference: str = "depth",
    axial_greatest_of: bool = False,
) -> NullModel:
    """Estimate the local null model of a γ-map (module doc, steps 1–3).

    resolution: (lateral, axial) resolution cell in metres (δρ_D, c0/(2Δf)): the unit of the training
    window (± `window_cells` cells laterally and in depth, default ± 6 × ± 3: measured on 2-D fog, ± 12 × ± 6
    over the physical level gained power on sparse scatterers but let the false alarms rise to 3α at
    α = 0.01; "compact": `COMPACT_WINDOW_CELLS` of the map's dimension) and of the guard region around
    censored nodes. `CFAR_SETTINGS["compact"]` holds the settings calibrated on the focused speckle.
    level: a physical null level of γ² known up to a constant (fpcore.background: the data's energy in
    the fingerprint's own time support times the aperture factor); the CFAR then only corrects what it
    leaves (default: none, γ² itself). visible: nodes where the fingerprint can be tested (the others
    neither train nor count as cells). heavy_tails: fit a local K law (step 2, off by default); tail_fit: the
    (u, U) range of the map's own tail fit (step 2b; None: the speckle law as is); greatest_of: the level
    is the greater of the full window's and each lateral half's (step 1, GO-CFAR; off by default).
    cut_guard: ± resolution cells around the cell under test left out of its own training mean (the
    radar CA-CFAR's guard cells; 0, the default: the window's mean includes the node itself, which masks a
    target with its own echo). censor_reference: what `censor` compares a node with before it is left out
    of training — "depth" (default), the robust per-depth median; "local", the window's uncensored mean
    around it (with the same guard); or "median", the window's median (`local_median`), which a target's own
    lobes do not raise. censor = inf censors nothing. axial_greatest_of: the level is the greater of the
    training window's and of each of its two axial sides' (the nodes above, the nodes below the cell under test,
    each less the guard box; GO-CFAR along depth, step 1; off by default, docs/design.md §4.9), with the
    training-cell count of the one chosen. The "compact" setting censors only nodes 30× above the window's
    median (a null node does so with probability ≈ e^{−30}): a target's main lobe and sidelobes and
    other strong targets in the window, not the background's own bright grains, whose removal biased the
    level low on the focused speckle (§4.9).
    """
    g2 = np.asarray(gamma, np.float64) ** 2
    if level is not None:
        g2 = g2 / np.maximum(np.asarray(level, np.float64), 1e-300)
    nd = g2.ndim
    vis = np.ones(g2.shape, bool) if visible is None else np.asarray(visible, bool)
    lat_res, ax_res = resolution
    if window_cells is None:
        window_cells = (6.0, 3.0)
    elif window_cells == "compact":
        window_cells = COMPACT_WINDOW_CELLS[min(max(nd, 2), 3)]
    elif isinstance(window_cells, str):
        raise ValueError(f"window_cells: expected (lateral, axial) cells or 'compact', got {window_cells!r}")
    cells = [lat_res] * (nd - 1) + [ax_res]
    half = [
        max(int(round(w * c / s)), 2)
        for w, c, s in zip([window_cells[0]] * (nd - 1) + [window_cells[1]], cells, grid.spacing, strict=True)
    ]
    sizes = [min(2 * h + 1, n) for h, n in zip(half, g2.shape, strict=True)]

    if censor_reference not in ("depth", "local", "median"):
        raise ValueError(f"censor_reference: expected 'depth', 'local' or 'median', got {censor_reference!r}")
    # The cell under test's guard box (nodes per axis), left out of its own training mean.
    gsizes = (
        [
            min(2 * max(1, int(np.ceil(cut_guard * c / s))) + 1, n)
            for c, s, n in zip(cells, grid.spacing, g2.shape, strict=True)
        ]
        if cut_guard > 0
        else None
    )

    def box_sum(values: np.ndarray, box: list[int]) -> np.ndarray:
        return uniform_filter(values, box, mode="constant") * float(np.prod(box))

    def local_sums(values: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mean of `values` over the window's `weights`, NaN where none; the weights' sum in the window)."""
        s = box_sum(values * weights, sizes)
        n = box_sum(weights, sizes)
        if gsizes is not None:  # CA-CFAR: the window less the guard box around the cell under test
            s_g, n_g = box_sum(values * weights, gsizes), box_sum(weights, gsizes)
            ring = n - n_g > 0.25 * n  # else (a window mostly guard, at the grid's edges) the whole window
            s, n = np.where(ring, s - s_g, s), np.where(ring, n - n_g, n)
        return np.where(n > 1e-6, s / np.maximum(n, 1e-30), np.nan), n

    def local_mean(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
        return local_sums(values, weights)[0]

    # Robust first pass: the local median of γ² over visible nodes (exponential: median = ln 2 × mean),
    # through per-depth medians smoothed over the depth window.
    med = depth_median(g2, vis) / np.log(2)
    med = uniform_filter1d(med, sizes[-1], mode="nearest")
    if censor_reference == "median" and np.isfinite(censor):
        # floored at 1e-3 of the depth's median: a window mostly at γ = 0 would censor all the rest
        t0 = g2 / np.maximum(local_median(g2, vis, half, cells, grid.spacing), np.maximum(1e-3 * med, 1e-300))
    elif censor_reference == "local" and np.isfinite(censor):
        t0 = g2 / np.maximum(np.nan_to_num(local_mean(g2, vis.astype(np.float64)), nan=np.inf), 1e-300)
    else:
        t0 = g2 / np.maximum(med, 1e-300)
    hot = ((t0 > censor) & vis).astype(np.float32)

    def guard(n_cells: float) -> np.ndarray:
        """Censored nodes dilated by a guard of `n_cells` resolution cells (a separable box)."""
        if not hot.any():
            return np.zeros(hot.shape, bool)
        radius = [max(1, int(np.ceil(n_cells * c / s))) for c, s in zip(cells, grid.spacing, strict=True)]
        return uniform_filter(hot, [2 * r + 1 for r in radius], mode="constant") > 1e-6

    train = (vis & ~guard(1.0)).astype(np.float64)
    power, count = local_sums(g2, train)  # count: the training nodes in the window (less the guard box)
    if axial_greatest_of:
        for side_power, side_count in axial_sides(g2, train, sizes, gsizes):
            use = np.isfinite(side_power) & ~(side_power <= power)  # where the side is brighter (or the ring empty)
            power = np.where(use, side_power, power)
            count = np.where(use, side_count, count)
    if greatest_of:
        # GO-CFAR (Hansen & Sawyers 1980) across each lateral axis: the larger of the window's two
        # lateral halves, where a half holds at least a quarter of its nodes in training. At a level
        # edge (the border of the insonified region) the full window averages the dark side in and
        # under-estimates the bright side; the bright half does not.
        for axis in range(nd - 1):
            half = list(sizes)
            h = sizes[axis] // 2
            half[axis] = h + 1
            for side in (-1, 1):
                shift = [0] * nd
                shift[axis] = side * (h // 2)
                num = uniform_filter(g2 * train, half, mode="constant", origin=shift)
                den = uniform_filter(train, half, mode="constant", origin=shift)
                power = np.fmax(power, np.where(den > 0.25, num / np.maximum(den, 1e-30), 0.0))
    power = np.where(np.isfinite(power), power, np.broadcast_to(med, g2.shape))
    stat = g2 / np.maximum(power, 1e-300)
    nu = np.full(g2.shape, np.inf)
    if heavy_tails:
        # The shape is estimated on the training nodes (what stands out is censored with its guard).
        n = local_mean(np.ones_like(stat), train)  # support of the window (NaN where none trains)
        m1 = local_mean(stat, train)
        ml = local_mean(np.log(np.maximum(stat, 1e-12)), train)
        ok = np.isfinite(n) & np.isfinite(m1) & np.isfinite(ml)
        nu = np.where(ok, k_shape(np.where(ok, ml - np.log(np.maximum(m1, 1e-30)), 0.0)), np.inf)
    fwhm = np.array([_lag1_fwhm(stat, train > 0, ax) for ax in range(nd)])
    # Independent training cells per node: the training nodes in its window over the nodes per resel.
    # As in radar CA-CFAR, the cell under test's own guard region is not training by design: nodes
    # censored within ± `own_guard` cells of a node (its own peak and sidelobes) do not count as missing.
    if own_guard > 0:
        near = [max(1, int(np.ceil(own_guard * c / s))) * 2 + 1 for c, s in zip(cells, grid.spacing, strict=True)]
        censored = (vis & (train == 0)).astype(np.float64)
        count += uniform_filter(censored, near, mode="constant") * float(np.prod(near))
    train_cells = np.maximum(count / float(np.prod(fwhm)), 2.0)
    level_out = power if level is None else power * np.asarray(level, np.float64)
    return NullModel(
        grid,
        np.ascontiguousarray(level_out, dtype=np.float32),
        fwhm,
        train_cells.astype(np.float32),
        stat.astype(np.float32),
        nu,
        vis,
        tail_fit,
        tuple(max(1, int(np.ceil(2.0 * c / s))) for c, s in zip(cells, grid.spacing, strict=True)),
    )


def _one_sided(x: np.ndarray, axis: int, near: int, far: int, side: int) -> np.ndarray:
    """Σ x over the offsets near … far (inclusive, ≥ 1) from each node along `axis`, on `side` (−1: lower
    indices, +1: higher), zero beyond the array (cumulative sums)."""
    n = x.shape[axis]
    c = np.concatenate([np.zeros_like(np.take(x, [0], axis=axis)), np.cumsum(x, axis=axis)], axis=axis)
    i = np.arange(n)
    if side > 0:
        hi, lo = np.minimum(i + far + 1, n), np.minimum(i + near, n)
    else:
        hi, lo = np.maximum(i - near + 1, 0), np.maximum(i - far, 0)
    return np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)


def axial_sides(
    g2: np.ndarray, train: np.ndarray, sizes: list[int], gsizes: list[int] | None
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(mean of g2 over the training nodes, their count) in each axial side of the training window — the nodes
    above and the nodes below the cell under test (offsets 1 … half the window along depth, the last axis, the
    window's full lateral extent), each less the guard box `gsizes` (None: no guard); NaN where a side holds
    fewer than a quarter of its nodes in training (at the grid's top and bottom, a side is mostly outside)."""
    axis = g2.ndim - 1
    lateral = [*sizes[:-1], 1]
    nominal = float(np.prod(lateral))

    def box(values: np.ndarray, shape: list[int]) -> np.ndarray:
        return uniform_filter(values, shape, mode="constant") * float(np.prod(shape))

    vw = g2 * train
    num_l, den_l = box(vw, lateral), box(train, lateral)
    half = sizes[-1] // 2
    out = []
    for side in (-1, 1):
        num = _one_sided(num_l, axis, 1, half, side)
        den = _one_sided(den_l, axis, 1, half, side)
        expected = nominal * half
        if gsizes is not None and gsizes[-1] // 2 >= 1:
            g_lat = [*gsizes[:-1], 1]
            g = min(gsizes[-1] // 2, half)
            num = num - _one_sided(box(vw, g_lat), axis, 1, g, side)
            den = den - _one_sided(box(train, g_lat), axis, 1, g, side)
            expected -= float(np.prod(g_lat)) * g
        ok = den > 0.25 * max(expected, 1.0)
        out.append((np.where(ok, num / np.maximum(den, 1e-30), np.nan), den))
    return out


def depth_median(g2: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Per depth (last axis), the median of g2 over the visible nodes (1 where none is visible; NaN ignored):
    numpy's nanmedian of the masked map, by one sort (invisible nodes sort last)."""
    nz = g2.shape[-1]
    valid = np.asarray(visible, bool) & np.isfinite(g2)
    flat = np.sort(np.where(valid, g2, np.inf).reshape(-1, nz), axis=0)
    count = valid.reshape(-1, nz).sum(axis=0)
    lo, hi = np.maximum((count - 1) // 2, 0), np.maximum(count // 2, 0)
    cols = np.arange(nz)
    med = 0.5 * (flat[lo, cols] + flat[np.minimum(hi, flat.shape[0] - 1), cols])
    return np.where(count > 0, med, 1.0)


def local_median(
    g2: np.ndarray, visible: np.ndarray, half: list[int], cells: list[float], spacing: tuple[float, ...]
) -> np.ndarray:
    """A robust local level: the median of γ² over the training window (± `half` nodes per axis) of the
    visible nodes on a lattice of one node per resolution cell (nearly independent samples), over ln 2 (the
    exponential law's median/mean), linearly interpolated back to the grid. Half the window may be a
    target's own main lobe and sidelobes without raising it (a censoring reference; §4.9)."""
    stride = [min(max(1, int(round(c / s))), n) for c, s, n in zip(cells, spacing, g2.shape, strict=True)]
    sub = tuple(slice(st // 2, None, st) for st in stride)
    coarse = np.where(np.asarray(visible, bool)[sub], g2[sub], np.inf)  # invisible nodes sort last
    hc = [max(1, int(round(h / st))) for h, st in zip(half, stride, strict=True)]
    padded = np.pad(coarse, [(h, h) for h in hc], constant_values=np.inf)
    win = np.sort(sliding_window_view(padded, [2 * h + 1 for h in hc]).reshape(*coarse.shape, -1), axis=-1)
    count = np.sum(np.isfinite(win), axis=-1)  # visible nodes per window, sorted first
    lo_i, hi_i = np.maximum((count - 1) // 2, 0), count // 2
    med = 0.5 * (np.take_along_axis(win, lo_i[..., None], -1) + np.take_along_axis(win, hi_i[..., None], -1))[..., 0]
    med = med / log(2)
    ok = (count > 0) & np.isfinite(med)
    med = np.where(ok, med, float(np.median(med[ok])) if ok.any() else 1.0)
    for axis, (n, st) in enumerate(zip(g2.shape, stride, strict=True)):  # separable linear interpolation
        pos = np.clip((np.arange(n) - st // 2) / st, 0, med.shape[axis] - 1)
        lo = pos.astype(int)
        hi = np.minimum(lo + 1, med.shape[axis] - 1)
        w = (pos - lo).reshape([-1 if ax == axis else 1 for ax in range(med.ndim)])
        med = np.take(med, lo, axis=axis) * (1 - w) + np.take(med, hi, axis=axis) * w
    return med


def greater_level(wide: NullModel, compact: NullModel, gamma: np.ndarray) -> NullModel:
    """The "both" setting from its two models (`cfar_null_model`; a greatest-of CFAR, Hansen & Sawyers 1980,
    across two training windows): at every node the greater level, the
    training-cell count of the window chosen, T = γ² over that level; the smoothness is the wide model's."""
    use = compact.power > wide.power
    power = np.where(use, compact.power, wide.power)
    stat = np.asarray(gamma, np.float64) ** 2 / np.maximum(power.astype(np.float64), 1e-300)
    return replace(
        wide,
        power=np.ascontiguousarray(power, np.float32),
        train_cells=np.where(use, compact.train_cells, wide.train_cells).astype(np.float32),
        statistic=np.minimum(stat, np.finfo(np.float32).max).astype(np.float32),
        _significance=None,
    )


def cfar_null_model(
    setting: str,
    gamma: np.ndarray,
    grid: Grid,
    resolution: tuple[float, float],
    level: np.ndarray | None = None,
    visible: np.ndarray | None = None,
) -> NullModel:
    """The null model of a named CFAR setting (`CFAR_NAMES`, docs/design.md §4.9). "both": the greater of the
    "wide" and "compact" levels at every node (a greatest-of CFAR across two training windows), with the
    training-cell count of the one chosen; each window under-estimates where the other does not — the wide
    one at the focused speckle's lateral concentration and surface peak, the compact one between a target's
    own lobes in water — so the greater is the conservative estimate (`greater_level`)."""
    check_cfar(setting)
    if setting != "both":
        return null_model(gamma, grid, resolution, level=level, visible=visible, **CFAR_SETTINGS[setting])
    wide = null_model(gamma, grid, resolution, level=level, visible=visible)
    compact = null_model(gamma, grid, resolution, level=level, visible=visible, **CFAR_SETTINGS["compact"])
    return greater_level(wide, compact, gamma)
