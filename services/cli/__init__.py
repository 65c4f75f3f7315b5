"""`fp` — the command line front door (``main``; the ``fp`` entry point).

`fp demo` runs the main job on the built-in simulated scenario (``services.cli.demo``). `fp locate`, `fp track`,
`fp characterise` and `fp simulate` work on UFF files; `fp publish|process|record|recover` run the
streaming nodes one by one; `fp view` and `fp figure` show recordings. Each command lives in its own
module here (argument parser and run function); the work is done by the rest of ``services`` and by
``fpcore``. `fp --version` prints ``fpcore.__version__``, the project's one version.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from typing import NoReturn

import fpcore
from fpcore import budget, kernel_gpu
from services.cli.characterise import add_characterise_parser
from services.cli.convert import add_convert_parser
from services.cli.demo import add_demo_parser
from services.cli.figure import add_figure_parser
from services.cli.locate import add_locate_parser
from services.cli.merge import add_merge_parser
from services.cli.process import add_process_parser
from services.cli.publish import add_publish_parser
from services.cli.record import add_record_parser, add_recover_parser
from services.cli.simulate import add_simulate_parser
from services.cli.track import add_track_parser
from services.cli.view import add_view_parser
from services.cli.worker import add_worker_parser

__all__ = ["build_parser", "main"]


class OneLineParser(argparse.ArgumentParser):
    """argparse with its usage errors on one line (`fp locate: error: argument --n-freq: …`), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    ap = OneLineParser(prog="fp", description="Fingerprint localisation of targets in scattering media.")
    ap.add_argument("--version", action="version", version=f"fp {fpcore.__version__}")
    ap.add_argument("--debug", action="store_true", help="on an unexpected error, print the Python traceback too")
    ap.add_argument(
        "--memory-budget",
        metavar="SIZE",
        help="refuse requests estimated above this size, e.g. 8GiB or 25%% of the RAM (default: "
        f"${budget.ENV_VAR}, else {budget.DEFAULT_FRACTION * 100:.0f}%% of the RAM; fpcore.budget)",
    )
    ap.add_argument(
        "--device",
        choices=kernel_gpu.DEVICES,
        help="where γ and confocal maps run: gpu (cufinufft + CuPy, the 'gpu' extra; an error without a usable "
        "CUDA device), cpu, or auto (the GPU when one is usable) (default: $FP_DEVICE, else auto)",
    )
    sub = ap.add_subparsers(dest="command", required=True)
    add_demo_parser(sub)
    add_locate_parser(sub)
    add_track_parser(sub)
    add_simulate_parser(sub)
    add_characterise_parser(sub)
    add_convert_parser(sub)  # PICMUS / UFF / MCAP (issue 14)
    # Streaming nodes (issue 4): each registers its subcommand and handler (docs/design.md §2, §7).
    add_publish_parser(sub)
    add_process_parser(sub)
    add_worker_parser(sub)  # sharded processing: γ workers + merger (issue 15, docs/scaling.md)
    add_merge_parser(sub)
    add_record_parser(sub)
    add_recover_parser(sub)
    # Recordings to Rerun / PNG (issue 6).
    add_view_parser(sub)
    add_figure_parser(sub)
    return ap


def join_negative_values(argv: list[str]) -> list[str]:
    """`--r0 -1.5mm,11mm` → `--r0=-1.5mm,11mm`: argparse takes a value that starts with '-' for an option
    unless it is a plain number, so coordinates, ranges and velocities with a negative first component
    are joined to their option here (any long option followed by '-<digit>' or '-.<digit>')."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else ""
        if (
            a.startswith("--")
            and "=" not in a
            and len(nxt) > 1
            and nxt[0] == "-"
            and (nxt[1].isdigit() or (nxt[1] == "." and nxt[2:3].isdigit()))
        ):
            out.append(f"{a}={nxt}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def _one_line(text: object) -> str:
    """An error message on one line (a library's multi-line message keeps its first line)."""
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    return lines[0] if lines else type(text).__name__


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(join_negative_values(list(sys.argv[1:] if argv is None else argv)))
    try:
        budget.set_memory_budget(
            budget.parse_bytes(args.memory_budget, "--memory-budget") if args.memory_budget else None
        )
        if args.device is not None:
            kernel_gpu.set_device(args.device)  # also exported in FP_DEVICE for the nodes a command starts
        return int(args.func(args))
    except (ValueError, OSError) as exc:
        print(f"fp {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyError as exc:  # a name that is not in a table (scenario, fingerprint, key): the message says which
        print(f"fp {args.command}: error: {_one_line(exc.args[0] if exc.args else exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fp {args.command}: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print(
            f"fp {args.command}: error: not enough memory for this request (a smaller grid, band or fewer "
            "frames may fit)",
            file=sys.stderr,
        )
        return 2
    except Exception as exc:  # last resort: one line, never a traceback unless asked for (--debug)
        if type(exc).__name__ == "ZError":  # zenoh: a bad endpoint or configuration
            print(f"fp {args.command}: error: bus (zenoh): {_one_line(exc)}", file=sys.stderr)
            return 2
        if args.debug:
            traceback.print_exc()
        print(
            f"fp {args.command}: error: {type(exc).__name__}: {_one_line(exc)} (unexpected; run `fp --debug "
            f"{args.command} …` for the traceback)",
            file=sys.stderr,
        )
        return 3
