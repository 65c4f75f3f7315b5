"""γ worker node (`fp worker`): one share of a rig's frames, computed for a merger (docs/scaling.md).

The merger (``services.nodes.merger``) receives the rig's frames on ``fp/<rig>/rf`` and forwards each one,
as it came (payload and header attachment), to one worker on ``fp/<rig>/@shard/assign/<name>``. For each
frame the worker runs the single-node pipeline without its tracker (``services.pipeline.Pipeline`` with
``track=False``: band and output projection, confocal image, one γ-map per fingerprint, null models,
detections), builds the wire messages the processor would publish (``services.convert.frame_messages``)
and sends one shard result on ``fp/<rig>/@shard/result``: those messages' FPWIRE01 payloads exactly as
they will be published, each map's null model (the tracker's input, fpcore.cfar.NullModel) and the
tracker's settings.

Shares (the merger's ``--shard``, docs/scaling.md): a frame forwarded as it came (attachment: the RFFrame
header) is a whole frame — every fingerprint and the confocal image. A *part* carries the attachment
``FPPART01`` + uint32 length + JSON ``{"units": [...]}`` + the RFFrame header: the units are fingerprint
names and ``@image`` (the confocal image and the frame's truth report, computed by one worker per frame);
the worker computes only those (``Pipeline.process(names=…, with_image=…)``) and says which units its result
covers. Every worker holds (builds) the whole dictionary, so a share moves to another worker at once.
A frame that fails (bad payload, or anything its computation raises) is answered
``failed`` with its ErrorReport (``services.nodes.frame_errors``, as the processor reports it) and the
worker goes on: every assigned frame is answered. The merger runs the one tracker in frame order and
publishes.

Dictionary: every worker serves the dictionary protocol (``services.registry``) for its own pipeline on
``fp/<rig>/@shard/assign/<name>/dictionary/**``; the merger answers ``fp/<rig>/dictionary/**`` for the
deployment from them (services.nodes.merger).

The worker announces itself with the liveliness token ``fp/<rig>/alive/worker/<name>`` (declared last,
after its subscription): the merger's membership, and the shares, follow the tokens.

Shard result payload (``FPSHARD1``, internal: it never leaves ``@shard``): the FPWIRE01 layout — 8-byte
magic, uint32 header length, uint32 flags 0, a UTF-8 JSON header, zero padding to a multiple of 64, then
64-aligned raw little-endian buffers listed in the header's ``arrays`` ({name, dtype, shape, offset,
nbytes}). No pickle.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from fpcore.cfar import NullModel
from fpcore.grid import Grid
from services.convert import frame_messages
from services.messages import ErrorReport, RFFrame
from services.nodes.base import Node, start_warmed_thread
from services.nodes.frame_errors import failure_report, truth_report
from services.pipeline import Pipeline, PipelineConfig, tracker_settings
from services.registry import DictionaryServer, FingerprintSpec
from services.runtime import limit_blas_threads
from services.topics import Keys
from services.wire import DEFAULT_MAX_BYTES, WireError, decode, decode_header, encode, error_report

__all__ = [
    "IMAGE_UNIT",
    "ShardResult",
    "Worker",
    "WorkerConfig",
    "decode_shard",
    "default_worker_name",
    "encode_part",
    "encode_shard",
    "split_part",
    "worker_dictionary_root",
]

log = logging.getLogger("fp.worker")
SHARD_MAGIC = b"FPSHARD1"
_PREFIX = struct.Struct("<8sII")
_ALIGN = 64
KINDS = ("result", "failed")
PART_MAGIC = b"FPPART01"
_PART = struct.Struct("<8sI")
#: The unit of a part that stands for the frame's own outputs: the confocal image and the truth report.
IMAGE_UNIT = "@image"
#: The unit of a whole frame (a frame forwarded as it came).
WHOLE = "*"


def default_worker_name() -> str:
    """``<host>-<pid>``: unique on the bus, and a plain key chunk."""
    host = "".join(c if c.isalnum() or c in "_-." else "-" for c in socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"


def worker_dictionary_root(keys: Keys, worker: str) -> str:
    """``fp/<rig>/@shard/assign/<worker>/dictionary``: a worker's own dictionary queryable (under what the
    merger assigns to it; ``@shard`` keeps it out of ``fp/<rig>/**``)."""
    return f"{keys.shard_assign_to(worker)}/dictionary"


@dataclass(frozen=True)
class _WorkerKeys(Keys):
    """The rig's keys with the dictionary queryable moved to the worker's own root."""

    root: str = ""

    @property
    def dictionary_root(self) -> str:
        return self.root


def encode_part(units: list[str], header: bytes) -> bytes:
    """The attachment of a part of a frame: ``FPPART01``, the units (JSON), then the RFFrame header."""
    doc = json.dumps({"units": units}, separators=(",", ":")).encode()
    return _PART.pack(PART_MAGIC, len(doc)) + doc + header


def split_part(attachment: bytes) -> tuple[list[str] | None, bytes]:
    """(units, RFFrame header) of an assignment's attachment; units None for a whole frame. ValueError on a
    malformed part."""
    if attachment[: len(PART_MAGIC)] != PART_MAGIC:
        return None, attachment
    try:
        _, n = _PART.unpack_from(attachment, 0)
        units = json.loads(attachment[_PART.size : _PART.size + n])["units"]
        if not isinstance(units, list) or not all(isinstance(u, str) for u in units):
            raise ValueError("units: expected a list of names")
        return units, attachment[_PART.size + n :]
    except (ValueError, KeyError, TypeError, struct.error) as exc:
        raise ValueError(f"part attachment: {exc}") from None


# -- the shard result payload -----------------------------------------------------------------------
@dataclass
class ShardResult:
    """One frame's results from a worker: ``messages`` are (topic, FPWIRE01 payload) in publish order."""

    frame_index: int
    timestamp: float
    worker: str
    kind: str = "result"  # result | failed (messages: the ErrorReport)
    messages: list[tuple[str, bytes]] = dataclasses.field(default_factory=list)
    nulls: dict[str, NullModel] = dataclasses.field(default_factory=dict)
    tracker: dict[str, float] = dataclasses.field(default_factory=dict)
    grid: Grid | None = None
    compute_s: float = 0.0
    units: list[str] = dataclasses.field(default_factory=lambda: [WHOLE])  # what it covers (module doc)


def encode_shard(res: ShardResult) -> bytes:
    """The FPSHARD1 payload of ``res`` (module doc)."""
    bufs: list[tuple[str, np.ndarray]] = []

    def buf(name: str, arr: Any) -> str:
        bufs.append((name, np.ascontiguousarray(arr)))
        return name

    grid = None
    if res.grid is not None:
        g = res.grid
        grid = {a: None if getattr(g, a) is None else buf(f"grid.{a}", getattr(g, a)) for a in ("x", "y", "z")}
    nulls: dict[str, dict[str, Any]] = {}
    for name, nm in res.nulls.items():
        fields: dict[str, Any] = {}
        for f in dataclasses.fields(nm):
            v = getattr(nm, f.name)
            if f.name == "grid":
                continue
            if isinstance(v, np.ndarray):
                fields[f.name] = {"buffer": buf(f"null.{len(nulls)}.{f.name}", v)}
            elif isinstance(v, tuple):
                fields[f.name] = {"tuple": [float(x) if isinstance(x, (float, np.floating)) else int(x) for x in v]}
            else:
                keep = isinstance(v, (int, np.integer)) and not isinstance(v, bool)  # an int stays one (n_maps)
                fields[f.name] = {"value": None if v is None else int(v) if keep else float(v)}
        nulls[name] = fields
    msgs = [[topic, buf(f"msg.{i}", np.frombuffer(p, np.uint8))] for i, (topic, p) in enumerate(res.messages)]
    arrays, offset = [], 0
    for name, a in bufs:
        arrays.append(
            {"name": name, "dtype": a.dtype.str, "shape": list(a.shape), "offset": offset, "nbytes": a.nbytes}
        )
        offset += -(-a.nbytes // _ALIGN) * _ALIGN
    header = {
        "frame_index": res.frame_index,
        "timestamp": res.timestamp,
        "worker": res.worker,
        "kind": res.kind,
        "units": res.units,
        "compute_s": res.compute_s,
        "tracker": res.tracker,
        "grid": grid,
        "nulls": nulls,
        "messages": msgs,
        "arrays": arrays,
    }
    hdr = json.dumps(header, separators=(",", ":")).encode()
    start = -(-(_PREFIX.size + len(hdr)) // _ALIGN) * _ALIGN
    parts = [_PREFIX.pack(SHARD_MAGIC, len(hdr), 0), hdr, bytes(start - _PREFIX.size - len(hdr))]
    for (_, a), d in zip(bufs, arrays, strict=True):
        parts.append(a.tobytes())
        parts.append(bytes(-(-d["nbytes"] // _ALIGN) * _ALIGN - d["nbytes"]))
    return b"".join(parts)


def decode_shard(payload: bytes) -> ShardResult:
    """Inverse of :func:`encode_shard`; ValueError (one line) on a malformed payload. Arrays are read-only views."""
    try:
        magic, n, flags = _PREFIX.unpack_from(payload, 0)
        if magic != SHARD_MAGIC or flags != 0 or _PREFIX.size + n > len(payload):
            raise ValueError("bad magic, flags or header length")
        h = json.loads(payload[_PREFIX.size : _PREFIX.size + n])
        start = -(-(_PREFIX.size + n) // _ALIGN) * _ALIGN
        views: dict[str, np.ndarray] = {}
        for d in h["arrays"]:
            lo, hi = start + int(d["offset"]), start + int(d["offset"]) + int(d["nbytes"])
            if hi > len(payload):
                raise ValueError(f"buffer {d['name']!r} runs past the payload")
            dt, count = np.dtype(d["dtype"]), int(np.prod(d["shape"], dtype=np.int64))
            if count * dt.itemsize != hi - lo:
                raise ValueError(f"buffer {d['name']!r}: shape and nbytes disagree")
            views[d["name"]] = np.frombuffer(payload, dt, count=count, offset=lo).reshape(d["shape"])
        grid = None
        if h["grid"] is not None:
            ax = {a: None if b is None else views[b] for a, b in h["grid"].items()}
            grid = Grid(ax["x"], ax["z"], ax["y"])
        nulls = {}
        for name, fields in h["nulls"].items():
            kw: dict[str, Any] = {}
            for k, v in fields.items():
                kw[k] = views[v["buffer"]] if "buffer" in v else tuple(v["tuple"]) if "tuple" in v else v["value"]
            nulls[name] = NullModel(grid=grid, **kw)
        messages = [(str(t), views[b].tobytes()) for t, b in h["messages"]]
        kind = str(h["kind"])
        if kind not in KINDS:
            raise ValueError(f"kind {kind!r}")
        return ShardResult(
            int(h["frame_index"]),
            float(h["timestamp"]),
            str(h["worker"]),
            kind,
            messages,
            nulls,
            dict(h["tracker"]),
            grid,
            float(h.get("compute_s", 0.0)),
            [str(u) for u in h.get("units", [WHOLE])],
        )
    except (ValueError, KeyError, TypeError, struct.error) as exc:
        raise ValueError(f"shard result: {exc}") from None


# -- the node -----------------------------------------------------------------------------------------
@dataclass
class WorkerConfig(PipelineConfig):
    """Worker settings on top of the processing settings (its pipeline never tracks: the merger does)."""

    rig: str = "demo"
    name: str = ""
    max_frame_bytes: int = DEFAULT_MAX_BYTES
    blas_threads: int | None = 1

    def __post_init__(self) -> None:
        self.name = self.name or default_worker_name()
        super().__post_init__()


class Worker(Node):
    """A γ worker on an open zenoh session: ``with Worker(session, cfg, specs): ...`` (module doc)."""

    role = "worker"

    def __init__(
        self,
        session: zenoh.Session,
        config: WorkerConfig,
        fingerprints: list[FingerprintSpec] | tuple[FingerprintSpec, ...] = (),
    ) -> None:
        super().__init__(session, config.rig, config.name)
        self.cfg = dataclasses.replace(config, track=False)
        self.pipeline = Pipeline(self.cfg, fingerprints)
        self._cond = threading.Condition()
        self._assigned: deque[tuple[int, Any, list[str] | None]] = deque()  # (frame index, payload, units)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        root = worker_dictionary_root(self.keys, self.name)
        self._server = DictionaryServer(session, _WorkerKeys(config.rig, root), self.pipeline, f"{self.name}-dict")
        self.frames_computed = 0
        self.parts_computed = 0
        self.failed = 0
        self.received = 0

    @property
    def token_key(self) -> str:
        return f"{self.keys.alive('worker')}/{self.name}"  # always …/alive/worker/<name>

    def _open(self) -> None:
        if self.cfg.blas_threads is not None:
            try:
                limit_blas_threads(self.cfg.blas_threads)
            except OSError:
                pass
        self.declare_publishers("shard_result", "errors")
        self._thread = start_warmed_thread(self.pipeline.warm_up, self._work, f"{self.name}-work")
        self._server.start_thread()
        self._server.declare()
        self._subs = [self.session.declare_subscriber(self.keys.shard_assign_to(self.name), self._on_assign)]

    def _shutdown(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._server.undeclare()
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=30)
        self._server.join(timeout=30)

    def stats(self) -> dict[str, Any]:
        return {
            "worker": self.name,
            "received": self.received,
            "computed": self.frames_computed,
            "parts": self.parts_computed,
            "failed": self.failed,
            "setup_s": self.pipeline.setup_s,
        }

    # -- input (a zenoh callback: no copy, no work) --------------------------------------------------------
    def _on_assign(self, sample: zenoh.Sample) -> None:
        att = sample.attachment
        try:
            units, header = split_part(att.to_bytes() if att is not None else b"")
            fi = decode_header(header, strict=False).frame_index
        except (ValueError, WireError):
            units, fi = None, None
        if fi is None:  # the merger forwards only frames it could index
            log.warning("%s: a frame without its index (or a malformed part); ignored", self.name)
            return
        with self._cond:
            self.received += 1
            self._assigned.append((fi, sample.payload, units))
            self._cond.notify_all()

    # -- work --------------------------------------------------------------------------------------------
    def _work(self) -> None:
        """The frame loop: every assigned frame is answered, ``result`` or ``failed`` (the merger waits for it)."""
        while not self._stop.is_set():
            with self._cond:
                if not self._assigned:
                    self._cond.wait(0.2)
                    continue
                fi, payload, units = self._assigned.popleft()
            try:
                res = self._compute(fi, payload) if units is None else self._compute(fi, payload, units)
                data = encode_shard(res)
            except Exception as exc:  # the thread never dies on one frame (its token would stay up)
                self.failed += 1
                log.exception("frame %s failed", fi)
                res = self._failed(fi, 0.0, [], failure_report(exc, fi, self.keys.rf, self.name), units)
                data = encode_shard(res)
            if res.kind == "result":
                self.frames_computed += units is None
                self.parts_computed += units is not None
            self._send(fi, data)

    def _failed(
        self, fi: int, timestamp: float, pre: list[tuple[str, bytes]], rep: ErrorReport, units: list[str] | None
    ) -> ShardResult:
        return ShardResult(fi, timestamp, self.name, "failed", [*pre, ("errors", encode(rep))], units=units or [WHOLE])

    def _compute(self, fi: int, payload: Any, units: list[str] | None = None) -> ShardResult:
        """One frame (``units`` None) or part of one, as ``Processor._work`` does it: a frame that is refused
        or whose processing (pipeline, output messages, encoding) raises is answered ``failed`` with its
        ErrorReport."""
        t0 = time.perf_counter()
        key = self.keys.rf
        raw = payload.to_bytes()
        try:
            msg = decode(raw, max_bytes=self.cfg.max_frame_bytes, expect=RFFrame)
        except WireError as exc:
            self.failed += 1
            return self._failed(fi, 0.0, [], error_report(exc, key, raw, node=self.name), units)
        assert isinstance(msg, RFFrame)
        own = units is None or IMAGE_UNIT in units  # the frame's own outputs: image, truth report
        truth = truth_report(msg, key, self.name) if own else None  # processed without its truth, as fp process
        pre = [] if truth is None else [("errors", encode(truth))]
        try:
            return self._result(fi, msg, pre, t0, units)
        except Exception as exc:  # reported in frame order by the merger, like the processor's failures
            self.failed += 1
            log.exception("frame %s failed", fi)
            return self._failed(fi, msg.timestamp, pre, failure_report(exc, fi, key, self.name), units)

    def _result(
        self, fi: int, msg: RFFrame, pre: list[tuple[str, bytes]], t0: float, units: list[str] | None = None
    ) -> ShardResult:
        names = None if units is None else [u for u in units if u != IMAGE_UNIT]
        if names is not None:
            held = set(self.pipeline.names)
            missing = [n for n in names if n not in held]
            if missing:
                raise ValueError(
                    f"worker {self.name} has no fingerprint {', '.join(map(repr, missing))} (it holds "
                    f"{sorted(held)}): every worker needs the same dictionary"
                )
        image = None if units is None else IMAGE_UNIT in units and self.cfg.publish_image
        res = self.pipeline.process(msg.to_acquisition(), names=names, with_image=image)
        out = frame_messages(res, fi, msg.timestamp)
        msgs = list(pre)
        if out["image"] is not None:
            msgs.append(("image", encode(out["image"])))
        msgs.extend(("gamma", encode(g)) for g in out["gamma"])
        msgs.append(("detections", encode(out["detections"])))
        settings = tracker_settings(res.acq, res.band, self.pipeline.cfg)
        dt = time.perf_counter() - t0
        return ShardResult(
            fi, msg.timestamp, self.name, "result", msgs, res.nulls, settings, res.grid, dt, units or [WHOLE]
        )

    def _send(self, fi: int, payload: bytes) -> None:
        try:
            self._pubs["shard_result"].put(payload, timestamp=self.session.new_timestamp())
        except Exception as exc:  # pragma: no cover - only when the session is going down
            log.error("%s: could not send frame %s: %s", self.name, fi, exc)
