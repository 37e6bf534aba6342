"""Time the file cannot show: macros, waits and the start of a print, with where each came from.

Owns the values (`MacroTimes`: a time per macro name, from the profile's ``[macros]`` table or
learned from the printer's history, and a learned time before the first extrusion), the record
an estimate keeps of what it counted (`TimedPart`), and how the parts add up (`Parts`).

Klipper's ``print_stats`` (klippy/extras/print_stats.py at 84104bbbd) starts ``print_duration``
at the first extrusion: time counted before it is *prep* (start macro, homing, heating), the
rest is printing. Mainsail, Fluidd and KlipperScreen show ``estimated_time - print_duration``
as the remaining time, so the time comments kestimator writes hold the printing part only and
the prep part is written on a line of its own.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping

# print_stats counts the print as started once the filament used exceeds this (mm).
FIRST_EXTRUSION_MM = 0.0000001
ADD_TIME_SOURCE = "ESTIMATOR_ADD_TIME"
HOMING_SOURCE = "homing time (--homing-time / homing_time_s)"
HEAT_SOURCE = "heat time (--heat-time / heat_time_s)"
LEARNED_PREP_LABEL = "before the first extrusion"
MOTION_CORRECTION_LABEL = "motion correction (printer slower than the planner)"
# The name under which a time per tool change (any T<n>) is kept.
TOOL_CHANGE = "T"


@dataclasses.dataclass(frozen=True)
class MacroTime:
    """Seconds one run of something takes, and where that number came from."""

    seconds: float
    source: str


@dataclasses.dataclass(frozen=True)
class MacroTimes:
    """What the estimate adds for macros: a time per macro name (upper case, as Klipper
    looks macros up) and, if learned, one time for everything before the first extrusion."""

    macros: Mapping[str, MacroTime] = dataclasses.field(default_factory=dict)
    before_first_extrusion: MacroTime | None = None
    motion_ratio: MacroTime | None = None
    """Learned: the printer's motion after the first extrusion takes this many times the
    planner's (``seconds`` holds the ratio; only above 1)."""
    warnings: tuple[str, ...] = ()
    """What of the learned times was not used and why (a damaged store), for the front
    end to show."""

    def time_of(self, name: str) -> MacroTime | None:
        """The time of one run of the command `name`, if known (a tool change T<n> takes
        the time given for ``T`` when it has none of its own)."""
        found = self.macros.get(name)
        if found is None and name[:1] == TOOL_CHANGE and name[1:].isdigit():
            return self.macros.get(TOOL_CHANGE)
        return found


def check_seconds(value: object) -> float:
    """A duration from a file a person wrote: a finite number of seconds, 0 or more."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value >= 0.0):
        raise ValueError("must be a number of seconds, 0 or more")
    return float(value)


def merge(*layers: Mapping[str, MacroTime]) -> dict[str, MacroTime]:
    """Later layers win, name by name."""
    merged: dict[str, MacroTime] = {}
    for layer in layers:
        merged.update(layer)
    return merged


@dataclasses.dataclass
class TimedPart:
    """What one kind of added time came to in one file."""

    name: str
    source: str
    count: int = 0
    seconds: float = 0.0
    before_first_extrusion_s: float = 0.0
    """The share counted before the first extrusion (not in print_duration)."""
    covered: int = 0
    """Runs not counted on their own: a learned time before the first extrusion holds them."""


@dataclasses.dataclass(frozen=True)
class Parts:
    """How an estimate's total splits."""

    total_s: float
    """Until the last move has finished, every added time included."""
    motion_s: float
    """Klipper's planner alone (exact)."""
    added_s: float
    """Macros, waits, ESTIMATOR_ADD_TIME and learned time."""
    before_first_extrusion_s: float
    """Added time counted before the first extrusion."""
    print_duration_s: float
    """What Klipper's print_duration will show at the end: the total less that prep time."""

    @classmethod
    def of(cls, total_s: float, parts: Iterable[TimedPart]) -> Parts:
        """Split `total_s` by the added times recorded in `parts`."""
        listed = list(parts)
        added = sum(p.seconds for p in listed)
        prep = sum(p.before_first_extrusion_s for p in listed)
        return cls(total_s=total_s, motion_s=total_s - added, added_s=added,
                   before_first_extrusion_s=prep, print_duration_s=total_s - prep)
