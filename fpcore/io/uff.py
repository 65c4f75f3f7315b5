"""UFF (USTB's HDF5 ultrasound file format): plane-wave channel data in and out.

Reads files written by USTB (MATLAB, ``uff.write_object``) and by pyuff-ustb, one
:class:`~fpcore.acquisition.Acquisition` per frame, and writes files that both read back. The reader
and the writer stay in this one file with the layout below: each mirrors the other field by field, and
a change to one half is a change to the other.

Layout written (h5py view; every UFF node carries the string attributes ``class`` and ``name``)::

    /                      attr version = "v1.2.0" (fixed-length string, 1-element array, as
                           MATLAB's hdf5write stores it; USTB's reader refuses files without it)
    /<name>                uff.channel_data; attrs size=[1,1], array=0,
                           fp_metadata (JSON: probe pitch/band, sines, frame indices, timestamps),
                           fp_truth (JSON list, one truth dict per frame) -- USTB ignores both
      sampling_frequency   (1,1) float64, class "double", attrs complex=0, imaginary=0
      initial_time         (1,1) t0 [s]
      sound_speed          (1,1) c0 [m/s]
      modulation_frequency (1,1) 0 (RF); on reading, f_m > 0 with complex data (a group data/real +
                           data/imag, as USTB writes complex arrays) is IQ, converted to RF
                           (fpcore/io/iq.py)
      data                 (N_frames, N_waves, N_channels, N_samples): MATLAB's column-major
                           [time x channel x wave x frame] as h5py (row-major) sees it
      probe                uff.linear_array (N, pitch, element_width, element_height, geometry)
                           when the elements sit where USTB's linear_array puts them, else
                           uff.probe (geometry only); geometry (7, N_u) = MATLAB's [N_u x 7]
                           rows x, y, z, theta, phi, width, height
      pulse                uff.pulse: center_frequency, fractional_bandwidth, phase
      sequence             uff.wave array (attrs size=[1,N], array=1) of sequence_0001, ...
                           (a single wave is written in place, as USTB does); each has
                           wavefront (uff.wavefront, 0 = plane), source (uff.point: distance=Inf,
                           azimuth, elevation [rad]), delay = 0 [s], sound_speed = c0

Conventions:

* **Angles.** A plane wave's direction is USTB's point at infinity: unit vector
  (sin az cos el, sin el, cos az cos el), as in USTB's DAS beamformer. Hence
  s_x = sin(azimuth) cos(elevation), s_y = sin(elevation) and back
  azimuth = atan2(s_x, c), elevation = asin(s_y), c = sqrt(1 - s_x^2 - s_y^2). In 2D (s_y = 0)
  this is simply s_x = sin(azimuth). (USTB's ``uff.wave.delay_values`` helper uses sin(az) for x
  without the cos(el) factor; the beamformer, which we follow, is exact.)
* **Time zero.** USTB: channel sample k of wave n is at channel time initial_time + k/fs, and an
  echo with path time T (T = 0 when the plane wavefront crosses the origin) appears at channel
  time T - delay_n. Ours: sample k at t0 + k/fs with the same time zero. So
  t0 = initial_time + delay_n. We write delay_n = 0, initial_time = t0. On reading, unequal
  per-wave delays are aligned onto t0 = initial_time + min(delay) by a band-limited (Fourier)
  shift; the record is lengthened by the spread so nothing is cut (integer-sample shifts are
  exact copies).
* **Axis order.** h5py sees (frame, wave, channel, time); each Acquisition's rf is
  (N_u, N_theta, N_t) = data[frame].transpose(1, 0, 2). MATLAB drops trailing singleton
  dimensions, so 3-D (wave, channel, time) and 2-D (channel, time) data mean one frame/one wave.
* **Element order.** USTB's matrix_array recomputes a y-fastest geometry from N_x/N_y/pitch when
  read in MATLAB; our matrix probes are x-fastest, so they are written as a generic uff.probe with
  an explicit geometry (the channel order is always the geometry's order).
* **Probe band.** Taken from fp_metadata, else from uff.pulse (bandwidth =
  fractional_bandwidth x center_frequency), else estimated from the data's mean power spectrum
  (-6 dB band). The pitch comes from fp_metadata, linear_array.pitch / matrix_array.pitch_x, or
  the smallest element spacing.
* **Timestamps.** From fp_metadata; otherwise frame i gets timestamp i N_waves / PRF when the file
  has a PRF (frames assumed back to back), else 0.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np
import scipy.fft as sfft

from fpcore import budget
from fpcore.acquisition import Acquisition, PlaneWaveSequence, Probe
from fpcore.geometry import cosines
from fpcore.io.iq import iq_to_rf, rf_upsampling
from fpcore.truth import Truth

__all__ = [
    "UFFError",
    "UFF_VERSION",
    "read_uff",
    "write_uff",
    "list_uff_datasets",
    "read_uff_json",
    "write_uff_json",
    "sines_to_angles",
    "angles_to_sines",
]

UFF_VERSION = "v1.2.0"
META_ATTR = "fp_metadata"
TRUTH_ATTR = "fp_truth"
_WAVEFRONTS = {0: "plane", 1: "spherical", 2: "photoacoustic"}

PathLike = str | os.PathLike[str]


class UFFError(ValueError):
    """Bad UFF input: the message names the field and the expected value."""


# ----------------------------------------------------------------------------------------------
# Angles


def sines_to_angles(sines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Direction sines (N, 2) -> USTB (azimuth, elevation) in radians (see module docs)."""
    s = np.asarray(sines, dtype=np.float64).reshape(-1, 2)
    c = cosines(s)
    return np.arctan2(s[:, 0], c), np.arcsin(s[:, 1])


def angles_to_sines(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """USTB (azimuth, elevation) in radians -> direction sines (N, 2)."""
    az = np.atleast_1d(np.asarray(azimuth, dtype=np.float64))
    el = np.atleast_1d(np.asarray(elevation, dtype=np.float64))
    return np.stack([np.sin(az) * np.cos(el), np.sin(el)], axis=1)


# ----------------------------------------------------------------------------------------------
# JSON helpers


def _jsonable(value: Any, field: str) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v, f"{field}.{k}") for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist(), field)
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, f"{field}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise UFFError(
        f"{field}: expected JSON-able values (numbers, strings, lists, dicts, arrays), got {type(value).__name__}"
    )


def _dumps(value: Any, field: str) -> str:
    return json.dumps(_jsonable(value, field), allow_nan=True)


def write_uff_json(path: PathLike, key: str, value: Any, dataset: str = "channel_data") -> None:
    """Store a small JSON-able value as the string attribute ``key`` of a dataset group.

    USTB and pyuff-ustb ignore such attributes, so the file stays a valid UFF file.
    """
    text = _dumps(value, key)
    with h5py.File(path, "a") as f:
        if dataset not in f:
            raise UFFError(f"dataset: expected one of {_datasets(f)}, got {dataset!r}")
        f[dataset].attrs[key] = text


def read_uff_json(path: PathLike, key: str, dataset: str | None = None) -> Any:
    """Read back a value stored by :func:`write_uff_json` (None if the attribute is absent)."""
    with h5py.File(path, "r") as f:
        name = _choose_dataset(f, dataset)
        return _load_json_attr(f[name], key, name)


# ----------------------------------------------------------------------------------------------
# Low-level HDF5 writing in USTB's layout


def _str_attr(obj: h5py.HLObject, key: str, text: str) -> None:
    """Fixed-length ASCII string attribute, scalar, exact length (as MATLAB's h5writeatt)."""
    obj.attrs[key] = np.bytes_(text.encode("ascii") or b" ")


def _version_attr(f: h5py.File) -> None:
    """Root ``version``: 1-element fixed-length null-terminated string, like MATLAB's hdf5write."""
    raw = UFF_VERSION.encode("ascii")
    tid = h5py.h5t.C_S1.copy()
    tid.set_size(len(raw) + 1)
    tid.set_strpad(h5py.h5t.STR_NULLTERM)
    f.attrs.create("version", np.array([raw], dtype=f"S{len(raw) + 1}"), shape=(1,), dtype=h5py.Datatype(tid))


def _uff_group(parent: h5py.Group, key: str, cls: str, n: int = 1) -> h5py.Group:
    g = parent.create_group(key)
    _str_attr(g, "class", cls)
    _str_attr(g, "name", key)
    g.attrs["size"] = np.array([1.0, float(n)])
    g.attrs["array"] = np.array([1.0 if n > 1 else 0.0])
    return g


def _num(parent: h5py.Group, key: str, value: Any, **kwargs: Any) -> h5py.Dataset:
    arr = np.asarray(value)
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)  # MATLAB scalars are 1 x 1
    ds = parent.create_dataset(key, data=arr, **kwargs)
    cls = {np.dtype(np.float32): "single", np.dtype(np.int16): "int16"}.get(arr.dtype, "double")
    _str_attr(ds, "class", cls)
    _str_attr(ds, "name", key)
    ds.attrs["complex"] = np.array([0.0])
    ds.attrs["imaginary"] = np.array([0.0])
    return ds


def _is_ustb_linear(pos: np.ndarray, pitch: float) -> bool:
    """True if positions are exactly where USTB's uff.linear_array puts N elements of this pitch."""
    n = pos.shape[0]
    x = (np.arange(1, n + 1) - (n + 1) / 2) * pitch
    return bool(np.allclose(pos[:, 0], x, rtol=0, atol=1e-9 * pitch) and not np.any(pos[:, 1:]))


def _write_probe(cd: h5py.Group, probe: Probe) -> None:
    pos = probe.positions
    n = pos.shape[0]
    linear = _is_ustb_linear(pos, probe.pitch)
    width = probe.pitch
    height = 10.0 * probe.pitch if probe.is_linear else probe.pitch
    geometry = np.zeros((7, n))
    geometry[:3] = pos.T
    geometry[5] = width
    geometry[6] = height
    if linear:
        g = _uff_group(cd, "probe", "uff.linear_array")
        _num(g, "N", float(n))
        _num(g, "pitch", float(probe.pitch))
        _num(g, "element_width", width)
        _num(g, "element_height", height)
    else:
        g = _uff_group(cd, "probe", "uff.probe")
    _num(g, "geometry", geometry)


def _write_wave(parent: h5py.Group, key: str, az: float, el: float, c0: float) -> None:
    w = _uff_group(parent, key, "uff.wave")
    ds = w.create_dataset("wavefront", data=np.array([[0]], dtype=np.int32))
    _str_attr(ds, "class", "uff.wavefront")
    _str_attr(ds, "name", "wavefront")
    src = _uff_group(w, "source", "uff.point")
    _num(src, "distance", np.inf)
    _num(src, "azimuth", float(az))
    _num(src, "elevation", float(el))
    _num(w, "delay", 0.0)
    _num(w, "sound_speed", float(c0))


def _check_frames(frames: Sequence[Acquisition]) -> None:
    ref = frames[0]
    for i, fr in enumerate(frames):
        rf = np.asarray(fr.rf)
        if np.iscomplexobj(rf) or not np.issubdtype(rf.dtype, np.number):
            raise UFFError(f"frames[{i}].rf: expected real RF samples, got dtype {rf.dtype}")
        if not np.all(np.isfinite(rf)):
            raise UFFError(f"frames[{i}].rf: expected finite samples, found NaN or Inf")
        expected = (fr.probe.n_elements, fr.sequence.n_waves)
        if rf.ndim != 3 or rf.shape[:2] != expected:
            raise UFFError(
                f"frames[{i}].rf: expected shape (N_u={expected[0]}, N_theta={expected[1]}, N_t), got {rf.shape}"
            )
        if i == 0:
            continue
        checks: list[tuple[str, bool, Any]] = [
            ("rf.shape", rf.shape == ref.rf.shape, ref.rf.shape),
            ("rf.dtype", rf.dtype == ref.rf.dtype, ref.rf.dtype),
            ("fs", fr.fs == ref.fs, ref.fs),
            ("t0", fr.t0 == ref.t0, ref.t0),
            ("c0", fr.c0 == ref.c0, ref.c0),
            ("probe", _same_probe(fr.probe, ref.probe), "the probe of frames[0]"),
            ("sequence", np.array_equal(fr.sequence.sines, ref.sequence.sines), "the sequence of frames[0]"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise UFFError(
                    f"frames[{i}].{name}: expected {want} (all frames of a UFF dataset share one acquisition set-up)"
                )


def _same_probe(a: Probe, b: Probe) -> bool:
    return (
        np.array_equal(a.positions, b.positions)
        and a.pitch == b.pitch
        and a.centre_frequency == b.centre_frequency
        and a.bandwidth == b.bandwidth
    )


def write_uff(
    path: PathLike,
    frames: Sequence[Acquisition] | Acquisition,
    name: str = "channel_data",
    truth: Sequence[Mapping[str, Any] | Truth] | Mapping[str, Any] | Truth | None = None,
    *,
    mode: Literal["w", "a"] = "w",
    compression: Literal["gzip"] | None = None,
) -> None:
    """Write frames sharing one set-up as a UFF ``uff.channel_data`` dataset ``name``.

    truth: one JSON-able dict or `Truth` per frame (or one for all frames); default: each frame's truth.
    mode "w" creates the file, "a" adds a dataset to an existing UFF file (or creates it).
    """
    seq = [frames] if isinstance(frames, Acquisition) else list(frames)
    if not seq:
        raise UFFError("frames: expected at least one Acquisition, got none")
    if not all(isinstance(fr, Acquisition) for fr in seq):
        raise UFFError("frames: expected Acquisition objects")
    if not name or "/" in name:
        raise UFFError(f"name: expected a non-empty group name without '/', got {name!r}")
    _check_frames(seq)
    if truth is None:
        truths: list[Any] = [dict(fr.truth) for fr in seq]
    elif isinstance(truth, Truth):
        truths = [truth.to_dict()] * len(seq)
    elif isinstance(truth, Mapping):
        truths = [dict(truth)] * len(seq)
    else:
        truths = [t.to_dict() if isinstance(t, Truth) else t for t in truth]
        if len(truths) != len(seq):
            raise UFFError(f"truth: expected {len(seq)} dicts (one per frame), got {len(truths)}")
    ref = seq[0]
    probe = ref.probe
    sines = ref.sequence.sines
    meta = {
        "writer": "fingerprint fpcore.io.uff",
        "format": 1,
        "probe": {"pitch": probe.pitch, "centre_frequency": probe.centre_frequency, "bandwidth": probe.bandwidth},
        "sines": sines,
        "frame_index": [int(fr.frame_index) for fr in seq],
        "timestamp": [float(fr.timestamp) for fr in seq],
    }
    meta_text = _dumps(meta, "metadata")
    truth_text = _dumps(truths, "truth")

    data = np.stack([np.asarray(fr.rf) for fr in seq])  # (F, N_u, N_theta, N_t)
    if data.dtype not in (np.float32, np.float64, np.int16):
        data = data.astype(np.float32)
    data = np.ascontiguousarray(data.transpose(0, 2, 1, 3))  # (F, N_theta, N_u, N_t)
    az, el = sines_to_angles(sines)

    if mode not in ("w", "a"):
        raise UFFError(f"mode: expected 'w' or 'a', got {mode!r}")
    with h5py.File(path, mode) as f:
        version = f.attrs.get("version")
        if version is None:
            _version_attr(f)
        elif _text(version) != UFF_VERSION:
            raise UFFError(f"version: expected {UFF_VERSION} to append to, got {_text(version)!r}")
        if name in f:
            raise UFFError(f"name: dataset {name!r} already exists in {os.fspath(path)!r}")
        cd = _uff_group(f, name, "uff.channel_data")
        cd.attrs[META_ATTR] = meta_text
        cd.attrs[TRUTH_ATTR] = truth_text
        _num(cd, "sampling_frequency", float(ref.fs))
        _num(cd, "initial_time", float(ref.t0))
        _num(cd, "sound_speed", float(ref.c0))
        _num(cd, "modulation_frequency", 0.0)
        if ref.sequence.prf is not None:
            _num(cd, "PRF", float(ref.sequence.prf))
        kw: dict[str, Any] = {}
        if compression:
            kw = {"compression": compression, "chunks": (1, 1) + data.shape[2:]}
        _num(cd, "data", data, **kw)
        _write_probe(cd, probe)
        pulse = _uff_group(cd, "pulse", "uff.pulse")
        _num(pulse, "center_frequency", float(probe.centre_frequency))
        _num(pulse, "fractional_bandwidth", float(probe.bandwidth / probe.centre_frequency))
        _num(pulse, "phase", 0.0)
        if len(az) == 1:
            _write_wave(cd, "sequence", az[0], el[0], ref.c0)
        else:
            sq = _uff_group(cd, "sequence", "uff.wave", n=len(az))
            for i in range(len(az)):
                _write_wave(sq, f"sequence_{i + 1:04d}", az[i], el[i], ref.c0)


# ----------------------------------------------------------------------------------------------
# Reading


def _text(raw: Any) -> str:
    if isinstance(raw, np.ndarray):
        if raw.size == 0:
            return ""
        if raw.dtype.kind in "ui":  # MATLAB char datasets: uint16 codes
            return "".join(chr(int(c)) for c in raw.ravel() if c)
        raw = raw.ravel()[0]
    if isinstance(raw, (bytes, np.bytes_)):
        raw = bytes(raw).decode("utf-8", errors="replace")
    return str(raw).replace("\x00", "").strip()


def _cls(node: h5py.HLObject) -> str:
    raw = node.attrs.get("class")
    return "" if raw is None else _text(raw)


def _datasets(f: h5py.File) -> list[str]:
    return [k for k, v in f.items() if isinstance(v, h5py.Group) and _cls(v) == "uff.channel_data"]


def list_uff_datasets(path: PathLike) -> list[str]:
    """Names of the uff.channel_data datasets at the root of a UFF file."""
    with h5py.File(path, "r") as f:
        return _datasets(f)


def _choose_dataset(f: h5py.File, dataset: str | None) -> str:
    names = _datasets(f)
    if dataset is not None:
        key = dataset.strip("/")
        if key in f and isinstance(f[key], h5py.Group) and _cls(f[key]) == "uff.channel_data":
            return key
        raise UFFError(f"dataset: expected one of {names} (uff.channel_data groups), got {dataset!r}")
    if not names:
        raise UFFError(
            f"dataset: expected a uff.channel_data group at the file root, found none (root holds {list(f.keys())})"
        )
    if len(names) > 1:
        raise UFFError(f"dataset: the file holds several uff.channel_data datasets {names}; choose one with dataset=")
    return names[0]


def _node(group: h5py.Group, key: str, field: str, what: str) -> h5py.HLObject:
    if key not in group:
        raise UFFError(f"{field}: missing (expected {what})")
    return group[key]


def _array(group: h5py.Group, key: str, field: str, what: str) -> np.ndarray:
    node = _node(group, key, field, what)
    if isinstance(node, h5py.Group):
        if "real" in node:
            raise UFFError(f"{field}: expected real values ({what}), got complex")
        raise UFFError(f"{field}: expected a dataset ({what}), got a group")
    arr = np.asarray(node[()])
    if arr.dtype.kind not in "fiub":
        raise UFFError(f"{field}: expected numbers ({what}), got dtype {arr.dtype}")
    return arr


def _scalar(group: h5py.Group, key: str, field: str, what: str, default: float | None = None) -> float:
    if default is not None and key not in group:
        return default
    arr = _array(group, key, field, what)
    if arr.size != 1:
        raise UFFError(f"{field}: expected a scalar ({what}), got shape {arr.shape}")
    value = float(arr.ravel()[0])
    if math.isnan(value):
        raise UFFError(f"{field}: expected a number ({what}), got NaN")
    return value


def _items(node: h5py.Group, cls: str) -> list[h5py.Group]:
    """A UFF object array (children name_0001, ...) or a single object stored in place."""
    kids = [(k, v) for k, v in node.items() if isinstance(v, h5py.Group) and _cls(v) == cls]
    array_flag = node.attrs.get("array")
    is_array = bool(np.ravel(array_flag)[0]) if array_flag is not None else False
    if kids and (is_array or not any(k in node for k in ("source", "wavefront", "geometry"))):

        def order(kv: tuple[str, h5py.Group]) -> tuple[int, str]:
            m = re.search(r"(\d+)$", kv[0])
            return (int(m.group(1)) if m else 0, kv[0])

        return [v for _, v in sorted(kids, key=order)]
    return [node]


def _read_probe(cd: h5py.Group, field: str) -> tuple[np.ndarray, float | None]:
    pr = _node(cd, "probe", field, "a uff.probe group with a geometry")
    if not isinstance(pr, h5py.Group):
        raise UFFError(f"{field}: expected a uff.probe group, got a dataset")
    cls = _cls(pr)
    pitch: float | None = None
    if cls == "uff.linear_array":
        if "pitch" in pr:
            pitch = _scalar(pr, "pitch", f"{field}/pitch", "element pitch in m")
    elif cls == "uff.matrix_array":
        if "pitch_x" in pr:
            pitch = _scalar(pr, "pitch_x", f"{field}/pitch_x", "element pitch in m")
    if "geometry" in pr:
        geo = _array(pr, "geometry", f"{field}/geometry", "MATLAB [N x 7] = h5py (7, N)")
        if geo.ndim != 2 or not 3 <= geo.shape[0] <= 7:
            hint = " (stored row-major? transpose it)" if geo.ndim == 2 and 3 <= geo.shape[1] <= 7 else ""
            raise UFFError(
                f"{field}/geometry: expected h5py shape (7, N_elements) (MATLAB "
                f"[N x 7]: x y z theta phi width height), got {geo.shape}{hint}"
            )
        return np.ascontiguousarray(geo[:3].T, dtype=np.float64), pitch
    if cls == "uff.linear_array":
        n = int(_scalar(pr, "N", f"{field}/N", "number of elements"))
        p = _scalar(pr, "pitch", f"{field}/pitch", "element pitch in m")
        x = (np.arange(1, n + 1) - (n + 1) / 2) * p
        return np.stack([x, np.zeros(n), np.zeros(n)], axis=1), p
    if cls == "uff.matrix_array":
        nx = int(_scalar(pr, "N_x", f"{field}/N_x", "elements along x"))
        ny = int(_scalar(pr, "N_y", f"{field}/N_y", "elements along y"))
        px = _scalar(pr, "pitch_x", f"{field}/pitch_x", "pitch along x in m")
        py = _scalar(pr, "pitch_y", f"{field}/pitch_y", "pitch along y in m")
        x0 = (np.arange(nx) - (nx - 1) / 2) * px
        y0 = (np.arange(ny) - (ny - 1) / 2) * py
        xx, yy = np.meshgrid(x0, y0, indexing="ij")  # USTB: X(:) of meshgrid(x0, y0) -> y fastest
        return np.stack([xx.ravel(), yy.ravel(), np.zeros(nx * ny)], axis=1), px
    raise UFFError(f"{field}/geometry: missing (expected the element geometry, h5py shape (7, N))")


def _read_sequence(cd: h5py.Group, field: str, c0: float) -> tuple[np.ndarray, np.ndarray]:
    """(sines (N, 2), delays (N,)) of the plane-wave sequence."""
    sq = _node(cd, "sequence", field, "a uff.wave group or array of plane waves")
    if not isinstance(sq, h5py.Group):
        raise UFFError(f"{field}: expected a uff.wave group, got a dataset")
    waves = _items(sq, "uff.wave")
    az, el, delay = [], [], []
    for i, w in enumerate(waves):
        wf_field = f"{field}[{i}]"
        wavefront = 1  # USTB's default: spherical (a spherical wave from infinity is plane)
        if "wavefront" in w:
            value = _scalar(w, "wavefront", f"{wf_field}/wavefront", "0 = plane")
            if not math.isfinite(value):
                raise UFFError(f"{wf_field}/wavefront: expected plane (0), got {value}")
            wavefront = int(round(value))
        if wavefront not in (0, 1):
            raise UFFError(
                f"{wf_field}/wavefront: expected plane (0), got {_WAVEFRONTS.get(wavefront, wavefront)} ({wavefront})"
            )
        src = _node(w, "source", f"{wf_field}/source", "a uff.point with the wave direction")
        dist = _scalar(src, "distance", f"{wf_field}/source/distance", "Inf", default=0.0)
        if wavefront == 1 and not math.isinf(dist):
            a0 = _scalar(src, "azimuth", f"{wf_field}/source/azimuth", "rad", default=0.0)
            e0 = _scalar(src, "elevation", f"{wf_field}/source/elevation", "rad", default=0.0)
            kind = "focused" if dist * math.cos(a0) * math.cos(e0) > 0 else "diverging"
            raise UFFError(
                f"{wf_field}/source/distance: expected Inf (plane wave), got {dist:g} m "
                f"({kind} wave); only plane waves are supported"
            )
        a = _scalar(src, "azimuth", f"{wf_field}/source/azimuth", "angle in rad", default=0.0)
        e = _scalar(src, "elevation", f"{wf_field}/source/elevation", "angle in rad", default=0.0)
        if not (math.cos(a) * math.cos(e) > 0):
            raise UFFError(
                f"{wf_field}/source/azimuth: expected a wave travelling into z > 0 "
                f"(|azimuth|, |elevation| < 90 deg), got ({a:g}, {e:g}) rad"
            )
        if "sound_speed" in w:
            cw = _scalar(w, "sound_speed", f"{wf_field}/sound_speed", "m/s")
            if not math.isclose(cw, c0, rel_tol=1e-6):
                raise UFFError(
                    f"{wf_field}/sound_speed: expected the channel_data sound_speed "
                    f"{c0:g} m/s (one c0 per acquisition), got {cw:g} m/s"
                )
        az.append(a)
        el.append(e)
        delay.append(_scalar(w, "delay", f"{wf_field}/delay", "s", default=0.0))
    return angles_to_sines(np.array(az), np.array(el)), np.array(delay)


def _estimate_band(rf: np.ndarray, fs: float) -> tuple[float, float]:
    """(-6 dB centre, width) of the mean power spectrum of a few traces."""
    traces = rf.reshape(-1, rf.shape[-1])
    step = max(1, traces.shape[0] // 256)
    spec = np.mean(np.abs(sfft.rfft(traces[::step].astype(np.float64), axis=-1)) ** 2, axis=0)
    freqs = np.fft.rfftfreq(rf.shape[-1], 1.0 / fs)
    spec[0] = 0.0
    k = int(np.argmax(spec))
    if spec[k] <= 0:
        return fs / 4, fs / 4
    above = spec >= spec[k] / 4  # -6 dB in amplitude
    lo = k
    while lo > 0 and above[lo - 1]:
        lo -= 1
    hi = k
    while hi < len(spec) - 1 and above[hi + 1]:
        hi += 1
    df = freqs[1] - freqs[0]
    return float(0.5 * (freqs[lo] + freqs[hi])), float(max(freqs[hi] - freqs[lo], df))


def _min_spacing(pos: np.ndarray) -> float | None:
    if pos.shape[0] < 2:
        return None
    from scipy.spatial import cKDTree

    d, _ = cKDTree(pos).query(pos, k=2)
    spacing = d[:, 1][d[:, 1] > 0]
    return float(spacing.min()) if spacing.size else None


def _data_nodes(cd: h5py.Group, name: str, fmod: float) -> tuple[h5py.Dataset, h5py.Dataset | None]:
    """(samples, imaginary part or None) of ``data``: real RF, or IQ as USTB writes complex arrays (a group
    ``data`` with datasets ``real`` and ``imag``, attribute complex = 1) or as a native complex dataset."""
    dnode = _node(cd, "data", f"{name}/data", "the channel data")
    inode = None
    if isinstance(dnode, h5py.Group):
        if not ("real" in dnode and "imag" in dnode):
            raise UFFError(
                f"{name}/data: expected a dataset (RF) or a group with real and imag datasets (IQ), "
                f"got a group holding {list(dnode.keys())}"
            )
        dnode, inode = dnode["real"], dnode["imag"]
        if not (isinstance(dnode, h5py.Dataset) and isinstance(inode, h5py.Dataset)) or inode.shape != dnode.shape:
            raise UFFError(f"{name}/data: expected real and imag datasets of one shape, got {dnode} and {inode}")
    is_iq = inode is not None or dnode.dtype.kind == "c"
    if is_iq and fmod == 0:
        raise UFFError(f"{name}/data: complex (IQ) samples need modulation_frequency > 0 Hz, got 0 (RF)")
    if not is_iq and fmod > 0:
        raise UFFError(
            f"{name}/modulation_frequency: {fmod:g} Hz means IQ data, but {name}/data holds real samples "
            "(expected complex data or data/real + data/imag)"
        )
    if dnode.dtype.kind not in "fiuc" or (inode is not None and inode.dtype.kind not in "fiu"):
        raise UFFError(f"{name}/data: expected numbers, got dtype {dnode.dtype}")
    return dnode, inode


def _align(rf: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Delay wave n of rf (N_u, N_theta, N_t) by shifts[n] >= 0 samples onto a longer axis."""
    n_u, n_w, n_t = rf.shape
    n_out = n_t + int(math.ceil(shifts.max() - 1e-9))
    out_dtype = rf.dtype if np.issubdtype(rf.dtype, np.floating) else np.float32
    out = np.zeros((n_u, n_w, n_out), dtype=out_dtype)
    integer = np.abs(shifts - np.round(shifts)) < 1e-6
    for w in np.nonzero(integer)[0]:
        s = int(round(shifts[w]))
        out[:, w, s : s + n_t] = rf[:, w]
    frac = np.nonzero(~integer)[0]
    if frac.size:
        n_fft = sfft.next_fast_len(n_out + 1, real=True)
        spec = sfft.rfft(rf[:, frac].astype(np.float64), n=n_fft, axis=-1)
        f = np.fft.rfftfreq(n_fft)  # cycles per sample
        spec *= np.exp(-2j * np.pi * f[None, None, :] * shifts[frac][None, :, None])
        out[:, frac] = sfft.irfft(spec, n=n_fft, axis=-1)[..., :n_out].astype(out_dtype)
    return out


def read_uff(
    path: PathLike,
    dataset: str | None = None,
    *,
    frames: Sequence[int] | slice | None = None,
) -> list[Acquisition]:
    """Read a UFF uff.channel_data dataset of plane-wave RF data: one Acquisition per frame.

    dataset: name of the uff.channel_data group (needed when the file holds several).
    frames: indices or slice of the frames to read (default: all).

    Bad input raises a ValueError that names the file or field: :class:`UFFError`, ``fpcore.budget.BudgetError``
    (declared sizes beyond the memory budget) or ``fpcore.io.formats.FormatError`` (another format); what
    h5py raises on a damaged HDF5 file (OSError, KeyError, ValueError, RuntimeError) is turned into a UFFError
    naming the file, with the cause chained.
    """
    from fpcore.io.formats import FormatError

    try:
        return _read_uff(path, dataset, frames)
    except (UFFError, budget.BudgetError, FormatError, MemoryError):
        raise
    except (OSError, KeyError, ValueError, RuntimeError) as exc:  # h5py/HDF5 on a damaged file (our own bugs,
        # TypeError, NameError, AttributeError, ..., are not caught: the fuzz tests would see them)
        raise UFFError(f"{path}: expected a readable UFF (HDF5) file, got {type(exc).__name__}: {exc}") from exc


def _read_uff(path: PathLike, dataset: str | None, frames: Sequence[int] | slice | None) -> list[Acquisition]:
    if not Path(path).is_file():
        raise UFFError(f"{path}: expected an existing UFF (HDF5) file, found none")
    if dataset is None and _detect(path) == "picmus":
        from fpcore.io.picmus import read_picmus

        acqs = read_picmus(path)
        return acqs if frames is None else (acqs[frames] if isinstance(frames, slice) else [acqs[i] for i in frames])
    with _open_hdf5(path) as f:
        name = _choose_dataset(f, dataset)
        cd = f[name]
        fs = _scalar(cd, "sampling_frequency", f"{name}/sampling_frequency", "Hz")
        t_init = _scalar(cd, "initial_time", f"{name}/initial_time", "time of the first sample, s")
        c0 = _scalar(cd, "sound_speed", f"{name}/sound_speed", "m/s")
        fmod = _scalar(cd, "modulation_frequency", f"{name}/modulation_frequency", "0 for RF", default=0.0)
        if not (fmod >= 0 and math.isfinite(fmod)):
            raise UFFError(f"{name}/modulation_frequency: expected 0 (RF) or a frequency > 0 Hz (IQ), got {fmod}")
        if not (fs > 0 and math.isfinite(fs)):
            raise UFFError(f"{name}/sampling_frequency: expected a positive frequency in Hz, got {fs}")
        fs_iq = fs
        fs = fs * rf_upsampling(fs, fmod)  # IQ becomes RF at this rate (fpcore/io/iq.py)
        if not (c0 > 0 and math.isfinite(c0)):
            raise UFFError(f"{name}/sound_speed: expected a positive speed in m/s, got {c0}")
        if not math.isfinite(t_init):
            raise UFFError(f"{name}/initial_time: expected a finite time in s, got {t_init}")
        positions, pitch = _read_probe(cd, f"{name}/probe")
        _check_positions(positions, f"{name}/probe/geometry")
        sines, delays = _read_sequence(cd, f"{name}/sequence", c0)
        n_u, n_w = positions.shape[0], sines.shape[0]

        dnode, inode = _data_nodes(cd, name, fmod)
        shape = dnode.shape
        full = (1,) * (4 - len(shape)) + tuple(shape) if 2 <= len(shape) <= 4 else None
        if full is None or full[1:3] != (n_w, n_u):
            hint = ""
            if (
                len(shape) >= 2
                and shape[1] == n_u
                and ((len(shape) == 2 and n_w == 1) or (len(shape) >= 3 and shape[2] == n_w))
            ):
                hint = " (axes look row-major [time, channel, wave, frame]: reverse them)"
            raise UFFError(
                f"{name}/data: expected h5py shape (N_frames, N_waves={n_w}, "
                f"N_channels={n_u}, N_samples) (MATLAB [time x channel x wave x frame]); "
                f"got {shape}: the channel axis must match the probe's {n_u} elements and "
                f"the wave axis the sequence's {n_w} waves{hint}"
            )
        n_frames = full[0]
        idx = list(range(n_frames))
        if frames is not None:
            try:
                idx = idx[frames] if isinstance(frames, slice) else [idx[int(i)] for i in frames]
            except IndexError as exc:
                raise UFFError(f"frames: expected indices below {n_frames}, got {frames}") from exc
        _check_declared(f"{name}/data", shape, n_frames, len(idx), np.dtype(dnode.dtype).itemsize, frames)

        meta = _load_json_attr(cd, META_ATTR, name)
        truths = _load_json_attr(cd, TRUTH_ATTR, name)
        if meta is not None and not isinstance(meta, dict):
            raise UFFError(f"{name}.attrs[{META_ATTR!r}]: expected a JSON object, got {type(meta).__name__}")
        meta = meta or {}
        if not isinstance(truths, list) or len(truths) != n_frames:
            truths = [{} for _ in range(n_frames)]
        _check_meta(meta, n_frames, f"{name}.attrs[{META_ATTR!r}]")
        _check_truths(truths, f"{name}.attrs[{TRUTH_ATTR!r}]")

        def per_frame(key: str) -> list[Any] | None:
            v = meta.get(key)
            return v if isinstance(v, list) and len(v) == n_frames else None

        frame_index = per_frame("frame_index") or list(range(n_frames))
        prf_key = "PRF" if "PRF" in cd else "prf"
        prf = _scalar(cd, prf_key, f"{name}/{prf_key}", "Hz", default=0.0)
        timestamps = per_frame("timestamp") or [i * n_w / prf if prf > 0 else 0.0 for i in range(n_frames)]
        msines = meta.get("sines")
        if msines is not None and np.shape(msines) == sines.shape and np.allclose(msines, sines, rtol=0, atol=1e-9):
            sines = np.asarray(msines, dtype=np.float64)  # exact values of our own writer

        if not np.all(np.isfinite(delays)):
            raise UFFError(f"{name}/sequence: expected finite wave delays in s, got {delays.tolist()}")
        shifts = (delays - delays.min()) * fs
        budget.check(
            f"{name}/sequence delays (spread {float(np.ptp(delays)):g} s = {float(shifts.max()):.3g} samples)",
            budget.array_bytes((len(idx), n_u, n_w, full[3] + float(shifts.max())), 4),
            "expected per-wave delays within the record",
        )
        t0 = t_init + float(delays.min())
        rfs = []
        for i in idx:
            raw = np.asarray(dnode[i] if len(shape) == 4 else dnode[()])
            if inode is not None:
                raw = raw + 1j * np.asarray(inode[i] if len(shape) == 4 else inode[()], dtype=np.float32)
            rf = np.ascontiguousarray(raw.reshape(n_w, n_u, -1).transpose(1, 0, 2))
            if not np.issubdtype(rf.dtype, np.inexact):
                rf = rf.astype(np.float32)
            if not np.all(np.isfinite(rf)):
                raise UFFError(f"{name}/data: expected finite RF samples, found NaN or Inf in frame {i}")
            try:
                budget.check_rf_amplitude(rf, f"{name}/data (frame {i})")
            except ValueError as exc:
                raise UFFError(str(exc)) from None
            if fmod > 0:
                rf, _ = iq_to_rf(rf, fs_iq, t_init, fmod)
            if np.any(shifts > 1e-6):
                rf = _align(rf, shifts)
            rfs.append((i, rf))

        mprobe = meta.get("probe")
        if not isinstance(mprobe, dict):
            mprobe = {}
        fc, bw = mprobe.get("centre_frequency"), mprobe.get("bandwidth")
        if not (fc and bw) and "pulse" in cd and isinstance(cd["pulse"], h5py.Group):
            pulse = cd["pulse"]
            pfc = _scalar(pulse, "center_frequency", f"{name}/pulse/center_frequency", "Hz", default=0.0)
            pbw = _scalar(
                pulse,
                "fractional_bandwidth",
                f"{name}/pulse/fractional_bandwidth",
                "fraction of the centre frequency",
                default=0.0,
            )
            if pfc > 0 and pbw > 0:
                fc, bw = pfc, pbw * pfc
        if not (fc and bw):
            sample = rfs[0][1] if rfs else np.asarray(dnode[0] if len(shape) == 4 else dnode[()])
            fc, bw = _estimate_band(sample, fs)
        pitch = mprobe.get("pitch") or pitch or _min_spacing(positions)
        if not pitch or pitch <= 0:
            raise UFFError(
                f"{name}/probe: expected a pitch (linear_array.pitch or several distinct element positions), found none"
            )

    try:
        probe = Probe(positions, float(pitch), float(fc), float(bw))
        sequence = PlaneWaveSequence(sines, prf=prf if prf > 0 else None)
    except ValueError as exc:
        raise UFFError(f"{name}: {exc}") from exc
    return [
        Acquisition(
            rf=rf,
            fs=fs,
            t0=t0,
            c0=c0,
            probe=probe,
            sequence=sequence,
            frame_index=int(frame_index[i]),
            timestamp=float(timestamps[i]),
            truth=dict(truths[i]) if isinstance(truths[i], dict) else {"value": truths[i]},
        )
        for i, rf in rfs
    ]


def _detect(path: PathLike) -> str:
    """``fpcore.io.formats.detect_format`` (not HDF5, .mat, PICMUS: read it or say what it is); an HDF5 file
    that cannot be opened (truncated, corrupt) is a UFFError naming the file."""
    from fpcore.io.formats import detect_format

    try:
        return detect_format(path)
    except OSError as exc:
        raise UFFError(f"{path}: expected a UFF (HDF5) file, could not read it ({exc})") from None


def _open_hdf5(path: PathLike) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except OSError as exc:  # not HDF5, truncated, corrupt
        raise UFFError(f"{path}: expected a UFF (HDF5) file, could not read it ({exc})") from None


def _check_positions(positions: np.ndarray, field: str) -> None:
    if positions.shape[0] < 1 or not np.all(np.isfinite(positions)):
        raise UFFError(f"{field}: expected finite element positions in m, found NaN or Inf")
    if positions.shape[0] > 1 and np.unique(np.round(positions, 12), axis=0).shape[0] < positions.shape[0]:
        raise UFFError(f"{field}: expected {positions.shape[0]} elements at distinct positions, found duplicates")


def _check_declared(field: str, shape: tuple[int, ...], n_frames: int, n_read: int, itemsize: int, frames: Any) -> None:
    """The declared data shape: frames and samples present, and the frames to read within the memory budget
    (a sparse file may declare terabytes it does not hold; fpcore.budget)."""
    if n_frames < 1:
        raise UFFError(f"{field}: expected at least one frame, the file declares shape {shape} (0 frames)")
    if shape[-1] < 2:
        raise UFFError(f"{field}: expected at least 2 time samples per trace, the file declares shape {shape}")
    if n_read < 1:
        raise UFFError(f"frames: the selection {frames} holds none of the file's {n_frames} frame(s)")
    per_frame = budget.array_bytes(shape[-3:] if len(shape) >= 3 else shape, max(itemsize, 4))
    # the samples as read, the float32 copy and its transposition
    budget.check(
        f"{field}: {n_read} frame(s) of declared shape {tuple(shape[-3:])}",
        3 * n_read * per_frame,
        "read fewer frames (--frames) or check the file's declared shape",
    )


def _finite_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_meta(meta: dict[str, Any], n_frames: int, field: str) -> None:
    """fp_metadata written by this module: numbers where numbers belong."""
    probe = meta.get("probe")
    if probe is not None:
        if not isinstance(probe, dict):
            raise UFFError(f"{field}.probe: expected a JSON object, got {type(probe).__name__}")
        for k in ("pitch", "centre_frequency", "bandwidth"):
            v = probe.get(k)
            if v is not None and not (_finite_number(v) and v > 0):
                raise UFFError(f"{field}.probe.{k}: expected a positive number, got {v!r:.80}")
    for k in ("timestamp", "frame_index"):
        v = meta.get(k)
        if not isinstance(v, list):
            continue
        for i, x in enumerate(v):
            ok = _finite_number(x) if k == "timestamp" else (isinstance(x, int) and not isinstance(x, bool) and x >= 0)
            if not ok:
                what = "a finite number in s" if k == "timestamp" else "an integer >= 0"
                raise UFFError(f"{field}.{k}[{i}]: expected {what}, got {x!r:.80}")
    s = meta.get("sines")
    if s is not None:
        arr = np.asarray(s, dtype=object)
        if not all(_finite_number(x) for x in arr.ravel()):
            raise UFFError(f"{field}.sines: expected finite numbers, got {str(s)[:80]}")


def _check_truths(truths: list[Any], field: str) -> None:
    """Each frame's truth: a JSON object without NaN or infinite numbers (e.g. 1e400)."""

    def bad(v: Any, path: str) -> str | None:
        if isinstance(v, float) and not math.isfinite(v):
            return f"{path}: expected a finite number, got {v}"
        if isinstance(v, dict):
            return next((b for k, x in v.items() if (b := bad(x, f"{path}.{k}"))), None)
        if isinstance(v, list):
            return next((b for i, x in enumerate(v) if (b := bad(x, f"{path}[{i}]"))), None)
        return None

    for i, t in enumerate(truths):
        problem = bad(t, f"{field}[{i}]")
        if problem:
            raise UFFError(problem)


def _load_json_attr(group: h5py.Group, key: str, name: str) -> Any:
    raw = group.attrs.get(key)
    if raw is None:
        return None
    try:
        return json.loads(_text(raw))
    except json.JSONDecodeError as exc:
        raise UFFError(f"{name}.attrs[{key!r}]: expected a JSON string ({exc})") from exc
