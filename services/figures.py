"""PNG figures: γ over the confocal image (dB), 2D maps and 3D cross-sections through a point."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fpcore import Grid

__all__ = ["gamma_over_confocal"]


def _sections(grid: Grid, vol: np.ndarray, at: np.ndarray) -> list[tuple[str, np.ndarray, list[float], str, str]]:
    """(title, image (rows = vertical axis), extent mm, xlabel, ylabel) of the sections through `at`."""
    mm = 1e3
    if grid.ndim == 2:
        return [("x–z", vol.T, [grid.x[0] * mm, grid.x[-1] * mm, grid.z[-1] * mm, grid.z[0] * mm], "x (mm)", "z (mm)")]
    i, j, _ = grid.nearest_index(at)
    return [
        (f"x–z at y = {grid.y[j] * mm:.1f} mm", vol[:, j, :].T,
         [grid.x[0] * mm, grid.x[-1] * mm, grid.z[-1] * mm, grid.z[0] * mm], "x (mm)", "z (mm)"),
        (f"y–z at x = {grid.x[i] * mm:.1f} mm", vol[i, :, :].T,
         [grid.y[0] * mm, grid.y[-1] * mm, grid.z[-1] * mm, grid.z[0] * mm], "y (mm)", "z (mm)"),
    ]


def _in_plane(grid: Grid, p: np.ndarray, k: int) -> tuple[float, float]:
    return (p[0] * 1e3, p[2] * 1e3) if (grid.ndim == 2 or k == 0) else (p[1] * 1e3, p[2] * 1e3)


def gamma_over_confocal(path: str | Path, grid: Grid, confocal: np.ndarray, gamma: np.ndarray,
                        found: np.ndarray, truth: np.ndarray | None = None, title: str = "",
                        threshold: float = 0.6) -> None:
    """Confocal image in dB (grey, −30…0 dB) with γ ≥ threshold·max in colour; markers at the detection
    (and truth); 2D: one section, 3D: x–z and y–z sections through the detection."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conf_db = 10 * np.log10(confocal / max(float(confocal.max()), 1e-30) + 1e-12)
    conf_secs = _sections(grid, conf_db, found)
    gam_secs = _sections(grid, gamma, found)
    n = len(conf_secs)
    fig, axes = plt.subplots(1, 2 * n, figsize=(5 * 2 * n, 4.6), constrained_layout=True, squeeze=False)
    for k, ((name, cimg, ext, xl, yl), (_, gimg, _, _, _)) in enumerate(zip(conf_secs, gam_secs, strict=True)):
        for m, overlay in enumerate((False, True)):
            ax = axes[0, 2 * k + m]
            ax.imshow(cimg, extent=ext, cmap="gray", vmin=-30, vmax=0, aspect="equal")
            if overlay:
                g = np.ma.masked_less(gimg, threshold * float(gamma.max()))
                im = ax.imshow(g, extent=ext, cmap="autumn", alpha=0.85, aspect="equal",
                               vmin=threshold * float(gamma.max()), vmax=float(gamma.max()))
                fig.colorbar(im, ax=ax, label="γ", shrink=0.8)
                ax.plot(*_in_plane(grid, found, k), "+", color="lime", ms=14, mew=2, label="detection")
                ax.set_title(f"γ ≥ {threshold:.0%} of max over confocal, {name}")
            else:
                ax.set_title(f"confocal image (dB), {name}")
            if truth is not None:
                ax.plot(*_in_plane(grid, truth, k), "o", mfc="none", mec="cyan", ms=16, label="truth")
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            if overlay or truth is not None:
                ax.legend(loc="lower right", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
