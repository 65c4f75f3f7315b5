"""Recording size per frame, by channel (issue 14: the quick demo's recording, target ≤ 5 MB a frame).

    fp demo --out out/demo && python bench/bench_recording_size.py out/demo/demo-*.mcap
    python bench/bench_recording_size.py REC.mcap --what-if   # + the same messages re-encoded other ways

Frames = the number of RF messages. Per channel (the key's last parts: ``rf``, ``gamma``, ``image``,
``display/…``): messages, bytes as recorded (uncompressed) and compressed, per frame. "Compressed" is each
message compressed alone with the chunk's codec (zstd level 3, as the MCAP writer does), an estimate of its
share of the chunks; the file's own size per frame is printed first. ``--what-if`` re-encodes the bus
messages of the file: float32 maps, uint16 maps (GammaMap / ConfocalImage 1.1), each without and with the
recorder's byte shuffle, so one file answers what each choice costs.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import zstandard

from services.messages import ConfocalImage, GammaMap
from services.recording import iter_raw, shuffle_payload, wire_payload
from services.wire import decode, encode


def _channel(topic: str) -> str:
    parts = topic.split("/")
    return "/".join(parts[2:4]) if len(parts) > 3 and parts[2] == "display" else "/".join(parts[2:])


def _z(data: bytes) -> int:
    return len(zstandard.compress(data))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mcap", type=Path)
    ap.add_argument("--what-if", action="store_true", help="also re-encode the maps float32 / uint16, ± shuffle")
    args = ap.parse_args(argv)
    raw: dict[str, int] = defaultdict(int)
    comp: dict[str, int] = defaultdict(int)
    count: dict[str, int] = defaultdict(int)
    alt: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    frames = 0
    for _schema, channel, msg in iter_raw(args.mcap):
        name = f"{_channel(channel.topic)} [{channel.message_encoding}]"
        data = bytes(msg.data)
        raw[name] += len(data)
        comp[name] += _z(data)
        count[name] += 1
        payload = wire_payload(channel, msg)
        if payload is None or channel.message_encoding == "json":
            continue
        m = decode(payload)
        frames += m.schema_name == "RFFrame"
        if not args.what_if:
            continue
        if isinstance(m, GammaMap):
            variants = {"float32": m.model_copy(update={"gamma_step": None}), "uint16": m}
            if m.gamma_step is None:
                from services.convert import gamma_step

                variants["uint16"] = GammaMap.model_validate({**m.model_dump(), "gamma_step": gamma_step(m.gamma)})
        elif isinstance(m, ConfocalImage):
            from services.convert import confocal_db_codes

            variants = {"float32": m.model_copy(update={"db_step": None, "db_floor": None}), "uint16": m}
            if m.db_step is None:
                variants["uint16"] = confocal_db_codes(m)
        else:
            variants = {"as sent": m}
        for label, v in variants.items():
            p = encode(v)
            alt[_channel(channel.topic)][label] += _z(p)
            alt[_channel(channel.topic)][label + " + shuffle"] += _z(shuffle_payload(p))
    frames = max(frames, 1)
    size = args.mcap.stat().st_size
    print(f"{args.mcap}: {size / 1e6:.1f} MB, {frames} RF frame(s): {size / frames / 1e6:.2f} MB a frame")
    print(f"{'channel':44s} {'msgs':>5s} {'raw MB/frame':>13s} {'zstd MB/frame':>14s}")
    for name in sorted(raw, key=lambda n: -comp[n]):
        print(f"{name:44s} {count[name]:5d} {raw[name] / frames / 1e6:13.3f} {comp[name] / frames / 1e6:14.3f}")
    print(
        f"{'total':44s} {sum(count.values()):5d} {sum(raw.values()) / frames / 1e6:13.3f} "
        f"{sum(comp.values()) / frames / 1e6:14.3f}"
    )
    if args.what_if:
        print("\nre-encoded (zstd MB/frame):")
        for ch, row in sorted(alt.items()):
            print(f"  {ch:24s} " + "  ".join(f"{k} {v / frames / 1e6:.3f}" for k, v in row.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
