"""Securing the bus with zenoh's own features (issue 13, item 4; docs/wire.md, "Securing the bus").

The processor runs in router mode with the committed ``deploy/zenoh/router.json5`` (TLS only, user/password
authentication, access rules per key expression), its secrets generated into ``tmp_path`` by the documented
``deploy/zenoh/make_secrets.py``; every other session is a client on loopback. An unauthenticated session can
neither call the dictionary nor publish RF the processor accepts; an authenticated but unauthorised one (viewer)
only reads; the operator and the publisher can. A non-loopback listener needs ``--allow-remote``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from services.bus import (
    BusConfig,
    bus_warnings,
    free_port,
    listen_endpoints,
    open_session,
    remote_endpoints,
    wait_for_token,
    zenoh_config,
)
from services.messages import RFFrame
from services.nodes.processor import Processor, ProcessorConfig
from services.nodes.publisher import Publisher
from services.registry import FingerprintSpec, dictionary_request
from services.sources import AcquisitionSource, born_frames
from services.topics import keys
from services.wire import decode, encode

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy" / "zenoh"
SMALL: dict[str, Any] = {"x_range": (-5e-3, 5e-3), "z_range": (10e-3, 22e-3), "spacing": 0.25e-3, "n_freq": 24}
USERS = "processor,publisher,operator,viewer"

needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not on PATH: no certificates")


@pytest.fixture(scope="module")
def secrets(tmp_path_factory) -> Path:
    """The documented command, run for real: CA, router certificate, credentials, one client config per user."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl not on PATH: the certificates cannot be generated")
    out = tmp_path_factory.mktemp("secrets")
    res = subprocess.run(
        [sys.executable, str(DEPLOY / "make_secrets.py"), "--out", str(out), "--users", USERS, "--force"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    assert {"ca.crt", "router.crt", "router.key", "credentials.txt", "viewer.json5"} <= {p.name for p in out.iterdir()}
    # The committed router configuration, pointed at these secrets (it names deploy/zenoh/secrets/ otherwise).
    text = (DEPLOY / "router.json5").read_text()
    assert text.count('"deploy/zenoh/secrets/') == 3  # certificate, key, credentials
    (out / "router.json5").write_text(text.replace('"deploy/zenoh/secrets/', f'"{out}/'))
    return out


@pytest.fixture(scope="module")
def data() -> dict[str, Any]:
    frames, cal = born_frames(3)
    return {"frames": frames, "cal": cal}


def router_bus(secrets: Path, port: int) -> BusConfig:
    return BusConfig(
        mode=None,
        listen=[f"tls/127.0.0.1:{port}"],
        connect=[],
        multicast=None,
        shm=None,
        config_file=str(secrets / "router.json5"),
        connect_timeout_ms=None,
    )


def client_bus(config_file: Path, port: int, proto: str = "tls") -> BusConfig:
    """A client from a generated config file (``--zenoh-config``), on this test's port."""
    return BusConfig(
        mode=None,
        listen=None,
        connect=[f"{proto}/127.0.0.1:{port}"],
        multicast=None,
        shm=None,
        config_file=str(config_file),
        connect_timeout_ms=None,
    )


def anonymous_config(secrets: Path, tmp_path: Path, mode: str = "client") -> Path:
    """A session that trusts the CA (so TLS succeeds) but has no login."""
    doc = json.loads("\n".join((secrets / "viewer.json5").read_text().splitlines()[1:]))
    del doc["transport"]["auth"]
    doc["mode"] = mode
    if mode == "peer":
        doc["listen"] = {"endpoints": ["tcp/127.0.0.1:0"]}
    f = tmp_path / f"anonymous-{mode}.json5"
    f.write_text(json.dumps(doc))
    return f


def rf_payload(acq: Any) -> bytes:
    return encode(RFFrame.from_acquisition(acq))


@needs_openssl
@pytest.mark.timeout(120)
def test_only_authenticated_and_authorised_sessions_reach_the_processor(secrets, data, tmp_path) -> None:
    rig, port = "sec", free_port()
    cfg = ProcessorConfig(rig=rig, queue="fifo", **SMALL)
    k = keys(rig)
    with open_session(router_bus(secrets, port)) as s_router:
        with Processor(s_router, cfg, [FingerprintSpec("marker", calibration=data["cal"])]) as node:
            # 1. No login: a client cannot even open its session …
            with pytest.raises(OSError, match="could not open the zenoh client session"):
                with open_session(client_bus(anonymous_config(secrets, tmp_path), port)):
                    pass
            # … and a peer (which opens without its link) reaches nothing: no dictionary, no RF accepted.
            with open_session(client_bus(anonymous_config(secrets, tmp_path, "peer"), port)) as s:
                assert not wait_for_token(s, k.alive("processor"), 1.0)
                assert dictionary_request(s, rig, "list", timeout=1.5)["error"].startswith("no reply")
                assert dictionary_request(s, rig, "set", payload={"svd_threshold": 0.5}, timeout=1.5)["ok"] is False
                s.put(k.rf, rf_payload(data["frames"][0]))
                time.sleep(1.0)
            assert node.frames_processed == 0 and node.rejected == 0 and node.cfg.svd_threshold == 0.4
            # 2. A wrong password is refused like no login.
            wrong = json.loads("\n".join((secrets / "viewer.json5").read_text().splitlines()[1:]))
            wrong["transport"]["auth"]["usrpwd"]["password"] = "not-the-password"
            (tmp_path / "wrong.json5").write_text(json.dumps(wrong))
            with pytest.raises(OSError, match="could not open"):
                with open_session(client_bus(tmp_path / "wrong.json5", port)):
                    pass
            # 3. The viewer logs in: it lists the dictionary and follows the outputs, but cannot change the
            #    dictionary or publish RF (the router's access rules drop both).
            with open_session(client_bus(secrets / "viewer.json5", port)) as s_view:
                assert wait_for_token(s_view, k.alive("processor"), 10)
                listing = dictionary_request(s_view, rig, "list", timeout=10)
                assert listing["ok"] and [e["name"] for e in listing["entries"]] == ["marker"]
                refused = dictionary_request(s_view, rig, "set", payload={"svd_threshold": 0.5}, timeout=1.5)
                assert refused["ok"] is False and refused["error"].startswith("no reply")
                assert dictionary_request(s_view, rig, "remove", "marker", timeout=1.5)["ok"] is False
                s_view.put(k.rf, rf_payload(data["frames"][0]))
                time.sleep(1.0)
                assert node.frames_processed == 0 and node.dictionary == ["marker"] and node.cfg.svd_threshold == 0.4
                seen: list[bytes] = []
                lock = threading.Lock()

                def on_detections(sample: Any) -> None:
                    with lock:
                        seen.append(sample.payload.to_bytes())

                sub = s_view.declare_subscriber(k.detections, on_detections)
                # The viewer may announce itself as a viewer, never as the rig's processor or a worker.
                forged = [s_view.liveliness().declare_token(f"{k.alive(r)}/forged") for r in ("processor", "worker")]
                own = s_view.liveliness().declare_token(f"{k.alive('viewer')}/v1")
                # 4. The operator changes the dictionary; the publisher's frames are processed and reach the viewer.
                with open_session(client_bus(secrets / "operator.json5", port)) as s_op:
                    assert wait_for_token(s_op, f"{k.alive('viewer')}/v1", 10)
                    assert not wait_for_token(s_op, f"{k.alive('processor')}/forged", 1.0)
                    assert not wait_for_token(s_op, f"{k.alive('worker')}/**", 0.5)
                    for t in [*forged, own]:
                        t.undeclare()
                    res = dictionary_request(s_op, rig, "set", payload={"svd_threshold": 0.5}, timeout=20)
                    assert res["ok"] and res["params"]["svd_threshold"] == 0.5 and node.cfg.svd_threshold == 0.5
                with open_session(client_bus(secrets / "publisher.json5", port)) as s_pub:
                    src = AcquisitionSource(data["frames"][:2])
                    summary = Publisher(s_pub, rig, src, pace="ack", wait_timeout=20).run()
                assert summary["published"] == 2 and summary["acked"] == 2 and summary["synced"] == 1  # its barrier
                assert node.frames_processed == 2 and node.rejected == 0 and node.failed == 0
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline and len(seen) < 2:
                    time.sleep(0.05)
                sub.undeclare()
                with lock:
                    assert sorted(decode(p).frame_index for p in seen) == [0, 1]


@needs_openssl
@pytest.mark.timeout(60)
def test_tls_link_needs_the_ca_and_refuses_plain_tcp(secrets, tmp_path) -> None:
    """The router listens on tls/ only: the generated client (CA + login) gets through; the same client over
    tcp/, or without the CA (the server certificate is not trusted), does not."""
    rig, port = "tls", free_port()
    with open_session(router_bus(secrets, port)) as s_router:
        q = s_router.declare_queryable(keys(rig).dictionary, lambda query: query.reply(query.key_expr, b'{"ok": true}'))
        try:
            with open_session(client_bus(secrets / "viewer.json5", port)) as s:
                assert dictionary_request(s, rig, "list", timeout=10) == {"ok": True}
            with pytest.raises(OSError, match="could not open"):
                with open_session(client_bus(secrets / "viewer.json5", port, proto="tcp")):
                    pass
            doc = json.loads("\n".join((secrets / "viewer.json5").read_text().splitlines()[1:]))
            del doc["transport"]["link"]["tls"]["root_ca_certificate"]
            (tmp_path / "no-ca.json5").write_text(json.dumps(doc))
            with pytest.raises(OSError, match="could not open"):
                with open_session(client_bus(tmp_path / "no-ca.json5", port)):
                    pass
        finally:
            q.undeclare()


def test_non_loopback_listeners_need_allow_remote(tmp_path) -> None:
    loop = [
        "tcp/127.0.0.1:7447",
        "tcp/[::1]:1",
        "tls/localhost:7447",
        "unixsock-stream//tmp/fp.sock",
        "tcp/127.0.0.2:1",
    ]
    remote = ["tcp/0.0.0.0:7447", "tls/[::]:7447", "tcp/10.0.0.5:1", "tcp/bus.lab:7447", "quic/192.168.1.2:7447"]
    assert remote_endpoints(loop + remote) == remote
    with pytest.raises(ValueError, match=r"--listen: tcp/0\.0\.0\.0:7447 is not a loopback .* --allow-remote"):
        zenoh_config(BusConfig(listen=["tcp/0.0.0.0:7447"], connect=[]))
    cfg = zenoh_config(BusConfig(listen=["tcp/0.0.0.0:7447"], connect=[], allow_remote=True))
    notes = bus_warnings(cfg)
    assert "other hosts can reach this node" in notes[0] and any("authentication" in n for n in notes)
    assert any("not encrypted" in n for n in notes) and any("access control" in n for n in notes)
    assert bus_warnings(zenoh_config(BusConfig(listen=["tcp/127.0.0.1:7447"], connect=[]))) == []
    # A config file in router mode without listen endpoints would get zenoh's default, tcp/[::]:7447.
    f = tmp_path / "router.json5"
    f.write_text('{ mode: "router" }')
    bare = BusConfig(mode=None, listen=None, connect=[], multicast=None, config_file=str(f), shm=None)
    assert listen_endpoints(zenoh_config(BusConfig(listen=["tcp/127.0.0.1:1"], config_file=str(f), mode=None))) == [
        "tcp/127.0.0.1:1"
    ]
    with pytest.raises(ValueError, match=r"tcp/\[::\]:7447 is not a loopback"):
        zenoh_config(bare)


def test_cli_refuses_a_remote_listener_in_one_line(tmp_path) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "services.cli", "process", "--model", "point", "--listen", "tcp/192.0.2.1:7447"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "Traceback" not in res.stderr
    assert "--allow-remote" in lines[0] and "tcp/192.0.2.1:7447" in lines[0]
    missing = tmp_path / "none.json5"
    res = subprocess.run(
        [sys.executable, "-m", "services.cli", "record", "--zenoh-config", str(missing)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2 and res.stderr.strip() == f"fp record: error: --zenoh-config: no such file '{missing}'"


@needs_openssl
def test_make_secrets_never_overwrites_without_force(secrets) -> None:
    res = subprocess.run(
        [sys.executable, str(DEPLOY / "make_secrets.py"), "--out", str(secrets)], capture_output=True, text=True
    )
    assert res.returncode == 2 and "already holds" in res.stderr and "--force" in res.stderr
    assert (secrets / "credentials.txt").stat().st_mode & 0o077 == 0  # passwords readable by their owner only
    for p in [secrets, *(secrets / f"{u}.json5" for u in USERS.split(",")), *secrets.glob("*.key")]:
        assert p.stat().st_mode & 0o077 == 0, p.name  # keys and client configs (passwords) too, and the folder
    users = [line.split(":", 1)[0] for line in (secrets / "credentials.txt").read_text().splitlines()]
    assert users == USERS.split(",")
