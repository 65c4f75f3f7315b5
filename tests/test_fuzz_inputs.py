"""Property-based fuzzing (hypothesis; issue 13.7) of the three doors bad input comes through: the unit parser
(``services.units``), the wire decoder (``services.wire``) and the UFF reader (``fpcore.io.uff``). Whatever
the input, each answers with a value or with the project's own error type — never another exception.
``bench/fuzz_inputs.py`` runs the same mutations at scale (≥ 10,000 inputs)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fpcore.budget import BudgetError
from fpcore.io import read_uff, write_uff
from fpcore.io.formats import FormatError
from fpcore.io.uff import UFFError
from services.messages import Message, examples
from services.units import UnitError, parse_band, parse_frequency, parse_length, parse_position, parse_range
from services.wire import WireError, decode, decode_header, encode

FAST = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SOME = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ------------------------------------------------------------------------------------------ unit parser
_pieces = st.sampled_from(
    ["", "-", "+", ".", "e", "E", "1", "0", "25", "1e308", "1e999", "nan", "inf", "mm", "m", "um", "µm", "cm", "MHz"]
    + ["kHz", "Hz", "GHz", ":", ",", " ", "x", "\x00", "٣", "1_0"]
)
_quantities = st.one_of(st.text(max_size=30), st.lists(_pieces, max_size=8).map("".join))


@FAST
@given(_quantities)
def test_unit_parser_returns_finite_values_or_a_unit_error(text: str) -> None:
    for parse in (
        lambda t: [parse_length(t, "--x")],
        lambda t: [parse_frequency(t, "--f")],
        lambda t: parse_position(t, "--r0"),
        lambda t: list(parse_range(t, "--z")),
        lambda t: list(parse_band(t, "--band")),
    ):
        try:
            values = parse(text)
        except UnitError as exc:
            assert str(exc).startswith("--"), exc  # the message names the option
            continue
        assert all(isinstance(v, float) and math.isfinite(v) for v in values), (text, values)


@FAST
@given(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e300, max_value=1e300))
def test_lengths_in_millimetres_round_trip(v: float) -> None:
    assert parse_length(f"{v!r}mm") == pytest.approx(v * 1e-3, rel=1e-12, abs=1e-300)


# ----------------------------------------------------------------------------------------- wire decoder
_PAYLOADS = {name: encode(msg) for name, msg in examples().items()}


@FAST
@given(st.sampled_from(sorted(_PAYLOADS)), st.data())
def test_wire_mutants_raise_only_wire_error(name: str, data: st.DataObject) -> None:
    raw = bytearray(_PAYLOADS[name])
    ops = data.draw(st.lists(st.sampled_from(["flip", "truncate", "insert", "header"]), min_size=1, max_size=3))
    for op in ops:
        if not raw:
            break
        if op == "flip":
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] = data.draw(st.integers(0, 255))
        elif op == "truncate":
            raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
        elif op == "insert":
            i = data.draw(st.integers(0, len(raw)))
            raw[i:i] = data.draw(st.binary(min_size=1, max_size=32))
        else:
            raw = bytearray(_header_mutant(bytes(raw), data))
    for payload in (bytes(raw), memoryview(bytes(raw)), bytearray(raw)):
        try:
            msg = decode(payload)
        except WireError as exc:
            assert exc.field and exc.problem
            continue
        assert isinstance(msg, Message)
    try:
        decode_header(bytes(raw), strict=False)
    except WireError:
        pass


def _header_mutant(raw: bytes, data: st.DataObject) -> bytes:
    """One header value replaced by arbitrary JSON (incl. 1e400-sized numbers), the payload re-assembled with
    its original data section; a payload whose header cannot be read is returned unchanged."""
    try:
        hlen = int.from_bytes(raw[8:12], "little")
        doc = json.loads(raw[16 : 16 + hlen])
        key = data.draw(st.sampled_from(sorted(doc)))
    except (ValueError, TypeError, AttributeError):
        return raw
    doc[key] = data.draw(
        st.recursive(
            st.none()
            | st.booleans()
            | st.integers(-(2**70), 2**70)
            | st.floats(allow_nan=False)
            | st.text(max_size=20)
            | st.just(math.inf),
            lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
            max_leaves=12,
        )
    )
    hdr = json.dumps(doc).replace("Infinity", "1e400").encode()
    body = raw[-(-(16 + hlen) // 64) * 64 :]
    head = raw[:8] + len(hdr).to_bytes(4, "little") + raw[12:16] + hdr
    return head + bytes(-(-len(head) // 64) * 64 - len(head)) + body


def test_wire_keeps_a_broken_truth_out_but_the_frame_in() -> None:
    raw = _PAYLOADS["RFFrame"]
    hlen = int.from_bytes(raw[8:12], "little")
    doc = json.loads(raw[16 : 16 + hlen])
    doc["truth"] = {"position_m": [0.0, 0.0, "@"]}
    hdr = json.dumps(doc).replace('"@"', "1e400").encode()
    head = raw[:8] + len(hdr).to_bytes(4, "little") + raw[12:16] + hdr
    msg = decode(head + bytes(-(-len(head) // 64) * 64 - len(head)) + raw[-(-(16 + hlen) // 64) * 64 :])
    assert msg.truth is None and "truth.position_m[2]" in (msg.truth_problem or "")
    assert msg.rf.shape == examples()["RFFrame"].rf.shape


# ------------------------------------------------------------------------------------------- UFF reader
@pytest.fixture(scope="module")
def base_uff(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from fpcore import Acquisition, PlaneWaveSequence, Probe

    probe = Probe.linear(8, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.from_angles(np.linspace(-5, 5, 3))
    rf = np.random.default_rng(0).standard_normal((8, 3, 64)).astype(np.float32)
    path = tmp_path_factory.mktemp("fuzz") / "base.uff"
    write_uff(path, [Acquisition(rf, 20e6, 0.0, 1500.0, probe, seq, truth={"band_hz": [1.5e6, 3.5e6]})] * 2)
    return path


def _dataset_names(path: Path) -> list[str]:
    names: list[str] = []
    with h5py.File(path, "r") as f:
        f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
    return sorted(names)


_values = st.one_of(
    st.floats(width=64),
    st.integers(-(2**40), 2**40),
    st.lists(st.floats(width=64), min_size=0, max_size=6),
    st.text(max_size=6).map(lambda t: np.bytes_(t.encode("utf-8", "replace"))),
    st.tuples(st.integers(0, 3), st.integers(0, 4), st.integers(0, 9)).map(lambda s: np.zeros(s)),
)
_attrs = st.one_of(
    st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=40),  # h5py-storable
    st.sampled_from(['{"probe": 1}', '{"timestamp": ["a"]}', "[1e400]", '{"sines": [[null]]}', "[{}]", "{"]),
)


@SOME
@given(st.data())
def test_uff_reader_raises_only_its_own_errors(base_uff: Path, tmp_path_factory, data: st.DataObject) -> None:
    path = tmp_path_factory.mktemp("m") / "m.uff"
    shutil.copyfile(base_uff, path)
    names = _dataset_names(base_uff)
    with h5py.File(path, "r+") as f:
        for _ in range(data.draw(st.integers(1, 3))):
            what = data.draw(st.sampled_from(["dataset", "delete", "attr"]))
            if what == "attr":
                key = data.draw(st.sampled_from(["fp_metadata", "fp_truth"]))
                f["channel_data"].attrs[key] = data.draw(_attrs)
                continue
            name = data.draw(st.sampled_from(names))
            if name not in f:
                continue
            del f[name]
            if what == "dataset":
                f.create_dataset(name, data=data.draw(_values))
    try:
        frames = read_uff(path)
    except (UFFError, BudgetError, FormatError) as exc:
        assert str(exc)
        return
    assert frames and all(np.all(np.isfinite(a.rf)) for a in frames)


@pytest.mark.parametrize("value", [math.inf, -math.inf, 1e300])
def test_uff_wavefront_beyond_an_integer_is_named(base_uff: Path, tmp_path: Path, value: float) -> None:
    """Found by bench/fuzz_inputs.py once read_uff stopped turning every exception into a UFFError: an infinite
    wavefront code raised OverflowError (int(inf)) from our own parsing."""
    path = tmp_path / "wf.uff"
    shutil.copyfile(base_uff, path)
    with h5py.File(path, "r+") as f:
        wf = "channel_data/sequence/sequence_0002/wavefront"
        del f[wf]
        f.create_dataset(wf, data=value)
    with pytest.raises(UFFError, match=r"sequence\[1\]/wavefront: expected plane \(0\), got") as info:
        read_uff(path)
    assert "\n" not in str(info.value)


@SOME
@given(st.integers(0, 10**9))
def test_uff_reader_on_truncated_files(base_uff: Path, tmp_path_factory, at: int) -> None:
    """Truncated at any byte: a UFFError naming the file. (Zeroed or flipped bytes inside HDF5's own metadata
    can hang the HDF5 library in C, beyond any Python timeout; bench/fuzz_inputs.py runs those in a watchdog
    process and counts the hangs.)"""
    raw = base_uff.read_bytes()
    path = tmp_path_factory.mktemp("b") / "b.uff"
    path.write_bytes(raw[: at % len(raw)])
    with pytest.raises((UFFError, FormatError)) as err:
        read_uff(path)
    assert str(path) in str(err.value)
