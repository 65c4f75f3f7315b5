"""`fp publish`: run the publisher node (``services.nodes.publisher``) from the command line.

Sources: a simulator scenario, a UFF file, an MCAP recording (replayed byte for byte) or the live
ingest key; pacing options (original timing, fixed rate, acknowledgements, none) and the bus options
of ``services.bus``. Prints a JSON summary when the source ends or the node is signalled.
"""

from __future__ import annotations

import argparse
import json
import logging

from services.bus import (
    DEFAULT_HUB,
    EPHEMERAL,
    add_bus_arguments,
    bus_from_args,
    open_session,
    stop_on_signals,
    tune_malloc,
)
from services.cli.imaging import int_at_least, number_in
from services.cli.scenario_args import add_scenario_arguments, scenario_kwargs
from services.nodes.publisher import PACES, Publisher
from services.sources import IngestSource, MCAPSource, SimulatorSource, Source, UFFSource
from services.topics import keys
from services.wire import DEFAULT_MAX_BYTES

__all__ = ["add_publish_parser", "run_publish", "source_from_args"]


def add_publish_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "publish",
        help="publish RF frames on fp/<rig>/rf",
        description="Publisher: frames from a simulator scenario, a UFF file, an MCAP recording or "
        "the live ingest key fp/<rig>/ingest, on fp/<rig>/rf.",
    )
    p.add_argument("--rig", default="demo", help="rig name (default demo)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", help="simulator scenario (sinking-sphere, lesion-marker, muscle-fibres)")
    src.add_argument("--uff", help="UFF file of plane-wave frames")
    src.add_argument("--mcap", help="MCAP recording: replay its …/rf messages (same bytes)")
    src.add_argument("--ingest", action="store_true", help="forward valid frames put on fp/<rig>/ingest")
    p.add_argument("--full", action="store_true", help="full-size scenario (default: quick)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    add_scenario_arguments(p)
    p.add_argument("--dataset", help="dataset name inside the UFF file")
    p.add_argument("--from-rig", help="MCAP replay: the recorded rig to replay (default: any)")
    p.add_argument("--frames", type=int_at_least(1), help="publish at most this many frames")
    p.add_argument(
        "--repeat", type=int_at_least(1), default=1, help="replay a finite source this many times (default 1)"
    )
    pace = p.add_argument_group("pacing")
    pace.add_argument(
        "--pace",
        choices=PACES,
        help="original timing (default), fixed rate, ack (as fast as the processor takes) or none",
    )
    pace.add_argument("--rate", type=number_in(0), help="frames per second (implies --pace rate)")
    pace.add_argument("--fast", action="store_true", help="as fast as the consumer takes (same as --pace ack)")
    pace.add_argument("--speed", type=number_in(0), default=1.0, help="original timing × speed (default 1)")
    pace.add_argument("--window", type=int_at_least(1), default=2, help="frames in flight with --pace ack (default 2)")
    pace.add_argument(
        "--wait-for",
        default="processor",
        help="nodes to wait for before publishing: processor, recorder, both comma-separated, or none",
    )
    pace.add_argument(
        "--wait-timeout", type=number_in(0, lo_open=False), default=10.0, help="seconds to wait for them (default 10)"
    )
    pace.add_argument(
        "--ack-timeout", type=number_in(0), default=30.0, help="give up on a frame's ack after (default 30)"
    )
    p.add_argument(
        "--max-frame-bytes", type=int_at_least(1), default=DEFAULT_MAX_BYTES, help="ingest: refuse larger frames"
    )
    add_bus_arguments(p, listen=EPHEMERAL, connect=DEFAULT_HUB, warm_shm=True)  # sends frames: SHM pool at start
    p.set_defaults(func=run_publish)


def source_from_args(args: argparse.Namespace) -> Source:
    if args.scenario:
        return SimulatorSource(
            args.scenario,
            n_frames=args.frames,
            quick=not args.full,
            seed=args.seed,
            repeat=args.repeat,
            **scenario_kwargs(args, args.scenario),
        )
    if args.uff:
        return UFFSource(args.uff, args.dataset, repeat=args.repeat)
    if args.mcap:
        return MCAPSource(args.mcap, from_rig=args.from_rig, repeat=args.repeat)
    return IngestSource(args.rig)


def run_publish(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bus = bus_from_args(args)  # checked first: a bad --zenoh-config or an exposed --listen fails at once
    tune_malloc()
    pace = args.pace or ("ack" if args.fast else "rate" if args.rate else "none" if args.ingest else "original")
    wait_for = [] if args.wait_for == "none" else [w.strip() for w in args.wait_for.split(",") if w.strip()]
    source = source_from_args(args)
    stop = stop_on_signals()
    with open_session(bus) as session:
        pub = Publisher(
            session,
            args.rig,
            source,
            pace=pace,
            rate=args.rate,
            speed=args.speed,
            window=args.window,
            wait_for=wait_for,
            wait_timeout=args.wait_timeout,
            ack_timeout=args.ack_timeout,
            max_frame_bytes=args.max_frame_bytes,
            limit=args.frames,
        )
        if isinstance(source, IngestSource):
            source.bind(session)
            print(json.dumps({"ready": True, "ingest": keys(args.rig).ingest}), flush=True)
        summary = pub.run(stop)
    print(json.dumps(summary), flush=True)
    return 0
