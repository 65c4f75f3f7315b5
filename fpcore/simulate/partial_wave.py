"""Exact partial-wave scattering of elastic / fluid / rigid spheres (3D) and cylinders (2D) in a fluid.

Coefficients (Faran 1951, J. Acoust. Soc. Am. 23, 405; Hickling 1962) are obtained by solving the
boundary conditions mode by mode, in the physicist's e^{-iωt} convention, for a unit plane wave

    3D:  p_inc = Σ_n (2n+1) i^n j_n(kr) P_n(cos Θ),      p_sc = Σ_n (2n+1) i^n A_n h_n^{(1)}(kr) P_n(cos Θ)
    2D:  p_inc = Σ_n ε_n i^n J_n(kr) cos nΘ,              p_sc = Σ_n ε_n i^n A_n H_n^{(1)}(kr) cos nΘ

(Θ: angle between the incident propagation direction and the observation direction from the centre,
ε_0 = 1, ε_n = 2). The solid is described by Lamé potentials (sphere: u = ∇φ + ∇×∇×(r ψ);
cylinder: u = ∇φ + ∇×(ψ ẑ)) and three conditions hold at r = a for n ≥ 1: continuity of normal
displacement, σ_rr = −p, σ_rθ = 0 (n = 0: the first two only). Material losses enter as complex
wave speeds c/(1 + iδ) (Im k > 0 in this convention).

This package's spectra use numpy's e^{-i2πft} (docs/design.md §4.1): the physical field is the complex
conjugate, i.e. A_n → conj(A_n), i^n → (−i)^n, h^{(1)} → h^{(2)} (see `special`). For a lossless
scatterer S_n = 1 + 2A_n is unimodular (energy conservation), which the tests check together with the
rigid (A_n = −j_n'/h_n') and fluid limits.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import scipy.special as sp

__all__ = [
    "Elastic",
    "sphere_coefficients",
    "cylinder_coefficients",
    "rigid_sphere_coefficients",
    "fluid_sphere_coefficients",
    "rigid_cylinder_coefficients",
    "fluid_cylinder_coefficients",
]


_F = TypeVar("_F", bound=Callable[..., np.ndarray])


def _quiet(fn: _F) -> _F:
    """Silence over/underflow of high-order Bessel functions at small arguments (masked out anyway)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with np.errstate(all="ignore"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


@dataclass(frozen=True)
class Elastic:
    """Isotropic solid: density (kg/m³), compressional and shear speeds (m/s), loss factors δ (1/(2Q)).

    Defaults: the paper's sphere (Supplementary S3, Table S1): ρ = 5700, c_p = 2700, c_t = 2000.
    A shear speed of 0 makes it a fluid.
    """

    density: float = 5700.0
    c_p: float = 2700.0
    c_t: float = 2000.0
    loss_p: float = 0.0
    loss_t: float = 0.0

    @property
    def is_fluid(self) -> bool:
        return self.c_t == 0.0


def _cp(mat: Elastic) -> complex:
    return mat.c_p / (1 + 1j * mat.loss_p)


def _ct(mat: Elastic) -> complex:
    return mat.c_t / (1 + 1j * mat.loss_t)


def _sph_j(n: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """j_n, j_n', j_n'' (complex-safe)."""
    j = sp.spherical_jn(n, z)
    jp = sp.spherical_jn(n, z, derivative=True)
    jpp = -2.0 / z * jp - (1.0 - n * (n + 1) / z**2) * j
    return j, jp, jpp


def _cyl_j(n: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """J_n, J_n', J_n'' (complex-safe)."""
    j = sp.jv(n, z)
    jp = sp.jvp(n, z)
    jpp = -jp / z - (1.0 - n**2 / z**2) * j
    return j, jp, jpp


def _active(ka: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Modes that matter: n ≤ n_terms(ka) (beyond, |A_n| ~ (ka/n)^{2n+1} underflows; A_n := 0)."""
    return np.asarray(n) <= np.ceil(ka + 4.05 * np.cbrt(ka) + 12)


def _solve_modes(rows: list[list[np.ndarray]], rhs: list[np.ndarray], n: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Solve the per-mode 3×3 systems (2×2 where n = 0) for the first unknown A_n (0 where inactive)."""
    shape = np.broadcast(*[x for r in rows for x in r], *rhs).shape
    m = np.zeros(shape + (3, 3), dtype=np.complex128)
    b = np.zeros(shape + (3,), dtype=np.complex128)
    for i in range(3):
        for j in range(3):
            m[..., i, j] = rows[i][j]
        b[..., i] = rhs[i]
    n0 = np.broadcast_to(n, shape) == 0
    # n = 0: the shear potential does not exist; decouple it with an identity row/column.
    m[n0, :, 2] = 0.0
    m[n0, 2, :] = 0.0
    m[n0, 2, 2] = 1.0
    b[n0, 2] = 0.0
    off = ~np.broadcast_to(active, shape)
    m[off] = np.eye(3)
    b[off] = 0.0
    # Row equilibration keeps the solve well conditioned across orders.
    scale = np.max(np.abs(m), axis=-1, keepdims=True)
    scale[scale == 0] = 1.0
    x = np.linalg.solve(m / scale, (b / scale[..., 0])[..., None])[..., 0]
    return x[..., 0]


@_quiet
def sphere_coefficients(
    ka: np.ndarray, n: np.ndarray, mat: Elastic, rho0: float = 1000.0, c0: float = 1500.0
) -> np.ndarray:
    """Faran coefficients A_n(ka) of an elastic sphere (physicist's convention, see module doc).

    ka and n broadcast together (e.g. ka[:, None], n[None, :]). The sphere radius only enters via ka.
    """
    if mat.is_fluid:
        return fluid_sphere_coefficients(ka, n, mat.density / rho0, mat.c_p / c0, mat.loss_p)
    ka = np.asarray(ka, dtype=np.float64)
    n = np.asarray(n)
    x = ka
    cl, ct = _cp(mat), _ct(mat)
    x1 = x * c0 / cl
    x2 = x * c0 / ct
    nn = n * (n + 1.0)
    j = sp.spherical_jn(n, x)
    jp = sp.spherical_jn(n, x, derivative=True)
    h = j + 1j * sp.spherical_yn(n, x)
    hp = jp + 1j * sp.spherical_yn(n, x, derivative=True)
    jl, jlp, jlpp = _sph_j(n, x1)
    jt, jtp, jtpp = _sph_j(n, x2)
    rho1 = mat.density
    lam = rho1 * (cl**2 - 2 * ct**2)
    mu = rho1 * ct**2
    s = 1.0 / (rho0 * c0**2)
    # Unknowns (A, b', c') with potentials B = b' a²/(ρ0 c0²), C = c' a²/(ρ0 c0²).
    rows = [
        [hp, -x * x1 * jlp, -x * nn * jt],
        [h, s * (-lam * x1**2 * jl + 2 * mu * x1**2 * jlpp), s * 2 * mu * nn * (x2 * jtp - jt)],
        [np.zeros_like(h), 2 * x1 * jlp - 2 * jl, x2**2 * jtpp + (nn - 2) * jt],
    ]
    rhs = [-jp, -j, np.zeros_like(j)]
    return _solve_modes(rows, rhs, n, _active(x, n))


@_quiet
def rigid_sphere_coefficients(ka: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Rigid immovable sphere: A_n = −j_n'(ka)/h_n^{(1)}'(ka)."""
    jp = sp.spherical_jn(n, ka, derivative=True)
    a = -jp / (jp + 1j * sp.spherical_yn(n, ka, derivative=True))
    return np.where(_active(ka, n), a, 0.0)


@_quiet
def fluid_sphere_coefficients(
    ka: np.ndarray, n: np.ndarray, rho_ratio: float, c_ratio: float, loss: float = 0.0
) -> np.ndarray:
    """Fluid sphere (density ρ1 = rho_ratio ρ0, speed c1 = c_ratio c0):
    A_n = −(j_n' − Q j_n)/(h_n' − Q h_n), Q = (k1 ρ0)/(k ρ1) j_n'(k1 a)/j_n(k1 a)."""
    x = np.asarray(ka, dtype=np.float64)
    x1 = x / (c_ratio / (1 + 1j * loss))
    j = sp.spherical_jn(n, x)
    jp = sp.spherical_jn(n, x, derivative=True)
    h = j + 1j * sp.spherical_yn(n, x)
    hp = jp + 1j * sp.spherical_yn(n, x, derivative=True)
    q = (x1 / x) / rho_ratio * sp.spherical_jn(n, x1, derivative=True) / sp.spherical_jn(n, x1)
    return np.where(_active(x, n), -(jp - q * j) / (hp - q * h), 0.0)


@_quiet
def cylinder_coefficients(
    ka: np.ndarray, n: np.ndarray, mat: Elastic, rho0: float = 1000.0, c0: float = 1500.0
) -> np.ndarray:
    """Faran coefficients A_n(ka) of an infinite elastic cylinder at normal incidence (2D)."""
    if mat.is_fluid:
        return fluid_cylinder_coefficients(ka, n, mat.density / rho0, mat.c_p / c0, mat.loss_p)
    x = np.asarray(ka, dtype=np.float64)
    n = np.asarray(n)
    cl, ct = _cp(mat), _ct(mat)
    x1 = x * c0 / cl
    x2 = x * c0 / ct
    j = sp.jv(n, x)
    jp = sp.jvp(n, x)
    h = sp.hankel1(n, x)
    hp = sp.h1vp(n, x)
    jl, jlp, jlpp = _cyl_j(n, x1)
    jt, jtp, jtpp = _cyl_j(n, x2)
    rho1 = mat.density
    lam = rho1 * (cl**2 - 2 * ct**2)
    mu = rho1 * ct**2
    s = 1.0 / (rho0 * c0**2)
    rows = [
        [hp, -x * x1 * jlp, -x * n * jt],
        [h, s * (-lam * x1**2 * jl + 2 * mu * x1**2 * jlpp), s * 2 * mu * n * (x2 * jtp - jt)],
        [np.zeros_like(h), 2 * n * (jl - x1 * jlp), x2 * jtp - x2**2 * jtpp - n**2 * jt],
    ]
    rhs = [-jp, -j, np.zeros_like(j)]
    return _solve_modes(rows, rhs, n, _active(x, n))


@_quiet
def rigid_cylinder_coefficients(ka: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Rigid immovable cylinder: A_n = −J_n'(ka)/H_n^{(1)}'(ka)."""
    a = -sp.jvp(n, ka) / sp.h1vp(n, ka)
    return np.where(_active(ka, n), a, 0.0)


@_quiet
def fluid_cylinder_coefficients(
    ka: np.ndarray, n: np.ndarray, rho_ratio: float, c_ratio: float, loss: float = 0.0
) -> np.ndarray:
    """Fluid cylinder: A_n = −(J_n' − Q J_n)/(H_n' − Q H_n), Q = (k1 ρ0)/(k ρ1) J_n'(k1 a)/J_n(k1 a)."""
    x = np.asarray(ka, dtype=np.float64)
    x1 = x / (c_ratio / (1 + 1j * loss))
    q = (x1 / x) / rho_ratio * sp.jvp(n, x1) / sp.jv(n, x1)
    a = -(sp.jvp(n, x) - q * sp.jv(n, x)) / (sp.h1vp(n, x) - q * sp.hankel1(n, x))
    return np.where(_active(x, n), a, 0.0)
