"""The paper's headline on the simulated quick sinking-sphere scenario (issue 3 acceptance).

On the confocal image the spheres are not the brightest spots (confocal contrast at the sphere < 2),
while the γ-map of each sphere's calibration fingerprint puts its maximum within 1 mm of the truth
with C_γ ≥ 5 and PFA < 1e-6 (paper Fig. 2 and S6).
"""

from __future__ import annotations

import numpy as np
import pytest

import fpcore
from fpcore.simulate import scenario


@pytest.fixture(scope="module")
def setup():
    sc = scenario("sinking-sphere", quick=True, seed=0)
    grid = sc.roi.grid()  # x ±11 mm, y ±5 mm, z 20–31 mm, 0.25 mm
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=sc.band))
    fps = sc.fingerprints(imager.out_sines_for(sc.frame(0)))
    return sc, grid, imager, fps


@pytest.mark.parametrize("frame", [0, 20])
def test_spheres_hidden_on_confocal_found_by_gamma(setup, frame: int) -> None:
    sc, grid, imager, fps = setup
    acq = sc.frame(frame)
    pw = imager.plane_waves(acq)
    conf = imager.confocal(pw)
    lam = sc.c0 / sc.probe.centre_frequency
    for tg in acq.ground_truth.targets or []:
        r, radius = tg.position, 0.5 * tg.diameter
        gamma = imager.gamma(pw, fps[tg.name])
        det = fpcore.detect(
            gamma,
            grid,
            lam,
            sc.probe.aperture[0],
            sc.band[1] - sc.band[0],
            sc.c0,
            name=tg.name,
            exclusion_radius=radius,
        )[0]
        assert np.linalg.norm(np.array(det.position_m) - r) < 1e-3
        assert det.c_gamma >= 5.0
        assert det.pfa < 1e-6
        c_conf, _ = fpcore.contrasts(conf, grid, r, radius)
        assert c_conf < 2.0
        assert gamma.max() <= 1.0
