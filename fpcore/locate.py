"""One call from a frame and a fingerprint to calibrated detections (docs/design.md §4.7–4.10).

``locate(imager, acq, fp)`` = plane waves → γ-map (paper eq. P) → its local null model (the data's energy
in the fingerprint's time support × the aperture factor, fpcore.background, corrected by the CFAR of
fpcore.cfar) → the most significant peaks with C_γ, calibrated PFA and Cramér–Rao precision, kept below
``max_pfa`` (fpcore.metrics.detect). The streaming pipeline (services.pipeline) runs the same steps.
``locate_union(imagers, acq, fp)`` maps the frame with several imagers (as recorded and weighted by 1/v(t),
docs/design.md §4.14) and keeps the most significant map's detections, their PFA by the union bound (eq. W2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from .acquisition import Acquisition, PlaneWaveData
from .background import NullLevel
from .cfar import DEFAULT_CFAR, NullModel, cfar_null_model
from .fingerprint import Fingerprint
from .grid import Grid
from .likelihood import Imager
from .metrics import DEFAULT_MAX_PFA, Detection, detect, resolution_cell

__all__ = [
    "Located",
    "locate",
    "locate_union",
    "null_of",
    "physical_level_of",
    "resolution_of",
    "union_null",
    "union_of",
    "union_pfa",
]


@dataclass
class Located:
    """What `locate` found: the γ-map, its null model (significance, visible region) and the detections."""

    gamma: np.ndarray
    null: NullModel
    detections: list[Detection]


def resolution_of(grid: Grid, acq: Acquisition, band: tuple[float, float]) -> tuple[float, float]:
    """(δρ_D at the grid's middle depth, c0/(2Δf)): the resolution cell the null model is measured in."""
    lam = acq.c0 / acq.probe.centre_frequency
    return resolution_cell(lam, acq.probe.aperture[0], band[1] - band[0], acq.c0, 0.5 * (grid.z[0] + grid.z[-1]))


def physical_level_of(
    grid: Grid,
    acq: Acquisition,
    pw: PlaneWaveData,
    fp: Fingerprint,
    band: tuple[float, float],
    level: NullLevel,
    aperture: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(level, visible) of `level` for one fingerprint on this frame (eq. B1 × the aperture factor; no
    single-scattering mixture, which needs the map): what `null_of` passes to the CFAR, made before the map
    when the caller has something to overlap it with. `aperture`: the fingerprint's A(r) from
    `level.aperture`, made beforehand on the imager's thread (off it, the imager must not be called)."""
    return level.level(acq, pw, fp, resolution_of(grid, acq, band), aperture=aperture)


def null_of(
    gamma: np.ndarray,
    grid: Grid,
    acq: Acquisition,
    pw: PlaneWaveData,
    fp: Fingerprint,
    band: tuple[float, float],
    level: NullLevel | None,
    image: np.ndarray | None = None,
    physical: tuple[np.ndarray, np.ndarray] | None = None,
) -> NullModel:
    """The local null model of one γ-map, with `level`'s physical null level (None: the CFAR alone);
    `image`: the frame's confocal image when the caller has made it (the single-scattering level uses it);
    `physical`: `physical_level_of`'s (level, visible) for this frame and fingerprint, already made (not with
    a single-scattering level)."""
    res = resolution_of(grid, acq, band)
    if level is None:
        lev, vis = None, None
    elif physical is not None and not level.single_scattering:
        lev, vis = physical
    else:
        lev, vis = level.level(acq, pw, fp, res, gamma=gamma, image=image)
    return cfar_null_model(level.cfar if level is not None else DEFAULT_CFAR, gamma, grid, res, level=lev, visible=vis)


def locate(
    imager: Imager,
    acq: Acquisition,
    fp: Fingerprint,
    level: NullLevel | None = None,
    *,
    pw: PlaneWaveData | None = None,
    n_peaks: int = 1,
    max_pfa: float | None = DEFAULT_MAX_PFA,
    interior: bool = False,
) -> Located:
    """γ-map of `fp` on `acq` and its detections with calibrated PFA (module doc). `level`: a NullLevel of
    this imager, kept between frames (it caches the fingerprint's aperture factor); default: a new one."""
    pw = imager.plane_waves(acq) if pw is None else pw
    band = imager.config.band
    gamma = imager.gamma(pw, fp)
    nm = null_of(gamma, imager.grid, acq, pw, fp, band, NullLevel(imager) if level is None else level)
    lam = acq.c0 / acq.probe.centre_frequency
    dets = detect(
        gamma,
        imager.grid,
        lam,
        acq.probe.aperture[0],
        band[1] - band[0],
        acq.c0,
        name=fp.name,
        n_peaks=n_peaks,
        interior=interior,
        null=nm,
        max_pfa=max_pfa,
    )
    return Located(gamma, nm, dets)


def union_pfa(pfa: float, n_maps: int) -> float:
    """Eq. (W2) of docs/design.md §4.14: a node taken from whichever of `n_maps` statistics' maps is the most
    significant, each map calibrated on its own, has the PFA n_maps × its own, capped at 1. Under the null,
    P(K min_k p_k < α) ≤ Σ_k P(p_k < α/K) ≤ α whatever the maps' dependence (Bonferroni)."""
    if not 0.0 <= pfa <= 1.0:
        raise ValueError(f"pfa: expected a probability in [0, 1], got {pfa}")
    if n_maps < 1:
        raise ValueError(f"n_maps: expected at least 1, got {n_maps}")
    return min(1.0, n_maps * float(pfa))


def locate_union(
    imagers: Sequence[Imager],
    acq: Acquisition,
    fp: Fingerprint,
    levels: Sequence[NullLevel] | None = None,
    *,
    n_peaks: int = 1,
    max_pfa: float | None = DEFAULT_MAX_PFA,
    interior: bool = False,
) -> tuple[Located, int]:
    """The frame located on each imager's map (e.g. the frame as recorded and weighted by 1/v(t), eq. W1); the map
    whose most significant node is the most significant of all, every PFA of its detections by eq. (W2), kept
    below `max_pfa`. Returns that map's Located and its imager's index. `levels`: one NullLevel per imager, kept
    between frames (default: new ones); `n_peaks`, `interior`: as `locate`'s."""
    if not imagers:
        raise ValueError("imagers: expected one or more Imagers")
    if levels is not None and len(levels) != len(imagers):
        raise ValueError(f"levels: expected one per imager ({len(imagers)}), got {len(levels)}")
    found = [
        locate(im, acq, fp, None if levels is None else levels[k], n_peaks=n_peaks, max_pfa=None, interior=interior)
        for k, im in enumerate(imagers)
    ]
    return union_of(found, max_pfa)


def union_of(found: Sequence[Located], max_pfa: float | None = DEFAULT_MAX_PFA) -> tuple[Located, int]:
    """Eq. (W2) on maps already located (each with `max_pfa=None`, so that its most significant node is there): the
    map whose most significant node is the most significant of all, every PFA of its detections multiplied by the
    number of maps, kept below `max_pfa`; and its index. The returned null model carries the factor
    (`NullModel.n_maps`), so that a PFA read from it later (a tracker's gate) is the union's too."""
    if not found:
        raise ValueError("found: expected one or more Located maps")
    # the most significant node: the smallest PFA among a map's detections (above SURE_SIGNIFICANCE they are ordered
    # by γ, fpcore.cfar.NullModel.ranking, so with n_peaks > 1 the first need not be it)
    best = min(range(len(found)), key=lambda k: min((d.pfa for d in found[k].detections), default=1.0))
    dets = [replace(d, pfa=union_pfa(d.pfa, len(found))) for d in found[best].detections]
    if max_pfa is not None:
        dets = [d for d in dets if d.pfa < max_pfa]
    return Located(found[best].gamma, union_null(found[best].null, len(found)), dets), best


def union_null(null: NullModel, n_maps: int) -> NullModel:
    """`null` as the null model of a map chosen among `n_maps` statistics' maps (eq. W2): the same map, its
    cached significance kept, every PFA it reports n_maps × its own (`NullModel.n_maps`)."""
    if n_maps < 1:
        raise ValueError(f"n_maps: expected at least 1, got {n_maps}")
    return replace(null, n_maps=n_maps)
