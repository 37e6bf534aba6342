"""Times recorded at file lines (layer markers, slicer time comments), stored compactly.

A file may hold a million layer markers: a list of (line, seconds) tuples costs about a
hundred bytes per entry, these two arrays sixteen. Lines are recorded in file order, so a
line's time is found by bisection.
"""

from __future__ import annotations

from array import array
from bisect import bisect_left
from collections.abc import Callable, Iterable, Iterator, Mapping


class TimedLines:
    """(line, seconds) pairs in file order; indexable and iterable like a list of tuples."""

    __slots__ = ("lines", "times")

    def __init__(self, pairs: Iterable[tuple[int, float]] = ()) -> None:
        self.lines = array("q")
        self.times = array("d")
        for line, t in pairs:
            self.append(line, t)

    def append(self, line: int, t: float) -> None:
        """Add the time at `line` (after every line recorded so far)."""
        self.lines.append(line)
        self.times.append(t)

    def set_time(self, index: int, t: float) -> None:
        """Set the time of the `index`-th pair (a look-ahead callback resolving it)."""
        self.times[index] = t

    def map_times(self, function: Callable[[float], float]) -> None:
        """Replace every time t by function(t), in place."""
        times = self.times
        for i in range(len(times)):
            times[i] = function(times[i])

    def __len__(self) -> int:
        return len(self.lines)

    def __bool__(self) -> bool:
        return len(self.lines) > 0

    def __getitem__(self, index: int) -> tuple[int, float]:
        return self.lines[index], self.times[index]

    def __iter__(self) -> Iterator[tuple[int, float]]:
        return zip(self.lines, self.times)

    def __eq__(self, other: object) -> bool:
        if isinstance(other, TimedLines):
            return self.lines == other.lines and self.times == other.times
        if isinstance(other, list):
            return list(self) == other
        return NotImplemented

    def __repr__(self) -> str:
        return "TimedLines(%d pairs)" % len(self)

    def index_of(self, line: int) -> int:
        """The index of `line`'s pair, or -1 if no time was recorded there."""
        lines = self.lines
        i = bisect_left(lines, line)
        return i if i < len(lines) and lines[i] == line else -1

    def by_line(self, offset: float = 0.0) -> LineTimes:
        """A read-only mapping line -> max(0, t + offset)."""
        return LineTimes(self, offset)


class LineTimes(Mapping[int, float]):
    """line -> seconds over a `TimedLines` (optionally shifted, never below 0)."""

    def __init__(self, timed: TimedLines, offset: float = 0.0) -> None:
        self._timed = timed
        self._offset = offset

    def __getitem__(self, line: int) -> float:
        i = self._timed.index_of(line)
        if i < 0:
            raise KeyError(line)
        t = self._timed.times[i]
        return t if not self._offset else max(0.0, t + self._offset)

    def __contains__(self, line: object) -> bool:
        return isinstance(line, int) and self._timed.index_of(line) >= 0

    def __iter__(self) -> Iterator[int]:
        return iter(self._timed.lines)

    def __len__(self) -> int:
        return len(self._timed)
