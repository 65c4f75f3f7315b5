"""Foldy–Lax multiple scattering: optical theorem of the point scatterers, Born limit, and the
scattering mean free path measured from the decay of the coherent wave (paper Supplementary S1)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore.simulate import (
    coherent_wave,
    cross_section,
    foldy_lax_excitation,
    incident_phase,
    passive_strength,
    point_strength,
)


@pytest.mark.parametrize("dim", [2, 3])
def test_point_strength_obeys_the_optical_theorem(dim: int) -> None:
    k = 2 * np.pi
    unitary = 4 * np.pi / k**2 if dim == 3 else 4 / k
    for frac in (0.05, 0.5, 1.0):
        t = point_strength(frac * unitary, k, dim)
        np.testing.assert_allclose(cross_section(t, k, dim), frac * unitary, rtol=1e-12)
        im_g0 = k / (4 * np.pi) if dim == 3 else 0.25  # −Im G(0) for the e^{-ikr} Green function
        np.testing.assert_allclose((1 / t).imag, im_g0, rtol=1e-12)
    with pytest.raises(ValueError, match="unitary"):
        point_strength(1.5 * unitary, k, dim)
    assert np.all((1 / passive_strength(np.array([0.0, 3.0]), k, dim, loss=0.1)).imag > im_g0)


def test_weak_scatterers_reduce_to_born() -> None:
    rng = np.random.default_rng(1)
    pts = np.stack([rng.uniform(-3, 3, 12), np.zeros(12), rng.uniform(1, 6, 12)], axis=1)
    k = 2 * np.pi
    inc = incident_phase(k, np.array([[0.0, 0.0], [0.3, 0.0]]), pts)
    psi = foldy_lax_excitation(pts, 1e-4, k, inc, dim=2)
    np.testing.assert_allclose(psi, inc, atol=1e-4)


def test_scattering_mean_free_path_from_coherent_wave_decay() -> None:
    """|⟨ψ⟩(z)| ∝ exp(−z/(2ℓ_s)) with ℓ_s = 1/(n σ_s) (independent scattering) within 20 %.

    2D slab of resonant lossless point scatterers (wavelength 1, ℓ_s = 5, kℓ_s ≈ 31), 60 realisations
    of the exact Foldy–Lax solution at normal incidence.
    """
    k = 2 * np.pi
    t = point_strength(4 / k, k, 2)  # unitary limit
    ls = 5.0
    density = 1.0 / (cross_section(t, k, 2) * ls)
    depths = np.linspace(1.0, 9.0, 12)
    psi = coherent_wave(
        np.random.default_rng(7), k, t, density, width=60.0, thickness=10.0, depths=depths, dim=2, n_real=60
    )
    slope = np.polyfit(depths, np.log(np.abs(psi)), 1)[0]
    ls_measured = -1.0 / (2 * slope)
    assert abs(ls_measured / ls - 1) < 0.2
