"""The simulated rig (docs/design.md §6): `Placement` (a target, its positions per frame and its
calibration position r0) and `Scenario` (probe, sequence, time window, targets, medium), which makes the
frames on demand with their ground truth, and each target's calibration acquisition and fingerprint. The
ready-made rigs are built in `fpcore.simulate.scenarios`.

A frame is X(f) = S(f) [H_static + Σ_moving H_target(r_n) + V_n(f)] → RF + electronic noise, with
H_static the interface echo, the medium's single-scattering speckle and the targets that do not move
(computed once), the moving targets re-evaluated exactly at their trajectory positions, and V_n the
multiple-scattering background of frame n (`medium.DiffuseBackground`). Targets inside the medium
are attenuated along their ballistic legs (`medium.ScatteringLayer.attenuate`). Interactions between
distinct targets, and between targets and the medium's scatterers, are neglected (single target–medium
coupling through extinction only), as in the paper's model R = σ_T R_0 + M (Supplementary S4).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..acquisition import Acquisition, PlaneWaveSequence, Probe
from ..fingerprint import Fingerprint, from_calibration
from ..grid import Roi
from ..truth import MediumTruth, TargetTruth, Truth
from .medium import DiffuseBackground, ScatteringLayer
from .targets import Target
from .waves import Band, TimeWindow, radiate_points

__all__ = ["Placement", "Scenario"]


@dataclass
class Placement:
    """A target of the scene: its positions per frame (n_frames, 3) and its calibration position r0."""

    target: Target
    positions: np.ndarray
    calibration_position: np.ndarray
    kind: str = "target"
    in_medium: bool = True
    in_scene: bool = True  # False: a calibration-only target (e.g. one fibre of a fibrous medium)

    def __post_init__(self) -> None:
        self.positions = np.atleast_2d(np.asarray(self.positions, dtype=np.float64))
        self.calibration_position = np.asarray(self.calibration_position, dtype=np.float64)

    @property
    def moving(self) -> bool:
        return bool(np.ptp(self.positions, axis=0).max() > 0)

    def velocity(self, i: int, frame_rate: float) -> np.ndarray:
        """Velocity at frame i (m/s): central difference of the trajectory (one-sided at its ends)."""
        p = self.positions
        if p.shape[0] < 2:
            return np.zeros(3)
        i = min(max(i, 0), p.shape[0] - 1)  # like `position`: the last position holds after the trajectory
        a, b = max(i - 1, 0), min(i + 1, p.shape[0] - 1)
        return (p[b] - p[a]) / (b - a) * frame_rate

    def position(self, i: int) -> np.ndarray:
        return self.positions[min(i, self.positions.shape[0] - 1)]


@dataclass
class Scenario:
    """A simulated rig: probe, sequence, window, targets, medium; frames on demand with ground truth.

    roi: the region the scenario is meant to be imaged over (`Roi.grid()` gives the grid), where one is
    defined (sinking-sphere, sinking-cylinder, lesion-marker)."""

    name: str
    probe: Probe
    sequence: PlaneWaveSequence
    c0: float
    window: TimeWindow
    pulse: Band
    n_frames: int
    placements: dict[str, Placement]
    dim: int
    seed: int = 0
    quick: bool = False
    rho0: float = 1000.0
    frame_rate: float = 10.0
    layer: ScatteringLayer | None = None
    speckle: tuple[np.ndarray, np.ndarray] | None = None
    clutter: list[tuple[Target, np.ndarray]] = field(default_factory=list)
    noise_rms: float = 0.0
    calibration_noise_rms: float = 0.0
    description: str = ""
    extra_truth: dict[str, Any] = field(default_factory=dict)
    roi: Roi | None = None  # the region to image (`roi.grid()`); None: none defined, image the record's window
    _static: np.ndarray | None = field(default=None, init=False, repr=False)
    _diffuse: DiffuseBackground | None = field(default=None, init=False, repr=False)
    _next: int = field(default=0, init=False, repr=False)

    # -- description ------------------------------------------------------------------------------
    @property
    def band(self) -> tuple[float, float]:
        """(f_min, f_max): the −6 dB transducer band (Hz), the band to process."""
        return self.pulse.f_min, self.pulse.f_max

    @property
    def fs(self) -> float:
        return self.window.fs

    @property
    def t0(self) -> float:
        return self.window.t0

    @property
    def n_samples(self) -> int:
        return self.window.n_samples

    @property
    def frame_nbytes(self) -> int:
        return self.probe.n_elements * self.sequence.n_waves * self.window.n_samples * 4

    @property
    def target_names(self) -> list[str]:
        return list(self.placements)

    @property
    def bins(self) -> np.ndarray:
        return self.window.band_bins(self.pulse)

    @property
    def freqs(self) -> np.ndarray:
        return self.window.freqs()[self.bins]

    # -- physics ------------------------------------------------------------------------------------
    def _target_h(self, pl: Placement, r: np.ndarray, in_medium: bool, sines: np.ndarray | None = None) -> np.ndarray:
        el = self.probe.positions
        s = self.sequence.sines if sines is None else sines
        h = pl.target.transfer(el, s, self.freqs, self.c0, r)
        if in_medium and self.layer is not None:
            h = self.layer.attenuate(h, r, pl.target.diameter, el, s, self.rho0, self.c0, freqs=self.freqs)
        return h

    def static_transfer(self) -> np.ndarray:
        """H of everything that does not change between frames (N_f, N_u, N_θ), computed once."""
        if self._static is None:
            el, s, f = self.probe.positions, self.sequence.sines, self.freqs
            h = np.zeros((f.size, el.shape[0], s.shape[0]), dtype=np.complex64)
            if self.layer is not None:
                h += self.layer.interface_echo(el, s, f, self.c0, self.rho0)
            if self.speckle is not None:
                pts, t = self.speckle
                att_in = att_out = None
                if self.layer is not None:
                    lay = self.layer
                    att_in = np.stack([lay.attenuation_in(p, s) for p in pts])
                    att_out = np.stack([lay.attenuation_out(p, el) for p in pts], axis=1)
                radiate_points(pts, t, el, s, f, self.c0, self.dim, att_in=att_in, att_out=att_out, out=h)
            for target, r in self.clutter:
                h += target.transfer(el, s, f, self.c0, r)
            for pl in self.placements.values():
                if pl.in_scene and not pl.moving:
                    h += self._target_h(pl, pl.position(0), pl.in_medium)
            self._static = h
        return self._static

    def _background(self) -> DiffuseBackground | None:
        if self.layer is None:
            return None
        if self._diffuse is None:
            ax, ay = self.probe.aperture
            radius = 0.5 * (np.sqrt(ax * ay) if self.dim == 3 and ay > 0 else ax)
            self._diffuse = DiffuseBackground.cached(
                self.layer,
                self.probe.positions,
                self.sequence.sines,
                self.window,
                self.pulse,
                self.c0,
                self.dim,
                radius,
                self._background_rng(),
            )
        return self._diffuse

    def _background_rng(self) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, 1]))

    def _electronic_noise(self, rf: np.ndarray, rms: float, key: tuple[int, ...]) -> None:
        if rms > 0:
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, *key]))
            rf += rng.standard_normal(rf.shape, dtype=np.float32) * np.float32(rms)

    # -- truth ---------------------------------------------------------------------------------------
    def ground_truth(self, i: int) -> Truth:
        """Ground truth of frame i: the targets in the scene (position, velocity, depth below the layer's
        surface), the medium and `extra_truth`."""
        targets = []
        for name, pl in self.placements.items():
            if not pl.in_scene:
                continue
            r = pl.position(i)
            v = pl.velocity(i, self.frame_rate) if pl.moving else None
            depth = float(r[2] - self.layer.z_surface) if self.layer is not None and pl.in_medium else None
            targets.append(
                TargetTruth(
                    name=name,
                    kind=pl.kind,
                    position_m=_vec3(r),
                    diameter_m=float(pl.target.diameter),
                    moving=pl.moving,
                    velocity_m_s=None if v is None else _vec3(v),
                    depth_below_surface_m=depth,
                )
            )
        medium = None
        if self.layer is not None:
            lay = self.layer
            medium = MediumTruth(
                z_surface_m=lay.z_surface,
                ls_m=lay.ls,
                la_m=float(lay.la),
                l_ext_m=lay.l_ext,
                envelope=lay.envelope,
                frame_displacement_m=lay.frame_displacement,
                interface_reflection=lay.reflection(self.rho0, self.c0),
            )
        out = Truth(
            scenario=self.name,
            quick=self.quick,
            seed=self.seed,
            frame_index=i,
            time_s=i / self.frame_rate,
            dim=self.dim,
            band_hz=(self.pulse.f_min, self.pulse.f_max),
            targets=targets,
            medium=medium,
        )
        return out.merged(self.extra_truth) if self.extra_truth else out

    def truth(self, i: int) -> dict[str, Any]:
        """Ground truth of frame i as the JSON object frames carry (``ground_truth(i).to_dict()``)."""
        return self.ground_truth(i).to_dict()

    # -- frames ---------------------------------------------------------------------------------------
    def _acquisition(self, rf: np.ndarray, i: int, truth: Truth) -> Acquisition:
        return Acquisition(
            rf,
            self.fs,
            self.t0,
            self.c0,
            self.probe,
            self.sequence,
            frame_index=i,
            timestamp=i / self.frame_rate,
            truth=truth.to_dict(),
        )

    def _reset(self) -> None:
        if self._diffuse is not None:  # frame 0's draws again; the envelopes are kept
            self._diffuse.restart(self._background_rng())
        self._next = 0

    def frame(self, i: int) -> Acquisition:
        """Frame i (sequential access is cheapest: the background evolves frame to frame)."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame index {i} outside [0, {self.n_frames})")
        if i < self._next:
            self._reset()
        bg = self._background()
        while self._next < i:  # advance the background state (its draws only: `DiffuseBackground.skip`)
            if bg is not None:
                bg.skip()
            self._next += 1
        h = self.static_transfer().copy()
        for pl in self.placements.values():
            if pl.in_scene and pl.moving:
                h += self._moving_target_h(pl, i)
        if bg is not None:
            h += bg.next()
        self._next = i + 1
        return self.acquisition_of(h, i)

    def acquisition_of(self, h: np.ndarray, i: int, noise: bool = True) -> Acquisition:
        """Frame i's acquisition of a transfer H (N_f, N_u, N_θ) on the band bins: the pulse's spectrum, the
        record's synthesis and (noise=True) frame i's own electronic-noise draw — what `frame` does to the
        scene's H. A part of a frame's H alone (`DiffuseBackground.next_orders`, `static_transfer`) gives that
        part's frame, e.g. to map a fingerprint on it (γ's numerator is linear in R, paper eq. P)."""
        x = h * self.pulse.spectrum(self.freqs).astype(np.float32)[:, None, None]
        rf = self.window.synthesize(x, self.bins)
        if noise:
            self._electronic_noise(rf, self.noise_rms, (2, i))
        return self._acquisition(rf, i, self.ground_truth(i))

    def _moving_target_h(self, pl: Placement, i: int) -> np.ndarray:
        """H of a moving target in frame i. With the sequence's prf set, transmit j sees the target where
        it is when j fires, r_i + v_i τ_j (τ_j from `PlaneWaveSequence.transmit_times`): the within-frame
        motion that motion-aware fingerprints undo (fpcore.fingerprint module doc)."""
        r = pl.position(i)
        if self.sequence.prf is None:
            return self._target_h(pl, r, pl.in_medium)
        v = pl.velocity(i, self.frame_rate)
        s = self.sequence.sines
        cols = [
            self._target_h(pl, r + v * tau, pl.in_medium, s[j : j + 1])
            for j, tau in enumerate(self.sequence.transmit_times())
        ]
        return np.concatenate(cols, axis=2)

    def target_echo(self, name: str, i: int) -> Acquisition:
        """Frame i with only target `name`, through the medium (no background, interface or noise): its own
        echo, e.g. for the confocal contrast C_I of the paper's eq. (1) against `without_targets()`."""
        pl = self.placements[name]
        h = self._moving_target_h(pl, i) if pl.moving else self._target_h(pl, pl.position(i), pl.in_medium)
        return self.acquisition_of(h, i, noise=False)

    def without_targets(self) -> Scenario:
        """The same rig, medium and noise with no target in the scene: fog-only frames, the null
        hypothesis a false-alarm probability is checked on (calibrations still work)."""
        return replace(self, placements={n: replace(p, in_scene=False) for n, p in self.placements.items()})

    def frames(self) -> Iterator[Acquisition]:
        """All frames in order (generator)."""
        for i in range(self.n_frames):
            yield self.frame(i)

    def fingerprints(
        self, out_sines: np.ndarray, n_freq: int | None = None, svd_threshold: float = 0.4, whiten_modes: bool = True
    ) -> dict[str, Fingerprint]:
        """Each target's calibration fingerprint (fpcore.from_calibration, paper Methods) on this band,
        gated at its front face (r0 and diameter from the calibration's truth); whiten_modes=False keeps R0′."""
        out = {}
        for name in self.target_names:
            truth = self.calibration_truth(name)
            out[name] = from_calibration(
                self.calibration(name),
                truth.r0,
                out_sines,
                self.band,
                n_freq,
                diameter=truth.diameter,
                svd_threshold=svd_threshold,
                name=name,
                whiten_modes=whiten_modes,
            )
        return out

    def calibration_truth(self, target_name: str) -> Truth:
        """Truth of the calibration acquisition of one target: r0_m, diameter_m, the target at r0."""
        if target_name not in self.placements:
            raise KeyError(f"target {target_name!r}: expected one of {self.target_names}")
        pl = self.placements[target_name]
        r0, d = _vec3(pl.calibration_position), float(pl.target.diameter)
        return Truth(
            scenario=self.name,
            calibration=True,
            quick=self.quick,
            seed=self.seed,
            r0_m=r0,
            diameter_m=d,
            band_hz=(self.pulse.f_min, self.pulse.f_max),
            targets=[TargetTruth(name=target_name, kind=pl.kind, position_m=r0, diameter_m=d, moving=False)],
        )

    def calibration(self, target_name: str) -> Acquisition:
        """The target alone in water at its calibration position r0 (truth: `calibration_truth`)."""
        truth = self.calibration_truth(target_name)
        pl = self.placements[target_name]
        r0 = pl.calibration_position
        h = self._target_h(pl, r0, in_medium=False)
        x = h * self.pulse.spectrum(self.freqs).astype(np.float32)[:, None, None]
        rf = self.window.synthesize(x, self.bins)
        self._electronic_noise(rf, self.calibration_noise_rms, (3, self.target_names.index(target_name)))
        return self._acquisition(rf, 0, truth)


def _vec3(r: np.ndarray) -> tuple[float, float, float]:
    """A position or velocity as the three plain floats a truth record holds."""
    x, y, z = (float(v) for v in r)
    return x, y, z
