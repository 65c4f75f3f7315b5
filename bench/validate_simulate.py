"""Validate the forward model (fpcore.simulate) against physics and print the figures.

    .venv/bin/python bench/validate_simulate.py            # ~2–4 min on 2 cores
    .venv/bin/python bench/validate_simulate.py --full     # + the headline on full frames (slow)
    .venv/bin/python bench/validate_simulate.py --headline-only --layer focal_return=True --layer confocal_notch=True
                                    # the quick headline on a background option (docs/design.md §6.6), ~6 min
                                    # (any focal-return option replaces the default set: the pairs, F6)
    .venv/bin/python bench/validate_simulate.py --headline-only --scenario sinking-cylinder   # its 2-D analogue
    .venv/bin/python bench/validate_simulate.py --headline-only --no-whitening --null-single-scattering \
        --layer depth_ls=2.5 [--full]     # F = R0′ with the null level of eq. (B2) (docs/design.md §4.9)
    .venv/bin/python bench/validate_simulate.py --headline-only --time-weighting [--full]
                                    # γ of each frame weighted by its own 1/v(t) (eq. W1, docs/design.md §4.14)

Sections:
 1. Faran coefficients: energy conservation, rigid limit, low-frequency (equivalent fluid) limit.
 2. ℓ_s measured from the decay of the coherent wave (Foldy–Lax, 2D and 3D) vs the input ℓ_s.
 3. Confocal contrast of a target vs depth in the scattering layer: fitted decay length vs ℓ_s.
 4. Sphere echo richness: reverberation time, N_T, N_S (fpcore.from_calibration).
 5. Multiple-scattering background: correlation frequency δf, frame-to-frame correlation,
    correlation with the target echo.
 6. Frame sizes and generation times (quick and full).
 7. Sinking-sphere headline with the fingerprint core (confocal contrast, C_γ, localisation, PFA),
    and the lesion-marker check.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import background_metrics as bm  # noqa: E402

import fpcore  # noqa: E402
import fpcore.simulate as sim
from fpcore.acquisition import PlaneWaveSequence, Probe
from fpcore.geometry import cosines
from fpcore.metrics import contrasts


def section(title: str) -> None:
    print(f"\n== {title}")


def faran_checks() -> None:
    section("1. Faran partial-wave coefficients")
    ka = np.linspace(0.5, 60, 120)[:, None]
    n = np.arange(0, 90)[None, :]
    lossless = sim.Elastic(5700.0, 2700.0, 2000.0)
    for name, coef in (
        ("sphere", sim.sphere_coefficients(ka, n, lossless)),
        ("cylinder", sim.cylinder_coefficients(ka, n, lossless)),
    ):
        print(f"  {name:8s}: max | |1 + 2A_n| − 1 | = {np.max(np.abs(np.abs(1 + 2 * coef) - 1)):.1e} (lossless ⇒ 0)")
    heavy = sim.Elastic(5700.0e8, 2700.0, 2000.0)
    err = np.max(np.abs(sim.sphere_coefficients(ka, n, heavy) - sim.rigid_sphere_coefficients(ka, n)))
    print(f"  rigid limit (ρ × 1e8): max |A_n − A_n^rigid| = {err:.1e}")
    ka0, n0 = np.array([[0.03]]), np.arange(2)[None, :]
    c_eq = np.sqrt(lossless.c_p**2 - 4 * lossless.c_t**2 / 3)
    rel = np.max(
        np.abs(
            sim.sphere_coefficients(ka0, n0, lossless) / sim.fluid_sphere_coefficients(ka0, n0, 5.7, c_eq / 1500) - 1
        )
    )
    print(f"  ka = 0.03: monopole/dipole vs equivalent fluid (bulk modulus): rel. diff {rel:.1e}")


def mean_free_path() -> None:
    section("2. Scattering mean free path from the coherent wave (Foldy–Lax)")
    k = 2 * np.pi  # wavelength = 1
    for dim, ls, width, thick, n_real in ((2, 5.0, 60.0, 10.0, 80), (3, 3.0, 14.0, 6.0, 12)):
        unitary = 4 / k if dim == 2 else 4 * np.pi / k**2
        t = sim.point_strength(unitary, k, dim)
        density = 1.0 / (sim.cross_section(t, k, dim) * ls)
        z = np.linspace(0.5, thick - 0.5, 12)
        t0 = time.perf_counter()
        psi = sim.coherent_wave(np.random.default_rng(1), k, t, density, width, thick, z, dim, n_real=n_real)
        slope = np.polyfit(z, np.log(np.abs(psi)), 1)[0]
        ls_m = -1 / (2 * slope)
        print(
            f"  {dim}D: input ℓ_s = {ls:.2f} λ (n = {density:.3f}/λ^{dim}, resonant scatterers, "
            f"{int(density * width ** (dim - 1) * thick)} per slab, {n_real} realisations): "
            f"measured ℓ_s = {ls_m:.2f} λ ({100 * (ls_m / ls - 1):+.1f} %), {time.perf_counter() - t0:.1f} s"
        )


def _pw_confocal(
    h: np.ndarray,
    probe: Probe,
    sines: np.ndarray,
    freqs: np.ndarray,
    c0: float,
    spec: np.ndarray,
    pixels: np.ndarray,
    s_out: np.ndarray,
) -> np.ndarray:
    """Confocal intensity (docs/design.md §4.3) with a Hann-apodised receive aperture, at given pixels (P, 3)."""
    k = 2 * np.pi * freqs / c0
    u = probe.positions
    ax = (np.ptp(u[:, 0]) + probe.pitch) / 2
    ay = (np.ptp(u[:, 1]) + probe.pitch) / 2
    w = np.cos(0.5 * np.pi * u[:, 0] / ax) ** 2 * (np.cos(0.5 * np.pi * u[:, 1] / ay) ** 2 if ay > probe.pitch else 1)
    p = np.exp(-1j * k[:, None, None] * (s_out @ u[:, :2].T)[None]) * w
    r = p @ (h * spec[:, None, None])
    ci, co = cosines(sines), cosines(s_out)  # c = √(1 − s_x² − s_y²) (docs/design.md §4)
    kx = k[:, None, None] * (s_out[None, :, None, 0] + sines[None, None, :, 0])
    ky = k[:, None, None] * (s_out[None, :, None, 1] + sines[None, None, :, 1])
    kz = k[:, None, None] * (co[None, :, None] + ci[None, None, :])
    return np.array([abs(np.sum(r * np.exp(1j * (kx * x + ky * y + kz * z)))) ** 2 for x, y, z in pixels])


def _point_target_and_fog(
    layer: sim.ScatteringLayer,
    probe: Probe,
    sines: np.ndarray,
    freqs: np.ndarray,
    c0: float,
    spec: np.ndarray,
    s_out: np.ndarray,
    fogs: list[np.ndarray],
    depths: np.ndarray,
    dim: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At each depth below the surface, on axis: the confocal intensity of a point target through the medium
    (both legs, ℓ_ext(f)), of the same target in water, and the fog's mean confocal intensity per realisation
    over 5 pixels in x (and 5 in y in 3-D) within ±2 mm. (N_z,), (N_z,), (N_z, n_real)."""
    target, water, fog = [], [], []
    xs = np.linspace(-2e-3, 2e-3, 5)
    for d in depths:
        r = np.array([0.0, 0.0, layer.z_surface + d])
        h0 = sim.radiate_points(r[None], np.array([1e-3]), probe.positions, sines, freqs, c0, dim)
        h = layer.attenuate(h0, r, 0.0, probe.positions, sines, freqs=freqs)
        target.append(_pw_confocal(h, probe, sines, freqs, c0, spec, r[None], s_out)[0])
        water.append(_pw_confocal(h0, probe, sines, freqs, c0, spec, r[None], s_out)[0])
        pix = np.array([[x, 0.0, r[2]] for x in xs] + ([[0.0, y, r[2]] for y in xs] if dim == 3 else []))
        fog.append([_pw_confocal(v, probe, sines, freqs, c0, spec, pix, s_out).mean() for v in fogs])
    return np.array(target), np.array(water), np.array(fog)


def contrast_vs_depth() -> None:
    section("3. Confocal contrast of a point target vs depth z − z_s = 1…5 ℓ_s (C_I ∝ exp(−z/ℓ_s), paper eq. (1))")
    print("  C_I = I_target(r) / ⟨I_background⟩ at the same depth (apodised plane-wave confocal, 4 realisations),")
    print("  target normalised by the same target in water (removes the free-space 1/r² range loss)")
    c0, fc = 1500.0, 2.2e6
    band = sim.Band(1.8e6, 2.6e6)
    for dim in (2, 3):
        if dim == 2:  # a small linear array under 10 mm of water
            probe, seq = Probe.linear(32, c0 / fc / 2, fc, 0.8e6), PlaneWaveSequence.uniform_sines(9, 0.15)
            s_out = np.stack([np.linspace(-0.5, 0.5, 41), np.zeros(41)], 1)
            z_s, t_win = 10e-3, (12e-6, 32e-6)
        else:  # the quick sinking-sphere rig: 16×16 elements, 10.9 mm aperture, 16 mm of water
            probe, seq = Probe.matrix(16, 16, c0 / fc, fc, 0.8e6), PlaneWaveSequence.uniform_sines(5, 0.2, ny=5)
            g = np.linspace(-0.45, 0.45, 13)
            s_out = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
            z_s, t_win = 16e-3, (20e-6, 40e-6)
        radius = 0.5 * probe.aperture[0]
        for envelope in ("escape", "diffusion"):
            layer = sim.ScatteringLayer(z_surface=z_s, ls=1.8e-3, la=8e-3, envelope=envelope)
            win = sim.TimeWindow.covering(10.4e6, *t_win, guard=20e-6)
            bins = win.band_bins(band)
            f = win.freqs()[bins]
            spec = band.spectrum(f)
            bgs = [
                sim.DiffuseBackground(
                    layer, probe.positions, seq.sines, win, band, c0, dim, radius, np.random.default_rng(s)
                ).next()
                for s in range(4)
            ]
            depths = np.arange(1, 6) * layer.ls
            i_t, in_water, fog = _point_target_and_fog(layer, probe, seq.sines, f, c0, spec, s_out, bgs, depths, dim)
            cs = i_t / fog.mean(axis=1)
            raw = np.polyfit(depths, np.log(cs), 1)[0]
            slope = np.polyfit(depths, np.log(cs / in_water), 1)[0]
            print(
                f"  {dim}D, envelope={envelope:9s}: C_I ∝ exp(−z/ℓ_C), ℓ_C = {-1 / slope * 1e3:.2f} mm "
                f"= {-1 / (slope * layer.ls):.2f} ℓ_s (input ℓ_s = 1.80 mm, ℓ_ext = {layer.l_ext * 1e3:.2f} mm); "
                f"with the point target's free-space 1/r spreading left in: {-1 / (raw * layer.ls):.2f} ℓ_s"
            )


def contrast_vs_depth_scenario(n_real: int = 8, **layer_overrides: Any) -> float:
    """C_I of a point target at 1…5 ℓ_s in the quick sinking-sphere rig with the scenario's own medium and
    background (diffusion envelope, halo geometry, the beams' reciprocity, the beads' focused speckle, ℓ_s(f)
    and the ballistic filter ℓ_ext(f)): the slope of ln C_I against depth times ℓ_s(f_c), the paper's eq. (1)
    law, in the geometry the headline uses (the Foldy–Lax slabs are too small for it in 3-D: README);
    `layer_overrides` change the medium (e.g. la=np.inf, ls_exponent=0.0) to see what sets the slope. Returns
    −slope × ℓ_s."""
    sc = sim.scenario("sinking-sphere", quick=True, seed=0)
    assert sc.layer is not None
    lay = replace(sc.layer, **layer_overrides)
    probe, seq, win, band, c0 = sc.probe, sc.sequence, sc.window, sc.pulse, sc.c0
    bins = win.band_bins(band)
    f = win.freqs()[bins]
    spec = band.spectrum(f)
    g = np.linspace(-0.45, 0.45, 13)
    s_out = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    radius = 0.5 * float(np.sqrt(probe.aperture[0] * probe.aperture[1]))
    bgs = [
        sim.DiffuseBackground.cached(
            lay, probe.positions, seq.sines, win, band, c0, 3, radius, np.random.default_rng(s)
        ).next()
        for s in range(n_real)
    ]
    ls_c = float(lay.ls_at(band.centre))
    depths = np.arange(1, 6) * ls_c
    i_t, in_water, m = _point_target_and_fog(lay, probe, seq.sines, f, c0, spec, s_out, bgs, depths, 3)
    e = i_t / in_water  # the echo re the same target in water (the free-space range loss divided out)

    def slope(fog_mean: np.ndarray) -> float:
        return -float(np.polyfit(depths, np.log(e / fog_mean), 1)[0]) * ls_c

    k = slope(m.mean(axis=1))
    se = bm.jackknife_se(slope, m.T)
    ci = e / m.mean(axis=1)
    print(
        f"  3D, the sinking-sphere scenario's medium {layer_overrides or ''} (quick rig, {n_real} realisations): "
        f"ln C_I(z)/C_I(ℓ_s) at "
        f"1…5 ℓ_s = "
        + ", ".join(f"{v:.2f}" for v in np.log(ci / ci[0]))
        + f"; echo alone {np.log(e[-1] / e[0]):.2f}, fog alone {np.log(m[-1].mean() / m[0].mean()):.2f} at 5 ℓ_s; "
        f"−d ln C_I/dz × ℓ_s(f_c) = {k:.2f} ± {se:.2f} (jackknife; paper eq. (1): 1; ℓ_a = {lay.la * 1e3:.0f} mm "
        f"adds 2ℓ_s/ℓ_a = {2 * ls_c / lay.la:.2f} to the echo's fall)"
    )
    return k


def sphere_richness(sc: sim.Scenario, imager: fpcore.Imager, verbose: bool = True) -> dict[str, fpcore.Fingerprint]:
    if verbose:
        section("4. Sphere echoes (calibrations in water)")
    fps = {}
    for name in sc.target_names:
        cal = sc.calibration(name)
        truth = cal.ground_truth
        r0 = truth.r0
        env = np.sqrt(np.mean(cal.rf.astype(np.float64) ** 2, axis=(0, 1)))
        t = cal.times
        peak = t[np.argmax(env)]
        below = np.nonzero(env > 0.1 * env.max())[0]
        pw = imager.plane_waves(cal)
        fp = fpcore.from_calibration(cal, r0, pw.out_sines, sc.band, None, diameter=truth.diameter, name=name)
        fps[name] = fp
        if verbose:
            print(
                f"  {name} (d = {truth.diameter * 1e3:.0f} mm, r0 = {np.round(r0 * 1e3, 2)} mm): "
                f"echo above −20 dB for {(t[below[-1]] - peak) * 1e6:.0f} µs after the specular peak; "
                f"N_T = {fp.n_t:.1f}, N_S = {fp.n_s:.1f} (σ_p ≥ 0.4 σ_1, mean over the band)"
            )
    return fps


def background_stats(sc: sim.Scenario) -> None:
    section("5. Multiple-scattering background (sinking-sphere, quick)")
    bg = sc._background()
    assert bg is not None
    v0 = bg.next().copy()
    v1 = bg.next()
    # Frequency correlation of M: |⟨M(f) M*(f + Δf)⟩| / ⟨|M|²⟩.
    df = sc.freqs[1] - sc.freqs[0]
    c = [abs(np.vdot(v0[: -j or None], v0[j:])) / np.vdot(v0, v0).real for j in range(0, 40)]
    j_half = next((j for j, x in enumerate(c) if x < 0.5), len(c))
    print(
        f"  correlation frequency δf (half width) ≈ {j_half * df / 1e3:.0f} kHz → N_f = Δf/δf ≈ "
        f"{(sc.band[1] - sc.band[0]) / max(j_half * df, df):.0f} grains in the band"
    )
    rho = abs(np.vdot(v0, v1)) / (np.linalg.norm(v0) * np.linalg.norm(v1))
    w = bg.envelope.astype(np.float64) ** 2
    print(
        f"  frame-to-frame correlation of M: {rho:.2f} (DWS model, intensity-weighted g1 = "
        f"{np.sum(w * bg.g1) / np.sum(w):.2f}; grain displacement {sc.layer.frame_displacement * 1e6:.0f} µm)"
    )
    pl = sc.placements["sphere1"]
    h = sc._target_h(pl, pl.position(0), True)
    print(f"  |corr(M, target echo)| = {abs(np.vdot(h, v0)) / (np.linalg.norm(h) * np.linalg.norm(v0)):.3f}")
    print(f"  output directions |s_o| ≤ {bg.s_d:.2f}, {bg.n_o} plane waves, baseband {bg.n_bb} samples")


def timings() -> None:
    section("6. Frame sizes and generation times (2 cores)")
    for name in sim.SCENARIOS:
        for quick in (True, False):
            sc = sim.scenario(name, quick=quick, seed=0)
            t0 = time.perf_counter()
            sc.static_transfer()
            t_static = time.perf_counter() - t0
            t0 = time.perf_counter()
            sc.frame(0)
            t_first = time.perf_counter() - t0
            n = 3 if quick else 2
            t0 = time.perf_counter()
            for i in range(1, 1 + n):
                sc.frame(i)
            t_frame = (time.perf_counter() - t0) / n
            print(
                f"  {name:15s} {'quick' if quick else 'full ':5s}: {sc.probe.n_elements:4d} el × "
                f"{sc.sequence.n_waves:2d} pw × {sc.n_samples:4d} samples (fs {sc.fs / 1e6:.1f} MHz) = "
                f"{sc.frame_nbytes / 1e6:5.1f} MB/frame, {sc.n_frames} frames; precompute {t_static:5.1f} s, "
                f"first frame {t_first:4.1f} s, then {t_frame:4.2f} s/frame"
            )


#: The paper's figures for its two spheres (main text eq. (1), eq. G and after; Fig. 2; S6).
PAPER = {
    "sphere1": {"depth_ls": "5", "C_I": 1 / 150, "C_gamma": "6–7", "N_S": 20, "N_T": 32, "G": 640, "PFA": "< 1e-8"},
    "sphere2": {"depth_ls": "4", "C_I": 1 / 50, "C_gamma": "6–7", "N_S": 12, "N_T": 32, "G": 380, "PFA": "< 1e-8"},
}


def reverberation_n_t(cal: fpcore.Acquisition, band: tuple[float, float]) -> float:
    """The paper's N_T ∼ Δf Δt with Δt the time the calibration echo stays above −20 dB of its peak."""
    env = np.sqrt(np.mean(cal.rf.astype(np.float64) ** 2, axis=(0, 1)))
    above = np.nonzero(env > 0.1 * env.max())[0]
    return (band[1] - band[0]) * (above[-1] - int(np.argmax(env))) / cal.fs


def brightest_near(conf: np.ndarray, mesh: list[np.ndarray], r_grid: np.ndarray, radius: float) -> tuple:
    """Index of a target echo's brightest confocal point within 1.5 mm of its surface (centre `r_grid` on the grid's
    axes, `radius`): the target's intensity in C_I (paper eq. (1))."""
    near = sum((m - c) ** 2 for m, c in zip(mesh, r_grid, strict=True)) < (radius + 1.5e-3) ** 2
    return np.unravel_index(np.argmax(np.where(near, conf, 0.0)), conf.shape)


def headline(
    quick: bool,
    frames: list[int],
    configs: dict[str, dict] | None = None,
    scenario: str = "sinking-sphere",
    whiten_modes: bool = True,
    null_single_scattering: bool = False,
    time_weighting: bool = False,
) -> list[dict]:
    """The paper's figures, measured (issue: the paper's regime). Per configuration, target and frame: C_I (the
    target's own echo — simulated alone through the medium — at its brightest point over the fog's mean confocal
    intensity at that depth), C_γ at the truth with and without the angular filter, N_S, N_T (participation
    width and the paper's Δf·Δt_{−20 dB}), G = N_S·N_T, the measured gain C_γ/C_I, and the detector's most
    significant peak (fpcore.locate on the whole record: distance to the truth, calibrated PFA) against the
    Cramér–Rao radius. `scenario`: the sinking spheres (3-D) or their 2-D analogue, the sinking cylinders;
    whiten_modes=False: the fingerprints are R0′ itself (paper S2, Fig. S7a; `from_calibration`);
    null_single_scattering: the detector's null level with eq. (B2) (docs/design.md §4.9); time_weighting: γ and
    its null level on the frame weighted by its own 1/v(t) (eq. W1, docs/design.md §4.14; C_I stays the
    unweighted image's)."""
    configs = configs or {
        "paper (default)": {},
        "paper's stated positions": {"sink": sim.scenarios.PAPER_POSITIONS[0], "sphere2_depth": 7e-3},
        "depth 3 ℓ_s": {"depth_ls": 3.0},
        "depth 2 ℓ_s (demo)": {"depth_ls": 2.0},
        "legacy": {"conventions": "legacy"},
    }
    size = "quick" if quick else "full"
    section(f"7. The paper's regime, measured ({size} {scenario}; paper: C_I 1/150 and 1/50, C_γ 6–7, G 640/380)")
    rows = []
    for label, kw in configs.items():
        sc = sim.scenario(scenario, quick=quick, seed=0, **kw)
        fog = sc.without_targets()
        first = sc.frame(0)
        grid = fpcore.Grid.for_acquisition(first, sc.band)  # the default grid: the record's whole time window
        grid_c = replace(sc.roi, z_range=(17e-3, sc.roi.z_range[1])).grid()  # confocal from 1 mm under z_s
        imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band, time_weighting=time_weighting))
        imager_c = fpcore.Imager(fpcore.ImagingConfig(grid_c, band=sc.band))
        level = fpcore.NullLevel(imager, single_scattering=null_single_scattering)
        mesh = np.meshgrid(*grid_c.axes, indexing="ij")
        fps, fps_raw, nt_paper = {}, {}, {}
        out_sines = imager.out_sines_for(first)
        for name in sc.target_names:
            cal = sc.calibration(name)
            t = cal.ground_truth
            kw_fp = {"diameter": t.diameter, "name": name, "whiten_modes": whiten_modes}
            fps[name] = fpcore.from_calibration(cal, t.r0, out_sines, sc.band, None, **kw_fp)
            fps_raw[name] = fpcore.from_calibration(cal, t.r0, out_sines, sc.band, None, angular_filter=False, **kw_fp)
            nt_paper[name] = reverberation_n_t(cal, sc.band)
        lay = sc.layer
        assert lay is not None
        for i in frames:
            acq = sc.frame(i)
            pw = imager.plane_waves(acq)
            conf_fog = imager_c.confocal(imager_c.plane_waves(fog.frame(i)))
            for tg in acq.ground_truth.targets or []:
                r, a = np.asarray(tg.position, float), 0.5 * tg.diameter
                r_grid = r[[0, 2]] if sc.dim == 2 else r  # on the grid's axes: (x, z) in 2-D
                conf_t = imager_c.confocal(imager_c.plane_waves(sc.target_echo(tg.name, i)))
                ib = brightest_near(conf_t, mesh, r_grid, a)
                c_i = float(conf_t[ib] / conf_fog[np.abs(mesh[-1] - grid_c.z[ib[-1]]) < 0.5e-3].mean())
                loc = fpcore.locate(imager, acq, fps[tg.name], level, pw=pw, max_pfa=None)
                det = loc.detections[0]
                cg = contrasts(loc.gamma, grid, r, a)[0]
                cg_raw = contrasts(imager.gamma(pw, fps_raw[tg.name]), grid, r, a)[0]
                fp = fps[tg.name]
                err = float(np.linalg.norm(np.array(det.position_m) - r))
                row = {
                    "config": label,
                    "target": tg.name,
                    "frame": i,
                    "depth_ls": float((r[2] - lay.z_surface) / lay.ls),
                    "C_I": c_i,
                    "C_gamma": cg,
                    "C_gamma_no_angular_filter": cg_raw,
                    "N_S": fp.n_s,
                    "N_T": fp.n_t,
                    "N_T_paper_definition": nt_paper[tg.name],
                    "G": fp.n_s * (fp.n_t or 0.0),
                    "G_measured": cg / c_i,
                    "peak_error_mm": err * 1e3,
                    "peak_pfa": det.pfa,
                    "peak_c_gamma": det.c_gamma,
                    "cramer_rao_mm": det.precision_m[0] * 1e3,
                }
                rows.append(row)
                print(
                    f"  {label:20s} {tg.name} frame {i:2d} at {row['depth_ls']:.1f} ℓ_s: C_I = 1/{1 / c_i:5.1f}  "
                    f"C_γ(truth) = {cg:5.2f} (no angular filter {cg_raw:5.2f})  N_S = {fp.n_s:4.1f}  N_T = "
                    f"{fp.n_t:4.1f} (Δf·Δt₋₂₀dB = {nt_paper[tg.name]:4.1f})  G = {row['G']:4.0f}, measured "
                    f"C_γ/C_I = {row['G_measured']:5.0f} | most significant peak {err * 1e3:5.2f} mm from the "
                    f"truth (Cramér–Rao δρ_L {row['cramer_rao_mm']:.2f} mm), C_γ {det.c_gamma:5.2f}, "
                    f"calibrated PFA {det.pfa:.1e}"
                )
    return rows


def why_c_gamma(quick: bool = True, frame: int = 0) -> list[dict]:
    """Why C_γ falls short of the paper's in its regime (issue 12, item 4): C_γ at the truth of each sphere on
    the default scenario's frame, one candidate changed at a time — the calibration position (the truth's
    initial position instead of (0, 0, 25) mm), the whitening threshold, the angular filter, the processed
    band (the transducer's whole support instead of its −6 dB band), the sphere's ring-down (a lossless
    sphere), and the background (none: C_γ of the target against electronic noise only, the ceiling)."""
    section(f"9. Why C_γ falls short in the paper's regime ({'quick' if quick else 'full'}, frame {frame})")
    base = sim.scenario("sinking-sphere", quick=quick, seed=0, n_frames=frame + 1)
    grid = replace(base.roi, z_range=(17e-3, base.roi.z_range[1])).grid()
    lossless = sim.Elastic(5700.0, 2700.0, 2000.0)
    scenarios = {
        "default": base,
        "calibration at the truth": sim.scenario(
            "sinking-sphere", quick=quick, n_frames=frame + 1, calibration="nominal"
        ),
        "lossless sphere (longer ring-down)": replace(
            base,
            placements={n: replace(p, target=replace(p.target, material=lossless)) for n, p in base.placements.items()},
        ),
    }
    support = base.pulse.support
    variants: list[tuple[str, str, dict]] = [
        ("default", "default", {}),
        ("calibration at the truth", "calibration at the truth", {}),
        ("whitening threshold 0.2 (paper 0.4)", "default", {"svd_threshold": 0.2}),
        ("whitening threshold 0.1", "default", {"svd_threshold": 0.1}),
        ("no angular filter", "default", {"angular_filter": False}),
        (f"band {support[0] / 1e6:.1f}–{support[1] / 1e6:.1f} MHz (whole support)", "default", {"band": support}),
        ("lossless sphere (longer ring-down)", "lossless sphere (longer ring-down)", {}),
        ("no background (noise only)", "no background", {}),
    ]
    frames, cals, rows = {}, {}, []
    for label, sc_name, kw in variants:
        if sc_name == "no background":
            sc = replace(base, layer=None)
            sc_key = sc_name
        else:
            sc, sc_key = scenarios[sc_name], sc_name
        band = kw.pop("band", sc.band)
        imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=band))
        if sc_key not in frames:
            if sc_name == "no background":  # targets attenuated by the medium, no fog: the medium's layer for H only
                acq = base.target_echo("sphere1", frame)
                both = acq.rf + base.target_echo("sphere2", frame).rf
                frames[sc_key] = base._acquisition(both, frame, base.ground_truth(frame))
            else:
                frames[sc_key] = sc.frame(frame)
            cals[sc_key] = {n: sc.calibration(n) for n in sc.target_names}
        acq = frames[sc_key]
        pw = imager.plane_waves(acq)
        row = {"variant": label}
        for tg in acq.ground_truth.targets or []:
            cal = cals[sc_key][tg.name]
            t = cal.ground_truth
            fp = fpcore.from_calibration(cal, t.r0, pw.out_sines, band, None, diameter=t.diameter, name=tg.name, **kw)
            cg = contrasts(imager.gamma(pw, fp), grid, tg.position, 0.5 * tg.diameter)[0]
            row[tg.name] = {"C_gamma": cg, "N_S": fp.n_s, "N_T": fp.n_t}
        rows.append(row)
        print(
            f"  {label:44s} "
            + "  ".join(
                f"{n}: C_γ(truth) {v['C_gamma']:5.2f} (N_S {v['N_S']:4.1f}, N_T {v['N_T']:4.1f})"
                for n, v in row.items()
                if n != "variant"
            )
        )
    return rows


def lesion() -> None:
    section("8. Lesion marker (quick): γ vs confocal in speckle at z − z_s ≈ ℓ_s")
    sc = sim.scenario("lesion-marker", quick=True)
    grid = sc.roi.grid()
    im = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    cal = sc.calibration("marker")
    fp = fpcore.from_calibration(
        cal, cal.ground_truth.r0, im.plane_waves(cal).out_sines, sc.band, None, diameter=cal.ground_truth.diameter
    )
    acq = sc.frame(0)
    pw = im.plane_waves(acq)
    g, conf = im.gamma(pw, fp), im.confocal(pw)
    r = acq.ground_truth.target("marker").position
    rp = grid.position(np.unravel_index(np.argmax(g), g.shape))
    rc = grid.position(np.unravel_index(np.argmax(conf), conf.shape))
    print(
        f"  N_S = {fp.n_s:.1f}, N_T = {fp.n_t:.1f}; γ peak {np.linalg.norm(rp - r) * 1e3:.2f} mm from truth, "
        f"C_γ = {contrasts(g, grid, r, 1.5e-3)[0]:.1f}; confocal C = {contrasts(conf, grid, r, 1.5e-3)[0]:.2f}, "
        f"confocal max {np.linalg.norm(rc - r) * 1e3:.1f} mm from truth"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="also run the headline on full frames (slow)")
    ap.add_argument(
        "--layer", action="append", default=[], help="KEY=VALUE: the scenario layer's option (runs the headline only)"
    )
    ap.add_argument("--headline-only", action="store_true", help="only the quick headline's paper row (frames 0, 31)")
    ap.add_argument(
        "--no-whitening", action="store_true", help="the headline only, its fingerprints F = R0′ (paper S2, Fig. S7a)"
    )
    ap.add_argument(
        "--null-single-scattering",
        action="store_true",
        help="the headline only, its null level with eq. (B2) (docs/design.md §4.9)",
    )
    ap.add_argument(
        "--time-weighting",
        action="store_true",
        help="the headline only, γ of each frame weighted by its own 1/v(t) (eq. W1, docs/design.md §4.14)",
    )
    ap.add_argument(
        "--scenario",
        default="sinking-sphere",
        choices=("sinking-sphere", "sinking-cylinder"),
        help="the headline's scenario with --headline-only or --layer (sinking-cylinder: its 2-D analogue)",
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    if args.layer or args.headline_only or args.no_whitening or args.null_single_scattering or args.time_weighting:
        from validate_background import parse_layer

        kw = parse_layer(args.layer)
        label = "paper" + "".join(f", {k}={v}" for k, v in kw.items()) + (", F = R0′" if args.no_whitening else "")
        label += ", null (B2)" if args.null_single_scattering else ""
        label += ", 1/v(t)" if args.time_weighting else ""
        opts = {
            "whiten_modes": not args.no_whitening,
            "null_single_scattering": args.null_single_scattering,
            "time_weighting": args.time_weighting,
        }
        headline(True, [0, 31], {label: kw}, args.scenario, **opts)
        if args.full:
            headline(False, [0], {label: kw}, args.scenario, **opts)
        print(f"\n(total {time.perf_counter() - t0:.0f} s)")
        return
    faran_checks()
    mean_free_path()
    contrast_vs_depth()
    contrast_vs_depth_scenario()
    sc = sim.scenario("sinking-sphere", quick=True, seed=0)
    background_stats(sc)
    timings()
    rows = headline(True, [0, 31])
    why_c_gamma(True)
    if args.full:
        rows += headline(False, [0], {"paper (default)": {}, "depth 2 ℓ_s (demo)": {"depth_ls": 2.0}})
    out = Path("out/bench")
    out.mkdir(parents=True, exist_ok=True)
    (out / "headline.json").write_text(json.dumps(rows, indent=1))
    print(f"  (rows written to {out / 'headline.json'})")
    lesion()
    print(f"\n(total {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
