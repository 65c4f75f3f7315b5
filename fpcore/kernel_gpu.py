"""GPU backend of the beamforming kernel: cufinufft + CuPy (docs/design.md §5, "GPU backend").

The sum is the one of every map (`fpcore.kernel`):

    B(r) = Σ_j w_j exp(+i K_j·r),   K_j = k_f (s_o + s_i, c_o + c_i),

evaluated on a regular grid r = r_c + n·Δ as a type-1 NUFFT with points K_j Δ (mod 2π) and strengths
w_j e^{iK_j·r_c}, exactly as `fpcore.kernel.GridTransform` does, but with the plan, the points, the
strengths and the map on a CUDA device (cufinufft's `Plan` mirrors finufft's: `Plan(1, n_modes, n_trans,
eps, dtype=...)`, `setpts(x, y, z)`, `execute(c)` on CuPy arrays).

The glue is written against a `Backend`: an array module (`xp`) and a plan factory. `cuda_backend()` is
CuPy + cufinufft; `emulated_backend()` is numpy + finufft, which runs the same glue on the CPU so tests
check it against `GridTransform` and `direct_sum` where no device exists (CI). CuPy and cufinufft are
optional (`pip install .[gpu]`) and imported lazily; `cuda_problem()` says, once per process and never
raising, why the device backend cannot run (None when it can).

Choice of device: `fp --device auto|cpu|gpu` or the FP_DEVICE environment variable (same values;
`set_device`). "auto" (default) uses the GPU kernel when a device is usable, "cpu" never does, "gpu"
requires it. `fpcore.likelihood.KERNELS` lists `GpuTransform` first, so ImagingConfig.kernel = "auto"
takes it only when `GpuTransform.supports` (a usable device, not forced to the CPU).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .grid import Grid
from .kernel import default_threads, type1_geometry, wavevectors

__all__ = [
    "Backend",
    "DEVICES",
    "ENV_VAR",
    "GpuTransform",
    "cuda_backend",
    "cuda_problem",
    "device_preference",
    "emulated_backend",
    "set_device",
]

ENV_VAR = "FP_DEVICE"
DEVICES = ("auto", "cpu", "gpu")

PlanFactory = Callable[[tuple[int, ...], int, float, str], Any]


@dataclass(frozen=True)
class Backend:
    """Where the kernel runs: `name`, array module `xp` (cupy or numpy) and a type-1 plan factory
    `make_plan(n_modes, n_trans, eps, dtype)` returning an object with finufft's `setpts`/`execute`."""

    name: str
    xp: Any
    make_plan: PlanFactory

    def to_host(self, a: Any) -> np.ndarray:
        """A numpy copy of a device array (numpy arrays pass through)."""
        return a.get() if hasattr(a, "get") and not isinstance(a, np.ndarray) else np.asarray(a)

    def synchronize(self) -> None:
        """Wait for the device's queued work (timing); nothing on the CPU."""
        if self.name == "cuda":
            self.xp.cuda.Device().synchronize()


def _upsampfac(eps: float) -> float:
    """finufft's oversampling as in `GridTransform`: 1.25 (smaller FFTs) down to eps = 1e-4, else 2."""
    return 1.25 if eps >= 1e-4 else 2.0


def emulated_backend(nthreads: int | None = None) -> Backend:
    """numpy + finufft: the GPU glue run on the CPU (tests, `bench/bench_gpu.py --emulate`)."""
    import finufft

    def make_plan(n_modes: tuple[int, ...], n_trans: int, eps: float, dtype: str) -> Any:
        return finufft.Plan(
            1,
            n_modes,
            n_trans=n_trans,
            eps=eps,
            isign=1,
            dtype=dtype,
            nthreads=nthreads or default_threads(),
            fftw=0,
            upsampfac=_upsampfac(eps),
        )

    return Backend("cpu-emulated", np, make_plan)


def cuda_backend(device_id: int = 0) -> Backend:
    """CuPy + cufinufft on CUDA device `device_id`; RuntimeError naming what is missing otherwise."""
    problem = cuda_problem()
    if problem is not None:
        raise RuntimeError(f"GPU backend: {problem}")
    import cufinufft
    import cupy

    def make_plan(n_modes: tuple[int, ...], n_trans: int, eps: float, dtype: str) -> Any:
        # cufinufft's default oversampling (2): 1.25 is not available for every cufinufft version/method
        return cufinufft.Plan(1, n_modes, n_trans=n_trans, eps=eps, isign=1, dtype=dtype, gpu_device_id=device_id)

    return Backend("cuda", cupy, make_plan)


_PROBLEM: list[str | None] = []  # cached result of the device probe (one entry once probed)


def cuda_problem() -> str | None:
    """Why the CUDA backend cannot run here (CuPy or cufinufft missing, no device, driver error), or
    None when it can. Probed once per process; never raises."""
    if not _PROBLEM:
        _PROBLEM.append(_probe())
    return _PROBLEM[0]


def _probe() -> str | None:
    try:
        import cupy
    except Exception as exc:  # ImportError, or a CUDA library that fails to load
        return f"CuPy is not importable ({type(exc).__name__}: {exc}); install the 'gpu' extra"
    try:
        n = int(cupy.cuda.runtime.getDeviceCount())
    except Exception as exc:  # no driver, no device
        return f"no CUDA device ({type(exc).__name__}: {exc})"
    if n < 1:
        return "no CUDA device (cupy.cuda.runtime.getDeviceCount() = 0)"
    try:
        import cufinufft  # noqa: F401
    except Exception as exc:
        return f"cufinufft is not importable ({type(exc).__name__}: {exc}); install the 'gpu' extra"
    return None


_CHOICE: list[str] = []  # set_device's choice (overrides FP_DEVICE when set)


def set_device(choice: str | None) -> None:
    """Device for the kernels of this process: 'auto', 'cpu' or 'gpu' (None: back to FP_DEVICE). The
    choice is exported in FP_DEVICE so that child processes follow it. 'gpu' without a usable device is
    a ValueError saying why."""
    _CHOICE.clear()
    if choice is None:
        return
    if choice not in DEVICES:
        raise ValueError(f"device: expected one of {', '.join(DEVICES)}, got {choice!r}")
    if choice == "gpu" and cuda_problem() is not None:
        raise ValueError(f"device: 'gpu' needs a usable CUDA device, but {cuda_problem()}")
    _CHOICE.append(choice)
    os.environ[ENV_VAR] = choice


def device_preference() -> str:
    """The device choice: `set_device`'s, else FP_DEVICE, else 'auto' (ValueError for another value)."""
    if _CHOICE:
        return _CHOICE[0]
    value = os.environ.get(ENV_VAR, "").strip().lower() or "auto"
    if value not in DEVICES:
        raise ValueError(f"{ENV_VAR}: expected one of {', '.join(DEVICES)}, got {value!r}")
    return value


def _device_usable() -> bool:
    """True when the GPU kernel should run: not forced to the CPU and a device is usable. FP_DEVICE=gpu
    without a usable device is a ValueError (asked for explicitly, never silently replaced)."""
    pref = device_preference()
    if pref == "cpu":
        return False
    problem = cuda_problem()
    if pref == "gpu" and problem is not None:
        raise ValueError(f"{ENV_VAR}=gpu: needs a usable CUDA device, but {problem}")
    return problem is None


class GpuTransform:
    """B(r) = Σ_j w_j e^{iK_j·r} on a regular grid by a type-1 NUFFT on a `Backend` (default: CUDA).

    Same conventions as `fpcore.kernel.GridTransform` (points K_j Δ mod 2π, strength ramp e^{iK·r_c}
    with the grid's index N//2 at mode 0), so both give the same map to the NUFFT accuracy `eps`.
    A `fpcore.kernel.Kernel`: `ramp` is a host array (for templates built on the host), `__call__` and
    `execute_ramped` take host or device strengths and return a host map; `map` and `execute_device`
    keep the map on the device (`fpcore.imaging_gpu.DeviceImager`).
    """

    def __init__(
        self,
        K: np.ndarray,
        grid: Grid,
        eps: float = 1e-4,
        n_trans: int = 1,
        backend: Backend | None = None,
        precision: str = "single",
    ) -> None:
        if K.shape[1] != grid.ndim:
            raise ValueError(f"K: expected {grid.ndim} components for a {grid.ndim}D grid, got {K.shape[1]}")
        if precision not in ("single", "double"):
            raise ValueError(f"precision: expected 'single' or 'double', got {precision!r}")
        self.backend = backend or cuda_backend()
        xp = self.backend.xp
        self.grid = grid
        self.n_samples = K.shape[0]
        self.n_trans = n_trans
        self.complex_dtype = np.complex64 if precision == "single" else np.complex128
        real_dtype = np.float32 if precision == "single" else np.float64
        self.ramp, pts = type1_geometry(K, grid, self.complex_dtype)  # GridTransform's conventions
        self._ramp = xp.asarray(self.ramp)
        self._pts = [xp.asarray(p.astype(real_dtype)) for p in pts]  # kept alive for the plan
        self._plan = self.backend.make_plan(grid.shape, n_trans, eps, np.dtype(self.complex_dtype).name)
        self._plan.setpts(*self._pts)

    @staticmethod
    def supports(out_sines: np.ndarray, in_sines: np.ndarray, ndim: int) -> bool:
        """Every geometry, when a CUDA device is usable and the device choice is not 'cpu'."""
        return _device_usable()

    @classmethod
    def for_geometry(
        cls, freqs: np.ndarray, out_sines: np.ndarray, in_sines: np.ndarray, c0: float, grid: Grid, eps: float
    ) -> GpuTransform:
        """The kernel of K_j = k_f (s_o + s_i, c_o + c_i) (`wavevectors`) on `grid`, on the CUDA device."""
        return cls(wavevectors(freqs, out_sines, in_sines, c0, grid.ndim), grid, eps=eps)

    def _strengths(self, w: Any) -> Any:
        xp = self.backend.xp
        w = xp.asarray(w)
        if w.shape[-1] != self.n_samples:
            raise ValueError(f"weights: expected last axis {self.n_samples}, got {w.shape}")
        return w

    def map(self, weights: Any) -> Any:
        """Σ_j w_j e^{iK_j·r} on the grid, left on the device; weights (N_s,) or (n_trans, N_s)."""
        return self.execute_device(self._strengths(weights) * self._ramp)

    def execute_device(self, c: Any) -> Any:
        """The map (on the device) of strengths already multiplied by `ramp`."""
        xp = self.backend.xp
        shape = (self.n_samples,) if self.n_trans == 1 else (self.n_trans, self.n_samples)
        c = xp.ascontiguousarray(xp.asarray(c).astype(self.complex_dtype, copy=False).reshape(shape))
        return self._plan.execute(c)

    def __call__(self, weights: Any) -> np.ndarray:
        """Host map of Σ_j w_j e^{iK_j·r}; weights (N_s,) or (n_trans, N_s), host or device."""
        return self.backend.to_host(self.map(weights))

    def execute_ramped(self, c: Any) -> np.ndarray:
        """Host map of strengths already multiplied by `ramp` (the `Kernel` protocol)."""
        return self.backend.to_host(self.execute_device(c))
