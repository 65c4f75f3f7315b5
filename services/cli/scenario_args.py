"""Options shared by the commands that build a simulator scenario (`fp simulate`, `fp demo`, `fp publish`,
`fp process --scenario`): the depth of the sinking scenarios' targets in mean free paths, and the
conventions (fpcore.simulate.scenarios.CONVENTIONS; docs/design.md §6.4)."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from services.cli.imaging import number_in

__all__ = ["add_scenario_arguments", "scenario_kwargs", "depth_note", "SINKING"]

#: The scenarios whose targets lie in the granular suspension (they take depth_ls and conventions).
SINKING = ("sinking-sphere", "sinking-cylinder")


def add_scenario_arguments(p: argparse.ArgumentParser, default_depth_ls: float | None = None) -> None:
    """--depth-ls (None unless given: the command applies `default_depth_ls` to sinking scenarios) and
    --conventions."""
    from fpcore.simulate.scenarios import CONVENTIONS, paper_regime_ls

    lo, hi = paper_regime_ls()
    regime = f"the paper's regime, the spheres {lo:.1f}–{hi:.1f} ℓ_s"
    default = regime if default_depth_ls is None else f"{default_depth_ls:g}"
    p.add_argument(
        "--depth-ls",
        type=_depth,
        default=None,
        metavar="N|paper",
        help=f"sinking scenarios: the targets' centres N ℓ_s below the surface, or 'paper' for the paper's regime "
        f"(default {default})",
    )
    p.add_argument(
        "--conventions",
        choices=CONVENTIONS,
        default="paper",
        help="sinking scenarios: the paper's conventions (default) or the earlier, easier legacy rig",
    )


def scenario_kwargs(args: argparse.Namespace, name: str, default_depth_ls: float | None = None) -> dict[str, Any]:
    """The scenario keyword arguments these options ask for; a clear error for a scenario without them."""
    depth, conv = getattr(args, "depth_ls", None), getattr(args, "conventions", "paper")
    if name not in SINKING:
        if conv != "paper" or depth not in (None, "paper"):
            raise ValueError(f"--depth-ls/--conventions: only for {', '.join(SINKING)}, not {name}")
        return {}
    depth = default_depth_ls if depth is None else depth
    out: dict[str, Any] = {"conventions": conv}
    if depth is not None and depth != "paper":
        out["depth_ls"] = float(depth)
    return out


def _depth(text: str) -> float | str:
    """--depth-ls: 'paper' or a positive number of mean free paths."""
    if text.strip().lower() == "paper":
        return "paper"
    return number_in(0)(text)


def depth_note(sc: Any) -> str:
    """One line: where the scenario's targets lie below the surface, in ℓ_s, and the paper's depths."""
    lay = getattr(sc, "layer", None)
    if lay is None or sc.name not in SINKING:
        return ""
    parts = []
    for name, pl in sc.placements.items():
        if pl.in_scene and pl.in_medium:
            z = (pl.positions[:, 2] - lay.z_surface) / lay.ls
            span = f"{z.min():.1f}" if np.ptp(z) < 0.05 else f"{z[0]:.1f} → {z[-1]:.1f}"
            parts.append(f"{name} {span} ℓ_s")
    from fpcore.simulate.scenarios import paper_regime_ls

    lo, hi = paper_regime_ls(sc.name)
    return "targets' centres below the surface: " + ", ".join(parts) + f" (the paper's regime: {lo:.1f}–{hi:.1f} ℓ_s)"
