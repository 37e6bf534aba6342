"""Durations for people: `1h 02m 03s`. The one formatter the CLI, report and plugins share.

(Slicer-specific duration text, the kind written back into G-code, lives with each slicer
adapter in `kestimator.slicers`.)
"""

from __future__ import annotations

SECONDS_PER_MINUTE = 60
SECONDS_PER_HOUR = 3600

MAX_PRINT_S = 366 * 24 * 3600.0
"""The longest time kestimator believes: a year. No print runs that long, so a total (or a
time added to it) beyond this comes from an absurd value (an acceleration of 1e-300, an
added time of 1e300 s) and is refused with the line where time passed it, never written
into a file as a 150-digit `M73 R`."""


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
