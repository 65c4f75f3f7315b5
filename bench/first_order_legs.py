"""Which first order exact multiple scattering carries: regress a Foldy–Lax reference's K on its first order computed
two ways on the same scatterers — each leg between the array and a scatterer through the coherent wave at normal
incidence, ⟨T⟩(z)², or along its slant, ⟨T⟩(z)^{R/z} per leg (`foldy_lax_reference.single_scattering`). The one K
holds gives a = ⟨K⁽¹⁾* K⟩/⟨|K⁽¹⁾|²⟩ ≈ 1 for every class of element pairs (by distance from the array's centre);
the other drifts with the slant, and correlates less with K.

    python bench/first_order_legs.py [--reference out/bench/fl_reference_2d.npz] [--realisations 24]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import foldy_lax_reference as flr  # noqa: E402

CLASSES = 4


def regress(s: flr.Setup, data: dict[str, np.ndarray], n_real: int) -> dict[str, dict[str, np.ndarray]]:
    """a (CLASSES, CLASSES) complex and the correlation with K per class pair, for legs 'normal' and 'slant'."""
    freqs, el = data["freqs"], s.elements()
    tbar = data["T"].mean(axis=0)
    rho = np.hypot(el[:, 0], el[:, 1])
    edges = np.quantile(rho, np.linspace(0.0, 1.0, CLASSES + 1))
    onehot = np.eye(CLASSES)[np.clip(np.searchsorted(edges, rho, side="right") - 1, 0, CLASSES - 1)]
    num = {key: np.zeros((CLASSES, CLASSES), complex) for key in ("normal", "slant")}
    den = {key: np.zeros((CLASSES, CLASSES)) for key in num}
    kk = np.zeros((CLASSES, CLASSES))
    for r, pts in enumerate(flr._redrawn(s, data, n_real)):
        d = flr._pairwise(el, pts, s.dim)
        vertical = pts[None, :, 2] - el[:, None, 2]
        for m, f in enumerate(freqs):
            k = 2 * np.pi * f / s.c0
            t = complex(s.strength(np.array(k)))
            g = flr.green(k, d, s.dim)
            # the same coherent leg with the slant ratio R/z set to 1: ⟨T⟩(z) per leg, the normal incidence
            normal = g * flr._slant_legs(tbar[m], data["depths"], el, pts, vertical)
            slant = g * flr._slant_legs(tbar[m], data["depths"], el, pts, d)
            k1 = {"normal": (normal * t) @ normal.T, "slant": (slant * t) @ slant.T}
            big = data["K"][r, m].astype(complex)
            for key, x in k1.items():
                num[key] += onehot.T @ (np.conj(x) * big) @ onehot
                den[key] += onehot.T @ (np.abs(x) ** 2) @ onehot
            kk += onehot.T @ (np.abs(big) ** 2) @ onehot
        print(f"  realisation {r + 1}/{n_real}", flush=True)
    return {
        key: {
            "a": num[key] / den[key],
            "corr": np.abs(num[key]) / np.sqrt(den[key] * kk),
            "a_all": num[key].sum() / den[key].sum(),
            "corr_all": np.abs(num[key].sum()) / np.sqrt(den[key].sum() * kk.sum()),
        }
        for key in num
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference", type=Path, default=flr.default_path(2, False))
    ap.add_argument("--realisations", type=int, default=24)
    args = ap.parse_args(argv)
    if not args.reference.exists():
        print(f"--reference: expected a Foldy–Lax file (bench/foldy_lax_reference.py), got {args.reference}")
        return 2
    if args.realisations < 1:
        print(f"--realisations: expected an integer >= 1, got {args.realisations}")
        return 2
    s, data = flr.load(args.reference)
    res = regress(s, data, args.realisations)
    for key, r in res.items():
        a = r["a_all"]
        corr = float(r["corr_all"])
        print(f"\nfirst order with {key} legs: a = {abs(a):.3f} ∠ {np.angle(a):+.3f} rad, correlation {corr:.3f}")
        print("  |a| by class pair (rows, columns: element classes from the centre out):")
        print(np.array2string(np.abs(r["a"]), precision=3))
        print("  correlation with K by class pair:")
        print(np.array2string(r["corr"], precision=3))
    return 0


if __name__ == "__main__":
    sys.exit(main())
