"""Targets with rich echoes: transfer functions H(f, u_out, θ_in) at the array elements.

Every target returns the field it scatters, at each element, for each incident plane wave of unit
amplitude (e^{-i2πft} spectra, outgoing e^{-ikr}; see `waves`), as complex64 (N_f, N_u, N_θ):

* `ElasticSphere` (3D) / `ElasticCylinder` (2D): exact partial-wave (Faran) series evaluated at the
  elements with the outgoing spherical (cylindrical) Hankel functions — not a far-field formula — so
  the specular echo, the bulk reverberations inside the solid and the circumferential (Rayleigh-type,
  whispering-gallery) waves are all there (paper Supplementary S3, Extended Data Fig. 1;
  docs/design.md §4.5, §6):

      H = e^{−ik(s·ρ_c + c z_c)} Σ_n (2n+1)(−i)^n Ā_n h_n^{(2)}(k|u − r_c|) P_n(cos Θ)      (3D)
      H = e^{−ik(s x_c + c z_c)} Σ_n ε_n (−i)^n Ā_n H_n^{(2)}(k|u − r_c|) cos(nΘ)            (2D)

  with cos Θ = k̂_in · (u − r_c)/|u − r_c| and Ā_n the conjugated Faran coefficients
  (`partial_wave`). Moving the target is exact: the series is re-evaluated at the new centre; the
  coefficients (which depend on frequency only) are cached.
* `PointCluster`: point scatterers, Born (independent) or coupled by Foldy–Lax (`foldy_lax`), which
  makes a cage of a few strong scatterers ring (lesion-marker model).
* `MirrorSegment`: a straight reflector of length L, tilt α (and azimuth in 3D), as a Born line of
  points (spacing ≤ λ_min/4) with strength per unit length 2ik·r·w: in 2D (w = 1) an infinite line
  reflects a normally incident plane wave with coefficient r (∫G dx = −i/(2k) e^{−ik|z|}); in 3D
  the fibre behaves as a strip of width w (paper Methods, "Numerical computation of the fingerprint
  operator": Γ_rr diagonal along the mirror).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..geometry import cosines, from_xyz, mirror_direction
from .foldy_lax import foldy_lax_excitation, passive_strength
from .partial_wave import Elastic, cylinder_coefficients, sphere_coefficients
from .special import hankel2_orders, legendre_orders, n_terms, sph_hankel2_orders
from .waves import incident_phase, radiate_points

__all__ = [
    "Target",
    "ElasticSphere",
    "ElasticCylinder",
    "PointCluster",
    "MirrorSegment",
    "PAPER_SPHERE_MATERIAL",
]

#: Sphere of the paper (Supplementary S3, Table S1). A metal-like loss (Q ≈ 1000) makes the echo ring
#: down by 20 dB about 40 µs after the specular echo, the reverberation time the paper reports (main text).
PAPER_SPHERE_MATERIAL = Elastic(density=5700.0, c_p=2700.0, c_t=2000.0, loss_p=5e-4, loss_t=5e-4)


class Target(Protocol):
    """Anything that scatters: H(f, u, θ) for a placement `position` (m, (3,))."""

    name: str
    dim: int

    @property
    def diameter(self) -> float: ...

    def transfer(
        self, elements: np.ndarray, sines: np.ndarray, freqs: np.ndarray, c0: float, position: np.ndarray
    ) -> np.ndarray: ...


def _hat_in(sines: np.ndarray) -> np.ndarray:
    s = np.asarray(sines, dtype=np.float64)
    return np.stack([s[:, 0], s[:, 1], cosines(s)], axis=1)


@dataclass
class _PartialWaveTarget(ABC):
    """Shared Faran-series machinery: cached series weights per (frequencies, c0) and the transfer."""

    diameter: float
    material: Elastic = PAPER_SPHERE_MATERIAL
    rho0: float = 1000.0
    name: str = "target"
    dim: int = 3
    chunk: int = 64
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    @abstractmethod
    def _weights(self, ka: np.ndarray, n: np.ndarray, c0: float) -> np.ndarray:
        """Series weights for ka (N_f, 1) and orders n (N_n,) — the sphere's or the cylinder's."""

    def coefficients(self, freqs: np.ndarray, c0: float) -> np.ndarray:
        """Series weights, shape (N_f, N_n), cached per (frequencies, c0)."""
        key = (np.asarray(freqs).tobytes(), float(c0))
        if key not in self._cache:
            ka = 2 * np.pi * np.asarray(freqs, dtype=np.float64) * (0.5 * self.diameter) / c0
            n = np.arange(n_terms(ka.max()) + 1)
            self._cache[key] = self._weights(ka[:, None], n, c0)
        return self._cache[key]

    def transfer(
        self, elements: np.ndarray, sines: np.ndarray, freqs: np.ndarray, c0: float, position: np.ndarray
    ) -> np.ndarray:
        return _series_transfer(
            self.coefficients(freqs, c0),
            elements,
            sines,
            freqs,
            c0,
            np.asarray(position, dtype=np.float64),
            self.dim,
            self.chunk,
        )


@dataclass
class ElasticSphere(_PartialWaveTarget):
    """Elastic sphere of `diameter` (m) in a fluid (ρ0, c0 at evaluation) — Faran series (3D)."""

    name: str = "sphere"
    dim: int = 3

    def _weights(self, ka: np.ndarray, n: np.ndarray, c0: float) -> np.ndarray:
        """(2n+1)(−i)^n conj(A_n) — the e^{-i2πft} series weights."""
        coef = sphere_coefficients(ka, n[None, :], self.material, self.rho0, c0)
        return np.conj(coef) * ((2 * n + 1) * (-1j) ** n)[None, :]


@dataclass
class ElasticCylinder(_PartialWaveTarget):
    """Infinite elastic (or fluid, c_t = 0) cylinder along y of `diameter` (m) — Faran series (2D)."""

    name: str = "cylinder"
    dim: int = 2

    def _weights(self, ka: np.ndarray, n: np.ndarray, c0: float) -> np.ndarray:
        """ε_n (−i)^n conj(A_n), ε_0 = 1, ε_n = 2."""
        coef = cylinder_coefficients(ka, n[None, :], self.material, self.rho0, c0)
        return np.conj(coef) * (np.where(n == 0, 1.0, 2.0) * (-1j) ** n)[None, :]


def _series_transfer(
    coef: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    freqs: np.ndarray,
    c0: float,
    rc: np.ndarray,
    dim: int,
    chunk: int,
) -> np.ndarray:
    """Σ_n coef_n(f) R_n(k|u − r_c|) Y_n(cos Θ_uθ) times the incident phase at the centre."""
    el = np.asarray(elements, dtype=np.float64)
    freqs = np.asarray(freqs, dtype=np.float64)
    k = 2 * np.pi * freqs / c0
    n_f, n_n = coef.shape
    n_u, n_i = el.shape[0], sines.shape[0]
    kin = from_xyz(_hat_in(sines), dim)  # 2D: the x–z plane (docs/design.md §3)
    if dim == 2:
        kin = kin / np.linalg.norm(kin, axis=1, keepdims=True)
    vec = from_xyz(el, dim) - from_xyz(rc, dim)[None, :]
    dist = np.linalg.norm(vec, axis=1)
    if np.any(dist <= 0):
        raise ValueError("target: an element lies at the scatterer's centre")
    cos_t = np.clip((vec / dist[:, None]) @ kin.T, -1.0, 1.0)  # (N_u, N_θ)
    out = np.empty((n_u, n_i, n_f), dtype=np.complex64)
    for a in range(0, n_u, chunk):
        sl = slice(a, min(a + chunk, n_u))
        z = k[None, :] * dist[sl, None]  # (c, f)
        if dim == 3:
            radial = sph_hankel2_orders(z, n_n - 1)  # (n, c, f)
            ang = legendre_orders(cos_t[sl], n_n - 1)  # (n, c, θ)
        else:
            radial = hankel2_orders(z, n_n - 1)
            ang = np.cos(np.arange(n_n)[:, None, None] * np.arccos(cos_t[sl])[None, :, :])
        radial *= coef.T[:, None, :]
        wr = radial.view(np.float64)  # (n, c, 2f): real matmul with the real angular factor
        res = np.matmul(np.transpose(ang, (1, 2, 0)), np.transpose(wr, (1, 0, 2)))  # (c, θ, 2f)
        out[sl] = res.view(np.complex128)
    s = np.asarray(sines, dtype=np.float64)
    pin = rc[0] * s[:, 0] + (rc[1] * s[:, 1] if dim == 3 else 0.0) + rc[2] * cosines(s)
    ph = np.exp(-1j * k[:, None] * pin[None, :])  # (f, θ)
    res = np.transpose(out, (2, 0, 1)) * ph[:, None, :].astype(np.complex64)
    return np.ascontiguousarray(res, dtype=np.complex64)


@dataclass
class PointCluster:
    """Point scatterers at `offsets` (N, 3) from the placement, with t_j(k) = 1/(x_j + i(1+loss)Im₀(k))
    (`foldy_lax.passive_strength`; x_j = `inverse_t`, real, so each point is passive at every k).

    coupled=True solves Foldy–Lax among them at every frequency (multiple scattering inside the
    cluster: a ringing, spatially rich echo); coupled=False is the Born sum.
    """

    offsets: np.ndarray
    inverse_t: np.ndarray
    loss: float = 0.0
    coupled: bool = True
    name: str = "cluster"
    dim: int = 3
    size: float | None = None

    @property
    def diameter(self) -> float:
        if self.size is not None:
            return float(self.size)
        o = np.asarray(self.offsets, dtype=float)
        return float(2 * np.max(np.linalg.norm(o, axis=1))) if o.size else 0.0

    def transfer(
        self, elements: np.ndarray, sines: np.ndarray, freqs: np.ndarray, c0: float, position: np.ndarray
    ) -> np.ndarray:
        pts = np.asarray(position, dtype=np.float64)[None, :] + np.asarray(self.offsets, dtype=np.float64)
        freqs = np.asarray(freqs, dtype=np.float64)
        k = 2 * np.pi * freqs / c0
        x = np.broadcast_to(np.asarray(self.inverse_t, dtype=np.float64), (pts.shape[0],))
        t = np.stack([passive_strength(x, kk, self.dim, self.loss) for kk in k], axis=1)  # (N, N_f)
        if not self.coupled:
            return radiate_points(pts, t, elements, sines, freqs, c0, self.dim)

        last: dict[int, np.ndarray] = {}

        def excitation(m: int) -> np.ndarray:
            if m not in last:
                last.clear()
                last[m] = foldy_lax_excitation(pts, t[:, m], k[m], incident_phase(k[m], sines, pts), self.dim)
            return last[m]

        return radiate_points(pts, t, elements, sines, freqs, c0, self.dim, excitation=excitation)


@dataclass
class MirrorSegment:
    """Straight reflector (length L, tilt α, azimuth) as a Born line of points (see module doc)."""

    length: float
    alpha: float = 0.0
    azimuth: float = 0.0
    reflectivity: float = 1.0
    width: float = 1.0
    spacing: float | None = None
    name: str = "mirror"
    dim: int = 2

    @property
    def diameter(self) -> float:
        return float(self.length)

    def points(self, position: np.ndarray, h: float) -> tuple[np.ndarray, float]:
        n = max(1, int(np.ceil(self.length / h)))
        step = self.length / n
        ell = (np.arange(n) + 0.5) * step - 0.5 * self.length
        return np.asarray(position, float)[None, :] + ell[:, None] * mirror_direction(self.alpha, self.azimuth), step

    def transfer(
        self, elements: np.ndarray, sines: np.ndarray, freqs: np.ndarray, c0: float, position: np.ndarray
    ) -> np.ndarray:
        freqs = np.asarray(freqs, dtype=np.float64)
        h = self.spacing if self.spacing is not None else c0 / freqs.max() / 4
        pts, step = self.points(position, h)
        k = 2 * np.pi * freqs / c0
        w = 1.0 if self.dim == 2 else self.width
        strength = np.full(pts.shape[0], self.reflectivity * step * w, dtype=np.complex128)
        return radiate_points(pts, strength, elements, sines, freqs, c0, self.dim, spectral=2j * k)
