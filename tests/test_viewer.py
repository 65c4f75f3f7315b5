"""`fp view` / `fp figure` on the shipped sample recording (issue 6)."""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from services.cli import main
from services.messages import GammaMap
from services.recorder import iter_raw
from services.viewer import iter_messages, to_figure, to_rrd
from services.wire import decode

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "recordings" / "sinking-sphere-quick.mcap"
RERUN_CLI = Path(sys.executable).with_name("rerun")


def _gamma_frames() -> list[int]:
    return sorted({m.frame_index for _, m in iter_messages(SAMPLE) if isinstance(m, GammaMap)})


def test_sample_recording_decodes_with_current_schemas() -> None:
    assert SAMPLE.stat().st_size < 5_000_000
    n = 0
    for _schema, channel, msg in iter_raw(SAMPLE):
        decoded = decode(msg.data)  # raises WireError on any schema drift
        assert channel.topic.startswith("fp/") and channel.message_encoding == "fpwire"
        assert decoded.schema_name == channel.metadata.get("schema_name", decoded.schema_name)
        n += 1
    assert n > 0
    assert len(_gamma_frames()) >= 3


def test_view_writes_rrd_with_one_row_per_frame(tmp_path: Path) -> None:
    rrd = tmp_path / "sample.rrd"
    assert main(["view", str(SAMPLE), "--rrd", str(rrd)]) == 0
    assert rrd.stat().st_size > 0
    frames = _gamma_frames()
    if RERUN_CLI.exists():
        res = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(rrd)], capture_output=True, text=True,
                             timeout=60)
        assert res.returncode == 0, res.stderr

    from rerun.chunk import RrdReader

    reader = RrdReader(rrd)
    assert reader.blueprints(), "default blueprint missing"
    rows: dict[str, list[int]] = defaultdict(list)
    for chunk in reader.stream():
        if not chunk.is_static and "frame" in chunk.timeline_names:
            rows[chunk.entity_path] += chunk.to_record_batch().column("frame").to_pylist()
    gamma_entities = [e for e in rows if e.startswith("/world/gamma/") or e.endswith("/gamma")]
    assert gamma_entities
    for entity in gamma_entities:
        assert sorted(rows[entity]) == frames, entity
    for prefix in ("/world/detections/", "/world/tracks/", "/series/", "/sections/"):
        assert any(e.startswith(prefix) for e in rows), prefix


def test_to_rrd_summary(tmp_path: Path) -> None:
    out = to_rrd(SAMPLE, tmp_path / "s.rrd")
    assert out["undecodable"] == 0 and out["error"] is None
    assert out["frames"] == _gamma_frames()
    for fp in out["fingerprints"]:
        assert out["logged"][f"world/gamma/{fp}"] == len(out["frames"])
        assert out["logged"][f"sections/{fp}/xz/gamma"] == len(out["frames"])


def test_figure_png(tmp_path: Path) -> None:
    png = tmp_path / "f.png"
    frame = _gamma_frames()[1]
    assert main(["figure", str(SAMPLE), "--frame", str(frame), "--png", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_figure_missing_frame(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="frame 999"):
        to_figure(SAMPLE, 999, tmp_path / "x.png")


def test_live_view_logs_the_bus_to_rrd(tmp_path) -> None:
    """`fp view --live`: messages put on fp/demo/* over loopback zenoh end up in the .rrd, per frame."""
    import threading
    import time

    import zenoh

    from services.bus import EPHEMERAL, BusConfig, free_port, open_session, wait_for_matching, wait_for_token
    from services.recorder import iter_raw
    from services.viewer import live_to_rrd

    hub = f"tcp/127.0.0.1:{free_port()}"
    stop = threading.Event()
    out: dict = {}
    live: dict = {}
    rrd = tmp_path / "live.rrd"
    pubs: dict[str, zenoh.Publisher] = {}
    with open_session(BusConfig(listen=[hub], connect=[], shm="off")) as session:
        viewer = threading.Thread(target=lambda: out.update(live_to_rrd(
            BusConfig(listen=[EPHEMERAL], connect=[hub], shm="off"), "demo", rrd, stop=stop, duration=60,
            stats=live)))
        viewer.start()
        try:
            assert wait_for_token(session, "fp/demo/alive/viewer", 20.0)
            # One blocking publisher per key, each matched before the first put: a plain session.put drops
            # under load (congestion control DROP) and a put before the subscription arrives is lost.
            n = 0
            for _schema, channel, msg in iter_raw(SAMPLE):
                if channel.topic not in pubs:
                    pubs[channel.topic] = session.declare_publisher(
                        channel.topic, congestion_control=zenoh.CongestionControl.BLOCK)
                    assert wait_for_matching(pubs[channel.topic], 20.0), channel.topic
                pubs[channel.topic].put(bytes(msg.data))
                n += 1
            deadline = time.monotonic() + 20.0  # until the viewer has logged every message
            while live.get("messages", 0) < n and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            for pub in pubs.values():
                pub.undeclare()
            stop.set()
            viewer.join(30)
    assert (out["messages"], out["undecodable"], out["dropped"]) == (n, 0, 0)
    assert out["frames"] == [0, 1, 2, 3]
    assert rrd.stat().st_size > 10_000
