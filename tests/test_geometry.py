"""fpcore.geometry: direction cosines, the 2D↔3D coordinate mapping and the mirror direction (docs/design.md §3–4)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore import Grid
from fpcore.geometry import cosines, from_xyz, mirror_direction, to_xyz


def test_cosines_complete_unit_directions() -> None:
    s = np.array([[0.0, 0.0], [0.3, 0.0], [0.2, -0.4], [-0.6, 0.5]])
    c = cosines(s)
    assert np.allclose(s[:, 0] ** 2 + s[:, 1] ** 2 + c**2, 1.0, rtol=0, atol=1e-15)
    assert np.all(c > 0) and c[0] == 1.0
    assert c[1] == np.sqrt(1 - 0.3**2)


def test_xyz_mapping_round_trips_in_2d_and_3d() -> None:
    xz = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert np.array_equal(to_xyz(xz, 2), [[1.0, 0.0, 2.0], [3.0, 0.0, 4.0]])
    assert np.array_equal(to_xyz([1.0, 2.0], 2), [1.0, 0.0, 2.0])
    r = np.array([[1.0, 5.0, 2.0], [3.0, -1.0, 4.0]])
    assert np.array_equal(from_xyz(r, 2), xz)  # y is dropped in the x–z plane
    assert np.array_equal(from_xyz(to_xyz(xz, 2), 2), xz)
    assert np.array_equal(from_xyz(r, 3), r) and np.array_equal(to_xyz(r, 3), r)
    with pytest.raises(ValueError, match="coords"):
        to_xyz(r, 2)
    with pytest.raises(ValueError, match="r: expected"):
        from_xyz(xz, 2)


def test_grid_helpers_follow_the_grid_dimension() -> None:
    g2 = Grid.centred((0.0, 20e-3), (5, 7), 1e-3)
    g3 = Grid.centred((0.0, 1e-3, 20e-3), (5, 4, 7), 1e-3)
    r = np.array([1e-3, 2e-3, 21e-3])
    assert np.array_equal(g2.from_xyz(r), [1e-3, 21e-3])
    assert np.array_equal(g3.from_xyz(r), r)
    assert np.array_equal(g2.position((2, 3)), g2.to_xyz([g2.x[2], g2.z[3]]))
    assert g2.nearest_index(r) == (3, 4)
    assert np.array_equal(g2.points()[:, 1], np.zeros(g2.size))
    back = Grid.from_axes(g3.axes)
    assert all(np.array_equal(a, b) for a, b in zip(back.axes, g3.axes, strict=True)) and back.y is not None
    assert Grid.from_axes(g2.axes).y is None and Grid.from_axes(g2.axes).shape == g2.shape


def test_mirror_direction_is_the_tilted_unit_vector() -> None:
    t = mirror_direction(np.deg2rad(30.0), np.deg2rad(90.0))
    assert np.linalg.norm(t) == pytest.approx(1.0)
    assert np.allclose(t, [0.0, np.cos(np.deg2rad(30.0)), 0.5], atol=1e-15)
    assert np.array_equal(mirror_direction(0.0), [1.0, 0.0, 0.0])


def test_mean_secants_are_the_fans_averages() -> None:
    """⟨1/cos φ⟩ over a line aperture D at range R has the closed form (a√(1 + a²) + asinh a)/(2a), a = D/(2R); over
    a square it is the mean of √(1 + (ρx² + ρy²)/R²) (a dense Monte Carlo); both → 1 far away. ⟨1/c⟩ over a span of
    sines S per axis is 1 + S²/24 per axis to leading order, and 1 for a single direction."""
    from fpcore.geometry import secant_over_aperture, secant_over_sines

    d, r = 10e-3, np.array([5e-3, 25e-3, 1.0])
    a = d / (2 * r)
    np.testing.assert_allclose(
        secant_over_aperture([d], r), (a * np.sqrt(1 + a**2) + np.arcsinh(a)) / (2 * a), rtol=1e-9
    )
    rho = np.random.default_rng(0).uniform(-d / 2, d / 2, (400_000, 2))
    mc = np.mean(np.sqrt(1 + (rho**2).sum(1) / 8e-3**2))
    assert secant_over_aperture([d, d], 8e-3) == pytest.approx(mc, rel=1e-3)
    assert secant_over_aperture([d, d], 10.0) == pytest.approx(1.0, abs=1e-6)
    assert secant_over_sines([0.0, 0.0]) == pytest.approx(1.0, abs=1e-12)
    assert secant_over_sines([0.1, 0.1]) == pytest.approx(1 + 2 * 0.01 / 24, rel=2e-6)  # + O(S⁴): 1.5e-6
    s = np.random.default_rng(1).uniform(-0.4, 0.4, (400_000, 2))
    assert secant_over_sines([0.8, 0.8]) == pytest.approx(np.mean(1 / np.sqrt(1 - (s**2).sum(1))), rel=1e-3)
