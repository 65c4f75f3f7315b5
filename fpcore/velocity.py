"""Live velocity estimates: a dictionary of motion-aware fingerprints F_v over a velocity grid, evaluated
on a small region around a detection (paper, Discussion; docs/design.md §4.12, §4.13).

A target moving at v while the transmits fire at times τ_j is seen by transmit j at r + v τ_j
(``fpcore.fingerprint.moving_fingerprint``). For each v of a :class:`VelocityGrid` (symmetric about
zero, covering a stated maximum speed: no knowledge of the target's velocity is needed) γ(r, v) is
computed on a region of interest (ROI) around the detection, and the per-pixel argmax over (r, v) gives
the position at the middle of the sequence and the velocity (q_opt of docs/design.md §4.12).

Cost: one NUFFT per velocity (batched ``batch`` at a time) on the ROI only. The plan is made once per
ROI shape and spacing; the ROI is moved to each detection by the phase ramp e^{iK·p} on the weights
(a shift of the grid, fpcore.kernel.GridTransform), so no plan is rebuilt per frame. The NUFFT's
spreading cost grows with the number of samples N_f N_o N_i, not with the ROI's size.

Precision: the velocity is read on the grid, so its error is at most half a step per axis, σ_v =
step/√12 (uniform quantisation), which :class:`VelocityEstimate` reports and the tracker uses as the
velocity measurement's noise (fpcore.tracking, docs/design.md §4.13).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .acquisition import PlaneWaveData
from .fingerprint import Fingerprint, motion_ramp
from .geometry import from_xyz
from .grid import Grid
from .kernel import GridTransform, wavevectors
from .metrics import refine_peak

__all__ = ["MAX_VELOCITY_STATES", "VelocityEstimate", "VelocityGrid", "VelocitySearch"]

#: Largest number of velocities one grid may hold (each costs one NUFFT per detection and frame).
MAX_VELOCITY_STATES = 4096


@dataclass(frozen=True)
class VelocityGrid:
    """Velocities v = (i_x, i_y, i_z) · step with |v_a| ≤ max_speed[a] on each axis (x, y, z), m/s; an axis
    whose maximum is 0 is not searched (its velocity is not measured). ``roi_half_width`` (m): the
    region searched around each detection, ± this on every axis."""

    max_speed: tuple[float, float, float]
    step: float
    roi_half_width: float = 3e-3

    def __post_init__(self) -> None:
        if len(self.max_speed) != 3 or not all(math.isfinite(v) and v >= 0 for v in self.max_speed):
            raise ValueError(f"velocity grid: expected 3 maximum speeds >= 0 m/s (x, y, z), got {self.max_speed}")
        if not (math.isfinite(self.step) and self.step > 0):
            raise ValueError(f"velocity grid: expected a step > 0 m/s, got {self.step}")
        if not (math.isfinite(self.roi_half_width) and self.roi_half_width > 0):
            raise ValueError(f"velocity grid: expected a region half-width > 0 m, got {self.roi_half_width}")
        if max(self.max_speed) == 0:
            raise ValueError("velocity grid: every maximum speed is 0 (nothing to search)")
        n = self.size(3)
        if n > MAX_VELOCITY_STATES:
            raise ValueError(
                f"velocity grid: {n} velocities at a step of {self.step:g} m/s exceed {MAX_VELOCITY_STATES} "
                "(expected a larger step or smaller maximum speeds)"
            )

    def axis(self, a: int) -> np.ndarray:
        """The searched values on axis a (0 x, 1 y, 2 z): 0, ±step, … up to max_speed[a]."""
        n = int(np.floor(self.max_speed[a] / self.step + 1e-9))
        return np.arange(-n, n + 1) * self.step

    def size(self, ndim: int = 3) -> int:
        """Number of velocities on a grid of ``ndim`` dimensions (2: y is not searched)."""
        axes = (0, 2) if ndim == 2 else (0, 1, 2)
        return int(np.prod([self.axis(a).size for a in axes]))

    def velocities(self, ndim: int = 3) -> np.ndarray:
        """(N, 3) velocities (x, y, z), m/s; on a 2-D (x–z) grid v_y = 0."""
        ax = [self.axis(0), np.zeros(1) if ndim == 2 else self.axis(1), self.axis(2)]
        mesh = np.meshgrid(*ax, indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1)

    def sigma(self, ndim: int = 3) -> np.ndarray:
        """σ of the estimate per axis (x, y, z): step/√12 on a searched axis, 0 where not measured."""
        searched = [self.max_speed[0] > 0, ndim == 3 and self.max_speed[1] > 0, self.max_speed[2] > 0]
        return np.where(searched, self.step / math.sqrt(12.0), 0.0)

    def describe(self) -> str:
        vx, vy, vz = self.max_speed
        return (
            f"|v_x| ≤ {vx:g}, |v_y| ≤ {vy:g}, |v_z| ≤ {vz:g} m/s at {self.step:g} m/s, "
            f"± {self.roi_half_width * 1e3:g} mm around each detection"
        )


@dataclass(eq=False)
class VelocityEstimate:
    """The argmax over (r, v) of γ in the region around ``origin_m`` (all (x, y, z), SI)."""

    fingerprint: str
    origin_m: np.ndarray  # where the region was centred (the detection)
    position_m: np.ndarray  # the peak of γ(r, v*): the position at the middle of the sequence
    velocity_m_s: np.ndarray
    sigma_m_s: np.ndarray  # per axis; 0: not measured
    gamma: float  # γ(r*, v*)
    n_states: int
    seconds: float


class VelocitySearch:
    """The velocity dictionary of one fingerprint for one set of transmit times, evaluated per detection."""

    def __init__(
        self,
        fp: Fingerprint,
        vgrid: VelocityGrid,
        transmit_times: np.ndarray,
        batch: int = 16,
        eps: float = 1e-4,
        thin: bool = True,
    ) -> None:
        self.fp, self.vgrid, self.batch, self.eps, self.thin = fp, vgrid, max(1, int(batch)), eps, thin
        self.tau = np.asarray(transmit_times, float).reshape(-1)
        if self.tau.size != fp.in_sines.shape[0]:
            raise ValueError(
                f"transmit_times: expected {fp.in_sines.shape[0]} values (one per transmit), got {self.tau.size}"
            )
        self._kernels: dict[tuple, tuple[GridTransform, np.ndarray, list[np.ndarray], tuple]] = {}
        self._fps: dict[tuple, Fingerprint] = {}

    def _thinned(self, keep: tuple[slice, slice]) -> Fingerprint:
        """The fingerprint on the kept frequencies and output directions (cached)."""
        key = (keep[0].step, keep[1].step)
        if key not in self._fps:
            f = self.fp
            self._fps[key] = Fingerprint(
                np.ascontiguousarray(f.data[keep]),
                f.freqs[keep[0]],
                f.out_sines[keep[1]],
                f.in_sines,
                f.c0,
                f.r0,
                name=f.name,
            )
        return self._fps[key]

    def strides(self, pw: PlaneWaveData, ndim: int) -> tuple[int, int]:
        """(frequency, output-direction) strides that keep the sampled sum's aliases out of the ROI: every
        D-th sample of a uniform sampling repeats γ at the period c0/(2 D Δf) in depth (K_z ≈ 2k,
        docs/design.md §4.1) and λ_min/(D Δs) laterally (§4.2); D is the largest stride whose period is at
        least twice the ROI's width (4 × half-width). Outputs are thinned on a 2-D (x–z) grid only (a
        line of sines); 1 where the sampling is not uniform."""
        span = 4 * self.vgrid.roi_half_width

        def stride(values: np.ndarray, period_times_step: float) -> int:
            d = np.diff(values)
            if values.size < 3 or not np.allclose(d, d[0], rtol=1e-6, atol=0) or d[0] <= 0:
                return 1
            return max(1, int(np.floor(period_times_step / (d[0] * span))))

        d_f = stride(np.asarray(pw.freqs, float), pw.c0 / 2)
        out = np.asarray(pw.out_sines, float)
        d_o = 1
        if ndim == 2 and np.all(out[:, 1] == 0):
            d_o = stride(out[:, 0], pw.c0 / float(np.max(pw.freqs)))
        return d_f, d_o

    def _setup(self, pw: PlaneWaveData, spacing: tuple[float, ...]) -> tuple[GridTransform, np.ndarray, list, tuple]:
        """The NUFFT plan on the ROI centred at the origin, the kept samples' K, the ROI's axis offsets and
        the (frequency, output) index of the kept samples (:meth:`strides`)."""
        ndim = len(spacing)
        key = (ndim, tuple(float(d) for d in spacing), pw.data.shape, pw.freqs.tobytes(), pw.out_sines.tobytes())
        hit = self._kernels.get(key)
        if hit is None:
            offs = []
            for d in spacing:
                n = max(1, int(round(self.vgrid.roi_half_width / d)))
                offs.append(np.arange(-n, n + 1) * d)
            d_f, d_o = self.strides(pw, ndim) if self.thin else (1, 1)
            keep = (slice(None, None, d_f), slice(None, None, d_o))
            K = wavevectors(pw.freqs[keep[0]], pw.out_sines[keep[1]], pw.in_sines, pw.c0, ndim)
            kern = GridTransform(K, Grid.from_axes(offs), eps=self.eps, n_trans=self.batch)
            hit = self._kernels[key] = (kern, K, offs, keep)
        return hit

    def estimate(self, pw: PlaneWaveData, origin: np.ndarray, spacing: tuple[float, ...]) -> VelocityEstimate:
        """γ(r, v) on the ROI around ``origin`` (x, y, z) for every velocity of the grid; the argmax."""
        t0 = time.perf_counter()
        ndim = len(spacing)
        kern, K, offs, keep = self._setup(pw, spacing)
        fp = self._thinned(keep)
        origin = np.asarray(origin, float).reshape(3)
        p = from_xyz(origin, ndim)
        r = np.ascontiguousarray(pw.data[keep]).ravel()
        r_norm = float(np.sqrt(np.vdot(r, r).real))
        norm = math.sqrt(fp.norm2)
        # w_v = R · conj(F_v) e^{-iK·r0} / (‖R‖‖F‖), shifted to the ROI's centre p by e^{iK·p} (‖F_v‖ = ‖F‖)
        base = (r * np.exp(1j * (K @ p))).astype(np.complex64) / np.float32(max(norm, 1e-300) * max(r_norm, 1e-300))
        base *= fp.centred_conj(ndim)
        vels = self.vgrid.velocities(ndim)
        best_val, best_q, best_map = -1.0, 0, None
        w = np.zeros((self.batch, K.shape[0]), np.complex64)
        for a in range(0, len(vels), self.batch):
            idx = range(a, min(a + self.batch, len(vels)))
            w[:] = 0
            for j, q in enumerate(idx):  # conj(F_v) = conj(F) conj(F_v/F)
                w[j] = base * np.conj(motion_ramp(fp, vels[q], self.tau)).ravel()
            out = np.abs(kern(w))
            for j, q in enumerate(idx):
                m = float(out[j].max())
                if m > best_val:
                    best_val, best_q, best_map = m, q, out[j].copy()
        assert best_map is not None
        roi = Grid.from_axes([o + c for o, c in zip(offs, p, strict=True)])
        index = tuple(int(i) for i in np.unravel_index(int(np.argmax(best_map)), best_map.shape))
        pos, val = refine_peak(best_map, roi, index)
        return VelocityEstimate(
            fp.name,
            origin,
            pos,
            vels[best_q].copy(),
            self.vgrid.sigma(ndim),
            float(val),
            len(vels),
            time.perf_counter() - t0,
        )
