"""`fp figure`: PNG of γ over the confocal image for one recorded frame (``services.viewing.frame_figure``)."""

from __future__ import annotations

import argparse
from typing import Any

from services.viewing.frame_figure import to_figure

__all__ = ["add_figure_parser", "run_figure"]


def run_figure(args: argparse.Namespace) -> int:
    """`fp figure`: PNG of γ over the confocal image for one frame."""
    if not 0 < args.threshold < 1:
        raise ValueError(f"--threshold: expected a fraction of γ at the detection in (0, 1), got {args.threshold:g}")
    out = to_figure(args.recording, args.frame, args.png, fingerprint=args.fingerprint, threshold=args.threshold)
    print(f"{out['png']}: frame {out['frame']}, {', '.join(out['fingerprints'])}")
    return 0


def add_figure_parser(sub: Any) -> argparse.ArgumentParser:
    """Register `fp figure`."""
    p = sub.add_parser(
        "figure",
        help="PNG of γ over the confocal image for one recorded frame",
        description="Sections of one frame's confocal image (dB) and of its γ-maps (dB) over "
        "it, as in the paper's Figure 2: scale bars, detections, sphere outlines "
        "when the fingerprint's diameter is known.",
    )
    p.add_argument("recording", help="MCAP file written by `fp record`/`fp demo`")
    p.add_argument("--frame", type=int, required=True, help="frame index")
    p.add_argument("--png", required=True, help="output PNG")
    p.add_argument("--fingerprint", default=None, help="only this fingerprint's γ-map (default: all of the frame's)")
    p.add_argument(
        "--threshold",
        type=float,
        default=0.6,
        help="colour γ ≥ threshold × γ at the detection (γ's peak without one), i.e. from 20·log10(threshold) dB "
        "to 0 dB and above (default 0.6: −4.4 dB)",
    )
    p.set_defaults(func=run_figure)
    return p
