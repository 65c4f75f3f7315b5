"""The recorder's CPU time per frame, without the bus (issue 14: the recorder's cost at high frame rates).

    python bench/bench_recorder_cpu.py                       # demo grid (826k voxels), int16 RF, 12 frames
    python bench/bench_recorder_cpu.py --grid bench --float-rf

One process, one thread: the frames of the quick sinking-sphere scenario (cached by bench/bench_streaming.py)
go through the pipeline once; the processor's messages of each frame (RF, confocal image, γ-maps, tracks,
detections; ``services.convert.frame_messages``) are encoded and then written by the recorder's own segment
writer and display (``services.nodes.recorder``), as its writer thread does, for every configuration.
``time.process_time`` is CPU time (the least of 3 runs, after an untimed one), so the figures hold on a loaded
machine better than frames/s do. Sizes are
the files'. The same script runs against an older checkout (``PYTHONPATH=<checkout>``): options that checkout
lacks (shuffle, map encoding, zstd level) are reported as such.
"""

from __future__ import annotations

import argparse
import inspect
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_streaming import CASES, cached_frames  # noqa: E402

from services import convert  # noqa: E402
from services.messages import RFFrame  # noqa: E402
from services.nodes import recorder as rec_mod  # noqa: E402
from services.pipeline import Pipeline, PipelineConfig  # noqa: E402
from services.registry import FingerprintSpec  # noqa: E402
from services.topics import keys  # noqa: E402
from services.wire import encode  # noqa: E402


def frame_payloads(args: argparse.Namespace, map_encoding: str) -> list[list[tuple[str, bytes]]]:
    frames, cals = cached_frames("sinking-sphere", 2, ["sphere1", "sphere2"])
    grid = CASES["3d"]["grid"] if args.grid == "bench" else {}  # demo: the default grid over the whole record
    specs = [FingerprintSpec(name, calibration=cal) for name, cal in cals.items()]
    pipe = Pipeline(PipelineConfig(**grid), specs)
    k = keys("cpu")
    per_frame = []
    kw = (
        {"map_encoding": map_encoding} if "map_encoding" in inspect.signature(convert.frame_messages).parameters else {}
    )
    for i in range(args.frames):
        acq = frames[i % len(frames)]
        res = pipe.process(acq)
        out = convert.frame_messages(res, i, float(i), **kw)
        rf = RFFrame.from_acquisition(acq).model_copy(update={"frame_index": i})
        if not args.float_rf:
            rf = convert.quantise_rf(rf, 16)
        msgs = [(k.rf, rf), (k.image, out["image"]), *[(k.gamma, g) for g in out["gamma"]]]
        msgs += [(k.tracks, out["tracks"]), (k.detections, out["detections"])]
        per_frame.append([(key, encode(m)) for key, m in msgs])
    return per_frame


def record(
    per_frame: list[list[tuple[str, bytes]]], path: Path, compression: str, shuffle: bool, display: bool
) -> float:
    """CPU seconds to record every frame, as the recorder's writer thread does."""
    params = inspect.signature(rec_mod._Segment.__init__).parameters
    if hasattr(rec_mod, "use_zstd_level"):
        rec_mod.use_zstd_level()
    seg = rec_mod._Segment(path, compression, 4 << 20, "fp/**", **({"shuffle": shuffle} if "shuffle" in params else {}))
    show = None
    if display:
        from services.viewing.foxglove_view import FoxgloveDisplay

        show = FoxgloveDisplay()
    decoded = getattr(rec_mod, "_DISPLAYED", frozenset()) if show is not None else frozenset()
    new_write = "decoded" in inspect.signature(rec_mod._Segment.write).parameters
    t = time.process_time()
    for n, frame in enumerate(per_frame):
        for key, payload in frame:
            r = rec_mod._Received(key, payload, None, n, n)
            msg = seg.write(r, decoded) if new_write else seg.write(r)
            if msg is not None and show is not None:
                seg.write_display(show.feed(key, msg, n), n)
        seg.flush()
    seg.finish()
    return time.process_time() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--grid", choices=("demo", "bench"), default="demo")
    ap.add_argument("--float-rf", action="store_true", help="float32 RF (bench_streaming's) instead of int16")
    ap.add_argument("--map-encoding", choices=("uint16", "float32"), default="uint16")
    args = ap.parse_args()
    has_shuffle = "shuffle" in inspect.signature(rec_mod._Segment.__init__).parameters
    level = getattr(__import__("services.recording", fromlist=["x"]), "ZSTD_LEVEL", 3)
    if "map_encoding" not in inspect.signature(convert.frame_messages).parameters:
        args.map_encoding = "float32 (this checkout has no map encoding)"
    print(
        f"bench_recorder_cpu: {rec_mod.__file__}; load {os.getloadavg()[0]:.1f}; grid {args.grid}; "
        f"RF {'float32' if args.float_rf else 'int16'}; maps {args.map_encoding}; zstd level {level}",
        flush=True,
    )
    per_frame = frame_payloads(args, args.map_encoding)
    mb = sum(len(p) for f in per_frame for _, p in f) / len(per_frame) / 1e6
    print(f"  {len(per_frame)} frames, {mb:.2f} MB of payloads a frame", flush=True)
    configs = [("zstd", True, True), ("zstd", False, True), ("zstd", True, False), ("lz4", True, True)]
    configs += [("none", False, True), ("none", False, False)]
    with tempfile.TemporaryDirectory() as tmp:
        record(per_frame[:2], Path(tmp) / "warm.mcap", "zstd", has_shuffle, True)  # imports, first calls: untimed
        for compression, shuffle, display in configs:
            if shuffle and not has_shuffle:
                continue
            path = Path(tmp) / f"{compression}-{shuffle}-{display}.mcap"
            cpu = min(record(per_frame, path, compression, shuffle, display) for _ in range(3))
            size = path.stat().st_size / len(per_frame) / 1e6
            label = f"{compression}{' + shuffle' if shuffle else ''}{'' if display else ', no display'}"
            print(
                f"  {label:28s} {1e3 * cpu / len(per_frame):7.1f} ms CPU a frame   {size:6.2f} MB a frame", flush=True
            )
    print(f"  load after {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
