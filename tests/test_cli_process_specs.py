"""`fp process`'s fingerprint options: --no-whitening keeps R0′ for the calibration fingerprints only."""

from __future__ import annotations

import pytest

from services.cli import build_parser
from services.cli.process import specs_from_args


def _args(*argv: str):
    return build_parser().parse_args(["process", *argv])


def test_no_whitening_keeps_r0_prime_for_calibrations_and_leaves_models_alone() -> None:
    specs = specs_from_args(_args("--scenario", "sinking-sphere", "--model", "point", "--no-whitening"))
    cal = [sp for sp in specs if sp.calibration is not None]
    assert {sp.name for sp in cal} == {"sphere1", "sphere2"}
    assert all(not sp.whiten_modes for sp in cal)
    assert all(sp.whiten_modes for sp in specs if sp.model is not None)  # a model has no modes: untouched
    assert all(sp.whiten_modes for sp in specs_from_args(_args("--scenario", "sinking-sphere")))  # the default


def test_no_whitening_without_a_calibration_names_the_option() -> None:
    with pytest.raises(ValueError, match="--no-whitening: applies to calibration fingerprints"):
        specs_from_args(_args("--model", "point", "--no-whitening"))


def test_time_weighting_reaches_the_processor_and_its_imager() -> None:
    """--time-weighting (docs/design.md §4.14) sets PipelineConfig.time_weighting, which the imager maps with."""
    import numpy as np

    from fpcore import PlaneWaveSequence, Probe
    from fpcore.born import born_points
    from services.cli.process import config_from_args
    from services.imaging_setup import make_imager

    assert config_from_args(_args("--scenario", "sinking-sphere", "--time-weighting")).time_weighting
    assert not config_from_args(_args("--scenario", "sinking-sphere")).time_weighting  # the default
    acq = born_points(
        Probe.linear(16, 0.3e-3, 2.5e6, 1.5e6), PlaneWaveSequence.from_angles([0.0]), [[0, 0, 10e-3]], [1]
    )
    for flag in (False, True):
        imager = make_imager(acq, (2e6, 3e6), time_weighting=flag)
        assert imager.config.time_weighting is flag
    assert np.isfinite(imager.plane_waves(acq).data).all()
