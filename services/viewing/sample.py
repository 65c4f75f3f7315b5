"""The shipped sample recording (``recordings/sinking-sphere-quick.mcap``): the quick sinking-sphere scenario,
digitised by a ``adc_bits`` ADC as a scanner would (int16 RF with its scale), run through the whole pipeline
(``services.nodes.local.run_pipeline``) and recorded with its RF, so that `fp publish --mcap` replays it,
`fp view` and `fp figure` show it and Foxglove opens it (tests/test_viewer.py, tests/test_foxglove_recording.py).
"""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

from services.recording import MESSAGE_ENCODING, copy_messages, iter_raw

__all__ = ["make_sample_recording"]


def make_sample_recording(
    path: str | Path,
    n_frames: int = 3,
    spacing: float = 0.5e-3,
    adc_bits: int = 10,
    drop: tuple[str, ...] = (),
    depth_ls: float = 2.0,
) -> dict[str, int]:
    """Record the quick sinking-sphere scenario with the project's pipeline (the spheres `depth_ls` mean free
    paths deep, as in `fp demo`; the scenario's region of interest from 1 mm under the surface, grid step
    ``spacing``; RF through an ``adc_bits`` ADC) and copy it to ``path`` (zstd chunks) without the ``drop``
    topics. Returns the message count per key."""
    from mcap.writer import CompressionType, Writer

    from fpcore.simulate import scenario
    from services.convert import QuantisedSource
    from services.nodes.local import run_pipeline
    from services.nodes.processor import ProcessorConfig
    from services.sources import SimulatorSource

    roi = scenario("sinking-sphere", quick=True).roi
    assert roi is not None  # the scenario defines the region it is imaged over
    grid = replace(roi, z_range=(17e-3, roi.z_range[1])).grid(spacing)  # 2 ℓ_s deep spheres start at 19.6 mm
    sim = SimulatorSource("sinking-sphere", n_frames=n_frames, quick=True, depth_ls=depth_ls)
    source = QuantisedSource(sim, adc_bits)
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_pipeline(
            source,
            rig="demo",
            out_dir=tmp,
            n_frames=n_frames,
            processor=ProcessorConfig(rig="demo", queue="fifo", grid=grid),
            recorder={"shuffle": False},  # the sample keeps the payloads exactly as they travelled (fpwire)
        )
        sources = (
            m for src in summary["recording"]["files"] for m in iter_raw(src) if m[1].topic.split("/")[2] not in drop
        )
        with open(path, "wb") as f:
            w = Writer(f, compression=CompressionType.ZSTD)
            w.start(profile="", library="fingerprint services.viewing.sample")
            w.add_metadata(
                "fingerprint",
                {
                    "wire": "FPWIRE01",
                    "message_encoding": MESSAGE_ENCODING,
                    "sample": f"sinking-sphere quick, spheres {depth_ls:g} ℓ_s deep, {n_frames} frames, "
                    f"{adc_bits}-bit RF, grid step {spacing * 1e3:g} mm"
                    + (f", without {', '.join(drop)}" if drop else ""),
                },
            )
            kept = copy_messages(w, sources)
            w.finish()
    return dict(kept)
