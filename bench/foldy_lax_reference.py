"""Foldy–Lax reference of the multiple-scattering background (issue 12): a slab of point scatterers under
water, probed by an array in reflection, exact multiple scattering (fpcore.simulate.foldy_lax).

    .venv/bin/python bench/foldy_lax_reference.py --dim 2            # 23 min (2 cores shared, load ~3.6)
    .venv/bin/python bench/foldy_lax_reference.py --dim 2 --quick    # 3 min (same load)
    .venv/bin/python bench/foldy_lax_reference.py --dim 3 --quick    # 2 min
    .venv/bin/python bench/foldy_lax_reference.py --dim 3            # 23 min (same load; ~3 × 83 LUs of 3900²)
    .venv/bin/python bench/foldy_lax_reference.py --dim 2 --elements 12 --out out/bench/fl_reference_2d_12el.npz
                                                                     # 6 min: the 2-D slab under the 3-D array's 4.1 mm
    .venv/bin/python bench/foldy_lax_reference.py --dim 3 --thickness 10 --out out/bench/fl_reference_3d_deep.npz
                                                                     # ~45 min: a 5.6 ℓ_s slab (fit 1–5 ℓ_s)

Scaling (paper Supplementary S1, granular suspension): ℓ_s = 1.8 mm at f_c = 2.2 MHz, λ = 0.68 mm
(c0 = 1500 m/s), band 1.8–2.6 MHz (−6 dB; the Hann support 1.4–3.0 MHz is computed). The slab is
lossless (ℓ_a = ∞; the paper's ℓ_a = 8 mm is left out on purpose, the comparison then tests the
scattering part alone). Scatterers are resonant lossless points, 1/t = i Im₀(k) (x = 0 in
`foldy_lax.passive_strength`), so σ_s(f) = 4/k (2D) or 4π/k² (3D) and ℓ_s(f) = 1/(n σ_s(f)) grows with
f (∝ f in 2D, ∝ f² in 3D); the density n makes ℓ_s(f_c) = 1.8 mm. Both are stored per frequency.

What is computed, per frequency and realisation (one LU per frequency, all right-hand sides at once):

* K(f, u, v): the scattered field at element u from a unit point source (monopole, G) at element v
  (no direct path): K = g_uᵀ T (I − G T)⁻¹ g_v, exactly symmetric (reciprocity).
* The plane-wave transmits are synthesised from K as the probe fires them: element v emits with
  weight q_v(θ) = 2ik c_θ p^{dim−1} e^{−ik a·v} (a planar monopole layer of density 2ikc radiates the unit
  plane wave e^{−ik(a·ρ + c z)}, since ∫ G dρ = e^{−ikz}/(2ik) in 2D and 3D), so
  R(f, u, θ) = Σ_v K(f, u, v) q_v(θ) — a finite-aperture plane wave, which is what insonifies the
  medium in an experiment (`plane_waves`).
* T(z, f) = ⟨ψ⟩(z)/ψ_inc(z): the coherent wave in the slab for an infinite plane wave at normal
  incidence, with the lateral average taken analytically over a Gaussian window as in
  `fpcore.simulate.foldy_lax.coherent_wave`.

Saved to out/bench/fl_reference_{2d,3d}.npz (geometry and parameters included, `load`).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from rich.progress import Progress

from fpcore.simulate.foldy_lax import cross_section, passive_strength, random_slab
from fpcore.simulate.waves import Band, TimeWindow, green

OUT = Path("out/bench")


@dataclass(frozen=True)
class Setup:
    """Geometry and physics of one reference run (SI units)."""

    dim: int
    n_side: int  # elements along x (and y in 3D)
    width: float  # slab lateral extent (x, and y in 3D)
    thickness: float
    n_real: int
    z_surface: float = 5e-3
    c0: float = 1500.0
    f_c: float = 2.2e6
    ls_c: float = 1.8e-3  # ℓ_s at f_c
    band_lo: float = 1.8e6
    band_hi: float = 2.6e6
    fs: float = 10.4e6
    t_end: float = 60e-6
    guard: float = 20e-6
    seed: int = 0

    @property
    def pitch(self) -> float:
        return self.c0 / self.f_c / 2

    @property
    def band(self) -> Band:
        return Band(self.band_lo, self.band_hi)

    @property
    def window(self) -> TimeWindow:
        return TimeWindow.covering(self.fs, 0.0, self.t_end, guard=self.guard)

    def freqs(self) -> np.ndarray:
        w = self.window
        return w.freqs()[w.band_bins(self.band)]

    def elements(self) -> np.ndarray:
        x = (np.arange(self.n_side) - (self.n_side - 1) / 2) * self.pitch
        if self.dim == 2:
            return np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
        yy, xx = np.meshgrid(x, x, indexing="ij")
        return np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)

    @property
    def aperture_radius(self) -> float:
        """Half the array's extent (one pitch added), the insonified half-width."""
        return 0.5 * self.n_side * self.pitch

    def strength(self, k: np.ndarray) -> np.ndarray:
        """Resonant lossless t(k) = 1/(i Im₀(k)) (module doc)."""
        return passive_strength(np.zeros_like(k), k, self.dim)  # type: ignore[arg-type]

    @property
    def density(self) -> float:
        """n with n σ_s(f_c) = 1/ℓ_s(f_c)."""
        kc = 2 * np.pi * self.f_c / self.c0
        return 1.0 / (float(cross_section(self.strength(np.array(kc)), kc, self.dim)) * self.ls_c)


def setup_for(dim: int, quick: bool) -> Setup:
    """2D: 64-element linear array (21.8 mm) over a 64 mm × 12 mm slab (6.7 ℓ_s, ~980 scatterers), 24
    realisations (quick: 32 elements, 40 × 9 mm, 4 realisations). 3D: 12×12 matrix array (4.1 mm) over a
    12 × 12 × 7.2 mm slab (4 ℓ_s, ~3900 scatterers), 3 realisations (quick: 8×8 array, 9 × 9 × 5.4 mm,
    ~1650 scatterers, 1 realisation). The 3D slab is narrower than the diffusion halo: late times lose
    energy through its sides (a limit of a dense solve on 2 cores, said where the figures are printed)."""
    if dim == 2:
        if quick:
            return Setup(2, 32, 40e-3, 9e-3, 4, t_end=45e-6)
        return Setup(2, 64, 64e-3, 12e-3, 24)
    if dim == 3:
        if quick:
            return Setup(3, 8, 9e-3, 5.4e-3, 1, t_end=35e-6, guard=10e-6)
        return Setup(3, 12, 12e-3, 7.2e-3, 3, t_end=40e-6, guard=12e-6)
    raise ValueError(f"dim: expected 2 or 3, got {dim}")


def _pairwise(p: np.ndarray, q: np.ndarray, dim: int) -> np.ndarray:
    if dim == 2:
        return np.hypot(p[:, None, 0] - q[None, :, 0], p[:, None, 2] - q[None, :, 2])
    return np.linalg.norm(p[:, None, :] - q[None, :, :], axis=2)


def solve_realisation(
    s: Setup, pts: np.ndarray, freqs: np.ndarray, depths: np.ndarray, tick: object | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """K (N_f, N_u, N_u) complex64 and T (N_f, N_z) complex128 for one realisation (module doc)."""
    el = s.elements()
    n_u, n = el.shape[0], pts.shape[0]
    d_ss = _pairwise(pts, pts, s.dim)
    np.fill_diagonal(d_ss, 1.0)
    d_es = _pairwise(el, pts, s.dim)  # (N_u, N)
    sig = s.width / 6  # Gaussian lateral window of the coherent average (foldy_lax.coherent_wave)
    rho2 = pts[:, 0] ** 2 + (pts[:, 1] ** 2 if s.dim == 3 else 0.0)
    w = np.exp(-rho2 / (2 * sig**2))
    norm = np.sqrt(2 * np.pi) * sig if s.dim == 2 else 2 * np.pi * sig**2
    dz = np.abs(depths[:, None] - pts[None, :, 2])
    kk = np.empty((freqs.size, n_u, n_u), dtype=np.complex64)
    tz = np.empty((freqs.size, depths.size), dtype=np.complex128)
    # 3D: e^{−ikd} advanced from bin to bin by e^{−iΔk d} (re-anchored every 16 bins), as waves.radiate_points
    inv = 1.0 / (4 * np.pi * d_ss) if s.dim == 3 else None
    dk = 2 * np.pi * (freqs[1] - freqs[0]) / s.c0 if freqs.size > 1 else 0.0
    for m, f in enumerate(freqs):
        k = 2 * np.pi * f / s.c0
        t = complex(s.strength(np.array(k)))
        if inv is None:
            g = green(k, d_ss, s.dim)
        else:
            if m % 16 == 0:
                ph = np.exp(-1j * k * d_ss)
                step = np.exp(-1j * dk * d_ss)
            else:
                ph *= step
            g = ph * inv
        np.fill_diagonal(g, 0.0)
        a = np.eye(n, dtype=np.complex128) - g * t
        del g
        lu = sla.lu_factor(a, overwrite_a=True, check_finite=False)
        g_es = green(k, d_es, s.dim)  # (N_u, N)
        rhs = np.concatenate([g_es.T, np.exp(-1j * k * pts[:, 2])[:, None]], axis=1)
        psi = sla.lu_solve(lu, rhs, check_finite=False)
        kk[m] = (g_es @ (t * psi[:, :n_u])).astype(np.complex64)
        src = w * t * psi[:, n_u] / norm
        scat = (src[None, :] * (-0.5j / k) * np.exp(-1j * k * dz)).sum(axis=1)
        tz[m] = 1.0 + scat * np.exp(1j * k * depths)
        if tick is not None:
            tick()  # type: ignore[operator]
    return kk, tz


def plane_waves(
    kk: np.ndarray, freqs: np.ndarray, elements: np.ndarray, sines: np.ndarray, c0: float, pitch: float, dim: int
) -> np.ndarray:
    """R(…, f, u, θ) = Σ_v K(…, f, u, v) q_v(θ), q_v = 2ik c_θ p^{dim−1} e^{−ik a·v} (module doc)."""
    k = 2 * np.pi * np.asarray(freqs, float) / c0
    s = np.asarray(sines, float)
    c = np.sqrt(1.0 - s[:, 0] ** 2 - s[:, 1] ** 2)
    ph = np.asarray(elements, float)[:, :2] @ s.T  # (N_v, N_θ)
    q = 2j * k[:, None, None] * c[None, None, :] * pitch ** (dim - 1) * np.exp(-1j * k[:, None, None] * ph[None])
    return np.matmul(kk, q.astype(np.complex64))


def run(s: Setup, path: Path) -> dict[str, np.ndarray]:
    freqs = s.freqs()
    depths = s.z_surface + np.linspace(0.0, s.thickness, 25)
    rng = np.random.default_rng(s.seed)
    n_u = s.elements().shape[0]
    kk = np.empty((s.n_real, freqs.size, n_u, n_u), dtype=np.complex64)
    tz = np.empty((s.n_real, freqs.size, depths.size), dtype=np.complex128)
    counts = []
    t0 = time.perf_counter()
    with Progress() as prog:
        task = prog.add_task(f"FL {s.dim}D", total=s.n_real * freqs.size)
        for r in range(s.n_real):
            pts = random_slab(rng, s.density, s.width, s.thickness, s.dim, z0=s.z_surface)
            counts.append(pts.shape[0])
            prog.update(task, description=f"FL {s.dim}D real {r + 1}/{s.n_real} N={pts.shape[0]}")
            kk[r], tz[r] = solve_realisation(s, pts, freqs, depths, lambda: prog.advance(task))
            if not prog.console.is_terminal:
                print(
                    f"realisation {r + 1}/{s.n_real}: N = {pts.shape[0]}, {time.perf_counter() - t0:.0f} s", flush=True
                )
    k = 2 * np.pi * freqs / s.c0
    sigma = cross_section(s.strength(k), k, s.dim)
    out = dict(
        K=kk,
        T=tz,
        depths=depths,
        freqs=freqs,
        elements=s.elements(),
        sigma_s=sigma,
        ls=1.0 / (s.density * sigma),
        n_scatterers=np.array(counts),
        density=np.array(s.density),
        seconds=np.array(time.perf_counter() - t0),
        **{f"setup_{k_}": np.array(v) for k_, v in asdict(s).items()},
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)  # type: ignore[arg-type]
    return out


def _redrawn(s: Setup, data: dict[str, np.ndarray], n_real: int | None = None) -> Iterator[np.ndarray]:
    """The scatterers of the first `n_real` (all) saved realisations, drawn again from the setup's seed in `run`'s
    order; a count that differs from the saved one is refused (a stale or foreign file)."""
    rng = np.random.default_rng(s.seed)
    n = data["K"].shape[0] if n_real is None else min(n_real, data["K"].shape[0])
    for r in range(n):
        pts = random_slab(rng, s.density, s.width, s.thickness, s.dim, z0=s.z_surface)
        if pts.shape[0] != int(data["n_scatterers"][r]):
            raise ValueError(f"realisation {r}: redrawn {pts.shape[0]} scatterers, saved {data['n_scatterers'][r]}")
        yield pts


def _slant_legs(tbar: np.ndarray, depths: np.ndarray, el: np.ndarray, pts: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N_u, N) the coherent wave's factor on each straight leg between element u and scatterer j, ⟨T⟩(z_j)^{p_uj}
    with p_uj = R_uj/(z_j − z_u): the effective medium's extinction and phase along the slant, whose length in the
    slab is p_uj times the depth a normally incident wave crosses (paper S1: the ballistic wave decays as
    e^{−L/2ℓ_ext} along its path). log⟨T⟩ is continued in depth (phase unwrapped) from ⟨T⟩ ≈ 1 at the surface."""
    log_t = np.log(np.abs(tbar)) + 1j * np.unwrap(np.angle(tbar))
    lt = np.interp(pts[:, 2], depths, log_t.real) + 1j * np.interp(pts[:, 2], depths, log_t.imag)
    p = dist / (pts[None, :, 2] - el[:, None, 2])
    return np.exp(p * lt[None, :])


def single_scattering(s: Setup, data: dict[str, np.ndarray]) -> np.ndarray:
    """K⁽¹⁾ (n_real, N_f, N_u, N_u) complex64: the first order of each saved realisation in the independent-
    scattering approximation, each scatterer excited and re-radiating through the coherent wave,
    K⁽¹⁾_uv = Σ_j G(u, r_j) ⟨T⟩(z_j)^{p_uj} t ⟨T⟩(z_j)^{p_vj} G(r_j, v) (paper S1: the ballistic wave both ways,
    each leg extinguished along its slant, `_slant_legs`). Regressed on K, this first order is carried at
    |a| = 1.03 (1.00–1.06 over the element pairs) on the 2-D reference, where the legs at normal incidence,
    ⟨T⟩(z_j)², are carried at 0.79 (0.75 for the outer pairs): K holds the slant legs. The scatterers are drawn
    again from the setup's seed, in `run`'s order (checked against the saved counts); K − K⁽¹⁾ is then the
    multiple scattering (with the first order's fluctuation about ⟨T⟩)."""
    freqs, el = data["freqs"], s.elements()
    tbar = data["T"].mean(axis=0)  # (N_f, N_z)
    out = np.empty(data["K"].shape, dtype=np.complex64)
    for r, pts in enumerate(_redrawn(s, data)):
        d = _pairwise(el, pts, s.dim)
        for m, f in enumerate(freqs):
            k = 2 * np.pi * f / s.c0
            g = green(k, d, s.dim) * _slant_legs(tbar[m], data["depths"], el, pts, d)
            out[r, m] = (g * complex(s.strength(np.array(k)))) @ g.T
    return out


def double_scattering(s: Setup, data: dict[str, np.ndarray], n_real: int | None = None) -> np.ndarray:
    """K⁽²⁾ (n_real, N_f, N_u, N_u) complex64 of the first `n_real` realisations: the second order in the same
    approximation, K⁽²⁾_uv = Σ_{i≠j} G(u, r_i) ⟨T⟩(z_i)^{p_ui} t ⟨G⟩(r_i, r_j) t ⟨T⟩(z_j)^{p_vj} G(r_j, v), the legs
    between the array and the scatterers through the coherent wave along their slant (`_slant_legs`, as
    `single_scattering`) and the leg between them through the mean Green
    function ⟨G⟩ = G e^{−r/2ℓ_s(f)} (its extinction). Symmetric (reciprocity). With resonant scatterers the
    orders interfere, so |K⁽¹⁾|², |K⁽²⁾|² and the rest do not add up to |K|²."""
    freqs, el = data["freqs"], s.elements()
    tbar = data["T"].mean(axis=0)  # (N_f, N_z)
    pts_all = list(_redrawn(s, data, n_real))
    out = np.empty((len(pts_all),) + data["K"].shape[1:], dtype=np.complex64)
    for r, pts in enumerate(pts_all):
        d = _pairwise(el, pts, s.dim)
        dd = _pairwise(pts, pts, s.dim)
        np.fill_diagonal(dd, 1.0)  # i = j is left out below
        for m, f in enumerate(freqs):
            k = 2 * np.pi * f / s.c0
            leg = _slant_legs(tbar[m], data["depths"], el, pts, d)
            g = green(k, d, s.dim) * leg * complex(s.strength(np.array(k)))
            inner = green(k, dd, s.dim) * np.exp(-dd / (2 * float(data["ls"][m])))
            np.fill_diagonal(inner, 0.0)
            out[r, m] = g @ inner @ g.T
    return out


def load(path: Path) -> tuple[Setup, dict[str, np.ndarray]]:
    """The Setup and arrays of a saved reference."""
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    fields = {k[6:]: data[k].item() for k in data if k.startswith("setup_")}
    s = Setup(**fields)
    return replace(s), data


def default_path(dim: int, quick: bool) -> Path:
    return OUT / f"fl_reference_{dim}d{'_quick' if quick else ''}.npz"


def configured(dim: int, args: argparse.Namespace) -> Setup:
    """`setup_for(dim, args.quick)` with the command line's overrides (lengths in mm)."""
    s = setup_for(dim, args.quick)
    if args.realisations is not None:
        s = replace(s, n_real=args.realisations)
    if args.elements is not None:
        s = replace(s, n_side=args.elements)
    if args.thickness is not None:
        s = replace(s, thickness=args.thickness * 1e-3)
    if args.width is not None:
        s = replace(s, width=args.width * 1e-3)
    return s


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dim", choices=("2", "3", "both"), default="2")
    ap.add_argument("--quick", action="store_true", help="small run (smaller slab, fewer realisations)")
    ap.add_argument("--realisations", type=int, default=None, help="override the number of realisations")
    ap.add_argument("--elements", type=int, default=None, help="override the elements along x (and y in 3D)")
    ap.add_argument("--thickness", type=float, default=None, help="override the slab's thickness (mm)")
    ap.add_argument("--width", type=float, default=None, help="override the slab's lateral extent (mm)")
    ap.add_argument("--out", default=None, help="write here instead of the default path (one --dim only)")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    for name in ("realisations", "elements"):
        value = getattr(args, name)
        if value is not None and value < 1:
            print(f"--{name}: expected an integer >= 1, got {value}", file=sys.stderr)
            return 2
    for name in ("thickness", "width"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            print(f"--{name}: expected a length in mm > 0, got {value}", file=sys.stderr)
            return 2
    if args.out and args.dim == "both":
        print("--out: expected one --dim (2 or 3), got --dim both", file=sys.stderr)
        return 2
    for dim in (2, 3) if args.dim == "both" else (int(args.dim),):
        s = configured(dim, args)
        path = Path(args.out) if args.out else default_path(dim, args.quick)
        out = run(s, path)
        lam = s.c0 / s.f_c
        print(
            f"{dim}D: n = {s.density:.4g} m^-{dim}, σ_s(f_c) = {1 / (s.density * s.ls_c):.4g} m^{dim - 1}, "
            f"ℓ_s(f_c) = {s.ls_c * 1e3:.2f} mm (ℓ_s/λ = {s.ls_c / lam:.2f}; ℓ_s over the band "
            f"{out['ls'].min() * 1e3:.2f}–{out['ls'].max() * 1e3:.2f} mm), slab {s.width * 1e3:.0f} mm wide × "
            f"{s.thickness * 1e3:.1f} mm ({s.thickness / s.ls_c:.1f} ℓ_s), N = {out['n_scatterers'].tolist()}, "
            f"{out['freqs'].size} frequencies, {float(out['seconds']):.0f} s -> {path}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
