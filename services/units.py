"""Command-line quantities: lengths in metres by default, with an optional unit suffix (issue 7).

`parse_length("25mm") == 0.025`; `parse_position("0,25mm")` — when only the last component carries a
unit, it applies to all of them ("1,25mm" is 1 mm, 25 mm); `parse_band("1.8MHz:2.6MHz")`.
"""

from __future__ import annotations

import math
import re

__all__ = ["parse_length", "parse_position", "parse_frequency", "parse_band", "parse_range", "UnitError"]

_LENGTH = {"": 1.0, "m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
_FREQ = {"": 1.0, "hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}
_NUM = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zA-Zµ]*)\s*$")


class UnitError(ValueError):
    """A command-line quantity that cannot be read; the message names the option."""


def _split(text: str, option: str) -> tuple[float, str]:
    m = _NUM.match(text)
    if not m:
        raise UnitError(f"{option}: cannot read {text!r} (expected a number with an optional unit, e.g. 25mm)")
    value = float(m.group(1))
    if not math.isfinite(value):
        raise UnitError(f"{option}: expected a finite number, got {text!r}")
    return value, m.group(2)


def _finite(value: float, text: str, option: str) -> float:
    if not math.isfinite(value):
        raise UnitError(f"{option}: expected a finite quantity, got {text!r}")
    return value


def parse_length(text: str, option: str = "length") -> float:
    value, unit = _split(text, option)
    if unit not in _LENGTH:
        raise UnitError(f"{option}: unknown length unit {unit!r} in {text!r} (use m, cm, mm or um)")
    return _finite(value * _LENGTH[unit], text, option)


def parse_position(text: str, option: str = "position", n: tuple[int, ...] = (2, 3)) -> list[float]:
    parts = [p for p in text.split(",")]
    if len(parts) not in n:
        raise UnitError(f"{option}: expected {' or '.join(map(str, n))} comma-separated values, got {text!r}")
    units = [_split(p, option)[1] for p in parts]
    if units[-1] and not any(units[:-1]):
        parts = [p + units[-1] for p in parts[:-1]] + [parts[-1]]
    return [parse_length(p, option) for p in parts]


def parse_range(text: str, option: str) -> tuple[float, float]:
    """'a:b' lengths (a unit on b alone applies to both)."""
    parts = text.split(":")
    if len(parts) != 2:
        raise UnitError(f"{option}: expected 'start:stop', got {text!r}")
    a, b = parse_position(",".join(parts), option, n=(2,))
    if not b > a:
        raise UnitError(f"{option}: expected start < stop, got {text!r}")
    return a, b


def parse_frequency(text: str, option: str = "frequency") -> float:
    value, unit = _split(text, option)
    if unit.lower() not in _FREQ:
        raise UnitError(f"{option}: unknown frequency unit {unit!r} in {text!r} (use Hz, kHz or MHz)")
    return _finite(value * _FREQ[unit.lower()], text, option)


def parse_band(text: str, option: str = "--band") -> tuple[float, float]:
    parts = text.split(":")
    if len(parts) != 2:
        raise UnitError(f"{option}: expected 'f_min:f_max', e.g. 1.8MHz:2.6MHz, got {text!r}")
    u_last = _split(parts[1], option)[1]
    if u_last and not _split(parts[0], option)[1]:
        parts[0] += u_last
    lo, hi = parse_frequency(parts[0], option), parse_frequency(parts[1], option)
    if not 0 <= lo < hi:
        raise UnitError(f"{option}: expected 0 <= f_min < f_max, got {text!r}")
    return lo, hi
