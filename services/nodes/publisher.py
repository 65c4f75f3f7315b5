"""Publisher node (`fp publish`) (docs/design.md §2, §7).

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
nobody, then announces its SHM pool to them (``services.bus_warm.announce_pool``: mapped before the first
frame, not at it); after the last frame it waits for the same nodes' barrier replies (``services.bus.sync_with``)
before it closes, so a frame still in its shared memory is not lost; its own token is
``fp/<rig>/alive/publisher``. Ingest items are untrusted: they are decoded
and validated (shape, dtype, NaN, truncation, version, size) and refused with an ErrorReport on
``fp/<rig>/errors``; valid ones are forwarded as the same bytes.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from services.bus import sync_with, wait_for_matching, wait_for_token
from services.bus_warm import announce_pool
from services.messages import RFFrame
from services.nodes.base import Node
from services.sources import Item, Source
from services.topics import Keys, sync_of
from services.wire import DEFAULT_MAX_BYTES, WireError, decode, decode_header, error_report, extract_header

__all__ = ["PACES", "AckTracker", "Publisher"]

log = logging.getLogger("fp.publisher")
PACES = ("original", "rate", "ack", "none")


class AckTracker:
    """Counts the processor's per-frame acknowledgements (Detections / ErrorReport frame indices)."""

    def __init__(self, session: zenoh.Session, rig: str) -> None:
        k = Keys(rig)
        self._cond = threading.Condition()
        self._pending: Counter[int] = Counter()
        self._order: list[int] = []
        self.acked = 0
        self.timed_out = 0
        self._subs = [session.declare_subscriber(key, self._on_ack) for key in k.acks]

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


class Publisher(Node):
    """Publishes a source's frames on ``fp/<rig>/rf`` (see the module doc for pacing and validation)."""

    role = "publisher"

    def __init__(
        self,
        session: zenoh.Session,
        rig: str,
        source: Source,
        pace: str = "original",
        rate: float | None = None,
        speed: float = 1.0,
        window: int = 2,
        wait_for: Iterable[str] = ("processor",),
        wait_timeout: float = 10.0,
        ack_timeout: float = 30.0,
        max_frame_bytes: int = DEFAULT_MAX_BYTES,
        limit: int | None = None,
        name: str = "publisher",
        on_publish: Callable[[Item, float], None] | None = None,
    ) -> None:
        if pace not in PACES:
            raise ValueError(f"--pace: expected one of {', '.join(PACES)}, got {pace!r}")
        if pace == "rate" and not (rate and rate > 0):
            raise ValueError(f"--rate: expected a positive frame rate in Hz, got {rate}")
        if window < 1:
            raise ValueError(f"--window: expected >= 1, got {window}")
        if speed <= 0:
            raise ValueError(f"--speed: expected > 0, got {speed}")
        super().__init__(session, rig, name)
        self.rig, self.source = rig, source
        self.pace, self.rate, self.speed, self.window = pace, rate, speed, window
        self.wait_for = tuple(wait_for)
        self.wait_timeout, self.ack_timeout = wait_timeout, ack_timeout
        self.max_frame_bytes, self.limit = max_frame_bytes, limit
        self.on_publish = on_publish
        self.published = 0
        self.rejected = 0
        self.bytes = 0
        self.publish_times: dict[int, float] = {}
        self.synced = 0  # awaited nodes that answered the closing barrier
        self._run_stop = threading.Event()
        self._acks: AckTracker | None = None

    def _token_key(self, node: str) -> str:
        if node == "processor":
            return self.keys.alive_any("processor")
        if node == "recorder":
            return Keys("*").alive("recorder")
        raise ValueError(f"--wait-for: expected processor and/or recorder, got {node!r}")

    def _sync_key(self, node: str) -> str:
        return sync_of(self._token_key(node))  # the barrier of the nodes whose tokens it waited for

    def _validate(self, item: Item) -> Item | None:
        """Decode an untrusted payload; refuse it with an ErrorReport, or return it with a fresh header."""
        try:
            msg = decode(item.payload, max_bytes=self.max_frame_bytes, expect=RFFrame)
        except WireError as exc:
            self.rejected += 1
            self.report(error_report(exc, self.keys.ingest, item.payload, node=self.name))
            return None
        return Item(item.payload, extract_header(item.payload), msg.frame_index, float(msg.timestamp))

    # -- lifecycle (Node) ---------------------------------------------------------------------------------
    def _open(self) -> None:
        bind = getattr(self.source, "bind", None)
        if bind is not None:  # before the token: a peer that sees the token also has the ingest subscription
            bind(self.session, self._run_stop)
        self.declare_publishers("rf", "errors")
        self._acks = AckTracker(self.session, self.rig) if self.pace == "ack" else None

    def _shutdown(self) -> None:
        stop_source = getattr(self.source, "stop", None)
        if stop_source is not None:
            stop_source()
        if self._acks is not None:
            self._acks.close()

    def run(self, stop: threading.Event | None = None) -> dict[str, Any]:
        """Publish until the source ends (or ``stop``); returns counts and timing."""
        stop = self._run_stop = stop or threading.Event()
        s = self.session
        self.start()
        rf_pub, acks = self._pubs["rf"], self._acks
        t_start = time.time()
        t_first: float | None = None
        seen: list[str] = []
        try:
            for node in self.wait_for:
                if wait_for_token(s, self._token_key(node), self.wait_timeout):
                    seen.append(node)
                else:
                    if self.pace == "ack" and node == "processor":
                        raise TimeoutError(
                            f"no processor on fp/{self.rig} after {self.wait_timeout:.0f} s (--pace ack needs one)"
                        )
                    log.warning(
                        "no %s seen on fp/%s after %.0f s; publishing anyway", node, self.rig, self.wait_timeout
                    )
            if self.wait_for:
                if wait_for_matching(rf_pub, self.wait_timeout):
                    announce_pool(s)  # the nodes waited for map this session's SHM pool now, not at the first frame
                else:
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
            for node in seen if self.published else ():  # the last frames may still be in shared memory
                if sync_with(s, self._sync_key(node), self.wait_timeout):  # (services.bus.sync_with)
                    self.synced += 1
                else:
                    log.warning("the %s on fp/%s did not answer the closing barrier", node, self.rig)
        finally:
            self.close()
        t_end = time.time()
        span = t_end - (t_first or t_start)
        return {
            "published": self.published,
            "rejected": self.rejected,
            "bytes": self.bytes,
            "acked": None if acks is None else acks.acked,
            "synced": self.synced,
            "ack_timeouts": None if acks is None else acks.timed_out,
            "wall_s": t_end - t_start,
            "frame_rate_hz": self.published / span if span > 0 else 0.0,
            "pace": self.pace,
        }
