"""Which channel-data format a file is in, and one reader for all (UFF, PICMUS, MATLAB v7.3 holding either).

* UFF (USTB): an HDF5 file whose root holds a group with attribute ``class = uff.channel_data``;
* PICMUS: an HDF5 file with ``/US/US_DATASET0000/data`` (fpcore/io/picmus.py);
* ``.mat``: a MATLAB v7.3 file *is* HDF5 (with a 512-byte user block), so one that holds either layout
  is read as such; anything else — a v5/v6/v7 ``.mat`` (not HDF5), a v7.3 file of plain variables or of
  MATLAB objects saved with ``save`` (opaque outside MATLAB) — gets one line saying what was found and
  how to export it (USTB: ``channel_data.write(uff('data.uff'), 'channel_data')``).
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py

from fpcore.acquisition import Acquisition

__all__ = ["FormatError", "detect_format", "read_channel_data"]

PathLike = str | os.PathLike[str]

_EXPORT = "in MATLAB, write it with USTB as UFF: channel_data.write(uff('data.uff'), 'channel_data')"


class FormatError(ValueError):
    """A file in no channel-data format we read: the message says what was found."""


def _matlab_header(path: Path) -> str:
    with open(path, "rb") as fh:
        head = fh.read(128)
    return head[:116].decode("latin-1", errors="replace").split("\x00")[0].strip() if head.startswith(b"MATLAB") else ""


def _matlab_class(node: h5py.HLObject) -> str:
    cls = node.attrs.get("MATLAB_class")
    return cls.decode() if isinstance(cls, bytes) else (str(cls) if cls is not None else type(node).__name__)


def _variables(f: h5py.File) -> str:
    out = []
    for k, v in f.items():
        if k.startswith("#"):  # MATLAB's internal #refs# / #subsystem# groups
            continue
        out.append(f"{k} ({_matlab_class(v)})")
    return ", ".join(out[:8]) + (" …" if len(out) > 8 else "") if out else "no variables"


def detect_format(path: PathLike) -> str:
    """``"uff"`` or ``"picmus"``; raises :class:`FormatError` with what the file is otherwise."""
    from fpcore.io.picmus import PICMUS_GROUP, is_picmus
    from fpcore.io.uff import _datasets

    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: expected an existing UFF, PICMUS or MATLAB v7.3 file, found none")
    header = _matlab_header(p)
    if not h5py.is_hdf5(p):
        if header:
            raise FormatError(
                f"{p}: a MATLAB .mat file that is not HDF5 ({header[:40]!r}: v5/v7 format); expected UFF or "
                f"PICMUS channel data: save it with `save -v7.3` in USTB's layout, or {_EXPORT}"
            )
        with open(p, "rb") as fh:
            magic = fh.read(8)
        raise FormatError(
            f"{p}: expected an HDF5 file (UFF, PICMUS or MATLAB v7.3), found another format (first bytes {magic!r})"
        )
    with h5py.File(p, "r") as f:
        if _datasets(f):
            return "uff"
        if is_picmus(f):
            return "picmus"
        if header:
            objects = [k for k, v in f.items() if _matlab_class(v).startswith("uff.")]
            what = (
                f"MATLAB object(s) {objects} saved with `save` (opaque outside MATLAB)"
                if objects
                else f"variables {_variables(f)}"
            )
            raise FormatError(
                f"{p}: a MATLAB v7.3 file holding {what}, none in USTB's UFF layout (a group with class "
                f"uff.channel_data) or PICMUS's (/{PICMUS_GROUP}); {_EXPORT}"
            )
        raise FormatError(
            f"{p}: expected a uff.channel_data group (UFF) or /{PICMUS_GROUP} (PICMUS) in this HDF5 file, "
            f"found root {list(f.keys())[:8]}"
        )


def read_channel_data(path: PathLike, dataset: str | None = None) -> list[Acquisition]:
    """Frames of a UFF or PICMUS file (RF or IQ; a MATLAB v7.3 file holding either), one per frame."""
    from fpcore.io.picmus import read_picmus
    from fpcore.io.uff import read_uff

    kind = detect_format(path)
    return read_uff(path, dataset) if kind == "uff" else read_picmus(path)
