"""The γ-over-confocal figure's overlay scale (services/viewing/figures.py)."""

from __future__ import annotations

import numpy as np

from fpcore.grid import Grid
from services.viewing.figures import Target, _reference_value, gamma_over_confocal


def _grid(dim: int) -> Grid:
    x = np.linspace(-5e-3, 5e-3, 21)
    z = np.linspace(15e-3, 30e-3, 31)
    return Grid(x, z, x.copy() if dim == 3 else None)


def test_the_overlay_is_scaled_to_gamma_at_the_detection_not_the_maps_maximum(tmp_path) -> None:
    """γ larger under the interface than at the target (the demo's last frame: the target's γ 0.56 × the map's
    maximum) must not hide the target's spot: the overlay's 0 dB is γ at the detection, found between nodes."""
    for dim in (2, 3):
        grid = _grid(dim)
        gamma = np.full(grid.shape, 0.01, dtype=np.float32)
        target = grid.nearest_index(np.array([2e-3, 0.0, 22e-3]))
        surface = grid.nearest_index(np.array([-3e-3, 0.0, 15e-3]))
        gamma[target] = 0.5
        gamma[surface] = 1.0
        found = np.array([2.1e-3, 0.1e-3, 22.2e-3])  # a refined peak, between nodes
        assert _reference_value(grid, Target("t", gamma, found)) == 0.5
        # nothing positive near the detection: the map's maximum, as before
        assert _reference_value(grid, Target("t", np.where(gamma == 1.0, 1.0, 0.0), found)) == 1.0
        png = tmp_path / f"fig{dim}.png"
        confocal = np.ones(grid.shape)
        gamma_over_confocal(png, grid, confocal, gamma, found, truth=found, name="t", diameter=4e-3, c_gamma=7.5)
        assert png.stat().st_size > 5_000
