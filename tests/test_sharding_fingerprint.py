"""Sharding by fingerprint over real zenoh on loopback (issue 15.1; docs/scaling.md).

`fp merge --shard fingerprint` runs as the zenoh router (tcp/127.0.0.1, scouting off); two `fp worker`
subprocesses hold the same two-entry dictionary (a calibration, ``marker``, and a ``point`` model) and each
computes its share of every frame's fingerprints, one of them also the confocal image. The dictionary query
through the merger lists the union of the workers' entries. One worker is killed by its pid (SIGKILL)
while frames are in flight: every frame is still acknowledged once and in order, each γ-map and image is
published once, and detections and tracks equal the single-node pipeline's on the same frames. An add
and a remove through the merger reach the surviving worker. Processes are stopped by pid in ``finally``.
"""

from __future__ import annotations

import json
import os
import signal
import threading
from pathlib import Path
from typing import Any

import pytest

from fpcore.io import write_uff
from services.bus import free_port, open_session, wait_for_token
from services.convert import frame_messages
from services.nodes.publisher import Publisher
from services.nodes.shares import split_units, worker_groups
from services.nodes.worker import IMAGE_UNIT, encode_part, split_part
from services.pipeline import Pipeline, PipelineConfig
from services.registry import FingerprintSpec, dictionary_request
from services.sources import AcquisitionSource, born_frames
from services.topics import keys
from tests.test_sharding import CONFIG, _client, _same_detections, _same_tracks
from tests.test_streaming import GRID, Collector, Node

N_FRAMES = 12


def test_shares_are_dealt_in_turn_and_groups_split_the_dictionary() -> None:
    units = ["a", "b", "c", IMAGE_UNIT]
    assert split_units(units, ["w0", "w1"], 0) == {"w0": ["a", "c"], "w1": ["b", IMAGE_UNIT]}
    assert split_units(units, ["w0", "w1"], 1) == {"w1": ["a", "c"], "w0": ["b", IMAGE_UNIT]}
    assert split_units(units, ["w0"], 5) == {"w0": units}
    assert worker_groups(["w3", "w0", "w2", "w1"], 2) == [["w0", "w1"], ["w2", "w3"]]
    assert worker_groups(["a", "b", "c"], 2) == [["a", "b", "c"]]  # no group of one
    assert worker_groups(["a", "b", "c", "d", "e"], 2) == [["a", "b"], ["c", "d", "e"]]
    att = encode_part(["a", IMAGE_UNIT], b"HEADER")
    assert split_part(att) == (["a", IMAGE_UNIT], b"HEADER") and split_part(b"HEADER") == (None, b"HEADER")
    with pytest.raises(ValueError, match="part attachment"):
        split_part(att[:12])


def _reference(frames: list, specs: list[FingerprintSpec]) -> dict[int, dict[str, Any]]:
    pipe = Pipeline(PipelineConfig(**CONFIG), specs)
    out = {}
    for i, acq in enumerate(frames):
        msgs = frame_messages(pipe.process(acq), i, acq.timestamp)
        out[i] = {"detections": msgs["detections"], "tracks": msgs["tracks"]}
    return out


@pytest.mark.timeout(120)
def test_fingerprint_shards_worker_killed_nothing_lost_identical_and_dictionary_union(tmp_path: Path) -> None:
    frames, cal = born_frames(N_FRAMES)
    cal_path = tmp_path / "cal.uff"
    write_uff(cal_path, cal)
    rig, port = "fpshard", free_port()
    hub = f"tcp/127.0.0.1:{port}"
    client = ["--mode", "client", "--connect", hub]
    wargs = ["worker", "--rig", rig, "--calibration", str(cal_path), "--model", "point", *GRID, "--n-freq", "24"]
    margs = ["merge", "--rig", rig, "--queue", "fifo", "--shard", "fingerprint", "--workers", "2"]
    procs: list[Node] = []
    try:
        merger = Node([*margs, "--mode", "router", "--listen", hub], tmp_path / "merge.log")
        procs.append(merger)
        workers = [Node([*wargs, "--name", f"w{i}", *client], tmp_path / f"w{i}.log") for i in range(2)]
        procs += workers
        specs = [FingerprintSpec("marker", calibration=cal), FingerprintSpec("point", model="point")]
        reference = _reference(frames, specs)  # while the nodes start
        for w in workers:
            w.wait_ready()
        merger.wait_ready()
        killed = threading.Event()

        def kill_one(item: Any, t: float) -> None:  # a worker dies with parts of frames in flight
            if item.frame_index == N_FRAMES // 2 and not killed.is_set():
                os.kill(workers[1].pid, signal.SIGKILL)
                killed.set()

        k = keys(rig)
        with open_session(_client(port)) as s:
            assert wait_for_token(s, k.alive("worker") + "/w1", 10)
            listed = dictionary_request(s, rig, "list", timeout=20)
            col = Collector(s, rig)
            pub = Publisher(
                s, rig, AcquisitionSource(frames), pace="ack", window=4, wait_timeout=30, on_publish=kill_one
            )
            summary = pub.run()
            dets = col.wait(k.detections, N_FRAMES)
            tracks = col.wait(k.tracks, N_FRAMES)
            gammas, images, errors = col.on(k.gamma), col.on(k.image), col.on(k.errors)
            col.close()
            added = dictionary_request(s, rig, "add", "extra", {"model": "point"}, timeout=30)
            after_add = dictionary_request(s, rig, "list", timeout=20)
            removed = dictionary_request(s, rig, "remove", "extra", timeout=20)
            missing = dictionary_request(s, rig, "get", "nosuch", timeout=20)
        os.kill(merger.pid, signal.SIGTERM)
        out, _ = merger.proc.communicate(timeout=30)
        stats = json.loads([ln for ln in out.splitlines() if '"stopped"' in ln][-1])
        assert killed.is_set() and workers[1].proc.wait(5) == -signal.SIGKILL
        # the dictionary through the merger: the union of both workers' entries, each listed per worker
        assert listed["ok"] and [e["name"] for e in listed["entries"]] == ["marker", "point"]
        assert listed["workers"] == {"w0": ["marker", "point"], "w1": ["marker", "point"]}
        assert added["ok"] and added["workers"] == {"w0": True} and added["added"]["name"] == "extra"
        assert [e["name"] for e in after_add["entries"]] == ["marker", "point", "extra"]
        assert removed["ok"] and removed["entries"] == ["marker", "point"]
        assert not missing["ok"] and "nosuch" in missing["error"]
        # every frame acknowledged once, in order; each γ-map and image published once
        assert summary["published"] == N_FRAMES and summary["acked"] == N_FRAMES and summary["ack_timeouts"] == 0
        assert errors == []
        assert [d.frame_index for d in dets] == list(range(N_FRAMES))
        assert [t.frame_index for t in tracks] == list(range(N_FRAMES))
        assert sorted((g.frame_index, g.fingerprint) for g in gammas) == [
            (i, n) for i in range(N_FRAMES) for n in ("marker", "point")
        ]
        assert sorted(im.frame_index for im in images) == list(range(N_FRAMES))
        for d in dets:
            assert _same_detections(d, reference[d.frame_index]["detections"]), d.frame_index
        for t in tracks:
            assert _same_tracks(t, reference[t.frame_index]["tracks"]), t.frame_index
        assert any(t.tracks and t.tracks[0].status == "confirmed" for t in tracks)
        assert {d.fingerprint for f in dets for d in f.detections} >= {"marker"}
        # both workers computed parts before w1 died; its parts in flight went to w0; nothing twice
        assert stats["shard"] == "fingerprint" and stats["frames_processed"] == N_FRAMES
        assert stats["duplicates"] == 0 and stats["pending"] == 0
        assert stats["per_worker"]["w1"] >= 1 and stats["per_worker"]["w0"] == N_FRAMES
        assert stats["workers"] == ["w0"]
        assert "worker w1 left" in (tmp_path / "merge.log").read_text()
    finally:
        for p in procs:
            p.stop()


def test_both_frames_over_groups_fingerprints_over_their_workers() -> None:
    """``--shard both`` in this process: four workers in two groups of two; each frame is split over the
    two workers of one group, both groups get frames, and detections and tracks equal the single node's."""
    from services.bus import BusConfig
    from services.nodes.merger import Merger, MergerConfig
    from services.nodes.worker import Worker, WorkerConfig

    frames, cal = born_frames(6)
    specs = [FingerprintSpec("marker", calibration=cal), FingerprintSpec("point", model="point")]
    reference = _reference(frames, specs)
    port, rig = free_port(), "both"
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    mcfg = MergerConfig(rig=rig, queue="fifo", depth=1, min_workers=4, wait_workers_s=30, shard="both", group_size=2)
    k, names = keys(rig), ["a", "b", "c", "d"]
    with open_session(hub) as hs, open_session(_client(port)) as ws, open_session(_client(port)) as ps:
        nodes = [Worker(ws, WorkerConfig(**CONFIG, rig=rig, name=n), specs) for n in names]
        for w in nodes:
            w.start()
        try:
            with Merger(hs, mcfg) as m:
                emitted: list[str] = []
                emit = m._emit

                def record(f: Any, res: Any) -> None:
                    emitted.append(res.worker)
                    emit(f, res)

                m._emit = record  # type: ignore[method-assign]
                col = Collector(ps, rig)
                summary = Publisher(ps, rig, AcquisitionSource(frames), pace="ack", window=4, wait_timeout=30).run()
                dets, tracks = col.wait(k.detections, 6), col.wait(k.tracks, 6)
                col.close()
        finally:
            for w in nodes:
                w.close()
    assert summary["acked"] == 6 and [d.frame_index for d in dets] == list(range(6))
    assert set(emitted) == {"a,b", "c,d"}  # each frame on one group, split over both of its workers
    for d, t in zip(dets, tracks, strict=True):
        assert _same_detections(d, reference[d.frame_index]["detections"]), d.frame_index
        assert _same_tracks(t, reference[t.frame_index]["tracks"]), t.frame_index
    assert sum(w.parts_computed for w in nodes) == 12 and all(w.parts_computed for w in nodes)


def test_a_worker_without_a_fingerprint_fails_the_frame_and_refused_changes_name_the_workers() -> None:
    """Worker ``b`` lacks the ``point`` entry the first worker gave the merger: the frame whose ``point``
    unit it is dealt fails once, with an ErrorReport naming the fingerprint, and the next frame merges. A
    dictionary add every worker refuses is answered ``ok: false`` with each worker's reason."""
    from services.bus import BusConfig
    from services.nodes.merger import Merger, MergerConfig
    from services.nodes.worker import Worker, WorkerConfig

    frames, cal = born_frames(2)
    marker = FingerprintSpec("marker", calibration=cal)
    port, rig = free_port(), "mismatch"
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    mcfg = MergerConfig(rig=rig, queue="fifo", depth=1, min_workers=1, wait_workers_s=30, shard="fingerprint")
    k = keys(rig)
    with open_session(hub) as hs, open_session(_client(port)) as ws, open_session(_client(port)) as ps:
        with Worker(ws, WorkerConfig(**CONFIG, rig=rig, name="a"), [marker, FingerprintSpec("point", model="point")]):
            with Merger(hs, mcfg) as m:
                with Worker(ws, WorkerConfig(**CONFIG, rig=rig, name="b"), [marker]):
                    assert wait_for_token(ps, k.alive("worker") + "/b", 10)
                    col = Collector(ps, rig)
                    summary = Publisher(ps, rig, AcquisitionSource(frames), pace="ack", window=1, wait_timeout=20).run()
                    errs, dets = col.wait(k.errors, 1), col.wait(k.detections, 1)
                    refused = dictionary_request(ps, rig, "add", "bad", {"model": "mirror"}, timeout=20)
                    col.close()
                    names = m._names
    assert summary["acked"] == 2 and names == ["marker", "point"]
    assert [(e.frame_index, e.node) for e in errs] == [(0, "b")] and "'point'" in errs[0].problem
    assert [d.frame_index for d in dets] == [1] and m.failed == 1 and m.frames_processed == 1
    assert not refused["ok"] and refused["workers"] == {"a": False, "b": False}
    assert "a: " in refused["error"] and "b: " in refused["error"] and "mirror" in refused["error"]
