"""Small geometric conventions shared by the library (docs/design.md §3–4).

* A propagation direction is given by its sines (s_x, s_y); its cosine is c = √(1 − s_x² − s_y²)
  (docs/design.md §4; the plane wave e^{-ik(s·ρ + c z)} travels into z > 0) — `cosines`.
* Positions are (x, y, z) in metres. A 2D (x–z) problem lives in the plane y = 0: its coordinates
  (x, z) map to (x, 0, z) and back (docs/design.md §3) — `to_xyz`, `from_xyz` (and `Grid.to_xyz`,
  `Grid.from_xyz`).
* A straight segment (mirror, fibre) tilted by α from the x axis towards +z and turned by an azimuth
  about z has the unit vector t̂ = (cos α cos φ, cos α sin φ, sin α) (paper, Methods "Numerical
  computation of the fingerprint operator"; docs/design.md §4.5) — `mirror_direction`.
* A straight leg of depth d below a flat surface, at angle φ from the normal, is d/cos φ long; its mean
  secant ⟨1/cos φ⟩ over a uniform fan of rays (an aperture seen from a range, a span of sines) sets the
  legs' extinction e^{−q d/ℓ_ext} (docs/design.md §6.3) — `secant_over_aperture`, `secant_over_sines`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["cosines", "to_xyz", "from_xyz", "mirror_direction", "secant_over_aperture", "secant_over_sines"]

#: Gauss–Legendre nodes per lateral axis of the mean secants (smooth integrands: the line aperture's closed form to
#: 1e-9 with rays to 45°, tests/test_geometry.py).
_QUADRATURE = np.polynomial.legendre.leggauss(24)


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


def _rectangle_quadrature(widths: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Nodes ρ² = ρx² + ρy² and weights (summing to 1) of the uniform mean over a rectangle of per-axis widths."""
    x, wt = _QUADRATURE
    r2, weights = np.zeros(1), np.ones(1)
    for width in np.atleast_1d(np.asarray(widths, dtype=np.float64)):
        r2 = (r2[:, None] + (0.5 * float(width) * x[None, :]) ** 2).ravel()
        weights = (weights[:, None] * (0.5 * wt[None, :])).ravel()
    return r2, weights


def secant_over_aperture(aperture: ArrayLike, ranges: ArrayLike) -> np.ndarray:
    """⟨1/cos φ⟩ = ⟨√(1 + ρ²/R²)⟩ of the rays from a point at range R (`ranges`, m, any shape) on the axis to the
    points of an aperture (per-axis widths, m: one for a line array, two for a rectangle), uniform over it."""
    r = np.asarray(ranges, dtype=np.float64)
    r2, weights = _rectangle_quadrature(aperture)
    flat = r.ravel()
    out = np.empty(flat.size)
    for lo in range(0, flat.size, 4096):  # bounded memory: 4096 ranges × the nodes at a time
        rr = flat[lo : lo + 4096, None]
        out[lo : lo + 4096] = np.sqrt(1.0 + r2[None, :] / rr**2) @ weights
    return out.reshape(r.shape)


def secant_over_sines(span: ArrayLike) -> float:
    """⟨1/c⟩ = ⟨1/√(1 − s²)⟩ of plane waves whose sines are uniform over ±span/2 per axis (one or two axes)."""
    s2, weights = _rectangle_quadrature(span)
    return float((1.0 / np.sqrt(1.0 - s2)) @ weights)
