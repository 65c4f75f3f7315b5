"""`fp record` (the recorder node, ``services.nodes.recorder``) and `fp recover` (salvage of a recording
whose writer was killed, ``services.recording.recover``) from the command line.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from datetime import datetime, timezone
from pathlib import Path

from services.bus import add_bus_arguments, bus_from_args, open_session, stop_on_signals, tune_malloc, wait_until
from services.nodes.recorder import Recorder
from services.recording import COMPRESSION, recover

__all__ = ["add_record_parser", "add_recover_parser", "run_record", "run_recover"]


def add_record_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="record every fp/** message to MCAP",
        description="Recorder: every message on fp/** (or --rig's; --include/--exclude narrow it) to MCAP, one "
        "channel per key: RF, γ-maps and images as their wire payload, small messages as JSON, plus Foxglove "
        "display channels; zstd chunks, flushed every --flush-interval.",
    )
    p.add_argument("-o", "--output", help="MCAP file (default recordings/<rig or all>-<UTC time>.mcap)")
    p.add_argument("--rig", help="record only fp/<rig>/** (default: every rig, fp/**)")
    p.add_argument(
        "--include",
        action="append",
        metavar="KEYEXPR",
        help="record only keys matching this zenoh key expression (repeatable; e.g. 'fp/*/detections')",
    )
    p.add_argument(
        "--exclude",
        action="append",
        metavar="KEYEXPR",
        help="leave out keys matching this key expression (repeatable; e.g. 'fp/*/rf')",
    )
    p.add_argument("--compression", choices=tuple(COMPRESSION), default="zstd", help="chunk compression (default zstd)")
    p.add_argument(
        "--no-shuffle",
        action="store_true",
        help="record RF, γ and confocal payloads exactly as they travelled (fpwire) instead of byte-shuffled "
        "(fpwire-shuffled, the default under compression: 12–17 %% smaller; docs/wire.md)",
    )
    p.add_argument(
        "--no-display",
        action="store_true",
        help="no Foxglove display channels (fp/<rig>/display/…: sections and scene), only the bus messages",
    )
    p.add_argument("--flush-interval", type=float, default=0.5, help="seconds between flushes (default 0.5)")
    p.add_argument("--max-bytes", type=int, help="rotate when a file reaches this size")
    p.add_argument("--max-seconds", type=float, help="rotate when a file is this old")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: run until signalled)")
    add_bus_arguments(p)
    p.set_defaults(func=run_record)


def add_recover_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "recover",
        help="salvage an MCAP file whose writer was killed",
        description="Copies every message of the complete, CRC-valid chunks of BROKEN into a complete file "
        "and prints a JSON report (messages kept, per key; chunks read and corrupted; complete only when the "
        "whole file was read and every CRC matched). Exit 2 when BROKEN is not an MCAP file or holds no "
        "readable message (nothing is written then).",
    )
    p.add_argument("broken", help="the damaged MCAP file")
    p.add_argument("-o", "--output", help="output file (default BROKEN.recovered.mcap)")
    p.set_defaults(func=run_recover)


def run_record(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bus = bus_from_args(args)  # checked first: a bad --zenoh-config or an exposed --listen fails at once
    tune_malloc()
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    out = Path(args.output or f"recordings/{args.rig or 'all'}-{stamp}.mcap")
    stop = stop_on_signals()
    with open_session(bus) as session:
        rec = Recorder(
            session,
            out,
            rig=args.rig,
            compression=args.compression,
            flush_interval=args.flush_interval,
            max_bytes=args.max_bytes,
            max_seconds=args.max_seconds,
            include=args.include,
            exclude=args.exclude,
            display=not args.no_display,
            shuffle=not args.no_shuffle,
        )
        with rec:
            print(json.dumps({"ready": True, "key_expr": rec.key_expr, "output": str(out)}), flush=True)
            wait_until(stop, args.duration)
        print(json.dumps({"stopped": True, **rec.summary()}), flush=True)
    return 0 if rec.error is None else 1


def run_recover(args: argparse.Namespace) -> int:
    report = recover(args.broken, args.output)  # RecordingError (exit 2): not an MCAP, or nothing readable
    print(json.dumps(report, indent=2))
    if not report["complete"]:
        print(
            f"fp recover: warning: {args.broken} is damaged: {report['corrupted_chunks']} corrupted chunk(s) of "
            f"{report['chunks']} skipped{'; reading stopped at ' + report['error'] if report['error'] else ''}",
            file=sys.stderr,
        )
    return 0
