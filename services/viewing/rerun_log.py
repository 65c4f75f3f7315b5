"""Recordings and the live bus to Rerun (`fp view`) (docs/design.md §2, §7 stack notes).

`fp view REC.mcap --rrd out.rrd` (:func:`to_rrd`) decodes every FPWIRE01 message of a recording
(``services.recording``) and logs it to Rerun natively (Rerun shows custom MCAP encodings only as
blobs), on the timelines ``frame`` (sequence) and ``acquisition_time`` (the frames' source clock):

* ``world/gamma/<fingerprint>``: the γ-volume (``Volume3D``, float16; metres, z down);
* ``world/detections/<fingerprint>``: detections (``Points3D``, radius = max Cramér–Rao precision);
* ``world/tracks/<id>``: the positions of each track so far (``LineStrips3D``);
* ``sections/<fingerprint>/{xz,yz}/{confocal,gamma}``: the confocal image in dB (grey, −30…0 dB) and γ
  (``DepthImage`` with a colour map, values under ``threshold``·max left out) through the detection;
* ``series/<fingerprint>/{c_gamma,log10_pfa}`` and ``series/latency_ms/{median,p95}`` (``Scalars``).

A default blueprint (sections, 3D view, time series) is stored in the ``.rrd``; open it with
`rerun FILE.rrd`. `fp view --live` logs the bus as it runs (:func:`live_to_rrd`), optionally also to
the loopback web viewer of ``services.viewing.server``.
"""

from __future__ import annotations

import math
import queue
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.messages import (
    ConfocalImage,
    Detection,
    Detections,
    GammaMap,
    Grid,
    Message,
    Status,
    Tracks,
)
from services.recording import iter_messages
from services.topics import keys
from services.viewing.figures import peak_position
from services.wire import WireError, decode

__all__ = ["live_to_rrd", "to_rrd"]

DB_FLOOR = -30.0


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
                self._log(
                    f"world/detections/{d.fingerprint}",
                    rr.Points3D(
                        [d.position_m],
                        radii=[max(d.precision_m)],
                        labels=[f"{d.fingerprint}: C_γ {d.contrast_c_gamma:.1f}"],
                    ),
                )
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
        self._log(
            f"world/gamma/{g.fingerprint}",
            rr.Volume3D(
                values,
                voxel_size=step,
                translation=corner,
                value_range=(self.threshold * float(np.max(g.gamma)), float(np.max(g.gamma))),
                colormap="inferno",
            ),
        )

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
            at = np.array(det.position_m) if det is not None else peak_position(g.grid, g.gamma)
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
                self._log(
                    f"{base}/gamma",
                    rr.DepthImage(
                        shown, meter=1.0, colormap="inferno", depth_range=(self.threshold * gmax, gmax), draw_order=1.0
                    ),
                )
            fr.done.add(name)
        if final:
            del self.frames[frame_index]

    def finish(self) -> None:
        for k in sorted(self.frames):
            self._sections(k, final=True)

    def blueprint(self) -> Any:
        import rerun.blueprint as rrb

        planes = ("xz", "yz") if self.has_3d else ("xz",)
        sections = [
            rrb.Spatial2DView(origin=f"sections/{fp}/{p}", name=f"{fp} {p}: γ over confocal (dB)")
            for fp in self.fingerprints
            for p in planes
        ]
        series = [
            rrb.TimeSeriesView(origin="series", contents=f"series/*/{k}/**", name=name)
            for k, name in (("c_gamma", "C_γ"), ("log10_pfa", "log10 PFA"))
        ]
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
    return {
        "rrd": str(rrd),
        "messages": n,
        "undecodable": report.get("undecodable", 0),
        "error": report.get("error"),
        "frames": sorted(conv.frame_indices),
        "fingerprints": list(conv.fingerprints),
        "logged": dict(conv.logged),
    }


def live_to_rrd(
    bus: Any,
    rig: str,
    rrd: str | Path,
    *,
    duration: float | None = None,
    stop: Any = None,
    threshold: float = 0.6,
    stats: dict[str, int] | None = None,
    grpc_url: str | None = None,
) -> dict[str, Any]:
    """Subscribe to the processor's outputs on ``fp/<rig>/{gamma,image,detections,tracks,status}`` and
    log them to a Rerun ``.rrd`` as they arrive (same entities and blueprint as `to_rrd`), until
    `duration` seconds pass or `stop` (a threading.Event; default: SIGINT/SIGTERM) is set. Announces
    itself with the liveliness token ``fp/<rig>/alive/viewer``. Raw RF frames are not subscribed.
    `stats` (optional) is updated live with the counts of messages logged, undecodable and dropped.
    With ``grpc_url`` (a Rerun gRPC proxy, e.g. `serve_loopback`'s) the same stream also goes there, and
    the blueprint is re-sent whenever a new fingerprint appears."""
    import rerun as rr

    from services.bus import open_session, sample_bytes, stop_on_signals

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
        subs = [
            session.declare_subscriber(k.topic(t), on_sample)
            for t in ("gamma", "image", "detections", "tracks", "status")
        ]
        token = session.liveliness().declare_token(k.alive("viewer"))
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
