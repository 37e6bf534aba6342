"""The one error type kestimator raises for bad input or failed I/O.

Every user-facing failure carries the file and, where known, the 1-based line, so the
command line can print exactly one line and exit non-zero without a traceback.
"""

from __future__ import annotations

import os


class KestimatorError(Exception):
    """A problem with a user's file or settings, printable as one line."""

    def __init__(self, message: str, path: "str | os.PathLike[str] | None" = None,
                 line: int | None = None) -> None:
        self.message = message
        self.path = os.fspath(path) if path is not None else None
        self.line = line
        super().__init__(str(self))

    def __str__(self) -> str:
        where = ""
        if self.path is not None:
            where = self.path + (":%d" % self.line if self.line is not None else "") + ": "
        return where + self.message
