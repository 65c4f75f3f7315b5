"""The frame pipeline: RF frame → band-limited plane waves → confocal image, one γ-map per fingerprint,
detections and tracks (docs/design.md §4.3, §4.7–4.10).

:class:`Pipeline` holds the imaging set-up (``fpcore.Imager`` on a grid for the frames' geometry), the
fingerprint dictionary (``services.registry.Entry``, built with ``services.models``) and the tracker.
They are set up for the geometry of the first frame (or calibration) and again whenever the geometry
(probe, sequence, sampling, sound speed) or a parameter changes. :meth:`Pipeline.process` is
thread-safe (one lock for processing and dictionary changes) and returns a :class:`FrameResult`;
``services.convert`` turns it into wire messages.

No zenoh here: the processor node (``services.nodes.processor``) runs it on the bus, `fp track` runs
it offline, `fp locate` shares its imaging set-up (``services.imaging_setup``), fingerprint construction and
per-frame steps (``fpcore.locate``: γ, null model, detections), and tests and notebooks run it too.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Collection, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any, get_args

import numpy as np

from fpcore import Acquisition, Fingerprint, Grid, Imager, NullLevel
from fpcore.acquisition import PlaneWaveData
from fpcore.background import NullPower
from fpcore.cfar import DEFAULT_CFAR, NullModel, check_cfar
from fpcore.locate import Located, null_of, physical_level_of, resolution_of, union_of
from fpcore.metrics import DEFAULT_MAX_PFA, Detection
from fpcore.tracking import Tracker, TrackState
from fpcore.velocity import VelocityEstimate, VelocitySearch
from services.frame_steps import (
    find_targets,
    geometry_key,
    make_tracker,
    tracker_settings,
    truth_error,
    truth_positions,
)
from services.imaging_setup import check_grid_axes, check_imaging_budget, imaging_estimate, make_imager
from services.messages import Statistic
from services.models import build_fingerprint
from services.registry import Entry, FingerprintSpec, check_setup_size, set_changes

__all__ = [
    "UNION_STATISTICS",
    "FrameResult",
    "Pipeline",
    "PipelineConfig",
    "check_grid_axes",
    "check_imaging_budget",
    "find_targets",
    "geometry_key",
    "imaging_estimate",
    "make_imager",
    "make_tracker",
    "tracker_settings",
    "truth_error",
    "truth_positions",
]

log = logging.getLogger("fp.pipeline")
_Union = tuple[dict[str, str], PlaneWaveData] | None  # `Pipeline._numerics`: the union's maps kept, the weighted frame

#: PipelineConfig.union's two statistics, in the order of its maps (FrameResult.statistic): the frame as recorded and
#: weighted by its own 1/v(t) (docs/design.md §4.14, eqs. W1–W2)
UNION_STATISTICS: tuple[str, ...] = get_args(Statistic)


@dataclass
class PipelineConfig:
    """Processing settings. Ranges in metres; ``band`` in Hz (default: the frame's truth band, else the
    probe's −6 dB band); ``n_freq`` frequencies kept in the band (None: every bin of the 2×-padded record:
    no delay wrap, fpcore Spectrum); ``n_peaks`` detections per fingerprint; ``max_pfa``: a detection is
    reported only below this calibrated false-alarm probability (docs/design.md §4.9); ``interior``: the
    border heuristic (skip maxima within δρ_D of the grid's border; off by default, the local significance
    does not need it); ``track_integrate``: the tracker searches the mean of the last K γ-maps
    (fpcore.tracking); ``single_scattering_null``: the null level mixes in the single-scattering level of
    docs/design.md §4.9 eq. (B2) (fpcore.speckle_level: for backgrounds dominated by single scattering; it
    costs power on targets that stand out of the confocal image, and makes the image every frame); ``cfar``: the
    named CFAR setting of the null models and the tracker (fpcore.cfar.CFAR_NAMES: "compact", the default —
    calibrated on the focused single-scattering speckle and on water —, "wide", the earlier default, or
    "both", the greater level; docs/design.md §4.9); ``time_weighting``: every frame is weighted by its own inverse
    variance 1/v(t) before γ (docs/design.md §4.14, eq. W1; ``fpcore.ImagingConfig.time_weighting``); ``union``:
    every frame is mapped both as recorded and weighted by 1/v(t), and per fingerprint the map whose most
    significant node is the more significant is kept — its detections and the tracker's gates at twice their PFA
    (docs/design.md §4.14, eq. W2; ``fpcore.locate.union_of``)."""

    band: tuple[float, float] | None = None
    n_freq: int | None = None
    svd_threshold: float = 0.4
    grid: Grid | None = None
    x_range: tuple[float, float] | None = None
    y_range: tuple[float, float] | None = None
    z_range: tuple[float, float] | None = None
    spacing: float | None = None
    n_out: int | None = None
    n_peaks: int = 1
    max_pfa: float = DEFAULT_MAX_PFA
    interior: bool = False
    eps: float = 1e-5
    publish_image: bool = True
    track: bool = True
    track_integrate: int = 1
    memory_budget: int | None = None  # bytes; None: fpcore.budget.memory_budget() (fp --memory-budget, env)
    single_scattering_null: bool = False
    time_weighting: bool = False
    union: bool = False
    cfar: str = DEFAULT_CFAR

    def __post_init__(self) -> None:
        check_cfar(self.cfar, "--cfar")
        if self.union and self.time_weighting:
            raise ValueError("--union: maps each frame both as recorded and weighted by 1/v(t); drop --time-weighting")
        if not 0 < self.svd_threshold <= 1:
            raise ValueError(f"--svd-threshold: expected 0 < t <= 1, got {self.svd_threshold}")
        if self.n_peaks < 1:
            raise ValueError(f"--targets: expected >= 1, got {self.n_peaks}")
        if not 0 < self.max_pfa <= 1:
            raise ValueError(f"--max-pfa: expected 0 < p <= 1, got {self.max_pfa}")
        if self.track_integrate < 1:
            raise ValueError(f"--track-integrate: expected an integer >= 1, got {self.track_integrate}")
        if self.union and self.track_integrate > 1:  # a mean of maps chosen frame by frame has no union bound of 2
            raise ValueError(
                f"--track-integrate: expected 1 with --union (eq. W2 is per frame), got {self.track_integrate}"
            )


@dataclass
class FrameResult:
    """What one frame gave: γ-maps (fingerprint name → map on ``grid``), the confocal image (None when
    not asked for), detections with their distance to the frame's truth, tracks, and the time of the
    three compute stages (s; 'gamma_kernel': the γ-maps and the image, with the part of the null models and
    detections made alongside them, Pipeline._second_stage; 'detection': the rest of those, the velocities
    and the tracker)."""

    acq: Acquisition
    pw: PlaneWaveData
    band: tuple[float, float]
    grid: Grid
    fingerprints: dict[str, Fingerprint]
    gammas: dict[str, np.ndarray]
    image: np.ndarray | None
    detections: list[tuple[Detection, float | None]]
    tracks: list[TrackState]
    stage_s: dict[str, float] = field(default_factory=dict)
    nulls: dict[str, NullModel] = field(default_factory=dict)  # each γ-map's null model (a merger's tracker)
    # per detection (same order): its velocity estimate, None where its fingerprint has no velocity grid
    velocities: list[VelocityEstimate | None] = field(default_factory=list)
    motion: dict[str, list[VelocityEstimate]] = field(default_factory=dict)  # every estimate (tracker input)
    notices: list[str] = field(default_factory=list)  # said once per pipeline (e.g. no PRF: no velocity)
    velocity_s: float = 0.0  # time of the velocity dictionaries (included in stage 'detection')
    # with PipelineConfig.union: per fingerprint, the map kept (UNION_STATISTICS: "as recorded" or "weighted"), and
    # the frame's plane waves weighted by 1/v(t) (the weighted maps' normalisation)
    statistic: dict[str, str] = field(default_factory=dict)
    weighted_pw: PlaneWaveData | None = None


class Pipeline:
    """Frames in, :class:`FrameResult` out; holds the fingerprint dictionary (a ``DictionaryHost``)."""

    def __init__(
        self, config: PipelineConfig, fingerprints: list[FingerprintSpec] | tuple[FingerprintSpec, ...] = ()
    ) -> None:
        self.cfg = config
        self._entries: dict[str, Entry] = {s.name: Entry(s) for s in fingerprints}
        self.lock = threading.RLock()
        self._imager: Imager | None = None
        self._level: NullLevel | None = None
        self._weighted: tuple[Imager, NullLevel] | None = None  # PipelineConfig.union: the 1/v(t)-weighted maps'
        self._tracker: Tracker | None = None
        self._geom: tuple | None = None
        self._band: tuple[float, float] | None = None
        self._last_acq: Acquisition | None = None
        self._ref: Acquisition | None = None  # the acquisition of the last set-up (calibration or frame)
        self.setup_s = 0.0
        self._noticed: set[str] = set()
        self._second: ThreadPoolExecutor | None = None  # the null models' thread (process, overlap)

    # -- set-up --------------------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Set up on the first calibration's geometry (NUFFT plan, fingerprints) before frames arrive."""
        cal = next((e.spec.calibration for e in self._entries.values() if e.spec.calibration is not None), None)
        if cal is not None:
            with self.lock:
                try:
                    self.setup(cal)
                except ValueError as exc:
                    log.error("set-up on the calibration geometry failed: %s", exc)
                    return
                try:
                    self._rehearse(cal)
                except Exception as exc:  # a warm-up only: the first frame pays instead, the node starts
                    log.warning("the rehearsal frame on the calibration failed (%s: %s)", type(exc).__name__, exc)

    def _rehearse(self, acq: Acquisition) -> None:
        """One frame's numerics on ``acq`` (the calibration, same geometry) as `process` runs them — γ-maps,
        null models and detections on the second thread, the confocal image — with nothing kept: the tracker
        is not updated. The frame-sized buffers, the compiled kernels and the second thread's malloc arena are
        then warm when the first frame comes (issue 15, item 4)."""
        imager, band = self._imager, self._band
        if imager is None or band is None:
            return
        fps = {n: e.fp for n, e in self._entries.items() if e.fp is not None}
        if not fps:
            return
        pw = imager.plane_waves(acq)
        self._numerics(acq, pw, fps, band, truth_positions(acq.ground_truth), self.cfg.publish_image, track=False)

    def setup(self, acq: Acquisition) -> None:
        """Imager, tracker and every fingerprint for the geometry of ``acq``."""
        with self.lock:
            t0 = time.perf_counter()
            cfg = self.cfg
            band = cfg.band or acq.default_band()
            ranges = {"x_range": cfg.x_range, "y_range": cfg.y_range, "z_range": cfg.z_range, "spacing": cfg.spacing}
            # sized first (fpcore.budget): a refused geometry leaves the previous set-up in place
            self._imager = imager = make_imager(
                acq,
                band,
                cfg.grid,
                ranges=ranges,
                n_freq=cfg.n_freq,
                n_out=cfg.n_out,
                eps=cfg.eps,
                n_fingerprints=len(self._entries) * (2 if cfg.union else 1),  # union: two maps each
                memory_budget=cfg.memory_budget,
                time_weighting=cfg.time_weighting,
            )
            grid = imager.grid

            def level_of(im: Imager) -> NullLevel:
                return NullLevel(
                    im,
                    single_scattering=cfg.single_scattering_null,
                    cfar=cfg.cfar,
                    cache=max(8, 2 * len(self._entries)),  # every fingerprint's aperture factor kept (one map each)
                )

            self._level = level_of(imager)
            self._weighted = None
            if cfg.union:  # eq. W2: a second imager on the same grid and output directions, frames weighted by 1/v(t)
                weighted = make_imager(
                    acq,
                    band,
                    grid,
                    n_freq=cfg.n_freq,
                    n_out=cfg.n_out,
                    eps=cfg.eps,
                    n_fingerprints=len(self._entries),
                    memory_budget=cfg.memory_budget,
                    time_weighting=True,
                )
                self._weighted = (weighted, level_of(weighted))
            self._band = band
            self._geom = geometry_key(acq)
            self._ref = acq
            self._tracker = make_tracker(grid, tracker_settings(acq, band, cfg)) if cfg.track else None
            pw = imager.plane_waves(acq)
            imager.kernel(pw)  # NUFFT plan (FFTW planning: seconds) before the first frame is timed
            w_pw = None
            if self._weighted is not None:  # the weighted frame's plane waves and plan, once (union)
                w_pw = self._weighted[0].plane_waves(acq)
                self._weighted[0].kernel(w_pw)
            for entry in self._entries.values():
                self._build(entry, acq, pw)
                if entry.fp is not None:
                    try:
                        imager.template(pw, entry.fp)
                        # aperture factor (cached) and the null level's NUFFT plan, before the first frame is timed
                        self._level.level(acq, pw, entry.fp, resolution_of(grid, acq, band))
                        if self._weighted is not None and w_pw is not None:  # the same for the weighted maps
                            w_imager, w_level = self._weighted
                            w_imager.template(w_pw, entry.fp)
                            w_level.level(acq, w_pw, entry.fp, resolution_of(grid, acq, band))
                        if self.cfg.single_scattering_null:
                            self._level.speckle.point_response(pw, entry.fp)  # eq. (B2)'s |h|²
                    except ValueError as exc:
                        entry.fp, entry.error = None, str(exc)
            self.setup_s += time.perf_counter() - t0
            log.info(
                "set up for %s elements × %s waves × %s samples: band %.2f–%.2f MHz, grid %s, dictionary %s",
                acq.probe.n_elements,
                acq.sequence.n_waves,
                acq.n_samples,
                band[0] / 1e6,
                band[1] / 1e6,
                grid.shape,
                list(self._entries),
            )

    def _build(self, entry: Entry, acq: Acquisition, pw: PlaneWaveData) -> None:
        imager, band = self._imager, self._band
        assert imager is not None and band is not None
        entry.fp, entry.error = None, None
        try:
            entry.fp = build_fingerprint(entry.spec, acq, pw, imager, band, self.cfg.n_freq, self.cfg.svd_threshold)
        except ValueError as exc:
            entry.error = str(exc)
            log.error("fingerprint %r: %s", entry.spec.name, exc)

    @property
    def grid(self) -> Grid:
        """The imaging grid of the current set-up (ValueError before the first set-up)."""
        if self._imager is None:
            raise ValueError("pipeline: not set up yet (no frame or calibration seen)")
        return self._imager.grid

    # -- dictionary (services.registry.DictionaryHost) ----------------------------------------------------
    @property
    def names(self) -> list[str]:
        with self.lock:
            return list(self._entries)

    def entry(self, name: str) -> dict[str, Any] | None:
        with self.lock:
            e = self._entries.get(name)
            return None if e is None else e.describe()

    def add(self, spec: FingerprintSpec) -> dict[str, Any]:
        """Add or replace a dictionary entry (built now if a frame or the calibration gives the geometry).
        Transactional: if the entry cannot be built (or a first set-up fails), the dictionary and the set-up
        stay as they were and the error is raised."""
        with self.lock:
            saved = self._snapshot()
            try:
                prev = self._entries.get(spec.name)
                entry = Entry(spec)
                self._entries = {**self._entries, spec.name: entry}
                ref = next((a for a in (self._last_acq, self._ref, spec.calibration) if a is not None), None)
                if ref is not None:
                    if self._imager is None:
                        self._entries = {n: e if n == spec.name else Entry(e.spec) for n, e in self._entries.items()}
                        self.setup(ref)
                    else:
                        self._build(entry, ref, self._imager.plane_waves(ref))
                if entry.error is not None:
                    raise ValueError(entry.error)
            except BaseException:
                self._restore(saved)
                raise
            if prev is not None and prev.fp is not None:
                self._forget(prev.fp)
            return entry.describe()

    def remove(self, name: str) -> None:
        with self.lock:
            entry = self._entries.get(name)
            if entry is None:
                raise KeyError(name)
            self._entries = {n: e for n, e in self._entries.items() if n != name}
            if entry.fp is not None:
                self._forget(entry.fp)

    def _forget(self, fp: Fingerprint) -> None:
        """Drop `fp`'s cached templates from every imager (the weighted one too, with ``union``)."""
        for imager in (self._imager, *(self._weighted[:1] if self._weighted is not None else ())):
            if imager is not None:
                imager.forget(fp)

    #: What a set-up replaces (rebinds, never mutates in place): saved and restored by the transactions.
    _STATE = ("cfg", "_entries", "_imager", "_level", "_weighted", "_tracker", "_geom", "_band", "_ref", "setup_s")

    def _snapshot(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self._STATE}

    def _restore(self, saved: dict[str, Any]) -> None:
        for k, v in saved.items():
            setattr(self, k, v)

    def set_params(self, params: dict[str, Any]) -> None:
        """Change band, n_freq, svd_threshold or n_peaks; fingerprints are rebuilt. Transactional: the
        request is validated, its set-up size checked against the memory budget, and the set-up (imager,
        null level, tracker, every fingerprint, on fresh entries) rebuilt on the last frame's geometry;
        the pipeline keeps it only if that succeeds and every entry built before still builds. Otherwise
        ValueError (or MemoryError) is raised and the pipeline is exactly as it was (same configuration,
        set-up objects and fingerprints). Before any frame or calibration the settings are only
        validated and stored (the first frame sets up with them)."""
        changes = set_changes(params)
        with self.lock:
            new_cfg = replace(self.cfg, **changes)  # PipelineConfig.__post_init__ checks the ranges
            ref = self._last_acq if self._last_acq is not None else self._ref
            if ref is None:
                self.cfg, self._geom = new_cfg, None
                return
            check_setup_size(ref, new_cfg.band or ref.default_band(), new_cfg.n_freq, new_cfg.memory_budget)
            saved = self._snapshot()
            built = [n for n, e in self._entries.items() if e.fp is not None]
            try:
                self.cfg = new_cfg
                self._entries = {n: Entry(e.spec) for n, e in self._entries.items()}  # the old ones stay intact
                self.setup(ref)
                lost = {n: self._entries[n].error for n in built if self._entries[n].fp is None}
                if lost:
                    raise ValueError(
                        "set: refused, these fingerprints would not build: "
                        + "; ".join(f"{n}: {err}" for n, err in lost.items())
                    )
            except BaseException:
                self._restore(saved)
                raise

    def params(self) -> dict[str, Any]:
        c = self.cfg
        grid = self._imager.grid if self._imager is not None else c.grid
        return {
            "band_hz": list(self._band or c.band or []) or None,
            "n_freq": c.n_freq,
            "svd_threshold": c.svd_threshold,
            "n_peaks": c.n_peaks,
            "grid_shape": list(grid.shape) if grid is not None else None,
        }

    def describe(self) -> dict[str, Any]:
        with self.lock:
            return {"params": self.params(), "entries": [e.describe() for e in self._entries.values()]}

    # -- processing --------------------------------------------------------------------------------------
    def process(
        self, acq: Acquisition, names: Collection[str] | None = None, with_image: bool | None = None
    ) -> FrameResult:
        """γ-maps, image, detections and tracks of one frame (set-up first if its geometry is new); each
        detection comes with its distance to the nearest truth target of the same name, else of any name.
        ``names``: only these fingerprints (a γ worker's share, services.nodes.worker; None: all);
        ``with_image``: compute the confocal image or not (None: ``publish_image``)."""
        with self.lock:
            if self._geom != geometry_key(acq):
                self.setup(acq)
            self._last_acq = acq
            imager, band = self._imager, self._band
            assert imager is not None and band is not None
            fps = {n: e.fp for n, e in self._entries.items() if e.fp is not None and (names is None or n in names)}
            cfg = self.cfg
            t0 = time.perf_counter()
            pw = imager.plane_waves(acq)
            t1 = time.perf_counter()
            want_image = cfg.publish_image if with_image is None else with_image
            grid = imager.grid
            gammas, image, nulls, dets, tracks, t2, union = self._numerics(
                acq, pw, fps, band, truth_positions(acq.ground_truth), want_image
            )
            tv = time.perf_counter()
            # the velocity search on the frame each fingerprint's kept map was made from (with union: its null model
            # gates the motion measurements, fpcore.tracking)
            frames = {n: union[1] for n, st in union[0].items() if st == "weighted"} if union is not None else {}
            velocities, motion, notices = self._velocities(acq, pw, grid, dets, frames)
            if self._level is not None and gammas and not NullPower.uniform(pw.freqs) and "bins" not in self._noticed:
                self._noticed.add("bins")  # a set-up warning in the node's log, once; not a frame error
                log.warning(
                    "n_freq: the %d frequencies kept are unevenly spaced bins, so the physical null level "
                    "(docs/design.md §4.9) is skipped and the CFAR alone sets the level; keep every bin (no n_freq) "
                    "or choose n_freq so that the band's bins divide evenly",
                    pw.freqs.size,
                )
            tv = time.perf_counter() - tv
            if tracks is None:  # not updated with the detections: it takes the velocity estimates
                tracks = (
                    self._tracker.update(gammas, acq.timestamp, nulls=nulls, motion=motion)
                    if self._tracker is not None and gammas
                    else []
                )
            t3 = time.perf_counter()
        return FrameResult(
            acq,
            pw,
            band,
            grid,
            fps,
            gammas,
            image,
            dets,
            tracks,
            {"spectrum_projection": t1 - t0, "gamma_kernel": t2 - t1, "detection": t3 - t2},
            nulls,
            velocities,
            motion,
            notices,
            tv,
            *(union or ({}, None)),
        )

    def _numerics(
        self,
        acq: Acquisition,
        pw: PlaneWaveData,
        fps: Mapping[str, Fingerprint],
        band: tuple[float, float],
        truths: Any,
        want_image: bool,
        track: bool = True,
    ) -> tuple[dict[str, np.ndarray], np.ndarray | None, dict[str, NullModel], list, list | None, float, _Union]:
        """One frame's γ-maps, confocal image (None unless ``want_image``), null models, detections and tracks
        (`_second_stage`; with ``union``, `_union_numerics`), the time the maps and the image were done
        (perf_counter), and with ``union`` per fingerprint the map kept and the weighted frame's plane waves
        (else None)."""
        imager = self._imager
        assert imager is not None
        if self._weighted is not None:
            return self._union_numerics(acq, pw, fps, band, truths, want_image, track)
        if self.cfg.single_scattering_null:  # eq. (B2) needs the image first: no overlap
            gammas = {n: imager.gamma(pw, fp) for n, fp in fps.items()}
            image = imager.confocal(pw)
            nulls, dets, tracks = self._second_stage(acq, pw, fps, band, truths, False, image, track)(gammas)()
            return gammas, image if want_image else None, nulls, dets, tracks, time.perf_counter(), None
        stage = self._second_stage(acq, pw, fps, band, truths, True, track=track)
        gammas = {n: imager.gamma(pw, fp) for n, fp in fps.items()}
        result = stage(gammas)
        image = imager.confocal(pw) if want_image else None
        t_done = time.perf_counter()
        nulls, dets, tracks = result()
        return gammas, image, nulls, dets, tracks, t_done, None

    def _union_numerics(
        self,
        acq: Acquisition,
        pw: PlaneWaveData,
        fps: Mapping[str, Fingerprint],
        band: tuple[float, float],
        truths: Any,
        want_image: bool,
        track: bool,
    ) -> tuple[dict[str, np.ndarray], np.ndarray | None, dict[str, NullModel], list, list | None, float, _Union]:
        """`_numerics` with ``union`` (docs/design.md §4.14, eq. W2): each fingerprint mapped on the frame as
        recorded and weighted by 1/v(t), each map with its own null model (`null_of`, its own frame's level) and
        detections; `fpcore.locate.union_of` keeps the map whose most significant node is the more significant,
        its detections at twice their PFA, and its null model carries the factor (the tracker's gates). The
        confocal image is the frame's as recorded. Serial: the two maps' null models are not overlapped."""
        imager, level, grid, cfg = self._imager, self._level, self.grid, self.cfg
        assert imager is not None and self._weighted is not None
        w_imager, w_level = self._weighted
        w_pw = w_imager.plane_waves(acq)
        image = imager.confocal(pw) if want_image or cfg.single_scattering_null else None
        gammas: dict[str, np.ndarray] = {}
        nulls: dict[str, NullModel] = {}
        statistic: dict[str, str] = {}
        dets: list[tuple[Detection, float | None]] = []
        for name, fp in fps.items():
            found = []
            for im, lev, frame_pw, img in ((imager, level, pw, image), (w_imager, w_level, w_pw, None)):
                g = im.gamma(frame_pw, fp)
                nm = null_of(g, grid, acq, frame_pw, fp, band, lev, img)
                dets_k = find_targets(g, grid, acq, band, name, cfg.n_peaks, cfg.interior, nm, None)
                found.append(Located(g, nm, dets_k))
            kept, k = union_of(found, cfg.max_pfa)
            gammas[name], nulls[name], statistic[name] = kept.gamma, kept.null, UNION_STATISTICS[k]
            dets += [(d, truth_error(np.asarray(d.position_m, float), truths, name)) for d in kept.detections]
        t_done = time.perf_counter()
        tracks = None
        if track and not self._with_velocity():  # else `process` updates it with the velocity estimates
            tracker = self._tracker
            tracks = tracker.update(gammas, acq.timestamp, nulls=nulls) if tracker is not None and gammas else []
        return gammas, image if want_image else None, nulls, dets, tracks, t_done, (statistic, w_pw)

    def _with_velocity(self) -> bool:
        """Whether a fingerprint has a velocity dictionary: the tracker then waits for its estimates."""
        return any(e.spec.velocity_grid is not None and e.fp is not None for e in self._entries.values())

    def _second_stage(
        self,
        acq: Acquisition,
        pw: PlaneWaveData,
        fps: Mapping[str, Fingerprint],
        band: tuple[float, float],
        truths: Any,
        overlap: bool,
        image: np.ndarray | None = None,
        track: bool = True,
    ) -> Callable[[Mapping[str, np.ndarray]], Callable[[], tuple[dict[str, NullModel], list, list | None]]]:
        """The frame's null models, detections and tracks, as stage(gammas) → a call that returns (nulls,
        detections, tracks). Tracks are None when a fingerprint has a velocity dictionary: the tracker then
        waits for the velocity estimates (`_velocities`, after the image: they use the imager's kernel).

        Each γ-map's null model is fpcore.locate.null_of: the physical level (docs/design.md §4.9, eq. B1 ×
        the aperture factor), which does not need the map, then the CFAR on the map. With ``overlap`` a second
        thread makes the physical levels at once, while the caller makes the γ-maps, then the CFARs and the
        detections (find_targets) while the caller makes the confocal image: both use the 2 cores, and the
        serial parts of one (the CFAR's filters, the peak search, the level's products) fill the other's idle
        time. The fingerprints' aperture factors (cached; made by the imager's kernel, which is not
        re-entrant) are made here first. ``image``: the frame's confocal image, for the single-scattering
        level (``single_scattering_null``; no overlap). ``track``: False leaves the tracker alone (tracks None)."""
        level, grid, cfg = self._level, self.grid, self.cfg
        apertures: dict[str, np.ndarray] = {}
        if level is not None:  # here, on the imager's thread; the second thread gets them as arrays
            res = resolution_of(grid, acq, band)
            apertures = {n: level.aperture(acq, pw, fp, res) for n, fp in fps.items()}

        def physical() -> dict[str, tuple[np.ndarray, np.ndarray]]:
            if level is None or level.single_scattering:
                return {}
            return {n: physical_level_of(grid, acq, pw, fp, band, level, apertures[n]) for n, fp in fps.items()}

        with_velocity = self._with_velocity()

        def finish(
            gammas: Mapping[str, np.ndarray], levels: Mapping[str, tuple[np.ndarray, np.ndarray]]
        ) -> tuple[dict[str, NullModel], list, list | None]:
            nulls = {n: null_of(g, grid, acq, pw, fps[n], band, level, image, levels.get(n)) for n, g in gammas.items()}
            dets: list[tuple[Detection, float | None]] = []
            for name, g in gammas.items():
                for d in find_targets(g, grid, acq, band, name, cfg.n_peaks, cfg.interior, nulls[name], cfg.max_pfa):
                    dets.append((d, truth_error(np.asarray(d.position_m, float), truths, name)))
            tracks = None
            if track and not with_velocity:  # no velocity estimate to wait for (`_velocities` makes none)
                tracker = self._tracker
                tracks = tracker.update(gammas, acq.timestamp, nulls=nulls) if tracker is not None and gammas else []
            return nulls, dets, tracks

        if not overlap or not fps:
            return lambda gammas: lambda: finish(gammas, physical())
        if self._second is None:
            self._second = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fp-null")
        levels = self._second.submit(physical)

        def stage(gammas: Mapping[str, np.ndarray]) -> Callable[[], tuple[dict[str, NullModel], list, list | None]]:
            assert self._second is not None
            return self._second.submit(lambda: finish(gammas, levels.result())).result

        return stage

    def _notice(self, key: str, text: str, out: list[str]) -> None:
        if key not in self._noticed:
            self._noticed.add(key)
            out.append(text)
            log.warning("%s", text)

    def _velocities(
        self,
        acq: Acquisition,
        pw: PlaneWaveData,
        grid: Grid,
        dets: list[tuple[Detection, float | None]],
        frames: Mapping[str, PlaneWaveData] | None = None,
    ) -> tuple[list[VelocityEstimate | None], dict[str, list[VelocityEstimate]], list[str]]:
        """The velocity dictionaries (fpcore.velocity) of the fingerprints that have one, searched around each
        of their detections and each of their tracks' predicted positions (a region already searched, within
        half its half-width, is not searched again), on the frame `pw`, or on `frames[name]` where given (with
        ``union``: the weighted frame, where the fingerprint's kept map is the weighted one). Without a PRF the
        transmit times are unknown: said once (a notice), and no velocity is estimated."""
        notices: list[str] = []
        per_det: list[VelocityEstimate | None] = [None] * len(dets)
        motion: dict[str, list[VelocityEstimate]] = {}
        wanted = {n: e for n, e in self._entries.items() if e.spec.velocity_grid is not None and e.fp is not None}
        if not wanted:
            return per_det, motion, notices
        if acq.sequence.prf is None:
            self._notice(
                "prf",
                "prf: the frames carry no pulse repetition frequency (RFFrame 1.1 'prf'), so the transmit times "
                f"are unknown; velocity estimates of {sorted(wanted)} skipped",
                notices,
            )
            return per_det, motion, notices
        self._noticed.discard("prf")
        tau = acq.sequence.transmit_times()
        preds = self._tracker.predictions(acq.timestamp) if self._tracker is not None else []
        for name, entry in wanted.items():
            vg = entry.spec.velocity_grid
            assert vg is not None and entry.fp is not None
            search = entry.velocity
            stale = not isinstance(search, VelocitySearch) or search.fp is not entry.fp
            if stale or not np.array_equal(search.tau, tau):
                search = entry.velocity = VelocitySearch(entry.fp, vg, tau, eps=max(self.cfg.eps, 1e-4))
            found: list[VelocityEstimate] = []
            origins = [(i, np.asarray(d.position_m, float)) for i, (d, _) in enumerate(dets) if d.fingerprint == name]
            origins += [(None, p) for n, p in preds if n == name]
            for i, origin in origins:
                est = next((e for e in found if np.linalg.norm(e.origin_m - origin) <= vg.roi_half_width / 2), None)
                if est is None:
                    est = search.estimate((frames or {}).get(name, pw), origin, grid.spacing)
                    found.append(est)
                if i is not None:
                    per_det[i] = est
            motion[name] = found
        return per_det, motion, notices
