"""UFF (USTB HDF5 format) channel data: round trips, pyuff-ustb interoperability, bad input."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from fpcore.acquisition import Acquisition, PlaneWaveSequence, Probe
from fpcore.io import (
    UFF_VERSION,
    UFFError,
    angles_to_sines,
    list_uff_datasets,
    read_uff,
    read_uff_json,
    sines_to_angles,
    write_uff,
    write_uff_json,
)

FS, T0, C0 = 20e6, 2.5e-6, 1480.0


def _frames(probe: Probe, seq: PlaneWaveSequence, n_frames: int = 3, n_t: int = 40, seed: int = 0) -> list[Acquisition]:
    rng = np.random.default_rng(seed)
    return [
        Acquisition(
            rng.standard_normal((probe.n_elements, seq.n_waves, n_t)).astype(np.float32),
            FS,
            T0,
            C0,
            probe,
            seq,
            frame_index=10 + i,
            timestamp=0.05 * i,
            truth={"position": [0.0, 0.001 * i, 0.02], "diameter": 0.01},
        )
        for i in range(n_frames)
    ]


def _linear() -> tuple[Probe, PlaneWaveSequence]:
    return Probe.linear(16, 3e-4, 2.5e6, 1.5e6), PlaneWaveSequence.from_angles([-12.0, -4.0, 0.0, 7.0])


def _matrix() -> tuple[Probe, PlaneWaveSequence]:
    return (Probe.matrix(4, 3, 5e-4, 2.2e6, 0.8e6), PlaneWaveSequence.from_angles([-8.0, 0.0, 8.0], [-5.0, 5.0]))


def _assert_same(a: Acquisition, b: Acquisition) -> None:
    assert a.rf.dtype == b.rf.dtype
    np.testing.assert_array_equal(a.rf, b.rf)
    assert (a.fs, a.t0, a.c0, a.frame_index, a.timestamp) == (b.fs, b.t0, b.c0, b.frame_index, b.timestamp)
    np.testing.assert_array_equal(a.probe.positions, b.probe.positions)
    assert (a.probe.pitch, a.probe.centre_frequency, a.probe.bandwidth) == (
        b.probe.pitch,
        b.probe.centre_frequency,
        b.probe.bandwidth,
    )
    np.testing.assert_array_equal(a.sequence.sines, b.sequence.sines)
    assert a.sequence.prf == b.sequence.prf
    assert a.truth == b.truth


# ---------------------------------------------------------------------------------------------
# Round trips


def test_round_trip_keeps_the_prf(tmp_path: Path) -> None:
    """The pulse repetition frequency (motion-aware fingerprints need it) travels as the UFF PRF."""
    probe, seq = _linear()
    seq = PlaneWaveSequence(seq.sines, prf=2500.0)
    write_uff(tmp_path / "prf.uff", _frames(probe, seq, n_frames=1))
    back = read_uff(tmp_path / "prf.uff")[0]
    assert back.sequence.prf == 2500.0
    np.testing.assert_allclose(back.sequence.transmit_times(), (np.arange(4) - 1.5) / 2500.0)


@pytest.mark.parametrize("setup", [_linear, _matrix], ids=["linear-2d", "matrix-3d"])
def test_round_trip_identical(tmp_path: Path, setup) -> None:
    probe, seq = setup()
    frames = _frames(probe, seq)
    path = tmp_path / "rt.uff"
    write_uff(path, frames)
    back = read_uff(path)
    assert len(back) == len(frames)
    for a, b in zip(frames, back, strict=True):
        _assert_same(a, b)
    with h5py.File(path, "r") as f:
        assert f.attrs["version"][0].decode() == UFF_VERSION
        cd = f["channel_data"]
        assert cd.attrs["class"].decode() == "uff.channel_data"
        # MATLAB [time x channel x wave x frame] seen reversed by h5py
        assert cd["data"].shape == (3, seq.n_waves, probe.n_elements, 40)
        assert cd["probe"].attrs["class"].decode() == ("uff.linear_array" if probe.is_linear else "uff.probe")
        assert cd["probe/geometry"].shape == (7, probe.n_elements)
        assert np.isinf(cd["sequence/sequence_0001/source/distance"][()]).all()
    # selected frames, and the frame-level truth override
    sub = read_uff(path, frames=[2])
    assert len(sub) == 1 and sub[0].frame_index == 12
    write_uff(tmp_path / "t.uff", frames[0], truth={"label": "x"})
    assert read_uff(tmp_path / "t.uff")[0].truth == {"label": "x"}


def test_angle_conventions() -> None:
    sines = np.array([[0.3, 0.0], [-0.2, 0.1], [0.0, -0.4]])
    az, el = sines_to_angles(sines)
    np.testing.assert_allclose(az[0], np.arcsin(0.3))  # 2D: s_x = sin(azimuth)
    np.testing.assert_allclose(el, np.arcsin(sines[:, 1]))
    # USTB's point at infinity: (sin az cos el, sin el, cos az cos el)
    np.testing.assert_allclose(np.sin(az) * np.cos(el), sines[:, 0], atol=1e-15)
    np.testing.assert_allclose(angles_to_sines(az, el), sines, atol=1e-15)


def test_json_helpers_and_several_datasets(tmp_path: Path) -> None:
    probe, seq = _linear()
    path = tmp_path / "two.uff"
    write_uff(path, _frames(probe, seq, 1), name="first")
    write_uff(path, _frames(probe, seq, 2, seed=1), name="second", mode="a")
    assert sorted(list_uff_datasets(path)) == ["first", "second"]
    assert len(read_uff(path, dataset="second")) == 2
    write_uff_json(path, "notes", {"rig": "A", "gain": np.float32(3.0)}, dataset="first")
    assert read_uff_json(path, "notes", dataset="first") == {"rig": "A", "gain": 3.0}
    assert read_uff_json(path, "absent", dataset="first") is None
    with pytest.raises(UFFError, match="dataset"):
        read_uff(path)
    with pytest.raises(UFFError, match="dataset"):
        read_uff(path, dataset="third")
    with pytest.raises(UFFError, match="name"):
        write_uff(path, _frames(probe, seq, 1), name="first", mode="a")


# ---------------------------------------------------------------------------------------------
# Files in USTB's MATLAB layout (written here the way uff.write_object writes them)


def _mat_attrs(obj, cls: str, name: str) -> None:
    obj.attrs["class"] = np.bytes_(cls.encode())
    obj.attrs["name"] = np.bytes_(name.encode())


def _mat_num(g: h5py.Group, key: str, value) -> None:
    arr = np.asarray(value, dtype=np.float32)  # MATLAB stores doubles as single
    ds = g.create_dataset(key, data=arr.reshape(1, 1) if arr.ndim == 0 else arr)
    _mat_attrs(ds, "double", key)
    ds.attrs["complex"] = 0.0
    ds.attrs["imaginary"] = 0.0


def _mat_group(parent: h5py.Group, key: str, cls: str, n: int = 1) -> h5py.Group:
    g = parent.create_group(key)
    _mat_attrs(g, cls, key)
    g.attrs["size"] = np.array([1.0, n])
    g.attrs["array"] = 1.0 if n > 1 else 0.0
    return g


def test_reads_matlab_layout_with_per_wave_delays(tmp_path: Path) -> None:
    n_el, pitch, fs, n_t = 8, 3e-4, 40e6, 64
    angles = np.deg2rad([-10.0, 0.0, 10.0])
    delay_samples = np.array([2, 0, 5])
    rng = np.random.default_rng(3)
    data = rng.standard_normal((n_t, n_el, 3)).astype(np.float32)  # MATLAB [time x ch x wave]
    path = tmp_path / "ustb.uff"
    with h5py.File(path, "w") as f:
        f.attrs["version"] = np.array([b"v1.2.0"], dtype="S7")
        cd = _mat_group(f, "channel_data", "uff.channel_data")
        _mat_num(cd, "sampling_frequency", fs)
        _mat_num(cd, "initial_time", 1e-6)
        _mat_num(cd, "sound_speed", 1540.0)
        _mat_num(cd, "modulation_frequency", 0.0)
        _mat_num(cd, "data", data.T)  # one frame: trailing singleton dropped -> 3-D
        pr = _mat_group(cd, "probe", "uff.linear_array")
        _mat_num(pr, "N", n_el)
        _mat_num(pr, "pitch", pitch)
        x = (np.arange(1, n_el + 1) - (n_el + 1) / 2) * pitch
        geo = np.zeros((n_el, 7))
        geo[:, 0], geo[:, 5], geo[:, 6] = x, pitch, 10 * pitch
        _mat_num(pr, "geometry", geo.T)
        pu = _mat_group(cd, "pulse", "uff.pulse")
        _mat_num(pu, "center_frequency", 5e6)
        _mat_num(pu, "fractional_bandwidth", 0.6)
        sq = _mat_group(cd, "sequence", "uff.wave", n=3)
        for i, a in enumerate(angles):
            w = _mat_group(sq, f"sequence_{i + 1:04d}", "uff.wave")
            wf = w.create_dataset("wavefront", data=np.array([[0.0]], dtype=np.float32))
            _mat_attrs(wf, "uff.wavefront", "wavefront")
            src = _mat_group(w, "source", "uff.point")
            _mat_num(src, "distance", np.inf)
            _mat_num(src, "azimuth", a)
            _mat_num(src, "elevation", 0.0)
            _mat_num(w, "delay", delay_samples[i] / fs)
            _mat_num(w, "sound_speed", 1540.0)
    (acq,) = read_uff(path)
    # t0 = initial_time + min(delay); wave n is delayed by (delay_n - min) samples
    assert acq.t0 == pytest.approx(1e-6)
    assert acq.rf.shape == (n_el, 3, n_t + 5)
    for i, d in enumerate(delay_samples):
        np.testing.assert_array_equal(acq.rf[:, i, d : d + n_t], data[:, :, i].T)
        assert not acq.rf[:, i, :d].any()
    np.testing.assert_allclose(acq.sequence.sines[:, 0], np.sin(np.float32(angles)), rtol=1e-6)
    np.testing.assert_allclose(acq.probe.positions[:, 0], x, rtol=1e-6)
    assert acq.probe.pitch == pytest.approx(pitch)
    assert acq.probe.centre_frequency == pytest.approx(5e6)
    assert acq.probe.bandwidth == pytest.approx(3e6)
    assert acq.c0 == pytest.approx(1540.0) and acq.fs == pytest.approx(fs)
    assert acq.frame_index == 0


# ---------------------------------------------------------------------------------------------
# pyuff-ustb interoperability


def test_reads_pyuff_ustb_file(tmp_path: Path) -> None:
    pyuff = pytest.importorskip("pyuff_ustb")
    nx, ny, pitch, n_t, n_f = 3, 2, 4e-4, 30, 2
    x0 = (np.arange(nx) - (nx - 1) / 2) * pitch
    y0 = (np.arange(ny) - (ny - 1) / 2) * pitch
    yy, xx = np.meshgrid(y0, x0, indexing="ij")
    geometry = np.zeros((7, nx * ny))
    geometry[0], geometry[1], geometry[5:] = xx.ravel(), yy.ravel(), pitch
    probe = pyuff.MatrixArray(N_x=nx, N_y=ny, pitch_x=pitch, pitch_y=pitch, geometry=geometry)
    az = np.deg2rad([-6.0, 0.0, 9.0])
    el = np.deg2rad([3.0, 0.0, -4.0])
    seq = [
        pyuff.Wave(
            wavefront=pyuff.Wavefront.plane,
            source=pyuff.Point(distance=np.inf, azimuth=a, elevation=e),
            delay=0.0,
            sound_speed=1500.0,
        )
        for a, e in zip(az, el, strict=True)
    ]
    data = np.random.default_rng(5).standard_normal((n_t, nx * ny, 3, n_f)).astype(np.float32)
    cd = pyuff.ChannelData(
        sampling_frequency=25e6,
        initial_time=-1e-6,
        sound_speed=1500.0,
        modulation_frequency=0.0,
        sequence=seq,
        probe=probe,
        data=data,
        pulse=pyuff.Pulse(center_frequency=3e6, fractional_bandwidth=0.5, phase=0.0),
    )
    path = tmp_path / "pyuff.uff"
    cd.write(str(path), "channel_data", ignore_missing_compulsory_fields=True)
    frames = read_uff(path)
    assert [fr.frame_index for fr in frames] == [0, 1]
    for k, fr in enumerate(frames):
        np.testing.assert_array_equal(fr.rf, data[..., k].transpose(1, 2, 0))
        assert (fr.fs, fr.t0, fr.c0) == (25e6, -1e-6, 1500.0)
    np.testing.assert_allclose(frames[0].sequence.sines, angles_to_sines(az, el))
    np.testing.assert_allclose(frames[0].sequence.sines[:, 0], np.sin(az) * np.cos(el))
    np.testing.assert_array_equal(frames[0].probe.positions, geometry[:3].T)
    assert frames[0].probe.pitch == pitch
    assert frames[0].probe.centre_frequency == 3e6
    assert frames[0].probe.bandwidth == pytest.approx(1.5e6)


@pytest.mark.parametrize("setup", [_linear, _matrix], ids=["linear-2d", "matrix-3d"])
def test_pyuff_ustb_reads_our_file(tmp_path: Path, setup) -> None:
    pyuff = pytest.importorskip("pyuff_ustb")
    probe, seq = setup()
    frames = _frames(probe, seq, 2)
    path = tmp_path / "ours.uff"
    write_uff(path, frames)
    cd = pyuff.Uff(str(path))["channel_data"]
    np.testing.assert_array_equal(cd.data, np.stack([fr.rf for fr in frames], -1).transpose(2, 0, 1, 3))
    assert (cd.sampling_frequency, cd.initial_time, cd.sound_speed, cd.modulation_frequency) == (FS, T0, C0, 0.0)
    np.testing.assert_array_equal(cd.probe.xyz, probe.positions)
    az = np.array([w.source.azimuth for w in cd.sequence], dtype=float)
    el = np.array([w.source.elevation for w in cd.sequence], dtype=float)
    assert all(np.isinf(w.source.distance) for w in cd.sequence)
    assert all(w.wavefront == pyuff.Wavefront.plane for w in cd.sequence)
    np.testing.assert_allclose(angles_to_sines(az, el), seq.sines, atol=1e-15)
    assert cd.pulse.center_frequency == probe.centre_frequency


# ---------------------------------------------------------------------------------------------
# Bad input


@pytest.fixture
def good_file(tmp_path: Path) -> Path:
    probe, seq = _linear()
    path = tmp_path / "good.uff"
    write_uff(path, _frames(probe, seq, 2))
    return path


def _edit(path: Path, fn) -> None:
    with h5py.File(path, "a") as f:
        fn(f["channel_data"])


def test_missing_field(good_file: Path) -> None:
    _edit(good_file, lambda cd: cd.__delitem__("sampling_frequency"))
    with pytest.raises(UFFError, match="sampling_frequency: missing"):
        read_uff(good_file)


def test_missing_probe(good_file: Path) -> None:
    _edit(good_file, lambda cd: cd.__delitem__("probe"))
    with pytest.raises(UFFError, match="probe: missing"):
        read_uff(good_file)


def test_wrong_axis_order(good_file: Path) -> None:
    def transpose(cd: h5py.Group) -> None:
        data = cd["data"][()]
        del cd["data"]
        cd.create_dataset("data", data=data.T)  # row-major [time, channel, wave, frame]

    _edit(good_file, transpose)
    with pytest.raises(UFFError, match=r"data: expected h5py shape .*16 elements.*row-major"):
        read_uff(good_file)


def test_nan_in_data(good_file: Path) -> None:
    def poison(cd: h5py.Group) -> None:
        cd["data"][1, 0, 3, 7] = np.nan

    _edit(good_file, poison)
    with pytest.raises(UFFError, match="data: expected finite"):
        read_uff(good_file)
    assert len(read_uff(good_file, frames=[0])) == 1


def test_diverging_wave_refused(good_file: Path) -> None:
    def diverge(cd: h5py.Group) -> None:
        w = cd["sequence/sequence_0002"]
        w["wavefront"][...] = 1  # spherical
        w["source/distance"][...] = 0.01
        w["source/azimuth"][...] = np.pi  # behind the array

    _edit(good_file, diverge)
    with pytest.raises(UFFError, match=r"sequence\[1\]/source/distance: expected Inf.*diverging"):
        read_uff(good_file)


def test_real_data_with_a_modulation_frequency_refused(good_file: Path) -> None:
    # IQ is read (tests/test_iq.py); real samples that claim a modulation frequency are not IQ.
    _edit(good_file, lambda cd: cd["modulation_frequency"].__setitem__(Ellipsis, 2e6))
    with pytest.raises(UFFError, match=r"modulation_frequency: 2e\+06 Hz means IQ data, but .* real samples"):
        read_uff(good_file)


def test_write_refuses_bad_frames(tmp_path: Path) -> None:
    probe, seq = _linear()
    frames = _frames(probe, seq, 2)
    frames[1].rf[0, 0, 0] = np.nan
    with pytest.raises(UFFError, match=r"frames\[1\].rf: expected finite"):
        write_uff(tmp_path / "x.uff", frames)
    frames = _frames(probe, seq, 2)
    frames[1].fs = 2 * FS
    with pytest.raises(UFFError, match=r"frames\[1\].fs"):
        write_uff(tmp_path / "x.uff", frames)
    with pytest.raises(UFFError, match="frames"):
        write_uff(tmp_path / "x.uff", [])
    with pytest.raises(UFFError, match="truth"):
        write_uff(tmp_path / "x.uff", _frames(probe, seq, 2), truth=[{}])


def test_fractional_delay_alignment_and_band_estimate(tmp_path: Path) -> None:
    fs, fc, n_t = 40e6, 5e6, 256
    t = np.arange(n_t) / fs

    def pulse(tt: np.ndarray) -> np.ndarray:
        return np.exp(-(((tt - 3e-6) * 2e6) ** 2)) * np.cos(2 * np.pi * fc * (tt - 3e-6))

    probe = Probe.linear(4, 3e-4, 1.0, 1.0)  # band replaced below by the estimate
    seq = PlaneWaveSequence.from_angles([0.0, 5.0])
    rf = np.zeros((4, 2, n_t))
    rf[:, 0] = pulse(t)
    rf[:, 1] = pulse(t + 0.5 / fs)  # this wave was recorded with delay = 0.5 sample
    path = tmp_path / "frac.uff"
    write_uff(path, Acquisition(rf, fs, 0.0, C0, probe, seq))
    with h5py.File(path, "a") as f:
        cd = f["channel_data"]
        del cd.attrs["fp_metadata"], cd["pulse"]
        cd["sequence/sequence_0002/delay"][...] = 0.5 / fs
    (acq,) = read_uff(path)
    assert acq.rf.shape[-1] == n_t + 1
    np.testing.assert_allclose(acq.rf[:, 1, :n_t], np.broadcast_to(pulse(t), (4, n_t)), atol=2e-3)
    np.testing.assert_array_equal(acq.rf[:, 0, :n_t], rf[:, 0])
    assert acq.probe.centre_frequency == pytest.approx(fc, rel=0.05)
    assert 0.5e6 < acq.probe.bandwidth < 2e6


def test_single_wave_single_frame(tmp_path: Path) -> None:
    probe = Probe.linear(5, 2e-4, 3e6, 2e6)
    seq = PlaneWaveSequence.from_angles([3.0])
    (frame,) = _frames(probe, seq, 1)
    path = tmp_path / "one.uff"
    write_uff(path, frame)
    _assert_same(frame, read_uff(path)[0])
    with h5py.File(path, "r") as f:  # one wave is stored in place, as USTB does
        assert "source" in f["channel_data/sequence"]
    pyuff = pytest.importorskip("pyuff_ustb")
    cd = pyuff.Uff(str(path))["channel_data"]
    assert cd.N_waves == 1 and cd.N_frames == 1
    np.testing.assert_allclose(np.sin(cd.sequence.source.azimuth), seq.sines[0, 0])
