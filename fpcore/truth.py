"""Ground truth carried with a frame: the typed view of its JSON record (docs/design.md §6).

Simulated frames carry what was simulated (scenario, targets with positions, diameters, velocities, the
medium, …) so that a processed frame can be scored against it. On the wire, in UFF files (``fp_truth``)
and in JSON the truth is a plain JSON object — `Acquisition.truth` holds that dict. `Truth` is its typed
view: ``Truth.from_dict(d).to_dict() == d`` for every JSON object ``d`` (keys a field does not know, or
values of an unexpected type, are kept in ``extra`` and written back as they came), and the keys of a
record built by `fpcore.simulate` come back in the same order, so its JSON text is unchanged.

Layout (every key optional; units in the names)::

    {"scenario": str, "calibration": bool, "quick": bool, "seed": int, "frame_index": int,
     "time_s": float, "dim": 2 | 3, "r0_m": [x, y, z], "diameter_m": float, "band_hz": [f_min, f_max],
     "targets": [{"name", "kind", "position_m": [x, y, z], "diameter_m", "moving",
                  "velocity_m_s": [vx, vy, vz], "depth_below_surface_m"}, …],
     "medium": {"z_surface_m", "ls_m", "la_m", "l_ext_m", "envelope", "frame_displacement_m",
                "interface_reflection"},
     "fibres": [{"position_m": [x, y, z], "alpha_rad", "length_m"}, …], …any other key}

Frames carry ``frame_index``, ``time_s``, ``dim``, ``targets`` (and ``medium`` under a scattering
layer); a calibration acquisition (the target alone in water) carries ``calibration: true``, ``r0_m``
and ``diameter_m``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

__all__ = ["Truth", "TargetTruth", "MediumTruth", "FibreTruth"]

_R = TypeVar("_R", bound="_Record")


class _Invalid:
    """Marker: a value that does not fit its field (kept verbatim in ``extra``)."""


_INVALID = _Invalid()


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _number(v: Any) -> Any:
    return v if _is_number(v) else _INVALID


def _integer(v: Any) -> Any:
    return v if isinstance(v, int) and not isinstance(v, bool) else _INVALID


def _boolean(v: Any) -> Any:
    return v if isinstance(v, bool) else _INVALID


def _text(v: Any) -> Any:
    return v if isinstance(v, str) else _INVALID


def _vector(n: int) -> Callable[[Any], Any]:
    def parse(v: Any) -> Any:
        ok = isinstance(v, (list, tuple)) and len(v) == n and all(_is_number(x) for x in v)
        return tuple(v) if ok else _INVALID

    return parse


def _as_list(v: Any) -> Any:
    return list(v)


def _same(v: Any) -> Any:
    return v


def _spec(parse: Callable[[Any], Any], dump: Callable[[Any], Any] = _same) -> dict[str, Any]:
    return {"parse": parse, "dump": dump}


def _vec(n: int) -> dict[str, Any]:
    return _spec(_vector(n), _as_list)


def _record(cls: type[_Record]) -> dict[str, Any]:
    def parse(v: Any) -> Any:
        return cls.from_dict(v) if isinstance(v, Mapping) else _INVALID

    return _spec(parse, lambda r: r.to_dict())


def _records(cls: type[_Record]) -> dict[str, Any]:
    def parse(v: Any) -> Any:
        if not isinstance(v, list) or not all(isinstance(e, Mapping) for e in v):
            return _INVALID
        return [cls.from_dict(e) for e in v]

    return _spec(parse, lambda rs: [r.to_dict() for r in rs])


class _Record:
    """from_dict/to_dict for a dataclass whose fields carry a (parse, dump) pair in their metadata.

    A field set to None is absent from the record; ``extra`` holds the keys no field takes, in order."""

    extra: dict[str, Any]

    def __post_init__(self) -> None:
        clash = [k for k in self.extra if k in self._keys() and getattr(self, k) is not None]
        if clash:
            raise ValueError(f"extra: keys {clash} are fields of {type(self).__name__}; set the fields instead")

    @classmethod
    def _keys(cls) -> dict[str, dataclasses.Field[Any]]:
        record: Any = cls  # every subclass is a dataclass
        return {f.name: f for f in dataclasses.fields(record) if f.name != "extra"}

    @classmethod
    def from_dict(cls: type[_R], d: Mapping[str, Any]) -> _R:
        """The typed view of a JSON object (values that do not fit a field go to ``extra``)."""
        if not isinstance(d, Mapping):
            raise TypeError(f"{cls.__name__}.from_dict: expected a mapping (JSON object), got {type(d).__name__}")
        fields = cls._keys()
        known: dict[str, Any] = {}
        extra: dict[str, Any] = {}
        for k, v in d.items():
            f = fields.get(k)
            parsed = f.metadata["parse"](v) if f is not None else _INVALID
            if parsed is _INVALID:
                extra[k] = v
            else:
                known[k] = parsed
        make: Callable[..., _R] = cls  # a dataclass: fields as keywords
        return make(**known, extra=extra)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object: fields in declaration order (None: absent), then ``extra``."""
        out: dict[str, Any] = {}
        for name, f in self._keys().items():
            v = getattr(self, name)
            if v is not None:
                out[name] = f.metadata["dump"](v)
        out.update(self.extra)
        return out


@dataclass
class TargetTruth(_Record):
    """One target of a frame: name, kind, centre position (m), diameter (m), whether it moves, its
    velocity (m/s, moving targets) and its depth below the scattering layer's surface (m)."""

    name: str | None = field(default=None, metadata=_spec(_text))
    kind: str | None = field(default=None, metadata=_spec(_text))
    position_m: tuple[float, float, float] | None = field(default=None, metadata=_vec(3))
    diameter_m: float | None = field(default=None, metadata=_spec(_number))
    moving: bool | None = field(default=None, metadata=_spec(_boolean))
    velocity_m_s: tuple[float, float, float] | None = field(default=None, metadata=_vec(3))
    depth_below_surface_m: float | None = field(default=None, metadata=_spec(_number))
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def position(self) -> np.ndarray:
        """Centre (x, y, z) in metres as an array (ValueError if the record has none)."""
        if self.position_m is None:
            raise ValueError(f"target {self.name!r}: the truth has no position_m")
        return np.array(self.position_m, dtype=float)

    @property
    def diameter(self) -> float:
        """Diameter (m) (ValueError if the record has none)."""
        if self.diameter_m is None:
            raise ValueError(f"target {self.name!r}: the truth has no diameter_m")
        return float(self.diameter_m)

    @property
    def velocity(self) -> np.ndarray:
        """Velocity (m/s) as an array; zero when the record has none (a static target)."""
        return np.zeros(3) if self.velocity_m_s is None else np.array(self.velocity_m_s, dtype=float)


@dataclass
class MediumTruth(_Record):
    """The scattering layer: surface depth, scattering/absorption/extinction lengths (m), the background
    envelope model, the scatterers' displacement between frames (m) and the interface reflection."""

    z_surface_m: float | None = field(default=None, metadata=_spec(_number))
    ls_m: float | None = field(default=None, metadata=_spec(_number))
    la_m: float | None = field(default=None, metadata=_spec(_number))
    l_ext_m: float | None = field(default=None, metadata=_spec(_number))
    envelope: str | None = field(default=None, metadata=_spec(_text))
    frame_displacement_m: float | None = field(default=None, metadata=_spec(_number))
    interface_reflection: float | None = field(default=None, metadata=_spec(_number))
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class FibreTruth(_Record):
    """One fibre of a fibrous medium: centre (m), tilt α (rad) and length (m)."""

    position_m: tuple[float, float, float] | None = field(default=None, metadata=_vec(3))
    alpha_rad: float | None = field(default=None, metadata=_spec(_number))
    length_m: float | None = field(default=None, metadata=_spec(_number))
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class Truth(_Record):
    """Ground truth of one acquisition (module doc); `to_dict` is the JSON layout frames carry."""

    scenario: str | None = field(default=None, metadata=_spec(_text))
    calibration: bool | None = field(default=None, metadata=_spec(_boolean))
    quick: bool | None = field(default=None, metadata=_spec(_boolean))
    seed: int | None = field(default=None, metadata=_spec(_integer))
    frame_index: int | None = field(default=None, metadata=_spec(_integer))
    time_s: float | None = field(default=None, metadata=_spec(_number))
    dim: int | None = field(default=None, metadata=_spec(_integer))
    r0_m: tuple[float, float, float] | None = field(default=None, metadata=_vec(3))
    diameter_m: float | None = field(default=None, metadata=_spec(_number))
    band_hz: tuple[float, float] | None = field(default=None, metadata=_vec(2))
    targets: list[TargetTruth] | None = field(default=None, metadata=_records(TargetTruth))
    medium: MediumTruth | None = field(default=None, metadata=_record(MediumTruth))
    fibres: list[FibreTruth] | None = field(default=None, metadata=_records(FibreTruth))
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def r0(self) -> np.ndarray:
        """Calibration position r0 (x, y, z) in metres as an array (ValueError if the record has none)."""
        if self.r0_m is None:
            raise ValueError("truth: no r0_m (not a calibration acquisition)")
        return np.array(self.r0_m, dtype=float)

    @property
    def diameter(self) -> float:
        """Calibrated target's diameter (m) (ValueError if the record has none)."""
        if self.diameter_m is None:
            raise ValueError("truth: no diameter_m (not a calibration acquisition)")
        return float(self.diameter_m)

    def target(self, name: str) -> TargetTruth:
        """The target called `name` (KeyError naming the known ones if absent)."""
        for t in self.targets or []:
            if t.name == name:
                return t
        raise KeyError(f"target {name!r}: expected one of {[t.name for t in self.targets or []]}")

    def merged(self, other: Mapping[str, Any]) -> Truth:
        """This truth with the keys of the JSON object `other` added (or replaced), as `dict.update`."""
        return Truth.from_dict({**self.to_dict(), **other})
