"""schemas/*.json are generated from the message models and must be up to date."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from services import schemas_gen
from services.messages import MESSAGE_TYPES, examples
from services.wire import header_bytes


def test_checked_in_schemas_are_up_to_date() -> None:
    problems = schemas_gen.stale()
    assert not problems, f"{problems}: run `python -m services.schemas_gen`"


def test_check_cli_exit_codes(tmp_path: Path) -> None:
    ok = subprocess.run([sys.executable, "-m", "services.schemas_gen", "--check"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert schemas_gen.main(["--dir", str(tmp_path)]) == 0
    assert schemas_gen.main(["--check", "--dir", str(tmp_path)]) == 0
    target = tmp_path / "RFFrame.json"
    target.write_text(target.read_text().replace('"RFFrame"', '"RFFrameX"'))
    (tmp_path / "Status.json").unlink()
    (tmp_path / "Old.json").write_text('{"x-wire": "old"}')
    assert schemas_gen.stale(tmp_path) == [
        "RFFrame.json: stale",
        "Status.json: missing",
        "Old.json: not generated from a model",
    ]
    assert schemas_gen.main(["--check", "--dir", str(tmp_path)]) == 1
    schemas_gen.main(["--dir", str(tmp_path)])
    assert schemas_gen.stale(tmp_path) == []


def _resolve(schema: dict, node: dict) -> dict:
    ref = node.get("$ref")
    return schema["$defs"][ref.rsplit("/", 1)[1]] if ref else node


def _conforms(schema: dict, node: dict, value: object, names: set[str], path: str) -> None:
    """A small structural check of a header against its schema (objects, required keys, buffers)."""
    node = _resolve(schema, node)
    if "x-array" in node:
        assert isinstance(value, str) and value in names, f"{path}: {value!r} is not a described buffer"
        return
    if "anyOf" in node:
        if value is None:
            return
        node = _resolve(schema, next(n for n in node["anyOf"] if n.get("type") != "null"))
    if node.get("type") == "object" and "properties" in node:
        assert isinstance(value, dict), path
        assert set(node.get("required", [])) <= set(value), f"{path}: missing required"
        assert set(value) <= set(node["properties"]), f"{path}: keys outside the schema"
        for k, v in value.items():
            _conforms(schema, node["properties"][k], v, names, f"{path}.{k}")
    elif node.get("type") == "array" and "items" in node:
        for i, v in enumerate(value):  # type: ignore[arg-type]
            _conforms(schema, node["items"], v, names, f"{path}.{i}")


@pytest.mark.parametrize("kind", list(MESSAGE_TYPES))
def test_headers_conform_to_schema(kind: str) -> None:
    msg = examples()[kind]
    header = json.loads(header_bytes(msg))
    schema = json.loads((schemas_gen.DEFAULT_DIR / f"{msg.schema_name}.json").read_text())
    assert schema["title"] == msg.schema_name and "arrays" in schema["properties"]
    _conforms(schema, schema, header, {d["name"] for d in header["arrays"]}, msg.schema_name)


def test_headers_validate_with_jsonschema() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    for msg in examples().values():
        schema = json.loads((schemas_gen.DEFAULT_DIR / f"{msg.schema_name}.json").read_text())
        jsonschema.validate(json.loads(header_bytes(msg)), schema)


def test_array_fields_are_documented() -> None:
    rf = json.loads((schemas_gen.DEFAULT_DIR / "RFFrame.json").read_text())
    assert rf["properties"]["rf"]["x-array"] == {"dtype": ["<f4", "<i2"], "finite": True, "ndim": 3}
    assert set(MESSAGE_TYPES) == {p.stem for p in schemas_gen.DEFAULT_DIR.glob("*.json")}
