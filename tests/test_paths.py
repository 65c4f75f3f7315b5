"""The transport Monte Carlo of the multiple scattering (fpcore.simulate.paths, docs/design.md §6.6)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore.simulate import paths as P
from fpcore.simulate.foldy_lax import cross_section, passive_strength
from fpcore.simulate.waves import green


def _walks(dim: int, n: int = 4000, seed: int = 0, **kw: float) -> P.Paths:
    args = dict(l_max=40e-3, z_top=5e-3, start_half_width=2e-3, start_depth=4e-3)
    args.update(kw)
    return P.draw_paths(np.random.default_rng(seed), dim, 1.8e-3, n, **args)  # type: ignore[arg-type]


@pytest.mark.parametrize("dim", [2, 3])
def test_transport_kernel_is_a_probability_density(dim: int) -> None:
    """n|t|²|G(d)|² e^{−d/ℓ_s} integrates to 1 over the plane (2-D) or space (3-D): the walk's exponential step and
    isotropic direction are the ladder's own measure (module doc), for resonant point scatterers of any k."""
    k, ls = 2 * np.pi * 2.2e6 / 1500.0, 1.8e-3
    t = complex(passive_strength(np.zeros(1), k, dim)[0])
    n = 1.0 / (float(cross_section(t, k, dim)) * ls)
    d = np.linspace(1e-9, 40 * ls, 2000001)
    g2 = np.abs(green(k, d, dim)) ** 2  # the exact Green function
    shell = 4 * np.pi * d**2 if dim == 3 else 2 * np.pi * d
    total = np.trapezoid(n * abs(t) ** 2 * g2 * np.exp(-d / ls) * shell, d)
    # 3-D: exact; 2-D: the far-field |G|² = 1/(8πkd) of the walk, 1.8 % above the Hankel function's near field
    assert total == pytest.approx(1.0, rel=0.025 if dim == 2 else 1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_walks_take_exponential_isotropic_steps_and_stay_in_the_medium(dim: int) -> None:
    p = _walks(dim, thickness=8e-3, half_width=6e-3)
    assert np.all(np.diff(p.walk) >= 0)
    assert np.all((p.end[:, 2] > 5e-3) & (p.end[:, 2] < 13e-3) & (np.abs(p.end[:, 0]) <= 6e-3))
    assert np.all(p.length <= 40e-3)
    # consecutive events of one walk: orders step by one, the step is the length increment
    same = p.walk[1:] == p.walk[:-1]
    assert np.all(p.order[1:][same] == p.order[:-1][same] + 1)
    steps = np.diff(p.length)[same]
    vec = np.diff(p.end, axis=0)[same]
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), steps, rtol=1e-9)
    # unbiased only in an unbounded medium: there, mean step ℓ_s and isotropic directions
    q = _walks(dim, n=20000, thickness=np.inf, start_depth=0.5, l_max=4e-3, z_top=-1.0)
    first = q.order == 2
    d = q.end[first] - q.start[q.walk[first]]
    r = np.linalg.norm(d, axis=1)
    sel = q.length[first] < 4e-3  # the cut at l_max: compare with the truncated exponential's mean
    trunc = 1.8e-3 - 4e-3 * np.exp(-4 / 1.8) / (1 - np.exp(-4 / 1.8))
    assert r[sel].mean() == pytest.approx(trunc, rel=0.03)
    cos_z = d[:, 2] / r
    assert abs(cos_z.mean()) < 0.03
    assert (cos_z**2).mean() == pytest.approx(1 / 3 if dim == 3 else 1 / 2, abs=0.02)


def test_start_density_is_the_importance_weight() -> None:
    """With start_decay, 1/(N_w π₁) integrates the same as uniform starts: Σ start_weight = the start volume."""
    vol = (4e-3) ** 2 * 4e-3
    for decay in (None, 1.5e-3):
        p = _walks(3, n=20000, start_decay=decay)  # type: ignore[arg-type]
        assert p.start_weight.sum() == pytest.approx(vol, rel=0.05 if decay else 1e-9)


def _rig(dim: int) -> tuple[P.StraightRays, P.Synthesised, np.ndarray, np.ndarray]:
    n = 4
    x = (np.arange(n) - 1.5) * 0.34e-3
    el = np.stack([x, np.zeros(n), np.zeros(n)], axis=1)
    sines = np.stack([np.array([-0.3, -0.1, 0.1, 0.3]), np.zeros(4)], axis=1)
    freqs = np.linspace(2.0e6, 2.4e6, 9)
    ls = np.full(freqs.size, 1.8e-3)
    return P.StraightRays(el, 5e-3, dim), P.Synthesised(sines, 0.34e-3), freqs, ls


@pytest.mark.parametrize("dim", [2, 3])
def test_the_field_is_reciprocal(dim: int) -> None:
    """K(u, v) = K(v, u) in the element basis (each path with its reversed partner, module doc): recovered from
    the synthesised transmits R = K q through the invertible weights q."""
    rays, tx, freqs, ls = _rig(dim)
    p = _walks(dim, n=300, thickness=6e-3, half_width=5e-3)
    r = P.path_spectra(p, freqs, 1500.0, ls, rays, tx)
    for m in (0, 4, 8):
        k = 2 * np.pi * freqs[m] / 1500.0
        kk = r[m] @ np.linalg.inv(tx.weights(k, rays.receivers, dim).astype(np.complex128))
        assert np.abs(kk - kk.T).max() < 1e-4 * np.abs(kk).max()


def test_compiled_sums_equal_the_direct_evaluation() -> None:
    rays, tx, freqs, ls = _rig(3)
    freqs = np.linspace(2.0e6, 2.4e6, 33)
    ls = 1.8e-3 * (freqs / 2.2e6) ** 2
    p = _walks(3, n=120, thickness=6e-3, half_width=5e-3)
    fast = P.path_spectra(p, freqs, 1500.0, ls, rays, tx, la=8e-3)
    saved, P.nb = P.nb, None
    try:
        slow = P.path_spectra(p, freqs, 1500.0, ls, rays, tx, la=8e-3)
    finally:
        P.nb = saved
    assert np.abs(fast - slow).max() < 1e-2 * np.abs(slow).max()


def test_first_order_is_the_born_intensity_of_the_medium() -> None:
    """The walks' starts as single scatterers (weight n|t|²/(N_w π₁)) give on average the first order's intensity
    ∫ n|t|² |G_c(u, r)|² |G_c(r, u)|² d³r over the start box, source and receiver one element, by quadrature."""
    el = np.array([[0.0, 0.0, 0.0]])
    rays = P.StraightRays(el, 5e-3, 3)
    freqs = np.array([2.2e6])
    k = 2 * np.pi * 2.2e6 / 1500.0
    ls = 1.8e-3

    class Point(P.Synthesised):
        def weights(self, k: float, receivers: np.ndarray, dim: int) -> np.ndarray:
            return np.ones((1, 1), dtype=np.complex64)  # the element itself as the source: I = G_c(r, v)

    tx = Point(np.zeros((1, 2)), 1.0)
    acc = []
    for seed in range(40):
        p = _walks(3, n=400, seed=seed, l_max=1e-4)
        acc.append(np.abs(P.path_spectra(p, freqs, 1500.0, ls, rays, tx, la=np.inf, first_order=True)[0, 0, 0]) ** 2)
    # quadrature over the start box |x|, |y| ≤ 2 mm, 5 ≤ z ≤ 9 mm, with the legs' own extinction e^{−d_b/ℓ_s}
    g = np.linspace(-2e-3, 2e-3, 41)
    z = np.linspace(5e-3, 9e-3, 41)
    xx, yy, zz = np.meshgrid(g, g, z, indexing="ij")
    d = np.sqrt(xx**2 + yy**2 + zz**2)
    below = d * (zz - 5e-3) / zz
    integrand = (4 * np.pi / ls) * (np.abs(green(k, d, 3)) ** 2 * np.exp(-below / ls)) ** 2
    exact = np.trapezoid(np.trapezoid(np.trapezoid(integrand, z, axis=2), g, axis=1), g, axis=0)
    assert np.mean(acc) == pytest.approx(exact, rel=0.1)


def test_bad_arguments_name_the_field() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="dim"):
        P.draw_paths(rng, 4, 1e-3, 10, 1e-2, 0.0, 1e-3, 1e-3)
    with pytest.raises(ValueError, match="ls_ref"):
        P.draw_paths(rng, 3, 0.0, 10, 1e-2, 0.0, 1e-3, 1e-3)
    with pytest.raises(ValueError, match="start_depth"):
        P.draw_paths(rng, 3, 1e-3, 10, 1e-2, 0.0, 1e-3, 2e-3, thickness=1e-3)
    with pytest.raises(ValueError, match="n_walks"):
        P.draw_paths(rng, 3, 1e-3, 0, 1e-2, 0.0, 1e-3, 1e-3)
