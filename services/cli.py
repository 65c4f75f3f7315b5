"""`fp` — the command line front door.

`fp demo` runs the main job on a built-in simulated scenario: a rich target (a cluster of reflectors,
like a lesion marker) moves through speckle that hides it on the confocal image; a calibration
acquisition of the target alone gives the fingerprint (time gate, SVD whitening, angular filter);
every frame gets a γ-map, a detection with C_γ, PFA and Cramér–Rao precision, a live table, and the
run ends with a JSON summary and a PNG of γ over the confocal image.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .characterise import add_characterise_parser
from .locate import add_locate_parser, run_locate
from .processor import add_process_parser
from .publisher import add_publish_parser
from .recorder import add_record_parser, add_recover_parser
from .simulate_cmd import add_simulate_parser

__all__ = ["main"]


def _demo_scene(rng: np.random.Generator, n_frames: int):
    from fpcore import PlaneWaveSequence, Probe

    probe = Probe.linear(64, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.from_angles(np.linspace(-12, 12, 9))
    offs = rng.uniform(-1.5e-3, 1.5e-3, (14, 3))
    offs[:, 1] = 0.0
    amps = rng.uniform(0.5, 1.0, 14)
    start, stop = np.array([-2.5e-3, 0.0, 16e-3]), np.array([2.5e-3, 0.0, 26e-3])
    path = [start + (stop - start) * k / max(n_frames - 1, 1) for k in range(n_frames)]
    return probe, seq, offs, amps, path


def cmd_demo(args: argparse.Namespace) -> int:
    """Offline demo of the fingerprint pipeline on the built-in simulated scene."""
    from rich.console import Console
    from rich.live import Live
    from rich.table import Table

    from fpcore import Grid, Imager, ImagingConfig, contrasts, detect, from_calibration
    from fpcore.born import born_points

    from .figures import gamma_over_confocal

    if args.frames < 1:
        raise ValueError(f"--frames: expected at least 1, got {args.frames}")
    if args.speckle < 0 or args.speckle_level < 0:
        raise ValueError("--speckle/--speckle-level: expected non-negative values")
    console = Console()
    rng = np.random.default_rng(args.seed)
    probe, seq, offs, amps, path = _demo_scene(rng, args.frames)
    c0, band, n_freq = 1540.0, (1.6e6, 3.4e6), 40
    lam = c0 / probe.centre_frequency
    r0 = np.array([0.0, 0.0, 20e-3])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    grid = Grid.regular((-7e-3, 7e-3), (12e-3, 30e-3), c0 / band[1] / 3)
    imager = Imager(ImagingConfig(grid, band, n_freq))
    console.print(f"[bold]fingerprint demo[/]: linear array {probe.n_elements} elements, {seq.n_waves} plane "
                  f"waves, band {band[0] / 1e6:.1f}–{band[1] / 1e6:.1f} MHz, grid {grid.shape}")
    t = time.perf_counter()
    cal = born_points(probe, seq, r0 + offs, amps, n_t=900)
    fp = from_calibration(cal, r0, imager.out_sines_for(cal), band, n_freq, diameter=3e-3, name="marker")
    console.print(f"calibration fingerprint: N_S = {fp.n_s:.1f}, N_T = {fp.n_t:.1f}, G ≈ N_S·N_T = "
                  f"{fp.n_s * fp.n_t:.0f} ({time.perf_counter() - t:.2f} s)")
    speckle = np.stack([rng.uniform(-9e-3, 9e-3, args.speckle), np.zeros(args.speckle),
                        rng.uniform(10e-3, 32e-3, args.speckle)], axis=1)
    speckle_amp = rng.standard_normal(args.speckle) * args.speckle_level
    table = Table(title="per-frame detections")
    for col in ("frame", "x, z (mm)", "truth (mm)", "error (mm)", "C_γ", "PFA", "δρ_L (mm)", "confocal C"):
        table.add_column(col, justify="right")
    rows = []
    with Live(table, console=console, refresh_per_second=8):
        for k, truth in enumerate(path):
            # Frame-to-frame decorrelation of the background: a fraction of the scatterers is redrawn.
            redraw = rng.random(args.speckle) < 0.2
            speckle_amp[redraw] = rng.standard_normal(redraw.sum()) * args.speckle_level
            pts = np.concatenate([truth + offs, speckle])
            acq = born_points(probe, seq, pts, np.concatenate([amps, speckle_amp]), n_t=900,
                              frame_index=k, timestamp=0.05 * k)
            pw = imager.plane_waves(acq)
            gamma = imager.gamma(pw, fp)
            conf = imager.confocal(pw)
            det = detect(gamma, grid, lam, probe.aperture[0], band[1] - band[0], c0, name=fp.name)[0]
            pos = np.array(det.position_m)
            err = float(np.linalg.norm(pos - truth))
            c_conf, _ = contrasts(conf, grid, truth, 2e-3)
            rows.append({"frame_index": k, "position_m": det.position_m, "truth_m": truth.tolist(),
                         "error_m": err, "gamma_max": det.gamma_max, "c_gamma": det.c_gamma, "c_pfa": det.c_pfa,
                         "pfa": det.pfa, "precision_m": det.precision_m, "confocal_contrast": c_conf})
            table.add_row(str(k), f"{pos[0] * 1e3:+.2f}, {pos[2] * 1e3:.2f}",
                          f"{truth[0] * 1e3:+.2f}, {truth[2] * 1e3:.2f}", f"{err * 1e3:.2f}",
                          f"{det.c_gamma:.1f}", f"{det.pfa:.1e}", f"{det.precision_m[0] * 1e3:.2f}", f"{c_conf:.2f}")
    title = (f"frame {k}: detection error {err * 1e3:.2f} mm, C_γ = {det.c_gamma:.1f}, PFA = {det.pfa:.1e}, "
             f"confocal contrast {c_conf:.2f}")
    png = out / "demo_gamma_over_confocal.png"
    gamma_over_confocal(png, grid, conf, gamma, pos, truth=path[-1], title=title)
    errors = np.array([r["error_m"] for r in rows])
    summary = {"frames": rows, "n_s": fp.n_s, "n_t": fp.n_t, "gain_estimate": fp.n_s * fp.n_t,
               "rms_error_m": float(np.sqrt(np.mean(errors ** 2))), "max_error_m": float(errors.max()),
               "figure": str(png)}
    (out / "demo_summary.json").write_text(json.dumps(summary, indent=2))
    console.print(f"RMS error {summary['rms_error_m'] * 1e3:.2f} mm, max {summary['max_error_m'] * 1e3:.2f} mm; "
                  f"wrote {out / 'demo_summary.json'} and {png}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="fp", description="Fingerprint localisation of targets in scattering media.")
    sub = ap.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="run the main job on the built-in simulated scenario")
    demo.add_argument("--frames", type=int, default=8, help="number of frames (default 8)")
    demo.add_argument("--speckle", type=int, default=1500, help="number of background scatterers (default 1500)")
    demo.add_argument("--speckle-level", type=float, default=0.6,
                      help="background scatterer amplitude, relative to the target's (default 0.6)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.set_defaults(func=cmd_demo)
    add_locate_parser(sub)
    sub.choices["locate"].set_defaults(func=run_locate)
    add_simulate_parser(sub)
    add_characterise_parser(sub)
    # Streaming nodes (issue 4): each registers its subcommand and handler (DESIGN §2, §7).
    add_publish_parser(sub)
    add_process_parser(sub)
    add_record_parser(sub)
    add_recover_parser(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ValueError, OSError) as exc:
        print(f"fp {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
