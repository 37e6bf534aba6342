"""One streaming pass over a G-code file: Klipper's time at every line that matters.

Owns the timeline: reading the file line by line (lines end at LF, as Klipper reads them),
layer markers, the `; ESTIMATOR_ADD_TIME` comment, warnings, and the `Estimate` result.
Per-feature and per-object sums are `kestimator.segments`'. The file is never held in
memory: only the look-ahead queue (bounded by Klipper's own flush rule) and the recorded
times (one per layer and per sample) are kept.
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
import struct
from array import array
from collections.abc import Callable, Iterable, Iterator, Sequence
from functools import partial
from itertools import chain, islice
from typing import Final

from kestimator.durations import MAX_PRINT_S
from kestimator.errors import CommandError, KestimatorError, MoveError, ParamError, PrintEndsError
from kestimator.gcode import (
    SCAN_PLAIN_MOVES,
    Command,
    parse_line,
    parse_plain_move_regex,
    parse_plain_move_scan,
)
from kestimator.interpreter import KIND_MACRO, MAX_COMMAND_NAMES, Interpreter
from kestimator.limits import Limits
from kestimator.macros import (
    ADD_TIME_SOURCE,
    FIRST_EXTRUSION_MM,
    LEARNED_PREP_LABEL,
    MOTION_CORRECTION_LABEL,
    MacroTimes,
    Parts,
    TimedPart,
)
from kestimator.preflight import KIND_STOP, Finding, Preflight
from kestimator.segments import OBJECT_COMMANDS, Segments
from kestimator.stops import Stop, StopLog, known_stops, stop_commands
from kestimator.timedlines import TimedLines
from kestimator.toolhead import Move, make_toolhead

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

# Comment markers that start a layer.
LAYER_MARKERS: Final = (";LAYER_CHANGE", ";LAYER:", "; CHANGE_LAYER")
# Comment markers that name the feature (extrusion role) of the moves that follow.
FEATURE_MARKERS: Final = (";TYPE:", "; FEATURE:")
ADD_TIME_MARKER: Final = "ESTIMATOR_ADD_TIME"
# Estimate.commands kind of commands Klipper does not know.
KIND_UNKNOWN: Final = "unknown"
# At most this many warnings are kept (each names its line); the rest are counted.
MAX_WARNINGS: Final = 100
# The file is read in blocks of this size; a line is held whole up to MAX_LINE_BYTES.
# 16 KiB: the same CPU as 1 MiB blocks under CPython; under PyPy, whose GC frees large
# objects late, peak RSS 146 MB instead of 210 MB on the 40 MB file.
READ_BLOCK_BYTES: Final = 1 << 14
MAX_LINE_BYTES: Final = 1 << 20
# Progress samples kept for placing M73 lines: at most this many (memory stays bounded);
# when full, every other sample is dropped and the spacing doubles.
MAX_SAMPLES: Final = 65536
FIRST_SAMPLE_SPACING_S: Final = 0.01
# Once the samples' spacing has grown past TAIL_SPACING_S (a long print), the last
# TAIL_SAMPLES moves at least that far apart are kept too (`Estimate.tail_lines`): the
# progress table needs the end of a print finer than the doubled spacing (memory bounded).
TAIL_SPACING_S: Final = 0.2
TAIL_SAMPLES: Final = 4096
# ProgressSamples holds back at most this many samples before moving them into its arrays.
SAMPLES_PENDING: Final = 1024
# Parsed commands kept for lines that repeat (memory stays bounded: only short lines are
# kept, and the cache is emptied when full).
MAX_CACHED_COMMANDS: Final = 4096
MAX_CACHED_COMMAND_CHARS: Final = 200
# An ESTIMATOR_ADD_TIME label is kept to this many characters.
MAX_LABEL_CHARS: Final = 60
# A progress callback hears about once per this many bytes read.
PROGRESS_EVERY_BYTES: Final = 1 << 20


@dataclasses.dataclass
class Estimate:
    """What Klipper's planner gives for one file."""

    path: str
    total_s: float
    # (line, seconds) of each layer marker, in file order.
    layers: TimedLines
    features: dict[str, float]
    n_moves: int
    n_lines: int
    ignored_commands: dict[str, int]
    warnings: list[str]
    warnings_dropped: int
    # Progress samples: the move on line sample_lines[i] ends at sample_times[i] seconds
    # (spacing at most total_s / 32768, so any line's time is known to that precision).
    sample_lines: array
    sample_times: array
    # Exact times at comment lines asked for (e.g. Cura's ;TIME_ELAPSED:), in file order
    # (`marks.by_line()` maps line -> t).
    marks: TimedLines
    first_command_line: int | None
    last_move_line: int | None
    # Net filament the moves push (mm of E, after M221; retractions count negative).
    filament_mm: float = 0.0
    # The lines other than plain moves that the `note` matcher given to the estimate
    # matched, by number, in file order (inject's pass 2 stops its block copies there).
    noted_lines: array = dataclasses.field(default_factory=lambda: array("q"))
    # Object name -> seconds; NO_OBJECT is time outside every labelled object. Empty when
    # the file labels no objects. Sums to total_s (as features do).
    objects: dict[str, float] = dataclasses.field(default_factory=dict)
    # Commands that are not Klipper's own motion commands, by kind, each name -> times run:
    # "macro" (a printer.cfg [gcode_macro] with a template: not run, counted as 0 s),
    # "expanded_macro" (a literal [gcode_macro]: its commands ran, their time is included),
    # "module" (a no-time command of a module the printer's config has),
    # "unknown" (Klipper does not know it: skipped; the same as ignored_commands).
    commands: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)
    # What Klipper will do with the file on this printer (kestimator.preflight): where it
    # stops the print, which commands it skips.
    preflight: list[Finding] = dataclasses.field(default_factory=list)

    @property
    def stops_print(self) -> bool:
        """Klipper will stop this print at a command error."""
        return any(f.kind == KIND_STOP for f in self.preflight)
    # Time added where the file runs macros, waits or says ESTIMATOR_ADD_TIME, by kind.
    timed_parts: list[TimedPart] = dataclasses.field(default_factory=list)
    # Commands that are no Klipper command and have no time (macros whose time is unknown).
    untimed_macros: dict[str, int] = dataclasses.field(default_factory=dict)
    # Heater waits ("heater_waits") and G28 lines ("homings") counted as 0 s: no time was
    # given for them, and no learned start time holds them. Empty when there are none.
    untimed_waits: dict[str, int] = dataclasses.field(default_factory=dict)
    # When the first move that extrudes starts (print_stats starts print_duration there).
    first_extrusion_t: float | None = None
    # The print's end sampled finer than sample_lines/sample_times once a long print made
    # their spacing pass TAIL_SPACING_S: the move on tail_lines[i] ends at tail_times[i].
    tail_lines: array = dataclasses.field(default_factory=lambda: array("q"))
    tail_times: array = dataclasses.field(default_factory=lambda: array("d"))
    # Lines of unknown commands left out of ignored_commands and commands: their names came
    # after MAX_COMMAND_NAMES others (memory stays bounded).
    ignored_unlisted: int = 0
    # (line, t, object name -> seconds it still takes from there to the end) at each layer
    # marker, with any exclusion applied (an excluded object's time drops to 0). Empty when
    # no object is labelled; bounded by segments.MAX_REMAINING_LAYERS (markers thinned to
    # every 2nd, 4th, ...) and MAX_REMAINING_OBJECTS (the first objects to print).
    object_remaining: list[tuple[int, float, dict[str, float]]] = dataclasses.field(
        default_factory=list)
    # The commands at which the print waits for a person (kestimator.stops), in file order,
    # each with Klipper's time from the start to when the printer stands there; at most
    # stops.MAX_STOPS, the further ones counted in stops_unlisted.
    stops: list[Stop] = dataclasses.field(default_factory=list)
    stops_unlisted: int = 0

    @property
    def parts(self) -> Parts:
        """The total split into Klipper's motion and the added times."""
        return Parts.of(self.total_s, self.timed_parts)

    @property
    def first_layer_s(self) -> float | None:
        """Seconds from the first layer marker to the second (None without two layers)."""
        if len(self.layers) < 2:
            return None
        return self.layers[1][1] - self.layers[0][1]


def _is_layer_marker(comment_line: str) -> bool:
    for marker in LAYER_MARKERS:
        if comment_line.startswith(marker):
            rest = comment_line[len(marker):]
            if marker == ";LAYER:":
                return rest.strip().lstrip("-").isdigit()
            return not rest.strip()
    return False


# Called with each batch of planned moves and the time the first of them starts.
MoveObserver = Callable[[list[Move], float], None]
# Called with the number of bytes read so far (about once per PROGRESS_EVERY_BYTES).
ProgressCallback = Callable[[int], None]
# (line, command): the command runs right before the file's line `line` (1-based), as if
# typed at the printer's console at that moment of the print (EXCLUDE_OBJECT NAME=...,
# M220 S150). Events on one line run in list order; an event on the line after the last
# runs at the end, events further on never run.
Event = tuple[int, str]


def iter_lines(path: str | os.PathLike[str],
               progress: ProgressCallback | None = None) -> Iterator[bytes]:
    """The file's lines as bytes, split at LF only (the LF is dropped; a CR before it stays).

    Memory stays bounded whatever the file holds: it is read in blocks, and a line longer
    than MAX_LINE_BYTES is never held whole (see `over_long_line`). `progress` hears the
    bytes read so far, about once per PROGRESS_EVERY_BYTES and at the end. The lines of a
    block come as one list, flattened by C code (no generator step per line).
    """
    return chain.from_iterable(_line_batches(path, progress))


def _line_batches(path: str | os.PathLike[str],
                  progress: ProgressCallback | None) -> Iterator[list[bytes]]:
    try:
        with open(path, "rb", buffering=0) as f:
            yield from split_line_batches(f.read, os.fspath(path), progress)
    except IsADirectoryError:
        raise KestimatorError("is a directory, not a G-code file", path) from None
    except OSError as exc:
        raise KestimatorError("cannot read file: %s" % (exc.strerror or exc), path) from None


def split_line_batches(read: Callable[[int], bytes], path: str,
                       progress: ProgressCallback | None) -> Iterator[list[bytes]]:
    """The lines `read` gives, block by block: a list of lines per block (see iter_lines)."""
    for parts, _ in line_batches_at(read, path, progress):
        yield parts


def line_batches_at(read: Callable[[int], bytes], path: str,
                    progress: ProgressCallback | None = None, lineno: int = 0,
                    offset: int = 0) -> Iterator[tuple[list[bytes], int]]:
    """split_line_batches' lists, each with the byte offset of the line that follows it
    (-1 where that is not known: after the rest of an over-long line was skipped). `read`
    starts at byte `offset` of the file, at the start of line `lineno` + 1."""
    # A line that fits in a block is split out by C code; only a line that spans blocks
    # (its start is `rest`) can be over MAX_LINE_BYTES (READ_BLOCK_BYTES <= that bound).
    rest = b""
    done = 0
    next_report = PROGRESS_EVERY_BYTES
    skipping: bytes | None = None  # the start of an over-long line whose rest is skipped
    while True:
        block = read(READ_BLOCK_BYTES)
        if not block:
            break
        done += len(block)
        if progress is not None and done >= next_report:
            progress(done)
            next_report = done + PROGRESS_EVERY_BYTES
        if skipping is not None:
            nl = block.find(b"\n")
            if nl < 0:
                continue
            lineno += 1
            yield [over_long_line(skipping, lineno, path)], -1
            skipping = None
            block = block[nl + 1:]
        parts = block.split(b"\n")
        if rest:
            first = rest + parts[0]
            if len(first) > MAX_LINE_BYTES and len(parts) > 1:
                first = over_long_line(first[:MAX_LINE_BYTES], lineno + 1, path)
            parts[0] = first
        rest = parts.pop()
        if parts:
            lineno += len(parts)
            yield parts, offset + done - len(rest)
        if len(rest) > MAX_LINE_BYTES:
            skipping = rest[:MAX_LINE_BYTES]
            rest = b""
    if skipping is not None:
        yield [over_long_line(skipping, lineno + 1, path)], -1
    elif rest:
        yield [rest], offset + done
    if progress is not None:
        progress(done)


def over_long_line(head: bytes, lineno: int, path: str) -> bytes:
    """What stands for a line longer than MAX_LINE_BYTES, given its first MAX_LINE_BYTES.

    Klipper reads a line whole, whatever its length, and ignores what follows a ``;``. A
    line whose start already holds a ``;`` (a comment, or a command with a long comment) is
    therefore exactly its start; any other such line is refused (a command line of
    megabytes is no G-code a slicer writes, and reading it whole costs memory without
    bound), with the file and line named."""
    if b";" in head:
        return head
    raise KestimatorError("a line of over %d MiB with no comment: kestimator reads no "
                          "command line that long" % (MAX_LINE_BYTES >> 20), path, lineno)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Warnings:
    """The warnings of one file, each naming file and line: the first MAX_WARNINGS kept, the
    rest counted; repeats of the same key are counted on the first ("N more like it")."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.kept: list[str] = []
        self.repeats: list[int] = []
        self.keys: dict[str, int] = {}
        self.dropped = 0

    def add(self, message: str, line: int | None, key: str | None) -> None:
        """One warning at `line` (None: the whole file)."""
        if key is not None:
            index = self.keys.get(key)
            if index is not None:
                self.repeats[index] += 1
                return
        if len(self.kept) >= MAX_WARNINGS:
            self.dropped += 1
            return
        where = "%s:%d: " % (self.path, line) if line is not None else "%s: " % self.path
        if key is not None:
            self.keys[key] = len(self.kept)
        self.kept.append(where + message)
        self.repeats.append(0)

    def final(self) -> list[str]:
        """The warnings as reported, with their repeat counts."""
        return [w if not n else "%s (%d more like it)" % (w, n)
                for w, n in zip(self.kept, self.repeats)]


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ProgressSamples:
    """Where the print is at times through it: the move on line lines[i] ends at times[i],
    spaced at least `spacing` apart (at most MAX_SAMPLES kept: when full, every other one
    goes and the spacing doubles), and, once that spacing has passed TAIL_SPACING_S, the
    last TAIL_SAMPLES moves TAIL_SPACING_S apart (`tail_lines`, `tail_times`)."""

    def __init__(self) -> None:
        self.lines = array("q")
        self.times = array("d")
        self.spacing = FIRST_SAMPLE_SPACING_S
        # The next time add() wants; the next regular sample's time.
        self.next_t = 0.0
        self.next_regular_t = 0.0
        # The tail: arrays, not a deque of pairs, so a checkpoint (kestimator.resume)
        # pickles it as two blocks of bytes (a deque's 4,096 tuples took 0.4 ms of 1.2).
        self.tail_lines = array("q")
        self.tail_times = array("d")
        # Samples (and tail samples) not yet in lines and times (tail): add() appends
        # to lists, which the compiled build does in C, where an array's
        # append is a method call by name (8 % of a compiled inject). flush() moves them.
        self.new_lines: list[int] = []
        self.new_times: list[float] = []
        self.new_tail_lines: list[int] = []
        self.new_tail_times: list[float] = []

    def add(self, line: int, t: float) -> None:
        """The move on `line` ends at `t` (at least next_t)."""
        if t >= self.next_regular_t:
            new_lines = self.new_lines
            if len(self.lines) + len(new_lines) >= MAX_SAMPLES:
                self.flush()
                del self.lines[1::2]
                del self.times[1::2]
                self.spacing *= 2.0
            elif len(new_lines) >= SAMPLES_PENDING:
                self.flush()
            new_lines.append(line)
            self.new_times.append(t)
            self.next_regular_t = t + self.spacing
        if self.spacing > TAIL_SPACING_S:
            new_tail_lines = self.new_tail_lines
            if len(new_tail_lines) >= SAMPLES_PENDING:
                self.flush()
            new_tail_lines.append(line)
            self.new_tail_times.append(t)
            self.next_t = min(self.next_regular_t, t + TAIL_SPACING_S)
        else:
            self.next_t = self.next_regular_t

    def flush(self) -> None:
        """Move the samples add() holds back into lines, times and tail."""
        if self.new_lines:
            # struct packs the lists in C; array.extend converts item by item, as slowly
            # as append (its typecode is parsed for each).
            n = len(self.new_lines)
            self.lines.frombytes(struct.pack("%dq" % n, *self.new_lines))
            self.times.frombytes(struct.pack("%dd" % n, *self.new_times))
            self.new_lines.clear()
            self.new_times.clear()
        if self.new_tail_lines:
            n = len(self.new_tail_lines)
            self.tail_lines.frombytes(struct.pack("%dq" % n, *self.new_tail_lines))
            self.tail_times.frombytes(struct.pack("%dd" % n, *self.new_tail_times))
            self.new_tail_lines.clear()
            self.new_tail_times.clear()
            self._trim_tail()

    def add_tail(self, line: int, t: float) -> None:
        """One more tail sample, past those add() took (flushed first)."""
        self.flush()
        self.tail_lines.append(line)
        self.tail_times.append(t)
        self._trim_tail()

    def _trim_tail(self) -> None:
        """Keep the last TAIL_SAMPLES tail samples."""
        extra = len(self.tail_lines) - TAIL_SAMPLES
        if extra > 0:
            del self.tail_lines[:extra]
            del self.tail_times[:extra]

    def map_times(self, function: Callable[[float], float]) -> None:
        """Every time t becomes function(t)."""
        self.flush()
        times = self.times
        for i in range(len(times)):
            times[i] = function(times[i])
        tail_times = self.tail_times
        for i in range(len(tail_times)):
            tail_times[i] = function(tail_times[i])


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Timeline:
    """Drives the interpreter over lines and records times at the lines asked for."""

    def __init__(self, limits: Limits, path: str = "<input>", homing_time: float = 0.0,
                 heat_time: float = 0.0, sample: bool = False,
                 mark_prefixes: tuple[str, ...] = (),
                 observer: MoveObserver | None = None,
                 macros: MacroTimes | None = None,
                 note: Callable[[bytes], object] | None = None,
                 events: Sequence[Event] = ()) -> None:
        self.path = path
        self.observer = observer
        self.events = EventRunner(self, events) if events else None
        self.toolhead = make_toolhead(limits, on_moves=self._on_moves)
        self.warnings = Warnings(path)
        self.interp = Interpreter(limits, self.toolhead, self._warn_here,
                                  homing_time=homing_time, heat_time=heat_time,
                                  add_time=self.add_time)
        self.macros = macros if macros is not None else MacroTimes()
        if self.macros.macros:
            self.interp.on_unknown = self._unknown_command
        self.interp.on_unshown = self._unknown_command
        self.timed_parts: dict[tuple[str, str], TimedPart] = {}
        # Where the last added time ended (0: none yet).
        self._rest_until = 0.0
        self.first_extrusion_t: float | None = None
        self.preflight = Preflight()
        self.interp.preflight = self.preflight
        # Time per feature and per object (kestimator.segments).
        self.split = Segments(self.toolhead)
        self.layers = TimedLines()
        self.marks = TimedLines()
        self.mark_prefixes = mark_prefixes
        self.note = note
        self.noted_lines = array("q")
        self.sample = sample
        self.samples = ProgressSamples()
        self.n_moves = 0
        self.filament_mm = 0.0
        self.lineno = 0
        self.first_command_line: int | None = None
        self._warned_macros: set[str] = set()
        self._commands: dict[str, Command] = {}
        # What the printer's kinematics does that is not modelled: said once, up front;
        # its commands that change motion are named where they run.
        for message in self.toolhead.kin.warnings:
            self.warn(message, None, "kinematics:" + message)
        if self.toolhead.kin.unchecked is not None:
            self.preflight.moves_unchecked(self.toolhead.kin.unchecked)
        self._kin_commands = self.toolhead.kin.commands
        self.stops = stop_log(limits, self.interp)  # kestimator.stops
        learned = self.macros.before_first_extrusion
        if learned is not None:
            # The printer's own history measured everything before the first extrusion:
            # it stands at the start, and the added times it holds are not counted again.
            self.toolhead.add_time(learned.seconds)
            self._rest_until = self.toolhead.print_time
            part = self._part(LEARNED_PREP_LABEL, learned.source)
            part.count = 1
            part.seconds = part.before_first_extrusion_s = learned.seconds

    # Callbacks from the toolhead
    def _on_moves(self, moves: list[Move], start_t: float) -> None:
        split = self.split
        split.rest_until(start_t)
        segment_time = split.segment_time
        changes = split.changes
        segment = split.segment
        t = start_t
        filament = self.filament_mm
        samples = self.samples
        next_sample_t = samples.next_t if self.sample else math.inf
        if self.first_extrusion_t is None:
            self.first_extrusion_t = first_extrusion(moves, start_t, filament)
        # The current segment's sum stays in a local (unboxed in the compiled build) and
        # goes back to segment_time before anything reads it: the same additions.
        seconds = segment_time[segment]
        for move in moves:
            while changes and changes[0][0] <= move.tag:
                sid = changes.popleft()[1]
                segment_time[segment] = seconds
                if sid < 0:  # a layer marker: each object's time before this move
                    split.snapshot(-1 - sid)
                else:
                    segment = sid
                seconds = segment_time[segment]
            dt = move.accel_t + move.cruise_t + move.decel_t
            seconds = seconds + dt
            t += dt
            filament += move.axes_d_e
            if t >= next_sample_t:
                samples.add(move.tag, t)
                next_sample_t = samples.next_t
        segment_time[segment] = seconds
        if t > MAX_PRINT_S:
            raise _too_long_move(self.path, moves, start_t)
        split.segment = segment
        split.counted_until = t
        self.filament_mm = filament
        self.n_moves += len(moves)
        if self.observer is not None:
            self.observer(moves, start_t)

    def _part(self, name: str, source: str) -> TimedPart:
        part = self.timed_parts.get((name, source))
        if part is None:
            part = self.timed_parts[(name, source)] = TimedPart(name, source)
        return part

    def add_time(self, seconds: float, name: str, source: str) -> None:
        """Time that passes with the toolhead at rest where this line runs `name`.

        Before the first extrusion it is prep time (not in print_duration); when a learned
        time before the first extrusion stands in for all of it, it is only counted.
        """
        toolhead = self.toolhead
        toolhead.wait_moves()
        part = self._part(name, source)
        part.count += 1
        prep = self.first_extrusion_t is None
        if prep and self.macros.before_first_extrusion is not None:
            part.covered += 1
            return
        before = toolhead.print_time
        split = self.split
        split.rest_until(before)
        toolhead.add_time(seconds)
        if toolhead.print_time > MAX_PRINT_S:
            raise _too_long_added(self.path, self.lineno, name, seconds, source)
        # add_time stopped the head: every queued segment change has been applied.
        split.segment_time[split.queued_segment] += toolhead.print_time - before
        split.counted_until = toolhead.print_time
        self._rest_until = toolhead.print_time
        part.seconds += seconds
        if prep:
            part.before_first_extrusion_s += seconds

    def _correct_motion(self, total: float) -> float:
        """Apply a learned motion ratio to the motion after the first extrusion.

        The extra time is spread evenly over everything after the first extrusion: the
        times recorded there (layers, marks, progress samples) stretch by one factor and
        every feature's and object's time grows in proportion, so the parts still add up.
        """
        ratio = self.macros.motion_ratio
        first = self.first_extrusion_t
        if ratio is None or ratio.seconds <= 1.0 or first is None or total <= first:
            return total
        added_after = sum(p.seconds - p.before_first_extrusion_s
                          for p in self.timed_parts.values())
        extra = (ratio.seconds - 1.0) * max(0.0, total - first - added_after)
        factor = (total - first + extra) / (total - first)

        def stretch(t: float) -> float:
            return t if t <= first else first + (t - first) * factor
        self.layers.map_times(stretch)
        self.marks.map_times(stretch)
        self.samples.map_times(stretch)
        grow = (total + extra) / total
        self.split.scale(grow)
        part = self._part(MOTION_CORRECTION_LABEL, ratio.source)
        part.count = 1
        part.seconds = extra
        return total + extra

    def _unknown_command(self, name: str) -> bool:
        """A command Klipper does not know (a macro), or one whose time the file cannot
        show: timed if the table has it (True then)."""
        timed = self.macros.time_of(name)
        if timed is not None:
            self.add_time(timed.seconds, name, timed.source)
        return timed is not None

    def _warn_here(self, message: str, key: str | None = None) -> None:
        self.warn(message, self.lineno, key)

    def warn(self, message: str, line: int | None = None, key: str | None = None) -> None:
        """Keep a warning naming file and line; repeats of the same key are only counted."""
        self.warnings.add(message, line, key)

    def _record(self, store: TimedLines, lineno: int) -> None:
        """The time at which the printer reaches ``lineno``: when every move queued before
        it has finished (a look-ahead callback, as in Klipper's register_lookahead_callback)
        or, with nothing queued, Klipper's print_time there (after any dwell or motors-off
        pause since the last move), read without the flush or priming that
        get_last_move_time would do: a comment changes nothing in Klipper."""
        toolhead = self.toolhead
        if toolhead.lookahead.is_empty():
            if self._rest_until:
                # Nothing moved since an added time: the line comes after it, not before.
                store.append(lineno, max(toolhead.last_move_end_t, self._rest_until))
            else:
                store.append(lineno, toolhead.print_time)
            return
        index = len(store)
        store.append(lineno, 0.0)
        # A partial, not a closure: the worker pickles the planner (kestimator.resume).
        self.toolhead.register_lookahead_callback(partial(store.set_time, index))

    # Per line
    def feed(self, raw: bytes) -> None:
        """Process one line (bytes, with or without its line ending)."""
        self.feed_lines((raw,))

    def feed_lines(self, lines: Iterable[bytes]) -> None:
        """Process every line of `lines`, in order (running the events due before each)."""
        events = self.events
        if events is not None and events.pending():
            events.feed_lines(lines)
        else:
            self._feed_lines(lines)

    def _feed_lines(self, lines: Iterable[bytes]) -> None:
        """The per-line loop: process every line of `lines`, in order."""
        gcode_move = self.interp.gcode_move
        lineno = self.lineno
        try:
            for raw in lines:
                lineno += 1
                if SCAN_PLAIN_MOVES:
                    plain, x, y, z, e, f = parse_plain_move_scan(raw)
                else:
                    plain, x, y, z, e, f = parse_plain_move_regex(raw)
                if not plain:
                    self.lineno = lineno
                    self._feed_other(raw)
                    continue
                # A plain G0/G1 line: what `_feed_other` would do, without a Command.
                if self.first_command_line is None:
                    self.first_command_line = lineno
                gcode_move.tag = lineno
                try:
                    gcode_move.plain_move(x, y, z, e, f)
                except MoveError as exc:
                    self.lineno = lineno
                    gcode_move.reset_last_position()
                    self._reject(raw.decode("utf-8", "replace").strip(), exc)
        finally:
            # A plain move needs no self.lineno (its move carries the line): it is stored
            # only where something reads it, and here, whatever ends the loop.
            self.lineno = lineno

    def _feed_other(self, raw: bytes) -> None:
        """Any line but a plain G0/G1 one (self.lineno is already this line's number)."""
        note = self.note
        if note is not None and note(raw) is not None:
            self.noted_lines.append(self.lineno)
        text = raw.decode("utf-8", "replace")
        stripped = text.strip()
        if not stripped:
            return
        if stripped[0] == ";":
            self._comment(stripped)
            return
        # Lines other than plain moves repeat (G10/G11, M204 S.., fan and temperature
        # commands): parse each distinct text once. A Command is never changed after
        # parsing, so one can serve every line with that text.
        commands = self._commands
        cmd = commands.get(stripped)
        if cmd is None:
            cmd = parse_line(stripped)
            if len(stripped) <= MAX_CACHED_COMMAND_CHARS:
                if len(commands) >= MAX_CACHED_COMMANDS:
                    commands.clear()
                commands[stripped] = cmd
        if not cmd.name:
            if cmd.comment is not None:
                self._comment(";" + cmd.comment)
            return
        if self.first_command_line is None:
            self.first_command_line = self.lineno
        if cmd.name in OBJECT_COMMANDS:
            self.split.object_command(cmd, self.lineno)
        if cmd.name in self._kin_commands:
            self.warn(self._kin_commands[cmd.name], self.lineno, "kinematics:" + cmd.name)
        if cmd.name in self.stops.names:  # a paused print runs the look-ahead out (stop_log)
            self.toolhead.run_out()
            if self.stops.note(cmd.name, len(self.layers)):
                self._record(self.stops.times, self.lineno)
        self.interp.gcode_move.tag = self.lineno
        try:
            self.interp.execute(cmd)
        except (CommandError, MoveError) as exc:
            self._command_error(stripped, exc, "reject:" + cmd.name)
        if self.toolhead.print_time > MAX_PRINT_S:
            raise _too_long_wait(self.path, self.lineno, stripped, self.toolhead.print_time)

    def _reject(self, stripped: str, exc: Exception) -> None:
        """Klipper rejects this plain move line (as `execute` would report it)."""
        self._command_error(stripped, exc, "reject:" + stripped[:2])

    def _command_error(self, stripped: str, exc: Exception, key: str) -> None:
        """Klipper answers this line with an error: a warning, and the pre-flight's stop."""
        message = klipper_error_text(stripped, exc)
        if isinstance(exc, PrintEndsError):
            self.warn("'%s': %s" % (stripped, message), self.lineno, key)
        else:
            self.warn("Klipper rejects '%s': %s" % (stripped, message.split("\n")[0]),
                      self.lineno, key)
        stop = self.preflight.command_error(self.lineno, message.replace("\n", " "))
        if stop is not None:
            # A bound method, not a closure with `stop` as default: mypy for Python 3.9
            # (the mypyc build there) refuses that default's narrowed type.
            self.toolhead.register_lookahead_callback(stop.set_time)

    def _comment(self, text: str) -> None:
        if _is_layer_marker(text):
            self.split.layer_marker(len(self.layers), self.lineno)
            self._record(self.layers, self.lineno)
            return
        if self.mark_prefixes and text.startswith(self.mark_prefixes):
            self._record(self.marks, self.lineno)
            return
        for marker in FEATURE_MARKERS:
            if text.startswith(marker):
                self.split.set_feature(text[len(marker):].strip(), self.lineno)
                return
        if "printing object" in text and self.split.object_comment(text, self.lineno):
            return
        body = text.lstrip(";").strip()
        if body.startswith(ADD_TIME_MARKER):
            self._add_time(body[len(ADD_TIME_MARKER):].split())

    def _add_time(self, words: list[str]) -> None:
        parsed = parse_add_time(words)
        if isinstance(parsed, str):
            self.warn(parsed, self.lineno)
            return
        self.add_time(parsed[0], parsed[1], ADD_TIME_SOURCE)

    def finish(self) -> Estimate:
        """Flush the planner and return the estimate."""
        total = self.toolhead.finish()
        self.split.rest_until(total)
        self.split.flush_snapshots()
        last_line = self.toolhead.last_move_line
        self.samples.flush()
        if self.sample and last_line is not None:
            # The last move's end, sampled or not: where the file's moves end.
            self.samples.add_tail(last_line, self.toolhead.last_move_end_t)
        total = self._correct_motion(total)
        interp = self.interp
        for name in interp.extruders.extra_steppers:
            self.warn("[extruder_stepper %s]: its pressure advance is not known (its options "
                      "are not in the printer's settings), so not counted in the "
                      "step-generation flush delay (times after full stops may be short by "
                      "up to its pressure_advance_smooth_time)" % name)
        mesh_note = interp.unloaded_mesh_note()
        if mesh_note is not None:
            self.warn(mesh_note)
        if interp.gcode_move.moved_e_before_mode:
            self.warn("extrusion moves come before any M82/M83: Klipper starts in absolute "
                      "extrusion mode, which was assumed")
        # Unknown commands may be macros of the printer (the pre-flight says when the
        # config given lacks them); template macros of the config are macros (0 s unless
        # the profile times them).
        unknown = dict(interp.ignored)
        for name, count in interp.command_kinds.get(KIND_MACRO, {}).items():
            unknown[name] = unknown.get(name, 0) + count
        untimed = {name: count for name, count in sorted(unknown.items())
                   if self.macros.time_of(name) is None and not _looks_like_gcode(name)}
        config_macros = interp.command_kinds.get(KIND_MACRO, {})
        for name in untimed:
            if name not in self._warned_macros and name not in config_macros:
                self._warned_macros.add(name)
                self.warn("'%s' is not a Klipper command: if it is a macro on your printer, "
                          "its effect on time is unknown and counted as 0 s" % name)
        ran = [(name, count) for name, count in untimed.items() if name in config_macros]
        if ran:
            self.warn("macros of the printer config ran: %s; their time is not included "
                      "(counted as 0 s)" % ", ".join("%s x%d" % kv for kv in ran))
        if interp.ignored_unlisted:
            self.warn("%d more lines of unknown commands are not listed: the file uses more "
                      "than %d names of commands Klipper does not know"
                      % (interp.ignored_unlisted, MAX_COMMAND_NAMES))
        commands = {kind: dict(sorted(names.items()))
                    for kind, names in sorted(interp.command_kinds.items())}
        if interp.ignored:
            commands[KIND_UNKNOWN] = dict(sorted(interp.ignored.items()))
        features, objects = self.split.totals()
        object_remaining = self.split.remaining(list(self.layers))
        return Estimate(
            path=self.path, total_s=total, layers=self.layers, features=features,
            n_moves=self.n_moves, n_lines=self.lineno,
            ignored_commands=dict(sorted(interp.ignored.items())),
            ignored_unlisted=interp.ignored_unlisted,
            warnings=self.warnings.final(), warnings_dropped=self.warnings.dropped,
            sample_lines=self.samples.lines, sample_times=self.samples.times,
            marks=self.marks, noted_lines=self.noted_lines,
            first_command_line=self.first_command_line,
            last_move_line=self.toolhead.last_move_line, filament_mm=self.filament_mm,
            timed_parts=sorted(self.timed_parts.values(),
                               key=lambda p: (-p.seconds, p.name, p.source)),
            untimed_macros=untimed, first_extrusion_t=self.first_extrusion_t,
            untimed_waits=untimed_waits(interp, self.macros),
            objects=objects, commands=commands, preflight=self.preflight.findings(),
            object_remaining=object_remaining,
            stops=self.stops.listed(), stops_unlisted=self.stops.unlisted,
            tail_lines=array("q", self.samples.tail_lines),
            tail_times=array("d", self.samples.tail_times))


def stop_log(limits: Limits, interp: Interpreter) -> StopLog:
    """The stops of an estimate, with the stop commands this printer runs: a command
    Klipper does not know on a known config is skipped (the print goes on there). At each
    the print waits for a person and reads no further line, so Klipper runs its look-ahead
    out (toolhead.py `_handle_step_flush` -> `_flush_lookahead(is_runout=True)`): every
    earlier move ends at rest, and that moment is the stop's time (`Timeline._feed_other`)."""
    known = None if interp.modules is None else interp.registered | frozenset(interp.macros)
    return StopLog(known_stops(stop_commands(limits.stop_commands, limits.gcode_macros), known))


def first_extrusion(moves: list[Move], start_t: float, filament: float) -> float | None:
    """When the net filament (`filament` before `moves`) first exceeds print_stats'
    threshold during `moves`, if it does."""
    t = start_t
    for move in moves:
        filament += move.axes_d_e
        if filament >= FIRST_EXTRUSION_MM:
            return t
        t += move.accel_t + move.cruise_t + move.decel_t
    return None


def parse_add_time(words: list[str]) -> tuple[float, str] | str:
    """`; ESTIMATOR_ADD_TIME <seconds> [label]`'s words: (seconds, part name), or what is
    wrong with them."""
    try:
        seconds = float(words[0])
    except (IndexError, ValueError):
        return "ESTIMATOR_ADD_TIME needs a number of seconds"
    if not 0.0 <= seconds < float("inf"):
        return "ESTIMATOR_ADD_TIME needs a finite, non-negative time"
    label = " ".join(words[1:])[:MAX_LABEL_CHARS]
    return seconds, ADD_TIME_MARKER + (" " + label if label else "")


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class EventRunner:
    """Runs a Timeline's events (`Event`) right before their lines."""

    def __init__(self, timeline: Timeline, events: Sequence[Event]) -> None:
        self.timeline = timeline
        # Events not yet run, in line order (a stable sort keeps a line's list order).
        self.events = sorted(events, key=lambda event: event[0])
        self.next = 0

    def pending(self) -> bool:
        """Some events have not run yet."""
        return self.next < len(self.events)

    def feed_lines(self, lines: Iterable[bytes]) -> None:
        """The timeline's feed_lines, stopping before each event's line to run it. The
        lines between two events go through the per-line loop in one call: without events
        that loop is untouched."""
        timeline = self.timeline
        events = self.events
        rest = iter(lines)
        while self.next < len(events):
            line = events[self.next][0]
            if line - 1 > timeline.lineno:
                timeline._feed_lines(islice(rest, line - 1 - timeline.lineno))
                if timeline.lineno < line - 1:
                    return  # the lines ran out before the event's line
            while self.next < len(events) and events[self.next][0] <= line:
                self.run(line, events[self.next][1])
                self.next += 1
        timeline._feed_lines(rest)

    def run(self, line: int, command: str) -> None:
        """Run `command` right before line `line`, as typed at the console: Klipper answers
        an error (a warning here) but the print goes on."""
        timeline = self.timeline
        text = command.strip()
        cmd = parse_line(text)
        if not cmd.name:
            return
        before = timeline.lineno
        timeline.lineno = max(line, 1)
        try:
            if cmd.name in OBJECT_COMMANDS:
                timeline.split.object_command(cmd, timeline.lineno)
            timeline.interp.gcode_move.tag = timeline.lineno
            try:
                timeline.interp.execute(cmd)
            except (CommandError, MoveError) as exc:
                timeline.warn("Klipper answers '%s' (run before this line) with an error: %s"
                              % (text, klipper_error_text(text, exc).split("\n")[0]),
                              timeline.lineno, "event:" + text)
        finally:
            timeline.lineno = before


# A print whose time passes MAX_PRINT_S (a year) is refused where it passed it: as moves
# are timed, where a line waits, where time is added, and (a learned correction) at the end.
OVER_A_YEAR: Final = "the print would last over a year by this line: "


def _too_long_move(path: str, moves: list[Move], start_t: float) -> KestimatorError:
    """The error naming the move of `moves` during which time passes MAX_PRINT_S."""
    t = start_t
    for move in moves:
        dt = move.accel_t + move.cruise_t + move.decel_t
        t += dt
        if t > MAX_PRINT_S:
            break
    return KestimatorError(
        OVER_A_YEAR + "its move takes %.3g s (%.6g mm at up to %.3g mm/s, acceleration %.3g "
        "mm/s^2): its length, or a speed or acceleration in force, is absurd "
        "(SET_VELOCITY_LIMIT or M204 in the file, or a limit of the printer's config)"
        % (dt, move.move_d, move.cruise_v, move.accel), path, move.tag)


def _too_long_added(path: str, line: int, name: str, seconds: float,
                    source: str) -> KestimatorError:
    return KestimatorError(OVER_A_YEAR + "%s adds %.3g s here (%s)" % (name, seconds, source),
                           path, line or None)


def _too_long_wait(path: str, line: int, text: str, until: float) -> KestimatorError:
    return KestimatorError(OVER_A_YEAR + "'%s' waits until %.3g s" % (text[:80], until),
                           path, line)


def untimed_waits(interp: Interpreter, macros: MacroTimes) -> dict[str, int]:
    """The heater waits and homings that counted as 0 s (none when a learned start time
    holds the start, where they are)."""
    if macros.before_first_extrusion is not None:
        return {}
    counts = {"heater_waits": interp.heaters.untimed_waits,
              "homings": interp.untimed_homings}
    return {kind: count for kind, count in counts.items() if count}


def klipper_error_text(command_line: str, exc: Exception) -> str:
    """The error as Klipper words it (a parameter error names the command line)."""
    if isinstance(exc, ParamError):
        return "Error on '%s': %s" % (command_line, exc)
    return str(exc)


def _looks_like_gcode(name: str) -> bool:
    return len(name) >= 2 and name[0] in "GMTD" and name[1].isdigit()


def estimate_lines(lines: Iterable[bytes], limits: Limits, path: str = "<input>",
                   homing_time: float = 0.0, heat_time: float = 0.0, sample: bool = False,
                   mark_prefixes: tuple[str, ...] = (),
                   observer: MoveObserver | None = None,
                   macros: MacroTimes | None = None,
                   note: Callable[[bytes], object] | None = None,
                   events: Sequence[Event] = ()) -> Estimate:
    """Estimate from an iterable of byte lines (split at LF).

    With `sample`, progress samples for M73 placement are kept; comment lines starting
    with one of `mark_prefixes` get their exact time in `Estimate.marks`; `observer` sees
    every planned move (with its start time) as the planner releases them; `macros` times the
    macros the file runs (and may hold a learned time before the first extrusion); the
    numbers of the lines other than plain G0/G1 moves for which `note(line)` is not None
    are in `Estimate.noted_lines`; each event's command (`Event`) runs right before its line.
    """
    timeline = Timeline(limits, path, homing_time=homing_time, heat_time=heat_time,
                        sample=sample, mark_prefixes=mark_prefixes, observer=observer,
                        macros=macros, note=note, events=events)
    return run_timeline(timeline, partial(_fed, timeline, lines))


def _fed(timeline: Timeline, lines: Iterable[bytes]) -> Timeline:
    timeline.feed_lines(lines)
    return timeline


def run_timeline(timeline: Timeline, feed: Callable[[], Timeline],
                 live: Callable[[], Timeline] | None = None) -> Estimate:
    """`feed()`, which feeds `timeline` its lines and returns the timeline it ended with,
    then that one's estimate, checked, with the errors of estimate_lines. kestimator.resume
    feeds a timeline restored mid-file so, and goes on with copies of it: `live()` is the
    one running (an error names its line)."""
    path = timeline.path
    try:
        timeline = feed()
        est = timeline.finish()
    except (ArithmeticError, ValueError) as exc:
        # Values Klipper accepts one by one can still break its arithmetic together (a
        # velocity so small its square is 0); Klipper would shut down, we name the line.
        if live is not None:
            timeline = live()
        raise KestimatorError("the planner cannot compute a time at or before this line "
                              "(%s: %s)" % (type(exc).__name__, exc), path,
                              timeline.lineno or None) from None
    if not math.isfinite(est.total_s):
        # A move longer than a float can square (X with 155 digits) takes forever.
        raise KestimatorError("a move at or before this line is too long to time (%s s)"
                              % est.total_s, path, est.last_move_line or est.n_lines or None)
    if est.total_s > MAX_PRINT_S:
        raise KestimatorError("the print would last over a year (%.3g s)" % est.total_s, path,
                              est.last_move_line or est.n_lines or None)
    return est


def estimate_file(path: str | os.PathLike[str], limits: Limits, homing_time: float = 0.0,
                  heat_time: float = 0.0, sample: bool = False,
                  mark_prefixes: tuple[str, ...] = (),
                  observer: MoveObserver | None = None,
                  progress: ProgressCallback | None = None,
                  macros: MacroTimes | None = None,
                  events: Sequence[Event] = ()) -> Estimate:
    """Estimate a G-code file in one streaming pass (`progress` hears the bytes read);
    each event's command runs right before its line (see `Event`)."""
    path_s = os.fspath(path)
    if os.path.isdir(path_s):
        raise KestimatorError("is a directory, not a G-code file", path_s)
    return estimate_lines(iter_lines(path_s, progress), limits, path_s, homing_time=homing_time,
                          heat_time=heat_time, sample=sample, mark_prefixes=mark_prefixes,
                          observer=observer, macros=macros, events=events)


def estimate_text(text: str, limits: Limits, homing_time: float = 0.0,
                  heat_time: float = 0.0, macros: MacroTimes | None = None,
                  events: Sequence[Event] = ()) -> Estimate:
    """Estimate G-code given as a string (for tests and embedding)."""
    return estimate_lines(io.BytesIO(text.encode("utf-8")), limits, "<text>",
                          homing_time=homing_time, heat_time=heat_time, macros=macros,
                          events=events)
