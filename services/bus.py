"""Zenoh plumbing shared by the streaming nodes (docs/design.md §2, §7 and its "Stack notes").

Every node runs an embedded zenoh session: peer mode, loopback endpoints, multicast scouting off.
Sessions always close (``with open_session(bus) as s:``) and callback subscribers are undeclared
before their session closes (a callback subscriber left open hangs the process at exit).

Topology on one machine (no router): the processor listens on ``tcp/127.0.0.1:7447`` and every other
node listens on an ephemeral loopback port and connects to it; gossip scouting (zenoh's default)
then links the peers directly, so publisher → recorder needs no relay. A ``connect`` endpoint that is
not up yet is retried in the background; ``connect/timeout_ms`` bounds ``open()`` (stack notes: a
dead endpoint without it can hang). Across machines: give ``--connect`` endpoints, ``--mode router``
for a relay, or a JSON5 file (``--zenoh-config``; explicit flags override its fields).

Exposure (docs/wire.md, "Securing the bus"): a node listens on loopback unless told otherwise. A listen
endpoint on any other address — ``tcp/0.0.0.0:…``, a host name, an interface address, or zenoh's
own default ``tcp/[::]:…`` when a config file gives none — is refused with one line unless the node
is started with ``--allow-remote`` (``BusConfig.allow_remote``); then it prints a warning, which
also says when the session has no user/password authentication or a link is not TLS
(``services.bus_exposure``). Access control, authentication and TLS are zenoh's own
(``transport/auth/usrpwd``, ``access_control``, ``tls/`` endpoints), configured in the
``--zenoh-config`` file; ``deploy/zenoh/`` holds an example.

Shared memory (stack notes): zenoh 1.x moves messages ≥ 3 KB through SHM between processes on one
host, from a 16 MiB pool by default — too small for 10–50 MB frames. ``shm="auto"`` (default) keeps
SHM on with a 512 MiB pool when /dev/shm has ≥ 2 GiB free (measured ≈ 2× TCP loopback throughput),
and switches SHM off otherwise (TCP loopback, ≈ 0.8 GB/s) so that a small /dev/shm (Docker's
64 MiB default) never fails allocations; ``"off"`` or a pool size in MiB force either choice. The pool
is allocated lazily: the first large message a session sends pays for it (≈ 0.5 s for 512 MiB here,
page faults); sessions with ``warm_shm`` (``fp process``, ``fp publish``) pay it when they open, before
the node's "ready" (``services.bus_warm``). Measured with 9 MB frames between two
processes: 860 MB/s with the pool vs 540 MB/s over TCP loopback (payload copy included); in the
whole pipeline the gain is small (12.6 vs 12.2 frames/s, 3D bench) because processing dominates.

Back-pressure primitives (docs/design.md §7): :class:`LatestSlot` is the depth-1 ring between a zenoh
callback and a worker (live mode: keep the newest, count what it replaces); :class:`FifoSlot` blocks
the callback when full (replay mode: drop nothing; the block propagates to the publisher through
zenoh's BLOCK congestion control).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import json
import os
import queue
import shutil
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Generic, Literal, TypeVar

import zenoh

from services.bus_exposure import bus_warnings, config_file, listen_endpoints, remote_endpoints, zerror_line
from services.messages import Message
from services.wire import encode_with_header

__all__ = [
    "DEFAULT_HUB",
    "BusConfig",
    "bus_warnings",
    "FifoSlot",
    "LatestSlot",
    "add_bus_arguments",
    "bus_from_args",
    "free_port",
    "listen_endpoints",
    "open_session",
    "put_message",
    "remote_endpoints",
    "sample_bytes",
    "sample_publish_time",
    "stop_on_signals",
    "tune_malloc",
    "sync_with",
    "wait_for_matching",
    "wait_for_token",
    "wait_until",
    "zenoh_config",
]

#: The well-known loopback endpoint of a one-machine deployment (the processor listens there).
DEFAULT_HUB = "tcp/127.0.0.1:7447"
EPHEMERAL = "tcp/127.0.0.1:0"
_SHM_AUTO_POOL_MIB = 512
_SHM_AUTO_MIN_FREE = 2 << 30


@dataclass
class BusConfig:
    """How a node joins the bus. ``None`` fields keep the JSON5 file's value (or zenoh's default)."""

    mode: Literal["peer", "router", "client"] | None = "peer"
    listen: list[str] | None = field(default_factory=lambda: [EPHEMERAL])
    connect: list[str] | None = field(default_factory=lambda: [DEFAULT_HUB])
    multicast: bool | None = False
    config_file: str | None = None
    shm: str | None = "auto"  # "auto" | "off" | pool size in MiB
    connect_timeout_ms: int | None = 2000
    allow_remote: bool = False  # listen on non-loopback addresses (with a warning); refused otherwise
    warm_shm: bool = False  # create the SHM pool at open, not at the first large message (services.bus_warm)

    def shm_pool_bytes(self) -> int | None:
        """Pool size to configure, or None to disable SHM (see the module doc)."""
        s = str(self.shm or "auto").strip().lower()
        if s == "off":
            return None
        if s == "auto":
            try:
                free = shutil.disk_usage("/dev/shm").free
            except OSError:
                return None
            return _SHM_AUTO_POOL_MIB << 20 if free >= _SHM_AUTO_MIN_FREE else None
        try:
            mib = int(s)
        except ValueError:
            raise ValueError(f"--shm: expected 'auto', 'off' or a pool size in MiB, got {self.shm!r}") from None
        if mib <= 0:
            raise ValueError(f"--shm: expected a positive pool size in MiB, got {mib}")
        return mib << 20


def zenoh_config(bus: BusConfig) -> zenoh.Config:
    """The zenoh.Config of ``bus`` (file first, then the explicit settings). ValueError (one line) for an
    unreadable file, or a listen endpoint off loopback without ``allow_remote``."""
    if bus.mode not in (None, "peer", "router", "client"):
        raise ValueError(f"--mode: expected peer, router or client, got {bus.mode!r}")
    cfg = config_file(bus.config_file) if bus.config_file else zenoh.Config()
    if bus.mode is not None:
        cfg.insert_json5("mode", json.dumps(bus.mode))
    mode = json.loads(cfg.get_json("mode") or "null") or "peer"
    if bus.listen is not None and mode != "client":
        cfg.insert_json5("listen/endpoints", json.dumps(list(bus.listen)))
    if bus.connect is not None:
        cfg.insert_json5("connect/endpoints", json.dumps(list(bus.connect)))
    if bus.connect_timeout_ms is not None or json.loads(cfg.get_json("connect/timeout_ms")) is None:
        cfg.insert_json5("connect/timeout_ms", str(int(bus.connect_timeout_ms or 2000)))
    if bus.multicast is not None:
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(bus.multicast)))
    if bus.shm is not None or not bus.config_file:  # else shared memory as the file says
        pool = bus.shm_pool_bytes()
        if pool is None:
            cfg.insert_json5("transport/shared_memory/enabled", "false")
        else:
            cfg.insert_json5("transport/shared_memory/enabled", "true")
            cfg.insert_json5("transport/shared_memory/transport_optimization/pool_size", str(pool))
    remote = remote_endpoints(listen_endpoints(cfg)) if mode != "client" else []
    if remote and not bus.allow_remote:
        raise ValueError(
            f"--listen: {', '.join(remote)} is not a loopback address (other hosts could connect); pass "
            "--allow-remote to accept that, after securing the bus (docs/wire.md, 'Securing the bus')"
        )
    return cfg


_log_once = threading.Lock()
_log_done = False


@contextlib.contextmanager
def open_session(bus: BusConfig) -> Iterator[zenoh.Session]:
    """``with open_session(bus) as session:`` — opens, and always closes, a zenoh session."""
    global _log_done
    with _log_once:
        if not _log_done:
            zenoh.try_init_log_from_env()  # RUST_LOG/ZENOH_LOG when set; quiet otherwise
            _log_done = True
    cfg = zenoh_config(bus)
    mode = json.loads(cfg.get_json("mode") or "null") or "peer"
    warm, unpinned = False, None
    if bus.warm_shm:
        from services.bus_warm import pin_ephemeral_ports, wants_warmup

        warm = wants_warmup(cfg)
        if warm:
            unpinned = pin_ephemeral_ports(cfg)
    notes = bus_warnings(cfg) if mode != "client" else []
    if notes:
        print(f"fp: warning: {'; '.join(notes)}", file=sys.stderr, flush=True)
    for attempt in range(3):
        try:
            session = zenoh.open(cfg)
            break
        except zenoh.ZError as exc:
            from services.bus_warm import repin_after

            if attempt < 2 and repin_after(exc, cfg, unpinned):
                continue  # a pinned port was taken by another process meanwhile: a fresh one
            first = zerror_line(exc)
            where = [f"connect {json.loads(cfg.get_json('connect/endpoints') or 'null') or []}"]
            if mode != "client":
                where.insert(0, f"listen {listen_endpoints(cfg)}")
            raise OSError(f"bus: could not open the zenoh {mode} session ({', '.join(where)}): {first}") from exc
    with session:
        sink = None
        if warm:
            from services.bus_warm import WARM_KEYS, forget_pool, warm_shm_pool

            sink = session.declare_subscriber(WARM_KEYS, lambda sample: None)  # others' warm-ups map their pools
            warm_shm_pool(session, cfg)
        try:
            yield session
        finally:
            if sink is not None:
                sink.undeclare()
                forget_pool(session)


def add_bus_arguments(
    p: argparse.ArgumentParser, listen: str = EPHEMERAL, connect: str | None = DEFAULT_HUB, warm_shm: bool = False
) -> None:
    """--mode, --listen, --connect, --multicast, --zenoh-config, --shm, --allow-remote (defaults per node;
    ``warm_shm`` for nodes that send large messages, ``BusConfig.warm_shm``)."""
    g = p.add_argument_group("bus (zenoh)")
    g.add_argument("--mode", choices=("peer", "router", "client"), help="zenoh mode (default peer)")
    g.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help=f"endpoint to listen on, repeatable (default {listen}); 'none' for no listener",
    )
    g.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help=f"endpoint to connect to, repeatable (default {connect or 'none'}); 'none' for none",
    )
    g.add_argument("--multicast", action="store_true", help="enable multicast scouting (off by default)")
    g.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file (flags above override it)")
    g.add_argument(
        "--shm",
        help="shared memory: auto (512 MiB pool if /dev/shm allows), off, or the pool size in MiB (default auto)",
    )
    g.add_argument("--connect-timeout-ms", type=int, help="connect/timeout_ms (default 2000)")
    g.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow listening on a non-loopback address (e.g. tcp/0.0.0.0:7447); prints a warning. "
        "Secure the bus first: docs/wire.md, 'Securing the bus'",
    )
    p.set_defaults(_bus_listen=listen, _bus_connect=connect, _bus_warm_shm=warm_shm)


def _endpoints(values: list[str] | None, default: str | None, from_file: bool) -> list[str] | None:
    if values is None:
        if from_file:
            return None
        return [default] if default else []
    return [] if values == ["none"] else [v for v in values if v != "none"]


def bus_from_args(args: argparse.Namespace) -> BusConfig:
    """BusConfig from the arguments of :func:`add_bus_arguments`: with ``--zenoh-config``, what no flag
    sets comes from the file; without, the defaults of the module doc. Checked (ValueError, one line):
    the file reads, and no listener leaves loopback without ``--allow-remote``."""
    file = args.zenoh_config
    listen = _endpoints(args.listen, args._bus_listen, bool(file))
    if listen is None and not _file_sets_listen(file):  # never zenoh's default, every interface
        listen = [args._bus_listen] if args._bus_listen else []
    bus = BusConfig(
        mode=args.mode or (None if file else "peer"),
        listen=listen,
        connect=_endpoints(args.connect, args._bus_connect, bool(file)),
        multicast=True if args.multicast else (None if file else False),
        config_file=file,
        shm=args.shm or (None if file else "auto"),
        connect_timeout_ms=args.connect_timeout_ms or (None if file else 2000),
        allow_remote=bool(getattr(args, "allow_remote", False)),
        warm_shm=bool(getattr(args, "_bus_warm_shm", False)),
    )
    zenoh_config(bus)  # a bad file or an exposed listener fails here, before the node's set-up
    return bus


def _file_sets_listen(path: str) -> bool:
    """Whether the zenoh config file ``path`` gives its own ``listen/endpoints``."""
    value = config_file(path).get_json("listen/endpoints")
    return value != zenoh.Config().get_json("listen/endpoints")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now (tests: distinct endpoints per test)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def put_message(pub: zenoh.Publisher, session: zenoh.Session, msg: Message) -> int:
    """Encode and publish ``msg`` with its header as the attachment and a session timestamp; returns bytes."""
    payload, header = encode_with_header(msg)
    pub.put(payload, attachment=header, timestamp=session.new_timestamp())
    return len(payload)


def sample_bytes(sample: zenoh.Sample) -> bytes:
    """The payload as bytes (one copy: ZBytes exposes no buffer protocol)."""
    return sample.payload.to_bytes()


def sample_publish_time(sample: zenoh.Sample) -> float | None:
    """Publisher's wall-clock time of the sample (seconds), from its zenoh timestamp if it has one."""
    ts = sample.timestamp
    if ts is None:
        return None
    try:
        return ts.get_time().timestamp()
    except (ValueError, OverflowError, OSError):
        return None


def wait_for_token(session: zenoh.Session, key: str, timeout: float) -> bool:
    """True once a liveliness token matching ``key`` is alive (polled until ``timeout`` seconds)."""
    deadline = time.monotonic() + timeout
    while True:
        replies = session.liveliness().get(key, timeout=min(1.0, max(timeout, 0.05)))
        if any(r.ok is not None for r in replies):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)


def sync_with(session: zenoh.Session, key: str, timeout: float) -> int:
    """Barrier: query every node's ``@sync`` queryable matching ``key``; returns how many replied.

    A reply leaves the node after it has taken every message this session sent it before the query: a link
    delivers in order, and a node's callbacks run in arrival order. A sender whose large payloads travel
    through shared memory must wait for this before closing its session: zenoh drops, silently, a sample
    whose sender's memory is gone before the receiver has mapped it (measured: a one-frame ``fp publish``
    lost its frame at the recorder in 4 of 6 runs; none with the barrier)."""
    replies = session.get(
        key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=max(timeout, 0.05)
    )
    return sum(r.ok is not None for r in replies)


def wait_for_matching(pub: zenoh.Publisher, timeout: float) -> bool:
    """True once ``pub`` has a matching subscriber (polled until ``timeout`` seconds): a liveliness token
    can reach a peer before the subscriptions declared with it, and a put before them is lost."""
    deadline = time.monotonic() + timeout
    while not pub.matching_status.matching:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)
    return True


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT/SIGTERM: node commands then undeclare and close their session cleanly."""
    ev = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        ev.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return ev


def wait_until(stop: threading.Event, duration: float | None = None) -> None:
    """Block until ``stop`` is set (or ``duration`` seconds have passed); wakes often for signals."""
    deadline = None if duration is None else time.monotonic() + duration
    while not stop.wait(0.2):
        if deadline is not None and time.monotonic() >= deadline:
            return


def tune_malloc(mmap_threshold: int = 32 << 20, trim_threshold: int = 1 << 30) -> bool:
    """Raise glibc's mmap/trim thresholds so that frame-sized buffers are reused instead of being
    mmap'ed and page-faulted anew for every frame (stack notes: this halves throughput otherwise).

    32 MiB is glibc's largest mmap threshold on 64-bit. No-op (False) off glibc or with
    ``FP_NO_MALLOC_TUNING`` set.
    """
    if os.environ.get("FP_NO_MALLOC_TUNING"):
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        m_trim, m_mmap = -1, -3
        return bool(libc.mallopt(m_mmap, mmap_threshold)) and bool(libc.mallopt(m_trim, trim_threshold))
    except (OSError, AttributeError):
        return False


T = TypeVar("T")


class LatestSlot(Generic[T]):
    """Ring buffer of depth 1: ``put`` replaces an unread item (counted in ``dropped``), never blocks."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._full = False
        self.dropped = 0

    def put(self, item: T, stop: threading.Event | None = None) -> None:
        with self._cond:
            if self._full:
                self.dropped += 1
            self._item, self._full = item, True
            self._cond.notify()

    def get(self, timeout: float | None = None) -> T:
        """The newest item; raises queue.Empty after ``timeout`` seconds."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._full, timeout):
                raise queue.Empty
            item, self._item, self._full = self._item, None, False
            return item

    def qsize(self) -> int:
        return int(self._full)


class FifoSlot(Generic[T]):
    """Bounded FIFO: ``put`` blocks while full (nothing is dropped); ``dropped`` stays 0."""

    def __init__(self, depth: int = 8) -> None:
        if depth < 1:
            raise ValueError(f"fifo depth: expected >= 1, got {depth}")
        self._q: queue.Queue[T] = queue.Queue(maxsize=depth)
        self.dropped = 0

    def put(self, item: T, stop: threading.Event | None = None) -> None:
        while True:
            try:
                self._q.put(item, timeout=0.2)
                return
            except queue.Full:
                if stop is not None and stop.is_set():
                    return

    def get(self, timeout: float | None = None) -> T:
        return self._q.get(timeout=timeout)

    def qsize(self) -> int:
        return self._q.qsize()
