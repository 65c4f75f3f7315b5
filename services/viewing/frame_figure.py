"""`fp figure`: one recorded frame as a PNG in the paper's Figure 2 layout (docs/design.md §2, §7).

:func:`to_figure` reads frame N's γ-maps (all fingerprints, or one), confocal image, detections and
ground truth from a recording (``services.recording``) and draws them with
``services.viewing.figures.targets_over_confocal``: confocal image in dB, γ in dB over it, scale bars,
each sphere's outline from its fingerprint's ``diameter_m`` state, C_γ per target.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fpcore.truth import TargetTruth, Truth
from services.messages import ConfocalImage, Detection, Detections, GammaMap, RFFrame
from services.recording import iter_messages
from services.viewing.figures import Target, peak_position, targets_over_confocal

__all__ = ["to_figure"]


def _diameter(*states: dict[str, Any] | None) -> float | None:
    """The first positive ``diameter_m`` of the given states / truth entries, m."""
    for st in states:
        d = (st or {}).get("diameter_m")
        if isinstance(d, (int, float)) and d > 0:
            return float(d)
    return None


def _pfa_text(pfa: float) -> str:
    return "PFA < 1e-300" if pfa == 0 else f"PFA = {pfa:.1e}"  # 0: exp(−πC²/4) underflowed


def to_figure(
    recording: str | Path, frame: int, png: str | Path, *, fingerprint: str | None = None, threshold: float = 0.6
) -> dict[str, Any]:
    """PNG of the frame's γ-maps (every fingerprint, or only ``fingerprint``) over its confocal image, in
    the layout of the paper's Figure 2 (``services.viewing.figures.targets_over_confocal``): sections through each
    detection (γ's peak when none), the sphere's outline when its diameter is known (the fingerprint's
    ``diameter_m`` state, else the ground truth's), the truth when the frame's RF message carries it."""
    gammas: dict[str, GammaMap] = {}
    image: ConfocalImage | None = None
    dets: list[Detection] = []
    truth: dict[str, TargetTruth] = {}
    for _key, msg in iter_messages(recording):
        if getattr(msg, "frame_index", None) != frame:
            continue
        if isinstance(msg, GammaMap) and fingerprint in (None, msg.fingerprint):
            gammas.setdefault(msg.fingerprint, msg)
        elif isinstance(msg, ConfocalImage) and image is None:
            image = msg
        elif isinstance(msg, Detections):
            dets = msg.detections
        elif isinstance(msg, RFFrame):
            for t in Truth.from_dict(msg.truth or {}).targets or []:
                if t.name is not None:
                    truth[t.name] = t
    if not gammas or image is None:
        raise ValueError(
            f"{recording}: frame {frame} has no γ-map{f' of {fingerprint}' if fingerprint else ''} and confocal image"
        )
    grids = {g.grid.to_grid().shape for g in gammas.values()} | {image.grid.to_grid().shape}
    if len(grids) > 1:
        raise ValueError(f"{recording}: frame {frame}: γ-maps and confocal image on different grids {grids}")
    targets: list[Target] = []
    summary: list[str] = []
    for name, g in gammas.items():
        det = next((d for d in dets if d.fingerprint == name), None)
        found = np.array(det.position_m) if det is not None else peak_position(g.grid, g.gamma)
        t = truth.get(name, TargetTruth())
        targets.append(
            Target(
                name,
                g.gamma,
                found,
                _diameter(det.state if det else None, g.state, t.to_dict()),
                t.position if t.position_m is not None else None,
                det.contrast_c_gamma if det is not None else None,
            )
        )
        summary.append(
            f"{name}: C_γ = {det.contrast_c_gamma:.1f}, {_pfa_text(det.pfa)}"
            if det is not None
            else f"{name}: no detection (γ's peak)"
        )
    confocal = image.image if image.scale == "linear" else (10 ** (image.image / 10)).astype(np.float32)
    title = f"frame {frame}: γ over the confocal image\n" + "; ".join(summary)
    targets_over_confocal(
        png, gammas[next(iter(gammas))].grid.to_grid(), confocal, targets, title=title, threshold=threshold
    )
    return {
        "png": str(png),
        "frame": frame,
        "fingerprint": targets[0].name,
        "fingerprints": [t.name for t in targets],
        "detection": targets[0].found.tolist(),
        "diameters_m": {t.name: t.diameter for t in targets},
    }
