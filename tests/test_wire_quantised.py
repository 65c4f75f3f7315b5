"""Quantised maps on the wire (GammaMap / ConfocalImage 1.1: uint16 codes with a stated step) and the recorder's
byte shuffle: error bounds against the float values, old versions still decoding, refusals naming the field."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from services.convert import CONFOCAL_DB_STEP, confocal_db_codes, frame_messages, gamma_step
from services.messages import UINT16_MAX, ConfocalImage, GammaMap, Grid, examples
from services.recording import iter_messages, shuffle_payload
from services.wire import ALIGN, PREFIX_SIZE, WireError, decode, decode_header, encode

SAMPLE = Path(__file__).resolve().parent.parent / "recordings" / "sinking-sphere-quick.mcap"
F32 = float(np.finfo(np.float32).eps)


def _grid() -> Grid:
    return Grid(x=np.linspace(-4e-3, 4e-3, 21), y=np.linspace(-2e-3, 2e-3, 9), z=np.linspace(10e-3, 20e-3, 33))


def _gamma(rng: np.random.Generator, top: float = 0.63) -> np.ndarray:
    g = rng.random(_grid().shape) ** 3 * top  # most values small, as on a γ-map
    g.flat[123] = top
    return g.astype(np.float32)


def _speckle(rng: np.random.Generator) -> np.ndarray:
    """|I|² with a huge dynamic range (exponential speckle over 1e-12…1) and exact zeros."""
    img = rng.exponential(size=_grid().shape) * 10.0 ** rng.uniform(-12, 0, _grid().shape)
    img.flat[:50] = 0.0
    return img.astype(np.float32)


def _split(payload: bytes) -> tuple[dict, bytes]:
    _, hlen, _ = struct.unpack_from("<8sII", payload)
    start = -(-(PREFIX_SIZE + hlen) // ALIGN) * ALIGN
    return json.loads(payload[PREFIX_SIZE : PREFIX_SIZE + hlen]), payload[start:]


def _pack(header: dict, data: bytes) -> bytes:
    hb = json.dumps(header).encode()
    start = -(-(PREFIX_SIZE + len(hb)) // ALIGN) * ALIGN
    return struct.pack("<8sII", b"FPWIRE01", len(hb), 0) + hb + bytes(start - PREFIX_SIZE - len(hb)) + data


def _edit(payload: bytes, edit) -> bytes:  # noqa: ANN001
    header, data = _split(payload)
    edit(header)
    return _pack(header, data)


def test_gamma_travels_as_uint16_within_half_a_step() -> None:
    rng = np.random.default_rng(0)
    g = _gamma(rng)
    step = gamma_step(g)
    assert step == pytest.approx(0.63 / UINT16_MAX)
    msg = GammaMap(frame_index=3, timestamp=1.0, fingerprint="s", grid=_grid(), gamma=g, gamma_step=step)
    assert msg.gamma.dtype == np.float32 and np.array_equal(msg.gamma, g)  # Python holds the float values
    payload = encode(msg)
    head = decode_header(payload)
    assert head.schema_version == "1.2" and GammaMap.version() == (1, 2)  # 1.2: the optional statistic (--union)
    assert {d.name: d.dtype for d in head.arrays}["gamma"] == "<u2" and head.fields["gamma_step"] == step
    back = decode(payload)
    assert isinstance(back, GammaMap) and back.gamma.dtype == np.float32 and not back.gamma.flags.writeable
    err = np.abs(back.gamma.astype(np.float64) - g)
    bound = step / 2 + F32 * float(g.max())  # half a step, plus float32's rounding of code × step
    assert float(err.max()) <= bound and float(err.max()) > step / 4  # the bound is reached, not loose
    assert float(err.max()) <= 0.63 / 131070 * (1 + 1e-6) + F32  # docs/wire.md: γ_max / 131070
    assert np.unravel_index(np.argmax(back.gamma), g.shape) == np.unravel_index(np.argmax(g), g.shape)
    assert len(payload) < 0.55 * len(encode(msg.model_copy(update={"gamma_step": None})))  # 2 bytes, not 4
    again = encode(back)  # re-encoding decoded values gives the same codes
    assert _split(again)[1] == _split(payload)[1]


def test_confocal_image_travels_as_db_codes_within_half_a_step() -> None:
    rng = np.random.default_rng(1)
    lin = _speckle(rng)
    img = ConfocalImage(frame_index=3, timestamp=1.0, grid=_grid(), image=lin)
    q = confocal_db_codes(img)
    assert q.scale == "db" and q.db_step == CONFOCAL_DB_STEP
    top = 10 * np.log10(float(lin.max()))
    assert q.db_floor == pytest.approx(top - UINT16_MAX * CONFOCAL_DB_STEP)
    back = decode(encode(q))
    assert isinstance(back, ConfocalImage) and back.schema_version == "1.1" and back.scale == "db"
    assert decode_header(encode(q)).arrays[-1].dtype == "<u2"
    level = np.full(lin.shape, q.db_floor)
    np.log10(lin.astype(np.float64), out=level, where=lin > 0)
    level[lin > 0] *= 10
    err = np.abs(back.image.astype(np.float64) - level)
    bound = CONFOCAL_DB_STEP / 2 + F32 * 700  # half a step in dB, plus float32 at |level| ≤ 700 dB
    assert float(err.max()) <= bound and float(err.max()) > CONFOCAL_DB_STEP / 4
    assert np.all(back.image[lin == 0] == np.float32(q.db_floor))  # zeros read as the floor, 655 dB down
    assert float(np.min(level[lin > 0])) > q.db_floor  # every non-zero value of the 120 dB range is within


def test_linear_confocal_image_with_a_db_step_reads_back_linear() -> None:
    rng = np.random.default_rng(2)
    lin = _speckle(rng)
    msg = ConfocalImage(frame_index=1, timestamp=0.0, grid=_grid(), image=lin, db_step=0.01)
    assert msg.db_floor == pytest.approx(10 * np.log10(float(lin.max())) - 655.35)  # set from the image
    back = decode(encode(msg))
    assert back.scale == "linear" and back.image.dtype == np.float32
    nz = lin > 0
    rel = np.abs(back.image[nz].astype(np.float64) / lin[nz] - 1)
    assert float(rel.max()) <= 10 ** (0.005 / 10) - 1 + 4 * F32  # 0.115 %: half a step of 0.01 dB
    assert np.all(back.image[~nz] == 0)  # code 0 reads 0 in a linear image


def test_old_versions_still_decode() -> None:
    """GammaMap and ConfocalImage 1.0 (float32, before the step fields) decode as before."""
    for msg in (examples()["GammaMap"], examples()["ConfocalImage"]):

        def as_1_0(h: dict) -> None:
            h["schema_version"] = "1.0"
            for k in ("gamma_step", "db_step", "db_floor"):
                h.pop(k, None)

        old = decode(_edit(encode(msg), as_1_0))
        assert old.schema_version == "1.0" and type(old) is type(msg)
        name = "gamma" if isinstance(msg, GammaMap) else "image"
        assert getattr(old, name).dtype == np.float32 and np.array_equal(getattr(old, name), getattr(msg, name))


def test_the_shipped_sample_recording_still_decodes() -> None:
    """Every map of the shipped sample decodes to float32 (it was recorded with GammaMap / ConfocalImage 1.0)."""
    versions: set[tuple[str, str]] = set()
    for _key, m in iter_messages(SAMPLE):
        if isinstance(m, (GammaMap, ConfocalImage)):
            versions.add((m.schema_name, m.schema_version))
            values = m.gamma if isinstance(m, GammaMap) else m.image
            assert values.dtype == np.float32 and np.isfinite(values).all()
    assert {name for name, _v in versions} == {"GammaMap", "ConfocalImage"}


def test_refusals_name_the_field() -> None:
    rng = np.random.default_rng(3)
    g = _gamma(rng)
    gm = GammaMap(frame_index=0, timestamp=0.0, fingerprint="s", grid=_grid(), gamma=g, gamma_step=gamma_step(g))
    codes = encode(gm)
    with pytest.raises(WireError) as info:
        decode(_edit(codes, lambda h: h.pop("gamma_step")))  # uint16 codes without their step
    assert info.value.field == "gamma_step" and "expected with uint16" in info.value.problem
    with pytest.raises(WireError) as info:
        decode(_edit(codes, lambda h: h.update(gamma_step=1e36)))  # codes × step beyond float32
    assert info.value.field == "gamma_step"
    img = confocal_db_codes(ConfocalImage(frame_index=0, timestamp=0.0, grid=_grid(), image=_speckle(rng)))
    for key in ("db_floor", "db_step"):
        with pytest.raises(WireError) as info:
            decode(_edit(encode(img), lambda h, k=key: h.pop(k)))
        assert info.value.field == key
    with pytest.raises(ValidationError, match="gamma_step"):  # a step too small would clip γ_max
        GammaMap(frame_index=0, timestamp=0.0, fingerprint="s", grid=_grid(), gamma=g, gamma_step=1e-9)
    with pytest.raises(ValidationError, match="γ ≥ 0"):
        GammaMap(frame_index=0, timestamp=0.0, fingerprint="s", grid=_grid(), gamma=-g, gamma_step=1.0)
    with pytest.raises(ValidationError, match="db_floor"):
        ConfocalImage(frame_index=0, timestamp=0.0, grid=_grid(), image=_speckle(rng), db_floor=-10.0)
    with pytest.raises(ValueError, match="map_encoding"):
        frame_messages(None, 0, 0.0, "float8")  # type: ignore[arg-type]


def test_detections_are_computed_on_float_gamma_before_quantisation() -> None:
    """The processor's messages differ only in how the maps travel: detections and tracks are the same."""
    from services.pipeline import Pipeline, PipelineConfig
    from services.registry import FingerprintSpec
    from services.sources import born_frames

    frames, cal = born_frames(2)
    cfg = PipelineConfig(x_range=(-4e-3, 4e-3), z_range=(12e-3, 20e-3), spacing=0.25e-3, n_freq=16)
    pipe = Pipeline(cfg, [FingerprintSpec("marker", calibration=cal)])
    res = pipe.process(frames[0])
    f32, u16 = (frame_messages(res, 0, 0.0, enc) for enc in ("float32", "uint16"))
    assert f32["detections"] == u16["detections"] and f32["tracks"] == u16["tracks"]
    assert f32["detections"].detections  # there is a detection to compare
    raw, q = f32["gamma"][0], decode(encode(u16["gamma"][0]))
    assert float(np.abs(q.gamma - raw.gamma).max()) <= float(raw.gamma.max()) / 131070 + F32
    im = decode(encode(u16["image"]))
    lin = res.image.astype(np.float64)
    ok = lin > float(lin.max()) * 1e-60
    assert float(np.abs(im.image[ok] - 10 * np.log10(lin[ok])).max()) <= 0.005 + F32 * 700


@pytest.mark.parametrize("name", list(examples()))
def test_shuffle_is_undone_exactly(name: str) -> None:
    payload = encode(examples()[name])
    shuffled = shuffle_payload(payload)
    assert len(shuffled) == len(payload) and shuffled[:PREFIX_SIZE] == payload[:PREFIX_SIZE]
    assert shuffle_payload(shuffled, inverse=True) == payload
    if decode_header(payload).arrays:
        assert shuffled != payload
    assert shuffle_payload(b"FPWIRE01garbage") == b"FPWIRE01garbage"  # unreadable: kept as it is


def test_shuffle_leaves_overlapping_or_overrunning_buffers_as_they_came() -> None:
    """A malformed payload is recorded raw: shuffling buffers that overlap could not be undone."""
    payload = encode(examples()["GammaMap"])

    def overlap(h: dict) -> None:
        h["arrays"][1]["offset"] = 0  # grid.z over grid.x

    def overrun(h: dict) -> None:
        h["arrays"][2]["shape"], h["arrays"][2]["nbytes"] = [50, 6], 1200

    for edit in (overlap, overrun):
        bad = _edit(payload, edit)
        assert shuffle_payload(bad) == bad and shuffle_payload(bad, inverse=True) == bad


def test_recorder_shuffles_under_compression_and_gives_back_the_wire_bytes(tmp_path: Path) -> None:
    """A segment written with the shuffle records ``fpwire-shuffled`` channels, smaller under zstd, and
    services.recording gives back the exact wire payloads; payloads are decoded only for what uses them."""
    from services.nodes.recorder import _Received, _Segment
    from services.recording import SHUFFLED_ENCODING, iter_raw, iter_recording
    from services.topics import keys

    rng = np.random.default_rng(4)
    x, y, z = np.meshgrid(*(np.linspace(-1, 1, n) for n in _grid().shape), indexing="ij")
    smooth = [np.exp(-((x - 0.1 * i) ** 2 + y**2 + z**2) * 4) for i in range(3)]  # a peak moving on a γ-map
    gs = [(0.6 * s * (1 + 0.01 * rng.standard_normal(s.shape))).astype(np.float32) for s in smooth]
    msgs = [
        GammaMap(frame_index=i, timestamp=0.0, fingerprint="s", grid=_grid(), gamma=g, gamma_step=gamma_step(g))
        for i, g in enumerate(gs)
    ]
    payloads = [encode(m) for m in msgs] + [encode(examples()["RFFrame"]), encode(examples()["Detections"])]
    topics = [keys("q").gamma] * 3 + [keys("q").rf, keys("q").detections]
    sizes = {}
    for shuffle in (False, True):
        path = tmp_path / f"s{shuffle}.mcap"
        seg = _Segment(path, "zstd", chunk_size=1 << 20, key_expr="fp/**", shuffle=shuffle)
        got = [seg.write(_Received(k, p, None, i, i)) for i, (k, p) in enumerate(zip(topics, payloads, strict=True))]
        seg.finish()
        sizes[shuffle] = path.stat().st_size
        assert [k for k, *_ in iter_recording(path)] == topics
        assert [p for _, p, *_ in iter_recording(path)] == payloads  # the wire bytes, exactly
        encodings = {c.topic.rsplit("/", 1)[-1]: c.message_encoding for _, c, _ in iter_raw(path)}
        assert encodings == {
            "gamma": SHUFFLED_ENCODING if shuffle else "fpwire",
            "rf": SHUFFLED_ENCODING if shuffle else "fpwire",
            "detections": "json",
        }
        assert got[:4] == [None] * 4 and got[4] is not None  # only the JSON message needed decoding
    assert sizes[True] < sizes[False]
    seg = _Segment(tmp_path / "d.mcap", "zstd", chunk_size=1 << 20, key_expr="fp/**")
    back = seg.write(_Received(topics[0], payloads[0], None, 0, 0), frozenset({"GammaMap"}))
    seg.finish()
    assert isinstance(back, GammaMap) and back.frame_index == 0  # decoded when the display uses it
