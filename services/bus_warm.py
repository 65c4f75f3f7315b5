"""Initialise a session's shared-memory pool when it opens, before its node says "ready" (issue 15, item 4).

zenoh creates a session's SHM pool (``transport/shared_memory/transport_optimization``) at the first
message over the SHM threshold that the session sends, and that first message waits for it: measured
here with 9 MB frames and the 512 MiB pool of ``services.bus`` (``shm="auto"``), 390–490 ms for the first
put against 2 ms for the next ones. For a publisher that is the first RF frame, for a processor its
first maps, so the first frame's latency was ~10× the median. :func:`warm_shm_pool` pays it at start
instead: a short-lived client session connects to the session's own loopback listener and receives
64 KiB messages on a key outside ``fp/**`` (no recorder sees them) until one comes through the pool;
measured, the first frame's put then takes 13–16 ms. A receiver maps a sender's pool at its first
message from it (≈ 50 ms once): warming sessions also subscribe to the warm-up key, so those already
linked when another one warms map its pool then. A publisher that joins a running processor usually warms
before the processor's subscription has reached it, so it also puts one warm-up message once its subscribers
match (:func:`announce_pool`): measured on quick 3-D frames (`bench/bench_first_frame.py`), the first frame's
latency was 1.1–2.5× the median (over 2× in 7 of 22 runs: the processor mapping the pool at the first
frame), and is 1.06–1.43× with it (20 runs; later that day, a noisier hour, 1.09–2.45 over 40 runs, 4 of
them above 2×).

Only for sessions that send large messages (``BusConfig.warm_shm``: ``fp process``, ``fp publish``),
that have SHM on and listen on loopback TCP, without user/password authentication (the helper
session could not log in) — otherwise nothing is done. Listeners on port 0 are given a free port
first (:func:`pin_ephemeral_ports`) so the helper knows where to connect; when another process takes that
port before the session binds it, ``services.bus.open_session`` pins a fresh one (3 tries in all).
"""

from __future__ import annotations

import json
import queue
import time

import zenoh

from services.bus_exposure import is_loopback, listen_endpoints

__all__ = [
    "WARM_KEYS",
    "announce_pool",
    "forget_pool",
    "pin_ephemeral_ports",
    "repin_after",
    "wants_warmup",
    "warm_shm_pool",
]

#: Where warm-up messages go; a warming session also subscribes here (``services.bus.open_session``), so a
#: session that warms later (a publisher joining a processor) reaches it too, and it maps that session's
#: pool now rather than at its first frame.
WARM_KEYS = "_fp_warmup/**"

_PAYLOAD = 64 << 10  # above zenoh's message_size_threshold (3 KiB by default)
_WARMED: set[str] = set()  # zids of the sessions whose pool `warm_shm_pool` made (announce_pool's condition)


def _loopback_tcp(cfg: zenoh.Config) -> list[str]:
    return [e for e in listen_endpoints(cfg) if e.startswith("tcp/") and is_loopback(e)]


def wants_warmup(cfg: zenoh.Config) -> bool:
    """SHM on, not a client, a loopback TCP listener, no user/password login, tcp not excluded."""
    get = lambda key: json.loads(cfg.get_json(key) or "null")  # noqa: E731
    protocols = get("transport/link/protocols")
    return (
        bool(get("transport/shared_memory/enabled"))
        and (get("mode") or "peer") != "client"
        and get("transport/auth/usrpwd/dictionary_file") is None
        and (protocols is None or "tcp" in protocols)
        and bool(_loopback_tcp(cfg))
    )


def pin_ephemeral_ports(cfg: zenoh.Config) -> list[str] | None:
    """Loopback ``tcp/…:0`` listeners get a port that is free now (the helper session must know it); returns
    the endpoints as they were when one was pinned (None otherwise), for :func:`repin_after` to retry with."""
    from services.bus import free_port

    eps = listen_endpoints(cfg)
    pinned = [f"{e[:-2]}:{free_port()}" if e.startswith("tcp/127.") and e.endswith(":0") else e for e in eps]
    if pinned == eps:
        return None
    cfg.insert_json5("listen/endpoints", json.dumps(pinned))
    return eps


def repin_after(exc: Exception, cfg: zenoh.Config, original: list[str] | None) -> bool:
    """After opening failed with ``exc``: when it is "address in use" on ports :func:`pin_ephemeral_ports`
    chose (another process took one between the probe and the bind), pin fresh ones; True to try again."""
    text = str(exc)
    if original is None or not ("Address already in use" in text or "os error 98" in text or "10048" in text):
        return False
    cfg.insert_json5("listen/endpoints", json.dumps(original))
    pin_ephemeral_ports(cfg)
    return True


def warm_shm_pool(session: zenoh.Session, cfg: zenoh.Config, timeout: float = 5.0) -> bool:
    """Make ``session`` create its SHM pool now (see the module doc); True once a message reached the helper
    through shared memory."""
    from services.bus import wait_for_matching

    eps = [e for e in _loopback_tcp(cfg) if not e.endswith(":0")]
    if not eps:
        return False
    helper = zenoh.Config()
    helper.insert_json5("mode", '"client"')
    helper.insert_json5("connect/endpoints", json.dumps(eps[:1]))
    helper.insert_json5("scouting/multicast/enabled", "false")
    helper.insert_json5("transport/shared_memory/enabled", "true")
    key = f"_fp_warmup/{session.info.zid()}"
    received: queue.Queue[bool] = queue.Queue()
    try:
        with zenoh.open(helper) as h:
            sub = h.declare_subscriber(key, lambda sample: received.put(sample.payload.as_shm() is not None))
            pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + timeout
            try:
                if not wait_for_matching(pub, timeout):
                    return False
                # The pool is created in the background of the first large put, which itself goes by TCP;
                # put again until a message travels through the pool (the second one, here).
                while time.monotonic() < deadline:
                    pub.put(bytes(_PAYLOAD))
                    try:
                        if received.get(timeout=0.5):
                            _WARMED.add(str(session.info.zid()))
                            return True
                        time.sleep(0.02)  # it came by TCP: the pool is still being made
                    except queue.Empty:  # the helper's subscription may not have reached the session yet
                        pass
                return False
            finally:
                pub.undeclare()
                sub.undeclare()
    except zenoh.ZError:
        return False


def forget_pool(session: zenoh.Session) -> None:
    """The session is closing: `announce_pool` no longer applies to it."""
    _WARMED.discard(str(session.info.zid()))


def announce_pool(session: zenoh.Session) -> None:
    """One small message on this session's warm-up key (``WARM_KEYS``) through its pool, so that the receivers
    linked by now — a processor a publisher has just seen — map the pool before the first frame, not at it
    (≈ 20–60 ms once). A publisher calls it after the nodes it waits for match its RF key: a processor that
    joined the bus first had not yet reached this session when its own warm-up ran. Best effort: nothing
    happens on error, nor for a session whose pool `warm_shm_pool` did not make: the announcement would
    create the pool itself, and the first frame would be the pool's next message, which a receiver that
    cannot map the pool yet drops."""
    if str(session.info.zid()) not in _WARMED:
        return
    try:
        pub = session.declare_publisher(
            f"_fp_warmup/{session.info.zid()}", congestion_control=zenoh.CongestionControl.BLOCK
        )
        try:
            pub.put(bytes(_PAYLOAD))
        finally:
            pub.undeclare()
    except zenoh.ZError:
        pass
