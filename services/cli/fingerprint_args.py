"""The fingerprint options shared by `fp locate` and `fp track`: a calibration (with its r0, diameter and
time gate, checked against the file's own record) or a numerical model, and the decision threshold."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fpcore import Acquisition, Grid
from fpcore.cfar import CFAR_NAMES, DEFAULT_CFAR
from fpcore.geometry import to_xyz
from fpcore.locate import resolution_of
from fpcore.metrics import DEFAULT_MAX_PFA
from fpcore.velocity import VelocityGrid
from services.cli.imaging import number_in
from services.models import check_calibration, check_r0, parse_model, recorded_position
from services.registry import DEFAULT_VELOCITY_STEP, FingerprintSpec, parse_velocity_grid
from services.units import parse_length, parse_position

__all__ = [
    "add_fingerprint_arguments",
    "add_time_weighting_argument",
    "add_velocity_arguments",
    "add_whitening_argument",
    "calibration_name",
    "calibration_r0",
    "fingerprint_spec",
    "parse_velocity_grid",
    "velocity_grid_from_args",
    "warn_r0",
]


def add_fingerprint_arguments(p: argparse.ArgumentParser) -> None:
    """--calibration | --model, --r0, --force, --diameter, --gate, --no-whitening, --max-pfa, --dataset."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--calibration", help="UFF file: the target alone in water at r0 (fingerprint source)")
    src.add_argument("--model", help="numerical fingerprint: 'point' or 'mirror:L=2mm,alpha=10' (alpha in degrees)")
    p.add_argument(
        "--r0",
        help="calibration target position X,Z[,Y] (default: the position the calibration file "
        "records); refused if it differs from that by more than a resolution cell",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="proceed (with a warning) when --r0 disagrees with the calibration file's recorded position",
    )
    p.add_argument(
        "--diameter",
        help="target size for the time gate, e.g. 10mm (default: from the calibration's "
        "truth, else measured from the calibration: the echo's first arrival)",
    )
    p.add_argument(
        "--gate",
        choices=("front", "none"),
        default="front",
        help="calibration time gate: 'front' (paper: after the front face's echo) or 'none'",
    )
    add_whitening_argument(p)
    p.add_argument(
        "--max-pfa",
        type=number_in(0, 1),
        default=DEFAULT_MAX_PFA,
        help=f"report a detection only below this calibrated false-alarm probability (default {DEFAULT_MAX_PFA:g})",
    )
    add_null_arguments(p)
    p.add_argument("--dataset", help="dataset name inside the UFF file(s) when there are several")


def add_whitening_argument(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--no-whitening (docs/design.md §4.4), shared by fp locate, fp track, fp process and fp demo."""
    p.add_argument(
        "--no-whitening",
        action="store_true",
        help="calibration fingerprints F = R0′, the gated calibration itself (paper S2, Fig. S7a), instead of its "
        "whitened singular modes (eq. finger): in the simulated fog 1.2–11× more F_T/F_M at 2–5 ℓ_s; under a "
        "scattering layer's surface it matches the beads' single scattering, which the P·A null level underrates: "
        "pair it with --null-single-scattering there (README, 'The paper's gain law, measured')",
    )


def add_time_weighting_argument(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--time-weighting (docs/design.md §4.14), shared by fp locate, track, process, demo and characterise."""
    p.add_argument(
        "--time-weighting",
        action="store_true",
        help="weigh each frame by its own inverse variance 1/v(t) before γ (eq. W1: the matched filter in a fog "
        "that decays in time; the null level follows the weighted frame)",
    )


def add_null_arguments(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The null model's options (docs/design.md §4.9) and the time weighting its statistic is made with
    (§4.14), shared by fp locate, fp track, fp process/worker and fp demo."""
    add_time_weighting_argument(p)
    p.add_argument(
        "--union",
        action="store_true",
        help="map each frame both as recorded and weighted by 1/v(t), and keep per fingerprint the more significant "
        "map's detections, and its tracker gates, at twice their PFA (eq. W2, docs/design.md §4.14): the "
        "weighting's gain in a fog that decays, without its cost on a target that rules its frame's energy",
    )
    p.add_argument(
        "--null-single-scattering",
        action="store_true",
        help="mix the single-scattering level into the null level (docs/design.md §4.9, eq. B2): for backgrounds "
        "dominated by single scattering; costs power on targets that stand out of the confocal image",
    )
    p.add_argument(
        "--cfar",
        choices=CFAR_NAMES,
        default=DEFAULT_CFAR,
        help=f"the CFAR setting of the null model (docs/design.md §4.9; default {DEFAULT_CFAR}): 'compact' (± 1 axial "
        "cell, a guard around the node, a target's own lobes censored against the window's median: calibrated "
        "on single-scattering speckle and in water), 'wide' (± 6 × ± 3 cells, the earlier default; not calibrated "
        "on single-scattering speckle) or 'both' (the greater of the two levels)",
    )


def calibration_name(path: str, cal: Acquisition) -> str:
    """The fingerprint's name: the target the calibration file records (so tracks and detections compare
    with that target's truth), else the file's stem."""
    targets = cal.ground_truth.targets
    name = targets[0].name if targets else None
    return name if name else Path(path).stem


def calibration_r0(args: argparse.Namespace, cal: Acquisition) -> tuple[np.ndarray, float | None]:
    """(r0, diameter) of the calibration: the options', else the file's; diameter None = measure it."""
    recorded, d_rec = recorded_position(cal)
    if args.r0:
        v = parse_position(args.r0, "--r0")
        r0 = to_xyz(v, 2) if len(v) == 2 else np.array([v[0], v[2], v[1]])  # X,Z,Y → (x, y, z)
    elif recorded is not None:
        r0 = recorded
    else:
        raise ValueError("--r0: the calibration file has no target position in its truth; give --r0 X,Z[,Y]")
    if args.diameter:
        d = parse_length(args.diameter, "--diameter")
        if not d > 0:
            raise ValueError(f"--diameter: expected a length > 0, got {args.diameter!r}")
        return r0, d
    return r0, d_rec


def fingerprint_spec(
    args: argparse.Namespace, first: Acquisition, model_r0: tuple[float, float, float] | None = None
) -> tuple[FingerprintSpec, Acquisition | None]:
    """The dictionary entry of the options (and the calibration read, if any), checked against `first`;
    a model is centred at `model_r0` (None: the grid's centre)."""
    from fpcore.io import read_uff

    if not 0 < args.max_pfa <= 1:
        raise ValueError(f"--max-pfa: expected 0 < p <= 1, got {args.max_pfa}")
    if not args.calibration:
        if args.no_whitening:
            raise ValueError("--no-whitening: applies to a --calibration fingerprint (a model has no modes to whiten)")
        parse_model(args.model)  # a bad spec fails here, before any imaging
        return FingerprintSpec(args.model.partition(":")[0], model=args.model, r0=model_r0), None
    cal = read_uff(args.calibration, args.dataset)[0]
    check_calibration(cal, first)
    r0, diameter = calibration_r0(args, cal)
    name = calibration_name(args.calibration, cal)
    spec = FingerprintSpec(
        name,
        calibration=cal,
        r0=tuple(r0),
        diameter=diameter,
        gate=args.gate == "front",
        whiten_modes=not args.no_whitening,
    )
    return spec, cal


def warn_r0(
    args: argparse.Namespace,
    spec: FingerprintSpec,
    cal: Acquisition | None,
    grid: Grid,
    first: Acquisition,
    band: tuple[float, float],
) -> str | None:
    """`check_r0` for an --r0 given on the command line (ValueError unless --force; else the warning)."""
    if cal is None or not args.r0 or spec.r0 is None:
        return None
    return check_r0(np.asarray(spec.r0), cal, resolution_of(grid, first, band), force=args.force)


def add_velocity_arguments(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--velocity-grid, --velocity-roi: a live velocity dictionary per fingerprint (off by default)."""
    p.add_argument(
        "--velocity-grid",
        metavar="VMAX[:STEP]",
        help="estimate each target's velocity with a dictionary of motion-aware fingerprints (needs the frames' "
        "PRF): velocities from -VMAX to +VMAX per axis in steps of STEP m/s (default "
        f"{DEFAULT_VELOCITY_STEP:g}); VMAX is one speed for every axis or VX,VZ[,VY] (0: axis not searched), "
        "e.g. 0.5,0.2:0.1. The tracker uses the estimates as velocity measurements. Off by default",
    )
    p.add_argument(
        "--velocity-roi",
        default="3mm",
        help="half-width of the region searched around each detection and track (default 3mm)",
    )


def velocity_grid_from_args(args: argparse.Namespace) -> VelocityGrid | None:
    """The options' VelocityGrid, None when --velocity-grid is not given."""
    text = getattr(args, "velocity_grid", None)
    return None if text is None else parse_velocity_grid(text, getattr(args, "velocity_roi", "3mm"))
