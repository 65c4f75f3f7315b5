"""The single-scattering grid's output plane waves against a point's spreading (docs/design.md §6.6): does one
point of the grid, on the axis at the depth d, put 1/R² of energy on the elements (R = z_surface + d)?

    .venv/bin/python bench/output_grid_alias.py              # the 3-D Foldy–Lax deep rig with the focal return
    .venv/bin/python bench/output_grid_alias.py --lit 2.7    # every depth lit by the beams as at 2.7 mm

The grid of `SingleScatteringField` is summed over a regular grid of output sines Δs apart (`output_grid`), which
repeats every source laterally every λ/Δs; the sine cut-off s_end hides those images from the elements for a
shallow source only. In 3-D the spacing grows when MAX_DIRECTIONS would be exceeded, so a grid reaching deep (the
focal return runs to the record's end) has images ≈ 20 mm apart, and a deep point's images come in at small sines.
Printed per depth: the element energy of one point × R², relative to the shallowest depth (1 for a point whose
spreading is right), with the point lit as at a fixed depth (`--lit`, the focal return's way: its beams' power
fixed) and by its own beams (the beads' way; the number of transmits that light it is printed as well).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import foldy_lax_reference as flr  # noqa: E402
import validate_background as vb  # noqa: E402

from fpcore.simulate.diffuse import DiffuseBackground, project_plane_waves  # noqa: E402
from fpcore.simulate.medium import ScatteringLayer  # noqa: E402

DEPTHS_MM = (2.0, 5.0, 10.0, 15.0, 20.0)


def point_energies(bg: DiffuseBackground, light: np.ndarray | None) -> list[tuple[float, float, int]]:
    """(depth, element energy at the band centre, transmits within 10 % of the brightest) of one unit point of the
    grid on the axis at each of DEPTHS_MM, lit as `light` says (`add_focal_return`)."""
    ss = bg.single
    assert ss is not None
    ss.add_focal_return(np.ones((ss.centres.size, ss.nz)), None, light)
    ss.draw_beads = False
    ss.advance()
    assert ss.fr_state is not None
    out = []
    for d in DEPTHS_MM:
        i = int(np.argmin(np.abs(ss.depths - d * 1e-3)))
        ss.fr_state[:] = 0
        ss.fr_state[ss.nx // 2, ss.ny // 2, i] = 1.0
        v = project_plane_waves(ss.spectrum(), bg.freqs, bg.c0, bg.elements, ss.s_out, ss.axes, ss.keep)
        e = np.abs(v[v.shape[0] // 2]) ** 2  # (N_u, N_θ)
        per_tx = e.sum(axis=0)
        out.append((float(ss.depths[i]), float(e.sum()), int(np.sum(per_tx > 0.1 * per_tx.max()))))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lit", type=float, default=2.7, help="the fixed lighting depth below the surface (mm)")
    args = ap.parse_args(argv)
    if not args.lit >= 0:
        print(f"--lit: expected a depth >= 0 mm, got {args.lit}", file=sys.stderr)
        return 2
    s = replace(flr.setup_for(3, False), thickness=10e-3)
    layer = ScatteringLayer(
        z_surface=s.z_surface,
        ls=s.ls_c,
        la=np.inf,
        envelope="diffusion",
        cbs=True,
        single_scattering="field",
        angular="halo",
        focal_return=True,
        thickness=s.thickness,
        width=s.width,
    )
    sines = vb.transmit_sines(3)

    def background() -> DiffuseBackground:
        return DiffuseBackground(
            layer, s.elements(), sines, s.window, s.band, s.c0, 3, s.aperture_radius, np.random.default_rng(1)
        )

    bg = background()
    ss = bg.single
    assert ss is not None
    lam = s.c0 / s.f_c
    print(
        f"3-D Foldy–Lax deep rig with the focal return: grid {ss.nx}×{ss.ny}×{ss.nz} to {ss.depths[-1] * 1e3:.1f} mm, "
        f"{ss.n_o} output directions, Δs = {ss.ds:.4f}, images λ/Δs = {lam / ss.ds * 1e3:.1f} mm apart at f_c"
    )
    fixed = point_energies(bg, np.full(ss.nz, args.lit * 1e-3))
    own = point_energies(background(), None)  # a fresh grid: the lighting is set before the first spectrum
    r0f = (s.z_surface + fixed[0][0]) ** 2 * fixed[0][1]
    r0o = (s.z_surface + own[0][0]) ** 2 * own[0][1]
    print(f"  depth (mm)   R (mm)   E·R² lit at {args.lit:.1f} mm   E·R² own beams   transmits lighting it")
    for (d, ef, _), (_, eo, n_lit) in zip(fixed, own, strict=True):
        r2 = (s.z_surface + d) ** 2
        row = f"  {d * 1e3:8.1f}   {(s.z_surface + d) * 1e3:6.1f}   {r2 * ef / r0f:17.2f}   {r2 * eo / r0o:14.2f}"
        print(f"{row}   {n_lit:5d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
