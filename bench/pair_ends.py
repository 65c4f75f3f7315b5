"""The focal-return pairs' ends: how far above its apparent depth each end of a pair lies, and what receiving the
pairs from their ends' own depths would cost (docs/design.md §6.6, F6 and "The pairs' ends' depths").

    .venv/bin/python bench/pair_ends.py            # the 3-D Foldy–Lax deep slab and the quick headline rig, ~2 min

A pair (F6) is drawn at its paths' apparent depth d = (d₁ + d_n + L)/2 (L the path's length between its ends), where
its ends lie at d − Δ₁ and d − Δ_n. With the transmit's sine a, the receive's b and c = √(1 − |s|²), a path's phase
k[c_a d₁ + c_b d_n + L] is k[(c_a + c_b) d + (1 − c_a) Δ₁ + (1 − c_b) Δ_n]: the grid's NUFFT makes the first term
exactly, the second could ride on each transmit's grid (as the pairs' lateral phases do), the third depends on the
output direction, so an exact receive from the ends needs one NUFFT set per class of Δ_n within which
k (1 − c_b) Δ_n stays within ±π/4 over the output directions the depth chunk keeps. Printed per rig:

- by apparent depth, the ν'-weighted end offset Δ = d − (d₁ + d_n)/2 (mean and 10 / 50 / 90 %), for the paths whose
  ends lie within one grid step laterally and the rest, with their share of ν' and ν'/E (the defocus D of F6 on
  average: ν' = E W′/2, W′ of the ends moved onto the axis);
- per depth chunk of the grid (`SingleScatteringField._depth_chunks`): the receive correction's rate k_max(1 − c_b)
  over the chunk's output directions, the 90 % Δ of its depths and the classes it would take;
- the share of a frame's time spent in the grid's spectrum (its NUFFTs), which each class would repeat.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import foldy_lax_reference as flr  # noqa: E402
import validate_background as vb  # noqa: E402

import fpcore.simulate as sim  # noqa: E402
from fpcore.simulate import paths as P  # noqa: E402
from fpcore.simulate.diffuse import focal_walks  # noqa: E402
from fpcore.simulate.medium import DiffuseBackground, ScatteringLayer  # noqa: E402
from fpcore.simulate.single_scattering import SingleScatteringField  # noqa: E402

#: The validation's default layer (bench/validate_background.py with --slab --match-dispersion).
SLAB_LAYER = {
    "envelope": "diffusion",
    "cbs": True,
    "single_scattering": "field",
    "angular": "halo",
    "focal_return": True,
    "focal_return_pairs": True,
    "focal_return_shallow": True,
}


def slab_background() -> tuple[DiffuseBackground, np.ndarray, np.ndarray, Any]:
    """The 3-D Foldy–Lax deep slab's model background, its elements, sines and time window."""
    s, data = flr.load(Path("out/bench/fl_reference_3d_deep.npz"))
    kw = {**SLAB_LAYER, "thickness": s.thickness, "width": s.width}
    kw.update(ls_exponent=vb.dispersion_exponent(s, data), f_ref=s.f_c)
    layer = ScatteringLayer(
        z_surface=s.z_surface, ls=s.ls_c, la=np.inf, density=1000.0, sound_speed=1500.0, frame_displacement=0.0, **kw
    )
    sines = vb.transmit_sines(3)
    rng = np.random.default_rng(1)
    bg = DiffuseBackground(layer, s.elements(), sines, s.window, s.band, s.c0, 3, s.aperture_radius, rng)
    return bg, s.elements(), sines, s.window


def headline_background() -> tuple[DiffuseBackground, np.ndarray, np.ndarray, Any]:
    """The quick sinking-sphere rig's background (its default layer), its elements, sines and time window."""
    sc = sim.scenario("sinking-sphere", quick=True, n_frames=1)
    bg = sc.without_targets()._background()
    assert bg is not None
    return bg, sc.probe.positions, sc.sequence.sines, sc.window


def quantiles(x: np.ndarray, w: np.ndarray, q: tuple[float, ...]) -> list[float]:
    """Weighted quantiles of x."""
    order = np.argsort(x)
    cum = np.cumsum(w[order]) / w.sum()
    return [float(x[order][min(np.searchsorted(cum, p), x.size - 1)]) for p in q]


def report(name: str, bg: DiffuseBackground, elements: np.ndarray, sines: np.ndarray, window: Any) -> None:
    """The module doc's three tables for one rig: its background (with the focal return as pairs), elements, sines
    and time window; the walks are the rig's own tables' (`diffuse.focal_walks`), weighted as `paths.focal_pairs`
    weights them (E of F3 at the band's centre times D = W′/2 of the ends moved onto the axis)."""
    single = bg.single
    assert single is not None and single._fr_light is not None
    layer, c0 = single.layer, single.c0
    walks, _, rig, span, aperture = focal_walks(layer, single, elements, sines, single.centres, c0, 3, window)
    assert rig is not None
    z_s = layer.z_surface
    w = walks.walk
    d1, dn = walks.start[w, 2] - z_s, walks.end[:, 2] - z_s
    d_app = 0.5 * (d1 + dn + walks.length)
    offset = d_app - 0.5 * (d1 + dn)
    sep = np.hypot(*(walks.end[:, :2] - walks.start[w, :2]).T)
    f_c = float(np.mean(single.centres))
    q_in, q_out = P.leg_obliquities(walks, span, aperture, z_s)
    energy = P.path_energies(walks, float(layer.ls_at(f_c)), layer.la, z_s, q_in, q_out)
    dep = single.depths
    cell = np.floor(d_app / single.hz + 0.5).astype(np.int64)
    ok = (cell >= 0) & (cell < dep.size)
    first, last = walks.start[w].copy(), walks.end.copy()
    first[:, :2], last[:, :2] = 0.0, 0.0  # (F6): the ends moved onto the axis, their depths kept
    overlap = np.zeros(d_app.size)
    overlap[ok] = P.discrete_focal_overlap(
        first[ok], last[ok], z_s + d_app[ok], 2 * np.pi * f_c / c0, rig, z_s + single._fr_light[cell[ok]]
    )
    nu = energy * overlap / 2
    close = sep <= single.hx
    grid = f"{single.nx}×{single.ny}×{single.nz}"
    print(f"\n{name}: {walks.n_paths} path ends; grid {grid}, h_x {single.hx * 1e3:.3f} mm")
    print("  apparent depth  ends        ν' share  ν'/E   Δ mean  Δ 10 / 50 / 90 %  (mm)")
    top = float(dep[-1])
    edges = [e for e in (0.0, 1e-3, 2e-3, 3e-3, 5e-3, 8e-3, 12e-3) if e < top] + [top]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = ok & (d_app >= lo) & (d_app < hi)
        for label, m in (("≤ 1 step", sel & close), ("farther", sel & ~close)):
            if nu[m].sum() <= 0:
                continue
            q = quantiles(offset[m], nu[m], (0.1, 0.5, 0.9))
            mean = float(np.sum(offset[m] * nu[m]) / nu[m].sum())
            print(
                f"  {lo * 1e3:4.1f}–{hi * 1e3:4.1f} mm   {label:9s}  {nu[m].sum() / nu[sel].sum():5.2f}   "
                f"{nu[m].sum() / energy[m].sum():5.2f}  {mean * 1e3:5.2f}   " + " / ".join(f"{x * 1e3:.2f}" for x in q)
            )
    k_max = 2 * np.pi * float(single.freqs.max()) / c0
    cos_out = np.sqrt(1.0 - (single.s_out**2).sum(axis=1))
    total = 0.0
    print("  depth chunk  output directions  k_max(1 − c_b) (rad/mm)  Δ 90 % (mm)  classes for ±π/4")
    for i0, i1, o_idx, _ in single._depth_chunks():
        rate = k_max * float((1.0 - cos_out[o_idx]).max())
        sel = ok & (cell >= i0) & (cell < i1)
        d90 = quantiles(offset[sel], nu[sel], (0.9,))[0] if nu[sel].sum() > 0 else 0.0
        n_class = max(1, int(np.ceil(rate * d90 / (np.pi / 2))))
        total += n_class * (i1 - i0)
        print(
            f"  {dep[i0] * 1e3:4.1f}–{dep[i1 - 1] * 1e3:4.1f} mm  {o_idx.size:17d}  {rate * 1e-3:23.2f}  "
            f"{d90 * 1e3:11.2f}  {n_class:16d}"
        )
    print(f"  classes, averaged over the grid's depths: {total / single.nz:.1f}")
    spent = [0.0]
    spectrum = SingleScatteringField.spectrum

    def timed(self: SingleScatteringField) -> np.ndarray:
        t0 = time.perf_counter()
        out = spectrum(self)
        spent[0] += time.perf_counter() - t0
        return out

    SingleScatteringField.spectrum = timed  # type: ignore[method-assign]
    try:  # a fresh draw on the rig's tables (a frozen medium repeats its frame)
        bg.fork(np.random.default_rng(2)).next_orders()  # the plans built
        spent[0] = 0.0
        t0 = time.perf_counter()
        bg.fork(np.random.default_rng(3)).next_orders()
        frame = time.perf_counter() - t0
    finally:
        SingleScatteringField.spectrum = spectrum  # type: ignore[method-assign]
    print(f"  a frame {frame:.1f} s, of which the grid's spectrum {spent[0]:.1f} s ({spent[0] / frame:.0%})")


def main() -> int:
    report("3-D Foldy–Lax deep slab (the validation's layer)", *slab_background())
    report("quick headline rig (sinking-sphere, its default layer)", *headline_background())
    return 0


if __name__ == "__main__":
    sys.exit(main())
