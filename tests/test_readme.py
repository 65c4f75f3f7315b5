"""The README runs as written (issue 14): its Python blocks, and every `fp …` line of its shell blocks.

The `fp` lines run in README order in one working folder (with `recordings/` linked in), on the quick data
the README's own `fp simulate` lines write. A command that finishes by itself runs in-process (`main`,
exit code 0); one that runs until stopped — `fp process`, `fp record`, `fp view --serve/--live/--foxglove` —
runs as a background process that the test stops by pid once it has served (the README's `kill %1 %2`).
To keep the test quick, REDUCED appends options to some lines (fewer frames, a coarser grid; the 2-D
scenario for the demo and the streaming chain) and the streaming nodes get loopback endpoints of their
own; `make` lines are not run (`make test` is this suite, `make demo` is `fp demo`). `broken.mcap` (the
input of `fp recover`) is the sample recording without its summary, as a killed writer leaves it.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from services.bus import free_port
from services.cli import main
from services.recording import iter_raw
from services.topics import parse_key

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TEXT = README.read_text()
BLOCKS = re.findall(r"```python\n(.*?)```", TEXT, re.S)
SHELL = re.findall(r"```bash\n(.*?)```", TEXT, re.S)

GRID_2D = ["--spacing", "0.5mm", "--n-freq", "16"]
#: README line prefix → options appended in the test (only to make it quick; the line itself is unchanged).
REDUCED: dict[str, list[str]] = {
    "demo": ["--scenario", "sinking-cylinder", "--frames", "1", "--out", "demo-out"],
    "simulate sinking-sphere": ["--frames", "1"],
    "simulate sinking-cylinder": ["--frames", "2"],
    "simulate muscle-fibres": ["--frames", "1"],
    "locate sim/": ["--spacing", "1mm", "--n-freq", "16"],
    "locate sim2d/": GRID_2D,
    "locate fibres/": GRID_2D,
    "track sim2d/": GRID_2D,
    "characterise": GRID_2D,
    "process": ["--scenario", "sinking-cylinder", *GRID_2D],
    "publish": ["--scenario", "sinking-cylinder", "--frames", "1", "--wait-timeout", "90"],
}
FINITE = {"simulate", "locate", "track", "characterise", "convert", "figure", "recover", "demo", "publish"}


def fp_lines() -> list[list[str]]:
    """Every `fp …` command of the README's shell blocks (lines split at `;` and `&`, comments dropped)."""
    out = []
    for block in SHELL:
        for line in block.splitlines():
            for part in re.split(r"[;&]", line.split("#", 1)[0]):
                words = shlex.split(part)
                if words[:1] == ["fp"]:
                    out.append(words[1:])
    return out


def _reduced(args: list[str]) -> list[str]:
    joined = " ".join(args)
    extra = [opt for prefix, opts in REDUCED.items() if joined.startswith(prefix) for opt in opts]
    return args + extra


def _runs_until_stopped(args: list[str]) -> bool:
    return args[0] in ("process", "record") or (
        args[0] == "view" and any(a in args for a in ("--serve", "--live", "--foxglove"))
    )


class Background:
    """`python -m services.cli ARGS` in the working folder, stopped by pid (SIGTERM, then SIGKILL)."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.args = args
        self.log = cwd / f"bg-{args[0]}-{free_port()}.log"
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "services.cli", *args], cwd=cwd, stdout=log, stderr=log)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> int | None:
        if self.alive():
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        return self.proc.returncode


def _wait_port(port: int, proc: Background, timeout: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.alive():
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.3)
    return False


def test_readme_has_a_library_example_and_says_how_to_stop_the_nodes() -> None:
    assert BLOCKS and "fpcore.locate" in BLOCKS[0]
    lines = [ln.strip() for block in SHELL for ln in block.splitlines()]
    assert any(ln.startswith("kill %1 %2") for ln in lines)  # the streaming example stops its nodes
    cmds = fp_lines()
    assert ["--version"] in cmds and any(c[0] == "convert" for c in cmds)
    # Every file a command reads is written by an earlier line (or shipped): nothing like DATA.uff or fibres.uff.
    assert not any(re.search(r"\bDATA\.uff|\bCAL\.uff|…|\[--", " ".join(c)) for c in cmds)


@pytest.mark.parametrize("code", BLOCKS)
def test_readme_python_block_runs(code: str, capsys) -> None:
    ns: dict = {"__name__": "readme"}
    exec(compile(code, str(README), "exec"), ns)
    assert "PFA" in capsys.readouterr().out  # the example prints its detection
    found, acq = ns.get("found"), ns.get("acq")
    if found is not None and acq is not None:  # the library example: the calibrated target, where the truth is
        truth = [np.asarray(t.position_m) for t in acq.ground_truth.targets]
        assert found.detections
        for d in found.detections:
            assert min(np.linalg.norm(np.asarray(d.position_m) - p) for p in truth) < 1e-3


@pytest.mark.timeout(400)
def test_readme_command_lines_run(tmp_path, monkeypatch, capsys) -> None:
    work = tmp_path / "work"
    work.mkdir()
    (work / "recordings").symlink_to(ROOT / "recordings")
    sample = ROOT / "recordings" / "sinking-sphere-quick.mcap"
    raw = sample.read_bytes()
    (work / "broken.mcap").write_bytes(raw[: len(raw) - 64])  # footer and end of the summary gone
    monkeypatch.chdir(work)
    hub = free_port()
    background: list[Background] = []
    ran = []
    try:
        for args in fp_lines():
            cmd = _reduced(args)
            if _runs_until_stopped(cmd):
                if cmd[0] == "process":
                    cmd += ["--listen", f"tcp/127.0.0.1:{hub}", "--connect", "none"]
                elif cmd[0] == "record":
                    cmd += ["--connect", f"tcp/127.0.0.1:{hub}"]
                elif "--serve" in cmd:
                    port = free_port()
                    cmd += ["--port", str(port), "--grpc-port", str(free_port())]
                else:  # live viewers: a bus of their own (the streaming chain is over by now)
                    cmd += ["--listen", f"tcp/127.0.0.1:{free_port()}", "--connect", "none"]
                bg = Background(cmd, work)
                background.append(bg)
                if "--serve" in cmd:
                    assert _wait_port(port, bg), bg.log.read_text()[-2000:]
                    assert bg.stop() is not None
                elif cmd[0] == "view":
                    time.sleep(3)
                    assert bg.alive(), bg.log.read_text()[-2000:]
                    bg.stop()
                ran.append(args)
                continue
            if cmd[0] == "publish":
                cmd += ["--connect", f"tcp/127.0.0.1:{hub}"]
            if cmd[0] in FINITE or cmd[0].startswith("-") or "--help" in cmd:
                try:
                    rc = main(cmd)
                except SystemExit as exc:  # --help, --version
                    rc = int(exc.code or 0)
            else:  # a command this test does not know: as a process, it must finish by itself
                rc = subprocess.run([sys.executable, "-m", "services.cli", *cmd], cwd=work, timeout=120).returncode
            err = capsys.readouterr().err
            assert rc == 0, f"fp {' '.join(cmd)}: exit {rc}\n{err[-2000:]}"
            if cmd[0] == "publish":  # the README's `kill %1 %2`: the processor and the recorder, by pid
                time.sleep(1.0)
                for bg in background:
                    if bg.args[0] in ("process", "record"):
                        assert bg.alive(), bg.log.read_text()[-2000:]
                        bg.stop()
            ran.append(args)
    finally:
        for bg in background:
            bg.stop()
    assert len(ran) == len(fp_lines())
    # What the lines wrote: both spheres' calibrations, the fibres file, the recording of the streaming chain.
    assert (work / "sim" / "calibration_sphere2.uff").is_file() and not (work / "sim" / "calibration.uff").exists()
    assert (work / "fibres" / "frames.uff").is_file() and (work / "fibres.png").stat().st_size > 10_000
    assert (work / "fixed.mcap").is_file()
    recorded = Counter(parse_key(ch.topic)[1] for _, ch, _ in iter_raw(work / "rec.mcap"))
    assert recorded["rf"] == 1 and recorded["detections"] == 1, recorded  # the frame and its results
    shutil.rmtree(work / "sim", ignore_errors=True)


def test_output_is_plain_and_unwrapped_when_not_a_terminal(capsys) -> None:
    """README: piped output keeps its progress (plain lines) and its tables (never wrapped)."""
    from rich.table import Table

    from services.cli.output import make_console, progress

    console = make_console()  # pytest captures stdout: not a terminal
    assert not console.is_terminal
    with progress(console) as bar:
        task = bar.add_task("γ-maps", total=4)
        for _ in range(4):
            bar.advance(task)
    table = Table(title="fp locate a/very/long/path/to/frames.uff")
    for k in range(10):
        table.add_column(f"column number {k}")
    table.add_row(*[f"value {k} with some width" for k in range(10)])
    console.print(table)
    out = capsys.readouterr().out
    assert "γ-maps 1/4 (" in out and "γ-maps 4/4 (" in out and "\x1b[" not in out
    row = next(line for line in out.splitlines() if "value 0" in line)
    assert "value 9 with some width" in row and len(row) > 200  # one line, not wrapped at 80 columns
