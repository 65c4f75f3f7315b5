"""The frame pipeline and the dictionary protocol offline, without zenoh (services.pipeline, services.convert,
services.registry), and the dependency direction of the services package."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from services.convert import frame_messages
from services.messages import Detections, Tracks
from services.pipeline import Pipeline, PipelineConfig
from services.registry import DictionaryServer, FingerprintSpec
from services.sources import born_frames
from services.topics import keys

SMALL = {"x_range": (-5e-3, 5e-3), "z_range": (10e-3, 22e-3), "spacing": 0.25e-3, "n_freq": 24}


def test_offline_modules_do_not_import_zenoh_and_nodes_do_not_import_the_cli() -> None:
    pure = "services.pipeline, services.convert, services.registry, services.models, services.topics"
    code = f"import sys, {pure}; assert 'zenoh' not in sys.modules, 'zenoh imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
    nodes = (
        "services.nodes.processor, services.nodes.publisher, services.nodes.recorder, services.nodes.local, "
        "services.viewing.rerun_log, services.viewing.server, services.viewing.sample, "
        "services.viewing.frame_figure"
    )
    code = f"import sys, {nodes}; cli = [m for m in sys.modules if m.startswith('services.cli')]; assert not cli, cli"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.fixture(scope="module")
def pipeline() -> tuple[Pipeline, list]:
    frames, cal = born_frames(3)
    pipe = Pipeline(PipelineConfig(**SMALL), [FingerprintSpec("marker", calibration=cal)])
    pipe.warm_up()
    return pipe, frames


def test_pipeline_locates_the_target_offline(pipeline) -> None:
    pipe, frames = pipeline
    for acq in frames:
        res = pipe.process(acq)
        assert set(res.gammas) == {"marker"} and res.image is not None and res.image.shape == res.grid.shape
        assert len(res.detections) == 1
        det, err = res.detections[0]
        assert det.fingerprint == "marker" and err is not None and err < 0.5e-3
        msgs = frame_messages(res, acq.frame_index, acq.timestamp)
        assert isinstance(msgs["detections"], Detections) and isinstance(msgs["tracks"], Tracks)
        assert msgs["detections"].detections[0].truth_error_m == err
        assert msgs["detections"].frame_index == msgs["image"].frame_index == acq.frame_index
        assert [g.fingerprint for g in msgs["gamma"]] == ["marker"]
        assert set(res.stage_s) == {"spectrum_projection", "gamma_kernel", "detection"}
    assert pipe.setup_s > 0


def test_dictionary_protocol_offline(pipeline) -> None:
    pipe, frames = pipeline
    k = keys("t")
    server = DictionaryServer(None, k, pipe)  # type: ignore[arg-type]  # handle() needs no session
    ok, doc, reply_key = server.handle(k.dictionary, b"", b"")
    assert ok and reply_key == k.dictionary_op("list") and [e["name"] for e in doc["entries"]] == ["marker"]
    model = json.dumps({"model": "point", "r0_m": [0.0, 0.0, 0.015]}).encode()
    ok, doc, _ = server.handle(k.dictionary_op("add", "pt"), model, b"")
    assert ok and doc["added"]["provenance"] == "model:point" and pipe.names == ["marker", "pt"]
    with pytest.raises(ValueError, match="plain name"):
        server.handle(k.dictionary_op("add", "list"), model, b"")
    ok, doc, _ = server.handle(k.dictionary_op("get", "pt"), b"", b"")
    assert ok and doc["entry"]["built"]
    res = pipe.process(frames[0])
    assert set(res.gammas) == {"marker", "pt"}
    ok, doc, _ = server.handle(k.dictionary_op("remove", "nope"), b"", b"")
    assert not ok and "no entry 'nope'" in doc["error"]
    ok, doc, _ = server.handle(k.dictionary_op("remove", "pt"), b"", b"")
    assert ok and doc["entries"] == ["marker"]
    ok, doc, _ = server.handle(k.dictionary_op("set"), json.dumps({"svd_threshold": 0.6}).encode(), b"")
    assert ok and doc["params"]["svd_threshold"] == 0.6 and all(e["built"] for e in doc["entries"])


def test_fp_version(capsys) -> None:
    import fpcore
    from services.cli import main

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"fp {fpcore.__version__}"


def test_cfar_setting_reaches_the_null_models_and_the_tracker() -> None:
    """`PipelineConfig.cfar` (fp process/track/locate --cfar) is the setting the frame's null models and the
    tracker use (fpcore.cfar.CFAR_NAMES); an unknown name is refused, naming the option."""
    import numpy as np

    from fpcore.cfar import cfar_null_model
    from fpcore.locate import resolution_of

    frames, cal = born_frames(1)
    pipe = Pipeline(PipelineConfig(**SMALL, cfar="wide"), [FingerprintSpec("marker", calibration=cal)])
    res = pipe.process(frames[0])
    assert pipe._tracker is not None and pipe._tracker.config.cfar == "wide"
    assert pipe._level is not None and pipe._level.cfar == "wide"
    fp = res.fingerprints["marker"]
    r = resolution_of(res.grid, res.acq, res.band)
    lev, vis = pipe._level.level(res.acq, res.pw, fp, r)
    direct = cfar_null_model("wide", res.gammas["marker"], res.grid, r, level=lev, visible=vis)
    default = cfar_null_model("compact", res.gammas["marker"], res.grid, r, level=lev, visible=vis)
    assert np.array_equal(res.nulls["marker"].statistic, direct.statistic)
    assert not np.array_equal(direct.statistic, default.statistic)
    with pytest.raises(ValueError, match="--cfar"):
        PipelineConfig(**SMALL, cfar="narrow")


def test_many_fingerprints_give_the_serial_maps() -> None:
    """The second thread never runs the imager (its kernels are not re-entrant): the aperture factors are made
    on the imager's thread and handed over, even when their cache holds fewer than the dictionary (here set back
    to the earlier 8, for 9 fingerprints). Before, an aperture missed in the cache was remade on the second
    thread while the main thread made the γ-maps with the same kernel, and maps came out wrong (|Δγ| 0.54)."""
    import numpy as np

    frames, cal = born_frames(3)
    specs = [FingerprintSpec("marker", calibration=cal)] + [
        FingerprintSpec(f"p{i}", model="point", r0=(0.0, 0.0, 0.012 + 0.001 * i)) for i in range(8)
    ]
    pipe = Pipeline(PipelineConfig(**SMALL), specs)
    pipe.warm_up()
    assert pipe._level is not None
    pipe._level._cache = 8  # every frame misses: the factors are remade, on the imager's thread
    for acq in frames:
        res = pipe.process(acq)
        pw = pipe._imager.plane_waves(acq)
        for name, g in res.gammas.items():
            assert np.array_equal(g, pipe._imager.gamma(pw, res.fingerprints[name])), name
