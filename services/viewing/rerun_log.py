"""Recordings and the live bus to Rerun (`fp view`, the ``rerun-loader-fingerprint`` data loader) (docs/design.md
§2, §7 stack notes; docs/wire.md "MCAP recordings").

:class:`RerunLog` decodes the bus messages (``services.recording``; Rerun shows custom MCAP encodings only as
blobs) and logs them natively on the timelines ``frame`` (sequence) and ``acquisition_time`` (the frames'
source clock). 3-D entities are in metres (``world``: x lateral, y elevation, z depth, z down):

* ``world/gamma/<fingerprint>``: the γ-volume (``Volume3D``, float16); a 2-D map is a textured quad in the
  x–z plane (``Mesh3D``), not an empty volume;
* ``world/probe``: the probe's elements (``Boxes3D``, pitch × pitch × 0.2 mm) from the RF frames;
* ``world/truth``: the ground truth the RF frames carry (``Ellipsoids3D`` at the targets' diameters);
* ``world/detections/<fingerprint>``: detections (``Points3D``, radius = the largest Cramér–Rao precision);
* ``world/tracks/<id>``: each track's path (``LineStrips3D``), ``…/covariance`` its 3σ position ellipsoid
  (``Ellipsoids3D``), ``…/velocity`` its velocity (``Arrows3D``, the distance travelled in 10 s);
* ``sections/<fingerprint>/{xz,yz}/{confocal,gamma}``: the confocal image (grey, −30…0 dB) and γ (colour map,
  values under ``threshold``·max left out) through the detection, in **millimetres**: each image carries a
  ``Transform3D`` (pixel → mm: scale = grid step, translation = the first cell's corner), and the section's
  ``detection``, ``truth`` (outline at the target's diameter) and ``probe`` (elements in the plane) are drawn
  in mm on it;
* ``series/<fingerprint>/{c_gamma,log10_pfa}`` and ``series/latency_ms/{median,p95}`` (``Scalars``).

A default blueprint (sections, 3D view, time series) is stored with the data. `fp view --live` logs the bus
as it runs (:func:`live_to_rrd`), optionally also to the loopback web viewer of ``services.viewing.server``.
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

from services.messages import ConfocalImage, Detections, GammaMap, Message, RFFrame, Status, Tracks
from services.recording import RecordingError, iter_messages
from services.topics import keys
from services.viewing.display import DB_FLOOR, FrameAssembler, ReadyFrame, Section, confocal_db, sections, truth_targets
from services.wire import WireError, decode

__all__ = ["RerunLog", "live_to_rrd", "log_recording", "to_rrd"]

MM = 1e3
ARROW_SECONDS = 10.0


def _frame_of(h: str) -> int:
    return 0 if h == "x" else 1


@dataclass
class RerunLog:
    """Streams decoded messages into a Rerun recording stream (see the module doc for the entities)."""

    rec: Any
    threshold: float = 0.6
    prefix: str = ""
    frames: FrameAssembler = field(default_factory=FrameAssembler)
    fingerprints: list[str] = field(default_factory=list)
    track_paths: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)
    logged: Counter[str] = field(default_factory=Counter)
    frame_indices: set[int] = field(default_factory=set)
    has_3d: bool = False
    probe: np.ndarray | None = None
    pitch: float = 3e-4
    truth: dict[int, list[tuple[str, np.ndarray, float | None]]] = field(default_factory=dict)

    def _time(self, frame_index: int, timestamp: float) -> None:
        self.rec.set_time("frame", sequence=frame_index)
        if timestamp > 1e8:  # an epoch time
            self.rec.set_time("acquisition_time", timestamp=timestamp)
        else:
            self.rec.set_time("acquisition_time", duration=timestamp)
        self.frame_indices.add(frame_index)

    def _log(self, path: str, archetype: Any, *extra: Any, static: bool = False) -> None:
        self.rec.log(f"{self.prefix}{path}", archetype, *extra, static=static)
        self.logged[path] += 1

    def start(self) -> None:
        import rerun as rr

        self._log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)

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
        if isinstance(msg, RFFrame):
            self._rf(msg)
            return
        if not isinstance(msg, (GammaMap, ConfocalImage, Detections, Tracks)):
            return
        self._time(msg.frame_index, msg.timestamp)
        if isinstance(msg, GammaMap):
            if msg.fingerprint not in self.fingerprints:
                self.fingerprints.append(msg.fingerprint)
            self._volume(msg)
        elif isinstance(msg, Detections):
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
        elif isinstance(msg, Tracks):
            self._tracks(msg)
        for ready in self.frames.feed(msg):
            self._sections(ready)

    def finish(self) -> None:
        for ready in self.frames.finish():
            self._sections(ready)

    # -- entities ---------------------------------------------------------------------------------------
    def _rf(self, msg: RFFrame) -> None:
        import rerun as rr

        pos = np.asarray(msg.probe.positions, float)
        if self.probe is None or self.probe.shape != pos.shape or not np.array_equal(self.probe, pos):
            self.probe, self.pitch = pos, float(msg.probe.pitch)
            half = [0.45 * self.pitch, 0.45 * self.pitch, 0.1e-3]
            boxes = rr.Boxes3D(centers=pos, half_sizes=[half] * len(pos), colors=[150, 150, 180])
            self._log("world/probe", boxes, static=True)
        targets = truth_targets(msg)
        self.truth[msg.frame_index] = targets
        for k in [k for k in self.truth if k < msg.frame_index - 16]:
            del self.truth[k]
        if targets:
            self._time(msg.frame_index, msg.timestamp)
            self._log(
                "world/truth",
                rr.Ellipsoids3D(
                    centers=[p for _n, p, _d in targets],
                    radii=[(d or 1e-3) / 2 for _n, _p, d in targets],
                    labels=[f"truth {n}" for n, _p, _d in targets],
                    colors=[60, 200, 80],
                    fill_mode="MajorWireframe",
                ),
            )

    def _tracks(self, msg: Tracks) -> None:
        import rerun as rr

        for t in msg.tracks:
            pts = self.track_paths.setdefault(t.id, [])
            pts.append(t.position_m)
            base = f"world/tracks/{t.id}"
            self._log(base, rr.LineStrips3D([pts], labels=[f"track {t.id} {t.fingerprint}"]))
            c = np.asarray(t.covariance, float)
            w, v = np.linalg.eigh(0.5 * (c + c.T))
            if np.linalg.det(v) < 0:
                v[:, 2] *= -1
            from scipy.spatial.transform import Rotation

            self._log(
                f"{base}/covariance",
                rr.Ellipsoids3D(
                    centers=[t.position_m],
                    half_sizes=[3 * np.sqrt(np.clip(w, 0, None))],
                    quaternions=[rr.Quaternion(xyzw=Rotation.from_matrix(v).as_quat())],
                    colors=[60, 150, 255],
                ),
            )
            self._log(
                f"{base}/velocity",
                rr.Arrows3D(
                    origins=[t.position_m], vectors=[np.asarray(t.velocity_m_s) * ARROW_SECONDS], colors=[60, 150, 255]
                ),
            )

    def _volume(self, g: GammaMap) -> None:
        import rerun as rr

        grid = g.grid
        gmax = max(float(np.max(g.gamma)), 1e-30)
        if grid.y is None:  # a 2-D map: a textured quad in the x–z plane (metres)
            import matplotlib

            dx, dz = Section("xz", g.gamma.T, grid.x, grid.z, 0.0).step
            x0, x1 = float(grid.x[0]) - dx / 2, float(grid.x[-1]) + dx / 2
            z0, z1 = float(grid.z[0]) - dz / 2, float(grid.z[-1]) + dz / 2
            rgba = matplotlib.colormaps["inferno"](np.clip(g.gamma.T / gmax, 0, 1))
            rgba[..., 3] = np.where(g.gamma.T >= self.threshold * gmax, 1.0, 0.25)
            self._log(
                f"world/gamma/{g.fingerprint}",
                rr.Mesh3D(
                    vertex_positions=[[x0, 0, z0], [x1, 0, z0], [x1, 0, z1], [x0, 0, z1]],
                    triangle_indices=[[0, 1, 2], [0, 2, 3]],
                    vertex_texcoords=[[0, 0], [1, 0], [1, 1], [0, 1]],
                    albedo_texture=(rgba * 255).astype(np.uint8),
                ),
            )
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
                value_range=(self.threshold * gmax, gmax),
                colormap="inferno",
            ),
        )

    def _sections(self, fr: ReadyFrame) -> None:
        """Log a frame's sections (through each fingerprint's detection) in millimetres."""
        import rerun as rr

        conf = confocal_db(fr.image) if fr.image is not None else None
        truths = self.truth.get(fr.frame_index, [])
        for g, at, det in fr.gammas:
            self._time(fr.frame_index, g.timestamp)
            gmax = float(np.max(g.gamma))
            csec = {s.plane: s for s in sections(fr.image.grid, conf, at)} if conf is not None and fr.image else {}
            for sec in sections(g.grid, g.gamma, at):
                base = f"sections/{g.fingerprint}/{sec.plane}"
                c = csec.get(sec.plane)
                if c is not None and c.data.shape == sec.data.shape:
                    grey = np.clip((c.data - DB_FLOOR) / -DB_FLOOR * 255, 0, 255).astype(np.uint8)
                    self._image(f"{base}/confocal", sec, rr.Image(grey, draw_order=0.0))
                shown = np.where(sec.data >= self.threshold * gmax, sec.data, 0).astype(np.float32)
                img = rr.DepthImage(
                    shown, meter=1.0, colormap="inferno", depth_range=(self.threshold * gmax, gmax), draw_order=1.0
                )
                self._image(f"{base}/gamma", sec, img)
                self._overlays(base, sec, at if det is not None else None, truths)

    def _image(self, path: str, sec: Section, archetype: Any) -> None:
        """An image whose pixels are placed in mm by a Transform3D (scale = the grid step)."""
        import rerun as rr

        dh, dz = sec.step
        corner = [(float(sec.h[0]) - dh / 2) * MM, (float(sec.z[0]) - dz / 2) * MM, 0.0]
        self._log(path, rr.Transform3D(translation=corner, scale=[dh * MM, dz * MM, 1.0]), archetype)

    def _overlays(
        self, base: str, sec: Section, det: np.ndarray | None, truths: list[tuple[str, np.ndarray, float | None]]
    ) -> None:
        import rerun as rr

        h = _frame_of(sec.plane[0])  # index of the horizontal coordinate in [x, y, z]
        normal = 1 - h  # xz: y is the normal; yz: x
        if det is not None:
            self._log(
                f"{base}/detection",
                rr.Points2D([[det[h] * MM, det[2] * MM]], radii=[0.3], colors=[255, 60, 30], draw_order=3.0),
            )
        circles = []
        for _n, p, d in truths:
            r = (d or 1e-3) / 2
            if abs(p[normal] - sec.at) < r:  # the plane cuts the target
                rc = math.sqrt(max(r * r - (p[normal] - sec.at) ** 2, 0.0))
                t = np.linspace(0, 2 * np.pi, 49)
                circles.append(np.stack([(p[h] + rc * np.cos(t)) * MM, (p[2] + rc * np.sin(t)) * MM], 1))
        if circles:
            self._log(f"{base}/truth", rr.LineStrips2D(circles, colors=[60, 200, 80], draw_order=2.0))
        if self.probe is not None:
            on = self.probe[np.abs(self.probe[:, normal] - sec.at) <= self.pitch / 2 + 1e-9]
            if len(on):
                pts = np.stack([on[:, h] * MM, on[:, 2] * MM], 1)
                self._log(f"{base}/probe", rr.Points2D(pts, radii=[self.pitch * MM * 0.4], colors=[150, 150, 180]))

    def blueprint(self) -> Any:
        import rerun.blueprint as rrb

        planes = ("xz", "yz") if self.has_3d else ("xz",)
        secs = [
            rrb.Spatial2DView(origin=f"{self.prefix}sections/{fp}/{p}", name=f"{fp} {p} (mm): γ over confocal (dB)")
            for fp in self.fingerprints
            for p in planes
        ]
        series = [
            rrb.TimeSeriesView(origin=f"{self.prefix}series", contents=f"{self.prefix}series/*/{k}/**", name=name)
            for k, name in (("c_gamma", "C_γ"), ("log10_pfa", "log10 PFA"))
        ]
        series.append(rrb.TimeSeriesView(origin=f"{self.prefix}series/latency_ms", name="latency (ms)"))
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Grid(*secs, name="sections") if secs else rrb.Spatial2DView(origin=f"{self.prefix}sections"),
                rrb.Vertical(rrb.Spatial3DView(origin=f"{self.prefix}world", name="3D (m)"), rrb.Vertical(*series)),
                column_shares=[2, 1],
            ),
            collapse_panels=False,
        )


def log_recording(recording: str | Path, rec: Any, *, threshold: float = 0.6, prefix: str = "") -> dict[str, Any]:
    """Log every bus message of an MCAP recording to the stream ``rec``; RecordingError if nothing could be read."""
    conv = RerunLog(rec, threshold=threshold, prefix=prefix)
    conv.start()
    report: dict[str, Any] = {}
    n = 0
    for _key, msg in iter_messages(recording, report):
        conv.feed(msg)
        n += 1
    conv.finish()
    if n == 0:
        damage = f"; {report['error']}" if report.get("error") else ""
        raise RecordingError(
            f"{recording}: no fingerprint message could be read ({report.get('undecodable', 0)} undecodable, "
            f"{report.get('corrupted_chunks', 0)} corrupted chunk(s){damage})"
        )
    return {
        "messages": n,
        "undecodable": report.get("undecodable", 0),
        "corrupted_chunks": report.get("corrupted_chunks", 0),
        "error": report.get("error"),
        "frames": sorted(conv.frame_indices),
        "fingerprints": list(conv.fingerprints),
        "logged": dict(conv.logged),
        "blueprint": conv.blueprint(),
    }


def to_rrd(recording: str | Path, rrd: str | Path, *, threshold: float = 0.6) -> dict[str, Any]:
    """Convert an MCAP recording to a Rerun ``.rrd`` (with a default blueprint); returns the frame indices
    logged, the fingerprints and the number of logs per entity. RecordingError (no .rrd left) when the file
    is not an MCAP or holds no readable fingerprint message."""
    import rerun as rr

    recording, rrd = Path(recording), Path(rrd)
    if not recording.is_file():
        raise FileNotFoundError(f"{recording}: no such file")
    rec = rr.RecordingStream("fingerprint", recording_id=recording.stem)
    rec.save(rrd)
    try:
        out = log_recording(recording, rec, threshold=threshold)
    except Exception:
        rec.disconnect()
        rrd.unlink(missing_ok=True)
        raise
    rec.send_blueprint(out.pop("blueprint"), make_active=True, make_default=True)
    rec.flush()
    rec.disconnect()
    return {"rrd": str(rrd), **out}


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
    """Subscribe to ``fp/<rig>/{rf,gamma,image,detections,tracks,status}`` and log the messages to a Rerun
    ``.rrd`` as they arrive (same entities and blueprint as `to_rrd`; RF frames give the probe and the ground
    truth), until `duration` seconds pass or `stop` (a threading.Event; default: SIGINT/SIGTERM) is set.
    Announces itself with the liveliness token ``fp/<rig>/alive/viewer``. `stats` (optional) is updated live
    with the counts of messages logged, undecodable and dropped. With ``grpc_url`` (a Rerun gRPC proxy, e.g.
    `serve_loopback`'s) the same stream also goes there, and the blueprint is re-sent whenever a new
    fingerprint appears."""
    import rerun as rr

    from services.bus import open_session, sample_bytes, stop_on_signals

    rrd = Path(rrd)
    rec = rr.RecordingStream("fingerprint", recording_id=f"live-{rig}")
    if grpc_url:
        rec.set_sinks(rr.FileSink(str(rrd)), rr.GrpcSink(grpc_url))
    else:
        rec.save(rrd)
    conv = RerunLog(rec, threshold=threshold)
    conv.start()
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
            for t in ("rf", "gamma", "image", "detections", "tracks", "status")
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
