"""MCAP recordings of the bus: reading them back, copying them, salvaging broken ones (docs/design.md §7,
docs/wire.md "MCAP recordings"). The recorder node that writes them is ``services.nodes.recorder``.

Channels, one per key expression, schema and encoding:

* messages without arrays (Detections, Tracks, Status, ErrorReport: :data:`JSON_SCHEMAS`) as plain JSON
  (message encoding ``"json"``, :data:`JSON_ENCODING`): the message's JSON header exactly as it travelled,
  with its JSON Schema (``jsonschema``) — any MCAP tool shows them;
* RF frames, γ-maps and confocal images as the compact FPWIRE01 payload (``"fpwire"``,
  :data:`MESSAGE_ENCODING`), or, under chunk compression by default, that payload with its buffers
  byte-shuffled in place (``"fpwire-shuffled"``, :data:`SHUFFLED_ENCODING`, :func:`shuffle_payload`;
  :func:`wire_payload` restores it), with the JSON Schema of their header; a message whose header is
  unreadable or of an unsupported schema/version is kept raw on a channel whose schema is
  :data:`UNKNOWN_SCHEMA`;
* display channels (``fp/<rig>/display/…``, ``protobuf``, Foxglove's well-known schemas; written by the
  recorder from ``services.viewing.foxglove``) — derived views, skipped by :func:`iter_messages`.

Reading is non-seeking and tolerant (:func:`iter_raw`): every chunk's CRC is checked (a corrupted chunk is
skipped and counted), a file whose writer was killed yields every message of its complete chunks, and a
file that is not an MCAP raises :class:`RecordingError`. :func:`recover` copies what is readable into a
complete file and reports what it could not read.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import mcap.writer
import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, get_chunk_data_stream
from mcap.writer import CompressionType, Writer

from services.messages import Message
from services.wire import ALIGN, MAGIC, PREFIX_SIZE, WireError, decode, decode_header, extract_header

__all__ = [
    "COMPRESSION",
    "JSON_ENCODING",
    "JSON_SCHEMAS",
    "MESSAGE_ENCODING",
    "BUS_ENCODINGS",
    "RecordingError",
    "SHUFFLED_ENCODING",
    "UNKNOWN_SCHEMA",
    "ZSTD_LEVEL",
    "copy_messages",
    "iter_messages",
    "iter_raw",
    "iter_recording",
    "json_to_wire",
    "recover",
    "shuffle_payload",
    "topic_counts",
    "use_zstd_level",
    "wire_payload",
]

log = logging.getLogger("fp.recording")

MESSAGE_ENCODING = "fpwire"
#: FPWIRE01 payload with every buffer byte-shuffled in place (:func:`shuffle_payload`): the recorder's default
#: under chunk compression (the planes of equal-significance bytes compress 12–17 % smaller with zstd).
SHUFFLED_ENCODING = "fpwire-shuffled"
JSON_ENCODING = "json"
#: message encodings of bus channels (the others are display channels).
BUS_ENCODINGS = (MESSAGE_ENCODING, SHUFFLED_ENCODING, JSON_ENCODING)
#: schemas recorded as plain JSON (no arrays: the wire header is the whole message).
JSON_SCHEMAS = frozenset({"Detections", "Tracks", "Status", "ErrorReport"})
UNKNOWN_SCHEMA = json.dumps(
    {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "unknown",
        "description": "Header unreadable or of an unsupported schema/version; the payload is recorded raw.",
    },
    indent=2,
).encode()
#: chunk compression of the recorder (``--compression``; zstd by default).
COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}
#: zstd level of the chunks this process writes (:func:`use_zstd_level`): level 1 compresses a quick demo frame
#: within 1 % of level 3 (the library's default) in a fifth to a half of the time.
ZSTD_LEVEL = 1
MCAP_MAGIC = b"\x89MCAP0\r\n"
#: largest record the reader loads (a corrupt length field must not allocate 2⁶² bytes; issue 13).
RECORD_SIZE_LIMIT = min(4 << 30, (os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")) // 4)

RawMessage = tuple[Schema | None, Channel, McapMessage]


class RecordingError(ValueError):
    """The file is not an MCAP recording, or nothing could be read from it."""


class _ZstdAtLevel:
    """What ``mcap.writer`` calls of ``zstandard`` (``compress(data)``), at a given level; the rest is
    ``zstandard``'s own."""

    def __init__(self, level: int) -> None:
        self.level = level

    def compress(self, data: bytes) -> bytes:
        return zstandard.compress(data, self.level)

    def __getattr__(self, name: str) -> Any:
        return getattr(zstandard, name)


def use_zstd_level(level: int = ZSTD_LEVEL) -> None:
    """Make every MCAP ``Writer`` of this process compress zstd chunks at ``level`` (mcap's Writer has no
    level option and calls ``zstandard.compress(data)``, level 3). Any zstd reader reads them."""
    if not 1 <= level <= 22:
        raise ValueError(f"zstd level: expected 1…22, got {level}")
    mcap.writer.zstandard = _ZstdAtLevel(level)  # type: ignore[attr-defined]


def _check_magic(path: Path) -> None:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC:
        found = "an empty file" if not head else f"{head!r}"
        raise RecordingError(f"{path}: not an MCAP file (expected the magic {MCAP_MAGIC!r}, found {found})")


def _chunk_records(chunk: Chunk) -> list[Any]:
    """The records of a chunk, its CRC (over the uncompressed bytes) checked first; raises on any damage."""
    stream, n = get_chunk_data_stream(chunk, validate_crc=True)
    out: list[Any] = []
    while stream.count < n:
        opcode, length = stream.read1(), stream.read8()
        start = stream.count
        if opcode == Opcode.CHANNEL:
            out.append(Channel.read(stream))
        elif opcode == Opcode.MESSAGE:
            out.append(McapMessage.read(stream, length))
        elif opcode == Opcode.SCHEMA:
            out.append(Schema.read(stream))
        else:
            stream.read(length)
        extra = length - (stream.count - start)
        if extra < 0:
            raise McapError(f"chunk record (opcode {opcode}) of {length} bytes read as {stream.count - start}")
        stream.read(extra)  # fields a newer MCAP version may add
    return out


def _summary(path: Path) -> Any:
    """The summary section of a complete file (None for a file whose writer was killed, or a damaged one)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            return make_reader(f, validate_crcs=False).get_summary()
    except Exception:
        return None


def iter_raw(path: str | Path, report: dict[str, Any] | None = None) -> Iterator[RawMessage]:
    """Every message of an MCAP file in file order, read sequentially (no summary needed: a file whose
    writer was killed gives all its complete chunks). Each chunk's CRC is checked: a corrupted chunk is
    skipped and counted in ``report["corrupted_chunks"]`` (and messages whose channel only it declared, in
    ``report["orphaned_messages"]``, unless the file's summary declares it); damage that stops the reading is
    noted in ``report["error"]`` instead of raising. Raises :class:`RecordingError` if the file is not an MCAP."""
    path = Path(path)
    _check_magic(path)
    rep = report if report is not None else {}
    rep.setdefault("error", None)
    rep.update(chunks=0, corrupted_chunks=0)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}

    def records(items: Iterable[Any]) -> Iterator[RawMessage]:
        for r in items:
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                channels[r.id] = r
            elif isinstance(r, McapMessage):
                ch = channels.get(r.channel_id)
                if ch is None:  # declared in a corrupted chunk, and the file has no summary to say what it was
                    rep["orphaned_messages"] += 1
                    continue
                yield schemas.get(ch.schema_id), ch, r

    rep["orphaned_messages"] = 0
    summary = _summary(path)  # a complete file repeats its schemas and channels there
    if summary is not None:
        schemas.update(summary.schemas)
        channels.update(summary.channels)
    with open(path, "rb") as f:
        reader = StreamReader(f, emit_chunks=True, record_size_limit=RECORD_SIZE_LIMIT)
        try:
            for rec in reader.records:
                if not isinstance(rec, Chunk):
                    yield from records([rec])
                    continue
                rep["chunks"] += 1
                try:
                    inner = _chunk_records(rec)
                except Exception as exc:  # CRC mismatch, bad compression, bad inner record: skip this chunk
                    rep["corrupted_chunks"] += 1
                    log.warning("%s: chunk %d skipped: %s", path, rep["chunks"], exc)
                    continue
                yield from records(inner)
        except (McapError, struct.error, ValueError, EOFError, MemoryError, zlib.error) as exc:
            rep["error"] = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def topic_counts(path: str | Path) -> Counter[str]:
    """Messages per key of the bus channels of a recording: from its summary when it has one, else by
    reading it through. RecordingError if it is not an MCAP."""
    path = Path(path)
    _check_magic(path)
    summary = _summary(path)
    counts: Counter[str] = Counter()
    if summary is not None and summary.statistics is not None:
        for cid, n in summary.statistics.channel_message_counts.items():
            ch = summary.channels.get(cid)
            if ch is not None and ch.message_encoding in BUS_ENCODINGS:
                counts[ch.topic] += n
        return counts
    for _schema, ch, _msg in iter_raw(path):
        if ch.message_encoding in BUS_ENCODINGS:
            counts[ch.topic] += 1
    return counts


def json_to_wire(data: bytes) -> bytes:
    """The FPWIRE01 payload of a message recorded as JSON (its header; no buffers)."""
    head = bytes(data)
    pad = -(16 + len(head)) % ALIGN
    return MAGIC + struct.pack("<II", len(head), 0) + head + b"\0" * pad


def _buffers(payload: bytes) -> list[tuple[int, int, int]]:
    """(start, nbytes, itemsize) of every multi-byte buffer of a payload whose header reads and whose buffers lie
    inside it without overlapping; none otherwise (such a payload is recorded as it came)."""
    try:
        hdr = extract_header(payload)
        head = decode_header(hdr, strict=False)
    except WireError:
        return []
    start = -(-(PREFIX_SIZE + len(hdr)) // ALIGN) * ALIGN
    spans = sorted((start + d.offset, d.nbytes, np.dtype(d.dtype).itemsize) for d in head.arrays)
    end = start
    for s, n, _item in spans:
        if s < end or s + n > len(payload):
            return []
        end = s + n
    return [(s, n, item) for s, n, item in spans if item > 1 and n]


def shuffle_payload(payload: bytes, inverse: bool = False) -> bytes:
    """The payload with every multi-byte buffer byte-shuffled (byte 0 of every item, then byte 1, …), in
    place: same length, prefix, header and offsets (``inverse``: back to the wire payload). Strided slice
    copies, ≈ 3 ms for 9 MB. A payload whose header does not read, or whose buffers overlap or overrun it, is
    returned as it is (so the inverse always restores it)."""
    out: np.ndarray | None = None
    for start, n, item in _buffers(payload):
        if out is None:
            out = np.frombuffer(bytearray(payload), np.uint8)
        src = np.frombuffer(payload, np.uint8, n, start)
        dst = out[start : start + n]
        m = n // item
        for k in range(item):
            if inverse:
                dst[k::item] = src[k * m : (k + 1) * m]
            else:
                dst[k * m : (k + 1) * m] = src[k::item]
    return payload if out is None else out.tobytes()


def wire_payload(channel: Channel, msg: McapMessage) -> bytes | None:
    """The wire payload of a recorded bus message (JSON channels re-wrapped, shuffled ones restored); None
    for display channels."""
    if channel.message_encoding == MESSAGE_ENCODING:
        return bytes(msg.data)
    if channel.message_encoding == SHUFFLED_ENCODING:
        return shuffle_payload(bytes(msg.data), inverse=True)
    if channel.message_encoding == JSON_ENCODING:
        return json_to_wire(msg.data)
    return None


def iter_recording(path: str | Path) -> Iterator[tuple[str, bytes, int, int]]:
    """``(key, wire payload, log_time_ns, publish_time_ns)`` of every bus message of an MCAP file in file
    order (display channels left out). Tolerant like :func:`iter_raw`."""
    for _schema, channel, msg in iter_raw(path):
        payload = wire_payload(channel, msg)
        if payload is not None:
            yield channel.topic, payload, int(msg.log_time), int(msg.publish_time)


def iter_messages(path: str | Path, report: dict[str, Any] | None = None) -> Iterator[tuple[str, Message]]:
    """(key, decoded message) for every bus message of a recording (fpwire and JSON channels), in file
    order; messages that do not decode are counted in ``report["undecodable"]`` and skipped."""
    bad = 0
    for _schema, channel, msg in iter_raw(path, report):
        payload = wire_payload(channel, msg)
        if payload is None:
            continue
        try:
            yield channel.topic, decode(payload)
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
    ``<stem>.recovered.mcap``) and report how many were kept, per key, and how many chunks were corrupted.
    ``complete`` is true only when the whole file was read and every CRC matched. Raises
    :class:`RecordingError` (and writes nothing) when the input is not an MCAP or holds no readable message."""
    broken = Path(broken)
    out = Path(fixed) if fixed else broken.with_name(f"{broken.stem}.recovered.mcap")
    if out.resolve() == broken.resolve():
        raise ValueError("recover: the output must differ from the broken file")
    _check_magic(broken)
    report: dict[str, Any] = {"input": str(broken), "output": str(out), "error": None}
    span: dict[str, int] = {}

    def timed(messages: Iterable[RawMessage]) -> Iterator[RawMessage]:
        for m in messages:
            t = m[2].log_time
            span["first"], span["last"] = min(span.get("first", t), t), max(span.get("last", t), t)
            yield m

    tmp = out.with_name(out.name + ".part")
    try:
        with open(tmp, "wb") as f:
            w = Writer(f, compression=CompressionType.ZSTD)
            w.start(profile="", library="fingerprint services.recording (recovered)")
            by_key = copy_messages(w, timed(iter_raw(broken, report)))
            w.finish()
        if not by_key:
            raise RecordingError(
                f"{broken}: no readable message ({report['corrupted_chunks']} corrupted chunk(s) of "
                f"{report['chunks']}{'; ' + report['error'] if report['error'] else ''})"
            )
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    report.update(
        messages=sum(by_key.values()),
        by_key=dict(by_key),
        complete=report["error"] is None and report["corrupted_chunks"] == 0 and report["orphaned_messages"] == 0,
        first_log_time_ns=span.get("first"),
        last_log_time_ns=span.get("last"),
    )
    return report
