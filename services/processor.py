"""Processor node (`fp process`): RF frames in; γ-maps, confocal image, detections, tracks out (docs/design.md §2, §7).

Per frame on ``fp/<rig>/rf`` it publishes, in this order, each carrying the input's frame index and
acquisition timestamp: ``…/image`` (ConfocalImage, docs/design.md §4.3), one ``…/gamma`` (GammaMap) per
fingerprint (§4.7), ``…/tracks`` (Tracks, ``fpcore.tracking.Tracker``) and last ``…/detections``
(Detections: C_γ, C, PFA, Cramér–Rao precision, error to the frame's ground truth if it carries
one; §4.8–4.10). Detections come last so that they double as the per-frame acknowledgement that
paces a replaying publisher. ``…/status`` carries a Status every second (frames processed, rate,
publish→detection latency median/p95, dropped, rejected, dictionary names); the liveliness token
``fp/<rig>/alive/processor`` says the node is up.

Back-pressure (docs/design.md §7): ``queue="newest"`` (live) puts a depth-1 ring between the zenoh callback
and the worker thread — the worker always takes the newest frame and the ones it skips are counted
as ``dropped``; ``queue="fifo"`` (replay) blocks the callback when its FIFO is full, so nothing is
dropped and the block reaches the publisher through BLOCK congestion control.

Bad input (docs/design.md §7): frames are validated in the callback (``services.wire.decode`` with
``max_frame_bytes``; oversize payloads are refused before they are copied). A refused frame yields
exactly one ErrorReport on ``…/errors`` naming the field and the problem, is counted as
``rejected``, and the node goes on; so does a frame whose processing fails (e.g. a geometry that
does not match the fingerprints).

Dictionary (docs/design.md §3): fingerprints are built from calibration acquisitions (target alone at r0;
§4.4) or numerical models (§4.5) against the geometry of the frames (band, frequencies, output
directions) — at start on the geometry of the first calibration (so the NUFFT plan is ready before
the node announces itself), at the first frame otherwise, and again whenever the frame geometry or a
parameter changes.
At run time the queryable ``fp/<rig>/dictionary/**`` answers JSON:

* ``get fp/<rig>/dictionary/list`` (or ``…/**``): entries and parameters;
* ``get fp/<rig>/dictionary/<name>``: one entry;
* ``get fp/<rig>/dictionary/add/<name>`` with payload either an RFFrame (calibration; options
  ``{"r0_m": [x, y, z], "diameter_m": d}`` as JSON in the attachment, default: the frame's truth) or
  JSON ``{"model": "point" | "mirror:L=2mm,alpha=10", "r0_m": [...]}``;
* ``get fp/<rig>/dictionary/remove/<name>``;
* ``get fp/<rig>/dictionary/set`` with JSON ``{"band_hz": [lo, hi], "n_freq": n, "svd_threshold": t,
  "n_peaks": k}``: fingerprints are rebuilt.

:func:`dictionary_request` is the client side.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import zenoh

from fpcore import Acquisition, Fingerprint, Grid, Imager, ImagingConfig, detect, from_calibration
from fpcore.acquisition import PlaneWaveData
from fpcore.tracking import Tracker, TrackerConfig
from services.bus import (
    FifoSlot,
    LatestSlot,
    add_bus_arguments,
    bus_from_args,
    open_session,
    put_message,
    sample_publish_time,
    stop_on_signals,
    tune_malloc,
    wait_until,
)
from services.imaging_args import add_imaging_arguments, build_model, grid_ranges
from services.messages import (
    ConfocalImage,
    Detection,
    Detections,
    ErrorReport,
    GammaMap,
    Latency,
    Normalisation,
    RFFrame,
    Status,
    Track,
    Tracks,
)
from services.messages import Grid as WireGrid
from services.sources import FingerprintSpec
from services.units import parse_band, parse_length, parse_position
from services.wire import DEFAULT_MAX_BYTES, MAGIC, WireError, decode, error_report, keys

__all__ = [
    "STAGES",
    "Processor",
    "ProcessorConfig",
    "add_process_parser",
    "dictionary_request",
    "limit_blas_threads",
    "run_process",
]

log = logging.getLogger("fp.processor")

#: Stages timed per frame (seconds, summed): the benchmark prints their shares.
STAGES = ("decode", "spectrum_projection", "gamma_kernel", "detection", "encode_publish")
_RESERVED = {"list", "add", "remove", "set", "**", "*"}


@dataclass
class ProcessorConfig:
    """Processing settings. Ranges in metres; ``band`` in Hz (default: the frame's truth band, else
    the probe's −6 dB band); ``n_freq`` frequencies kept in the band (None: every bin).

    ``blas_threads`` caps OpenBLAS for the whole process (None: leave it): the output projection is a
    batch of small GEMMs whose OpenBLAS worker threads spin against the zenoh, recorder and publisher
    threads — on 2 cores the spectrum+projection stage ran 6× slower with 2 BLAS threads than with 1
    (bench/bench_streaming.py). The NUFFT keeps its own threads (FP_THREADS).
    """

    rig: str = "demo"
    name: str = "processor"
    queue: str = "newest"  # "newest" (live) | "fifo" (replay)
    fifo_depth: int = 8
    band: tuple[float, float] | None = None
    n_freq: int | None = None  # every bin of the 2×-padded record: no delay wrap (fpcore Spectrum)
    svd_threshold: float = 0.4
    grid: Grid | None = None
    x_range: tuple[float, float] | None = None
    y_range: tuple[float, float] | None = None
    z_range: tuple[float, float] | None = None
    spacing: float | None = None
    n_out: int | None = None
    n_peaks: int = 1
    eps: float = 1e-5
    max_frame_bytes: int = DEFAULT_MAX_BYTES
    publish_image: bool = True
    track: bool = True
    track_integrate: int = 1  # tracker: search the mean of the last K γ-maps (fpcore.tracking)
    status_period: float = 1.0
    blas_threads: int | None = 1

    def __post_init__(self) -> None:
        if self.queue not in ("newest", "fifo"):
            raise ValueError(f"--queue: expected 'newest' or 'fifo', got {self.queue!r}")
        if not 0 < self.svd_threshold <= 1:
            raise ValueError(f"--svd-threshold: expected 0 < t <= 1, got {self.svd_threshold}")
        if self.n_peaks < 1:
            raise ValueError(f"--targets: expected >= 1, got {self.n_peaks}")
        if self.track_integrate < 1:
            raise ValueError(f"--track-integrate: expected an integer >= 1, got {self.track_integrate}")


@dataclass
class _Job:
    msg: RFFrame
    key: str
    t_pub: float
    t_decode: float


@dataclass
class _Entry:
    spec: FingerprintSpec
    fp: Fingerprint | None = None
    error: str | None = None

    def describe(self) -> dict[str, Any]:
        fp = self.fp
        source = "calibration" if self.spec.calibration is not None else f"model:{self.spec.model}"
        d: dict[str, Any] = {"name": self.spec.name, "source": source, "built": fp is not None, "error": self.error}
        if fp is not None:
            d.update(provenance=fp.provenance, r0_m=[float(v) for v in fp.r0], n_s=float(fp.n_s),
                     n_t=None if fp.n_t is None else float(fp.n_t), shape=list(fp.data.shape),
                     state={k: v for k, v in fp.state.items() if isinstance(v, (int, float, str))})
        return d


def limit_blas_threads(n: int) -> bool:
    """Set OpenBLAS's thread count at run time (numpy's bundled scipy-openblas or a system OpenBLAS);
    False if no OpenBLAS is loaded."""
    import ctypes

    done = False
    with open("/proc/self/maps") as maps:
        libs = sorted({line.split()[-1] for line in maps if "openblas" in line.lower() and "/" in line})
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for sym in ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                    "openblas_set_num_threads64_", "openblas_set_num_threads"):
            fn = getattr(lib, sym, None)
            if fn is not None:
                fn(ctypes.c_int(n))
                done = True
                break
    return done


def _finite(v: float, cap: float = 1e300) -> float:
    """A JSON-safe non-negative number (C_γ is infinite on a map that is zero outside the peak)."""
    return 0.0 if math.isnan(v) else float(min(max(v, 0.0), cap))


def _geometry_key(acq: Acquisition) -> tuple:
    return (acq.probe.positions.tobytes(), acq.sequence.sines.tobytes(), float(acq.fs), acq.n_samples,
            float(acq.c0))


def _truth_positions(truth: dict[str, Any] | None) -> list[tuple[str | None, np.ndarray]]:
    out = []
    for t in (truth or {}).get("targets", []) or []:
        if isinstance(t, dict) and isinstance(t.get("position_m"), list) and len(t["position_m"]) == 3:
            out.append((t.get("name"), np.asarray(t["position_m"], float)))
    return out


class Processor:
    """The processor node on an open zenoh session: ``with Processor(session, cfg, specs): ...``."""

    def __init__(self, session: zenoh.Session, config: ProcessorConfig,
                 fingerprints: list[FingerprintSpec] | tuple[FingerprintSpec, ...] = (),
                 on_result: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.session = session
        self.cfg = config
        self.keys = keys(config.rig)
        self.on_result = on_result
        self._entries: dict[str, _Entry] = {s.name: _Entry(s) for s in fingerprints}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._slot: LatestSlot[_Job] | FifoSlot[_Job] = (
            LatestSlot() if config.queue == "newest" else FifoSlot(config.fifo_depth))
        self._control: queue.Queue[Any] = queue.Queue()
        self._imager: Imager | None = None
        self._tracker: Tracker | None = None
        self._geom: tuple | None = None
        self._band: tuple[float, float] | None = None
        self._last_acq: Acquisition | None = None
        self._ref: Acquisition | None = None  # the acquisition of the last set-up (calibration or frame)
        self._threads: list[threading.Thread] = []
        self._decls: list[Any] = []
        self._pubs: dict[str, zenoh.Publisher] = {}
        self.frames_processed = 0
        self.rejected = 0
        self.failed = 0
        self.stage_s = dict.fromkeys(STAGES, 0.0)
        self.stats_frames = 0
        self.setup_s = 0.0
        self._latency: deque[float] = deque(maxlen=200)
        self._done_times: deque[float] = deque(maxlen=200)
        self._started = False

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> Processor:
        s, k = self.session, self.keys
        if self.cfg.blas_threads is not None:
            try:
                limit_blas_threads(self.cfg.blas_threads)
            except OSError:  # no /proc (not Linux): leave BLAS as it is
                pass
        block = zenoh.CongestionControl.BLOCK
        for topic in ("gamma", "image", "detections", "tracks", "status", "errors"):
            self._pubs[topic] = s.declare_publisher(getattr(k, topic), congestion_control=block)
        self._threads = [threading.Thread(target=self._work, name=f"{self.cfg.name}-worker", daemon=True),
                         threading.Thread(target=self._serve, name=f"{self.cfg.name}-control", daemon=True),
                         threading.Thread(target=self._status_loop, name=f"{self.cfg.name}-status", daemon=True)]
        cal = next((e.spec.calibration for e in self._entries.values() if e.spec.calibration is not None), None)
        if cal is not None:  # warm up on the calibration's geometry before announcing the node
            with self._lock:
                try:
                    self._setup(cal)
                except ValueError as exc:
                    log.error("set-up on the calibration geometry failed: %s", exc)
        for t in self._threads:
            t.start()
        self._sub = s.declare_subscriber(k.rf, self._on_frame)
        self._queryable = s.declare_queryable(k.dictionary, self._on_query)
        token_key = f"fp/{self.cfg.rig}/alive/processor" + ("" if self.cfg.name == "processor" else f"/{self.cfg.name}")
        self._token = s.liveliness().declare_token(token_key)
        self._started = True
        return self

    def close(self) -> None:
        """Undeclare the callbacks first (no new work), stop the threads, then the publishers."""
        if not self._started:
            return
        self._started = False
        self._sub.undeclare()
        self._queryable.undeclare()
        self._stop.set()
        self._control.put(None)
        for t in self._threads:
            t.join(timeout=30)
        try:
            self._publish_status()
        except Exception:  # the session may already be closing
            pass
        self._token.undeclare()
        for p in self._pubs.values():
            p.undeclare()

    def __enter__(self) -> Processor:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def dropped(self) -> int:
        return self._slot.dropped

    @property
    def dictionary(self) -> list[str]:
        with self._lock:
            return list(self._entries)

    def reset_stats(self) -> None:
        """Start the latency and stage statistics afresh (e.g. after warm-up frames); counters stay."""
        self.stage_s = dict.fromkeys(STAGES, 0.0)
        self.stats_frames = 0
        self._latency.clear()
        self._done_times.clear()

    def stats(self) -> dict[str, Any]:
        """Counters, latency (ms), per-stage time (s, summed over the ``stats_frames`` frames since start
        or the last :meth:`reset_stats`) and the one-off set-up time."""
        lat = np.asarray(self._latency, float)
        return {"frames_processed": self.frames_processed, "stats_frames": self.stats_frames,
                "dropped": self.dropped, "rejected": self.rejected,
                "failed": self.failed, "frame_rate_hz": self._rate(),
                "latency_ms": {"median": float(np.median(lat)) if lat.size else None,
                               "p95": float(np.percentile(lat, 95)) if lat.size else None},
                "stages_s": dict(self.stage_s), "setup_s": self.setup_s, "dictionary": self.dictionary}

    def _rate(self) -> float:
        d = self._done_times
        if len(d) < 2 or d[-1] <= d[0]:
            return 0.0
        return (len(d) - 1) / (d[-1] - d[0])

    # -- input --------------------------------------------------------------------------------------
    def _on_frame(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        t_pub = sample_publish_time(sample) or time.time()
        raw: bytes | None = None
        try:
            n = len(sample.payload)
            if n > self.cfg.max_frame_bytes:  # refuse before copying; the header comes from the attachment
                att = sample.attachment
                raw = att.to_bytes() if att is not None else None
                raise WireError("payload", f"{n} bytes exceeds the limit max_bytes={self.cfg.max_frame_bytes}")
            raw = sample.payload.to_bytes()
            t0 = time.perf_counter()
            msg = decode(raw, max_bytes=self.cfg.max_frame_bytes, expect=RFFrame)
            t_dec = time.perf_counter() - t0
        except WireError as exc:
            self.rejected += 1
            self._report(error_report(exc, key, raw, node=self.cfg.name))
            return
        except Exception as exc:  # never let a callback raise into zenoh
            self.rejected += 1
            self._report(ErrorReport(key=key, field="payload", problem=f"{type(exc).__name__}: {exc}",
                                     node=self.cfg.name))
            return
        self._slot.put(_Job(msg, key, t_pub, t_dec), self._stop)

    def _report(self, rep: ErrorReport) -> None:
        log.warning("refused %s (frame %s): %s: %s", rep.key, rep.frame_index, rep.field, rep.problem)
        try:
            put_message(self._pubs["errors"], self.session, rep)
        except Exception as exc:  # pragma: no cover - only when the session is going down
            log.error("could not publish an error report: %s", exc)

    # -- dictionary ----------------------------------------------------------------------------------
    def _setup(self, acq: Acquisition) -> None:
        """Imager, tracker and every fingerprint for the geometry of ``acq`` (called under the lock)."""
        t0 = time.perf_counter()
        cfg = self.cfg
        band = cfg.band or acq.default_band()
        grid = cfg.grid or Grid.for_acquisition(acq, band, cfg.x_range, cfg.y_range, cfg.z_range, cfg.spacing)
        out_sines = None
        if cfg.n_out:
            from fpcore import output_sines
            out_sines = output_sines(acq.probe, acq.c0, band[1], n=cfg.n_out)
        self._imager = Imager(ImagingConfig(grid, band, cfg.n_freq, out_sines, eps=cfg.eps))
        self._band = band
        self._geom = _geometry_key(acq)
        self._ref = acq
        lam = acq.c0 / acq.probe.centre_frequency
        # One track per fingerprint and expected target (cfg.n_peaks): a calibration describes one object.
        self._tracker = (Tracker(grid, lam, acq.probe.aperture[0], band[1] - band[0], acq.c0,
                                 TrackerConfig(max_tracks_per_map=max(1, cfg.n_peaks),
                                               integrate_frames=cfg.track_integrate)) if cfg.track else None)
        pw = self._imager.plane_waves(acq)
        self._imager.kernel(pw)  # NUFFT plan (FFTW planning: seconds) before the first frame is timed
        for entry in self._entries.values():
            self._build(entry, acq, pw)
            if entry.fp is not None:
                try:
                    self._imager.template(pw, entry.fp)
                except ValueError as exc:
                    entry.fp, entry.error = None, str(exc)
        self.setup_s += time.perf_counter() - t0
        log.info("set up for %s elements × %s waves × %s samples: band %.2f–%.2f MHz, grid %s, dictionary %s",
                 acq.probe.n_elements, acq.sequence.n_waves, acq.n_samples, band[0] / 1e6, band[1] / 1e6,
                 grid.shape, [e.describe()["name"] for e in self._entries.values()])

    def _build(self, entry: _Entry, acq: Acquisition, pw: PlaneWaveData) -> None:
        spec, imager, band = entry.spec, self._imager, self._band
        assert imager is not None and band is not None
        entry.fp, entry.error = None, None
        try:
            if spec.calibration is not None:
                from services.locate import check_calibration

                cal = spec.calibration
                check_calibration(cal, acq)
                r0, diameter = self._cal_position(spec)
                entry.fp = from_calibration(cal, r0, imager.out_sines_for(cal), band, self.cfg.n_freq,
                                            diameter=diameter, svd_threshold=self.cfg.svd_threshold, name=spec.name)
            else:
                r0 = np.asarray(spec.r0, float) if spec.r0 is not None else imager.grid.centre_index_point()
                if r0.shape == (2,):
                    r0 = np.array([r0[0], 0.0, r0[1]])
                entry.fp = build_model(str(spec.model), pw, r0, spec.name)
        except ValueError as exc:
            entry.error = str(exc)
            log.error("fingerprint %r: %s", spec.name, exc)

    @staticmethod
    def _cal_position(spec: FingerprintSpec) -> tuple[np.ndarray, float]:
        cal = spec.calibration
        assert cal is not None
        truth = cal.truth if isinstance(cal.truth, dict) else {}
        target = (truth.get("targets") or [{}])[0]
        if spec.r0 is not None:
            r0 = np.asarray(spec.r0, float)
        elif "r0_m" in truth:
            r0 = np.asarray(truth["r0_m"], float)
        elif isinstance(target, dict) and "position_m" in target:
            r0 = np.asarray(target["position_m"], float)
        else:
            raise ValueError(f"fingerprint {spec.name!r}: r0 unknown (give r0_m, or a calibration with truth)")
        if r0.shape != (3,):
            raise ValueError(f"fingerprint {spec.name!r}: r0 must be (x, y, z) in metres, got {r0.tolist()}")
        d = spec.diameter
        if d is None:
            d = float(truth.get("diameter_m", target.get("diameter_m", 0.0) if isinstance(target, dict) else 0.0))
        return r0, float(d)

    def add(self, spec: FingerprintSpec) -> dict[str, Any]:
        """Add or replace a dictionary entry (built now if a frame or the calibration gives the geometry)."""
        with self._lock:
            prev = self._entries.get(spec.name)
            entry = _Entry(spec)
            self._entries[spec.name] = entry
            ref = next((a for a in (self._last_acq, self._ref, spec.calibration) if a is not None), None)
            if ref is not None:
                if self._imager is None:
                    self._setup(ref)
                else:
                    self._build(entry, ref, self._imager.plane_waves(ref))
            if entry.error is not None:
                if prev is None:
                    del self._entries[spec.name]
                else:
                    self._entries[spec.name] = prev
                raise ValueError(entry.error)
            if prev is not None and prev.fp is not None and self._imager is not None:
                self._imager.forget(prev.fp)
            return entry.describe()

    def remove(self, name: str) -> None:
        with self._lock:
            entry = self._entries.pop(name, None)
            if entry is None:
                raise KeyError(name)
            if entry.fp is not None and self._imager is not None:
                self._imager.forget(entry.fp)

    def set_params(self, params: dict[str, Any]) -> None:
        """Change band, n_freq, svd_threshold or n_peaks; fingerprints are rebuilt."""
        allowed = {"band_hz", "n_freq", "svd_threshold", "n_peaks"}
        unknown = set(params) - allowed
        if unknown:
            raise ValueError(f"set: unknown parameter(s) {sorted(unknown)}; expected some of {sorted(allowed)}")
        changes: dict[str, Any] = {}
        if "band_hz" in params:
            b = params["band_hz"]
            if not (isinstance(b, list) and len(b) == 2 and 0 <= float(b[0]) < float(b[1])):
                raise ValueError(f"set: band_hz must be [f_min, f_max] with 0 <= f_min < f_max, got {b!r}")
            changes["band"] = (float(b[0]), float(b[1]))
        if "n_freq" in params:
            changes["n_freq"] = None if params["n_freq"] is None else int(params["n_freq"])
        if "svd_threshold" in params:
            changes["svd_threshold"] = float(params["svd_threshold"])
        if "n_peaks" in params:
            changes["n_peaks"] = int(params["n_peaks"])
        with self._lock:
            self.cfg = replace(self.cfg, **changes)
            self._geom = None  # rebuild at the next frame …
            ref = self._last_acq if self._last_acq is not None else self._ref
            if ref is not None:  # … or now, to report errors in the reply
                self._setup(ref)

    def params(self) -> dict[str, Any]:
        c = self.cfg
        grid = self._imager.grid if self._imager is not None else c.grid
        return {"band_hz": list(self._band or c.band or []) or None, "n_freq": c.n_freq,
                "svd_threshold": c.svd_threshold, "n_peaks": c.n_peaks, "queue": c.queue,
                "grid_shape": list(grid.shape) if grid is not None else None}

    def describe(self) -> dict[str, Any]:
        with self._lock:
            return {"rig": self.cfg.rig, "node": self.cfg.name, "params": self.params(),
                    "entries": [e.describe() for e in self._entries.values()]}

    # -- queryable ------------------------------------------------------------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        self._control.put(query)

    def _serve(self) -> None:
        while True:
            query = self._control.get()
            if query is None:
                return
            try:
                ok, doc, reply_key = self._handle(query)
            except Exception as exc:  # a bad request never takes the node down
                ok, doc, reply_key = False, {"ok": False, "error": f"{type(exc).__name__}: {exc}"}, None
            try:
                body = json.dumps(doc).encode()
                if ok:
                    query.reply(reply_key or str(query.key_expr), body)
                else:
                    query.reply_err(body)
            except Exception as exc:
                log.error("dictionary reply failed: %s", exc)
            del query  # finalises the query

    def _handle(self, query: zenoh.Query) -> tuple[bool, dict[str, Any], str | None]:
        prefix = f"fp/{self.cfg.rig}/dictionary"
        key = str(query.key_expr)
        rest = key[len(prefix):].lstrip("/") if key.startswith(prefix) else ""
        parts = rest.split("/") if rest else []
        op = parts[0] if parts else "list"
        if op in ("list", "**", "*") or any("*" in p for p in parts):
            return True, {"ok": True, **self.describe()}, f"{prefix}/list" if "*" in key else key
        payload = query.payload.to_bytes() if query.payload is not None else b""
        att = query.attachment.to_bytes() if query.attachment is not None else b""
        if op == "add":
            name = "/".join(parts[1:])
            if not name or name in _RESERVED:
                raise ValueError("add: expected fp/<rig>/dictionary/add/<name> with a plain name")
            entry = self.add(_spec_from_request(name, payload, att))
            return True, {"ok": True, "added": entry}, None
        if op == "remove":
            name = "/".join(parts[1:])
            try:
                self.remove(name)
            except KeyError:
                return False, {"ok": False, "error": f"remove: no entry {name!r}; have {self.dictionary}"}, None
            return True, {"ok": True, "removed": name, "entries": self.dictionary}, None
        if op == "set":
            params = json.loads(payload.decode() or "{}")
            if not isinstance(params, dict):
                raise ValueError("set: expected a JSON object of parameters")
            self.set_params(params)
            return True, {"ok": True, **self.describe()}, None
        name = "/".join(parts)
        with self._lock:
            entry = self._entries.get(name)
            if entry is None:
                return False, {"ok": False, "error": f"no entry {name!r}; have {list(self._entries)}"}, None
            return True, {"ok": True, "entry": entry.describe()}, None

    # -- processing ------------------------------------------------------------------------------------
    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                job = self._slot.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                self._process(job)
            except Exception as exc:  # the node never dies on one frame
                self.failed += 1
                msg = str(exc)
                field_ = "geometry" if isinstance(exc, ValueError) else "processing"
                log.exception("frame %s failed", job.msg.frame_index)
                self._report(ErrorReport(frame_index=job.msg.frame_index, key=job.key, field=field_,
                                         problem=f"{type(exc).__name__}: {msg}"[:2000], node=self.cfg.name))

    def _process(self, job: _Job) -> None:
        msg = job.msg
        acq = msg.to_acquisition()
        pubs, s = self._pubs, self.session
        st = self.stage_s
        with self._lock:
            if self._geom != _geometry_key(acq):
                self._setup(acq)
            self._last_acq = acq
            imager, band = self._imager, self._band
            assert imager is not None and band is not None
            fps = {n: e.fp for n, e in self._entries.items() if e.fp is not None}
            cfg = self.cfg
            t0 = time.perf_counter()
            pw = imager.plane_waves(acq)
            t1 = time.perf_counter()
            gammas = {n: imager.gamma(pw, fp) for n, fp in fps.items()}
            image = imager.confocal(pw) if cfg.publish_image else None
            t2 = time.perf_counter()
            grid = imager.grid
            lam = acq.c0 / acq.probe.centre_frequency
            truths = _truth_positions(msg.truth)
            dets: list[Detection] = []
            for name, g in gammas.items():
                fp = fps[name]
                state = {k: float(v) for k, v in fp.state.items()
                         if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}
                for d in detect(g, grid, lam, acq.probe.aperture[0], band[1] - band[0], acq.c0, name=name,
                                n_peaks=cfg.n_peaks, interior=True):  # as fp locate and the tracker
                    pos = np.asarray(d.position_m, float)
                    named = [t for n, t in truths if n == name]
                    cands = named or [t for _, t in truths]
                    err = min((float(np.linalg.norm(pos - t)) for t in cands), default=None)
                    dets.append(Detection(fingerprint=name, state=state, position_m=tuple(pos.tolist()),
                                          gamma_max=max(float(d.gamma_max), 0.0),
                                          contrast_c_gamma=_finite(d.c_gamma), contrast_c=_finite(d.c_pfa),
                                          pfa=float(np.clip(d.pfa, 0.0, 1.0)),
                                          precision_m=(float(d.precision_m[0]), float(d.precision_m[1])),
                                          truth_error_m=err))
            tracks: list[Track] = []
            if self._tracker is not None and gammas:
                for tr in self._tracker.update(gammas, acq.timestamp):
                    c = np.asarray(tr.covariance_m2, float)
                    c = 0.5 * (c + c.T)
                    tracks.append(Track(id=tr.track_id, fingerprint=tr.fingerprint, position_m=tuple(tr.position_m),
                                        velocity_m_s=tuple(tr.velocity_m_s),
                                        covariance=tuple(tuple(row) for row in c.tolist()),
                                        confidence=float(np.clip(tr.confidence, 0.0, 1.0)), age=tr.age))
            t3 = time.perf_counter()
        fi, ts = msg.frame_index, msg.timestamp
        wgrid = WireGrid.from_grid(grid)
        r_energy = float(np.vdot(pw.data, pw.data).real)
        if image is not None:
            put_message(pubs["image"], s, ConfocalImage(frame_index=fi, timestamp=ts, grid=wgrid, image=image))
        for name, g in gammas.items():
            fp = fps[name]
            g_m = float(np.sqrt(np.mean(np.square(g, dtype=np.float64))))
            norm = Normalisation(band_hz=band, r_energy=r_energy, f_energy=fp.norm2, gamma_m=g_m)
            state = {k: float(v) for k, v in fp.state.items()
                     if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}
            put_message(pubs["gamma"], s, GammaMap(frame_index=fi, timestamp=ts, fingerprint=name, state=state,
                                                   grid=wgrid, gamma=g, normalisation=norm))
        put_message(pubs["tracks"], s, Tracks(frame_index=fi, timestamp=ts, tracks=tracks))
        det_msg = Detections(frame_index=fi, timestamp=ts, detections=dets)
        t_done = time.time()
        put_message(pubs["detections"], s, det_msg)
        t4 = time.perf_counter()
        latency_ms = max(t_done - job.t_pub, 0.0) * 1e3
        st["decode"] += job.t_decode
        st["spectrum_projection"] += t1 - t0
        st["gamma_kernel"] += t2 - t1
        st["detection"] += t3 - t2
        st["encode_publish"] += t4 - t3
        self._latency.append(latency_ms)
        self._done_times.append(time.monotonic())
        self.frames_processed += 1
        self.stats_frames += 1
        if self.on_result is not None:
            self.on_result({"frame_index": fi, "timestamp": ts, "latency_ms": latency_ms,
                            "detections": [d.model_dump(mode="json") for d in dets],
                            "tracks": [t.model_dump(mode="json") for t in tracks],
                            "gamma": gammas, "image": image, "grid": grid, "truth": msg.truth})

    # -- status ----------------------------------------------------------------------------------------
    def _publish_status(self) -> None:
        st = self.stats()
        lat = st["latency_ms"]
        put_message(self._pubs["status"], self.session, Status(
            node=self.cfg.name, frames_processed=self.frames_processed, frame_rate_hz=st["frame_rate_hz"],
            latency_ms=Latency(median=lat["median"], p95=lat["p95"]), dropped=self.dropped,
            rejected=self.rejected, dictionary=st["dictionary"]))

    def _status_loop(self) -> None:
        while not self._stop.wait(self.cfg.status_period):
            try:
                self._publish_status()
            except Exception as exc:  # pragma: no cover
                log.error("status: %s", exc)


def _spec_from_request(name: str, payload: bytes, attachment: bytes) -> FingerprintSpec:
    """FingerprintSpec from an ``add`` query: an RFFrame calibration payload or a JSON model spec."""
    if payload[: len(MAGIC)] == MAGIC:
        try:
            frame = decode(payload, expect=RFFrame)
        except WireError as exc:
            raise ValueError(f"add: calibration payload refused: {exc}") from None
        opts = json.loads(attachment.decode() or "{}") if attachment else {}
        r0 = opts.get("r0_m")
        return FingerprintSpec(name, calibration=frame.to_acquisition(), r0=None if r0 is None else tuple(r0),
                               diameter=opts.get("diameter_m"))
    try:
        doc = json.loads(payload.decode() or "{}")
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ValueError("add: expected an RFFrame payload (calibration) or a JSON model spec") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("model"), str):
        raise ValueError('add: expected JSON {"model": "point" | "mirror:L=2mm,alpha=10", "r0_m": [x, y, z]}')
    r0 = doc.get("r0_m")
    return FingerprintSpec(name, model=doc["model"], r0=None if r0 is None else tuple(float(v) for v in r0))


def dictionary_request(session: zenoh.Session, rig: str, op: str = "list", name: str | None = None,
                       payload: bytes | dict[str, Any] | None = None, options: dict[str, Any] | None = None,
                       timeout: float = 30.0) -> dict[str, Any]:
    """Client of the dictionary queryable: ``op`` is list, get, add, remove or set. Returns the JSON reply
    (``{"ok": False, "error": ...}`` on refusal; ``{"ok": False, "error": "no reply"}`` on timeout)."""
    base = f"fp/{rig}/dictionary"
    if op == "list":
        key = f"{base}/list"
    elif op == "get":
        key = f"{base}/{name}"
    elif op in ("add", "remove"):
        if not name:
            raise ValueError(f"{op}: a name is required")
        key = f"{base}/{op}/{name}"
    elif op == "set":
        key = f"{base}/set"
    else:
        raise ValueError(f"op: expected list, get, add, remove or set, got {op!r}")
    body = json.dumps(payload).encode() if isinstance(payload, dict) else payload
    att = json.dumps(options).encode() if options else None
    deadline = time.monotonic() + timeout
    while True:  # no reply at all: the link or the queryable's declaration may not be up yet; ask again
        left = max(deadline - time.monotonic(), 0.1)
        for reply in session.get(key, payload=body, attachment=att, timeout=left):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
            return json.loads(reply.err.payload.to_bytes())
        if time.monotonic() >= deadline:
            return {"ok": False, "error": "no reply (is a processor running on this rig?)"}
        time.sleep(0.2)


# ------------------------------------------------------------------------------------------------ CLI
def add_process_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("process", help="run the processor node (γ-maps, detections, tracks)",
                       description="Processor node: subscribes to fp/<rig>/rf, publishes gamma, image, detections, "
                                   "tracks, status and errors; dictionary queryable at fp/<rig>/dictionary/**. "
                                   "Lengths are metres unless a unit is given (25mm).")
    p.add_argument("--rig", default="demo", help="rig name in the key expressions fp/<rig>/… (default demo)")
    p.add_argument("--name", default="processor", help="node name (default processor)")
    src = p.add_argument_group("fingerprint dictionary (at least one, or add at run time)")
    src.add_argument("--calibration", action="append", default=[], metavar="FILE",
                     help="UFF calibration (target alone at r0), repeatable; entry named after the file")
    src.add_argument("--r0", help="calibration target position X,Z[,Y] (default: from the calibration's truth)")
    src.add_argument("--diameter", help="target size for the time gate, e.g. 10mm (default: from the truth)")
    src.add_argument("--dataset", help="dataset name inside the calibration UFF")
    src.add_argument("--model", action="append", default=[], metavar="SPEC",
                     help="numerical fingerprint 'point' or 'mirror:L=2mm,alpha=10', repeatable")
    src.add_argument("--scenario", help="calibrations of a simulator scenario's targets (e.g. sinking-sphere)")
    src.add_argument("--full", action="store_true", help="full-size scenario (default: quick)")
    img = p.add_argument_group("imaging")
    add_imaging_arguments(img, peaks_help="peaks reported per fingerprint")
    img.add_argument("--no-image", action="store_true", help="do not publish the confocal image")
    img.add_argument("--no-track", action="store_true", help="do not run the tracker")
    img.add_argument("--track-integrate", type=int, default=1, metavar="K",
                     help="tracker: search the mean of the last K γ-maps (fog decorrelates, a slow target "
                          "persists; the track lags by v(K−1)Δt/2; default 1)")
    node = p.add_argument_group("node")
    node.add_argument("--queue", choices=("newest", "fifo"), default="newest",
                      help="newest: live, keep the newest frame, count drops; fifo: replay, block, drop nothing")
    node.add_argument("--fifo-depth", type=int, default=8, help="FIFO depth in fifo mode (default 8)")
    node.add_argument("--max-frame-bytes", type=int, default=DEFAULT_MAX_BYTES,
                      help=f"refuse larger frames (default {DEFAULT_MAX_BYTES})")
    node.add_argument("--status-period", type=float, default=1.0, help="seconds between Status messages")
    node.add_argument("--duration", type=float, help="stop after this many seconds (default: run until signalled)")
    add_bus_arguments(p, listen="tcp/127.0.0.1:7447", connect=None)
    p.set_defaults(func=run_process)


def _xyz(text: str, option: str) -> tuple[float, float, float]:
    v = parse_position(text, option)
    return (v[0], v[2] if len(v) == 3 else 0.0, v[1])


def specs_from_args(args: argparse.Namespace) -> list[FingerprintSpec]:
    """Fingerprint specs of the `fp process` options."""
    from pathlib import Path

    from fpcore.io import read_uff

    specs = []
    r0 = _xyz(args.r0, "--r0") if args.r0 else None
    diameter = parse_length(args.diameter, "--diameter") if args.diameter else None
    for path in args.calibration:
        cal = read_uff(path, args.dataset)[0]
        specs.append(FingerprintSpec(Path(path).stem, calibration=cal, r0=r0, diameter=diameter))
    for i, spec in enumerate(args.model):
        name = spec.partition(":")[0] + (f"{i}" if len(args.model) > 1 else "")
        specs.append(FingerprintSpec(name, model=spec, r0=r0))
    if args.scenario:
        from services.sources import SimulatorSource

        specs.extend(SimulatorSource(args.scenario, quick=not args.full).fingerprint_specs())
    return specs


def config_from_args(args: argparse.Namespace) -> ProcessorConfig:
    return ProcessorConfig(
        rig=args.rig, name=args.name, queue=args.queue, fifo_depth=args.fifo_depth,
        band=parse_band(args.band) if args.band else None, n_freq=args.n_freq, svd_threshold=args.svd_threshold,
        **grid_ranges(args), n_out=args.n_out,
        n_peaks=args.targets, max_frame_bytes=args.max_frame_bytes, publish_image=not args.no_image,
        track=not args.no_track, track_integrate=args.track_integrate, status_period=args.status_period)


def run_process(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    tune_malloc()
    cfg = config_from_args(args)
    specs = specs_from_args(args)
    stop = stop_on_signals()
    with open_session(bus_from_args(args)) as session:
        with Processor(session, cfg, specs) as node:
            log.info("processor on fp/%s/rf (%s queue), dictionary %s", cfg.rig, cfg.queue, node.dictionary)
            print(json.dumps({"ready": True, "rig": cfg.rig, "dictionary": node.dictionary}), flush=True)
            wait_until(stop, args.duration)
        print(json.dumps({"stopped": True, **{k: v for k, v in node.stats().items() if k != "dictionary"}}),
              flush=True)
    return 0
