"""Imaging options shared by `fp locate`, `fp process` and `fp characterise`.

One place for the band / grid / output-direction / SVD options (lengths in metres unless a unit is
given, docs/design.md §3). The `point | mirror:L=…,alpha=…` model specs are built by ``services.models``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from services.units import parse_length, parse_range

__all__ = ["add_imaging_arguments", "grid_ranges", "int_at_least", "number_in"]


def int_at_least(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer in [lo, hi]; argparse names the option in its one-line error."""
    want = f"an integer >= {lo}" + (f" and <= {hi}" if hi is not None else "")

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}") from None
        if v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}")
        return v

    return parse


def number_in(lo: float, hi: float = math.inf, lo_open: bool = True, hi_open: bool = False) -> Callable[[str], float]:
    """argparse type: a finite number in the interval (lo, hi] (ends open or closed as asked)."""
    want = f"a finite number {'>' if lo_open else '>='} {lo:g}" + (
        f" and {'<' if hi_open else '<='} {hi:g}" if math.isfinite(hi) else ""
    )

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}") from None
        ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}")
        return v

    return parse


def add_imaging_arguments(p: argparse.ArgumentParser | Any, peaks_help: str = "peaks reported per frame") -> None:
    """--band, --n-freq, --x/--y/--z, --spacing, --n-out, --svd-threshold, --targets."""
    p.add_argument(
        "--band",
        help="frequency band f_min:f_max, e.g. 1.8MHz:2.6MHz (default: the frame's "
        "simulated band, else the probe's -6 dB band)",
    )
    p.add_argument(
        "--n-freq",
        type=int_at_least(1),
        default=None,
        help="frequencies kept in the band; it sets the delay window (n−1)/bandwidth, so keep "
        "it ≥ bandwidth × record length (default: every bin of the 2× zero-padded record)",
    )
    p.add_argument(
        "--x",
        dest="x_range",
        help="lateral range of the grid, e.g. --x=-8mm:8mm (default: the transmit fan over the aperture)",
    )
    p.add_argument("--y", dest="y_range", help="elevation range (3D), e.g. --y=-8mm:8mm (default: as --x)")
    p.add_argument(
        "--z",
        dest="z_range",
        help="depth range, e.g. 10mm:40mm (default: the record's time window; "
        "start below strong interfaces, where γ's normalisation favours "
        "the most energetic depths)",
    )
    p.add_argument("--spacing", help="grid spacing (default λ_min/3 in 2D, λ_min/2 in 3D)")
    p.add_argument(
        "--n-out", type=int_at_least(1), help="output directions per lateral axis (default: elements per axis)"
    )
    p.add_argument(
        "--svd-threshold", type=number_in(0, 1), default=0.4, help="kept singular values σ_p ≥ t σ_1 (default 0.4)"
    )
    p.add_argument("--targets", type=int_at_least(1, 1000), default=1, help=f"{peaks_help} (default 1)")


def grid_ranges(args: argparse.Namespace) -> dict[str, Any]:
    """The parsed --x/--y/--z/--spacing as keyword arguments of `fpcore.Grid.for_acquisition`."""
    y = getattr(args, "y_range", None)
    return {
        "x_range": parse_range(args.x_range, "--x") if args.x_range is not None else None,
        "y_range": parse_range(y, "--y") if y is not None else None,
        "z_range": parse_range(args.z_range, "--z") if args.z_range is not None else None,
        "spacing": _spacing(args.spacing) if args.spacing is not None else None,
    }


def _spacing(text: str) -> float:
    d = parse_length(text, "--spacing")
    if not 1e-9 <= d <= 1.0:  # outside, no grid fits in memory or none has two nodes; the budget checks the rest
        raise ValueError(f"--spacing: expected a length between 1nm and 1m, got {text!r}")
    return d
