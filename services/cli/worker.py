"""`fp worker`: run a γ worker (``services.nodes.worker``) for a sharded processor (docs/scaling.md).

The fingerprint and imaging options are `fp process`'s (the same dictionary on every worker). The worker
computes the frames, or the parts of frames, that a merger (`fp merge`, whose ``--shard`` chooses the
shares) assigns to it, and serves its dictionary to the merger; membership follows the workers' liveliness
tokens, so workers may be started and stopped at any time. Prints a JSON "ready" line once the node is
up and a JSON summary when it stops (SIGINT/SIGTERM or ``--duration``).
"""

from __future__ import annotations

import argparse
import json
import logging

from services.bus import bus_from_args, open_session, stop_on_signals, tune_malloc, wait_until
from services.cli.process import add_process_parser, config_from_args, specs_from_args
from services.nodes.worker import Worker, WorkerConfig

__all__ = ["add_worker_parser", "run_worker"]

log = logging.getLogger("fp.worker")
WAIT_FOR_ROUTER_MS = 60_000
_UNUSED = ("--queue", "--fifo-depth", "--status-period", "--no-track", "--name")  # the merger's, or redefined


def add_worker_parser(sub: argparse._SubParsersAction) -> None:
    scratch = argparse.ArgumentParser(add_help=False).add_subparsers()
    add_process_parser(scratch)  # fp process's options, taken as they are
    proc = scratch.choices["process"]
    proc._actions = [a for a in proc._actions if not set(a.option_strings) & {*_UNUSED, "-h", "--help"}]
    for group in proc._action_groups:
        group._group_actions = [a for a in group._group_actions if a in proc._actions]
    p = sub.add_parser(
        "worker",
        parents=[proc],
        conflict_handler="resolve",
        help="run a γ worker of a sharded processor (with fp merge)",
        description="γ worker: computes the frames of fp/<rig>/rf that the merger (fp merge) assigns to it "
        "(whole frames, or a share of their fingerprints: fp merge --shard) and returns their γ-maps, image, null "
        "models and detections; announces itself on "
        "fp/<rig>/alive/worker/<name>. Fingerprint and imaging options as fp process. Waits up to 60 s for its "
        "router unless --connect-timeout-ms says otherwise. docs/scaling.md.",
    )
    node = p.add_argument_group("worker")
    node.add_argument("--name", help="worker name on the bus (default <host>-<pid>)")
    p.set_defaults(func=run_worker, name=None, _bus_listen="tcp/127.0.0.1:0", _bus_connect="tcp/127.0.0.1:7447")


def run_worker(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if args.connect_timeout_ms is None and not args.zenoh_config:
        args.connect_timeout_ms = WAIT_FOR_ROUTER_MS  # started before its router: wait for it
    bus = bus_from_args(args)
    tune_malloc()
    args.queue, args.fifo_depth, args.status_period, args.no_track = "fifo", 1, 1.0, True
    pc = config_from_args(args)
    fields = {k: getattr(pc, k) for k in WorkerConfig.__dataclass_fields__ if hasattr(pc, k) and k != "name"}
    cfg = WorkerConfig(**fields, name=args.name or "")
    specs = specs_from_args(args)
    stop = stop_on_signals()
    with open_session(bus) as session:
        with Worker(session, cfg, specs) as node:
            log.info("worker %s on %s", node.name, node.keys.rf)
            print(json.dumps({"ready": True, "rig": cfg.rig, "worker": node.name}), flush=True)
            wait_until(stop, args.duration)
        print(json.dumps({"stopped": True, **node.stats()}), flush=True)
    return 0
