"""Partial-wave (Faran) scattering: energy conservation, rigid and fluid limits, special functions,
and the sign convention of the series against the Born point scatterer (docs/design.md §4.1, §6)."""

from __future__ import annotations

import numpy as np
import scipy.special as sp

from fpcore.acquisition import Probe
from fpcore.simulate import (
    Elastic,
    ElasticCylinder,
    ElasticSphere,
    cylinder_coefficients,
    fluid_cylinder_coefficients,
    fluid_sphere_coefficients,
    radiate_points,
    rigid_cylinder_coefficients,
    rigid_sphere_coefficients,
    sphere_coefficients,
)
from fpcore.simulate.special import hankel2_0, hankel2_orders, legendre_orders, sph_hankel2_orders

KA = np.linspace(0.5, 50.0, 60)[:, None]
N = np.arange(0, 75)[None, :]
PAPER = Elastic(5700.0, 2700.0, 2000.0)  # lossless version of the paper's sphere (Supplementary Table S1)


def test_special_functions_match_scipy() -> None:
    z = np.array([0.7, 3.0, 25.0, 180.0])
    n = np.arange(31)
    h = sph_hankel2_orders(z, 30)
    ref = sp.spherical_jn(n[:, None], z[None, :]) - 1j * sp.spherical_yn(n[:, None], z[None, :])
    np.testing.assert_allclose(h, ref, rtol=1e-9)
    np.testing.assert_allclose(hankel2_orders(z, 30), sp.hankel2(n[:, None], z[None, :]), rtol=1e-9)
    x = np.linspace(-1, 1, 7)
    np.testing.assert_allclose(legendre_orders(x, 30), sp.eval_legendre(n[:, None], x[None, :]), atol=1e-12)
    zz = np.linspace(1.0, 400.0, 500)
    np.testing.assert_allclose(hankel2_0(zz), sp.hankel2(0, zz), rtol=2e-6)


def test_lossless_coefficients_conserve_energy() -> None:
    """S_n = 1 + 2A_n is unimodular for every lossless scatterer (sphere and cylinder)."""
    for coef in (
        sphere_coefficients(KA, N, PAPER),
        cylinder_coefficients(KA, N, PAPER),
        fluid_sphere_coefficients(KA, N, 1.3, 1.2),
        fluid_cylinder_coefficients(KA, N, 0.9, 0.8),
    ):
        assert np.max(np.abs(np.abs(1 + 2 * coef) - 1)) < 1e-9
    lossy = sphere_coefficients(KA, N, Elastic(5700.0, 2700.0, 2000.0, 1e-3, 1e-3))
    assert np.all(np.abs(1 + 2 * lossy) <= 1 + 1e-12)


def test_rigid_limit() -> None:
    """ρ_solid → ∞ at fixed wave speeds: the sphere (cylinder) becomes rigid and immovable."""
    heavy = Elastic(5700.0e8, 2700.0, 2000.0)
    assert np.max(np.abs(sphere_coefficients(KA, N, heavy) - rigid_sphere_coefficients(KA, N))) < 1e-4
    assert np.max(np.abs(cylinder_coefficients(KA, N, heavy) - rigid_cylinder_coefficients(KA, N))) < 1e-4


def test_low_frequency_limit_is_the_equivalent_fluid() -> None:
    """ka ≪ 1: monopole and dipole of an elastic sphere equal those of a fluid sphere with the solid's
    bulk modulus K = ρ(c_p² − 4c_t²/3) (cylinder, plane strain: K = ρ(c_p² − c_t²))."""
    ka = np.array([0.02, 0.05])[:, None]
    n = np.arange(2)[None, :]
    m = PAPER
    c_sph = np.sqrt(m.c_p**2 - 4 * m.c_t**2 / 3)
    c_cyl = np.sqrt(m.c_p**2 - m.c_t**2)
    np.testing.assert_allclose(
        sphere_coefficients(ka, n, m), fluid_sphere_coefficients(ka, n, m.density / 1000, c_sph / 1500), rtol=1e-5
    )
    np.testing.assert_allclose(
        cylinder_coefficients(ka, n, m), fluid_cylinder_coefficients(ka, n, m.density / 1000, c_cyl / 1500), rtol=1e-5
    )


def test_series_sign_convention_matches_born_point() -> None:
    """A small, weakly compressible fluid sphere scatters like a Born point t = k² γ_κ V (e^{-ikr} convention):
    checks conj/(-i)^n/h^(2) of the series against the Green function used everywhere else."""
    c0, a = 1500.0, 0.01e-3  # ka ≈ 0.08
    c1 = 1500.0 / np.sqrt(1.01)  # κ1/κ0 − 1 = 0.01, same density
    sphere = ElasticSphere(2 * a, Elastic(1000.0, c1, 0.0))
    probe = Probe.linear(5, 2e-3, 2e6, 1e6)
    sines = np.array([[0.0, 0.0], [0.2, 0.0]])
    f = np.array([1.5e6, 2.0e6])
    r = np.array([0.5e-3, 0.0, 20e-3])
    h = sphere.transfer(probe.positions, sines, f, c0, r)
    k = 2 * np.pi * f / c0
    vol = 4 / 3 * np.pi * a**3
    ref = np.stack(
        [
            radiate_points(r[None, :], np.array([kk**2 * 0.01 * vol]), probe.positions, sines, f[i : i + 1], c0, 3)[0]
            for i, kk in enumerate(k)
        ]
    )
    np.testing.assert_allclose(h, ref, rtol=1.5e-2)


def test_large_rigid_sphere_specular_amplitude_and_time() -> None:
    """Geometrical limit: a rigid sphere's backscatter amplitude → (a/2)/d (form function 1)."""
    a, c0, d = 5e-3, 1500.0, 30e-3
    sphere = ElasticSphere(2 * a, Elastic(5700.0e8, 2700.0, 2000.0))
    probe = Probe.linear(1, 1e-3, 2e6, 1e6)
    f = np.linspace(2.0e6, 2.1e6, 41)
    h = sphere.transfer(probe.positions, np.zeros((1, 2)), f, c0, np.array([0.0, 0.0, d]))[:, 0, 0]
    amp = np.abs(h).mean()
    assert abs(amp / (a / 2 / d) - 1) < 0.15
    # Phase slope ⇒ delay of the specular echo 2(d − a)/c0.
    delay = -np.polyfit(2 * np.pi * f, np.unwrap(np.angle(h)), 1)[0]
    assert abs(delay - 2 * (d - a) / c0) < 0.05e-6


def test_elastic_cylinder_transfer_runs_and_rings() -> None:
    """2D analogue: finite, outgoing, and with energy after the specular echo (elastic response)."""
    cyl = ElasticCylinder(4e-3)
    probe = Probe.linear(8, 0.5e-3, 2e6, 1e6)
    f = np.linspace(1.5e6, 2.5e6, 64)
    h = cyl.transfer(probe.positions, np.array([[0.0, 0.0]]), f, 1500.0, np.array([0.0, 0.0, 15e-3]))
    assert h.shape == (64, 8, 1) and np.all(np.isfinite(h))
    rigid = ElasticCylinder(4e-3, Elastic(5700.0e8, 2700.0, 2000.0)).transfer(
        probe.positions, np.array([[0.0, 0.0]]), f, 1500.0, np.array([0.0, 0.0, 15e-3])
    )
    assert np.linalg.norm(h - rigid) > 0.1 * np.linalg.norm(rigid)
