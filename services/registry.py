"""The fingerprint dictionary: its entries, and the queryable protocol that manages it at run time
(docs/design.md §3).

A :class:`FingerprintSpec` says how to build an entry: from a calibration acquisition (target alone at
r0; docs/design.md §4.4) or a numerical model (§4.5). An :class:`Entry` holds the spec, the built
fingerprint or the error that prevented it. The entries live in the processing pipeline
(``services.pipeline.Pipeline``), which rebuilds them against the frames' geometry.

Protocol (server: :class:`DictionaryServer`, client: :func:`dictionary_request`); the queryable
``fp/<rig>/dictionary/**`` answers JSON (keys from ``services.topics``):

* ``get fp/<rig>/dictionary/list`` (or ``…/**``): entries and parameters;
* ``get fp/<rig>/dictionary/<name>``: one entry;
* ``get fp/<rig>/dictionary/add/<name>`` with payload either an RFFrame (calibration; options
  ``{"r0_m": [x, y, z], "diameter_m": d}`` as JSON in the attachment, default: the frame's truth) or
  JSON ``{"model": "point" | "mirror:L=2mm,alpha=10", "r0_m": [...]}``; either may add
  ``"velocity_grid": "VMAX[:STEP]"`` (and ``"velocity_roi"``): a live velocity dictionary (fpcore.velocity);
* ``get fp/<rig>/dictionary/remove/<name>``;
* ``get fp/<rig>/dictionary/set`` with JSON ``{"band_hz": [lo, hi], "n_freq": n, "svd_threshold": t,
  "n_peaks": k}``: fingerprints are rebuilt.

Changes are transactional: ``add`` and ``set`` are validated and built on the side (``set`` also has its
set-up size checked against the memory budget first, :func:`check_setup_size`); the host keeps them only
on success. A refused change answers ``ok: false`` with the reason and leaves the dictionary and its
parameters exactly as they were.

Queries are answered one at a time on the server's own thread (a rebuild takes seconds; the zenoh
callback only queues). zenoh is not imported here: the server and the client use the session they
are given.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from fpcore import budget
from fpcore.velocity import VelocityGrid
from services.messages import RFFrame
from services.topics import Keys
from services.units import parse_length
from services.wire import MAGIC, WireError, decode

if TYPE_CHECKING:  # pragma: no cover
    import zenoh

    from fpcore import Fingerprint
    from fpcore.acquisition import Acquisition

__all__ = [
    "RESERVED",
    "SET_PARAMS",
    "DictionaryHost",
    "DictionaryServer",
    "Entry",
    "FingerprintSpec",
    "check_setup_size",
    "dictionary_request",
    "parse_velocity_grid",
    "set_changes",
    "spec_from_request",
]

log = logging.getLogger("fp.registry")

#: Names an entry cannot take (they are operations or wildcards).
RESERVED = frozenset({"list", "add", "remove", "set", "**", "*"})

#: Velocity step when a velocity grid spec gives none, m/s.
DEFAULT_VELOCITY_STEP = 0.1

#: The parameters a ``set`` query may change.
SET_PARAMS = ("band_hz", "n_freq", "svd_threshold", "n_peaks")


@dataclass
class FingerprintSpec:
    """A dictionary entry to build: a calibration acquisition of the target alone at ``r0`` or a model
    spec (``"point"``, ``"mirror:L=2mm,alpha=10"``) centred at ``r0`` (docs/design.md §4.4–4.5)."""

    name: str
    calibration: Acquisition | None = None
    model: str | None = None
    r0: tuple[float, float, float] | None = None
    diameter: float | None = None  # None: from the calibration's truth, else measured (first arrival)
    gate: bool = True  # the paper's time gate after the front face; False keeps the whole record
    whiten_modes: bool = True  # the paper's whitened modes (eq. finger); False keeps R0′ itself (S2, Fig. S7a)
    # a velocity dictionary searched around each detection and track (fpcore.velocity; None: off)
    velocity_grid: VelocityGrid | None = None

    def __post_init__(self) -> None:
        if (self.calibration is None) == (self.model is None):
            raise ValueError(f"fingerprint {self.name!r}: give exactly one of a calibration or a model spec")


@dataclass
class Entry:
    """One dictionary entry: its spec, and the fingerprint built for the current geometry (or why not)."""

    spec: FingerprintSpec
    fp: Fingerprint | None = None
    error: str | None = None
    velocity: Any = None  # fpcore.velocity.VelocitySearch for the current fingerprint and transmit times

    def describe(self) -> dict[str, Any]:
        fp = self.fp
        source = "calibration" if self.spec.calibration is not None else f"model:{self.spec.model}"
        d: dict[str, Any] = {"name": self.spec.name, "source": source, "built": fp is not None, "error": self.error}
        vg = self.spec.velocity_grid
        if vg is not None:
            d["velocity_grid"] = {
                "max_speed_m_s": list(vg.max_speed),
                "step_m_s": vg.step,
                "roi_half_width_m": vg.roi_half_width,
            }
        if fp is not None:
            d.update(
                provenance=fp.provenance,
                r0_m=[float(v) for v in fp.r0],
                n_s=float(fp.n_s),
                n_t=None if fp.n_t is None else float(fp.n_t),
                shape=list(fp.data.shape),
                state={k: v for k, v in fp.state.items() if isinstance(v, (int, float, str))},
            )
        return d


class DictionaryHost(Protocol):
    """What the server manages (``services.pipeline.Pipeline``)."""

    @property
    def names(self) -> list[str]: ...

    def describe(self) -> dict[str, Any]: ...

    def entry(self, name: str) -> dict[str, Any] | None: ...

    def add(self, spec: FingerprintSpec) -> dict[str, Any]: ...

    def remove(self, name: str) -> None: ...

    def set_params(self, params: dict[str, Any]) -> None: ...


def spec_from_request(name: str, payload: bytes, attachment: bytes) -> FingerprintSpec:
    """FingerprintSpec from an ``add`` query: an RFFrame calibration payload or a JSON model spec."""
    if payload[: len(MAGIC)] == MAGIC:
        try:
            frame = decode(payload, expect=RFFrame)
        except WireError as exc:
            raise ValueError(f"add: calibration payload refused: {exc}") from None
        opts = json.loads(attachment.decode() or "{}") if attachment else {}
        r0 = opts.get("r0_m")
        return FingerprintSpec(
            name,
            calibration=frame.to_acquisition(),
            r0=None if r0 is None else tuple(r0),
            diameter=opts.get("diameter_m"),
            velocity_grid=_velocity_option(opts),
        )
    try:
        doc = json.loads(payload.decode() or "{}")
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ValueError("add: expected an RFFrame payload (calibration) or a JSON model spec") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("model"), str):
        raise ValueError('add: expected JSON {"model": "point" | "mirror:L=2mm,alpha=10", "r0_m": [x, y, z]}')
    r0 = doc.get("r0_m")
    return FingerprintSpec(
        name,
        model=doc["model"],
        r0=None if r0 is None else tuple(float(v) for v in r0),
        velocity_grid=_velocity_option(doc),
    )


def _velocity_option(doc: dict[str, Any]) -> VelocityGrid | None:
    """``"velocity_grid": "VMAX[:STEP]"`` (and ``"velocity_roi": "3mm"``) of an add request, None if absent."""
    spec = doc.get("velocity_grid")
    if spec is None:
        return None
    if not isinstance(spec, str):
        raise ValueError(f'add: velocity_grid must be a string "VMAX[:STEP]" (e.g. "0.5,0.2:0.1"), got {spec!r}')
    names = ("add: velocity_grid", "add: velocity_roi")
    return parse_velocity_grid(spec, str(doc.get("velocity_roi", "3mm")), names)


def parse_velocity_grid(
    text: str, roi: str = "3mm", names: tuple[str, str] = ("--velocity-grid", "--velocity-roi")
) -> VelocityGrid:
    """VelocityGrid of ``--velocity-grid VMAX[:STEP]`` (VMAX: one speed, or VX,VZ[,VY]) and ``--velocity-roi``;
    ValueError naming the option (``names``: how the caller calls the two), what was expected and what was
    found."""
    opt, roi_opt = names
    expect = "VMAX[:STEP] in m/s, VMAX one speed or VX,VZ[,VY] (e.g. 0.5,0.2:0.1)"
    speeds, _, step_txt = str(text).strip().partition(":")
    try:
        v = [float(x) for x in speeds.split(",")]
        step = float(step_txt) if step_txt.strip() else DEFAULT_VELOCITY_STEP
    except ValueError:
        raise ValueError(f"{opt}: expected {expect}, got {text!r}") from None
    if len(v) not in (1, 2, 3):
        raise ValueError(f"{opt}: expected {expect}, got {text!r}")
    xyz = (v[0], v[0], v[0]) if len(v) == 1 else (v[0], v[2] if len(v) == 3 else 0.0, v[1])
    half = parse_length(roi, roi_opt)
    try:
        return VelocityGrid(xyz, step, half)
    except ValueError as exc:
        raise ValueError(f"{opt}: {exc} (from {text!r}, {roi_opt} {roi!r})") from None


def _number(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"set: {name} must be a finite number, got {v!r}")
    return float(v)


def _count(name: str, v: Any) -> int:
    x = _number(name, v)
    if x != int(x) or x < 1:
        raise ValueError(f"set: {name} must be an integer >= 1, got {v!r}")
    return int(x)


def set_changes(params: Any) -> dict[str, Any]:
    """The PipelineConfig fields a ``set`` request changes (``{"band_hz": [lo, hi], "n_freq": n,
    "svd_threshold": t, "n_peaks": k}``; ``n_freq`` null: every bin), each checked for type and range;
    ValueError names the parameter, what was expected and what was found."""
    if not isinstance(params, dict):
        raise ValueError(f"set: expected a JSON object of parameters, got {type(params).__name__}")
    unknown = set(params) - set(SET_PARAMS)
    if unknown:
        raise ValueError(f"set: unknown parameter(s) {sorted(unknown)}; expected some of {sorted(SET_PARAMS)}")
    changes: dict[str, Any] = {}
    if "band_hz" in params:
        b = params["band_hz"]
        if not (isinstance(b, (list, tuple)) and len(b) == 2):
            raise ValueError(f"set: band_hz must be [f_min, f_max] in Hz, got {b!r}")
        lo, hi = _number("band_hz", b[0]), _number("band_hz", b[1])
        if not 0 <= lo < hi:
            raise ValueError(f"set: band_hz must be [f_min, f_max] with 0 <= f_min < f_max, got {b!r}")
        changes["band"] = (lo, hi)
    if "n_freq" in params:
        changes["n_freq"] = None if params["n_freq"] is None else _count("n_freq", params["n_freq"])
    if "svd_threshold" in params:
        t = _number("svd_threshold", params["svd_threshold"])
        if not 0 < t <= 1:
            raise ValueError(f"set: svd_threshold must be in (0, 1], got {t:g}")
        changes["svd_threshold"] = t
    if "n_peaks" in params:
        changes["n_peaks"] = _count("n_peaks", params["n_peaks"])
    return changes


def check_setup_size(
    acq: Acquisition, band: tuple[float, float], n_freq: int | None, limit: int | None = None
) -> float:
    """Estimated bytes of the spectrum stage of a set-up for frames like ``acq`` (``Acquisition.spectrum``:
    the complex64 half spectrum of the zero-padded record, N_FFT from ``fpcore.budget.spectrum_bins``, and
    three copies of the kept bins, as ``fpcore.budget.imaging_bytes`` counts them); ``fpcore.budget.BudgetError``
    (a ValueError) before anything is allocated when it exceeds ``limit`` (default: the memory budget)."""
    n_ch = int(acq.probe.n_elements) * int(acq.sequence.n_waves)
    n_fft, n_f = budget.spectrum_bins(int(acq.n_samples), float(acq.fs), band, n_freq)
    need = 8.0 * n_ch * (n_fft / 2 + 1) + 3 * 8.0 * n_f * n_ch
    budget.check(
        f"set: refused, n_freq={n_freq} over the band {band[0] / 1e6:g}–{band[1] / 1e6:g} MHz "
        f"({n_ch}-channel frames, N_FFT {n_fft})",
        need,
        "ask for fewer frequencies (n_freq) or a wider band",
        budget=limit,
    )
    return need


class DictionaryServer:
    """The queryable ``fp/<rig>/dictionary/**`` of a host, answered on a thread of its own."""

    def __init__(self, session: zenoh.Session, rig_keys: Keys, host: DictionaryHost, name: str = "dictionary") -> None:
        self.session, self.keys, self.host, self.name = session, rig_keys, host, name
        self._control: queue.Queue[Any] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._queryable: Any = None

    def start_thread(self) -> None:
        """Start answering (queries queue until the queryable is declared with :meth:`declare`)."""
        self._thread = threading.Thread(target=self._serve, name=self.name, daemon=True)
        self._thread.start()

    def declare(self) -> None:
        self._queryable = self.session.declare_queryable(self.keys.dictionary, self._control.put)

    def undeclare(self) -> None:
        """No new queries; the thread finishes the queued ones (see :meth:`join`)."""
        if self._queryable is not None:
            self._queryable.undeclare()
            self._queryable = None
        self._control.put(None)

    def join(self, timeout: float = 30) -> None:
        if self._thread is not None:
            self._thread.join(timeout=timeout)

    def _serve(self) -> None:
        while True:
            query = self._control.get()
            if query is None:
                return
            try:
                ok, doc, reply_key = self.handle(str(query.key_expr), _bytes(query.payload), _bytes(query.attachment))
            except Exception as exc:  # a bad request never takes the node down
                ok, doc, reply_key = False, {"ok": False, "error": f"{type(exc).__name__}: {exc}"}, None
            try:
                body = json.dumps(doc).encode()
                if ok:
                    query.reply(reply_key or str(query.key_expr), body)
                else:
                    query.reply_err(body)
            except Exception as exc:
                log.error("dictionary reply failed: %s", exc)
            del query  # finalises the query

    def handle(self, key: str, payload: bytes, attachment: bytes) -> tuple[bool, dict[str, Any], str | None]:
        """(ok, JSON reply, reply key or None for the query's own key) of one query."""
        k, host = self.keys, self.host
        parts = k.dictionary_path(key)
        op = parts[0] if parts else "list"
        if op in ("list", "**", "*") or any("*" in p for p in parts):
            return True, {"ok": True, **host.describe()}, k.dictionary_op("list") if "*" in key else key
        if op == "add":
            name = "/".join(parts[1:])
            if not name or name in RESERVED:
                raise ValueError("add: expected fp/<rig>/dictionary/add/<name> with a plain name")
            entry = host.add(spec_from_request(name, payload, attachment))
            return True, {"ok": True, "added": entry}, None
        if op == "remove":
            name = "/".join(parts[1:])
            try:
                host.remove(name)
            except KeyError:
                return False, {"ok": False, "error": f"remove: no entry {name!r}; have {host.names}"}, None
            return True, {"ok": True, "removed": name, "entries": host.names}, None
        if op == "set":
            try:
                params = json.loads(payload.decode() or "{}")
            except (UnicodeDecodeError, json.JSONDecodeError):
                raise ValueError("set: expected a JSON object of parameters") from None
            try:
                host.set_params(params)  # transactional: on failure the host is as it was
            except (ValueError, MemoryError) as exc:
                error = str(exc) if isinstance(exc, ValueError) else f"set: refused, out of memory: {exc}"
                return False, {"ok": False, "error": error, "params": host.describe()["params"]}, None
            return True, {"ok": True, **host.describe()}, None
        name = "/".join(parts)
        entry = host.entry(name)
        if entry is None:
            return False, {"ok": False, "error": f"no entry {name!r}; have {host.names}"}, None
        return True, {"ok": True, "entry": entry}, None


def _bytes(z: Any) -> bytes:
    return z.to_bytes() if z is not None else b""


def dictionary_request(
    session: zenoh.Session,
    rig: str,
    op: str = "list",
    name: str | None = None,
    payload: bytes | dict[str, Any] | None = None,
    options: dict[str, Any] | None = None,
    timeout: float = 30.0,
) -> dict[str, Any]:
    """Client of the dictionary queryable: ``op`` is list, get, add, remove or set. Returns the JSON reply
    (``{"ok": False, "error": ...}`` on refusal; ``{"ok": False, "error": "no reply"}`` on timeout)."""
    key = Keys(rig).dictionary_op(op, name)
    body = json.dumps(payload).encode() if isinstance(payload, dict) else payload
    att = json.dumps(options).encode() if options else None
    deadline = time.monotonic() + timeout
    while True:  # no reply at all: the link or the queryable's declaration may not be up yet; ask again
        left = max(deadline - time.monotonic(), 0.1)
        for reply in session.get(key, payload=body, attachment=att, timeout=left):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
            return json.loads(reply.err.payload.to_bytes())
        if time.monotonic() >= deadline:
            return {"ok": False, "error": "no reply (is a processor running on this rig?)"}
        time.sleep(0.2)
