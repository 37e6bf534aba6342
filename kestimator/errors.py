"""The errors: kestimator's own for bad input or failed I/O, and Klipper's command errors.

`KestimatorError` is the one error kestimator raises to its caller: every user-facing
failure carries the file and, where known, the 1-based line, so the command line can print
exactly one line and exit non-zero without a traceback. `CommandError`, `ParamError` and
`MoveError` are what Klipper answers a command or move with (upstream's
`printer.command_error`); the timeline catches them, reports the line and, as Klipper does,
stops the print there (the pre-flight).
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


class CommandError(Exception):
    """Klipper would answer this command with an error and not run it (upstream's
    `gcode.CommandError`, raised as `printer.command_error`)."""


class ParamError(CommandError):
    """A parameter error of Klipper's `gcmd.get*`: Klipper words it
    "Error on '<command line>': <this text>"."""


class PrintEndsError(CommandError):
    """A command after which Klipper runs no more of the file, without an error of its own:
    RESTART and FIRMWARE_RESTART restart Klipper (gcode.py `request_restart`)."""


class MoveError(Exception):
    """Klipper would reject this move (`Move.move_error`; the G-code layer adds file and
    line)."""


def fixed(value: float, decimals: int = 3) -> str:
    """`"%.3f" % value`, the same on every build: PyPy's %-formatting writes a number of
    1e50 or more as "1e+50", `format` writes every digit on CPython and PyPy alike."""
    return format(value, ".%df" % decimals)
