"""GPU backend (fpcore.kernel_gpu, fpcore.imaging_gpu; docs/design.md §5 "GPU backend").

The device glue runs here on numpy + finufft (`emulated_backend`): the same code as on CuPy + cufinufft,
checked against `GridTransform`, `direct_sum` and the host `Imager`. Tests that need a CUDA device
(CuPy, cufinufft and a GPU) are skipped where none is usable, e.g. in CI.
"""

from __future__ import annotations

import numpy as np
import pytest

import fpcore.kernel_gpu as kg
from fpcore import Grid, GridTransform, Imager, ImagingConfig, PlaneWaveSequence, Probe, direct_sum
from fpcore.born import born_points
from fpcore.fingerprint import point_fingerprint
from fpcore.imaging_gpu import DeviceImager, DevicePlaneWaveData, make_imager
from fpcore.kernel_gpu import GpuTransform, cuda_problem, emulated_backend
from fpcore.likelihood import KERNELS, make_kernel
from tests.test_kernel import _geometry  # the kernel tests' speckle geometry, shared

needs_cuda = pytest.mark.skipif(cuda_problem() is not None, reason=f"GPU backend not usable here: {cuda_problem()}")


@pytest.mark.parametrize("ndim", [2, 3])
def test_emulated_device_kernel_matches_direct_sum_and_finufft(ndim: int) -> None:
    K, grid, w = _geometry(ndim, np.random.default_rng(10 + ndim))
    kern = GpuTransform(K, grid, eps=1e-5, backend=emulated_backend(nthreads=1))
    fast = kern(w)
    ref = direct_sum(w, K, grid.points()).reshape(grid.shape)
    assert fast.shape == grid.shape and fast.dtype == np.complex64
    assert np.abs(fast - ref).max() <= 1e-4 * np.abs(ref).max()
    host = GridTransform(K, grid, eps=1e-5)(w)
    assert np.abs(fast - host).max() <= 1e-4 * np.abs(ref).max()
    # execute_ramped: strengths already multiplied by the ramp (γ templates)
    assert np.allclose(kern.execute_ramped(w * kern.ramp), fast, rtol=0, atol=1e-6 * np.abs(fast).max())


def test_emulated_batch_and_bad_weights() -> None:
    K, grid, w = _geometry(2, np.random.default_rng(3))
    kern = GpuTransform(K, grid, eps=1e-5, n_trans=2, backend=emulated_backend(nthreads=1))
    maps = kern(np.stack([w, 2j * w]))
    assert maps.shape == (2, *grid.shape)
    assert np.allclose(maps[1], 2j * maps[0], rtol=0, atol=1e-5 * np.abs(maps[0]).max())
    with pytest.raises(ValueError, match="weights: expected last axis"):
        kern(w[:-1])


def _frame():
    probe = Probe.matrix(10, 10, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.uniform_sines(3, 0.1, ny=3)
    target = np.array([0.3e-3, -0.2e-3, 14e-3])
    acq = born_points(probe, seq, target[None, :], np.array([1.0]), fs=20e6, n_t=512, c0=1540.0)
    grid = Grid.centred((0.0, 0.0, 14e-3), (16, 16, 20), 0.3e-3)
    return acq, grid, target


def test_emulated_device_imager_matches_host_imager() -> None:
    acq, grid, target = _frame()
    cfg = ImagingConfig(grid, (1.8e6, 3.2e6), n_freq=24, eps=1e-5, kernel="nufft")
    host, dev = Imager(cfg), DeviceImager(cfg, backend=emulated_backend(nthreads=1))
    pw_h, pw_d = host.plane_waves(acq), dev.plane_waves(acq)
    assert isinstance(pw_d, DevicePlaneWaveData) and pw_d.shape == pw_h.data.shape
    scale = np.abs(pw_h.data).max()
    assert np.abs(pw_d.device - pw_h.data).max() <= 1e-5 * scale  # spectrum + projection (numpy FFT)
    conf_h, conf_d = host.confocal(pw_h), dev.confocal(pw_d)
    assert conf_d.dtype == np.float32
    assert np.abs(conf_d - conf_h).max() <= 1e-3 * conf_h.max()
    fp = point_fingerprint(pw_h.freqs, pw_h.out_sines, pw_h.in_sines, acq.c0, target)
    g_h, g_d = host.gamma(pw_h, fp), dev.gamma(pw_d, fp)
    assert g_d.dtype == np.float32 and g_d.shape == grid.shape
    assert np.abs(g_d - g_h).max() <= 1e-3
    assert g_d.max() <= 1.0 + 1e-5 and g_d.max() > 10 * np.median(g_d)  # the point's own fingerprint stands out
    peak = grid.position(np.unravel_index(int(g_d.argmax()), g_d.shape))
    assert np.all(np.abs(peak - target) <= 0.3e-3 * 1.0001)
    dev.forget(fp)
    assert len(dev._device_templates) == 0


def test_auto_never_picks_gpu_without_a_device(monkeypatch: pytest.MonkeyPatch) -> None:
    assert next(iter(KERNELS)) == "gpu"  # first in line for kernel="auto" …
    K, grid, _ = _geometry(2, np.random.default_rng(0))
    monkeypatch.setattr(kg, "_PROBLEM", ["no CUDA device (test)"])
    monkeypatch.setattr(kg, "_CHOICE", [])
    monkeypatch.delenv(kg.ENV_VAR, raising=False)
    assert not GpuTransform.supports(np.zeros((3, 2)), np.zeros((2, 2)), 2)  # … only where one is usable
    cfg = ImagingConfig(grid, (2e6, 3e6), kernel="auto")
    acq_pw = _pw(grid)
    assert not isinstance(Imager(cfg).kernel(acq_pw), GpuTransform)
    assert type(make_imager(cfg)) is Imager
    with pytest.raises(ValueError, match="kernel: 'gpu' needs a usable CUDA device"):
        make_kernel("gpu", acq_pw, grid, 1e-4)
    monkeypatch.setenv(kg.ENV_VAR, "gpu")  # asked for explicitly: an error, not a silent CPU run
    with pytest.raises(ValueError, match="FP_DEVICE=gpu: needs a usable CUDA device, but no CUDA device"):
        make_kernel("auto", acq_pw, grid, 1e-4)
    monkeypatch.setenv(kg.ENV_VAR, "tpu")
    with pytest.raises(ValueError, match="FP_DEVICE: expected one of auto, cpu, gpu, got 'tpu'"):
        kg.device_preference()


def test_device_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kg, "_CHOICE", [])
    monkeypatch.setenv(kg.ENV_VAR, "auto")
    monkeypatch.setattr(kg, "_PROBLEM", [None])  # pretend a device is usable: only the choice decides
    assert GpuTransform.supports(np.zeros((3, 2)), np.zeros((2, 2)), 3)
    kg.set_device("cpu")
    assert kg.device_preference() == "cpu" and not GpuTransform.supports(np.zeros((3, 2)), np.zeros((2, 2)), 3)
    import os

    assert os.environ[kg.ENV_VAR] == "cpu"  # children follow
    with pytest.raises(ValueError, match="device: expected one of auto, cpu, gpu, got 'cuda'"):
        kg.set_device("cuda")
    monkeypatch.setattr(kg, "_PROBLEM", ["CuPy is not importable (test)"])
    with pytest.raises(ValueError, match="device: 'gpu' needs a usable CUDA device, but CuPy is not importable"):
        kg.set_device("gpu")
    kg.set_device(None)
    assert kg.device_preference() == "cpu"  # back to FP_DEVICE


def test_probe_never_raises() -> None:
    problem = kg._probe()
    assert problem is None or isinstance(problem, str)
    if problem is not None:
        with pytest.raises(RuntimeError, match="GPU backend: "):
            kg.cuda_backend()


def _pw(grid: Grid):
    from fpcore import PlaneWaveData

    freqs = np.linspace(2.0e6, 3.0e6, 5)
    so = np.stack([np.linspace(-0.5, 0.5, 9), np.zeros(9)], axis=1)
    si = np.stack([np.linspace(-0.2, 0.2, 3), np.zeros(3)], axis=1)
    return PlaneWaveData(np.ones((5, 9, 3), np.complex64), freqs, so, si, 1500.0)


@needs_cuda
@pytest.mark.parametrize("ndim", [2, 3])
def test_cuda_kernel_matches_direct_sum(ndim: int) -> None:
    K, grid, w = _geometry(ndim, np.random.default_rng(20 + ndim))
    fast = GpuTransform(K, grid, eps=1e-5)(w)
    ref = direct_sum(w, K, grid.points()).reshape(grid.shape)
    assert np.abs(fast - ref).max() <= 1e-4 * np.abs(ref).max()


@needs_cuda
def test_cuda_imager_matches_host_imager() -> None:
    acq, grid, target = _frame()
    cfg = ImagingConfig(grid, (1.8e6, 3.2e6), n_freq=24, eps=1e-5, kernel="nufft")
    host, dev = Imager(cfg), DeviceImager(cfg)
    pw_h, pw_d = host.plane_waves(acq), dev.plane_waves(acq)
    fp = point_fingerprint(pw_h.freqs, pw_h.out_sines, pw_h.in_sines, acq.c0, target)
    assert np.abs(dev.gamma(pw_d, fp) - host.gamma(pw_h, fp)).max() <= 1e-3
    conf_h = host.confocal(pw_h)
    assert np.abs(dev.confocal(pw_d) - conf_h).max() <= 1e-3 * conf_h.max()


def test_cli_device_gpu_without_device_is_one_line(monkeypatch: pytest.MonkeyPatch, capsys, tmp_path) -> None:
    from services.cli import main

    monkeypatch.setattr(kg, "_CHOICE", [])
    monkeypatch.setattr(kg, "_PROBLEM", ["no CUDA device (test)"])
    rc = main(
        ["--device", "gpu", "figure", str(tmp_path / "none.mcap"), "--frame", "0", "--png", str(tmp_path / "a.png")]
    )
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err == "fp figure: error: device: 'gpu' needs a usable CUDA device, but no CUDA device (test)"
