"""Scaling benchmark of sharded processing (issue 15.2; docs/scaling.md): throughput and publish → detection
latency of one `fp process` node against `fp merge` + 1, 2, 4 `fp worker` processes, every node behind a
zenoh router on loopback, on the same quick or full-size 3-D frames; detections and tracks compared with the
single node's.

    python bench/bench_scaling.py                       # 1, 2, 4 workers, 24 measured frames each
    python bench/bench_scaling.py --size full --frames 8 --warmup 1   # full-size frames (58.6 MB)
    python bench/bench_scaling.py --workers 1 2 --frames 12
    python bench/bench_scaling.py --shard fingerprint --workers 1 2   # both spheres' fingerprints, split

Frames: the quick 3-D sinking-sphere scenario (cached by bench/bench_streaming.py under out/bench/cache),
its grid (x −9…−1 mm, y ±4 mm, z 18–30 mm) and 40 frequencies; ``--size full``: the scenario's full-size
rig (32×32 elements × 25 plane waves × 572 samples, 58.6 MB a frame, cached the same way with a ``-full``
suffix) on the processor's default grid (76×76×143) and every band bin, as `fp process` runs it without
options. A few distinct frames are cycled with new indices and timestamps. The single node is
`fp process --mode router`; a sharded run is `fp merge --mode router` with its workers as zenoh clients.
The publisher (this process, a client) paces on acknowledgements with 2 frames in flight per worker.
Each worker's kernel threads: FP_THREADS = max(1, CPUs // workers). The first (``--warmup`` + 2) ×
workers frames (each worker's first frames and the frames queued behind them) are left out of the
figures; CPU time per frame is counted over the others. ``--shard`` is the merger's (docs/scaling.md).
``--fingerprints 2`` gives every run (the single node's too) both spheres' calibrations, a dictionary to
split: the default with ``--shard fingerprint`` and ``both`` (``--group-size``); ``frame`` defaults to
one (sphere1). It also prints what one frame costs outside the numerics (copy, wire encode/decode).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from bench_streaming import CASES, cached_frames  # noqa: E402

from services.bus import BusConfig, free_port, open_session  # noqa: E402
from services.messages import RFFrame  # noqa: E402
from services.nodes.publisher import Publisher  # noqa: E402
from services.sources import AcquisitionSource  # noqa: E402
from services.topics import keys  # noqa: E402
from services.wire import decode, encode  # noqa: E402

#: the processor's grid options per --size: quick, the bench_streaming grid; full, the defaults (76×76×143, every bin)
GRIDS = {"quick": ["--x=-9mm:-1mm", "--y=-4mm:4mm", "--z=18mm:30mm", "--n-freq", "40"], "full": []}


class Proc:
    """An `fp` subprocess (``python -m services.cli``), stopped by its pid."""

    def __init__(self, args: list[str], log: Path, env: dict[str, str] | None = None) -> None:
        self.log = log
        with open(log, "w") as err:
            self.p = subprocess.Popen(
                [sys.executable, "-m", "services.cli", *args],
                cwd=ROOT,
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
                env={**os.environ, **(env or {})},
            )

    def wait_ready(self, timeout: float = 900.0) -> None:  # full-size set-up: a minute or more per node
        out, deadline = self.p.stdout, time.monotonic() + timeout
        assert out is not None
        while time.monotonic() < deadline and self.p.poll() is None:
            if select.select([out], [], [], 0.2)[0] and '"ready"' in out.readline():
                return
        raise RuntimeError(f"node did not start:\n{self.log.read_text()[-2000:]}")

    def cpu_s(self) -> float:
        """CPU seconds (user + system) the process has used so far (Linux /proc)."""
        try:
            fields = Path(f"/proc/{self.p.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, IndexError, ValueError):
            return float("nan")

    def stop(self) -> dict[str, Any]:
        """SIGTERM by pid; the node's JSON summary (SIGKILL after 30 s)."""
        if self.p.poll() is None:
            os.kill(self.p.pid, signal.SIGTERM)
        try:
            out, _ = self.p.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            os.kill(self.p.pid, signal.SIGKILL)
            out, _ = self.p.communicate(timeout=10)
        lines = [ln for ln in (out or "").splitlines() if '"stopped"' in ln]
        return json.loads(lines[-1]) if lines else {}


def run(
    label: str, n_workers: int, frames: list, cals: list[Path], args: argparse.Namespace, tmp: Path
) -> dict[str, Any]:
    """One configuration: its nodes, the frames through them, what came back."""
    rig, port = f"scale{n_workers}", free_port()
    hub = f"tcp/127.0.0.1:{port}"
    # every worker's first frames, and the window of frames queued behind them
    warmup = (args.warmup + 2) * max(1, n_workers)
    total = warmup + args.frames
    fp_args = ["--rig", rig, *[a for c in cals for a in ("--calibration", str(c))], *GRIDS[args.size]]
    procs: list[Proc] = []
    head: Proc
    t0 = time.perf_counter()
    try:
        if n_workers == 0:
            head = Proc(["process", *fp_args, "--queue", "fifo", "--mode", "router", "--listen", hub], tmp / "p.log")
            procs.append(head)
        else:
            head = Proc(
                ["merge", "--rig", rig, "--queue", "fifo", "--workers", str(n_workers), "--mode", "router"]
                + ["--listen", hub, "--wait-workers", "300", "--shard", args.shard]
                + ["--group-size", str(args.group_size)],
                tmp / f"m{n_workers}.log",
            )
            threads = str(max(1, (os.cpu_count() or 1) // n_workers))  # every worker computes every frame's
            # spectrum and projection in the fingerprint modes: still one share of the cores each
            for i in range(n_workers):
                cmd = ["worker", *fp_args, "--name", f"w{i}", "--mode", "client", "--connect", hub]
                procs.append(Proc(cmd, tmp / f"w{n_workers}-{i}.log", {"FP_THREADS": threads}))
            procs.append(head)
        for p in procs:
            p.wait_ready()
        startup = time.perf_counter() - t0
        sent: dict[int, float] = {}
        got: dict[str, dict[int, Any]] = {"detections": {}, "tracks": {}}
        recv: dict[int, float] = {}
        gammas: list[bytes] = []
        lock = threading.Lock()
        k = keys(rig)

        def on_gamma(sample: Any) -> None:  # kept as bytes, decoded by compare() after the run
            with lock:
                gammas.append(sample.payload.to_bytes())

        def on(sample: Any) -> None:
            msg = decode(sample.payload.to_bytes())
            topic = str(sample.key_expr).rsplit("/", 1)[-1]
            with lock:
                got[topic][msg.frame_index] = msg
                if topic == "detections":
                    recv[msg.frame_index] = time.time()
                    if msg.frame_index == warmup - 1:  # CPU counted from here: the measured frames only
                        cpu0[:] = [p.cpu_s() for p in procs]
                        own0[0] = sum(os.times()[:2])

        window = 2 * max(1, n_workers)
        cpu0 = [float("nan")] * len(procs)
        own0 = [float("nan")]
        with open_session(BusConfig(mode="client", listen=None, connect=[hub], shm=args.shm)) as s:
            subs = [s.declare_subscriber(t, f) for t, f in ((k.detections, on), (k.tracks, on), (k.gamma, on_gamma))]
            pub = Publisher(
                s,
                rig,
                AcquisitionSource(frames, repeat=-(-total // len(frames)), limit=total),
                pace="ack",
                window=window,
                wait_timeout=60,
                ack_timeout=120,
                on_publish=lambda item, t: sent.__setitem__(item.frame_index, t),
            )
            summary = pub.run()
            deadline = time.monotonic() + 30
            while len(got["tracks"]) < total and time.monotonic() < deadline:
                time.sleep(0.05)
            for sub in subs:
                sub.undeclare()
        cpu = [p.cpu_s() - c for p, c in zip(procs, cpu0, strict=True)]
        own = sum(os.times()[:2]) - own0[0]
    finally:
        stats = [p.stop() for p in procs]
    meas = [i for i in sorted(recv) if i >= warmup]
    lat = np.array([recv[i] - sent[i] for i in meas]) * 1e3
    span = recv[meas[-1]] - recv[warmup - 1] if warmup >= 1 and len(meas) > 1 else float("nan")
    return {
        "label": label,
        "workers": n_workers,
        "window": window,
        "frames": len(recv),
        "published": summary["published"],
        "rate_hz": len(meas) / span if span > 0 else float("nan"),
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p95_ms": float(np.percentile(lat, 95)) if lat.size else float("nan"),
        "startup_s": startup,
        "detections": got["detections"],
        "tracks": got["tracks"],
        "gammas": gammas,
        "head_stats": stats[-1],
        # CPU ms per frame: the publisher (this process), the head node (processor or merger + router), workers
        "cpu_ms": {
            "publisher": 1e3 * own / len(meas),
            "head": 1e3 * cpu[-1] / len(meas),
            "workers": 1e3 * sum(cpu[:-1]) / len(meas),
        },
        "latency_ms": {i: round(1e3 * (recv[i] - sent[i]), 1) for i in meas},
        "load": os.getloadavg()[0],  # 1-min load average at the end of the run (our processes included)
    }


def frame_costs(acq: Any, repeat: int = 5) -> dict[str, float]:
    """CPU ms (median of ``repeat``) of what each hop does to one frame outside the numerics: a plain copy
    of its RF array, the FPWIRE01 encoding (header + one copy of the RF into the payload), the decoding
    (validation; the RF is a view), and ``bytes()`` of the payload (what a Python receiver that copies does)."""

    def med(fn: Any) -> float:
        fn()
        ts = []
        for _ in range(repeat):
            t = time.process_time()
            fn()
            ts.append(time.process_time() - t)
        return float(np.median(ts)) * 1e3

    msg = RFFrame.from_acquisition(acq)
    payload = encode(msg)
    return {
        "mb": len(payload) / 1e6,
        "copy_ms": med(lambda: acq.rf.copy()),
        "encode_ms": med(lambda: encode(msg)),
        "decode_ms": med(lambda: decode(payload)),
        "bytes_ms": med(lambda: bytes(memoryview(payload))),
    }


def gamma_delta(ref: dict[str, Any], run_: dict[str, Any]) -> tuple[float, float, int, int]:
    """(max |Δγ| over the frames both runs published, the same in uint16 codes of the reference's map
    (``gamma_step``; nan for float32 maps), maps compared, detections in the reference): the γ-maps as
    they travelled. Where the frames give no detection, the maps show that the runs computed the same."""

    def maps(r: dict[str, Any]) -> dict[tuple[int, str], Any]:
        return {(m.frame_index, m.fingerprint): m for m in (decode(b) for b in r["gammas"])}

    a, b = maps(ref), maps(run_)
    common = sorted(set(a) & set(b))
    worst = max((float(np.max(np.abs(a[k].gamma - b[k].gamma))) for k in common), default=float("nan"))
    codes = max(
        (float(np.max(np.abs(a[k].gamma - b[k].gamma))) / (a[k].gamma_step or float("nan")) for k in common),
        default=float("nan"),
    )
    n_det = sum(len(d.detections) for d in ref["detections"].values())
    return worst, codes, len(common), n_det


def compare(ref: dict[str, Any], run_: dict[str, Any]) -> tuple[bool, float]:
    """Same detections and tracks per frame (counts, names, track ids and status); the largest position
    difference in metres (the NUFFT's multithreaded sums differ at ≈ 1e-7 relative)."""
    same, worst = True, 0.0
    for i, d in ref["detections"].items():
        e = run_["detections"].get(i)
        t, u = ref["tracks"].get(i), run_["tracks"].get(i)
        if e is None or t is None or u is None or len(d.detections) != len(e.detections):
            return False, float("nan")
        if len(t.tracks) != len(u.tracks):
            return False, float("nan")
        for a, b in zip(d.detections, e.detections, strict=True):
            same &= a.fingerprint == b.fingerprint
            worst = max(worst, float(np.max(np.abs(np.subtract(a.position_m, b.position_m)))))
        for a, b in zip(t.tracks, u.tracks, strict=True):
            same &= (a.id, a.fingerprint, a.status) == (b.id, b.fingerprint, b.status)
            worst = max(worst, float(np.max(np.abs(np.subtract(a.position_m, b.position_m)))))
    return same and worst < 1e-6, worst


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4], help="worker counts (default 1 2 4)")
    ap.add_argument("--frames", type=int, default=24, help="measured frames per run (default 24)")
    ap.add_argument("--warmup", type=int, default=3, help="warm-up frames left out (default 3)")
    ap.add_argument("--distinct", type=int, default=2, help="distinct simulated frames, cycled (default 2)")
    ap.add_argument("--shm", default="auto", help="the publisher's zenoh shared memory (default auto)")
    ap.add_argument(
        "--shard",
        choices=("frame", "fingerprint", "both"),
        default="frame",
        help="fp merge --shard (default frame; fingerprint/both use both spheres' fingerprints in every run)",
    )
    ap.add_argument(
        "--fingerprints",
        type=int,
        choices=(1, 2),
        help="dictionary entries: 1 (sphere1) or 2 (sphere1, sphere2); default 1 with --shard frame, else 2",
    )
    ap.add_argument("--group-size", type=int, default=2, help="fp merge --group-size for --shard both (default 2)")
    ap.add_argument(
        "--size", choices=("quick", "full"), default="quick", help="quick (9.2 MB) or full-size (58.6 MB) frames"
    )
    ap.add_argument("--json", help="write the table as JSON")
    args = ap.parse_args()
    if args.warmup < 1:
        ap.error("--warmup: expected >= 1")
    case = CASES["3d"]
    n_fp = args.fingerprints or (1 if args.shard == "frame" else 2)
    targets = ["sphere1", "sphere2"][:n_fp]
    quick = args.size == "quick"
    frames, _ = cached_frames(case["scenario"], args.distinct, targets, quick=quick)
    tag = case["scenario"] if quick else f"{case['scenario']}-full"
    cals = [Path("out/bench/cache") / f"{tag}-cal-{t}.uff" for t in targets]
    a = frames[0]
    cpus = os.cpu_count()
    print(
        f"{'quick' if quick else 'full-size'} 3-D {case['scenario']}: {a.probe.n_elements} elements × "
        f"{a.sequence.n_waves} plane waves × {a.n_samples} samples = {a.rf.nbytes / 1e6:.1f} MB/frame; "
        f"{args.warmup} warm-up + {args.frames} frames per run; fingerprints {targets}, --shard {args.shard}; "
        f"{cpus} CPU(s), load average {os.getloadavg()[0]:.1f} at start (shared machine)",
        flush=True,
    )
    fc = frame_costs(a)
    print(
        f"per frame, outside the numerics (CPU ms, median of 5): RF copy {fc['copy_ms']:.1f}, wire encode "
        f"{fc['encode_ms']:.1f}, decode {fc['decode_ms']:.2f}, bytes() of the {fc['mb']:.1f} MB payload "
        f"{fc['bytes_ms']:.1f}; load {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in [0, *args.workers]:
            label = (
                "single node (fp process)" if n == 0 else f"fp merge --shard {args.shard} + {n} worker{'s' * (n > 1)}"
            )
            r = run(label, n, frames, cals, args, Path(tmp))
            rows.append(r)
            merger = {k: r["head_stats"].get(k) for k in ("per_worker", "reassigned", "duplicates")} if n else {}
            print(
                f"  {label}: {r['rate_hz']:.2f} frames/s, p50 {r['p50_ms']:.0f} ms, p95 {r['p95_ms']:.0f} ms, "
                f"start-up {r['startup_s']:.0f} s, load {r['load']:.1f}, CPU ms/frame {json.dumps(r['cpu_ms'])} "
                f"{json.dumps(merger)}",
                flush=True,
            )
    ref = rows[0]
    print(
        "\n| run | frames/s | × single node | p50 ms | p95 ms | CPU ms/frame: publisher, processor or merger, "
        "workers | cores used | load | detections & tracks = single node | γ-maps: max |Δγ| (maps) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    table = []
    for r in rows:
        same, worst = compare(ref, r) if r is not ref else (True, 0.0)
        ratio = r["rate_hz"] / ref["rate_hz"]
        dg, dcodes, n_maps, n_det = gamma_delta(ref, r)
        cell = "reference" if r is ref else ("yes" if same else "NO") + f" (max Δ {worst * 1e9:.1f} nm)"
        cell += f"; {n_det} detections" if r is ref else ""
        gcell = "reference" if r is ref else f"{dg:.1e} = {dcodes:.1f} code ({n_maps})"
        c = r["cpu_ms"]
        cores = r["rate_hz"] * (c["publisher"] + c["head"] + c["workers"]) / 1e3  # CPU s per s: the cores we got
        print(
            f"| {r['label']} | {r['rate_hz']:.1f} | {ratio:.2f} | {r['p50_ms']:.0f} | {r['p95_ms']:.0f} | "
            f"{c['publisher']:.0f}, {c['head']:.0f}, {c['workers']:.0f} | {cores:.2f} | {r['load']:.1f} | {cell} | "
            f"{gcell} |"
        )
        keep = ("label", "workers", "window", "frames", "rate_hz", "p50_ms", "p95_ms", "cpu_ms", "latency_ms", "load")
        table.append(
            {k: r[k] for k in keep}
            | {"ratio": ratio, "cores": cores, "same": same, "max_delta_m": worst}
            | {"max_delta_gamma": dg, "max_delta_codes": dcodes, "maps_compared": n_maps, "ref_detections": n_det}
        )
    print(
        f"\nMachine: {cpus} CPU(s), shared with other jobs (load average {os.getloadavg()[0]:.1f} at the end). "
        "'cores used' = frames/s × the CPU time per frame of all our processes: what the run got of the machine. "
        "The rate is that share divided by the CPU time per frame; sharding adds CPU per frame (the merger "
        "receives each frame, forwards it to a worker, decodes the γ-maps and tracks; each worker receives, "
        "decodes and encodes) and spreads the workers' part over processes — it raises the rate only where "
        "idle cores are left for the workers. Latency grows with the frames in flight (2 per worker: "
        "Little's law)."
    )
    if args.json:
        Path(args.json).write_text(json.dumps({"size": args.size, "frame_costs": fc, "runs": table}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
