"""Streaming benchmark: sustained frames/s and publish → detection latency of the whole pipeline
(publisher + processor + recorder in one process over zenoh on loopback; services.nodes.local.run_pipeline),
with the share of processor time in each stage (docs/design.md §7, §8: speed is measured by scripts).

    python bench/bench_streaming.py                 # 3D sinking-sphere (quick) and 2D muscle-fibres (quick)
    python bench/bench_streaming.py --only 2d --frames 40 --no-record
    python bench/bench_streaming.py --only 3d --frames 40 --compression lz4 --no-display --adc-bits 16

Frames come from the simulator (``fpcore.simulate``), which is exact but slow (seconds per 3D frame):
a few distinct frames are generated once, cached as UFF under ``out/bench/cache`` and cycled with new
frame indices (``--distinct``). Pacing is "as fast as the processor takes" (ack, ``--window`` frames in
flight, default 2: throughput; 1: latency ≈ one frame's processing);
the first ``--warmup`` frames (shared-memory pool page faults, caches) are left out of the figures.
Stages: decode (wire → arrays, in the subscriber callback), spectrum + projection (rFFT of the band
and P_θu), γ kernel (one NUFFT per fingerprint + the confocal image), detection (peaks, contrasts,
PFA, precision, tracker), encode/publish (wire encoding and zenoh puts of image, γ-maps, tracks,
detections). Recorder: zstd (level 1), byte shuffle and display channels by default (``--compression``,
``--no-shuffle``, ``--no-display``); ``--map-encoding`` is the processor's (uint16 maps by default);
``--adc-bits`` digitises the RF as `fp demo` does (int16 with its scale; default: float32 RF). The recording's
size per frame is printed (``--keep`` keeps it).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from fpcore.acquisition import Acquisition
from fpcore.io import read_uff, write_uff
from services.nodes.local import run_pipeline
from services.nodes.processor import STAGES, ProcessorConfig
from services.registry import FingerprintSpec
from services.sources import AcquisitionSource

CACHE = Path("out/bench/cache")

#: name → (scenario, targets used as fingerprints, processor grid settings)
CASES: dict[str, dict[str, Any]] = {
    "3d": {
        "scenario": "sinking-sphere",
        "targets": ["sphere1"],
        "grid": {"x_range": (-9e-3, -1e-3), "y_range": (-4e-3, 4e-3), "z_range": (18e-3, 30e-3)},
    },
    "2d": {
        "scenario": "muscle-fibres",
        "targets": ["fibre"],
        "grid": {"x_range": (-6e-3, 6e-3), "z_range": (10e-3, 20e-3)},
    },
}


def cached_frames(
    scenario: str, n: int, targets: list[str], quick: bool = True
) -> tuple[list[Acquisition], dict[str, Acquisition]]:
    """n distinct frames and the targets' calibrations, generated once (seed 0; ``quick=False``: the
    scenario's full-size rig, cached with a ``-full`` suffix)."""
    CACHE.mkdir(parents=True, exist_ok=True)
    tag = scenario if quick else f"{scenario}-full"
    frames_path = CACHE / f"{tag}-{n}.uff"
    cal_paths = {t: CACHE / f"{tag}-cal-{t}.uff" for t in targets}
    if not frames_path.exists() or not all(p.exists() for p in cal_paths.values()):
        from fpcore import simulate

        sc = simulate.scenario(scenario, quick=quick, seed=0, n_frames=max(n, 2))
        t = time.perf_counter()
        frames = [sc.frame(i) for i in range(n)]
        write_uff(frames_path, frames)
        for name, p in cal_paths.items():
            write_uff(p, sc.calibration(name))
        print(
            f"  simulated {n} frame(s) + {len(targets)} calibration(s) of {scenario} in "
            f"{time.perf_counter() - t:.1f} s (cached in {CACHE})",
            flush=True,
        )
    return read_uff(frames_path), {t: read_uff(p)[0] for t, p in cal_paths.items()}


def run_case(name: str, args: argparse.Namespace) -> dict[str, Any]:
    case = CASES[name]
    frames, cals = cached_frames(case["scenario"], args.distinct, case["targets"])
    a = frames[0]
    total = args.warmup + args.frames
    repeat = -(-total // len(frames))
    specs = [FingerprintSpec(t, calibration=c) for t, c in cals.items()]
    cfg = ProcessorConfig(
        rig=f"bench{name}", queue="fifo", n_freq=args.n_freq, map_encoding=args.map_encoding, **case["grid"]
    )
    print(
        f"[{name}] {case['scenario']} (quick): {a.probe.n_elements} elements × {a.sequence.n_waves} plane waves "
        f"× {a.n_samples} samples = {a.rf.nbytes / 1e6:.1f} MB/frame; fingerprints {case['targets']}; "
        f"{args.warmup} warm-up + {args.frames} frames",
        flush=True,
    )
    source: Any = AcquisitionSource(frames, repeat=repeat, limit=total)
    if args.adc_bits:  # int16 RF with its scale, as `fp demo` publishes it
        from services.convert import QuantisedSource

        source = QuantisedSource(source, args.adc_bits)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) if not args.keep else Path("out/bench") / name
        t = time.perf_counter()
        s = run_pipeline(
            source,
            rig=cfg.rig,
            out_dir=out,
            n_frames=total,
            fingerprints=specs,
            processor=cfg,
            record=not args.no_record,
            shm=args.shm,
            warmup=args.warmup,
            window=args.window,
            recorder={"compression": args.compression, "display": not args.no_display, "shuffle": not args.no_shuffle},
        )
        wall = time.perf_counter() - t
        rec_mb = sum(Path(f).stat().st_size for f in s["recording"]["files"]) / 1e6 if s.get("recording") else 0.0
    measured = s["frames"][args.warmup :]
    dets = [d for r in measured for d in r["detections"]]
    err = sorted(d["truth_error_m"] for d in dets if d["truth_error_m"] is not None)
    lat = s["latency_ms"]
    print(
        f"  sustained {s['frame_rate_hz']:.2f} frames/s; publish→detection latency median {lat['median']:.0f} ms, "
        f"p95 {lat['p95']:.0f} ms; processed {s['frames_processed']}/{s['frames_published']}, dropped "
        f"{s['dropped']}, rejected {s['rejected']}; set-up {s['setup_s']:.1f} s, run {wall:.1f} s",
        flush=True,
    )
    shares = "  ".join(
        f"{k.replace('_', ' ')} {100 * s['stage_share'][k]:.1f}% ({1e3 * s['stage_mean_s'][k]:.1f} ms)" for k in STAGES
    )
    print(f"  stages per frame: {shares}", flush=True)
    if rec_mb:
        print(f"  recording {rec_mb:.1f} MB, {rec_mb / total:.2f} MB a frame", flush=True)
    if dets:
        c = sorted(d["contrast_c_gamma"] for d in dets)[len(dets) // 2]
        e = f", median error to the truth {1e3 * err[len(err) // 2]:.2f} mm" if err else ""
        print(f"  detections: median C_γ {c:.1f}{e}", flush=True)
    s.pop("frames")
    s["case"], s["frame_mb"], s["recording_mb"] = name, a.rf.nbytes / 1e6, rec_mb
    return s


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=tuple(CASES), help="run one case")
    ap.add_argument("--frames", type=int, default=30, help="measured frames per case (default 30)")
    ap.add_argument("--warmup", type=int, default=3, help="warm-up frames left out (default 3)")
    ap.add_argument("--distinct", type=int, default=2, help="distinct simulated frames, cycled (default 2)")
    ap.add_argument("--n-freq", type=int, default=40, help="frequencies in the band (default 40)")
    ap.add_argument("--window", type=int, default=2, help="frames in flight (default 2; 1 = lowest latency)")
    ap.add_argument("--no-record", action="store_true", help="run without the recorder")
    ap.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="recorder chunks")
    ap.add_argument("--no-shuffle", action="store_true", help="recorder: payloads as they travelled")
    ap.add_argument("--no-display", action="store_true", help="recorder: no Foxglove display channels")
    ap.add_argument("--map-encoding", choices=("uint16", "float32"), default="uint16", help="processor's maps")
    ap.add_argument("--adc-bits", type=int, default=0, help="int16 RF of this many bits (default 0: float32)")
    ap.add_argument("--shm", default="auto", help="zenoh shared memory: auto, off or pool MiB (default auto)")
    ap.add_argument("--keep", action="store_true", help="keep the recordings under out/bench/<case>")
    ap.add_argument("--json", help="write the summaries as JSON")
    args = ap.parse_args()
    recorder = f"on ({args.compression}, shuffle {not args.no_shuffle}, display {not args.no_display})"
    print(
        f"bench_streaming: {os.cpu_count()} CPU(s), load {os.getloadavg()[0]:.1f}, recorder "
        f"{'off' if args.no_record else recorder}, "
        f"maps {args.map_encoding}, RF {f'int16 ({args.adc_bits} bits)' if args.adc_bits else 'float32'}, "
        f"shm {args.shm}, {args.window} frame(s) in flight",
        flush=True,
    )
    results = [run_case(name, args) for name in ([args.only] if args.only else CASES)]
    print(f"load after: {os.getloadavg()[0]:.1f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
