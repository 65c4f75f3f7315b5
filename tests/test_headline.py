"""The paper's headline on the simulated quick sinking-sphere scenario, as it is (issues 3 and 12).

In the paper's regime (the default: the spheres' own echoes 1/50–1/150 of the fog at their depth, the
paper's eq. (1), no background gain, calibrations at (0, 0, 25) mm in water) the spheres are hidden on
the confocal image. At 2 ℓ_s
(the demo's depth) the γ-map of each sphere's calibration fingerprint puts its maximum within 1 mm of
the truth with C_γ ≥ 5; the calibrated PFA is below the detection threshold (1e-3) on frame 0, and on
frame 20 for sphere 2 — sphere 1 has settled 0.4 mm deeper into the beads' focused speckle there and
stands at PFA ≈ 2e-3 (the tracker keeps it; README, "Tracking"). Between the two this implementation
loses the spheres (README, "The paper's regime"; bench/validate_simulate.py measures why).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import fpcore
from fpcore.metrics import DEFAULT_MAX_PFA
from fpcore.simulate import scenario


def test_paper_regime_spheres_are_hidden_and_fainter_than_the_fog() -> None:
    sc = scenario("sinking-sphere", quick=True, seed=0, n_frames=2)
    grid = replace(sc.roi, z_range=(17e-3, sc.roi.z_range[1])).grid()  # the caps lie 3–4 mm under the surface
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    acq = sc.frame(0)
    conf = imager.confocal(imager.plane_waves(acq))
    fog = imager.confocal(imager.plane_waves(sc.without_targets().frame(0)))
    mesh = np.meshgrid(*grid.axes, indexing="ij")
    ratios = {}
    for tg in acq.ground_truth.targets or []:
        r, a = tg.position, 0.5 * tg.diameter
        assert fpcore.contrasts(conf, grid, r, a)[0] < 2.0  # not a bright spot on the confocal image
        own = imager.confocal(imager.plane_waves(sc.target_echo(tg.name, 0)))
        near = sum((m - c) ** 2 for m, c in zip(mesh, r, strict=True)) < (a + 1.5e-3) ** 2
        ib = np.unravel_index(np.argmax(np.where(near, own, 0.0)), own.shape)
        ratios[tg.name] = own[ib] / fog[np.abs(mesh[2] - grid.z[ib[2]]) < 0.5e-3].mean()
    # The paper's 1/150 (sphere 1) and 1/50 (sphere 2), main text eq. (1); measured 1/68 and 1/72 on frame 0
    # on the focused speckle (sphere 1 settles to 1/133 by the last frame).
    assert 1 / 160 <= ratios["sphere1"] <= 1 / 45, ratios
    assert 1 / 160 <= ratios["sphere2"] <= 1 / 45, ratios


@pytest.fixture(scope="module")
def shallow():
    sc = scenario("sinking-sphere", quick=True, seed=0, depth_ls=2.0)
    first = sc.frame(0)
    grid = fpcore.Grid.for_acquisition(first, sc.band)  # the default grid: the record's whole time window
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    fps = sc.fingerprints(imager.out_sines_for(first))
    return sc, grid, imager, fps


@pytest.mark.parametrize("frame", [0, 20])
def test_at_two_mean_free_paths_gamma_finds_both_spheres(shallow, frame: int) -> None:
    sc, grid, imager, fps = shallow
    acq = sc.frame(frame)
    pw = imager.plane_waves(acq)
    level = fpcore.NullLevel(imager)
    for tg in acq.ground_truth.targets or []:
        r = tg.position
        assert np.allclose(sc.placements[tg.name].calibration_position, [0.0, 0.0, 25e-3])  # not the truth
        loc = fpcore.locate(imager, acq, fps[tg.name], level, pw=pw, max_pfa=None)
        det = loc.detections[0]
        assert np.linalg.norm(np.array(det.position_m) - r) < 1e-3
        assert det.c_gamma >= 5.0
        # detected: calibrated PFA < 1e-3, but for sphere 1 on frame 20 (≈ 2e-3 measured: module doc)
        assert det.pfa < (1e-2 if (frame, tg.name) == (20, "sphere1") else DEFAULT_MAX_PFA)
        assert loc.gamma.max() <= 1.0


def test_r0_prime_with_the_single_scattering_null_is_specific_and_finds_the_spheres_at_2_5_ls() -> None:
    """F = R0′ (paper S2, Fig. S7a) with the null level of eq. (B2) (docs/design.md §4.9, §4.11).

    R0′ gains more than the whitened modes in this fog, but with the P·A level alone sphere 2's R0′ reads the beads'
    single-scattering speckle just under the surface as a target (PFA ≈ 1e-5 on this target-free medium; README,
    "The paper's gain law, measured"). Eq. (B2) follows that speckle: on the same medium no node is significant,
    and at 2.5 ℓ_s sphere 1 is detected and sphere 2's most significant node is on it, not on the surface.
    """
    sc = scenario("sinking-sphere", quick=True, seed=0, n_frames=1, depth_ls=2.5)
    first = sc.frame(0)
    grid = fpcore.Grid.for_acquisition(first, sc.band)
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    level = fpcore.NullLevel(imager, single_scattering=True)
    fps = sc.fingerprints(imager.out_sines_for(first), whiten_modes=False)
    fog = sc.without_targets().frame(0)
    pw_fog = imager.plane_waves(fog)
    for fp in fps.values():  # target-free: nothing below PFA 0.01 (P·A gives 9.5e-6 for sphere 2's R0′)
        det = fpcore.locate(imager, fog, fp, level, pw=pw_fog, max_pfa=None).detections[0]
        assert det.pfa > 1e-2, (fp.name, det.pfa, det.position_m)
    pw = imager.plane_waves(first)
    for tg in first.ground_truth.targets or []:
        det = fpcore.locate(imager, first, fps[tg.name], level, pw=pw, max_pfa=None).detections[0]
        assert np.linalg.norm(np.array(det.position_m) - tg.position) < 1e-3, (tg.name, det.position_m)
        if tg.name == "sphere1":  # measured 5.5e-14; sphere 2 stands at 0.018 on this medium (18 of 24 detected)
            assert det.pfa < DEFAULT_MAX_PFA
