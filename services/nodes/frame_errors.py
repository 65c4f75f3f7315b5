"""The ErrorReports a frame's processing yields, shared by the processor and the γ workers (docs/design.md §7).

A node that processes frames reports, on ``fp/<rig>/errors``, a frame whose processing failed (one report,
the frame's acknowledgement) and a frame it processed without its ground truth; both nodes build those
reports here so that `fp process` and a sharded `fp merge` + `fp worker` report the same frame the same way.
"""

from __future__ import annotations

from pydantic import ValidationError

from fpcore.budget import BudgetError
from services.messages import ErrorReport, RFFrame

__all__ = ["failure_field", "failure_report", "truth_report"]

_PROBLEM_CHARS = 2000


def failure_field(exc: BaseException) -> str:
    """The report's field for a frame that failed with ``exc``: ``budget`` (the frame's geometry needs more
    memory than the budget, fpcore.budget), ``geometry`` (the pipeline refused the frame: a ValueError, e.g.
    a geometry that does not match the fingerprints) or ``processing`` (anything else, including an output
    message that does not validate, e.g. a non-finite energy from an RF scaled out of range)."""
    if isinstance(exc, BudgetError):
        return "budget"
    if isinstance(exc, ValueError) and not isinstance(exc, ValidationError):
        return "geometry"
    return "processing"


def failure_report(exc: BaseException, frame_index: int | None, key: str, node: str) -> ErrorReport:
    """The one ErrorReport of a frame whose processing raised ``exc``."""
    return ErrorReport(
        frame_index=frame_index,
        key=key,
        field=failure_field(exc),
        problem=f"{type(exc).__name__}: {exc}"[:_PROBLEM_CHARS],
        node=node,
    )


def truth_report(msg: RFFrame, key: str, node: str) -> ErrorReport | None:
    """The report of a frame whose ground truth was refused (``RFFrame.truth_problem``): its RF is good and it
    is processed without the truth. None when the truth is fine or absent."""
    if not msg.truth_problem:
        return None
    problem = f"{msg.truth_problem}; the truth was dropped and the frame processed without it"
    return ErrorReport(frame_index=msg.frame_index, key=key, field="truth", problem=problem[:_PROBLEM_CHARS], node=node)
