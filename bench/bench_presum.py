"""Benchmark: PresumTransform (lattice pre-sum, fpcore/kernel_presum.py) vs GridTransform (finufft).

    python bench/bench_presum.py [--which 2d 3d] [--threads 2] [--repeats 9] [--points 48] [--disc]

Per geometry: set-up time, first call (numba cache load or compile), time per map (median after a
warm-up), speed-up over GridTransform measured in the same run, error against direct_sum at random
nodes plus the map's peak (relative to the map maximum), and peak memory (tracemalloc, numpy buffers;
ru_maxrss for the whole process). Weights: speckle-like random complex64. docs/design.md §5.

Geometries (realistic, sines on one lattice δs):
* 2D: c0 = 1540 m/s, 60 frequencies over 5.5–9.5 MHz, 128 output sines spanning ±0.9, 31 transmit
  sines on the same δs (±12°), 256 × 256 grid at λ_min/4.
* 3D: c0 = 1500 m/s, 40 frequencies over 1.8–2.6 MHz, 32 × 32 output sines (tensor grid, |s| ≤ 0.62
  per axis), 11 × 11 transmit sines on the same δs (±11.5°), 64³ grid at λ_min/4 — 4.96 M samples.
  --disc: the probe's full angular spectrum instead (output sines on the disc |s| ≤ 0.95 of a 32 × 32
  tensor grid, δs = 1.9/31, transmits ±5 δs = ±18°; 3.9 M samples, wider depth band).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fpcore.grid import Grid  # noqa: E402
from fpcore.kernel import GridTransform, direct_sum, wavevectors  # noqa: E402
from fpcore.kernel_presum import PresumTransform  # noqa: E402


def _tensor(ax: np.ndarray) -> np.ndarray:
    yy, xx = np.meshgrid(ax, ax, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def geometry(which: str, disc: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, Grid]:
    """(freqs, out_sines, in_sines, c0, grid) of the benchmark geometries."""
    if which == "2d":
        c0, freqs = 1540.0, np.linspace(5.5e6, 9.5e6, 60)
        ds = 1.8 / 127
        so = (np.arange(128) - 63.5) * ds
        si = np.arange(-15, 16) * ds
        out, inn = np.stack([so, 0 * so], 1), np.stack([si, 0 * si], 1)
        grid = Grid.centred((0.7e-3, 25e-3), (256, 256), c0 / freqs.max() / 4)
    else:
        c0, freqs = 1500.0, np.linspace(1.8e6, 2.6e6, 40)
        ds = 1.9 / 31 if disc else 0.04
        out = _tensor((np.arange(32) - 15.5) * ds)
        if disc:
            out = out[np.sum(out**2, axis=1) <= 0.95**2]
        inn = _tensor(np.arange(-5, 6) * ds)
        grid = Grid.centred((1e-3, -0.5e-3, 30e-3), (64, 64, 64), c0 / freqs.max() / 4)
    return freqs, out, inn, c0, grid


def _timeit(fn: Callable[[], object], repeats: int) -> tuple[float, float, float]:
    """(median, min) wall ms per call after a warm-up, and median process CPU ms (all threads; less
    sensitive to other jobs on the machine)."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.min(wall)), 1e3 * float(np.median(cpu))


def _peak_mb(fn: Callable[[], object]) -> float:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def run(which: str, threads: int, repeats: int, n_points: int, disc: bool, eps: float) -> None:
    freqs, so, si, c0, grid = geometry(which, disc)
    ndim = grid.ndim
    n = freqs.size * so.shape[0] * si.shape[0]
    rng = np.random.default_rng(0)
    w = (rng.standard_normal(n) + 1j * rng.standard_normal(n)).astype(np.complex64)
    print(
        f"\n== {which.upper()}{' (disc)' if disc else ''}: {freqs.size} f × {so.shape[0]} out × {si.shape[0]} in "
        f"= {n / 1e6:.2f} M samples, grid {grid.shape}, Δ = {grid.spacing[0] * 1e6:.1f} µm, "
        f"{threads} threads, eps = {eps:g}"
    )

    t = time.perf_counter()
    P = PresumTransform(freqs, so, si, c0, grid, eps=eps, nthreads=threads)
    t_setup = time.perf_counter() - t
    t = time.perf_counter()
    B = P(w)
    t_first = time.perf_counter() - t
    med, best, cpu = _timeit(lambda: P(w), repeats)
    print(
        f"presum   ({P.lateral} lateral, σ = {P.sigma:.2f}, bands {P._glen.min()}–{P._glen.max()} bins): "
        f"setup {t_setup:.2f} s, first call {t_first:.2f} s, per map {med:.1f} ms (min {best:.1f}, "
        f"CPU {cpu:.0f} ms)"
    )
    rss_presum = _maxrss_mb()

    K = wavevectors(freqs, so, si, c0, ndim)
    t = time.perf_counter()
    G = GridTransform(K, grid, eps=eps, nthreads=threads)
    t_gsetup = time.perf_counter() - t
    Bg = G(w)
    gmed, gbest, gcpu = _timeit(lambda: G(w), max(3, repeats // 2))
    print(
        f"finufft  (GridTransform): setup {t_gsetup:.2f} s, per map {gmed:.1f} ms (min {gbest:.1f}, CPU {gcpu:.0f} ms)"
    )
    print(f"speed-up {gmed / med:.1f}× (median), {gbest / best:.1f}× (min), {gcpu / cpu:.1f}× (CPU)")

    flat = B.ravel()
    idx = np.concatenate([[int(np.argmax(np.abs(flat)))], rng.choice(flat.size, n_points, replace=False)])
    t = time.perf_counter()
    ref = direct_sum(w, K, grid.points()[idx], chunk=4)
    peak = float(np.abs(flat).max())
    err = np.abs(flat[idx] - ref).max() / peak
    gerr = np.abs(Bg.ravel()[idx] - ref).max() / peak
    print(
        f"error vs direct_sum at {idx.size} nodes (peak included), / map max: presum {err:.2e}, "
        f"finufft {gerr:.2e}; |presum − finufft| max over the map / max: "
        f"{np.abs(B - Bg).max() / peak:.2e}   ({time.perf_counter() - t:.1f} s)"
    )

    mem_setup = _peak_mb(lambda: PresumTransform(freqs, so, si, c0, grid, eps=eps, nthreads=threads))
    mem_call = _peak_mb(lambda: P(w))
    buffers = sum(v.nbytes for v in vars(P).values() if isinstance(v, np.ndarray)) / 2**20
    print(
        f"memory (presum): buffers {buffers:.0f} MB, peak during set-up {mem_setup:.0f} MB, per call "
        f"{mem_call:.1f} MB (tracemalloc); process max RSS before finufft {rss_presum:.0f} MB "
        f"(weights {w.nbytes / 2**20:.0f} MB)"
    )


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--which", nargs="+", default=["3d", "2d"], choices=["2d", "3d"])
    ap.add_argument("--threads", type=int, default=int(os.environ.get("FP_THREADS", "2")))
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--points", type=int, default=48, help="random nodes for the direct-sum check")
    ap.add_argument("--eps", type=float, default=1e-4)
    ap.add_argument("--disc", action="store_true", help="3D: disc of output sines up to 0.95 (see doc)")
    a = ap.parse_args()
    for which in a.which:
        run(which, a.threads, a.repeats, a.points, a.disc and which == "3d", a.eps)


if __name__ == "__main__":
    main()
