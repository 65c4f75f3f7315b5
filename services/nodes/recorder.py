"""Recorder node (`fp record`) (docs/design.md §2, §7; docs/wire.md "MCAP recordings").

Every message on ``fp/**`` (or one rig's ``fp/<rig>/**``; ``include`` / ``exclude`` key expressions narrow
it) goes to MCAP:

* one channel per key expression, header schema and encoding: topic = the key (``fp/bench/rf``); messages
  without arrays (Detections, Tracks, Status, ErrorReport) as plain JSON (encoding ``json``: their header,
  which is the whole message) with their JSON Schema, so that any MCAP tool reads them; RF frames, γ-maps
  and confocal images as the FPWIRE01 payload (encoding ``fpwire``), schema = the JSON Schema of the header;
* RF is kept as it came: int16 RF with its ``rf_scale`` (RFFrame 1.2) from an integer source, as scanners
  deliver it (half the bytes of float32, and it compresses: 3.1 MB a quick demo frame with zstd vs 8.7 MB);
* a malformed message is still recorded raw under its key: on a channel of its header's schema when the
  header is readable and supported, else on a channel whose schema is ``"unknown"``; channel metadata keeps
  the schema name/version the header claimed;
* display channels ``fp/<rig>/display/…`` in Foxglove's well-known schemas (``services.viewing.foxglove_view``:
  γ and confocal sections as ``foxglove.Grid`` in metres, detections, tracks, truth and probe as
  ``foxglove.SceneUpdate``), unless ``display=False``;
* log_time = receive time, publish_time = the sender's zenoh timestamp (both ns since the epoch);
  sequence = per-channel counter;
* RF, γ and confocal payloads byte-shuffled in place under compression (``shuffle``, default; encoding
  ``fpwire-shuffled``, ``services.recording.shuffle_payload``): 12–17 % smaller with zstd; a payload is
  decoded only for the display channels that use it (never with ``display=False``);
* zstd chunk compression (level 1, ``services.recording.use_zstd_level``) by default (``none`` and ``lz4``
  too); flushed every ``flush_interval`` (0.5 s):
  ``Writer.flush()`` closes the open chunk, so a killed recorder loses at most the last interval
  (``services.recording.recover`` salvages the rest);
* rotation by size (``max_bytes``) and/or age (``max_seconds``): segments ``<stem>-000.mcap``, …

The zenoh callback only queues, within a byte budget (``max_queue_bytes``, 512 MiB: a slow disk blocks
the bus instead of growing memory, docs/design.md §7 "replay blocks"); a writer thread converts, writes,
flushes and rotates.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any

import zenoh
from mcap.writer import Writer

from services.messages import MESSAGE_TYPES, Message
from services.nodes.base import Node
from services.recording import (
    COMPRESSION,
    JSON_ENCODING,
    JSON_SCHEMAS,
    MESSAGE_ENCODING,
    SHUFFLED_ENCODING,
    UNKNOWN_SCHEMA,
    shuffle_payload,
    use_zstd_level,
)
from services.schemas_gen import render
from services.topics import ALL_RIGS
from services.wire import WireError, decode, decode_header, extract_header

__all__ = ["Recorder"]

log = logging.getLogger("fp.recorder")
#: schemas the display channels are made from (the others are never decoded for them).
_DISPLAYED = frozenset({"RFFrame", "GammaMap", "ConfocalImage", "Detections", "Tracks"})


@dataclass
class _Received:
    key: str
    payload: bytes
    attachment: bytes | None
    log_ns: int
    pub_ns: int


def _schema_of(payload: bytes, attachment: bytes | None) -> tuple[str, dict[str, str]]:
    """(schema label, channel metadata): the header's schema if readable and supported, else "unknown"."""
    for source in (payload, attachment):
        if source is None:
            continue
        try:
            hdr = decode_header(extract_header(source) if source is payload else source, strict=False)
        except WireError:
            continue
        meta = {"schema_name": hdr.schema_name, "schema_version": hdr.schema_version}
        cls = MESSAGE_TYPES.get(hdr.schema_name)
        if cls is not None and int(hdr.schema_version.split(".")[0]) == cls.version()[0]:
            return hdr.schema_name, meta
        return "unknown", meta
    return "unknown", {}


class _Segment:
    """One MCAP file being written, with its own schema/channel registrations."""

    def __init__(self, path: Path, compression: str, chunk_size: int, key_expr: str, shuffle: bool = False) -> None:
        self.path = path
        self.shuffle = shuffle
        self.file: IO[bytes] = open(path, "wb")  # closed in finish()
        self.writer = Writer(self.file, chunk_size=chunk_size, compression=COMPRESSION[compression])
        self.writer.start(profile="", library="fingerprint services.nodes.recorder")
        self.writer.add_metadata(
            "fingerprint",
            {
                "wire": "FPWIRE01",
                "message_encoding": SHUFFLED_ENCODING if shuffle else MESSAGE_ENCODING,
                "key_expr": key_expr,
                "started": datetime.now(timezone.utc).isoformat(),
            },
        )
        self.schemas: dict[str, int] = {}
        self.channels: dict[tuple[str, str, str], int] = {}
        self.sequence: Counter[int] = Counter()
        self.opened = time.monotonic()
        self.messages = 0
        self.unflushed = 0

    def channel(self, key: str, label: str, meta: dict[str, str], encoding: str = MESSAGE_ENCODING) -> int:
        cid = self.channels.get((key, label, encoding))
        if cid is None:
            sid = self.schemas.get(label)
            if sid is None:
                data = render(MESSAGE_TYPES[label]).encode() if label in MESSAGE_TYPES else UNKNOWN_SCHEMA
                sid = self.writer.register_schema(label, "jsonschema", data)
                self.schemas[label] = sid
            cid = self.writer.register_channel(key, encoding, sid, {"key": key, **meta})
            self.channels[(key, label, encoding)] = cid
        return cid

    def display_channel(self, topic: str, fmsg: Any) -> int:
        """The channel of a Foxglove display message (schema and encoding from foxglove-sdk)."""
        schema = type(fmsg).get_schema()
        cid = self.channels.get((topic, schema.name, schema.encoding))
        if cid is None:
            sid = self.schemas.get(schema.name)
            if sid is None:
                sid = self.writer.register_schema(schema.name, schema.encoding, bytes(schema.data))
                self.schemas[schema.name] = sid
            cid = self.writer.register_channel(topic, schema.encoding, sid, {"display": "foxglove"})
            self.channels[(topic, schema.name, schema.encoding)] = cid
        return cid

    def add(self, cid: int, log_ns: int, data: bytes, pub_ns: int) -> None:
        self.sequence[cid] += 1
        self.writer.add_message(cid, log_ns, data, pub_ns, self.sequence[cid])
        self.messages += 1
        self.unflushed += 1

    def write(self, rec: _Received, decoded: frozenset[str] = frozenset()) -> Message | None:
        """Record one bus message (see the module doc). Returns it decoded when its schema is in ``decoded``
        (what the display channels use) and it decodes; messages recorded as JSON are always decoded (only a
        valid one is), the others never needlessly (their payload is recorded as it came)."""
        label, meta = _schema_of(rec.payload, rec.attachment)
        msg: Message | None = None
        if label != "unknown" and (label in JSON_SCHEMAS or label in decoded):
            try:
                msg = decode(rec.payload)
            except WireError:
                msg = None
        data, encoding = rec.payload, MESSAGE_ENCODING
        if msg is not None and label in JSON_SCHEMAS:
            data, encoding = extract_header(rec.payload), JSON_ENCODING
        elif self.shuffle:
            data, encoding = shuffle_payload(rec.payload), SHUFFLED_ENCODING
        self.add(self.channel(rec.key, label, meta, encoding), rec.log_ns, data, rec.pub_ns)
        return msg

    def write_display(self, items: list[tuple[str, Any]], log_ns: int) -> None:
        for topic, fmsg in items:
            self.add(self.display_channel(topic, fmsg), log_ns, fmsg.encode(), log_ns)

    def flush(self) -> None:
        if self.unflushed:
            self.writer.flush()
            self.unflushed = 0

    def size(self) -> int:
        return self.file.tell()

    def finish(self) -> None:
        self.writer.finish()
        self.file.close()


def _key_exprs(option: str, values: list[str] | None) -> list[zenoh.KeyExpr]:
    out = []
    for v in values or []:
        try:
            out.append(zenoh.KeyExpr(v))
        except Exception as exc:  # zenoh.ZError: not a key expression
            why = str(exc).split(" at /")[0]  # zenoh appends its Rust source location
            raise ValueError(
                f"{option}: expected a zenoh key expression such as 'fp/*/rf', got {v!r} ({why})"
            ) from None
    return out


class Recorder(Node):
    """Records ``key_expr`` (default ``fp/**``) to ``path`` on an open session: ``with Recorder(s, path): ...``.
    Its liveliness token is ``fp/<rig>/alive/recorder`` (``fp/_any/alive/recorder`` when it records every rig)."""

    role = "recorder"

    def __init__(
        self,
        session: zenoh.Session,
        path: str | Path,
        key_expr: str = ALL_RIGS,
        rig: str | None = None,
        compression: str = "zstd",
        flush_interval: float = 0.5,
        max_bytes: int | None = None,
        max_seconds: float | None = None,
        chunk_size: int = 4 << 20,
        max_queue_bytes: int = 512 << 20,
        include: list[str] | None = None,
        exclude: list[str] | None = None,
        display: bool = True,
        shuffle: bool = True,
    ) -> None:
        if compression not in COMPRESSION:
            raise ValueError(f"--compression: expected one of {', '.join(COMPRESSION)}, got {compression!r}")
        use_zstd_level()
        if flush_interval <= 0:
            raise ValueError(f"--flush-interval: expected > 0 s, got {flush_interval}")
        self.include = _key_exprs("--include", include)
        self.exclude = _key_exprs("--exclude", exclude)
        super().__init__(session, rig or "_any")
        self.path = Path(path)
        self.key_expr = self.keys.all if rig else key_expr
        self.rig = rig
        self.compression = compression
        self.shuffle = shuffle and compression != "none"  # shuffled bytes only pay under compression
        self.flush_interval = flush_interval
        self.max_bytes = max_bytes
        self.max_seconds = max_seconds
        self.chunk_size = chunk_size
        self._q: queue.Queue[_Received | None] = queue.Queue()
        self._queued = 0  # bytes waiting for the writer
        self._budget = threading.Condition()
        self.max_queue_bytes = max_queue_bytes
        self._stop = threading.Event()
        self.counts: Counter[str] = Counter()
        self.received = 0
        self.files: list[Path] = []
        self._segment: _Segment | None = None
        self._thread: threading.Thread | None = None
        self.error: str | None = None
        self.display: Any = None
        if display:
            from services.viewing.foxglove_view import FoxgloveDisplay

            self.display = FoxgloveDisplay()
        self.skipped = 0  # messages left out by include/exclude

    def wanted(self, key: str) -> bool:
        """Whether ``key`` passes ``include`` (any, when given) and no ``exclude``."""
        k = zenoh.KeyExpr(key)
        if self.include and not any(e.intersects(k) for e in self.include):
            return False
        return not any(e.intersects(k) for e in self.exclude)

    @property
    def rotating(self) -> bool:
        return self.max_bytes is not None or self.max_seconds is not None

    def _next_path(self) -> Path:
        if not self.rotating:
            return self.path
        return self.path.with_name(f"{self.path.stem}-{len(self.files):03d}{self.path.suffix or '.mcap'}")

    def _open_segment(self) -> None:
        path = self._next_path()
        path.parent.mkdir(parents=True, exist_ok=True)
        self._segment = _Segment(path, self.compression, self.chunk_size, self.key_expr, self.shuffle)
        self.files.append(path)

    def _open(self) -> None:
        self._open_segment()
        self._thread = threading.Thread(target=self._write_loop, name="recorder-writer", daemon=True)
        self._thread.start()
        self._sub = self.session.declare_subscriber(self.key_expr, self._on_sample)

    def _shutdown(self) -> None:
        """Undeclare the subscriber, write what is queued, finish the file (summary and index)."""
        self._sub.undeclare()
        self._q.put(None)
        if self._thread is not None:
            self._thread.join(timeout=60)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self._stop.is_set():  # the writer has failed (see ``error``): nothing drains the queue any more
            return
        if (self.include or self.exclude) and not self.wanted(str(sample.key_expr)):
            self.skipped += 1
            return
        log_ns = time.time_ns()
        ts = sample.timestamp
        pub_ns = log_ns
        if ts is not None:
            try:
                pub_ns = int(ts.get_time().timestamp() * 1e9)
            except (ValueError, OverflowError, OSError):
                pass
        att = sample.attachment
        rec = _Received(
            str(sample.key_expr), sample.payload.to_bytes(), att.to_bytes() if att is not None else None, log_ns, pub_ns
        )
        n = len(rec.payload)
        with self._budget:  # an oversized message still goes alone
            while self._queued and self._queued + n > self.max_queue_bytes and not self._stop.is_set():
                self._budget.wait(0.5)
            self._queued += n
        self._q.put(rec)

    def _write_loop(self) -> None:
        last_flush = time.monotonic()
        try:
            while True:
                wait = max(0.0, self.flush_interval - (time.monotonic() - last_flush))
                idle = False
                try:
                    rec = self._q.get(timeout=wait)
                except queue.Empty:
                    rec, idle = None, True
                seg = self._segment
                assert seg is not None
                if rec is None and not idle:
                    break
                if rec is not None:
                    msg = seg.write(rec, _DISPLAYED if self.display is not None else frozenset())
                    if msg is not None and self.display is not None:
                        seg.write_display(self.display.feed(rec.key, msg, rec.log_ns), rec.log_ns)
                    self.counts[rec.key] += 1
                    self.received += 1
                    with self._budget:
                        self._queued -= len(rec.payload)
                        self._budget.notify_all()
                now = time.monotonic()
                if now - last_flush >= self.flush_interval:
                    seg.flush()
                    last_flush = now
                    if (self.max_bytes is not None and seg.size() >= self.max_bytes) or (
                        self.max_seconds is not None and now - seg.opened >= self.max_seconds
                    ):
                        if seg.messages:
                            seg.finish()
                            self._open_segment()
        except Exception as exc:  # disk full, …: stop recording loudly, keep the process alive
            self.error = f"{type(exc).__name__}: {exc}"
            log.exception("recorder stopped")
            self._stop.set()
        finally:
            if self._segment is not None:
                try:
                    if self.display is not None and self.error is None:
                        now = time.time_ns()
                        self._segment.write_display(self.display.finish(now), now)
                    self._segment.finish()
                except Exception:
                    log.exception("could not finish %s", self._segment.path)
                self._segment = None

    def summary(self) -> dict[str, Any]:
        return {
            "files": [str(p) for p in self.files],
            "messages": self.received,
            "by_key": dict(self.counts),
            "skipped": self.skipped,
            "error": self.error,
        }
