"""No first-frame stall (issue 15, item 4): the numba kernels of fpcore.kernel_presum_loops are cached on disk, so a
fresh process loads them instead of compiling them, and importing never fails for want of a writable cache folder;
sessions that send large messages create their shared-memory pool when they open (services.bus_warm), not at their
first frame. (The latency ratio itself is measured by bench/bench_first_frame.py: no wall-clock test here.)"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numba  # noqa: F401  (a required dependency: its absence fails these tests, never skips them)
import pytest

ROOT = Path(__file__).resolve().parent.parent

# A small γ through the structured kernel (both lateral variants), then each kernel's cache hits and misses.
RUN = """
import json, numpy as np
import fpcore.kernel_presum_loops as L
from fpcore.grid import Grid
from fpcore.kernel_presum import PresumTransform
ax = (np.arange(4) - 1.5) * 0.037
yy, xx = np.meshgrid(ax, ax, indexing="ij")
so = np.stack([xx.ravel(), yy.ravel()], 1)
si = np.array([[-0.037, 0.0], [0.0, 0.0], [0.037, 0.0]])
freqs = np.linspace(3e6, 5e6, 4)
grid = Grid.centred((0.0, 0.0, 12e-3), (6, 5, 7), 0.1e-3)
w = np.ones(freqs.size * so.shape[0] * si.shape[0], np.complex64)
for lateral in ("exact", "nufft"):
    PresumTransform(freqs, so, si, 1540.0, grid, nthreads=1, lateral=lateral)(w)
names = [n for n in dir(L) if hasattr(getattr(L, n), "stats") and hasattr(getattr(L, n), "py_func")]
print(json.dumps({n: [sum(getattr(L, n).stats.cache_hits.values()), sum(getattr(L, n).stats.cache_misses.values())]
                  for n in names}))
"""


def _run(code: str, env: dict[str, str]) -> dict:
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=240, check=False
    )
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.timeout(300)
def test_a_fresh_process_loads_the_kernels_from_the_disk_cache(tmp_path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    first = _run(RUN, env)  # an empty cache folder: every kernel used is compiled and written
    used = {n for n, (_, misses) in first.items() if misses}
    assert {"spread_depth", "depth_synthesis"} <= used and len(used) >= 4, first
    assert len(list((tmp_path / "cache").rglob("*.nbi"))) >= len(used)
    second = _run(RUN, env)  # a fresh process: loaded, nothing compiled (a kernel only called by others,
    assert all(misses == 0 for _, misses in second.values()), second  # e.g. accumulate, is inside its callers)
    assert sum(hits for hits, _ in second.values()) >= len(used) - 1 and second["spread_depth"][0] >= 1, second


FALLBACK = (
    "import json, numba, fpcore.kernel_presum_loops as L; "
    "print(json.dumps({'dir': numba.config.CACHE_DIR, 'fallback': L._fallback_cache_dir(), "
    "'cache_path': L.spread_depth.stats.cache_path}))"
)


def _no_locator(tmp: Path) -> dict[str, str]:
    """numba finds no locator (only the NUMBA_CACHE_DIR one allowed, and it unset); temporary directory ``tmp``."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["NUMBA_CACHE_LOCATOR_CLASSES"] = "UserProvidedCacheLocator"
    env["TMPDIR"] = str(tmp)
    return env


def test_no_writable_cache_folder_falls_back_to_the_temporary_directory(tmp_path) -> None:
    """The decorator points the cache at a per-user folder of the temporary directory, created 0700, instead of
    failing the import."""
    doc = _run(FALLBACK, _no_locator(tmp_path))
    assert doc["dir"] == doc["fallback"] and doc["cache_path"].startswith(doc["fallback"])
    assert Path(doc["fallback"]).parent == tmp_path and Path(doc["fallback"]).stat().st_mode & 0o777 == 0o700


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX owners and modes")
@pytest.mark.parametrize("mode", [0o755, 0o777, "link"])
def test_a_fallback_folder_others_could_write_or_read_is_not_used(tmp_path, mode) -> None:
    """numba's cache index is a pickle: a folder open to others (or a link planted in its place) is never
    loaded from; the kernels are compiled without a cache."""
    folder = tmp_path / f"fpcore-numba-cache-{os.getuid()}"
    if mode == "link":
        (tmp_path / "elsewhere").mkdir(mode=0o700)
        folder.symlink_to(tmp_path / "elsewhere")
    else:
        folder.mkdir()
        folder.chmod(mode)
    doc = _run(FALLBACK, _no_locator(tmp_path))
    assert doc == {"dir": "", "fallback": None, "cache_path": None}
    assert not any(tmp_path.rglob("*.nbi"))


def test_a_sending_session_creates_its_shm_pool_when_it_opens() -> None:
    import zenoh

    from services.bus import EPHEMERAL, BusConfig, zenoh_config
    from services.bus_warm import pin_ephemeral_ports, wants_warmup, warm_shm_pool

    if BusConfig(shm="auto").shm_pool_bytes() is None:
        pytest.skip("/dev/shm has no room for a pool: SHM is off here")
    cfg = zenoh_config(BusConfig(listen=[EPHEMERAL], connect=[], shm="64", warm_shm=True))
    assert wants_warmup(cfg)
    pin_ephemeral_ports(cfg)
    (endpoint,) = json.loads(cfg.get_json("listen/endpoints"))
    assert endpoint.startswith("tcp/127.0.0.1:") and not endpoint.endswith(":0")
    with zenoh.open(cfg) as session:
        assert warm_shm_pool(session, cfg)  # the helper received the 64 KiB message through shared memory
    # Nothing to do without SHM, in client mode (no listener) or when the listener wants a login.
    assert not wants_warmup(zenoh_config(BusConfig(listen=[EPHEMERAL], connect=[], shm="off")))
    assert not wants_warmup(zenoh_config(BusConfig(mode="client", listen=None, connect=[EPHEMERAL], shm="64")))
    login = zenoh_config(BusConfig(listen=[EPHEMERAL], connect=[], shm="64"))
    login.insert_json5("transport/auth/usrpwd/dictionary_file", '"/dev/null"')
    assert not wants_warmup(login)


def test_a_pinned_port_taken_meanwhile_is_replaced(monkeypatch: pytest.MonkeyPatch) -> None:
    """pin_ephemeral_ports probes a free port that the session binds later: when another process takes it in
    between ("address in use"), open_session pins a fresh one instead of failing."""
    import socket

    import services.bus as bus_module
    from services.bus import EPHEMERAL, BusConfig, open_session, zenoh_config
    from services.bus_warm import wants_warmup

    if not wants_warmup(zenoh_config(BusConfig(listen=[EPHEMERAL], connect=[], shm="64", warm_shm=True))):
        pytest.skip("no SHM warm-up here: nothing is pinned")
    real = bus_module.free_port
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        probes: list[int] = []

        def racy_free_port() -> int:  # the first probe returns a port another process holds by now
            probes.append(busy if not probes else real())
            return probes[-1]

        monkeypatch.setattr(bus_module, "free_port", racy_free_port)
        with open_session(BusConfig(listen=[EPHEMERAL], connect=[], shm="64", warm_shm=True)) as session:
            assert session.info.zid() is not None
        assert len(probes) == 2 and probes[0] == busy != probes[1]


def test_the_publisher_announces_its_pool_before_its_first_frame() -> None:
    """A processor that joined the bus before the publisher never got the publisher's own warm-up messages, so it
    mapped the publisher's SHM pool at the first frame (20–60 ms once: the first frame's latency was over 2× the
    median in ~1 run in 3). The publisher now puts one warm-up message (services.bus_warm.announce_pool) once its
    subscribers match: the processor receives it — and maps the pool — before the first RF frame. A session
    whose pool was not made at open does not announce (the announcement would make it; test below)."""
    from services.bus import EPHEMERAL, BusConfig, free_port, open_session
    from services.bus_warm import WARM_KEYS
    from services.nodes.publisher import Publisher
    from services.sources import AcquisitionSource, born_frames
    from services.topics import keys

    if BusConfig(shm="auto").shm_pool_bytes() is None:
        pytest.skip("/dev/shm has no room for a pool: SHM is off here")
    rig, hub = "announce", f"tcp/127.0.0.1:{free_port()}"
    frames, _ = born_frames(1)
    seen: list[str] = []
    with open_session(BusConfig(listen=[hub], connect=[], shm="off")) as proc:
        subs = [proc.declare_subscriber(k, lambda s: seen.append(str(s.key_expr))) for k in (WARM_KEYS, keys(rig).rf)]
        token = proc.liveliness().declare_token(keys(rig).alive("processor", "p0"))
        # the publisher's session warms its own pool at open (as fp publish): only such a session announces it
        with open_session(BusConfig(listen=[EPHEMERAL], connect=[hub], shm="64", warm_shm=True)) as pub_session:
            zid = str(pub_session.info.zid())
            src = AcquisitionSource(frames, repeat=1, limit=1)
            Publisher(pub_session, rig, src, pace="rate", rate=100.0, limit=1, wait_for=("processor",)).run()
            deadline = time.monotonic() + 10
            while keys(rig).rf not in seen and time.monotonic() < deadline:
                time.sleep(0.02)
        token.undeclare()
        for sub in subs:
            sub.undeclare()
    assert keys(rig).rf in seen, seen
    warm = [i for i, k in enumerate(seen) if k == f"_fp_warmup/{zid}"]
    assert warm and warm[0] < seen.index(keys(rig).rf), seen


def test_a_session_without_a_warmed_pool_does_not_announce() -> None:
    """announce_pool puts nothing for a session whose pool warm_shm_pool did not make (SHM off here): the
    announcement would create the pool, and the first frame would be the pool's next message."""
    from services.bus import EPHEMERAL, BusConfig, free_port, open_session
    from services.bus_warm import WARM_KEYS, announce_pool

    hub = f"tcp/127.0.0.1:{free_port()}"
    seen: list[str] = []
    with open_session(BusConfig(listen=[hub], connect=[], shm="off")) as listener:
        sub = listener.declare_subscriber(WARM_KEYS, lambda s: seen.append(str(s.key_expr)))
        with open_session(BusConfig(listen=[EPHEMERAL], connect=[hub], shm="off")) as other:
            probe = other.declare_publisher("_fp_warmup/probe")
            deadline = time.monotonic() + 10
            while not seen and time.monotonic() < deadline:  # the subscription has reached `other`
                probe.put(b"x")
                time.sleep(0.05)
            probe.undeclare()
            n, zid = len(seen), str(other.info.zid())
            announce_pool(other)
            time.sleep(0.5)
        sub.undeclare()
    assert n >= 1 and f"_fp_warmup/{zid}" not in seen[n:], seen
