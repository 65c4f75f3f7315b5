"""Bad input through the real `fp` entry: one line naming the option, a non-zero exit, no traceback —
and a last-resort handler for anything unexpected (the traceback only under --debug)."""

from __future__ import annotations

import pytest

import services.cli as cli
from services.cli import main


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> str:
    d = tmp_path_factory.mktemp("err")
    assert main(["simulate", "sinking-cylinder", "--quick", "--out", str(d), "--frames", "1"]) == 0
    return str(d / "frames.uff")


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["demo", "--scenario", "nope"], "scenario 'nope'"),
        (["locate", "{frames}", "--model", "point", "--z", "0:1e999mm"], "--z: expected a finite number"),
        (["locate", "{frames}", "--model", "point", "--frames", "3:1"], "--frames"),
    ],
)
def test_bad_input_is_one_line_and_a_nonzero_exit(argv, needle, frames, capsys) -> None:
    capsys.readouterr()
    assert main([a.format(frames=frames) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and "Traceback" not in err[0]


def test_unexpected_errors_are_one_line_unless_debug(monkeypatch, capsys, tmp_path) -> None:
    def boom(args) -> int:
        raise RuntimeError("disk on fire")

    parser = cli.build_parser()
    real = parser.parse_args

    def parse(argv):
        ns = real(argv)
        ns.func = boom
        return ns

    monkeypatch.setattr(parser, "parse_args", parse)
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    assert main(["simulate", "sinking-cylinder", "--quick", "--out", str(tmp_path)]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "RuntimeError: disk on fire" in err and "--debug" in err
    assert main(["--debug", "simulate", "sinking-cylinder", "--quick", "--out", str(tmp_path)]) == 3
    assert "Traceback" in capsys.readouterr().err
