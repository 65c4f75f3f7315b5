"""PresumTransform (fpcore/kernel_presum.py) against the direct sum (docs/design.md §5)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from fpcore.grid import Grid  # noqa: E402
from fpcore.kernel import direct_sum, wavevectors  # noqa: E402
from fpcore.kernel_presum import PresumTransform, lattice  # noqa: E402

C0 = 1540.0
FREQS = np.linspace(3e6, 5e6, 5)
DS = 0.037


def _tensor(ax: np.ndarray) -> np.ndarray:
    yy, xx = np.meshgrid(ax, ax, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def _sines(ndim: int) -> tuple[np.ndarray, np.ndarray]:
    """Output sines: a symmetric linspace (half-integer multiples of δs); transmits: integer multiples of
    2δs, so m = n_o + n_i has both parities — one lattice with different offsets per set."""
    if ndim == 2:
        so = (np.arange(20) - 9.5) * DS
        si = np.arange(-3, 4) * 2 * DS
        return np.stack([so, np.zeros_like(so)], 1), np.stack([si, np.zeros_like(si)], 1)
    return _tensor((np.arange(6) - 2.5) * DS), _tensor(np.arange(-1, 2) * DS)


def _check(grid: Grid, so: np.ndarray, si: np.ndarray, seed: int = 0, **kw: object) -> float:
    rng = np.random.default_rng(seed)
    T = PresumTransform(FREQS, so, si, C0, grid, nthreads=2, **kw)
    K = wavevectors(FREQS, so, si, C0, grid.ndim)
    w = (rng.standard_normal(K.shape[0]) + 1j * rng.standard_normal(K.shape[0])).astype(np.complex64)
    got = T(w)
    assert got.shape == grid.shape and got.dtype == np.complex64
    ref = direct_sum(w, K, grid.points()).reshape(grid.shape)
    return float(np.abs(got - ref).max() / np.abs(ref).max())


@pytest.mark.parametrize("shape", [(33, 40), (32, 27)])
@pytest.mark.parametrize("lateral", ["exact", "nufft"])
def test_2d_matches_direct_sum(shape: tuple[int, int], lateral: str) -> None:
    grid = Grid.centred((0.6e-3, 14e-3), shape, 0.08e-3)  # off-centre laterally, deep
    assert _check(grid, *_sines(2), lateral=lateral) < 1e-4


@pytest.mark.parametrize("shape", [(9, 10, 11), (8, 7, 12)])
@pytest.mark.parametrize("lateral", ["exact", "nufft"])
def test_3d_matches_direct_sum(shape: tuple[int, int, int], lateral: str) -> None:
    grid = Grid.centred((0.5e-3, -0.3e-3, 12e-3), shape, 0.1e-3)
    assert _check(grid, *_sines(3), seed=1, lateral=lateral) < 1e-4


def test_integer_multiples_anisotropic_spacing_and_folded_band() -> None:
    """Plain integer multiples of δs; coarse depth spacing (K_zΔz spans more than 2π: the band axis folds)."""
    so = np.stack([np.arange(-12, 13) * DS, np.zeros(25)], 1)
    si = np.stack([np.arange(-2, 3) * 3 * DS, np.zeros(5)], 1)
    grid = Grid(np.arange(24) * 0.07e-3 - 1e-3, np.arange(20) * 0.45e-3 + 5e-3)
    T = PresumTransform(FREQS, so, si, C0, grid)
    assert T._nglob == T._nfz  # the union of the bands is longer than the fine grid: folded
    assert _check(grid, so, si, seed=2) < 1e-4


def test_complex128_batch_and_threads_agree() -> None:
    so, si = _sines(2)
    grid = Grid.centred((0.0, 10e-3), (16, 21), 0.08e-3)
    rng = np.random.default_rng(3)
    n = FREQS.size * so.shape[0] * si.shape[0]
    w = rng.standard_normal((2, n)) + 1j * rng.standard_normal((2, n))
    one = PresumTransform(FREQS, so, si, C0, grid, nthreads=1)(w)
    two = PresumTransform(FREQS, so, si, C0, grid, nthreads=3)(w)
    assert one.shape == (2, *grid.shape)
    K = wavevectors(FREQS, so, si, C0, 2)
    ref = direct_sum(w[1], K, grid.points()).reshape(grid.shape)
    assert np.abs(one[1] - ref).max() < 1e-4 * np.abs(ref).max()
    assert np.abs(one - two).max() < 1e-5 * np.abs(one).max()


def test_applicable() -> None:
    so2, si2 = _sines(2)
    so3, si3 = _sines(3)
    assert PresumTransform.applicable(so2, si2, ndim=2)
    assert PresumTransform.applicable(so3, si3)
    assert PresumTransform.applicable(so2[:, 0], si2[:, 0], ndim=2)  # 1D sines
    assert PresumTransform.applicable(np.linspace(-0.9, 0.9, 128), np.linspace(-0.2, 0.2, 3), ndim=2)
    ((ds, a_o, a_i),) = lattice(so2, si2, 2)
    assert ds == pytest.approx(DS, rel=1e-9) and a_o == pytest.approx(-9.5 * DS)
    rng = np.random.default_rng(4)
    assert not PresumTransform.applicable(rng.uniform(-0.5, 0.5, 20), si2[:, 0], ndim=2)
    assert not PresumTransform.applicable(so2[:, 0], np.array([0.0, 0.1 * np.sqrt(2) * DS]), ndim=2)
    jitter = so3.copy()
    jitter[5, 1] += 1e-6  # y off the lattice: fails in 3D only
    assert not PresumTransform.applicable(jitter, si3)
    assert PresumTransform.applicable(jitter[:, 0], si3[:, 0], ndim=2)
    with pytest.raises(ValueError, match="lattice"):
        PresumTransform(FREQS, jitter, si3, C0, Grid.centred((0, 0, 1e-2), (4, 4, 4), 1e-4))
    with pytest.raises(ValueError, match="weights"):
        PresumTransform(FREQS, so2, si2, C0, Grid.centred((0, 1e-2), (8, 8), 1e-4))(np.ones(3))
