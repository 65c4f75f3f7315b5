"""Recorder: kill -9 mid-run and `fp recover`, rotation, salvage of truncated files (issue 4; docs/design.md §7,
stack notes on mcap flush/non-seeking reads)."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader

from services.bus import BusConfig, free_port, open_session, put_message, wait_for_matching, wait_for_token
from services.cli import main
from services.messages import Status, examples
from services.nodes.recorder import Recorder, _Received, _Segment
from services.recording import iter_raw, recover, wire_payload
from services.topics import ALL_RIGS, keys
from services.wire import decode, encode

ROOT = Path(__file__).resolve().parent.parent


def _start_recorder(args: list[str], log: Path) -> subprocess.Popen:
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "record", *args],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
    assert proc.stdout is not None
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and proc.poll() is None:
        if select.select([proc.stdout], [], [], 0.2)[0] and '"ready"' in proc.stdout.readline():
            return proc
    os.kill(proc.pid, signal.SIGKILL)
    raise RuntimeError(f"recorder did not start:\n{log.read_text()[-3000:]}")


def _summary_ok(path: Path) -> bool:
    """True for a complete MCAP file (a seeking reader finds its summary)."""
    with open(path, "rb") as f:
        try:
            return make_reader(f).get_summary() is not None
        except Exception:
            return False


@pytest.mark.timeout(60)
def test_kill9_recorder_then_recover_keeps_everything_flushed(tmp_path, capsys) -> None:
    """A recorder killed with SIGKILL mid-run: `fp recover` returns every message older than ~1 s before the
    kill (flush every 0.5 s; docs/design.md §7 stack notes)."""
    rig, port = "k9", free_port()
    path, fixed = tmp_path / "live.mcap", tmp_path / "fixed.mcap"
    sent: list[tuple[int, float]] = []
    frame = encode(examples()["RFFrame"])
    proc = None
    try:
        with open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as s:
            proc = _start_recorder(
                ["--rig", rig, "-o", str(path), "--flush-interval", "0.5", "--connect", f"tcp/127.0.0.1:{port}"],
                tmp_path / "rec.log",
            )
            assert wait_for_token(s, keys(rig).alive("recorder"), 20)
            k = keys(rig)
            block = zenoh.CongestionControl.BLOCK
            status_pub = s.declare_publisher(k.status, congestion_control=block)
            rf_pub = s.declare_publisher(k.rf, congestion_control=block)
            assert wait_for_matching(status_pub, 20) and wait_for_matching(rf_pub, 20)
            t_end = time.time() + 3.0
            i = 0
            while time.time() < t_end:
                put_message(status_pub, s, Status(node="test", frames_processed=i))
                sent.append((i, time.time()))
                if i % 20 == 0:
                    rf_pub.put(frame)
                i += 1
                time.sleep(0.01)
            t_kill = time.time()
            os.kill(proc.pid, signal.SIGKILL)  # mid-run: messages are still flowing
            for j in range(i, i + 20):
                put_message(status_pub, s, Status(node="test", frames_processed=j))
            proc.wait(timeout=10)
            status_pub.undeclare()
            rf_pub.undeclare()
    finally:
        if proc is not None and proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
    assert not _summary_ok(path)  # the killed file has no summary
    assert main(["recover", str(path), "-o", str(fixed)]) == 0
    report = json.loads(capsys.readouterr().out)
    kept = [decode(wire_payload(c, m)).frames_processed for _, c, m in iter_raw(fixed) if c.topic == keys(rig).status]
    must = {i for i, t in sent if t < t_kill - 1.0}
    assert must and must <= set(kept), f"lost {sorted(must - set(kept))[:10]}"
    assert report["messages"] == sum(report["by_key"].values()) >= len(must)
    assert report["by_key"][keys(rig).rf] >= 1
    assert _summary_ok(fixed)


@pytest.mark.timeout(60)
def test_rotation_by_size_and_clean_close(tmp_path) -> None:
    rig, port = "rot", free_port()
    payloads = []
    base = examples()["RFFrame"]
    with (
        open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as s_rec,
        open_session(BusConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])) as s,
    ):
        with Recorder(s_rec, tmp_path / "rot.mcap", rig=rig, flush_interval=0.1, max_bytes=12_000) as rec:
            assert wait_for_token(s, keys(rig).alive("recorder"), 20)
            pub = s.declare_publisher(keys(rig).rf, congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_for_matching(pub, 20)
            for i in range(30):
                msg = base.model_copy(update={"frame_index": i})
                payloads.append(encode(msg))
                put_message(pub, s, msg)
                time.sleep(0.02)
            deadline = time.monotonic() + 10
            while rec.received < 30 and time.monotonic() < deadline:
                time.sleep(0.05)
            pub.undeclare()
    files = rec.files
    assert len(files) >= 2 and [p.name for p in files][:2] == ["rot-000.mcap", "rot-001.mcap"]
    got = []
    for p in files:
        assert _summary_ok(p)  # every segment is a complete MCAP file
        got += [b for _, c, m in iter_raw(p) if (b := wire_payload(c, m)) is not None]  # not the display channels
    assert got == payloads  # the wire bytes, in order, nothing lost across segments


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_recover_truncated_file_keeps_complete_chunks(tmp_path, compression) -> None:
    path = tmp_path / "t.mcap"
    seg = _Segment(path, compression, chunk_size=1 << 20, key_expr=ALL_RIGS)
    msgs = [encode(Status(node="n", frames_processed=i, timestamp=0.0)) for i in range(50)]
    bad = b"FPWIRE01garbage"
    for i, payload in enumerate(msgs):
        seg.write(_Received(keys("t").status, payload, None, 1_000 + i, 1_000 + i))
        if i % 10 == 9:
            seg.flush()  # chunks of 10 messages
    seg.write(_Received(keys("t").status, bad, None, 2_000, 2_000))
    seg.finish()
    full = recover(path, tmp_path / "full.mcap")
    assert full["complete"] and full["messages"] == 51
    schemas = {c.topic + "|" + (s.name if s else "") for s, c, _ in iter_raw(tmp_path / "full.mcap")}
    status = keys("t").status
    assert schemas == {f"{status}|Status", f"{status}|unknown"}  # the raw bad message has its own channel
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) == 6
    fourth = chunks[3]
    cut = tmp_path / "cut.mcap"  # as if the writer died while writing the 4th chunk
    cut.write_bytes(path.read_bytes()[: fourth.chunk_start_offset + fourth.chunk_length // 2])
    rep = recover(cut, tmp_path / "cut_fixed.mcap")
    kept = [wire_payload(c, m) for _, c, m in iter_raw(tmp_path / "cut_fixed.mcap")]
    assert not rep["complete"] and rep["error"]
    assert rep["messages"] == len(kept) == 30 and kept == msgs[:30]


@pytest.mark.timeout(60)
def test_include_and_exclude_key_expressions(tmp_path) -> None:
    """--include narrows what is recorded, --exclude leaves keys out; the rest is recorded (zstd by default)."""
    port = free_port()
    path = tmp_path / "sel.mcap"
    rf = encode(examples()["RFFrame"])
    with (
        open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as s_rec,
        open_session(BusConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])) as s,
    ):
        with Recorder(s_rec, path, include=["fp/inc/**"], exclude=["fp/*/rf"], flush_interval=0.1) as rec:
            assert wait_for_token(s, keys("_any").alive("recorder"), 20)
            block = zenoh.CongestionControl.BLOCK
            pubs = {
                k: s.declare_publisher(k, congestion_control=block)
                for k in (keys("inc").status, keys("inc").rf, keys("oth").status)
            }
            for p in pubs.values():
                assert wait_for_matching(p, 20)
            for i in range(5):
                put_message(pubs[keys("inc").status], s, Status(node="n", frames_processed=i))
                pubs[keys("inc").rf].put(rf)
                put_message(pubs[keys("oth").status], s, Status(node="n", frames_processed=i))
            deadline = time.monotonic() + 10
            while rec.received + rec.skipped < 15 and time.monotonic() < deadline:
                time.sleep(0.05)
            for p in pubs.values():
                p.undeclare()
    topics = [c.topic for _, c, _ in iter_raw(path)]
    assert topics == [keys("inc").status] * 5 and rec.skipped == 10
    with open(path, "rb") as f:
        assert {c.compression for c in make_reader(f).get_summary().chunk_indexes} == {"zstd"}
    with pytest.raises(ValueError, match="--include: expected a zenoh key expression"):
        Recorder(s_rec, path, include=["fp//bad"])


def test_int16_rf_with_its_scale_travels_and_decodes() -> None:
    """RFFrame 1.2: int16 RF with rf_scale (a scanner's ADC) decodes to float32 RF × scale, within half a step."""
    from services.convert import quantise_rf
    from services.messages import RFFrame

    frame = examples()["RFFrame"]
    q = quantise_rf(frame, bits=12)
    back = decode(encode(q))
    assert isinstance(back, RFFrame) and back.rf.dtype.str == "<i2" and back.rf_scale == q.rf_scale
    assert int(abs(back.rf).max()) == 2047
    err = abs(back.to_acquisition().rf - frame.rf).max()
    assert err <= q.rf_scale / 2 * (1 + 1e-6)
    assert len(encode(q)) < len(encode(frame))
    with pytest.raises(Exception, match="rf_scale"):
        RFFrame.model_validate({**frame.model_dump(), "rf_scale": 2.0})  # float RF has no scale


def test_demo_listens_on_the_well_known_hub_that_the_live_viewer_connects_to() -> None:
    """`fp view --live` with no flags connects to DEFAULT_HUB; `fp demo` listens there (or on a free port, said on
    its console, when another node holds it)."""
    import socket

    from services.bus import DEFAULT_HUB, bus_from_args
    from services.cli import build_parser
    from services.cli.demo import demo_hub

    view = build_parser().parse_args(["view", "--live"])
    assert bus_from_args(view).connect == [DEFAULT_HUB]
    port = int(DEFAULT_HUB.rsplit(":", 1)[1])
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            pytest.skip(f"{DEFAULT_HUB} is held by another process on this machine")
        s.listen()
        other = demo_hub(None)  # the hub is taken: a free loopback port instead
        assert other.startswith("tcp/127.0.0.1:") and other != DEFAULT_HUB
    assert demo_hub(None) == DEFAULT_HUB
    with pytest.raises(ValueError, match="--listen: expected a loopback endpoint"):
        demo_hub("tcp/0.0.0.0:7447")
