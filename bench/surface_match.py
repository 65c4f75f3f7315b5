"""What a fingerprint matches under the suspension's surface: the frame split into its parts (docs/design.md §4.9).

    python bench/surface_match.py                          # seed 0, sphere 2's R0′ (its surface node, PFA ≈ 1e-5)
    python bench/surface_match.py --seed 3 --fingerprint sphere1 --whitened

γ's numerator n = γ‖R‖ is linear in R (paper eq. P), so a target-free frame's parts can be mapped one at a time: the
static part (the flat interface's echo, `ScatteringLayer.interface_echo`), the Gaussian field (the orders it carries),
the beads' single scattering (with the focal return's pairs drawn on the beads' grid) and the electronic noise. For the
whole frame and for each part, on the quick rig's default grid: ‖R‖, n at the whole frame's most significant node and
the part's own maximum of n, and the most significant node (its calibrated PFA, the compact CFAR) with the physical
null level P·A (eq. B1, the default) and with eq. (B2) (`NullLevel(single_scattering=True)`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import fpcore  # noqa: E402
from fpcore.simulate import scenario  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="the medium (default 0, the headline's)")
    ap.add_argument("--fingerprint", default="sphere2", help="the target whose fingerprint is mapped")
    ap.add_argument("--whitened", action="store_true", help="the whitened modes (default: F = R0′, paper S2 Fig. S7a)")
    args = ap.parse_args()
    sc = scenario("sinking-sphere", quick=True, seed=args.seed, n_frames=1)
    if args.fingerprint not in sc.target_names:
        ap.error(f"--fingerprint: expected one of {sc.target_names}, got {args.fingerprint!r}")
    first = sc.frame(0)
    grid = fpcore.Grid.for_acquisition(first, sc.band)
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    levels = {"P·A": fpcore.NullLevel(imager), "B2": fpcore.NullLevel(imager, single_scattering=True)}
    fp = sc.fingerprints(imager.out_sines_for(first), whiten_modes=args.whitened)[args.fingerprint]
    fog = sc.without_targets()
    static = fog.static_transfer()
    background = fog._background()
    assert background is not None, "the sinking-sphere scenario has a scattering layer"
    fog._reset()  # frame 0's draws
    multiple, single = background.next_orders()
    assert single is not None, "the default layer draws the beads' single scattering as a field"
    parts = {
        "whole target-free frame": (static + multiple + single, True),
        "interface (static part)": (static, False),
        "Gaussian field": (multiple, False),
        "beads' single scattering": (single, False),
        "electronic noise": (np.zeros_like(static), True),
        "all but the single scattering": (static + multiple, True),
    }
    kind = "whitened modes" if args.whitened else "R0′"
    print(f"seed {args.seed}, frame 0 without targets, {args.fingerprint}'s {kind}; grid {grid.shape}")
    node: tuple[int, ...] | None = None
    for label, (h, noise) in parts.items():
        acq = fog.acquisition_of(h, 0, noise)
        pw = imager.plane_waves(acq)
        r_norm = float(np.linalg.norm(pw.data))
        locs = {lname: fpcore.locate(imager, acq, fp, level, pw=pw, max_pfa=None) for lname, level in levels.items()}
        n = locs["P·A"].gamma * r_norm
        if node is None:  # the whole frame's most significant node (P·A): where the parts are read
            node = grid.nearest_index(locs["P·A"].detections[0].position_m)
        tops = [
            f"{lname} {loc.detections[0].pfa:.1e} at z {loc.detections[0].position_m[2] * 1e3:.2f} mm"
            for lname, loc in locs.items()
        ]
        print(
            f"  {label:30s} ‖R‖ {r_norm:.2e}  n at the node {n[node]:.2e} (its max {n.max():.2e})  "
            f"most significant: {'; '.join(tops)}"
        )


if __name__ == "__main__":
    main()
