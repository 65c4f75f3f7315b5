"""``rerun-loader-fingerprint``: a Rerun external data loader, so that ``rerun recording.mcap`` opens our recordings
with the same entities and blueprint as `fp view` (``services.viewing.rerun_log``).

Rerun's protocol (rerun-sdk 0.41): the viewer runs every executable named ``rerun-loader-*`` on the ``PATH``
with the file as the positional argument and ``--recording-id``, ``--application-id``, ``--entity-path-prefix``,
``--static`` and time options; a loader writes its data as an RRD stream to standard output, or exits with
code 66 (``rr.EXTERNAL_DATA_LOADER_INCOMPATIBLE_EXIT_CODE``) for a file it does not know. This one takes MCAP
files that hold fingerprint bus channels (``fp/<rig>/…``) and leaves every other file to the other loaders
(Rerun's own MCAP loader still shows the raw channels next to ours).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["INCOMPATIBLE", "main", "is_fingerprint_recording"]

#: rr.EXTERNAL_DATA_LOADER_INCOMPATIBLE_EXIT_CODE
INCOMPATIBLE = 66


def is_fingerprint_recording(path: Path) -> bool:
    """An MCAP file with at least one fingerprint bus channel (fp/<rig>/… in fpwire or JSON)."""
    from services.recording import RecordingError, topic_counts

    if not path.is_file() or path.suffix.lower() != ".mcap":
        return False
    try:
        return any(k.startswith("fp/") for k in topic_counts(path))
    except (RecordingError, OSError):
        return False


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rerun-loader-fingerprint",
        description="Rerun external data loader for fingerprint MCAP recordings (run by `rerun FILE.mcap`): "
        "writes an RRD stream to standard output; exit 66 for other files.",
    )
    p.add_argument("filepath")
    p.add_argument("--application-id", help="application id the viewer recommends")
    p.add_argument("--opened-application-id", help="the viewer's currently opened application, if any")
    p.add_argument("--recording-id", help="recording id shared by every loader of this file")
    p.add_argument("--opened-recording-id", help="the viewer's currently opened recording, if any")
    p.add_argument("--entity-path-prefix", help="prefix for every entity path")
    p.add_argument("--static", action="store_true", help="log everything as static (ignored: the data is temporal)")
    for opt in ("--time", "--sequence", "--time_sequence", "--time_duration_nanos", "--time_timestamp_nanos"):
        p.add_argument(opt, action="append", help=argparse.SUPPRESS)
    return p


def main(argv: list[str] | None = None) -> int:
    args, _unknown = _parser().parse_known_args(argv)  # options of later viewers are ignored, not fatal
    path = Path(args.filepath)
    if not is_fingerprint_recording(path):
        return INCOMPATIBLE
    import rerun as rr

    from services.viewing.rerun_log import log_recording

    rec = rr.RecordingStream(args.application_id or "fingerprint", recording_id=args.recording_id or path.stem)
    rec.stdout()
    prefix = f"{args.entity_path_prefix.strip('/')}/" if args.entity_path_prefix else ""
    try:
        out = log_recording(path, rec, prefix=prefix)
    except (ValueError, OSError) as exc:
        print(f"rerun-loader-fingerprint: error: {exc}", file=sys.stderr)
        rec.flush()
        return 1
    rec.send_blueprint(out["blueprint"], make_active=True, make_default=True)
    rec.flush()
    rec.disconnect()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
