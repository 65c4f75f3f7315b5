"""A full-size 3-D frame from RF to tracks, offline, with its stages profiled (issue 15, item 6: ≤ 1 s a
frame on one worker, 2 cores).

    python bench/bench_full_frame.py                     # 6 measured frames after 1 warm-up
    python bench/bench_full_frame.py --frames 10 --json out/bench/full_frame.json

Frames: the sinking-sphere scenario's full-size rig (32×32 elements × 25 plane waves × 572 samples,
58.6 MB of float32 RF; simulated once and cached under out/bench/cache by bench/bench_streaming.py's
``cached_frames(quick=False)``), sphere1's calibration as the one fingerprint, and the processor's defaults:
the grid ``Grid.for_acquisition`` gives (76×76×143), every band bin of the 2×-padded record, the tracker on —
exactly `services.pipeline.Pipeline` as `fp process` and `fp track` run it. Distinct frames are cycled with
new indices and timestamps.

Prints the wall time and the process CPU time per frame of ``Pipeline.process`` (median, p95) with its three
stages (the null models run on a second thread while the confocal image is made: 'gamma_kernel' holds the
γ-maps, the image and whatever of the null models overlaps it, 'detection' the rest), then each stage split
into its calls, each timed alone on the last frame (median of ``--repeat``):
spectrum (rFFT of the padded record, band bins), projection (P_θu products), γ (one fingerprint), confocal
image, null model (the physical null level, eq. B1, and the CFAR), detections, tracker update. The bus adds
decoding and encoding: bench/bench_scaling.py ``--size full`` runs the same frames through `fp process` and
sharded workers.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from bench_streaming import cached_frames  # noqa: E402

from fpcore.acquisition import to_plane_waves  # noqa: E402
from fpcore.locate import null_of  # noqa: E402
from services.pipeline import Pipeline, PipelineConfig, find_targets  # noqa: E402
from services.registry import FingerprintSpec  # noqa: E402


def timed(fn: Callable[[], Any], repeat: int) -> tuple[float, float]:
    """(wall, CPU) seconds of fn(), medians over ``repeat`` calls after one untimed call."""
    fn()
    wall, cpu = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.median(wall)), float(np.median(cpu))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6, help="measured frames (default 6)")
    ap.add_argument("--warmup", type=int, default=1, help="warm-up frames left out (default 1)")
    ap.add_argument("--repeat", type=int, default=3, help="calls per stage in the split (median; default 3)")
    ap.add_argument("--n-freq", type=int, help="frequencies kept in the band (default: every bin, as fp process)")
    ap.add_argument("--no-image", action="store_true", help="no confocal image (fp process --no-image's choice)")
    ap.add_argument("--json", help="write the figures as JSON")
    args = ap.parse_args()
    if args.frames < 1 or args.warmup < 0 or args.repeat < 1 or (args.n_freq is not None and args.n_freq < 2):
        ap.error("--frames and --repeat: expected >= 1, --warmup >= 0, --n-freq >= 2")
    t = time.perf_counter()
    frames, cals = cached_frames("sinking-sphere", 2, ["sphere1"], quick=False)
    a = frames[0]
    print(
        f"bench_full_frame: sinking-sphere full size, {a.probe.n_elements} elements × {a.sequence.n_waves} plane "
        f"waves × {a.n_samples} samples = {a.rf.nbytes / 1e6:.1f} MB (loaded in {time.perf_counter() - t:.1f} s); "
        f"n_freq {args.n_freq or 'all bins'}, image {not args.no_image}; {os.cpu_count()} CPU(s), "
        f"FP_THREADS={os.environ.get('FP_THREADS', 'all')}, load {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    cfg = PipelineConfig(n_freq=args.n_freq, publish_image=not args.no_image)
    pipe = Pipeline(cfg, [FingerprintSpec("sphere1", calibration=cals["sphere1"])])
    t = time.perf_counter()
    pipe.warm_up()
    print(f"  set-up (imager, NUFFT plan, fingerprint) {time.perf_counter() - t:.1f} s; grid {pipe.grid.shape}")
    total = args.warmup + args.frames
    walls, cpus, stages = [], [], []
    res: Any = None
    span = frames[-1].timestamp - frames[0].timestamp
    span = 2 * span if span > 0 else 0.2  # frames cycled as AcquisitionSource does: new indices, later times
    for n in range(total):
        acq = dataclasses.replace(
            frames[n % len(frames)],
            frame_index=n,
            timestamp=frames[n % len(frames)].timestamp + n // len(frames) * span,
        )
        t, c = time.perf_counter(), time.process_time()
        res = pipe.process(acq)
        w, u = time.perf_counter() - t, time.process_time() - c
        if n >= args.warmup:
            walls.append(w)
            cpus.append(u)
            stages.append(res.stage_s)
        print(
            f"  frame {n}{' (warm-up)' * (n < args.warmup)}: {w * 1e3:.0f} ms wall, {u * 1e3:.0f} ms CPU; "
            + ", ".join(f"{k} {v * 1e3:.0f}" for k, v in res.stage_s.items())
            + f"; {len(res.detections)} detection(s), {len(res.tracks)} track(s)",
            flush=True,
        )
    wall_ms = 1e3 * np.array(walls)
    mean_stage = {k: 1e3 * float(np.mean([s[k] for s in stages])) for k in stages[0]}
    print(
        f"Pipeline.process, {args.frames} frames: median {np.median(wall_ms):.0f} ms, p95 "
        f"{np.percentile(wall_ms, 95):.0f} ms wall ({1e3 / np.median(wall_ms):.2f} frames/s); CPU "
        f"{1e3 * np.median(cpus):.0f} ms/frame (≈ {np.median(cpus) / np.median(walls):.2f} cores); stages (mean ms): "
        + ", ".join(f"{k} {v:.0f} ({100 * v / sum(mean_stage.values()):.0f} %)" for k, v in mean_stage.items())
        + f"; load {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    # each stage's calls, timed alone on the last frame, as Pipeline.process makes them
    imager, acq, band, grid = pipe._imager, res.acq, res.band, res.grid  # noqa: SLF001 (bench: the same objects)
    assert imager is not None
    fp = res.fingerprints["sphere1"]
    cfg = imager.config
    spec = acq.spectrum(cfg.band[0], cfg.band[1], cfg.n_freq)
    out = imager.out_sines_for(acq)
    pw = to_plane_waves(spec, out)
    g = imager.gamma(pw, fp)
    null = null_of(g, grid, acq, pw, fp, band, pipe._level)  # noqa: SLF001
    split = {
        "spectrum (rFFT, band bins)": lambda: acq.spectrum(cfg.band[0], cfg.band[1], cfg.n_freq),
        "projection (P_θu)": lambda: to_plane_waves(spec, out),
        "γ-map (1 fingerprint)": lambda: imager.gamma(pw, fp),
        "confocal image": lambda: imager.confocal(pw),
        # a fresh R_θθ array each call (+ its copy, ≈ 30 ms): the level caches the data side per array
        "null model (+ copy of R_θθ)": lambda: null_of(
            g,
            grid,
            acq,
            dataclasses.replace(pw, data=pw.data.copy()),
            fp,
            band,
            pipe._level,  # noqa: SLF001
        ),
        "detections": lambda: find_targets(g, grid, acq, band, "sphere1", 1, False, null, pipe.cfg.max_pfa),
    }
    figures = {}
    print(
        f"stage split (median of {args.repeat}, ms wall / CPU): R_θθ {pw.data.shape} = {pw.data.size / 1e6:.1f} M "
        f"samples, {spec.data.nbytes / 1e6:.0f} MB spectrum",
        flush=True,
    )
    for name, fn in split.items():
        w, u = timed(fn, args.repeat)
        figures[name] = {"wall_ms": 1e3 * w, "cpu_ms": 1e3 * u}
        print(f"  {name:28s} {1e3 * w:7.0f} / {1e3 * u:7.0f}", flush=True)
    walls_t, cpus_t = [], []
    for _ in range(args.repeat):  # the tracker's update on copies of its state (a later frame each time)
        tracker = copy.deepcopy(pipe._tracker)  # noqa: SLF001
        assert tracker is not None
        t, c = time.perf_counter(), time.process_time()
        tracker.update(res.gammas, acq.timestamp + 0.1, nulls=res.nulls)
        walls_t.append(time.perf_counter() - t)
        cpus_t.append(time.process_time() - c)
    figures["tracker update"] = {"wall_ms": 1e3 * float(np.median(walls_t)), "cpu_ms": 1e3 * float(np.median(cpus_t))}
    print(f"  {'tracker update':28s} {1e3 * np.median(walls_t):7.0f} / {1e3 * np.median(cpus_t):7.0f}")
    print(f"load {os.getloadavg()[0]:.1f}", flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(
            json.dumps(
                {
                    "frame_mb": a.rf.nbytes / 1e6,
                    "grid": list(pipe.grid.shape),
                    "wall_ms": wall_ms.tolist(),
                    "cpu_ms": (1e3 * np.array(cpus)).tolist(),
                    "stage_mean_ms": mean_stage,
                    "split": figures,
                    "load": os.getloadavg()[0],
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
