"""The confocal image's kernel path (issue 15, item 6): PresumTransform's exact lateral DFTs run the y outputs
in slabs of `kernel_presum_loops.SLAB_Q` q (the y sums of a slab, then its x sums, kept in cache) — checked
against the direct sum on grids whose N_y spans several slabs (odd and even, a partial last slab), with dense
(confocal) and sparse (fingerprint-like) weights, in 3-D and 2-D."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from fpcore import kernel_presum_loops as loops  # noqa: E402
from fpcore.grid import Grid  # noqa: E402
from fpcore.kernel import direct_sum, wavevectors  # noqa: E402
from fpcore.kernel_presum import PresumTransform, _pad  # noqa: E402

C0 = 1540.0
DS = 0.029
FREQS = np.linspace(3e6, 5e6, 5)


def _disc(radius: int) -> np.ndarray:
    """Output sines on a lattice of step DS, half-step offset, cut to a disc."""
    ax = (np.arange(-radius, radius) + 0.5) * DS
    yy, xx = np.meshgrid(ax, ax, indexing="ij")
    keep = xx.ravel() ** 2 + yy.ravel() ** 2 <= (radius * DS) ** 2
    return np.stack([xx.ravel()[keep], yy.ravel()[keep]], axis=1)


def _error(grid: Grid, so: np.ndarray, si: np.ndarray, sparse: bool) -> float:
    T = PresumTransform(FREQS, so, si, C0, grid, lateral="exact", nthreads=2)
    K = wavevectors(FREQS, so, si, C0, grid.ndim)
    rng = np.random.default_rng(3)
    w = (rng.standard_normal(K.shape[0]) + 1j * rng.standard_normal(K.shape[0])).astype(np.complex64)
    if sparse:  # a fingerprint's angular support: an off-centre cone of output directions
        cone = np.hypot(so[:, 0] + 2 * DS, so[:, 1] - DS) < 2.5 * DS
        w = (w.reshape(FREQS.size, so.shape[0], si.shape[0]) * cone[None, :, None]).ravel()
    got = T(w)
    assert got.shape == grid.shape and got.dtype == np.complex64
    ref = direct_sum(w, K, grid.points()).reshape(grid.shape)
    return float(np.abs(got - ref).max() / np.abs(ref).max())


@pytest.mark.parametrize("ny", [2 * 2 * loops.SLAB_Q + 3, 2 * 2 * loops.SLAB_Q + 6])
@pytest.mark.parametrize("sparse", [False, True])
def test_3d_slabs_match_direct_sum(ny: int, sparse: bool) -> None:
    so = _disc(5)
    si = np.stack([np.array([-2.0, 0.0, 2.0, 0.0]) * DS, np.array([0.0, 1.0, 0.0, -2.0]) * DS], axis=1)
    grid = Grid.centred((0.3e-3, -0.2e-3, 10e-3), (11, ny, 9), 0.1e-3)
    assert _error(grid, so, si, sparse) < 1e-4


@pytest.mark.parametrize("shape", [(31, 24), (26, 17)])
def test_2d_exact_path_matches_direct_sum(shape: tuple[int, int]) -> None:
    so = (np.arange(24) - 11.5) * DS
    si = np.arange(-3, 4) * 2 * DS
    sines = [np.stack([s, np.zeros_like(s)], 1) for s in (so, si)]
    grid = Grid.centred((0.5e-3, 12e-3), shape, 0.08e-3)
    assert _error(grid, *sines, sparse=False) < 1e-4


def test_accumulator_rows_are_not_4k_apart() -> None:
    """The tile accumulators' row length (`kernel_presum._pad`): at least what is asked, whole cache lines, and none
    of 8 rows starts within 48 floats of a multiple of 4 KiB from another (store-to-load aliasing, L1 sets)."""
    for n in [1, 186, 512, 1000, 1024, 1030, 1536, 2000, 2048, 2090, 4096, 5000]:
        padded = _pad(n)
        assert n <= padded < n + 1024 and padded % 16 == 0
        assert all(48 <= k * padded % 1024 <= 1024 - 48 for k in range(1, 8))
    assert _pad(2048) == 2096
