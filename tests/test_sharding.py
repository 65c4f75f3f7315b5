"""Sharded processing over real zenoh on loopback (issue 15.1; docs/scaling.md).

`fp merge` runs as the zenoh router (tcp/127.0.0.1, scouting off), two `fp worker` subprocesses connect
to it as clients, and a replaying publisher (paced by acknowledgements) sends small 2-D Born frames from
the test process. One worker is killed by its pid (SIGKILL) while frames are in flight: every frame is
still merged exactly once, and the detections and tracks equal the single-node pipeline's on the same
frames. Processes are stopped by pid in ``finally``.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fpcore.io import write_uff
from services.bus import BusConfig, free_port, open_session, wait_for_token
from services.convert import frame_messages
from services.messages import Detections, Tracks
from services.nodes.publisher import Publisher
from services.nodes.worker import ShardResult, decode_shard, encode_shard
from services.pipeline import Pipeline, PipelineConfig
from services.registry import FingerprintSpec
from services.sources import AcquisitionSource, born_frames
from services.topics import keys
from services.wire import decode
from tests.test_streaming import GRID, Collector, Node

N_FRAMES = 16
CONFIG: dict[str, Any] = {"x_range": (-5e-3, 5e-3), "z_range": (10e-3, 22e-3), "spacing": 0.25e-3, "n_freq": 24}


def _client(port: int) -> BusConfig:
    return BusConfig(mode="client", listen=None, connect=[f"tcp/127.0.0.1:{port}"], shm="off")


def _single_node(frames: list, cal: Any) -> dict[int, dict[str, Any]]:
    """What `fp process` publishes per frame: its own pipeline, in-process."""
    pipe = Pipeline(PipelineConfig(**CONFIG), [FingerprintSpec("marker", calibration=cal)])
    out = {}
    for i, acq in enumerate(frames):
        msgs = frame_messages(pipe.process(acq), i, acq.timestamp)
        out[i] = {"detections": msgs["detections"], "tracks": msgs["tracks"]}
    return out


def _same_detections(a: Detections, b: Detections) -> bool:
    """Equal up to the NUFFT's multithreaded summation order (≈ 1e-7 relative)."""
    return len(a.detections) == len(b.detections) and all(
        x.fingerprint == y.fingerprint
        and np.allclose(x.position_m, y.position_m, rtol=0, atol=1e-8)
        and np.isclose(x.gamma_max, y.gamma_max, rtol=1e-4)
        and np.isclose(x.pfa, y.pfa, rtol=1e-2, atol=1e-30)
        for x, y in zip(a.detections, b.detections, strict=True)
    )


def _same_tracks(a: Tracks, b: Tracks) -> bool:
    return len(a.tracks) == len(b.tracks) and all(
        (x.id, x.fingerprint, x.status, x.age) == (y.id, y.fingerprint, y.status, y.age)
        and np.allclose(x.position_m, y.position_m, rtol=0, atol=1e-8)
        and np.allclose(x.velocity_m_s, y.velocity_m_s, rtol=0, atol=1e-6)
        and np.allclose(x.covariance, y.covariance, rtol=1e-4, atol=1e-14)
        and np.isclose(x.confidence, y.confidence, rtol=1e-6)
        for x, y in zip(a.tracks, b.tracks, strict=True)
    )


def test_shard_payload_round_trip() -> None:
    """FPSHARD1: messages, null models (every field) and the grid come back as they went."""
    frames, cal = born_frames(1)
    pipe = Pipeline(PipelineConfig(**CONFIG, track=False), [FingerprintSpec("marker", calibration=cal)])
    res = pipe.process(frames[0])
    msgs = frame_messages(res, 0, frames[0].timestamp)
    from services.wire import encode

    sent = ShardResult(
        0, 0.5, "w-1", "result", [("detections", encode(msgs["detections"]))], res.nulls, {"c0": 1540.0}, res.grid
    )
    back = decode_shard(encode_shard(sent))
    assert (back.frame_index, back.timestamp, back.worker, back.kind, back.tracker) == (
        0,
        0.5,
        "w-1",
        "result",
        {"c0": 1540.0},
    )
    assert back.messages == sent.messages
    assert back.grid is not None and np.array_equal(back.grid.x, res.grid.x) and back.grid.y is None
    nm, nm2 = res.nulls["marker"], back.nulls["marker"]
    assert np.array_equal(nm.significance, nm2.significance) and np.array_equal(nm.visible, nm2.visible)
    assert nm.tail_fit == nm2.tail_fit and nm.guard_nodes == nm2.guard_nodes
    assert nm.gate_pfa(5.0, np.array([3.0, 3.0])) == nm2.gate_pfa(5.0, np.array([3.0, 3.0]))
    with pytest.raises(ValueError, match="shard result"):
        decode_shard(b"FPSHARD1" + bytes(8))


@pytest.mark.timeout(120)
def test_worker_killed_mid_run_nothing_lost_tracks_identical(tmp_path: Path) -> None:
    frames, cal = born_frames(N_FRAMES)
    cal_path = tmp_path / "cal.uff"
    write_uff(cal_path, cal)
    rig, port = "shard", free_port()
    hub = f"tcp/127.0.0.1:{port}"
    client = ["--mode", "client", "--connect", hub]
    wargs = ["worker", "--rig", rig, "--calibration", str(cal_path), *GRID, "--n-freq", "24"]
    procs: list[Node] = []
    try:
        merger = Node(
            ["merge", "--rig", rig, "--queue", "fifo", "--workers", "2", "--mode", "router", "--listen", hub],
            tmp_path / "merge.log",
        )
        procs.append(merger)
        workers = [Node([*wargs, "--name", f"w{i}", *client], tmp_path / f"w{i}.log") for i in range(2)]
        procs += workers
        reference = _single_node(frames, cal)  # while the nodes start
        for w in workers:
            w.wait_ready()
        merger.wait_ready()
        killed = threading.Event()

        def kill_one(item: Any, t: float) -> None:  # a worker dies with frames in flight
            if item.frame_index == N_FRAMES // 2 and not killed.is_set():
                os.kill(workers[1].pid, signal.SIGKILL)
                killed.set()

        with open_session(_client(port)) as s:
            assert wait_for_token(s, keys(rig).alive("worker") + "/w1", 10)
            col = Collector(s, rig)
            pub = Publisher(
                s, rig, AcquisitionSource(frames), pace="ack", window=4, wait_timeout=30, on_publish=kill_one
            )
            summary = pub.run()
            k = keys(rig)
            dets = col.wait(k.detections, N_FRAMES)
            tracks = col.wait(k.tracks, N_FRAMES)
            errors = col.on(k.errors)
            col.close()
        os.kill(merger.pid, signal.SIGTERM)
        out, _ = merger.proc.communicate(timeout=30)
        stats = json.loads([ln for ln in out.splitlines() if '"stopped"' in ln][-1])
        assert killed.is_set() and workers[1].proc.wait(5) == -signal.SIGKILL
        assert summary["published"] == N_FRAMES and summary["acked"] == N_FRAMES and summary["ack_timeouts"] == 0
        assert errors == []
        # exactly once, in frame order
        assert [d.frame_index for d in dets] == list(range(N_FRAMES))
        assert [t.frame_index for t in tracks] == list(range(N_FRAMES))
        for d in dets:
            assert _same_detections(d, reference[d.frame_index]["detections"]), d.frame_index
        for t in tracks:
            assert _same_tracks(t, reference[t.frame_index]["tracks"]), t.frame_index
        assert any(t.tracks and t.tracks[0].status == "confirmed" for t in tracks)
        # w1 merged frames before it died, its frames in flight went to w0; nothing lost, nothing twice
        assert stats["frames_processed"] == N_FRAMES and stats["duplicates"] == 0
        assert stats["per_worker"]["w1"] >= 1 and stats["per_worker"]["w0"] + stats["per_worker"]["w1"] == N_FRAMES
        assert stats["reassigned"] >= 1 and stats["workers"] == ["w0"]
        assert "worker w1 left" in (tmp_path / "merge.log").read_text()
    finally:
        for p in procs:
            p.stop()


def test_in_process_merger_reuses_indices_reports_bad_frames_and_drops_in_live_mode() -> None:
    """Merger (router) and one worker in this process: a second replay of the same frame indices is merged
    again (as a processor would); a frame without a readable header gets one ErrorReport from the merger;
    in live mode (keep newest) a burst is merged in order with the skipped frames counted as dropped."""
    from services.nodes.merger import Merger, MergerConfig
    from services.nodes.worker import Worker, WorkerConfig

    frames, cal = born_frames(4)
    port = free_port()
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    for queue in ("fifo", "newest"):
        rig = f"inproc-{queue}"
        wcfg = WorkerConfig(**CONFIG, rig=rig, name="solo")
        with open_session(hub) as hs, open_session(_client(port)) as ws, open_session(_client(port)) as ps:
            with Worker(ws, wcfg, [FingerprintSpec("marker", calibration=cal)]):
                with Merger(hs, MergerConfig(rig=rig, queue=queue, depth=1, min_workers=1, wait_workers_s=20)) as m:
                    col = Collector(ps, rig)
                    k = keys(rig)
                    if queue == "fifo":
                        for _ in range(2):
                            Publisher(ps, rig, AcquisitionSource(frames), pace="ack", window=2, wait_timeout=20).run()
                        dets = col.wait(k.detections, 8)
                        assert [d.frame_index for d in dets] == [0, 1, 2, 3] * 2
                        ps.put(k.rf, b"not a frame")
                        errs = col.wait(k.errors, 1)
                        assert len(errs) == 1 and errs[0].node == "merger" and errs[0].frame_index is None
                        assert m.rejected == 1 and m.frames_processed == 8 and m.dropped == 0
                    else:
                        many = AcquisitionSource(frames, repeat=3)  # 12 frames back to back
                        Publisher(ps, rig, many, pace="none", wait_timeout=20).run()
                        deadline = time.monotonic() + 30
                        while m.frames_processed + m.dropped < 12 and time.monotonic() < deadline:
                            time.sleep(0.05)
                        dets = col.on(k.detections)
                        idx = [d.frame_index for d in dets]
                        assert idx == sorted(idx) and len(idx) == m.frames_processed
                        assert m.dropped >= 1 and m.frames_processed + m.dropped == 12 and 11 in idx
                    col.close()


def test_frame_timeout_moves_a_hung_workers_frame() -> None:
    """A worker that hangs on a frame keeps its token; with a frame timeout the merger sends that frame to
    the other worker, merges the first result, in order, and counts the hung worker's late one as duplicate."""
    from services.nodes.merger import Merger, MergerConfig
    from services.nodes.worker import Worker, WorkerConfig

    frames, cal = born_frames(4)
    port, rig = free_port(), "hung"
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    specs = [FingerprintSpec("marker", calibration=cal)]
    mcfg = MergerConfig(rig=rig, queue="fifo", depth=1, min_workers=2, wait_workers_s=20, frame_timeout_s=1.0)
    with open_session(hub) as hs, open_session(_client(port)) as s1, open_session(_client(port)) as s2:
        with (
            Worker(s1, WorkerConfig(**CONFIG, rig=rig, name="hangs"), specs) as hung,
            Worker(s2, WorkerConfig(**CONFIG, rig=rig, name="fine"), specs),
        ):
            compute = hung._compute

            def stall_once(fi: int, payload: Any) -> Any:  # hangs 4 s on its first frame
                if hung.frames_computed == 0:
                    time.sleep(4.0)
                return compute(fi, payload)

            hung._compute = stall_once  # type: ignore[method-assign]
            with Merger(hs, mcfg) as m, open_session(_client(port)) as ps:
                col = Collector(ps, rig)
                summary = Publisher(ps, rig, AcquisitionSource(frames), pace="ack", window=2, wait_timeout=20).run()
                dets = col.wait(keys(rig).detections, 4)
                deadline = time.monotonic() + 10  # every frame moved comes back late from the slow worker
                while (m.duplicates < 1 or m.duplicates < m.timed_out) and time.monotonic() < deadline:
                    time.sleep(0.05)
                col.close()
                assert summary["acked"] == 4 and [d.frame_index for d in dets] == [0, 1, 2, 3]
                # on a loaded machine a frame after the stall may also outlast the 1 s timeout: moved as well
                assert m.timed_out >= 1 and m.duplicates == m.timed_out and m.per_worker["fine"] >= 1


def _order(col: Collector, rig: str) -> list[tuple[str, int]]:
    """(topic, frame index) of the detections and error reports, in arrival order."""
    k = keys(rig)
    with col._lock:
        items = [(key, p) for key, p, _ in col.items if key in (k.detections, k.errors)]
    return [(key.rsplit("/", 1)[-1], decode(p).frame_index) for key, p in items]


def test_a_frame_that_fails_in_the_worker_yields_one_error_report_and_the_next_frames_merge(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A frame whose output messages raise (as a non-finite Normalisation does for an RF scaled to 1e30)
    and one whose computation raises outside the frame's try: each is answered ``failed``, the merger
    publishes one ErrorReport per frame in frame order and merges the frames after them (fifo); the worker's
    thread lives on. Without tracking (--no-track) the Status still names the dictionary."""
    from services.nodes import worker as worker_module
    from services.nodes.merger import Merger, MergerConfig
    from services.nodes.worker import Worker, WorkerConfig

    real = worker_module.frame_messages

    def bad_output(res: Any, fi: int, ts: float) -> Any:
        if fi == 1:
            raise RuntimeError("injected: the frame's messages do not validate")
        return real(res, fi, ts)

    monkeypatch.setattr(worker_module, "frame_messages", bad_output)
    frames, cal = born_frames(4)
    port, rig = free_port(), "fails"
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    mcfg = MergerConfig(
        rig=rig, queue="fifo", depth=1, min_workers=1, wait_workers_s=20, track=False, status_period=0.2
    )
    k = keys(rig)
    with open_session(hub) as hs, open_session(_client(port)) as ws, open_session(_client(port)) as ps:
        with Worker(ws, WorkerConfig(**CONFIG, rig=rig, name="w"), [FingerprintSpec("marker", calibration=cal)]) as w:
            compute = w._compute

            def raises_outside(fi: int, payload: Any) -> Any:
                if fi == 2:
                    raise TypeError("injected: outside the frame's try")
                return compute(fi, payload)

            w._compute = raises_outside  # type: ignore[method-assign]
            with Merger(hs, mcfg) as m:
                col = Collector(ps, rig)
                summary = Publisher(ps, rig, AcquisitionSource(frames), pace="ack", window=2, wait_timeout=20).run()
                dets, errs = col.wait(k.detections, 2), col.wait(k.errors, 2)
                deadline = time.monotonic() + 10
                while not any(s.frames_processed == 2 for s in col.on(k.status)) and time.monotonic() < deadline:
                    time.sleep(0.05)
                statuses = [s for s in col.on(k.status) if s.frames_processed == 2]
                order = _order(col, rig)
                col.close()
                alive = w._thread is not None and w._thread.is_alive()
        assert summary["acked"] == 4 and summary["ack_timeouts"] == 0
        assert [d.frame_index for d in dets] == [0, 3]
        assert [(e.frame_index, e.field, e.node) for e in errs] == [(1, "processing", "w"), (2, "processing", "w")]
        assert errs[0].problem.startswith("RuntimeError: injected") and errs[1].problem.startswith("TypeError")
        assert order == [("detections", 0), ("errors", 1), ("errors", 2), ("detections", 3)]
        assert alive and w.failed == 2 and w.frames_computed == 2
        assert m.failed == 2 and m.frames_processed == 2 and m.stats()["pending"] == 0
        assert statuses and statuses[-1].dictionary == ["marker"] and m.dictionary == ["marker"]


def test_frame_deadline_gives_up_a_frame_its_only_worker_never_returns() -> None:
    """One worker hangs on frame 1 (its token stays, there is no other worker to re-send it to): with
    --frame-deadline the merger gives the frame up with one ErrorReport (field deadline), merges the next
    frames once the worker is back, and counts the late result as a duplicate."""
    from services.nodes.merger import Merger, MergerConfig
    from services.nodes.worker import Worker, WorkerConfig

    frames, cal = born_frames(4)
    port, rig = free_port(), "deadline"
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    mcfg = MergerConfig(rig=rig, queue="fifo", depth=1, min_workers=1, wait_workers_s=20)
    k, release = keys(rig), threading.Event()
    with open_session(hub) as hs, open_session(_client(port)) as ws, open_session(_client(port)) as ps:
        with Worker(ws, WorkerConfig(**CONFIG, rig=rig, name="w"), [FingerprintSpec("marker", calibration=cal)]) as w:
            compute = w._compute

            def hangs(fi: int, payload: Any) -> Any:  # until the merger has given frame 1 up
                if fi == 1:
                    release.wait(20)
                return compute(fi, payload)

            w._compute = hangs  # type: ignore[method-assign]
            with Merger(hs, mcfg) as m:
                col = Collector(ps, rig)
                pub = threading.Thread(
                    target=Publisher(ps, rig, AcquisitionSource(frames), pace="ack", window=2, wait_timeout=20).run
                )
                pub.start()
                # the deadline runs while frame 1 is the only frame out (a loaded machine may take seconds
                # over the worker's first frame): set once frame 0 is merged, lifted once frame 1 is given up
                col.wait(k.detections, 1)
                m.cfg.frame_deadline_s = 0.5
                errs = col.wait(k.errors, 1)
                m.cfg.frame_deadline_s = None
                release.set()
                pub.join(30)
                dets = col.wait(k.detections, 3)
                deadline = time.monotonic() + 10
                while m.duplicates < 1 and time.monotonic() < deadline:
                    time.sleep(0.05)
                order = _order(col, rig)
                col.close()
        assert [(e.frame_index, e.field, e.node) for e in errs] == [(1, "deadline", "merger")]
        assert "worker(s) w within 0.5 s" in errs[0].problem and "(--frame-deadline 0.5)" in errs[0].problem
        assert [d.frame_index for d in dets] == [0, 2, 3]
        assert order == [("detections", 0), ("errors", 1), ("detections", 2), ("detections", 3)]
        assert m.failed == 1 and m.frames_processed == 3 and m.duplicates == 1


def test_merger_refuses_frames_over_its_fifo_depth_and_counts_the_unmerged_at_stop() -> None:
    """No worker alive, --fifo-depth 2: the merger holds two frames and refuses the next ones, each with one
    ErrorReport naming the limit; at stop the two held frames are counted as pending."""
    from services.nodes.merger import Merger, MergerConfig

    frames, _ = born_frames(4)
    port, rig = free_port(), "full"
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    mcfg = MergerConfig(rig=rig, queue="fifo", min_workers=0, wait_workers_s=0, fifo_depth=2)
    k = keys(rig)
    with open_session(hub) as hs, open_session(_client(port)) as ps:
        m = Merger(hs, mcfg)
        with m:
            col = Collector(ps, rig)
            summary = Publisher(ps, rig, AcquisitionSource(frames), pace="none", wait_timeout=20).run()
            errs = col.wait(k.errors, 2)
            col.close()
        stats = m.stats()
    assert summary["published"] == 4
    assert [(e.frame_index, e.field) for e in errs] == [(2, "fifo_depth"), (3, "fifo_depth")]
    assert "--fifo-depth 2" in errs[0].problem
    assert stats["pending"] == 2 and stats["dropped"] == 2 and stats["frames_processed"] == 0
