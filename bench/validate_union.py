"""The union of the unweighted and time-weighted statistics (docs/design.md §4.14, eq. W2), on simulated media.

Each medium's frame is located on two maps — the frame as recorded and weighted by its own 1/v(t) (eq. W1) — and on
their union (`fpcore.locate.union_of`, as `fpcore.locate_union` takes it: the more significant map's node, its PFA
doubled). Target-free media give the fraction of maps whose most significant node reports PFA < 0.05 / 0.01 / 1e-3
(calibrated: ≤ α); with --targets,
every target's map, detected when its most significant node lies within 1 mm at PFA < 1e-3.

    python bench/validate_union.py --dim 3 --media 30 --seed0 9700                 # target-free, 3-D (~8 min)
    python bench/validate_union.py --dim 3 --targets --media 12 --depth-ls 4       # detection at 4 ℓ_s (~4 min)
    python bench/validate_union.py --dim 2 --media 100                             # target-free, 2-D

One frame per medium (frames of one medium are correlated), the quick rig, the default grid (the record's whole
time window), the default (compact) CFAR and the physical null level of eq. (B1), as `fpcore.locate` runs them.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from rich.progress import Progress

import fpcore
from fpcore import Grid
from fpcore.locate import union_of
from fpcore.simulate import scenario

ALPHAS = (0.05, 0.01, 1e-3)
LABELS = ("as recorded", "weighted by 1/v(t)", "union (W2)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dim", type=int, choices=(2, 3), default=3, help="2: sinking-cylinder, 3: sinking-sphere")
    ap.add_argument("--media", type=int, default=30, help="simulated media, one frame each")
    ap.add_argument("--seed0", type=int, default=9700, help="first medium")
    ap.add_argument("--targets", action="store_true", help="keep the targets: detection power instead of the null")
    ap.add_argument("--depth-ls", type=float, help="targets' depth in ℓ_s (scenario option)")
    args = ap.parse_args()
    if args.media < 1:
        ap.error("--media: expected >= 1")
    name = "sinking-sphere" if args.dim == 3 else "sinking-cylinder"
    opts = {} if args.depth_ls is None else {"depth_ls": args.depth_ls}
    pfas: list[list[float]] = [[], [], []]
    hits: list[list[bool]] = [[], [], []]
    chosen: list[int] = []
    t0 = time.perf_counter()
    imagers = levels = fps = None
    with Progress() as progress:
        task = progress.add_task(f"{name} {'with targets' if args.targets else 'fog only'}", total=args.media)
        for seed in range(args.seed0, args.seed0 + args.media):
            sc = scenario(name, quick=True, seed=seed, n_frames=1, **opts)
            if imagers is None:
                first = sc.frame(0)
                grid = Grid.for_acquisition(first, sc.band)
                imagers = [
                    fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band, time_weighting=w)) for w in (False, True)
                ]
                levels = [fpcore.NullLevel(im) for im in imagers]
                fps = sc.fingerprints(imagers[0].out_sines_for(first))
            assert imagers is not None and levels is not None and fps is not None
            if not args.targets:
                sc = sc.without_targets()
            acq = sc.frame(0)
            truth = {t.name: np.asarray(t.position) for t in (acq.ground_truth.targets if acq.ground_truth else [])}
            for tname, fp in fps.items():
                if not args.targets and tname != next(iter(fps)):
                    continue  # one map per target-free medium: independent maps
                maps = [fpcore.locate(im, acq, fp, lev, max_pfa=None) for im, lev in zip(imagers, levels, strict=True)]
                union, k = union_of(maps, max_pfa=None)  # eq. W2 on the two maps, as fpcore.locate_union takes it
                tops = [m.detections[0] for m in maps]
                chosen.append(k)
                for i, d in enumerate([*tops, union.detections[0]]):
                    pfas[i].append(d.pfa)
                    if tname in truth:
                        err = float(np.linalg.norm(np.asarray(d.position_m) - truth[tname]))
                        hits[i].append(d.pfa < 1e-3 and err < 1e-3)
            progress.advance(task)
    print(f"\n{name}, {args.media} media from seed {args.seed0}, {opts or 'scenario defaults'}, compact CFAR:")
    for label, p, h in zip(LABELS, pfas, hits, strict=True):
        arr = np.asarray(p)
        if args.targets:
            med = float(np.median(np.log10(np.maximum(arr, 1e-300))))
            print(f"  {label:20s} detected within 1 mm at PFA < 1e-3: {sum(h)}/{len(h)}; median log10 PFA {med:.1f}")
        else:
            rates = " / ".join(f"{np.mean(arr < a):.3f}" for a in ALPHAS)
            print(f"  {label:20s} below {' / '.join(f'{a:g}' for a in ALPHAS)}: {rates}")
    print(f"  the union took the weighted map on {sum(chosen)} of {len(chosen)} maps")
    print(f"(total {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
