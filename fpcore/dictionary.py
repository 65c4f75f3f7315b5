"""Dictionaries of fingerprints over target states q and the per-pixel argmax (docs/design.md §4.12).

q_opt(r) = argmax_q γ(r, q) (paper eq. after Fig. 4: fibre orientation α and length L per pixel).

Two families:
* explicit fingerprints (e.g. calibrations of several sphere sizes): one kernel call per state;
* reflectivity models whose fingerprint depends on the sum wavevector K only, F_q(K) = ∫ w_q(r')
  e^{-iK·r'} dr' (mirrors, points). Then γ_num(r, q) = |∫ w_q(r') B(r + r') dr'| with B the complex
  confocal field (paper S7 with F ≡ 1), i.e. a correlation computed by FFT:
  one NUFFT gives B on a padded grid; per state, C = IFFT[FFT(B) · F*_q(κ) · T(κ)].
  This is exact (up to the NUFFT accuracy and an exponentially small taper tail) because B is
  band-limited: its spectrum lies on the samples K_j, and T is a C^∞ window equal to 1 on the
  support of K (after demodulation by K_c in depth) and 0 beyond it, so no aliasing enters.
  `method="exact"` evaluates every state with the NUFFT instead (the reference in the tests).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import scipy.fft as sfft

from .acquisition import PlaneWaveData
from .fingerprint import Fingerprint, mirror_response, sinc_segment
from .geometry import mirror_direction, to_xyz
from .grid import Grid
from .kernel import GridTransform, default_threads, wavevectors
from .likelihood import Imager

__all__ = ["ModelFamily", "Dictionary", "DictionaryResult", "mirror_family"]


@dataclass
class ModelFamily:
    """Fingerprints F_q(K) of a reflectivity model centred on the origin, one per state q."""

    kind: str
    states: list[dict]
    response: Callable[[np.ndarray, dict], np.ndarray]  # (K3 (N_s, 3), state) -> F_q(K) (N_s,)
    # Optional split F_q(K) = profile(project(K, q), q) where project depends on few state keys
    # (a mirror's K·t̂ depends on α only): projections are then shared by the states of a group.
    group: Callable[[dict], object] | None = None
    project: Callable[[np.ndarray, dict], np.ndarray] | None = None
    profile: Callable[[np.ndarray, dict], np.ndarray] | None = None

    def responses(self, K3: np.ndarray, indices: list[int], cache: dict) -> Iterator[np.ndarray]:
        """F_q(K) for the given states, reusing projections of a group through `cache`."""
        for q in indices:
            state = self.states[q]
            if self.project is None or self.profile is None or self.group is None:
                yield self.response(K3, state)
                continue
            key = self.group(state)
            if key not in cache:
                cache.clear()
                cache[key] = self.project(K3, state)
            yield self.profile(cache[key], state)


def mirror_family(lengths: np.ndarray, alphas: np.ndarray, azimuth: float = 0.0) -> ModelFamily:
    """Mirrors of every (α, L): F = L sinc(K·t̂ L/2π) (paper, Methods; docs/design.md §4.5)."""
    states = [{"alpha_rad": float(a), "length_m": float(L)} for a in alphas for L in lengths]

    def resp(K3: np.ndarray, q: dict) -> np.ndarray:
        return mirror_response(K3, q["length_m"], q["alpha_rad"], azimuth)

    def project(K3: np.ndarray, q: dict) -> np.ndarray:
        return K3 @ mirror_direction(q["alpha_rad"], azimuth).astype(K3.dtype)

    def profile(kt: np.ndarray, q: dict) -> np.ndarray:
        return sinc_segment(kt, q["length_m"])

    return ModelFamily("mirror", states, resp, group=lambda q: q["alpha_rad"], project=project, profile=profile)


@dataclass
class DictionaryResult:
    """Per-pixel maximum of γ over the states and the index of the best state."""

    gamma_max: np.ndarray
    best: np.ndarray
    states: list[dict]
    grid: Grid
    per_state: np.ndarray | None = field(default=None)

    def state_map(self, key: str) -> np.ndarray:
        """Map of one state parameter at the best state of each pixel (e.g. 'alpha_rad')."""
        values = np.array([q[key] for q in self.states], dtype=float)
        return values[self.best]


def _smooth_step(t: np.ndarray) -> np.ndarray:
    """C^∞ step from 0 (t ≤ 0) to 1 (t ≥ 1)."""
    t = np.clip(t, 0.0, 1.0)
    with np.errstate(divide="ignore", over="ignore"):
        a = np.where(t > 0, np.exp(-1.0 / np.where(t > 0, t, 1)), 0.0)
        b = np.where(t < 1, np.exp(-1.0 / np.where(t < 1, 1 - t, 1)), 0.0)
    return a / (a + b)


def _taper(kappa: np.ndarray, lo: float, hi: float, period: float) -> np.ndarray | None:
    """Window = 1 on [lo, hi], C^∞ to 0 across the gap to the next period; None if no gap."""
    gap = period - (hi - lo)
    if gap <= 0.1 * period:
        return None
    ramp = 0.45 * gap
    d_hi = np.mod(kappa - hi, period)  # distance above hi, going up (wrapped)
    d_lo = np.mod(lo - kappa, period)  # distance below lo, going down (wrapped)
    inside = np.mod(kappa - lo, period) <= (hi - lo)
    w = np.minimum(_smooth_step(1 - d_hi / ramp), 1.0) + np.minimum(_smooth_step(1 - d_lo / ramp), 1.0)
    return np.where(inside, 1.0, np.minimum(w, 1.0))


class Dictionary:
    """A set of fingerprints over states q; evaluate() gives γ per state and the argmax per pixel."""

    def __init__(self, fingerprints: list[Fingerprint] | None = None, family: ModelFamily | None = None) -> None:
        if (fingerprints is None) == (family is None):
            raise ValueError("dictionary: give either explicit fingerprints or a model family")
        self.fingerprints = fingerprints
        self.family = family
        self._correlators: dict[tuple, _FFTCorrelator | None] = {}  # per geometry: plans reused across frames

    @property
    def states(self) -> list[dict]:
        if self.family is not None:
            return self.family.states
        return [dict(fp.state, name=fp.name) for fp in self.fingerprints or []]

    def __len__(self) -> int:
        return len(self.states)

    def evaluate(
        self,
        imager: Imager,
        pw: PlaneWaveData,
        method: str = "auto",
        batch: int = 16,
        keep_all: bool = False,
        progress: Callable[[int, int], None] | None = None,
    ) -> DictionaryResult:
        """γ(r, q) for every state; method 'auto' | 'fft' (model families) | 'exact' (NUFFT per state)."""
        grid = imager.grid
        r = pw.data.ravel()
        r_norm = float(np.sqrt(np.vdot(r, r).real))
        best_val = np.full(grid.shape, -1.0, dtype=np.float32)
        best_idx = np.zeros(grid.shape, dtype=np.int32)
        all_maps = np.empty((len(self),) + grid.shape, np.float32) if keep_all else None
        if method not in ("auto", "fft", "exact"):
            raise ValueError(f"method: expected 'auto', 'fft' or 'exact', got {method!r}")
        family = self.family if method in ("auto", "fft") else None  # the FFT path: model families only
        maps: Iterator[tuple[int, np.ndarray]]
        if family is not None:
            key = imager.cache_key(pw)  # content, not id(imager): an id can be reused by a new imager
            if key not in self._correlators:
                self._correlators = {key: _FFTCorrelator.build(pw, grid, imager.config.eps, family)}
            corr = self._correlators[key]
            if corr is None and method == "fft":
                raise ValueError("grid: too coarse for the FFT correlation (spectrum fills the grid's band)")
            maps = corr.maps(r, r_norm, batch) if corr is not None else self._exact(imager, pw, r, r_norm, batch)
        else:
            maps = self._exact(imager, pw, r, r_norm, batch)
        n = len(self)
        for q, g in maps:
            better = g > best_val
            best_val[better] = g[better]
            best_idx[better] = q
            if all_maps is not None:
                all_maps[q] = g
            if progress is not None:
                progress(q + 1, n)
        return DictionaryResult(best_val, best_idx, self.states, grid, all_maps)

    def _exact(
        self, imager: Imager, pw: PlaneWaveData, r: np.ndarray, r_norm: float, batch: int
    ) -> Iterator[tuple[int, np.ndarray]]:
        """Every state through the NUFFT, n_trans = batch states per call (plan shared)."""
        grid = imager.grid
        K = wavevectors(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, grid.ndim)
        K3 = to_xyz(K, grid.ndim)  # (K_x, K_z) → (K_x, 0, K_z) in 2D
        n = len(self)
        fps = self.fingerprints or []  # explicit fingerprints, when there is no family
        kern = GridTransform(K, grid, eps=imager.config.eps, n_trans=batch)
        for a in range(0, n, batch):
            idx = list(range(a, min(a + batch, n)))
            w = np.zeros((batch, K.shape[0]), np.complex64)
            for j, q in enumerate(idx):
                if self.family is not None:
                    f = self.family.response(K3, self.family.states[q]).astype(np.complex64)
                    t = np.conj(f)
                else:
                    fp = fps[q]
                    t = fp.centred_conj(grid.ndim)
                    f = fp.data.ravel()
                norm = float(np.sqrt(np.vdot(f, f).real))
                w[j] = r * t / np.float32(max(norm, 1e-300) * max(r_norm, 1e-300))
            out = kern(w)
            for j, q in enumerate(idx):
                yield q, np.abs(out[j]).astype(np.float32)


@dataclass
class _FFTCorrelator:
    """The NUFFT of B on a padded grid (demodulated by K_c in depth), the window T(κ) and the true
    wavevectors of the DFT grid and of the samples at which the states' responses are evaluated."""

    kernel: GridTransform
    taper: np.ndarray
    crop: tuple[slice, ...]
    K3_of_kappa: np.ndarray
    family: ModelFamily
    shape_ext: tuple[int, ...]
    k_samples3: np.ndarray
    norms: np.ndarray | None = None  # ‖F_q‖ over the samples per state: frame-independent, made once

    def state_norms(self) -> np.ndarray:
        """‖F_q‖ = (Σ_j |F_q(K_j)|²)^½ of every state over the acquisition's samples (eq. P's denominator)."""
        if self.norms is None:
            n = len(self.family.states)
            resp = self.family.responses(self.k_samples3, list(range(n)), {})
            self.norms = np.array([float(np.sqrt(np.vdot(f, f).real)) for f in resp])
        return self.norms

    @classmethod
    def build(cls, pw: PlaneWaveData, grid: Grid, eps: float, family: ModelFamily) -> _FFTCorrelator | None:
        K = wavevectors(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, grid.ndim)
        spacing = np.asarray(grid.spacing)
        lo, hi = K.min(axis=0), K.max(axis=0)
        centre = 0.5 * (lo + hi)
        centre[:-1] = 0.0  # demodulate in depth only; lateral spectra are centred already
        periods = 2 * np.pi / spacing
        if np.any(hi - centre >= periods / 2) or np.any(lo - centre <= -periods / 2):
            return None
        # Padding: the largest model extent (from the states) plus taper tails.
        extent = max((q.get("length_m", 0.0) for q in family.states), default=0.0)
        pad = [int(np.ceil(extent / 2 / d)) + 24 for d in spacing]
        shape_ext = tuple(sfft.next_fast_len(n + 2 * p) for n, p in zip(grid.shape, pad, strict=True))
        offs = [(ne - n) // 2 for ne, n in zip(shape_ext, grid.shape, strict=True)]
        axes_ext = [
            a[0] + (np.arange(ne) - o) * d for a, ne, o, d in zip(grid.axes, shape_ext, offs, spacing, strict=True)
        ]
        ext = Grid.from_axes(axes_ext)
        kern = GridTransform(K - centre[None, :], ext, eps=eps)
        kappa, tapers = [], []
        for d, (ne, step) in enumerate(zip(shape_ext, spacing, strict=True)):
            kap = 2 * np.pi * sfft.fftfreq(ne, step)
            t = _taper(kap, lo[d] - centre[d], hi[d] - centre[d], periods[d])
            if t is None:
                return None
            kappa.append(kap)
            tapers.append(t)
        taper = tapers[0]
        for t in tapers[1:]:
            taper = np.multiply.outer(taper, t)
        mesh = np.meshgrid(*kappa, indexing="ij")
        k_true = [m + c for m, c in zip(mesh, centre, strict=True)]
        K3k = to_xyz(np.stack([k.ravel() for k in k_true], axis=1), grid.ndim)
        Ks3 = to_xyz(K, grid.ndim)
        crop = tuple(slice(o, o + n) for o, n in zip(offs, grid.shape, strict=True))
        return cls(
            kern, taper.astype(np.float32), crop, K3k.astype(np.float32), family, shape_ext, Ks3.astype(np.float32)
        )

    def maps(self, r: np.ndarray, r_norm: float, batch: int) -> Iterator[tuple[int, np.ndarray]]:
        field_ext = self.kernel(r)
        axes = tuple(range(len(self.shape_ext)))
        spec = sfft.fftn(field_ext, axes=axes, workers=default_threads()).astype(np.complex64)
        spec *= self.taper
        n = len(self.family.states)
        norms = self.state_norms()
        cache_grid: dict = {}
        for a in range(0, n, batch):
            idx = list(range(a, min(a + batch, n)))
            stack = np.empty((len(idx),) + self.shape_ext, np.complex64)
            on_grid = self.family.responses(self.K3_of_kappa, idx, cache_grid)
            for j, resp in enumerate(on_grid):
                np.multiply(spec, np.conj(resp).reshape(self.shape_ext), out=stack[j])
            out = sfft.ifftn(stack, axes=tuple(range(1, stack.ndim)), workers=default_threads(), overwrite_x=True)
            for j, q in enumerate(idx):
                m = np.abs(out[(j,) + self.crop])
                yield q, (m / np.float32(max(norms[q], 1e-300) * max(r_norm, 1e-300))).astype(np.float32)
