"""PNG figures in the layout of the paper's Figure 2: cross-sections of γ over the confocal image.

Top row: the confocal image in dB (grey, −30…0 dB re its maximum), where a target deep in a scattering
medium is lost in the multiple-scattering fog. Bottom row: the same sections with each target's γ-map
over it, in dB re that map's value at the target's detection, one hue per target (red, green, …; the paper
draws the 10 mm sphere in red and the 8 mm one in green). γ is a normalised amplitude (a Cauchy–Schwarz ratio,
docs/design.md §4.7), so its dB are 20·log10(γ/γ_det); only γ ≥ ``threshold``·γ_det is coloured (0.6: −4.4 dB),
and γ above γ_det takes the top colour (γ is often largest just under the interface, where the detector's local
null level is high too, so a map's maximum is not the detection's scale).

Both rows carry a white scale bar and, when the target's diameter is known (the fingerprint's
``diameter_m`` state, or the ground truth), the dashed outline of the sphere of that diameter centred
on the detection, cut by the section plane; else a dotted 1 mm ring around the detection. There is no
marker on the detection itself: it would hide γ's spot, a few pixels wide. The ground truth, when
given, is a cyan diamond. 2D grids give one (x, z) section; 3D grids give (x, z) through the first
target and (y, z) through each target.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fpcore import Grid
from fpcore.geometry import to_xyz

__all__ = ["Target", "gamma_over_confocal", "peak_position", "targets_over_confocal", "tracks_over_confocal"]

DB_FLOOR = -30.0
#: (dim, bright) RGB of the γ overlay of the 1st, 2nd, … target (red and green as in the paper).
HUES: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((0.45, 0.0, 0.0), (1.0, 0.1, 0.05)),  # red
    ((0.0, 0.35, 0.0), (0.15, 1.0, 0.15)),  # green
    ((0.0, 0.15, 0.5), (0.2, 0.6, 1.0)),  # blue
    ((0.4, 0.0, 0.4), (1.0, 0.3, 1.0)),  # magenta
)
MM = 1e3
RING_MM = 1.0  # radius of the ring around a detection of unknown size, mm


@dataclass
class Target:
    """One target's γ-map and what is known about it; positions are [x, y, z] in metres (y ignored on
    a 2D grid)."""

    name: str
    gamma: np.ndarray
    found: np.ndarray
    diameter: float | None = None
    truth: np.ndarray | None = None
    c_gamma: float | None = None


def _reference_value(grid: Any, target: Target) -> float:
    """γ at the target's detection: the largest γ on the nodes next to `found` (a refined peak lies between
    nodes), or γ's maximum when that is not positive."""
    g = np.asarray(target.gamma)
    axes = (grid.x, grid.z) if grid.y is None else (grid.x, grid.y, grid.z)
    coords = np.asarray(target.found, dtype=np.float64)
    coords = coords[[0, 2]] if grid.y is None else coords
    near = tuple(
        slice(max(i - 1, 0), i + 2)
        for i in (int(np.argmin(np.abs(np.asarray(a) - c))) for a, c in zip(axes, coords, strict=True))
    )
    value = float(g[near].max()) if g[near].size else 0.0
    return value if value > 0 else max(float(g.max()), 1e-30)


def peak_position(grid: Any, gamma: np.ndarray) -> np.ndarray:
    """[x, y, z] (m) of γ's maximum on a grid (``fpcore.grid.Grid`` or the wire ``Grid``; y = 0 in 2D)."""
    idx = np.unravel_index(int(np.argmax(gamma)), gamma.shape)
    axes = (grid.x, grid.z) if grid.y is None else (grid.x, grid.y, grid.z)
    return to_xyz([float(a[k]) for a, k in zip(axes, idx, strict=True)], len(axes))


@dataclass
class _Section:
    plane: str  # "xz" or "yz"
    index: int | None  # index along the normal axis (None: the 2D grid itself)
    title: str
    extent: list[float]  # imshow extent, mm
    xlabel: str


def _edges(axis: np.ndarray) -> tuple[float, float]:
    """First and last pixel edges of a regular axis, mm (nodes are pixel centres)."""
    half = (float(axis[1] - axis[0]) if axis.size > 1 else 1e-4) / 2
    return (float(axis[0]) - half) * MM, (float(axis[-1]) + half) * MM


def _sections(grid: Grid, targets: Sequence[Target]) -> list[_Section]:
    """(x, z) through the first target, then (y, z) through each target (3D; repeated planes once)."""
    z0, z1 = _edges(grid.z)
    x_ext = [*_edges(grid.x), z1, z0]
    if grid.ndim == 2:
        return [_Section("xz", None, "(x, z)", x_ext, "x (mm)")]
    j0 = grid.nearest_index(targets[0].found)[1]
    out = [_Section("xz", j0, f"(x, z) at y = {grid.y[j0] * MM:.1f} mm", x_ext, "x (mm)")]
    seen: set[int] = set()
    for t in targets:
        i = grid.nearest_index(t.found)[0]
        if i in seen:
            continue
        seen.add(i)
        out.append(
            _Section(
                "yz", i, f"(y, z) at x = {grid.x[i] * MM:.1f} mm\nthrough {t.name}", [*_edges(grid.y), z1, z0], "y (mm)"
            )
        )
    return out


def _cut(vol: np.ndarray, sec: _Section) -> np.ndarray:
    """The section of a grid-shaped array, rows = z."""
    if sec.index is None:
        return vol.T
    return (vol[:, sec.index, :] if sec.plane == "xz" else vol[sec.index, :, :]).T


def _in_plane(p: np.ndarray, sec: _Section) -> tuple[float, float]:
    """(horizontal, z) of a point in a section, mm."""
    return (p[0] * MM, p[2] * MM) if sec.plane == "xz" else (p[1] * MM, p[2] * MM)


def _off_plane(grid: Grid, p: np.ndarray, sec: _Section) -> float:
    """Distance of a point from the section plane, m (0 on a 2D grid)."""
    if sec.index is None:
        return 0.0
    return (
        abs(float(p[1]) - float(grid.y[sec.index]))
        if sec.plane == "xz"
        else abs(float(p[0]) - float(grid.x[sec.index]))
    )


def _nice_length(span_mm: float) -> float:
    """A 1-2-5 length (mm) of at most about a third of ``span_mm``."""
    best = 1.0
    for decade in (0.1, 1.0, 10.0, 100.0):
        for m in (1.0, 2.0, 5.0):
            if m * decade <= span_mm / 3:
                best = m * decade
    return best


def _overlay_cmap(k: int) -> Any:
    """Colour map of the k-th target's γ (dB): dim hue, half transparent at the floor → bright, opaque at 0 dB."""
    from matplotlib.colors import LinearSegmentedColormap

    dim, bright = HUES[k % len(HUES)]
    return LinearSegmentedColormap.from_list(f"gamma{k}", [(*dim, 0.55), (*bright, 1.0)])


def targets_over_confocal(
    path: str | Path,
    grid: Grid,
    confocal: np.ndarray,
    targets: Sequence[Target],
    title: str = "",
    threshold: float = 0.6,
) -> None:
    """The paper's Figure 2 for one frame: confocal sections in dB (top row) and the same with each
    target's γ in dB over it (bottom row), scale bars, detections, sphere outlines; written to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    if not targets:
        raise ValueError("targets: expected at least one γ-map to draw")
    if not 0 < threshold < 1:
        raise ValueError(f"threshold: expected a fraction of γ at the detection in (0, 1), got {threshold:g}")
    for t in targets:
        if t.gamma.shape != grid.shape:
            raise ValueError(f"{t.name}: γ has shape {t.gamma.shape}, expected the grid's {grid.shape}")
    if confocal.shape != grid.shape:
        raise ValueError(f"confocal: shape {confocal.shape}, expected the grid's {grid.shape}")
    floor_db = 20 * math.log10(threshold)
    conf_db = 10 * np.log10(confocal / max(float(confocal.max()), 1e-30) + 1e-12)
    # Each γ in dB re its own value at the detection, not its map's maximum: γ is often largest just under the
    # interface, where the detector's local null level is too (fpcore.metrics.detect), and a spot 0.56 × that
    # maximum would vanish under the threshold (the demo's last frame, 2026-12-07).
    gamma_db = [20 * np.log10(np.maximum(t.gamma, 1e-30) / _reference_value(grid, t)) for t in targets]
    secs = _sections(grid, targets)
    widths = [s.extent[1] - s.extent[0] for s in secs]
    height = abs(secs[0].extent[2] - secs[0].extent[3])
    bar = _nice_length(min(widths))
    panel_h = 3.0
    fig_w = min(panel_h * sum(widths) / height + 2.6, 24.0)
    fig, axes = plt.subplots(
        2, len(secs), figsize=(fig_w, 2 * panel_h + 1.3), squeeze=False, width_ratios=widths, layout="constrained"
    )
    for c, sec in enumerate(secs):
        for row in (0, 1):
            ax = axes[row, c]
            ax.set_facecolor("black")
            grey = ax.imshow(
                _cut(conf_db, sec),
                extent=sec.extent,
                cmap="gray",
                vmin=DB_FLOOR,
                vmax=0,
                aspect="equal",
                interpolation="nearest",
            )
            if row == 1:
                for k, gdb in enumerate(gamma_db):
                    g = np.ma.masked_less(_cut(gdb, sec), floor_db)
                    ax.imshow(
                        g,
                        extent=sec.extent,
                        cmap=_overlay_cmap(k),
                        vmin=floor_db,
                        vmax=0.0,
                        aspect="equal",
                        interpolation="nearest",
                    )
            for k, t in enumerate(targets):
                colour = HUES[k % len(HUES)][1]
                h, v = _in_plane(t.found, sec)
                off = _off_plane(grid, t.found, sec)
                in_plane = off <= max(grid.spacing)
                # No marker on the detection itself: it would hide γ's spot (a few pixels wide).
                if t.diameter:
                    r2 = (t.diameter / 2) ** 2 - off**2  # the sphere cut by this plane
                    if r2 > 0:
                        ax.add_patch(Circle((h, v), math.sqrt(r2) * MM, fill=False, ls="--", lw=1.4, ec=colour))
                elif in_plane:
                    ax.add_patch(Circle((h, v), RING_MM, fill=False, ls=":", lw=1.4, ec=colour))
                if in_plane and row == 1 and t.c_gamma is not None:
                    right = h > 0.5 * (sec.extent[0] + sec.extent[1])  # the label on the side with room for it
                    ax.text(
                        h - RING_MM if right else h + RING_MM,
                        v + RING_MM,
                        f"C$_γ$ = {t.c_gamma:.1f}",
                        color=colour,
                        ha="right" if right else "left",
                        va="top",
                        fontsize=9,
                        fontweight="bold",
                        clip_on=True,
                        bbox={"facecolor": "black", "alpha": 0.6, "pad": 1.5, "lw": 0},
                    )
                if t.truth is not None and _off_plane(grid, t.truth, sec) <= max(grid.spacing):
                    ax.plot(*_in_plane(t.truth, sec), "D", mfc="none", mec="cyan", ms=12, mew=1.0)
            ax.add_artist(
                AnchoredSizeBar(
                    ax.transData,
                    bar,
                    f"{bar:g} mm",
                    "lower left",
                    pad=0.4,
                    color="white",
                    frameon=False,
                    size_vertical=height / 60,
                    fontproperties={"size": 9},
                )
            )
            ax.set_xlim(sec.extent[0], sec.extent[1])
            ax.set_ylim(sec.extent[2], sec.extent[3])
            if row == 0:
                ax.set_title(sec.title, fontsize=10)
            else:
                ax.set_xlabel(sec.xlabel)
            if c == 0:
                ax.set_ylabel(("confocal image" if row == 0 else "γ over confocal") + "\nz (mm)")
    fig.colorbar(grey, ax=axes[0, :], label="confocal (dB re max)", shrink=0.9, pad=0.01, aspect=15)
    for k in reversed(range(len(targets))):  # the first target's bar nearest the maps
        fig.colorbar(
            ScalarMappable(Normalize(floor_db, 0.0), _overlay_cmap(k)),
            ax=axes[1, :],
            shrink=0.9,
            pad=0.01,
            aspect=15,
            label=f"γ {targets[k].name} (dB re its detection)",
        )
    handles = []
    for k, t in enumerate(targets):
        colour = HUES[k % len(HUES)][1]
        handles.append(
            Line2D(
                [],
                [],
                ls="--",
                color=colour,
                label=f"{t.name}: outline of d = {t.diameter * MM:g} mm centred on its detection",
            )
            if t.diameter
            else Line2D([], [], ls=":", color=colour, label=f"{t.name}: {RING_MM:g} mm ring around its detection")
        )
    if any(t.truth is not None for t in targets):
        handles.append(Line2D([], [], ls="none", marker="D", mfc="none", mec="cyan", label="ground truth"))
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=9, frameon=False)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def gamma_over_confocal(
    path: str | Path,
    grid: Grid,
    confocal: np.ndarray,
    gamma: np.ndarray,
    found: np.ndarray,
    truth: np.ndarray | None = None,
    title: str = "",
    threshold: float = 0.6,
    *,
    name: str = "target",
    diameter: float | None = None,
    c_gamma: float | None = None,
) -> None:
    """One γ-map over the confocal image (`targets_over_confocal` with a single `Target`); ``diameter``
    (m) draws the target's outline at ``found``, ``c_gamma`` labels it."""
    targets_over_confocal(
        path,
        grid,
        confocal,
        [
            Target(
                name,
                gamma,
                np.asarray(found, float),
                diameter,
                None if truth is None else np.asarray(truth, float),
                c_gamma,
            )
        ],
        title=title,
        threshold=threshold,
    )


def tracks_over_confocal(
    path: str | Path, grid: Grid, confocal: np.ndarray, history: list[dict], title: str = ""
) -> None:
    """Tracks against the truth over the confocal image (dB; 3D: the x–z section at y = 0), with one zoom
    per target and the distance to the truth per frame (issue 5 figure).

    ``history``: one entry per frame, ``{"frame_index", "tracks": [{"id", "fingerprint", "position_m"}],
    "truth": [{"name", "position_m", "diameter_m"}]}``; a track is compared with the truth of the target
    its fingerprint is named after. Optional: a track's ``"cr_radius_m"`` (drawn under its error) and a
    frame's ``"argmax": [{"name", "position_m"}]``, the per-frame global maxima (× and their error).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    sec = confocal[:, grid.nearest_index(np.zeros(3))[1], :] if grid.ndim == 3 else confocal
    img = 10 * np.log10(sec.T / max(float(sec.max()), 1e-30) + 1e-12)
    ext = [grid.x[0] * MM, grid.x[-1] * MM, grid.z[-1] * MM, grid.z[0] * MM]
    names = sorted(
        {t["name"] for h in history for t in h.get("truth", [])}
        | {tr["fingerprint"] for h in history for tr in h["tracks"]}
    )
    colours = {n: HUES[k % len(HUES)][1] for k, n in enumerate(names)}
    truth = {
        n: np.array(
            [[h["frame_index"], *t["position_m"]] for h in history for t in h.get("truth", []) if t["name"] == n]
        ).reshape(-1, 4)
        for n in names
    }
    argmax = {
        n: np.array(
            [[h["frame_index"], *a["position_m"]] for h in history for a in h.get("argmax", []) if a["name"] == n]
        ).reshape(-1, 4)
        for n in names
    }
    tracks: dict[tuple[str, int], list[list[float]]] = {}
    cr: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for h in history:
        for tr in h["tracks"]:
            tracks.setdefault((tr["fingerprint"], tr["id"]), []).append([h["frame_index"], *tr["position_m"]])
            if tr.get("cr_radius_m") is not None:
                cr.setdefault((tr["fingerprint"], tr["id"]), []).append((h["frame_index"], tr["cr_radius_m"]))
    fig = plt.figure(figsize=(5 + 4 * len(names), 8), constrained_layout=True)
    gs = fig.add_gridspec(2, 1 + len(names), height_ratios=[1.4, 1])
    ax0 = fig.add_subplot(gs[0, 0])
    zooms = [fig.add_subplot(gs[0, 1 + k]) for k in range(len(names))]
    ax_err = fig.add_subplot(gs[1, :])
    for ax in [ax0, *zooms]:
        ax.imshow(img, extent=ext, cmap="gray", vmin=-30, vmax=0, aspect="equal")
        for n in names:
            tru = truth[n]
            if tru.size:
                ax.plot(tru[:, 1] * MM, tru[:, 3] * MM, "-", color="cyan", lw=2.5, alpha=0.8)
                ax.plot(tru[-1, 1] * MM, tru[-1, 3] * MM, "o", mfc="none", mec="cyan", ms=9)  # last (or static)
                d = next((t.get("diameter_m") for h in history for t in h.get("truth", []) if t["name"] == n), None)
                if d:
                    ax.add_patch(
                        Circle((tru[0, 1] * MM, tru[0, 3] * MM), d / 2 * MM, fill=False, ec=colours[n], ls=":", lw=1)
                    )
        for (n, tid), pts in tracks.items():
            p = np.array(pts)
            ax.plot(p[:, 1] * MM, p[:, 3] * MM, ".-", color=colours[n], ms=4, lw=1, label=f"track {tid} ({n})")
        for n, a in argmax.items():
            if a.size:
                ax.plot(
                    a[:, 1] * MM, a[:, 3] * MM, "x", color=colours[n], ms=5, alpha=0.7, label=f"per-frame argmax ({n})"
                )
    ax0.set_xlim(ext[0], ext[1])
    ax0.set_ylim(ext[2], ext[3])
    ax0.plot([], [], "-", color="cyan", lw=2.5, label="truth")
    ax0.legend(loc="lower left", fontsize=7)
    ax_err.set_title("distance of each track to its target's truth, per frame", fontsize=9)
    ax0.set_title(
        (f"{title}\n" if title else "") + "tracks and truth (cyan, ○ last) over the confocal\nimage"
        f"{' at y = 0' if grid.ndim == 3 else ''} (dB); dotted: target outline",
        fontsize=9,
    )
    for ax in [ax0, *zooms]:
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("z (mm)")
    for ax, n in zip(zooms, names, strict=True):
        pts = [truth[n][:, [1, 3]]] + [np.array(p)[:, [1, 3]] for (m, _), p in tracks.items() if m == n]
        allp = np.concatenate([p for p in pts if p.size]) * MM if any(p.size for p in pts) else np.zeros((1, 2))
        centre = truth[n][:, [1, 3]].mean(axis=0) * MM if truth[n].size else allp.mean(axis=0)
        half = max(1.0, 0.75 * float(np.ptp(allp, axis=0).max()) + 0.3)
        half = min(half, 5.0)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] + half, centre[1] - half)
        ax.set_title(f"zoom on {n}", fontsize=9)

    def plot_errors(n: str, rows: np.ndarray, style: str, label: str) -> None:
        """Distance (mm) of rows [frame, x, y, z] to target n's truth in the same frame."""
        tru = {int(f): r for f, *r in truth[n]}
        e = np.array([(f, np.linalg.norm(np.array(r) - tru[int(f)]) * MM) for f, *r in rows if int(f) in tru])
        if e.size:
            ax_err.semilogy(e[:, 0], np.maximum(e[:, 1], 1e-3), style, color=colours[n], ms=5, label=label)

    for (n, tid), pts in tracks.items():
        plot_errors(n, np.array(pts), "o-", f"track {tid} ({n})")
        if (n, tid) in cr:
            c = np.array(cr[(n, tid)])
            ax_err.semilogy(
                c[:, 0], c[:, 1] * MM, "-", color=colours[n], lw=3, alpha=0.3, label=f"Cramér–Rao radius ({n})"
            )
    for n, a in argmax.items():
        plot_errors(n, a, "x:", f"per-frame argmax ({n})")
    ax_err.axhline(1.0, color="k", ls="--", lw=0.8, label="1 mm")
    ax_err.set_xlabel("frame")
    ax_err.set_ylabel("distance to truth (mm)")
    ax_err.legend(fontsize=7, ncol=4)
    fig.savefig(path, dpi=110)
    plt.close(fig)
