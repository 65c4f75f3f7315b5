"""The focal return's overlap per path against the direct sum (docs/design.md §6.6, eqs. F2 and F2′).

    .venv/bin/python bench/focal_overlap_check.py                     # the quick sinking-sphere rig, 30 paths a bin
    .venv/bin/python bench/focal_overlap_check.py --rig fl3d          # the 3-D Foldy–Lax deep rig (4.1 mm array)
    .venv/bin/python bench/focal_overlap_check.py --per-bin 60 --out out/bench/focal_overlap_headline.npz
    .venv/bin/python bench/focal_overlap_check.py --rig fl3d --bins 10 12 --per-bin 20 --patch 14   # late, wide

For paths drawn in the rig's medium (`paths.draw_paths`, first scatterings weighted by the incident extinction),
sampled by their energy in bins of apparent depth (d₁ + d_n + L)/2 of 1 ℓ_s, their midpoints within ±2 mm of the
axis (--mid-window widens it): the confocal return of each path's own field — at the elements through
`path_spectra` (the transmits as the rig fires them: `PlaneWaveBeams` for the sinking sphere, synthesised by the
elements for Foldy–Lax), delay-and-summed at its apparent depth over a ±6 mm patch centred on its midpoint, its
energy per frequency summed with the band's weights — against the model's: W times the same of a point at the
midpoint in focus, with W the Gaussian foci of (F2) or the discrete overlap of (F2′) (`paths.discrete_focal_overlap`,
of the path moved across so that its midpoint lies on the axis, as `paths.focal_return` takes it: the point at the
midpoint carries the beams' walk-off). Printed per bin: Σ direct / Σ model in dB (0: the focal return's variance is
right there). About 2 s a path on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import background_metrics as bm  # noqa: E402
import foldy_lax_reference as flr  # noqa: E402
import validate_background as vb  # noqa: E402

from fpcore.geometry import secant_over_sines  # noqa: E402
from fpcore.simulate.paths import (  # noqa: E402
    A_W,
    FocalRig,
    Paths,
    PlaneWaveBeams,
    StraightRays,
    Synthesised,
    discrete_focal_overlap,
    draw_paths,
    focal_overlap,
    path_spectra,
)

#: The confocal patch (half-width, points per side; --patch widens it at the same spacing) and the frequencies'
#: stride of the direct sum.
PATCH, PATCH_POINTS, FREQ_STRIDE = 6e-3, 25, 3
#: The paths' midpoints are taken within this of the axis by default (--mid-window widens it: the model's focal
#: return holds off the axis as well, where the steered beams have walked away).
MID_WINDOW = 2e-3


@dataclass
class Rig:
    """What the check needs of a rig (lengths in m, z the range from the array)."""

    elements: np.ndarray
    sines: np.ndarray
    freqs: np.ndarray
    weights: np.ndarray  # the band's spectral weight per frequency
    c0: float
    z_surface: float
    aperture: float
    transmits: Any
    f_c: float
    ls: float
    lext: float
    la: float
    walk_kw: dict[str, Any]
    l_max: float


def headline_rig() -> Rig:
    import fpcore.simulate as sim

    sc = sim.scenario("sinking-sphere", quick=True, n_frames=1)
    layer = sc.layer
    assert layer is not None
    aperture = float(np.sqrt(np.prod(sc.probe.aperture)))
    f_c = float(sc.pulse.centre)
    lext = float(layer.l_ext_at(f_c))
    return Rig(
        sc.probe.positions,
        sc.sequence.sines,
        sc.freqs,
        bm.spectral_weight(sc.freqs, sc.pulse),
        sc.c0,
        layer.z_surface,
        aperture,
        PlaneWaveBeams(sc.sequence.sines, aperture, layer.z_surface, sc.c0 / f_c),
        f_c,
        float(layer.ls_at(f_c)),
        lext,
        layer.la,
        {"start_half_width": 8e-3, "start_depth": 12 * lext, "start_decay": lext},
        sc.c0 * (sc.window.t0 + sc.window.duration) - 2 * layer.z_surface,
    )


def foldy_lax_rig() -> Rig:
    s = replace(flr.setup_for(3, False), thickness=10e-3)
    sines = vb.transmit_sines(3)
    freqs = s.freqs()
    half = s.width / 2
    kw = {"start_half_width": half, "start_depth": s.thickness, "start_decay": s.ls_c}
    kw.update(thickness=s.thickness, half_width=half)
    return Rig(
        s.elements(),
        sines,
        freqs,
        bm.spectral_weight(freqs, s.band),
        s.c0,
        s.z_surface,
        s.n_side * s.pitch,
        Synthesised(sines, s.pitch),
        s.f_c,
        s.ls_c,
        s.ls_c,
        np.inf,
        kw,
        s.c0 * s.t_end,
    )


def one_path(first: np.ndarray, last: np.ndarray, length: float) -> Paths:
    """A single path (no extinction: ℓ_s = 1 km, unit weight)."""
    return Paths(3, first[None], np.array([0]), last[None], np.array([2], np.int32), np.array([length]), 1e3,
                 np.array([1.0]), 1.0)  # fmt: skip


def patch_energy(
    rig: Rig, v: np.ndarray, r_app: float, patch: float = PATCH, centre: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """Σ over the patch (half-width `patch`, centred laterally on `centre`) of |B_f|² at the range r_app, per
    frequency of the stride (weights² applied)."""
    x = np.linspace(-patch, patch, 1 + int(round((PATCH_POINTS - 1) * patch / PATCH)))
    yy, xx = np.meshgrid(x + centre[1], x + centre[0], indexing="ij")
    pts = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, r_app)], axis=1)
    d_out = np.linalg.norm(pts[:, None, :] - rig.elements[None], axis=2)
    d_in = pts[:, :2] @ rig.sines.T + r_app * np.sqrt(1 - (rig.sines**2).sum(1))[None]
    out = []
    for m in range(0, rig.freqs.size, FREQ_STRIDE):
        k = 2 * np.pi * rig.freqs[m] / rig.c0
        b = np.sum((np.exp(1j * k * d_out) @ v[m]) * np.exp(1j * k * d_in), axis=1)
        out.append(rig.weights[m] ** 2 * float(np.sum(np.abs(b) ** 2)))
    return np.array(out)


def check(
    rig: Rig, first: np.ndarray, last: np.ndarray, length: float, focal: FocalRig, patch: float = PATCH
) -> tuple[float, float, float]:
    """(direct, F2 model, F2′ model) confocal energies of one path (`patch_energy` summed, every patch centred on the
    path's midpoint; the path's own over a patch of half-width `patch`, the points' in focus over the default one,
    which holds them). F2′ as `paths.focal_return` takes it: W′ of the path moved across so that its midpoint lies on
    the axis, times a point at the midpoint lit by the transmits where it lies (as the grid lights it)."""
    rays = StraightRays(rig.elements, rig.z_surface, 3)
    big = np.full(rig.freqs.size, 1e3)
    r_app = 0.5 * (first[2] + last[2] + length)
    mid = np.array([*(0.5 * (first[:2] + last[:2])), r_app])
    at = (float(mid[0]), float(mid[1]))
    direct = patch_energy(
        rig, path_spectra(one_path(first, last, length), rig.freqs, rig.c0, big, rays, rig.transmits), r_app, patch, at
    )
    point = one_path(mid, mid, 0.0)
    e_pt = patch_energy(
        rig, path_spectra(point, rig.freqs, rig.c0, big, rays, rig.transmits, first_order=True), r_app, centre=at
    )
    ks = 2 * np.pi * rig.freqs[::FREQ_STRIDE] / rig.c0
    span = focal.span
    a_r = A_W * (2 * np.pi / ks) * np.sqrt(r_app**2 + rig.aperture**2 / 4) / rig.aperture
    dz1, dzn = np.array([r_app - first[2]]), np.array([r_app - last[2]])
    delta = (last[:2] - first[:2])[None]
    w2 = np.array(
        [
            focal_overlap(delta, A_W * (2 * np.pi / k) / span, np.full((1, 2), a), dz1, dzn, k)[0]
            for k, a in zip(ks, a_r, strict=True)
        ]
    )
    a, b = (first - [mid[0], mid[1], 0.0])[None], (last - [mid[0], mid[1], 0.0])[None]  # centred on the axis
    wp = np.array([discrete_focal_overlap(a, b, np.array([r_app]), k, focal)[0] for k in ks])
    return float(direct.sum()), float(np.sum(w2 * e_pt)), float(np.sum(wp * e_pt))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rig", choices=("headline", "fl3d"), default="headline")
    ap.add_argument("--per-bin", type=int, default=30, help="paths sampled per 1-ℓ_s bin of apparent depth")
    ap.add_argument("--walks", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--bins", type=int, nargs="+", default=None, help="apparent depths (ℓ_s) of the bins")
    ap.add_argument(
        "--patch",
        type=float,
        default=PATCH * 1e3,
        help="half-width (mm) of the patch the paths' own confocal energy is summed over (deep, defocused paths "
        "spread wider than the default 6 mm: 14 mm holds them at 10–12 ℓ_s on the Foldy–Lax rig)",
    )
    ap.add_argument(
        "--mid-window",
        type=float,
        default=MID_WINDOW * 1e3,
        help="half-width (mm) per lateral axis of the window the paths' midpoints are sampled in",
    )
    ap.add_argument("--out", type=Path, default=None, help="save the sampled paths and their energies (npz)")
    args = ap.parse_args(argv)
    if args.per_bin < 1 or args.walks < 1 or args.patch <= 0 or args.mid_window <= 0:
        print(
            f"--per-bin, --walks, --patch, --mid-window: expected integers >= 1 and a patch and a window > 0 mm, got "
            f"{args.per_bin}, {args.walks}, {args.patch}, {args.mid_window}",
            file=sys.stderr,
        )
        return 2
    rig = headline_rig() if args.rig == "headline" else foldy_lax_rig()
    focal = FocalRig.from_grid(
        rig.sines, np.array([rig.aperture] * 2), 3, np.array([rig.aperture] * 2), rig.c0 / rig.f_c
    )
    assert focal is not None
    walks = draw_paths(np.random.default_rng(args.seed), 3, rig.ls, args.walks, rig.l_max, rig.z_surface, **rig.walk_kw)
    w = walks.walk
    d1, dn = walks.start[w, 2] - rig.z_surface, walks.end[:, 2] - rig.z_surface
    d_app = 0.5 * (d1 + dn + walks.length)
    span = focal.span
    energy = walks.start_weight[w] * np.exp(-walks.length / rig.la - (secant_over_sines(span) * d1 + dn) / rig.lext)
    mid = 0.5 * (walks.start[w, :2] + walks.end[:, :2])
    rng = np.random.default_rng(1)
    bins = args.bins or (range(1, 9) if args.rig == "headline" else range(1, 6))
    print(
        f"{args.rig}: direct / model confocal return of single paths, Σ over {args.per_bin} paths a bin (dB), "
        f"midpoints within ±{args.mid_window:g} mm of the axis"
    )
    print("  apparent depth   direct/F2   direct/F2′   mean |midpoint|")
    rows, t0 = [], time.perf_counter()
    for b in bins:
        sel = np.flatnonzero((np.abs(d_app / rig.ls - b) < 0.5) & (np.abs(mid).max(axis=1) <= args.mid_window * 1e-3))
        pick = rng.choice(sel, args.per_bin, p=energy[sel] / energy[sel].sum())
        got = np.array(
            [
                check(rig, walks.start[w[i]], walks.end[i], float(walks.length[i]), focal, args.patch * 1e-3)
                for i in pick
            ]
        )
        rows += [[b, *walks.start[w[i]], *walks.end[i], walks.length[i], *g] for i, g in zip(pick, got, strict=True)]
        direct, f2, f2p = got.sum(axis=0)
        print(
            f"  {b} ℓ_s           {10 * np.log10(direct / f2):+6.1f}      {10 * np.log10(direct / f2p):+6.1f}"
            f"       {1e3 * np.mean(np.hypot(*mid[pick].T)):.1f} mm   ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        np.savez(args.out, rows=np.array(rows), columns="bin x1 y1 z1 xn yn zn L direct F2 F2p")
    return 0


if __name__ == "__main__":
    sys.exit(main())
