"""`fp locate`: per-frame target localisation from UFF files (issue 7).

DATA.uff frames + a fingerprint (a calibration UFF of the target alone at r0, or a numerical model)
→ per frame: detected position(s), γ_max, C_γ and C = (γ_max/γ_M)², PFA, Cramér–Rao precision;
a table on screen, JSON in SI units with the unit in the key, and a PNG of γ over the confocal image.
The imaging set-up, the fingerprint construction and the detection step are the processor's
(``services.pipeline``, ``services.models``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from fpcore import Acquisition, Fingerprint, NullLevel, locate, locate_union, moving_fingerprint
from fpcore.geometry import to_xyz
from services.cli.fingerprint_args import add_fingerprint_arguments, fingerprint_spec, warn_r0
from services.cli.imaging import add_imaging_arguments, grid_ranges
from services.cli.output import make_console, progress
from services.imaging_setup import make_imager
from services.models import build_fingerprint
from services.pipeline import UNION_STATISTICS, truth_error, truth_positions
from services.units import parse_band

__all__ = ["add_locate_parser", "run_locate"]


def add_locate_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "locate",
        help="locate a target in every frame of a UFF file",
        description="Per frame: detected position(s), γ_max, contrasts C_γ and C, PFA and "
        "Cramér–Rao precision. Lengths are metres unless a unit is given (25mm).",
    )
    p.add_argument("data", help="UFF file with the plane-wave frames")
    add_fingerprint_arguments(p)
    add_imaging_arguments(p)
    p.add_argument("--json", help="write the results as JSON (SI units)")
    p.add_argument("--png", help="write a PNG of γ over the confocal image (last frame)")
    p.add_argument("--frames", help="frame indices to process, e.g. 0:10 (default: all)")
    p.add_argument(
        "--velocity",
        metavar="VX,VZ[,VY]",
        help="target velocity in m/s: use the motion-aware fingerprint (each transmit sees the target "
        "where it is when that transmit fires; needs the data's PRF)",
    )
    p.add_argument(
        "--skip-border",
        action="store_true",
        help="heuristic: skip maxima closer than the diffraction resolution to the grid's border "
        "(off by default: the local significance does not need it)",
    )
    p.set_defaults(func=run_locate)


def _moving(fp: Fingerprint, text: str, data: Acquisition) -> Fingerprint:
    """The motion-aware fingerprint for --velocity VX,VZ[,VY] (m/s) and the data's transmit times."""
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"--velocity: expected VX,VZ[,VY] in m/s, got {text!r}") from None
    if len(v) not in (2, 3) or not np.all(np.isfinite(v)):
        raise ValueError(f"--velocity: expected VX,VZ[,VY] in m/s, got {text!r}")
    if data.sequence.prf is None:
        raise ValueError("--velocity: the data has no PRF (UFF channel_data/PRF), so the transmit times are unknown")
    velocity = to_xyz(v, 2) if len(v) == 2 else np.array([v[0], v[2], v[1]])  # VX,VZ,VY → (x, y, z)
    return moving_fingerprint(fp, velocity, data.sequence.transmit_times())


def frame_selection(text: str) -> slice | list[int]:
    """--frames 'I' or 'A:B' (A < B, non-negative integers; either end may be left out)."""
    if not text.strip():
        raise ValueError(f"--frames: expected I or A:B with integers, got {text!r}")
    a, colon, b = text.partition(":")
    try:
        start, stop = int(a) if a else 0, (int(b) if b else None)
    except ValueError:
        raise ValueError(f"--frames: expected I or A:B with integers, got {text!r}") from None
    if start < 0 or (stop is not None and stop <= start):
        raise ValueError(f"--frames: expected 0 <= A < B, got {text!r}")
    return slice(start, stop) if colon else [start]


def run_locate(args: argparse.Namespace) -> int:
    from rich.table import Table

    from fpcore.io import read_uff
    from services.viewing.figures import gamma_over_confocal

    console = make_console()
    sel = None
    if args.frames is not None:
        sel = frame_selection(args.frames)
    frames = read_uff(args.data, args.dataset, frames=sel)
    first = frames[0]
    band = parse_band(args.band) if args.band is not None else first.default_band()
    if args.union and args.time_weighting:
        raise ValueError("--union: maps the frames both as recorded and weighted; drop --time-weighting")
    imager = make_imager(
        first, band, ranges=grid_ranges(args), n_freq=args.n_freq, n_out=args.n_out, time_weighting=args.time_weighting
    )
    grid = imager.grid
    imagers = [imager]
    if args.union:  # docs/design.md §4.14, eq. W2: a second imager on the same grid, each frame weighted by 1/v(t)
        imagers.append(make_imager(first, band, grid, n_freq=args.n_freq, n_out=args.n_out, time_weighting=True))
    spec, cal = fingerprint_spec(args, first, model_r0=(0.0, 0.0, 0.0))
    warning = warn_r0(args, spec, cal, grid, first, band)
    if warning:
        console.print(f"[yellow]warning:[/yellow] {warning}")
    fp = build_fingerprint(spec, first, None, imager, band, args.n_freq, args.svd_threshold)
    if args.calibration:
        how = (
            "no gate"
            if args.gate == "none"
            else f"gate after the front face, d = {fp.state['diameter_m'] * 1e3:.1f} mm"
            + (" (measured: first arrival)" if spec.diameter is None else "")
        )
        modes = "F = R0′ (not whitened)" if args.no_whitening else "whitened modes"
        console.print(
            f"fingerprint from {args.calibration}: r0 = {np.round(fp.r0 * 1e3, 2)} mm, {how}, {modes}, "
            f"N_S = {fp.n_s:.1f}, N_T = {fp.n_t:.1f}, N_S·N_T = {fp.n_s * fp.n_t:.0f} (eq. G's count)"
        )
    if args.velocity is not None:
        fp = _moving(fp, args.velocity, first)
    console.print(f"{len(frames)} frame(s), band {band[0] / 1e6:.2f}–{band[1] / 1e6:.2f} MHz, grid {grid.shape}")
    results = []
    table = Table(title=f"fp locate {args.data}")
    for col in ("frame", "position (mm)", "γ_max", "C_γ", "C", "PFA", "δρ_L, δz_L (mm)", "error (mm)"):
        table.add_column(col, justify="right")
    levels = [NullLevel(im, single_scattering=args.null_single_scattering, cfar=args.cfar) for im in imagers]
    if args.union:
        console.print("statistic: the union of the frames as recorded and weighted by 1/v(t) (eq. W2: PFA × 2)")
    with progress(console) as bar:
        task = bar.add_task("γ-maps", total=len(frames))
        for acq in frames:
            chosen = 0
            if args.union:
                found, chosen = locate_union(
                    imagers, acq, fp, levels, n_peaks=args.targets, max_pfa=args.max_pfa, interior=args.skip_border
                )
            else:
                found = locate(
                    imager, acq, fp, levels[0], n_peaks=args.targets, max_pfa=args.max_pfa, interior=args.skip_border
                )
            gamma, dets = found.gamma, found.detections
            truths = truth_positions(acq.ground_truth)
            row = {"frame_index": acq.frame_index, "timestamp_s": acq.timestamp, "detections": []}
            if args.union:
                row["statistic"] = UNION_STATISTICS[chosen]
            for d in dets:
                pos = np.array(d.position_m)
                err = truth_error(pos, truths)  # the nearest target, whatever its name
                row["detections"].append(
                    {
                        "fingerprint": d.fingerprint,
                        "position_m": d.position_m,
                        "gamma_max": d.gamma_max,
                        "c_gamma": d.c_gamma,
                        "c_pfa": d.c_pfa,
                        "c_local": d.c_local,
                        "pfa": d.pfa,
                        "precision_m": d.precision_m,
                        "truth_error_m": err,
                    }
                )
                table.add_row(
                    str(acq.frame_index),
                    ", ".join(f"{v * 1e3:.2f}" for v in pos),
                    f"{d.gamma_max:.3f}",
                    f"{d.c_gamma:.2f}",
                    f"{d.c_pfa:.1f}",
                    f"{d.pfa:.1e}",
                    f"{d.precision_m[0] * 1e3:.2f}, {d.precision_m[1] * 1e3:.3f}",
                    "" if err is None else f"{err * 1e3:.2f}",
                )
            if not dets:
                table.add_row(str(acq.frame_index), f"no detection (PFA < {args.max_pfa:g})", *[""] * 6)
            results.append(row)
            bar.advance(task)
    console.print(table)
    if args.json:
        doc = {
            "data": str(args.data),
            "fingerprint": {
                "name": fp.name,
                "provenance": fp.provenance,
                "r0_m": fp.r0.tolist(),
                "n_s": fp.n_s,
                "n_t": fp.n_t,
            },
            "band_hz": list(band),
            "grid_spacing_m": list(grid.spacing),
            "max_pfa": args.max_pfa,
            "frames": results,
        }
        Path(args.json).write_text(json.dumps(doc, indent=2))
        console.print(f"wrote {args.json}")
    if args.png and dets:
        near = np.array(dets[0].position_m)  # the truth of the target this detection belongs to
        truth = min((t for _, t in truths), key=lambda t: float(np.linalg.norm(t - near))) if truths else None
        gamma_over_confocal(
            args.png,
            grid,
            imager.confocal(imager.plane_waves(acq)),
            gamma,
            np.array(dets[0].position_m),
            truth=truth,
            title=f"{Path(args.data).name} frame {acq.frame_index}: C_γ = {dets[0].c_gamma:.1f}, "
            f"PFA = {dets[0].pfa:.1e}",
            name=fp.name,
            diameter=fp.state.get("diameter_m") or None,
            c_gamma=dets[0].c_gamma,
        )
        console.print(f"wrote {args.png}")
    return 0
