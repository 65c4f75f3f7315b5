"""Tracker on synthetic γ-maps: it follows targets where the per-frame argmax jumps to fog spikes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from fpcore import Grid
from fpcore.tracking import Tracker, TrackerConfig

LAM = 0.7e-3


def _fog(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Speckle-like background: |smoothed complex Gaussian|, mean ≈ 0.1."""
    z = gaussian_filter(rng.standard_normal(shape), 2) + 1j * gaussian_filter(rng.standard_normal(shape), 2)
    g = np.abs(z)
    return 0.1 * g / g.mean()


def _blob(grid: Grid, centre: np.ndarray, amp: float, width: float) -> np.ndarray:
    mesh = np.meshgrid(*grid.axes, indexing="ij")
    c = (centre[0], centre[2]) if grid.ndim == 2 else centre
    d2 = sum((m - ci) ** 2 for m, ci in zip(mesh, c, strict=True))
    return amp * np.exp(-d2 / (2 * width**2))


def _run(n_frames: int = 30, spike_every: int = 4):
    rng = np.random.default_rng(0)
    grid = Grid.centred((0.0, 25e-3), (120, 120), 0.15e-3)
    tracker = Tracker(grid, LAM, 20e-3, 0.8e6, 1500.0, TrackerConfig(max_tracks_per_map=2))
    v1, v2 = np.array([0.0, 0.0, 2e-3]), np.array([1e-3, 0.0, 1e-3])  # m/s
    p1, p2 = np.array([-3e-3, 0.0, 20e-3]), np.array([3e-3, 0.0, 22e-3])
    results = []
    for k in range(n_frames):
        t = 0.1 * k
        t1, t2 = p1 + v1 * t, p2 + v2 * t
        gamma = _fog(rng, grid.shape) + _blob(grid, t1, 0.45, 0.3e-3) + _blob(grid, t2, 0.4, 0.3e-3)
        if k > 2 and k % spike_every == 0:  # a fog fluctuation brighter than the targets, far away
            gamma += _blob(grid, np.array([-6e-3, 0.0, 30e-3]), 0.8, 0.25e-3)
        argmax = grid.position(np.unravel_index(int(gamma.argmax()), gamma.shape))
        states = tracker.update({"sphere": gamma.astype(np.float32)}, t)
        results.append((t1, t2, argmax, states))
    return grid, results


def test_tracks_follow_both_targets_with_stable_ids_through_fog_spikes() -> None:
    grid, results = _run()
    ids_seen: dict[int, list[float]] = {}
    argmax_failures = 0
    for k, (t1, t2, argmax, states) in enumerate(results):
        if min(np.linalg.norm(argmax - t1), np.linalg.norm(argmax - t2)) > 1e-3:
            argmax_failures += 1
        if k < 2:
            continue
        assert len(states) == 2, f"frame {k}: {len(states)} tracks"
        for s in states:
            pos = np.array(s.position_m)
            err = min(np.linalg.norm(pos - t1), np.linalg.norm(pos - t2))
            assert err < 0.5e-3, f"frame {k}: track {s.track_id} off by {err * 1e3:.2f} mm"
            ids_seen.setdefault(s.track_id, []).append(pos[0])
    assert argmax_failures >= 5  # the per-frame argmax alone jumps to the spikes
    assert len(ids_seen) == 2  # ids stable: no track was dropped and re-born
    # Each id stays on its own target (x of target 1 is −3 mm, target 2 starts at +3 mm).
    assert sorted(np.sign(np.mean(v)) for v in ids_seen.values()) == [-1.0, 1.0]


def test_velocity_and_confidence_are_estimated() -> None:
    _, results = _run(n_frames=25)
    states = {s.track_id: s for s in results[-1][3]}
    vels = sorted((s.velocity_m_s for s in states.values()), key=lambda v: v[0])
    assert np.allclose(vels[0], [0.0, 0.0, 2e-3], atol=0.6e-3)
    assert np.allclose(vels[1], [1e-3, 0.0, 1e-3], atol=0.6e-3)
    assert all(s.confidence > 0.9 and s.status == "confirmed" for s in states.values())


def _ramp_to_top(grid: Grid, amp: float) -> np.ndarray:
    """γ rising towards the top of the ROI (like γ under a suspension's surface), maximal on the border."""
    z = np.meshgrid(*grid.axes, indexing="ij")[-1]
    return amp * np.exp(-(z - grid.z[0]) / 0.5e-3)


def test_detect_finds_the_target_under_a_bright_border_without_the_heuristic() -> None:
    """γ rising towards the top border (as under a suspension's surface) holds the global maximum; the
    local significance (fpcore.cfar) still picks the target, with or without the border heuristic."""
    from fpcore import detect

    rng = np.random.default_rng(1)
    grid = Grid.centred((0.0, 25e-3), (120, 120), 0.15e-3)
    target = np.array([2e-3, 0.0, 26e-3])
    gamma = _fog(rng, grid.shape) + _ramp_to_top(grid, 0.9) + _blob(grid, target, 0.5, 0.3e-3)
    assert grid.position(np.unravel_index(int(np.argmax(gamma)), gamma.shape))[2] < grid.z[0] + 0.5e-3
    plain = detect(gamma, grid, LAM, 20e-3, 0.8e6, 1500.0)[0]
    inner = detect(gamma, grid, LAM, 20e-3, 0.8e6, 1500.0, interior=True)[0]
    assert np.linalg.norm(np.array(plain.position_m) - target) < 0.3e-3
    assert np.linalg.norm(np.array(inner.position_m) - target) < 0.3e-3


def test_births_and_gates_ignore_a_bright_border() -> None:
    """A target near γ that rises towards the ROI's top border: the track starts on the target, not on
    the border, and its gate never takes the border (the per-frame argmax always does)."""
    rng = np.random.default_rng(2)
    grid = Grid.centred((0.0, 25e-3), (120, 120), 0.15e-3)
    tracker = Tracker(grid, LAM, 20e-3, 0.8e6, 1500.0, TrackerConfig(max_tracks_per_map=1))
    p0, v = np.array([0.0, 0.0, 22e-3]), np.array([0.0, 0.0, -2e-3])  # rising towards the border
    for k in range(12):
        t = 0.1 * k
        truth = p0 + v * t
        gamma = _fog(rng, grid.shape) + _ramp_to_top(grid, 0.9) + _blob(grid, truth, 0.5, 0.3e-3)
        argmax = grid.position(np.unravel_index(int(gamma.argmax()), gamma.shape))
        assert np.linalg.norm(argmax - truth) > 2e-3
        (state,) = tracker.update({"t": gamma.astype(np.float32)}, t)
        assert state.track_id == 1
        assert np.linalg.norm(np.array(state.position_m) - truth) < 0.3e-3, f"frame {k}"


def test_integrating_frames_suppresses_decorrelating_fog_spikes() -> None:
    """Fog spikes that change every frame near a static, weak target: searching the mean of the last K
    maps keeps the track on the target where the single-frame gate can be pulled off."""
    grid = Grid.centred((0.0, 25e-3), (120, 120), 0.15e-3)
    truth = np.array([0.0, 0.0, 25e-3])

    def errors(k_frames: int) -> np.ndarray:
        rng = np.random.default_rng(3)
        tracker = Tracker(
            grid, LAM, 20e-3, 0.8e6, 1500.0, TrackerConfig(max_tracks_per_map=1, integrate_frames=k_frames)
        )
        errs = []
        for k in range(30):
            # A target significant at the default birth threshold (calibrated PFA < 1e-3 on this map: 9e-5
            # under the default compact CFAR, whose ± 2-cell window trains on fewer cells than the wide one's).
            gamma = _fog(rng, grid.shape) + _blob(grid, truth, 0.5, 0.3e-3)
            if k > 0:  # a spike brighter than the target, 0.8 mm away, at a new place every frame
                ang = rng.uniform(0, 2 * np.pi)
                gamma += _blob(grid, truth + 0.8e-3 * np.array([np.cos(ang), 0.0, np.sin(ang)]), 0.65, 0.25e-3)
            (state,) = tracker.update({"t": gamma.astype(np.float32)}, 0.1 * k)
            errs.append(np.linalg.norm(np.array(state.position_m) - truth))
        return np.array(errs)

    single, integrated = errors(1), errors(4)
    assert np.sqrt(np.mean(integrated**2)) < 0.5 * np.sqrt(np.mean(single**2))
    assert integrated.max() < 0.4e-3


def test_integrate_frames_must_be_positive() -> None:
    grid = Grid.centred((0.0, 25e-3), (20, 20), 0.15e-3)
    with pytest.raises(ValueError, match="integrate_frames"):
        Tracker(grid, LAM, 20e-3, 0.8e6, 1500.0, TrackerConfig(integrate_frames=0))


def test_tracks_the_simulated_sinking_cylinder() -> None:
    """The 2D analogue of the headline, on the simulator: each cylinder's track stays within 1 mm of the
    truth on every frame with one id, and within 1.5 × the mean Cramér–Rao radius in RMS."""
    import fpcore
    from fpcore.metrics import cramer_rao_precision, diffraction_resolution
    from fpcore.simulate import scenario

    # The 2-D analogue in its legacy conventions: in the paper's this implementation misses the cylinders (README).
    sc = scenario("sinking-cylinder", quick=True, seed=0, n_frames=10, conventions="legacy")
    grid = sc.roi.grid()  # x ±11 mm, z 20–31 mm, 0.1 mm
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    fps = sc.fingerprints(imager.out_sines_for(sc.frame(0)))
    lam = sc.c0 / sc.probe.centre_frequency
    ap = sc.probe.aperture[0]
    tracker = Tracker(grid, lam, ap, sc.band[1] - sc.band[0], sc.c0, TrackerConfig(max_tracks_per_map=1))
    errs: dict[str, list[float]] = {n: [] for n in fps}
    crs: dict[str, list[float]] = {n: [] for n in fps}
    ids: dict[str, set[int]] = {n: set() for n in fps}
    for acq in sc.frames():
        pw = imager.plane_waves(acq)
        states = {
            s.fingerprint: s for s in tracker.update({n: imager.gamma(pw, f) for n, f in fps.items()}, acq.timestamp)
        }
        for tg in acq.ground_truth.targets or []:
            s = states[tg.name]
            errs[tg.name].append(float(np.linalg.norm(np.array(s.position_m) - tg.position)))
            d_lat, d_ax = cramer_rao_precision(lam, diffraction_resolution(lam, ap, s.position_m[2]), s.c_gamma)
            crs[tg.name].append(float(np.hypot(d_lat, d_ax)))
            ids[tg.name].add(s.track_id)
    for name in fps:
        e = np.array(errs[name])
        assert e.max() < 1e-3, f"{name}: {e.max() * 1e3:.2f} mm"
        assert np.sqrt(np.mean(e**2)) <= 1.5 * np.mean(crs[name]), name
        assert len(ids[name]) == 1


@pytest.mark.timeout(20)
def test_detect_interior_on_coarse_and_thin_grids() -> None:
    """Regressions: a coarse grid (refinement may move a peak past its exclusion ball) terminates, and
    an axis thinner than two border bands is left alone rather than emptied."""
    from fpcore import detect

    rng = np.random.default_rng(4)
    coarse = Grid.regular((-10e-3, 10e-3), (15e-3, 35e-3), 2e-3)
    gamma = _fog(rng, coarse.shape) + _ramp_to_top(coarse, 0.9)
    dets = detect(gamma, coarse, LAM, 20e-3, 0.8e6, 1500.0, n_peaks=3, interior=True, exclusion_radius=0.5e-3)
    assert all(coarse.z[0] + 1e-3 < d.position_m[2] for d in dets)
    thin = Grid.regular((-5e-3, 5e-3), (24.7e-3, 25.3e-3), 0.1e-3)
    target = np.array([1e-3, 0.0, 25e-3])
    gamma = _fog(rng, thin.shape) + _blob(thin, target, 0.5, 0.3e-3)
    (det,) = detect(gamma, thin, LAM, 20e-3, 0.8e6, 1500.0, interior=True)
    assert abs(det.position_m[0] - target[0]) < 0.2e-3


def test_a_track_without_significant_measurements_coasts_then_is_lost() -> None:
    """The target vanishes after 6 frames: the track reports 'coasting' with a falling confidence, then
    'lost' once (after max_misses misses), then disappears — never a confident 1.0 on fog."""
    rng = np.random.default_rng(4)
    grid = Grid.centred((0.0, 25e-3), (120, 120), 0.15e-3)
    target = np.array([1e-3, 0.0, 25e-3])
    tracker = Tracker(grid, LAM, 20e-3, 0.8e6, 1500.0, TrackerConfig(max_tracks_per_map=1, max_misses=3))
    history = []
    for k in range(12):
        gamma = _fog(rng, grid.shape) + (_blob(grid, target, 0.5, 0.3e-3) if k < 6 else 0.0)
        history.append(tracker.update({"t": gamma.astype(np.float32)}, 0.1 * k))
    statuses = [s[0].status if s else None for s in history]
    assert statuses[0] == "tentative" and statuses[1:6] == ["confirmed"] * 5
    assert statuses[6:9] == ["coasting"] * 3
    assert statuses[9] == "lost" and statuses[10] is None
    conf = [s[0].confidence for s in history[5:10]]
    assert all(b < a for a, b in zip(conf[:-1], conf[1:], strict=True)) and conf[-1] < 0.1
