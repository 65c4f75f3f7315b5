"""The shipped sample recording (``recordings/sinking-sphere-quick.mcap``): the quick sinking-sphere
scenario run through the whole pipeline (``services.nodes.local.run_pipeline``), recorded, and copied
without the raw RF frames so that it stays small (tests/test_viewer.py reads it).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from services.recording import MESSAGE_ENCODING, copy_messages, iter_raw

__all__ = ["make_sample_recording"]


def make_sample_recording(
    path: str | Path, n_frames: int = 4, spacing: float = 0.5e-3, drop: tuple[str, ...] = ("rf",)
) -> dict[str, int]:
    """Record the quick sinking-sphere scenario with the project's pipeline (the scenario's region of
    interest, grid step ``spacing``) and copy it to ``path`` without the ``drop`` topics (RF frames: ~9 MB each).
    Returns the message count per key."""
    from mcap.writer import CompressionType, Writer

    from fpcore.simulate import scenario
    from services.nodes.local import run_pipeline
    from services.nodes.processor import ProcessorConfig

    roi = scenario("sinking-sphere", quick=True).roi
    assert roi is not None  # the scenario defines the region it is imaged over
    grid = roi.grid(spacing)
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_pipeline(
            "sinking-sphere",
            rig="demo",
            out_dir=tmp,
            n_frames=n_frames,
            processor=ProcessorConfig(rig="demo", queue="fifo", grid=grid),
        )
        sources = (
            m
            for src in summary["recording"]["files"]
            for m in iter_raw(src)
            if m[1].topic.rsplit("/", 1)[-1] not in drop
        )
        with open(path, "wb") as f:
            w = Writer(f, compression=CompressionType.NONE)
            w.start(profile="", library="fingerprint services.viewing.sample")
            w.add_metadata(
                "fingerprint",
                {
                    "wire": "FPWIRE01",
                    "message_encoding": MESSAGE_ENCODING,
                    "sample": f"sinking-sphere quick, {n_frames} frames, grid step "
                    f"{spacing * 1e3:g} mm, without {', '.join(drop)}",
                },
            )
            kept = copy_messages(w, sources)
            w.finish()
    return dict(kept)
