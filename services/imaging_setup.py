"""Imaging set-up for frames like a given one: the Imager on its grid (on a CUDA device when one is
chosen) and the memory checks made before anything is allocated (docs/design.md §4.3, fpcore.budget).

Shared by the pipeline (``services.pipeline``, which re-exports these names), `fp locate` and
`fp characterise`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from fpcore import Acquisition, Grid, Imager, ImagingConfig, budget
from fpcore.imaging_gpu import make_imager as make_device_imager

__all__ = ["check_grid_axes", "check_imaging_budget", "imaging_estimate", "make_imager"]


def make_imager(
    acq: Acquisition,
    band: tuple[float, float],
    grid: Grid | None = None,
    *,
    ranges: dict[str, Any] | None = None,
    n_freq: int | None = None,
    n_out: int | None = None,
    eps: float | None = None,
    n_fingerprints: int = 1,
    memory_budget: int | None = None,
    time_weighting: bool = False,
) -> Imager:
    """An Imager for frames like ``acq``: ``grid``, else ``Grid.for_acquisition`` with ``ranges``
    (x_range, y_range, z_range, spacing); ``n_out`` output directions per lateral axis (None: the
    elements); ``eps`` the NUFFT tolerance (None: fpcore's default); ``time_weighting``: each frame weighted by
    1/v(t) before γ (``fpcore.ImagingConfig.time_weighting``)."""
    if grid is None:
        check_grid_axes(acq, band, ranges or {}, memory_budget)
        grid = Grid.for_acquisition(acq, band, **(ranges or {}))
    check_imaging_budget(acq, band, grid, n_freq, n_out, n_fingerprints, memory_budget)
    out_sines = None
    if n_out:
        from fpcore import output_sines

        out_sines = output_sines(acq.probe, acq.c0, band[1], n=n_out)
    extra = {} if eps is None else {"eps": eps}
    # On a CUDA device (fp --device, FP_DEVICE) the whole frame's imaging runs there; else the host Imager.
    return make_device_imager(ImagingConfig(grid, band, n_freq, out_sines, time_weighting=time_weighting, **extra))


def check_grid_axes(
    acq: Acquisition, band: tuple[float, float], ranges: Mapping[str, Any], memory_budget: int | None = None
) -> None:
    """Refuse (``fpcore.budget.BudgetError``) grid axes whose node count alone exceeds the budget, before they
    are made: the axis extents are bounded by the options' ranges, else by the record (z) and twice the aperture
    (x, y; ``Grid.for_acquisition``)."""
    lam = acq.c0 / band[1] if band[1] > 0 else float("inf")
    step = ranges.get("spacing") or lam / 3
    t_last = abs(acq.t0) + acq.n_samples / acq.fs
    apert = acq.probe.aperture
    bounds = {
        "--x": ranges.get("x_range") or (-apert[0], apert[0]),
        "--z": ranges.get("z_range") or (2 * lam, acq.c0 * t_last / 2),
    }
    if not acq.probe.is_linear:
        bounds["--y"] = ranges.get("y_range") or (-apert[1], apert[1])
    for option, (lo, hi) in bounds.items():
        nodes = (hi - lo) / step + 1
        if not nodes >= 2:
            raise ValueError(
                f"imaging grid axis {option}: [{lo:g}, {hi:g}] m holds fewer than 2 nodes at a spacing of {step:g} m "
                f"(expected a spacing below the range; for z the record's time window reaches {acq.c0 * t_last / 2:g} "
                "m: check the sampling frequency and initial time)"
            )
        budget.check(
            f"imaging grid axis {option} ({nodes:.3g} nodes at a {step * 1e3:.3g} mm spacing)",
            8 * nodes,
            budget=memory_budget,
        )


def imaging_estimate(
    acq: Acquisition,
    band: tuple[float, float],
    grid: Grid,
    n_freq: int | None,
    n_out: int | None,
    n_fingerprints: int = 1,
) -> float:
    """Estimated peak bytes of imaging one frame like ``acq`` on ``grid`` (``fpcore.budget.imaging_bytes``):
    the spectrum's bins, the output directions ``Imager.out_sines_for`` will make, the grid."""
    n_fft, n_f = budget.spectrum_bins(acq.n_samples, acq.fs, band, n_freq)
    probe = acq.probe
    s_max = min(0.95, acq.c0 / (2 * probe.pitch * probe.centre_frequency))
    width = (float(np.ptp(grid.x)), float(np.ptp(grid.y)) if grid.y is not None else 0.0)
    axes = None if probe.is_linear else probe.grid_axes()
    counts: tuple[int, ...] = (probe.n_elements,) if axes is None else (axes[0].size, axes[1].size)
    if not probe.is_linear and axes is None:
        side = int(np.ceil(np.sqrt(probe.n_elements)))
        counts = (side, side)
    n_o = budget.output_directions(counts, s_max, band[1], acq.c0, width, n_out)
    return budget.imaging_bytes(grid.shape, n_f, n_o, acq.sequence.n_waves, probe.n_elements, n_fft, n_fingerprints)


def check_imaging_budget(
    acq: Acquisition,
    band: tuple[float, float],
    grid: Grid,
    n_freq: int | None,
    n_out: int | None,
    n_fingerprints: int = 1,
    memory_budget: int | None = None,
) -> None:
    """Refuse (BudgetError) imaging whose estimate (:func:`imaging_estimate`) exceeds the memory budget."""
    est = imaging_estimate(acq, band, grid, n_freq, n_out, n_fingerprints)
    budget.check(
        f"imaging {acq.probe.n_elements} elements × {acq.sequence.n_waves} waves × {acq.n_samples} samples "
        f"on a {'×'.join(map(str, grid.shape))} grid (n_freq {n_freq or 'all bins'}, n_out {n_out or 'default'})",
        est,
        "a smaller grid (--x/--y/--z, --spacing), fewer frequencies (--n-freq) or output directions (--n-out)",
        budget=memory_budget,
    )
