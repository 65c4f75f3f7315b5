"""Generate the JSON Schemas of the wire headers into ``schemas/<SchemaName>.json``.

The schema describes the JSON header of each message as ``services.wire`` writes it (the MCAP
schema of the channel): array fields are strings naming a buffer, and ``arrays`` lists the buffer
descriptors. Each array field carries ``x-array`` (allowed dtypes, ndim, finiteness).

    python -m services.schemas_gen            # (re)write schemas/*.json
    python -m services.schemas_gen --check    # exit 1 if any file is missing, stale or extra
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from services.arrays import ArrayDescriptor
from services.messages import MESSAGE_TYPES, Message

__all__ = ["DEFAULT_DIR", "header_schema", "render", "stale", "write", "main"]

DEFAULT_DIR = Path(__file__).resolve().parent.parent / "schemas"
_DIALECT = "https://json-schema.org/draft/2020-12/schema"
_LAYOUT = (
    "Wire payload: b'FPWIRE01' | uint32 LE header length H | uint32 flags (0) | H bytes of this JSON "
    "header | zero padding to a multiple of 64 | little-endian C-order buffers at the 64-aligned "
    "offsets given in `arrays` (from the start of the data section). The header alone travels as "
    "the zenoh attachment."
)


def header_schema(cls: type[Message]) -> dict[str, Any]:
    """JSON Schema of the wire header of ``cls``."""
    schema = cls.model_json_schema(mode="validation")
    desc = ArrayDescriptor.model_json_schema(mode="validation")
    schema.setdefault("$defs", {})["ArrayDescriptor"] = desc
    schema["properties"]["arrays"] = {
        "description": "Descriptors of the array buffers that follow the header.",
        "items": {"$ref": "#/$defs/ArrayDescriptor"},
        "title": "Arrays",
        "type": "array",
    }
    major, minor = cls.version()
    return {
        "$schema": _DIALECT,
        "$id": f"fingerprint/{schema['title']}/{major}.{minor}",
        "x-wire": _LAYOUT,
        **schema,
    }


def render(cls: type[Message]) -> str:
    """Schema file text (stable formatting, trailing newline)."""
    return json.dumps(header_schema(cls), indent=2, ensure_ascii=False, sort_keys=True) + "\n"


def _expected() -> dict[str, str]:
    return {f"{name}.json": render(cls) for name, cls in MESSAGE_TYPES.items()}


def stale(directory: Path = DEFAULT_DIR) -> list[str]:
    """Problems found in ``directory``: missing, out-of-date or unexpected schema files."""
    expected = _expected()
    problems = []
    for fname, text in expected.items():
        path = directory / fname
        if not path.exists():
            problems.append(f"{fname}: missing")
        elif path.read_text(encoding="utf-8") != text:
            problems.append(f"{fname}: stale")
    problems += [
        f"{p.name}: not generated from a model" for p in sorted(directory.glob("*.json")) if p.name not in expected
    ]
    return problems


def write(directory: Path = DEFAULT_DIR) -> list[Path]:
    """Write every schema; remove files this generator wrote for messages that no longer exist."""
    directory.mkdir(parents=True, exist_ok=True)
    expected = _expected()
    for p in directory.glob("*.json"):
        if p.name not in expected and '"x-wire"' in p.read_text(encoding="utf-8", errors="replace"):
            p.unlink()
    paths = []
    for fname, text in expected.items():
        path = directory / fname
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.schemas_gen", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if schemas/ is not up to date")
    parser.add_argument("--dir", type=Path, default=DEFAULT_DIR, help=f"output folder (default {DEFAULT_DIR})")
    args = parser.parse_args(argv)
    if args.check:
        problems = stale(args.dir)
        for p in problems:
            print(p, file=sys.stderr)
        if problems:
            print("run: python -m services.schemas_gen", file=sys.stderr)
            return 1
        print(f"{len(MESSAGE_TYPES)} schemas up to date in {args.dir}")
        return 0
    for path in write(args.dir):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
