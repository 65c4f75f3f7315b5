"""Recordings to Rerun (`fp view`) and to a static PNG (`fp figure`) (docs/design.md §2, §7 stack notes).

`fp view REC.mcap --rrd out.rrd` decodes every FPWIRE01 message of a recording (``services.recorder``)
and logs it to Rerun natively (Rerun shows custom MCAP encodings only as blobs), on the timelines
``frame`` (sequence) and ``acquisition_time`` (the frames' source clock):

* ``world/gamma/<fingerprint>``: the γ-volume (``Volume3D``, float16; metres, z down);
* ``world/detections/<fingerprint>``: detections (``Points3D``, radius = max Cramér–Rao precision);
* ``world/tracks/<id>``: the positions of each track so far (``LineStrips3D``);
* ``sections/<fingerprint>/{xz,yz}/{confocal,gamma}``: the confocal image in dB (grey, −30…0 dB) and γ
  (``DepthImage`` with a colour map, values under ``threshold``·max left out) through the detection;
* ``series/<fingerprint>/{c_gamma,log10_pfa}`` and ``series/latency_ms/{median,p95}`` (``Scalars``).

A default blueprint (sections, 3D view, time series) is stored in the ``.rrd``; open it with
`rerun FILE.rrd`. `fp view --live` logs the bus as it runs (`live_to_rrd`).

`fp view REC.mcap --serve` / `fp view --live --serve` serve the Rerun web viewer **on 127.0.0.1 only**
(`serve_loopback`). rerun-sdk's Python helpers cannot do that: ``rr.serve_web_viewer`` and ``rr.serve_grpc``
take no bind address and listen on 0.0.0.0 (checked in 0.41; no environment variable changes it), so
anyone on the network could read the recording. The ``rerun`` executable shipped in the same wheel
(``rerun_cli``) can: ``rerun --serve-web --bind 127.0.0.1`` binds both its HTTP server (the web viewer's
page and Wasm, ``--port``) and its gRPC proxy (the data, ``--grpc-port``) to loopback. `serve_loopback`
runs it as a child process, checks the child's listening sockets (``/proc``) and refuses to go on if
one is not loopback. The bind address is not an option on purpose: to look from another machine,
forward the two ports over SSH (``ssh -L 9090:127.0.0.1:9090 -L 9876:127.0.0.1:9876 HOST``).

`fp figure REC.mcap --frame N --png out.png`: ``services.figures.targets_over_confocal`` of frame N's
γ-maps (all fingerprints, or ``--fingerprint``) over its confocal image, in the paper's Figure 2 layout:
confocal image in dB, γ in dB over it, scale bars, each sphere's outline from its fingerprint's
``diameter_m`` state, C_γ per target.
"""

from __future__ import annotations

import argparse
import ctypes
import importlib.util
import ipaddress
import logging
import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any
from urllib.parse import quote

import numpy as np

from services.messages import (
    ConfocalImage,
    Detection,
    Detections,
    GammaMap,
    Grid,
    Message,
    RFFrame,
    Status,
    Tracks,
)
from services.recorder import MESSAGE_ENCODING, iter_raw
from services.wire import WireError, decode

__all__ = [
    "add_figure_parser",
    "add_view_parser",
    "iter_messages",
    "listening_addresses",
    "live_to_rrd",
    "make_sample_recording",
    "run_figure",
    "run_view",
    "serve_loopback",
    "to_figure",
    "to_rrd",
]

log = logging.getLogger("fp.viewer")

DB_FLOOR = -30.0
LOOPBACK = "127.0.0.1"
DEFAULT_WEB_PORT = 9090
DEFAULT_GRPC_PORT = 9876


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


def _db(image: np.ndarray, scale: str = "linear") -> np.ndarray:
    """Confocal image in dB relative to its maximum (already dB: shifted so the max is 0)."""
    if scale == "db":
        return image - float(np.max(image))
    return 10 * np.log10(image / max(float(np.max(image)), 1e-30) + 1e-12)


def _nearest(axis: np.ndarray, v: float) -> int:
    return int(np.argmin(np.abs(axis - v)))


def _sections(grid: Grid, vol: np.ndarray, at: np.ndarray) -> dict[str, np.ndarray]:
    """Sections through ``at`` (rows = z): ``xz`` (2D and 3D) and ``yz`` (3D)."""
    if grid.y is None:
        return {"xz": vol.T}
    i, j = _nearest(grid.x, float(at[0])), _nearest(grid.y, float(at[1]))
    return {"xz": vol[:, j, :].T, "yz": vol[i, :, :].T}


def _peak(grid: Grid, gamma: np.ndarray) -> np.ndarray:
    idx = np.unravel_index(int(np.argmax(gamma)), gamma.shape)
    axes = (grid.x, grid.z) if grid.y is None else (grid.x, grid.y, grid.z)
    p = [float(a[k]) for a, k in zip(axes, idx, strict=True)]
    return np.array([p[0], 0.0, p[1]] if grid.y is None else p)


@dataclass
class _Frame:
    gamma: dict[str, GammaMap] = field(default_factory=dict)
    image: ConfocalImage | None = None
    detections: dict[str, Detection] | None = None
    done: set[str] = field(default_factory=set)


@dataclass
class _Converter:
    """Streams decoded messages into a Rerun recording stream."""

    rec: Any
    threshold: float = 0.6
    frames: dict[int, _Frame] = field(default_factory=dict)
    fingerprints: list[str] = field(default_factory=list)
    track_paths: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)
    logged: Counter[str] = field(default_factory=Counter)
    frame_indices: set[int] = field(default_factory=set)
    has_3d: bool = False

    def _time(self, frame_index: int, timestamp: float) -> None:
        self.rec.set_time("frame", sequence=frame_index)
        if timestamp > 1e8:  # an epoch time
            self.rec.set_time("acquisition_time", timestamp=timestamp)
        else:
            self.rec.set_time("acquisition_time", duration=timestamp)
        self.frame_indices.add(frame_index)

    def _log(self, path: str, archetype: Any) -> None:
        self.rec.log(path, archetype)
        self.logged[path] += 1

    def feed(self, msg: Message) -> None:
        import rerun as rr

        if isinstance(msg, Status):
            self.rec.reset_time()
            self.rec.set_time("frame", sequence=max(msg.frames_processed - 1, 0))
            for stat in ("median", "p95"):
                v = getattr(msg.latency_ms, stat)
                if v is not None:
                    self._log(f"series/latency_ms/{stat}", rr.Scalars(v))
            return
        if not isinstance(msg, (GammaMap, ConfocalImage, Detections, Tracks)):
            return
        self._time(msg.frame_index, msg.timestamp)
        fr = self.frames.setdefault(msg.frame_index, _Frame())
        if isinstance(msg, GammaMap):
            if msg.fingerprint not in self.fingerprints:
                self.fingerprints.append(msg.fingerprint)
            fr.gamma[msg.fingerprint] = msg
            self._volume(msg)
        elif isinstance(msg, ConfocalImage):
            fr.image = msg
        elif isinstance(msg, Detections):
            fr.detections = {d.fingerprint: d for d in msg.detections}
            for d in msg.detections:
                self._log(f"world/detections/{d.fingerprint}",
                          rr.Points3D([d.position_m], radii=[max(d.precision_m)],
                                      labels=[f"{d.fingerprint}: C_γ {d.contrast_c_gamma:.1f}"]))
                self._log(f"series/{d.fingerprint}/c_gamma", rr.Scalars(d.contrast_c_gamma))
                self._log(f"series/{d.fingerprint}/log10_pfa", rr.Scalars(math.log10(max(d.pfa, 1e-300))))
        else:
            for t in msg.tracks:
                pts = self.track_paths.setdefault(t.id, [])
                pts.append(t.position_m)
                self._log(f"world/tracks/{t.id}", rr.LineStrips3D([pts], labels=[f"track {t.id} {t.fingerprint}"]))
        self._sections(msg.frame_index, final=False)
        for old in [k for k in self.frames if k < msg.frame_index - 8]:
            self._sections(old, final=True)

    def _volume(self, g: GammaMap) -> None:
        import rerun as rr

        grid = g.grid
        if grid.y is None:
            return
        self.has_3d = True
        step = [float(np.mean(np.diff(a))) if a.size > 1 else 1e-4 for a in (grid.x, grid.y, grid.z)]
        corner = [float(a[0]) - s / 2 for a, s in zip((grid.x, grid.y, grid.z), step, strict=True)]
        values = np.ascontiguousarray(g.gamma.transpose(2, 1, 0)).astype(np.float16)
        self._log(f"world/gamma/{g.fingerprint}",
                  rr.Volume3D(values, voxel_size=step, translation=corner,
                              value_range=(self.threshold * float(np.max(g.gamma)), float(np.max(g.gamma))),
                              colormap="inferno"))

    def _sections(self, frame_index: int, final: bool) -> None:
        """Log the sections of a frame's γ-maps once its image and detections are in (or at the end)."""
        import rerun as rr

        fr = self.frames.get(frame_index)
        if fr is None:
            return
        if not final and (fr.image is None or fr.detections is None):
            return
        for name, g in fr.gamma.items():
            if name in fr.done:
                continue
            det = (fr.detections or {}).get(name)
            at = np.array(det.position_m) if det is not None else _peak(g.grid, g.gamma)
            self._time(frame_index, g.timestamp)
            gmax = float(np.max(g.gamma))
            gam = _sections(g.grid, g.gamma, at)
            conf = _sections(fr.image.grid, _db(fr.image.image, fr.image.scale), at) if fr.image is not None else {}
            for plane, gimg in gam.items():
                base = f"sections/{name}/{plane}"
                if plane in conf and conf[plane].shape == gimg.shape:
                    grey = np.clip((conf[plane] - DB_FLOOR) / -DB_FLOOR * 255, 0, 255).astype(np.uint8)
                    self._log(f"{base}/confocal", rr.Image(grey, draw_order=0.0))
                shown = np.where(gimg >= self.threshold * gmax, gimg, 0).astype(np.float32)
                self._log(f"{base}/gamma", rr.DepthImage(shown, meter=1.0, colormap="inferno",
                                                        depth_range=(self.threshold * gmax, gmax), draw_order=1.0))
            fr.done.add(name)
        if final:
            del self.frames[frame_index]

    def finish(self) -> None:
        for k in sorted(self.frames):
            self._sections(k, final=True)

    def blueprint(self) -> Any:
        import rerun.blueprint as rrb

        planes = ("xz", "yz") if self.has_3d else ("xz",)
        sections = [rrb.Spatial2DView(origin=f"sections/{fp}/{p}", name=f"{fp} {p}: γ over confocal (dB)")
                    for fp in self.fingerprints for p in planes]
        series = [rrb.TimeSeriesView(origin="series", contents=f"series/*/{k}/**", name=name)
                  for k, name in (("c_gamma", "C_γ"), ("log10_pfa", "log10 PFA"))]
        series.append(rrb.TimeSeriesView(origin="series/latency_ms", name="latency (ms)"))
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Grid(*sections, name="sections") if sections else rrb.Spatial2DView(origin="sections"),
                rrb.Vertical(rrb.Spatial3DView(origin="world", name="3D"), rrb.Vertical(*series)),
                column_shares=[2, 1],
            ),
            collapse_panels=False,
        )


def to_rrd(recording: str | Path, rrd: str | Path, *, threshold: float = 0.6) -> dict[str, Any]:
    """Convert an MCAP recording to a Rerun ``.rrd`` (with a default blueprint); returns the frame
    indices logged, the fingerprints and the number of logs per entity."""
    import rerun as rr

    recording, rrd = Path(recording), Path(rrd)
    if not recording.is_file():
        raise FileNotFoundError(f"{recording}: no such file")
    rec = rr.RecordingStream("fingerprint", recording_id=recording.stem)
    rec.save(rrd)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)
    conv = _Converter(rec, threshold=threshold)
    report: dict[str, Any] = {}
    n = 0
    for _key, msg in iter_messages(recording, report):
        conv.feed(msg)
        n += 1
    conv.finish()
    rec.send_blueprint(conv.blueprint(), make_active=True, make_default=True)
    rec.flush()
    rec.disconnect()
    return {"rrd": str(rrd), "messages": n, "undecodable": report.get("undecodable", 0),
            "error": report.get("error"), "frames": sorted(conv.frame_indices),
            "fingerprints": list(conv.fingerprints), "logged": dict(conv.logged)}


def _diameter(*states: dict[str, Any] | None) -> float | None:
    """The first positive ``diameter_m`` of the given states / truth entries, m."""
    for st in states:
        d = (st or {}).get("diameter_m")
        if isinstance(d, (int, float)) and d > 0:
            return float(d)
    return None


def _pfa_text(pfa: float) -> str:
    return "PFA < 1e-300" if pfa == 0 else f"PFA = {pfa:.1e}"  # 0: exp(−πC²/4) underflowed


def to_figure(recording: str | Path, frame: int, png: str | Path, *, fingerprint: str | None = None,
              threshold: float = 0.6) -> dict[str, Any]:
    """PNG of the frame's γ-maps (every fingerprint, or only ``fingerprint``) over its confocal image, in
    the layout of the paper's Figure 2 (``services.figures.targets_over_confocal``): sections through each
    detection (γ's peak when none), the sphere's outline when its diameter is known (the fingerprint's
    ``diameter_m`` state, else the ground truth's), the truth when the frame's RF message carries it."""
    from services.figures import Target, targets_over_confocal

    gammas: dict[str, GammaMap] = {}
    image: ConfocalImage | None = None
    dets: list[Detection] = []
    truth: dict[str, dict[str, Any]] = {}
    for _key, msg in iter_messages(recording):
        if getattr(msg, "frame_index", None) != frame:
            continue
        if isinstance(msg, GammaMap) and fingerprint in (None, msg.fingerprint):
            gammas.setdefault(msg.fingerprint, msg)
        elif isinstance(msg, ConfocalImage) and image is None:
            image = msg
        elif isinstance(msg, Detections):
            dets = msg.detections
        elif isinstance(msg, RFFrame):
            for t in (msg.truth or {}).get("targets") or []:
                if isinstance(t, dict) and isinstance(t.get("name"), str):
                    truth[t["name"]] = t
    if not gammas or image is None:
        raise ValueError(f"{recording}: frame {frame} has no γ-map{f' of {fingerprint}' if fingerprint else ''} "
                         f"and confocal image")
    grids = {g.grid.to_grid().shape for g in gammas.values()} | {image.grid.to_grid().shape}
    if len(grids) > 1:
        raise ValueError(f"{recording}: frame {frame}: γ-maps and confocal image on different grids {grids}")
    targets: list[Target] = []
    summary: list[str] = []
    for name, g in gammas.items():
        det = next((d for d in dets if d.fingerprint == name), None)
        found = np.array(det.position_m) if det is not None else _peak(g.grid, g.gamma)
        t = truth.get(name, {})
        pos = t.get("position_m")
        targets.append(Target(name, g.gamma, found, _diameter(det.state if det else None, g.state, t),
                              np.asarray(pos, float) if isinstance(pos, list) and len(pos) == 3 else None,
                              det.contrast_c_gamma if det is not None else None))
        summary.append(f"{name}: C_γ = {det.contrast_c_gamma:.1f}, {_pfa_text(det.pfa)}" if det is not None
                       else f"{name}: no detection (γ's peak)")
    confocal = image.image if image.scale == "linear" else (10 ** (image.image / 10)).astype(np.float32)
    title = f"frame {frame}: γ over the confocal image\n" + "; ".join(summary)
    targets_over_confocal(png, gammas[next(iter(gammas))].grid.to_grid(), confocal, targets, title=title,
                          threshold=threshold)
    return {"png": str(png), "frame": frame, "fingerprint": targets[0].name,
            "fingerprints": [t.name for t in targets], "detection": targets[0].found.tolist(),
            "diameters_m": {t.name: t.diameter for t in targets}}


def make_sample_recording(path: str | Path, n_frames: int = 4, spacing: float = 0.5e-3,
                          drop: tuple[str, ...] = ("rf",)) -> dict[str, int]:
    """Record the quick sinking-sphere scenario with the project's pipeline (demo region of interest,
    grid step ``spacing``) and copy it to ``path`` without the ``drop`` topics (RF frames: ~9 MB each).
    Returns the message count per key."""
    from mcap.writer import CompressionType, Writer

    from fpcore import Grid as CoreGrid
    from services.processor import ProcessorConfig
    from services.publisher import run_pipeline

    grid = CoreGrid.regular((-11e-3, 11e-3), (20e-3, 31e-3), spacing, y_range=(-5e-3, 5e-3))
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_pipeline("sinking-sphere", rig="demo", out_dir=tmp, n_frames=n_frames,
                               processor=ProcessorConfig(rig="demo", queue="fifo", grid=grid))
        kept: Counter[str] = Counter()
        with open(path, "wb") as f:
            w = Writer(f, compression=CompressionType.NONE)
            w.start(profile="", library="fingerprint services.viewer (sample)")
            w.add_metadata("fingerprint", {"wire": "FPWIRE01", "message_encoding": MESSAGE_ENCODING,
                                           "sample": f"sinking-sphere quick, {n_frames} frames, grid step "
                                                     f"{spacing * 1e3:g} mm, without {', '.join(drop)}"})
            schemas: dict[int, int] = {}
            channels: dict[int, int] = {}
            for src in summary["recording"]["files"]:
                for schema, channel, msg in iter_raw(src):
                    if channel.topic.rsplit("/", 1)[-1] in drop:
                        continue
                    if schema is not None and schema.id not in schemas:
                        schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                    if channel.id not in channels:
                        channels[channel.id] = w.register_channel(
                            channel.topic, channel.message_encoding,
                            schemas.get(channel.schema_id, 0), dict(channel.metadata))
                    w.add_message(channels[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
                    kept[channel.topic] += 1
            w.finish()
    return dict(kept)


def live_to_rrd(bus: Any, rig: str, rrd: str | Path, *, duration: float | None = None,
                stop: Any = None, threshold: float = 0.6, stats: dict[str, int] | None = None,
                grpc_url: str | None = None) -> dict[str, Any]:
    """Subscribe to the processor's outputs on ``fp/<rig>/{gamma,image,detections,tracks,status}`` and
    log them to a Rerun ``.rrd`` as they arrive (same entities and blueprint as `to_rrd`), until
    `duration` seconds pass or `stop` (a threading.Event; default: SIGINT/SIGTERM) is set. Announces
    itself with the liveliness token ``fp/<rig>/alive/viewer``. Raw RF frames are not subscribed.
    `stats` (optional) is updated live with the counts of messages logged, undecodable and dropped.
    With ``grpc_url`` (a Rerun gRPC proxy, e.g. `serve_loopback`'s) the same stream also goes there, and
    the blueprint is re-sent whenever a new fingerprint appears."""
    import queue
    import time

    import rerun as rr

    from services.bus import open_session, sample_bytes, stop_on_signals
    from services.wire import keys

    rrd = Path(rrd)
    rec = rr.RecordingStream("fingerprint", recording_id=f"live-{rig}")
    if grpc_url:
        rec.set_sinks(rr.FileSink(str(rrd)), rr.GrpcSink(grpc_url))
    else:
        rec.save(rrd)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)
    conv = _Converter(rec, threshold=threshold)
    layout: tuple[tuple[str, ...], bool] = ((), False)
    inbox: queue.Queue[bytes] = queue.Queue(maxsize=512)
    stats = stats if stats is not None else {}
    stats.update(messages=0, undecodable=0, dropped=0)
    stop = stop if stop is not None else stop_on_signals()
    k = keys(rig)

    def on_sample(sample: Any) -> None:
        try:
            inbox.put_nowait(sample_bytes(sample))
        except queue.Full:
            stats["dropped"] += 1

    def feed(payload: bytes) -> None:
        nonlocal layout
        try:
            conv.feed(decode(payload))
            stats["messages"] += 1
        except WireError:
            stats["undecodable"] += 1
        if grpc_url and (tuple(conv.fingerprints), conv.has_3d) != layout:
            layout = (tuple(conv.fingerprints), conv.has_3d)
            rec.send_blueprint(conv.blueprint(), make_active=True, make_default=True)

    with open_session(bus) as session:
        subs = [session.declare_subscriber(key, on_sample) for key in (k.gamma, k.image, k.detections, k.tracks,
                                                                       k.status)]
        token = session.liveliness().declare_token(f"fp/{rig}/alive/viewer")
        t_end = time.monotonic() + duration if duration else math.inf
        try:
            while not stop.is_set() and time.monotonic() < t_end:
                try:
                    feed(inbox.get(timeout=0.1))
                except queue.Empty:
                    continue
        finally:
            for sub in subs:
                sub.undeclare()
            token.undeclare()
    while not inbox.empty():
        feed(inbox.get_nowait())
    conv.finish()
    rec.send_blueprint(conv.blueprint(), make_active=True, make_default=True)
    rec.flush()
    rec.disconnect()
    return {"rrd": str(rrd), **stats, "frames": sorted(conv.frame_indices), "fingerprints": list(conv.fingerprints)}


def rerun_executable() -> Path:
    """The ``rerun`` executable of the installed rerun-sdk wheel (``RERUN_CLI_PATH`` overrides it, as for
    ``python -m rerun_cli``)."""
    override = os.environ.get("RERUN_CLI_PATH")
    if override:
        path = Path(override)
    else:
        spec = importlib.util.find_spec("rerun_cli")
        if spec is None or not spec.submodule_search_locations:
            raise FileNotFoundError("rerun_cli: not installed; reinstall rerun-sdk (it ships the rerun executable)")
        path = Path(next(iter(spec.submodule_search_locations))) / ("rerun.exe" if sys.platform == "win32"
                                                                     else "rerun")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no rerun executable; reinstall rerun-sdk or set RERUN_CLI_PATH")
    return path


def _proc_net_address(hex_addr: str) -> str:
    """``0100007F`` (IPv4) or 32 hex digits (IPv6) of /proc/net/tcp*, each 32-bit word in host order."""
    raw = bytes.fromhex(hex_addr)
    words = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4)) if sys.byteorder == "little" else raw
    return str(ipaddress.ip_address(words))


def listening_addresses(pid: int | None = None, port: int | None = None) -> list[tuple[str, int]] | None:
    """(IP, port) of the TCP sockets in LISTEN state, read from ``/proc/net/tcp`` and ``tcp6``: those of
    process ``pid`` (all the network namespace's when None), on ``port`` only if given. None where
    ``/proc`` does not exist (not Linux)."""
    if not Path("/proc/net/tcp").exists():
        return None
    inodes: set[str] | None = None
    if pid is not None:
        inodes = set()
        try:
            fds = list(Path(f"/proc/{pid}/fd").iterdir())
        except FileNotFoundError:  # the process is gone
            return []
        for fd in fds:
            try:
                target = os.readlink(fd)
            except OSError:  # closed meanwhile
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    out: list[tuple[str, int]] = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not Path(table).exists():
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            cols = line.split()
            if len(cols) < 10 or cols[3] != "0A":  # 0A: TCP_LISTEN
                continue
            addr, port_hex = cols[1].rsplit(":", 1)
            p = int(port_hex, 16)
            if (port is None or p == port) and (inodes is None or cols[9] in inodes):
                out.append((_proc_net_address(addr), p))
    return out


def _check_port(option: str, port: int) -> None:
    if not 1 <= port <= 65535:
        raise ValueError(f"{option}: expected a TCP port 1…65535, got {port}")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((LOOPBACK, port))
        except OSError as exc:
            raise ValueError(f"{option}: {LOOPBACK}:{port} is not free ({exc.strerror}); "
                             f"give another port") from None


def _check_ports(port: int, grpc_port: int) -> None:
    """ValueError naming the option unless both ports are valid, distinct and free on 127.0.0.1."""
    if port == grpc_port:
        raise ValueError(f"--port and --grpc-port: expected two different ports, got {port} twice")
    _check_port("--port", port)
    _check_port("--grpc-port", grpc_port)


def _accepts(port: int) -> bool:
    try:
        with socket.create_connection((LOOPBACK, port), timeout=0.5):
            return True
    except OSError:
        return False


def _listening(pid: int, ports: set[int]) -> bool:
    """Whether process ``pid`` listens on all ``ports`` (its own sockets, from /proc; elsewhere: whether
    the ports accept connections on 127.0.0.1)."""
    own = listening_addresses(pid)
    if own is None:
        return all(_accepts(p) for p in ports)
    return ports <= {p for _, p in own}


@dataclass
class LoopbackViewer:
    """A running ``rerun --serve-web --bind 127.0.0.1`` child: web viewer on ``web_port``, gRPC proxy
    (recording data) on ``grpc_port``. Stop it with `stop` (or use it as a context manager)."""

    proc: subprocess.Popen[bytes]
    web_port: int
    grpc_port: int
    log: IO[bytes]

    @property
    def grpc_url(self) -> str:
        """The proxy's URL, for ``rr.GrpcSink`` or ``rerun --connect``."""
        return f"rerun+http://{LOOPBACK}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """The page to open in a browser: the web viewer, connected to the proxy."""
        return f"http://{LOOPBACK}:{self.web_port}/?url={quote(self.grpc_url, safe='')}"

    def log_tail(self, n: int = 1500) -> str:
        """The end of the child's output, without terminal colours."""
        self.log.flush()
        self.log.seek(0)
        text = self.log.read().decode(errors="replace")
        return re.sub(r"\x1b\[[0-9;]*m", "", text)[-n:].strip()

    def stop(self, timeout: float = 10.0) -> int:
        """Terminate the child (SIGTERM, then SIGKILL after ``timeout`` s); returns its exit code."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        self.log.close()
        return int(self.proc.returncode)

    def __enter__(self) -> LoopbackViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _die_with_parent() -> None:
    """In the rerun child (Linux): receive SIGTERM when the parent dies, even by SIGKILL, so a killed
    `fp view --serve` never leaves a server holding its ports (prctl PR_SET_PDEATHSIG)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass  # not Linux: the parent's own cleanup stops the child


def serve_loopback(rrd: str | Path | None = None, *, port: int = DEFAULT_WEB_PORT,
                   grpc_port: int = DEFAULT_GRPC_PORT, server_memory_limit: str = "1GiB",
                   timeout: float = 30.0) -> LoopbackViewer:
    """Start the Rerun web viewer and its gRPC proxy bound to 127.0.0.1 only, serving ``rrd`` (or, without
    one, whatever an SDK logs to `LoopbackViewer.grpc_url`). Returns once both ports accept connections
    and the child's listening sockets are checked to be loopback (Linux); raises ValueError for a bad or
    busy port, ChildProcessError when rerun exits or listens elsewhere, TimeoutError after ``timeout`` s.
    The child is stopped if the calling *thread* ends (PR_SET_PDEATHSIG): call it from a thread that
    lives as long as the viewer should."""
    _check_ports(port, grpc_port)
    if rrd is not None and not Path(rrd).is_file():
        raise FileNotFoundError(f"{rrd}: no such .rrd file")
    cmd = [str(rerun_executable()), "--serve-web", "--bind", LOOPBACK, "--web-viewer-port", str(port),
           "--port", str(grpc_port), "--server-memory-limit", server_memory_limit]
    if rrd is not None:
        cmd.append(str(Path(rrd).resolve()))
    log_file = tempfile.TemporaryFile()
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log_file, stderr=subprocess.STDOUT,
                            env={**os.environ, "NO_COLOR": "1"}, preexec_fn=_die_with_parent)
    viewer = LoopbackViewer(proc, port, grpc_port, log_file)
    deadline = time.monotonic() + timeout
    while not _listening(proc.pid, {port, grpc_port}):
        if proc.poll() is not None:
            tail = viewer.log_tail()
            viewer.stop()
            raise ChildProcessError(f"rerun --serve-web exited with code {proc.returncode}: {tail}")
        if time.monotonic() > deadline:
            viewer.stop()
            raise TimeoutError(f"rerun --serve-web: ports {port} (--port) and {grpc_port} (--grpc-port) not "
                               f"open on {LOOPBACK} after {timeout:g} s")
        time.sleep(0.05)
    listening = listening_addresses(proc.pid)
    exposed = [a for a in listening or [] if not ipaddress.ip_address(a[0]).is_loopback]
    if listening is None:
        log.warning("cannot list the sockets of rerun (pid %d) here: loopback binding not checked", proc.pid)
    if exposed:
        viewer.stop()
        raise ChildProcessError(f"rerun --serve-web listens on {exposed}, not only on {LOOPBACK}; stopped it")
    log.info("rerun web viewer on %s (pid %d), listening on %s", viewer.url, proc.pid, listening)
    return viewer


def _serve_until_stopped(viewer: LoopbackViewer, stop: Any, duration: float | None) -> None:
    """Block until ``stop`` is set, ``duration`` s pass or the viewer's process ends (an error)."""
    deadline = time.monotonic() + duration if duration else math.inf
    while not stop.wait(0.2) and time.monotonic() < deadline:
        if viewer.proc.poll() is not None:
            if stop.wait(0.5):  # Ctrl-C in a terminal reaches the child too; not an error
                return
            raise ChildProcessError(f"rerun --serve-web exited with code {viewer.proc.returncode}: "
                                    f"{viewer.log_tail()}")


def run_view(args: argparse.Namespace) -> int:
    """`fp view`: convert a recording to ``.rrd``, or log the live bus (``--live``) to one; with
    ``--serve``, also serve it in the Rerun web viewer on 127.0.0.1 until Ctrl-C/SIGTERM."""
    from services.bus import stop_on_signals

    if args.duration is not None and args.duration <= 0:
        raise ValueError(f"--duration: expected seconds > 0, got {args.duration:g}")
    if args.serve:
        _check_ports(args.port, args.grpc_port)  # before a conversion that may take a while
    if args.live:
        from services.bus import bus_from_args

        rrd = Path(args.rrd or f"live-{args.rig}.rrd")
        stop = stop_on_signals()
        viewer = serve_loopback(port=args.port, grpc_port=args.grpc_port) if args.serve else None
        try:
            if viewer is not None:
                print(f"Rerun web viewer (loopback only): {viewer.url}  (Ctrl-C stops)", flush=True)
            out = live_to_rrd(bus_from_args(args), args.rig, rrd, duration=args.duration, stop=stop,
                              threshold=args.threshold, grpc_url=viewer.grpc_url if viewer else None)
        finally:
            if viewer is not None:
                viewer.stop()
        print(f"{out['rrd']}: {len(out['frames'])} frames, {out['messages']} messages "
              f"({out['undecodable']} undecodable, {out['dropped']} dropped)")
        return 0
    if not args.recording:
        raise ValueError("recording: give an MCAP file, or --live to follow the bus")
    rrd = Path(args.rrd) if args.rrd else Path(args.recording).with_suffix(".rrd")
    out = to_rrd(args.recording, rrd, threshold=args.threshold)
    print(f"{out['rrd']}: {len(out['frames'])} frames, {out['messages']} messages "
          f"({out['undecodable']} undecodable), fingerprints {', '.join(out['fingerprints']) or 'none'}",
          flush=True)
    if args.serve:
        stop = stop_on_signals()
        with serve_loopback(rrd, port=args.port, grpc_port=args.grpc_port) as viewer:
            print(f"Rerun web viewer (loopback only): {viewer.url}  (Ctrl-C stops)", flush=True)
            _serve_until_stopped(viewer, stop, args.duration)
    return 0


def run_figure(args: argparse.Namespace) -> int:
    """`fp figure`: PNG of γ over the confocal image for one frame."""
    if not 0 < args.threshold < 1:
        raise ValueError(f"--threshold: expected a fraction of γ's maximum in (0, 1), got {args.threshold:g}")
    out = to_figure(args.recording, args.frame, args.png, fingerprint=args.fingerprint, threshold=args.threshold)
    print(f"{out['png']}: frame {out['frame']}, {', '.join(out['fingerprints'])}")
    return 0


def add_view_parser(sub: Any) -> argparse.ArgumentParser:
    """Register `fp view`."""
    p = sub.add_parser("view", help="convert an MCAP recording to a Rerun .rrd (and serve it: --serve)",
                       description="Log a recording's γ-maps, confocal images, detections, tracks and time "
                                   "series to Rerun natively, with a default blueprint; --serve shows it in "
                                   "the Rerun web viewer on 127.0.0.1.")
    p.add_argument("recording", nargs="?", help="MCAP file written by `fp record`/`fp demo`")
    p.add_argument("--rrd", default=None, help="output .rrd (default: the recording with .rrd, or live-<rig>.rrd)")
    p.add_argument("--live", action="store_true", help="follow the zenoh bus instead of a file (Ctrl-C stops)")
    p.add_argument("--rig", default="demo", help="rig to follow with --live (default demo)")
    p.add_argument("--duration", type=float, default=None,
                   help="with --live or --serve: stop after this many seconds (default: at Ctrl-C/SIGTERM)")
    p.add_argument("--threshold", type=float, default=0.6, help="show γ ≥ threshold·max (default 0.6)")
    g = p.add_argument_group("web viewer (--serve)",
                             "Bound to 127.0.0.1 only, not configurable: the recording must not be readable "
                             "from the network. From another machine: ssh -L PORT:127.0.0.1:PORT for both ports.")
    g.add_argument("--serve", action="store_true",
                   help="serve the .rrd (or the live stream) in the Rerun web viewer on 127.0.0.1 and print the URL")
    g.add_argument("--port", type=int, default=DEFAULT_WEB_PORT,
                   help=f"HTTP port of the web viewer page (default {DEFAULT_WEB_PORT})")
    g.add_argument("--grpc-port", type=int, default=DEFAULT_GRPC_PORT,
                   help=f"port of the gRPC proxy the page reads the data from (default {DEFAULT_GRPC_PORT})")
    from services.bus import DEFAULT_HUB, EPHEMERAL, add_bus_arguments

    add_bus_arguments(p, listen=EPHEMERAL, connect=DEFAULT_HUB)
    p.set_defaults(func=run_view)
    return p


def add_figure_parser(sub: Any) -> argparse.ArgumentParser:
    """Register `fp figure`."""
    p = sub.add_parser("figure", help="PNG of γ over the confocal image for one recorded frame",
                       description="Sections of one frame's confocal image (dB) and of its γ-maps (dB) over "
                                   "it, as in the paper's Figure 2: scale bars, detections, sphere outlines "
                                   "when the fingerprint's diameter is known.")
    p.add_argument("recording", help="MCAP file written by `fp record`/`fp demo`")
    p.add_argument("--frame", type=int, required=True, help="frame index")
    p.add_argument("--png", required=True, help="output PNG")
    p.add_argument("--fingerprint", default=None, help="only this fingerprint's γ-map (default: all of the frame's)")
    p.add_argument("--threshold", type=float, default=0.6,
                   help="colour γ ≥ threshold·max, i.e. from 20·log10(threshold) dB to 0 dB (default 0.6: −4.4 dB)")
    p.set_defaults(func=run_figure)
    return p
