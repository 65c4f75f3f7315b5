"""Publisher node (`fp publish`) and the one-process pipeline :func:`run_pipeline` (docs/design.md §2, §7).

The publisher puts one ``RFFrame`` payload per frame on ``fp/<rig>/rf`` — congestion control BLOCK
(never DROP: frames are not discarded at the sender), the wire header as the attachment, and a zenoh
timestamp (the processor measures publish → detection latency from it). Sources are in
``services.sources`` (simulator scenario, UFF file, MCAP replay, live ingest key ``fp/<rig>/ingest``).

Pacing (``pace``):

* ``original`` — the source's own timing (acquisition timestamps; MCAP log times), × ``speed``;
* ``rate`` — a fixed frame rate;
* ``ack`` — as fast as the consumer takes: at most ``window`` frames are in flight; a frame is done
  when the processor publishes its Detections (or an ErrorReport naming its frame index) — the
  processor publishes Detections last for every frame, so they are its acknowledgement. The default
  window of 2 keeps the processor busy (one frame computed, one queued) and never overflows a
  keep-newest ring, so nothing is dropped in either processor mode;
* ``none`` — back to back (zenoh's BLOCK still stops the sender when the transport is full).

Before the first frame the publisher waits for the liveliness tokens of the nodes in ``wait_for``
(``fp/<rig>/alive/processor``, the recorder's ``fp/*/alive/recorder``), so nothing is published to
nobody; its own token is ``fp/<rig>/alive/publisher``. Ingest items are untrusted: they are decoded
and validated (shape, dtype, NaN, truncation, version, size) and refused with an ErrorReport on
``fp/<rig>/errors``; valid ones are forwarded as the same bytes.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from services.bus import (
    DEFAULT_HUB,
    EPHEMERAL,
    BusConfig,
    add_bus_arguments,
    bus_from_args,
    free_port,
    open_session,
    put_message,
    stop_on_signals,
    tune_malloc,
    wait_for_matching,
    wait_for_token,
)
from services.messages import RFFrame
from services.sources import (
    FingerprintSpec,
    IngestSource,
    Item,
    MCAPSource,
    SimulatorSource,
    Source,
    UFFSource,
)
from services.wire import DEFAULT_MAX_BYTES, WireError, decode, decode_header, error_report, keys

__all__ = ["AckTracker", "Publisher", "add_publish_parser", "run_pipeline", "run_publish"]

log = logging.getLogger("fp.publisher")
PACES = ("original", "rate", "ack", "none")


class AckTracker:
    """Counts the processor's per-frame acknowledgements (Detections / ErrorReport frame indices)."""

    def __init__(self, session: zenoh.Session, rig: str) -> None:
        k = keys(rig)
        self._cond = threading.Condition()
        self._pending: Counter[int] = Counter()
        self._order: list[int] = []
        self.acked = 0
        self.timed_out = 0
        self._subs = [session.declare_subscriber(k.detections, self._on_ack),
                      session.declare_subscriber(k.errors, self._on_ack)]

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs = []

    def _on_ack(self, sample: zenoh.Sample) -> None:
        att = sample.attachment
        try:
            raw = att.to_bytes() if att is not None else sample.payload.to_bytes()
            fi = decode_header(raw, strict=False).frame_index
        except WireError:
            return
        if fi is None:
            return
        with self._cond:
            if self._pending[fi] > 0:
                self._pending[fi] -= 1
                self._order.remove(fi)
                self.acked += 1
                self._cond.notify_all()

    def expect(self, frame_index: int | None) -> None:
        if frame_index is None:
            return
        with self._cond:
            self._pending[frame_index] += 1
            self._order.append(frame_index)

    @property
    def in_flight(self) -> int:
        with self._cond:
            return len(self._order)

    def wait_below(self, n: int, timeout: float, stop: threading.Event) -> None:
        """Wait until fewer than ``n`` frames are in flight; a frame unacknowledged for ``timeout`` s is
        given up (counted in ``timed_out``)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while len(self._order) >= n and not stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    fi = self._order.pop(0)
                    self._pending[fi] -= 1
                    self.timed_out += 1
                    log.warning("no acknowledgement of frame %s within %.0f s; going on", fi, timeout)
                    deadline = time.monotonic() + timeout
                    continue
                self._cond.wait(min(left, 0.2))


def _sleep_until(t_wall: float, stop: threading.Event) -> None:
    while not stop.is_set():
        left = t_wall - time.time()
        if left <= 0:
            return
        stop.wait(min(left, 0.2))


class Publisher:
    """Publishes a source's frames on ``fp/<rig>/rf`` (see the module doc for pacing and validation)."""

    def __init__(self, session: zenoh.Session, rig: str, source: Source, pace: str = "original",
                 rate: float | None = None, speed: float = 1.0, window: int = 2,
                 wait_for: Iterable[str] = ("processor",), wait_timeout: float = 10.0, ack_timeout: float = 30.0,
                 max_frame_bytes: int = DEFAULT_MAX_BYTES, limit: int | None = None, name: str = "publisher",
                 on_publish: Callable[[Item, float], None] | None = None) -> None:
        if pace not in PACES:
            raise ValueError(f"--pace: expected one of {', '.join(PACES)}, got {pace!r}")
        if pace == "rate" and not (rate and rate > 0):
            raise ValueError(f"--rate: expected a positive frame rate in Hz, got {rate}")
        if window < 1:
            raise ValueError(f"--window: expected >= 1, got {window}")
        if speed <= 0:
            raise ValueError(f"--speed: expected > 0, got {speed}")
        self.session, self.rig, self.source = session, rig, source
        self.keys = keys(rig)
        self.pace, self.rate, self.speed, self.window = pace, rate, speed, window
        self.wait_for = tuple(wait_for)
        self.wait_timeout, self.ack_timeout = wait_timeout, ack_timeout
        self.max_frame_bytes, self.limit, self.name = max_frame_bytes, limit, name
        self.on_publish = on_publish
        self.published = 0
        self.rejected = 0
        self.bytes = 0
        self.publish_times: dict[int, float] = {}

    def _token_key(self, node: str) -> str:
        if node == "processor":
            return f"fp/{self.rig}/alive/processor/**"
        if node == "recorder":
            return "fp/*/alive/recorder"
        raise ValueError(f"--wait-for: expected processor and/or recorder, got {node!r}")

    def _validate(self, item: Item) -> Item | None:
        """Decode an untrusted payload; refuse it with an ErrorReport, or return it with a fresh header."""
        try:
            msg = decode(item.payload, max_bytes=self.max_frame_bytes, expect=RFFrame)
        except WireError as exc:
            self.rejected += 1
            rep = error_report(exc, f"fp/{self.rig}/ingest", item.payload, node=self.name)
            log.warning("ingest refused (frame %s): %s: %s", rep.frame_index, rep.field, rep.problem)
            put_message(self._err_pub, self.session, rep)
            return None
        from services.wire import extract_header

        return Item(item.payload, extract_header(item.payload), msg.frame_index, float(msg.timestamp))

    def run(self, stop: threading.Event | None = None) -> dict[str, Any]:
        """Publish until the source ends (or ``stop``); returns counts and timing."""
        stop = stop or threading.Event()
        s = self.session
        bind = getattr(self.source, "bind", None)
        if bind is not None:
            bind(s, stop)
        block = zenoh.CongestionControl.BLOCK
        rf_pub = s.declare_publisher(self.keys.rf, congestion_control=block)
        self._err_pub = s.declare_publisher(self.keys.errors, congestion_control=block)
        acks = AckTracker(s, self.rig) if self.pace == "ack" else None
        # Declared after the ingest subscription: a peer that sees the token also has the subscription.
        token = s.liveliness().declare_token(
            f"fp/{self.rig}/alive/publisher" + ("" if self.name == "publisher" else f"/{self.name}"))
        t_start = time.time()
        t_first: float | None = None
        try:
            for node in self.wait_for:
                if not wait_for_token(s, self._token_key(node), self.wait_timeout):
                    if self.pace == "ack" and node == "processor":
                        raise TimeoutError(f"no processor on fp/{self.rig} after {self.wait_timeout:.0f} s "
                                           "(--pace ack needs one)")
                    log.warning("no %s seen on fp/%s after %.0f s; publishing anyway", node, self.rig,
                                self.wait_timeout)
            if self.wait_for and not wait_for_matching(rf_pub, self.wait_timeout):
                log.warning("no subscriber to %s after %.0f s; publishing anyway", self.keys.rf, self.wait_timeout)
            t0_wall: float | None = None
            t0_src = 0.0
            for item in self.source:
                if stop.is_set() or (self.limit is not None and self.published >= self.limit):
                    break
                if not item.trusted:
                    checked = self._validate(item)
                    if checked is None:
                        continue
                    item = checked
                if t0_wall is None:
                    t0_wall, t0_src = time.time(), item.t_s
                if self.pace == "original":
                    _sleep_until(t0_wall + (item.t_s - t0_src) / self.speed, stop)
                elif self.pace == "rate":
                    _sleep_until(t0_wall + self.published / float(self.rate or 1.0), stop)
                elif acks is not None:
                    acks.wait_below(self.window, self.ack_timeout, stop)
                if stop.is_set():
                    break
                if acks is not None:
                    acks.expect(item.frame_index)
                t = time.time()
                rf_pub.put(item.payload, attachment=item.header or None, timestamp=s.new_timestamp())
                t_first = t if t_first is None else t_first
                if item.frame_index is not None:
                    self.publish_times[item.frame_index] = t
                self.published += 1
                self.bytes += len(item.payload)
                if self.on_publish is not None:
                    self.on_publish(item, t)
            if acks is not None:
                acks.wait_below(1, self.ack_timeout, stop)
        finally:
            stop_source = getattr(self.source, "stop", None)
            if stop_source is not None:
                stop_source()
            if acks is not None:
                acks.close()
            token.undeclare()
            rf_pub.undeclare()
            self._err_pub.undeclare()
        t_end = time.time()
        span = t_end - (t_first or t_start)
        return {"published": self.published, "rejected": self.rejected, "bytes": self.bytes,
                "acked": None if acks is None else acks.acked, "ack_timeouts": None if acks is None else acks.timed_out,
                "wall_s": t_end - t_start, "frame_rate_hz": self.published / span if span > 0 else 0.0,
                "pace": self.pace}


# ------------------------------------------------------------------------------------------------ pipeline
def run_pipeline(source: Source | str, rig: str = "demo", out_dir: str | Path = "out/pipeline",
                 n_frames: int | None = None, progress_callback: Callable[[dict[str, Any]], None] | None = None,
                 *, fingerprints: list[FingerprintSpec] | None = None, processor: Any = None, record: bool = True,
                 pace: str = "ack", window: int = 2, quick: bool = True, shm: str = "auto",
                 warmup: int = 0, timeout: float = 600.0) -> dict[str, Any]:
    """Publisher + processor + recorder in one process, over zenoh on loopback; returns when every frame
    is processed (and recorded). ``fp demo`` and the benchmark call it.

    source: a Source (``services.sources``) or a simulator scenario name (``"sinking-sphere"``; quick
    unless ``quick=False``). fingerprints: default, the source's calibrations
    (``SimulatorSource.fingerprint_specs``). processor: a ``ProcessorConfig`` (default: FIFO queue,
    ``rig``). ``progress_callback(result)`` runs in the processor's worker thread after each frame with
    ``frame_index, timestamp, latency_ms, detections, tracks, gamma`` (name → array), ``image``,
    ``grid``, ``truth`` — keep it quick. The summary (also written to ``out_dir/pipeline_summary.json``)
    has counts, rates, latency median/p95, mean stage times and their shares, the recording and the
    per-frame detections. ``warmup`` frames are left out of the rate, latency and stage statistics
    (the first messages of a session page-fault its shared-memory pool: ≈ 0.5 s once, see services.bus).
    """
    from services.processor import STAGES, Processor, ProcessorConfig
    from services.recorder import Recorder

    src: Source = SimulatorSource(source, n_frames=n_frames, quick=quick) if isinstance(source, str) else source
    if fingerprints is None:
        specs = getattr(src, "fingerprint_specs", None)
        fingerprints = specs() if specs is not None else []
    cfg = processor or ProcessorConfig(rig=rig, queue="fifo")
    if cfg.rig != rig:
        raise ValueError(f"processor config rig {cfg.rig!r} differs from rig {rig!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    hub = f"tcp/127.0.0.1:{free_port()}"
    rows: list[dict[str, Any]] = []
    latencies: list[float] = []
    marks: dict[str, float] = {}
    nodes: list[Any] = []

    def on_result(res: dict[str, Any]) -> None:
        rows.append({"frame_index": res["frame_index"], "timestamp": res["timestamp"],
                     "latency_ms": res["latency_ms"], "detections": res["detections"], "tracks": res["tracks"]})
        if len(rows) > warmup:
            latencies.append(res["latency_ms"])
        if len(rows) == warmup:
            nodes[0].reset_stats()
            marks["t_warm"] = time.time()
        marks["t_last"] = time.time()
        if progress_callback is not None:
            progress_callback(res)

    tune_malloc()
    t0 = time.time()
    rec: Any = None
    with contextlib.ExitStack() as stack:
        s_proc = stack.enter_context(open_session(BusConfig(listen=[hub], connect=[], shm=shm)))
        node = stack.enter_context(Processor(s_proc, cfg, fingerprints, on_result=on_result))
        nodes.append(node)
        if record:
            s_rec = stack.enter_context(open_session(BusConfig(listen=[EPHEMERAL], connect=[hub], shm=shm)))
            stamp = time.strftime("%Y%m%dT%H%M%S")
            rec = stack.enter_context(Recorder(s_rec, out / f"{rig}-{stamp}.mcap", rig=rig))
        s_pub = stack.enter_context(open_session(BusConfig(listen=[EPHEMERAL], connect=[hub], shm=shm)))
        pub = Publisher(s_pub, rig, src, pace=pace, window=window, limit=n_frames, ack_timeout=timeout,
                        wait_for=("processor", "recorder") if record else ("processor",), wait_timeout=30.0)
        pub_summary = pub.run()
        deadline = time.monotonic() + 10.0  # the last acknowledged frame finishes its bookkeeping
        expected = pub.published - node.rejected
        while time.monotonic() < deadline and (node.frames_processed + node.failed < expected
                                               or len(rows) < node.frames_processed):
            time.sleep(0.02)
        while rec is not None and time.monotonic() < deadline and (
                rec.counts[keys(rig).detections] < node.frames_processed or rec.received < pub.published):
            time.sleep(0.05)
        stats = node.stats()
    wall = time.time() - t0
    n = max(stats["stats_frames"], 1)
    stages = {k: stats["stages_s"][k] / n for k in STAGES}
    rate = pub_summary["frame_rate_hz"]
    if warmup and "t_warm" in marks and stats["stats_frames"] > 0 and marks["t_last"] > marks["t_warm"]:
        rate = stats["stats_frames"] / (marks["t_last"] - marks["t_warm"])
    total = sum(stages.values()) or 1.0
    lat = np.asarray(latencies, float)
    summary: dict[str, Any] = {
        "rig": rig, "frames_published": pub_summary["published"], "frames_processed": stats["frames_processed"],
        "dropped": stats["dropped"], "rejected": stats["rejected"], "failed": stats["failed"],
        "wall_s": wall, "publish_wall_s": pub_summary["wall_s"],
        "frame_rate_hz": rate, "warmup_frames": warmup,
        "latency_ms": {"median": float(np.median(lat)) if lat.size else None,
                       "p95": float(np.percentile(lat, 95)) if lat.size else None},
        "stage_mean_s": stages, "stage_share": {k: v / total for k, v in stages.items()},
        "setup_s": stats["setup_s"], "dictionary": stats["dictionary"],
        "recording": rec.summary() if rec is not None else None,
        "frames": sorted(rows, key=lambda r: r["frame_index"]), "out_dir": str(out),
    }
    (out / "pipeline_summary.json").write_text(json.dumps(summary, indent=2))
    return summary


# ------------------------------------------------------------------------------------------------------- CLI
def add_publish_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("publish", help="publish RF frames on fp/<rig>/rf",
                       description="Publisher: frames from a simulator scenario, a UFF file, an MCAP recording or "
                                   "the live ingest key fp/<rig>/ingest, on fp/<rig>/rf.")
    p.add_argument("--rig", default="demo", help="rig name (default demo)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", help="simulator scenario (sinking-sphere, lesion-marker, muscle-fibres)")
    src.add_argument("--uff", help="UFF file of plane-wave frames")
    src.add_argument("--mcap", help="MCAP recording: replay its …/rf messages (same bytes)")
    src.add_argument("--ingest", action="store_true", help="forward valid frames put on fp/<rig>/ingest")
    p.add_argument("--full", action="store_true", help="full-size scenario (default: quick)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    p.add_argument("--dataset", help="dataset name inside the UFF file")
    p.add_argument("--from-rig", help="MCAP replay: the recorded rig to replay (default: any)")
    p.add_argument("--frames", type=int, help="publish at most this many frames")
    p.add_argument("--repeat", type=int, default=1, help="replay a finite source this many times (default 1)")
    pace = p.add_argument_group("pacing")
    pace.add_argument("--pace", choices=PACES, help="original timing (default), fixed rate, ack (as fast as the "
                                                    "processor takes) or none")
    pace.add_argument("--rate", type=float, help="frames per second (implies --pace rate)")
    pace.add_argument("--fast", action="store_true", help="as fast as the consumer takes (same as --pace ack)")
    pace.add_argument("--speed", type=float, default=1.0, help="original timing × speed (default 1)")
    pace.add_argument("--window", type=int, default=2, help="frames in flight with --pace ack (default 2)")
    pace.add_argument("--wait-for", default="processor",
                      help="nodes to wait for before publishing: processor, recorder, both comma-separated, or none")
    pace.add_argument("--wait-timeout", type=float, default=10.0, help="seconds to wait for them (default 10)")
    pace.add_argument("--ack-timeout", type=float, default=30.0, help="give up on a frame's ack after (default 30)")
    p.add_argument("--max-frame-bytes", type=int, default=DEFAULT_MAX_BYTES, help="ingest: refuse larger frames")
    add_bus_arguments(p, listen=EPHEMERAL, connect=DEFAULT_HUB)
    p.set_defaults(func=run_publish)


def source_from_args(args: argparse.Namespace) -> Source:
    if args.scenario:
        return SimulatorSource(args.scenario, n_frames=args.frames, quick=not args.full, seed=args.seed,
                               repeat=args.repeat)
    if args.uff:
        return UFFSource(args.uff, args.dataset, repeat=args.repeat)
    if args.mcap:
        return MCAPSource(args.mcap, from_rig=args.from_rig, repeat=args.repeat)
    return IngestSource(args.rig)


def run_publish(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    tune_malloc()
    pace = args.pace or ("ack" if args.fast else "rate" if args.rate else "none" if args.ingest else "original")
    wait_for = [] if args.wait_for == "none" else [w.strip() for w in args.wait_for.split(",") if w.strip()]
    source = source_from_args(args)
    stop = stop_on_signals()
    with open_session(bus_from_args(args)) as session:
        pub = Publisher(session, args.rig, source, pace=pace, rate=args.rate, speed=args.speed, window=args.window,
                        wait_for=wait_for, wait_timeout=args.wait_timeout, ack_timeout=args.ack_timeout,
                        max_frame_bytes=args.max_frame_bytes, limit=args.frames)
        if isinstance(source, IngestSource):
            source.bind(session)
            print(json.dumps({"ready": True, "ingest": f"fp/{args.rig}/ingest"}), flush=True)
        summary = pub.run(stop)
    print(json.dumps(summary), flush=True)
    return 0
