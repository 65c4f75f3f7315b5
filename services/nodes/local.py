"""All the streaming nodes in one process: :func:`run_pipeline`, what `fp demo`, the benchmark and the
sample recording run (docs/design.md §2, §7).

Publisher → processor → recorder, each on its own zenoh session, linked over TCP on loopback (a free
port; the processor's session listens there), exactly as separate processes would be; the publisher
paces on the processor's acknowledgements by default, so every frame is processed and recorded.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from services.bus import EPHEMERAL, BusConfig, free_port, open_session, tune_malloc
from services.nodes.processor import STAGES, Processor, ProcessorConfig
from services.nodes.publisher import Publisher
from services.nodes.recorder import Recorder
from services.registry import FingerprintSpec
from services.sources import SimulatorSource, Source
from services.topics import Keys

__all__ = ["run_pipeline"]


def run_pipeline(
    source: Source | str,
    rig: str = "demo",
    out_dir: str | Path = "out/pipeline",
    n_frames: int | None = None,
    progress_callback: Callable[[dict[str, Any]], None] | None = None,
    *,
    fingerprints: list[FingerprintSpec] | None = None,
    processor: ProcessorConfig | None = None,
    record: bool = True,
    pace: str = "ack",
    window: int = 2,
    quick: bool = True,
    shm: str = "auto",
    warmup: int = 0,
    timeout: float = 600.0,
    hub: str | None = None,
    recorder: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Publisher + processor + recorder in one process, over zenoh on loopback; returns when every frame
    is processed (and recorded). ``fp demo`` and the benchmark call it.

    source: a Source (``services.sources``) or a simulator scenario name (``"sinking-sphere"``; quick
    unless ``quick=False``). fingerprints: default, the source's calibrations
    (``SimulatorSource.fingerprint_specs``). processor: a ``ProcessorConfig`` (default: FIFO queue,
    ``rig``). ``progress_callback(result)`` runs in the processor's worker thread after each frame with
    ``frame_index, timestamp, latency_ms, detections, tracks, gamma`` (name → array), ``image``,
    ``grid``, ``truth`` — keep it quick. The summary (also written to ``out_dir/pipeline_summary.json``)
    has counts, rates, latency median/p95, mean stage times and their shares, the recording and the
    per-frame detections. ``warmup`` frames are left out of the rate, latency and stage statistics
    (the first messages of a session page-fault its shared-memory pool: ≈ 0.5 s once, see services.bus).
    ``hub``: the endpoint the processor's session listens on (default: a free loopback port; `fp demo` gives
    the well-known ``tcp/127.0.0.1:7447`` so that `fp view --live` finds it). ``recorder``: keyword arguments of
    the ``Recorder`` (``compression``, ``display``, ``shuffle``, …; the bench compares them).
    """
    src: Source = SimulatorSource(source, n_frames=n_frames, quick=quick) if isinstance(source, str) else source
    if fingerprints is None:
        specs = getattr(src, "fingerprint_specs", None)
        fingerprints = specs() if specs is not None else []
    cfg = processor or ProcessorConfig(rig=rig, queue="fifo")
    if cfg.rig != rig:
        raise ValueError(f"processor config rig {cfg.rig!r} differs from rig {rig!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    hub = hub or f"tcp/127.0.0.1:{free_port()}"
    rows: list[dict[str, Any]] = []
    latencies: list[float] = []
    marks: dict[str, float] = {}
    nodes: list[Any] = []

    def on_result(res: dict[str, Any]) -> None:
        rows.append(
            {
                "frame_index": res["frame_index"],
                "timestamp": res["timestamp"],
                "latency_ms": res["latency_ms"],
                "detections": res["detections"],
                "tracks": res["tracks"],
            }
        )
        if len(rows) > warmup:
            latencies.append(res["latency_ms"])
        if len(rows) == warmup:
            nodes[0].reset_stats()
            marks["t_warm"] = time.time()
        marks["t_last"] = time.time()
        if progress_callback is not None:
            progress_callback(res)

    tune_malloc()
    t0 = time.time()
    rec: Any = None
    with contextlib.ExitStack() as stack:
        s_proc = stack.enter_context(open_session(BusConfig(listen=[hub], connect=[], shm=shm, warm_shm=True)))
        node = stack.enter_context(Processor(s_proc, cfg, fingerprints, on_result=on_result))
        nodes.append(node)
        if record:
            s_rec = stack.enter_context(open_session(BusConfig(listen=[EPHEMERAL], connect=[hub], shm=shm)))
            stamp = time.strftime("%Y%m%dT%H%M%S")
            rec = stack.enter_context(Recorder(s_rec, out / f"{rig}-{stamp}.mcap", rig=rig, **(recorder or {})))
        s_pub = stack.enter_context(open_session(BusConfig(listen=[EPHEMERAL], connect=[hub], shm=shm, warm_shm=True)))
        pub = Publisher(
            s_pub,
            rig,
            src,
            pace=pace,
            window=window,
            limit=n_frames,
            ack_timeout=timeout,
            wait_for=("processor", "recorder") if record else ("processor",),
            wait_timeout=30.0,
        )
        pub_summary = pub.run()
        deadline = time.monotonic() + 10.0  # the last acknowledged frame finishes its bookkeeping
        expected = pub.published - node.rejected
        while time.monotonic() < deadline and (
            node.frames_processed + node.failed < expected or len(rows) < node.frames_processed
        ):
            time.sleep(0.02)
        while (
            rec is not None
            and time.monotonic() < deadline
            and (rec.counts[Keys(rig).detections] < node.frames_processed or rec.received < pub.published)
        ):
            time.sleep(0.05)
        stats = node.stats()
    wall = time.time() - t0
    n = max(stats["stats_frames"], 1)
    stages = {k: stats["stages_s"][k] / n for k in STAGES}
    rate = pub_summary["frame_rate_hz"]
    if warmup and "t_warm" in marks and stats["stats_frames"] > 0 and marks["t_last"] > marks["t_warm"]:
        rate = stats["stats_frames"] / (marks["t_last"] - marks["t_warm"])
    total = sum(stages.values()) or 1.0
    lat = np.asarray(latencies, float)
    summary: dict[str, Any] = {
        "rig": rig,
        "frames_published": pub_summary["published"],
        "frames_processed": stats["frames_processed"],
        "dropped": stats["dropped"],
        "rejected": stats["rejected"],
        "failed": stats["failed"],
        "wall_s": wall,
        "publish_wall_s": pub_summary["wall_s"],
        "frame_rate_hz": rate,
        "warmup_frames": warmup,
        "latency_ms": {
            "median": float(np.median(lat)) if lat.size else None,
            "p95": float(np.percentile(lat, 95)) if lat.size else None,
        },
        "stage_mean_s": stages,
        "stage_share": {k: v / total for k, v in stages.items()},
        "setup_s": stats["setup_s"],
        "dictionary": stats["dictionary"],
        "recording": rec.summary() if rec is not None else None,
        "frames": sorted(rows, key=lambda r: r["frame_index"]),
        "out_dir": str(out),
    }
    (out / "pipeline_summary.json").write_text(json.dumps(summary, indent=2))
    return summary
