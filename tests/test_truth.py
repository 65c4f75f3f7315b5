"""fpcore.truth.Truth: the typed view of a frame's ground truth keeps its JSON layout exactly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fpcore.acquisition import Acquisition, PlaneWaveSequence, Probe
from fpcore.io import read_uff, write_uff
from fpcore.simulate import SCENARIOS, scenario
from fpcore.truth import TargetTruth, Truth

FRAME_KEYS = ["scenario", "quick", "seed", "frame_index", "time_s", "dim", "band_hz", "targets"]
TARGET_KEYS = ["name", "kind", "position_m", "diameter_m", "moving"]


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario_truths_keep_their_layout_and_round_trip(name: str) -> None:
    sc = scenario(name, quick=True, seed=0)
    for i in (0, sc.n_frames - 1):
        d = sc.truth(i)
        assert list(d)[: len(FRAME_KEYS)] == FRAME_KEYS
        for t in d["targets"]:
            keys = TARGET_KEYS + (["velocity_m_s"] if t["moving"] else [])
            assert list(t)[: len(keys)] == keys
        back = Truth.from_dict(json.loads(json.dumps(d))).to_dict()
        assert json.dumps(back) == json.dumps(d)  # same keys, values and order: same JSON text
        t = sc.ground_truth(i)
        assert t.frame_index == i and t.dim == sc.dim and t.extra.keys() <= {"orientation_field", "fascia_z_m"}
    for target in sc.target_names:
        cal = sc.calibration_truth(target)
        d = cal.to_dict()
        assert list(d) == ["scenario", "calibration", "quick", "seed", "r0_m", "diameter_m", "band_hz", "targets"]
        assert np.array_equal(cal.r0, sc.placements[target].calibration_position)
        assert cal.diameter == sc.placements[target].target.diameter
        assert cal.target(target).moving is False and cal.target(target).position_m == cal.r0_m
        assert json.dumps(Truth.from_dict(d).to_dict()) == json.dumps(d)


def test_typed_fields_of_a_simulated_frame() -> None:
    sc = scenario("sinking-sphere", quick=True, seed=0, n_frames=4)
    t = sc.ground_truth(2)
    s1, s2 = t.target("sphere1"), t.target("sphere2")
    assert np.array_equal(s1.position, sc.placements["sphere1"].position(2))
    assert np.allclose(s1.velocity, sc.placements["sphere1"].velocity(2, sc.frame_rate))
    assert s1.moving and not s2.moving and s2.velocity_m_s is None and np.array_equal(s2.velocity, np.zeros(3))
    assert t.medium is not None and t.medium.ls_m == pytest.approx(1.8e-3)
    assert s1.depth_below_surface_m == pytest.approx(s1.position[2] - t.medium.z_surface_m)
    assert t.band_hz == sc.band
    with pytest.raises(KeyError, match="sphere3"):
        t.target("sphere3")
    fib = scenario("muscle-fibres", quick=True, n_frames=1, z_range=(12e-3, 18e-3)).ground_truth(0)
    assert fib.targets == [] and fib.fibres and fib.fibres[0].alpha_rad is not None
    assert "orientation_field" in fib.extra


def test_unknown_keys_and_odd_values_round_trip_verbatim() -> None:
    d = {
        "targets": [{"position_m": [0.0, 0.0, 0.02], "d": 0.01}],
        "note": "θ",
        "seed": True,
        "band_hz": [1, "x"],
        "medium": [1, 2],
        "fibres": [{"alpha_rad": "steep"}],
        "frame_index": 3,
    }
    t = Truth.from_dict(d)
    assert t.to_dict() == d
    assert t.seed is None and t.extra["seed"] is True  # a bool is not an int seed
    assert t.band_hz is None and t.medium is None and t.frame_index == 3
    assert t.targets == [TargetTruth(position_m=(0.0, 0.0, 0.02), extra={"d": 0.01})]
    assert t.fibres is not None and t.fibres[0].extra == {"alpha_rad": "steep"}
    assert Truth.from_dict({}).to_dict() == {} and Truth().to_dict() == {}
    assert Truth(frame_index=1).merged({"note": 1, "frame_index": 2}).to_dict() == {"frame_index": 2, "note": 1}
    with pytest.raises(ValueError, match="extra"):
        Truth(seed=1, extra={"seed": 2})
    with pytest.raises(TypeError):
        Truth.from_dict([1, 2])  # type: ignore[arg-type]


def test_acquisition_views_and_uff_carry_the_truth(tmp_path: Path) -> None:
    probe, seq = Probe.linear(8, 3e-4, 2.5e6, 1.5e6), PlaneWaveSequence.from_angles([-5.0, 0.0, 5.0])
    rf = np.zeros((8, 3, 32), np.float32)
    truth = Truth(
        scenario="bench",
        band_hz=(1.9e6, 2.7e6),
        targets=[TargetTruth(name="a", position_m=(0.0, 0.0, 0.02), diameter_m=1e-3, moving=False)],
    )
    acq = Acquisition(rf, 20e6, 0.0, 1500.0, probe, seq, truth=truth.to_dict())
    assert acq.ground_truth == truth
    assert acq.default_band() == (1.9e6, 2.7e6)
    assert Acquisition(rf, 20e6, 0.0, 1500.0, probe, seq).default_band() == (1.75e6, 3.25e6)
    write_uff(tmp_path / "t.uff", [acq, acq], truth=[truth, {"other": 1}])
    a, b = read_uff(tmp_path / "t.uff")
    assert a.truth == truth.to_dict() and a.ground_truth == truth
    assert b.truth == {"other": 1} and b.ground_truth.extra == {"other": 1}
