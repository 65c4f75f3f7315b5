"""Scenarios and the statistical multiple-scattering background: frames, ground truth, calibration,
reproducibility, frame-to-frame decorrelation, independence from the target, and the confocal contrast
law C_I ∝ exp(−z/ℓ_s) (paper main text eq. (1); docs/design.md §4.11, §6)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fpcore.acquisition import PlaneWaveSequence, Probe
from fpcore.simulate import (
    SCENARIOS,
    Band,
    DiffuseBackground,
    ScatteringLayer,
    TimeWindow,
    radiate_points,
    scenario,
)


@pytest.fixture(scope="module")
def sinking() -> object:
    return scenario("sinking-sphere", quick=True, seed=0, n_frames=3)


def test_sinking_sphere_frames_carry_truth(sinking) -> None:
    sc = sinking
    assert sc.band == (1.8e6, 2.6e6) and sc.n_frames == 3
    frames = list(sc.frames())
    z1 = []
    for i, acq in enumerate(frames):
        assert acq.rf.shape == (256, 25, sc.n_samples) and acq.rf.dtype == np.float32
        assert np.all(np.isfinite(acq.rf)) and acq.frame_index == i
        assert acq.fs == sc.fs and acq.t0 == sc.t0
        truth = json.loads(json.dumps(acq.truth))  # JSON-serialisable
        names = [t["name"] for t in truth["targets"]]
        assert names == ["sphere1", "sphere2"] and truth["scenario"] == "sinking-sphere"
        z1.append(truth["targets"][0]["position_m"][2])
        assert truth["targets"][1]["position_m"] == pytest.approx([4.75e-3, 0.0, 25.6e-3])  # 9.6 mm: C_I ≈ 1/77
        depth = truth["targets"][0]["depth_below_surface_m"] / truth["medium"]["ls_m"]
        assert 5.2 <= depth <= 5.6  # where the confocal contrast is within the paper's (scenarios._SPHERE_DEPTHS)
    assert z1[0] < z1[1] < z1[2]  # sinking
    assert frames[1].timestamp > frames[0].timestamp
    assert sc.frame_nbytes < 12e6


def test_calibration_is_the_target_alone_at_r0(sinking) -> None:
    sc = sinking
    cal = sc.calibration("sphere1")
    r0 = np.array(cal.truth["r0_m"])
    assert cal.truth["calibration"] and cal.truth["diameter_m"] == 10e-3
    assert cal.rf.shape == (256, 25, sc.n_samples)
    # The specular echo of the front face arrives at τ_in + τ_out (paper eq. specular_filter).
    u = np.argmin(np.linalg.norm(sc.probe.positions[:, :2] - r0[:2], axis=1))
    i = int(np.argmin(np.linalg.norm(sc.sequence.sines, axis=1)))
    front = r0 - np.array([0.0, 0.0, 5e-3])
    t_exp = (
        front[0] * sc.sequence.sines[i, 0]
        + front[1] * sc.sequence.sines[i, 1]
        + front[2] * np.sqrt(1 - np.sum(sc.sequence.sines[i] ** 2))
        + np.linalg.norm(sc.probe.positions[u] - front)
    ) / sc.c0
    t_peak = cal.times[np.argmax(np.abs(cal.rf[u, i]))]
    assert abs(t_peak - t_exp) < 1e-6
    with pytest.raises(KeyError):
        sc.calibration("nope")


def test_reproducible_and_decorrelating_frames() -> None:
    a = scenario("sinking-sphere", quick=True, seed=3, n_frames=2)
    b = scenario("sinking-sphere", quick=True, seed=3, n_frames=2)
    c = scenario("sinking-sphere", quick=True, seed=4, n_frames=2)
    f0 = a.frame(0).rf
    np.testing.assert_array_equal(f0, b.frame(0).rf)
    assert not np.allclose(f0, c.frame(0).rf)
    f1 = a.frame(1).rf
    late = a.frame(0).times > 32e-6  # multiple scattering from ≥ 6 mm below the surface
    x, y = f0[:, :, late].ravel(), f1[:, :, late].ravel()
    rho = np.dot(x, y) / np.sqrt(np.dot(x, x) * np.dot(y, y))
    assert 0.05 < rho < 0.98  # partially decorrelated by the grains' motion


def _small_2d(envelope: str = "escape", displacement: float = 0.0):
    c0, fc = 1500.0, 2.2e6
    probe = Probe.linear(32, c0 / fc / 2, fc, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(9, 0.15)
    band = Band(1.8e6, 2.6e6)
    win = TimeWindow.covering(10.4e6, 12e-6, 32e-6, guard=20e-6)
    layer = ScatteringLayer(z_surface=10e-3, ls=1.8e-3, la=8e-3, envelope=envelope, frame_displacement=displacement)
    return c0, probe, seq, band, win, layer


def test_background_level_follows_its_envelope_and_ignores_the_target() -> None:
    c0, probe, seq, band, win, layer = _small_2d()
    radius = 0.5 * probe.aperture[0]
    bg = DiffuseBackground(layer, probe.positions, seq.sines, win, band, c0, 2, radius, np.random.default_rng(0))
    v = bg.next()
    bins = win.band_bins(band)
    s = band.spectrum(win.freqs()[bins]).astype(np.float32)[:, None, None]
    rf = win.synthesize(v * s, bins)
    t = win.times()
    for a in (16e-6, 20e-6, 24e-6):
        m = (t >= a) & (t < a + 2e-6)
        tau = a + 1e-6 - 2 * layer.z_surface / c0
        model = layer.intensity(np.array([tau]), c0, radius, 2, band.pulse_energy())[0]
        assert 0.7 < rf[:, :, m].var() / model < 1.6
    r = np.array([0.0, 0.0, 14e-3])
    h = radiate_points(r[None, :], np.array([1e-3]), probe.positions, seq.sines, win.freqs()[bins], c0, 2)
    rho = abs(np.vdot(h, v)) / (np.linalg.norm(h) * np.linalg.norm(v))
    assert rho < 0.05


def test_frame_to_frame_correlation_follows_dws() -> None:
    c0, probe, seq, band, win, layer = _small_2d(displacement=40e-6)
    bg = DiffuseBackground(
        layer, probe.positions, seq.sines, win, band, c0, 2, 0.5 * probe.aperture[0], np.random.default_rng(1)
    )
    v0 = bg.next().copy()
    v1 = bg.next()
    measured = abs(np.vdot(v0, v1)) / (np.linalg.norm(v0) * np.linalg.norm(v1))
    w = (bg.envelope**2).astype(np.float64)
    expected = float(np.sum(w * bg.g1) / np.sum(w))  # intensity-weighted g₁
    assert abs(measured - expected) < 0.1


def _apodised_confocal(
    h: np.ndarray,
    probe: Probe,
    seq: PlaneWaveSequence,
    freqs: np.ndarray,
    c0: float,
    spectrum: np.ndarray,
    xs: np.ndarray,
    z: float,
) -> np.ndarray:
    """A small plane-wave confocal image (docs/design.md §4.3) with a Hann-apodised receive aperture, |s_o| ≤ 0.5."""
    k = 2 * np.pi * freqs / c0
    u = probe.positions[:, 0]
    so = np.linspace(-0.5, 0.5, 41)
    w = np.hanning(u.size + 2)[1:-1]
    p = np.exp(-1j * k[:, None, None] * so[None, :, None] * u[None, None, :]) * w
    r = p @ (h * spectrum[:, None, None])
    si = seq.sines[:, 0]
    ci, co = np.sqrt(1 - si**2), np.sqrt(1 - so**2)
    out = []
    for x in xs:
        ph = np.exp(
            1j
            * k[:, None, None]
            * ((so[None, :, None] + si[None, None, :]) * x + (co[None, :, None] + ci[None, None, :]) * z)
        )
        out.append(abs(np.sum(r * ph)) ** 2)
    return np.array(out)


def test_confocal_contrast_falls_as_exp_minus_z_over_ls() -> None:
    """Point target at depths z − z_s = 1…5 ℓ_s: C_I = I_target/⟨I_background⟩ decays with a length ≈ ℓ_s."""
    c0, probe, seq, band, win, layer = _small_2d()
    bins = win.band_bins(band)
    f = win.freqs()[bins]
    spec = band.spectrum(f)
    depths = np.arange(1, 6) * layer.ls
    xs = np.linspace(-2e-3, 2e-3, 9)
    backgrounds = [
        DiffuseBackground(
            layer, probe.positions, seq.sines, win, band, c0, 2, 0.5 * probe.aperture[0], np.random.default_rng(s)
        ).next()
        for s in range(4)
    ]
    contrast = []
    for d in depths:
        r = np.array([0.0, 0.0, layer.z_surface + d])
        h0 = radiate_points(r[None, :], np.array([1e-3]), probe.positions, seq.sines, f, c0, 2)
        h = layer.attenuate(h0, r, 0.0, probe.positions, seq.sines)
        # Target intensity relative to the same target in water: removes the free-space range loss.
        i_t = (
            _apodised_confocal(h, probe, seq, f, c0, spec, np.array([0.0]), r[2])[0]
            / _apodised_confocal(h0, probe, seq, f, c0, spec, np.array([0.0]), r[2])[0]
        )
        i_m = np.mean([_apodised_confocal(v, probe, seq, f, c0, spec, xs, r[2]).mean() for v in backgrounds])
        contrast.append(i_t / i_m)
    slope = np.polyfit(depths, np.log(contrast), 1)[0]
    assert abs(-1.0 / (slope * layer.ls) - 1.0) < 0.2


def test_other_scenarios_quick_smoke() -> None:
    les = scenario("lesion-marker", quick=True, n_frames=1)
    acq = les.frame(0)
    assert acq.rf.shape[:2] == (256, 25) and acq.truth["targets"][0]["name"] == "marker"
    assert np.allclose(acq.truth["targets"][0]["position_m"], [3.5e-3, 4.5e-3, 32e-3])
    assert les.calibration("marker").truth["r0_m"][2] == pytest.approx(30e-3)
    mus = scenario("muscle-fibres", quick=True, n_frames=1, z_range=(12e-3, 18e-3))
    acq = mus.frame(0)
    assert acq.rf.shape[:2] == (96, 11) and acq.probe.is_linear
    assert len(acq.truth["fibres"]) > 15 and acq.truth["targets"] == []
    alphas = np.array([f["alpha_rad"] for f in acq.truth["fibres"]])
    assert alphas.min() < np.deg2rad(-10) and alphas.max() > np.deg2rad(10)  # orientation varies
    assert mus.calibration("fibre").truth["targets"][0]["kind"] == "fibre"


def test_sinking_cylinder_is_the_2d_analogue() -> None:
    sc = scenario("sinking-cylinder", quick=True, n_frames=12)
    assert sc.dim == 2 and sc.probe.is_linear and sc.probe.n_elements == 64
    first, last = sc.truth(0)["targets"], sc.truth(11)["targets"]
    assert [t["name"] for t in first] == ["cylinder1", "cylinder2"]
    assert [t["diameter_m"] for t in first] == [10e-3, 8e-3]
    assert first[0]["moving"] and not first[1]["moving"]
    # cylinder 1 settles 9.9 → 10.5 mm below the surface (as sphere 1), decelerating; cylinder 2 stays put
    assert first[0]["depth_below_surface_m"] == pytest.approx(9.9e-3)
    assert last[0]["depth_below_surface_m"] == pytest.approx(10.5e-3)
    assert last[1]["position_m"] == first[1]["position_m"]
    acq = sc.frame(0)
    assert acq.rf.shape[:2] == (64, 11) and np.all(np.isfinite(acq.rf))
    cal = sc.calibration("cylinder1")
    assert cal.truth["r0_m"] == pytest.approx([0.0, 0.0, 25e-3])  # once, in water, on the axis: not the truth
    legacy = scenario("sinking-cylinder", quick=True, n_frames=12, conventions="legacy")
    assert legacy.truth(0)["targets"][0]["depth_below_surface_m"] == pytest.approx(8e-3)
    assert legacy.calibration("cylinder1").truth["r0_m"] == legacy.truth(0)["targets"][0]["position_m"]
    # The paper's layer draws the focal return as two-point paths on the beads' grid (F6, docs/design.md §6.6: all four
    # figures against Foldy–Lax in 2-D); the legacy rig does not; one focal override replaces the set.
    for layer in (sc.layer, scenario("sinking-sphere", quick=True, n_frames=2).layer):
        assert layer is not None and layer.focal_return and layer.focal_return_pairs and layer.focal_return_shallow
        assert not layer.confocal_notch and not layer.focal_return_excess
    assert legacy.layer is not None and not legacy.layer.focal_return
    off = scenario("sinking-cylinder", quick=True, n_frames=2, focal_return=False).layer
    assert off is not None and not (off.focal_return or off.focal_return_pairs or off.focal_return_shallow)
    notch = scenario("sinking-cylinder", quick=True, n_frames=2, focal_return=True, confocal_notch=True).layer
    assert notch is not None and notch.confocal_notch and not notch.focal_return_pairs
    shallow = scenario("sinking-cylinder", quick=True, n_frames=12, depth_ls=2.0)
    assert shallow.truth(0)["targets"][1]["depth_below_surface_m"] == pytest.approx(3.6e-3)
    with pytest.raises(ValueError, match="depth_ls"):
        scenario("sinking-cylinder", quick=True, depth_ls=-1.0)


def test_registry_and_full_sizes() -> None:
    assert set(SCENARIOS) == {"sinking-sphere", "sinking-cylinder", "fast-cylinder", "lesion-marker", "muscle-fibres"}
    with pytest.raises(KeyError):
        scenario("nope")
    full = scenario("sinking-sphere")
    assert full.probe.n_elements == 1024 and abs(full.probe.pitch - 1500 / 2.2e6 / 2) < 1e-9
    assert 10e6 < full.frame_nbytes < 100e6 and full.fs == pytest.approx(4 * 2.6e6)
    assert scenario("muscle-fibres").frame_nbytes < 100e6
    assert scenario("lesion-marker").frame_nbytes < 100e6
