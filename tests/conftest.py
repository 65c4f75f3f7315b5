"""Shared test fixtures: small probes and plane-wave sequences."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore import PlaneWaveSequence, Probe


@pytest.fixture
def linear_setup() -> tuple[Probe, PlaneWaveSequence]:
    return Probe.linear(48, 0.3e-3, 2.5e6, 1.5e6), PlaneWaveSequence.from_angles(np.linspace(-12, 12, 7))


@pytest.fixture
def matrix_setup() -> tuple[Probe, PlaneWaveSequence]:
    probe = Probe.matrix(12, 12, 0.3e-3, 2.5e6, 1.5e6)
    return probe, PlaneWaveSequence.from_angles(np.linspace(-8, 8, 3), np.linspace(-8, 8, 3))
