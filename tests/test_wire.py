"""Wire format and message models: round trips, zero-copy views, alignment, refusal of bad input."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest
from pydantic import ValidationError

from services.messages import (
    MAX_RF_ABS,
    ConfocalImage,
    Detection,
    Detections,
    ErrorReport,
    GammaMap,
    Grid,
    Latency,
    Message,
    Normalisation,
    Probe,
    RFFrame,
    Status,
    Track,
    Tracks,
)
from services.topics import keys, parse_key
from services.wire import (
    ALIGN,
    MAGIC,
    PREFIX_SIZE,
    WireError,
    decode,
    decode_header,
    encode,
    encode_with_header,
    error_report,
    extract_header,
    header_bytes,
)

# ------------------------------------------------------------------------------------------- fixtures


def make_rf(n_u: int = 8, n_theta: int = 5, n_t: int = 64, dtype: str = "<f4", seed: int = 0) -> RFFrame:
    rng = np.random.default_rng(seed)
    x = (np.arange(n_u) - (n_u - 1) / 2) * 3e-4
    positions = np.stack([x, np.zeros(n_u), np.zeros(n_u)], axis=1)
    sines = np.stack([np.linspace(-0.3, 0.3, n_theta), np.zeros(n_theta)], axis=1)
    rf = rng.standard_normal((n_u, n_theta, n_t))
    rf = (rf * 1000).astype(dtype) if np.dtype(dtype).kind == "i" else rf.astype(dtype)
    return RFFrame(
        frame_index=7,
        timestamp=12.5,
        fs=20e6,
        t0=1e-6,
        c0=1480.0,
        probe=Probe(positions=positions, pitch=3e-4, centre_frequency=2.2e6, bandwidth=0.8e6),
        sines=sines,
        rf=rf,
        truth={"targets": [{"position_m": [0.0, 0.0, 0.02], "d": 0.01}], "note": "θ"},
    )


def make_grid(three_d: bool = False) -> Grid:
    return Grid(
        x=np.linspace(-5e-3, 5e-3, 11),
        y=np.linspace(-2e-3, 2e-3, 5) if three_d else None,
        z=np.linspace(10e-3, 20e-3, 13),
    )


def make_gamma(three_d: bool = False) -> GammaMap:
    g = make_grid(three_d)
    gamma = np.random.default_rng(1).random(g.shape, dtype=np.float32)
    return GammaMap(
        frame_index=7,
        timestamp=12.5,
        fingerprint="sphere_10mm",
        state={"d": 0.01},
        grid=g,
        gamma=gamma,
        normalisation=Normalisation(band_hz=(1.8e6, 2.6e6), r_energy=2.0, gamma_m=0.1),
    )


def make_image() -> ConfocalImage:
    g = make_grid()
    img = np.full(g.shape, -40.0, np.float32)
    img[5, 6] = 0.0
    return ConfocalImage(frame_index=7, timestamp=12.5, grid=g, image=img, scale="db")


def make_detections() -> Detections:
    d = Detection(
        fingerprint="sphere_10mm",
        position_m=(0.0, 0.0, 0.02),
        gamma_max=0.8,
        contrast_c_gamma=9.0,
        contrast_c=36.0,
        pfa=1e-8,
        precision_m=(1e-4, 2e-5),
        truth_error_m=3e-5,
    )
    return Detections(frame_index=7, timestamp=12.5, detections=[d, d.model_copy(update={"truth_error_m": None})])


def make_tracks() -> Tracks:
    cov = ((1e-8, 1e-9, 0.0), (1e-9, 2e-8, 0.0), (0.0, 0.0, 3e-8))
    t = Track(id=1, position_m=(0.0, 0.0, 0.02), velocity_m_s=(0.0, 0.0, 1e-3), covariance=cov, confidence=0.9, age=12)
    return Tracks(frame_index=7, timestamp=12.5, tracks=[t])


def make_status() -> Status:
    return Status(
        node="proc-1",
        timestamp=1.7e9,
        frames_processed=100,
        frame_rate_hz=9.5,
        latency_ms=Latency(median=40.0, p95=70.0),
        dropped=2,
        rejected=1,
        dictionary=["a", "b"],
    )


def make_error() -> ErrorReport:
    return ErrorReport(frame_index=3, key=keys("bench").rf, field="rf", problem="contains NaN", timestamp=1.0)


MAKERS = {
    "RFFrame": make_rf,
    "RFFrame_int16": lambda: make_rf(dtype="<i2"),
    "GammaMap2D": make_gamma,
    "GammaMap3D": lambda: make_gamma(True),
    "ConfocalImage": make_image,
    "Detections": make_detections,
    "Tracks": make_tracks,
    "Status": make_status,
    "ErrorReport": make_error,
}


def arrays_of(msg: Message) -> dict[str, np.ndarray]:
    """Flatten array fields to dotted names (same naming as the wire)."""
    out: dict[str, np.ndarray] = {}

    def walk(m: object, prefix: str) -> None:
        for name in type(m).model_fields:
            v = getattr(m, name)
            if isinstance(v, np.ndarray):
                out[prefix + name] = v
            elif isinstance(v, (Probe, Grid)):
                walk(v, prefix + name + ".")

    walk(msg, "")
    return out


def split(payload: bytes) -> tuple[dict, bytes]:
    """(header dict, data section) of a payload."""
    magic, hlen, _ = struct.unpack_from("<8sII", payload)
    assert magic == MAGIC
    start = -(-(PREFIX_SIZE + hlen) // ALIGN) * ALIGN
    return json.loads(payload[PREFIX_SIZE : PREFIX_SIZE + hlen]), payload[start:]


def pack(header: dict, data: bytes, *, magic: bytes = MAGIC, flags: int = 0) -> bytes:
    """Re-assemble a payload from a (possibly tampered) header and a data section."""
    hb = json.dumps(header).encode()
    start = -(-(PREFIX_SIZE + len(hb)) // ALIGN) * ALIGN
    return struct.pack("<8sII", magic, len(hb), flags) + hb + bytes(start - PREFIX_SIZE - len(hb)) + data


def tamper(msg: Message, edit) -> bytes:  # noqa: ANN001
    header, data = split(encode(msg))
    out = edit(header, data)
    return pack(*out) if isinstance(out, tuple) else pack(header, data)


def desc(header: dict, name: str) -> dict:
    return next(d for d in header["arrays"] if d["name"] == name)


def refused(payload: object, *needles: str, **kw: object) -> WireError:
    with pytest.raises(WireError) as info:
        decode(payload, **kw)  # type: ignore[arg-type]
    for n in needles:
        assert n in str(info.value), f"{n!r} not in {info.value}"
    return info.value


# ------------------------------------------------------------------------------------------ round trip


@pytest.mark.parametrize("kind", list(MAKERS))
def test_round_trip_values_and_views(kind: str) -> None:
    msg = MAKERS[kind]()
    payload = encode(msg)
    assert isinstance(payload, bytes)
    out = decode(payload)
    assert type(out) is type(msg)
    plain = {k: v for k, v in msg.model_dump().items()}
    back = out.model_dump()
    for name, arr in arrays_of(msg).items():
        view = arrays_of(out)[name]
        assert view.dtype == arr.dtype and view.shape == arr.shape
        np.testing.assert_array_equal(view, arr)
        # a view into the payload, not a copy
        assert np.shares_memory(view, np.frombuffer(payload, np.uint8))
        assert not view.flags.writeable and not view.flags.owndata
    assert _strip_arrays(back) == _strip_arrays(plain)


def _strip_arrays(d: object) -> object:
    if isinstance(d, dict):
        return {k: _strip_arrays(v) for k, v in d.items() if not isinstance(v, np.ndarray)}
    if isinstance(d, (list, tuple)):
        return [_strip_arrays(v) for v in d]
    return d


@pytest.mark.parametrize("kind", list(MAKERS))
def test_layout_alignment_and_header(kind: str) -> None:
    msg = MAKERS[kind]()
    payload, hdr = encode_with_header(msg)
    assert payload[:8] == MAGIC
    hlen = struct.unpack_from("<I", payload, 8)[0]
    assert payload[PREFIX_SIZE : PREFIX_SIZE + hlen] == hdr == header_bytes(msg) == extract_header(payload)
    start = -(-(PREFIX_SIZE + hlen) // ALIGN) * ALIGN
    assert start % 64 == 0 and set(payload[PREFIX_SIZE + hlen : start]) <= {0}
    header = json.loads(hdr)
    end = 0
    for d in header["arrays"]:
        assert d["offset"] % 64 == 0 and (start + d["offset"]) % 64 == 0
        assert d["offset"] >= end
        end = d["offset"] + d["nbytes"]
    assert len(payload) == start + end
    h = decode_header(hdr)
    assert h.schema_name == msg.schema_name and h.schema_version == "{}.{}".format(*type(msg).version())
    assert type(msg).version()[0] == 1  # every schema is still at major 1 (old recordings decode)
    assert [a.name for a in h.arrays] == [d["name"] for d in header["arrays"]]
    assert decode_header(payload) == h
    if "frame_index" in type(msg).model_fields:
        assert h.frame_index == msg.frame_index  # type: ignore[attr-defined]


def test_rf_header_names_buffers_by_field_path() -> None:
    msg = make_rf()
    header = json.loads(header_bytes(msg))
    assert header["rf"] == "rf" and header["sines"] == "sines" and header["probe"]["positions"] == "probe.positions"
    d = desc(header, "rf")
    assert d == {"name": "rf", "dtype": "<f4", "shape": [8, 5, 64], "offset": d["offset"], "nbytes": 8 * 5 * 64 * 4}


def test_array_used_twice_travels_once() -> None:
    ax = np.linspace(0, 1e-2, 9)
    g = GammaMap(
        frame_index=0, timestamp=0.0, fingerprint="f", grid=Grid(x=ax, z=ax), gamma=np.zeros((9, 9), np.float32)
    )
    header = json.loads(header_bytes(g))
    assert [d["name"] for d in header["arrays"]] == ["grid.x", "gamma"]
    out = decode(encode(g))
    np.testing.assert_array_equal(out.grid.z, ax)


def test_message_without_arrays_and_writable_views() -> None:
    p = encode(make_detections())
    assert len(p) % 64 == 0  # header + padding only
    buf = bytearray(encode(make_rf()))
    out = decode(buf)
    assert out.rf.flags.writeable and np.shares_memory(out.rf, np.frombuffer(buf, np.uint8))


def test_big_endian_and_non_contiguous_arrays_encode_little_endian() -> None:
    ref = make_rf()
    be = ref.model_copy(update={})
    be.rf = ref.rf.astype(">f4")
    be.sines = ref.sines.astype(">f8")
    assert be.rf.dtype.str == "<f4"  # normalised at construction
    rf_t = np.ascontiguousarray(np.transpose(ref.rf, (2, 0, 1))).transpose(1, 2, 0)  # non-contiguous view
    nc = ref.model_copy()
    nc.rf = rf_t
    assert not nc.rf.flags.c_contiguous
    for msg in (be, nc):
        header = json.loads(header_bytes(msg))
        assert {d["dtype"] for d in header["arrays"]} <= {"<f4", "<f8"}
        out = decode(encode(msg))
        np.testing.assert_array_equal(out.rf, ref.rf)
        np.testing.assert_array_equal(out.sines, ref.sines)


def test_unaligned_memory_decodes() -> None:
    payload = encode(make_rf())
    for shift in (1, 3, 7):
        buf = bytearray(len(payload) + shift)
        buf[shift:] = payload
        out = decode(memoryview(buf)[shift:])
        np.testing.assert_array_equal(out.rf, make_rf().rf)
        assert float(out.rf.sum()) == pytest.approx(float(make_rf().rf.sum()), rel=1e-5)


def test_newer_minor_version_is_read_and_unknown_fields_ignored() -> None:
    def edit(h: dict, d: bytes) -> None:
        h["schema_version"] = "1.7"
        h["new_field"] = {"x": 1}

    out = decode(tamper(make_rf(), edit))
    assert isinstance(out, RFFrame) and out.schema_version == "1.7"


def test_expect_type() -> None:
    p = encode(make_status())
    assert isinstance(decode(p, expect=Status), Status)
    refused(p, "schema_name", "expected RFFrame, got Status", expect=RFFrame)


# ----------------------------------------------------------------------------------------- bad input


def test_not_bytes_and_short_and_magic() -> None:
    refused(12345, "payload", "expected bytes")
    refused("text", "payload", "expected bytes")
    refused(b"", "payload", "truncated")
    refused(MAGIC + b"\x00", "payload", "truncated")
    p = encode(make_status())
    refused(b"XXWIRE01" + p[8:], "magic", "expected b'FPWIRE01'")
    refused(p[:12] + b"\x01\x00\x00\x00" + p[16:], "flags", "expected 0")


def test_header_length_beyond_payload() -> None:
    p = bytearray(encode(make_status()))
    struct.pack_into("<I", p, 8, len(p))
    refused(bytes(p), "header_length", "beyond the payload")


@pytest.mark.parametrize(
    ("header", "needle"),
    [
        (b"{not json", "expected a JSON object"),
        (b"\xff\xfe{}", "UTF-8"),
        (b"[1, 2]", "got list"),
        (b'{"schema_name": "RFFrame", "schema_version": "1.0", "x": NaN}', "NaN is not valid JSON"),
        (b'{"schema_version": "1.0"}', "schema_name"),
        (b'{"schema_name": "Bogus", "schema_version": "1.0"}', "unknown schema 'Bogus'"),
        (b'{"schema_name": "Status", "schema_version": "2.0", "node": "n"}', "newer than this reader"),
        (b'{"schema_name": "Status", "schema_version": "0.9", "node": "n"}', "older than this reader"),
        (b'{"schema_name": "Status", "schema_version": "one", "node": "n"}', "expected 'MAJOR.MINOR'"),
        (b'{"schema_name": "Status", "schema_version": "1.0", "arrays": 3, "node": "n"}', "arrays"),
        (b"[" * 100000 + b"]" * 100000, "header"),
    ],
)
def test_bad_headers(header: bytes, needle: str) -> None:
    pad = -(-(PREFIX_SIZE + len(header)) // ALIGN) * ALIGN - PREFIX_SIZE - len(header)
    refused(struct.pack("<8sII", MAGIC, len(header), 0) + header + bytes(pad), needle)
    with pytest.raises(WireError):
        decode_header(header)


def test_newer_major_named() -> None:
    def edit(h: dict, d: bytes) -> None:
        h["schema_version"] = "2.0"

    e = refused(tamper(make_rf(), edit), "schema_version", "RFFrame 2.0 is newer", "expected major version 1")
    assert e.field == "schema_version"


def test_truncated_and_trailing() -> None:
    p = encode(make_rf())
    e = refused(p[:-10], "arrays['rf']", "truncated")
    assert e.field == "arrays['rf']"
    refused(p + b"\x00" * 64, "payload", "expected exactly")


def test_oversize() -> None:
    p = encode(make_rf())
    refused(p, "payload", f"exceeds the limit max_bytes={len(p) - 1}", max_bytes=len(p) - 1)
    assert isinstance(decode(p, max_bytes=len(p)), RFFrame)


def _set(array: str, **changes: object):  # noqa: ANN202
    def edit(h: dict, d: bytes) -> None:
        desc(h, array).update(changes)

    return edit


def test_descriptor_problems() -> None:
    msg = make_rf()
    n = msg.rf.nbytes
    refused(tamper(msg, _set("rf", dtype=">f4")), "arrays['rf'].dtype", "big-endian", "'<f4'")
    refused(tamper(msg, _set("rf", dtype="<U4")), "arrays['rf'].dtype", "not one of")
    refused(tamper(msg, _set("rf", nbytes=n - 4)), "arrays['rf'].nbytes", "does not match shape")
    refused(tamper(msg, _set("rf", shape=[8, 5, -64])), "arrays['rf'].shape")
    refused(
        tamper(msg, _set("rf", offset=desc(json.loads(header_bytes(msg)), "rf")["offset"] + 8)),
        "arrays['rf'].offset",
        "multiple of 64",
    )
    refused(tamper(msg, _set("rf", offset=0)), "overlaps")
    refused(tamper(msg, _set("rf", name="rf2")), "rf", "buffer 'rf' is not described")

    def dup(h: dict, d: bytes) -> None:
        h["arrays"].append(dict(desc(h, "sines")))

    refused(tamper(msg, dup), "arrays['sines']", "unique")

    def extra(h: dict, d: bytes) -> tuple[dict, bytes]:
        h["arrays"].append(
            {"name": "spare", "dtype": "|u1", "shape": [3], "offset": len(d) + 64 - len(d) % 64, "nbytes": 3}
        )
        return h, d + bytes(64 - len(d) % 64) + b"abc"

    refused(tamper(msg, extra), "arrays['spare']", "not referenced by any field of RFFrame")


def test_dtype_and_shape_against_the_model() -> None:
    msg = make_rf()

    def as_f8(h: dict, d: bytes) -> None:  # reinterpret the rf buffer as half as many float64
        r = desc(h, "rf")
        r["dtype"], r["shape"] = "<f8", [8, 5, 32]

    refused(tamper(msg, as_f8), "rf", "expected dtype float32 or int16, got <f8")

    def as_2d(h: dict, d: bytes) -> None:
        desc(h, "rf")["shape"] = [40, 64]

    refused(tamper(msg, as_2d), "rf", "expected 3 dimensions")

    def wrong_n_theta(h: dict, d: bytes) -> None:
        desc(h, "rf")["shape"] = [8, 4, 80]

    e = refused(tamper(msg, wrong_n_theta), "rf", "expected shape (N_u=8, N_θ=5, N_t)")
    assert e.field == "rf"

    def pos_f4(h: dict, d: bytes) -> None:
        r = desc(h, "probe.positions")
        r["dtype"], r["shape"] = "<f4", [16, 3]

    refused(tamper(msg, pos_f4), "probe.positions", "expected dtype float64, got <f4")

    def gamma_shape(h: dict, d: bytes) -> None:
        desc(h, "gamma")["shape"] = [13, 11]

    refused(tamper(make_gamma(), gamma_shape), "gamma", "expected the grid's shape (11, 13)")


@pytest.mark.parametrize(
    ("field", "value"), [("rf", np.nan), ("rf", np.inf), ("sines", -np.inf), ("probe.positions", np.nan)]
)
def test_non_finite_refused(field: str, value: float) -> None:
    msg = make_rf()
    payload = bytearray(encode(msg))
    out = decode(payload)
    view = arrays_of(out)[field]
    view.reshape(-1)[view.size // 2] = value  # poke through the writable view
    e = refused(bytes(payload), field, "contains NaN or inf; expected finite values")
    assert e.field == field


def test_field_level_problems() -> None:
    def edit_field(**kv: object):  # noqa: ANN202
        def edit(h: dict, d: bytes) -> None:
            h.update(kv)

        return edit

    rf = make_rf()
    refused(tamper(rf, edit_field(frame_index="3")), "frame_index", "valid integer")
    refused(tamper(rf, edit_field(fs=-1.0)), "fs", "greater than 0")
    refused(tamper(rf, edit_field(rf=[1.0, 2.0])), "rf", "expected the name of a buffer")

    def drop(h: dict, d: bytes) -> None:
        del h["frame_index"]

    refused(tamper(rf, drop), "frame_index", "Field required")
    det = make_detections()

    def bad_pfa(h: dict, d: bytes) -> None:
        h["detections"][1]["pfa"] = 1.5

    refused(tamper(det, bad_pfa), "detections.1.pfa", "less than or equal to 1", "1.5")


def test_fuzzed_payloads_raise_only_wire_error() -> None:
    rng = np.random.default_rng(42)
    base = [encode(make_rf(n_u=4, n_theta=2, n_t=8)), encode(make_detections()), encode(make_gamma())]
    outcomes = {"ok": 0, "refused": 0}
    for i in range(600):
        p = bytearray(base[i % len(base)])
        op = rng.integers(4)
        if op == 0:  # flip bytes anywhere
            for j in rng.integers(0, len(p), size=rng.integers(1, 6)):
                p[j] = int(rng.integers(256))
        elif op == 1:  # flip bytes in the header region
            for j in rng.integers(0, min(len(p), 600), size=rng.integers(1, 4)):
                p[j] = int(rng.integers(256))
        elif op == 2:  # truncate
            p = p[: int(rng.integers(0, len(p)))]
        else:  # shift start (unaligned, garbage prefix)
            p = bytearray(rng.integers(0, 256, size=int(rng.integers(1, 9)), dtype=np.uint8).tobytes()) + p
        try:
            decode(bytes(p))
            outcomes["ok"] += 1
        except WireError:
            outcomes["refused"] += 1
        try:
            decode_header(bytes(p[:700]), strict=bool(i % 2))
        except WireError:
            pass
    assert outcomes["refused"] > 300


# ------------------------------------------------------------------------------------- construction


def test_construction_checks() -> None:
    rf = make_rf()
    with pytest.raises(ValidationError, match="expected dtype float32 or int16, got float64"):
        RFFrame(**{**rf.__dict__, "rf": rf.rf.astype(np.float64)})
    with pytest.raises(ValidationError, match="contains NaN"):
        bad = rf.rf.copy()
        bad[0, 0, 0] = np.nan
        RFFrame(**{**rf.__dict__, "rf": bad})
    with pytest.raises(ValidationError, match="s_x"):
        RFFrame(**{**rf.__dict__, "sines": np.full((5, 2), 0.9)})
    with pytest.raises(ValidationError):
        RFFrame(**{**rf.__dict__, "fs": float("nan")})
    p = Probe(positions=np.zeros((4, 3), np.float32), pitch=1e-3, centre_frequency=1e6, bandwidth=1e6)
    assert p.positions.dtype == np.float64  # safe cast
    with pytest.raises(ValidationError, match="symmetric"):
        Track(
            id=0,
            position_m=(0, 0, 0),
            velocity_m_s=(0, 0, 0),
            covariance=((1, 1, 0), (0, 1, 0), (0, 0, 1)),
            confidence=0.5,
            age=0,
        )


def test_fpcore_conversions() -> None:
    acq_mod = pytest.importorskip("fpcore.acquisition")
    grid_mod = pytest.importorskip("fpcore.grid")
    msg = make_rf()
    acq = msg.to_acquisition()
    assert isinstance(acq, acq_mod.Acquisition) and np.shares_memory(acq.rf, msg.rf)
    back = RFFrame.from_acquisition(acq)
    np.testing.assert_array_equal(back.rf, msg.rf)
    assert back.truth == msg.truth and back.frame_index == msg.frame_index
    g = make_grid(True).to_grid()
    assert isinstance(g, grid_mod.Grid) and Grid.from_grid(g).shape == make_grid(True).shape


def test_prf_travels_and_frames_without_it_still_decode() -> None:
    """RFFrame 1.1 carries the PRF (motion-aware fingerprints need the transmit times); a 1.0 header,
    written before the field existed, still decodes, with prf None."""
    import dataclasses

    from fpcore.acquisition import PlaneWaveSequence

    acq = make_rf().to_acquisition()
    assert acq.sequence.prf is None and RFFrame.from_acquisition(acq).prf is None
    moving = dataclasses.replace(acq, sequence=PlaneWaveSequence(acq.sequence.sines, prf=4e3))
    msg = RFFrame.from_acquisition(moving)
    assert msg.prf == 4e3 and msg.schema_version == "1.2" and RFFrame.version() == (1, 2)
    back = decode(encode(msg)).to_acquisition()
    assert back.sequence.prf == 4e3
    np.testing.assert_allclose(back.sequence.transmit_times(), moving.sequence.transmit_times())

    def as_1_0(h: dict, d: bytes) -> None:
        h["schema_version"] = "1.0"
        del h["prf"]

    old = decode(tamper(msg, as_1_0))
    assert isinstance(old, RFFrame) and old.schema_version == "1.0" and old.prf is None
    np.testing.assert_array_equal(old.rf, msg.rf)
    with pytest.raises(ValueError, match="prf"):
        old.to_acquisition().sequence.transmit_times()


@pytest.mark.parametrize("prf", [0.0, -1e3, "fast"])
def test_bad_prf_refused(prf: object) -> None:
    def edit(h: dict, d: bytes) -> None:
        h["prf"] = prf

    assert refused(tamper(make_rf(), edit), "prf").field == "prf"
    for bad in (prf, float("inf"), float("nan")):
        with pytest.raises(ValidationError, match="prf"):
            RFFrame.model_validate({**make_rf().model_dump(), "prf": bad})


def test_rf_amplitude_limit_on_the_wire() -> None:
    """RF beyond fpcore.budget.MAX_RF_ABS (float32 spectra would overflow) is refused at decoding in one line
    naming rf, or rf_scale for int16 RF scaled past it; rf_scale must be finite and positive."""
    from fpcore import budget

    assert budget.MAX_RF_ABS == MAX_RF_ABS
    big = make_rf()

    payload = bytearray(encode(big))
    decode(payload).rf[1, 2, 3] = -1e30
    e = refused(bytes(payload), "rf", "samples reach 1e+30", "above 1e+12")
    assert e.field == "rf" and "\n" not in str(e)
    edge = bytearray(encode(big))
    decode(edge).rf[0, 0, 0] = 1e12  # at the limit: accepted
    decode(bytes(edge))

    i16 = make_rf(dtype="<i2")

    def scaled(value: object):  # noqa: ANN202
        def edit(h: dict, d: bytes) -> None:
            h["rf_scale"] = value

        return edit

    peak = float(np.max(np.abs(i16.rf.astype(np.float64))))
    assert decode(tamper(i16, scaled(1e12 / peak))).rf_scale == 1e12 / peak
    e = refused(tamper(i16, scaled(1e300)), "rf_scale", "expected at most", "got 1e+300")
    assert e.field == "rf_scale" and "\n" not in str(e)
    for bad in (0.0, -1.0, "big"):
        assert refused(tamper(i16, scaled(bad)), "rf_scale").field == "rf_scale"
    for bad in (float("inf"), float("nan"), 1e300):
        with pytest.raises(ValidationError, match="rf_scale"):
            RFFrame.model_validate({**i16.model_dump(), "rf_scale": bad})


# ----------------------------------------------------------------------------------- copies / purity


def test_30mb_frame_costs_one_copy_to_encode_and_none_to_decode() -> None:
    """Encoding copies the array once (straight into the payload); decoding copies no array."""
    msg = make_rf(n_u=64, n_theta=16, n_t=7680)  # 64 × 16 × 7680 × 4 B = 31.5 MB
    nbytes = msg.rf.nbytes
    assert nbytes > 30e6
    tracemalloc.start()
    try:
        payload = encode(msg)
        _, peak_encode = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        base, _ = tracemalloc.get_traced_memory()
        out = decode(payload)
        _, peak_decode = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert nbytes <= len(payload) < nbytes + 64 * 1024
    assert peak_encode < nbytes + 2 * 1024 * 1024, f"encode peak {peak_encode} for {nbytes} B of data"
    assert peak_decode - base < 1024 * 1024, f"decode allocated {peak_decode - base} B"
    assert np.shares_memory(out.rf, np.frombuffer(payload, np.uint8))


def test_wire_module_is_pure() -> None:
    code = "import sys, services.wire, services.messages; assert 'zenoh' not in sys.modules, 'zenoh imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


# ------------------------------------------------------------------------------------ errors & keys


def test_error_report_from_wire_error() -> None:
    msg = make_rf()
    bad = bytearray(encode(msg))
    decode(bad).rf[0, 0, 0] = np.nan
    with pytest.raises(WireError) as info:
        decode(bytes(bad))
    rep = error_report(info.value, keys("bench").rf, bytes(bad), node="proc")
    assert (rep.frame_index, rep.field, rep.key) == (7, "rf", keys("bench").rf)
    assert "expected finite" in rep.problem and rep.header_excerpt.startswith('{"schema_name":"RFFrame"')
    assert decode(encode(rep)) == rep
    junk = error_report(WireError("magic", "bad"), keys("bench").rf, b"garbage")
    assert junk.frame_index is None and "garbage" in junk.header_excerpt


def test_keys() -> None:
    k = keys("bench")
    assert (k.rf, k.gamma, k.detections, k.tracks, k.image, k.status, k.errors) == (
        "fp/bench/rf",
        "fp/bench/gamma",
        "fp/bench/detections",
        "fp/bench/tracks",
        "fp/bench/image",
        "fp/bench/status",
        "fp/bench/errors",
    )
    assert k.dictionary == "fp/bench/dictionary/**" and k.dictionary_entry("sphere/d10") == (
        "fp/bench/dictionary/sphere/d10"
    )
    assert k.all == "fp/bench/**" and keys("*").rf == "fp/*/rf"
    assert k.for_message(make_rf()) == k.rf and k.for_message(ErrorReport) == k.errors
    assert parse_key("fp/bench/dictionary/x") == ("bench", "dictionary/x")
    for bad in ("", "a/b", "a*", "x y"):
        with pytest.raises(ValueError, match="rig"):
            keys(bad)
    with pytest.raises(ValueError):
        parse_key("zz/bench")


def test_examples_cover_every_type_and_round_trip() -> None:
    from services.messages import MESSAGE_TYPES, examples

    ex = examples()
    assert set(ex) == set(MESSAGE_TYPES)
    for msg in ex.values():
        out = decode(encode(msg))
        assert _strip_arrays(out.model_dump()) == _strip_arrays(msg.model_dump())
        for name, arr in arrays_of(msg).items():
            np.testing.assert_array_equal(arrays_of(out)[name], arr)
