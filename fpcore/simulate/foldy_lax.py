"""Exact multiple scattering between point scatterers (Foldy–Lax) and the coherent wave they leave.

Each scatterer j (t-matrix t_j) is excited by ψ_j = ψ_inc(r_j) + Σ_{l≠j} G(r_j, r_l) t_l ψ_l, and the
field is ψ(r) = ψ_inc(r) + Σ_j G(r, r_j) t_j ψ_j (Foldy 1945; Lax 1951). One dense solve per frequency.

Point scatterers obey the optical theorem when Im(1/t) = −Im G(0) (energy conservation of a point
scatterer; de Vries, van Coevorden & Lagendijk, Rev. Mod. Phys. 70, 447 (1998)). With this
package's e^{-ikr} Green functions (`waves.green`), Im G(0) = −k/(4π) in 3D and −1/4 in 2D, so

    t = 1 / (x + i k/(4π))   (3D),     t = 1 / (x + i/4)   (2D),     x real,

with scattering cross-section σ_s = |t|²/(4π) (3D) and width σ_s = |t|²/(4k) (2D); x = 0 is the
resonant (unitary) limit σ_s = 4π/k² (3D), 4/k (2D). For a density n of such scatterers the
independent-scattering approximation gives the scattering mean free path ℓ_s = 1/(n σ_s), and the
coherent (ensemble-averaged) wave decays as |⟨ψ⟩| ∝ exp(−z/(2ℓ_s)) (paper Supplementary S1,
eq. ⟨ψ⟩(z, f)). `coherent_wave` measures that decay from realisations; the tests compare it with
the input ℓ_s.
"""

from __future__ import annotations

import numpy as np

from .waves import green, incident_phase

__all__ = [
    "passive_strength",
    "point_strength",
    "cross_section",
    "foldy_lax_excitation",
    "random_slab",
    "coherent_wave",
]


def point_strength(sigma_s: float, k: float, dim: int, branch: int = 1) -> complex:
    """Lossless point-scatterer t with total scattering cross-section (3D) or width (2D) σ_s."""
    if dim == 3:
        t2 = 4 * np.pi * sigma_s
        im = k / (4 * np.pi)
    elif dim == 2:
        t2 = 4 * k * sigma_s
        im = 0.25
    else:
        raise ValueError(f"dim: expected 2 or 3, got {dim}")
    x2 = 1.0 / t2 - im**2
    if x2 < -1e-12 * im**2:
        raise ValueError(f"sigma_s = {sigma_s:g} exceeds the unitary limit of a point scatterer at k = {k:g}")
    return 1.0 / (branch * np.sqrt(max(x2, 0.0)) + 1j * im)


def passive_strength(inverse_re: np.ndarray, k: float, dim: int, loss: float = 0.0) -> np.ndarray:
    """t(k) = 1/(x + i(1 + loss) Im₀(k)), Im₀ = k/(4π) (3D) or 1/4 (2D): lossless at loss = 0 at every k,
    absorbing for loss > 0 (a fixed t would violate the optical theorem away from its design k)."""
    im = k / (4 * np.pi) if dim == 3 else 0.25
    return 1.0 / (np.asarray(inverse_re, dtype=np.float64) + 1j * (1.0 + loss) * im)


def cross_section(t: complex | np.ndarray, k: float, dim: int) -> np.ndarray:
    """σ_s = |t|²/(4π) (3D) or |t|²/(4k) (2D)."""
    t2 = np.abs(np.asarray(t)) ** 2
    return t2 / (4 * np.pi) if dim == 3 else t2 / (4 * k)


def foldy_lax_excitation(
    points: np.ndarray, t: complex | np.ndarray, k: float, incident: np.ndarray, dim: int
) -> np.ndarray:
    """Exciting fields ψ (N_s, N_rhs) solving (I − G T) ψ = ψ_inc, G_jl = G(r_j, r_l) (j ≠ l), T = diag(t)."""
    p = np.asarray(points, dtype=np.float64)
    n = p.shape[0]
    if dim == 2:
        d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 2] - p[None, :, 2])
    else:
        d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
    np.fill_diagonal(d, 1.0)
    g = green(k, d, dim)
    np.fill_diagonal(g, 0.0)
    tt = np.broadcast_to(np.asarray(t, dtype=np.complex128), (n,))
    m = np.eye(n, dtype=np.complex128) - g * tt[None, :]
    return np.linalg.solve(m, np.asarray(incident, dtype=np.complex128))


def random_slab(
    rng: np.random.Generator, density: float, width: float, thickness: float, dim: int, z0: float = 0.0
) -> np.ndarray:
    """Poisson points (N, 3) in [−w/2, w/2]^(dim−1) × [z0, z0 + thickness] (y = 0 in 2D)."""
    vol = width ** (dim - 1) * thickness
    n = rng.poisson(density * vol)
    x = rng.uniform(-width / 2, width / 2, n)
    y = rng.uniform(-width / 2, width / 2, n) if dim == 3 else np.zeros(n)
    z = rng.uniform(z0, z0 + thickness, n)
    return np.stack([x, y, z], axis=1)


def coherent_wave(
    rng: np.random.Generator,
    k: float,
    t: complex,
    density: float,
    width: float,
    thickness: float,
    depths: np.ndarray,
    dim: int,
    n_real: int = 40,
    window: float | None = None,
) -> np.ndarray:
    """⟨ψ⟩(z)/ψ_inc(z) in a slab [0, thickness] of random Foldy–Lax scatterers, plane wave at normal incidence.

    The lateral average is taken analytically with a Gaussian window w(x) (std `window`, default
    width/6) centred on the axis, so edge scatterers do not bias it:
    ⟨ψ_s⟩(z) = Σ_j w(ρ_j) t ψ_j ∫ G dρ / ∫ w dρ, with ∫ G(ρ, Δz) dρ = (−i/(2k)) e^{−ik|Δz|} in 2D and
    3D alike (plane-wave spectrum of G at zero transverse wavenumber; paraxial over the window,
    valid while window² ≫ λ·thickness). Averaged over `n_real` realisations.
    """
    sig = width / 6 if window is None else window
    depths = np.asarray(depths, dtype=np.float64)
    acc = np.zeros(depths.size, dtype=np.complex128)
    for _ in range(n_real):
        pts = random_slab(rng, density, width, thickness, dim)
        inc = incident_phase(k, np.zeros((1, 2)), pts)
        psi = foldy_lax_excitation(pts, t, k, inc, dim)[:, 0]
        rho2 = pts[:, 0] ** 2 + (pts[:, 1] ** 2 if dim == 3 else 0.0)
        w = np.exp(-rho2 / (2 * sig**2))
        norm = np.sqrt(2 * np.pi) * sig if dim == 2 else 2 * np.pi * sig**2
        src = w * t * psi / norm
        dz = np.abs(depths[:, None] - pts[None, :, 2])
        scat = (src[None, :] * (-0.5j / k) * np.exp(-1j * k * dz)).sum(axis=1)
        acc += 1.0 + scat * np.exp(1j * k * depths)
    return acc / n_real
