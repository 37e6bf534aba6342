"""Durations for people: `1h 02m 03s`. The one formatter the CLI, report and plugins share.

(Slicer-specific duration text, the kind written back into G-code, lives with each slicer
adapter in `kestimator.slicers`.)
"""

from __future__ import annotations

SECONDS_PER_MINUTE = 60
SECONDS_PER_HOUR = 3600


def format_duration(seconds: float) -> str:
    """`1h 02m 03s`, `4m 05s` or `7s`, rounded to the nearest second."""
    whole = int(round(seconds))
    hours, rest = divmod(whole, SECONDS_PER_HOUR)
    minutes, secs = divmod(rest, SECONDS_PER_MINUTE)
    if hours:
        return "%dh %02dm %02ds" % (hours, minutes, secs)
    if minutes:
        return "%dm %02ds" % (minutes, secs)
    return "%ds" % secs
