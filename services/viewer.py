"""Recordings to Rerun (`fp view`) and to a static PNG (`fp figure`) (DESIGN.md §2, §7 stack notes).

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

`fp figure REC.mcap --frame N --png out.png`: ``services.figures.gamma_over_confocal`` of the first
γ-map of frame N over that frame's confocal image, marker at its detection.
"""

from __future__ import annotations

import argparse
import logging
import math
import tempfile
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.messages import ConfocalImage, Detection, Detections, GammaMap, Grid, Message, Status, Tracks
from services.recorder import MESSAGE_ENCODING, iter_raw
from services.wire import WireError, decode

__all__ = [
    "add_figure_parser",
    "add_view_parser",
    "iter_messages",
    "make_sample_recording",
    "run_figure",
    "run_view",
    "to_figure",
    "to_rrd",
]

log = logging.getLogger("fp.viewer")

DB_FLOOR = -30.0


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


def to_figure(recording: str | Path, frame: int, png: str | Path, *, fingerprint: str | None = None,
              threshold: float = 0.6) -> dict[str, Any]:
    """PNG of the first γ-map of ``frame`` (or that of ``fingerprint``) over the frame's confocal image,
    marker at its detection (γ's peak when none)."""
    from services.figures import gamma_over_confocal

    gamma: GammaMap | None = None
    image: ConfocalImage | None = None
    det: Detection | None = None
    dets: list[Detection] = []
    for _key, msg in iter_messages(recording):
        if getattr(msg, "frame_index", None) != frame:
            continue
        if isinstance(msg, GammaMap) and gamma is None and fingerprint in (None, msg.fingerprint):
            gamma = msg
        elif isinstance(msg, ConfocalImage) and image is None:
            image = msg
        elif isinstance(msg, Detections):
            dets = msg.detections
    if gamma is None or image is None:
        raise ValueError(f"{recording}: frame {frame} has no γ-map{f' of {fingerprint}' if fingerprint else ''} "
                         f"and confocal image")
    det = next((d for d in dets if d.fingerprint == gamma.fingerprint), None)
    found = np.array(det.position_m) if det is not None else _peak(gamma.grid, gamma.gamma)
    confocal = image.image if image.scale == "linear" else (10 ** (image.image / 10)).astype(np.float32)
    title = f"frame {frame}, {gamma.fingerprint}"
    if det is not None:
        title += f": C_γ = {det.contrast_c_gamma:.1f}, PFA = {det.pfa:.1e}"
    gamma_over_confocal(png, gamma.grid.to_grid(), confocal, gamma.gamma, found, title=title, threshold=threshold)
    return {"png": str(png), "frame": frame, "fingerprint": gamma.fingerprint, "detection": found.tolist()}


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
                stop: Any = None, threshold: float = 0.6, stats: dict[str, int] | None = None) -> dict[str, Any]:
    """Subscribe to the processor's outputs on ``fp/<rig>/{gamma,image,detections,tracks,status}`` and
    log them to a Rerun ``.rrd`` as they arrive (same entities and blueprint as `to_rrd`), until
    `duration` seconds pass or `stop` (a threading.Event; default: SIGINT/SIGTERM) is set. Announces
    itself with the liveliness token ``fp/<rig>/alive/viewer``. Raw RF frames are not subscribed.
    `stats` (optional) is updated live with the counts of messages logged, undecodable and dropped."""
    import queue
    import time

    import rerun as rr

    from services.bus import open_session, sample_bytes, stop_on_signals
    from services.wire import keys

    rrd = Path(rrd)
    rec = rr.RecordingStream("fingerprint", recording_id=f"live-{rig}")
    rec.save(rrd)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)
    conv = _Converter(rec, threshold=threshold)
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
        try:
            conv.feed(decode(payload))
            stats["messages"] += 1
        except WireError:
            stats["undecodable"] += 1

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


def run_view(args: argparse.Namespace) -> int:
    """`fp view`: convert a recording to ``.rrd``, or log the live bus (``--live``) to one."""
    if args.live:
        from services.bus import bus_from_args

        rrd = Path(args.rrd or f"live-{args.rig}.rrd")
        out = live_to_rrd(bus_from_args(args), args.rig, rrd, duration=args.duration, threshold=args.threshold)
        print(f"{out['rrd']}: {len(out['frames'])} frames, {out['messages']} messages "
              f"({out['undecodable']} undecodable, {out['dropped']} dropped)")
        return 0
    if not args.recording:
        raise ValueError("recording: give an MCAP file, or --live to follow the bus")
    rrd = Path(args.rrd) if args.rrd else Path(args.recording).with_suffix(".rrd")
    out = to_rrd(args.recording, rrd, threshold=args.threshold)
    print(f"{out['rrd']}: {len(out['frames'])} frames, {out['messages']} messages "
          f"({out['undecodable']} undecodable), fingerprints {', '.join(out['fingerprints']) or 'none'}")
    return 0


def run_figure(args: argparse.Namespace) -> int:
    """`fp figure`: PNG of γ over the confocal image for one frame."""
    out = to_figure(args.recording, args.frame, args.png, fingerprint=args.fingerprint, threshold=args.threshold)
    print(f"{out['png']}: frame {out['frame']}, {out['fingerprint']}")
    return 0


def add_view_parser(sub: Any) -> argparse.ArgumentParser:
    """Register `fp view`."""
    p = sub.add_parser("view", help="convert an MCAP recording to a Rerun .rrd",
                       description="Log a recording's γ-maps, confocal images, detections, tracks and time "
                                   "series to Rerun natively, with a default blueprint.")
    p.add_argument("recording", nargs="?", help="MCAP file written by `fp record`/`fp demo`")
    p.add_argument("--rrd", default=None, help="output .rrd (default: the recording with .rrd, or live-<rig>.rrd)")
    p.add_argument("--live", action="store_true", help="follow the zenoh bus instead of a file (Ctrl-C stops)")
    p.add_argument("--rig", default="demo", help="rig to follow with --live (default demo)")
    p.add_argument("--duration", type=float, default=None, help="with --live: stop after this many seconds")
    p.add_argument("--threshold", type=float, default=0.6, help="show γ ≥ threshold·max (default 0.6)")
    from services.bus import DEFAULT_HUB, EPHEMERAL, add_bus_arguments

    add_bus_arguments(p, listen=EPHEMERAL, connect=DEFAULT_HUB)
    p.set_defaults(func=run_view)
    return p


def add_figure_parser(sub: Any) -> argparse.ArgumentParser:
    """Register `fp figure`."""
    p = sub.add_parser("figure", help="PNG of γ over the confocal image for one recorded frame",
                       description="γ-map of one frame over its confocal image (dB), marker at the detection.")
    p.add_argument("recording", help="MCAP file written by `fp record`/`fp demo`")
    p.add_argument("--frame", type=int, required=True, help="frame index")
    p.add_argument("--png", required=True, help="output PNG")
    p.add_argument("--fingerprint", default=None, help="fingerprint (default: the frame's first γ-map)")
    p.add_argument("--threshold", type=float, default=0.6, help="colour γ ≥ threshold·max (default 0.6)")
    p.set_defaults(func=run_figure)
    return p
