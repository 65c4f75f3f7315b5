"""Imager: kernel choice through the Kernel protocol, and bounded caches keyed by content, not id()."""

from __future__ import annotations

import gc

import numpy as np
import pytest

import fpcore.likelihood as likelihood
from fpcore import Grid, Imager, ImagingConfig, PlaneWaveData, mirror_fingerprint
from fpcore.kernel import GridTransform, Kernel
from fpcore.kernel_presum import PresumTransform

C0 = 1500.0
FREQS = np.linspace(1.8e6, 2.6e6, 12)
OUT = np.stack([np.linspace(-0.5, 0.5, 33), np.zeros(33)], axis=1)  # one lattice with the transmits
IN = np.stack([np.linspace(-0.25, 0.25, 5), np.zeros(5)], axis=1)
R = np.array([0.0, 0.0, 20e-3])
ALPHAS = np.deg2rad([-30.0, -15.0, 0.0, 15.0, 30.0, 45.0])


def _setup(kernel: str = "auto") -> tuple[ImagingConfig, PlaneWaveData]:
    grid = Grid.centred((0.0, 20e-3), (48, 40), 0.1e-3)
    scene = mirror_fingerprint(FREQS, OUT, IN, C0, 3e-3, np.deg2rad(15.0), r0=R)
    return ImagingConfig(grid, (1.8e6, 2.6e6), kernel=kernel), PlaneWaveData(scene.data, FREQS, OUT, IN, C0)


def _fp(alpha: float):
    return mirror_fingerprint(FREQS, OUT, IN, C0, 3e-3, alpha, r0=R)


def test_kernel_choice_by_name_without_isinstance(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FP_DEVICE", "cpu")  # on a CUDA machine 'auto' would take the GPU kernel first
    cfg, pw = _setup()
    auto: Kernel = Imager(cfg).kernel(pw)
    assert type(auto) is PresumTransform  # the sines lie on one lattice
    nufft: Kernel = Imager(_setup("nufft")[0]).kernel(pw)
    assert type(nufft) is GridTransform
    a, b = np.abs(auto(pw.data.ravel())), np.abs(nufft(pw.data.ravel()))
    assert np.allclose(a, b, rtol=0, atol=1e-4 * b.max())
    off = PlaneWaveData(pw.data, FREQS, OUT + np.array([[0.0123, 0.0]]) * np.linspace(0, 1, 33)[:, None] ** 2, IN, C0)
    with pytest.raises(ValueError, match="one lattice"):
        Imager(_setup("presum")[0]).kernel(off)
    assert type(Imager(cfg).kernel(off)) is GridTransform  # auto falls back to the general kernel
    with pytest.raises(ValueError, match="kernel: expected"):
        ImagingConfig(cfg.grid, cfg.band, kernel="fast")


@pytest.mark.parametrize("kernel", ["auto", "nufft"])
def test_template_cache_is_bounded_and_fresh(kernel: str) -> None:
    cfg, pw = _setup(kernel)
    imager = Imager(cfg, max_templates=3)
    fps = [_fp(a) for a in ALPHAS]
    maps = []
    for _ in range(2):
        for fp in fps:
            maps.append(imager.gamma(pw, fp))
            assert len(imager._templates) <= 3
    for fp, g in zip(fps * 2, maps, strict=True):
        ref = Imager(cfg).gamma(pw, fp)
        assert np.allclose(g, ref, rtol=0, atol=1e-5)
    assert not np.allclose(maps[0], maps[3], atol=1e-2)  # the fingerprints do give different maps
    imager.forget(fps[-1])
    assert len(imager._templates) == 2
    for i in range(6):  # new geometries: the kernel cache stays bounded too
        other = PlaneWaveData(pw.data, FREQS * (1 + 1e-3 * (i + 1)), OUT, IN, C0)
        imager.confocal(other)
        assert len(imager._kernels) <= 4


def test_a_new_fingerprint_reusing_an_id_gets_its_own_template(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg, pw = _setup()
    imager = Imager(cfg)
    # Fingerprints created and dropped one after the other: CPython hands the freed memory (and so the
    # id) to the next one; every map must still be that fingerprint's own.
    for a in ALPHAS:
        fp = _fp(a)
        got = imager.gamma(pw, fp)
        assert np.allclose(got, Imager(cfg).gamma(pw, fp), rtol=0, atol=1e-5), np.rad2deg(a)
        del fp
        gc.collect()
    # Even if every object had the same id, no template is shared between fingerprints.
    monkeypatch.setattr(likelihood, "id", lambda obj: 0, raising=False)
    first, second = _fp(ALPHAS[0]), _fp(ALPHAS[-1])
    imager = Imager(cfg)
    g1, g2 = imager.gamma(pw, first), imager.gamma(pw, second)
    assert np.allclose(g2, Imager(cfg).gamma(pw, second), rtol=0, atol=1e-5)
    assert not np.allclose(g1, g2, atol=1e-2)
    assert first.token != second.token
