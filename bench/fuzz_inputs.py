"""Long fuzz run over every door bad input comes through (issue 13.7); prints counts per outcome.

* wire: N mutants (default 10,000) of every message type's payload — byte flips, truncations, insertions,
  splices of two payloads, header values replaced by arbitrary JSON (incl. 1e400) — through
  ``services.wire.decode`` (expected: a message or WireError, nothing else) and ``decode_header``;
* UFF: damaged files (datasets replaced by random values/shapes/dtypes, deleted, metadata and truth
  attributes rewritten, bytes truncated/zeroed/flipped) through ``fpcore.io.read_uff`` (expected: frames or
  UFFError / BudgetError / FormatError);
* CLI: the bad-input corpus of tests/test_cli_badinput.py plus every (option, bad value) pair of `fp locate`,
  `fp track`, `fp characterise` and `fp process`, in-process through ``services.cli.main`` with a per-case
  alarm (expected: one error line, a non-zero exit, no traceback, no hang).

    python bench/fuzz_inputs.py [--wire 10000] [--uff 1500] [--seed 0] [--rlimit-gib 8]

The address space is capped (``--rlimit-gib``) so that a missed size check fails here, not the machine.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import importlib.util
import io
import json
import os
import resource
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fpcore.budget import BudgetError  # noqa: E402
from fpcore.io import read_uff  # noqa: E402
from fpcore.io.formats import FormatError  # noqa: E402
from fpcore.io.uff import UFFError  # noqa: E402
from services.messages import Message, examples  # noqa: E402
from services.wire import WireError, decode, decode_header, encode  # noqa: E402


@functools.cache
def _corpus_module() -> Any:
    """tests/test_cli_badinput.py: the corpus, its base frames and the in-process runner."""
    spec = importlib.util.spec_from_file_location("badinput", ROOT / "tests" / "test_cli_badinput.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


# ----------------------------------------------------------------------------------------------- wire
def _json_value(rng: np.random.Generator, depth: int = 0) -> Any:
    k = rng.integers(0, 9 if depth < 2 else 7)
    if k == 0:
        return None
    if k == 1:
        return bool(rng.integers(0, 2))
    if k == 2:
        return int(rng.integers(-(2**62), 2**62))
    if k == 3:
        return float(rng.choice([0.0, -1.0, 1e-300, 1e300, rng.standard_normal() * 10.0 ** rng.integers(-5, 40)]))
    if k == 4:
        return "@HUGE@"  # becomes 1e400 in the JSON text
    if k == 5:
        return "".join(chr(int(c)) for c in rng.integers(32, 0x2FF, size=rng.integers(0, 12)))
    if k == 6:
        return str(rng.choice(["rf", "probe.positions", "grid.x", "RFFrame", "9.9", "1.0", ""]))
    if k == 7:
        return [_json_value(rng, depth + 1) for _ in range(rng.integers(0, 4))]
    return {str(rng.integers(0, 99)): _json_value(rng, depth + 1) for _ in range(rng.integers(0, 4))}


def _rebuild(raw: bytes, doc: dict[str, Any]) -> bytes:
    hlen = int.from_bytes(raw[8:12], "little")
    hdr = json.dumps(doc).replace('"@HUGE@"', "1e400").encode()
    body = raw[-(-(16 + hlen) // 64) * 64 :]
    head = raw[:8] + len(hdr).to_bytes(4, "little") + raw[12:16] + hdr
    return head + bytes(-(-len(head) // 64) * 64 - len(head)) + body


def wire_mutant(rng: np.random.Generator, payloads: list[bytes]) -> bytes:
    raw = bytearray(payloads[rng.integers(len(payloads))])
    for _ in range(rng.integers(1, 4)):
        if not raw:
            break
        op = rng.integers(0, 6)
        if op == 0:  # flip bytes
            for i in rng.integers(0, len(raw), size=rng.integers(1, 9)):
                raw[i] = int(rng.integers(0, 256))
        elif op == 1:
            raw = raw[: rng.integers(0, len(raw))]
        elif op == 2:
            i = int(rng.integers(0, len(raw) + 1))
            raw[i:i] = rng.bytes(int(rng.integers(1, 65)))
        elif op == 3:  # splice
            other = payloads[rng.integers(len(payloads))]
            i = int(rng.integers(0, len(raw) + 1))
            raw = raw[:i] + other[rng.integers(0, len(other)) :]
        else:  # one header value replaced, or a field deleted
            try:
                hlen = int.from_bytes(raw[8:12], "little")
                doc = json.loads(bytes(raw[16 : 16 + hlen]))
                key = sorted(doc)[rng.integers(len(doc))]
            except (ValueError, TypeError, AttributeError, UnicodeDecodeError):
                continue
            if op == 4:
                doc[key] = _json_value(rng)
            else:
                del doc[key]
            raw = bytearray(_rebuild(bytes(raw), doc))
    return bytes(raw)


def fuzz_wire(n: int, rng: np.random.Generator) -> collections.Counter[str]:
    payloads = [encode(m) for m in examples().values()]
    out: collections.Counter[str] = collections.Counter()
    for _ in range(n):
        raw = wire_mutant(rng, payloads)
        try:
            msg = decode(raw)
            out["decoded" if isinstance(msg, Message) else f"decoded a {type(msg).__name__}"] += 1
        except WireError:
            out["WireError"] += 1
        except Exception as exc:  # the finding this run exists for
            out[f"OTHER {type(exc).__name__}"] += 1
        try:
            decode_header(raw, strict=False)
        except WireError:
            pass
        except Exception as exc:
            out[f"OTHER (decode_header) {type(exc).__name__}"] += 1
    return out


# ------------------------------------------------------------------------------------------------ UFF
def _random_value(rng: np.random.Generator) -> Any:
    k = rng.integers(0, 7)
    if k == 0:
        return float(rng.choice([np.nan, np.inf, -np.inf, 0.0, -1.0, 1e300, 1e-300, 3.0]))
    if k == 1:
        return int(rng.integers(-(2**40), 2**40))
    if k == 2:
        return rng.standard_normal(rng.integers(0, 7)) * 10.0 ** rng.integers(-3, 40)
    if k == 3:
        return np.bytes_(rng.bytes(int(rng.integers(0, 8))).replace(b"\x00", b"a") or b"x")
    if k == 4:
        return np.zeros(tuple(rng.integers(0, 5, size=rng.integers(0, 5))), dtype=rng.choice(["<f4", "<i2", "<c8"]))
    if k == 5:
        return np.full((1, 1), rng.choice([np.nan, 1e38, -1e30, 2.0]))
    return np.array([[1.0, 2.0], [3.0, 4.0]])


_ATTRS = ['{"probe": 1}', '{"timestamp": ["a"]}', "[1e400]", '{"sines": [[null]]}', "[{}]", "{", "", "[]"]
_ATTRS += ['{"frame_index": [-1, 2.5]}', '{"probe": {"pitch": "x"}}', '[{"band_hz": [1e400, 1]}, {}]']


def byte_damage(rng: np.random.Generator, base: Path, path: Path) -> str:
    """Truncate, zero or flip a run of bytes; returns what was done."""
    raw = bytearray(base.read_bytes())
    at, n = int(rng.integers(0, len(raw))), int(rng.integers(1, 4097))
    how = ("truncate", "zero", "flip")[rng.integers(0, 3)]
    if how == "truncate":
        raw = raw[:at]
    elif how == "zero":
        raw[at : at + n] = bytes(len(raw[at : at + n]))
    else:
        raw[at : at + n] = bytes(b ^ 0xA5 for b in raw[at : at + n])
    path.write_bytes(bytes(raw))
    return f"{how} {n} B at {at}"


def _outcome(path: Path) -> str:
    try:
        frames = read_uff(path)
        ok = all(np.all(np.isfinite(a.rf)) for a in frames) and frames
        return "read" if ok else "read, but non-finite or empty"
    except (UFFError, BudgetError, FormatError) as exc:
        return type(exc).__name__
    except Exception as exc:
        return f"OTHER {type(exc).__name__}: {str(exc)[:60]}"


def uff_worker(folder: Path) -> None:
    """Child process: the outcome of every file named on stdin, one line each (HDF5 may hang in C on a
    damaged file, beyond any Python timeout: the parent kills this process then)."""
    for line in sys.stdin:
        print(_outcome(folder / line.strip()), flush=True)


def fuzz_damaged_bytes(n: int, rng: np.random.Generator, base: Path, work: Path, timeout_s: float) -> Any:
    """n byte-damaged copies of ``base`` read by a watchdog child process; a file that takes longer than
    ``timeout_s`` counts as a hang (the child is killed by pid and restarted)."""
    import select
    import subprocess

    folder = work / "damaged"
    folder.mkdir()
    what = {f"d{i}.uff": byte_damage(rng, base, folder / f"d{i}.uff") for i in range(n)}
    out: collections.Counter[str] = collections.Counter()
    hangs: list[str] = []
    todo = list(what)
    while todo:
        child = subprocess.Popen(
            [sys.executable, __file__, "--uff-worker", str(folder)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert child.stdin is not None and child.stdout is not None
        while todo:
            name = todo.pop(0)
            child.stdin.write(name + "\n")
            child.stdin.flush()
            if select.select([child.stdout], [], [], timeout_s)[0]:
                out[child.stdout.readline().strip() or "worker died"] += 1
                continue
            out["hang (HDF5, killed)"] += 1
            hangs.append(f"{name}: {what[name]}")
            os.kill(child.pid, signal.SIGKILL)
            break
        child.stdin.close()
        child.wait()
    return out, hangs


def uff_mutant(rng: np.random.Generator, base: Path, names: list[str], path: Path) -> None:
    import h5py

    shutil.copyfile(base, path)
    with h5py.File(path, "r+") as f:
        for _ in range(rng.integers(1, 4)):
            what = rng.integers(0, 3)
            if what == 0:
                f["channel_data"].attrs[str(rng.choice(["fp_metadata", "fp_truth"]))] = str(rng.choice(_ATTRS))
                continue
            name = names[rng.integers(len(names))]
            if name not in f:
                continue
            del f[name]
            if what == 1:
                f.create_dataset(name, data=_random_value(rng))


def fuzz_uff(n: int, rng: np.random.Generator, work: Path) -> collections.Counter[str]:
    import h5py

    base = work / "base.uff"
    _corpus_module().write_uff(base, _corpus_module()._base_frames())
    names: list[str] = []
    with h5py.File(base, "r") as f:
        f.visititems(lambda k, o: names.append(k) if isinstance(o, h5py.Dataset) else None)
    out: collections.Counter[str] = collections.Counter()
    path = work / "m.uff"
    for _ in range(n):
        uff_mutant(rng, base, names, path)
        out[_outcome(path)] += 1
    return out, base


# ------------------------------------------------------------------------------------------------ CLI
BAD_VALUES = ["0", "-1", "nan", "inf", "1e999", "", "abc", "1e308", "-1e-300", "3:1", "1,2,3,4", "0x10", "1.5.2"]
#: (option, value) pairs that are valid input (frame 0, a 0 s run; a mirror 1e308 m long is odd, not wrong).
VALID = {("--frames", "0"), ("--frame", "0"), ("--duration", "0"), ("--model", "1e308")}
OPTIONS = {
    "locate": ["--z", "--x", "--spacing", "--n-freq", "--n-out", "--targets", "--svd-threshold", "--max-pfa"]
    + ["--band", "--frames", "--velocity", "--r0", "--model"],
    "track": ["--z", "--spacing", "--n-freq", "--n-out", "--targets", "--svd-threshold", "--max-pfa", "--band"],
    "characterise": ["--angles", "--lengths", "--frame", "--n-freq", "--spacing", "--band", "--z"],
    "process": ["--spacing", "--n-freq", "--n-out", "--targets", "--fifo-depth", "--max-frame-bytes"]
    + ["--status-period", "--duration", "--track-integrate", "--model", "--max-pfa", "--band"],
}


class _Hang(BaseException):
    pass


def _alarm(*_: Any) -> None:
    raise _Hang


def cli_cases(base: Path, corpus: Any) -> list[tuple[str, list[str]]]:
    cases, _ = corpus.build_corpus(base.parent / "corpus")
    out = [(c.category, c.argv) for c in cases]
    b = str(base)
    for cmd, opts in OPTIONS.items():
        head = {
            "locate": ["locate", b, "--model", "point"],
            "track": ["track", b, "--model", "point"],
            "characterise": ["characterise", b],
            "process": ["process", "--model", "point", "--duration", "0", "--listen", "tcp/127.0.0.1:0"],
        }[cmd]
        for opt in opts:
            for v in (v for v in BAD_VALUES if (opt, v) not in VALID):
                if cmd == "locate" and opt == "--r0":  # --r0 goes with a calibration
                    argv = ["locate", b, "--calibration", b, f"{opt}={v}"]
                elif opt == "--model":
                    argv = [x for x in head if x not in ("--model", "point")] + [f"{opt}=mirror:L={v}"]
                else:
                    argv = [*head, f"{opt}={v}"]
                out.append((f"{cmd} {opt}={v}", argv))
    return out


def fuzz_cli(work: Path, timeout_s: int) -> tuple[collections.Counter[str], list[str], float]:
    corpus = _corpus_module()
    base = work / "cli" / "base.uff"
    base.parent.mkdir(parents=True, exist_ok=True)
    corpus.write_uff(base, corpus._base_frames())
    cases = cli_cases(base, corpus)
    out: collections.Counter[str] = collections.Counter()
    bad: list[str] = []
    signal.signal(signal.SIGALRM, _alarm)
    t0 = time.perf_counter()
    for name, argv in cases:
        signal.alarm(timeout_s)
        try:
            o = corpus.run_in_process(argv)
            v = corpus.verdict(o)
            if v == "ok" and "(unexpected;" in o.lines[0]:
                v = "unexpected exception (exit 3)"
        except _Hang:
            v, o = "hang", None
        finally:
            signal.alarm(0)
        out[v] += 1
        if v != "ok":
            bad.append(f"{v}: {name}: {o.lines[-1][:160] if o and o.lines else ''}")
    return out, bad, time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--wire", type=int, default=10_000, help="wire mutants (default 10000)")
    ap.add_argument("--uff", type=int, default=1_500, help="UFF files with mutated datasets/attributes (default 1500)")
    ap.add_argument("--damaged", type=int, default=500, help="UFF files with damaged bytes (default 500)")
    ap.add_argument("--uff-worker", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=int, default=60, help="seconds per CLI case before it counts as a hang")
    ap.add_argument("--rlimit-gib", type=float, default=8.0, help="address-space cap (GiB; 0: none)")
    args = ap.parse_args()
    if args.uff_worker:
        uff_worker(Path(args.uff_worker))
        return 0
    if args.rlimit_gib > 0:
        cap = int(args.rlimit_gib * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    rng = np.random.default_rng(args.seed)
    print(f"fuzz_inputs: seed {args.seed}, {os.cpu_count()} CPUs, address space cap {args.rlimit_gib:g} GiB")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        t = time.perf_counter()
        wire = fuzz_wire(args.wire, rng)
        print(f"wire: {args.wire} mutants in {time.perf_counter() - t:.1f} s: {dict(wire.most_common())}")
        t = time.perf_counter()
        uff, base = fuzz_uff(args.uff, rng, work)
        print(f"uff: {args.uff} mutated files in {time.perf_counter() - t:.1f} s: {dict(uff.most_common())}")
        t = time.perf_counter()
        dmg, hangs = fuzz_damaged_bytes(args.damaged, rng, base, work, args.timeout / 3)
        print(f"uff bytes: {args.damaged} damaged files in {time.perf_counter() - t:.1f} s: {dict(dmg.most_common())}")
        for line in hangs:
            print("   hang:", line)
        with contextlib.redirect_stderr(io.StringIO()):
            cli, bad, secs = fuzz_cli(work, args.timeout)
        print(f"cli: {sum(cli.values())} bad inputs in-process in {secs:.1f} s: {dict(cli.most_common())}")
        for line in bad:
            print("  ", line)
    total = args.wire + args.uff + args.damaged + sum(cli.values())
    others = sum(v for k, v in [*wire.items(), *uff.items(), *dmg.items()] if k.startswith("OTHER")) + sum(
        v for k, v in cli.items() if k != "ok"
    )
    print(f"HDF5 hangs on damaged bytes (outside Python's reach): {dmg['hang (HDF5, killed)']}")
    print(f"total: {total} inputs; {others} outside the project's error types or not one clean line")
    return 0 if others == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
