"""`fp view` / `fp figure` on the shipped sample recording (issue 6)."""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from services.cli import main
from services.messages import GammaMap
from services.recording import iter_messages, iter_raw, iter_recording, wire_payload
from services.topics import PREFIX, keys
from services.viewing.frame_figure import to_figure
from services.viewing.rerun_log import to_rrd
from services.wire import decode

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "recordings" / "sinking-sphere-quick.mcap"
RERUN_CLI = Path(sys.executable).with_name("rerun")


def _gamma_frames() -> list[int]:
    return sorted({m.frame_index for _, m in iter_messages(SAMPLE) if isinstance(m, GammaMap)})


def test_sample_recording_decodes_with_current_schemas() -> None:
    assert SAMPLE.stat().st_size < 6_500_000  # 6.2 MB: the halo geometry and the beams' reciprocity (5.6 MB before)
    n = 0
    for _schema, channel, msg in iter_raw(SAMPLE):
        assert channel.topic.startswith(f"{PREFIX}/")
        payload = wire_payload(channel, msg)  # None: a Foxglove display channel (tests/test_foxglove_recording.py)
        if payload is None:
            assert channel.message_encoding == "protobuf" and "/display/" in channel.topic
            continue
        decoded = decode(payload)  # raises WireError on any schema drift
        assert channel.message_encoding == (
            "json" if not type(decoded).model_fields.keys() & {"rf", "gamma", "image"} else "fpwire"
        )
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
        res = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=60)
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


def test_figure_draws_every_fingerprint_with_its_recorded_diameter(tmp_path: Path) -> None:
    """The Figure 2 layout: all γ-maps of the frame, outlines from the fingerprints' diameter_m state."""
    import matplotlib.image

    frame = _gamma_frames()[2]
    states = {
        m.fingerprint: m.state for _, m in iter_messages(SAMPLE) if isinstance(m, GammaMap) and m.frame_index == frame
    }
    out = to_figure(SAMPLE, frame, tmp_path / "all.png")
    assert out["fingerprints"] == list(states)
    assert out["diameters_m"] == {k: v["diameter_m"] for k, v in states.items()}
    img = matplotlib.image.imread(tmp_path / "all.png")
    assert img.shape[0] > 500 and img.shape[1] > 1000  # two rows, (x, z) + one (y, z) per sphere
    one = to_figure(SAMPLE, frame, tmp_path / "one.png", fingerprint="sphere2")
    assert one["fingerprints"] == ["sphere2"] and one["detection"][0] > 0


def test_figure_rejects_bad_threshold(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["figure", str(SAMPLE), "--frame", "1", "--png", str(tmp_path / "x.png"), "--threshold", "1.5"]) == 2
    assert "--threshold: expected a fraction of γ at the detection in (0, 1), got 1.5" in capsys.readouterr().err


def test_figure_missing_frame(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="frame 999"):
        to_figure(SAMPLE, 999, tmp_path / "x.png")


@pytest.mark.parametrize("serve", [False, True], ids=["rrd", "rrd+serve"])
def test_live_view_logs_the_bus_to_rrd(tmp_path: Path, serve: bool) -> None:
    """`fp view --live [--serve]`: messages put on fp/demo/* over loopback zenoh end up in the .rrd, per
    frame; with --serve they are also streamed to a web viewer whose sockets are checked to be loopback
    only (what reaches the viewer is rerun's business; the .rrd is the same stream)."""
    import threading
    import time

    import zenoh

    from services.bus import EPHEMERAL, BusConfig, free_port, open_session, wait_for_matching, wait_for_token
    from services.viewing.rerun_log import live_to_rrd
    from services.viewing.server import serve_loopback

    hub = f"tcp/127.0.0.1:{free_port()}"
    stop = threading.Event()
    out: dict = {}
    live: dict = {}
    rrd = tmp_path / "live.rrd"
    pubs: dict[str, zenoh.Publisher] = {}
    web, grpc = _two_ports()
    viewer = serve_loopback(port=web, grpc_port=grpc) if serve else None
    try:
        with open_session(BusConfig(listen=[hub], connect=[], shm="off")) as session:
            thread = threading.Thread(
                target=lambda: out.update(
                    live_to_rrd(
                        BusConfig(listen=[EPHEMERAL], connect=[hub], shm="off"),
                        "demo",
                        rrd,
                        stop=stop,
                        duration=60,
                        stats=live,
                        grpc_url=viewer.grpc_url if viewer else None,
                    )
                )
            )
            thread.start()
            try:
                assert wait_for_token(session, keys("demo").alive("viewer"), 20.0)
                # One blocking publisher per key, each matched before the first put: a plain session.put
                # drops under load (congestion control DROP) and a put before the subscription arrives is lost.
                n = 0
                for topic, payload, _log, _pub in iter_recording(SAMPLE):
                    if topic not in pubs:
                        pubs[topic] = session.declare_publisher(topic, congestion_control=zenoh.CongestionControl.BLOCK)
                        assert wait_for_matching(pubs[topic], 20.0), topic
                    pubs[topic].put(payload)
                    n += 1
                deadline = time.monotonic() + 20.0  # until the viewer has logged every message
                while live.get("messages", 0) < n and time.monotonic() < deadline:
                    time.sleep(0.05)
            finally:
                for pub in pubs.values():
                    pub.undeclare()
                stop.set()
                thread.join(30)
        assert (out["messages"], out["undecodable"], out["dropped"]) == (n, 0, 0)
        assert out["frames"] == _gamma_frames()
        assert rrd.stat().st_size > 10_000
        if viewer is not None:
            expected = _rrd_entities(rrd)
            assert {"/world/gamma/sphere1", "/world/tracks/1", "/sections/sphere2/yz/gamma"} <= expected
            _assert_loopback_only(viewer.web_port, viewer.grpc_port)
    finally:
        if viewer is not None:
            viewer.stop()


# --- `fp view --serve`: the Rerun web viewer on 127.0.0.1 only -----------------------------------------------


def _rrd_entities(rrd: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {chunk.entity_path for chunk in RrdReader(rrd).stream()}


def _local_addresses() -> list[tuple[int, tuple]]:
    """(family, sockaddr without port) of this machine's non-loopback addresses, from /proc."""
    import ipaddress
    import socket

    out: list[tuple[int, tuple]] = []
    fib = Path("/proc/net/fib_trie")
    if fib.exists():
        lines = fib.read_text().splitlines()
        v4 = {lines[i - 1].split()[-1] for i, line in enumerate(lines) if "/32 host LOCAL" in line}
        out += [(socket.AF_INET, (a,)) for a in sorted(v4) if not ipaddress.ip_address(a).is_loopback]
    inet6 = Path("/proc/net/if_inet6")
    if inet6.exists():
        for line in inet6.read_text().splitlines():
            hexaddr, ifindex = line.split()[:2]
            addr = ipaddress.IPv6Address(bytes.fromhex(hexaddr))
            if not addr.is_loopback:
                out.append((socket.AF_INET6, (str(addr), 0, int(ifindex, 16) if addr.is_link_local else 0)))
    return out


def _assert_loopback_only(*ports: int) -> None:
    """Every TCP listener on ``ports`` (the whole network namespace, /proc/net/tcp{,6}) is 127.0.0.1, and a
    connection to each port through each non-loopback address of this machine is refused."""
    import socket

    from services.viewing.server import listening_addresses

    for port in ports:
        listeners = listening_addresses(port=port)
        if listeners is None:
            pytest.skip("no /proc/net/tcp: cannot list listening sockets here")
        assert listeners and {ip for ip, _ in listeners} == {"127.0.0.1"}, (port, listeners)
        for family, addr in _local_addresses():
            with socket.socket(family, socket.SOCK_STREAM) as s:
                s.settimeout(2.0)
                with pytest.raises(OSError):  # refused (or unreachable): anything but a connection
                    s.connect((addr[0], port, *addr[1:]))


def _two_ports() -> tuple[int, int]:
    """Two distinct free loopback ports (web viewer, gRPC)."""
    from services.bus import free_port

    a = free_port()
    b = free_port()
    while b == a:
        b = free_port()
    return a, b


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def test_view_serve_binds_loopback_only(tmp_path: Path) -> None:
    """`fp view REC --serve` in a child process: the page, its Wasm and the recording's data come over
    http://127.0.0.1; nothing listens on another address; SIGTERM stops it and its rerun server."""
    import os
    import queue
    import signal
    import threading
    import urllib.request

    from services.viewing.server import listening_addresses

    if not Path("/proc/net/tcp").exists():
        pytest.skip("needs Linux /proc to check the listening sockets")
    web, grpc = _two_ports()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "view",
            str(SAMPLE),
            "--rrd",
            str(tmp_path / "s.rrd"),
            "--serve",
            "--port",
            str(web),
            "--grpc-port",
            str(grpc),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )  # its own process group: the rerun child is in it too
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True).start()
    rerun_pids: list[int] = []
    try:
        url = ""
        while "loopback only" not in url:
            url = lines.get(timeout=30)
        assert f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy" in url
        rerun_pids = _children(proc.pid)
        assert rerun_pids
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=5) as r:
            assert r.status == 200 and b"Rerun" in r.read()
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/re_viewer_bg.wasm", timeout=5) as r:
            assert r.read(4) == b"\x00asm"
        assert "/world/gamma/sphere1" in _rrd_entities(tmp_path / "s.rrd")
        _assert_loopback_only(web, grpc)
        assert {ip for pid in rerun_pids for ip, _ in listening_addresses(pid) or []} == {"127.0.0.1"}
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
        assert listening_addresses(port=web) == [] and listening_addresses(port=grpc) == []
        assert not any(Path(f"/proc/{pid}").exists() for pid in rerun_pids)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # whatever is left of the group we started
        except ProcessLookupError:
            pass
        proc.wait(5)


def test_view_serve_rejects_bad_ports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import socket

    from services.bus import free_port

    assert main(["view", str(SAMPLE), "--rrd", str(tmp_path / "s.rrd"), "--serve", "--port", "0"]) == 2
    assert "--port: expected a TCP port 1…65535, got 0" in capsys.readouterr().err
    assert main(["view", str(SAMPLE), "--serve", "--port", "9999", "--grpc-port", "9999"]) == 2
    assert "expected two different ports" in capsys.readouterr().err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["view", str(SAMPLE), "--serve", "--port", str(free_port()), "--grpc-port", str(port)]) == 2
        assert f"--grpc-port: 127.0.0.1:{port} is not free" in capsys.readouterr().err
    assert not (tmp_path / "s.rrd").exists()  # checked before converting
