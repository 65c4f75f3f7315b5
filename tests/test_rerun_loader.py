"""Rerun as its power users expect (issue 14 item 2): the `rerun-loader-fingerprint` data loader that `rerun
recording.mcap` runs, and what the .rrd holds — sections in millimetres through transforms, the probe, the ground
truth, track covariance ellipsoids and velocity arrows, 2-D maps as images."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.messages import GammaMap
from services.recording import iter_messages
from services.viewing.rerun_loader import INCOMPATIBLE, main

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "recordings" / "sinking-sphere-quick.mcap"
RERUN_CLI = Path(sys.executable).with_name("rerun")


def _chunks(rrd: Path) -> dict[str, list]:
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(rrd).stream():
        out.setdefault(chunk.entity_path, []).append(chunk)
    return out


def _column(chunks: list, needle: str) -> list:
    """Values of the first column whose name contains ``needle`` (e.g. 'Transform3D:scale')."""
    vals: list = []
    for c in chunks:
        batch = c.to_record_batch()
        for name in batch.schema.names:
            if needle in name:
                vals += [v for v in batch.column(name).to_pylist() if v is not None]
    return vals


@pytest.fixture(scope="module")
def loaded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The loader run as Rerun runs it: an executable on the PATH, the file and a recording id, RRD on stdout."""
    exe = shutil.which("rerun-loader-fingerprint", path=str(Path(sys.executable).parent))
    assert exe, "rerun-loader-fingerprint is not installed (pyproject [project.scripts])"
    rrd = tmp_path_factory.mktemp("loader") / "sample.rrd"
    with open(rrd, "wb") as out:
        res = subprocess.run(
            [exe, str(SAMPLE), "--recording-id", "rec-1", "--application-id", "rerun_viewer", "--static"],
            stdout=out,
            stderr=subprocess.PIPE,
            timeout=120,
        )
    assert res.returncode == 0, res.stderr.decode()[-2000:]
    return rrd


def test_loader_writes_a_readable_rrd_with_the_expected_entities(loaded: Path) -> None:
    if RERUN_CLI.exists():
        res = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(loaded)], capture_output=True, text=True, timeout=60)
        assert res.returncode == 0, res.stderr
    from rerun.chunk import RrdReader

    assert RrdReader(loaded).blueprints(), "default blueprint missing"
    entities = set(_chunks(loaded))
    fps = sorted({m.fingerprint for _, m in iter_messages(SAMPLE) if isinstance(m, GammaMap)})
    for fp in fps:
        assert {
            f"/world/gamma/{fp}",
            f"/world/detections/{fp}",
            f"/sections/{fp}/xz/gamma",
            f"/sections/{fp}/xz/confocal",
            f"/sections/{fp}/yz/gamma",
            f"/sections/{fp}/xz/truth",
            f"/sections/{fp}/xz/detection",
        } <= entities
    assert {"/world/probe", "/world/truth", "/world/tracks/1/covariance", "/world/tracks/1/velocity"} <= entities


def test_sections_are_in_millimetres_through_transforms(loaded: Path) -> None:
    chunks = _chunks(loaded)
    g = next(m for _, m in iter_messages(SAMPLE) if isinstance(m, GammaMap))
    dx, dz = float(np.diff(g.grid.x).mean()), float(np.diff(g.grid.z).mean())
    scales = _column(chunks[f"/sections/{g.fingerprint}/xz/gamma"], "scale")
    assert scales and np.allclose(np.asarray(scales[0]).ravel()[:2], [dx * 1e3, dz * 1e3])  # one pixel = one step, mm
    shifts = _column(chunks[f"/sections/{g.fingerprint}/xz/gamma"], "translation")
    assert np.allclose(np.asarray(shifts[0]).ravel()[:2], [(g.grid.x[0] - dx / 2) * 1e3, (g.grid.z[0] - dz / 2) * 1e3])
    det = _column(chunks[f"/sections/{g.fingerprint}/xz/detection"], "positions")
    x_mm, z_mm = np.asarray(det[0]).ravel()[:2]
    assert g.grid.x[0] * 1e3 <= x_mm <= g.grid.x[-1] * 1e3 and g.grid.z[0] * 1e3 <= z_mm <= g.grid.z[-1] * 1e3


def test_tracks_have_covariance_ellipsoids_and_velocity_arrows(loaded: Path) -> None:
    chunks = _chunks(loaded)
    half = np.asarray(_column(chunks["/world/tracks/1/covariance"], "half_sizes")[-1]).ravel()
    assert half.size == 3 and np.all(half > 0) and np.all(half < 5e-3)  # 3σ, metres
    vec = np.asarray(_column(chunks["/world/tracks/1/velocity"], "vectors")[-1]).ravel()
    assert vec.size == 3 and np.all(np.isfinite(vec))
    boxes = _column(chunks["/world/probe"], "centers")
    assert len(np.asarray(boxes[0]).reshape(-1, 3)) > 1  # one box per element


def test_loader_declines_other_files(tmp_path: Path) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("not an mcap")
    assert main([str(text), "--recording-id", "x"]) == INCOMPATIBLE
    assert main([str(tmp_path / "missing.mcap")]) == INCOMPATIBLE
    assert main([str(ROOT / "README.md")]) == INCOMPATIBLE


def test_two_d_maps_are_images_not_empty_volumes(tmp_path: Path) -> None:
    """A 2-D γ-map becomes a textured quad in the x–z plane (metres) and an x–z section in mm."""
    import rerun as rr

    from services.messages import examples
    from services.viewing.rerun_log import RerunLog

    rrd = tmp_path / "2d.rrd"
    rec = rr.RecordingStream("t", recording_id="2d")
    rec.save(rrd)
    conv = RerunLog(rec)
    conv.start()
    ex = examples()
    for name in ("RFFrame", "ConfocalImage", "GammaMap", "Tracks", "Detections"):
        conv.feed(ex[name])
    conv.finish()
    rec.flush()
    rec.disconnect()
    chunks = _chunks(rrd)
    verts = np.asarray(_column(chunks["/world/gamma/sphere_10mm"], "vertex_positions")[0]).reshape(-1, 3)
    g = ex["GammaMap"]
    assert verts.shape == (4, 3) and np.allclose(verts[:, 1], 0)  # the x–z plane
    assert verts[:, 0].min() < g.grid.x[0] < g.grid.x[-1] < verts[:, 0].max()
    assert _column(chunks["/world/gamma/sphere_10mm"], "albedo_texture") or _column(
        chunks["/world/gamma/sphere_10mm"], "ImageBuffer"
    )
    assert "/sections/sphere_10mm/xz/gamma" in chunks and "/sections/sphere_10mm/yz/gamma" not in chunks
    assert not conv.has_3d
