"""`fp track`: offline tracking of a UFF frame sequence with the processor's own pipeline and tracker.

DATA.uff frames + one calibration (or model) fingerprint → per frame: detections (calibrated PFA <
--max-pfa) and tracks (id, position, velocity, calibrated PFA of the last measurement, status
tentative/confirmed/coasting/lost). The work is ``services.pipeline.Pipeline`` — the same set-up,
null model, detector and ``fpcore.tracking.Tracker`` as the processor node — so an offline run and a
streamed one give the same tracks. JSON has `fp locate`'s layout (``frames[i]`` with ``frame_index``,
``detections``) plus ``tracks``; with a truth in the file each track carries its distance to it, and
the PNG draws tracks against the truth over the mean confocal image.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from services.cli.fingerprint_args import (
    add_fingerprint_arguments,
    add_velocity_arguments,
    fingerprint_spec,
    velocity_grid_from_args,
    warn_r0,
)
from services.cli.imaging import add_imaging_arguments, grid_ranges
from services.cli.output import make_console, progress
from services.pipeline import Pipeline, PipelineConfig, truth_error, truth_positions
from services.units import parse_band

__all__ = ["add_track_parser", "run_track"]


def add_track_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track",
        help="track targets through the frames of a UFF file (offline processor)",
        description="Per frame: detections and tracks (the processor's pipeline and tracker). "
        "Lengths are metres unless a unit is given (25mm).",
    )
    p.add_argument("data", help="UFF file with the plane-wave frames (in time order)")
    add_fingerprint_arguments(p)
    add_velocity_arguments(p)
    add_imaging_arguments(p, peaks_help="targets (tracks) per fingerprint")
    p.add_argument("--json", help="write detections and tracks per frame as JSON (SI units)")
    p.add_argument("--png", help="write a PNG of the tracks against the truth over the confocal image")
    p.set_defaults(func=run_track)


def _track_row(t: Any, truths: list[tuple[str | None, np.ndarray]]) -> dict[str, Any]:
    err = truth_error(np.asarray(t.position_m, float), truths, t.fingerprint) if truths else None
    return {
        "id": t.track_id,
        "fingerprint": t.fingerprint,
        "position_m": list(t.position_m),
        "velocity_m_s": list(t.velocity_m_s),
        "pfa": float(t.pfa),
        "status": t.status,
        "confidence": float(t.confidence),
        "measured": bool(t.measured),
        "truth_error_m": err,
    }


def _velocity_row(v: Any) -> dict[str, Any]:
    """A detection's velocity estimate (fpcore.velocity.VelocityEstimate) as JSON; {} without one."""
    if v is None:
        return {}
    return {
        "velocity_m_s": [float(x) for x in v.velocity_m_s],
        "velocity_sigma_m_s": [float(x) for x in v.sigma_m_s],
        "velocity_position_m": [float(x) for x in v.position_m],
        "velocity_gamma": float(v.gamma),
    }


def run_track(args: argparse.Namespace) -> int:
    from rich.table import Table

    from fpcore.io import read_uff

    console = make_console()
    frames = read_uff(args.data, args.dataset)
    first = frames[0]
    band = parse_band(args.band) if args.band is not None else first.default_band()
    r = grid_ranges(args)
    cfg = PipelineConfig(
        band=band,
        n_freq=args.n_freq,
        svd_threshold=args.svd_threshold,
        n_out=args.n_out,
        n_peaks=args.targets,
        max_pfa=args.max_pfa,
        single_scattering_null=args.null_single_scattering,
        cfar=args.cfar,
        time_weighting=args.time_weighting,
        union=args.union,
        x_range=r["x_range"],
        y_range=r["y_range"],
        z_range=r["z_range"],
        spacing=r["spacing"],
    )
    spec, cal = fingerprint_spec(args, first)
    spec = dataclasses.replace(spec, velocity_grid=velocity_grid_from_args(args))
    pipe = Pipeline(cfg, [spec])
    pipe.setup(first)
    grid = pipe.grid
    warning = warn_r0(args, spec, cal, grid, first, band)
    if warning:
        console.print(f"[yellow]warning:[/yellow] {warning}")
    entry = pipe.entry(spec.name) or {}
    if entry.get("error"):
        raise ValueError(f"fingerprint {spec.name!r}: {entry['error']}")
    console.print(
        f"{len(frames)} frame(s), band {band[0] / 1e6:.2f}–{band[1] / 1e6:.2f} MHz, grid {grid.shape}, "
        f"detections at PFA < {args.max_pfa:g}"
    )
    if args.union:
        console.print("statistic: the union of the frames as recorded and weighted by 1/v(t) (eq. W2: PFA × 2)")
    table = Table(title=f"fp track {args.data}")
    for col in ("frame", "detection (mm)", "PFA", "track", "status", "track position (mm)", "track PFA", "error (mm)"):
        table.add_column(col, justify="right")
    rows: list[dict[str, Any]] = []
    history: list[dict[str, Any]] = []
    conf_sum = None
    with progress(console) as bar:
        task = bar.add_task("tracking", total=len(frames))
        for acq in frames:
            res = pipe.process(acq)
            for note in res.notices:
                console.print(f"[yellow]warning:[/yellow] {note}")
            truths = truth_positions(acq.ground_truth)
            dets = [
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
                    **_velocity_row(v),
                }
                for (d, err), v in zip(res.detections, res.velocities, strict=True)
            ]
            tracks = [_track_row(t, truths) for t in res.tracks]
            row = {"frame_index": acq.frame_index, "timestamp_s": acq.timestamp, "detections": dets, "tracks": tracks}
            if res.statistic:  # --union: the map kept (eq. W2), as `fp locate --union` writes it
                row["statistic"] = res.statistic[spec.name]
            rows.append(row)
            history.append(
                {
                    "frame_index": acq.frame_index,
                    "tracks": tracks,
                    "truth": [{"name": n, "position_m": p.tolist()} for n, p in truths if n],
                }
            )
            if res.image is not None:
                conf_sum = res.image if conf_sum is None else conf_sum + res.image
            det_txt = ", ".join(f"{v * 1e3:.2f}" for v in dets[0]["position_m"]) if dets else "no detection"
            det_pfa = f"{dets[0]['pfa']:.1e}" if dets else ""
            if not tracks:
                table.add_row(str(acq.frame_index), det_txt, det_pfa, "", "no track", "", "", "")
            for k, t in enumerate(tracks):
                err = t["truth_error_m"]
                table.add_row(
                    str(acq.frame_index) if k == 0 else "",
                    det_txt if k == 0 else "",
                    det_pfa if k == 0 else "",
                    str(t["id"]),
                    t["status"],
                    ", ".join(f"{v * 1e3:.2f}" for v in t["position_m"]),
                    f"{t['pfa']:.1e}",
                    "" if err is None else f"{err * 1e3:.2f}",
                )
            bar.advance(task)
    console.print(table)
    if args.json:
        doc = {
            "data": str(args.data),
            "fingerprint": spec.name,
            "band_hz": list(band),
            "max_pfa": args.max_pfa,
            "grid_spacing_m": list(grid.spacing),
            "frames": rows,
        }
        Path(args.json).write_text(json.dumps(doc, indent=2))
        console.print(f"wrote {args.json}")
    if args.png and conf_sum is not None:
        from services.viewing.figures import tracks_over_confocal

        tracks_over_confocal(args.png, grid, conf_sum / len(frames), history, title=f"fp track {Path(args.data).name}")
        console.print(f"wrote {args.png}")
    return 0
