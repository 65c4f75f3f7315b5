"""IQ channel data (modulation_frequency > 0): USTB's demodulation convention both ways, UFF files with IQ
as USTB writes complex arrays (data/real + data/imag) or as a native complex dataset, a point target
located within one grid step after the round trip, and refusals in one line."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

import fpcore
from fpcore import PlaneWaveSequence, Probe
from fpcore.born import born_points
from fpcore.io import UFFError, iq_to_rf, read_uff, rf_to_iq, rf_upsampling, write_uff
from fpcore.io.iq import MAX_RF_UPSAMPLING

PROBE = Probe.linear(32, 0.3e-3, 2.5e6, 1.5e6)
SEQ = PlaneWaveSequence.from_angles(np.linspace(-10, 10, 5))
R0 = np.array([0.0, 0.0, 14e-3])
TARGET = np.array([1.0e-3, 0.0, 15.5e-3])
F_MOD, DECIMATION = 2.5e6, 4


def _pulse(t: np.ndarray) -> np.ndarray:
    return np.exp(-(((t - 10e-6) / 0.4e-6) ** 2)) * np.cos(2 * np.pi * 5e6 * (t - 10e-6) + 0.3)


def test_ustb_convention_round_trip_is_exact_in_band() -> None:
    fs, t0 = 40e6, 3e-6
    t = t0 + np.arange(800) / fs
    iq, fs_iq = rf_to_iq(_pulse(t)[None], fs, t0, 5.2e6, 4)
    assert fs_iq == 10e6 and iq.shape == (1, 200)
    # USTB: IQ(t) = A(t) e^{-i2π f_m t} on the absolute channel time, so the phase at t is the RF's
    # analytic phase minus 2π f_m t.
    k = 70  # the pulse's centre, t = 10 µs
    tk = t0 + k * 4 / fs
    assert np.angle(iq[0, k] * np.exp(2j * np.pi * 5.2e6 * tk)) == pytest.approx(
        np.angle(np.exp(1j * (2 * np.pi * 5e6 * (tk - 10e-6) + 0.3))), abs=1e-3
    )
    rf, fs_rf = iq_to_rf(iq, fs_iq, t0, 5.2e6)
    assert fs_rf == 30e6  # M = 3: 30 MHz > 2 (f_m + fs_IQ/2) = 20.4 MHz
    t2 = t0 + np.arange(rf.shape[-1]) / fs_rf
    assert np.abs(rf[0] - _pulse(t2)).max() < 1e-5


def test_upsampling_factor() -> None:
    assert rf_upsampling(5.208e6, 5.208e6) == 4  # PICMUS IQ → 20.8 MHz, the rate of its RF files
    assert rf_upsampling(20e6, 0.0) == 1
    assert rf_upsampling(5e6, 2.5e6) * 5e6 > 2 * (2.5e6 + 2.5e6)
    with pytest.raises(ValueError, match="modulation_frequency"):
        rf_upsampling(5e6, -1.0)
    # a misread header: 2 f_m/fs overflowed to inf (found by tests/test_fuzz_inputs.py) or asks for an absurd RF rate
    assert rf_upsampling(1.0, 0.5 * (MAX_RF_UPSAMPLING - 1) - 1e-6) == MAX_RF_UPSAMPLING
    for f_mod in (0.5 * (MAX_RF_UPSAMPLING - 1) * 20e6, 8.98846567431158e307):
        with pytest.raises(ValueError, match="modulation_frequency: expected below"):
            rf_upsampling(20e6, f_mod)


def _marker(centre: np.ndarray) -> fpcore.Acquisition:
    rng = np.random.default_rng(4)
    offs = rng.uniform(-0.8e-3, 0.8e-3, (8, 3))
    offs[:, 1] = 0.0
    acq = born_points(PROBE, SEQ, centre + offs, rng.uniform(0.5, 1.0, 8), n_t=720, t0=4e-6)
    noise = np.random.default_rng(int(centre[2] * 1e6)).standard_normal(acq.rf.shape)
    acq.rf = (acq.rf + 0.02 * np.abs(acq.rf).max() * noise).astype(np.float32)
    acq.truth = {"targets": [{"name": "marker", "position_m": centre.tolist()}]}
    return acq


def _to_iq_uff(path: Path, acq: fpcore.Acquisition, native: bool) -> None:
    """Our RF UFF, its data replaced by IQ as USTB writes a complex array: a group ``data`` (class single,
    complex = 1) with ``real`` and ``imag`` (imaginary = 0 / 1); or a native complex dataset."""
    write_uff(path, acq)
    with h5py.File(path, "r+") as f:
        cd = f["channel_data"]
        rf = cd["data"][()]  # (1, N_waves, N_channels, N_t)
        iq, fs_iq = rf_to_iq(rf, acq.fs, acq.t0, F_MOD, DECIMATION)
        del cd["data"], cd.attrs["fp_metadata"]  # as USTB writes it: no metadata of ours
        if native:
            cd.create_dataset("data", data=iq.astype(np.complex64))
        else:
            g = cd.create_group("data")
            for key, part, imaginary in (("real", iq.real, 0.0), ("imag", iq.imag, 1.0)):
                ds = g.create_dataset(key, data=part.astype(np.float32))
                ds.attrs["class"], ds.attrs["name"], ds.attrs["imaginary"] = (
                    np.bytes_("single"),
                    np.bytes_(key),
                    imaginary,
                )
            g.attrs["class"], g.attrs["name"], g.attrs["complex"] = np.bytes_("single"), np.bytes_("data"), 1.0
        cd["sampling_frequency"][...] = fs_iq
        cd["modulation_frequency"][...] = F_MOD


@pytest.mark.parametrize("native", [False, True], ids=["real_imag_group", "complex_dataset"])
def test_uff_iq_round_trip_locates_the_point_target(tmp_path, native) -> None:
    cal, acq = _marker(R0), _marker(TARGET)
    _to_iq_uff(tmp_path / "cal.uff", cal, native)
    _to_iq_uff(tmp_path / "data.uff", acq, native)
    got_cal, got = read_uff(tmp_path / "cal.uff")[0], read_uff(tmp_path / "data.uff")[0]
    assert got.fs == 15e6 and got.n_samples == acq.n_samples * 15 // 20 and got.t0 == acq.t0
    assert got.ground_truth.targets[0].position_m[2] == pytest.approx(TARGET[2])
    # Same band content as the RF it came from (bins every 1/(2 × record) at both rates).
    a, b = acq.spectrum(1.8e6, 3.2e6).data, got.spectrum(1.8e6, 3.2e6).data
    assert a.shape == b.shape and np.linalg.norm(a - b) / np.linalg.norm(a) < 1e-2
    band = (1.75e6, 3.25e6)  # the probe's (the pulse's band is kept by USTB in uff.pulse)
    grid = fpcore.Grid.for_acquisition(got_cal, band, x_range=(-5e-3, 5e-3), z_range=(10e-3, 20e-3))
    imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=band, n_freq=24))
    # The marker's own size sets the calibration's time gate (points within ±0.8 mm: 1.6 mm across).
    fp = fpcore.from_calibration(got_cal, R0, imager.out_sines_for(got_cal), band, n_freq=24, diameter=1.6e-3)
    found = fpcore.locate(imager, got, fp, interior=True)
    pos = np.asarray(found.detections[0].position_m)
    assert np.all(np.abs(pos - TARGET) <= max(grid.spacing)), (pos, TARGET, grid.spacing)
    assert found.detections[0].pfa < 1e-6


def _edit_data(path: Path, edit) -> None:
    with h5py.File(path, "r+") as f:
        edit(f["channel_data"])


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda cd: cd["modulation_frequency"].__setitem__(Ellipsis, 0.0), r"data: complex \(IQ\) samples need"),
        (lambda cd: cd["data"].__delitem__("imag"), "group with real and imag"),
        (lambda cd: cd["modulation_frequency"].__setitem__(Ellipsis, -2e6), "modulation_frequency: expected 0"),
        (lambda cd: cd["data/imag"].__setitem__((0, 0, 0, 3), np.nan), "finite"),
    ],
)
def test_bad_iq_refused_in_one_line(tmp_path, edit, match) -> None:
    path = tmp_path / "iq.uff"
    _to_iq_uff(path, _marker(R0), native=False)
    _edit_data(path, edit)
    with pytest.raises(UFFError, match=match) as info:
        read_uff(path)
    assert "\n" not in str(info.value)
