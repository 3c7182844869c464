"""The one exception type for bad input: it names the file and the problem."""

from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Bad input data: a missing, unreadable or invalid file, or a bad value.

    The message always names the file (when there is one) and the problem, so
    that a stage can report it in one line instead of a traceback.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(problem if path is None else f"{path}: {problem}")


EXCERPT_CHARS = 80
"""The most characters of an input's own text an error message quotes (issue 32: errors never echo a
file's contents beyond a bounded, escaped excerpt)."""


def excerpt(text: object, limit: int = EXCERPT_CHARS) -> str:
    """``text`` for an error message: non-printable characters escaped as ``repr`` does (a newline as
    ``\\n``: the message stays one line), cut to ``limit`` characters with "..." when longer."""
    shown = repr(str(text))[1:-1]
    return shown if len(shown) <= limit else shown[:limit] + "..."
