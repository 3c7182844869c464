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
