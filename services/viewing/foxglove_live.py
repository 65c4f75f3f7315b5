"""`fp view --live --foxglove`: the live bus served to the Foxglove app over a WebSocket on 127.0.0.1 only
(foxglove-sdk's server; docs/wire.md "MCAP recordings").

The same channels as a recording: Detections, Tracks, Status and ErrorReport as JSON with their JSON Schema,
and the display views of ``services.viewing.foxglove_view`` (γ and confocal sections as ``foxglove.Grid`` in
metres; detections, tracks, ground truth and probe as ``foxglove.SceneUpdate``). RF frames, γ-volumes and
confocal volumes are decoded for those views but not forwarded (Foxglove cannot read the FPWIRE01 payload).
Open the app's "Foxglove WebSocket" connection at ``ws://127.0.0.1:<port>``; from another machine, forward
the port over SSH.
"""

from __future__ import annotations

import math
import queue
import time
from typing import Any

from services.messages import MESSAGE_TYPES
from services.recording import JSON_SCHEMAS
from services.schemas_gen import render
from services.topics import keys
from services.viewing.foxglove_view import FoxgloveDisplay
from services.viewing.server import LOOPBACK, _check_port
from services.wire import WireError, decode, extract_header

__all__ = ["DEFAULT_FOXGLOVE_PORT", "serve_foxglove"]

DEFAULT_FOXGLOVE_PORT = 8765
_TOPICS = ("rf", "gamma", "image", "detections", "tracks", "status", "errors")


class _Channels:
    """foxglove-sdk channels of one server context, created on first use."""

    def __init__(self, context: Any) -> None:
        self.context = context
        self.channels: dict[str, Any] = {}

    def json(self, topic: str, schema_name: str, data: bytes, t_ns: int) -> None:
        import foxglove

        ch = self.channels.get(topic)
        if ch is None:
            schema = foxglove.Schema(
                name=schema_name, encoding="jsonschema", data=render(MESSAGE_TYPES[schema_name]).encode()
            )
            ch = self.channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding="json", context=self.context
            )
        ch.log(data, log_time=t_ns)

    def display(self, topic: str, fmsg: Any, t_ns: int) -> None:
        import foxglove

        ch = self.channels.get(topic)
        if ch is None:
            s = type(fmsg).get_schema()
            schema = foxglove.Schema(name=s.name, encoding=s.encoding, data=bytes(s.data))
            ch = self.channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding=s.encoding, context=self.context
            )
        ch.log(fmsg.encode(), log_time=t_ns)


def serve_foxglove(
    bus: Any,
    rig: str,
    *,
    port: int = DEFAULT_FOXGLOVE_PORT,
    duration: float | None = None,
    stop: Any = None,
    stats: dict[str, Any] | None = None,
    on_ready: Any = None,
) -> dict[str, Any]:
    """Serve ``fp/<rig>/…`` to Foxglove on ``ws://127.0.0.1:port`` until ``duration`` s pass or ``stop`` is set
    (default: SIGINT/SIGTERM). ``on_ready(url)`` is called once the server listens; ``stats`` is updated live
    (messages, undecodable, dropped, logged). Announces itself with ``fp/<rig>/alive/viewer``."""
    import foxglove

    from services.bus import open_session, sample_bytes, stop_on_signals

    if port != 0:
        _check_port("--foxglove-port", port)
    stats = stats if stats is not None else {}
    stats.update(messages=0, undecodable=0, dropped=0, logged=0)
    stop = stop if stop is not None else stop_on_signals()
    context = foxglove.Context()
    server = foxglove.start_server(name=f"fingerprint {rig}", host=LOOPBACK, port=port, context=context)
    url = f"ws://{LOOPBACK}:{server.port}"
    channels = _Channels(context)
    display = FoxgloveDisplay()
    inbox: queue.Queue[tuple[str, bytes, int]] = queue.Queue(maxsize=256)
    k = keys(rig)

    def on_sample(sample: Any) -> None:
        try:
            inbox.put_nowait((str(sample.key_expr), sample_bytes(sample), time.time_ns()))
        except queue.Full:
            stats["dropped"] += 1

    def feed(key: str, payload: bytes, t_ns: int) -> None:
        try:
            msg = decode(payload)
        except WireError:
            stats["undecodable"] += 1
            return
        stats["messages"] += 1
        if msg.schema_name in JSON_SCHEMAS:
            channels.json(key, msg.schema_name, extract_header(payload), t_ns)
            stats["logged"] += 1
        for topic, fmsg in display.feed(key, msg, t_ns):
            channels.display(topic, fmsg, t_ns)
            stats["logged"] += 1

    try:
        with open_session(bus) as session:
            subs = [session.declare_subscriber(k.topic(t), on_sample) for t in _TOPICS]
            token = session.liveliness().declare_token(k.alive("viewer"))
            if on_ready is not None:
                on_ready(url)
            t_end = time.monotonic() + duration if duration else math.inf
            try:
                while not stop.is_set() and time.monotonic() < t_end:
                    try:
                        feed(*inbox.get(timeout=0.1))
                    except queue.Empty:
                        continue
            finally:
                for sub in subs:
                    sub.undeclare()
                token.undeclare()
        while not inbox.empty():
            feed(*inbox.get_nowait())
        t = time.time_ns()
        for topic, fmsg in display.finish(t):
            channels.display(topic, fmsg, t)
    finally:
        server.stop()
    return {"url": url, **stats, "topics": sorted(channels.channels)}
