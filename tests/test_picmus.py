"""PICMUS files (IUS 2016 challenge layout, /US/US_DATASET0000): RF and IQ round trips, a point target
located within one grid step after the round trip, `.mat` files, bad input in one line."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

import fpcore
from fpcore import PlaneWaveSequence, Probe
from fpcore.born import born_points
from fpcore.io import (
    FormatError,
    PICMUSError,
    detect_format,
    read_channel_data,
    read_picmus,
    read_uff,
    rf_to_iq,
    write_picmus,
    write_uff,
)

PROBE = Probe.linear(48, 0.3e-3, 2.5e6, 1.5e6)
SEQ = PlaneWaveSequence.from_angles(np.linspace(-12, 12, 7))
R0 = np.array([0.0, 0.0, 15e-3])
TARGET = np.array([-1.2e-3, 0.0, 17e-3])
F_MOD = 2.5e6


def _marker(centre: np.ndarray, frame_index: int = 0) -> fpcore.Acquisition:
    """A point target: a small cluster of Born points (fpcore.born, the project's exact single-scattering model)."""
    rng = np.random.default_rng(3)
    offs = rng.uniform(-0.8e-3, 0.8e-3, (8, 3))
    offs[:, 1] = 0.0
    acq = born_points(PROBE, SEQ, centre + offs, rng.uniform(0.5, 1.0, 8), n_t=800, t0=4e-6, frame_index=frame_index)
    noise = np.random.default_rng(10 + frame_index).standard_normal(acq.rf.shape)
    acq.rf = (acq.rf + 0.02 * np.abs(acq.rf).max() * noise).astype(
        np.float32
    )  # electronic noise: a null to test against
    acq.truth = {"targets": [{"name": "marker", "position_m": centre.tolist()}]}
    return acq


def _write_published(path: Path, acq: fpcore.Acquisition, f_mod: float, decimation: int) -> None:
    """A file as the challenge published them: float32 datasets, scalars of shape (1,), no extra attributes."""
    rf = np.asarray(acq.rf, np.float64).transpose(1, 0, 2)  # (N_angles, N_channels, N_samples)
    if f_mod > 0:
        iq, fs = rf_to_iq(rf, acq.fs, acq.t0, f_mod, decimation)
        real, imag = iq.real, iq.imag
    else:
        real, imag, fs = rf, np.zeros_like(rf), acq.fs
    with h5py.File(path, "w") as f:
        g = f.create_group("US/US_DATASET0000")
        g.create_dataset("data/real", data=real.astype(np.float32))
        g.create_dataset("data/imag", data=imag.astype(np.float32))
        g.create_dataset("angles", data=np.arcsin(acq.sequence.sines[:, 0]).astype(np.float32))
        g.create_dataset("probe_geometry", data=acq.probe.positions.T.astype(np.float32))
        for key, v in (("sampling_frequency", fs), ("modulation_frequency", f_mod), ("initial_time", acq.t0)):
            g.create_dataset(key, data=np.array([v], np.float32))
        g.create_dataset("sound_speed", data=np.array([acq.c0], np.float32))


def _band_spectrum(acq: fpcore.Acquisition, band: tuple[float, float]) -> np.ndarray:
    spec = acq.spectrum(band[0] + 5e3, band[1] - 5e3)  # bins every 1/(2 × record) = 12.5 kHz at any fs
    assert spec.freqs[0] == pytest.approx(1.7625e6) and spec.freqs.size == 119
    return spec.data


def _locate(acq: fpcore.Acquisition, cal: fpcore.Acquisition) -> tuple[np.ndarray, float]:
    band = cal.default_band()
    grid = fpcore.Grid.for_acquisition(cal, band, x_range=(-6e-3, 6e-3), z_range=(10e-3, 22e-3))
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=band, n_freq=24))
    # The marker's own size sets the calibration's time gate (points within ±0.8 mm: 1.6 mm across).
    fp = fpcore.from_calibration(cal, R0, imager.out_sines_for(cal), band, n_freq=24, diameter=1.6e-3)
    found = fpcore.locate(imager, acq, fp, interior=True)
    assert found.detections, "no detection"
    return np.asarray(found.detections[0].position_m), max(grid.spacing)


@pytest.fixture(scope="module")
def frames() -> tuple[fpcore.Acquisition, fpcore.Acquisition]:
    return _marker(R0), _marker(TARGET)


@pytest.mark.parametrize("f_mod, decimation", [(0.0, 1), (F_MOD, 4)], ids=["rf", "iq"])
def test_published_layout_round_trip_locates_the_point_target(tmp_path, frames, f_mod, decimation) -> None:
    cal, acq = frames
    path = tmp_path / "target.hdf5"
    _write_published(path, acq, f_mod, decimation)
    assert detect_format(path) == "picmus"
    back = read_picmus(path)
    assert len(back) == 1
    got = back[0]
    if f_mod:
        assert got.fs == pytest.approx(5e6 * 3)  # IQ at 5 MHz around 2.5 MHz → RF at 15 MHz (fpcore.io.iq)
    assert got.t0 == pytest.approx(acq.t0, rel=1e-6) and got.c0 == pytest.approx(acq.c0)
    np.testing.assert_allclose(got.probe.positions, acq.probe.positions, atol=1e-9)
    np.testing.assert_allclose(got.sequence.sines, acq.sequence.sines, atol=1e-7)
    band = cal.default_band()
    a, b = _band_spectrum(acq, band), _band_spectrum(got, band)
    # The band survives: float32 storage for RF; for IQ also the interpolation of a record cut at its ends
    # (0.6 % here, noise reaches the ends).
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < (1e-2 if f_mod else 1e-3)
    # The band estimated from the data (PICMUS files carry none) is the transducer's, roughly.
    assert abs(got.probe.centre_frequency - PROBE.centre_frequency) < 0.3e6
    # Located with the probe's band (as a PICMUS user gives it, e.g. the L11-4v's); the calibration takes the
    # same path as the data (its frequencies must be the data's: same fs and record length).
    _write_published(tmp_path / "cal.hdf5", cal, f_mod, decimation)
    band_kw = {"centre_frequency": PROBE.centre_frequency, "bandwidth": PROBE.bandwidth}
    pos, step = _locate(read_picmus(path, **band_kw)[0], read_picmus(tmp_path / "cal.hdf5", **band_kw)[0])
    ref, _ = _locate(acq, cal)
    assert np.all(np.abs(pos - TARGET) <= step), (pos, TARGET, step)
    assert np.all(np.abs(pos - ref) <= step)  # where the original data put it


def test_writer_round_trip_keeps_metadata_and_frames(tmp_path, frames) -> None:
    cal, acq = frames
    acq2 = _marker(TARGET + [0.5e-3, 0, 0], frame_index=7)
    path = tmp_path / "two.hdf5"
    write_picmus(path, [acq, acq2], modulation_frequency=F_MOD, decimation=4)
    with h5py.File(path) as f:
        assert f["US/US_DATASET0000/data/real"].shape == (2, SEQ.n_waves, PROBE.n_elements, 200)
        assert f["US/US_DATASET0000/modulation_frequency"][0] == F_MOD
    back = read_picmus(path)
    assert [b.frame_index for b in back] == [0, 7]
    assert back[1].ground_truth.targets[0].position_m[0] == pytest.approx(TARGET[0] + 0.5e-3)
    assert (back[0].probe.centre_frequency, back[0].probe.bandwidth) == (2.5e6, 1.5e6)
    # RF write → read is exact up to float32.
    write_picmus(tmp_path / "rf.hdf5", acq)
    rf = read_picmus(tmp_path / "rf.hdf5")[0]
    np.testing.assert_allclose(rf.rf, acq.rf.astype(np.float32), rtol=0, atol=0)
    # read_uff and the generic reader take PICMUS files too.
    assert read_uff(path)[1].frame_index == 7
    assert len(read_channel_data(path)) == 2


def test_per_angle_initial_times_are_aligned(tmp_path, frames) -> None:
    _, acq = frames
    path = tmp_path / "t.hdf5"
    _write_published(path, acq, 0.0, 1)
    shift = np.arange(SEQ.n_waves) * 2 / acq.fs  # angle n starts 2n samples later: its samples move earlier
    with h5py.File(path, "r+") as f:
        g = f["US/US_DATASET0000"]
        real = g["data/real"][()]
        for n in range(SEQ.n_waves):
            real[n, :, : real.shape[2] - 2 * n] = real[n, :, 2 * n :].copy()
        g["data/real"][...] = real
        del g["initial_time"]
        g.create_dataset("initial_time", data=(acq.t0 + shift).astype(np.float64))
    got = read_picmus(path)[0]
    assert got.t0 == pytest.approx(acq.t0)
    k = 2 * (SEQ.n_waves - 1)  # wave n holds original samples [2n, N) once aligned
    np.testing.assert_allclose(got.rf[:, :, k : acq.n_samples], acq.rf[:, :, k:], atol=1e-6 * np.abs(acq.rf).max())


def test_mat_files_get_one_clear_line(tmp_path, frames) -> None:
    _, acq = frames
    v5 = tmp_path / "v5.mat"
    v5.write_bytes(b"MATLAB 5.0 MAT-file, Platform: GLNXA64".ljust(128, b" ") + bytes(64))
    with pytest.raises(FormatError, match=r"v5\.mat: a MATLAB \.mat file that is not HDF5.*v7\.3.*uff"):
        read_channel_data(v5)
    # v7.3 = HDF5 with a 512-byte user block; plain variables are named in the message.
    plain = tmp_path / "plain.mat"
    with h5py.File(plain, "w", userblock_size=512) as f:
        f.create_dataset("rf", data=np.zeros((3, 4))).attrs["MATLAB_class"] = np.bytes_("double")
    with open(plain, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan 1 00:00:00 2024 HDF5 schema 1.00 .")
    with pytest.raises(FormatError, match=r"MATLAB v7\.3 file holding variables rf \(double\), none in USTB"):
        read_uff(plain)
    # A v7.3 file that holds USTB's layout is read.
    ustb = tmp_path / "ustb.mat"
    with h5py.File(ustb, "w", userblock_size=512):
        pass
    write_uff(ustb, acq, mode="a")
    assert detect_format(ustb) == "uff"
    np.testing.assert_array_equal(read_channel_data(ustb)[0].rf, acq.rf)


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda g: g.__delitem__("angles"), "angles: missing"),
        (lambda g: (g.__delitem__("angles"), g.create_dataset("angles", data=np.zeros(3))), "angles: expected 7"),
        (lambda g: g["sampling_frequency"].__setitem__(0, 0.0), "sampling_frequency: expected a positive"),
        (lambda g: g["data/imag"].__setitem__((0, 0, 0), np.nan), "finite"),
        (lambda g: (g.__delitem__("probe_geometry"), g.create_dataset("probe_geometry", data=np.zeros((3, 5)))), "48"),
        (lambda g: g["modulation_frequency"].__setitem__(0, -1.0), "modulation_frequency: expected >= 0"),
    ],
)
def test_bad_picmus_input_one_line(tmp_path, frames, edit, field) -> None:
    _, acq = frames
    path = tmp_path / "bad.hdf5"
    _write_published(path, acq, F_MOD, 4)
    with h5py.File(path, "r+") as f:
        edit(f["US/US_DATASET0000"])
    with pytest.raises(PICMUSError, match=field) as info:
        read_picmus(path)
    assert "\n" not in str(info.value)
