"""Processor node (`fp process`): RF frames in; γ-maps, confocal image, detections, tracks out (docs/design.md §2, §7).

The frame work is ``services.pipeline.Pipeline``; this module is the node around it. Per frame on
``fp/<rig>/rf`` it publishes, in this order, each carrying the input's frame index and acquisition
timestamp: ``…/image`` (ConfocalImage, docs/design.md §4.3), one ``…/gamma`` (GammaMap) per
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

Dictionary (docs/design.md §3): fingerprints are built against the geometry of the frames — at start on
the geometry of the first calibration (so the NUFFT plan is ready before the node announces itself),
at the first frame otherwise, and again whenever the frame geometry or a parameter changes. The
queryable ``fp/<rig>/dictionary/**`` manages it at run time (``services.registry``).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from services.bus import FifoSlot, LatestSlot, sample_publish_time
from services.convert import MAP_ENCODINGS, frame_messages
from services.messages import ErrorReport, RFFrame
from services.nodes.base import Node, frame_rate, latency_summary, start_warmed_thread, status_message
from services.nodes.frame_errors import failure_report, truth_report
from services.pipeline import Pipeline, PipelineConfig
from services.registry import DictionaryServer, FingerprintSpec
from services.runtime import limit_blas_threads
from services.wire import DEFAULT_MAX_BYTES, WireError, decode, error_report

__all__ = ["STAGES", "Processor", "ProcessorConfig"]

log = logging.getLogger("fp.processor")

#: Stages timed per frame (seconds, summed): the benchmark prints their shares.
STAGES = ("decode", "spectrum_projection", "gamma_kernel", "detection", "encode_publish")


@dataclass
class ProcessorConfig(PipelineConfig):
    """Node settings on top of the processing settings (``services.pipeline.PipelineConfig``).

    ``blas_threads`` caps OpenBLAS for the whole process (None: leave it; ``services.runtime``). The
    NUFFT keeps its own threads (FP_THREADS).
    """

    rig: str = "demo"
    name: str = "processor"
    queue: str = "newest"  # "newest" (live) | "fifo" (replay)
    fifo_depth: int = 8
    max_frame_bytes: int = DEFAULT_MAX_BYTES
    status_period: float = 1.0
    blas_threads: int | None = 1
    map_encoding: str = "uint16"  # how γ and the confocal image travel: "uint16" codes or "float32" (convert)

    def __post_init__(self) -> None:
        if self.queue not in ("newest", "fifo"):
            raise ValueError(f"--queue: expected 'newest' or 'fifo', got {self.queue!r}")
        if self.map_encoding not in MAP_ENCODINGS:
            raise ValueError(f"--map-encoding: expected uint16 or float32, got {self.map_encoding!r}")
        super().__post_init__()


@dataclass
class _Job:
    msg: RFFrame
    key: str
    t_pub: float
    t_decode: float


class Processor(Node):
    """The processor node on an open zenoh session: ``with Processor(session, cfg, specs): ...``."""

    role = "processor"

    def __init__(
        self,
        session: zenoh.Session,
        config: ProcessorConfig,
        fingerprints: list[FingerprintSpec] | tuple[FingerprintSpec, ...] = (),
        on_result: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        super().__init__(session, config.rig, config.name)
        self.pipeline = Pipeline(config, fingerprints)
        self.on_result = on_result
        self._stop = threading.Event()
        self._slot: LatestSlot[_Job] | FifoSlot[_Job] = (
            LatestSlot() if config.queue == "newest" else FifoSlot(config.fifo_depth)
        )
        self._server = DictionaryServer(session, self.keys, self, name=f"{self.name}-control")
        self._threads: list[threading.Thread] = []
        self.frames_processed = 0
        self.rejected = 0
        self.failed = 0
        self.stage_s = dict.fromkeys(STAGES, 0.0)
        self.stats_frames = 0
        self._latency: deque[float] = deque(maxlen=200)
        self._done_times: deque[float] = deque(maxlen=200)

    @property
    def cfg(self) -> ProcessorConfig:
        return self.pipeline.cfg  # type: ignore[return-value]  # set_params keeps the ProcessorConfig

    # -- lifecycle ------------------------------------------------------------------------------
    def _open(self) -> None:
        if self.cfg.blas_threads is not None:
            try:
                limit_blas_threads(self.cfg.blas_threads)
            except OSError:  # no /proc (not Linux): leave BLAS as it is
                pass
        self.declare_publishers("gamma", "image", "detections", "tracks", "status", "errors")
        # set up on the calibration's geometry, on the frame thread, before announcing the node
        self._threads = [start_warmed_thread(self.pipeline.warm_up, self._work, f"{self.name}-worker")]
        self._threads.append(threading.Thread(target=self._status_loop, name=f"{self.name}-status", daemon=True))
        self._threads[1].start()
        self._server.start_thread()
        self._sub = self.session.declare_subscriber(self.keys.rf, self._on_frame)
        self._server.declare()

    def _shutdown(self) -> None:
        """Undeclare the callbacks first (no new work), let the threads finish the frames received, publish a
        last status."""
        self._sub.undeclare()
        self._server.undeclare()
        self._stop.set()
        for t in self._threads:
            t.join(timeout=30)
        self._server.join(timeout=30)
        try:
            self._publish_status()
            self.sync_recorders()  # the last outputs reach the recorders before the session closes
        except Exception:  # the session may already be closing
            pass

    @property
    def dropped(self) -> int:
        return self._slot.dropped

    @property
    def dictionary(self) -> list[str]:
        return self.pipeline.names

    def reset_stats(self) -> None:
        """Start the latency and stage statistics afresh (e.g. after warm-up frames); counters stay."""
        self.stage_s = dict.fromkeys(STAGES, 0.0)
        self.stats_frames = 0
        self._latency.clear()
        self._done_times.clear()

    def stats(self) -> dict[str, Any]:
        """Counters, latency (ms), per-stage time (s, summed over the ``stats_frames`` frames since start
        or the last :meth:`reset_stats`) and the one-off set-up time."""
        return {
            "frames_processed": self.frames_processed,
            "stats_frames": self.stats_frames,
            "dropped": self.dropped,
            "rejected": self.rejected,
            "failed": self.failed,
            "frame_rate_hz": frame_rate(self._done_times),
            "latency_ms": latency_summary(self._latency),
            "stages_s": dict(self.stage_s),
            "setup_s": self.pipeline.setup_s,
            "dictionary": self.dictionary,
        }

    # -- dictionary (services.registry.DictionaryHost: the pipeline's, with the node's identity) ------------
    @property
    def names(self) -> list[str]:
        return self.pipeline.names

    def entry(self, name: str) -> dict[str, Any] | None:
        return self.pipeline.entry(name)

    def add(self, spec: FingerprintSpec) -> dict[str, Any]:
        """Add or replace a dictionary entry (built now if a frame or the calibration gives the geometry)."""
        return self.pipeline.add(spec)

    def remove(self, name: str) -> None:
        self.pipeline.remove(name)

    def set_params(self, params: dict[str, Any]) -> None:
        """Change band, n_freq, svd_threshold or n_peaks; fingerprints are rebuilt. Transactional
        (``Pipeline.set_params``): a refused change raises and leaves the node's set-up as it was, so
        the frames that follow are processed as before."""
        self.pipeline.set_params(params)

    def describe(self) -> dict[str, Any]:
        with self.pipeline.lock:
            d = self.pipeline.describe()
            params = d["params"]
            grid_shape = params.pop("grid_shape")
            params.update(queue=self.cfg.queue, grid_shape=grid_shape)
            return {"rig": self.cfg.rig, "node": self.cfg.name, **d}

    # -- input --------------------------------------------------------------------------------------
    def _on_frame(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        t_pub = sample_publish_time(sample) or time.time()
        raw: bytes | None = None
        limit = self.cfg.max_frame_bytes
        try:
            n = len(sample.payload)
            if n > limit:  # refuse before copying; the header comes from the attachment
                att = sample.attachment
                raw = att.to_bytes() if att is not None else None
                raise WireError("payload", f"{n} bytes exceeds the limit max_bytes={limit}")
            raw = sample.payload.to_bytes()
            t0 = time.perf_counter()
            msg = decode(raw, max_bytes=limit, expect=RFFrame)
            t_dec = time.perf_counter() - t0
        except WireError as exc:
            self.rejected += 1
            self.report(error_report(exc, key, raw, node=self.name))
            return
        except Exception as exc:  # never let a callback raise into zenoh
            self.rejected += 1
            self.report(ErrorReport(key=key, field="payload", problem=f"{type(exc).__name__}: {exc}", node=self.name))
            return
        assert isinstance(msg, RFFrame)
        truth = truth_report(msg, key, self.name)  # the RF is good: processed without its truth
        if truth is not None:
            self.report(truth)
        self._slot.put(_Job(msg, key, t_pub, t_dec), self._stop)

    # -- processing ------------------------------------------------------------------------------------
    def _work(self) -> None:
        """Process frames until stopped; on stop, the frames already received are still processed (the
        subscription is closed first, so this ends): a frame the node took in is not dropped at shutdown."""
        while True:
            try:
                job = self._slot.get(timeout=0.1)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            try:
                self._process(job)
            except Exception as exc:  # the node never dies on one frame
                self.failed += 1
                log.exception("frame %s failed", job.msg.frame_index)
                self.report(failure_report(exc, job.msg.frame_index, job.key, self.name))

    def _process(self, job: _Job) -> None:
        msg = job.msg
        res = self.pipeline.process(msg.to_acquisition())
        for note in res.notices:  # said once (e.g. no PRF: no velocity estimates), the frame goes on
            field, _, problem = note.partition(": ")
            self.report(
                ErrorReport(frame_index=msg.frame_index, key=job.key, field=field, problem=problem, node=self.name)
            )
        t3 = time.perf_counter()
        fi, ts = msg.frame_index, msg.timestamp
        out = frame_messages(res, fi, ts, self.cfg.map_encoding)  # detections above used float γ
        if out["image"] is not None:
            self.publish("image", out["image"])
        for g in out["gamma"]:
            self.publish("gamma", g)
        self.publish("tracks", out["tracks"])
        t_done = time.time()
        # Counted before the acknowledgement goes out: whoever paces on it sees the frame accounted for.
        self.frames_processed += 1
        self.stats_frames += 1
        self.publish("detections", out["detections"])
        t4 = time.perf_counter()
        latency_ms = max(t_done - job.t_pub, 0.0) * 1e3
        st = self.stage_s
        st["decode"] += job.t_decode
        for stage, s in res.stage_s.items():
            st[stage] += s
        st["encode_publish"] += t4 - t3
        self._latency.append(latency_ms)
        self._done_times.append(time.monotonic())
        if self.on_result is not None:
            self.on_result(
                {
                    "frame_index": fi,
                    "timestamp": ts,
                    "latency_ms": latency_ms,
                    "detections": [d.model_dump(mode="json") for d in out["detections"].detections],
                    "tracks": [t.model_dump(mode="json") for t in out["tracks"].tracks],
                    "gamma": res.gammas,
                    "image": res.image,
                    "grid": res.grid,
                    "truth": msg.truth,
                }
            )

    # -- status ----------------------------------------------------------------------------------------
    def _publish_status(self) -> None:
        st = self.stats()
        self.publish("status", status_message(self.name, st, st["dictionary"]))

    def _status_loop(self) -> None:
        while not self._stop.wait(self.cfg.status_period):
            try:
                self._publish_status()
            except Exception as exc:  # pragma: no cover
                log.error("status: %s", exc)
