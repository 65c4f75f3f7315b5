"""`fp merge`: run the merger (``services.nodes.merger``), the ordered stage of a sharded processor.

It tracks and publishes in frame order what `fp process` publishes, from the γ workers' results (`fp
worker`); its token is the rig's processor token. Listens like `fp process` (``tcp/127.0.0.1:7447``);
``--mode router`` makes it the deployment's zenoh router (docs/scaling.md). Prints a JSON "ready" line
once at least ``--workers`` workers are alive, and a JSON summary when it stops.
"""

from __future__ import annotations

import argparse
import json
import logging

from services.bus import add_bus_arguments, bus_from_args, open_session, stop_on_signals, wait_until
from services.cli.imaging import int_at_least, number_in
from services.nodes.merger import Merger, MergerConfig

__all__ = ["add_merge_parser", "run_merge"]

log = logging.getLogger("fp.merger")


def add_merge_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "merge",
        help="run the merger of a sharded processor (tracks, ordered output; with fp worker)",
        description="Merger: assigns the frames of fp/<rig>/rf to the γ workers alive on "
        "fp/<rig>/alive/worker/*, runs the tracker in frame order and publishes gamma, image, tracks, "
        "detections, status and errors as fp process does; answers fp/<rig>/dictionary/** from the workers. "
        "docs/scaling.md.",
    )
    p.add_argument("--rig", default="demo", help="rig name in the key expressions fp/<rig>/… (default demo)")
    p.add_argument("--name", default="merger", help="node name (default merger)")
    p.add_argument(
        "--queue",
        choices=("newest", "fifo"),
        default="newest",
        help="newest: live, keep the newest waiting frame, count drops; fifo: replay, merge every frame",
    )
    p.add_argument("--depth", type=int_at_least(1), default=2, help="frames in flight per worker (default 2)")
    p.add_argument("--workers", type=int_at_least(0), default=1, help="workers to wait for before ready (default 1)")
    p.add_argument(
        "--wait-workers",
        type=number_in(0, 3600, lo_open=False),
        default=60.0,
        help="seconds to wait for them (default 60)",
    )
    p.add_argument(
        "--shard",
        choices=("frame", "fingerprint", "both"),
        default="frame",
        help="a worker's share: frame = whole frames; fingerprint = every frame split over all workers, each "
        "computing its share of the dictionary (one also the confocal image); both = workers in groups of "
        "--group-size, each frame split over one group (default frame; docs/scaling.md)",
    )
    p.add_argument(
        "--group-size", type=int_at_least(1), default=2, help="workers per group with --shard both (default 2)"
    )
    p.add_argument("--no-track", action="store_true", help="do not run the tracker (empty Tracks)")
    p.add_argument(
        "--frame-timeout",
        type=number_in(0, 3600),
        help="re-send a frame a live worker has not returned after this many seconds (a hung worker; the "
        "first result is merged). Default: only when the worker's token goes",
    )
    p.add_argument(
        "--frame-deadline",
        type=number_in(0, 86400),
        help="give up a frame still without a result this many seconds after it was first sent to a worker: "
        "one ErrorReport (field deadline) in its place, and the next frames go on. Default: wait",
    )
    p.add_argument(
        "--fifo-depth",
        type=int_at_least(1),
        default=8,
        help="frames held beyond the workers' --depth each (waiting for a worker or for an earlier frame); "
        "a frame over that is refused (fifo: with an ErrorReport naming the limit). Default 8",
    )
    p.add_argument(
        "--status-period", type=number_in(0, 3600), default=1.0, help="seconds between Status messages (default 1)"
    )
    p.add_argument(
        "--duration",
        type=number_in(0, 1e9, lo_open=False),
        help="stop after this many seconds (default: until signalled)",
    )
    add_bus_arguments(p, listen="tcp/127.0.0.1:7447", connect=None, warm_shm=True)  # forwards frames: SHM pool at start
    p.set_defaults(func=run_merge)


def run_merge(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bus = bus_from_args(args)
    cfg = MergerConfig(
        rig=args.rig,
        name=args.name,
        queue=args.queue,
        depth=args.depth,
        min_workers=args.workers,
        wait_workers_s=args.wait_workers,
        track=not args.no_track,
        status_period=args.status_period,
        frame_timeout_s=args.frame_timeout,
        frame_deadline_s=args.frame_deadline,
        fifo_depth=args.fifo_depth,
        shard=args.shard,
        group_size=args.group_size,
    )
    stop = stop_on_signals()
    with open_session(bus) as session:
        with Merger(session, cfg) as node:
            log.info("merger on %s (%s queue), workers %s", node.keys.rf, cfg.queue, node.workers)
            print(json.dumps({"ready": True, "rig": cfg.rig, "shard": cfg.shard, "workers": node.workers}), flush=True)
            wait_until(stop, args.duration)
        print(json.dumps({"stopped": True, **node.stats()}), flush=True)
    return 0
