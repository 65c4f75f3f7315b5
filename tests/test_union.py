"""The union of the unweighted and time-weighted statistics (docs/design.md §4.14, eq. W2): its PFA stays
calibrated whatever the maps' dependence, and it keeps a target that the weighting loses."""

from __future__ import annotations

import numpy as np
import pytest

import fpcore
from fpcore import locate_union, union_pfa
from fpcore.locate import union_of


@pytest.mark.parametrize("dependence", ["identical", "independent", "antithetic"])
@pytest.mark.parametrize("alpha", [0.05, 0.01])
def test_the_union_pfa_is_calibrated_whatever_the_dependence(dependence: str, alpha: float) -> None:
    """Two calibrated PFAs (uniform under the null), the most significant taken with eq. (W2): the rate below α is
    α/2 for identical maps, α − α²/4 for independent ones and α exactly for antithetic ones (p₁ = 1 − p₀), the
    Bonferroni bound's worst case; never above α."""
    rng = np.random.default_rng(7)
    p0 = rng.uniform(size=100_000)
    p1 = {"identical": p0, "independent": rng.uniform(size=p0.size), "antithetic": 1.0 - p0}[dependence]
    union = np.array([union_pfa(min(a, b), 2) for a, b in zip(p0, p1, strict=True)])
    expected = {"identical": alpha / 2, "independent": alpha - alpha**2 / 4, "antithetic": alpha}[dependence]
    rate = float(np.mean(union < alpha))
    sigma = np.sqrt(expected * (1 - expected) / p0.size)
    assert abs(rate - expected) < 5 * sigma
    assert rate < alpha + 5 * sigma


def test_bad_pfas_are_refused() -> None:
    with pytest.raises(ValueError, match="pfa: expected a probability"):
        union_pfa(1.5, 2)
    with pytest.raises(ValueError, match="n_maps: expected at least 1"):
        union_pfa(0.1, 0)
    with pytest.raises(ValueError, match="imagers: expected one or more"):
        locate_union([], None, None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="found: expected one or more"):
        union_of([])


def test_the_union_keeps_a_marker_that_rules_its_frame() -> None:
    """A Born marker over sparse speckle (services.sources.born_frames) rules its frame's energy: the weighting
    takes its echo for background and loses it (docs/validation.md, ninth session). The union takes the unweighted
    map, whose node is the more significant, at twice its PFA."""
    from services.sources import born_frames

    frames, cal = born_frames(1)
    (frame,) = frames
    band = frame.default_band()
    grid = fpcore.Grid.for_acquisition(frame, band, x_range=(-4e-3, 4e-3), z_range=(12e-3, 20e-3), spacing=0.25e-3)
    imagers = [fpcore.Imager(fpcore.ImagingConfig(grid, band, 16, time_weighting=w)) for w in (False, True)]
    r0 = np.asarray(cal.ground_truth.r0)
    fp = fpcore.from_calibration(cal, r0, imagers[0].out_sines_for(cal), band, 16, diameter=1.6e-3)
    alone = [fpcore.locate(im, frame, fp, max_pfa=None).detections[0] for im in imagers]
    truth = np.asarray(frame.ground_truth.targets[0].position)
    assert alone[0].pfa < 1e-8 and np.linalg.norm(np.asarray(alone[0].position_m) - truth) < 0.5e-3
    assert alone[1].pfa > 1e3 * alone[0].pfa  # the weighting's cost where a target rules the frame
    found, chosen = locate_union(imagers, frame, fp)
    assert chosen == 0
    (d,) = found.detections
    assert d.pfa == pytest.approx(2 * alone[0].pfa)
    assert d.position_m == alone[0].position_m
