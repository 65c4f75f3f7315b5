"""`fp characterise`: orientation and length maps from a mirror dictionary (issue 7; paper Fig. 4).

{α_opt(r), L_opt(r)} = argmax_{α, L} γ(r, α, L) (paper eq. after Fig. 4) with numerical mirror
fingerprints (fpcore.dictionary.mirror_family, FFT-correlation path). Outputs maps as NPZ, a JSON
summary in SI units (with the error against fibre truth when the file carries it) and a PNG of the
orientation vector field over the confocal image.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from services.cli.fingerprint_args import add_time_weighting_argument
from services.cli.imaging import grid_ranges, int_at_least
from services.cli.output import make_console, progress
from services.units import UnitError, parse_band, parse_length

__all__ = ["add_characterise_parser", "run_characterise"]


def _angles(text: str) -> np.ndarray:
    parts = text.split(":")
    try:
        a, b, step = (float(p) for p in parts)
    except ValueError:
        raise UnitError(
            f"--angles: expected start:stop:step in degrees, e.g. --angles=-40:40:5, got {text!r}"
        ) from None
    if not (step > 0 and a <= b and (b - a) / step <= 10_000):
        raise UnitError(f"--angles: expected start <= stop, step > 0 and at most 10000 angles, got {text!r}")
    return np.deg2rad(np.arange(a, b + 1e-9, step))


def _lengths(text: str) -> np.ndarray:
    parts = text.split(":")
    if len(parts) != 3:
        raise UnitError(f"--lengths: expected start:stop:count, e.g. 1mm:4mm:8, got {text!r}")
    lo, hi = parse_length(parts[0], "--lengths"), parse_length(parts[1], "--lengths")
    try:
        n = int(parts[2])
    except ValueError:
        raise UnitError(f"--lengths: expected an integer count, e.g. 1mm:4mm:8, got {text!r}") from None
    if not (0 < lo <= hi and 1 <= n <= 10_000):
        raise UnitError(f"--lengths: expected 0 < start <= stop and 1 <= count <= 10000, got {text!r}")
    return np.linspace(lo, hi, n)


def add_characterise_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "characterise",
        help="orientation/length maps from a dictionary of mirror fingerprints",
        description="Per pixel, the mirror orientation α and length L that maximise γ "
        "(paper Fig. 4). Lengths in metres unless a unit is given.",
    )
    p.add_argument("data", help="UFF file")
    p.add_argument("--dictionary", choices=["mirror"], default="mirror", help="fingerprint family (mirror)")
    p.add_argument(
        "--angles",
        default="-45:45:3",
        help="orientations start:stop:step in degrees (default -45:45:3; write --angles=-40:40:5)",
    )
    p.add_argument("--lengths", default="0.5mm:4mm:8", help="lengths start:stop:count (default 0.5mm:4mm:8)")
    p.add_argument("--frame", type=int_at_least(0), default=0, help="frame index in the file (default 0)")
    p.add_argument("--dataset", help="dataset name inside the UFF file when there are several")
    p.add_argument("--band", help="band f_min:f_max, e.g. 5.5MHz:9.5MHz (default: the probe's band)")
    p.add_argument(
        "--n-freq", type=int_at_least(1), default=None, help="frequencies kept (default: all bins, 2× padded)"
    )
    p.add_argument("--x", dest="x_range", help="lateral range, e.g. --x=-8mm:8mm")
    p.add_argument("--y", dest="y_range", help=argparse.SUPPRESS)
    p.add_argument("--z", dest="z_range", help="depth range, e.g. 5mm:25mm")
    p.add_argument("--spacing", help="grid spacing (default λ_min/3)")
    p.add_argument(
        "--threshold",
        type=float,
        default=0.25,
        help="pixels with γ_max ≥ threshold × its 99th percentile are reported (default 0.25)",
    )
    add_time_weighting_argument(p)
    p.add_argument("--json", help="summary JSON (SI units)")
    p.add_argument("--npz", help="maps: gamma_max, alpha_rad, length_m, x_m, z_m")
    p.add_argument("--png", help="vector-field figure over the confocal image")
    p.set_defaults(func=run_characterise)


def run_characterise(args: argparse.Namespace) -> int:
    from fpcore import Grid, Imager, ImagingConfig
    from fpcore.dictionary import Dictionary, mirror_family
    from fpcore.io import read_uff
    from services.imaging_setup import check_grid_axes, check_imaging_budget

    console = make_console()
    alphas, lengths = _angles(args.angles), _lengths(args.lengths)
    acq = read_uff(args.data, args.dataset, frames=[args.frame])[0]
    if not acq.probe.is_linear:
        raise ValueError("probe: fp characterise maps 2D (x–z) images; a linear array is expected")
    band = parse_band(args.band) if args.band is not None else acq.default_band()
    ranges = grid_ranges(args)
    check_grid_axes(acq, band, ranges)
    grid = Grid.for_acquisition(acq, band, **ranges)
    check_imaging_budget(acq, band, grid, args.n_freq, None, n_fingerprints=alphas.size * lengths.size)
    imager = Imager(ImagingConfig(grid, band, args.n_freq, time_weighting=args.time_weighting))
    pw = imager.plane_waves(acq)
    dic = Dictionary(family=mirror_family(lengths, alphas))
    console.print(f"{len(dic)} mirror fingerprints ({alphas.size} α × {lengths.size} L), grid {grid.shape}")
    with progress(console) as bar:
        task = bar.add_task("dictionary", total=len(dic))
        res = dic.evaluate(imager, pw, progress=lambda k, n: bar.update(task, completed=k))
    alpha_map, length_map = res.state_map("alpha_rad"), res.state_map("length_m")
    mask = res.gamma_max >= args.threshold * np.percentile(res.gamma_max, 99)
    summary = {
        "data": str(args.data),
        "frame_index": acq.frame_index,
        "band_hz": list(band),
        "n_states": len(dic),
        "pixels_reported": int(mask.sum()),
        "alpha_rad_median": float(np.median(alpha_map[mask])) if mask.any() else None,
        "length_m_median": float(np.median(length_map[mask])) if mask.any() else None,
    }
    fibres = acq.ground_truth.fibres
    if fibres:
        errs = []
        for f in fibres:
            if f.position_m is None or f.alpha_rad is None:
                continue  # nothing to compare with
            idx = grid.nearest_index(np.array(f.position_m))
            if mask[idx]:
                d = alpha_map[idx] - f.alpha_rad
                errs.append(abs((d + np.pi / 2) % np.pi - np.pi / 2))
        if errs:
            summary["truth_alpha_error_rad_median"] = float(np.median(errs))
            summary["truth_fibres_compared"] = len(errs)
            console.print(f"orientation error against {len(errs)} fibres: median {np.rad2deg(np.median(errs)):.1f}°")
    console.print(
        f"{int(mask.sum())} pixels above threshold; median α = "
        f"{np.rad2deg(summary['alpha_rad_median'] or 0):.1f}°, median L = "
        f"{(summary['length_m_median'] or 0) * 1e3:.2f} mm"
    )
    if args.npz:
        np.savez_compressed(
            args.npz, gamma_max=res.gamma_max, alpha_rad=alpha_map, length_m=length_map, x_m=grid.x, z_m=grid.z
        )
        console.print(f"wrote {args.npz}")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
        console.print(f"wrote {args.json}")
    if args.png:
        _vector_figure(args.png, grid, imager.confocal(pw), alpha_map, length_map, mask)
        console.print(f"wrote {args.png}")
    return 0


def _vector_figure(
    path: str, grid, confocal: np.ndarray, alpha: np.ndarray, length: np.ndarray, mask: np.ndarray
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ext = [grid.x[0] * 1e3, grid.x[-1] * 1e3, grid.z[-1] * 1e3, grid.z[0] * 1e3]
    fig, ax = plt.subplots(figsize=(8, 6), constrained_layout=True)
    ax.imshow(
        10 * np.log10(confocal.T / confocal.max() + 1e-12),
        extent=ext,
        cmap="gray",
        vmin=-45,
        vmax=0,
        alpha=0.7,
        aspect="equal",
    )
    step = max(1, int(round(0.6e-3 / grid.spacing[0])))
    sub = (slice(None, None, step), slice(None, None, step))
    xx, zz = np.meshgrid(grid.x * 1e3, grid.z * 1e3, indexing="ij")
    m = mask[sub]
    a = alpha[sub][m]
    q = ax.quiver(
        xx[sub][m],
        zz[sub][m],
        np.cos(a),
        np.sin(a),
        np.rad2deg(a),
        cmap="plasma",
        angles="xy",
        scale_units="xy",
        scale=1 / 0.5,
        headwidth=0,
        headlength=0,
        headaxislength=0,
        pivot="middle",
        width=0.004,
        alpha=0.9,
    )
    fig.colorbar(q, ax=ax, label="α_opt (deg)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title("Fibre orientation from the mirror dictionary over the confocal image (dB)")
    fig.savefig(path, dpi=110)
    plt.close(fig)
