"""bench/foldy_lax_reference.py's first-order split: K⁽¹⁾ is the whole field of one scatterer, the redrawn
scatterers are the saved ones, and the 3-D confocal patch of background_metrics averages both lateral axes."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import background_metrics as bm  # noqa: E402
import foldy_lax_reference as flr  # noqa: E402


def slab(tmp_path: Path, ls: float, n_real: int = 2) -> tuple[flr.Setup, dict[str, np.ndarray]]:
    """A small 2-D reference: 8 elements over a 20 × 4 mm slab, 21 frequencies (about a second)."""
    s = flr.Setup(2, 8, 20e-3, 4e-3, n_real, ls_c=ls, band_lo=2.0e6, band_hi=2.4e6, t_end=20e-6, guard=5e-6)
    flr.run(s, tmp_path / "fl.npz")
    return flr.load(tmp_path / "fl.npz")


def test_first_order_is_the_whole_field_of_one_scatterer(tmp_path, monkeypatch) -> None:
    """One point: no multiple scattering, K = G t G exactly, so K − K⁽¹⁾ is only ⟨T⟩^{p_u + p_v} − 1 (its own
    forward scattering in the coherent average along the slant legs, a few per cent)."""
    one = np.array([[1.2e-3, 0.0, 7e-3]])
    monkeypatch.setattr(flr, "random_slab", lambda *a, **k: one.copy())
    s, data = slab(tmp_path, ls=1e-3, n_real=1)
    k1 = flr.single_scattering(s, data)
    kk = data["K"]
    assert k1.shape == kk.shape
    tbar = data["T"].mean(axis=0)
    p = np.hypot(s.elements()[:, 0] - one[0, 0], s.elements()[:, 2] - one[0, 2]) / one[0, 2]  # (N_u,)
    log_t = np.log(np.abs(tbar)) + 1j * np.unwrap(np.angle(tbar), axis=1)
    lt = np.array(
        [
            np.interp(one[0, 2], data["depths"], x.real) + 1j * np.interp(one[0, 2], data["depths"], x.imag)
            for x in log_t
        ]
    )
    bound = float(np.abs(np.exp((p[:, None] + p[None, :])[None] * lt[:, None, None]) - 1).max())
    err = np.abs(kk - k1).max() / np.abs(kk).max()
    assert 0 < bound < 0.1
    assert err <= 1.2 * bound + 1e-5, (err, bound)
    # reciprocity, as the full solve: K⁽¹⁾_uv = K⁽¹⁾_vu
    assert np.abs(k1 - np.swapaxes(k1, 2, 3)).max() <= 1e-5 * np.abs(k1).max()


def test_first_order_is_a_part_of_a_dense_slab(tmp_path) -> None:
    """ℓ_s = 1 mm in a 4 mm slab: the rest K − K⁽¹⁾ is not small (the comparison has something to split)."""
    s, data = slab(tmp_path, ls=1e-3, n_real=1)
    assert data["n_scatterers"][0] > 100
    k1 = flr.single_scattering(s, data)
    assert np.linalg.norm(data["K"] - k1) / np.linalg.norm(data["K"]) > 0.3


def test_redraw_checks_the_saved_counts(tmp_path) -> None:
    s, data = slab(tmp_path, ls=1e-3, n_real=1)
    data = {**data, "n_scatterers": data["n_scatterers"] + 1}
    with pytest.raises(ValueError, match="realisation 0: redrawn"):
        flr.single_scattering(s, data)


def test_confocal_profile_3d_is_the_patch_mean() -> None:
    rng = np.random.default_rng(1)
    freqs = np.arange(2.0e6, 2.4e6, 50e3)
    x = (np.arange(4) - 1.5) * 0.34e-3
    yy, xx = np.meshgrid(x, x, indexing="ij")
    el = np.stack([xx.ravel(), yy.ravel(), np.zeros(16)], axis=1)
    sines = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1]])
    v = (rng.standard_normal((2, freqs.size, 16, 3)) + 1j * rng.standard_normal((2, freqs.size, 16, 3))).astype(
        np.complex64
    )
    z = np.array([5e-3, 6e-3])
    got = bm.confocal_profile(v, freqs, el, sines, 1500.0, 3, z, 1e-3, n_lateral=3)
    g = np.linspace(-1e-3, 1e-3, 3)
    pts = np.array([[a, b, d] for a in g for b in g for d in z])
    each = bm.confocal_background(v, freqs, el, sines, 1500.0, 3, pts, per_realisation=True)
    want = each.reshape(2, 9, 2).mean(axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_command_line_overrides_the_slab_in_mm() -> None:
    args = flr.parser().parse_args(["--dim", "3", "--thickness", "10", "--width", "15", "--realisations", "2"])
    s = flr.configured(3, args)
    base = flr.setup_for(3, quick=False)
    assert (s.thickness, s.width, s.n_real) == pytest.approx((10e-3, 15e-3, 2))
    assert (s.n_side, s.ls_c, s.dim) == (base.n_side, base.ls_c, 3)


@pytest.mark.parametrize("flag", ["--thickness", "--width"])
def test_command_line_refuses_a_non_positive_length(flag, capsys) -> None:
    assert flr.main(["--dim", "3", flag, "0"]) == 2
    assert f"{flag}: expected a length in mm > 0, got 0.0" in capsys.readouterr().err


def test_second_order_is_the_direct_double_sum_and_reciprocal(tmp_path, monkeypatch) -> None:
    """Two points: K⁽²⁾_uv = Σ_{i≠j} G(u, r_i) t⟨T⟩_i^{p_ui} ⟨G⟩_ij t⟨T⟩_j^{p_vj} G(r_j, v), ⟨G⟩ = G e^{−r/2ℓ_s},
    p_ui = R_ui/z_i (the slant legs), written out pair by pair; symmetric in u, v like the full solve."""
    two = np.array([[1.2e-3, 0.0, 7e-3], [-0.9e-3, 0.0, 8.1e-3]])
    monkeypatch.setattr(flr, "random_slab", lambda *a, **k: two.copy())
    s, data = slab(tmp_path, ls=1e-3, n_real=1)
    k2 = flr.double_scattering(s, data)
    el = s.elements()
    m = 7
    f = data["freqs"][m]
    k = 2 * np.pi * f / s.c0
    t = complex(s.strength(np.array(k)))
    tbar = data["T"].mean(axis=0)[m]
    log_t = np.log(np.abs(tbar)) + 1j * np.unwrap(np.angle(tbar))
    dist = [np.hypot(el[:, 0] - p[0], el[:, 2] - p[2]) for p in two]
    lt = [np.interp(p[2], data["depths"], log_t.real) + 1j * np.interp(p[2], data["depths"], log_t.imag) for p in two]
    leg = [t * np.exp(dist[i] / two[i, 2] * lt[i]) for i in range(2)]
    g = [flr.green(k, dist[i], 2) for i in range(2)]
    r = float(np.hypot(*(two[0] - two[1])[[0, 2]]))
    inner = complex(flr.green(k, np.array(r), 2)) * np.exp(-r / (2 * float(data["ls"][m])))
    want = sum(np.outer(g[i] * leg[i], g[j] * leg[j]) * inner for i, j in ((0, 1), (1, 0)))
    np.testing.assert_allclose(k2[0, m], want, rtol=2e-4, atol=1e-6 * np.abs(want).max())
    assert np.abs(k2 - np.swapaxes(k2, 2, 3)).max() <= 1e-5 * np.abs(k2).max()
