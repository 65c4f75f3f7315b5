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
