"""`fp view`: a recording (or the live bus) to a Rerun ``.rrd`` (``services.viewing.rerun_log``), with
``--serve`` in the Rerun web viewer on 127.0.0.1 only (``services.viewing.server``); ``--live --foxglove``
serves the bus to the Foxglove app on a loopback WebSocket (``services.viewing.foxglove_live``). A file that
is not an MCAP, or holds nothing readable, is refused (exit 2).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from services.viewing.foxglove_live import DEFAULT_FOXGLOVE_PORT
from services.viewing.rerun_log import live_to_rrd, to_rrd
from services.viewing.server import (
    DEFAULT_GRPC_PORT,
    DEFAULT_WEB_PORT,
    check_ports,
    serve_loopback,
    serve_until_stopped,
)

__all__ = ["add_view_parser", "run_view"]


def run_view(args: argparse.Namespace) -> int:
    """`fp view`: convert a recording to ``.rrd``, or log the live bus (``--live``) to one; with
    ``--serve``, also serve it in the Rerun web viewer on 127.0.0.1 until Ctrl-C/SIGTERM."""
    from services.bus import stop_on_signals

    if args.duration is not None and args.duration <= 0:
        raise ValueError(f"--duration: expected seconds > 0, got {args.duration:g}")
    if args.foxglove:
        return _foxglove(args)
    if args.serve:
        check_ports(args.port, args.grpc_port)  # before a conversion that may take a while
    if args.live:
        from services.bus import bus_from_args

        rrd = Path(args.rrd or f"live-{args.rig}.rrd")
        stop = stop_on_signals()
        viewer = serve_loopback(port=args.port, grpc_port=args.grpc_port) if args.serve else None
        try:
            if viewer is not None:
                print(f"Rerun web viewer (loopback only): {viewer.url}  (Ctrl-C stops)", flush=True)
            out = live_to_rrd(
                bus_from_args(args),
                args.rig,
                rrd,
                duration=args.duration,
                stop=stop,
                threshold=args.threshold,
                grpc_url=viewer.grpc_url if viewer else None,
            )
        finally:
            if viewer is not None:
                viewer.stop()
        print(
            f"{out['rrd']}: {len(out['frames'])} frames, {out['messages']} messages "
            f"({out['undecodable']} undecodable, {out['dropped']} dropped)"
        )
        return 0
    if not args.recording:
        raise ValueError("recording: give an MCAP file, or --live to follow the bus")
    rrd = Path(args.rrd) if args.rrd else Path(args.recording).with_suffix(".rrd")
    out = to_rrd(args.recording, rrd, threshold=args.threshold)  # RecordingError (exit 2): nothing readable
    print(
        f"{out['rrd']}: {len(out['frames'])} frames, {out['messages']} messages "
        f"({out['undecodable']} undecodable), fingerprints {', '.join(out['fingerprints']) or 'none'}",
        flush=True,
    )
    if out["corrupted_chunks"] or out["error"]:
        print(
            f"fp view: warning: {args.recording} is damaged: {out['corrupted_chunks']} corrupted chunk(s) skipped"
            f"{'; reading stopped at ' + out['error'] if out['error'] else ''} (`fp recover` salvages the rest)",
            file=sys.stderr,
        )
    if args.serve:
        stop = stop_on_signals()
        with serve_loopback(rrd, port=args.port, grpc_port=args.grpc_port) as viewer:
            print(f"Rerun web viewer (loopback only): {viewer.url}  (Ctrl-C stops)", flush=True)
            serve_until_stopped(viewer, stop, args.duration)
    return 0


def _foxglove(args: argparse.Namespace) -> int:
    """`fp view --live --foxglove`: the bus to the Foxglove app over a loopback WebSocket."""
    from services.bus import bus_from_args, stop_on_signals
    from services.viewing.foxglove_live import serve_foxglove

    if not args.live:
        raise ValueError(
            "--foxglove: serves the live bus (add --live); a recording opens in Foxglove directly (File → Open)"
        )
    out = serve_foxglove(
        bus_from_args(args),
        args.rig,
        port=args.foxglove_port,
        duration=args.duration,
        stop=stop_on_signals(),
        on_ready=lambda url: print(f"Foxglove WebSocket (loopback only): {url}  (Ctrl-C stops)", flush=True),
    )
    print(f"{out['url']}: {out['messages']} messages ({out['undecodable']} undecodable, {out['dropped']} dropped)")
    return 0


def add_view_parser(sub: Any) -> argparse.ArgumentParser:
    """Register `fp view`."""
    p = sub.add_parser(
        "view",
        help="convert an MCAP recording to a Rerun .rrd (and serve it: --serve)",
        description="Log a recording's γ-maps, confocal images, detections, tracks and time "
        "series to Rerun natively, with a default blueprint; --serve shows it in "
        "the Rerun web viewer on 127.0.0.1.",
    )
    p.add_argument("recording", nargs="?", help="MCAP file written by `fp record`/`fp demo`")
    p.add_argument("--rrd", default=None, help="output .rrd (default: the recording with .rrd, or live-<rig>.rrd)")
    p.add_argument("--live", action="store_true", help="follow the zenoh bus instead of a file (Ctrl-C stops)")
    p.add_argument("--rig", default="demo", help="rig to follow with --live (default demo)")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="with --live or --serve: stop after this many seconds (default: at Ctrl-C/SIGTERM)",
    )
    p.add_argument("--threshold", type=float, default=0.6, help="show γ ≥ threshold·max (default 0.6)")
    g = p.add_argument_group(
        "web viewer (--serve)",
        "Bound to 127.0.0.1 only, not configurable: the recording must not be readable "
        "from the network. From another machine: ssh -L PORT:127.0.0.1:PORT for both ports.",
    )
    g.add_argument(
        "--serve",
        action="store_true",
        help="serve the .rrd (or the live stream) in the Rerun web viewer on 127.0.0.1 and print the URL",
    )
    g.add_argument(
        "--port",
        type=int,
        default=DEFAULT_WEB_PORT,
        help=f"HTTP port of the web viewer page (default {DEFAULT_WEB_PORT})",
    )
    g.add_argument(
        "--grpc-port",
        type=int,
        default=DEFAULT_GRPC_PORT,
        help=f"port of the gRPC proxy the page reads the data from (default {DEFAULT_GRPC_PORT})",
    )
    f = p.add_argument_group("Foxglove (--live --foxglove)", "The WebSocket binds 127.0.0.1 only, like --serve.")
    f.add_argument(
        "--foxglove",
        action="store_true",
        help="with --live: serve the bus to the Foxglove app (JSON messages and display channels) on a "
        "loopback WebSocket instead of writing a .rrd",
    )
    f.add_argument(
        "--foxglove-port",
        type=int,
        default=DEFAULT_FOXGLOVE_PORT,
        help=f"port of the Foxglove WebSocket (default {DEFAULT_FOXGLOVE_PORT}; 0: any free port)",
    )
    from services.bus import DEFAULT_HUB, EPHEMERAL, add_bus_arguments

    add_bus_arguments(p, listen=EPHEMERAL, connect=DEFAULT_HUB)
    p.set_defaults(func=run_view)
    return p
