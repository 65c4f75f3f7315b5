"""First-frame latency against the median, in a fresh process (issue 15, item 4: no compile stall).

    python bench/bench_first_frame.py                  # quick 3-D sinking-sphere, numba cache as it is
    python bench/bench_first_frame.py --cold-cache     # numba cache in an empty folder: compiles everything
    python bench/bench_first_frame.py --no-warm-shm    # SHM pools created at the first large message

A processor and a publisher node in this process over zenoh on loopback, wired as `fp process` and
`fp publish` are (``BusConfig.warm_shm``: each creates its shared-memory pool when its session opens; no
recorder), on the quick 3-D frames of ``bench/bench_streaming.py`` (generated once, cached under
``out/bench/cache``), one frame in flight (a frame's latency is its own processing, no queueing). Prints
the publish → detection latency of the first frame, the median of the others and their ratio (target
≤ 2), and the time from opening the sessions to the processor being up ("ready").
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12, help="frames (default 12)")
    ap.add_argument("--cold-cache", action="store_true", help="numba cache in an empty folder (compile all)")
    ap.add_argument("--shm", default="auto", help="zenoh shared memory: auto, off or pool MiB (default auto)")
    ap.add_argument("--no-warm-shm", action="store_true", help="create the SHM pools at the first large message")
    ap.add_argument("--json", help="write the figures as JSON")
    args = ap.parse_args()
    if args.cold_cache:
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="fp-numba-cold-")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    t0 = time.perf_counter()
    from bench_streaming import CASES, cached_frames

    from services.bus import EPHEMERAL, BusConfig, free_port, open_session, tune_malloc
    from services.nodes.processor import Processor, ProcessorConfig
    from services.nodes.publisher import Publisher
    from services.registry import FingerprintSpec
    from services.sources import AcquisitionSource

    t_import = time.perf_counter() - t0
    tune_malloc()
    case = CASES["3d"]
    frames, cals = cached_frames(case["scenario"], 2, case["targets"])
    specs = [FingerprintSpec(t, calibration=c) for t, c in cals.items()]
    cfg = ProcessorConfig(rig="firstframe", queue="fifo", n_freq=40, **case["grid"])
    rows: list[dict] = []
    hub = f"tcp/127.0.0.1:{free_port()}"
    warm = not args.no_warm_shm
    t1 = time.perf_counter()
    with open_session(BusConfig(listen=[hub], connect=[], shm=args.shm, warm_shm=warm)) as s_proc:
        with Processor(s_proc, cfg, specs, on_result=rows.append) as node:
            t_ready = time.perf_counter() - t1
            with open_session(BusConfig(listen=[EPHEMERAL], connect=[hub], shm=args.shm, warm_shm=warm)) as s_pub:
                src = AcquisitionSource(frames, repeat=-(-args.frames // len(frames)), limit=args.frames)
                Publisher(s_pub, cfg.rig, src, pace="ack", window=1, limit=args.frames, wait_for=("processor",)).run()
                deadline = time.monotonic() + 30
                while len(rows) < args.frames and time.monotonic() < deadline:
                    time.sleep(0.02)
            setup_s = node.pipeline.setup_s
    wall = time.perf_counter() - t1
    s = {"frames": sorted(rows, key=lambda r: r["frame_index"]), "setup_s": setup_s}
    lat = [r["latency_ms"] for r in s["frames"]]
    first, rest = lat[0], statistics.median(lat[1:])
    out = {
        "cpus": os.cpu_count(),
        "numba_cache": "cold (empty folder)" if args.cold_cache else "as found",
        "shm": args.shm,
        "warm_shm": warm,
        "ready_s": t_ready,
        "import_s": t_import,
        "setup_s": s["setup_s"],
        "run_s": wall,
        "first_ms": first,
        "median_others_ms": rest,
        "ratio": first / rest,
        "latencies_ms": lat,
    }
    print(
        f"bench_first_frame: {os.cpu_count()} CPU(s), numba cache {out['numba_cache']}, shm {args.shm}"
        f"{' (pools warmed at start)' if warm and args.shm != 'off' else ''}; import {t_import:.1f} s, "
        f"set-up {s['setup_s']:.1f} s, ready after {t_ready:.1f} s; first frame {first:.0f} ms, "
        f"median of the next {len(lat) - 1} {rest:.0f} ms: ratio {first / rest:.2f}",
        flush=True,
    )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
