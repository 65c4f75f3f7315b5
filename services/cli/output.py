"""Console output of the `fp` commands, terminal or not (issue 14).

On a terminal: rich as usual (colours, transient progress bars, tables fitted to the window). When stdout is
not a terminal (a pipe, a file, CI logs): no colours or cursor tricks, tables are never wrapped (the console is
as wide as the widest line), and progress is plain text lines — ``γ-maps 2/4 (1.3 s)`` — at most about ten
per task, so a log shows that work goes on and how long it took.
"""

from __future__ import annotations

import time
from types import TracebackType
from typing import Any

from rich.console import Console
from rich.progress import Progress

__all__ = ["PlainProgress", "make_console", "progress"]

#: the console width used when stdout is not a terminal: wide enough that no table or line is wrapped.
PLAIN_WIDTH = 10_000


def make_console() -> Console:
    """A rich console for stdout: the terminal's, or a plain unwrapped one when stdout is not a terminal."""
    probe = Console()
    if probe.is_terminal:
        return probe
    return Console(width=PLAIN_WIDTH, no_color=True, highlight=False, emoji=False, soft_wrap=True)


class PlainProgress:
    """The part of ``rich.progress.Progress`` the commands use, as plain lines (``label k/n (t s)``)."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self._tasks: dict[int, dict[str, Any]] = {}

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        return None

    def add_task(self, description: str, total: float | None = None, **_: Any) -> int:
        task = len(self._tasks)
        self._tasks[task] = {"label": description, "total": total, "done": 0.0, "shown": -1, "t0": time.perf_counter()}
        return task

    def advance(self, task: int, advance: float = 1) -> None:
        self.update(task, completed=self._tasks[task]["done"] + advance)

    def update(self, task: int, completed: float | None = None, **_: Any) -> None:
        t = self._tasks[task]
        if completed is None:
            return
        t["done"] = completed
        total = t["total"]
        tenth = int(10 * completed / total) if total else int(completed)  # a line per tenth of the work
        if tenth == t["shown"]:
            return
        t["shown"] = tenth
        of = f"/{total:g}" if total else ""
        self.console.print(f"{t['label']} {completed:g}{of} ({time.perf_counter() - t['t0']:.1f} s)")


def progress(console: Console) -> Progress | PlainProgress:
    """A transient rich progress bar on a terminal, plain progress lines otherwise."""
    if console.is_terminal:
        return Progress(console=console, transient=True)
    return PlainProgress(console)
