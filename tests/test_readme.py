"""The README's Python examples run as written (a user copies them)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_readme_has_a_library_example() -> None:
    assert BLOCKS and "fpcore.locate" in BLOCKS[0]


@pytest.mark.parametrize("code", BLOCKS)
def test_readme_python_block_runs(code: str, capsys) -> None:
    exec(compile(code, str(README), "exec"), {"__name__": "readme"})
    assert "PFA" in capsys.readouterr().out  # the example prints its detection
