"""The CFAR settings ("wide", "compact", "both") side by side, on the same maps (docs/design.md §4.9).

    python bench/validate_cfar_window.py --dim 3 --single-scattering field --media 100 --seed0 8000
    python bench/validate_cfar_window.py --dim 2 --media 300                      # the default fog
    python bench/validate_cfar_window.py --dim 3 --targets --media 16 --depth-ls 2   # detection power
    python bench/validate_cfar_window.py --dim 3 --media 30 --unwhitened     # fingerprints F = R0′ (paper S2)
    python bench/validate_cfar_window.py --dim 3 --media 30 --fingerprint sphere2   # another target's fingerprint
    python bench/validate_cfar_window.py --dim 3 --media 30 --null-single-scattering   # the null level with eq. (B2)
    python bench/validate_cfar_window.py --dim 3 --media 30 --time-weighting   # γ of R/v(t) (eq. W1)

One frame per simulated medium (frames of one medium are correlated), the quick rig, the default grid (the
record's whole time window) and the physical null level P·A of eq. (B1), exactly what `fpcore.locate` uses;
each γ-map's null model is made with every setting (`fpcore.cfar.CFAR_SETTINGS`, "both" by `greater_level`) and
searched by `fpcore.detect` as `fpcore.locate` does: "wide" (± 6 × ± 3 cells, censoring at 8× the per-depth
median; the earlier default), "compact" (the default: `COMPACT_WINDOW_CELLS`, the cell under test guarded,
censoring at 30× the window's median) and "both" (the greater of the two levels). Target-free media: the
fraction whose most significant node reports PFA < 0.05 / 0.01 / 1e-3 (calibrated: ≤ α), with Clopper–Pearson
intervals, and the depths of the peaks below 0.05. With ``--targets``: every target's map, detected when that
node is within 1 mm of the truth at PFA < 1e-3.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from rich.progress import Progress

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from validate_pfa import interval  # noqa: E402

import fpcore  # noqa: E402
from fpcore.cfar import CFAR_NAMES, CFAR_SETTINGS, NullModel, greater_level, null_model  # noqa: E402
from fpcore.grid import Grid  # noqa: E402
from fpcore.locate import resolution_of  # noqa: E402
from fpcore.metrics import detect  # noqa: E402
from fpcore.simulate import scenario  # noqa: E402


def models(g: np.ndarray, grid: Grid, res: tuple[float, float], lev: np.ndarray, vis: np.ndarray) -> dict:
    """The null model of every CFAR setting (`CFAR_NAMES`), "both" made from the two others' (no third pass)."""
    out: dict[str, NullModel] = {
        name: null_model(g, grid, res, level=lev, visible=vis, **kw) for name, kw in CFAR_SETTINGS.items()
    }
    out["both"] = greater_level(out["wide"], out["compact"], g)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dim", type=int, choices=(2, 3), default=3, help="3: sinking-sphere, 2: sinking-cylinder")
    ap.add_argument("--single-scattering", choices=("envelope", "field"), help="the media's (default: scenario's)")
    ap.add_argument("--media", type=int, default=40, help="simulated media, one frame each (default 40)")
    ap.add_argument("--seed0", type=int, default=9000, help="first medium (the compact window was chosen on 8000–8999)")
    ap.add_argument("--targets", action="store_true", help="keep the targets: detection power instead of the null")
    ap.add_argument("--depth-ls", type=float, help="targets' depth in ℓ_s (scenario option)")
    ap.add_argument("--conventions", choices=("paper", "legacy"), help="scenario conventions (default: paper)")
    ap.add_argument(
        "--unwhitened", action="store_true", help="fingerprints F = R0′, the gated calibration (whiten_modes=False)"
    )
    ap.add_argument("--fingerprint", help="target-free media: map this target's fingerprint (default: the first)")
    ap.add_argument(
        "--null-single-scattering",
        action="store_true",
        help="the null level mixes in the beads' single-scattering level (eq. B2, NullLevel(single_scattering=True))",
    )
    ap.add_argument(
        "--time-weighting",
        action="store_true",
        help="map the frame weighted by its own inverse variance 1/v(t) (eq. W1, ImagingConfig.time_weighting)",
    )
    args = ap.parse_args()
    if args.media < 1:
        ap.error("--media: expected >= 1")
    if args.fingerprint and args.targets:
        ap.error("--fingerprint: for target-free media (with --targets every target's own fingerprint is mapped)")
    name = "sinking-sphere" if args.dim == 3 else "sinking-cylinder"
    opts: dict[str, Any] = {}
    for key, value in (("single_scattering", args.single_scattering), ("depth_ls", args.depth_ls)):
        if value is not None:
            opts[key] = value
    if args.conventions:
        opts["conventions"] = args.conventions
    pfas: dict[str, list[float]] = {c: [] for c in CFAR_NAMES}
    hits: dict[str, list[bool]] = {c: [] for c in CFAR_NAMES}
    depths: dict[str, list[float]] = {c: [] for c in CFAR_NAMES}
    imager = level = grid = fps = None
    with Progress() as progress:
        task = progress.add_task(f"{name} {'with targets' if args.targets else 'fog only'}", total=args.media)
        for seed in range(args.seed0, args.seed0 + args.media):
            sc = scenario(name, quick=True, seed=seed, n_frames=1, **opts)
            if grid is None:
                first = sc.frame(0)
                grid = Grid.for_acquisition(first, sc.band)
                imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band, time_weighting=args.time_weighting))
                level = fpcore.NullLevel(imager, single_scattering=args.null_single_scattering)
                fps = sc.fingerprints(imager.out_sines_for(first), whiten_modes=not args.unwhitened)
                if args.fingerprint and args.fingerprint not in fps:
                    ap.error(f"--fingerprint: expected one of {sorted(fps)}, got {args.fingerprint!r}")
            assert imager is not None and level is not None and fps is not None
            if not args.targets:
                sc = sc.without_targets()
            acq = sc.frame(0)
            pw = imager.plane_waves(acq)
            res = resolution_of(grid, acq, sc.band)
            lam, bw = acq.c0 / acq.probe.centre_frequency, sc.band[1] - sc.band[0]
            truth = {t.name: np.asarray(t.position) for t in (acq.ground_truth.targets if acq.ground_truth else [])}
            for tname, fp in fps.items():
                if not args.targets and tname != (args.fingerprint or next(iter(fps))):
                    continue  # one map per target-free medium: independent maps
                g = imager.gamma(pw, fp)
                lev, vis = level.level(acq, pw, fp, res, gamma=g)  # the map is used by eq. (B2) only
                for cname, nm in models(g, grid, res, lev, vis).items():
                    # the detector's own most significant peak (fpcore.detect, as fpcore.locate runs it)
                    top = detect(g, grid, lam, acq.probe.aperture[0], bw, acq.c0, null=nm, max_pfa=None)[0]
                    p, pos = top.pfa, np.asarray(top.position_m, float)
                    pfas[cname].append(p)
                    if args.targets and tname in truth:
                        hits[cname].append(p < 1e-3 and float(np.linalg.norm(pos - truth[tname])) < 1e-3)
                    elif p < 0.05:
                        depths[cname].append(round(float(pos[2]) * 1e3, 1))
            progress.advance(task)
    kind = "F = R0′ (not whitened)" if args.unwhitened else "whitened fingerprints"
    if args.fingerprint and not args.targets:
        kind += f", {args.fingerprint}'s"
    if args.null_single_scattering:
        kind += ", null level max(a P·A, b Q) (eq. B2)"
    if args.time_weighting:
        kind += ", frame weighted by 1/v(t) (eq. W1)"
    print(f"\n{name}, {args.media} media from seed {args.seed0}, {opts or 'scenario defaults'}, {kind}:")
    for cname in CFAR_NAMES:
        p = np.asarray(pfas[cname])
        if args.targets:
            logp = np.log10(np.maximum(p, 1e-300))
            print(
                f"  {cname:24s} detected within 1 mm at PFA < 1e-3: {sum(hits[cname])}/{len(hits[cname])}; "
                f"median log10 PFA {np.median(logp):.1f}"
            )
            continue
        parts = []
        for a in (0.05, 0.01, 1e-3):
            k = int(np.sum(p < a))
            lo, hi = interval(k, p.size)
            parts.append(f"α={a:g}: {k / p.size:.3f} [{lo:.3f}, {hi:.3f}]")
        print(f"  {cname:24s} " + "; ".join(parts) + f"; peaks < 0.05 at z (mm) {sorted(depths[cname])}")


if __name__ == "__main__":
    main()
