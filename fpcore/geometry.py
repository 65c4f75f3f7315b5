"""Small geometric conventions shared by the library (docs/design.md §3–4).

* A propagation direction is given by its sines (s_x, s_y); its cosine is c = √(1 − s_x² − s_y²)
  (docs/design.md §4; the plane wave e^{-ik(s·ρ + c z)} travels into z > 0) — `cosines`.
* Positions are (x, y, z) in metres. A 2D (x–z) problem lives in the plane y = 0: its coordinates
  (x, z) map to (x, 0, z) and back (docs/design.md §3) — `to_xyz`, `from_xyz` (and `Grid.to_xyz`,
  `Grid.from_xyz`).
* A straight segment (mirror, fibre) tilted by α from the x axis towards +z and turned by an azimuth
  about z has the unit vector t̂ = (cos α cos φ, cos α sin φ, sin α) (paper, Methods "Numerical
  computation of the fingerprint operator"; docs/design.md §4.5) — `mirror_direction`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["cosines", "to_xyz", "from_xyz", "mirror_direction"]


def cosines(sines: ArrayLike) -> np.ndarray:
    """c = √(1 − s_x² − s_y²) per direction (docs/design.md §4), float64, for sines of shape (N, 2)."""
    s = np.asarray(sines, dtype=np.float64)
    return np.sqrt(1.0 - s[:, 0] ** 2 - s[:, 1] ** 2)


def to_xyz(coords: ArrayLike, ndim: int) -> np.ndarray:
    """Grid coordinates → positions (x, y, z) (docs/design.md §3): (x, z) ↦ (x, 0, z) for ndim = 2,
    (x, y, z) unchanged for ndim = 3. Works on one point (ndim,) or on points (..., ndim)."""
    c = np.asarray(coords, dtype=np.float64)
    if c.shape[-1:] != (ndim,):
        raise ValueError(f"coords: expected a last axis of {ndim} (grid coordinates), got shape {c.shape}")
    if ndim == 3:
        return c
    if ndim == 2:
        return np.stack([c[..., 0], np.zeros_like(c[..., 0]), c[..., 1]], axis=-1)
    raise ValueError(f"ndim: expected 2 or 3, got {ndim}")


def from_xyz(r: ArrayLike, ndim: int) -> np.ndarray:
    """Positions (x, y, z) → grid coordinates (docs/design.md §3): (x, z) for ndim = 2 (y dropped),
    (x, y, z) for ndim = 3. Works on one position (3,) or on positions (..., 3)."""
    p = np.asarray(r, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"r: expected positions (x, y, z) along the last axis, got shape {p.shape}")
    if ndim == 3:
        return p
    if ndim == 2:
        return p[..., [0, 2]]
    raise ValueError(f"ndim: expected 2 or 3, got {ndim}")


def mirror_direction(alpha: float, azimuth: float = 0.0) -> np.ndarray:
    """Unit vector t̂ of a segment tilted by α (rad) from the x axis towards +z, turned by `azimuth`
    (rad) about z: (cos α cos φ, cos α sin φ, sin α) (paper, Methods; docs/design.md §4.5)."""
    return np.array([np.cos(alpha) * np.cos(azimuth), np.cos(alpha) * np.sin(azimuth), np.sin(alpha)])
