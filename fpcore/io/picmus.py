"""PICMUS (IEEE IUS 2016 plane-wave imaging challenge) channel data in and out.

The challenge's files (``*_dataset_rf.hdf5``, ``*_dataset_iq.hdf5``) are HDF5 in the layout of USTB's
predecessor; the h5py view, as the challenge's own loaders and CUBDL's ``PICMUSData`` read it::

    /US/US_DATASET0000/
      data/real, data/imag   (N_angles, N_channels, N_samples) float32 (MATLAB [samples x channels x
                             angles]); imag is zero in the RF files
      angles                 (N_angles,) steering angles in the x–z plane [rad]: s_x = sin(angle)
      probe_geometry         (3, N_channels) element centres, rows x, y, z [m]
      sampling_frequency     (1,) [Hz]
      modulation_frequency   (1,) [Hz]: 0 for RF, f_m > 0 for IQ (5.208 MHz in the IQ files)
      initial_time           (1,) or (N_angles,) time of the first sample [s]
      sound_speed            (1,) [m/s]
      PRF                    (1,) [Hz] (optional)

Conventions (the same as USTB's channel data, fpcore/io/uff.py): sample k of angle n is at channel time
initial_time_n + k/fs with time zero when the plane wavefront crosses the origin; per-angle initial times
are aligned onto their minimum by a band-limited shift, as the UFF reader does. IQ data are converted to
RF with USTB's phase convention (fpcore/io/iq.py: why, and how).

USTB also distributes the challenge's datasets as UFF (``PICMUS_experiment_resolution_distortion.uff``, …,
in USTB's ``examples/picmus``): :func:`fpcore.io.read_uff` reads those.

A PICMUS file holds one frame and no transducer band: the band is estimated from the data's mean power
spectrum (−6 dB) unless given, the pitch is the smallest element spacing. Files written here add a 4-D
``data`` (N_frames, N_angles, N_channels, N_samples) for several frames and the ``fp_metadata`` /
``fp_truth`` JSON attributes of the UFF writer (band, frame indices, timestamps, truth) on the dataset
group; other readers ignore them.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from fpcore.acquisition import Acquisition, PlaneWaveSequence, Probe
from fpcore.io.iq import iq_to_rf, rf_to_iq
from fpcore.io.uff import _align, _estimate_band, _min_spacing

__all__ = ["PICMUSError", "PICMUS_GROUP", "is_picmus", "read_picmus", "write_picmus"]

PICMUS_GROUP = "US/US_DATASET0000"
META_ATTR = "fp_metadata"
TRUTH_ATTR = "fp_truth"

PathLike = str | os.PathLike[str]


class PICMUSError(ValueError):
    """Bad PICMUS input: the message names the field, what was expected and what was found."""


def is_picmus(f: h5py.File) -> bool:
    """True when an open HDF5 file has PICMUS's ``/US/US_DATASET0000/data`` layout."""
    return PICMUS_GROUP in f and isinstance(f[PICMUS_GROUP], h5py.Group) and "data" in f[PICMUS_GROUP]


def _values(g: h5py.Group, key: str, what: str, default: float | None = None) -> np.ndarray:
    field = f"/{PICMUS_GROUP}/{key}"
    if key not in g:
        if default is not None:
            return np.array([default])
        raise PICMUSError(f"{field}: missing (expected {what})")
    node = g[key]
    if not isinstance(node, h5py.Dataset) or node.dtype.kind not in "fiu":
        raise PICMUSError(f"{field}: expected a numeric dataset ({what}), got {node}")
    arr = np.asarray(node[()], dtype=np.float64).ravel()
    if arr.size == 0 or not np.all(np.isfinite(arr)):
        raise PICMUSError(f"{field}: expected finite numbers ({what}), got {arr.tolist()[:4]}")
    return arr


def _scalar(g: h5py.Group, key: str, what: str, default: float | None = None, positive: bool = False) -> float:
    arr = _values(g, key, what, default)
    if arr.size != 1:
        raise PICMUSError(f"/{PICMUS_GROUP}/{key}: expected one value ({what}), got {arr.size}")
    v = float(arr[0])
    if positive and not v > 0:
        raise PICMUSError(f"/{PICMUS_GROUP}/{key}: expected a positive value ({what}), got {v:g}")
    return v


def _geometry(g: h5py.Group, n_ch: int | None) -> np.ndarray:
    geo = _values(g, "probe_geometry", "element centres, h5py shape (3, N_channels) [m]")
    shape = g["probe_geometry"].shape
    if len(shape) == 2 and shape[0] == 3:
        pos = geo.reshape(shape).T
    elif len(shape) == 2 and shape[1] == 3:
        pos = geo.reshape(shape)
    else:
        raise PICMUSError(f"/{PICMUS_GROUP}/probe_geometry: expected h5py shape (3, N_channels), got {shape}")
    if n_ch is not None and pos.shape[0] != n_ch:
        raise PICMUSError(
            f"/{PICMUS_GROUP}/probe_geometry: expected {n_ch} elements (the data's channel axis), got {pos.shape[0]}"
        )
    return np.ascontiguousarray(pos, dtype=np.float64)


def _json_attr(g: h5py.Group, key: str) -> Any:
    raw = g.attrs.get(key)
    if raw is None:
        return None
    try:
        return json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    except json.JSONDecodeError as exc:
        raise PICMUSError(f"/{PICMUS_GROUP}.attrs[{key!r}]: expected a JSON string ({exc})") from exc


def read_picmus(
    path: PathLike,
    *,
    centre_frequency: float | None = None,
    bandwidth: float | None = None,
) -> list[Acquisition]:
    """Read a PICMUS RF or IQ file: one Acquisition per frame (PICMUS files hold one), RF in float32.

    centre_frequency, bandwidth [Hz]: the transducer band (PICMUS files do not carry it); default: the
    writer's metadata if any, else the −6 dB band of the data's mean power spectrum.
    """
    p = Path(path)
    if not p.is_file():
        raise PICMUSError(f"{p}: expected an existing PICMUS (HDF5) file, found none")
    if not h5py.is_hdf5(p):
        raise PICMUSError(f"{p}: expected an HDF5 file (PICMUS layout /{PICMUS_GROUP}), found another format")
    with h5py.File(p, "r") as f:
        if not is_picmus(f):
            raise PICMUSError(f"{p}: expected the PICMUS group /{PICMUS_GROUP}/data, found root {list(f.keys())}")
        g = f[PICMUS_GROUP]
        d = g["data"]
        if isinstance(d, h5py.Dataset):
            real_node, imag_node = d, None  # a plain real dataset (not the published layout, but unambiguous)
        else:
            if "real" not in d:
                raise PICMUSError(f"/{PICMUS_GROUP}/data/real: missing (expected the in-phase / RF samples)")
            real_node, imag_node = d["real"], d.get("imag")
        shape = tuple(real_node.shape)
        if len(shape) not in (3, 4):
            raise PICMUSError(
                f"/{PICMUS_GROUP}/data/real: expected h5py shape (N_angles, N_channels, N_samples), got {shape}"
            )
        if imag_node is not None and tuple(imag_node.shape) != shape:
            raise PICMUSError(
                f"/{PICMUS_GROUP}/data/imag: expected the shape of data/real {shape}, got {imag_node.shape}"
            )
        full = shape if len(shape) == 4 else (1,) + shape
        n_frames, n_a, n_ch, _ = full
        angles = _values(g, "angles", "steering angles [rad], one per plane wave")
        if angles.size != n_a:
            hint = " (axes look reversed: MATLAB order read row-major?)" if shape[-1] == angles.size else ""
            raise PICMUSError(
                f"/{PICMUS_GROUP}/angles: expected {n_a} angles (the data's first axis, h5py shape "
                f"(N_angles, N_channels, N_samples) = {shape}), got {angles.size}{hint}"
            )
        if np.any(np.abs(angles) >= math.pi / 2):
            raise PICMUSError(f"/{PICMUS_GROUP}/angles: expected radians in (-π/2, π/2), got {angles.tolist()}")
        positions = _geometry(g, n_ch)
        fs = _scalar(g, "sampling_frequency", "Hz", positive=True)
        c0 = _scalar(g, "sound_speed", "m/s", positive=True)
        f_mod = _scalar(g, "modulation_frequency", "Hz, 0 for RF", default=0.0)
        if f_mod < 0:
            raise PICMUSError(f"/{PICMUS_GROUP}/modulation_frequency: expected >= 0 Hz, got {f_mod:g}")
        t_init = _values(g, "initial_time", "time of the first sample [s], one or one per angle")
        if t_init.size not in (1, n_a):
            raise PICMUSError(f"/{PICMUS_GROUP}/initial_time: expected 1 or {n_a} values, got {t_init.size}")
        t_init = np.broadcast_to(t_init, (n_a,))
        prf = _scalar(g, "PRF", "Hz", default=0.0)
        meta = _json_attr(g, META_ATTR)
        meta = meta if isinstance(meta, dict) else {}
        truths = _json_attr(g, TRUTH_ATTR)
        if not isinstance(truths, list) or len(truths) != n_frames:
            truths = [{} for _ in range(n_frames)]

        shifts_t = t_init - t_init.min()
        rfs = []
        fs_rf = fs
        for i in range(n_frames):
            re = np.asarray(real_node[i] if len(shape) == 4 else real_node[()])
            im = None if imag_node is None else np.asarray(imag_node[i] if len(shape) == 4 else imag_node[()])
            if not (np.all(np.isfinite(re)) and (im is None or np.all(np.isfinite(im)))):
                raise PICMUSError(f"/{PICMUS_GROUP}/data: expected finite samples, found NaN or Inf in frame {i}")
            per_angle = []
            for a in range(n_a):  # each angle has its own time origin for the IQ phase ramp
                iq = re[a] if im is None or f_mod == 0 else re[a] + 1j * im[a]
                rf_a, fs_rf = iq_to_rf(iq, fs, float(t_init[a]), f_mod)
                per_angle.append(rf_a)
            rf = np.ascontiguousarray(np.stack(per_angle).transpose(1, 0, 2))  # (N_u, N_theta, N_t)
            shifts = shifts_t * fs_rf
            if np.any(shifts > 1e-6):
                rf = _align(rf, shifts)
            rfs.append(rf)

    raw_probe = meta.get("probe")
    mprobe: dict[str, Any] = raw_probe if isinstance(raw_probe, dict) else {}
    fc = centre_frequency or mprobe.get("centre_frequency")
    bw = bandwidth or mprobe.get("bandwidth")
    if not (fc and bw):
        efc, ebw = _estimate_band(rfs[0], fs_rf)
        fc, bw = fc or efc, bw or ebw
    pitch = mprobe.get("pitch") or _min_spacing(positions)
    if not pitch:
        raise PICMUSError(f"/{PICMUS_GROUP}/probe_geometry: expected several distinct element positions")
    n_idx, stamps = meta.get("frame_index"), meta.get("timestamp")
    try:
        probe = Probe(positions, float(pitch), float(fc), float(bw))
        seq = PlaneWaveSequence(np.stack([np.sin(angles), np.zeros_like(angles)], axis=1), prf=prf or None)
    except ValueError as exc:
        raise PICMUSError(f"/{PICMUS_GROUP}: {exc}") from exc
    return [
        Acquisition(
            rf=rf,
            fs=fs_rf,
            t0=float(t_init.min()),
            c0=c0,
            probe=probe,
            sequence=seq,
            frame_index=int(n_idx[i]) if isinstance(n_idx, list) and len(n_idx) == n_frames else i,
            timestamp=float(stamps[i]) if isinstance(stamps, list) and len(stamps) == n_frames else 0.0,
            truth=dict(truths[i]) if isinstance(truths[i], dict) else {},
        )
        for i, rf in enumerate(rfs)
    ]


def write_picmus(
    path: PathLike,
    frames: Sequence[Acquisition] | Acquisition,
    *,
    modulation_frequency: float = 0.0,
    decimation: int = 1,
) -> None:
    """Write frames of one linear-array set-up in PICMUS's layout (a new file).

    modulation_frequency 0: RF in ``data/real``, zeros in ``data/imag`` (as the challenge's RF files);
    f_m > 0: IQ (fpcore.io.iq.rf_to_iq, USTB's convention) decimated by ``decimation``.
    """
    seq = [frames] if isinstance(frames, Acquisition) else list(frames)
    if not seq:
        raise PICMUSError("frames: expected at least one Acquisition, got none")
    ref = seq[0]
    sines = ref.sequence.sines
    if np.any(sines[:, 1] != 0) or np.any(ref.probe.positions[:, 1:] != 0):
        raise PICMUSError(
            "frames: expected a linear array on the x axis with in-plane plane waves (PICMUS stores one angle "
            "per wave and x–z geometry), got a 3-D set-up; write UFF instead"
        )
    for i, fr in enumerate(seq[1:], 1):
        if fr.rf.shape != ref.rf.shape or (fr.fs, fr.t0, fr.c0) != (ref.fs, ref.t0, ref.c0):
            raise PICMUSError(f"frames[{i}]: expected the set-up of frames[0] (shape, fs, t0, c0)")
    if not modulation_frequency >= 0 or int(decimation) < 1:
        raise PICMUSError(
            f"modulation_frequency/decimation: expected f_m >= 0 and an integer >= 1, got "
            f"{modulation_frequency}, {decimation}"
        )
    data = np.stack([np.asarray(fr.rf, dtype=np.float32).transpose(1, 0, 2) for fr in seq])  # (F, A, C, S)
    fs = ref.fs
    if modulation_frequency > 0:
        iq, fs = rf_to_iq(data, ref.fs, ref.t0, modulation_frequency, int(decimation))
        real, imag = iq.real.astype(np.float32), iq.imag.astype(np.float32)
    else:
        real, imag = data, np.zeros_like(data)
    if len(seq) == 1:
        real, imag = real[0], imag[0]
    p = ref.probe
    meta = {
        "writer": "fingerprint fpcore.io.picmus",
        "probe": {"pitch": p.pitch, "centre_frequency": p.centre_frequency, "bandwidth": p.bandwidth},
        "frame_index": [int(fr.frame_index) for fr in seq],
        "timestamp": [float(fr.timestamp) for fr in seq],
    }
    with h5py.File(path, "w") as f:
        g = f.create_group(PICMUS_GROUP)
        d = g.create_group("data")
        d.create_dataset("real", data=real)
        d.create_dataset("imag", data=imag)
        g.create_dataset("angles", data=np.arcsin(sines[:, 0]))  # float64 (the challenge used float32)
        g.create_dataset("probe_geometry", data=p.positions.T)
        for key, value in (
            ("sampling_frequency", fs),
            ("modulation_frequency", modulation_frequency),
            ("initial_time", ref.t0),
            ("sound_speed", ref.c0),
        ):
            g.create_dataset(key, data=np.array([value], dtype=np.float64))
        if ref.sequence.prf is not None:
            g.create_dataset("PRF", data=np.array([ref.sequence.prf]))
        g.attrs[META_ATTR] = json.dumps(meta)
        g.attrs[TRUTH_ATTR] = json.dumps([dict(fr.truth) for fr in seq])
