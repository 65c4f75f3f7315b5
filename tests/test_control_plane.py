"""Transactional control plane (issue 13, item 3): a refused ``set`` or ``add`` on the dictionary leaves the
pipeline exactly as it was — same configuration, same set-up objects, same fingerprints — and later frames are
processed as before; offline (services.pipeline, services.registry) and once through the zenoh queryable."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

import services.pipeline as pipeline_mod
from fpcore.budget import BudgetError
from services.pipeline import Pipeline, PipelineConfig
from services.registry import DictionaryServer, FingerprintSpec, check_setup_size, set_changes
from services.sources import born_frames
from services.topics import keys

SMALL: dict[str, Any] = {"x_range": (-5e-3, 5e-3), "z_range": (10e-3, 22e-3), "spacing": 0.25e-3, "n_freq": 24}


@pytest.fixture(scope="module")
def data() -> dict[str, Any]:
    frames, cal = born_frames(3)
    return {"frames": frames, "cal": cal}


def _pipeline(data: dict[str, Any]) -> Pipeline:
    pipe = Pipeline(PipelineConfig(**SMALL), [FingerprintSpec("marker", calibration=data["cal"])])
    pipe.warm_up()
    pipe.process(data["frames"][0])
    return pipe


def _state(pipe: Pipeline) -> dict[str, Any]:
    """What must not move: the description, the configuration and the identity of every set-up object."""
    return {
        "describe": json.dumps(pipe.describe(), sort_keys=True),
        "cfg": pipe.cfg,
        "objects": [id(pipe._imager), id(pipe._level), id(pipe._tracker), id(pipe._ref), pipe._geom, pipe._band],
        "entries": {n: (id(e), id(e.fp), e.error) for n, e in pipe._entries.items()},
    }


def _gammas(pipe: Pipeline, acq: Any) -> dict[str, np.ndarray]:
    return pipe.process(acq).gammas


def test_refused_set_leaves_the_pipeline_as_it_was(data) -> None:
    pipe = _pipeline(data)
    before = _state(pipe)
    g_before = _gammas(pipe, data["frames"][1])
    bad: list[tuple[dict[str, Any], str]] = [
        ({"n_freq": 20_000_000}, r"set: refused, n_freq=20000000 .* needs about .*GiB, over the memory budget"),
        ({"band_hz": [1e6, 1e9]}, "fs/2"),  # passes the parser, fails in the set-up (above Nyquist)
        ({"n_freq": "many"}, "n_freq must be a finite number"),
        ({"n_freq": 0}, "n_freq must be an integer >= 1"),
        ({"svd_threshold": 2}, r"svd_threshold must be in \(0, 1\]"),
        ({"n_peaks": 1.5}, "n_peaks must be an integer"),
        ({"band_hz": [3e6, 1e6]}, "f_min < f_max"),
        ({"colour": 1}, "unknown parameter"),
        ({"svd_threshold": 0.6, "n_freq": -3}, "n_freq"),  # one bad field refuses the whole request
    ]
    for params, match in bad:
        with pytest.raises(ValueError, match=match):
            pipe.set_params(params)
        assert _state(pipe) == before, params
    g_after = _gammas(pipe, data["frames"][1])
    assert g_after.keys() == g_before.keys() == {"marker"}
    np.testing.assert_allclose(g_after["marker"], g_before["marker"], rtol=1e-5, atol=1e-7)
    # A valid change is taken, and frames go on.
    pipe.set_params({"svd_threshold": 0.6, "n_freq": 20})
    assert pipe.cfg.svd_threshold == 0.6 and pipe.cfg.n_freq == 20 and id(pipe._imager) != before["objects"][0]
    res = pipe.process(data["frames"][2])
    assert set(res.gammas) == {"marker"} and len(res.detections) == 1


def test_a_set_up_that_fails_half_way_is_rolled_back(data, monkeypatch) -> None:
    """Fault injection: the fingerprint build fails (MemoryError in the middle of the set-up, or an entry that
    no longer builds) after the new imager exists; the old set-up and entries come back."""
    pipe = _pipeline(data)
    before = _state(pipe)
    real = pipeline_mod.build_fingerprint

    def oom(*args: Any, **kw: Any) -> Any:
        raise MemoryError("Unable to allocate 9.3 GiB")

    monkeypatch.setattr(pipeline_mod, "build_fingerprint", oom)
    with pytest.raises(MemoryError):
        pipe.set_params({"n_freq": 30})
    assert _state(pipe) == before

    def refuse(*args: Any, **kw: Any) -> Any:
        raise ValueError("calibration does not cover the band")

    monkeypatch.setattr(pipeline_mod, "build_fingerprint", refuse)
    with pytest.raises(ValueError, match="would not build: marker: calibration does not cover the band"):
        pipe.set_params({"svd_threshold": 0.5})
    assert _state(pipe) == before
    with pytest.raises(ValueError, match="does not cover"):
        pipe.add(FingerprintSpec("pt", model="point", r0=(0.0, 0.0, 0.015)))
    assert _state(pipe) == before and pipe.names == ["marker"]
    monkeypatch.setattr(pipeline_mod, "build_fingerprint", real)
    assert set(_gammas(pipe, data["frames"][1])) == {"marker"}


def test_refused_queries_answer_ok_false_and_change_nothing(data) -> None:
    pipe = _pipeline(data)
    k = keys("t")
    server = DictionaryServer(None, k, pipe)  # type: ignore[arg-type]  # handle() needs no session
    before = _state(pipe)
    ok, doc, _ = server.handle(k.dictionary_op("set"), json.dumps({"n_freq": 20_000_000}).encode(), b"")
    assert not ok and not doc["ok"] and "over the memory budget" in doc["error"] and doc["params"]["n_freq"] == 24
    with pytest.raises(ValueError, match="expected a JSON object"):  # the server thread answers ok:false
        server.handle(k.dictionary_op("set"), b"{not json", b"")
    with pytest.raises(ValueError, match="mirror needs L"):
        server.handle(k.dictionary_op("add", "m"), json.dumps({"model": "mirror:alpha=3"}).encode(), b"")
    ok, doc, _ = server.handle(k.dictionary_op("remove", "nope"), b"", b"")
    assert not ok and "no entry 'nope'" in doc["error"]
    assert _state(pipe) == before


def test_set_parser_and_size_estimate(data) -> None:
    assert set_changes({"band_hz": [1e6, 3e6], "n_freq": 40.0, "n_peaks": 2}) == {
        "band": (1e6, 3e6),
        "n_freq": 40,
        "n_peaks": 2,
    }
    assert set_changes({"n_freq": None}) == {"n_freq": None}
    for bad in ([], {"n_freq": True}, {"band_hz": [0, float("nan")]}, {"svd_threshold": "0.5"}):
        with pytest.raises(ValueError, match="set: "):
            set_changes(bad)
    acq = data["frames"][0]  # 32 elements × 5 waves × 400 samples at 20 MHz
    small = check_setup_size(acq, (1.5e6, 3.5e6), 24)
    assert small == 8 * 160 * 201 + 24 * 24 * 160  # N_FFT = max(N_t, 24 × 20 MHz / 2 MHz) = 400: 201 bins, 24 kept
    big = 8 * 160 * 100_000_001 + 24 * 20_000_000 * 160  # N_FFT = 20e6 × 20 MHz / 2 MHz = 2e8
    with pytest.raises(BudgetError, match="over the memory budget of 1 GiB"):
        check_setup_size(acq, (1.5e6, 3.5e6), 20_000_000, limit=1 << 30)
    assert check_setup_size(acq, (1.5e6, 3.5e6), 20_000_000, limit=big) == big


@pytest.mark.timeout(60)
def test_refused_set_through_the_queryable_keeps_the_processor_running(data) -> None:
    """One loopback round trip: ``set {"n_freq": 20000000}`` answers ok:false with the size refusal, the
    processor keeps its parameters, and a frame published afterwards is processed."""
    from services.bus import BusConfig, free_port, open_session, wait_for_token
    from services.nodes.processor import Processor, ProcessorConfig
    from services.nodes.publisher import Publisher
    from services.registry import dictionary_request
    from services.sources import AcquisitionSource

    rig, port = "txn", free_port()
    cfg = ProcessorConfig(rig=rig, queue="fifo", **SMALL)
    with (
        open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")) as s_proc,
        open_session(BusConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"], shm="off")) as s,
    ):
        with Processor(s_proc, cfg, [FingerprintSpec("marker", calibration=data["cal"])]) as node:
            assert wait_for_token(s, keys(rig).alive("processor"), 20)
            listing = dictionary_request(s, rig, "list")
            res = dictionary_request(s, rig, "set", payload={"n_freq": 20_000_000})
            assert res["ok"] is False and "over the memory budget" in res["error"] and "n_freq=20000000" in res["error"]
            assert res["params"] == listing["params"] and node.cfg.n_freq == 24
            assert dictionary_request(s, rig, "list") == listing
            summary = Publisher(s, rig, AcquisitionSource(data["frames"][:2]), pace="ack", wait_timeout=20).run()
            assert summary["published"] == 2
            assert node.frames_processed == 2 and node.failed == 0 and node.rejected == 0
