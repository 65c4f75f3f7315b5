"""The beamforming kernel behind every map (docs/design.md §5, paper Supplementary S7).

Every map the project computes is the same sum over the plane-wave samples j = (f, θ_out, θ_in):

    B(r) = Σ_j w_j exp(+i K_j · r),   K_j = k_f (s_o + s_i, c_o + c_i)            (docs/design.md §5)

* confocal image: w = R_θθ, I = |B|² (docs/design.md §4.3; paper eq. "confocal" and S7 eq. I_BF);
* γ-map numerator: w = R_θθ ∘ F*_θθ(r0) e^{-iK·r0}, γ ∝ |B| (paper S7 eq. gamma_BF).

On a regular grid r = r_c + n·Δ (n integer) this is a type-1 non-uniform FFT with points K_j Δ
(taken modulo 2π, which is exact at integer n) and strengths w_j e^{iK_j·r_c}. `GridTransform`
holds a finufft plan whose points are set once per acquisition geometry and grid, and reused for
every frame. `direct_sum` is the obviously-correct O(N_samples × N_points) reference.

Every kernel implements the `Kernel` protocol (`GridTransform`; `fpcore.kernel_presum.PresumTransform`
when the sines lie on one lattice), and every kernel class the `KernelType` protocol: which geometries
it serves (`supports`) and how it is built for one (`for_geometry`). `fpcore.likelihood.Imager` picks
the class by name or the first that supports the geometry (`ImagingConfig.kernel`).

Sign: with numpy's forward FFT (e^{-i2πft}) a point scatterer at r gives R_θθ ∝ e^{-iK·r}
(docs/design.md §7 stack note); the focusing phase is therefore e^{+iK·r}. tests/test_kernel.py checks
that a point's map peaks at its position.
"""

from __future__ import annotations

import os
from typing import Protocol

import numpy as np

from .geometry import cosines, from_xyz
from .grid import Grid

__all__ = ["wavevectors", "direct_sum", "GridTransform", "Kernel", "KernelType", "default_threads", "type1_geometry"]


class Kernel(Protocol):
    """B(r) = Σ_j w_j e^{iK_j·r} on `grid` for one acquisition geometry (docs/design.md §5).

    n_samples: number of samples j = (f, o, i) (C order); ramp: the strength ramp e^{iK_j·r_c} that
    `execute_ramped` expects already applied (a scalar 1 for kernels that apply it themselves).
    `__call__(w)` gives the map for raw weights; `execute_ramped(w · ramp)` the same map, for callers
    that cache w · ramp (γ templates). Maps are complex, grid-shaped.
    """

    grid: Grid
    n_samples: int
    ramp: np.ndarray

    def __call__(self, weights: np.ndarray) -> np.ndarray: ...

    def execute_ramped(self, c: np.ndarray) -> np.ndarray: ...


class KernelType(Protocol):
    """A kernel class (docs/design.md §5): whether it serves a geometry — output and transmit sines on a
    grid of `ndim` dimensions — and the kernel it builds for one (frequencies, sines, c0, grid, accuracy)."""

    def supports(self, out_sines: np.ndarray, in_sines: np.ndarray, ndim: int) -> bool: ...

    def for_geometry(
        self, freqs: np.ndarray, out_sines: np.ndarray, in_sines: np.ndarray, c0: float, grid: Grid, eps: float
    ) -> Kernel: ...


def default_threads() -> int:
    """Threads for the kernel: FP_THREADS if set, else the machine's CPU count."""
    env = os.environ.get("FP_THREADS")
    return int(env) if env else (os.cpu_count() or 1)


def wavevectors(freqs: np.ndarray, out_sines: np.ndarray, in_sines: np.ndarray, c0: float, ndim: int) -> np.ndarray:
    """K_j = k_f (s_o + s_i, c_o + c_i) for all samples, shape (N_f·N_o·N_i, ndim), order (f, o, i).

    ndim = 2 gives (K_x, K_z); ndim = 3 gives (K_x, K_y, K_z). c = √(1 − s_x² − s_y²) (docs/design.md §4).
    """
    k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
    so = np.asarray(out_sines, dtype=np.float64)
    si = np.asarray(in_sines, dtype=np.float64)
    co, ci = cosines(so), cosines(si)
    kx = k[:, None, None] * (so[None, :, None, 0] + si[None, None, :, 0])
    kz = k[:, None, None] * (co[None, :, None] + ci[None, None, :])
    if ndim == 2:
        return np.stack([kx.ravel(), kz.ravel()], axis=1)
    if ndim == 3:
        ky = k[:, None, None] * (so[None, :, None, 1] + si[None, None, :, 1])
        return np.stack([kx.ravel(), ky.ravel(), kz.ravel()], axis=1)
    raise ValueError(f"ndim: expected 2 or 3, got {ndim}")


def direct_sum(weights: np.ndarray, K: np.ndarray, points: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Reference: B(r_p) = Σ_j w_j exp(i K_j·r_p) for positions points (P, 3), in complex128."""
    w = np.asarray(weights, dtype=np.complex128).ravel()
    coords = from_xyz(np.asarray(points, dtype=np.float64).reshape(-1, 3), K.shape[1])  # K's layout
    out = np.empty(coords.shape[0], dtype=np.complex128)
    for a in range(0, coords.shape[0], chunk):
        phase = coords[a : a + chunk] @ K.T
        out[a : a + chunk] = np.exp(1j * phase) @ w
    return out


def type1_geometry(K: np.ndarray, grid: Grid, complex_dtype: type) -> tuple[np.ndarray, list[np.ndarray]]:
    """(ramp, points) of the type-1 NUFFT of `GridTransform` (module doc): the strength ramp e^{iK·r_c},
    r_c the grid's node N//2 where the index-0 mode sits (finufft/cufinufft modeord 0), and the points
    K_j Δ folded into [−π, π) per axis (exact on integer node offsets)."""
    spacing = np.asarray(grid.spacing)
    centre = grid.from_xyz(grid.centre_index_point())
    ramp = np.exp(1j * (K @ centre)).astype(complex_dtype)
    pts = [np.mod(K[:, d] * spacing[d] + np.pi, 2 * np.pi) - np.pi for d in range(grid.ndim)]
    return ramp, pts


class GridTransform:
    """B(r) = Σ_j w_j e^{iK_j·r} on a regular grid by a type-1 NUFFT (finufft), plan reused.

    K: (N_s, ndim) wavevectors (see `wavevectors`). eps: requested relative accuracy of finufft
    (errors scale with Σ|w|, not with the peak: speckle-like maps need eps ≈ 1e-4; docs/design.md §7).
    n_trans: number of weight vectors transformed per call (a dictionary batch).
    """

    def __init__(
        self,
        K: np.ndarray,
        grid: Grid,
        eps: float = 1e-4,
        n_trans: int = 1,
        nthreads: int | None = None,
        precision: str = "single",
    ) -> None:
        import finufft

        if K.shape[1] != grid.ndim:
            raise ValueError(f"K: expected {grid.ndim} components for a {grid.ndim}D grid, got {K.shape[1]}")
        self.grid = grid
        self.n_samples = K.shape[0]
        self.n_trans = n_trans
        self.complex_dtype = np.complex64 if precision == "single" else np.complex128
        real_dtype = np.float32 if precision == "single" else np.float64
        self.ramp, pts = type1_geometry(K, grid, self.complex_dtype)
        self._plan = finufft.Plan(
            1,
            grid.shape,
            n_trans=n_trans,
            eps=eps,
            isign=1,
            dtype="complex64" if precision == "single" else "complex128",
            nthreads=nthreads or default_threads(),
            fftw=0,
            upsampfac=1.25 if eps >= 1e-4 else 2.0,
        )
        self._plan.setpts(*[p.astype(real_dtype) for p in pts])

    @staticmethod
    def supports(out_sines: np.ndarray, in_sines: np.ndarray, ndim: int) -> bool:
        """Every geometry (the general kernel)."""
        return True

    @classmethod
    def for_geometry(
        cls, freqs: np.ndarray, out_sines: np.ndarray, in_sines: np.ndarray, c0: float, grid: Grid, eps: float
    ) -> GridTransform:
        """The kernel of the samples K_j = k_f (s_o + s_i, c_o + c_i) (`wavevectors`) on `grid`."""
        return cls(wavevectors(freqs, out_sines, in_sines, c0, grid.ndim), grid, eps=eps)

    def __call__(self, weights: np.ndarray) -> np.ndarray:
        """Map of Σ_j w_j e^{iK_j·r} on the grid; weights (N_s,) or (n_trans, N_s)."""
        w = np.asarray(weights)
        if w.shape[-1] != self.n_samples:
            raise ValueError(f"weights: expected last axis {self.n_samples}, got {w.shape}")
        return self.execute_ramped((w * self.ramp).astype(self.complex_dtype, copy=False))

    def execute_ramped(self, c: np.ndarray) -> np.ndarray:
        """Same map for strengths already multiplied by `ramp` (callers that cache w·ramp)."""
        if self.n_trans == 1:
            c = c.reshape(self.n_samples)
        else:
            c = c.reshape(self.n_trans, self.n_samples)
        return self._plan.execute(np.ascontiguousarray(c))
