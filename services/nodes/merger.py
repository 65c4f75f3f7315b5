"""Merger node (`fp merge`): the one ordered stage of a sharded processor (docs/scaling.md).

From the outside the merger is the rig's processor: its liveliness token is
``fp/<rig>/alive/processor/<name>`` (a publisher pacing on acknowledgements waits for it) and per frame it
publishes, in frame order, exactly what ``services.nodes.processor`` publishes — ``image``, one ``gamma``
per fingerprint, ``tracks``, then ``detections`` (the acknowledgement), or the frame's ErrorReport — plus
a Status every second. The γ-maps are computed by γ workers (``services.nodes.worker``); the merger runs
only the tracker (``services.pipeline.make_tracker``, fed each map's null model as the single node does).

Shares. The merger receives every frame on ``fp/<rig>/rf`` (it reads only the header attachment; it is
usually the deployment's router, so the frame is in its process anyway) and forwards it, as it came, to
one live worker on ``fp/<rig>/@shard/assign/<worker>`` — the least loaded, at most ``depth`` frames each,
ties rotating with the frame index — so each frame crosses the network once more, to one worker.
Membership is the set of liveliness tokens ``fp/<rig>/alive/worker/*`` (zenoh ends a token when its
session closes, its process dies or its link's lease expires), so shares re-balance by themselves as
workers come and go. The merger keeps each frame (zenoh's buffer, no copy) until its result is merged:

* a worker's token goes → the frames it had and did not return are sent to the others at once;
* no worker alive → frames wait (``fifo``) until one comes;
* a result that arrives twice (a worker thought dead came back) is published once (``duplicates``);
* a frame a worker could not compute comes back ``failed``: its ErrorReport is published in its place, in
  frame order, and the frames after it go on (``failed``);
* ``frame_timeout_s``: a frame a live worker has not returned in time goes to another live worker;
  ``frame_deadline_s``: a frame still without a result that long after it was first forwarded is given up —
  one ErrorReport (field ``deadline``) in its place, and a late result is counted as a duplicate.

Modes (``shard``). ``frame``: each frame goes whole to one worker, as above. ``fingerprint``: each frame
goes to every live worker, each computing its share of the dictionary (``services.nodes.shares``: the
fingerprints dealt in turn, plus ``@image`` — the confocal image and the truth report — to one of them);
the merger joins the parts as the single node orders them. ``both``: the live workers form groups of
``group_size`` (by name); each frame goes to one group (the least loaded), split over its members. A
dead worker's units that were not returned go to the frame's other live workers at once (every worker
holds the whole dictionary, so nothing is built on the way). The merger learns the dictionary's names from
the workers and answers ``fp/<rig>/dictionary/**`` for the deployment (``shares.DictionaryFront``).

Queue modes as the processor's: ``fifo`` (replay) keeps every frame until it is merged; ``newest`` (live)
keeps only the newest frame waiting for a free worker and counts the others as ``dropped``. Either way
the merger holds at most ``fifo_depth`` frames beyond its workers' ``depth`` each (waiting for a worker, or
merged and waiting for an earlier frame); a frame over that is refused and counted as ``dropped`` — in
``fifo`` mode with an ErrorReport naming the limit (the frame's acknowledgement). The merger refuses rather
than block the zenoh callback as the processor's FIFO does: the workers' results arrive on the same receive
threads, so a blocked callback could stall the very results that would free room.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from fpcore.tracking import Tracker, TrackState
from services.bus import sample_publish_time
from services.convert import motion_of, track
from services.messages import Detections, ErrorReport, GammaMap, Tracks
from services.nodes.base import Node, frame_rate, latency_summary, status_message
from services.nodes.frame_errors import failure_report
from services.nodes.shares import DictionaryFront, join_parts, split_units, worker_groups
from services.nodes.worker import IMAGE_UNIT, WHOLE, ShardResult, decode_shard, encode_part
from services.pipeline import make_tracker
from services.wire import WireError, decode, decode_header, encode, error_report, extract_header

__all__ = ["Merger", "MergerConfig"]

log = logging.getLogger("fp.merger")
SHARDS = ("frame", "fingerprint", "both")


@dataclass
class MergerConfig:
    """``depth``: frames in flight per worker (one computed, one waiting); ``min_workers``: the node announces
    itself once that many workers are alive (or after ``wait_workers_s``)."""

    rig: str = "demo"
    name: str = "merger"
    queue: str = "newest"  # "newest" (live) | "fifo" (replay)
    depth: int = 2
    min_workers: int = 1
    wait_workers_s: float = 60.0
    track: bool = True
    status_period: float = 1.0
    frame_timeout_s: float | None = None  # re-send a frame a live worker has not returned after this long
    frame_deadline_s: float | None = None  # give a frame up (ErrorReport) this long after its first forward
    fifo_depth: int = 8  # frames held beyond the workers' `depth` each; a frame over that is refused
    shard: str = "frame"  # frame | fingerprint | both (module doc)
    group_size: int = 2  # workers per group with shard="both"

    def __post_init__(self) -> None:
        if self.queue not in ("newest", "fifo"):
            raise ValueError(f"--queue: expected 'newest' or 'fifo', got {self.queue!r}")
        if self.depth < 1:
            raise ValueError(f"--depth: expected >= 1, got {self.depth}")
        if self.frame_timeout_s is not None and not self.frame_timeout_s > 0:
            raise ValueError(f"--frame-timeout: expected > 0 seconds, got {self.frame_timeout_s}")
        if self.frame_deadline_s is not None and not self.frame_deadline_s > 0:
            raise ValueError(f"--frame-deadline: expected > 0 seconds, got {self.frame_deadline_s}")
        if self.fifo_depth < 1:
            raise ValueError(f"--fifo-depth: expected >= 1, got {self.fifo_depth}")
        if self.shard not in SHARDS:
            raise ValueError(f"--shard: expected one of {', '.join(SHARDS)}, got {self.shard!r}")
        if self.group_size < 1:
            raise ValueError(f"--group-size: expected >= 1, got {self.group_size}")
        if self.min_workers < 0:
            raise ValueError(f"--workers: expected >= 0, got {self.min_workers}")


@dataclass
class _Frame:
    """A frame in hand: its units (``*`` or fingerprint names and ``@image``), who holds each, what came back."""

    t_pub: float
    payload: Any  # the RFFrame payload as zenoh delivered it (ZBytes), until the frame's result is in
    header: bytes
    units: list[str] | None = None  # None: not split yet
    owner: dict[str, str | None] = field(default_factory=dict)  # unit → worker computing it (None: to send)
    got: dict[str, ShardResult] = field(default_factory=dict)  # unit → the part that covered it
    targets: list[str] = field(default_factory=list)  # the workers it was split over
    sent: int = 0  # parts forwarded
    t_sent: dict[str, float] = field(default_factory=dict)  # unit → time.monotonic() of its last forward
    t_first: float = 0.0  # time.monotonic() of the first forward
    tried: set[str] = field(default_factory=set)  # workers it was forwarded to
    slow: set[str] = field(default_factory=set)  # workers that did not return it within the frame timeout
    result: ShardResult | None = None

    def out(self) -> dict[str, str]:
        """unit → worker, for the units forwarded and not returned."""
        return {u: w for u, w in self.owner.items() if w is not None and u not in self.got}

    def waiting(self) -> list[str]:
        """The units to forward (new, or their worker left or was too slow)."""
        return [u for u in self.units or [] if self.owner.get(u) is None and u not in self.got]

    @property
    def idle(self) -> bool:
        """Nothing of it out or back: a frame waiting for a worker."""
        return self.result is None and not self.got and not self.out()


class Merger(Node):
    """The ordered stage on an open zenoh session: ``with Merger(session, cfg): ...`` (module doc)."""

    role = "processor"

    def __init__(self, session: zenoh.Session, config: MergerConfig) -> None:
        super().__init__(session, config.rig, config.name)
        self.cfg = config
        self._cond = threading.Condition()
        self._members: set[str] = set()
        self._frames: dict[int, _Frame] = {}
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._tracker: Tracker | None = None
        self._tracker_key: Any = None
        self._names: list[str] | None = None  # the dictionary the workers hold (fingerprint modes split it)
        self._front = DictionaryFront(session, self.keys, lambda: self.workers, self._on_names, f"{self.name}-dict")
        self.frames_processed = 0
        self.dropped = 0
        self.rejected = 0
        self.reassigned = 0
        self.duplicates = 0
        self.timed_out = 0
        self.failed = 0
        self.per_worker: dict[str, int] = {}
        self.dictionary: list[str] = []
        self._latency: deque[float] = deque(maxlen=1000)
        self._done_times: deque[float] = deque(maxlen=200)

    # -- lifecycle ----------------------------------------------------------------------------------------
    def _open(self) -> None:
        self.declare_publishers("gamma", "image", "detections", "tracks", "status", "errors")
        pre = self.keys.alive("worker") + "/"
        self._pre = pre
        self._front.start()
        self._subs = [
            self.session.liveliness().declare_subscriber(f"{pre}*", self._on_token, history=True),
            self.session.declare_subscriber(self.keys.topic("shard_result"), self._on_result),
        ]
        deadline = time.monotonic() + self.cfg.wait_workers_s
        split = self.cfg.shard != "frame"
        with self._cond:
            while time.monotonic() < deadline and (
                len(self._members) < self.cfg.min_workers or (split and self._members and self._names is None)
            ):
                self._cond.wait(0.1)
            if len(self._members) < self.cfg.min_workers:
                log.warning(
                    "%d of %d workers after %.0f s; starting",
                    len(self._members),
                    self.cfg.min_workers,
                    self.cfg.wait_workers_s,
                )
        self._threads = [
            threading.Thread(target=self._emit_loop, name=f"{self.name}-merge", daemon=True),
            threading.Thread(target=self._status_loop, name=f"{self.name}-status", daemon=True),
        ]
        for t in self._threads:
            t.start()
        self._subs.append(self.session.declare_subscriber(self.keys.rf, self._on_frame))

    def _shutdown(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._front.stop()
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for t in self._threads:
            t.join(timeout=30)
        with self._cond:
            pending = sorted(self._frames)
        if pending:
            log.warning("stopped with %d frames not merged (counted as pending): %s", len(pending), pending[:20])
        try:
            self._publish_status()
            self.sync_recorders()  # the last outputs reach the recorders before the session closes
        except Exception:
            pass

    @property
    def workers(self) -> list[str]:
        with self._cond:
            return sorted(self._members)

    def stats(self) -> dict[str, Any]:
        with self._cond:
            pending = len(self._frames)
        return {
            "shard": self.cfg.shard,
            "frames_processed": self.frames_processed,
            "failed": self.failed,
            "pending": pending,  # frames in hand, not merged yet (at stop: never merged)
            "dropped": self.dropped,
            "rejected": self.rejected,
            "reassigned": self.reassigned,
            "duplicates": self.duplicates,
            "timed_out": self.timed_out,
            "per_worker": dict(self.per_worker),
            "workers": self.workers,
            "frame_rate_hz": frame_rate(self._done_times),
            "latency_ms": latency_summary(self._latency),
        }

    # -- membership, dictionary, frames and results (zenoh callbacks: bookkeeping only) ----------------------
    def _on_token(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr)[len(self._pre) :]
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._members.add(name)
                log.info("worker %s joined (%d)", name, len(self._members))
                self._front.refresh(name)
            else:
                self._members.discard(name)
                moved = []
                for fi, f in self._frames.items():
                    units = [u for u, w in f.out().items() if w == name]
                    for u in units:
                        f.owner[u] = None
                    if units and f.result is None:
                        moved.append(fi)
                self.reassigned += len(moved)
                log.warning("worker %s left (%d left); frames %s move to the others", name, len(self._members), moved)
            self._dispatch()
            self._cond.notify_all()

    def _on_names(self, worker: str, names: list[str], changed: bool) -> None:
        """A worker's dictionary: when it joined (the first one sets the deployment's), or after a change
        through the dictionary front (``changed``: the new dictionary)."""
        with self._cond:
            if self._names is not None and names != self._names and not changed:
                log.warning(
                    "worker %s holds %s, the others %s: every worker needs the same dictionary",
                    worker,
                    names,
                    self._names,
                )
            if self._names is None or changed:
                self._names = list(names)
                log.info("dictionary %s", self._names)
            self._dispatch()
            self._cond.notify_all()

    def _on_frame(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        att = sample.attachment
        try:
            raw = att.to_bytes() if att is not None else extract_header(sample.payload.to_bytes())
            fi = decode_header(raw, strict=False).frame_index
            if fi is None:
                raise WireError("frame_index", "expected the frame index in the header, found none")
        except WireError as exc:
            self.rejected += 1
            self.report(error_report(exc, key, None, node=self.name))
            return
        t_pub = sample_publish_time(sample) or time.time()
        newest = self.cfg.queue == "newest"
        with self._cond:
            if fi in self._frames:  # a frame already in hand (a re-sent frame); a later run may reuse indices
                return
            limit = self.cfg.fifo_depth + self.cfg.depth * len(self._members)
            replaced = sum(f.idle for f in self._frames.values()) if newest else 0
            held = len(self._frames) - replaced  # in live mode the new frame replaces the waiting one
            if held >= limit:
                self.dropped += 1
            else:
                self._frames[fi] = _Frame(t_pub, sample.payload, raw)
                self._dispatch()
                if newest:  # keep only the newest frame that waits for a worker
                    waiting = sorted(i for i, f in self._frames.items() if f.idle)
                    for i in waiting[:-1]:
                        del self._frames[i]
                        self.dropped += 1
                self._cond.notify_all()
        if held >= limit and not newest:  # replay: the frame's acknowledgement, naming the limit
            problem = (
                f"the merger holds {held} frames, its limit (--fifo-depth {self.cfg.fifo_depth} beyond --depth "
                f"{self.cfg.depth} per worker, {len(self._members)} workers); frame refused: pace the publisher "
                "(--pace ack, --window within the limit) or raise --fifo-depth"
            )
            self.report(ErrorReport(frame_index=fi, key=key, field="fifo_depth", problem=problem, node=self.name))

    def _on_result(self, sample: zenoh.Sample) -> None:
        try:
            res = decode_shard(sample.payload.to_bytes())
        except ValueError as exc:
            self.rejected += 1
            self.report(ErrorReport(key=str(sample.key_expr), field="shard", problem=str(exc)[:2000], node=self.name))
            return
        with self._cond:
            f = self._frames.get(res.frame_index)
            new = [] if f is None else [u for u in res.units if u in f.owner and u not in f.got]
            if f is None or not new:
                self.duplicates += 1
                return
            if f.result is not None:  # a part of a frame that failed in another worker: already answered
                return
            for u in new:
                f.got[u] = res
            if res.kind != "result":
                f.result = res  # the frame's ErrorReport, as the single node gives one
            elif f.units is not None and len(f.got) == len(f.units):
                f.result = res if f.units == [WHOLE] else join_parts(res.frame_index, f.units, f.got)
            if f.result is not None:
                f.payload = None
                self._dispatch()
            self._cond.notify_all()

    def _dispatch(self) -> None:
        """Forward what waits, oldest frame first (under the lock): a frame's orphaned units to its other live
        workers, new frames to the least loaded live worker (frame), every worker (fingerprint) or group (both)."""
        members = sorted(self._members)
        if not members:
            return
        load = dict.fromkeys(members, 0)
        for f in self._frames.values():
            for w in set(f.out().values()):
                if w in load and f.result is None:
                    load[w] += 1
        if self.cfg.shard != "frame":  # orphaned units first: the frame's live workers take them now
            for fi in sorted(self._frames):
                f = self._frames[fi]
                if f.result is None and f.sent and f.waiting():
                    live = [w for w in members if w not in f.slow]
                    cands = [w for w in live if w in f.targets] or live or members
                    self._send(fi, f, split_units(f.waiting(), cands, fi))
        for fi in sorted(self._frames):
            f = self._frames[fi]
            if f.result is not None or (f.units is not None and not f.waiting()):
                continue
            if self.cfg.shard == "frame":
                if not self._dispatch_whole(fi, f, members, load):
                    return
            elif not self._dispatch_split(fi, f, members, load):
                return

    def _dispatch_whole(self, fi: int, f: _Frame, members: list[str], load: dict[str, int]) -> bool:
        """``shard="frame"``: the whole frame to the least loaded free worker; False when none is free."""
        if f.slow and not set(members) - f.slow:  # only slow workers are left: back to them
            f.slow.clear()
        free = [w for w in members if load[w] < self.cfg.depth]
        if not free:
            return False
        free = [w for w in free if w not in f.slow] or ([] if f.slow else free)
        if free:
            n = len(members)
            w = min(free, key=lambda m: (load[m], (members.index(m) - fi) % n))
            load[w] += 1
            f.units, f.targets = [WHOLE], [w]
            self._send(fi, f, {w: [WHOLE]})
        return True

    def _dispatch_split(self, fi: int, f: _Frame, members: list[str], load: dict[str, int]) -> bool:
        """A new frame split over every worker (fingerprint) or one group (both); False when it must wait."""
        if self._names is None:
            return False  # the dictionary is not known yet
        groups = [members] if self.cfg.shard == "fingerprint" else worker_groups(members, self.cfg.group_size)
        free = [i for i, g in enumerate(groups) if all(load[w] < self.cfg.depth for w in g)]
        if not free:
            return False
        n = len(groups)
        g = groups[min(free, key=lambda i: (sum(load[w] for w in groups[i]), (i - fi) % n))]
        f.units, f.targets = [*self._names, IMAGE_UNIT], list(g)
        shares = split_units(f.units, g, fi)
        for w in shares:
            load[w] += 1
        self._send(fi, f, shares)
        return True

    def _send(self, fi: int, f: _Frame, shares: dict[str, list[str]]) -> None:
        now = time.monotonic()
        for w, units in shares.items():
            for u in units:
                f.owner[u], f.t_sent[u] = w, now
            f.t_first = f.t_first if f.sent else now
            f.sent += 1
            f.tried.add(w)
            self.session.put(
                self.keys.shard_assign_to(w),
                f.payload,
                attachment=f.header if units == [WHOLE] else encode_part(units, f.header),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

    # -- the ordered stage ----------------------------------------------------------------------------------
    def _emit_loop(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                head = min(self._frames) if self._frames else None
                f = self._frames.get(head) if head is not None else None
                if f is None or f.result is None:
                    self._cond.wait(0.2)
                    self._check_timeouts()
                    continue
                del self._frames[head]
            try:
                self._emit(f, f.result)
            except Exception as exc:  # the node never dies on one frame; reported as the processor does
                self.failed += 1
                log.exception("frame %s: merge failed", head)
                self.report(failure_report(exc, head, self.keys.rf, self.name))

    def _check_timeouts(self) -> None:
        """``frame_timeout_s``: a frame a live worker has not returned in time (hung, not dead: its token is
        still there) goes to another worker; the first result is merged, a later one counted as duplicate.
        ``frame_deadline_s``: a frame without a result that long after its first forward is given up."""
        self._check_deadlines()
        limit = self.cfg.frame_timeout_s
        if limit is None:
            return
        now = time.monotonic()
        moved = False
        for fi, f in self._frames.items():
            if f.result is not None:
                continue
            late = {w for u, w in f.out().items() if now - f.t_sent[u] > limit}
            for w in sorted(late):
                if not self._members - f.slow - {w}:  # only when another live worker can take it
                    continue
                log.warning("frame %s: no result from %s after %.1f s; sent to another worker", fi, w, limit)
                f.slow.add(w)
                for u, o in f.out().items():
                    if o == w:
                        f.owner[u] = None
                self.timed_out += 1
                moved = True
        if moved:
            self._dispatch()

    def _check_deadlines(self) -> None:
        """Give up the frames forwarded more than ``frame_deadline_s`` ago and still without a result (every
        worker that had them hung): one ErrorReport each, merged in frame order in place of the frame."""
        limit = self.cfg.frame_deadline_s
        if limit is None:
            return
        now = time.monotonic()
        for fi, f in self._frames.items():
            if f.result is None and f.sent and now - f.t_first > limit:
                tried = ", ".join(sorted(f.tried))
                log.warning("frame %s: no result from %s %.1f s after it was first sent; given up", fi, tried, limit)
                problem = (
                    f"no result from worker(s) {tried} within {limit:g} s of the frame's first forward "
                    f"(--frame-deadline {limit:g}); the frame is skipped"
                )
                rep = ErrorReport(frame_index=fi, key=self.keys.rf, field="deadline", problem=problem, node=self.name)
                f.result = ShardResult(fi, 0.0, self.name, "failed", [("errors", encode(rep))])
                f.payload, f.owner = None, {}

    def _emit(self, f: _Frame, res: ShardResult) -> None:
        """Publish one frame as the processor does: [truth report,] image, γ-maps, tracks, detections (or the
        frame's ErrorReport); the workers' payloads go out as they came."""
        gammas = [p for t, p in res.messages if t == "gamma"]
        if res.kind == "result":  # the dictionary the worker used, tracked or not
            self.dictionary = [str(decode_header(extract_header(p)).fields.get("fingerprint")) for p in gammas]
        # Counted before the acknowledgement (detections, or the frame's ErrorReport) goes out: whoever
        # paces on it sees the frame accounted for.
        if res.kind != "result":
            self.failed += 1
        else:
            self.frames_processed += 1
            for w in res.worker.split(","):  # a frame's parts: every worker that computed one
                self.per_worker[w] = self.per_worker.get(w, 0) + 1
            self._done_times.append(time.monotonic())
        for topic, payload in res.messages:
            if topic == "detections":
                states = self._track(res, gammas) if self.cfg.track else []
                tracks = Tracks(frame_index=res.frame_index, timestamp=res.timestamp, tracks=[track(t) for t in states])
                self.publish("tracks", tracks)
                self._latency.append(max(time.time() - f.t_pub, 0.0) * 1e3)
            self._pubs[topic].put(payload, attachment=extract_header(payload), timestamp=self.session.new_timestamp())

    def _track(self, res: ShardResult, gamma_payloads: list[bytes]) -> list[TrackState]:
        """The single node's tracker step (``Pipeline.process``) on the worker's maps and null models; a new
        tracker when the grid or the tracker's settings change (the pipeline's set-up does the same)."""
        maps: dict[str, np.ndarray] = {}
        for p in gamma_payloads:
            g = decode(p, expect=GammaMap)
            assert isinstance(g, GammaMap)
            maps[g.fingerprint] = g.gamma
        grid = res.grid
        if grid is None or not maps:
            return []
        ykey = None if grid.y is None else grid.y.tobytes()
        key = (grid.x.tobytes(), ykey, grid.z.tobytes(), sorted(res.tracker.items()))
        if self._tracker is None or key != self._tracker_key:
            self._tracker, self._tracker_key = make_tracker(grid, res.tracker), key
        motion = {}  # the detections' velocity estimates (Detections 1.2): velocity measurements
        for t, p in res.messages:
            if t == "detections":
                d = decode(p, expect=Detections)
                assert isinstance(d, Detections)
                motion = motion_of(d)
        return self._tracker.update(maps, res.timestamp, nulls=res.nulls, motion=motion)

    # -- status -------------------------------------------------------------------------------------------------
    def _publish_status(self) -> None:
        self.publish("status", status_message(self.name, self.stats(), self.dictionary))

    def _status_loop(self) -> None:
        while not self._stop.wait(self.cfg.status_period):
            try:
                self._publish_status()
            except Exception as exc:  # pragma: no cover
                log.error("status: %s", exc)
