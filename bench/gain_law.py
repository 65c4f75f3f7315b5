"""The paper's gain law G = C_γ/C_I ∼ N_S N_T (Supplementary S4, eqs. contrast_final and GG), measured.

    .venv/bin/python bench/gain_law.py             # quick sinking spheres, ~2 min on 2 cores
    .venv/bin/python bench/gain_law.py --full      # the full 32×32 array too (paper's depth and 3 ℓ_s), 3 min in all
    .venv/bin/python bench/gain_law.py --time-weighting   # every part weighted by the whole frame's 1/v(t) (eq. W1)

Writes out/bench/gain_law.json and out/bench/gain_law.png (G against depth, next to S4's setting and N_S·N_T).

S4 derives the fingerprint's contrast as an intensity ratio, C_γ = F_T/F_M: the mean of |Tr R F†|² with the
target's echo alone over that with the background alone, against the confocal image's C_I = σ_T²/σ_M², for a
background uncorrelated between plane waves, elements and frequencies, of one level σ_M². γ's numerator is linear
in R (paper eq. P), so a frame splits exactly into the target's echo (`Scenario.target_echo`) and the fog
(`Scenario.without_targets()`, the same realisation with its interface and noise): ρ = |n_T(r_t)|² / mean |n_M|²,
n = γ‖R‖ of each part, with no cross-term and no speckle at the truth. Both ρ and C_I take their background on
the same grid next to the target: within 3 mm laterally and 0.5 mm of its depth. The backgrounds are not uniform
across a grid, so G moves with where it is taken; the whole depth slab of the grid is printed as a second reading
("slab"). Next to the target is the reading the law's trivial case checks: one point reflector, one degree of freedom,
gives G = 1.1 there and 1.8–2.0 over a 27 mm-wide slab, whose edges lie beyond the aperture (tests/test_gain_law.py).
Printed:

1. S4's own setting: each sphere's calibration (in water, the fingerprint's own echo) in stationary, band-limited
   white noise, with the default fingerprint (gated after the front face, whitened at 0.4 σ_1), the gated matrix
   itself (R0′, paper S2 Fig. S7a: `whiten_modes=False`) and ungated, next to N_S·N_T and the share of the echo's
   energy the gate keeps (three noise draws: mean ± std).
2. In the scenario's fog at 2, 3, 4 ℓ_s and the paper's depth (frame 0): G on the fog itself with the default and
   with R0′, on white noise given the fog's own RMS time envelope (what the fog's decay alone gives), and, at the
   paper's depth, ungated.
3. The paper's figures read through S4: ρ = G·C_I, and the amplitude contrast C_γ = γ_t/mean γ that its Fig. 2 quotes
   (docs/design.md §4.8) would be about κ√(1 + ρ), κ = rms/mean of the background's γ (1.13 for Rayleigh).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.ndimage import uniform_filter1d

sys.path.insert(0, str(Path(__file__).resolve().parent))
from validate_simulate import PAPER, brightest_near, section  # noqa: E402

import fpcore  # noqa: E402
import fpcore.simulate as sim  # noqa: E402
from fpcore.fingerprint import time_gate  # noqa: E402
from fpcore.time_weighting import apply_time_weights, time_weights  # noqa: E402

#: Where the background is averaged: within PATCH (m) laterally of the target and SLAB (m) of its depth (of the
#: echo's brightest confocal point for C_I); as a second reading, over the grid's whole depth slab. The backgrounds
#: hold no target, so nothing is excluded.
SLAB = 0.5e-3
PATCH = 3e-3

#: The fingerprints compared (`fpcore.from_calibration` options): the default, gated and whitened (paper eq. finger);
#: the gated matrix itself, R0′ (paper S2, Fig. S7a); ungated.
DEFAULT = "gated, whitened (default)"
FINGERPRINTS: dict[str, dict] = {
    DEFAULT: {},
    "gated, R0′ (not whitened)": {"whiten_modes": False},
    "ungated, whitened": {"gate": False},
}


def white_noise_like(acq: fpcore.Acquisition, support: tuple[float, float], envelope=None, seed: int = 1):
    """Gaussian noise of `acq`'s shape, independent per element, transmit and sample, band-limited to `support`
    (the transducer's), of unit RMS, times `envelope(t)` if given: S4's background (stationary) or one that only
    shares a real background's time decay."""
    rng = np.random.default_rng(seed)
    n_t = acq.rf.shape[2]
    spec = np.fft.rfft(rng.standard_normal(acq.rf.shape), axis=2)
    f = np.fft.rfftfreq(n_t, 1.0 / acq.fs)
    spec[..., (f < support[0]) | (f > support[1])] = 0.0
    w = np.fft.irfft(spec, n=n_t, axis=2)
    w /= np.sqrt(np.mean(w**2))
    if envelope is not None:
        w *= envelope[None, None, :]
    return replace(acq, rf=w.astype(np.float32))


def rms_envelope(acq: fpcore.Acquisition, smooth_s: float = 1e-6) -> np.ndarray:
    """The frame's RMS over elements and transmits against time, smoothed over `smooth_s`."""
    power = np.mean(acq.rf.astype(np.float64) ** 2, axis=(0, 1))
    return np.sqrt(uniform_filter1d(power, size=max(1, int(round(smooth_s * acq.fs)))))


class SplitGain:
    """ρ, C_I and G = ρ/C_I of one target (echo alone) against backgrounds, on one grid and fingerprint."""

    def __init__(self, imager: fpcore.Imager, fp: fpcore.Fingerprint, echo: fpcore.Acquisition, r, radius: float):
        grid = imager.config.grid
        self.imager, self.fp = imager, fp
        mesh = np.meshgrid(*grid.axes, indexing="ij")
        self.r = np.asarray(r, dtype=float)
        r_grid = self.r[[0, 2]] if grid.ndim == 2 else self.r
        pw = imager.plane_waves(echo)
        # γ's numerator |Tr R F†| (paper eq. P) of the echo alone at the target: γ times ‖R‖
        # γ's numerator |Tr R F†| (paper eq. P) of the echo alone at the target: γ times ‖R‖
        self.num_t = float(imager.gamma(pw, fp)[grid.nearest_index(self.r)]) * float(np.linalg.norm(pw.data))
        conf = imager.confocal(pw)
        ib = brightest_near(conf, mesh, r_grid, radius)
        self.i_t = float(conf[ib])  # the echo's brightest confocal point near the target (paper eq. (1))
        lateral = sum((m - c) ** 2 for m, c in zip(mesh[:-1], r_grid[:-1], strict=True)) < PATCH**2
        at_target, at_cap = np.abs(mesh[-1] - r_grid[-1]) < SLAB, np.abs(mesh[-1] - mesh[-1][ib]) < SLAB
        self.regions = {"patch": (lateral & at_target, lateral & at_cap), "slab": (at_target, at_cap)}

    def against(self, background: fpcore.Acquisition) -> dict[str, float]:
        """C_I, ρ, G and κ against `background` next to the target (within PATCH laterally, SLAB in depth), and
        G over the whole depth slab of the grid ("G_slab")."""
        pw = self.imager.plane_waves(background)
        num_m = self.imager.gamma(pw, self.fp).astype(np.float64) * float(np.linalg.norm(pw.data))
        conf = self.imager.confocal(pw)
        out: dict[str, float] = {}
        for name, (where_gamma, where_confocal) in self.regions.items():
            c_i = self.i_t / float(conf[where_confocal].mean())
            rho = self.num_t**2 / float(np.mean(num_m[where_gamma] ** 2))
            if name == "patch":
                kappa = float(np.sqrt(np.mean(num_m[where_gamma] ** 2)) / np.mean(num_m[where_gamma]))
                out.update(C_I=c_i, rho=rho, G=rho / c_i, kappa=kappa)
            else:
                out[f"G_{name}"] = rho / c_i
        return out


def gated_share(cal: fpcore.Acquisition, r0, diameter: float, band: tuple[float, float]) -> float:
    """The share of the calibration echo's in-band energy that the fingerprint's gate keeps (paper eq.
    specular_filter; the gate `from_calibration` applies)."""
    full = cal.spectrum(*band).data
    kept = time_gate(cal, np.asarray(r0, float), diameter, 1.0 / (band[1] - band[0])).spectrum(*band).data
    return float(np.sum(np.abs(kept) ** 2) / np.sum(np.abs(full) ** 2))


def in_water(sc: sim.Scenario, seeds=(1, 2, 3)) -> list[dict]:
    """Section 1: G of each sphere's own calibration in stationary white noise (S4's setting)."""
    rows = []
    for name in sc.target_names:
        cal = sc.calibration(name)
        t = cal.ground_truth
        imager = fpcore.Imager(fpcore.ImagingConfig(fpcore.Grid.for_acquisition(cal, sc.band), band=sc.band))
        share = gated_share(cal, t.r0, t.diameter, sc.band)
        for label, fp_kw in FINGERPRINTS.items():
            fp = fpcore.from_calibration(
                cal, t.r0, imager.out_sines_for(cal), sc.band, None, diameter=t.diameter, name=name, **fp_kw
            )
            split = SplitGain(imager, fp, cal, t.r0, 0.5 * t.diameter)
            m = [split.against(white_noise_like(cal, sc.pulse.support, seed=s)) for s in seeds]
            g, g_slab = [x["G"] for x in m], [x["G_slab"] for x in m]
            row = {
                "target": name,
                "fingerprint": label,
                "G": float(np.mean(g)),
                "G_std": float(np.std(g)),
                "G_slab": float(np.mean(g_slab)),
                "N_S": fp.n_s,
                "N_T": fp.n_t,
                "gated_share": share,
            }
            rows.append(row)
            print(
                f"  {name} {label:26s} G = {row['G']:5.2f} ± {row['G_std']:.2f} (slab {row['G_slab']:4.2f})   "
                f"N_S N_T = {fp.n_s * fp.n_t:5.0f} "
                f"(N_S {fp.n_s:4.1f}, N_T {fp.n_t:4.1f})   share of the echo's energy after the gate {share:.2f}"
            )
    return rows


def in_fog(quick: bool, depths: tuple[float | None, ...], frame: int = 0, time_weighting: bool = False) -> list[dict]:
    """Section 2: G of each sphere in the scenario's fog, at each depth (None: the paper's default). time_weighting:
    the echo, the fog and the white noise each weighted by the whole frame's 1/v(t) (eq. W1: γ's numerator is linear
    in R, so the weighted frame splits as the unweighted one does)."""
    rows = []
    for depth in depths:
        sc = sim.scenario(
            "sinking-sphere", quick=quick, seed=0, n_frames=frame + 1, **({"depth_ls": depth} if depth else {})
        )
        lay = sc.layer
        assert lay is not None
        grid = replace(sc.roi, z_range=(lay.z_surface + 1e-3, sc.roi.z_range[1])).grid()
        imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
        fog = sc.without_targets().frame(frame)
        weights = time_weights(sc.frame(frame)) if time_weighting else np.ones(fog.n_samples)
        backgrounds = {
            "fog": apply_time_weights(fog, weights),
            "white, the fog's envelope": apply_time_weights(
                white_noise_like(fog, sc.pulse.support, rms_envelope(fog)), weights
            ),
        }
        truth = sc.ground_truth(frame)  # the targets' truth without making the frame
        for tg in truth.targets or []:
            cal = sc.calibration(tg.name)
            t = cal.ground_truth
            echo = apply_time_weights(sc.target_echo(tg.name, frame), weights)
            z_ls = float((tg.position[2] - lay.z_surface) / lay.ls)
            variants = dict(FINGERPRINTS) if depth is None else {k: FINGERPRINTS[k] for k in list(FINGERPRINTS)[:2]}
            for kind, fp_kw in variants.items():
                fp = fpcore.from_calibration(
                    cal, t.r0, imager.out_sines_for(fog), sc.band, None, diameter=t.diameter, name=tg.name, **fp_kw
                )
                split = SplitGain(imager, fp, echo, tg.position, 0.5 * tg.diameter)
                for label, bg in backgrounds.items():
                    if kind != DEFAULT and label != "fog":
                        continue
                    m = split.against(bg)
                    row = {"target": tg.name, "depth_ls": z_ls, "background": label, "fingerprint": kind, **m}
                    row["N_S_N_T"] = fp.n_s * (fp.n_t or 0.0)
                    rows.append(row)
                    print(
                        f"  {tg.name} at {z_ls:3.1f} ℓ_s, {kind:24s} {label:26s} "
                        f"C_I = 1/{1 / m['C_I']:7.1f}  ρ = F_T/F_M = {m['rho']:8.3f}  "
                        f"G = {m['G']:6.1f} (slab {m['G_slab']:6.1f})  "
                        f"(N_S N_T {row['N_S_N_T']:4.0f}; κ {m['kappa']:.2f})"
                    )
    return rows


def paper_through_s4() -> None:
    """Section 3: the paper's stated G and C_I, through S4."""
    for name, p in PAPER.items():
        rho = p["G"] * p["C_I"]
        print(
            f"  paper, {name}: ρ = G·C_I = {p['G']}/{1 / p['C_I']:.0f} = {rho:.1f}, so (γ_t/γ_M)² ≈ {1 + rho:.1f} and "
            f"the amplitude C_γ ≈ 1.13·√(1 + ρ) ≈ {1.13 * np.sqrt(1 + rho):.1f}; its Fig. 2 quotes C_γ {p['C_gamma']}"
        )


def plot(rows: dict[str, list[dict]], png: Path) -> None:
    """G against depth in the fog and in white noise with the fog's envelope (quick and full), next to S4's
    setting (each sphere in water) and N_S·N_T: the figure of sections 1–2."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    for ax, name in zip(axes, ("sphere1", "sphere2"), strict=True):
        n_s_n_t = None
        for size, marker in (("quick", "o"), ("full", "s")):
            fog = [r for r in rows.get(f"fog_{size}", []) if r["target"] == name]
            curves = (
                ("fog", DEFAULT, "C3", "fog"),
                ("white, the fog's envelope", DEFAULT, "C0", "white, the fog's envelope"),
                ("fog", "gated, R0′ (not whitened)", "C4", "fog, F = R0′ (not whitened)"),
            )
            for background, kind, colour, label in curves:
                pts = sorted(
                    (r["depth_ls"], r["G"]) for r in fog if r["background"] == background and r["fingerprint"] == kind
                )
                if pts:
                    x, y = zip(*pts, strict=True)
                    ax.plot(
                        x,
                        y,
                        marker=marker,
                        color=colour,
                        ls="-" if size == "quick" else "--",
                        label=f"{label} ({size})",
                    )
                    n_s_n_t = next(r["N_S_N_T"] for r in fog)
            water = [r for r in rows.get(f"water_{size}", []) if r["target"] == name and r["fingerprint"] == DEFAULT]
            for r in water:
                ax.axhline(
                    r["G"],
                    color="k",
                    ls=":" if size == "quick" else "-.",
                    lw=1,
                    label=f"in water, white noise ({size})",
                )
        if n_s_n_t:
            ax.axhline(n_s_n_t, color="C2", lw=1, label="N_S·N_T (S4's law)")
        ax.axhline(PAPER[name]["G"], color="C1", lw=1, label="the paper's G (640 / 380)")
        ax.set_yscale("log")
        ax.set_xlabel("centre depth (ℓ_s)")
        ax.set_title(f"{name}: G = (F_T/F_M)/C_I")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("G")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=4)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(png, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="the full 32×32 array too (the paper's depth and 3 ℓ_s)")
    ap.add_argument(
        "--time-weighting",
        action="store_true",
        help="section 2 with every part weighted by the whole frame's 1/v(t) (eq. W1, docs/design.md §4.14)",
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows: dict[str, list[dict]] = {}
    for quick in (True, False) if args.full else (True,):
        size = "quick" if quick else "full"
        sc = sim.scenario("sinking-sphere", quick=quick, seed=0, n_frames=1)
        section(f"1. S4's setting: each sphere in water, stationary white noise ({size})")
        rows[f"water_{size}"] = in_water(sc)
        section(f"2. In the fog, frame 0 ({size}; None = the paper's depth)")
        rows[f"fog_{size}"] = in_fog(
            quick, (2.0, 3.0, 4.0, None) if quick else (3.0, None), time_weighting=args.time_weighting
        )
    section("3. The paper's figures through S4")
    paper_through_s4()
    out = Path("out/bench")
    out.mkdir(parents=True, exist_ok=True)
    stem = "gain_law_weighted" if args.time_weighting else "gain_law"
    (out / f"{stem}.json").write_text(json.dumps(rows, indent=1))
    plot(rows, out / f"{stem}.png")
    print(f"\n  (rows in {out / stem}.json, figure {out / stem}.png; total {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
