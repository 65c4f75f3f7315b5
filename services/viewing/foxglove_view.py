"""Bus messages as Foxglove's well-known schemas (``foxglove-sdk``), for the recorder's display channels and
the live server of `fp view --foxglove` (docs/wire.md "MCAP recordings").

Display topics (``fp/<rig>/display/…``; frame of reference ``world``: x lateral, y elevation, z depth, metres):

* ``gamma/<fingerprint>/{xz,yz}`` — γ sections through the detection (else γ's maximum) as ``foxglove.Grid``
  (one float32 field ``gamma``; the cell size is the grid step in metres, the pose places the plane in the
  world); ``confocal/<fingerprint>/{xz,yz}`` — the confocal image (dB, field ``confocal_db``) on the same planes;
* ``detections``, ``tracks``, ``truth``, ``probe`` — ``foxglove.SceneUpdate``: detections as spheres (diameter
  = 2 × the largest Cramér–Rao precision) with a label; each track as its 3σ covariance ellipsoid, its velocity
  as an arrow (the distance travelled in :data:`ARROW_SECONDS`) and its path as a line; the ground truth of the
  RF frames (target spheres at their diameter); the probe's elements as cubes (pitch × pitch × 0.2 mm).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from services.messages import ConfocalImage, Detections, GammaMap, Message, RFFrame, Tracks
from services.topics import parse_key
from services.viewing.display import FrameAssembler, ReadyFrame, Section, confocal_db_sections, sections, truth_targets

__all__ = ["ARROW_SECONDS", "FRAME_ID", "FoxgloveDisplay", "display_topic"]

FRAME_ID = "world"
#: a track's velocity arrow is the distance it travels in this time.
ARROW_SECONDS = 10.0
_ELEMENT_THICKNESS = 0.2e-3


def display_topic(rig: str, *parts: str) -> str:
    """``fp/<rig>/display/<parts…>``: a derived view, never published on the bus."""
    return "/".join(("fp", rig, "display", *parts))


def _fm() -> Any:
    import foxglove.messages as fm

    return fm


def _stamp(t_ns: int) -> Any:
    return _fm().Timestamp(sec=int(t_ns // 1_000_000_000), nsec=int(t_ns % 1_000_000_000))


def _pose(p: Any, q: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)) -> Any:
    fm = _fm()
    return fm.Pose(
        position=fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=fm.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def _colour(r: float, g: float, b: float, a: float = 1.0) -> Any:
    return _fm().Color(r=r, g=g, b=b, a=a)


def _quat(m: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (columns: the rotated axes)."""
    from scipy.spatial.transform import Rotation

    if np.linalg.det(m) < 0:
        m = m * np.array([1.0, 1.0, -1.0])
    x, y, z, w = Rotation.from_matrix(m).as_quat()
    return float(x), float(y), float(z), float(w)


#: plane → rotation taking the Grid's local (x, y, z) to world axes: local x → h axis, local y → z (depth).
_PLANE_ROT = {
    "xz": _quat(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])),
    "yz": _quat(np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]])),
}


def section_grid(sec: Section, field_name: str, t_ns: int) -> Any:
    """A section as a ``foxglove.Grid`` in metres, placed on its plane in the world."""
    fm = _fm()
    dh, dz = sec.step
    corner = (
        [sec.h[0] - dh / 2, sec.at, sec.z[0] - dz / 2]
        if sec.plane == "xz"
        else [sec.at, sec.h[0] - dh / 2, sec.z[0] - dz / 2]
    )
    data = np.ascontiguousarray(sec.data, "<f4")
    return fm.Grid(
        timestamp=_stamp(t_ns),
        frame_id=FRAME_ID,
        pose=_pose(corner, _PLANE_ROT[sec.plane]),
        column_count=int(data.shape[1]),
        cell_size=fm.Vector2(x=dh, y=dz),
        row_stride=int(data.shape[1]) * 4,
        cell_stride=4,
        fields=[fm.PackedElementField(name=field_name, offset=0, type=fm.PackedElementFieldNumericType.Float32)],
        data=data.tobytes(),
    )


def _arrow(origin: Any, v: np.ndarray, colour: Any) -> Any | None:
    fm = _fm()
    length = float(np.linalg.norm(v)) * ARROW_SECONDS
    if not math.isfinite(length) or length <= 1e-9:
        return None
    u = v / np.linalg.norm(v)
    a = np.cross([1.0, 0.0, 0.0], u)  # rotate +x onto u
    s, c = float(np.linalg.norm(a)), float(u[0])
    if s < 1e-12:
        q = (0.0, 0.0, 0.0, 1.0) if c > 0 else (0.0, 0.0, 1.0, 0.0)
    else:
        half = math.atan2(s, c) / 2
        ax = a / s * math.sin(half)
        q = (float(ax[0]), float(ax[1]), float(ax[2]), math.cos(half))
    return fm.ArrowPrimitive(
        pose=_pose(origin, q),
        shaft_length=0.75 * length,
        shaft_diameter=max(0.05 * length, 0.1e-3),
        head_length=0.25 * length,
        head_diameter=max(0.15 * length, 0.3e-3),
        color=colour,
    )


class FoxgloveDisplay:
    """Turns decoded bus messages into (topic, Foxglove message) pairs; keeps the state a view needs
    (frames waiting for their detections, track paths, the probe last shown)."""

    def __init__(self) -> None:
        self.frames = FrameAssembler()
        self.paths: dict[tuple[str, int], list[tuple[float, float, float]]] = {}
        self.shown_tracks: dict[str, set[int]] = {}
        self.probe_shown: dict[str, bytes] = {}
        self.rig_of_frame: dict[int, str] = {}

    def feed(self, key: str, msg: Message, t_ns: int) -> list[tuple[str, Any]]:
        try:
            rig, _topic = parse_key(key)
        except ValueError:
            return []
        out: list[tuple[str, Any]] = []
        if isinstance(msg, RFFrame):
            out += self._rf(rig, msg, t_ns)
        elif isinstance(msg, Tracks):
            out.append((display_topic(rig, "tracks"), self._tracks(rig, msg, t_ns)))
        if isinstance(msg, (GammaMap, ConfocalImage)):
            self.rig_of_frame[msg.frame_index] = rig
        if isinstance(msg, Detections):
            out.append((display_topic(rig, "detections"), self._detections(msg, t_ns)))
        for ready in self.frames.feed(msg):
            out += self._sections(self.rig_of_frame.pop(ready.frame_index, rig), ready, t_ns)
        return out

    def finish(self, t_ns: int) -> list[tuple[str, Any]]:
        out: list[tuple[str, Any]] = []
        for ready in self.frames.finish():
            out += self._sections(self.rig_of_frame.pop(ready.frame_index, "_"), ready, t_ns)
        return out

    # -- messages ---------------------------------------------------------------------------------------
    def _sections(self, rig: str, fr: ReadyFrame, t_ns: int) -> list[tuple[str, Any]]:
        out = []
        img = fr.image
        top = float(np.max(img.image)) if img is not None and img.image.size else None
        for g, at, _det in fr.gammas:
            for sec in sections(g.grid, g.gamma, at):
                out.append((display_topic(rig, "gamma", g.fingerprint, sec.plane), section_grid(sec, "gamma", t_ns)))
            if img is not None and top is not None and img.grid.shape == g.grid.shape:
                for sec in confocal_db_sections(img, at, top):  # dB of the sections only, not of the volume
                    topic = display_topic(rig, "confocal", g.fingerprint, sec.plane)
                    out.append((topic, section_grid(sec, "confocal_db", t_ns)))
        return out

    def _entity(self, eid: str, t_ns: int, **prims: Any) -> Any:
        return _fm().SceneEntity(timestamp=_stamp(t_ns), frame_id=FRAME_ID, id=eid, **prims)

    def _rf(self, rig: str, msg: RFFrame, t_ns: int) -> list[tuple[str, Any]]:
        fm = _fm()
        out = []
        pos = np.asarray(msg.probe.positions, float)
        sig = pos.tobytes() + np.float64(msg.probe.pitch).tobytes()
        if self.probe_shown.get(rig) != sig:
            self.probe_shown[rig] = sig
            p = msg.probe.pitch
            cubes = [
                fm.CubePrimitive(
                    pose=_pose(e),
                    size=fm.Vector3(x=p * 0.9, y=p * 0.9, z=_ELEMENT_THICKNESS),
                    color=_colour(0.6, 0.6, 0.7),
                )
                for e in pos
            ]
            out.append(
                (display_topic(rig, "probe"), fm.SceneUpdate(entities=[self._entity("probe", t_ns, cubes=cubes)]))
            )
        targets = truth_targets(msg)
        spheres = [
            fm.SpherePrimitive(
                pose=_pose(p),
                size=fm.Vector3(x=d or 1e-3, y=d or 1e-3, z=d or 1e-3),
                color=_colour(0.2, 0.8, 0.3, 0.35),
            )
            for _n, p, d in targets
        ]
        texts = [
            fm.TextPrimitive(
                pose=_pose(p),
                billboard=True,
                font_size=12,
                scale_invariant=True,
                color=_colour(0.2, 0.8, 0.3),
                text=f"truth {n}",
            )
            for n, p, _d in targets
        ]
        ent = self._entity("truth", t_ns, spheres=spheres, texts=texts)
        out.append((display_topic(rig, "truth"), fm.SceneUpdate(entities=[ent])))
        return out

    def _detections(self, msg: Detections, t_ns: int) -> Any:
        fm = _fm()
        spheres, texts = [], []
        for d in msg.detections:
            r = max(max(d.precision_m), 0.1e-3)
            spheres.append(
                fm.SpherePrimitive(
                    pose=_pose(d.position_m), size=fm.Vector3(x=2 * r, y=2 * r, z=2 * r), color=_colour(1, 0.2, 0.1)
                )
            )
            texts.append(
                fm.TextPrimitive(
                    pose=_pose(d.position_m),
                    billboard=True,
                    font_size=12,
                    scale_invariant=True,
                    color=_colour(1, 0.3, 0.2),
                    text=f"{d.fingerprint}: C_γ {d.contrast_c_gamma:.1f}, PFA {d.pfa:.1e}",
                )
            )
        return fm.SceneUpdate(entities=[self._entity("detections", t_ns, spheres=spheres, texts=texts)])

    def _tracks(self, rig: str, msg: Tracks, t_ns: int) -> Any:
        fm = _fm()
        entities, alive = [], set()
        for t in msg.tracks:
            if t.status == "lost":
                continue
            alive.add(t.id)
            path = self.paths.setdefault((rig, t.id), [])
            path.append(tuple(t.position_m))
            c = np.asarray(t.covariance, float)
            w, v = np.linalg.eigh(0.5 * (c + c.T))
            size = 2 * 3 * np.sqrt(np.clip(w, 0, None))  # 3σ ellipsoid, diameters along the eigenvectors
            size = np.maximum(size, 0.05e-3)
            colour = _colour(0.2, 0.6, 1.0, 0.5)
            ell = fm.SpherePrimitive(
                pose=_pose(t.position_m, _quat(v)), size=fm.Vector3(x=size[0], y=size[1], z=size[2]), color=colour
            )
            arrow = _arrow(t.position_m, np.asarray(t.velocity_m_s, float), _colour(0.2, 0.6, 1.0))
            line = fm.LinePrimitive(
                type=fm.LinePrimitiveLineType.LineStrip,
                pose=_pose((0, 0, 0)),
                thickness=2,
                scale_invariant=True,
                points=[fm.Point3(x=p[0], y=p[1], z=p[2]) for p in path],
                color=_colour(0.2, 0.6, 1.0),
            )
            label = fm.TextPrimitive(
                pose=_pose(t.position_m),
                billboard=True,
                font_size=12,
                scale_invariant=True,
                color=_colour(0.2, 0.6, 1.0),
                text=f"track {t.id} {t.fingerprint} {t.status or ''}".strip(),
            )
            entities.append(
                self._entity(
                    f"track/{t.id}", t_ns, spheres=[ell], arrows=[arrow] if arrow else [], lines=[line], texts=[label]
                )
            )
        gone = self.shown_tracks.get(rig, set()) - alive
        self.shown_tracks[rig] = alive
        deletions = [
            fm.SceneEntityDeletion(timestamp=_stamp(t_ns), type=fm.SceneEntityDeletionType.MatchingId, id=f"track/{i}")
            for i in sorted(gone)
        ]
        return fm.SceneUpdate(deletions=deletions, entities=entities)
