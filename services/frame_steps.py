"""The per-frame steps of the pipeline that need no pipeline state (services.pipeline): the set-up's
geometry key, the tracker's settings and construction, the frames' truth, and the detections of one γ-map
against its null model (docs/design.md §4.7–4.10)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from fpcore import Acquisition, Grid, detect
from fpcore.cfar import DEFAULT_CFAR, NullModel
from fpcore.metrics import DEFAULT_MAX_PFA, Detection
from fpcore.tracking import Tracker, TrackerConfig
from fpcore.truth import Truth

if TYPE_CHECKING:
    from services.pipeline import PipelineConfig

__all__ = ["find_targets", "geometry_key", "make_tracker", "tracker_settings", "truth_error", "truth_positions"]


def geometry_key(acq: Acquisition) -> tuple:
    """What a set-up depends on: element positions, transmit sines, sampling, record length, sound speed."""
    return (acq.probe.positions.tobytes(), acq.sequence.sines.tobytes(), float(acq.fs), acq.n_samples, float(acq.c0))


def tracker_settings(acq: Acquisition, band: tuple[float, float], cfg: PipelineConfig) -> dict[str, Any]:
    """What the tracker of frames like ``acq`` depends on besides the grid (JSON-safe: a sharded merger gets
    it from the workers, services.nodes.merger): wavelength, aperture, bandwidth, sound speed, tracks per map
    (one per fingerprint and expected target, ``n_peaks``: a calibration describes one object), frames
    integrated, CFAR setting."""
    return {
        "wavelength": acq.c0 / acq.probe.centre_frequency,
        "aperture": float(acq.probe.aperture[0]),
        "bandwidth": band[1] - band[0],
        "c0": float(acq.c0),
        "max_tracks_per_map": max(1, cfg.n_peaks),
        "integrate_frames": cfg.track_integrate,
        "cfar": cfg.cfar,
    }


def make_tracker(grid: Grid, settings: Mapping[str, Any]) -> Tracker:
    """The tracker of :func:`tracker_settings` on ``grid``."""
    s = settings
    config = TrackerConfig(
        max_tracks_per_map=int(s["max_tracks_per_map"]),
        integrate_frames=int(s["integrate_frames"]),
        cfar=str(s.get("cfar", DEFAULT_CFAR)),
    )
    return Tracker(grid, s["wavelength"], s["aperture"], s["bandwidth"], s["c0"], config)


def truth_positions(truth: Truth | Mapping[str, Any] | None) -> list[tuple[str | None, np.ndarray]]:
    """(name, position) of the targets of a frame's ground truth (`Acquisition.ground_truth`, or the JSON
    record a message carries); targets without a position (x, y, z) are skipped."""
    if truth is None:
        return []
    view = truth if isinstance(truth, Truth) else Truth.from_dict(truth)
    return [(t.name, t.position) for t in view.targets or [] if t.position_m is not None]


def truth_error(
    position: np.ndarray, truths: list[tuple[str | None, np.ndarray]], name: str | None = None
) -> float | None:
    """Distance to the nearest truth target (those named ``name`` if there are any), None without truth."""
    pos = np.asarray(position, float)
    named = [t for n, t in truths if name is not None and n == name]
    cands = named or [t for _, t in truths]
    return min((float(np.linalg.norm(pos - t)) for t in cands), default=None)


def find_targets(
    gamma: np.ndarray,
    grid: Grid,
    acq: Acquisition,
    band: tuple[float, float],
    name: str,
    n_peaks: int = 1,
    interior: bool = False,
    null: NullModel | None = None,
    max_pfa: float | None = DEFAULT_MAX_PFA,
) -> list[Detection]:
    """Detections in one γ-map (``fpcore.detect``: C_γ, C, calibrated PFA, Cramér–Rao precision) against
    the map's null model (``fpcore.locate.null_of``; default: the CFAR alone), kept when PFA < ``max_pfa``;
    ``interior`` skips maxima within the diffraction resolution of the grid's border."""
    lam = acq.c0 / acq.probe.centre_frequency
    return detect(
        gamma,
        grid,
        lam,
        acq.probe.aperture[0],
        band[1] - band[0],
        acq.c0,
        name=name,
        n_peaks=n_peaks,
        interior=interior,
        null=null,
        max_pfa=max_pfa,
    )
