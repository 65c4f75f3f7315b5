"""MCAP recordings of the bus: reading them back, copying them, salvaging broken ones (docs/design.md §7,
stack notes). The recorder node that writes them is ``services.nodes.recorder``.

Conventions: one channel per key expression and header schema; message encoding ``"fpwire"``
(:data:`MESSAGE_ENCODING`: the FPWIRE01 payload exactly as it travelled); schema = the JSON Schema of
the message header, or :data:`UNKNOWN_SCHEMA` for a message whose header is unreadable or of an
unsupported schema/version.

Reading is non-seeking and tolerant (:func:`iter_raw`): a file whose writer was killed yields every
message of its complete chunks; :func:`recover` copies those into a complete file.
"""

from __future__ import annotations

import json
import logging
import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader
from mcap.records import Channel, Schema
from mcap.records import Message as McapMessage
from mcap.writer import CompressionType, Writer

from services.messages import Message
from services.wire import WireError, decode

__all__ = [
    "COMPRESSION",
    "MESSAGE_ENCODING",
    "UNKNOWN_SCHEMA",
    "copy_messages",
    "iter_messages",
    "iter_raw",
    "iter_recording",
    "recover",
]

log = logging.getLogger("fp.recording")

MESSAGE_ENCODING = "fpwire"
UNKNOWN_SCHEMA = json.dumps(
    {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "unknown",
        "description": "Header unreadable or of an unsupported schema/version; the payload is recorded raw.",
    },
    indent=2,
).encode()
#: chunk compression of the recorder (``--compression``).
COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}

RawMessage = tuple[Schema | None, Channel, McapMessage]


def iter_raw(path: str | Path, report: dict[str, Any] | None = None) -> Iterator[RawMessage]:
    """Every message of an MCAP file in file order, with a non-seeking reader (log_time_order=False):
    a file without summary (killed writer) gives all its complete chunks; the damage, if any, is noted
    in ``report["error"]`` instead of raising."""
    with open(path, "rb") as f:
        reader = NonSeekingReader(f, record_size_limit=None)
        try:
            yield from reader.iter_messages(log_time_order=False)
        except (McapError, struct.error, ValueError, EOFError) as exc:
            if report is None:
                return
            report["error"] = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def iter_recording(path: str | Path) -> Iterator[tuple[str, bytes, int, int]]:
    """``(key, payload, log_time_ns, publish_time_ns)`` of every message of an MCAP file in file order.

    Non-seeking and tolerant: a file whose writer was killed yields every message of its complete
    chunks and stops at the damage (stack notes).
    """
    for _schema, channel, msg in iter_raw(path):
        yield channel.topic, bytes(msg.data), int(msg.log_time), int(msg.publish_time)


def iter_messages(path: str | Path, report: dict[str, Any] | None = None) -> Iterator[tuple[str, Message]]:
    """(key, decoded message) for every fpwire message of a recording, in file order; messages that do
    not decode are counted in ``report["undecodable"]`` and skipped."""
    bad = 0
    for _schema, channel, msg in iter_raw(path, report):
        if channel.message_encoding != MESSAGE_ENCODING:
            continue
        try:
            yield channel.topic, decode(msg.data)
        except WireError as exc:
            bad += 1
            log.warning("%s: undecodable message on %s: %s", path, channel.topic, exc)
    if report is not None:
        report["undecodable"] = bad


def copy_messages(writer: Writer, messages: Iterable[RawMessage]) -> Counter[str]:
    """Write ``messages`` (from :func:`iter_raw`) to a started ``writer``, registering their schemas and
    channels once, times and sequence numbers kept; returns the count per key."""
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    by_key: Counter[str] = Counter()
    for schema, channel, msg in messages:
        if channel.id not in channels:
            sid = 0
            if schema is not None:
                if schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                sid = schemas[schema.id]
            channels[channel.id] = writer.register_channel(
                channel.topic, channel.message_encoding, sid, dict(channel.metadata)
            )
        writer.add_message(channels[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        by_key[channel.topic] += 1
    return by_key


def recover(broken: str | Path, fixed: str | Path | None = None) -> dict[str, Any]:
    """Copy every readable message of ``broken`` into a complete MCAP file (default
    ``<stem>.recovered.mcap``) and report how many were kept, per key."""
    broken = Path(broken)
    out = Path(fixed) if fixed else broken.with_name(f"{broken.stem}.recovered.mcap")
    if out.resolve() == broken.resolve():
        raise ValueError("recover: the output must differ from the broken file")
    if not broken.is_file():
        raise FileNotFoundError(f"{broken}: no such file")
    report: dict[str, Any] = {"input": str(broken), "output": str(out), "error": None}
    span: dict[str, int] = {}

    def timed(messages: Iterable[RawMessage]) -> Iterator[RawMessage]:
        for m in messages:
            t = m[2].log_time
            span["first"], span["last"] = min(span.get("first", t), t), max(span.get("last", t), t)
            yield m

    with open(out, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="", library="fingerprint services.recording (recovered)")
        by_key = copy_messages(w, timed(iter_raw(broken, report)))
        w.finish()
    report.update(
        messages=sum(by_key.values()),
        by_key=dict(by_key),
        complete=report["error"] is None,
        first_log_time_ns=span.get("first"),
        last_log_time_ns=span.get("last"),
    )
    return report
