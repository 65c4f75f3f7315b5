"""`fp convert` between UFF, PICMUS and MCAP: RF survives every hop, IQ output, one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore import PlaneWaveSequence, Probe
from fpcore.born import born_points
from fpcore.io import read_picmus, read_uff, write_uff
from services.cli import main
from services.cli.convert import read_frames


@pytest.fixture()
def uff(tmp_path):
    probe = Probe.linear(32, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.from_angles(np.linspace(-10, 10, 5))
    frames = [
        born_points(probe, seq, np.array([[0.5e-3 * k, 0, 15e-3]]), np.array([1.0]), n_t=600, frame_index=k)
        for k in range(2)
    ]
    for k, f in enumerate(frames):
        f.timestamp = 0.01 * k
        f.truth = {"targets": [{"name": "point", "position_m": [0.5e-3 * k, 0.0, 15e-3]}]}
    path = tmp_path / "a.uff"
    write_uff(path, frames)
    return path, frames


def test_uff_picmus_mcap_uff_keeps_the_rf(uff, tmp_path, capsys) -> None:
    path, frames = uff
    hops = [path, tmp_path / "b.hdf5", tmp_path / "c.mcap", tmp_path / "d.uff"]
    for a, b in zip(hops, hops[1:], strict=False):
        assert main(["convert", str(a), str(b)]) == 0
    assert "d.uff: 2 frame(s), 32 elements, 5 plane waves, 600 samples at 20 MHz (uff)" in capsys.readouterr().out
    back = read_uff(hops[-1])
    assert len(back) == 2
    for f, b in zip(frames, back, strict=True):
        np.testing.assert_array_equal(b.rf, f.rf.astype(np.float32))
        assert (b.fs, b.t0, b.c0, b.frame_index, b.timestamp) == (f.fs, f.t0, f.c0, f.frame_index, f.timestamp)
        assert b.truth == f.truth
        np.testing.assert_allclose(b.sequence.sines, f.sequence.sines, atol=1e-12)
    assert len(read_frames(hops[2])) == 2  # the recording holds fp/convert/rf RFFrame messages


def test_iq_output_and_back(uff, tmp_path) -> None:
    path, frames = uff
    iq = tmp_path / "iq.hdf5"
    assert main(["convert", str(path), str(iq), "--modulation-frequency", "2.5MHz", "--decimation", "4"]) == 0
    assert main(["convert", str(iq), str(tmp_path / "rf.uff")]) == 0
    back = read_uff(tmp_path / "rf.uff")[1]
    assert back.fs == 15e6 and read_picmus(iq)[1].fs == 15e6
    a, b = frames[1].spectrum(1.8e6, 3.2e6).data, back.spectrum(1.8e6, 3.2e6).data
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < 1e-2


@pytest.mark.parametrize(
    "argv, message",
    [
        (["{d}/a.uff", "{d}/x.txt"], "OUTPUT: expected a name ending in .uff"),
        (["{d}/none.uff", "{d}/y.uff"], "none.uff: expected an existing UFF, PICMUS or MATLAB v7.3 file"),
        (["{d}/m.mat", "{d}/y.uff"], "m.mat: a MATLAB .mat file that is not HDF5"),
        (["{d}/a.uff", "{d}/y.uff", "--modulation-frequency", "5MHz"], "IQ is written to PICMUS files"),
        (["{d}/a.uff", "{d}/a.uff"], "other than the input"),
    ],
)
def test_bad_input_one_line(uff, tmp_path, capsys, argv, message) -> None:
    (tmp_path / "m.mat").write_bytes(b"MATLAB 5.0 MAT-file, Platform: GLNXA64".ljust(200, b" "))
    assert main(["convert", *[a.format(d=tmp_path) for a in argv]]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
