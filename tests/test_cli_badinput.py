"""Bad-input corpus through the real `fp` (issue 13): generated corrupt UFF files and bad arguments, every
one answered by one line on stderr, a non-zero exit and no traceback.

The corpus (:func:`build_corpus`) covers: broken UFF files (zero samples, zero frames, non-numeric and
non-finite metadata, declared shapes far beyond the memory budget, truncated, text and empty files, wrong
geometry, RF near float32's limit), bad option values (ranges, counts, lengths, models, bands, frame
selections, unknown scenarios and options) and sizes beyond the memory budget (grids, frequencies, output
directions). Cases run in-process through ``services.cli.main`` (cheap); a representative few run as
subprocesses of the installed ``fp``. ``bench/fuzz_inputs.py`` reuses this corpus for its long run.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest

from fpcore import Acquisition, PlaneWaveSequence, Probe
from fpcore.io import write_uff

D = "channel_data"


@dataclass
class Case:
    """One bad input: a category, the `fp` arguments and what the error line must mention."""

    category: str
    argv: list[str]
    needle: str = ""


def _base_frames() -> list[Acquisition]:
    """Two small valid frames (16 elements, 3 plane waves, 400 samples) that every mutation starts from."""
    probe = Probe.linear(16, 0.3e-3, 2.5e6, 1.5e6)
    seq = PlaneWaveSequence.from_angles(np.linspace(-5, 5, 3))
    rng = np.random.default_rng(0)
    rf = rng.standard_normal((16, 3, 400)).astype(np.float32)
    truth = {"band_hz": [1.5e6, 3.5e6]}
    return [Acquisition(rf, 20e6, 0.0, 1500.0, probe, seq, frame_index=i, truth=truth) for i in range(2)]


def _replace(f: h5py.File, key: str, value: object, **kw: object) -> None:
    del f[key]
    f.create_dataset(key, data=value, **kw)


def _uff_mutations() -> dict[str, tuple[Callable[[h5py.File], None], str]]:
    """name → (edit of the base file, a word the error line must contain)."""

    def data(shape: tuple[int, ...], dtype: str = "<f4") -> Callable[[h5py.File], None]:
        return lambda f: _replace(f, f"{D}/data", np.zeros(shape, dtype))

    def scalar(key: str, value: object) -> Callable[[h5py.File], None]:
        return lambda f: _replace(f, f"{D}/{key}", value)

    def sparse(shape: tuple[int, ...]) -> Callable[[h5py.File], None]:
        def edit(f: h5py.File) -> None:
            del f[f"{D}/data"]
            f.create_dataset(f"{D}/data", shape=shape, dtype="<f4", chunks=(1, 1, 1, min(shape[-1], 1024)))

        return edit

    def attr(key: str, value: str) -> Callable[[h5py.File], None]:
        def edit(f: h5py.File) -> None:
            f[D].attrs[key] = value

        return edit

    def meta(**kw: object) -> Callable[[h5py.File], None]:
        def edit(f: h5py.File) -> None:
            m = json.loads(f[D].attrs["fp_metadata"])
            m.update(kw)
            f[D].attrs["fp_metadata"] = json.dumps(m)

        return edit

    def rf_scale(value: float) -> Callable[[h5py.File], None]:
        def edit(f: h5py.File) -> None:
            d = f[f"{D}/data"]
            d[...] = np.clip(np.sign(d[...]) * value, -3.4e38, 3.4e38).astype("<f4")

        return edit

    def wave(key: str, value: object) -> Callable[[h5py.File], None]:
        return lambda f: _replace(f, f"{D}/sequence/sequence_0002/{key}", value)

    def drop(key: str) -> Callable[[h5py.File], None]:
        def edit(f: h5py.File) -> None:
            del f[key]

        return edit

    nan = float("nan")
    return {
        "zero_samples": (data((2, 3, 16, 0)), "sample"),
        "zero_frames": (data((0, 3, 16, 400)), "frame"),
        "one_sample": (data((2, 3, 16, 1)), "sample"),
        "zero_channels": (data((2, 3, 0, 400)), "data"),
        "wrong_channels": (data((2, 3, 15, 400)), "data"),
        "wrong_waves": (data((2, 4, 16, 400)), "data"),
        "data_1d": (data((400,)), "data"),
        "data_5d": (data((1, 2, 3, 16, 400)), "data"),
        "data_complex": (data((2, 3, 16, 400), "<c8"), "data"),
        "data_strings": (lambda f: _replace(f, f"{D}/data", np.array([b"x"] * 8)), "data"),
        "data_group": (lambda f: (f.__delitem__(f"{D}/data"), f.create_group(f"{D}/data")), "data"),
        "data_missing": (drop(f"{D}/data"), "data"),
        "data_nan": (lambda f: f[f"{D}/data"].__setitem__((0, 0, 0, 5), nan), "finite"),
        "data_inf": (lambda f: f[f"{D}/data"].__setitem__((1, 2, 3, 7), np.inf), "finite"),
        "rf_near_float32_max": (rf_scale(1e38), "data"),
        "rf_1e30": (rf_scale(1e30), "data"),
        "sparse_2e31_samples": (sparse((1, 3, 16, 2**31)), "budget"),
        "sparse_1e6_frames": (sparse((1_000_000, 3, 16, 400)), "budget"),
        "fs_string": (scalar("sampling_frequency", np.array([b"fast"])), "sampling_frequency"),
        "fs_zero": (scalar("sampling_frequency", [[0.0]]), "sampling_frequency"),
        "fs_nan": (scalar("sampling_frequency", [[nan]]), "sampling_frequency"),
        "fs_inf": (scalar("sampling_frequency", [[np.inf]]), "sampling_frequency"),
        "fs_1e300": (scalar("sampling_frequency", [[1e300]]), "sampling frequency"),
        "fs_vector": (scalar("sampling_frequency", [1.0, 2.0]), "sampling_frequency"),
        "c0_negative": (scalar("sound_speed", [[-1500.0]]), "sound_speed"),
        "c0_string": (scalar("sound_speed", np.array([b"water"])), "sound_speed"),
        "t0_nan": (scalar("initial_time", [[nan]]), "initial_time"),
        "t0_inf": (scalar("initial_time", [[np.inf]]), "initial_time"),
        "t0_string": (scalar("initial_time", np.array([b"now"])), "initial_time"),
        "modulation_iq": (scalar("modulation_frequency", [[5e6]]), "modulation_frequency"),
        "modulation_nan": (scalar("modulation_frequency", [[nan]]), "modulation_frequency"),
        "geometry_transposed": (lambda f: _replace(f, f"{D}/probe/geometry", np.zeros((16, 7))), "geometry"),
        "geometry_nan": (lambda f: f[f"{D}/probe/geometry"].__setitem__((0, 3), nan), "probe"),
        "geometry_inf": (lambda f: f[f"{D}/probe/geometry"].__setitem__((2, 3), np.inf), "probe"),
        "geometry_collapsed": (lambda f: f[f"{D}/probe/geometry"].__setitem__(slice(None), 0.0), "probe"),
        "geometry_strings": (lambda f: _replace(f, f"{D}/probe/geometry", np.array([b"a"] * 7)), "geometry"),
        "probe_missing": (drop(f"{D}/probe"), "probe"),
        "pitch_negative": (meta(probe={"pitch": -3e-4, "centre_frequency": 2.5e6, "bandwidth": 1.5e6}), "pitch"),
        "pitch_string": (meta(probe={"pitch": "wide", "centre_frequency": 2.5e6, "bandwidth": 1.5e6}), "pitch"),
        "centre_frequency_string": (meta(probe={"pitch": 3e-4, "centre_frequency": "x", "bandwidth": 1.5e6}), "probe"),
        "bandwidth_negative": (meta(probe={"pitch": 3e-4, "centre_frequency": 2.5e6, "bandwidth": -1.0}), "probe"),
        "meta_probe_list": (meta(probe=[1, 2, 3]), "probe"),
        "timestamps_strings": (meta(timestamp=["a", "b"]), "timestamp"),
        "frame_index_strings": (meta(frame_index=["a", "b"]), "frame_index"),
        "frame_index_negative": (meta(frame_index=[-1, -2]), "frame_index"),
        "frame_index_floats": (meta(frame_index=[0.5, 1.5]), "frame_index"),
        "sines_strings": (meta(sines=[["a", "b"]] * 3), "sines"),
        "meta_not_json": (attr("fp_metadata", "{not json"), "fp_metadata"),
        "meta_is_list": (attr("fp_metadata", "[1, 2]"), "fp_metadata"),
        "truth_not_json": (attr("fp_truth", "[{"), "fp_truth"),
        "truth_huge_number": (attr("fp_truth", '[{"band_hz": [1e400, 2e400]}, {}]'), "band_hz"),
        "azimuth_backwards": (wave("source/azimuth", [[3.0]]), "azimuth"),
        "azimuth_nan": (wave("source/azimuth", [[nan]]), "azimuth"),
        "azimuth_string": (wave("source/azimuth", np.array([b"left"])), "azimuth"),
        "wavefront_photoacoustic": (wave("wavefront", [[2]]), "wavefront"),
        "wavefront_nan": (wave("wavefront", [[nan]]), "wavefront"),
        "focused_wave": (lambda f: (wave("wavefront", [[1]])(f), wave("source/distance", [[0.02]])(f)), "plane"),
        "delay_nan": (wave("delay", [[nan]]), "delay"),
        "delay_huge": (wave("delay", [[1e6]]), "delay"),
        "wave_sound_speed": (wave("sound_speed", [[1400.0]]), "sound_speed"),
        "sequence_missing": (drop(f"{D}/sequence"), "sequence"),
    }


def _raw_files(base: Path, d: Path) -> dict[str, tuple[Path, str]]:
    """Files that are not UFF at all."""
    raw = base.read_bytes()
    files = {
        "empty": b"",
        "text": b"frames: 1\nthis is not HDF5\n",
        "truncated_90": raw[: len(raw) // 10],
        "truncated_50": raw[: len(raw) // 2],
        "header_only": raw[:512],
        "flipped_bytes": bytes(b ^ 0xFF if 64 <= i < 2048 else b for i, b in enumerate(raw)),
    }
    out = {}
    for name, content in files.items():
        p = d / f"{name}.uff"
        p.write_bytes(content)
        out[name] = (p, "uff")
    h5 = d / "plain_hdf5.uff"
    with h5py.File(h5, "w") as f:
        f.create_dataset("x", data=np.arange(4))
    out["plain_hdf5"] = (h5, "dataset")
    out["directory"] = (d, "uff")
    out["missing"] = (d / "does-not-exist.uff", "uff")
    return out


def build_corpus(d: Path) -> tuple[list[Case], Path]:
    """Write the corrupt files into ``d``; return the cases and the valid base file."""
    d.mkdir(parents=True, exist_ok=True)
    base = d / "base.uff"
    write_uff(base, _base_frames())
    cases: list[Case] = []
    bad: dict[str, tuple[Path, str]] = {}
    for name, (edit, needle) in _uff_mutations().items():
        p = d / f"{name}.uff"
        shutil.copyfile(base, p)
        with h5py.File(p, "r+") as f:
            edit(f)
        bad[name] = (p, needle)
    raw = _raw_files(base, d)
    for name, (p, needle) in {**bad, **raw}.items():
        cases.append(Case(f"uff:{name}", ["locate", str(p), "--model", "point"], needle))
    # The same files as a calibration, and through the other UFF readers (track, characterise).
    for name in ("zero_samples", "zero_frames", "fs_string", "sparse_2e31_samples", "truncated_90", "text", "empty"):
        p, needle = {**bad, **raw}[name]
        cases.append(Case(f"uff-calibration:{name}", ["locate", str(base), "--calibration", str(p)], needle))
        cases.append(Case(f"uff-track:{name}", ["track", str(p), "--model", "point"], needle))
        cases.append(Case(f"uff-characterise:{name}", ["characterise", str(p)], needle))
    for name in ("zero_frames", "fs_nan", "sparse_2e31_samples", "text"):
        p, needle = {**bad, **raw}[name]
        cases.append(Case(f"uff-process:{name}", ["process", "--calibration", str(p), "--duration", "0"], needle))
    cases += _argument_cases(base)
    return cases, base


def _budget_first(argv: list[str]) -> list[str]:
    """'--budget SIZE' in a case's options → the global `fp --memory-budget SIZE` (so a case's verdict does
    not depend on the machine's RAM)."""
    if "--budget" not in argv:
        return argv
    i = argv.index("--budget")
    return ["--memory-budget", argv[i + 1], *argv[:i], *argv[i + 2 :]]


def _argument_cases(base: Path) -> list[Case]:
    b = str(base)
    loc = ["locate", b, "--model", "point"]
    opts: list[tuple[str, list[str], str]] = [
        ("z_overflow", ["--z", "0:1e999mm"], "--z"),
        ("z_reversed", ["--z", "10mm:5mm"], "--z"),
        ("z_text", ["--z", "deep"], "--z"),
        ("z_one_value", ["--z", "10mm"], "--z"),
        ("z_nan", ["--z", "nan:1"], "--z"),
        ("x_reversed", ["--x", "5mm:1mm"], "--x"),
        ("x_huge", ["--x=-1e300:1e300"], "--x"),
        ("grid_metres", ["--x=-1m:1m", "--z", "10mm:2m", "--budget", "8GiB"], "budget"),
        ("frames_reversed", ["--frames", "3:1"], "--frames"),
        ("frames_text", ["--frames", "a:b"], "--frames"),
        ("frames_negative", ["--frames=-1"], "--frames"),
        ("frames_beyond", ["--frames", "99"], "frames"),
        ("frames_empty_range", ["--frames", "5:9"], "frames"),
        ("targets_zero", ["--targets", "0"], "--targets"),
        ("targets_negative", ["--targets=-3"], "--targets"),
        ("targets_float", ["--targets", "1.5"], "--targets"),
        ("targets_huge", ["--targets", "100000000"], "--targets"),
        ("spacing_zero", ["--spacing", "0"], "--spacing"),
        ("spacing_negative", ["--spacing=-1mm"], "--spacing"),
        ("spacing_1um", ["--spacing", "1um", "--budget", "8GiB"], "budget"),
        ("spacing_10um_small_budget", ["--spacing", "10um", "--budget", "64MiB"], "budget"),
        ("spacing_1e-300", ["--spacing", "1e-300"], "--spacing"),
        ("spacing_text", ["--spacing", "fine"], "--spacing"),
        ("n_freq_zero", ["--n-freq", "0"], "--n-freq"),
        ("n_freq_negative", ["--n-freq=-4"], "--n-freq"),
        ("n_freq_1e8", ["--n-freq", "100000000", "--budget", "8GiB"], "budget"),
        ("n_freq_float", ["--n-freq", "1e8"], "--n-freq"),
        ("n_out_zero", ["--n-out", "0"], "--n-out"),
        ("n_out_negative", ["--n-out=-2"], "--n-out"),
        ("n_out_1e5", ["--n-out", "100000", "--budget", "2GiB"], "budget"),
        ("svd_zero", ["--svd-threshold", "0"], "--svd-threshold"),
        ("svd_nan", ["--svd-threshold", "nan"], "--svd-threshold"),
        ("svd_two", ["--svd-threshold", "2"], "--svd-threshold"),
        ("max_pfa_zero", ["--max-pfa", "0"], "--max-pfa"),
        ("max_pfa_nan", ["--max-pfa", "nan"], "--max-pfa"),
        ("max_pfa_text", ["--max-pfa", "low"], "--max-pfa"),
        ("band_reversed", ["--band", "3MHz:1MHz"], "--band"),
        ("band_text", ["--band", "wide"], "--band"),
        ("band_overflow", ["--band", "1:1e999"], "--band"),
        ("band_above_nyquist", ["--band", "1MHz:50MHz"], "band"),
        ("band_unit", ["--band", "1MHz:3parsec"], "--band"),
        ("band_negative", ["--band=-1MHz:3MHz"], "--band"),
        ("velocity_text", ["--velocity", "fast"], "--velocity"),
        ("velocity_nan", ["--velocity", "nan,0"], "--velocity"),
        ("dataset_missing", ["--dataset", "nope"], "dataset"),
        ("unknown_option", ["--bogus"], "--bogus"),
    ]
    cases = [Case(f"arg:locate:{name}", _budget_first(loc + extra), needle) for name, extra, needle in opts]
    models = [
        ("mirror_negative_L", "mirror:L=-2mm", "L"),
        ("mirror_zero_L", "mirror:L=0", "L"),
        ("mirror_alpha_nan", "mirror:L=2mm,alpha=nan", "alpha"),
        ("mirror_alpha_inf", "mirror:L=2mm,alpha=inf", "alpha"),
        ("mirror_alpha_text", "mirror:L=2mm,alpha=steep", "alpha"),
        ("mirror_no_L", "mirror:alpha=10", "L"),
        ("mirror_L_text", "mirror:L=long", "L"),
        ("mirror_L_overflow", "mirror:L=1e999", "L"),
        ("mirror_unknown_key", "mirror:L=2mm,beta=3", "beta"),
        ("model_unknown", "sphere", "model"),
        ("model_empty", "", "model"),
    ]
    cases += [Case(f"arg:model:{n}", ["locate", b, "--model", m], needle) for n, m, needle in models]
    cal = ["locate", b, "--calibration", b]
    cases += [
        Case("arg:calibration:diameter_negative", cal + ["--r0", "0,10mm", "--diameter=-5mm"], "--diameter"),
        Case("arg:calibration:diameter_nan", cal + ["--r0", "0,10mm", "--diameter", "nan"], "--diameter"),
        Case("arg:calibration:r0_text", cal + ["--r0", "here"], "--r0"),
        Case("arg:calibration:r0_four", cal + ["--r0", "1,2,3,4"], "--r0"),
        Case("arg:calibration:r0_overflow", cal + ["--r0", "0,1e999"], "--r0"),
        Case("arg:calibration:no_truth", cal, "--r0"),
        Case("arg:locate:no_source", ["locate", b], "--calibration"),
        Case("arg:locate:both_sources", loc + ["--calibration", b], "--calibration"),
    ]
    trk = ["track", b, "--model", "point"]
    cases += [
        Case("arg:track:frames_reversed", trk + ["--frames", "3:1"], "--frames"),
        Case("arg:track:targets_zero", trk + ["--targets", "0"], "--targets"),
        Case("arg:track:spacing_zero", trk + ["--spacing", "0"], "--spacing"),
        Case("arg:track:n_freq_zero", trk + ["--n-freq", "0"], "--n-freq"),
        Case("arg:track:z_overflow", trk + ["--z", "0:1e999mm"], "--z"),
    ]
    ch = ["characterise", b]
    cases += [
        Case("arg:characterise:angles_text", ch + ["--angles", "a:b:c"], "--angles"),
        Case("arg:characterise:angles_zero_step", ch + ["--angles=-10:10:0"], "--angles"),
        Case("arg:characterise:lengths_negative", ch + ["--lengths=-1mm:2mm:3"], "--lengths"),
        Case("arg:characterise:lengths_zero_count", ch + ["--lengths", "1mm:2mm:0"], "--lengths"),
        Case("arg:characterise:lengths_huge_count", ch + ["--lengths", "1mm:2mm:100000000"], "--lengths"),
        Case("arg:characterise:frame_negative", ch + ["--frame=-1"], "--frame"),
        Case("arg:characterise:frame_beyond", ch + ["--frame", "7"], "frame"),
        Case("arg:characterise:spacing_zero", ch + ["--spacing", "0"], "--spacing"),
        Case("arg:characterise:n_freq_zero", ch + ["--n-freq", "0"], "--n-freq"),
    ]
    cases += [
        Case("arg:demo:scenario_unknown", ["demo", "--scenario", "nope"], "nope"),
        Case("arg:demo:frames_zero", ["demo", "--frames", "0"], "--frames"),
        Case("arg:demo:frames_negative", ["demo", "--frames=-3"], "--frames"),
        Case("arg:simulate:scenario_unknown", ["simulate", "nope", "--out", str(base.parent / "sim")], "nope"),
        Case(
            "arg:simulate:frames_zero",
            ["simulate", "sinking-cylinder", "--quick", "--frames", "0", "--out", "x"],
            "--frames",
        ),
        Case(
            "arg:simulate:out_is_file",
            ["simulate", "sinking-cylinder", "--quick", "--frames", "1", "--out", str(base)],
            "exists",
        ),
        Case("arg:process:scenario_unknown", ["process", "--scenario", "nope", "--duration", "0"], "nope"),
        Case(
            "arg:process:targets_zero",
            ["process", "--model", "point", "--targets", "0", "--duration", "0"],
            "--targets",
        ),
        Case(
            "arg:process:spacing_zero",
            ["process", "--model", "point", "--spacing", "0", "--duration", "0"],
            "--spacing",
        ),
        Case(
            "arg:process:n_freq_zero", ["process", "--model", "point", "--n-freq", "0", "--duration", "0"], "--n-freq"
        ),
        Case("arg:process:n_out_zero", ["process", "--model", "point", "--n-out", "0", "--duration", "0"], "--n-out"),
        Case("arg:process:model_bad", ["process", "--model", "mirror:L=-2mm", "--duration", "0"], "L"),
        Case(
            "arg:process:fifo_zero",
            ["process", "--model", "point", "--fifo-depth", "0", "--duration", "0"],
            "--fifo-depth",
        ),
        Case(
            "arg:process:max_bytes_zero", ["process", "--model", "point", "--max-frame-bytes", "0"], "--max-frame-bytes"
        ),
        Case("arg:process:status_nan", ["process", "--model", "point", "--status-period", "nan"], "--status-period"),
        Case("arg:process:duration_negative", ["process", "--model", "point", "--duration=-1"], "--duration"),
        Case("arg:process:listen_bogus", ["process", "--model", "point", "--listen", "carrier-pigeon"], "endpoint"),
        Case(
            "arg:process:track_integrate_zero",
            ["process", "--model", "point", "--track-integrate", "0"],
            "--track-integrate",
        ),
        Case("arg:publish:uff_missing", ["publish", "--uff", str(base.parent / "nope.uff")], "nope.uff"),
        Case("arg:publish:rate_zero", ["publish", "--uff", b, "--rate", "0"], "--rate"),
        Case("arg:publish:frames_negative", ["publish", "--uff", b, "--frames=-1"], "--frames"),
        Case("arg:publish:repeat_zero", ["publish", "--uff", b, "--repeat", "0"], "--repeat"),
        Case("arg:fp:no_command", [], "command"),
        Case("arg:fp:unknown_command", ["teleport"], "teleport"),
    ]
    return cases


@dataclass
class Outcome:
    rc: int
    lines: list[str]
    seconds: float

    @property
    def traceback(self) -> bool:
        return any("Traceback" in line for line in self.lines)


def run_in_process(argv: list[str]) -> Outcome:
    """`fp ARGV` through ``services.cli.main`` in this process; stderr captured (argparse's exits too)."""
    from services.cli import main

    err, out = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            rc = main(list(argv))
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    lines = [line for line in err.getvalue().splitlines() if line.strip()]
    return Outcome(int(rc), lines, time.perf_counter() - t0)


def run_subprocess(argv: list[str], timeout: float = 120.0) -> Outcome:
    """`fp ARGV` as a real process (``python -m services.cli``); a hang counts as rc 124."""
    t0 = time.perf_counter()
    try:
        p = subprocess.run(
            [sys.executable, "-m", "services.cli", *argv], capture_output=True, text=True, timeout=timeout
        )
        rc, err = p.returncode, p.stderr
    except subprocess.TimeoutExpired as exc:
        rc, err = 124, (exc.stderr or b"").decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
    lines = [line for line in err.splitlines() if line.strip()]
    return Outcome(rc, lines, time.perf_counter() - t0)


def verdict(o: Outcome) -> str:
    """'ok' (one clean error line, non-zero exit), 'traceback', 'hang', 'zero-exit' or 'not-one-line'."""
    if o.rc == 124:
        return "hang"
    if o.traceback:
        return "traceback"
    if o.rc == 0:
        return "zero-exit"
    if len(o.lines) != 1 or "error" not in o.lines[0]:
        return "not-one-line"
    return "ok"


# ----------------------------------------------------------------------------------------------- tests


@pytest.fixture(scope="module")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Case], Path]:
    return build_corpus(tmp_path_factory.mktemp("badinput"))


def test_corpus_is_large_and_covers_every_category(corpus) -> None:
    cases, _ = corpus
    assert len(cases) >= 150
    kinds = {c.category.split(":")[0] for c in cases}
    assert {"uff", "uff-calibration", "uff-track", "uff-characterise", "uff-process", "arg"} <= kinds
    for needed in ("zero_samples", "zero_frames", "fs_string", "sparse_2e31", "z_overflow", "frames_reversed"):
        assert any(needed in c.category for c in cases), needed
    for needed in ("targets_zero", "spacing_zero", "n_freq_zero", "diameter_negative", "mirror_negative_L"):
        assert any(needed in c.category for c in cases), needed
    assert any("alpha_nan" in c.category for c in cases) and any("rf_near_float32_max" in c.category for c in cases)


def test_every_bad_input_is_one_line_and_a_nonzero_exit(corpus) -> None:
    """The whole corpus in-process: 0 tracebacks, 0 zero exits, one line naming what is wrong."""
    cases, _ = corpus
    failures = []
    for case in cases:
        o = run_in_process(case.argv)
        v = verdict(o)
        if v != "ok":
            failures.append(f"{case.category}: {v} rc={o.rc} {o.lines[-3:]}")
        elif case.needle and case.needle.lower() not in o.lines[0].lower():
            failures.append(f"{case.category}: the line does not mention {case.needle!r}: {o.lines[0]}")
    assert not failures, f"{len(failures)}/{len(cases)} bad inputs mishandled:\n" + "\n".join(failures)


@pytest.mark.parametrize(
    "name",
    ["arg:locate:z_overflow", "uff:zero_samples", "uff:sparse_2e31_samples", "arg:demo:scenario_unknown"],
)
def test_representative_bad_inputs_through_a_real_process(corpus, name) -> None:
    cases, _ = corpus
    case = next(c for c in cases if c.category == name)
    o = run_subprocess(case.argv)
    assert verdict(o) == "ok", (o.rc, o.lines)
    assert case.needle.lower() in o.lines[0].lower()


def test_the_base_file_itself_is_accepted(corpus, tmp_path) -> None:
    """The corpus's base file is valid: each case fails because of its one fault."""
    _, base = corpus
    o = run_in_process(["locate", str(base), "--model", "point", "--json", str(tmp_path / "r.json")])
    assert o.rc == 0, o.lines
    assert len(json.loads((tmp_path / "r.json").read_text())["frames"]) == 2


def test_a_second_processor_on_a_taken_port_is_one_line(capsys) -> None:
    """`fp process` while its port is taken (loopback): one line naming the endpoint, exit 2."""
    from services.bus import BusConfig, free_port, open_session

    port = free_port()
    with open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"], connect=[])):
        o = run_in_process(["process", "--model", "point", "--listen", f"tcp/127.0.0.1:{port}", "--duration", "0"])
    assert verdict(o) == "ok" and o.rc == 2, o.lines
    assert f"127.0.0.1:{port}" in o.lines[0] and "in use" in o.lines[0]
