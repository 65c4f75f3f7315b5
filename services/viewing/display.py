"""Display views of the bus messages, shared by the recorder's Foxglove channels, the live Foxglove server
and Rerun (docs/wire.md "MCAP recordings").

:class:`FrameAssembler` holds a frame's γ-maps and confocal image until its Detections arrive (the processor
publishes them last), so that sections go through the detection rather than γ's plain maximum (which can sit
on the suspension's surface); :func:`sections` cuts the x–z (and, in 3-D, y–z) sections through a point,
with their axes in metres. Pure numpy: no viewer imported.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from services.messages import ConfocalImage, Detection, Detections, GammaMap, Grid, Message, RFFrame

__all__ = [
    "FrameAssembler",
    "ReadyFrame",
    "Section",
    "confocal_db",
    "confocal_db_sections",
    "sections",
    "truth_targets",
]

DB_FLOOR = -30.0


@dataclass(frozen=True)
class Section:
    """A plane through a volume: ``data`` (rows = z, columns = the horizontal axis ``h``), the horizontal
    axis's name (``x`` or ``y``) and coordinates (m), the z coordinates (m), and where it cuts the normal
    axis (``y`` for ``xz``, ``x`` for ``yz``; 0 for a 2-D grid)."""

    plane: str
    data: np.ndarray
    h: np.ndarray
    z: np.ndarray
    at: float

    @property
    def step(self) -> tuple[float, float]:
        """Cell size (m) along h and z (1e-4 for a one-cell axis)."""
        return tuple(float(np.mean(np.diff(a))) if a.size > 1 else 1e-4 for a in (self.h, self.z))  # type: ignore[return-value]


def _nearest(axis: np.ndarray, v: float) -> int:
    return int(np.argmin(np.abs(axis - v)))


def sections(grid: Grid, vol: np.ndarray, at: np.ndarray) -> list[Section]:
    """Sections of ``vol`` (on ``grid``) through ``at`` = [x, y, z] m: ``xz`` (2-D: the map itself) and ``yz``
    (3-D), each with rows = z."""
    if grid.y is None:
        return [Section("xz", np.ascontiguousarray(vol.T, np.float32), grid.x, grid.z, 0.0)]
    i, j = _nearest(grid.x, float(at[0])), _nearest(grid.y, float(at[1]))
    return [
        Section("xz", np.ascontiguousarray(vol[:, j, :].T, np.float32), grid.x, grid.z, float(grid.y[j])),
        Section("yz", np.ascontiguousarray(vol[i, :, :].T, np.float32), grid.y, grid.z, float(grid.x[i])),
    ]


def _to_db(values: np.ndarray, top: float, scale: str) -> np.ndarray:
    if scale == "db":
        db = values - top
    else:
        db = 10 * np.log10(values / max(top, 1e-30) + 1e-12)
    return np.maximum(db, DB_FLOOR).astype(np.float32)


def confocal_db(image: ConfocalImage) -> np.ndarray:
    """The confocal image in dB relative to its maximum, floored at :data:`DB_FLOOR`."""
    return _to_db(image.image, float(np.max(image.image)), image.scale)


def confocal_db_sections(image: ConfocalImage, at: np.ndarray, top: float | None = None) -> list[Section]:
    """:func:`sections` of :func:`confocal_db`, converting only the sections (``top``: the image's maximum,
    when already known)."""
    top = float(np.max(image.image)) if top is None else top
    return [replace(sec, data=_to_db(sec.data, top, image.scale)) for sec in sections(image.grid, image.image, at)]


def truth_targets(frame: RFFrame) -> list[tuple[str, np.ndarray, float | None]]:
    """(name, position m, diameter m or None) of the targets of an RF frame's ground truth."""
    from fpcore.truth import Truth

    try:
        truth = Truth.from_dict(frame.truth or {})
    except (TypeError, ValueError):
        return []
    return [
        (t.name or f"target {k}", np.asarray(t.position, float), t.diameter_m)
        for k, t in enumerate(truth.targets or [])
        if t.position_m is not None
    ]


@dataclass
class ReadyFrame:
    """A frame whose γ-maps can be shown: each map with the point its sections go through."""

    frame_index: int
    timestamp: float
    image: ConfocalImage | None
    gammas: list[tuple[GammaMap, np.ndarray, Detection | None]]


@dataclass
class _Pending:
    gamma: dict[str, GammaMap] = field(default_factory=dict)
    image: ConfocalImage | None = None


@dataclass
class FrameAssembler:
    """Collects γ-maps and confocal images per frame; :meth:`feed` returns the frames made ready by a message
    (its Detections arrived, or it is ``keep`` frames older than the newest)."""

    keep: int = 8
    pending: dict[int, _Pending] = field(default_factory=dict)

    def feed(self, msg: Message) -> list[ReadyFrame]:
        from services.viewing.figures import peak_position

        out: list[ReadyFrame] = []
        if isinstance(msg, GammaMap):
            self.pending.setdefault(msg.frame_index, _Pending()).gamma[msg.fingerprint] = msg
        elif isinstance(msg, ConfocalImage):
            self.pending.setdefault(msg.frame_index, _Pending()).image = msg
        elif isinstance(msg, Detections):
            fr = self.pending.pop(msg.frame_index, None)
            if fr is not None:
                dets = {d.fingerprint: d for d in msg.detections}
                out.append(self._ready(msg.frame_index, fr, dets, peak_position))
        else:
            return out
        newest = max(self.pending, default=-1)
        for k in [k for k in self.pending if k < newest - self.keep]:
            out.append(self._ready(k, self.pending.pop(k), {}, peak_position))
        return out

    def finish(self) -> list[ReadyFrame]:
        from services.viewing.figures import peak_position

        out = [self._ready(k, self.pending[k], {}, peak_position) for k in sorted(self.pending)]
        self.pending.clear()
        return out

    @staticmethod
    def _ready(frame_index: int, fr: _Pending, dets: dict[str, Detection], peak: Any) -> ReadyFrame:
        gammas = []
        for name, g in fr.gamma.items():
            d = dets.get(name)
            at = np.asarray(d.position_m, float) if d is not None else peak(g.grid, g.gamma)
            gammas.append((g, at, d))
        ts = next(iter(fr.gamma.values())).timestamp if fr.gamma else (fr.image.timestamp if fr.image else 0.0)
        return ReadyFrame(frame_index, float(ts), fr.image, gammas)
