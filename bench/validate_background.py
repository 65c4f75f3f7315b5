"""Statistical multiple-scattering background (fpcore.simulate.medium) vs exact Foldy–Lax (issue 12).

    .venv/bin/python bench/validate_background.py                 # 2D (runs the FL reference if not cached)
    .venv/bin/python bench/validate_background.py --dim both
    .venv/bin/python bench/validate_background.py --dim 3 --quick
    .venv/bin/python bench/validate_background.py --layer cbs=True --layer single_scattering=field --match-dispersion
    .venv/bin/python bench/validate_background.py --layer envelope=diffusion --layer cbs=True \
        --layer single_scattering=field --match-dispersion --slab        # 2026-12-02's comparison (docs/validation.md)
    .venv/bin/python bench/validate_background.py --layer envelope=diffusion --layer cbs=True \
        --layer single_scattering=field --layer angular=halo --layer memory=True --match-dispersion --slab
                                                     # the memory-effect option (docs/design.md §6.5)
    .venv/bin/python bench/validate_background.py --layer envelope=diffusion --layer cbs=True \
        --layer single_scattering=field --layer angular=halo --layer focal_return=True --layer confocal_notch=True \
        --match-dispersion --slab --model-realisations 24
                   # the focal return with the confocal notch (docs/design.md §6.6, F4): an option (the 2-D scenarios'
                   # default for part of 2026-12-07; 12 min on 2 cores)
    .venv/bin/python bench/validate_background.py --layer envelope=diffusion --layer cbs=True \
        --layer single_scattering=field --layer angular=halo --layer focal_return=True \
        --layer focal_return_pairs=True --layer focal_return_shallow=True --match-dispersion --slab \
        --model-realisations 24
                   # the scenarios' default since 2026-12-07 (late): the focal return as two-point paths (F6; 2-D:
                   # all four pass, 1 min; with --reference out/bench/fl_reference_3d_deep.npz the 3-D slab, 4 min)
    .venv/bin/python bench/validate_background.py ... --double-scattering 6   # FL's focused matrix by order too
    .venv/bin/python bench/validate_background.py --reference out/bench/fl_reference_2d_12el.npz ...  # another rig
    .venv/bin/python bench/validate_background.py --reference out/bench/fl_reference_3d_deep.npz --slab \
        --layer envelope=diffusion --layer cbs=True --layer single_scattering=field --layer angular=halo \
        --match-dispersion --model-realisations 24       # the 5.6 ℓ_s 3-D slab: the slope over 1–5 ℓ_s (3.5 min)
    .venv/bin/python bench/validate_background.py --reference out/bench/fl_reference_3d_deep.npz --slab \
        --layer envelope=diffusion --layer cbs=True --layer single_scattering=field --layer angular=halo \
        --layer focal_return=True --layer confocal_notch=True --match-dispersion --model-realisations 24
                                 # the same slab, the focal return with the notch (12 min, 2 cores; three of four
                                 # pass since W′ is centred, the slope 0.77 against FL's 0.60)
    .venv/bin/python bench/validate_background.py --reference out/bench/fl_reference_3d_deep.npz --slab \
        --layer envelope=diffusion --layer cbs=True --layer single_scattering=field --layer angular=halo \
        --layer focal_return=True --layer focal_return_excess=True --match-dispersion --model-realisations 24
                                 # the same slab, the focal return's excess over the Gaussian field (F5; 15 min)
    .venv/bin/python bench/validate_background.py ... --layer measured_reciprocity=False
                                 # the background before the measured reciprocity (docs/design.md §6.3, R1–R2)

The Foldy–Lax reference (bench/foldy_lax_reference.py, cached in out/bench/) and the model are built
for the same geometry: array, finite-aperture plane-wave transmits, band, time window, a scattering
medium from z_surface down (FL: a slab; model: a half-space, or with --slab the same slab, bottom and sides) with
ℓ_s(f_c) = 1.8 mm, lossless, index-matched (no interface echo), frozen (frame_displacement 0). The
four agreement figures of the issue, measured with bench/background_metrics.py on both, side by side:

1. time envelope ⟨r²⟩(t): max |model/FL| in dB over the record, from the surface echo + 1 µs to the
   window end (issue: within ±3 dB);
2. frequency-correlation half-width over the same gate: model/FL (within 30 %);
3. coherent-backscattering enhancement after the surface echo + 5 µs (about 2: pass if 1.7–2.3), the
   envelope fitted outside |b + a| > q_out = max(0.2, 2λ/D) (D: the array's extent), the cone's height taken
   over the ladder extrapolated to b + a = 0 from a Gaussian fit over q_out–3 q_out (a small array sees the
   halo's profile through b + a, so the ladder is not flat; the peak over the flat mean is printed too);
4. confocal contrast slope −d ln C_I/dz times ℓ_s(f_c), fitted from 1 ℓ_s to 5 ℓ_s below the surface
   (or one pulse length c0/2B above the slab's bottom if shallower), the background averaged over a line
   (2D) or a patch (3D) of half-width half the aperture's (1 within 20 %); the model's slope minus Foldy–Lax's
   with their combined jackknife error, and Foldy–Lax's background split into its first scattering order
   (`foldy_lax_reference.single_scattering`) and the rest, say what sets it.
Also printed: the CBS enhancement and the memory effect (`background_metrics.memory_correlation`) by the paths'
age (gates after the surface echo), the focused matrix's intensity against the in–out separation at 1–4 ℓ_s
(`background_metrics.focused_profile`: FL's profile and model/FL), the confocal background and echo model/FL by
depth, and the share of each record's energy before the surface echo less `precursor_lead`, which no path
reaches (Foldy–Lax: the period's wrap-round; the model: that plus the speckle's aliasing where its output grid
is capped, `--ss-directions`).
Writes out/bench/validate_background.png (rows: dimensions; columns: the four figures).
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import background_metrics as bm  # noqa: E402
import foldy_lax_reference as flr  # noqa: E402

import fpcore.simulate.single_scattering as ss_mod  # noqa: E402
from fpcore.simulate.medium import DiffuseBackground, ScatteringLayer  # noqa: E402

#: Depth ranges below the surface (in ℓ_s(f_c)) over which the contrast slope is also refitted, where the fit
#: reaches them: the exact rate is a mean over depth (2-D Foldy–Lax: 0.55/ℓ_s over 1–2.5, 1.42 over 3–5).
DEPTH_RANGES = ((1.0, 2.5), (1.0, 3.5), (1.0, 5.0), (2.5, 5.0), (3.0, 5.0))


#: Gates after the surface echo (µs) over which the CBS enhancement is also measured, where the record reaches.
CBS_AGES = ((5.0, 10.0), (10.0, 20.0), (20.0, 30.0))
#: Gates after the surface echo (µs) and tilts (transmit steps) of the memory-effect correlation.
MEMORY_AGES = ((3.0, 6.0), (6.0, 12.0), (12.0, 25.0))
MEMORY_STEPS = (1, 2, 4)
#: The focused matrix's in–out separations (in wavelengths at f_c) and depths (in ℓ_s below the surface) at
#: which `background_metrics.focused_profile` is printed: where the confocal background's deficit sits.
FOCUSED_SEPARATIONS = (0.0, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0)
FOCUSED_DEPTHS = (1.0, 2.0, 3.0, 4.0)


def precursor_lead(s: flr.Setup, sines: np.ndarray) -> float:
    """How long before the normal-incidence surface echo 2 z_s/c0 a path through the medium can first arrive (s):
    the earliest element's firing in a synthesised plane wave, max_{u,θ} (−u·s_θ)/c0 (it reaches the surface
    below itself z_s/c0 later and comes back as soon), plus the pulse's length 1/B over the band's −6 dB width B
    (a delayed echo keeps ~10⁻³ of its energy that far ahead of it, < 10⁻² at 1 µs and < 10⁻⁴ at 2 µs by
    `test_energy_before_a_delayed_echo_is_its_pulse_tail_only`)."""
    fire = -(s.elements()[:, :2] @ np.asarray(sines, dtype=np.float64)[:, :2].T) / s.c0
    return float(max(fire.max(), 0.0)) + 1.0 / (s.band_hi - s.band_lo)


def transmit_sines(dim: int) -> np.ndarray:
    """2D: 21 sines in ±0.3; 3D: 7 × 7 in ±0.3 (x fastest)."""
    if dim == 2:
        s = np.linspace(-0.3, 0.3, 21)
        return np.stack([s, np.zeros_like(s)], axis=1)
    s = np.linspace(-0.3, 0.3, 7)
    yy, xx = np.meshgrid(s, s, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def model_realisations(
    s: flr.Setup, sines: np.ndarray, n_real: int, layer_kw: dict[str, Any], seed0: int = 1000
) -> np.ndarray:
    """V (n_real, N_f, N_u, N_θ) from the public model API, one independent rng per realisation."""
    return model_orders(s, sines, n_real, layer_kw, seed0)[0]


def model_orders(
    s: flr.Setup, sines: np.ndarray, n_real: int, layer_kw: dict[str, Any], seed0: int = 1000, beads: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """V and its first-order part (the beads' focused speckle, zero without single_scattering="field"; with the
    focal return, the beads' grid: the speckle and the focal return), both (n_real, N_f, N_u, N_θ), one independent
    rng per realisation; V minus that part is the Gaussian field (orders ≥ 2). `beads=False` draws the beads'
    reflectivity zero (`SingleScatteringField.draw_beads`: the focal return alone on the grid), each realisation
    built afresh (the flag shapes the grid's tables, which `DiffuseBackground.cached` shares)."""
    layer = ScatteringLayer(
        z_surface=s.z_surface,
        ls=s.ls_c,
        la=np.inf,
        density=1000.0,
        sound_speed=1500.0,
        frame_displacement=0.0,
        **layer_kw,
    )
    out, first = [], []
    rig = (layer, s.elements(), sines, s.window, s.band, s.c0, s.dim, s.aperture_radius)
    for r in range(n_real):  # the rig's tables built once, each realisation its own draws (`DiffuseBackground.cached`)
        rng = np.random.default_rng(seed0 + r)
        bg = DiffuseBackground.cached(*rig, rng) if beads else DiffuseBackground(*rig, rng)
        if not beads:
            assert bg.single is not None
            bg.single.draw_beads = False
        multiple, single = bg.next_orders()
        first.append(np.zeros_like(multiple) if single is None else single)
        out.append(multiple + first[-1])
        if r == 0 and bg.single is not None:
            print(f"  single scattering on {bg.single.n_o} output directions (Δs = {bg.single.ds:.4f})")
    return np.stack(out), np.stack(first)


def model_echo(s: flr.Setup, depths: np.ndarray, freqs: np.ndarray, layer_kw: dict[str, Any]) -> np.ndarray:
    """Reference-reflector echo under the model's extinction: (Σ_f S(f) e^{−(z − z_s)/ℓ_ext(f)})² (two legs)."""
    layer = ScatteringLayer(z_surface=s.z_surface, ls=s.ls_c, la=np.inf, **layer_kw)
    ls_f = np.asarray(layer.ls_at(freqs)) if hasattr(layer, "ls_at") else np.full(freqs.size, layer.ls)
    ls_f = np.broadcast_to(ls_f, freqs.shape)
    lext = 1.0 / (1.0 / ls_f + 1.0 / layer.la)
    depth = np.maximum(depths - s.z_surface, 0.0)
    w = s.band.spectrum(freqs)
    return (np.exp(-depth[:, None] / lext[None, :]) @ w) ** 2 / w.sum() ** 2


def fl_echo(data: dict[str, np.ndarray], freqs: np.ndarray, band: flr.Band) -> np.ndarray:
    """(Σ_f S(f) |⟨T⟩(z, f)|²)² — the coherent wave both ways (|⟨ψ⟩|⁴, paper S1), band-summed."""
    tbar = data["T"].mean(axis=0)  # (N_f, N_z)
    w = band.spectrum(freqs)
    return (w @ np.abs(tbar) ** 2) ** 2 / w.sum() ** 2


def measure(
    v: np.ndarray, s: flr.Setup, sines: np.ndarray, freqs: np.ndarray, depths: np.ndarray, echo: np.ndarray
) -> dict[str, Any]:
    t_on = 2 * s.z_surface / s.c0
    t, env = bm.time_envelope(v, freqs, s.band)
    fc = bm.frequency_correlation_width(v, freqs, gate=(t_on, s.t_end))
    cbs = bm.cbs_enhancement(
        v, freqs, s.elements(), sines, s.c0, s.dim, gate=(t_on + 5e-6, s.t_end), q_out=cbs_q_out(s)
    )
    # The same by the paths' age (the figure above is weighted by the early, brightest part of its gate).
    cbs_age = cbs_by_age(v, s, sines, freqs, [(a, b) for a, b in CBS_AGES if t_on + b * 1e-6 <= s.t_end])
    # The fit ends 5 ℓ_s deep, or one pulse length (c0/2B) above the slab's bottom: a confocal point shallower
    # than that is reached at its time by no path that touched the bottom (causality), so the slab's depth
    # does not bias the slope there (it ended 1.5 ℓ_s above the bottom before: 1–2.5 ℓ_s in 3-D, 1–3.5 now).
    pulse = s.c0 / (2 * (s.band_hi - s.band_lo))
    z_fit = (s.z_surface + s.ls_c, s.z_surface + min(5 * s.ls_c, s.thickness - pulse))
    ci = bm.confocal_contrast_slope(
        v, freqs, s.elements(), sines, s.c0, s.dim, depths, echo, z_fit, contrast_half_width(s), band=s.band
    )
    # The angular memory effect by age: the transmits' correlation under a common tilt of input and output.
    memory = {}
    for a, b in MEMORY_AGES:
        if t_on + b * 1e-6 <= s.t_end:
            vg = bm.gate_spectra(v, freqs, (t_on + a * 1e-6, t_on + b * 1e-6))
            r = bm.plane_wave_outputs(vg, freqs, s.elements(), sines, s.c0)
            memory[(a, b)] = bm.memory_correlation(r, sines, MEMORY_STEPS)
    # The focused reflection matrix against the in–out separation: how far from the focus the background is.
    focused = {zl: p["whole"] for zl, p in focused_profiles(s, {"whole": v}, sines, freqs).items()}
    return {
        "focused": focused,
        "t": t,
        "env": env,
        "fc": fc,
        "cbs": cbs,
        "cbs_age": cbs_age,
        "memory": memory,
        "ci": ci,
        "z_fit": z_fit,
    }


def cbs_q_out(s: flr.Setup) -> float:
    """The CBS's ladder bound for the rig's array (`background_metrics.cbs_ladder_bound`)."""
    return bm.cbs_ladder_bound(s.c0 / s.f_c, s.n_side * s.pitch)


def age_gates(s: flr.Setup, ages: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Each gate (a, b) µs after the surface echo as absolute times (s), ending at the record's end at the latest
    (b may be inf)."""
    t_on = 2 * s.z_surface / s.c0
    return [(t_on + a * 1e-6, min(t_on + b * 1e-6, s.t_end)) for a, b in ages]


def cbs_by_age(
    v: np.ndarray, s: flr.Setup, sines: np.ndarray, freqs: np.ndarray, ages: list[tuple[float, float]]
) -> dict[tuple[float, float], tuple[float, float]]:
    """The CBS enhancement over the ladder and its jackknife standard error in each gate (a, b) µs after the surface
    echo (`age_gates`)."""
    out = {}
    for age, gate in zip(ages, age_gates(s, ages), strict=True):
        c = bm.cbs_enhancement(v, freqs, s.elements(), sines, s.c0, s.dim, gate=gate, q_out=cbs_q_out(s))
        out[age] = (float(c["enhancement_ladder"]), float(c["enhancement_ladder_se"]))
    return out


def dispersion_exponent(s: flr.Setup, data: dict[str, np.ndarray]) -> float:
    """ℓ_s(f) = ℓ_s(f_c) (f/f_c)^(−x): x fitted on the Foldy–Lax medium's ℓ_s(f), rounded to 3 decimals."""
    return round(-float(np.polyfit(np.log(data["freqs"] / s.f_c), np.log(data["ls"]), 1)[0]), 3)


def contrast_half_width(s: flr.Setup) -> float:
    """Half-width of the line (2D) or patch (3D) the contrast's background is averaged over: half the
    insonified half-width, inside the aperture."""
    return 0.5 * s.aperture_radius


def fl_orders(s: flr.Setup, data: dict[str, np.ndarray], v_fl: np.ndarray, sines: np.ndarray) -> dict[str, Any]:
    """Foldy–Lax's confocal background (the slope's patch, realisation-averaged) split into the first order
    K⁽¹⁾ (`foldy_lax_reference.single_scattering`) and the rest K − K⁽¹⁾, per depth."""
    freqs = data["freqs"]
    v1 = flr.plane_waves(flr.single_scattering(s, data), freqs, s.elements(), sines, s.c0, s.pitch, s.dim)
    args = (freqs, s.elements(), sines, s.c0, s.dim, data["depths"], contrast_half_width(s))
    return {
        "single": bm.confocal_profile(v1, *args, band=s.band).mean(axis=0),
        "multiple": bm.confocal_profile(v_fl - v1, *args, band=s.band).mean(axis=0),
        "focused": focused_orders(s, v_fl, v1, sines, freqs),
        "v1": v1,
    }


def focused_profiles(
    s: flr.Setup, parts: dict[str, np.ndarray], sines: np.ndarray, freqs: np.ndarray
) -> dict[float, dict[str, np.ndarray]]:
    """The focused matrix's profile (`background_metrics.focused_profile`, FOCUSED_SEPARATIONS) of each array in
    `parts` at FOCUSED_DEPTHS (ℓ_s below the surface) above the slab's bottom less a pulse length."""
    seps = np.array(FOCUSED_SEPARATIONS) * s.c0 / s.f_c
    pulse = s.c0 / (2 * (s.band_hi - s.band_lo))
    hw = contrast_half_width(s)
    return {
        zl: {
            name: bm.focused_profile(
                x, freqs, s.elements(), sines, s.c0, s.dim, s.z_surface + zl * s.ls_c, seps, hw, band=s.band
            )
            for name, x in parts.items()
        }
        for zl in FOCUSED_DEPTHS
        if zl * s.ls_c < s.thickness - pulse
    }


def focused_orders(
    s: flr.Setup, v: np.ndarray, v1: np.ndarray, sines: np.ndarray, freqs: np.ndarray
) -> dict[float, tuple[np.ndarray, np.ndarray]]:
    """`focused_profiles` of the first order v1 and of the rest v − v1, as (first, rest) per depth."""
    prof = focused_profiles(s, {"first": v1, "rest": v - v1}, sines, freqs)
    return {zl: (p["first"], p["rest"]) for zl, p in prof.items()}


def compare(
    dim: int,
    quick: bool,
    n_model: int | None,
    layer_kw: dict[str, Any],
    match_dispersion: bool = False,
    slab: bool = False,
    reference: Path | None = None,
) -> dict[str, Any]:
    """Foldy–Lax (`reference`, or the default file of `dim`, made if missing) against the model on its setup;
    the reference's own setup sets the dimension."""
    path = reference or flr.default_path(dim, quick)
    if not path.exists():
        print(f"{path} missing: running the Foldy–Lax reference")
        flr.run(flr.setup_for(dim, quick), path)
    s, data = flr.load(path)
    dim = s.dim
    freqs = data["freqs"]
    if not np.allclose(freqs, s.freqs()):
        raise SystemExit(f"{path}: frequencies differ from the setup's window (stale cache? delete it)")
    if slab:  # the FL medium is a slab: the model's diffusion envelope gets the same bottom and sides
        layer_kw = {**layer_kw, "thickness": s.thickness, "width": s.width}
        print(f"  {dim}D model with the FL slab's {s.thickness * 1e3:.1f} mm thickness, {s.width * 1e3:.0f} mm width")
    if match_dispersion:  # ℓ_s(f) = ℓ_s(f_c) (f/f_c)^(−ls_exponent), fitted on the FL medium's ℓ_s(f)
        expo = dispersion_exponent(s, data)
        layer_kw = {**layer_kw, "ls_exponent": expo, "f_ref": s.f_c}
        print(f"  {dim}D model layer with the FL dispersion: ls_exponent = {expo:.3f}, f_ref = {s.f_c:g} Hz")
    sines = transmit_sines(dim)
    t0 = time.perf_counter()
    v_fl = flr.plane_waves(data["K"], freqs, s.elements(), sines, s.c0, s.pitch, dim)
    n_m = n_model or (24 if dim == 2 else 8)
    t1 = time.perf_counter()
    v_mod, v_mod1 = model_orders(s, sines, n_m, layer_kw)
    t_model = time.perf_counter() - t1
    depths = data["depths"]
    fl = measure(v_fl, s, sines, freqs, depths, fl_echo(data, freqs, s.band))
    fl["orders"] = fl_orders(s, data, v_fl, sines)
    mod = measure(v_mod, s, sines, freqs, depths, model_echo(s, depths, freqs, layer_kw))
    mod["focused_orders"] = focused_orders(s, v_mod, v_mod1, sines, freqs)
    # ℓ_s of the FL medium from its coherent wave at f_c (sanity: input 1.8 mm)
    m_c = int(np.argmin(np.abs(freqs - s.f_c)))
    tb = np.abs(data["T"].mean(axis=0)[m_c])
    sel = (depths > s.z_surface + 0.5e-3) & (depths < s.z_surface + s.thickness - 0.5e-3)
    ls_meas = -0.5 / np.polyfit(depths[sel], np.log(tb[sel]), 1)[0]
    kk = data["K"]
    asym = float(np.abs(kk - np.swapaxes(kk, 2, 3)).max() / np.abs(kk).max())
    return {
        "v_fl": v_fl,
        "asym": asym,
        "setup": s,
        "data": data,
        "fl": fl,
        "model": mod,
        "ls_meas": ls_meas,
        "n_model": n_m,
        "focal_return": bool(layer_kw.get("focal_return", False)),
        "t_model": t_model,
        "t_all": time.perf_counter() - t0,
    }


def figures(res: dict[str, Any]) -> list[tuple[str, float, float, str, bool]]:
    """(name, FL, model, criterion, pass) rows."""
    s: flr.Setup = res["setup"]
    fl, mod = res["fl"], res["model"]
    t = fl["t"]
    rec = (t >= 2 * s.z_surface / s.c0 + 1e-6) & (t <= s.t_end)
    db = 10 * np.log10(mod["env"][rec] / fl["env"][rec])
    dev = float(db[np.argmax(np.abs(db))])
    w_fl, w_mod = float(fl["fc"]["width"]), float(mod["fc"]["width"])
    e_fl, e_mod = float(fl["cbs"]["enhancement_ladder"]), float(mod["cbs"]["enhancement_ladder"])
    k_fl, k_mod = -fl["ci"]["slope"] * s.ls_c, -mod["ci"]["slope"] * s.ls_c
    return [
        ("time envelope: max model/FL (dB)", 0.0, dev, "|dev| <= 3 dB", abs(dev) <= 3.0),
        ("freq. corr. half-width (kHz)", w_fl / 1e3, w_mod / 1e3, "ratio within 30 %", abs(w_mod / w_fl - 1) <= 0.3),
        ("CBS enhancement over the ladder", e_fl, e_mod, "1.7-2.3", 1.7 <= e_mod <= 2.3),
        ("-dlnC_I/dz x l_s", k_fl, k_mod, "1 within 20 %", abs(k_mod - 1) <= 0.2),
    ]


def report(res: dict[str, Any]) -> None:
    s: flr.Setup = res["setup"]
    d = res["data"]
    lam = s.c0 / s.f_c
    print(
        f"\n== {s.dim}D: FL {s.n_real} realisations, N = {d['n_scatterers'].tolist()} scatterers, n = {s.density:.4g} "
        f"m^-{s.dim}, slab {s.width * 1e3:.0f} mm × {s.thickness * 1e3:.1f} mm ({s.thickness / s.ls_c:.1f} ℓ_s) from "
        f"z = {s.z_surface * 1e3:.0f} mm; ℓ_s(f_c) = {s.ls_c * 1e3:.2f} mm (ℓ_s/λ = {s.ls_c / lam:.2f}), measured from "
        f"⟨ψ⟩: {res['ls_meas'] * 1e3:.2f} mm; {d['freqs'].size} frequencies; model {res['n_model']} realisations "
        f"({res['t_model']:.1f} s)"
    )
    print(f"  {'figure':34s} {'FL':>9s} {'model':>9s}  criterion (model)")
    for name, a, b, crit, ok in figures(res):
        print(f"  {name:34s} {a:9.3g} {b:9.3g}  {crit:18s} {'PASS' if ok else 'FAIL'}")
    fl, mod = res["fl"], res["model"]
    t_on = 2 * s.z_surface / s.c0
    marks = t_on + np.array([2, 5, 10, 20, 30, 40, 50]) * 1e-6
    marks = marks[marks <= s.t_end]
    at = [int(np.argmin(np.abs(fl["t"] - tm))) for tm in marks]
    print(
        "  envelope model/FL (dB) at t − t_surface = "
        + ", ".join(
            f"{(tm - t_on) * 1e6:.0f} µs: {10 * np.log10(mod['env'][i] / fl['env'][i]):+.1f}"
            for tm, i in zip(marks, at, strict=True)
        )
    )
    # Before the surface echo less a pulse's and an oblique transmit's lead no path through the medium arrives:
    # there a record holds what its period 1/δf wraps round from late times, and a model's precursor.
    lead = precursor_lead(s, transmit_sines(s.dim))
    t_cut = t_on - lead
    pre = [bm.energy_before(r["t"], r["env"], t_cut) for r in (fl, mod)]
    print(
        f"  energy before t_surface − {lead * 1e6:.1f} µs (no path; the period's wrap-round and any "
        f"precursor), share of the record: FL {pre[0]:.2e}, model {pre[1]:.2e}"
    )
    # The contrast's two terms apart: its slope can agree while its level does not.
    z_ls = (fl["ci"]["depths"] - s.z_surface) / s.ls_c
    at_z = [(m, int(np.argmin(np.abs(z_ls - m)))) for m in (0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0) if m <= z_ls.max()]
    ratio_db = {key: 10 * np.log10(mod["ci"][key] / fl["ci"][key]) for key in ("background", "echo")}
    zf = (fl["ci"]["depths"] >= fl["z_fit"][0]) & (fl["ci"]["depths"] <= fl["z_fit"][1])
    print(
        "  confocal background model/FL (dB) at "
        + ", ".join(f"{m:g} ℓ_s: {ratio_db['background'][i]:+.1f}" for m, i in at_z)
        + f"; mean over the fit {np.mean(ratio_db['background'][zf]):+.1f} (echo: mean "
        f"{np.mean(ratio_db['echo'][zf]):+.1f}, max |·| {np.max(np.abs(ratio_db['echo'][zf])):.1f})"
    )
    print(
        f"  contrast slope × ℓ_s with its jackknife standard error over the realisations: "
        f"FL {-fl['ci']['slope'] * s.ls_c:.2f} ± {fl['ci']['slope_se'] * s.ls_c:.2f}, "
        f"model {-mod['ci']['slope'] * s.ls_c:.2f} ± {mod['ci']['slope_se'] * s.ls_c:.2f}"
    )
    k_fl, k_mod = (-r["ci"]["slope"] * s.ls_c for r in (fl, mod))  # −d ln C_I/dz × ℓ_s
    sigma = float(np.hypot(fl["ci"]["slope_se"], mod["ci"]["slope_se"])) * s.ls_c
    print(f"  contrast slope × ℓ_s, model − FL: {k_mod - k_fl:+.2f} ± {sigma:.2f} ({abs(k_mod - k_fl) / sigma:.1f} σ)")
    z, z_fit, o = res["data"]["depths"], fl["z_fit"], fl["orders"]
    sel = (z >= z_fit[0]) & (z <= z_fit[1])

    def fall(y: np.ndarray) -> float:
        return -float(np.polyfit(z[sel], np.log(y[sel]), 1)[0]) * s.ls_c

    at = [int(np.argmin(np.abs(z - s.z_surface - m * s.ls_c))) for m in (1, 2, 3) if m * s.ls_c <= s.thickness]
    share = o["single"] / (o["single"] + o["multiple"])
    echo = fl["ci"]["echo"]
    print(
        "  FL background by order, first order's share at "
        + ", ".join(f"{(z[i] - s.z_surface) / s.ls_c:.0f} ℓ_s: {share[i]:.2f}" for i in at)
        + f"; fall × ℓ_s over the fit: echo {fall(echo):.2f}, first order {fall(o['single']):.2f}, the rest "
        f"{fall(o['multiple']):.2f}, all {fall(fl['ci']['background']):.2f} (contrast over the rest alone: "
        f"{fall(echo) - fall(o['multiple']):.2f})"
    )
    parts = []
    for a, b in DEPTH_RANGES:
        rng = (s.z_surface + a * s.ls_c, s.z_surface + b * s.ls_c)
        if rng[1] > z_fit[1] + 1e-9 or int(((z >= rng[0]) & (z <= rng[1])).sum()) < 3:
            continue
        (k_f, e_f), (k_m, e_m) = (bm.slope_over(r["ci"], rng) for r in (fl, mod))
        parts.append(
            f"{a:g}–{b:g} ℓ_s FL {-k_f * s.ls_c:.2f} ± {e_f * s.ls_c:.2f}, "
            f"model {-k_m * s.ls_c:.2f} ± {e_m * s.ls_c:.2f}"
        )
    if parts:
        print("  contrast slope × ℓ_s by depth range (inside the fit): " + "; ".join(parts))
    flat = [fl["cbs"]["flatness"], mod["cbs"]["flatness"]]
    e_fl, e_mod = (float(r["cbs"]["enhancement_ladder"]) for r in (fl, mod))
    se_fl, se_mod = (float(r["cbs"]["enhancement_ladder_se"]) for r in (fl, mod))
    sig = float(np.hypot(se_fl, se_mod))
    print(
        f"  CBS over the ladder with its jackknife standard error over the realisations: FL {e_fl:.2f} ± "
        f"{se_fl:.2f}, model {e_mod:.2f} ± {se_mod:.2f}; model − FL {e_mod - e_fl:+.2f} ± {sig:.2f} "
        f"({abs(e_mod - e_fl) / sig:.1f} σ); model − 2.3: {(e_mod - 2.3) / se_mod:+.1f} σ"
    )
    print(
        f"  CBS peak over the mean outside the cone (separable envelope): FL {fl['cbs']['enhancement']:.2f}, "
        f"model {mod['cbs']['enhancement']:.2f}; the ladder extrapolated to q = 0: FL {fl['cbs']['ladder0']:.2f}, "
        f"model {mod['cbs']['ladder0']:.2f}"
    )
    if fl["cbs_age"]:
        print(
            "  CBS enhancement over the ladder by age after the surface echo: "
            + "; ".join(
                f"{a:g}–{b:g} µs FL {fl['cbs_age'][(a, b)][0]:.2f} ± {fl['cbs_age'][(a, b)][1]:.2f}, "
                f"model {mod['cbs_age'][(a, b)][0]:.2f} ± {mod['cbs_age'][(a, b)][1]:.2f}"
                for a, b in fl["cbs_age"]
            )
        )
    if fl["memory"]:
        print(
            "  memory effect C(m transmit steps) by age after the surface echo: "
            + "; ".join(
                f"{a:g}–{b:g} µs FL "
                + "/".join(f"{fl['memory'][(a, b)][m]:.2f}" for m in fl["memory"][(a, b)])
                + " model "
                + "/".join(f"{mod['memory'][(a, b)][m]:.2f}" for m in mod["memory"][(a, b)])
                for a, b in fl["memory"]
            )
            + f" (m = {', '.join(str(m) for m in MEMORY_STEPS)}; independent transmits ≈ 0)"
        )
    if fl["focused"]:
        sep = ", ".join(f"{x:g}" for x in FOCUSED_SEPARATIONS)
        print(f"  focused matrix ⟨|R(x − Δx/2, x + Δx/2)|²⟩ at Δx/λ = {sep} (the confocal image is Δx = 0):")
        for zl, prof in fl["focused"].items():
            fl_db = 10 * np.log10(prof / prof[0])
            ratio = 10 * np.log10(mod["focused"][zl] / prof)
            print(
                f"    {zl:g} ℓ_s: FL dB re Δx = 0 " + " ".join(f"{x:+.1f}" for x in fl_db)
                + "; model/FL dB " + " ".join(f"{x:+.1f}" for x in ratio)
            )  # fmt: skip
    if fl["orders"]["focused"]:
        # With the focal return the beads' grid also carries the orders ≥ 2 whose ends a focus sees (docs/design.md
        # §6.6): the model's grid is then not its first order alone.
        grid = "grid" if res.get("focal_return") else "first"
        print(
            "  the same by order, dB re FL's whole at Δx = 0 (first order: FL's on its redrawn scatterers, the "
            "model's focused speckle; the rest: orders ≥ 2"
            + (
                "; the model's grid: its beads' grid, the first order and the focal return; its rest: the Gaussian "
                "field)"
                if grid == "grid"
                else ")"
            )
            + ":"
        )
        for zl, (f1, fm) in fl["orders"]["focused"].items():
            m1, mm = mod["focused_orders"][zl]
            ref = fl["focused"][zl][0]
            parts = (("FL first", f1), (f"model {grid}", m1), ("FL rest", fm), ("model rest", mm))
            cells = [n + " " + " ".join(f"{10 * np.log10(x / ref):+.1f}" for x in p) for n, p in parts]
            print(f"    {zl:g} ℓ_s: " + "; ".join(cells))
    print(
        f"  CBS profile rms off 1 outside the cone: FL {flat[0]:.2f}, model {flat[1]:.2f}"
        + ("  (> 0.1: envelope not separable, the enhancement is not a cone height)" if max(flat) > 0.1 else "")
    )
    print(
        f"  reciprocity (plane-wave Q vs Q^T): FL {fl['cbs']['reciprocity']:.3f}, "
        f"model {mod['cbs']['reciprocity']:.3f} (FL element basis max|K − Kᵀ|/max|K| = {res['asym']:.1e}); "
        f"contrast fit over z = {res['fl']['z_fit'][0] * 1e3:.1f}-{res['fl']['z_fit'][1] * 1e3:.1f} mm"
    )


def report_orders(res: dict[str, Any], n_real: int) -> None:
    """Foldy–Lax's focused matrix (`focused_profiles`) split into the first order, the second
    (`foldy_lax_reference.double_scattering`) and the rest, on its first `n_real` realisations, in dB re the
    whole at Δx = 0 (resonant scatterers: the orders interfere, so the parts need not add up). The plane waves
    and the first order are `compare`'s."""
    s: flr.Setup = res["setup"]
    data = res["data"]
    sines = transmit_sines(s.dim)
    freqs = data["freqs"]
    n = min(n_real, data["K"].shape[0])
    v, v1 = res["v_fl"][:n], res["fl"]["orders"]["v1"][:n]
    k2 = flr.double_scattering(s, data, n)
    v2 = flr.plane_waves(k2, freqs, s.elements(), sines, s.c0, s.pitch, s.dim)
    parts = {"whole": v, "first": v1, "second": v2, "third and up": v - v1 - v2, "second and up": v - v1}
    sep = ", ".join(f"{x:g}" for x in FOCUSED_SEPARATIONS)
    print(f"  Foldy–Lax's focused matrix by order ({n} realisations), dB re the whole at Δx = 0, Δx/λ = {sep}:")
    for zl, prof in focused_profiles(s, parts, sines, freqs).items():
        ref = prof["whole"][0]
        cells = [name + " " + " ".join(f"{10 * np.log10(x / ref):+.1f}" for x in p) for name, p in prof.items()]
        print(f"    {zl:g} ℓ_s: " + "; ".join(cells))


def plot(results: list[dict[str, Any]], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(len(results), 4, figsize=(18, 4.2 * len(results)), squeeze=False)
    for row, res in zip(axs, results, strict=True):
        s: flr.Setup = res["setup"]
        for key, style, label in (("fl", "k-", "Foldy–Lax"), ("model", "r--", "model")):
            m = res[key]
            row[0].plot(m["t"] * 1e6, 10 * np.log10(np.maximum(m["env"], 1e-30)), style, label=label)
            row[1].plot(
                m["fc"]["dfs"] / 1e3, m["fc"]["corr"], style, label=f"{label}: {m['fc']['width'] / 1e3:.0f} kHz"
            )
            row[2].plot(
                m["cbs"]["q"], m["cbs"]["profile"], style + "o", ms=3, label=f"{label}: {m['cbs']['enhancement']:.2f}"
            )
            ci = m["ci"]
            z = (ci["depths"] - s.z_surface) / s.ls_c
            row[3].plot(z, np.log(ci["ci"] / ci["ci"][0]), style, label=f"{label}: {-ci['slope'] * s.ls_c:.2f}/ℓ_s")
        row[0].set(xlabel="t (µs)", ylabel="⟨r²⟩ (dB re pulse peak²)", title=f"{s.dim}D time envelope")
        t_on = 2 * s.z_surface / s.c0 * 1e6
        row[0].set_xlim(0, s.t_end * 1e6 + 10)
        ymax = 10 * np.log10(res["fl"]["env"].max())
        row[0].set_ylim(ymax - 70, ymax + 5)
        row[0].axvline(t_on, color="0.6", lw=0.8)
        row[1].axhline(0.5, color="0.6", lw=0.8)
        row[1].set(xlabel="Δf (kHz)", ylabel="|C(Δf)|", title="frequency correlation", xlim=(0, 300))
        row[2].axhline(1.0, color="0.6", lw=0.8)
        row[2].set(xlabel="|b + a| (sine)", ylabel="⟨|R|²⟩ / envelope", title="coherent backscattering")
        zf = [(zz - s.z_surface) / s.ls_c for zz in res["fl"]["z_fit"]]
        row[3].axvspan(*zf, color="0.9")
        zz = np.linspace(0, s.thickness / s.ls_c, 2)
        row[3].plot(zz, -zz, ":", color="0.4", label="e^{-z/ℓ_s}")
        row[3].set(xlabel="(z − z_s)/ℓ_s", ylabel="ln C_I (normalised)", title="confocal contrast")
        for ax in row:
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=90)


def parse_layer(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for it in items:
        key, sep, val = it.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"--layer: expected KEY=VALUE (a ScatteringLayer field), got {it!r}")
        try:
            out[key] = ast.literal_eval(val)
        except (ValueError, SyntaxError):
            out[key] = val
    return out


def model_commit() -> str:
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True)
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "fpcore/simulate"], capture_output=True, text=True, check=True
        )
        return rev.stdout.strip() + (" + uncommitted fpcore/simulate changes" if dirty.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dim", choices=("2", "3", "both"), default="2")
    ap.add_argument("--quick", action="store_true", help="use (or make) the quick FL references")
    ap.add_argument("--model-realisations", type=int, default=None, help="default 24 (2D), 8 (3D)")
    ap.add_argument("--layer", action="append", default=[], help="extra ScatteringLayer field KEY=VALUE")
    ap.add_argument(
        "--match-dispersion", action="store_true", help="give the model the FL medium's ℓ_s(f) (ls_exponent, f_ref)"
    )
    ap.add_argument(
        "--slab",
        action="store_true",
        help="give the model the FL slab's thickness and width (the diffusion envelope with the images of its "
        "bottom and sides)",
    )
    ap.add_argument(
        "--ss-directions",
        type=int,
        default=None,
        help="cap on the single scattering's output directions in 3D (default: the simulator's, "
        "fpcore.simulate.single_scattering.MAX_DIRECTIONS; 0: none, the grid its margin asks for)",
    )
    ap.add_argument(
        "--reference",
        default=None,
        help="a Foldy–Lax reference file (foldy_lax_reference.py --out), instead of the default one; its setup "
        "sets the dimension",
    )
    ap.add_argument(
        "--double-scattering",
        type=int,
        default=0,
        metavar="N",
        help="also split Foldy–Lax's focused matrix into the first, second and higher orders on its first N "
        "realisations (foldy_lax_reference.double_scattering; about a minute per 2-D realisation)",
    )
    ap.add_argument("--png", default="out/bench/validate_background.png")
    args = ap.parse_args(argv)
    ref = Path(args.reference) if args.reference else None
    if ref is not None and not ref.exists():
        print(f"--reference: {ref} does not exist (make it with bench/foldy_lax_reference.py --out)", file=sys.stderr)
        return 2
    try:
        layer_kw = parse_layer(args.layer)
        ScatteringLayer(z_surface=5e-3, ls=1.8e-3, **layer_kw)
    except (TypeError, ValueError) as exc:
        print(f"--layer: {exc}", file=sys.stderr)
        return 2
    if args.double_scattering < 0:
        print(f"--double-scattering: expected an integer >= 0, got {args.double_scattering}", file=sys.stderr)
        return 2
    if args.model_realisations is not None and args.model_realisations < 1:
        print(f"--model-realisations: expected an integer >= 1, got {args.model_realisations}", file=sys.stderr)
        return 2
    if args.ss_directions is not None:
        if args.ss_directions < 0:
            print(f"--ss-directions: expected an integer >= 0, got {args.ss_directions}", file=sys.stderr)
            return 2
        ss_mod.MAX_DIRECTIONS = args.ss_directions or 10**9
    print(f"model: fpcore.simulate.medium at {model_commit()}; layer options {layer_kw or 'none (defaults)'}")
    print(f"  single scattering: at most {ss_mod.MAX_DIRECTIONS} output directions in 3D")
    results = []
    # with --reference, one comparison: its file's setup sets the dimension (`compare`)
    dims = (2,) if ref is not None else (2, 3) if args.dim == "both" else (int(args.dim),)
    for dim in dims:
        res = compare(dim, args.quick, args.model_realisations, layer_kw, args.match_dispersion, args.slab, ref)
        report(res)
        if args.double_scattering:
            report_orders(res, args.double_scattering)
        results.append(res)
    plot(results, Path(args.png))
    print(f"\nwrote {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
