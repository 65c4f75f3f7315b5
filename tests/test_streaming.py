"""Streaming service over real zenoh on loopback (issue 4; docs/design.md §2, §7).

Nodes run as `fp process` / `fp record` subprocesses (stopped by pid in `finally`) or in-process;
every test uses its own random loopback port. Frames are small 2D Born frames (32 elements,
5 plane waves, 400 samples).
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fpcore.io import write_uff
from services.bus import BusConfig, FifoSlot, LatestSlot, free_port, open_session, wait_for_token
from services.messages import RFFrame
from services.nodes.processor import Processor, ProcessorConfig
from services.nodes.publisher import Publisher
from services.recording import JSON_SCHEMAS, SHUFFLED_ENCODING, iter_raw, wire_payload
from services.registry import FingerprintSpec, dictionary_request
from services.sources import AcquisitionSource, IngestSource, MCAPSource, born_frames
from services.topics import keys
from services.wire import decode, decode_header, encode, encode_with_header

ROOT = Path(__file__).resolve().parent.parent
GRID = ["--x=-5mm:5mm", "--z=10mm:22mm", "--spacing=0.25mm"]  # small grid: FFTW planning takes seconds
SMALL: dict[str, Any] = {"x_range": (-5e-3, 5e-3), "z_range": (10e-3, 22e-3), "spacing": 0.25e-3, "n_freq": 24}


# ----------------------------------------------------------------------------------------------- helpers
class Node:
    """A `python -m services.cli ARGS` subprocess (stderr to ``log``), stopped by pid."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.name, self.log = args[0], log
        with open(log, "w") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "services.cli", *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True
            )

    @property
    def pid(self) -> int:
        return self.proc.pid

    def wait_ready(self, timeout: float = 45.0) -> Node:
        """Wait for the node's JSON "ready" line."""
        out = self.proc.stdout
        assert out is not None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if select.select([out], [], [], 0.2)[0]:
                line = out.readline()
                if line.startswith("{") and json.loads(line).get("ready"):
                    return self
            if self.proc.poll() is not None:
                break
        self.stop()
        raise RuntimeError(f"node {self.name} did not start:\n{self.log.read_text()[-3000:]}")

    def stop(self, sig: int = signal.SIGTERM) -> None:
        """SIGTERM (clean shutdown) by pid; SIGKILL after 20 s."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, sig)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=10)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


class Collector:
    """Subscribes to fp/<rig>/** and keeps (key, payload, attachment) of everything."""

    def __init__(self, session: Any, rig: str) -> None:
        self.items: list[tuple[str, bytes, bytes | None]] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(keys(rig).all, self._on)

    def _on(self, sample: Any) -> None:
        att = sample.attachment
        with self._lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes(), att.to_bytes() if att else None))

    def close(self) -> None:
        self._sub.undeclare()

    def on(self, key: str) -> list[Any]:
        with self._lock:
            items = [(p, a) for k, p, a in self.items if k == key]
        return [decode(p) for p, _ in items]

    def wait(self, key: str, n: int, timeout: float = 20.0) -> list[Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if sum(k == key for k, _, _ in self.items) >= n:
                    break
            time.sleep(0.05)
        return self.on(key)


def client(port: int) -> BusConfig:
    return BusConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Any]:
    d = tmp_path_factory.mktemp("stream")
    frames, cal = born_frames(6)
    write_uff(d / "cal.uff", cal)
    return {"dir": d, "frames": frames, "cal": cal, "cal_path": d / "cal.uff"}


def _processor_args(rig: str, port: int, cal: Path, *extra: str) -> list[str]:
    return [
        "process",
        "--rig",
        rig,
        "--calibration",
        str(cal),
        *GRID,
        "--n-freq",
        "24",
        "--queue",
        "fifo",
        "--listen",
        f"tcp/127.0.0.1:{port}",
        *extra,
    ]


def _same_detections(a: Any, b: Any) -> bool:
    """Equal up to the NUFFT's multithreaded summation order (≈ 1e-7 relative)."""
    return len(a.detections) == len(b.detections) and all(
        x.fingerprint == y.fingerprint
        and np.allclose(x.position_m, y.position_m, rtol=0, atol=1e-8)
        and np.isclose(x.gamma_max, y.gamma_max, rtol=1e-4)
        and np.isclose(x.pfa, y.pfa, rtol=1e-2, atol=1e-30)
        and np.isclose(x.contrast_c_gamma, y.contrast_c_gamma, rtol=1e-4)
        for x, y in zip(a.detections, b.detections, strict=True)
    )


# ------------------------------------------------------------------------------------------------- tests
@pytest.mark.timeout(90)
def test_end_to_end_record_and_replay(data, tmp_path) -> None:
    """N frames → N GammaMap + N Detections (same indices); the MCAP holds them; its replay to a fresh
    processor gives the same detections."""
    rig, port, port2 = "e2e", free_port(), free_port()
    frames = data["frames"]
    n = len(frames)
    mcap_path = tmp_path / "run.mcap"
    procs = []
    try:  # the fresh processor of the replay starts now too: start-ups overlap
        procs.append(Node(_processor_args(rig, port2, data["cal_path"]), tmp_path / "proc2.log"))
        procs.append(Node(_processor_args(rig, port, data["cal_path"]), tmp_path / "proc.log"))
        procs.append(
            Node(
                ["record", "--rig", rig, "-o", str(mcap_path), "--connect", f"tcp/127.0.0.1:{port}"],
                tmp_path / "rec.log",
            )
        )
        for p in procs:
            p.wait_ready()
        with open_session(client(port)) as s:
            col = Collector(s, rig)
            pub = Publisher(
                s, rig, AcquisitionSource(frames), pace="ack", wait_for=("processor", "recorder"), wait_timeout=30
            )
            summary = pub.run()
            k = keys(rig)
            dets = col.wait(k.detections, n)
            gammas = col.wait(k.gamma, n)
            tracks = col.wait(k.tracks, n)
            col.close()
        assert summary["published"] == n and summary["acked"] == n
        assert sorted(d.frame_index for d in dets) == list(range(n))
        assert sorted(g.frame_index for g in gammas) == list(range(n))
        assert sorted(t.frame_index for t in tracks) == list(range(n))
        for d in dets:
            assert d.timestamp == pytest.approx(frames[d.frame_index].timestamp)
            det = d.detections[0]
            assert det.fingerprint == "marker" and 0 < det.gamma_max <= 1  # the target the calibration records
            assert det.truth_error_m is not None and det.truth_error_m < 0.5e-3
            assert det.pfa < 1e-3 and det.contrast_c_gamma > 3
        g = gammas[0]
        assert g.gamma.shape == g.grid.shape and float(g.gamma.max()) <= 1.0 + 1e-4
        time.sleep(1.2)  # at least one Status (1 s period) reaches the recorder
        procs.pop().stop()  # recorder: finishes the file
        rec: dict[str, list[bytes]] = {}
        schemas: dict[str, str] = {}
        for schema, channel, msg in iter_raw(mcap_path):
            rec.setdefault(channel.topic, []).append(wire_payload(channel, msg) or bytes(msg.data))
            expected = (
                "protobuf"
                if "/display/" in channel.topic
                else "json"
                if schema.name in JSON_SCHEMAS
                else SHUFFLED_ENCODING
            )
            assert channel.message_encoding == expected  # JSON: no arrays; protobuf: Foxglove display views
            schemas[channel.topic] = schema.name
        for topic in ("rf", "gamma", "image", "detections", "tracks"):
            assert len(rec[k.topic(topic)]) == n, topic
        assert schemas[k.rf] == "RFFrame" and schemas[k.detections] == "Detections"
        assert len(rec[k.status]) >= 1
        sent = {encode(RFFrame.from_acquisition(f)) for f in frames}
        assert set(rec[k.rf]) == sent  # the same bytes as on the wire
        # Replay the recording to the fresh processor (which saw nothing so far).
        with open_session(client(port2)) as s:
            col = Collector(s, rig)
            replay = Publisher(s, rig, MCAPSource(mcap_path), pace="ack", wait_timeout=30).run()
            dets2 = col.wait(k.detections, n)
            col.close()
        assert replay["published"] == n
        first = {d.frame_index: d for d in dets}
        again = {d.frame_index: d for d in dets2}
        assert sorted(again) == sorted(first)
        assert all(_same_detections(first[i], again[i]) for i in first)
    finally:
        for p in procs:
            p.stop()


@pytest.mark.timeout(150)
def test_a_publisher_that_ends_at_once_loses_no_frame(data, tmp_path) -> None:
    """Each `fp publish` of one frame ends right after its put, and the frame's shared memory goes with the
    process: its closing barrier (services.bus.sync_with) holds the session until the recorder has the frame.
    Without it, 4 runs in 6 lost the frame at the recorder (zenoh drops an unmappable sample silently)."""
    rig, port, runs = "shm", free_port(), 4
    uff, mcap_path = tmp_path / "one.uff", tmp_path / "one.mcap"
    write_uff(uff, data["frames"][0])
    # shared memory on, with a small pool (Docker's /dev/shm is 64 MiB); left to "auto" where even that is short
    shm_free = shutil.disk_usage("/dev/shm").free if os.path.isdir("/dev/shm") else 0
    shm = ["--shm", "32" if shm_free >= 64 << 20 else "auto"]
    rec = Node(
        ["record", "--rig", rig, "-o", str(mcap_path), "--listen", f"tcp/127.0.0.1:{port}", "--connect", "none", *shm],
        tmp_path / "rec.log",
    )
    try:
        rec.wait_ready()
        for _ in range(runs):
            pub = ["publish", "--rig", rig, "--uff", str(uff), "--wait-for", "recorder", "--wait-timeout", "30"]
            cmd = [sys.executable, "-m", "services.cli", *pub, "--connect", f"tcp/127.0.0.1:{port}", *shm]
            done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
            assert done.returncode == 0, done.stderr[-2000:]
            summary = json.loads(done.stdout.strip().splitlines()[-1])
            assert summary["published"] == 1 and summary["synced"] == 1, done.stderr[-2000:]
    finally:
        rec.stop()
    rf = [m for _, ch, m in iter_raw(mcap_path) if ch.topic == keys(rig).rf]
    assert len(rf) == runs, (tmp_path / "rec.log").read_text()[-2000:]


def _bad_payloads(frame: RFFrame) -> dict[str, tuple[bytes, bytes]]:
    """name → (payload, attachment) of the five kinds of bad input (docs/design.md §7)."""

    def build(**changes: Any) -> RFFrame:
        return RFFrame.model_construct(**{**dict(frame), **changes})

    def with_header(msg: RFFrame) -> tuple[bytes, bytes]:
        return encode_with_header(msg)

    rf = np.asarray(frame.rf)
    nan = rf.copy()
    nan[3, 2, 100] = np.nan
    good, hdr = encode_with_header(frame.model_copy(update={"frame_index": 3}))
    big = np.zeros(rf.shape[:2] + (rf.shape[2] * 8,), np.float32)
    return {
        "shape": with_header(build(frame_index=1, rf=rf[:-1].copy())),
        "nan": with_header(build(frame_index=2, rf=nan)),
        "truncated": (good[:-1000], hdr),
        "version": with_header(build(frame_index=4, schema_version="9.0")),
        "oversize": with_header(frame.model_copy(update={"frame_index": 5, "rf": big})),
    }


@pytest.mark.timeout(90)
def test_malformed_frames_are_reported_and_recorded(data, tmp_path) -> None:
    rig, port = "bad", free_port()
    frames = data["frames"]
    mcap_path = tmp_path / "bad.mcap"
    good = [
        RFFrame.from_acquisition(frames[0]),
        RFFrame.from_acquisition(frames[1]).model_copy(update={"frame_index": 6}),
    ]
    bad = _bad_payloads(RFFrame.from_acquisition(frames[2]))
    procs = []
    try:
        procs.append(
            Node(_processor_args(rig, port, data["cal_path"], "--max-frame-bytes", "600000"), tmp_path / "proc.log")
        )
        procs.append(
            Node(
                ["record", "--rig", rig, "-o", str(mcap_path), "--connect", f"tcp/127.0.0.1:{port}"],
                tmp_path / "rec.log",
            )
        )
        for p in procs:
            p.wait_ready()
        k = keys(rig)
        with open_session(client(port)) as s:
            assert wait_for_token(s, k.alive("processor"), 30)
            assert wait_for_token(s, k.alive("recorder"), 30)
            col = Collector(s, rig)
            import zenoh

            pub = s.declare_publisher(k.rf, congestion_control=zenoh.CongestionControl.BLOCK)
            sequence = [encode_with_header(good[0]), *bad.values(), encode_with_header(good[1])]
            for payload, header in sequence:
                pub.put(payload, attachment=header, timestamp=s.new_timestamp())
            errors = col.wait(k.errors, 5)
            dets = col.wait(k.detections, 2)
            time.sleep(1.2)  # a flush of the recorder, and a status after the last frame
            statuses = col.on(k.status)
            pub.undeclare()
            col.close()
        assert sorted(d.frame_index for d in dets) == [0, 6]  # the node went on after the bad frames
        by_index = {e.frame_index: e for e in errors}
        assert len(errors) == 5 and sorted(by_index) == [1, 2, 3, 4, 5]
        assert by_index[1].field == "rf" and "expected shape" in by_index[1].problem
        assert by_index[2].field == "rf" and "NaN" in by_index[2].problem
        assert "truncated" in by_index[3].problem or "expected exactly" in by_index[3].problem
        assert by_index[4].field == "schema_version" and "9.0" in by_index[4].problem
        assert by_index[5].field == "payload" and "exceeds the limit" in by_index[5].problem
        assert all(e.key == k.rf and e.node == "processor" for e in errors)
        assert statuses[-1].rejected == 5 and statuses[-1].frames_processed == 2
        procs.pop().stop()
        recorded: dict[bytes, str] = {}
        for schema, channel, msg in iter_raw(mcap_path):
            if channel.topic == k.rf:
                recorded[wire_payload(channel, msg) or b""] = schema.name
        for name, (payload, _) in bad.items():
            assert payload in recorded, name  # the raw bad message is kept
        assert recorded[bad["version"][0]] == "unknown"
        assert recorded[bad["nan"][0]] == "RFFrame"
    finally:
        for p in procs:
            p.stop()


@pytest.mark.timeout(60)
def test_live_mode_keeps_the_newest_frame_and_counts_drops(data) -> None:
    """Keep-newest back-pressure: frames sent faster than processed are dropped and counted; the newest
    frame is always processed (docs/design.md §7)."""
    rig, port = "live", free_port()
    frames = data["frames"]
    cfg = ProcessorConfig(rig=rig, queue="newest", **SMALL, status_period=0.2)
    done: list[int] = []

    def slow(result: dict[str, Any]) -> None:  # a slow consumer: 0.3 s per frame
        done.append(result["frame_index"])
        time.sleep(0.3)

    with (
        open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as s_proc,
        open_session(client(port)) as s_pub,
    ):
        with Processor(
            s_proc, cfg, [FingerprintSpec("pt", model="point", r0=(0.0, 0.0, 15e-3))], on_result=slow
        ) as node:
            src = AcquisitionSource(frames, repeat=2)
            summary = Publisher(s_pub, rig, src, pace="none", wait_timeout=20).run()
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and node.frames_processed + node.dropped < summary["published"]:
                time.sleep(0.05)
            time.sleep(0.3)
    n = summary["published"]
    assert n == 12
    assert node.dropped > 0 and node.frames_processed + node.dropped == n
    assert done[-1] == n - 1 and done == sorted(done)


@pytest.mark.timeout(60)
def test_dictionary_queryable(data) -> None:
    rig, port = "dict", free_port()
    cfg = ProcessorConfig(rig=rig, queue="fifo", **SMALL)
    with (
        open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as s_proc,
        open_session(client(port)) as s,
    ):
        with Processor(s_proc, cfg, [FingerprintSpec("marker", calibration=data["cal"])]) as node:
            assert wait_for_token(s, keys(rig).alive("processor"), 20)
            listing = dictionary_request(s, rig, "list")
            assert listing["ok"] and [e["name"] for e in listing["entries"]] == ["marker"]
            assert listing["entries"][0]["built"] and listing["entries"][0]["n_s"] >= 1
            added = dictionary_request(s, rig, "add", "pt", {"model": "point", "r0_m": [0.0, 0.0, 0.015]})
            assert added["ok"] and added["added"]["provenance"] == "model:point"
            cal2 = encode(RFFrame.from_acquisition(data["cal"]))
            added = dictionary_request(s, rig, "add", "cal2", cal2, options={"r0_m": [0.0, 0.0, 0.015]})
            assert added["ok"] and added["added"]["provenance"] == "calibration"
            bad = dictionary_request(s, rig, "add", "m", {"model": "mirror:alpha=3"})
            assert not bad["ok"] and "mirror needs L" in bad["error"]
            assert dictionary_request(s, rig, "get", "pt")["entry"]["name"] == "pt"
            assert dictionary_request(s, rig, "remove", "cal2")["entries"] == ["marker", "pt"]
            assert not dictionary_request(s, rig, "remove", "nope")["ok"]
            res = dictionary_request(s, rig, "set", payload={"svd_threshold": 0.6, "n_freq": 20})
            assert res["ok"] and res["params"]["svd_threshold"] == 0.6 and res["params"]["n_freq"] == 20
            assert all(e["built"] for e in res["entries"])
            assert not dictionary_request(s, rig, "set", payload={"colour": 1})["ok"]
            assert node.dictionary == ["marker", "pt"]
            # A frame after the changes: one γ-map per entry.
            col = Collector(s, rig)
            Publisher(s, rig, AcquisitionSource(data["frames"][:1]), pace="ack", wait_timeout=20).run()
            gammas = col.wait(keys(rig).gamma, 2)
            col.close()
            assert sorted(g.fingerprint for g in gammas) == ["marker", "pt"]


@pytest.mark.timeout(60)
def test_ingest_validates_and_forwards(data) -> None:
    """Anything put on fp/<rig>/ingest is validated by the publisher; good frames go on …/rf as the same bytes."""
    rig, port = "ing", free_port()
    frame = RFFrame.from_acquisition(data["frames"][0])
    good = encode(frame)
    rf = np.asarray(frame.rf).copy()
    rf[0, 0, 0] = np.inf
    bad = encode(RFFrame.model_construct(**{**dict(frame), "rf": rf, "frame_index": 9}))
    stop = threading.Event()
    # The ingest client creates its SHM pool when it opens, as `fp publish` does (services.bus_warm): created at
    # its first large put instead, the pool's next message — the good frame — could reach the publisher before
    # the pool was mappable there, and zenoh drops such a sample silently (≈ 1 run in 8 here).
    producer = replace(client(port), warm_shm=True)
    with (
        open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as s_pub,
        open_session(producer) as s,
    ):
        src = IngestSource(rig)
        pub = Publisher(s_pub, rig, src, pace="none", wait_for=())
        result: dict[str, Any] = {}
        th = threading.Thread(target=lambda: result.update(pub.run(stop)))
        th.start()
        try:
            col = Collector(s, rig)
            assert wait_for_token(s, keys(rig).alive("publisher"), 20)  # declared after the ingest subscription
            s.put(keys(rig).ingest, bad)
            s.put(keys(rig).ingest, good)
            col.wait(keys(rig).rf, 1)
            errs = col.wait(keys(rig).errors, 1)
            with col._lock:
                forwarded = [(p, a) for k, p, a in col.items if k == keys(rig).rf]
            col.close()
        finally:
            stop.set()
            th.join(timeout=10)
    assert len(forwarded) == 1 and forwarded[0][0] == good
    assert decode_header(forwarded[0][1]).frame_index == 0  # the header travels as the attachment
    assert len(errs) == 1 and errs[0].node == "publisher" and errs[0].key == keys(rig).ingest
    assert errs[0].frame_index == 9 and "NaN or inf" in errs[0].problem
    assert result["published"] == 1 and result["rejected"] == 1


def test_back_pressure_slots() -> None:
    ring: LatestSlot[int] = LatestSlot()
    for i in range(5):
        ring.put(i)
    assert ring.get(timeout=0.1) == 4 and ring.dropped == 4
    fifo: FifoSlot[int] = FifoSlot(2)
    fifo.put(1)
    fifo.put(2)
    stop = threading.Event()
    stop.set()
    fifo.put(3, stop)  # full: gives up only because stop is set (never drops otherwise)
    assert [fifo.get(timeout=0.1), fifo.get(timeout=0.1)] == [1, 2] and fifo.dropped == 0


def test_cli_registers_streaming_commands() -> None:
    from services.cli import build_parser

    ap = build_parser()
    for argv in (
        ["publish", "--ingest"],
        ["process"],
        ["record"],
        ["recover", "x.mcap"],
        ["locate", "d.uff", "--model", "point"],
    ):
        assert callable(ap.parse_args(argv).func), argv


def test_bus_config_flags_and_json5_file(tmp_path) -> None:
    """Defaults: peer, loopback, multicast off, connect/timeout_ms; a JSON5 file is kept where no flag is given."""
    import argparse

    from services.bus import DEFAULT_HUB, add_bus_arguments, bus_from_args, zenoh_config

    def get(cfg: Any, key: str) -> Any:
        return json.loads(cfg.get_json(key))

    ap = argparse.ArgumentParser()
    add_bus_arguments(ap)
    cfg = zenoh_config(bus_from_args(ap.parse_args(["--listen", "tcp/127.0.0.1:7000", "--shm", "off"])))
    assert get(cfg, "mode") == "peer" and get(cfg, "listen/endpoints") == ["tcp/127.0.0.1:7000"]
    assert get(cfg, "connect/endpoints") == [DEFAULT_HUB] and get(cfg, "connect/timeout_ms") == 2000
    assert get(cfg, "scouting/multicast/enabled") is False and get(cfg, "transport/shared_memory/enabled") is False
    cfg = zenoh_config(bus_from_args(ap.parse_args(["--shm", "64", "--connect", "none"])))
    assert get(cfg, "transport/shared_memory/transport_optimization/pool_size") == 64 << 20
    assert get(cfg, "connect/endpoints") == []
    f = tmp_path / "z.json5"
    f.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:9999"] },\n'
        "  scouting: { multicast: { enabled: true } } }  // a comment"
    )
    cfg = zenoh_config(bus_from_args(ap.parse_args(["--zenoh-config", str(f)])))
    assert get(cfg, "mode") == "client" and get(cfg, "connect/endpoints") == ["tcp/127.0.0.1:9999"]
    assert get(cfg, "scouting/multicast/enabled") is True and get(cfg, "connect/timeout_ms") == 2000
    cfg = zenoh_config(bus_from_args(ap.parse_args(["--zenoh-config", str(f), "--mode", "peer"])))
    assert get(cfg, "mode") == "peer"
