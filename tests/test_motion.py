"""Motion-aware fingerprints (paper, Discussion; fpcore.fingerprint module doc)."""

from __future__ import annotations

import numpy as np
import pytest

import fpcore
from fpcore.acquisition import PlaneWaveSequence
from fpcore.dictionary import Dictionary
from fpcore.simulate import scenario


def _point(n_in: int = 5) -> fpcore.Fingerprint:
    freqs = np.linspace(1.8e6, 2.6e6, 9)
    out = np.stack([np.linspace(-0.5, 0.5, 16), np.zeros(16)], axis=1)
    inn = np.stack([np.linspace(-0.2, 0.2, n_in), np.zeros(n_in)], axis=1)
    return fpcore.point_fingerprint(freqs, out, inn, 1500.0, np.array([0.0, 0.0, 20e-3]))


def test_transmit_times_need_a_positive_prf() -> None:
    seq = PlaneWaveSequence(np.zeros((3, 2)), prf=1000.0)
    np.testing.assert_allclose(seq.transmit_times(), [-1e-3, 0.0, 1e-3])
    with pytest.raises(ValueError, match="prf"):
        PlaneWaveSequence(np.zeros((3, 2))).transmit_times()
    with pytest.raises(ValueError, match="prf: expected a positive"):
        PlaneWaveSequence(np.zeros((3, 2)), prf=-5.0)


def test_common_time_is_the_virtual_shift_and_zero_velocity_is_identity() -> None:
    """If every transmit fired at the same time t, F_v is F virtually shifted by v t (paper eq. BF)."""
    fp = _point()
    v, t = np.array([0.3, 0.0, -0.1]), 2e-3
    moved = fpcore.moving_fingerprint(fp, v, np.full(5, t))
    np.testing.assert_allclose(moved.data, fp.shifted(fp.r0 + v * t), rtol=0, atol=1e-5)
    same = fpcore.moving_fingerprint(fp, np.zeros(3), np.linspace(-1e-3, 1e-3, 5))
    np.testing.assert_allclose(same.data, fp.data, rtol=0, atol=1e-7)
    assert moved.state["velocity_m_s"] == pytest.approx([0.3, 0.0, -0.1])
    with pytest.raises(ValueError, match="transmit_times: expected 5"):
        fpcore.moving_fingerprint(fp, v, np.zeros(4))


def test_motion_aware_fingerprint_undoes_the_smear_of_a_fast_target() -> None:
    """A cylinder crossing 2.5 mm within one sequence: the static fingerprint's γ collapses and misplaces
    it; F_v at the true velocity restores γ (×5 or more) and the position, and a velocity dictionary's
    per-pixel argmax at the peak recovers v (on its grid)."""
    sc = scenario("fast-cylinder", quick=True, n_frames=1)
    acq = sc.frame(0)
    tg = acq.ground_truth.target("cylinder")
    r, v = tg.position, tg.velocity
    grid = fpcore.Grid.regular((r[0] - 3e-3, r[0] + 3e-3), (r[2] - 3e-3, r[2] + 3e-3), 0.1e-3)
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    pw = imager.plane_waves(acq)
    fp = sc.fingerprints(pw.out_sines)["cylinder"]
    tau = sc.sequence.transmit_times()
    g_static = imager.gamma(pw, fp)
    g_moving = imager.gamma(pw, fpcore.moving_fingerprint(fp, v, tau))
    assert g_moving.max() > 5 * g_static.max()
    peak = grid.position(np.unravel_index(int(np.argmax(g_moving)), grid.shape))
    assert np.linalg.norm(peak - r) < 0.2e-3
    velocities = [np.array([a, 0.0, b]) for a in (-0.25, 0.0, 0.25, 0.5) for b in (-0.1, 0.0, 0.1, 0.2)]
    res = Dictionary([fpcore.moving_fingerprint(fp, u, tau) for u in velocities]).evaluate(imager, pw)
    idx = np.unravel_index(int(np.argmax(res.gamma_max)), grid.shape)
    assert res.states[int(res.best[idx])]["velocity_m_s"] == pytest.approx(list(v), abs=1e-9)
