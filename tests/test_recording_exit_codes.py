"""Honest exit codes for recordings (issue 13 item 5) and replay of the shipped sample (issue 14 item 3):
`fp recover` and `fp view` refuse what is not an MCAP or holds nothing readable; CRCs are checked and corrupted
chunks counted; `fp publish --mcap` refuses a recording without RF."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from services.cli import main
from services.messages import RFFrame
from services.recording import copy_messages, iter_messages, iter_raw, recover
from services.sources import MCAPSource

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "recordings" / "sinking-sphere-quick.mcap"


def _bad(kind: str, tmp: Path) -> Path:
    path = tmp / f"{kind}.mcap"
    if kind == "text":
        path.write_text("frame,x,z\n1,0.1,0.2\n")
    elif kind == "hdf5":
        path = tmp / "frames.uff"
        with h5py.File(path, "w") as f:
            f.create_dataset("channel_data/data", data=np.zeros((2, 3)))
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":  # 90 % cut: less than the first chunk is left
        data = SAMPLE.read_bytes()
        path.write_bytes(data[: len(data) // 10])
    return path


@pytest.mark.parametrize("kind", ["text", "hdf5", "empty", "truncated"])
def test_recover_and_view_refuse_unreadable_files(kind: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = _bad(kind, tmp_path)
    out, rrd = tmp_path / "out.mcap", tmp_path / "out.rrd"
    assert main(["recover", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "Traceback" not in err[0]
    assert ("not an MCAP file" in err[0]) if kind != "truncated" else ("no readable message" in err[0])
    assert not out.exists() and not list(tmp_path.glob("*.part"))
    assert main(["view", str(bad), "--rrd", str(rrd)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0]
    assert not rrd.exists()


def _corrupt_second_chunk(tmp: Path) -> Path:
    data = bytearray(SAMPLE.read_bytes())
    with open(SAMPLE, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 2
    c = chunks[1]
    data[c.chunk_start_offset + c.chunk_length // 2] ^= 0xFF  # one flipped byte inside the chunk's records
    path = tmp / "corrupt.mcap"
    path.write_bytes(bytes(data))
    return path


def test_crc_mismatch_is_counted_and_not_complete(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    whole = recover(SAMPLE, tmp_path / "whole.mcap")
    assert whole["complete"] and whole["corrupted_chunks"] == 0 and whole["chunks"] >= 2
    bad = _corrupt_second_chunk(tmp_path)
    assert main(["recover", str(bad), "-o", str(tmp_path / "fixed.mcap")]) == 0  # salvage: what is readable
    cap = capsys.readouterr()
    report = json.loads(cap.out)
    assert report["complete"] is False and report["corrupted_chunks"] == 1 and report["chunks"] == whole["chunks"]
    assert 0 < report["messages"] < whole["messages"]
    assert "1 corrupted chunk(s)" in cap.err
    kept = list(iter_raw(tmp_path / "fixed.mcap"))
    assert len(kept) == report["messages"]
    rep: dict = {}
    assert len(list(iter_raw(bad, rep))) == report["messages"] and rep["corrupted_chunks"] == 1
    assert main(["view", str(bad), "--rrd", str(tmp_path / "c.rrd")]) == 0  # what is left is shown, with a warning
    assert "damaged" in capsys.readouterr().err


def test_publish_refuses_a_recording_without_rf(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    no_rf = tmp_path / "no_rf.mcap"
    with open(no_rf, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        copy_messages(w, (m for m in iter_raw(SAMPLE) if not m[1].topic.endswith("/rf")))
        w.finish()
    assert main(["publish", "--mcap", str(no_rf), "--wait-for", "none"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--mcap" in err[0] and "no RF frames" in err[0] and str(no_rf) in err[0]


def test_shipped_sample_replays_int16_rf() -> None:
    """The sample keeps its RF (int16 with its scale, as a scanner delivers it), so `fp publish --mcap` replays
    every frame; the frames decode to the acquisitions the recorded detections were computed from."""
    assert SAMPLE.stat().st_size < 6_500_000  # 6.2 MB: the halo geometry and the beams' reciprocity (5.6 MB before)
    src = MCAPSource(SAMPLE)
    items = list(src)
    frames = [m for _, m in iter_messages(SAMPLE) if isinstance(m, RFFrame)]
    assert src.frames == len(items) == len(frames) >= 3
    for m in frames:
        assert m.rf.dtype == np.int16 and m.rf_scale is not None and m.rf_scale > 0
        acq = m.to_acquisition()
        assert acq.rf.dtype == np.float32 and np.max(np.abs(acq.rf)) == pytest.approx(
            np.max(np.abs(m.rf.astype(np.float64))) * m.rf_scale, rel=1e-6
        )
