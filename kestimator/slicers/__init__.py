"""Slicer adapters: which slicer wrote a G-code file, and what it estimated itself.

Owns the ordered list of adapters and the file reading for detection. Each family module owns
everything about its slicers' files (``orca.py``, ``prusaslicer.py``, ``cura.py``,
``generic.py``); ``base.py`` holds what they share. The list is explicit: the first adapter that
recognises a file wins, and a file none recognises is ``generic.UNKNOWN``. Only the first and
last MiB of a file are read, as Moonraker does, so even 40 MB files are detected at once.
``read_slicer_settings`` combines a file's embedded settings with the slicer's
post-processing environment through the same adapters (``settings.py`` has their shape), and
says when the file was sliced for another firmware's G-code flavour (``SlicerSettings.flavour``:
the settings' flavour, else RepRapFirmware's commands in the file's ends).
"""

from __future__ import annotations

import dataclasses
import io
import os
from collections.abc import Mapping

from kestimator.errors import KestimatorError
from kestimator.files import open_regular
from kestimator.slicers.base import (
    DETECT_WINDOW_BYTES,
    FileEnds,
    SlicerAdapter,
    SlicerInfo,
    flavour_from_commands,
    format_prusa_duration,
    parse_prusa_duration,
)
from kestimator.slicers.cura import CuraAdapter
from kestimator.slicers.generic import UNKNOWN, GenericAdapter
from kestimator.slicers.orca import OrcaAdapter
from kestimator.slicers.prusaslicer import PrusaSlicerAdapter
from kestimator.slicers.settings import NO_SETTINGS, SlicerConfig, SlicerSettings
from kestimator.stops import SLICER_STOP_KEYS

__all__ = [
    "ADAPTERS",
    "SlicerAdapter",
    "SlicerInfo",
    "SettingsCache",
    "SlicerSettings",
    "adapter_for",
    "detect",
    "detect_file",
    "read_file_ends",
    "format_prusa_duration",
    "parse_prusa_duration",
    "read_slicer_settings",
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


def read_file_ends(path: str | os.PathLike[str]) -> tuple[bytes, bytes]:
    """The first and last MiB of the file at ``path`` in whole lines (the same bytes twice if
    it is small). Raises ``KestimatorError`` if the file cannot be read or is not a regular
    file (`kestimator.files.open_regular`)."""
    return _whole_lines(_raw_ends(path))


def _raw_ends(path: str | os.PathLike[str]) -> tuple[bytes, bytes]:
    """The file's first MiB and its last MiB and a byte (the same bytes twice, the whole
    file, if it is small)."""
    with open_regular(path) as gcode:
        try:
            size = gcode.seek(0, os.SEEK_END)
            gcode.seek(0)
            if size <= DETECT_WINDOW_BYTES:
                whole = gcode.read()
                return whole, whole
            head = gcode.read(DETECT_WINDOW_BYTES)
            # One byte more than the window shows whether the window starts a line.
            gcode.seek(size - DETECT_WINDOW_BYTES - 1)
            return head, gcode.read()
        except OSError as exc:
            raise KestimatorError(f"cannot read G-code: {exc.strerror or exc}", path) from exc


def _whole_lines(raw: tuple[bytes, bytes]) -> tuple[bytes, bytes]:
    """`_raw_ends` in whole lines."""
    head, tail = raw
    if head is tail:
        return raw
    return _whole_lines_from_start(head), _whole_lines_to_end(tail)


def detect_file(path: str | os.PathLike[str]) -> SlicerInfo:
    """Recognise the slicer of the file at ``path``, reading at most its first and last MiB.

    Lines cut by a window's edge are left out, so a half line never passes for a whole one.
    Raises ``KestimatorError`` if the file cannot be read.
    """
    return detect(*read_file_ends(path))


ENVIRONMENT_ORIGIN = "SLIC3R_* environment"
FILE_ORIGIN = "settings in the file"


# SettingsCache reads the ends again this many bytes at a time.
COMPARE_BLOCK_BYTES = 1 << 16


class SettingsCache:
    """The last file's `read_slicer_settings`, by the very bytes it read (both ends, before
    they are cut to whole lines: cutting copies them) and the
    environment it was given: a process that asks again and again about one file (the
    worker, after each change typed during a print) reads the ends, but decodes and parses
    them only when they differ (1.2 of 1.7 ms). Holds one file's ends, 2 MiB at most, and
    the 64 KiB block it reads them again into (`holds`)."""

    def __init__(self) -> None:
        self.ends: tuple[bytes, bytes] | None = None
        self.environ: dict[str, str] | None = None
        self.result: tuple[SlicerInfo, SlicerSettings] | None = None
        # Where the ends are read again, a block at a time, to be compared with `ends`
        # (a fresh MiB took up to 1 ms to read; into this block, 0.15).
        self._block = bytearray(COMPARE_BLOCK_BYTES)

    def holds(self, path: str | os.PathLike[str]) -> bool:
        """Whether the file at `path` ends as `ends` do now (False if it cannot be read)."""
        if self.ends is None:
            return False
        head, tail = self.ends
        try:
            with open_regular(path) as gcode:
                size = gcode.seek(0, os.SEEK_END)
                if head is tail:  # a small file, whole
                    return size == len(head) and self._reads(gcode, 0, head)
                return self._reads(gcode, 0, head) and self._reads(gcode, size - len(tail),
                                                                   tail)
        except (OSError, KestimatorError):
            return False

    def _reads(self, gcode: io.BufferedReader, offset: int, expected: bytes) -> bool:
        """Whether `gcode` holds `expected` at `offset`."""
        gcode.seek(offset)
        block = self._block
        view = memoryview(expected)
        for start in range(0, len(expected), len(block)):
            part = view[start:start + len(block)]
            if len(part) < len(block):
                block = bytearray(len(part))
            if gcode.readinto(block) != len(part) or block != part:
                return False
        return True


def read_slicer_settings(path: str | os.PathLike[str] | None,
                         environ: Mapping[str, str] | None = None,
                         cache: SettingsCache | None = None
                         ) -> tuple[SlicerInfo, SlicerSettings]:
    """Which slicer wrote the file at ``path`` and what its settings say about the printer.

    The settings come from the file (its first and last MiB) and, when ``environ`` is given,
    from the slicer's post-processing environment (``SLIC3R_*``); per key the file wins. With
    no ``path`` only the environment is read. A file whose slicer is unknown (binary G-code,
    say) takes its family from the environment. Never fails on content; raises
    ``KestimatorError`` only if the file cannot be read. With a `cache`, the answer for the
    same bytes and environment as the last time is that answer (both parts are frozen).
    """
    if path is None:
        return _read_slicer_settings(None, environ)
    if cache is None:
        return _read_slicer_settings(FileEnds.from_bytes(*read_file_ends(path)), environ)
    copied = None if environ is None else dict(environ)
    if cache.result is not None and cache.environ == copied and cache.holds(path):
        return cache.result
    raw = _raw_ends(path)
    result = _read_slicer_settings(FileEnds.from_bytes(*_whole_lines(raw)), environ)
    cache.ends, cache.environ, cache.result = raw, copied, result
    return result


def _read_slicer_settings(ends: FileEnds | None, environ: Mapping[str, str] | None
                          ) -> tuple[SlicerInfo, SlicerSettings]:
    info = UNKNOWN
    if ends is not None:
        info = next((found for adapter in ADAPTERS
                     if (found := adapter.detect(ends)) is not None), UNKNOWN)
    adapter = adapter_for(info.family)
    config: SlicerConfig = {}
    origins: list[str] = []
    if environ is not None:
        from_environment = adapter.read_environment(environ)
        if from_environment is None and info is UNKNOWN:
            for candidate in ADAPTERS:
                from_environment = candidate.read_environment(environ)
                if from_environment is not None:
                    adapter = candidate
                    break
        if from_environment:
            config.update(from_environment)
            origins.append(ENVIRONMENT_ORIGIN)
    if ends is not None:
        from_file = adapter.read_settings(ends)
        if from_file:
            config.update(from_file)
            origins.insert(0, FILE_ORIGIN)
    # Sliced for another firmware: the settings' flavor says so, else (no flavor set)
    # RepRapFirmware's own commands in the file's ends do.
    if any(key in config for key in adapter.flavour_keys):
        flavour = adapter.foreign_flavour(info, config)
    else:
        flavour = None if ends is None else flavour_from_commands(ends)
    if not config:
        return info, NO_SETTINGS if flavour is None else dataclasses.replace(
            NO_SETTINGS, flavour=flavour)
    settings = adapter.map_settings(config)
    stop_gcode = tuple((key, config[key].text) for key in SLICER_STOP_KEYS if key in config)
    return info, dataclasses.replace(settings, origin=" + ".join(origins), flavour=flavour,
                                     stop_gcode=stop_gcode)
