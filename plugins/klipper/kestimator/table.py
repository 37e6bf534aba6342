# kestimator: the worker's table
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""The worker's answer, refused when it is not one: byte offsets of line starts and
Klipper's time there, each object's time left, the stops; the limits it is held to.
"""
from __future__ import annotations

import array
import base64
import bisect
import math
from typing import Any

# What the worker's table writer keeps at most (kestimator/progress_table.py:
# MAX_TABLE_POINTS, MAX_OBJECT_POINTS, MAX_OBJECTS, MAX_NAME_BYTES); an answer with
# more is refused. (Copied, not imported: this module runs in Klipper's Python without
# kestimator; tests/test_klipper_module.py holds the two to each other.)
MAX_TIME_POINTS = 20002
MAX_OBJECT_POINTS = 500
MAX_OBJECTS = 200
MAX_NAME_CHARS = 256
# The stops a table holds at most and a stop command's length (progress_table.py's
# MAX_TABLE_STOPS, MAX_STOP_COMMAND_BYTES).
MAX_STOPS = 1000
MAX_STOP_COMMAND_CHARS = 64


def _b64_chars(nbytes: int) -> int:
    return 4 * ((nbytes + 2) // 3)


def _decode_array(kind: str, text: Any, max_items: int,
                  what: str) -> array.array[Any]:
    """The machine array base64 `text` holds, refused past `max_items` items
    before anything is decoded."""
    out = array.array(kind)
    if not isinstance(text, str):
        raise ValueError("%s is not base64 text" % (what,))
    if len(text) > _b64_chars(max_items * out.itemsize):
        raise ValueError("more than %d %s" % (max_items, what))
    if text:
        out.frombytes(base64.b64decode(text, validate=True))
    return out


def _check_values(values: array.array[Any], what: str, low: float,
                  high: float | None = None, grow: bool = False) -> None:
    """All of `values` finite, within [low, high] and, with `grow`, in
    non-decreasing order (C-speed passes)."""
    if not len(values):
        return
    items = values.tolist()
    if not math.isfinite(sum(items)):
        raise ValueError("%s are not finite" % (what,))
    if grow:
        # (sorting what is already sorted is one pass)
        ordered = sorted(items)
        if items != ordered:
            raise ValueError("%s do not grow" % (what,))
        least, most = ordered[0], ordered[-1]
    else:
        least, most = min(items), max(items)
    if least < low or (high is not None and most > high):
        raise ValueError("%s are out of range" % (what,))


class Table:
    """One answer of the worker: byte offsets of line starts and the Klipper
    time at which every move on earlier lines has finished. Refused (ValueError)
    when it is not one: past the worker's own limits, or values that cannot be
    times."""

    def __init__(self, answer: dict[str, Any]) -> None:
        self.source = str(answer.get("source", "estimate"))[:20]
        total = answer.get("total_s")
        if (not isinstance(total, (int, float)) or isinstance(total, bool)
                or not math.isfinite(total) or total < 0.):
            raise ValueError("total_s is not a time")
        self.total_s = float(total)
        self.offsets = _decode_array("q", answer.get("offsets_b64", ""),
                                     MAX_TIME_POINTS, "time points")
        self.times = _decode_array("d", answer.get("times_b64", ""),
                                   MAX_TIME_POINTS, "time points")
        if len(self.offsets) != len(self.times) or not len(self.offsets):
            raise ValueError("table without points")
        _check_values(self.offsets, "offsets", 0, grow=True)
        _check_values(self.times, "times", 0., grow=True)
        names = answer.get("object_names") or []
        if not isinstance(names, list) or len(names) > MAX_OBJECTS:
            raise ValueError("more than %d objects" % (MAX_OBJECTS,))
        for name in names:
            if not isinstance(name, str) or len(name) > MAX_NAME_CHARS:
                raise ValueError("an object name is not a string of at most %d "
                                 "characters" % (MAX_NAME_CHARS,))
        self.object_names = list(names)
        # Klipper upper-cases object names; the file may not.
        self.object_keys = [name.upper() for name in names]
        self.object_offsets = _decode_array(
            "q", answer.get("object_offsets_b64", ""), MAX_OBJECT_POINTS,
            "object points")
        _check_values(self.object_offsets, "object offsets", 0, grow=True)
        n = len(self.object_offsets)
        flat = _decode_array("d", answer.get("object_remaining_b64", ""),
                             n * len(self.object_names), "object times")
        if len(flat) != n * len(self.object_names):
            raise ValueError("object table of the wrong size")
        _check_values(flat, "object times", 0.,
                      self.total_s * (1. + 1e-9) + 1e-6)
        self.object_remaining = [flat[i * n:(i + 1) * n]
                                 for i in range(len(self.object_names))]
        self._read_stops(answer)
        warnings = answer.get("warnings") or []
        if not isinstance(warnings, list):
            warnings = []
        self.warnings = [str(w)[:500] for w in warnings[:20]]
        # What the table holds in memory (its arrays), bytes.
        self.nbytes = sum(a.buffer_info()[1] * a.itemsize for a in
                          [self.offsets, self.times, self.object_offsets]
                          + self.object_remaining)

    def _read_stops(self, answer: dict[str, Any]) -> None:
        """The stops (where the print waits for a person): each one's byte offset,
        Klipper's time there, command and line (None when the answer has no lines)."""
        offsets = answer.get("stop_offsets") or []
        times = answer.get("stop_times") or []
        commands = answer.get("stop_commands") or []
        lines = answer.get("stop_lines")
        if not (isinstance(offsets, list) and isinstance(times, list)
                and isinstance(commands, list)) or len(offsets) > MAX_STOPS:
            raise ValueError("more than %d stops" % (MAX_STOPS,))
        if not len(offsets) == len(times) == len(commands):
            raise ValueError("stops of the wrong size")
        if not isinstance(lines, list) or len(lines) != len(offsets):
            lines = [None] * len(offsets)
        for offset, line in zip(offsets, lines):
            if not (_is_int(offset) and (line is None or _is_int(line))):
                raise ValueError("a stop's offset or line is not a whole number")
        for command in commands:
            if not isinstance(command, str) or len(command) > MAX_STOP_COMMAND_CHARS:
                raise ValueError("a stop's command is not a string of at most %d "
                                 "characters" % (MAX_STOP_COMMAND_CHARS,))
        self.stop_offsets = array.array("q", offsets)
        _check_values(self.stop_offsets, "stop offsets", 0, grow=True)
        for t in times:
            if not isinstance(t, (int, float)) or isinstance(t, bool):
                raise ValueError("a stop's time is not a number")
        self.stop_times = array.array("d", times)
        _check_values(self.stop_times, "stop times", 0.,
                      self.total_s * (1. + 1e-9) + 1e-6, grow=True)
        self.stop_commands = list(commands)
        self.stop_lines: list[int | None] = list(lines)

    def stop_after(self, position: int, passed: int) -> int:
        """The index of the first stop at or after file `position` and past the stop at
        offset `passed` (-1: none passed); len(stop_offsets) when no stop is left."""
        return max(bisect.bisect_left(self.stop_offsets, position),
                   bisect.bisect_right(self.stop_offsets, passed) if passed >= 0 else 0)

    def time_at(self, offset: int) -> float:
        """Table time at byte offset `offset`: that of the last point at or
        before it (exact at a point; between points the time lies between
        theirs, and the worker keeps them close; interpolating by bytes
        would guess wrong inside one long move)."""
        i = bisect.bisect_right(self.offsets, offset) - 1
        return self.times[max(0, i)]

    def objects_at(self, offset: int) -> dict[str, float]:
        """Each object's remaining seconds from byte offset `offset`."""
        if not self.object_names or not len(self.object_offsets):
            return {}
        j = bisect.bisect_right(self.object_offsets, offset) - 1
        j = max(0, j)
        return dict((name, self.object_remaining[i][j])
                    for i, name in enumerate(self.object_names))


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 1 << 62
