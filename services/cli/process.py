"""`fp process`: run the processor node (``services.nodes.processor``) from the command line.

Fingerprints from calibration UFF files, numerical models or a simulator scenario's calibrations;
imaging options as `fp locate`; node options (queue mode, frame size limit, status period) and the
bus options of ``services.bus``. Prints a JSON "ready" line once the node is up and a JSON summary
when it stops (SIGINT/SIGTERM or ``--duration``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging

from fpcore.geometry import to_xyz
from fpcore.metrics import DEFAULT_MAX_PFA
from services.bus import add_bus_arguments, bus_from_args, open_session, stop_on_signals, tune_malloc, wait_until
from services.cli.fingerprint_args import add_null_arguments, add_velocity_arguments, add_whitening_argument
from services.cli.imaging import add_imaging_arguments, grid_ranges, int_at_least, number_in
from services.cli.scenario_args import add_scenario_arguments, scenario_kwargs
from services.models import parse_model
from services.nodes.processor import Processor, ProcessorConfig
from services.registry import FingerprintSpec
from services.units import parse_band, parse_length, parse_position
from services.wire import DEFAULT_MAX_BYTES

__all__ = ["add_process_parser", "config_from_args", "run_process", "specs_from_args"]

log = logging.getLogger("fp.processor")


def add_process_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "process",
        help="run the processor node (γ-maps, detections, tracks)",
        description="Processor node: subscribes to fp/<rig>/rf, publishes gamma, image, detections, "
        "tracks, status and errors; dictionary queryable at fp/<rig>/dictionary/**. "
        "Lengths are metres unless a unit is given (25mm).",
    )
    p.add_argument("--rig", default="demo", help="rig name in the key expressions fp/<rig>/… (default demo)")
    p.add_argument("--name", default="processor", help="node name (default processor)")
    src = p.add_argument_group("fingerprint dictionary (at least one, or add at run time)")
    src.add_argument(
        "--calibration",
        action="append",
        default=[],
        metavar="FILE",
        help="UFF calibration (target alone at r0), repeatable; entry named after the target the file "
        "records (else the file)",
    )
    src.add_argument("--r0", help="calibration target position X,Z[,Y] (default: from the calibration's truth)")
    src.add_argument("--diameter", help="target size for the time gate, e.g. 10mm (default: from the truth)")
    src.add_argument("--dataset", help="dataset name inside the calibration UFF")
    src.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="SPEC",
        help="numerical fingerprint 'point' or 'mirror:L=2mm,alpha=10', repeatable",
    )
    src.add_argument("--scenario", help="calibrations of a simulator scenario's targets (e.g. sinking-sphere)")
    add_whitening_argument(src)
    add_velocity_arguments(src)
    src.add_argument("--full", action="store_true", help="full-size scenario (default: quick)")
    add_scenario_arguments(p)
    img = p.add_argument_group("imaging")
    add_imaging_arguments(img, peaks_help="peaks reported per fingerprint")
    img.add_argument(
        "--max-pfa",
        type=number_in(0, 1),
        default=DEFAULT_MAX_PFA,
        help=f"publish a detection only below this calibrated false-alarm probability (default {DEFAULT_MAX_PFA:g})",
    )
    img.add_argument(
        "--skip-border",
        action="store_true",
        help="heuristic: skip maxima within the diffraction resolution of the grid's border",
    )
    img.add_argument("--no-image", action="store_true", help="do not publish the confocal image")
    add_null_arguments(img)
    img.add_argument(
        "--map-encoding",
        choices=("uint16", "float32"),
        default="uint16",
        help="how γ-maps and the confocal image travel (and are recorded): uint16 codes (default; γ within "
        "γ_max/131070, the image in dB within 0.005 dB; detections are computed before, on float γ) or float32",
    )
    img.add_argument("--no-track", action="store_true", help="do not run the tracker")
    img.add_argument(
        "--track-integrate",
        type=int_at_least(1),
        default=1,
        metavar="K",
        help="tracker: search the mean of the last K γ-maps (fog decorrelates, a slow target "
        "persists; the track lags by v(K−1)Δt/2; default 1)",
    )
    node = p.add_argument_group("node")
    node.add_argument(
        "--queue",
        choices=("newest", "fifo"),
        default="newest",
        help="newest: live, keep the newest frame, count drops; fifo: replay, block, drop nothing",
    )
    node.add_argument("--fifo-depth", type=int_at_least(1), default=8, help="FIFO depth in fifo mode (default 8)")
    node.add_argument(
        "--max-frame-bytes",
        type=int_at_least(1),
        default=DEFAULT_MAX_BYTES,
        help=f"refuse larger frames (default {DEFAULT_MAX_BYTES})",
    )
    node.add_argument(
        "--status-period", type=number_in(0, 3600), default=1.0, help="seconds between Status messages (default 1)"
    )
    node.add_argument(
        "--duration",
        type=number_in(0, 1e9, lo_open=False),
        help="stop after this many seconds (default: run until signalled)",
    )
    add_bus_arguments(p, listen="tcp/127.0.0.1:7447", connect=None, warm_shm=True)  # sends maps: SHM pool at start
    p.set_defaults(func=run_process)


def _xyz(text: str, option: str) -> tuple[float, float, float]:
    """X,Z[,Y] (the options' order) → (x, y, z)."""
    v = parse_position(text, option)
    x, y, z = to_xyz(v, 2) if len(v) == 2 else (v[0], v[2], v[1])
    return float(x), float(y), float(z)


def specs_from_args(args: argparse.Namespace) -> list[FingerprintSpec]:
    """Fingerprint specs of the `fp process` options."""
    from pathlib import Path

    from fpcore.io import read_uff
    from services.cli.fingerprint_args import calibration_name, velocity_grid_from_args

    specs = []
    r0 = _xyz(args.r0, "--r0") if args.r0 else None
    diameter = parse_length(args.diameter, "--diameter") if args.diameter else None
    if diameter is not None and not diameter > 0:
        raise ValueError(f"--diameter: expected a length > 0, got {args.diameter!r}")
    for path in args.calibration:
        cal = read_uff(path, args.dataset)[0]
        name = calibration_name(path, cal)
        if any(sp.name == name for sp in specs):  # two files of one target: keep both, named after the files
            name = Path(path).stem
        specs.append(FingerprintSpec(name, calibration=cal, r0=r0, diameter=diameter))
    for i, spec in enumerate(args.model):
        parse_model(spec)  # a bad spec fails here, before the node starts
        name = spec.partition(":")[0] + (f"{i}" if len(args.model) > 1 else "")
        specs.append(FingerprintSpec(name, model=spec, r0=r0))
    if args.scenario:
        from services.sources import SimulatorSource

        kwargs = scenario_kwargs(args, args.scenario)
        specs.extend(SimulatorSource(args.scenario, quick=not args.full, **kwargs).fingerprint_specs())
    if args.no_whitening:
        if not args.calibration and not args.scenario:
            raise ValueError("--no-whitening: applies to calibration fingerprints (a model has no modes to whiten)")
        specs = [dataclasses.replace(sp, whiten_modes=False) if sp.calibration is not None else sp for sp in specs]
    vgrid = velocity_grid_from_args(args)
    return [dataclasses.replace(sp, velocity_grid=vgrid) for sp in specs] if vgrid is not None else specs


def config_from_args(args: argparse.Namespace) -> ProcessorConfig:
    return ProcessorConfig(
        rig=args.rig,
        name=args.name,
        queue=args.queue,
        fifo_depth=args.fifo_depth,
        band=parse_band(args.band) if args.band is not None else None,
        n_freq=args.n_freq,
        svd_threshold=args.svd_threshold,
        **grid_ranges(args),
        n_out=args.n_out,
        n_peaks=args.targets,
        max_pfa=args.max_pfa,
        interior=args.skip_border,
        max_frame_bytes=args.max_frame_bytes,
        publish_image=not args.no_image,
        single_scattering_null=args.null_single_scattering,
        cfar=args.cfar,
        time_weighting=args.time_weighting,
        union=args.union,
        map_encoding=args.map_encoding,
        track=not args.no_track,
        track_integrate=args.track_integrate,
        status_period=args.status_period,
    )


def run_process(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bus = bus_from_args(args)  # checked first: a bad --zenoh-config or an exposed --listen fails at once
    tune_malloc()
    cfg = config_from_args(args)
    specs = specs_from_args(args)
    stop = stop_on_signals()
    with open_session(bus) as session:
        with Processor(session, cfg, specs) as node:
            log.info("processor on %s (%s queue), dictionary %s", node.keys.rf, cfg.queue, node.dictionary)
            print(json.dumps({"ready": True, "rig": cfg.rig, "dictionary": node.dictionary}), flush=True)
            wait_until(stop, args.duration)
        print(json.dumps({"stopped": True, **{k: v for k, v in node.stats().items() if k != "dictionary"}}), flush=True)
    return 0
