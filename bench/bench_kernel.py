"""Benchmark of the γ-map kernel, 2D and 3D, and of a mirror dictionary (issue 2 sizes).

Prints, for each size: setup time, time per γ-map (median after a warm-up), the direct-sum reference
measured in the same run (on random nodes, extrapolated to the full grid and labelled so), the
speed-up, the error against the direct sum on those nodes (relative to the map maximum), and the
peak memory of one call.
Single precision, threads from FP_THREADS (default: all cores). Run: `python bench/bench_kernel.py`.
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

from fpcore import Grid, GridTransform, Imager, ImagingConfig, PlaneWaveData, direct_sum, wavevectors
from fpcore.dictionary import Dictionary, mirror_family
from fpcore.fingerprint import point_fingerprint

try:  # structured fast path (lateral pre-sum + 1D depth NUFFT), when present
    from fpcore.kernel_presum import PresumTransform
except ImportError:  # pragma: no cover
    PresumTransform = None


def _median_time(fn, repeat: int) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _peak_mb(fn) -> float:
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def geometry_2d() -> tuple[np.ndarray, np.ndarray, np.ndarray, float, Grid]:
    """Nf = 60 (5.5–9.5 MHz), 128 output sines, 31 plane waves on one δs grid, 256×256 at λ_min/4."""
    c0, ds = 1540.0, 0.9 / 64
    freqs = np.linspace(5.5e6, 9.5e6, 60)
    so = np.stack([np.arange(-64, 64) * ds, np.zeros(128)], axis=1)
    si = np.stack([np.arange(-15, 16) * ds, np.zeros(31)], axis=1)
    h = c0 / freqs[-1] / 4
    return freqs, so, si, c0, Grid.centred((0.0, 20e-3), (256, 256), h)


def geometry_3d() -> tuple[np.ndarray, np.ndarray, np.ndarray, float, Grid]:
    """Nf = 40 (1.8–2.6 MHz), 32×32 output sines, 11×11 plane waves on one δs grid, 64³ at λ_min/4."""
    c0, ds = 1500.0, 0.04
    freqs = np.linspace(1.8e6, 2.6e6, 40)
    n = np.arange(-16, 16) * ds
    yy, xx = np.meshgrid(n, n, indexing="ij")
    so = np.stack([xx.ravel(), yy.ravel()], axis=1)
    m = np.arange(-5, 6) * ds
    yy, xx = np.meshgrid(m, m, indexing="ij")
    si = np.stack([xx.ravel(), yy.ravel()], axis=1)
    h = c0 / freqs[-1] / 4
    return freqs, so, si, c0, Grid.centred((0.0, 0.0, 25e-3), (64, 64, 64), h)


def bench_map(label: str, geom, eps: float, repeat: int, n_ref: int) -> None:
    freqs, so, si, c0, grid = geom
    rng = np.random.default_rng(0)
    shape = (len(freqs), len(so), len(si))
    R = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)  # speckle-like
    pw = PlaneWaveData(R, freqs, so, si, c0)
    fp = point_fingerprint(freqs, so, si, c0, r0=grid.centre_index_point())
    K = wavevectors(freqs, so, si, c0, grid.ndim)
    weights = (R.ravel() * fp.centred_conj(grid.ndim)).astype(np.complex64)
    n_s = K.shape[0]
    print(
        f"\n== {label}: N_s = {n_s:,} samples (Nf={len(freqs)}, N_o={len(so)}, N_i={len(si)}), "
        f"grid {grid.shape}, eps={eps:g}"
    )
    # Direct reference on n_ref random nodes, extrapolated to the full grid.
    flat = np.random.default_rng(3).choice(grid.size, n_ref, replace=False)
    sub = grid.points()[flat]
    t = time.perf_counter()
    ref = direct_sum(weights, K, sub)
    t_ref = (time.perf_counter() - t) * grid.size / n_ref
    print(f"direct sum reference: {t_ref:8.2f} s per map (measured on {n_ref} nodes, extrapolated)")
    kernels = {"finufft type-1": lambda: GridTransform(K, grid, eps=eps)}
    if PresumTransform is not None and PresumTransform.applicable(so, si):
        kernels["lateral pre-sum + 1D depth NUFFT"] = lambda: PresumTransform(freqs, so, si, c0, grid, eps=eps)
    for name, make in kernels.items():
        t = time.perf_counter()
        kern = make()
        t_setup = time.perf_counter() - t
        t_map = _median_time(lambda kern=kern: kern(weights), repeat)
        out = kern(weights)
        err = np.abs(out.ravel()[flat] - ref).max() / np.abs(out).max()
        mem = _peak_mb(lambda kern=kern: kern(weights))
        print(
            f"{name:34s} setup {t_setup * 1e3:8.1f} ms | map {t_map * 1e3:8.1f} ms | "
            f"speed-up ×{t_ref / t_map:9.0f} | err {err:.1e} of max | peak {mem:7.1f} MB"
        )
    # The whole γ-map call (Hadamard product, norms, kernel) through the Imager.
    imager = Imager(ImagingConfig(grid, (freqs[0], freqs[-1]), len(freqs), so, eps))
    t_gamma = _median_time(lambda: imager.gamma(pw, fp), repeat)
    print(f"{'Imager.gamma (auto kernel, full call)':34s} map {t_gamma * 1e3:8.1f} ms")


def bench_dictionary(eps: float, n_alpha: int, n_len: int) -> None:
    freqs, so, si, c0, grid = geometry_2d()
    rng = np.random.default_rng(1)
    shape = (len(freqs), len(so), len(si))
    R = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    pw = PlaneWaveData(R, freqs, so, si, c0)
    imager = Imager(ImagingConfig(grid, (freqs[0], freqs[-1]), len(freqs), so, eps))
    lam = c0 / freqs.mean()
    dic = Dictionary(
        family=mirror_family(np.linspace(lam, 10 * lam, n_len), np.linspace(0, np.pi, n_alpha, endpoint=False))
    )
    print(f"\n== dictionary: {len(dic)} mirror fingerprints ({n_alpha} α × {n_len} L) on the 2D size, with argmax")
    t = time.perf_counter()
    dic.evaluate(imager, pw, method="fft")
    t_first = time.perf_counter() - t
    t = time.perf_counter()
    res = dic.evaluate(imager, pw, method="fft")
    t_fft = time.perf_counter() - t
    print(f"first frame (plan + padded-grid setup included): {t_first:6.2f} s")
    sub = Dictionary(family=mirror_family(np.linspace(lam, 10 * lam, n_len)[:2], np.array([0.0, 0.7])))
    t = time.perf_counter()
    sub.evaluate(imager, pw, method="exact", batch=4)
    t_exact = (time.perf_counter() - t) / len(sub) * len(dic)
    ref = sub.evaluate(imager, pw, method="exact", keep_all=True, batch=4).per_state
    fast = sub.evaluate(imager, pw, method="fft", keep_all=True).per_state
    err = np.abs(fast - ref).max() / ref.max()
    print(
        f"next frames, FFT correlation (one NUFFT + per-state FFT): {t_fft:6.2f} s total, "
        f"{t_fft / len(dic) * 1e3:5.2f} ms/state"
    )
    print(
        f"exact NUFFT per state (measured on {len(sub)}, extrapolated): {t_exact:6.2f} s "
        f"→ speed-up ×{t_exact / t_fft:.1f}; error {err:.1e} of max; argmax map {res.best.shape}"
    )
    mem = _peak_mb(lambda: dic.evaluate(imager, pw, method="fft"))
    print(f"peak memory of the dictionary call: {mem:.0f} MB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--eps", type=float, default=1e-5, help="NUFFT accuracy (default 1e-5)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--only", choices=["2d", "3d", "dict"], default=None)
    args = ap.parse_args()
    if args.only in (None, "2d"):
        bench_map("2D", geometry_2d(), args.eps, args.repeat, n_ref=512)
    if args.only in (None, "3d"):
        bench_map("3D", geometry_3d(), args.eps, max(2, args.repeat // 2), n_ref=48)
    if args.only in (None, "dict"):
        bench_dictionary(args.eps, 50, 20)


if __name__ == "__main__":
    main()
