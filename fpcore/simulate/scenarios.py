"""Ready-made acquisition scenarios with ground truth travelling with every frame (docs/design.md §6).

    >>> import fpcore.simulate as sim
    >>> sc = sim.scenario("sinking-sphere", quick=True, seed=0)
    >>> for acq in sc.frames():          # Acquisition (N_u, N_θ, N_t) float32, truth in acq.ground_truth
    ...     ...
    >>> cal = sc.calibration("sphere1")  # the target alone in water at r0 = cal.ground_truth.r0

Each is a function returning a `fpcore.simulate.scene.Scenario` (the rig and its frame model);
`scenario(name)` looks one up in `SCENARIOS`:

* ``sinking-sphere`` — the paper's first experiment (main text Fig. 1–3, Supplementary S1–S4): a
  32×32 matrix array (pitch λ/2 at 2.2 MHz, band 1.8–2.6 MHz) over 16 mm of water on a vibrated
  granular suspension (ℓ_s = 1.8 mm at 2.2 MHz, ℓ_a = 8 mm); a 10 mm sphere settling from 9.4 to 10.0 mm
  below the surface (5.2–5.6 ℓ_s) and a static 8 mm sphere 9.6 mm below (5.3 ℓ_s), where the spheres'
  confocal contrast is within the paper's 1/150 … 1/50,
  in the paper's conventions (CONVENTIONS); 5×5 plane waves; the background decorrelates between
  frames. ``quick``: 16×16 elements over the same aperture (pitch λ), fs = 6.5 MHz.
* ``sinking-cylinder`` — the 2D analogue of ``sinking-sphere`` (x–z plane, linear array, same band,
  suspension, depths and conventions): two elastic cylinders (d = 10 and 8 mm, the spheres' material)
  along y, one settling. ``quick``: 64 elements (pitch λ/2) instead of 128.
* ``fast-cylinder`` — 2D, water: a 10 mm cylinder moving at 0.27 m/s, plane waves fired at 1 kHz, so
  it travels several resolution cells within one sequence (motion-aware fingerprints, paper Discussion).
* ``lesion-marker`` — the paper's second experiment (Fig. 4): a wire-cage marker (Foldy–Lax cluster)
  at (3.5, 4.5, 32) mm in water-soaked foam (ℓ_s = 20 mm, so z − z_s ≈ ℓ_s) producing speckle
  (Born points whose backscatter matches ℓ_s) and a weak multiple-scattering background; 32×32
  matrix array at 3 MHz. ``quick``: 16×16 over the same aperture, a smaller speckle box.
* ``muscle-fibres`` — the calf experiment (Fig. 5), 2D: a linear array (5.5–9.5 MHz, c0 = 1580 m/s),
  fibres as Born mirror segments whose orientation follows a bipennate pattern (−20° above a central
  aponeurosis, +20° below, with a lateral gradient), plus fascia and weak speckle. ``quick``: 96
  elements (same pitch), 11 plane waves.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..acquisition import PlaneWaveSequence, Probe
from ..grid import Roi
from .medium import ScatteringLayer
from .scene import Placement, Scenario
from .targets import ElasticCylinder, ElasticSphere, MirrorSegment, PointCluster
from .waves import Band, TimeWindow, radiate_points

__all__ = [
    "scenario",
    "SCENARIOS",
    "CONVENTIONS",
    "PAPER_POSITIONS",
    "sinking_sphere",
    "sinking_cylinder",
    "fast_cylinder",
    "lesion_marker",
    "muscle_fibres",
]


def _sinking(a: np.ndarray, b: np.ndarray, n: int, rate: float = 2.0) -> np.ndarray:
    """Positions from a to b over n frames, decelerating like a sphere settling in a viscous bed:
    r(t) = a + (b − a)(1 − e^{−rate·t})/(1 − e^{−rate}), t = i/(n − 1)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    w = -np.expm1(-rate * t) / -np.expm1(-rate)
    return (1 - w) * np.asarray(a, float)[None, :] + w * np.asarray(b, float)[None, :]


#: Depths imaged under the granular suspension (surface at 16 mm): from 4 mm below the surface, where the
#: interface echo and the fog just under it no longer dominate γ's global normalisation (docs/design.md
#: §4.9 caveat, paper S2), to past the deepest target; both sinking scenarios use it.
_SUSPENSION_ROI_Z = (20e-3, 31e-3)


#: The two sets of conventions of the sinking scenarios. "paper" (default): the paper's depth convention
#: (a target attenuated at its centre, main text eq. (1)), ℓ_s(f) by the Rayleigh law of Supplementary S1
#: (the ballistic echo filtered by exp(−2z/ℓ_ext(f))), the beads' single scattering as a focused speckle
#: (``single_scattering="field"``; "envelope" keeps it inside the Gaussian field), a reciprocal background with coherent
#: backscattering, no gain on the background level, and every calibration once in water at a fixed
#: position independent of the truth (the paper's (0, 0, 25) mm).
#: "legacy" (for comparison only): the conventions before that change — attenuation from the front face,
#: a non-dispersive ℓ_s, all scattering orders in one Gaussian field, a per-scenario gain, calibrations at
#: each target's initial (true) position, and the shallower depths (docs/design.md §6.4).
CONVENTIONS = ("paper", "legacy")

#: Target depths below the surface (m). "paper": where this model reproduces the paper's confocal contrast,
#: C_I ≈ 1/150 for sphere 1 and 1/50 for sphere 2 (main text eq. (1): "4–5 ℓ_s", a factor 50–150), with the
#: focused single-scattering speckle: sphere 1 settling 9.9 → 10.5 mm (C_I 1/68 → 1/133 measured on frames 0
#: and 31), sphere 2 at 10 mm (1/72 → 1/68; README, "The paper's regime"). The speckle brightens the fog's
#: confocal image over the envelope background's, where 10.4 → 11 mm gave 1/75 → 1/156; with the speckle they
#: give 1/114 → 1/192 (and 10.0 → 10.6 mm 1/76 → 1/157: the measure moves by ~5 % with the sphere's
#: drift). The paper's stated centre depths, 9 and 7 mm, give C_I 1/28–1/46 and 1/7 with the speckle (1/13–1/24
#: and 1/2.8 with the envelope background): the spheres' own echoes stand out more than e^{−z/ℓ_s};
#: PAPER_POSITIONS keeps them. Legacy: 8 → 8.6 and 7.5 mm.
_DEPTHS = {"paper": ((9.9e-3, 10.5e-3), 10.0e-3), "legacy": ((8e-3, 8.6e-3), 7.5e-3)}
#: The spheres' since the halo geometry and the single scattering's own grid (2026-12-02): on that fog the
#: old 9.9 → 10.5 mm gave sphere 1 C_I 1/99 → 1/193, so it settles 9.6 → 10.2 mm (1/90 → 1/117 → 1/148 on
#: frames 0, 15, 31); sphere 2 stays at 10 mm (1/89 → 1/91 → 1/98). The cylinders keep _DEPTHS. With the focal
#: return drawn as two-point paths (2026-12-07, docs/design.md §6.6 F6: the fog within −0.7 … +1.1 dB of the exact
#: paths', +0.4 … +1.1 dB at 5–6 ℓ_s where the earlier default was within 0.2 dB) 9.6 → 10.2 and 10 mm gave C_I
#: 1/97 → 1/153 and 1/82 – 1/85 (quick, frames 0 and 31), 1/137 and 1/152 (the full array, frame 0): sphere 1
#: settles 9.4 → 10.0 mm and sphere 2 sits at 9.6 mm (0.2 and 0.4 mm higher, sized by the contrast's slope for a
#: margin from 1/150): 1/73 → 1/136 and 1/75 – 1/78 (quick), 1/103 and 1/115 (full), every one within 1/50–1/150.
#: With the pairs' separations drawn jointly (the same evening): 1/82 → 1/137 and 1/76 – 1/76, 1/94 and 1/102.
_SPHERE_DEPTHS = {"paper": ((9.4e-3, 10.0e-3), 9.6e-3), "legacy": _DEPTHS["legacy"]}
#: The paper's stated centre depths (main text: 9 and 7 mm), sphere 1 settling to 9 mm: pass as
#: ``sink=PAPER_POSITIONS[0], sphere2_depth=PAPER_POSITIONS[1]``.
PAPER_POSITIONS = ((8.4e-3, 9.0e-3), 7.0e-3)


def _depths(
    conventions: str,
    layer: ScatteringLayer,
    sink: tuple[float, float] | None,
    static_depth: float | None,
    depth_ls: float | None,
    table: dict[str, tuple[tuple[float, float], float]] = _DEPTHS,
) -> tuple[tuple[float, float], float]:
    """(settling target's start and end depth, static target's depth) below the surface (m)."""
    if depth_ls is not None:
        if not depth_ls > 0:
            raise ValueError(f"depth_ls: expected a positive number of mean free paths, got {depth_ls}")
        d = depth_ls * layer.ls
        return (sink or (d, d + 0.6e-3)), (d if static_depth is None else static_depth)
    return (sink or table[conventions][0]), (table[conventions][1] if static_depth is None else static_depth)


#: The suspension's ℓ_s at 2.2 MHz (Supplementary S1), the unit of the targets' depths (`_granular_suspension`).
SUSPENSION_LS = 1.8e-3


def paper_regime_ls(name: str = "sinking-sphere") -> tuple[float, float]:
    """The default centre depths below the surface, in ℓ_s at 2.2 MHz, of the targets of "sinking-sphere" or
    "sinking-cylinder" in the paper's conventions: (shallowest, deepest)."""
    tables = {"sinking-sphere": _SPHERE_DEPTHS, "sinking-cylinder": _DEPTHS}
    if name not in tables:
        raise ValueError(f"name: expected one of {sorted(tables)}, got {name!r}")
    (start, end), static = tables[name]["paper"]
    depths = np.array([start, end, static]) / SUSPENSION_LS
    return float(depths.min()), float(depths.max())


#: The layer's focal-return options (`ScatteringLayer`): an override of any of them replaces the scenario's default set.
_FOCAL_KEYS = {"focal_return", "focal_return_pairs", "focal_return_shallow", "focal_return_excess", "confocal_notch"}


def _granular_suspension(conventions: str = "paper", *, dim: int = 3, **overrides: Any) -> ScatteringLayer:
    """The vibrated granular suspension of the paper's first experiment (Supplementary S1): surface 16 mm
    below the array, ℓ_s = 1.8 mm at 2.2 MHz, ℓ_a = 8 mm, 50 µm scatterer motion between frames, in the
    given `conventions` (CONVENTIONS), for a rig of `dim` dimensions; `overrides` win."""
    if conventions not in CONVENTIONS:
        raise ValueError(f"conventions: expected one of {CONVENTIONS}, got {conventions!r}")
    params: dict[str, Any] = dict(
        z_surface=16e-3,
        ls=SUSPENSION_LS,
        la=8e-3,
        density=1900.0,
        sound_speed=1600.0,
        frame_displacement=50e-6,
        roughness=0.15e-3,
    )
    if conventions == "paper":
        # ℓ_s(f): Rayleigh (f^−4) below the beads' k a = 1 (f_cross = c0/(2π a) = 1.54 MHz for a = 155 µm),
        # saturating above; anchored at ℓ_s(2.2 MHz) = 1.8 mm (Supplementary S1).
        params.update(
            envelope="diffusion",  # the half-space diffusion envelope: Foldy–Lax agrees (bench/validate_background.py)
            attenuation_depth="centre",
            ls_exponent=4.0,
            f_ref=2.2e6,
            f_cross=1.54e6,
            # The beads' single scattering as a focused speckle (validated against Foldy–Lax: all four figures,
            # bench/validate_background.py), attenuated as exp(−2z/ℓ_ext(f)); the detector's default CFAR is
            # calibrated on it (docs/design.md §4.9). single_scattering="envelope" keeps the earlier background.
            single_scattering="field",
            cbs=True,
            # Each output direction sees the halo where its ray meets the surface, at that ray's delay (validated
            # against Foldy–Lax in 2-D and 3-D, bench/validate_background.py); angular="uniform" keeps the earlier.
            angular="halo",
        )
        # The orders ≥ 2 whose ends a focus sees, drawn as two-point paths on the beads' grid (F6 of docs/design.md
        # §6.6; the deeper paths stay in the Gaussian field): against the exact paths of the quick headline rig the
        # fog is within −0.6 … +0.7 dB at 1 … 8 ℓ_s and the contrast falls as e^{−1.26 z/ℓ_s} (paths 1.25 ± 0.03, 12
        # realisations; without them −4.7 dB at 1 ℓ_s and 1.50); against Foldy–Lax all four figures pass in 2-D (slope
        # 1.18 ± 0.02, FL 1.18 ± 0.03) and in 3-D the slope, the cone by age and the memory effect are Foldy–Lax's
        # (the CBS 7 % over: README, "The paper's regime"). Any of the focal
        # keys among the overrides replaces these three (focal_return=False turns the focal return off).
        if not _FOCAL_KEYS & overrides.keys():
            params.update(focal_return=True, focal_return_pairs=True, focal_return_shallow=True)
    else:
        params.update(attenuation_depth="front")
    params.update(overrides)
    return ScatteringLayer(**params)


def sinking_sphere(
    quick: bool = False,
    seed: int = 0,
    n_frames: int = 32,
    noise_rms: float = 2e-4,
    sink: tuple[float, float] | None = None,
    calibration: str | None = None,
    conventions: str = "paper",
    sphere2_depth: float | None = None,
    depth_ls: float | None = None,
    **layer_overrides: Any,
) -> Scenario:
    """Paper experiment 1: two metal spheres in a vibrated granular suspension, one sinking.

    Geometry (paper main text and Supplementary S1): suspension surface 16 mm below the array;
    sphere 1 (d = 10 mm) centre `sink` below the surface, settling (decelerating) along a straight
    trajectory that also drifts by 0.45 mm in x and 0.25 mm in y; sphere 2 (d = 8 mm) static,
    centre `sphere2_depth` below the surface; both start in the plane y = 0 at x = ∓4.75 mm. With the
    default `conventions="paper"` (see CONVENTIONS) sphere 1 settles from 9.4 to 10.0 mm (5.2 → 5.6 ℓ_s)
    and sphere 2 sits at 9.6 mm (5.3 ℓ_s): the depths at which their measured confocal contrast is within the
    paper's 1/150 … 1/50 (main text eq. (1); its stated 9 and 7 mm give 1/13–1/24 and 1/2.8 in this
    model, `PAPER_POSITIONS`); the background level is the transport model's, with no gain; the
    calibrations are simulated once, in water, at the paper's r0 = (0, 0, 25) mm (Methods), unless
    calibration="nominal" (r0 at each target's initial position: the truth, for comparison only).
    `conventions="legacy"`: the earlier, easier rig (front-face attenuation, 8 → 8.6 and 7.5 mm,
    background gain 2.5, nominal calibrations). `depth_ls`: both centres that many ℓ_s (at 2.2 MHz) below
    the surface instead, sphere 1 settling 0.6 mm from there (e.g. 2: where this implementation
    detects both spheres; README, "The paper's regime"). `layer_overrides` go to `ScatteringLayer`; the focal
    return of the orders ≥ 2 is drawn as two-point paths on the beads' grid (`focal_return_pairs`, F6 of
    docs/design.md §6.6) unless any focal-return option is among them (focal_return=False turns it off).
    """
    c0, fc = 1500.0, 2.2e6
    pitch = c0 / fc / 2
    if quick:
        probe = Probe.matrix(16, 16, 2 * pitch, fc, 0.8e6)
        fs = 6.5e6
    else:
        probe = Probe.matrix(32, 32, pitch, fc, 0.8e6)
        fs = 10.4e6
    seq = PlaneWaveSequence.uniform_sines(5, 0.2, ny=5)
    band = Band(1.8e6, 2.6e6)
    window = TimeWindow.covering(fs, 20e-6, 75e-6, guard=35e-6)
    legacy = conventions == "legacy"
    gain: dict[str, Any] = {"gain": 2.5} if legacy else {}
    layer = _granular_suspension(conventions, dim=3, **gain, **layer_overrides)
    zs = layer.z_surface
    calibration = calibration or ("nominal" if legacy else "axis")
    if calibration not in ("nominal", "axis"):
        raise ValueError(f"calibration: expected 'nominal' or 'axis', got {calibration!r}")
    sink, z2 = _depths(conventions, layer, sink, sphere2_depth, depth_ls, _SPHERE_DEPTHS)
    p1 = _sinking(np.array([-4.75e-3, 0.0, zs + sink[0]]), np.array([-5.2e-3, 0.25e-3, zs + sink[1]]), n_frames)
    p2 = np.array([[4.75e-3, 0.0, zs + z2]])
    axis = np.array([0.0, 0.0, 25e-3])
    s1 = Placement(ElasticSphere(10e-3, name="sphere1"), p1, axis if calibration == "axis" else p1[0], kind="sphere")
    s2 = Placement(ElasticSphere(8e-3, name="sphere2"), p2, axis if calibration == "axis" else p2[0], kind="sphere")
    return Scenario(
        "sinking-sphere",
        probe,
        seq,
        c0,
        window,
        band,
        n_frames,
        {"sphere1": s1, "sphere2": s2},
        dim=3,
        seed=seed,
        quick=quick,
        layer=layer,
        noise_rms=noise_rms,
        calibration_noise_rms=0.1 * noise_rms,
        description=sinking_sphere.__doc__ or "",
        roi=Roi((-11e-3, 11e-3), _SUSPENSION_ROI_Z, 0.25e-3, y_range=(-5e-3, 5e-3)),
    )


def sinking_cylinder(
    quick: bool = False,
    seed: int = 0,
    n_frames: int = 32,
    noise_rms: float = 2e-4,
    sink: tuple[float, float] | None = None,
    calibration: str | None = None,
    conventions: str = "paper",
    cylinder2_depth: float | None = None,
    depth_ls: float | None = None,
    **layer_overrides: Any,
) -> Scenario:
    """2D analogue of `sinking_sphere`: two elastic cylinders under a granular suspension, one settling.

    Linear array along x (pitch λ/2 at 2.2 MHz; 128 elements, quick: 64), 11 plane waves with sines in
    ±0.2, band 1.8–2.6 MHz; suspension surface 16 mm below the array (ℓ_s = 1.8 mm at 2.2 MHz,
    ℓ_a = 8 mm, frame displacement 50 µm); cylinder 1 (d = 10 mm) settles along `sink` with a 0.45 mm
    drift in x; cylinder 2 (d = 8 mm) static at `cylinder2_depth`; both of the spheres' material
    (ρ = 5700 kg/m³, c_p = 2700 m/s, c_t = 2000 m/s). `conventions` as in `sinking_sphere`: "paper"
    (default) puts the cylinders at the spheres' earlier depths (9.9 → 10.5 mm and 10 mm), takes the
    transport model's background level (no gain) and calibrates once in water on the axis at 25 mm;
    with the focal return of the orders ≥ 2 drawn as two-point paths on the beads' grid (as `sinking_sphere`; in 2-D
    the background that passes all four figures against Foldy–Lax, docs/design.md §6.6, F6; focal_return=False turns
    it off);
    "legacy": front-face attenuation, 8 → 8.6 and 7.5 mm, gain 1.0, calibrations at the initial
    (true) positions. calibration="nominal"/"axis" overrides the calibration position; `depth_ls` as in
    `sinking_sphere`.
    """
    c0, fc = 1500.0, 2.2e6
    pitch = c0 / fc / 2
    probe = Probe.linear(64 if quick else 128, pitch, fc, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(11, 0.2)
    band = Band(1.8e6, 2.6e6)
    window = TimeWindow.covering(10.4e6, 20e-6, 75e-6, guard=35e-6)
    legacy = conventions == "legacy"
    gain: dict[str, Any] = {"gain": 1.0} if legacy else {}
    layer = _granular_suspension(conventions, dim=2, **gain, **layer_overrides)
    zs = layer.z_surface
    calibration = calibration or ("nominal" if legacy else "axis")
    if calibration not in ("nominal", "axis"):
        raise ValueError(f"calibration: expected 'nominal' or 'axis', got {calibration!r}")
    sink, z2 = _depths(conventions, layer, sink, cylinder2_depth, depth_ls)
    p1 = _sinking(np.array([-4.75e-3, 0.0, zs + sink[0]]), np.array([-5.2e-3, 0.0, zs + sink[1]]), n_frames)
    p2 = np.array([[4.75e-3, 0.0, zs + z2]])
    axis = np.array([0.0, 0.0, 25e-3])
    r1, r2 = (p1[0], p2[0]) if calibration == "nominal" else (axis, axis)
    c1 = Placement(ElasticCylinder(10e-3, name="cylinder1"), p1, r1, kind="cylinder")
    c2 = Placement(ElasticCylinder(8e-3, name="cylinder2"), p2, r2, kind="cylinder")
    return Scenario(
        "sinking-cylinder",
        probe,
        seq,
        c0,
        window,
        band,
        n_frames,
        {"cylinder1": c1, "cylinder2": c2},
        dim=2,
        seed=seed,
        quick=quick,
        layer=layer,
        noise_rms=noise_rms,
        calibration_noise_rms=0.1 * noise_rms,
        description=sinking_cylinder.__doc__ or "",
        roi=Roi((-11e-3, 11e-3), _SUSPENSION_ROI_Z, 0.1e-3),
    )


def fast_cylinder(
    quick: bool = False,
    seed: int = 0,
    n_frames: int = 4,
    velocity: tuple[float, float, float] = (0.25, 0.0, 0.1),
    prf: float = 1000.0,
    noise_rms: float = 2e-4,
    diameter: float = 10e-3,
) -> Scenario:
    """A target moving fast enough to smear within one plane-wave sequence (motion-aware fingerprints).

    2D, water only: a 10 mm elastic cylinder (the spheres' material) crossing the field at `velocity`
    (m/s) from (−1, 0, 25) mm, insonified by 11 plane waves (sines in ±0.2) fired every 1/`prf`
    (10 ms per sequence at 1 kHz: 2.5 mm of lateral and 1 mm of axial travel within one frame, 3–4
    resolution cells and ~3 wavelengths); frames back to back (frame rate prf/11). Linear array at
    2.2 MHz (pitch λ/2; 128 elements, quick: 64), band 1.8–2.6 MHz. Calibration: the cylinder at rest
    at (0, 0, 25) mm.
    """
    c0, fc = 1500.0, 2.2e6
    probe = Probe.linear(64 if quick else 128, c0 / fc / 2, fc, 0.8e6)
    seq = PlaneWaveSequence(PlaneWaveSequence.uniform_sines(11, 0.2).sines, prf=prf)
    frame_rate = prf / seq.n_waves
    window = TimeWindow.covering(10.4e6, 22e-6, 60e-6, guard=25e-6)
    v = np.asarray(velocity, dtype=float)
    start = np.array([-1e-3, 0.0, 25e-3])
    traj = start[None, :] + v[None, :] * (np.arange(max(n_frames, 2))[:, None] / frame_rate)  # ≥ 2: moving
    pl = Placement(
        ElasticCylinder(diameter, name="cylinder"), traj, np.array([0.0, 0.0, 25e-3]), kind="cylinder", in_medium=False
    )
    return Scenario(
        "fast-cylinder",
        probe,
        seq,
        c0,
        window,
        Band(1.8e6, 2.6e6),
        n_frames,
        {"cylinder": pl},
        dim=2,
        seed=seed,
        quick=quick,
        frame_rate=frame_rate,
        noise_rms=noise_rms,
        calibration_noise_rms=0.1 * noise_rms,
        description=fast_cylinder.__doc__ or "",
    )


def marker_cage(diameter: float = 3e-3, n_per_ring: int = 12) -> np.ndarray:
    """Offsets of a wire-cage marker: three orthogonal rings (points every ≈ λ at 3 MHz)."""
    a = 0.5 * diameter
    phi = 2 * np.pi * np.arange(n_per_ring) / n_per_ring
    c, s = a * np.cos(phi), a * np.sin(phi)
    z = np.zeros_like(c)
    rings = [np.stack([c, s, z], 1), np.stack([c, z, s], 1), np.stack([z, c + 0.15 * a, s], 1)]
    pts = np.concatenate(rings)
    keep = [0]
    for i in range(1, pts.shape[0]):  # drop near-duplicates where rings cross
        if np.min(np.linalg.norm(pts[keep] - pts[i], axis=1)) > 0.3 * a:
            keep.append(i)
    return pts[keep]


def lesion_marker(
    quick: bool = False,
    seed: int = 0,
    n_frames: int | None = None,
    calibration: str = "axis",
    marker_points: int = 16,
    marker_inverse_t: float = 0.5,
) -> Scenario:
    """Paper experiment 2: a lesion marker in foam speckle at z − z_s ≈ ℓ_s (3D, matrix array).

    Foam (ℓ_s = 20 mm, ℓ_a = 60 mm) below 12 mm of water; the marker (a 3 mm wire cage of
    `marker_points` per ring on three rings, strong point scatterers coupled by Foldy–Lax, Re(1/t) =
    `marker_inverse_t` × k/4π, 5 % loss) at (3.5, 4.5, 32) mm (paper Fig. 4), i.e. 20 mm ≈ ℓ_s into the
    foam. Speckle: Born points (4 per mm³) in a box around the marker whose backscatter matches ℓ_s
    (|t|² = 4π/(n ℓ_s)), attenuated along their ballistic legs; plus the statistical multiple-scattering
    background of the foam. Static medium. Calibration (the marker alone in water): "axis" (default), once at
    the fixed r0 = (0, 0, 30) mm, independent of the truth; "nominal" (for comparison only): r0 2 mm above
    the marker (same lateral position, i.e. placed from the truth).
    """
    if calibration not in ("nominal", "axis"):
        raise ValueError(f"calibration: expected 'nominal' or 'axis', got {calibration!r}")
    c0, fc = 1500.0, 3.0e6
    if quick:
        probe = Probe.matrix(16, 16, 0.6e-3, fc, 1.6e6)
        fs = 10e6
        box = np.array([[0.5e-3, 6.5e-3], [1.5e-3, 7.5e-3], [28e-3, 36e-3]])
    else:
        probe = Probe.matrix(32, 32, 0.3e-3, fc, 1.6e6)
        fs = 15.2e6
        box = np.array([[-2.5e-3, 9.5e-3], [-1.5e-3, 10.5e-3], [26e-3, 38e-3]])
    n_frames = (4 if quick else 8) if n_frames is None else n_frames
    seq = PlaneWaveSequence.uniform_sines(5, 0.2, ny=5)
    band = Band(2.2e6, 3.8e6)
    window = TimeWindow.covering(fs, 33e-6, 58e-6, guard=15e-6)
    layer = ScatteringLayer(z_surface=12e-3, ls=20e-3, la=60e-3, density=1050.0, sound_speed=1520.0)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    # Speckle: n points per mm³ with backscatter consistent with ℓ_s: σ_s = 1/(n ℓ_s), |t|² = 4π σ_s.
    density = 4e9
    vol = float(np.prod(box[:, 1] - box[:, 0]))
    n_pts = rng.poisson(density * vol)
    pts = box[:, 0] + rng.uniform(size=(n_pts, 3)) * (box[:, 1] - box[:, 0])
    t_rms = np.sqrt(4 * np.pi / (density * layer.ls))
    t = rng.standard_normal(n_pts) * t_rms
    kc = 2 * np.pi * fc / c0
    x_res = marker_inverse_t * kc / (4 * np.pi)  # Re(1/t) in units of the radiative part Im(1/t) = k/4π
    cage = marker_cage(3e-3, marker_points)
    marker = PointCluster(cage, np.full(cage.shape[0], x_res), loss=0.05, coupled=True, name="marker", dim=3, size=3e-3)
    r_m = np.array([3.5e-3, 4.5e-3, 32e-3])
    r0 = r_m - np.array([0.0, 0.0, 2e-3]) if calibration == "nominal" else np.array([0.0, 0.0, 30e-3])
    pl = Placement(marker, r_m[None, :], r0, kind="marker")
    roi = Roi((0.5e-3, 6.5e-3), (28e-3, 36e-3), 0.15e-3, y_range=(1.5e-3, 7.5e-3))  # marker ± 3 mm (z: ± 4 mm)
    return Scenario(
        "lesion-marker",
        probe,
        seq,
        c0,
        window,
        band,
        n_frames,
        {"marker": pl},
        dim=3,
        seed=seed,
        quick=quick,
        layer=layer,
        speckle=(pts, t),
        noise_rms=2e-4,
        calibration_noise_rms=2e-5,
        description=lesion_marker.__doc__ or "",
        roi=roi,
    )


def bipennate_orientation(
    x: np.ndarray,
    z: np.ndarray,
    alpha_top: float = np.deg2rad(-20.0),
    alpha_deep: float = np.deg2rad(20.0),
    z_apo: float = 15e-3,
    width: float = 2e-3,
    gradient: float = np.deg2rad(0.5) / 1e-3,
) -> np.ndarray:
    """Fibre tilt α(x, z) (rad) of the muscle-fibres scenario: −20° above the aponeurosis, +20° below,
    a tanh transition of half-width `width`, plus a lateral gradient (0.5°/mm)."""
    w = 0.5 * (1 + np.tanh((np.asarray(z) - z_apo) / width))
    return (1 - w) * alpha_top + w * alpha_deep + gradient * np.asarray(x)


def muscle_fibres(
    quick: bool = False, seed: int = 0, n_frames: int = 4, z_range: tuple[float, float] = (6e-3, 25e-3)
) -> Scenario:
    """Calf experiment: fibres with a varying orientation, linear array 5.5–9.5 MHz (2D).

    Fibres (Poisson centres, 0.4 per mm², length 1.5–4 mm, reflectivity ≈ 0.1) fill `z_range` across
    the aperture with tilt `bipennate_orientation` (+ 2° jitter); fascia at 5.2 mm and a central
    aponeurosis at 15 mm are long specular mirrors; weak speckle fills the rest. The medium is static
    (frames differ by electronic noise). Calibration target "fibre": one 2.5 mm mirror at
    (0, 0, 15) mm, α = 0, in water (the base of a numerical fingerprint dictionary, paper Fig. 5).
    """
    c0, fc = 1580.0, 7.5e6
    n_el, n_pw = (96, 11) if quick else (192, 31)
    probe = Probe.linear(n_el, 0.2e-3, fc, 4e6)
    seq = PlaneWaveSequence.uniform_sines(n_pw, np.sin(np.deg2rad(15.0)))
    band = Band(5.5e6, 9.5e6)
    window = TimeWindow.covering(38e6, 5e-6, 34e-6, guard=12e-6)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 11]))
    half = 0.5 * probe.aperture[0]
    (z_lo, z_hi), z_apo = z_range, 15e-3
    area = 2 * half * (z_hi - z_lo)
    n_fib = rng.poisson(0.4e6 * area)
    xc = rng.uniform(-half, half, n_fib)
    zc = rng.uniform(z_lo, z_hi, n_fib)
    keep = np.abs(zc - z_apo) > 0.6e-3
    xc, zc = xc[keep], zc[keep]
    alpha = bipennate_orientation(xc, zc) + rng.normal(0, np.deg2rad(2.0), xc.size)
    length = rng.uniform(1.5e-3, 4e-3, xc.size)
    refl = 0.1 * np.exp(rng.normal(0, 0.3, xc.size))
    h = c0 / band.support[1] / 4
    pts, amps = [], []
    for x, z, a, L, r in zip(xc, zc, alpha, length, refl, strict=True):
        seg = MirrorSegment(L, a, reflectivity=r, dim=2)
        p, step = seg.points(np.array([x, 0.0, z]), h)
        pts.append(p)
        amps.append(np.full(p.shape[0], r * step))
    fib_pts = np.concatenate(pts)
    fib_amp = np.concatenate(amps)
    # Fascia and central aponeurosis: long specular mirrors.
    for z, r in ((5.2e-3, 0.3), (z_apo, 0.3)):
        seg = MirrorSegment(2 * half + 4e-3, 0.0, reflectivity=r, dim=2)
        p, step = seg.points(np.array([0.0, 0.0, z]), h)
        fib_pts = np.concatenate([fib_pts, p])
        fib_amp = np.concatenate([fib_amp, np.full(p.shape[0], r * step)])
    # Weak speckle (unresolved scatterers between fibres), amplitude ≈ 2k·r per point of a r = 0.02 sheet.
    dens = 15e6
    n_sp = rng.poisson(dens * area)
    sp_pts = np.stack([rng.uniform(-half, half, n_sp), np.zeros(n_sp), rng.uniform(z_lo, z_hi, n_sp)], 1)
    sp_amp = rng.standard_normal(n_sp) * 0.02 / np.sqrt(dens)
    clutter_pts = np.concatenate([fib_pts, sp_pts])
    clutter_amp = np.concatenate([fib_amp, sp_amp]).astype(np.complex128)
    fibres = _BornCloud(clutter_pts, clutter_amp, dim=2)
    calib = MirrorSegment(2.5e-3, 0.0, reflectivity=0.1, name="fibre", dim=2)
    pl = Placement(
        calib, np.array([[0.0, 0.0, 15e-3]]), np.array([0.0, 0.0, 15e-3]), kind="fibre", in_medium=False, in_scene=False
    )
    truth = {
        "fibres": [
            {"position_m": [float(x), 0.0, float(z)], "alpha_rad": float(a), "length_m": float(L)}
            for x, z, a, L in zip(xc, zc, alpha, length, strict=True)
        ],
        "orientation_field": {
            "model": "bipennate",
            "alpha_top_rad": float(np.deg2rad(-20.0)),
            "alpha_deep_rad": float(np.deg2rad(20.0)),
            "aponeurosis_z_m": z_apo,
            "transition_m": 2e-3,
            "lateral_gradient_rad_per_m": float(np.deg2rad(0.5) / 1e-3),
        },
        "fascia_z_m": [5.2e-3, z_apo],
    }
    return Scenario(
        "muscle-fibres",
        probe,
        seq,
        c0,
        window,
        band,
        n_frames,
        {"fibre": pl},
        dim=2,
        seed=seed,
        quick=quick,
        rho0=1060.0,
        clutter=[(fibres, np.zeros(3))],
        noise_rms=2e-4,
        calibration_noise_rms=2e-5,
        description=muscle_fibres.__doc__ or "",
        extra_truth=truth,
    )


@dataclass
class _BornCloud:
    """Static Born point cloud with strengths 2ik·a_j (mirror points and speckle), placed at `position`."""

    points: np.ndarray
    amplitudes: np.ndarray
    dim: int = 2
    name: str = "cloud"

    @property
    def diameter(self) -> float:
        return 0.0

    def transfer(
        self, elements: np.ndarray, sines: np.ndarray, freqs: np.ndarray, c0: float, position: np.ndarray
    ) -> np.ndarray:
        k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
        return radiate_points(
            self.points + np.asarray(position)[None, :],
            self.amplitudes,
            elements,
            sines,
            freqs,
            c0,
            self.dim,
            spectral=2j * k,
            chunk=4096,
        )


SCENARIOS: dict[str, Callable[..., Scenario]] = {
    "sinking-sphere": sinking_sphere,
    "sinking-cylinder": sinking_cylinder,
    "fast-cylinder": fast_cylinder,
    "lesion-marker": lesion_marker,
    "muscle-fibres": muscle_fibres,
}


def scenario(name: str, quick: bool = False, seed: int = 0, **kwargs: Any) -> Scenario:
    """Build a named scenario (see module doc): ``scenario("sinking-sphere", quick=True, seed=0)``."""
    if name not in SCENARIOS:
        raise KeyError(f"scenario {name!r}: expected one of {sorted(SCENARIOS)}")
    return SCENARIOS[name](quick=quick, seed=seed, **kwargs)
