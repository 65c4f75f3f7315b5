"""`fp convert IN OUT`: channel data between PICMUS, UFF and our MCAP recordings (issue 14).

Formats by file: ``.mcap`` is a recording (its ``fp/<rig>/rf`` RFFrame messages, docs/wire.md); any other
input is detected from its content (``fpcore.io.detect_format``: UFF, PICMUS, a MATLAB v7.3 file holding
either); the output format follows OUT's extension: ``.uff`` (USTB), ``.hdf5``/``.h5`` (PICMUS layout),
``.mcap``. IQ input is converted to RF on reading (fpcore/io/iq.py); ``--modulation-frequency`` writes IQ
to PICMUS. A recording written here replays with ``fp publish --mcap OUT``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

__all__ = ["add_convert_parser", "read_frames", "run_convert", "write_frames"]

OUTPUTS = {".uff": "uff", ".hdf5": "picmus", ".h5": "picmus", ".mcap": "mcap"}


def read_frames(path: str | Path, dataset: str | None = None, rig: str | None = None) -> list[Any]:
    """Acquisitions of a UFF/PICMUS/.mat file, or the RF frames of an MCAP recording (one rig's, if given)."""
    from fpcore.io import read_channel_data

    p = Path(path)
    if p.suffix.lower() != ".mcap":
        return read_channel_data(p, dataset)
    from services.messages import RFFrame
    from services.sources import MCAPSource
    from services.wire import decode

    if not p.is_file():
        raise ValueError(f"{p}: expected an existing MCAP recording, found none")
    frames = []
    for item in MCAPSource(p, from_rig=rig):
        msg = decode(item.payload)
        if isinstance(msg, RFFrame):
            frames.append(msg.to_acquisition())
    if not frames:
        raise ValueError(f"{p}: expected RF frames (fp/<rig>/rf messages) in the recording, found none")
    return frames


def write_frames(frames: list[Any], path: str | Path, rig: str = "convert") -> None:
    """Write RF frames as one MCAP channel ``fp/<rig>/rf`` (FPWIRE01 payloads, RFFrame JSON Schema, zstd)."""
    from mcap.writer import CompressionType, Writer

    from services.messages import RFFrame
    from services.recording import MESSAGE_ENCODING
    from services.schemas_gen import render
    from services.topics import keys
    from services.wire import encode

    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="fingerprint services.cli.convert")
        w.add_metadata("fingerprint", {"wire": "FPWIRE01", "message_encoding": MESSAGE_ENCODING})
        sid = w.register_schema("RFFrame", "jsonschema", render(RFFrame).encode())
        key = keys(rig).rf
        cid = w.register_channel(key, MESSAGE_ENCODING, sid, {"key": key, "schema_name": "RFFrame"})
        for seq, acq in enumerate(frames):
            t_ns = int(round(acq.timestamp * 1e9))
            w.add_message(cid, t_ns, encode(RFFrame.from_acquisition(acq)), t_ns, seq)
        w.finish()


def run_convert(args: argparse.Namespace) -> int:
    from fpcore.io import write_picmus, write_uff

    src, dst = Path(args.input), Path(args.output)
    kind = OUTPUTS.get(dst.suffix.lower())
    if kind is None:
        raise ValueError(f"OUTPUT: expected a name ending in {', '.join(OUTPUTS)}, got {dst.name!r}")
    if src.resolve() == dst.resolve():
        raise ValueError(f"OUTPUT: expected a file other than the input, got {dst}")
    if args.modulation_frequency and kind != "picmus":
        raise ValueError(f"--modulation-frequency: IQ is written to PICMUS files (.hdf5) only, got {dst.name!r}")
    frames = read_frames(src, args.dataset, args.rig)
    dst.parent.mkdir(parents=True, exist_ok=True)
    if kind == "uff":
        write_uff(dst, frames)
    elif kind == "picmus":
        write_picmus(dst, frames, modulation_frequency=args.modulation_frequency, decimation=args.decimation)
    else:
        write_frames(frames, dst, rig=args.rig or "convert")
    a = frames[0]
    print(
        f"{dst}: {len(frames)} frame(s), {a.probe.n_elements} elements, {a.sequence.n_waves} plane waves, "
        f"{a.n_samples} samples at {a.fs / 1e6:g} MHz ({kind}"
        + (f", written as IQ at f_m = {args.modulation_frequency / 1e6:g} MHz)" if args.modulation_frequency else ")")
    )
    return 0


def add_convert_parser(sub: Any) -> argparse.ArgumentParser:
    """Register `fp convert`."""
    from services.units import parse_frequency

    p = sub.add_parser(
        "convert",
        help="convert channel data between PICMUS, UFF and MCAP",
        description="Plane-wave channel data between PICMUS (.hdf5), USTB UFF (.uff) and our MCAP "
        "recordings (.mcap). IQ input (modulation_frequency > 0) becomes RF.",
    )
    p.add_argument("input", help="UFF, PICMUS, MATLAB v7.3 (.mat holding either) or MCAP file")
    p.add_argument("output", help="output file: .uff, .hdf5/.h5 (PICMUS layout) or .mcap")
    p.add_argument("--dataset", help="UFF channel_data group to read (when the file holds several)")
    p.add_argument("--rig", help="MCAP: rig of the fp/<rig>/rf channel to read or write (default: any / 'convert')")
    p.add_argument(
        "--modulation-frequency",
        type=parse_frequency,
        default=0.0,
        help="PICMUS output: write IQ demodulated at this frequency (e.g. 5.2MHz; default 0: RF)",
    )
    p.add_argument("--decimation", type=int, default=1, help="PICMUS IQ output: keep every D-th sample (default 1)")
    p.set_defaults(func=run_convert)
    return p
