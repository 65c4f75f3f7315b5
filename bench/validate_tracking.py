"""Tracking the two spheres of the sinking-sphere scenario through the fog (issue 5 validation).

Per frame: each sphere's γ-map (its calibration fingerprint), the tracker's position, the per-frame
argmax beside it, and the truth. Prints the errors, the RMS error against the mean Cramér–Rao
precision, the ids, and writes a PNG of the tracks against the truth over the confocal image.
Run: `python bench/validate_tracking.py [--full] [--frames N] [--png out.png]`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import fpcore
from fpcore.simulate import scenario
from fpcore.tracking import Tracker, TrackerConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="full-size scenario (slow)")
    ap.add_argument("--frames", type=int, default=None, help="number of frames (default: all)")
    ap.add_argument("--png", default="out/tracking.png", help="figure path")
    args = ap.parse_args()
    sc = scenario("sinking-sphere", quick=not args.full, seed=0)
    n = sc.n_frames if args.frames is None else min(args.frames, sc.n_frames)
    grid = fpcore.Grid.regular((-11e-3, 11e-3), (20e-3, 31e-3), 0.25e-3, y_range=(-5e-3, 5e-3))
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    fps = sc.fingerprints(fpcore.output_sines(sc.probe, sc.c0, sc.band[1]))
    lam = sc.c0 / sc.probe.centre_frequency
    bw = sc.band[1] - sc.band[0]
    tracker = Tracker(grid, lam, sc.probe.aperture[0], bw, sc.c0, TrackerConfig(max_tracks_per_map=1))
    rows: dict[str, list[tuple]] = {name: [] for name in sc.target_names}
    conf_sum = np.zeros(grid.shape, np.float64)
    ids: dict[str, set[int]] = {name: set() for name in sc.target_names}
    t_start = time.perf_counter()
    print(f"sinking-sphere ({'full' if args.full else 'quick'}), {n} frames, grid {grid.shape}")
    print(f"{'frame':>5} {'target':>8} {'track err (mm)':>15} {'argmax err (mm)':>16} {'δρ_L (mm)':>10} {'C_γ':>6}")
    for i in range(n):
        acq = sc.frame(i)
        pw = imager.plane_waves(acq)
        conf_sum += imager.confocal(pw)
        maps = {name: imager.gamma(pw, fp) for name, fp in fps.items()}
        states = tracker.update(maps, acq.timestamp)
        for tg in acq.truth["targets"]:
            name, r = tg["name"], np.array(tg["position_m"])
            g = maps[name]
            det = fpcore.detect(g, grid, lam, sc.probe.aperture[0], bw, sc.c0, name=name,
                                exclusion_radius=tg["diameter_m"] / 2)[0]
            arg_err = float(np.linalg.norm(np.array(det.position_m) - r))
            st = [s for s in states if s.fingerprint == name]
            tr_err = float(np.linalg.norm(np.array(st[0].position_m) - r)) if st else np.nan
            if st:
                ids[name].add(st[0].track_id)
            rows[name].append((i, r, np.array(st[0].position_m) if st else None, tr_err, arg_err,
                               det.precision_m[0], det.precision_m[1], det.c_gamma))
            print(f"{i:5d} {name:>8} {tr_err * 1e3:15.2f} {arg_err * 1e3:16.2f} {det.precision_m[0] * 1e3:10.2f} "
                  f"{det.c_gamma:6.1f}")
    print(f"\n{n} frames in {time.perf_counter() - t_start:.1f} s")
    for name, rs in rows.items():
        err = np.array([r[3] for r in rs])
        arg = np.array([r[4] for r in rs])
        lat = np.array([r[5] for r in rs])
        ax = np.array([r[6] for r in rs])
        cr = float(np.sqrt(np.mean(lat ** 2 * 2 + ax ** 2)))  # 3D Cramér–Rao radius (two lateral axes)
        print(f"{name}: track point in {np.isfinite(err).sum()}/{len(err)} frames, ids {sorted(ids[name])}; "
              f"track RMS {np.sqrt(np.nanmean(err ** 2)) * 1e3:.2f} mm, max {np.nanmax(err) * 1e3:.2f} mm; "
              f"argmax RMS {np.sqrt(np.mean(arg ** 2)) * 1e3:.2f} mm, max {arg.max() * 1e3:.2f} mm; "
              f"mean Cramér–Rao δρ_L {lat.mean() * 1e3:.2f} mm, δz_L {ax.mean() * 1e3:.3f} mm "
              f"(3D radius {cr * 1e3:.2f} mm)")
    _figure(args.png, grid, conf_sum / n, rows)
    print(f"wrote {args.png}")


def _figure(path: str, grid: fpcore.Grid, conf: np.ndarray, rows: dict[str, list[tuple]]) -> None:
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    j = grid.nearest_index(np.zeros(3))[1]
    img = 10 * np.log10(conf[:, j, :].T / conf.max() + 1e-12)
    ext = [grid.x[0] * 1e3, grid.x[-1] * 1e3, grid.z[-1] * 1e3, grid.z[0] * 1e3]
    fig, ax = plt.subplots(figsize=(8, 5), constrained_layout=True)
    ax.imshow(img, extent=ext, cmap="gray", vmin=-25, vmax=0, aspect="equal")
    colours = {"sphere1": "red", "sphere2": "lime"}
    for name, rs in rows.items():
        truth = np.array([r[1] for r in rs]) * 1e3
        track = np.array([r[2] for r in rs if r[2] is not None]) * 1e3
        c = colours.get(name, "orange")
        ax.plot(truth[:, 0], truth[:, 2], "--", color="cyan", lw=1.5)
        ax.plot(track[:, 0], track[:, 2], "o-", color=c, ms=3, lw=1, label=f"{name} track")
    ax.plot([], [], "--", color="cyan", label="truth")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title("Tracks through the fog over the mean confocal image (y = 0, dB)")
    ax.legend(loc="lower right", fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
