"""Default imaging grid of an acquisition: covers the record's depths and the transmit fan (docs/design.md §3)."""

from __future__ import annotations

import numpy as np

from fpcore import Acquisition, Grid, PlaneWaveSequence, Probe


def _acq(probe: Probe, seq: PlaneWaveSequence) -> Acquisition:
    rf = np.zeros((probe.n_elements, seq.n_waves, 400), np.float32)
    return Acquisition(rf, 10e6, 10e-6, 1500.0, probe, seq, truth={"band_hz": [1.8e6, 2.6e6]})


def test_default_grid_covers_record_depths_and_fan() -> None:
    probe = Probe.linear(32, 0.3e-3, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.from_angles([-10.0, 0.0, 10.0])
    acq = _acq(probe, seq)
    band = acq.default_band()
    assert band == (1.8e6, 2.6e6)  # the simulated frame's own band wins over the probe's
    g = Grid.for_acquisition(acq, band)
    assert g.ndim == 2
    z0, z1 = 1500.0 * acq.times[0] / 2, 1500.0 * acq.times[-1] / 2
    assert g.z[0] >= z0 - 1e-12 and abs(g.z[-1] - z1) <= g.spacing[1]
    ax = probe.aperture[0]
    assert ax / 2 < g.x[-1] <= ax  # widened by the fan, at most twice the half-aperture
    assert np.isclose(g.spacing[0], 1500.0 / 2.6e6 / 3)
    fixed = Grid.for_acquisition(acq, band, x_range=(-1e-3, 1e-3), z_range=(5e-3, 6e-3), spacing=1e-4)
    assert fixed.shape == (21, 11)


def test_default_band_is_the_probe_band_without_truth() -> None:
    probe = Probe.matrix(4, 4, 0.3e-3, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.from_angles([0.0], [0.0])
    acq = _acq(probe, seq)
    acq.truth = {}
    assert acq.default_band() == (1.8e6, 2.6e6)
    assert Grid.for_acquisition(acq, acq.default_band()).ndim == 3


def test_scenario_regions_of_interest() -> None:
    import pytest

    from fpcore import Roi
    from fpcore.simulate import scenario

    sphere = scenario("sinking-sphere", quick=True).roi
    assert sphere is not None
    g = sphere.grid()
    ref = Grid.regular((-11e-3, 11e-3), (20e-3, 31e-3), 0.25e-3, y_range=(-5e-3, 5e-3))
    assert g.shape == ref.shape == (89, 41, 45)
    assert all(np.array_equal(a, b) for a, b in zip(g.axes, ref.axes, strict=True))
    assert np.allclose(sphere.grid(0.5e-3).spacing, 0.5e-3, rtol=1e-9, atol=0)
    cyl = scenario("sinking-cylinder", quick=True).roi
    assert cyl is not None and cyl.ndim == 2 and cyl.grid().shape == (221, 111)
    assert scenario("lesion-marker", quick=True).roi is not None
    assert scenario("fast-cylinder", quick=True).roi is None
    with pytest.raises(ValueError, match="z_range"):
        Roi((0.0, 1e-3), (2e-3, 1e-3), 1e-4)
    with pytest.raises(ValueError, match="spacing"):
        Roi((0.0, 1e-3), (1e-3, 2e-3), 0.0)
