"""Recordings other tools read natively (issue 14 item 1): the shipped sample opened with the `mcap` reader, every
display channel decoded with Foxglove's own protobuf decoders, every JSON channel validated against its JSON
Schema; the live Foxglove server binds loopback only and forwards the bus."""

from __future__ import annotations

import importlib
import json
import threading
import time
from collections import Counter
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from services.messages import GammaMap, RFFrame
from services.recording import iter_messages
from services.viewing.display import truth_targets

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "recordings" / "sinking-sphere-quick.mcap"


def _decoder(schema_name: str):
    """The well-known schema's protobuf class (foxglove-schemas-protobuf), e.g. foxglove.Grid → Grid_pb2.Grid."""
    name = schema_name.removeprefix("foxglove.")
    return getattr(importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name)


def _messages() -> list[tuple[str, str, str, bytes]]:
    with open(SAMPLE, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return [(c.topic, c.message_encoding, s.name, bytes(m.data)) for s, c, m in reader.iter_messages()]


def test_every_display_channel_decodes_with_the_well_known_schemas() -> None:
    msgs = _messages()
    gamma = {(m.fingerprint, m.frame_index): m for _, m in iter_messages(SAMPLE) if isinstance(m, GammaMap)}
    rf = [m for _, m in iter_messages(SAMPLE) if isinstance(m, RFFrame)]
    n_frames = len({fi for _, fi in gamma})
    seen: Counter[str] = Counter()
    for topic, encoding, schema, data in msgs:
        if "/display/" not in topic:
            continue
        assert encoding == "protobuf" and schema.startswith("foxglove."), topic
        msg = _decoder(schema).FromString(data)
        seen[schema] += 1
        parts = topic.split("/")  # fp/<rig>/display/<kind>[/<fingerprint>/<plane>]
        if schema == "foxglove.Grid":
            kind, fp, plane = parts[3], parts[4], parts[5]
            g = next(m for (name, _), m in gamma.items() if name == fp)
            h = g.grid.x if plane == "xz" else g.grid.y
            assert msg.frame_id == "world" and msg.column_count == h.size
            assert msg.cell_size.x == pytest.approx(float(np.diff(h).mean()))  # metres, not pixels
            assert msg.cell_size.y == pytest.approx(float(np.diff(g.grid.z).mean()))
            assert len(msg.data) == msg.row_stride * g.grid.z.size and msg.cell_stride == 4
            assert [f.name for f in msg.fields] == ["gamma" if kind == "gamma" else "confocal_db"]
            values = np.frombuffer(msg.data, "<f4")
            assert np.all(np.isfinite(values))
            if kind == "gamma":
                assert 0 < values.max() <= 1
            assert msg.pose.position.z == pytest.approx(g.grid.z[0] - np.diff(g.grid.z).mean() / 2)
        elif parts[3] == "probe":
            (ent,) = msg.entities
            assert len(ent.cubes) == rf[0].probe.n_elements
            assert ent.cubes[0].size.x == pytest.approx(0.9 * rf[0].probe.pitch)
        elif parts[3] == "truth":
            (ent,) = msg.entities
            want = {n: (p, d) for n, p, d in truth_targets(rf[0])}
            assert len(ent.spheres) == len(want) > 0
            assert {round(s.size.x, 6) for s in ent.spheres} == {round(d, 6) for _, d in want.values()}
        elif parts[3] == "detections":
            (ent,) = msg.entities
            assert ent.spheres and all("C_γ" in t.text for t in ent.texts)
        elif parts[3] == "tracks":
            for ent in msg.entities:
                assert ent.id.startswith("track/") and len(ent.spheres) == 1 and ent.lines
                assert all(s.size.x > 0 and s.size.z > 0 for s in ent.spheres)  # the 3σ covariance ellipsoid
    assert seen["foxglove.Grid"] == 2 * 2 * 2 * n_frames  # γ and confocal × 2 planes × 2 fingerprints per frame
    assert seen["foxglove.SceneUpdate"] >= 3 * n_frames + 1  # detections, tracks, truth per frame + the probe


def test_small_messages_are_json_with_their_schema() -> None:
    with open(SAMPLE, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        kinds = Counter()
        for schema, channel, msg in reader.iter_messages():
            if channel.message_encoding != "json":
                continue
            assert schema.encoding == "jsonschema"
            obj = json.loads(msg.data)
            jsonschema.validate(obj, json.loads(schema.data))
            assert obj["schema_name"] == schema.name
            kinds[schema.name] += 1
    assert {"Detections", "Tracks", "Status"} <= set(kinds)
    encodings = {
        c.topic.rsplit("/", 1)[-1]: c.message_encoding for c in summary.channels.values() if "/display/" not in c.topic
    }
    assert encodings["rf"] == encodings["gamma"] == encodings["image"] == "fpwire"  # compact binary (docs/wire.md)
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}


@pytest.mark.timeout(60)
def test_live_foxglove_server_is_loopback_and_forwards_the_bus() -> None:
    """`fp view --live --foxglove`: the sample's bus messages put on loopback zenoh reach the server's channels;
    its WebSocket listens on 127.0.0.1 only."""
    import zenoh

    from services.bus import EPHEMERAL, BusConfig, free_port, open_session, wait_for_matching, wait_for_token
    from services.recording import iter_recording
    from services.topics import keys
    from services.viewing.foxglove_live import serve_foxglove
    from services.viewing.server import listening_addresses

    hub = f"tcp/127.0.0.1:{free_port()}"
    stop = threading.Event()
    urls: list[str] = []
    stats: dict = {}
    out: dict = {}
    port = free_port()
    with open_session(BusConfig(listen=[hub], connect=[], shm="off")) as session:
        thread = threading.Thread(
            target=lambda: out.update(
                serve_foxglove(
                    BusConfig(listen=[EPHEMERAL], connect=[hub], shm="off"),
                    "demo",
                    port=port,
                    duration=45,
                    stop=stop,
                    stats=stats,
                    on_ready=urls.append,
                )
            )
        )
        thread.start()
        pubs: dict[str, zenoh.Publisher] = {}
        try:
            assert wait_for_token(session, keys("demo").alive("viewer"), 20.0)
            assert urls == [f"ws://127.0.0.1:{port}"]
            listeners = listening_addresses(port=port)
            if listeners is not None:
                assert listeners and {ip for ip, _ in listeners} == {"127.0.0.1"}
            n = 0
            for topic, payload, _log, _pub in iter_recording(SAMPLE):
                if topic not in pubs:
                    pubs[topic] = session.declare_publisher(topic, congestion_control=zenoh.CongestionControl.BLOCK)
                    assert wait_for_matching(pubs[topic], 20.0), topic
                pubs[topic].put(payload)
                n += 1
            deadline = time.monotonic() + 20
            while stats.get("messages", 0) < n and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            for p in pubs.values():
                p.undeclare()
            stop.set()
            thread.join(30)
    assert out["messages"] == n and out["undecodable"] == 0
    topics = set(out["topics"])
    assert {"fp/demo/detections", "fp/demo/tracks", "fp/demo/display/probe", "fp/demo/display/truth"} <= topics
    assert any(t.startswith("fp/demo/display/gamma/") for t in topics)
