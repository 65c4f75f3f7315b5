"""Live velocity dictionaries (issue 15 item 3; docs/design.md §4.13): the grid and its options, the no-PRF
path, and `fast-cylinder` through the bus (publisher → processor over loopback zenoh) with and without a
velocity grid. Physics invariants only, no timing."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from fpcore.truth import Truth
from fpcore.velocity import VelocityGrid
from services.cli.fingerprint_args import parse_velocity_grid
from services.nodes.local import run_pipeline
from services.nodes.processor import ProcessorConfig
from services.pipeline import Pipeline, PipelineConfig
from services.sources import SimulatorSource

N_FRAMES = 4
GRID = "0.5,0.2:0.1"  # |v_x| ≤ 0.5, |v_z| ≤ 0.2 m/s: symmetric, the truth (0.25, 0.1) is not a grid centre


def test_velocity_grid_is_symmetric_and_its_options_are_checked() -> None:
    vg = parse_velocity_grid(GRID, "2mm")
    assert vg.max_speed == (0.5, 0.0, 0.2) and vg.step == pytest.approx(0.1) and vg.roi_half_width == 2e-3
    v = vg.velocities(2)
    assert v.shape == (11 * 5, 3) and np.allclose(v.sum(axis=0), 0) and np.all(v[:, 1] == 0)
    np.testing.assert_allclose(vg.sigma(2), [0.1 / np.sqrt(12), 0.0, 0.1 / np.sqrt(12)])
    assert parse_velocity_grid("0.3").max_speed == (0.3, 0.3, 0.3)
    for bad, what in (("fast", "--velocity-grid: expected VMAX"), ("0.5:-1", "step > 0"), ("1,2,3,4", "VMAX")):
        with pytest.raises(ValueError, match=what):
            parse_velocity_grid(bad)
    with pytest.raises(ValueError, match="exceed 4096"):
        VelocityGrid((10.0, 10.0, 10.0), 0.1)


def _specs(src: SimulatorSource, grid: str | None) -> list:
    vg = parse_velocity_grid(grid) if grid else None
    # water only: the whole record (the front face's echo) is kept, else the reverberation alias 5.5 mm above
    # the target is γ's largest peak (bench/validate_motion_live.py)
    return [dataclasses.replace(s, gate=False, velocity_grid=vg) for s in src.fingerprint_specs()]


def test_frames_without_prf_skip_the_velocity_estimate_and_say_so_once() -> None:
    src = SimulatorSource("fast-cylinder", n_frames=2, quick=True)
    pipe = Pipeline(PipelineConfig(publish_image=False), _specs(src, GRID))
    notices = []
    for acq in (src.scenario.frame(i) for i in range(2)):
        acq = dataclasses.replace(acq, sequence=dataclasses.replace(acq.sequence, prf=None))
        res = pipe.process(acq)
        notices += res.notices
        assert res.detections and all(v is None for v in res.velocities)
    assert len(notices) == 1 and notices[0].startswith("prf: ") and "cylinder" in notices[0]


def _bus_run(tmp_path: Any, grid: str | None) -> list[dict[str, Any]]:
    src = SimulatorSource("fast-cylinder", n_frames=N_FRAMES, quick=True)
    rows: list[dict[str, Any]] = []
    cfg = ProcessorConfig(rig="motion", queue="fifo", publish_image=False)
    summary = run_pipeline(
        src, "motion", tmp_path, N_FRAMES, rows.append, fingerprints=_specs(src, grid), processor=cfg, record=False
    )
    assert summary["frames_processed"] == N_FRAMES and summary["failed"] == 0
    return sorted(rows, key=lambda r: r["frame_index"])


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[dict[str, Any]]]:
    return {g: _bus_run(tmp_path_factory.mktemp(g), None if g == "off" else GRID) for g in ("off", "on")}


def _truth(row: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    tg = Truth.from_dict(row["truth"]).target("cylinder")
    return tg.position, tg.velocity


def test_velocity_estimate_at_the_first_detection_is_within_half_a_step(runs) -> None:
    """Frame 0 (the static peak within the ±3 mm region of the target): the motion-aware peak is on the target
    (within a grid step of 0.19 mm) and each velocity component within half a velocity step of the truth;
    γ of F_v there is several times the static peak's (the smear undone, paper Discussion)."""
    row = runs["on"][0]
    r, v = _truth(row)
    d = row["detections"][0]
    assert d["velocity_m_s"] is not None and d["velocity_sigma_m_s"][0] == pytest.approx(0.1 / np.sqrt(12))
    assert np.linalg.norm(np.asarray(d["velocity_position_m"]) - r) < 0.2e-3
    assert np.all(np.abs(np.asarray(d["velocity_m_s"]) - v) <= 0.05 + 1e-9)
    assert d["velocity_gamma"] > 5 * d["gamma_max"]
    assert all(det.get("velocity_m_s") is None for row in runs["off"] for det in row["detections"])


def test_tracker_with_velocity_measurements_follows_the_fast_target(runs) -> None:
    """Without the dictionary the constant-velocity track (prior speed σ 5 mm/s) cannot follow a 0.27 m/s
    target that moves 3 mm per frame; with it the track's position stays within 0.5 mm and its velocity within
    0.05 m/s of the truth on every frame after the first, and both errors are below the static run's."""
    errors: dict[str, list[tuple[float, float]]] = {}
    for label, rows in runs.items():
        errors[label] = []
        for row in rows[1:]:
            r, v = _truth(row)
            live = [t for t in row["tracks"] if t["status"] != "lost"]
            assert live, f"{label}: no track at frame {row['frame_index']}"
            t = min(live, key=lambda t: np.linalg.norm(np.asarray(t["position_m"]) - r))
            errors[label].append(
                (float(np.linalg.norm(np.asarray(t["position_m"]) - r)), float(np.linalg.norm(t["velocity_m_s"] - v)))
            )
    on, off = np.array(errors["on"]), np.array(errors["off"])
    assert np.all(on[:, 0] < 0.5e-3) and np.all(on[:, 1] < 0.05)
    assert on[-1, 0] < off[-1, 0] and on[-1, 1] < off[-1, 1]


def test_thinned_samples_give_the_same_estimate_as_all_samples() -> None:
    """The search thins frequencies and output directions only where the sampled sum's aliases stay outside
    the region (fpcore.velocity.VelocitySearch.strides): on fast-cylinder it keeps 1/4 of the samples or fewer
    and finds the same peak (within 0.05 mm), the same γ (within 2 %) and a velocity within half a step."""
    from fpcore.velocity import VelocitySearch

    src = SimulatorSource("fast-cylinder", n_frames=1, quick=True)
    pipe = Pipeline(PipelineConfig(publish_image=False), _specs(src, None))
    acq = src.scenario.frame(0)
    res = pipe.process(acq)
    tg = acq.ground_truth.target("cylinder")
    vg = parse_velocity_grid("0.3,0.1:0.1", "2mm")
    origin = tg.position + np.array([0.8e-3, 0.0, -0.5e-3])  # the region is not centred on the truth
    est = {}
    for thin in (False, True):
        search = VelocitySearch(res.fingerprints["cylinder"], vg, acq.sequence.transmit_times(), thin=thin)
        est[thin] = search.estimate(res.pw, origin, res.grid.spacing)
    assert np.prod(search.strides(res.pw, 2)) >= 4
    # v_x = 0.25 m/s lies halfway between two grid velocities (γ nearly tied): either is within half a step
    v = tg.velocity
    for e in est.values():
        assert np.all(np.abs(e.velocity_m_s - v) <= 0.05 + 1e-9)
    assert np.linalg.norm(est[True].position_m - est[False].position_m) < 0.05e-3
    assert est[True].gamma == pytest.approx(est[False].gamma, rel=0.02)
    assert np.linalg.norm(est[True].position_m - tg.position) < 0.2e-3


def test_dictionary_add_request_takes_a_velocity_grid() -> None:
    """The dictionary queryable's add (services.registry.spec_from_request): "velocity_grid" turns the entry's
    velocity dictionary on; a bad one is refused with one line naming the option."""
    import json

    from services.registry import Entry, spec_from_request

    body = {"model": "point", "r0_m": [0, 0, 0.02], "velocity_grid": "0.4:0.2", "velocity_roi": "2mm"}
    spec = spec_from_request("p", json.dumps(body).encode(), b"")
    assert spec.velocity_grid == VelocityGrid((0.4, 0.4, 0.4), 0.2, 2e-3)
    assert Entry(spec).describe()["velocity_grid"]["step_m_s"] == pytest.approx(0.2)
    assert spec_from_request("p", b'{"model": "point"}', b"").velocity_grid is None
    with pytest.raises(ValueError, match="velocity_grid must be a string"):
        spec_from_request("p", b'{"model": "point", "velocity_grid": 0.5}', b"")
    with pytest.raises(ValueError, match="add: velocity_grid: expected VMAX"):
        spec_from_request("p", b'{"model": "point", "velocity_grid": "fast"}', b"")


def test_processor_reports_frames_without_prf_once_and_goes_on() -> None:
    """fp process with a velocity grid, frames without PRF (RFFrame 1.0 writers): one ErrorReport naming
    'prf', every frame still acknowledged with its detections (no velocity estimate)."""
    import threading
    import time

    from services.bus import BusConfig, free_port, open_session
    from services.messages import Detections, ErrorReport, RFFrame
    from services.nodes.processor import Processor
    from services.topics import keys
    from services.wire import decode, encode_with_header

    src = SimulatorSource("fast-cylinder", n_frames=2, quick=True)
    k = keys("noprf")
    got: dict[str, list[Any]] = {"errors": [], "detections": []}
    lock = threading.Lock()

    def on(sample: Any) -> None:
        msg = decode(sample.payload.to_bytes())
        with lock:
            got["errors" if isinstance(msg, ErrorReport) else "detections"].append(msg)

    cfg = ProcessorConfig(rig="noprf", queue="fifo", publish_image=False)
    bus = BusConfig(listen=[f"tcp/127.0.0.1:{free_port()}"], connect=[], shm="off")
    with open_session(bus) as s, Processor(s, cfg, _specs(src, GRID)):
        subs = [s.declare_subscriber(k.errors, on), s.declare_subscriber(k.detections, on)]
        for acq in (src.scenario.frame(i) for i in range(2)):
            frame = RFFrame.from_acquisition(acq).model_copy(update={"prf": None})
            payload, header = encode_with_header(frame)
            s.put(k.rf, payload, attachment=header)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (len(got["detections"]) < 2 or not got["errors"]):
            time.sleep(0.05)
        for sub in subs:
            sub.undeclare()
    dets = [m for m in got["detections"] if isinstance(m, Detections)]
    assert len(dets) == 2 and all(d.detections for d in dets)
    assert all(det.velocity_m_s is None for d in dets for det in d.detections)
    assert len(got["errors"]) == 1 and got["errors"][0].field == "prf" and "velocity" in got["errors"][0].problem


def test_sharded_merger_tracks_with_the_workers_velocity_estimates() -> None:
    """fp merge (router) + one fp worker in this process: the worker's Detections carry the velocity estimates
    and the merger's tracker takes them as measurements (services.convert.motion_of), so after two frames
    the track's velocity is within half a step of the truth (a track without them still has ≈ 0)."""
    from services.bus import BusConfig, free_port, open_session
    from services.messages import Tracks
    from services.nodes.merger import Merger, MergerConfig
    from services.nodes.publisher import Publisher
    from services.nodes.worker import Worker, WorkerConfig
    from services.sources import AcquisitionSource
    from services.topics import keys
    from services.wire import decode

    src = SimulatorSource("fast-cylinder", n_frames=2, quick=True)
    frames = [src.scenario.frame(i) for i in range(2)]
    port, rig = free_port(), "vshard"
    hub = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm="off")
    client = BusConfig(mode="client", listen=None, connect=[f"tcp/127.0.0.1:{port}"], shm="off")
    k = keys(rig)
    tracks: list[Tracks] = []
    with open_session(hub) as hs, open_session(client) as ws, open_session(client) as ps:
        with Worker(ws, WorkerConfig(rig=rig, name="w1", publish_image=False), _specs(src, GRID)):
            with Merger(hs, MergerConfig(rig=rig, queue="fifo", min_workers=1, wait_workers_s=60)):
                sub = ps.declare_subscriber(k.tracks, lambda s: tracks.append(decode(s.payload.to_bytes())))
                Publisher(ps, rig, AcquisitionSource(frames), pace="ack", window=1, wait_timeout=60).run()
                sub.undeclare()
    last = max(tracks, key=lambda t: t.frame_index)
    v = frames[-1].ground_truth.target("cylinder").velocity
    assert last.frame_index == 1 and last.tracks
    assert np.all(np.abs(np.asarray(last.tracks[0].velocity_m_s) - v) <= 0.05 + 1e-9)
