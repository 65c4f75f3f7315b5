"""Shared test fixtures: small probes, plane-wave sequences and a plane-wave rig."""

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


@pytest.fixture
def point_rig() -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """A small 2-D plane-wave rig for point fingerprints: c0, 33 frequencies over 1.8–2.6 MHz, 31 output
    and 7 input directions (sines, shape (n, 2))."""
    out = np.stack([np.linspace(-0.5, 0.5, 31), np.zeros(31)], axis=1)
    inn = np.stack([np.linspace(-0.3, 0.3, 7), np.zeros(7)], axis=1)
    return 1540.0, np.linspace(1.8e6, 2.6e6, 33), out, inn
