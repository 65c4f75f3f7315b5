"""Regular imaging grids, 2D (x–z) and 3D (x–y–z) (docs/design.md §3)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from .geometry import from_xyz, to_xyz

if TYPE_CHECKING:
    from .acquisition import Acquisition

__all__ = ["Grid", "Roi"]


def _axis(start: float, step: float, n: int) -> np.ndarray:
    return start + step * np.arange(n)


@dataclass(frozen=True)
class Grid:
    """Regular grid. Axes are uniform; y is None for a 2D (x–z) grid.

    Arrays defined on the grid have shape (N_x, N_z) in 2D and (N_x, N_y, N_z) in 3D.
    """

    x: np.ndarray
    z: np.ndarray
    y: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("x", "y", "z"):
            a = getattr(self, name)
            if a is None:
                continue
            a = np.asarray(a, dtype=np.float64)
            if a.ndim != 1 or a.size < 1:
                raise ValueError(f"grid.{name}: expected a non-empty 1D axis")
            if a.size > 1 and not np.allclose(np.diff(a), a[1] - a[0], rtol=1e-6, atol=0):
                raise ValueError(f"grid.{name}: expected a uniform axis")
            object.__setattr__(self, name, a)

    @classmethod
    def regular(
        cls,
        x_range: tuple[float, float],
        z_range: tuple[float, float],
        spacing: float,
        y_range: tuple[float, float] | None = None,
    ) -> Grid:
        """Grid covering the ranges (metres) with the given spacing."""

        def ax(r: tuple[float, float]) -> np.ndarray:
            n = int(np.floor((r[1] - r[0]) / spacing + 1e-9)) + 1
            return _axis(r[0], spacing, n)

        return cls(ax(x_range), ax(z_range), None if y_range is None else ax(y_range))

    @classmethod
    def centred(cls, centre: tuple[float, ...], shape: tuple[int, ...], spacing: float | tuple[float, ...]) -> Grid:
        """Grid of the given shape ((N_x, N_z) or (N_x, N_y, N_z)) whose index N//2 sits on centre."""
        sp = np.broadcast_to(np.asarray(spacing, dtype=float), (len(shape),))
        if len(shape) not in (2, 3):
            raise ValueError(f"shape: expected 2 or 3 dimensions, got {shape}")
        return cls.from_axes([_axis(c - (n // 2) * d, d, n) for c, n, d in zip(centre, shape, sp, strict=True)])

    @classmethod
    def from_axes(cls, axes: Sequence[np.ndarray]) -> Grid:
        """Grid from its axes in array order: (x, z) in 2D, (x, y, z) in 3D (the order of `axes`)."""
        if len(axes) == 2:
            return cls(axes[0], axes[1])
        if len(axes) == 3:
            return cls(axes[0], axes[2], axes[1])
        raise ValueError(f"axes: expected 2 (x, z) or 3 (x, y, z) axes, got {len(axes)}")

    @classmethod
    def for_acquisition(
        cls,
        acq: Acquisition,
        band: tuple[float, float],
        x_range: tuple[float, float] | None = None,
        y_range: tuple[float, float] | None = None,
        z_range: tuple[float, float] | None = None,
        spacing: float | None = None,
    ) -> Grid:
        """Default imaging grid of an acquisition (docs/design.md §3), each part overridable.

        Depths: the record's time window, z = c0 t/2 (from 2λ). Lateral: the aperture widened by the
        transmit fan at the deepest point (z s/c), at most twice the aperture. Spacing: λ_min/3 (2D) or
        λ_min/2 (3D), λ_min = c0/f_max.
        """
        lam = acq.c0 / band[1]
        step = spacing or lam / (3 if acq.probe.is_linear else 2)
        t = acq.times
        z = z_range or (max(acq.c0 * t[0] / 2, 2 * lam), acq.c0 * t[-1] / 2)
        s = np.abs(acq.sequence.sines).max(axis=0)
        fan = z[1] * s / np.sqrt(1 - s**2)  # per axis: tan θ = s/c with c = √(1 − s²) (docs/design.md §4)
        half = [min(a / 2 + f, a) for a, f in zip(acq.probe.aperture, fan, strict=True)]
        x = x_range or (-half[0], half[0])
        if acq.probe.is_linear:
            return cls.regular(x, z, step)
        return cls.regular(x, z, step, y_range=y_range or (-half[1], half[1]))

    @property
    def ndim(self) -> int:
        return 2 if self.y is None else 3

    @property
    def axes(self) -> tuple[np.ndarray, ...]:
        return (self.x, self.z) if self.y is None else (self.x, self.y, self.z)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(a.size for a in self.axes)

    @property
    def spacing(self) -> tuple[float, ...]:
        return tuple(float(a[1] - a[0]) if a.size > 1 else 1.0 for a in self.axes)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def to_xyz(self, coords: ArrayLike) -> np.ndarray:
        """Grid coordinates ((x, z) in 2D, (x, y, z) in 3D; one point or (..., ndim)) → positions
        (x, y, z), y = 0 in 2D (docs/design.md §3; `fpcore.geometry.to_xyz`)."""
        return to_xyz(coords, self.ndim)

    def from_xyz(self, r: ArrayLike) -> np.ndarray:
        """Positions (x, y, z) (one or (..., 3)) → grid coordinates, (x, z) in 2D (docs/design.md §3)."""
        return from_xyz(r, self.ndim)

    def centre_index_point(self) -> np.ndarray:
        """Position (x, y, z) of the node with index N//2 along each axis (y = 0 in 2D)."""
        return self.to_xyz([a[a.size // 2] for a in self.axes])

    def points(self) -> np.ndarray:
        """All nodes as (size, 3) positions (x, y, z), in C order of the grid's shape."""
        mesh = np.meshgrid(*self.axes, indexing="ij")
        return self.to_xyz(np.stack([m.ravel() for m in mesh], axis=1))

    def position(self, index: tuple[int, ...]) -> np.ndarray:
        """(x, y, z) of a node given its index tuple."""
        return self.to_xyz([a[i] for a, i in zip(self.axes, index, strict=True)])

    def nearest_index(self, r: ArrayLike) -> tuple[int, ...]:
        """Index of the node nearest to position r = (x, y, z)."""
        coords = self.from_xyz(r)
        return tuple(
            int(np.clip(np.rint((c - a[0]) / (a[1] - a[0] if a.size > 1 else 1.0)), 0, a.size - 1))
            for c, a in zip(coords, self.axes, strict=True)
        )


@dataclass(frozen=True)
class Roi:
    """A region of interest (docs/design.md §3): the box x_range × (y_range) × z_range (m) and the grid
    step it is imaged at; y_range None: a 2D (x–z) region. `grid` makes the regular grid over it."""

    x_range: tuple[float, float]
    z_range: tuple[float, float]
    spacing: float
    y_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        for name in ("x_range", "y_range", "z_range"):
            r = getattr(self, name)
            if r is not None and not r[0] <= r[1]:
                raise ValueError(f"roi.{name}: expected (min, max) in metres, got {r}")
        if not self.spacing > 0:
            raise ValueError(f"roi.spacing: expected > 0 m, got {self.spacing}")

    @property
    def ndim(self) -> int:
        return 2 if self.y_range is None else 3

    def grid(self, spacing: float | None = None) -> Grid:
        """The regular grid covering the region, at `spacing` (m; default: the region's own step)."""
        return Grid.regular(
            self.x_range, self.z_range, self.spacing if spacing is None else spacing, y_range=self.y_range
        )
