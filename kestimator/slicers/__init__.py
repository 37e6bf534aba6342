"""Slicer adapters: which slicer wrote a G-code file, and what it estimated itself.

Owns the ordered list of adapters and the file reading for detection. Each family module owns
everything about its slicers' files (``orca.py``, ``prusaslicer.py``, ``cura.py``,
``generic.py``); ``base.py`` holds what they share. The list is explicit: the first adapter that
recognises a file wins, and a file none recognises is ``generic.UNKNOWN``. Only the first and
last MiB of a file are read, as Moonraker does, so even 40 MB files are detected at once.
"""

from __future__ import annotations

import os

from kestimator.errors import KestimatorError
from kestimator.slicers.base import (
    DETECT_WINDOW_BYTES,
    FileEnds,
    SlicerAdapter,
    SlicerInfo,
    format_prusa_duration,
    parse_prusa_duration,
)
from kestimator.slicers.cura import CuraAdapter
from kestimator.slicers.generic import UNKNOWN, GenericAdapter
from kestimator.slicers.orca import OrcaAdapter
from kestimator.slicers.prusaslicer import PrusaSlicerAdapter

__all__ = [
    "ADAPTERS",
    "SlicerAdapter",
    "SlicerInfo",
    "adapter_for",
    "detect",
    "detect_file",
    "format_prusa_duration",
    "parse_prusa_duration",
]

ADAPTERS: tuple[SlicerAdapter, ...] = (
    OrcaAdapter(),
    PrusaSlicerAdapter(),
    CuraAdapter(),
    GenericAdapter(),
)
"""Tried in this order; ``GenericAdapter`` comes last because it knows the rarer slicers."""


def adapter_for(family: str) -> SlicerAdapter:
    """The adapter of a family id (``SlicerInfo.family``); the generic one if unknown."""
    for adapter in ADAPTERS:
        if adapter.family == family:
            return adapter
    return ADAPTERS[-1]


def detect(head: bytes, tail: bytes) -> SlicerInfo:
    """Recognise the slicer from a file's first and last bytes (the same bytes if it is small).

    Never fails: a file no adapter recognises, or an empty one, is reported as "unknown".
    """
    ends = FileEnds.from_bytes(head, tail)
    for adapter in ADAPTERS:
        info = adapter.detect(ends)
        if info is not None:
            return info
    return UNKNOWN


def _whole_lines_from_start(data: bytes) -> bytes:
    """``data`` up to and including its last newline (the bytes after it may be half a line)."""
    return data[:data.rfind(b"\n") + 1]


def _whole_lines_to_end(data: bytes) -> bytes:
    """``data`` after its first newline (the bytes before it may be half a line)."""
    start = data.find(b"\n")
    return b"" if start < 0 else data[start + 1:]


def detect_file(path: str | os.PathLike[str]) -> SlicerInfo:
    """Recognise the slicer of the file at ``path``, reading at most its first and last MiB.

    Lines cut by a window's edge are left out, so a half line never passes for a whole one.
    Raises ``KestimatorError`` if the file cannot be read.
    """
    try:
        with open(path, "rb") as gcode:
            size = gcode.seek(0, os.SEEK_END)
            gcode.seek(0)
            if size <= DETECT_WINDOW_BYTES:
                whole = gcode.read()
                return detect(whole, whole)
            head = _whole_lines_from_start(gcode.read(DETECT_WINDOW_BYTES))
            # One byte more than the window shows whether the window starts a line.
            gcode.seek(size - DETECT_WINDOW_BYTES - 1)
            tail = gcode.read()
    except OSError as exc:
        raise KestimatorError(f"cannot read G-code: {exc.strerror or exc}", path) from exc
    return detect(head, _whole_lines_to_end(tail))
