"""Transport Monte Carlo of the multiple scattering (fpcore.simulate.paths) on the Foldy–Lax reference's rig:
an independent check of what the statistical background gets right and wrong (docs/design.md §6.6).

    .venv/bin/python bench/transport_paths.py                                  # 2-D reference, 6 × 3000 walks
    .venv/bin/python bench/transport_paths.py --reference out/bench/fl_reference_3d_deep.npz --walks 6000
    .venv/bin/python bench/transport_paths.py --reference out/bench/fl_reference_3d_deep.npz --walks 6000 --beams
    .venv/bin/python bench/transport_paths.py --reuse --focal-split --model-realisations 12   # the focal return, split
    .venv/bin/python bench/transport_paths.py --scenario --walks 8000  # the headline rig's exact paths, 6 × 8000 walks
    .venv/bin/python bench/transport_paths.py --scenario --reuse --realisations 12 --walks 8000   # the saved 6, + 6

The paths are drawn in the reference's slab (same ℓ_s(f) per frequency, lossless), their legs to the
elements through the coherent wave along each straight ray, the transmits synthesised from the elements as
the probe fires them (`foldy_lax_reference.plane_waves`' weights). Printed side by side for Foldy–Lax, the
paths and the model (`validate_background.model_orders`, the default layer with --slab): the focused
matrix's profile against the in–out separation of the orders ≥ 2 at 1–4 ℓ_s, the confocal background of the
orders ≥ 2 by depth, and the four agreement figures of the issue (`validate_background.measure`) on the
paths' field (their own first order plus the orders ≥ 2). With --beams (3-D): the paths' first order lit by the
transmits the array synthesises against the same lit by the speckle's model beam (`PlaneWaveBeams`, the simulator's
`single_scattering` beam), confocal, by depth. With --focal-split: the model with the focal return split into the
focal return alone and the Gaussian field it keeps, against Foldy–Lax, the paths and the default Gaussian field.
With --scenario (the sinking-sphere rig; --full the 32×32 array): the paths lit by the simulator's beams
(`PlaneWaveBeams`) and, with the same walks, by the transmits the elements synthesise (`Synthesised`), each set saved;
the confocal fog by depth, the point target's contrast slope (paired by realisation), the CBS by age with each fog's
plane-wave symmetry (only the synthesised paths are reciprocal as the array measures them: the CBS's reference), and
the time envelopes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import background_metrics as bm  # noqa: E402
import foldy_lax_reference as flr  # noqa: E402
import validate_background as vb  # noqa: E402

from fpcore.simulate.paths import (  # noqa: E402
    Paths,
    PlaneWaveBeams,
    StraightRays,
    Synthesised,
    draw_paths,
    path_spectra,
)


def slab_paths(s: flr.Setup, n_walks: int, rng: np.random.Generator) -> Paths:
    """Walks filling the reference's slab (first scatterings uniform in it), cut at the record's end."""
    return draw_paths(
        rng,
        s.dim,
        s.ls_c,
        n_walks,
        l_max=s.c0 * s.t_end,
        z_top=s.z_surface,
        start_half_width=s.width / 2,
        start_depth=s.thickness,
        thickness=s.thickness,
        half_width=s.width / 2,
    )


def path_realisations(
    s: flr.Setup, data: dict[str, np.ndarray], sines: np.ndarray, n_real: int, n_walks: int, seed: int = 2000
) -> tuple[np.ndarray, np.ndarray]:
    """(orders ≥ 2, first order), each (n_real, N_f, N_u, N_θ), one path draw per realisation."""
    rays = StraightRays(s.elements(), s.z_surface, s.dim)
    tx = Synthesised(sines, s.pitch)
    multi, first = [], []
    t0 = time.perf_counter()
    for r in range(n_real):
        p = slab_paths(s, n_walks, np.random.default_rng(seed + r))
        multi.append(path_spectra(p, data["freqs"], s.c0, data["ls"], rays, tx))
        first.append(path_spectra(p, data["freqs"], s.c0, data["ls"], rays, tx, first_order=True))
        print(f"  paths {r + 1}/{n_real}: {p.n_walks} walks, {p.n_paths} path ends, {time.perf_counter() - t0:.0f} s")
    return np.stack(multi), np.stack(first)


def beam_check(s: flr.Setup, data: dict[str, np.ndarray], sines: np.ndarray, n_real: int, n_walks: int) -> None:
    """The speckle's model beam against the synthesised transmits: the paths' first order lit by each (the same
    walks, the same receive legs), its confocal intensity at 1–4 ℓ_s, model beam / synthesised in dB."""
    freqs = data["freqs"]
    rays = StraightRays(s.elements(), s.z_surface, s.dim)
    beams = PlaneWaveBeams(sines, s.n_side * s.pitch, s.z_surface, s.c0 / s.f_c)
    lit: dict[str, list[np.ndarray]] = {"synthesised": [], "model beam": []}
    for r in range(n_real):
        p = slab_paths(s, n_walks, np.random.default_rng(9000 + r))
        for name, tx in (("synthesised", Synthesised(sines, s.pitch)), ("model beam", beams)):
            lit[name].append(path_spectra(p, freqs, s.c0, data["ls"], rays, tx, first_order=True))
        print(f"  first orders {r + 1}/{n_real}")
    depths = s.z_surface + np.arange(1, 5) * s.ls_c
    conf = {
        n: bm.confocal_profile(
            np.stack(v), freqs, s.elements(), sines, s.c0, s.dim, depths, vb.contrast_half_width(s), band=s.band
        ).mean(axis=0)
        for n, v in lit.items()
    }
    ratio = db(conf["model beam"] / conf["synthesised"])
    print(
        "the paths' first order lit by the model beam / by the synthesised transmits at 1 … 4 ℓ_s (dB): "
        + " / ".join(f"{x:+.1f}" for x in ratio)
    )


def focal_split(
    s: flr.Setup, data: dict[str, np.ndarray], sines: np.ndarray, parts: dict[str, np.ndarray], layer_kw: dict[str, Any]
) -> None:
    """Where the focal return's excess comes from (docs/design.md §6.6): the model with focal_return=True split into
    the focal return alone (the beads' reflectivity zero, `SingleScatteringField.draw_beads`) and the Gaussian field it
    keeps, against Foldy–Lax's orders ≥ 2, the paths and the default Gaussian field (`parts`: "FL", "paths", "model"),
    the same seeds as the default model. Printed: the confocal background by depth and the focused matrix's profile
    against the in–out separation, dB re Foldy–Lax, and the element-averaged envelopes."""
    freqs = data["freqs"]
    n_real = parts["model"].shape[0]
    # vb.model_orders' seeds: the default's Gaussian noise
    whole, alone = vb.model_orders(s, sines, n_real, {**layer_kw, "focal_return": True}, beads=False)
    kept = whole - alone
    split = {
        "FL": parts["FL"],
        "paths": parts["paths"],
        "GF": parts["model"],
        "GF kept": kept,
        "FR alone": alone,
    }
    depths = data["depths"]
    args_c = (freqs, s.elements(), sines, s.c0, s.dim, depths, vb.contrast_half_width(s))
    conf = {n: bm.confocal_profile(v, *args_c, band=s.band).mean(axis=0) for n, v in split.items()}
    conf["GF kept + FR"] = conf["GF kept"] + conf["FR alone"]
    names = [n for n in conf if n != "FL"]
    print("\nthe focal return split: confocal background of the orders ≥ 2 by depth, dB re Foldy–Lax")
    print("  depth    " + "  ".join(f"{n:>12}" for n in names))
    fit = []
    for j, z in enumerate(depths - s.z_surface):
        zl = z / s.ls_c
        if 0.4 <= zl <= 5.1:
            row = [float(db(conf[n][j] / conf["FL"][j])) for n in names]
            if zl >= 0.95:
                fit.append(row)
            print(f"  {zl:4.1f} ℓ_s " + "  ".join(f"{v:+12.1f}" for v in row))
    print("  mean 1–5 ℓ_s " + "  ".join(f"{n} {v:+.1f}" for n, v in zip(names, np.mean(fit, axis=0), strict=True)))
    prof = vb.focused_profiles(s, split, sines, freqs)
    print(
        "focused matrix, dB re Foldy–Lax's orders ≥ 2 at Δx = 0; Δx (λ): " + " ".join(map(str, vb.FOCUSED_SEPARATIONS))
    )
    for zl, p in prof.items():
        for name in split:
            print(f"  {zl:.0f} ℓ_s {name:9s} " + " ".join(f"{v:6.1f}" for v in db(p[name] / p["FL"][0])))
    t, e_gf = bm.time_envelope(split["GF"], freqs, s.band)
    t_on = 2 * s.z_surface / s.c0
    idx = [int(np.argmin(np.abs(t - t_on - tt * 1e-6))) for tt in (2, 5, 10, 20, 30)]
    print("element-averaged envelope re the default Gaussian field at +2 / 5 / 10 / 20 / 30 µs (dB):")
    for name in ("FL", "paths", "GF kept", "FR alone"):
        e = bm.time_envelope(split[name], freqs, s.band)[1]
        print(f"  {name:9s} " + " / ".join(f"{float(db(e[i] / e_gf[i])):+.1f}" for i in idx))


def headline(quick: bool, n_real: int, n_walks: int, layer_kw: dict[str, Any], reuse: bool = False) -> None:
    """The sinking-sphere rig: the paths' orders ≥ 2 against the model's Gaussian field, on its own medium
    (ℓ_s(f), ℓ_a, the interface), by depth, and what that does to the spheres' confocal contrast. `layer_kw`
    changes the model's layer (e.g. focal_return=True); with `reuse`, the paths saved by an earlier run."""
    import fpcore.simulate as sim

    sc = sim.scenario("sinking-sphere", quick=quick, n_frames=1)
    layer = sc.layer
    assert layer is not None
    el, sines, freqs = sc.probe.positions, sc.sequence.sines, sc.freqs
    aperture = float(np.sqrt(np.prod(sc.probe.aperture)))
    t_leg = float(np.sqrt(1.0 - layer.reflection(sc.rho0, sc.c0) ** 2))  # the interface, one way
    rays = StraightRays(el, layer.z_surface, 3, t_leg)
    tx = PlaneWaveBeams(sines, aperture, layer.z_surface, sc.c0 / sc.pulse.centre, t_leg)
    ls_f = np.asarray(layer.ls_at(freqs))
    t_end = sc.window.t0 + sc.window.duration
    l_max = sc.c0 * t_end - 2 * layer.z_surface
    reach = 0.5 * aperture + 20e-3 * float(np.max(np.abs(sines) / np.sqrt(1 - (sines**2).sum(1))[:, None])) + 5e-3
    lext_c = float(layer.l_ext_at(2.2e6))
    t0 = time.perf_counter()

    def path_set(tag: str, transmits: PlaneWaveBeams | Synthesised) -> np.ndarray:
        """n_real realisations of the paths' field with these transmits, saved (and with `reuse`, loaded and
        extended): seeds 3000 + r, n_walks walks each."""
        saved = flr.OUT / f"paths_headline_{'quick' if quick else 'full'}{tag}.npz"
        v_p: list[np.ndarray] = []
        if reuse and saved.exists():
            with np.load(saved) as z:
                v_p = list(z["paths"][:n_real])
                saved_walks = int(z["walks"]) if "walks" in z.files else None
            each = f" ({saved_walks} walks each)" if saved_walks else ""
            print(f"  paths: {len(v_p)} realisations from {saved}{each}")
            if len(v_p) < n_real and saved_walks not in (None, n_walks):
                raise SystemExit(f"--walks: the saved realisations have {saved_walks} walks each, got {n_walks}")
        n_drawn = n_real - len(v_p)
        for r in range(len(v_p), n_real):
            p = draw_paths(
                np.random.default_rng(3000 + r),
                3,
                float(layer.ls_at(2.2e6)),
                n_walks,
                l_max,
                layer.z_surface,
                start_half_width=reach,
                start_depth=12 * lext_c,
                start_decay=lext_c,
            )
            v_p.append(path_spectra(p, freqs, sc.c0, ls_f, rays, transmits, la=layer.la))
            print(
                f"  paths{tag} {r + 1}/{n_real}: {p.n_walks} walks, {p.n_paths} path ends, "
                f"{time.perf_counter() - t0:.0f} s"
            )
        out = np.stack(v_p)
        if n_drawn > 0:  # a fresh set, or the saved one extended (its seeds, then the new)
            flr.OUT.mkdir(parents=True, exist_ok=True)
            np.savez(saved, freqs=freqs, paths=out, walks=n_walks)
        return out

    parts = {"paths": path_set("", tx)}
    # The same walks with the transmits synthesised by the elements as the probe fires them: reciprocal as the array
    # measures it, the CBS's reference (the beams above are the simulator's own model of a transmit, not the receive's
    # functions, so their retro-reflected element is no diagonal one: their plane-wave symmetry is 0.77–0.83).
    synthesised = path_set("_synthesised", Synthesised(sines, sc.probe.pitch))
    models = {"model": sc}
    if layer_kw:
        models["model+"] = sim.scenario("sinking-sphere", quick=quick, n_frames=1, **layer_kw)
    for name, scen in models.items():  # the same seeds: the same beads and Gaussian field in each
        bg = scen.without_targets()._background()
        assert bg is not None
        orders = [bg.fork(np.random.default_rng(4000 + r)).next_orders() for r in range(n_real)]
        parts[name] = np.stack([m for m, _ in orders])
        parts[name + " first"] = np.stack([f for _, f in orders])
    # The paths' first order is the beads' speckle alone, the same seeds' beads drawn by the scenario without its
    # focal return: the default's grid holds the orders ≥ 2 too (F6 of docs/design.md §6.6), which the paths carry.
    bg = sim.scenario("sinking-sphere", quick=quick, n_frames=1, focal_return=False).without_targets()._background()
    assert bg is not None
    speckle = [bg.fork(np.random.default_rng(4000 + r)).next_orders()[1] for r in range(n_real)]
    assert all(x is not None for x in speckle)
    parts["speckle"] = np.stack(speckle)
    depths = layer.z_surface + np.arange(1, 9) * layer.ls
    conf = {
        name: bm.confocal_profile(v, freqs, el, sines, sc.c0, 3, depths, 5e-3, n_lateral=7, band=sc.pulse).mean(axis=0)
        for name, v in parts.items()
    }
    # the fogs: the beads' speckle (the model's first order alone) plus the paths; each model's own whole
    fogs = {"paths": conf["speckle"] + conf["paths"]}
    fogs.update({n: conf[n] + conf[n + " first"] for n in models})
    print(f"\nsinking-sphere ({'quick' if quick else 'full'}): confocal background by depth (patch ±5 mm), dB")
    print(
        "  depth  GF/paths (orders ≥ 2)  grid/paths (beads, with the focal return if on)  beads/paths  "
        + "  ".join(f"fog {n}/paths" for n in models)
    )
    for j, z in enumerate(depths - layer.z_surface):
        print(
            f"  {z / layer.ls:3.0f} ℓ_s  {db(conf['model'][j] / conf['paths'][j]):+6.1f}"
            f"  {db(conf['model first'][j] / conf['paths'][j]):+6.1f}"
            f"  {db(conf['speckle'][j] / conf['paths'][j]):+6.1f}  "
            + "  ".join(f"{db(fogs[n][j] / fogs['paths'][j]):+6.1f}" for n in models)
        )
    # The transmits as the array synthesises them against the beams (the simulator's transmit model), the same walks
    conf_syn = bm.confocal_profile(synthesised, freqs, el, sines, sc.c0, 3, depths, 5e-3, n_lateral=7, band=sc.pulse)
    print(
        "  the paths' orders ≥ 2 with the transmits synthesised by the elements / with the beams at 1 … 8 ℓ_s (dB): "
        + " / ".join(f"{db(a / b):+.1f}" for a, b in zip(conf_syn.mean(axis=0), conf["paths"], strict=True))
    )
    contrast_slopes(sc, {**parts, "synthesised": synthesised})
    split = {"paths, orders ≥ 2": parts["paths"], "paths synthesised, orders ≥ 2": synthesised}
    split["paths synthesised + beads"] = synthesised + parts["speckle"]
    split.update({"model, Gaussian field": parts["model"], "model, beads' grid": parts["model first"]})
    cbs_check(sc, {**fogs_of(parts, models), **split})
    cbs_by_band(sc, {"paths synthesised, orders ≥ 2": synthesised, "paths, orders ≥ 2": parts["paths"]})
    # The fogs' time envelopes (a changed model's beads are drawn on its own grid: only its whole fog compares)
    t, e_p = bm.time_envelope(parts["paths"] + parts["speckle"], freqs, sc.pulse)
    env = {n: bm.time_envelope(parts[n] + parts[n + " first"], freqs, sc.pulse)[1] for n in models}
    t_on = 2 * layer.z_surface / sc.c0
    env["paths synthesised"] = bm.time_envelope(synthesised + parts["speckle"], freqs, sc.pulse)[1]
    print("  time envelope of the fog (the beads' speckle and the orders ≥ 2), each / the paths' (dB):")
    for tt in (1, 2, 5, 10, 20, 30, 40, 50):
        i = int(np.argmin(np.abs(t - t_on - tt * 1e-6)))
        print(f"    +{tt:2d} µs: " + "  ".join(f"{n} {db(e[i] / e_p[i]):+5.1f}" for n, e in env.items()))


def contrast_slopes(sc: Any, parts: dict[str, np.ndarray]) -> None:
    """The confocal contrast of a point target on the axis at 1–5 ℓ_s (`validate_simulate`'s measure) over the
    fog of the model (speckle + Gaussian field) and over the fog of the paths (speckle + paths): −d ln C_I/dz ×
    ℓ_s(f_c), the paper's eq. (1) law, with the jackknife over realisations."""
    import validate_simulate as vs

    layer, band = sc.layer, sc.pulse
    freqs = sc.freqs
    g = np.linspace(-0.45, 0.45, 13)
    s_out = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    ls_c = float(layer.ls_at(band.centre))
    depths = np.arange(1, 6) * ls_c
    spec = band.spectrum(freqs)
    fogs = {"paths (the beads' speckle + the paths)": parts["speckle"] + parts["paths"]}
    for name in ("model", "model+"):
        if name in parts:
            fogs[f"{name} (its own fog)"] = parts[name + " first"] + parts[name]
    if "synthesised" in parts:  # the same paths, the transmits synthesised by the elements
        fogs["paths synthesised (the beads' speckle + the paths)"] = parts["speckle"] + parts["synthesised"]
    per_fog: dict[str, np.ndarray] = {}
    for name, fog in fogs.items():
        i_t, water, m = vs._point_target_and_fog(
            layer, sc.probe, sc.sequence.sines, freqs, sc.c0, spec, s_out, list(fog), depths, 3
        )
        e = i_t / water
        per_fog[name] = m

        def slope(fog_mean: np.ndarray, e: np.ndarray = e) -> float:
            return -float(np.polyfit(depths, np.log(e / fog_mean), 1)[0]) * ls_c

        k, se = slope(m.mean(axis=1)), bm.jackknife_se(slope, m.T)
        print(
            f"  contrast slope over 1–5 ℓ_s, {name}: −d ln C_I/dz × ℓ_s = {k:.2f} ± {se:.2f}; "
            f"fog at 2…5 ℓ_s re 1 ℓ_s: "
            + ", ".join(f"{db(m[j].mean() / m[0].mean()):+.1f}" for j in range(1, 5))
            + " dB"
        )
    # The model's slope minus the paths', paired by realisation: the two fogs share the beads' speckle of each seed,
    # so their difference is surer than the two errors above added (the echo e is the same target in both).
    ref = per_fog.pop(next(iter(fogs)))
    for name, m in per_fog.items():
        if m.shape != ref.shape:
            continue

        def difference(both: np.ndarray) -> float:
            fog_m, fog_p = both[: depths.size], both[depths.size :]  # the model's, the paths' (N_z,) each
            return float(np.polyfit(depths, np.log(fog_m / fog_p), 1)[0]) * ls_c

        both = np.concatenate([m, ref], axis=0).T  # (n_real, 2 N_z)
        d, se = difference(both.mean(axis=0)), bm.jackknife_se(difference, both)
        print(f"  slope {name} − paths, paired by realisation: {d:+.2f} ± {se:.2f}")


def fogs_of(parts: dict[str, np.ndarray], models: dict[str, Any]) -> dict[str, np.ndarray]:
    """The whole fogs' spectra (n_real, N_f, N_u, N_θ): the paths' (the beads' speckle and the paths) and each
    model's own (its beads' grid and its Gaussian field)."""
    out = {"paths": parts["speckle"] + parts["paths"]}
    out.update({n: parts[n + " first"] + parts[n] for n in models})
    return out


def cbs_q_out(sc: Any) -> float:
    """The CBS's ladder bound for a scenario's array (`background_metrics.cbs_ladder_bound`)."""
    return bm.cbs_ladder_bound(sc.c0 / sc.pulse.centre, float(np.sqrt(np.prod(sc.probe.aperture))))


#: The CBS's gates, µs after the surface echo (`validate_background.cbs_by_age`'s).
CBS_AGES = ((5.0, 10.0), (10.0, 20.0), (20.0, 30.0), (5.0, np.inf))


def cbs_check(sc: Any, fogs: dict[str, np.ndarray]) -> None:
    """The coherent-backscattering enhancement over the ladder (`background_metrics.cbs_enhancement`) of each of
    `fogs` (spectra (n_real, N_f, N_u, N_θ): the exact paths' fog, each model's, and any of their parts), by age
    after the surface echo, with jackknife errors: the issue's third figure in the headline rig itself, where the
    Foldy–Lax slab's 4 mm array is not the rig."""
    layer = sc.layer
    el, sines, freqs = sc.probe.positions, sc.sequence.sines, sc.freqs
    t_on = 2 * layer.z_surface / sc.c0
    t_end = sc.window.t0 + sc.window.duration
    q_out = cbs_q_out(sc)
    print(f"  CBS over the ladder by age after the surface echo (|b + a| > {q_out:.2f} the ladder), ± jackknife:")
    print(" " * 35 + " | ".join(f"{a:.0f}–{b:.0f} µs" for a, b in CBS_AGES) + "   (symmetry over the last gate)")
    for name, v in fogs.items():
        row = []
        for a, b in CBS_AGES:
            gate = (t_on + a * 1e-6, min(t_on + b * 1e-6, t_end))
            c = bm.cbs_enhancement(v, freqs, el, sines, sc.c0, 3, gate=gate, q_out=q_out)
            row.append(f"{c['enhancement_ladder']:.2f} ± {c['enhancement_ladder_se']:.2f}")
        print(f"    {name:30s} " + " | ".join(row) + f"   symmetry {c['reciprocity']:.3f}")


#: Thirds of the band for `cbs_by_band` (Hz): the quick array's grating lobes propagate in the top one.
CBS_BANDS = ((1.4e6, 1.8e6), (1.8e6, 2.4e6), (2.4e6, 3.0e6))


def cbs_by_band(sc: Any, fogs: dict[str, np.ndarray], age: tuple[float, float] = (10.0, 20.0)) -> None:
    """The CBS over the ladder at one age, in thirds of the band, for each of `fogs`: an array of pitch p has
    grating lobes only where λ < p(1 + |s|) (the quick rig's 0.68 mm: above 1.84 MHz for its most steered transmit,
    and propagating at less than grazing from about 2.4 MHz), so a retro peak made by them shows in the top third."""
    el, sines, freqs = sc.probe.positions, sc.sequence.sines, sc.freqs
    t_on = 2 * sc.layer.z_surface / sc.c0
    gate = (t_on + age[0] * 1e-6, t_on + age[1] * 1e-6)
    print(f"  CBS over the ladder at {age[0]:.0f}–{age[1]:.0f} µs by band, and the plane-wave symmetry:")
    for name, v in fogs.items():
        row = []
        for lo, hi in CBS_BANDS:
            m = (freqs >= lo) & (freqs < hi)
            c = bm.cbs_enhancement(v[:, m], freqs[m], el, sines, sc.c0, 3, gate=gate, q_out=cbs_q_out(sc))
            row.append(f"{lo / 1e6:.1f}–{hi / 1e6:.1f} MHz {c['enhancement_ladder']:.2f} ({c['reciprocity']:.2f})")
        print(f"    {name:30s} " + " | ".join(row))


def db(x: np.ndarray) -> np.ndarray:
    return 10 * np.log10(np.maximum(x, 1e-300))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference", type=Path, default=flr.default_path(2, False))
    ap.add_argument("--walks", type=int, default=3000, help="walks per realisation")
    ap.add_argument("--realisations", type=int, default=6)
    ap.add_argument("--model-realisations", type=int, default=8)
    ap.add_argument("--scenario", action="store_true", help="the sinking-sphere rig instead of a Foldy–Lax one")
    ap.add_argument("--full", action="store_true", help="with --scenario: the full 32×32 array")
    ap.add_argument("--layer", action="append", default=[], help="with --scenario: the model layer's KEY=VALUE")
    ap.add_argument("--reuse", action="store_true", help="the paths saved by an earlier run")
    ap.add_argument("--beams", action="store_true", help="3-D reference only: the model beam against the synthesised")
    ap.add_argument(
        "--focal-split", action="store_true", help="the focal return alone and the Gaussian field it keeps (§6.6)"
    )
    args = ap.parse_args(argv)
    if args.scenario:
        headline(not args.full, args.realisations, args.walks, vb.parse_layer(args.layer), args.reuse)
        return 0
    if not args.reference.exists():
        print(f"--reference: expected a Foldy–Lax file (bench/foldy_lax_reference.py), got {args.reference}")
        return 2
    s, data = flr.load(args.reference)
    freqs, sines = data["freqs"], vb.transmit_sines(s.dim)
    if args.beams:
        if s.dim != 3:
            print(f"--beams: expected a 3-D reference (the model beam is 3-D), got a {s.dim}-D one")
            return 2
        beam_check(s, data, sines, args.realisations, args.walks)
        return 0
    v_fl = flr.plane_waves(data["K"], freqs, s.elements(), sines, s.c0, s.pitch, s.dim)
    v_fl1 = flr.plane_waves(flr.single_scattering(s, data), freqs, s.elements(), sines, s.c0, s.pitch, s.dim)
    saved = flr.OUT / f"paths_{args.reference.stem}.npz"
    if args.reuse and saved.exists():
        with np.load(saved) as z:
            v_p, v_p1 = z["paths"], z["paths1"]
        print(f"  paths: {v_p.shape[0]} realisations from {saved}")
    else:
        v_p, v_p1 = path_realisations(s, data, sines, args.realisations, args.walks)
        np.savez(saved, paths=v_p, paths1=v_p1)
    expo = -float(np.polyfit(np.log(freqs / s.f_c), np.log(data["ls"]), 1)[0])
    layer_kw: dict[str, Any] = dict(
        envelope="diffusion",
        cbs=True,
        single_scattering="field",
        angular="halo",
        ls_exponent=round(expo, 3),
        f_ref=s.f_c,
        thickness=s.thickness,
        width=s.width,
    )
    v_m, v_m1 = vb.model_orders(s, sines, args.model_realisations, layer_kw)
    parts = {"FL": v_fl - v_fl1, "paths": v_p, "model": v_m - v_m1, "FL1": v_fl1, "paths1": v_p1, "model1": v_m1}
    overrides = vb.parse_layer(args.layer)
    if overrides:  # the same seeds draw the same beads: the changed model's orders ≥ 2 are V − the default's first
        v_x, _ = vb.model_orders(s, sines, args.model_realisations, {**layer_kw, **overrides})
        parts["model+"] = v_x - v_m1
        print(f"  model+: the default layer with {overrides}")
    if args.focal_split:
        focal_split(s, data, sines, parts, layer_kw)
        return 0
    prof = vb.focused_profiles(s, parts, sines, freqs)
    print(f"\n{s.dim}-D: focused matrix ⟨|R(x − Δx/2, x + Δx/2)|²⟩, dB re Foldy–Lax's orders ≥ 2 at Δx = 0")
    print("Δx (λ):        " + " ".join(f"{x:6.1f}" for x in vb.FOCUSED_SEPARATIONS))
    for zl, p in prof.items():
        ref = p["FL"][0]
        for name in parts:
            print(f"{zl:.0f} ℓ_s {name:7s} " + " ".join(f"{v:6.1f}" for v in db(p[name] / ref)))
    half = vb.contrast_half_width(s)
    depths = data["depths"]
    args_c = (freqs, s.elements(), sines, s.c0, s.dim, depths, half)
    multi = [n for n in ("FL", "paths", "model", "model+") if n in parts]
    conf = {n: bm.confocal_profile(parts[n], *args_c, band=s.band).mean(axis=0) for n in multi}
    print("\nconfocal background of the orders ≥ 2 (dB re Foldy–Lax) by depth below the surface:")
    for j, z in enumerate(depths - s.z_surface):
        zl = z / s.ls_c
        if 0.4 <= zl <= 5.1:
            print(
                f"  {zl:4.1f} ℓ_s: "
                + "  ".join(f"{n} {float(db(conf[n][j] / conf['FL'][j])):+5.1f}" for n in multi[1:])
            )
    t, e_fl = bm.time_envelope(v_fl - v_fl1, freqs, s.band)
    _, e_p = bm.time_envelope(v_p, freqs, s.band)
    _, e_m = bm.time_envelope(v_m - v_m1, freqs, s.band)
    t_on = 2 * s.z_surface / s.c0
    print("\ntime envelope of the orders ≥ 2 (dB re Foldy–Lax):")
    for tt in (1, 2, 5, 10, 20, 30, 40):
        i = int(np.argmin(np.abs(t - t_on - tt * 1e-6)))
        if t[i] < s.t_end:
            print(f"  +{tt:2d} µs: paths {db(e_p[i] / e_fl[i]):+5.1f}  model {db(e_m[i] / e_fl[i]):+5.1f}")
    echo = vb.fl_echo(data, freqs, s.band)
    res = vb.measure(v_p + v_p1, s, sines, freqs, depths, echo)
    fl = vb.measure(v_fl, s, sines, freqs, depths, echo)
    print("\nthe four figures, paths (own first order + orders ≥ 2) against Foldy–Lax:")
    for name, get in (
        ("frequency-correlation half-width (kHz)", lambda x: float(x["fc"]["width"]) / 1e3),
        ("CBS over the ladder", lambda x: float(x["cbs"]["enhancement_ladder"])),
        ("contrast slope × ℓ_s", lambda x: -float(x["ci"]["slope"]) * s.ls_c),
    ):
        print(f"  {name}: paths {get(res):.2f}, Foldy–Lax {get(fl):.2f}")
    print(
        f"  CBS's jackknife standard error over the realisations: paths ±{res['cbs']['enhancement_ladder_se']:.2f}, "
        f"Foldy–Lax ±{fl['cbs']['enhancement_ladder_se']:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
