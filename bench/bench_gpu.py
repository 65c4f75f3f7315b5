"""GPU backend vs CPU in the same run (issue 15.5; docs/design.md §5 "GPU backend").

Measures, when a CUDA device with CuPy and cufinufft is usable:

* the 3-D γ-volume: the kernel benchmark's size (64³, 40 frequencies × 1024 output × 121 transmit
  directions; bench/bench_kernel.py) and the full-size frame's (76×76×143 grid, every band bin):
  CPU `Imager.gamma` (kernel "auto": the lattice pre-sum) vs `DeviceImager.gamma` with R_θθ copied in
  from the host, and with R_θθ already on the device;
* a frame end to end, quick (16×16 elements × 25 plane waves × 358 samples, 9.2 MB) and full-size
  (32×32 × 25 × 572, 58.6 MB): RF on the host → spectrum + projection → γ-map and confocal image
  on the host, CPU `Imager` vs `DeviceImager`.

Frames are point reflectors in the sinking-sphere scenario's geometry (`fpcore.born`): the cost does not
depend on the content. Each figure is a median over --repeat calls after a warm-up, device work
synchronised; the γ error is max |γ_GPU − γ_CPU| (γ ≤ 1). Ratios are CPU time / GPU time.

Without a usable device it prints one line saying why and exits 0. `--emulate` runs the same device
code on numpy + finufft (`fpcore.kernel_gpu.emulated_backend`): a correctness check, whose times are
CPU times, not GPU figures.

    python bench/bench_gpu.py                # on a machine with a CUDA device
    python bench/bench_gpu.py --emulate --quick
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fpcore import Grid, Imager, ImagingConfig, PlaneWaveData, PlaneWaveSequence, Probe
from fpcore.born import born_points
from fpcore.fingerprint import point_fingerprint
from fpcore.imaging_gpu import DeviceImager, DevicePlaneWaveData
from fpcore.kernel_gpu import Backend, cuda_backend, cuda_problem, emulated_backend

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_kernel import geometry_3d  # noqa: E402  (the kernel bench's 3-D size, one definition)

BAND = (1.8e6, 2.6e6)
C0, FC = 1500.0, 2.2e6


def timed(fn: Callable[[], Any], repeat: int, backend: Backend) -> float:
    """Median seconds of fn() over `repeat` calls after one warm-up, device work included."""
    fn()
    backend.synchronize()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        backend.synchronize()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def kernel_volume() -> tuple[PlaneWaveData, Grid]:
    """bench/bench_kernel.py's 3-D size (its `geometry_3d`) with speckle-like data."""
    freqs, so, si, c0, grid = geometry_3d()
    rng = np.random.default_rng(0)
    shape = (freqs.size, so.shape[0], si.shape[0])
    R = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)  # speckle-like
    return PlaneWaveData(R, freqs, so, si, c0), grid


def frame(quick: bool):
    """A sinking-sphere-sized RF frame of three points (+ noise) and its default grid (docs/design.md §3)."""
    pitch = C0 / FC / 2
    probe = Probe.matrix(16, 16, 2 * pitch, FC, 0.8e6) if quick else Probe.matrix(32, 32, pitch, FC, 0.8e6)
    fs, n_t = (6.5e6, 358) if quick else (10.4e6, 572)
    seq = PlaneWaveSequence.uniform_sines(5, 0.2, ny=5)
    pts = np.array([[-4.75e-3, 0.0, 26e-3], [4.75e-3, 0.0, 26e-3], [0.0, 1e-3, 35e-3]])
    acq = born_points(probe, seq, pts, np.array([1.0, 0.7, 0.5]), fs=fs, n_t=n_t, c0=C0, t0=20e-6, bw=0.8e6)
    acq.rf = (acq.rf + 1e-3 * np.random.default_rng(1).standard_normal(acq.rf.shape)).astype(np.float32)
    return acq, Grid.for_acquisition(acq, BAND), pts[0]


def volume_case(label: str, pw: PlaneWaveData, grid: Grid, backend: Backend, repeat: int) -> dict[str, float]:
    fp = point_fingerprint(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, r0=grid.centre_index_point())
    cfg = ImagingConfig(grid, BAND, out_sines=pw.out_sines, eps=1e-5)
    cpu = Imager(cfg)
    t = time.perf_counter()
    g_cpu = cpu.gamma(pw, fp)
    setup_cpu = time.perf_counter() - t
    t_cpu = timed(lambda: cpu.gamma(pw, fp), repeat, backend)
    dev = DeviceImager(cfg, backend=backend)
    t = time.perf_counter()
    g_dev = dev.gamma(pw, fp)
    backend.synchronize()
    setup_dev = time.perf_counter() - t
    t_in = timed(lambda: dev.gamma(pw, fp), repeat, backend)
    resident = DevicePlaneWaveData(backend.xp.asarray(pw.data), pw.freqs, pw.out_sines, pw.in_sines, pw.c0, backend)
    t_res = timed(lambda: dev.gamma(resident, fp), repeat, backend)
    err = float(np.abs(g_dev - g_cpu).max())
    n_s = pw.data.size
    print(
        f"γ-volume {label}: grid {grid.shape}, N_s = {n_s:,} ({pw.data.shape}); CPU ({type(cpu.kernel(pw)).__name__}) "
        f"{t_cpu * 1e3:.1f} ms (first call {setup_cpu:.2f} s) | device {t_in * 1e3:.1f} ms with R_θθ copied in, "
        f"{t_res * 1e3:.1f} ms resident (first call {setup_dev:.2f} s) | "
        f"ratio ×{t_cpu / t_in:.1f} / ×{t_cpu / t_res:.1f} | max |Δγ| {err:.1e}",
        flush=True,
    )
    return {"cpu": t_cpu, "device": t_in, "resident": t_res, "err": err}


def frame_case(label: str, quick: bool, backend: Backend, repeat: int) -> dict[str, float]:
    acq, grid, target = frame(quick)
    cfg = ImagingConfig(grid, BAND, eps=1e-5)
    cpu, dev = Imager(cfg), DeviceImager(cfg, backend=backend)
    pw = cpu.plane_waves(acq)
    fp = point_fingerprint(pw.freqs, pw.out_sines, pw.in_sines, acq.c0, r0=target)

    def run(im: Imager) -> tuple[np.ndarray, np.ndarray]:
        p = im.plane_waves(acq)
        return im.gamma(p, fp), im.confocal(p)

    t = time.perf_counter()
    g_cpu, c_cpu = run(cpu)
    first_cpu = time.perf_counter() - t
    t = time.perf_counter()
    g_dev, c_dev = run(dev)
    backend.synchronize()
    first_dev = time.perf_counter() - t
    stages = {}
    for name, im in (("cpu", cpu), ("device", dev)):
        stages[name] = (
            timed(lambda im=im: im.plane_waves(acq), repeat, backend),
            timed(lambda im=im: run(im), repeat, backend),
        )
    err = float(np.abs(g_dev - g_cpu).max())
    cerr = float(np.abs(c_dev - c_cpu).max() / c_cpu.max())
    (sp_c, tot_c), (sp_d, tot_d) = stages["cpu"], stages["device"]
    print(
        f"frame {label}: RF {acq.rf.shape} = {acq.rf.nbytes / 1e6:.1f} MB, R_θθ {pw.data.shape}, grid {grid.shape}; "
        f"RF → γ + confocal: CPU {tot_c * 1e3:.0f} ms "
        f"(spectrum + projection {sp_c * 1e3:.0f}; first {first_cpu:.1f} s) "
        f"| device {tot_d * 1e3:.0f} ms (spectrum + projection {sp_d * 1e3:.0f}; first {first_dev:.1f} s) "
        f"| ratio ×{tot_c / tot_d:.1f} (spectrum + projection ×{sp_c / sp_d:.1f}) | max |Δγ| {err:.1e}, "
        f"confocal {cerr:.1e} of max",
        flush=True,
    )
    return {"cpu": tot_c, "device": tot_d, "err": err}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--emulate", action="store_true", help="run the device code on numpy + finufft (correctness)")
    ap.add_argument("--quick", action="store_true", help="only the kernel-size volume and the quick frame")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per figure (median; default 5)")
    args = ap.parse_args()
    problem = cuda_problem()
    if args.emulate:
        backend = emulated_backend()
        print("bench_gpu: EMULATED — the device code on numpy + finufft (CPU times, not GPU figures)", flush=True)
    elif problem is not None:
        print(f"bench_gpu: no usable CUDA device here ({problem}); nothing measured (--emulate checks the code path)")
        return 0
    else:
        backend = cuda_backend()
        props = backend.xp.cuda.runtime.getDeviceProperties(0)
        name = props["name"].decode() if isinstance(props["name"], bytes) else props["name"]
        print(f"bench_gpu: CUDA device 0: {name}, {props['totalGlobalMem'] / 2**30:.0f} GiB", flush=True)
    pw, grid = kernel_volume()
    results = {"volume kernel-size": volume_case("kernel-size", pw, grid, backend, args.repeat)}
    results["frame quick"] = frame_case("quick", True, backend, args.repeat)
    if not args.quick:
        acq, grid_f, _ = frame(False)
        pw_f = Imager(ImagingConfig(grid_f, BAND)).plane_waves(acq)
        results["volume full-size"] = volume_case("full-size", pw_f, grid_f, backend, args.repeat)
        results["frame full-size"] = frame_case("full-size", False, backend, args.repeat)
    if backend.name == "cuda":
        pool = backend.xp.get_default_memory_pool()
        print(f"device memory pool: {pool.total_bytes() / 2**20:.0f} MiB held, {pool.used_bytes() / 2**20:.0f} in use")
    print("summary (CPU / device): " + ", ".join(f"{k} ×{v['cpu'] / v['device']:.1f}" for k, v in results.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
