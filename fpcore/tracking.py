"""Tracking moving targets through the fog on γ-maps (issue 5; docs/design.md §1, §4.8–4.10).

Per-frame detection alone fails on deep frames: the global γ maximum can jump to a fog fluctuation
while the target's γ stays high near its last position. The tracker therefore:

* predicts each track with a constant-velocity Kalman filter (filterpy's `KalmanFilter`; white-noise
  acceleration process noise);
* searches the γ-map only inside a gate around the prediction (Mahalanobis radius `gate_sigma` of the
  innovation covariance, at least `min_gate`) for the most significant node against the map's local
  null level (fpcore.cfar, docs/design.md §4.9), so the calibrated false-alarm probability of the gated
  maximum is that of a maximum over the gate's resels, not over the whole field of view;
* uses the Cramér–Rao precision of each measurement as its noise, R = diag(δρ_L², …, δz²) with
  δρ_L = δρ_D/√C_γ (paper eq. loc) and, axially, the envelope resolution c0/(2Δf)/√C_γ (the peak of |γ|
  carries no carrier phase, so the paper's λ-based axial bound is not reached by this estimator),
  floored at the grid's quantisation variance spacing²/12;
* assigns candidates to tracks by `scipy.optimize.linear_sum_assignment` on Mahalanobis distances,
  starts a track from an unassigned interior peak (`skip_border`: births and gates take local maxima of γ
  at least δρ_D from the grid's border only — maxima on or next to the border are, most often, the
  flanks of something outside the region of interest, e.g. γ rising under a suspension's surface; a
  track whose prediction is itself in that band may still take them) whose field-of-view PFA is below
  `p_birth` (calibrated), confirms it after `confirm_hits` hits; a track without a significant measurement
  (gated PFA above `p_keep`) is *coasting*, and after `max_misses` consecutive misses *lost* (reported
  once with that status, then dropped);
* reports confidence = 1 − PFA of the last accepted measurement, halved by each miss since;
* optionally (`integrate_frames` = K > 1) searches the mean of the last K γ-maps: the fog decorrelates
  from frame to frame (docs/design.md §6, the suspension's frame-to-frame decorrelation) while a target's γ
  persists, so fog peaks fall by up to √K against it. The mean's peak sits at the target's mean position
  over the window, i.e. it lags by v(K − 1)Δt/2: use K > 1 for slow targets only (moving it forward by
  the track's own velocity estimate feeds back into that estimate and was found unstable). The noise of
  a measurement keeps the current frame's C_γ (the windows overlap, their errors are correlated);
* optionally takes velocity measurements (`motion`: fpcore.velocity.VelocityEstimate, the argmax of a
  velocity dictionary around a detection or a track's prediction; docs/design.md §4.13): an estimate
  inside a track's gate whose calibrated gated PFA (γ_v² against the map's local null level, times the
  number of velocities searched) is below `p_keep` updates the track with its position (the peak of the
  motion-aware γ, noise as above) and its velocity (noise σ_v = step/√12 per axis) in one Kalman update;
  a new track starts at such an estimate's position and velocity (prior σ_v instead of
  `initial_speed_sigma`) when it was centred on the birth's peak.

Tracks follow one fingerprint each (the γ-map they live on); several tracks may share a fingerprint.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment

from .cfar import DEFAULT_CFAR, NullModel, cfar_null_model
from .geometry import from_xyz
from .grid import Grid
from .metrics import (
    border_band,
    cramer_rao_precision,
    detect,
    diffraction_resolution,
    interior_peaks,
    refine_peak,
)

__all__ = ["TrackerConfig", "TrackState", "Tracker"]


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker settings (SI units)."""

    accel_noise: float = 5e-3  # m/s², white-acceleration level of the CV model (0.5 mm/s per frame at 10 Hz)
    gate_sigma: float = 4.0  # gate radius in standard deviations of the innovation
    min_gate: float | None = None  # m; default 2 δρ_D
    p_keep: float = 1e-2  # calibrated gated PFA below which a measurement is accepted
    p_birth: float = 1e-3  # calibrated field-of-view PFA below which an unassigned peak starts a track
    confirm_hits: int = 2  # hits (birth included) after which a track is confirmed
    max_misses: int = 5
    max_tracks_per_map: int = 2
    default_dt: float = 0.1  # s, when frames carry no distinct timestamps
    initial_speed_sigma: float = 5e-3  # m/s, prior on a new track's speed
    skip_border: bool = False  # births and gates take interior local maxima only (a heuristic; module doc)
    integrate_frames: int = 1  # K: search the mean of the last K γ-maps (see module doc)
    cfar: str = DEFAULT_CFAR  # the CFAR setting of the maps it searches itself (fpcore.cfar.CFAR_NAMES)


@dataclass
class TrackState:
    """What a track publishes per frame (positions (x, y, z), y = 0 on 2D grids)."""

    track_id: int
    fingerprint: str
    position_m: list[float]
    velocity_m_s: list[float]
    covariance_m2: list[list[float]]
    confidence: float
    age: int
    status: str
    measured: bool
    gamma: float
    pfa: float
    c_gamma: float  # contrast C_γ of the last accepted measurement in its frame (0 before any)
    # σ of the last accepted measurement per axis (x, y, z), m: the Kalman measurement noise, i.e. the
    # Cramér–Rao precision δρ_D/√C_γ laterally and c0/(2Δf)/√C_γ axially, floored at the grid's
    # quantisation spacing/√12; y is 0 on 2D grids (not measured).
    precision_m: list[float]


@dataclass
class _Track:
    track_id: int
    fingerprint: str
    kf: KalmanFilter
    age: int = 0
    hits: int = 1
    misses: int = 0
    confidence: float = 0.0
    last_pfa: float = 1.0
    gamma: float = 0.0
    measured: bool = True
    c_gamma: float = 0.0
    precision: np.ndarray | None = None
    history: list[np.ndarray] = field(default_factory=list)
    confirm_hits: int = 2
    max_misses: int = 5

    @property
    def status(self) -> str:
        """tentative → confirmed (confirm_hits hits) → coasting (missed since) → lost (too many misses)."""
        if self.misses > self.max_misses:
            return "lost"
        if self.hits < self.confirm_hits:
            return "tentative"
        return "coasting" if self.misses else "confirmed"


class Tracker:
    """Multi-target tracker over γ-maps of a fixed grid."""

    def __init__(
        self,
        grid: Grid,
        wavelength: float,
        aperture: float,
        bandwidth: float,
        c0: float,
        config: TrackerConfig | None = None,
    ) -> None:
        self.grid = grid
        self.wavelength = wavelength
        self.aperture = aperture
        self.bandwidth = bandwidth
        self.c0 = c0
        self.config = config or TrackerConfig()
        self.tracks: list[_Track] = []
        self._next_id = 1
        self._last_time: float | None = None
        self._mesh = list(np.meshgrid(*grid.axes, indexing="ij"))
        mid = 0.5 * (grid.z[0] + grid.z[-1])
        self._margin = diffraction_resolution(wavelength, aperture, max(mid, wavelength))  # border band width
        self._band = border_band(grid, self._margin, self._mesh)
        self._recent: dict[str, deque[tuple[np.ndarray, np.ndarray | None]]] = {}
        if self.config.integrate_frames < 1:
            raise ValueError(f"integrate_frames: expected an integer ≥ 1, got {self.config.integrate_frames}")
        self.nd = grid.ndim

    # --- geometry helpers -------------------------------------------------------------------
    def _coords(self, r3: np.ndarray) -> np.ndarray:
        return np.asarray(r3, float)[[0, 2]] if self.nd == 2 else np.asarray(r3, float)

    def _r3(self, c: np.ndarray) -> np.ndarray:
        return np.array([c[0], 0.0, c[1]]) if self.nd == 2 else np.asarray(c, float)

    def _resolution(self, depth: float) -> tuple[float, float]:
        return diffraction_resolution(self.wavelength, self.aperture, max(depth, self.wavelength)), self.c0 / (
            2 * self.bandwidth
        )

    def _noise(self, c_gamma: float, depth: float) -> np.ndarray:
        """Measurement covariance from the Cramér–Rao precision (paper eq. loc, docs/design.md §4.10)."""
        res, ax_res = self._resolution(depth)
        lat, _ = cramer_rao_precision(self.wavelength, res, c_gamma)
        # Axial: the tracker reads the envelope |γ| peak, which does not use the carrier phase that
        # the paper's axial bound (eq. axial2) assumes; its precision scales with the envelope's axial
        # resolution c0/(2Δf), so δz = c0/(2Δf)/√C_γ (same √C_γ law as eq. loc).
        ax = ax_res / np.sqrt(max(c_gamma, 1e-12))
        # Floor: the peak is read on the grid (parabolic refinement), σ ≥ spacing/√12 per axis.
        floor = np.array(
            [d**2 / 12 if a.size > 1 else 0.0 for a, d in zip(self.grid.axes, self.grid.spacing, strict=True)]
        )
        return np.diag(np.maximum([lat**2] * (self.nd - 1) + [ax**2], floor))

    def _new_filter(self, c: np.ndarray, meas_cov: np.ndarray) -> KalmanFilter:
        nd = self.nd
        kf = KalmanFilter(dim_x=2 * nd, dim_z=nd)
        kf.x = np.concatenate([c, np.zeros(nd)])
        kf.H = np.hstack([np.eye(nd), np.zeros((nd, nd))])
        kf.P = np.block(
            [[meas_cov, np.zeros((nd, nd))], [np.zeros((nd, nd)), np.eye(nd) * self.config.initial_speed_sigma**2]]
        )
        return kf

    def _set_dynamics(self, kf: KalmanFilter, dt: float) -> None:
        nd = self.nd
        kf.F = np.block([[np.eye(nd), dt * np.eye(nd)], [np.zeros((nd, nd)), np.eye(nd)]])
        q = self.config.accel_noise**2
        kf.Q = q * np.block(
            [[dt**4 / 4 * np.eye(nd), dt**3 / 2 * np.eye(nd)], [dt**3 / 2 * np.eye(nd), dt**2 * np.eye(nd)]]
        )

    # --- per-frame update -------------------------------------------------------------------
    def _dt(self, timestamp: float | None) -> float:
        if timestamp is not None and self._last_time is not None and timestamp > self._last_time:
            return timestamp - self._last_time
        return self.config.default_dt

    def predictions(self, timestamp: float | None = None) -> list[tuple[str, np.ndarray]]:
        """(fingerprint, predicted position (x, y, z)) of every live track at ``timestamp``, without
        advancing the tracker (where a velocity dictionary is searched before :meth:`update`)."""
        dt = self._dt(timestamp)
        out = []
        for tr in self.tracks:
            if tr.status != "lost":
                x = tr.kf.x
                out.append((tr.fingerprint, self._r3(x[: self.nd] + dt * x[self.nd :])))
        return out

    def update(
        self,
        gamma_maps: dict[str, np.ndarray],
        timestamp: float | None = None,
        levels: dict[str, tuple[np.ndarray, np.ndarray | None]] | None = None,
        nulls: dict[str, NullModel] | None = None,
        motion: dict[str, list[Any]] | None = None,
    ) -> list[TrackState]:
        """Advance all tracks with this frame's γ-maps (one per fingerprint name).

        levels: per name, (null level of γ², visible nodes) from fpcore.background.NullLevel — the
        physical background the significance is measured against (default: the CFAR alone); nulls: the
        maps' null models already computed by the caller (fpcore.cfar.null_model; used when the tracker
        searches the current frame, i.e. integrate_frames = 1); motion: per name, velocity estimates
        (fpcore.velocity.VelocityEstimate: ``position_m``, ``velocity_m_s``, ``sigma_m_s``, ``gamma``,
        ``n_states``, ``origin_m``) used as measurements (module doc).
        """
        dt = self._dt(timestamp)
        self._last_time = timestamp if timestamp is not None else (self._last_time or 0.0) + dt
        self.tracks = [t for t in self.tracks if t.status != "lost"]  # reported lost once, last frame
        for tr in self.tracks:
            self._set_dynamics(tr.kf, dt)
            tr.kf.predict()
            tr.age += 1
        for name, gamma in gamma_maps.items():
            g = np.asarray(gamma, np.float32)
            if g.shape != self.grid.shape:
                raise ValueError(f"gamma_maps[{name!r}]: expected shape {self.grid.shape}, got {g.shape}")
            level, visible = (levels or {}).get(name, (None, None))
            recent = self._recent.setdefault(name, deque(maxlen=self.config.integrate_frames))
            recent.append((g, level))
            if len(recent) > 1:
                searched = np.mean([m for m, _ in recent], axis=0)
                known = [v for _, v in recent if v is not None]
                lv = np.mean(known, axis=0) if len(known) == len(recent) else None
            else:
                searched, lv = g, level
            nm = (nulls or {}).get(name) if searched is g else None
            if nm is None:
                mid = 0.5 * (self.grid.z[0] + self.grid.z[-1])
                nm = cfar_null_model(self.config.cfar, searched, self.grid, self._resolution(mid), lv, visible)
            self._update_map(name, g, searched, nm, list((motion or {}).get(name, [])))
        return self.states()

    def _gated_peak(
        self, gamma: np.ndarray, nm: NullModel, tr: _Track, allowed: np.ndarray | None
    ) -> tuple[np.ndarray, float, float, np.ndarray] | None:
        """Most significant node inside the track's gate, among the `allowed` nodes (interior local maxima)
        unless the prediction itself is in the border band: (coords, γ, calibrated gated PFA, S)."""
        kf = tr.kf
        depth = kf.x[self.nd - 1]
        res, _ = self._resolution(depth)
        s_cov = kf.H @ kf.P @ kf.H.T + self._noise(4.0, depth)  # nominal C_γ for the gate size
        radius = self.config.gate_sigma * np.sqrt(np.linalg.eigvalsh(s_cov).max())
        radius = max(radius, self.config.min_gate or 2 * res)
        pred = kf.x[: self.nd]
        d2 = sum((m - ci) ** 2 for m, ci in zip(self._mesh, pred, strict=True))
        inside = (d2 <= radius**2) & nm.visible
        candidates = inside
        if allowed is not None and not self._band[self.grid.nearest_index(self._r3(pred))]:
            candidates = inside & allowed  # a border maximum is the flank of something outside
        if not candidates.any():
            return None
        masked = np.where(candidates, nm.ranking(gamma), -np.inf)
        idx = tuple(int(i) for i in np.unravel_index(int(np.argmax(masked)), gamma.shape))
        pos3, val = refine_peak(gamma, self.grid, idx)
        radius_nodes = np.array([radius / d for d in self.grid.spacing])
        p = nm.gate_pfa(float(nm.significance[idx]), radius_nodes)
        return self._coords(pos3), val, p, s_cov

    def _background_mean(self, gamma: np.ndarray, centres: list[np.ndarray]) -> float:
        """mean(γ) outside 2 δρ_D of every track: the denominator of C_γ (paper's figure, §4.8)."""
        outside = np.ones(gamma.shape, bool)
        for c in centres:
            res, _ = self._resolution(c[-1])
            d2 = sum((m - ci) ** 2 for m, ci in zip(self._mesh, c, strict=True))
            outside &= d2 > (2 * res) ** 2
        g = gamma[outside] if outside.any() else gamma.ravel()
        return float(g.mean())

    def _motion_in_gate(self, tr: _Track, nm: NullModel, motion: list[Any]) -> tuple[Any, float] | None:
        """The most significant velocity estimate inside the track's gate, with its calibrated PFA: γ_v²
        against the map's local null level γ_M² (statistic T, Rayleigh tail), as a gated maximum, times
        the number of velocities searched (docs/design.md §4.13); None without one."""
        kf = tr.kf
        depth = kf.x[self.nd - 1]
        res, _ = self._resolution(depth)
        s_cov = kf.H @ kf.P @ kf.H.T + self._noise(4.0, depth)
        radius = max(self.config.gate_sigma * np.sqrt(np.linalg.eigvalsh(s_cov).max()), self.config.min_gate or 2 * res)
        radius_nodes = np.array([radius / d for d in self.grid.spacing])
        best = None
        for m in motion:
            c = from_xyz(np.asarray(m.position_m, float), self.nd)
            v = c - kf.x[: self.nd]
            if float(v @ np.linalg.solve(s_cov, v)) > self.config.gate_sigma**2 and np.linalg.norm(v) > radius:
                continue
            node = self.grid.nearest_index(np.asarray(m.position_m, float))
            t = float(m.gamma) ** 2 / max(float(nm.power[node]), 1e-30)
            n = max(float(nm.train_cells[node]), 2.0)  # CA-CFAR law of a level from n cells (fpcore.cfar)
            s = n * np.log1p(t / n)
            p = min(1.0, nm.gate_pfa(s, radius_nodes) * max(int(m.n_states), 1))
            if best is None or p < best[1]:
                best = (m, p)
        return best

    def _motion_update(self, tr: _Track, m: Any, noise: np.ndarray) -> None:
        """One Kalman update with the estimate's position (noise ``noise``) and velocity (σ_v per axis; an
        axis with σ_v = 0 was not searched and is not measured)."""
        nd = self.nd
        sig = from_xyz(np.asarray(m.sigma_m_s, float), nd)
        axes = [a for a in range(nd) if sig[a] > 0]
        H = np.zeros((nd + len(axes), 2 * nd))
        H[:nd, :nd] = np.eye(nd)
        for k, a in enumerate(axes):
            H[nd + k, nd + a] = 1.0
        vel = from_xyz(np.asarray(m.velocity_m_s, float), nd)
        z = np.concatenate([from_xyz(np.asarray(m.position_m, float), nd), vel[axes]])
        R = np.zeros((len(z), len(z)))
        R[:nd, :nd] = noise
        R[nd:, nd:] = np.diag(sig[axes] ** 2)
        tr.kf.update(z, R=R, H=H)

    def _update_map(
        self, name: str, current: np.ndarray, gamma: np.ndarray, nm: NullModel, motion: list[Any] | None = None
    ) -> None:
        """Gate, assign and update the tracks of `name` on `gamma` (the current map or the window's mean)."""
        cfg = self.config
        tracks = [t for t in self.tracks if t.fingerprint == name]
        allowed = interior_peaks(gamma, self.grid, self._margin, self._mesh) if cfg.skip_border else None
        gated = [self._gated_peak(gamma, nm, t, allowed) for t in tracks]
        centres = [t.kf.x[: self.nd] for t in tracks]
        cur_mean = self._background_mean(current, centres)
        # Candidates: each track's gated maximum; cost = Mahalanobis distance² to each track.
        cands = [g for g in gated if g is not None]
        assigned: dict[int, int] = {}
        if tracks and cands:
            cost = np.full((len(tracks), len(cands)), 1e9)
            for i, tr in enumerate(tracks):
                gate = gated[i]
                for j, (c, _, _, _) in enumerate(cands):
                    s_cov = gate[3] if gate is not None else np.eye(self.nd)
                    v = c - tr.kf.x[: self.nd]
                    m2 = float(v @ np.linalg.solve(s_cov, v))
                    if m2 <= cfg.gate_sigma**2:
                        cost[i, j] = m2
            rows, cols = linear_sum_assignment(cost)
            assigned = {int(r): int(c) for r, c in zip(rows, cols, strict=True) if cost[r, c] < 1e9}
        motion = list(motion or [])
        for i, tr in enumerate(tracks):
            found = self._motion_in_gate(tr, nm, motion) if motion else None
            if found is not None and found[1] <= cfg.p_keep:
                m, p = found
                motion = [x for x in motion if x is not m]
                c = from_xyz(np.asarray(m.position_m, float), self.nd)
                val = float(m.gamma)
                c_gamma = val / cur_mean if cur_mean > 0 else np.inf
                noise = self._noise(c_gamma, c[-1])
                self._motion_update(tr, m, noise)
            else:
                match = assigned.get(i)
                if match is None:
                    self._miss(tr)
                    continue
                c, val, p, _ = cands[match]
                if p > cfg.p_keep:
                    self._miss(tr)
                    continue
                c_gamma = self._contrast(current, gamma, c, val, cur_mean)
                noise = self._noise(c_gamma, c[-1])
                tr.kf.update(c, R=noise)
            tr.c_gamma = float(c_gamma)
            tr.precision = np.sqrt(np.diag(noise))
            tr.hits += 1
            tr.misses = 0
            tr.measured = True
            tr.gamma = val
            tr.last_pfa = p
            tr.confidence = 1.0 - p
            tr.history.append(tr.kf.x[: self.nd].copy())
        self._births(name, gamma, current, tracks, nm, motion)

    def _contrast(self, current: np.ndarray, searched: np.ndarray, c: np.ndarray, val: float, mean: float) -> float:
        """C_γ of the current frame's map at `c` against its mean `mean` (the searched map's refined
        value `val` when it is the current map; the nearest node's value otherwise)."""
        if current is not searched:
            val = float(current[self.grid.nearest_index(self._r3(c))])
        return val / mean if mean > 0 else np.inf

    def _miss(self, tr: _Track) -> None:
        tr.misses += 1
        tr.measured = False
        tr.confidence *= 0.5
        tr.history.append(tr.kf.x[: self.nd].copy())

    def _births(
        self,
        name: str,
        gamma: np.ndarray,
        current: np.ndarray,
        tracks: list[_Track],
        nm: NullModel,
        motion: list[Any] | None = None,
    ) -> None:
        cfg = self.config
        if len([t for t in tracks if t.status != "lost"]) >= cfg.max_tracks_per_map:
            return
        dets = detect(
            gamma,
            self.grid,
            self.wavelength,
            self.aperture,
            self.bandwidth,
            self.c0,
            name=name,
            n_peaks=cfg.max_tracks_per_map,
            interior=cfg.skip_border,
            max_pfa=cfg.p_birth,
            null=nm,
        )
        for det in dets:
            live = [t for t in self.tracks if t.fingerprint == name and t.status != "lost"]
            if len(live) >= cfg.max_tracks_per_map:
                break
            c = self._coords(np.array(det.position_m))
            res, _ = self._resolution(c[-1])
            if any(np.linalg.norm(t.kf.x[: self.nd] - c) < 4 * res for t in live):
                continue
            c_gamma = det.c_gamma
            if current is not gamma:  # the window's mean was searched: C_γ of the current frame (module doc)
                mean = self._background_mean(current, [self._coords(np.asarray(d.position_m)) for d in dets])
                c_gamma = self._contrast(current, gamma, c, det.gamma_max, mean)
            noise = self._noise(c_gamma, c[-1])
            near = [m for m in motion or [] if np.linalg.norm(from_xyz(np.asarray(m.origin_m), self.nd) - c) <= res]
            m = near[0] if near else None
            if m is not None:  # the velocity dictionary searched around this peak: start at its estimate
                c = from_xyz(np.asarray(m.position_m, float), self.nd)
            kf = self._new_filter(c, noise)
            if m is not None:
                sig = from_xyz(np.asarray(m.sigma_m_s, float), self.nd)
                measured = sig > 0
                kf.x[self.nd :][measured] = from_xyz(np.asarray(m.velocity_m_s, float), self.nd)[measured]
                kf.P[self.nd :, self.nd :] = np.diag(np.where(measured, sig, self.config.initial_speed_sigma) ** 2)
            tr = _Track(
                self._next_id,
                name,
                kf,
                gamma=det.gamma_max,
                last_pfa=det.pfa,
                confidence=1 - det.pfa,
                c_gamma=c_gamma,
                precision=np.sqrt(np.diag(noise)),
                confirm_hits=cfg.confirm_hits,
                max_misses=cfg.max_misses,
            )
            tr.history.append(c.copy())
            self._next_id += 1
            self.tracks.append(tr)

    def states(self) -> list[TrackState]:
        out = []
        for t in self.tracks:
            nd = self.nd
            pos = self._r3(t.kf.x[:nd])
            vel = self._r3(t.kf.x[nd:])
            cov = np.zeros((3, 3))
            sel = [0, 2] if nd == 2 else [0, 1, 2]
            cov[np.ix_(sel, sel)] = t.kf.P[:nd, :nd]
            prec = self._r3(t.precision) if t.precision is not None else np.zeros(3)
            out.append(
                TrackState(
                    t.track_id,
                    t.fingerprint,
                    pos.tolist(),
                    vel.tolist(),
                    cov.tolist(),
                    float(t.confidence),
                    t.age,
                    t.status,
                    t.measured,
                    float(t.gamma),
                    float(t.last_pfa),
                    float(t.c_gamma),
                    prec.tolist(),
                )
            )
        return out
