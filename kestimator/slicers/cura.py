"""Cura (CuraEngine) files.

Owns how they are recognised (``;Generated with Cura_SteamEngine <version>``) and where Cura's
own estimate is: ``;TIME:<s>`` in the header (Griffin flavour: ``;PRINT.TIME:<s>``). Like
Moonraker, the largest such value in the first MiB counts.

CuraEngine writes its header before it knows the print time; run from the command line the
header stays as written, with ``;TIME:6666`` and an empty bounding box (``;MINX:2.14748e+06``,
larger than ``;MAXX:``; ``GCodeExport::getFileHeader`` in Ultimaker/CuraEngine). The Cura
application replaces that header with the real one. 6666 is therefore a placeholder unless the
header's bounding box was filled in; the Griffin header leaves ``;PRINT.TIME:`` out instead.
"""

from __future__ import annotations

import re

from kestimator.slicers.base import (
    FileEnds,
    KlipperTimes,
    SlicerAdapter,
    SlicerInfo,
    first_group,
    replace_group,
)

CURA_PLACEHOLDER_TIME_S = 6666.0
"""What CuraEngine writes in ``;TIME:`` while it does not know the print time yet."""

_VERSION_RE = re.compile(r"^;Generated with Cura_SteamEngine (\S+)", re.MULTILINE)
_TIME_RE = re.compile(r"^;TIME:(\d+(?:\.\d+)?)\s*$", re.MULTILINE)
_GRIFFIN_TIME_RE = re.compile(r"^;PRINT\.TIME:(\d+(?:\.\d+)?)\s*$", re.MULTILINE)
_FLOAT = r"(-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)"
_MIN_X_RE = re.compile(r"^;MINX:" + _FLOAT, re.MULTILINE)
_MAX_X_RE = re.compile(r"^;MAXX:" + _FLOAT, re.MULTILINE)


# ;TIME:<whole seconds> and ;PRINT.TIME:<whole seconds> in the header; ;TIME_ELAPSED:<%f>
# at the end of every layer: the time every move before it has finished.
_TIME_LINE_RE = re.compile(r"(?P<key>;TIME:|;PRINT\.TIME:)(?P<t>\d+(?:\.\d+)?)\s*")
_ELAPSED_LINE_RE = re.compile(r";TIME_ELAPSED:(?P<t>-?\d+(?:\.\d+)?)\s*")
ELAPSED_PREFIX = ";TIME_ELAPSED:"


def _has_filled_bounding_box(head: str) -> bool:
    """True if the header's bounding box was written after slicing (MINX <= MAXX)."""
    min_x_mm = first_group(_MIN_X_RE, head)
    max_x_mm = first_group(_MAX_X_RE, head)
    return min_x_mm is not None and max_x_mm is not None and float(min_x_mm) <= float(max_x_mm)


def cura_estimate_s(head: str) -> float | None:
    """Largest real ``;TIME:``/``;PRINT.TIME:`` in ``head``, None if only placeholders or none."""
    times_s = [float(value) for value in _TIME_RE.findall(head)]
    if not _has_filled_bounding_box(head):
        times_s = [time_s for time_s in times_s if time_s != CURA_PLACEHOLDER_TIME_S]
    times_s += [float(value) for value in _GRIFFIN_TIME_RE.findall(head)]
    return max(times_s, default=None)


class CuraAdapter(SlicerAdapter):
    """Files written by CuraEngine, from the Cura application or its command line."""

    family = "cura"
    time_comment_prefixes = (";TIME:", ";PRINT.TIME:", ELAPSED_PREFIX)
    mark_prefixes = (ELAPSED_PREFIX,)

    def detect(self, ends: FileEnds) -> SlicerInfo | None:
        match = _VERSION_RE.search(ends.head)
        if match is None:
            return None
        return SlicerInfo(
            name="Cura",
            family=self.family,
            version=match.group(1),
            estimate_s=cura_estimate_s(ends.head),
            first_layer_estimate_s=None,
        )

    def rewrite_time_comment(self, text: str, line: int, times: KlipperTimes) -> str | None:
        """``;TIME:``/``;PRINT.TIME:`` get the total, each ``;TIME_ELAPSED:`` its own time."""
        if text.startswith(ELAPSED_PREFIX):
            match = _ELAPSED_LINE_RE.fullmatch(text)
            elapsed_s = times.marks.get(line)
            if match is None or elapsed_s is None:
                return None
            return replace_group(match, "t", "%f" % elapsed_s)
        match = _TIME_LINE_RE.fullmatch(text)
        if match is None:
            return None
        return replace_group(match, "t", "%d" % round(times.total_s))
