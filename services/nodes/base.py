"""What every streaming node shares (docs/design.md §2, §7): start/close on an open zenoh session, use as
a context manager, its liveliness token ``fp/<rig>/alive/<role>[/<name>]`` (declared last on start, so
a peer that sees it also sees the node's subscriptions and queryables), its barrier queryable
``fp/<rig>/@sync/<role>[/<name>]`` (``services.bus.sync_with``), its publishers (congestion
control BLOCK: nothing is discarded at the sender) and error reports on ``fp/<rig>/errors``.

A subclass implements ``_open`` (declare inputs, start threads) and ``_shutdown`` (undeclare inputs,
drain, stop threads); ``close`` then undeclares the token and the publishers.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, ClassVar

import zenoh

from services.bus import put_message, sync_with
from services.messages import ErrorReport, Latency, Message, Status
from services.topics import Keys, sync_of

__all__ = ["Node", "start_warmed_thread"]


def latency_summary(latencies_ms: Any) -> dict[str, float | None]:
    """Median and p95 (ms) of a node's recent publish → result latencies (None before any frame)."""
    import numpy as np

    lat = np.asarray(latencies_ms, float)
    return {
        "median": float(np.median(lat)) if lat.size else None,
        "p95": float(np.percentile(lat, 95)) if lat.size else None,
    }


def frame_rate(done_times: Any) -> float:
    """Frames/s over a node's recent completion times (monotonic s); 0 before two frames."""
    d = list(done_times)
    return (len(d) - 1) / (d[-1] - d[0]) if len(d) > 1 and d[-1] > d[0] else 0.0


def status_message(node: str, st: dict[str, Any], dictionary: list[str]) -> Status:
    """The periodic Status of a frame-processing node (``fp process``, ``fp merge``) from its ``stats()``."""
    lat = st["latency_ms"]
    return Status(
        node=node,
        frames_processed=st["frames_processed"],
        frame_rate_hz=st["frame_rate_hz"],
        latency_ms=Latency(median=lat["median"], p95=lat["p95"]),
        dropped=st["dropped"],
        rejected=st["rejected"],
        dictionary=dictionary,
    )


def start_warmed_thread(warm: Callable[[], None], work: Callable[[], None], name: str) -> threading.Thread:
    """Start the daemon thread that runs ``warm()`` (a pipeline's start-up set-up) then ``work()`` (the frame
    loop); return it once ``warm`` is done, re-raising its error (the node does not start). The set-up runs on
    the frame thread so that the frame-sized buffers it frees stay in that thread's malloc arena for the first
    frame to reuse (set up on another thread, the first frame page-faulted through them: 66 ms against 30 ms
    on quick 3-D frames; issue 15, item 4)."""
    warmed = threading.Event()
    error: list[BaseException] = []

    def run() -> None:
        try:
            warm()
        except BaseException as exc:  # re-raised below, in the caller
            error.append(exc)
            return
        finally:
            warmed.set()
        work()

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    warmed.wait()
    if error:
        raise error[0]
    return thread


class Node:
    """Base of the publisher, processor and recorder nodes."""

    role: ClassVar[str] = "node"

    def __init__(self, session: zenoh.Session, rig: str, name: str | None = None) -> None:
        self.session = session
        self.keys = Keys(rig)
        self.name = name or self.role
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._token: Any = None
        self._sync: Any = None
        self._started = False
        self.log = logging.getLogger(f"fp.{self.role}")

    # -- lifecycle ---------------------------------------------------------------------------------
    def _open(self) -> None:
        """Declare publishers, subscriptions and queryables; start threads (before the token)."""

    def _shutdown(self) -> None:
        """Undeclare inputs first (no new work), then finish the work in hand (before the token goes)."""

    @property
    def token_key(self) -> str:
        return self.keys.alive(self.role, self.name)

    @property
    def sync_key(self) -> str:
        """The node's barrier queryable (``services.bus.sync_with``), named like its token."""
        return sync_of(self.token_key)

    def _on_sync(self, query: zenoh.Query) -> None:
        query.reply(self.sync_key, self.name.encode())

    def sync_recorders(self, timeout: float = 2.0) -> int:
        """Before a node that publishes outputs closes: wait until every recorder has taken them (the
        recorders' barrier, ``services.bus.sync_with``); returns how many answered (0 at once if none)."""
        return sync_with(self.session, Keys("*").sync("recorder"), timeout)

    def start(self) -> Node:
        if self._started:
            return self
        self._open()
        self._sync = self.session.declare_queryable(self.sync_key, self._on_sync)
        self._token = self.session.liveliness().declare_token(self.token_key)
        self._started = True
        return self

    def close(self) -> None:
        if not self._started:
            return
        self._started = False
        try:
            self._shutdown()
        finally:
            self._token.undeclare()
            self._sync.undeclare()
            for p in self._pubs.values():
                p.undeclare()
            self._pubs = {}

    def __enter__(self) -> Any:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- output -----------------------------------------------------------------------------------------
    def declare_publishers(self, *topics: str) -> None:
        """One BLOCK publisher per topic of ``services.topics.TABLE``."""
        block = zenoh.CongestionControl.BLOCK
        for topic in topics:
            self._pubs[topic] = self.session.declare_publisher(self.keys.topic(topic), congestion_control=block)

    def publish(self, topic: str, msg: Message) -> int:
        """Encode and publish ``msg`` (header as attachment, session timestamp); returns the payload bytes."""
        return put_message(self._pubs[topic], self.session, msg)

    def report(self, rep: ErrorReport) -> None:
        """Publish an ErrorReport on ``fp/<rig>/errors`` (logged, never raised)."""
        self.log.warning(
            "%s refused %s (frame %s): %s: %s", self.name, rep.key, rep.frame_index, rep.field, rep.problem
        )
        try:
            self.publish("errors", rep)
        except Exception as exc:  # pragma: no cover - only when the session is going down
            self.log.error("could not publish an error report: %s", exc)
