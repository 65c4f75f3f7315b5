"""Where the coherent-backscattering cone comes from, part by part (issue 12; docs/validation.md, 2026-12-07 evening).

    .venv/bin/python bench/cbs_by_part.py                                              # 2-D reference (1 min)
    .venv/bin/python bench/cbs_by_part.py --reference out/bench/fl_reference_3d_deep.npz --pairs-alone 12
                                                                                        # 3-D (15 min)

The CBS enhancement over the ladder (`background_metrics.cbs_enhancement`, with its jackknife error over the
realisations) by the paths' age after the surface echo, for Foldy–Lax (`bench/foldy_lax_reference.py`) whole, its
first order (`foldy_lax_reference.single_scattering`) and the rest, and for the scenarios' default background on the
same rig (`validate_background`'s layer with the reference's slab and dispersion) whole, its Gaussian field, its beads'
grid (the beads' speckle and the focal return's pairs), the beads alone (the same layer without the focal return) and,
with --pairs-alone N, the pairs alone (the beads' reflectivity zero, N realisations). Also each part's share of the
gate's energy (the beads': of the default's whole). The model's parts come from `DiffuseBackground.next_orders`,
so the beads' grid is one part.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import background_metrics as bm  # noqa: E402
import foldy_lax_reference as flr  # noqa: E402
import validate_background as vb  # noqa: E402

#: Gates after the surface echo (µs): the youngest paths, then older ones, then the whole record after 5 µs.
AGES = ((5.0, 10.0), (10.0, 20.0), (20.0, 30.0), (5.0, np.inf))
#: The scenarios' default focal return (F6 of docs/design.md §6.6).
FOCAL = {"focal_return": True, "focal_return_pairs": True, "focal_return_shallow": True}


def ages_in(s: flr.Setup) -> list[tuple[float, float]]:
    """The AGES that start inside the record."""
    return [(a, b) for a, b in AGES if 2 * s.z_surface / s.c0 + a * 1e-6 < s.t_end]


def energy(v: np.ndarray, s: flr.Setup, freqs: np.ndarray) -> np.ndarray:
    """Mean |V|² in each gate (`validate_background.age_gates`)."""
    return np.array([float(np.mean(np.abs(bm.gate_spectra(v, freqs, g)) ** 2)) for g in vb.age_gates(s, ages_in(s))])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", type=Path, default=None, help="a Foldy–Lax reference (default: the 2-D one)")
    ap.add_argument("--model-realisations", type=int, default=24)
    ap.add_argument("--pairs-alone", type=int, default=0, help="also the pairs alone, with this many realisations")
    args = ap.parse_args()
    path = args.reference or flr.default_path(2, False)
    if not path.exists():
        raise SystemExit(f"{path} missing: run bench/foldy_lax_reference.py first")
    s, data = flr.load(path)
    freqs = data["freqs"]
    sines = vb.transmit_sines(s.dim)
    base = {
        "envelope": "diffusion", "cbs": True, "single_scattering": "field", "angular": "halo",
        "thickness": s.thickness, "width": s.width, "ls_exponent": vb.dispersion_exponent(s, data), "f_ref": s.f_c,
    }  # fmt: skip
    v_fl = flr.plane_waves(data["K"], freqs, s.elements(), sines, s.c0, s.pitch, s.dim)
    v1 = flr.plane_waves(flr.single_scattering(s, data), freqs, s.elements(), sines, s.c0, s.pitch, s.dim)
    whole, grid = vb.model_orders(s, sines, args.model_realisations, {**base, **FOCAL})
    _, beads = vb.model_orders(s, sines, args.model_realisations, base)
    parts = {
        "Foldy–Lax, all": v_fl,
        "Foldy–Lax, orders ≥ 2": v_fl - v1,
        "Foldy–Lax, first order": v1,
        "model, all": whole,
        "model, the Gaussian field": whole - grid,
        "model, the beads' grid (beads and pairs)": grid,
        "model, the beads alone (no focal return)": beads,
    }
    if args.pairs_alone:
        parts["model, the pairs alone"] = vb.model_orders(s, sines, args.pairs_alone, {**base, **FOCAL}, beads=False)[1]
    share = {
        "Foldy–Lax, first order": energy(v1, s, freqs) / energy(v_fl, s, freqs),
        "model, the beads' grid (beads and pairs)": energy(grid, s, freqs) / energy(whole, s, freqs),
        # the same seeds draw the same beads with and without the focal return: their share of the default's whole
        "model, the beads alone (no focal return)": energy(beads, s, freqs) / energy(whole, s, freqs),
    }
    ages = ages_in(s)
    head = " | ".join(f"{a:g}–{b:g} µs" for a, b in ages)
    print(f"{s.dim}-D rig ({path.name}): CBS over the ladder ± jackknife by age after the surface echo: {head}")
    for name, v in parts.items():
        row = " | ".join(f"{e:.2f} ± {se:.2f}" for e, se in vb.cbs_by_age(v, s, sines, freqs, ages).values())
        extra = f"   share of the gate's energy {' / '.join(f'{x:.3f}' for x in share[name])}" if name in share else ""
        print(f"  {name:44s} {row}{extra}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
