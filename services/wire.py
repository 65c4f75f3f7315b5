"""Wire format: a versioned JSON header plus raw little-endian array buffers in one payload.

Byte layout (all integers little-endian)::

    offset  size  content
    0       8     magic b"FPWIRE01"  (format "FPWIRE", container version "01")
    8       4     H = header length in bytes (uint32)
    12      4     flags (uint32), must be 0
    16      H     header: UTF-8 JSON object (the message fields, arrays replaced by buffer names,
                  plus "arrays": [{name, dtype, shape, offset, nbytes}, ...])
    16+H    pad   zero bytes up to D = ceil64(16 + H), the start of the data section
    D+o_i   n_i   buffer i: raw C-order little-endian bytes; every o_i is a multiple of 64 and
                  buffers are separated by zero padding; the payload ends at the last buffer's end

The same header bytes travel as the zenoh attachment (:func:`header_bytes`, :func:`decode_header`), so
a recorder or filter can route on schema, frame index and shapes without touching the payload.
No base64, no pickle; arrays decode as numpy views into the payload (``np.frombuffer`` on a
memoryview, no copy; read-only when the payload is ``bytes``).

Cost: :func:`encode` copies each array once, straight into the output ``bytes`` (``bytes.join`` over
the arrays' buffers); a non-contiguous or big-endian array costs one more copy. :func:`decode` copies
only the header. tests/test_wire.py checks both with tracemalloc on a 30 MB frame.

Bad input never raises anything but :class:`WireError` from :func:`decode` / :func:`decode_header`.
This module is pure (no zenoh): the nodes in ``services`` do the transport.
"""

from __future__ import annotations

import json
import re
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ValidationError

from services.arrays import ArrayDescriptor, ArrayFieldError
from services.messages import MESSAGE_TYPES, VERSION_PATTERN, ErrorReport, Message

__all__ = [
    "ALIGN",
    "DEFAULT_MAX_BYTES",
    "MAGIC",
    "MAX_HEADER_BYTES",
    "PREFIX_SIZE",
    "Header",
    "WireError",
    "decode",
    "decode_header",
    "encode",
    "encode_with_header",
    "error_report",
    "extract_header",
    "header_bytes",
]

MAGIC = b"FPWIRE01"
_PREFIX = struct.Struct("<8sII")
PREFIX_SIZE = _PREFIX.size  # 16
ALIGN = 64
DEFAULT_MAX_BYTES = 256 * 1024 * 1024
MAX_HEADER_BYTES = 16 * 1024 * 1024
_VERSION_RE = re.compile(VERSION_PATTERN)


class WireError(ValueError):
    """A payload or header was refused; ``field`` names the culprit, ``problem`` what was expected."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


def _align(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


# ------------------------------------------------------------------------------------------ encoding


def _collect_arrays(model: BaseModel, prefix: str, out: dict[int, tuple[str, np.ndarray]]) -> None:
    for name in type(model).model_fields:
        _collect_value(getattr(model, name), prefix + name, out)


def _collect_value(value: Any, path: str, out: dict[int, tuple[str, np.ndarray]]) -> None:
    if isinstance(value, np.ndarray):
        out.setdefault(id(value), (path, value))  # one array used twice travels once
    elif isinstance(value, BaseModel):
        _collect_arrays(value, path + ".", out)
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _collect_value(item, f"{path}.{i}", out)


def _wire_array(arr: np.ndarray) -> np.ndarray:
    """C-contiguous little-endian version of ``arr`` (no copy when it already is)."""
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    return np.ascontiguousarray(arr)


def _layout(msg: Message) -> tuple[bytes, list[tuple[int, np.ndarray]]]:
    """Header bytes and (offset in data section, array) for each buffer."""
    if not isinstance(msg, Message):
        raise TypeError(f"expected a services.messages.Message, got {type(msg).__name__}")
    msg = msg.for_wire()  # quantised γ / confocal image: their uint16 codes (GammaMap, ConfocalImage 1.1)
    found: dict[int, tuple[str, np.ndarray]] = {}
    _collect_arrays(msg, "", found)
    descriptors: list[dict[str, Any]] = []
    placed: list[tuple[int, np.ndarray]] = []
    offset = 0
    for name, arr in found.values():
        dtype = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
        descriptors.append(
            {"name": name, "dtype": dtype.str, "shape": list(arr.shape), "offset": offset, "nbytes": arr.nbytes}
        )
        placed.append((offset, arr))
        offset = _align(offset + arr.nbytes)
    header = msg.model_dump(mode="json", context={"array_names": {k: v[0] for k, v in found.items()}})
    header["arrays"] = descriptors
    text = json.dumps(header, ensure_ascii=False, separators=(",", ":"), allow_nan=False)
    return text.encode("utf-8"), placed


def _assemble(hdr: bytes, placed: list[tuple[int, np.ndarray]]) -> bytes:
    data_start = _align(PREFIX_SIZE + len(hdr))
    parts: list[Any] = [_PREFIX.pack(MAGIC, len(hdr), 0), hdr, bytes(data_start - PREFIX_SIZE - len(hdr))]
    pos = 0
    for offset, arr in placed:
        if offset > pos:
            parts.append(bytes(offset - pos))
        parts.append(_wire_array(arr))
        pos = offset + arr.nbytes
    return b"".join(parts)  # the single copy of every array


def encode(msg: Message) -> bytes:
    """Serialize a message to one payload (layout in the module docstring)."""
    return _assemble(*_layout(msg))


def encode_with_header(msg: Message) -> tuple[bytes, bytes]:
    """``(payload, header)``: the payload and the header bytes to send as the attachment."""
    hdr, placed = _layout(msg)
    return _assemble(hdr, placed), hdr


def header_bytes(msg: Message) -> bytes:
    """The JSON header of ``msg`` exactly as :func:`encode` writes it (for the zenoh attachment)."""
    return _layout(msg)[0]


# ------------------------------------------------------------------------------------------ decoding


@dataclass(frozen=True)
class Header:
    """A decoded header: envelope plus the remaining message fields as plain JSON values."""

    schema_name: str
    schema_version: str
    arrays: list[ArrayDescriptor]
    fields: dict[str, Any] = field(default_factory=dict)

    @property
    def frame_index(self) -> int | None:
        v = self.fields.get("frame_index")
        return v if isinstance(v, int) and not isinstance(v, bool) else None

    @property
    def timestamp(self) -> float | None:
        v = self.fields.get("timestamp")
        return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None

    @property
    def message_type(self) -> type[Message] | None:
        return MESSAGE_TYPES.get(self.schema_name)

    @property
    def payload_nbytes(self) -> int | None:
        """Data-section size implied by the descriptors (None without arrays)."""
        return max((d.offset + d.nbytes for d in self.arrays), default=None)


def _bytes_view(payload: Any) -> memoryview:
    try:
        mv = memoryview(payload)
    except TypeError:
        raise WireError("payload", f"expected bytes, bytearray or memoryview, got {type(payload).__name__}") from None
    if not mv.c_contiguous:
        raise WireError("payload", "expected a contiguous buffer")
    return mv.cast("B") if (mv.format != "B" or mv.ndim != 1) else mv


def _split(mv: memoryview) -> tuple[bytes, int]:
    """Check the prefix; return (header bytes, start of the data section)."""
    n = mv.nbytes
    if n < PREFIX_SIZE:
        raise WireError("payload", f"truncated: {n} bytes, expected at least the {PREFIX_SIZE}-byte prefix")
    magic, hlen, flags = _PREFIX.unpack_from(mv, 0)
    if magic != MAGIC:
        raise WireError("magic", f"expected {MAGIC!r}, got {magic!r}")
    if flags != 0:
        raise WireError("flags", f"expected 0, got {flags}")
    if hlen > n - PREFIX_SIZE:
        raise WireError(
            "header_length", f"{hlen} bytes goes beyond the payload ({n - PREFIX_SIZE} bytes after the prefix)"
        )
    if hlen > MAX_HEADER_BYTES:
        raise WireError("header_length", f"{hlen} bytes exceeds the limit of {MAX_HEADER_BYTES}")
    return bytes(mv[PREFIX_SIZE : PREFIX_SIZE + hlen]), _align(PREFIX_SIZE + hlen)


def _reject_constant(token: str) -> Any:
    raise WireError("header", f"{token} is not valid JSON; expected finite numbers")


def _parse_json(hdr: bytes) -> dict[str, Any]:
    try:
        obj = json.loads(hdr.decode("utf-8"), parse_constant=_reject_constant)
    except UnicodeDecodeError as exc:
        raise WireError("header", f"expected UTF-8 JSON ({exc.reason} at byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise WireError("header", f"expected a JSON object ({exc.msg} at char {exc.pos})") from None
    except RecursionError:
        raise WireError("header", "JSON nested too deeply") from None
    if not isinstance(obj, dict):
        raise WireError("header", f"expected a JSON object, got {type(obj).__name__}")
    return obj


def _envelope(obj: dict[str, Any], strict: bool) -> Header:
    name = obj.get("schema_name")
    if not isinstance(name, str):
        raise WireError("schema_name", f"expected a string naming the message type, got {name!r:.80}")
    version = obj.get("schema_version")
    if not isinstance(version, str) or not _VERSION_RE.match(version):
        raise WireError("schema_version", f"expected 'MAJOR.MINOR', got {version!r:.80}")
    if strict:
        cls = MESSAGE_TYPES.get(name)
        if cls is None:
            raise WireError("schema_name", f"unknown schema {name!r:.80}; expected one of {', '.join(MESSAGE_TYPES)}")
        major, _ = cls.version()
        got = int(version.split(".")[0])
        if got != major:
            rel = "newer than" if got > major else "older than"
            raise WireError(
                "schema_version", f"{name} {version} is {rel} this reader; expected major version {major} ({major}.x)"
            )
    raw = obj.get("arrays", [])
    if not isinstance(raw, list):
        raise WireError("arrays", f"expected a list of array descriptors, got {type(raw).__name__}")
    arrays: list[ArrayDescriptor] = []
    for i, d in enumerate(raw):
        label = f"arrays[{d.get('name')!r:.80}]" if isinstance(d, dict) and "name" in d else f"arrays[{i}]"
        try:
            arrays.append(ArrayDescriptor.model_validate(d, strict=True))
        except ValidationError as exc:
            f, problem = _first_error(exc)
            raise WireError(f"{label}.{f}" if f else label, problem) from None
    names = [d.name for d in arrays]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise WireError(f"arrays[{dup!r}]", "expected unique buffer names, found a duplicate")
    fields = {k: v for k, v in obj.items() if k not in ("schema_name", "schema_version", "arrays")}
    return Header(name, version, arrays, fields)


def _views(mv: memoryview, data_start: int, arrays: list[ArrayDescriptor]) -> dict[str, np.ndarray]:
    n = mv.nbytes
    views: dict[str, np.ndarray] = {}
    end = 0
    for d in sorted(arrays, key=lambda d: d.offset):
        label = f"arrays[{d.name!r}]"
        start = data_start + d.offset
        if start + d.nbytes > n:
            raise WireError(
                label, f"truncated: needs payload bytes [{start}, {start + d.nbytes}) but the payload has {n}"
            )
        if d.offset < end:
            raise WireError(f"{label}.offset", f"{d.offset} overlaps the previous buffer (ends at {end})")
        dtype = np.dtype(d.dtype)
        if d.nbytes == 0:
            arr = np.zeros(d.shape, dtype)
            arr.flags.writeable = False
        else:
            arr = np.frombuffer(mv, dtype=dtype, count=d.nbytes // dtype.itemsize, offset=start).reshape(d.shape)
        views[d.name] = arr
        end = d.offset + d.nbytes
    expected = data_start + end
    if n != expected:
        raise WireError("payload", f"expected exactly {expected} bytes (data section starts at {data_start}), got {n}")
    return views


def _first_error(exc: ValidationError) -> tuple[str, str]:
    """(dotted field, problem) of the first pydantic error, with custom field errors unwrapped."""
    errs = exc.errors(include_url=False)
    e = errs[0]
    loc = ".".join(str(p) for p in e["loc"])
    err = (e.get("ctx") or {}).get("error")
    if isinstance(err, ArrayFieldError):
        loc, problem = ".".join(p for p in (loc, err.field) if p), err.problem
    else:
        problem = e["msg"].removeprefix("Value error, ")
        inp = e.get("input")
        if isinstance(inp, (int, float, str, bool)) or inp is None:
            problem += f" (got {inp!r:.80})"
    if len(errs) > 1:
        problem += f" (and {len(errs) - 1} more error(s))"
    return loc, problem


def decode(
    payload: bytes | bytearray | memoryview,
    max_bytes: int = DEFAULT_MAX_BYTES,
    expect: type[Message] | None = None,
) -> Message:
    """Decode and validate a payload; arrays are views into it. Raises only :class:`WireError`.

    ``max_bytes`` refuses oversize payloads before anything else; ``expect`` refuses other types.
    """
    try:
        return _decode(payload, max_bytes, expect)
    except WireError:
        raise
    except Exception as exc:  # safety net: bad input must surface as WireError only
        raise WireError("payload", f"undecodable ({type(exc).__name__}: {exc})") from exc


def _decode(payload: Any, max_bytes: int, expect: type[Message] | None) -> Message:
    mv = _bytes_view(payload)
    if mv.nbytes > max_bytes:
        raise WireError("payload", f"{mv.nbytes} bytes exceeds the limit max_bytes={max_bytes}")
    hdr, data_start = _split(mv)
    head = _envelope(_parse_json(hdr), strict=True)
    cls = MESSAGE_TYPES[head.schema_name]
    if expect is not None and cls is not expect:
        raise WireError("schema_name", f"expected {expect.__name__}, got {head.schema_name}")
    views = _views(mv, data_start, head.arrays)
    used: set[str] = set()
    try:
        msg = cls.model_validate_json(hdr, strict=True, context={"arrays": views, "used": used})
    except ValidationError as exc:
        f, problem = _first_error(exc)
        raise WireError(f or head.schema_name, problem) from None
    unused = [name for name in views if name not in used]
    if unused:
        raise WireError(f"arrays[{unused[0]!r}]", f"not referenced by any field of {head.schema_name}")
    return msg


def extract_header(payload: bytes | bytearray | memoryview) -> bytes:
    """The header bytes of a payload (prefix checked, arrays not read)."""
    try:
        return _split(_bytes_view(payload))[0]
    except WireError:
        raise
    except Exception as exc:
        raise WireError("payload", f"undecodable ({type(exc).__name__}: {exc})") from exc


def decode_header(data: bytes | bytearray | memoryview, *, strict: bool = True) -> Header:
    """Decode a header from the attachment (bare JSON) or from a whole payload (starts with MAGIC).

    ``strict`` also requires a known schema name and a supported major version; with
    ``strict=False`` (recorders) only the envelope's shape is checked. Raises only WireError.
    """
    try:
        mv = _bytes_view(data)
        hdr = _split(mv)[0] if mv[: len(MAGIC)] == MAGIC else bytes(mv)
        if len(hdr) > MAX_HEADER_BYTES:
            raise WireError("header_length", f"{len(hdr)} bytes exceeds the limit of {MAX_HEADER_BYTES}")
        return _envelope(_parse_json(hdr), strict=strict)
    except WireError:
        raise
    except Exception as exc:
        raise WireError("header", f"undecodable ({type(exc).__name__}: {exc})") from exc


def error_report(exc: WireError, key: str, payload: Any = None, node: str = "") -> ErrorReport:
    """The ``ErrorReport`` to publish for a refused message (frame index and header excerpt if readable)."""
    frame_index: int | None = None
    excerpt = ""
    if payload is not None:
        try:
            mv = _bytes_view(payload)
            try:
                raw = _split(mv)[0] if mv[: len(MAGIC)] == MAGIC else bytes(mv[:MAX_HEADER_BYTES])
                excerpt = raw[:1024].decode("utf-8", errors="replace")
                frame_index = decode_header(raw, strict=False).frame_index
            except WireError:
                excerpt = excerpt or repr(bytes(mv[:64]))
        except WireError:
            excerpt = f"<{type(payload).__name__}>"
    if frame_index is not None and frame_index < 0:
        frame_index = None
    return ErrorReport(
        frame_index=frame_index,
        key=key,
        field=exc.field,
        problem=exc.problem[:2000],
        header_excerpt=excerpt[:1024],
        node=node,
    )
