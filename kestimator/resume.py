"""Estimates that go on from saved planner states: the worker's answer after a change.

Owns the checkpoints of one file's estimate: while a pass runs, the whole planner (the
`Timeline` and everything it holds: toolhead with its look-ahead queue, gcode_move,
extruders, macros and variables, firmware retraction, input shaper, exclude_object, the
per-feature, per-object and per-layer sums, progress samples, warnings, pending look-ahead
callbacks) is pickled between two blocks of lines, the gap to the next checkpoint GAP_RATIO
of what is left of the file (at least MIN_GAP_RATIO of the file): denser towards the end,
where a change leaves less to replay. A later estimate of the same file whose events
(`estimate.Event`: commands typed at some line) agree with the saved run's up to a
checkpoint loads that checkpoint and reads the file on from its byte offset, so a change at
fraction f of the file costs at most (1 - f) / (1 - GAP_RATIO) of a pass (or 1 - f +
MIN_GAP_RATIO near the end) and the answer's constant; the estimate is bit for bit the one
a whole pass gives (the planner's floats are pickled exactly; tests/test_resume.py compares
the answers' bytes on every corpus file).

Memory stays bounded whatever the file: at most MAX_CHECKPOINTS checkpoints (about 50 for
any large file: 31 while the gaps shrink to MIN_GAP_RATIO, 20 in the last fifth), and no
more than MAX_CHECKPOINT_BYTES in all (past it no more are taken in that pass: later
changes replay from the last one). A checkpoint is the planner's pickle without its growing
arrays (samples, layer and mark times: `GROWING`), which are kept once, as what changed
since the previous checkpoint (plus one copy of them as at the last checkpoint, to find
what changed: the estimate's own size again), and without its caches (`CACHES`), which a
restored planner starts empty.
"""

from __future__ import annotations

import copyreg
import dataclasses
import functools
import io
import operator
import os
import pickle
from array import array
from bisect import bisect_right
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Final

from kestimator.estimate import (
    Estimate,
    Event,
    EventRunner,
    Timeline,
    line_batches_at,
    run_timeline,
)
from kestimator.progress_table import (
    Candidates,
    Selection,
    common_prefix,
    line_offsets_along,
    line_offsets_from,
)

# The gap after a checkpoint: this share of the rest of the file, at least MIN_GAP_RATIO of
# the file and MIN_GAP_BYTES (a small file has fewer checkpoints).
GAP_RATIO: Final = 0.05
MIN_GAP_RATIO: Final = 0.01
MIN_GAP_BYTES: Final = 1 << 14
MAX_CHECKPOINTS: Final = 100
# All checkpoints of a file together hold at most this many bytes.
MAX_CHECKPOINT_BYTES: Final = 64 << 20
# The candidates kept between answers with their offsets and what they were made from
# (`Resumable.line_offsets`): none when a table has more than this many.
MAX_KNOWN_OFFSETS: Final = 1 << 17
# The timeline's arrays that grow with the file, kept outside the pickles: (attribute of
# the timeline or "" for the timeline itself, attribute of that holding the array).
GROWING: Final = (("samples", "lines"), ("samples", "times"), ("layers", "lines"),
                  ("layers", "times"), ("marks", "lines"), ("marks", "times"),
                  ("", "noted_lines"))
# Caches of the timeline (memos: what they hold changes no result), pickled empty: the
# parsed-command cache was a fifth of a checkpoint's bytes and of its pickling time.
CACHES: Final = ("_commands",)


def _owner(timeline: Timeline, name: str) -> object:
    return getattr(timeline, name) if name else timeline


def _shared_prefix(a: list[int], b: list[int]) -> int:
    """How many leading items lists `a` and `b` share (compared by slices, in C)."""
    lo, hi = 0, min(len(a), len(b))  # a[:lo] == b[:lo]
    if a[:hi] == b[:hi]:
        return hi
    while hi - lo > 1:  # a[:hi] != b[:hi]
        mid = (lo + hi) // 2
        if a[lo:mid] == b[lo:mid]:
            lo = mid
        else:
            hi = mid
    return lo


def _has_dict(obj: object) -> bool:
    """Whether instances of `obj`'s class have a __dict__ (read without making one)."""
    return _instances_have_dict(type(obj))


def _instances_have_dict(cls: type) -> bool:
    return getattr(cls, "__dictoffset__", 0) != 0


def _new(cls: Any) -> object:
    """An instance of `cls` not yet initialised (its attributes come from `_set_attributes`)."""
    return cls.__new__(cls)


def _set_attributes(obj: object, state: dict[str, object]) -> None:
    """Set a loaded object's attributes one by one (frozen dataclasses too): on CPython
    3.11 and 3.12 it keeps them inline, as an object built by its __init__ does."""
    for name, value in state.items():
        object.__setattr__(obj, name, value)


def _plain_reduce(obj: object) -> tuple[Any, ...]:
    """The reduction of an instance of a plain kestimator class (`_Reductions`)."""
    return (_new, (type(obj),), obj.__dict__, None, None, _set_attributes)


def _is_plain(cls: type) -> bool:
    """Whether `cls` is a kestimator class whose instances keep their attributes in a
    __dict__ and pickle by it as object does."""
    return (_instances_have_dict(cls) and cls.__module__.startswith("kestimator.")
            and not issubclass(cls, BaseException)
            and cls.__reduce_ex__ is object.__reduce_ex__
            and cls.__reduce__ is object.__reduce__
            and getattr(cls, "__getstate__", None) is _OBJECT_GETSTATE
            and not hasattr(cls, "__setstate__"))


class _Reductions(dict):  # type: ignore[type-arg]
    """The pickler's dispatch table: for each class met, how its instances reduce.

    A plain kestimator class (`_is_plain`) pickles so that loading sets its attributes
    one by one (`_set_attributes`), not through its __dict__; every other class as pickle
    does (copyreg's table, else the object's own __reduce_ex__), and a metaclass's
    instances (classes) as pickle does, by name (no entry). The decision is made once
    per class: a reducer_override was a Python call for each object pickled (a third of a
    checkpoint's pickling)."""

    def __missing__(self, cls: type) -> Callable[[object], Any]:
        if issubclass(cls, type):
            raise KeyError(cls)
        reduce = copyreg.dispatch_table.get(cls)
        if reduce is None:
            reduce = (_plain_reduce if _is_plain(cls)
                      else operator.methodcaller("__reduce_ex__", PROTOCOL))
        self[cls] = reduce
        return reduce


# object.__getstate__ (Python 3.11 and later; None before).
_OBJECT_GETSTATE = getattr(object, "__getstate__", None)
PROTOCOL: Final = pickle.HIGHEST_PROTOCOL
_REDUCTIONS = _Reductions()


def _dumps(timeline: Timeline) -> bytes:
    out = io.BytesIO()
    pickler = pickle.Pickler(out, protocol=PROTOCOL)
    pickler.dispatch_table = _REDUCTIONS
    pickler.dump(timeline)
    return out.getvalue()


@dataclasses.dataclass
class Checkpoint:
    """The planner after line `lineno`, whose successor starts at byte `offset`."""

    lineno: int
    offset: int
    # How many of the run's events (in line order) had run.
    ran: int
    blob: bytes
    # Per GROWING array: (items kept from the previous checkpoint's, the items after them).
    deltas: list[tuple[int, array]]

    @property
    def nbytes(self) -> int:
        return len(self.blob) + sum(len(tail) * tail.itemsize for _, tail in self.deltas)


class Resumable:
    """One file's checkpoints, and estimates of that file that go on from them.

    `key` says what the checkpoints hold for (the file's identity and the settings);
    `size` is the file's size in bytes."""

    def __init__(self, key: object, size: int) -> None:
        self.key = key
        self.size = size
        self.min_gap = max(MIN_GAP_BYTES, int(size * MIN_GAP_RATIO))
        self.checkpoints: list[Checkpoint] = []
        # The events of the run the checkpoints come from, in line order.
        self.events: list[Event] = []
        # The GROWING arrays as at the last checkpoint.
        self._last: list[array] = []
        self.nbytes = 0
        # Where the last estimate started: the checkpoint's line (0: the file's start).
        self.resumed_at = 0
        # Whether the planner's pickle is still to be checked once; whether it cannot be.
        self.probe = True
        self.disabled = False
        # The last table's candidates (`Selection.candidates`: lines less one, ascending)
        # and the byte offset of the line after each, aligned (`line_offsets`): empty
        # where there were more than MAX_KNOWN_OFFSETS.
        self.candidates: list[int] = []
        self.candidate_offsets = array("q")
        # The last table's candidates with what they were made from (`select`'s
        # `previous`), under the same limit.
        self.made_from: Candidates | None = None
        # The line of each byte offset events were typed at (kestimator.worker.event_lines;
        # at most as many as one request's events).
        self.event_lines: dict[int, int] = {}

    def usable(self, events: Sequence[Event]) -> int:
        """The index of the last checkpoint valid for `events` (in line order), or -1:
        every event run before it is the saved run's, and no other is due by then."""
        found = -1
        for i, checkpoint in enumerate(self.checkpoints):
            ran = checkpoint.ran
            if list(events[:ran]) != self.events[:ran]:
                break
            if len(events) > ran and events[ran][0] <= checkpoint.lineno + 1:
                break
            found = i
        return found

    def estimate(self, path: str, new_timeline: Callable[[Sequence[Event]], Timeline],
                 events: Sequence[Event]) -> Estimate:
        """The estimate of `path` with `events`, from the last usable checkpoint (or from
        `new_timeline(events)` at the file's start), taking checkpoints as it goes."""
        ordered = sorted(events, key=lambda event: event[0])
        index = self.usable(ordered)
        if index >= 0:
            checkpoint = self.checkpoints[index]
            timeline = self._restore(index, ordered)
            lineno, offset = checkpoint.lineno, checkpoint.offset
            del self.checkpoints[index + 1:]
        else:
            timeline = new_timeline(ordered)
            lineno = offset = 0
            self.checkpoints = []
            self._last = [array(getattr(_owner(timeline, owner), name).typecode)
                          for owner, name in GROWING]
        self.nbytes = sum(c.nbytes for c in self.checkpoints)
        self.events = ordered
        self.resumed_at = lineno

        self.live = timeline

        def feed() -> Timeline:
            with open(path, "rb", buffering=0) as f:
                f.seek(offset)
                self._feed(line_batches_at(f.read, path, None, lineno, offset), offset)
            return self.live
        return run_timeline(timeline, feed, self._live)

    def _live(self) -> Timeline:
        return self.live

    def _feed(self, batches: Iterator[tuple[list[bytes], int]], offset: int) -> None:
        """Feed `self.live` the batches, taking checkpoints as due (and, in the pure build,
        going on with the checkpoint's copy: see `_save`)."""
        due = offset + self.gap(offset)
        for lines, after in batches:
            self.live.feed_lines(lines)
            if (due <= after < self.size and self.nbytes < MAX_CHECKPOINT_BYTES
                    and len(self.checkpoints) < MAX_CHECKPOINTS and not self.disabled):
                self._save(self.live, after)
                due = after + self.gap(after)

    def gap(self, offset: int) -> int:
        """Bytes from a checkpoint at `offset` to the next."""
        return max(self.min_gap, int((self.size - offset) * GAP_RATIO))

    def _save(self, timeline: Timeline, offset: int) -> None:
        """A checkpoint of `timeline` after its last line, the next one at `offset`.

        Pickling reads each object's __dict__, and on CPython 3.11 and 3.12 an object whose
        __dict__ was read keeps a real dict for life: its attributes are slower to read
        (a pass taking checkpoints cost 23 % more). So where the planner's objects have a
        __dict__ (the pure build), the pass goes on with the checkpoint's copy, whose
        objects were built attribute by attribute (`_set_attributes`); compiled classes
        have no __dict__ and go on as they are."""
        # The samples add() held back go into their arrays first (their pending lists
        # would pickle item by item; when they move changes nothing kept).
        timeline.samples.flush()
        growing = []
        for owner, name in GROWING:
            holder = _owner(timeline, owner)
            values = getattr(holder, name)
            growing.append(values)
            setattr(holder, name, array(values.typecode))
        caches = [getattr(timeline, name) for name in CACHES]
        for name in CACHES:
            setattr(timeline, name, {})
        copy: Timeline | None = None
        try:
            blob = _dumps(timeline)
            if self.probe or _has_dict(timeline):
                # That the planner loads again (once per file where the copy is not used).
                # A build whose classes do not (mypyc's native classes without
                # serializable=True cannot be created without their __init__'s arguments)
                # takes no checkpoints: whole passes.
                self.probe = False
                copy = pickle.loads(blob)
        except (pickle.PickleError, TypeError, AttributeError):
            self.disabled = True
            return
        finally:
            for (owner, name), values in zip(GROWING, growing):
                setattr(_owner(timeline, owner), name, values)
            for name, cache in zip(CACHES, caches):
                setattr(timeline, name, cache)
        if copy is not None and _has_dict(timeline):
            for (owner, name), values in zip(GROWING, growing):
                setattr(_owner(copy, owner), name, values)
            for name, cache in zip(CACHES, caches):
                setattr(copy, name, cache)
            self.live = copy
        deltas = []
        for last, values in zip(self._last, growing):
            kept = common_prefix(last, values)
            tail = values[kept:]
            deltas.append((kept, tail))
            # The copy as at this checkpoint, mended where it differs: a new copy of the
            # whole array (320 KB of samples on the 40 MB file) took fresh pages each time.
            del last[kept:]
            last.extend(tail)
        runner = timeline.events
        checkpoint = Checkpoint(timeline.lineno, offset,
                                runner.next if runner is not None else 0, blob, deltas)
        self.checkpoints.append(checkpoint)
        self.nbytes += checkpoint.nbytes

    def line_offsets(self, path: str, selection: Selection, line_bytes: float
                     ) -> tuple[list[int], list[int]]:
        """The byte offsets a table of `selection` needs (`ProgressTable.from_offsets`):
        of its lines and of its objects' lines, each line past the file's end at its end;
        `line_bytes`: the file's mean line length.

        The offset of every candidate (every line a table of this estimate could hold) is
        kept, aligned with the candidates: a later change moves the total, and with it
        which points the table keeps before the change, but the candidates before where
        that pass went on from are this one's. So an answer after a change counts only
        the candidates past its checkpoint that the last one did not have
        (`line_offsets_along`, each from the line before it) and reads the table's offsets
        by index (after a change at 90 % of the 40 MB file, the offsets and the table took
        8 ms, against 12 when each line was looked up in a dict of the 80,000 found so
        far). A file of more than MAX_KNOWN_OFFSETS candidates (countless layers) keeps
        none: each table counts its own lines, from the checkpoints'."""
        candidates = selection.candidates
        with open(path, "rb", buffering=0) as f:
            read_at: Callable[[int, int], bytes]
            if hasattr(os, "pread"):  # one call (no seek), and no Python frame per read
                read_at = functools.partial(os.pread, f.fileno())
            else:
                def read_at(size: int, offset: int) -> bytes:
                    f.seek(offset)
                    return f.read(size) or b""
            if len(candidates) > MAX_KNOWN_OFFSETS:
                self.candidates, self.candidate_offsets = [], array("q")
                self.made_from = None
                lines = sorted(selection.lines + selection.object_lines)
                known = self._anchors()
                found = line_offsets_from(read_at, lines, known, sorted(known), line_bytes)
                return ([found.get(line, self.size) for line in selection.lines],
                        [found.get(line, self.size) for line in selection.object_lines])
            offsets = self._candidate_offsets(read_at, candidates, line_bytes)
            self.candidates, self.candidate_offsets = candidates, offsets
            self.made_from = selection.made_from
            objects = self._offsets_among_candidates(read_at, selection.object_lines,
                                                     line_bytes)
        return [offsets[i] for i in selection.kept], objects

    def stop_offsets(self, path: str, selection: Selection, line_bytes: float) -> list[int]:
        """The byte offsets of the selection's stops' lines (a line past the file's end at
        its end), each counted from the closest candidate before it (`line_offsets` has
        found the candidates' offsets) or checkpoint."""
        lines = selection.stop_lines
        if not lines:
            return []
        with open(path, "rb", buffering=0) as f:
            def read_at(size: int, offset: int) -> bytes:
                f.seek(offset)
                return f.read(size) or b""
            if self.candidates and self.candidates == selection.candidates:
                return self._offsets_among_candidates(read_at, lines, line_bytes)
            known = self._anchors()
            found = line_offsets_from(read_at, lines, known, sorted(known), line_bytes)
        return [found.get(line, self.size) for line in lines]

    def _anchors(self) -> dict[int, int]:
        """Lines whose byte offsets the checkpoints give (line -> offset): line 1's and
        each checkpoint's next line's."""
        known = {1: 0}
        for checkpoint in self.checkpoints:
            known[checkpoint.lineno + 1] = checkpoint.offset
        return known

    def _candidate_offsets(self, read_at: Callable[[int, int], bytes],
                           candidates: list[int], line_bytes: float) -> array:
        """The byte offset of the line after each of `candidates` (the file's size past
        its end): those the last table's candidates share with them, from before where
        this pass went on from, as found then; the others found among the last table's
        later candidates (after a change at 90 % of the 40 MB file, half of them) or
        counted from the closest line before them whose offset is known."""
        old = self.candidates
        shared = bisect_right(candidates, self.resumed_at - 1)
        if shared > len(old) or candidates[:shared] != old[:shared]:
            shared = _shared_prefix(candidates, old)
        offsets = self.candidate_offsets[:shared]
        base_line, base = (candidates[shared - 1] + 1, offsets[-1]) if shared else (1, 0)
        offsets.extend(line_offsets_along(
            read_at, [line + 1 for line in candidates[shared:]],
            [line + 1 for line in old[shared:]], self.candidate_offsets[shared:],
            line_bytes, base_line=base_line, base=base, missing=self.size))
        return offsets

    def _offsets_among_candidates(self, read_at: Callable[[int, int], bytes],
                                  lines: list[int], line_bytes: float) -> list[int]:
        """The byte offsets of `lines` (ascending), each a candidate's line (an object
        point is a layer's) or counted from the closest one before it."""
        candidates, offsets = self.candidates, self.candidate_offsets
        known_lines: list[int] = []
        known_offsets: list[int] = []
        for line in lines:
            i = bisect_right(candidates, line - 1) - 1
            if i >= 0:
                known_lines.append(candidates[i] + 1)
                known_offsets.append(offsets[i])
        return line_offsets_along(read_at, lines, known_lines, known_offsets, line_bytes,
                                  missing=self.size)

    def _arrays_at(self, index: int) -> list[array]:
        """The GROWING arrays as at checkpoint `index`. Where no later checkpoint kept
        fewer items than they had then, they are the first items of the arrays as at the
        last checkpoint (`_last`): one copy, not the deltas of every checkpoint before
        (350 extends of the 40 MB file's arrays, a third of loading a checkpoint)."""
        result = []
        for i, last in enumerate(self._last):
            kept, tail = self.checkpoints[index].deltas[i]
            length = kept + len(tail)
            if all(later.deltas[i][0] >= length for later in self.checkpoints[index + 1:]):
                result.append(last[:length])
                continue
            values = array(last.typecode)
            for earlier in self.checkpoints[:index + 1]:
                kept, tail = earlier.deltas[i]
                del values[kept:]
                values.extend(tail)
            result.append(values)
        return result

    def _restore(self, index: int, events: list[Event]) -> Timeline:
        """The timeline of checkpoint `index`, to go on with `events`."""
        checkpoint = self.checkpoints[index]
        timeline: Timeline = pickle.loads(checkpoint.blob)
        self._last = self._arrays_at(index)
        for (owner, name), values in zip(GROWING, self._last):
            setattr(_owner(timeline, owner), name, array(values.typecode, values))
        if events:
            runner = EventRunner(timeline, events)
            runner.next = checkpoint.ran
            timeline.events = runner
        else:
            timeline.events = None
        return timeline
