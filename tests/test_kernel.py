"""The fast kernel equals the direct sum, and a point's map peaks at its position (docs/design.md §5, §8)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore import Grid, GridTransform, direct_sum, wavevectors


def _geometry(ndim: int, rng: np.random.Generator):
    freqs = np.linspace(2.0e6, 3.0e6, 9)
    if ndim == 2:
        so = np.stack([np.linspace(-0.6, 0.6, 17), np.zeros(17)], axis=1)
        si = np.stack([np.linspace(-0.2, 0.2, 5), np.zeros(5)], axis=1)
        grid = Grid.centred((0.4e-3, 20e-3), (40, 33), 1.5e-4)
    else:
        sx = np.linspace(-0.4, 0.4, 6)
        so = np.stack([a.ravel() for a in np.meshgrid(sx, sx, indexing="xy")], axis=1)
        si = np.array([[0.0, 0.0], [0.1, -0.05], [-0.1, 0.05]])
        grid = Grid.centred((0.2e-3, -0.1e-3, 20e-3), (14, 11, 16), 2.0e-4)
    K = wavevectors(freqs, so, si, 1500.0, ndim)
    w = (rng.standard_normal(K.shape[0]) + 1j * rng.standard_normal(K.shape[0])).astype(np.complex64)
    return K, grid, w


@pytest.mark.parametrize("ndim", [2, 3])
def test_nufft_matches_direct_sum_on_speckle(ndim: int) -> None:
    K, grid, w = _geometry(ndim, np.random.default_rng(ndim))
    fast = GridTransform(K, grid, eps=1e-5)(w)
    ref = direct_sum(w, K, grid.points()).reshape(grid.shape)
    assert fast.shape == grid.shape
    assert np.abs(fast - ref).max() <= 1e-4 * np.abs(ref).max()


def test_plan_reused_across_frames() -> None:
    K, grid, w = _geometry(2, np.random.default_rng(5))
    kern = GridTransform(K, grid, eps=1e-5)
    first = kern(w)
    second = kern(2 * w)
    assert np.allclose(second, 2 * first, rtol=1e-4, atol=1e-4 * np.abs(first).max())


@pytest.mark.parametrize("ndim", [2, 3])
def test_point_map_peaks_at_its_position(ndim: int) -> None:
    K, grid, _ = _geometry(ndim, np.random.default_rng(0))
    r = np.array([0.9e-3, -0.3e-3, 20.6e-3]) if ndim == 3 else np.array([0.9e-3, 0.0, 20.6e-3])
    coords = grid.from_xyz(r)
    data = np.exp(-1j * (K @ coords))  # a point at r: R_θθ ∝ e^{-iK·r} (docs/design.md §7 sign note)
    m = np.abs(GridTransform(K, grid, eps=1e-5)(data))
    peak = grid.position(np.unravel_index(int(m.argmax()), m.shape))
    assert np.all(np.abs(peak - r) <= np.array(grid.spacing).max() * 1.0001)
