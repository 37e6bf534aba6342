"""`inject`: write Klipper's times back into a G-code file without losing a byte.

Owns the second streaming pass (the G-code rewriting); the file it writes is replaced by
`kestimator.files` (`write_atomically`), as every file kestimator writes is. Pass 1
(`kestimator.estimate`) gives the total, progress samples and exact times at the lines that
need them; pass 2 copies every line byte for byte except the ones kestimator owns:

- every `M73` line is dropped and Klipper-true `M73 P<percent> R<minutes>` lines are
  written instead: `M73 P0 R<total>` right before the first command, one after every layer
  marker, one before any command at which the whole percent or the remaining minute
  changes, and `M73 P100 R0` right after the last move. Klipper has one mode and its M73
  reads only P, so the silent-mode (`Q`/`S`) and time-to-change (`C`/`D`) forms the slicer
  wrote are not kept;
- the slicer's own time comments, which the slicer adapter rewrites in place;
- one marker line, `; kestimator <version> ...`, right before the first M73, and after it,
  when the estimate counts time before the first extrusion (start macro, homing, heating),
  one line saying how long: `; time before first extrusion (kestimator) = ...`. The time
  comments hold what Klipper's print_duration measures, which starts at the first
  extrusion, so that line is the only place that time is written.

- last, after every other line, the progress table (`kestimator.progress_table`): its
  points' offsets are those of this output, noted as pass 2 writes it (the table's lines
  are stops of the block copy, like the noted lines), and its content checksum that of
  the output before it. Where it goes is `table_place`'s rule: before a slicer's settings
  block that the slicer reads back from the file's end (PrusaSlicer before 2.4, Slic3r,
  Slic3r PE, SuperSlicer), else in an old table's place when what follows that one may
  follow a table (what a post-processor appended after it stays after it), else at the
  end; an old table is dropped wherever it is. A file without a final line ending gets one
  before a table at its end, and
  its last line is processed as the line it becomes (a move gets its M73 P100 R0 after it,
  a layer marker its lines after it, a lone CR is a CRLF), as a second run reads it. The
  table records the printer settings the estimate ran with (`table_settings`), so that it
  is not followed on another printer.

Inserted lines take the line ending of the line they stand next to. A second run drops
its own lines and writes them again, so it is byte-identical. The output goes to a
temporary file in the destination's directory, is fsynced, and replaces the destination
atomically; on any error the destination is untouched and the temporary file is removed
(`kestimator.files.write_atomically`). Two in-place runs on one file take turns under an
exclusive flock on it (`kestimator.files.exclusive`), and a file that changed under us
(size, mtime or inode) is never replaced (`_write_output`).

Also owns the marker's exact format and its parsing (`marker_line`, `parse_marker`): only a
line in that format is ours. Where the output goes (a symlink written through, a device or
FIFO written straight through, anything else not a regular file refused) and which
attributes the replaced file keeps are `kestimator.files`' rules (`output_target`,
`keep_attributes`). A hard link's other names keep the old content (docs/CLI.md).
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import math
import os
import re
import stat
import zlib
from array import array
from bisect import bisect_left, bisect_right
from collections.abc import Callable, Iterable
from typing import BinaryIO

from kestimator import __version__
from kestimator.durations import format_duration
from kestimator.errors import KestimatorError
from kestimator.estimate import (
    MAX_LINE_BYTES,
    Estimate,
    ProgressCallback,
    estimate_lines,
    iter_lines,
)
from kestimator.filekind import SNIFF_BYTES, what_is_not_gcode
from kestimator.files import (
    OutputTarget,
    Write,
    exclusive,
    open_regular,
    output_target,
    same_file,
    write_atomically,
)
from kestimator.interpreter import printer_commands
from kestimator.limits import Limits, json_value
from kestimator.macros import MacroTimes
from kestimator.progress_table import (
    CHUNK_PREFIX,
    HEADER_PREFIX,
    ProgressTable,
    Selection,
    Settings,
    is_chunk_line,
    is_header_line,
    replaceable_table_at,
    select,
    setting_text,
    settings_block_start,
)
from kestimator.slicers import SlicerAdapter, SlicerInfo, adapter_for, detect, read_file_ends
from kestimator.slicers.base import HEAD, TAIL, FileEnds, KlipperTimes
from kestimator.stops import Stop
from kestimator.timedlines import TimedLines

MARKER_PREFIX = "; kestimator "
_MARKER_PREFIX_B = MARKER_PREFIX.encode()
# A SET_PRINT_STATS_INFO line the file's slicer (or start G-code) wrote, not ours.
_FOREIGN_LAYER_INFO_RE = re.compile(
    rb"^[ \t]*SET_PRINT_STATS_INFO\b(?![^\n]*; kestimator\r?$)", re.MULTILINE | re.IGNORECASE)
PREP_PREFIX = "; time before first extrusion (kestimator) = "
_PREP_PREFIX_B = PREP_PREFIX.encode()
# The comment written before each stop (kestimator.stops): Klipper's time from the start
# to when the printer stands there.
STOP_PREFIX = "; stop (kestimator) "
_STOP_PREFIX_B = STOP_PREFIX.encode()
# An M73's time-to-change parameter (Prusa firmware: minutes to the next colour change or
# pause), as a parameter word of the line.
_M73_C_RE = re.compile(rb"[ \t]C[ \t]*[-+0-9.]")
# The marker's exact format (`marker_line`): only a line matching it, after leading blanks and
# before its line ending, is ours. `limits=` runs to the end of the line and may hold any
# text (what it records is issue 17's), so it is matched loosely.
_MARKER_BODY = (rb"; kestimator (?P<version>\d+(?:\.\d+)+[0-9A-Za-z.+-]*)"
                rb" klipper_s=(?P<klipper_s>\d+\.\d{3})"
                rb" slicer_s=(?P<slicer_s>none|-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?|-?nan|-?inf)"
                rb" limits=(?P<limits>[^\r\n]*)")
_MARKER_RE = re.compile(_MARKER_BODY + rb"\r?\n?\Z")
_MARKER_IN_TEXT = re.compile(rb"^[ \t\x0b\x0c\r]*" + _MARKER_BODY + rb"\r?$", re.MULTILINE)
# A slicer estimate read back from a marker is believed only in [0, this] seconds (a year).
MAX_SLICER_ESTIMATE_S = 366 * 24 * 3600.0
BGCODE_MAGIC = b"GCDE"
SECONDS_PER_MINUTE = 60.0
PERCENT = 100.0
_NO_LINE_LIMIT = 1 << 62
# Pass 2 reads the file in blocks of this size. 64 KiB: the same CPU as 1 MiB blocks under
# CPython and PyPy; under PyPy, whose GC frees large objects late, peak RSS of pass 2 on
# the 40 MB file 150 MB instead of 201 MB.
COPY_BLOCK_BYTES = 1 << 16
# An M73 command (already left-stripped): M73 alone or followed by a space, tab, ';' or EOL.
_M73 = rb"[Mm]73(?:[ \t;\r\n]|\Z)"
_m73_at = re.compile(_M73).match
LAYER_INFO_COMMAND = b"SET_PRINT_STATS_INFO"
LAYER_INFO_SUFFIX = b" ; kestimator"


def attention_matcher(time_comment_prefixes: tuple[str, ...]) -> Callable[[bytes], object]:
    """`match(line)`: not None for a line `attention_pattern` describes (pass 1 notes them)."""
    return re.compile(attention_pattern(tuple(prefix.encode("utf-8")
                                              for prefix in time_comment_prefixes))).match


def attention_pattern(time_comment_prefixes: tuple[bytes, ...]) -> bytes:
    """What starts a line pass 2 must look at even in a quiet stretch (after the blanks
    `process` strips): an M73 (dropped), a SET_PRINT_STATS_INFO (ours are dropped and
    written again), our marker or time-before-first-extrusion line (dropped), or one of the
    slicer's time comments (rewritten). Every other comment is copied as it is, except a
    layer marker, which a quiet stretch ends before by its line number."""
    starts = [_M73, LAYER_INFO_COMMAND + b" ", re.escape(_MARKER_PREFIX_B),
              re.escape(_PREP_PREFIX_B), re.escape(_STOP_PREFIX_B), re.escape(HEADER_PREFIX),
              re.escape(CHUNK_PREFIX)]
    starts += [re.escape(prefix) for prefix in time_comment_prefixes]
    return rb"[ \t\r\x0b\x0c]*(?:%s)" % b"|".join(starts)


# Skip 2**k whole lines (k = 0..20: what pass 2 holds at once, a block and a carried line start
# of at most MAX_LINE_BYTES, is under 2**21 bytes).
_SKIP_LINES = tuple(re.compile(rb"(?:[^\n]*\n){%d}" % (1 << k)).match for k in range(21))


def _after_lines(data: bytes, pos: int, count: int) -> int:
    """Where the line `count` lines after the one at `pos` starts (they all end in LF)."""
    k = 0
    while count:
        if count & 1:
            match = _SKIP_LINES[k](data, pos)
            if match is None:
                raise ValueError("fewer than %d lines after position %d" % (count, pos))
            pos = match.end()
        count >>= 1
        k += 1
    return pos


def _lines_upto(data: bytes, pos: int, stop: int, most: int) -> tuple[int, int]:
    """(n, after): the first n <= `most` whole lines from `pos` (a line start) before
    `stop` (a line start), and where they end. Lines are counted in growing windows, so a
    far `stop` costs no more than the lines taken."""
    taken = 0
    window = 1 << 12
    while pos < stop:
        upto = min(pos + window, stop)
        found = data.count(b"\n", pos, upto)
        if taken + found >= most:
            return most, _after_lines(data, pos, most - taken)
        taken += found
        pos = upto
        window <<= 1
    return taken, stop


def _line_ending(raw: bytes, pending: bytes | None, eol: bytes) -> bytes:
    """The line ending of the line `raw`: its own or, without one, that of the last line
    copied (`pending`, not yet looked at) or `eol`, the one before."""
    last = raw if raw.endswith(b"\n") else pending if pending is not None else eol
    return b"\r\n" if last.endswith(b"\r\n") else b"\n"


def _is_m73(code: bytes) -> bool:
    """True for an M73 command line (already left-stripped)."""
    return _m73_at(code) is not None


def is_layer_info_line(code: bytes) -> bool:
    """True for a SET_PRINT_STATS_INFO line inject wrote (`code` left-stripped)."""
    return code.startswith(LAYER_INFO_COMMAND) and code.rstrip(b"\r\n").endswith(
        LAYER_INFO_SUFFIX)


def progress_pr(t: float, total_s: float) -> tuple[int, int]:
    """Whole percent done and whole minutes left at t seconds, each rounded to nearest."""
    if total_s <= 0.0:
        return 100, 0
    done = min(max(t / total_s, 0.0), 1.0)
    percent = int(done * PERCENT + 0.5)
    minutes = int(max(total_s - t, 0.0) / SECONDS_PER_MINUTE + 0.5)
    return percent, minutes


def stop_line(command: str, t: float) -> str:
    """The comment before a stop: its command and Klipper's time from the start."""
    return "%s%s = %s (%.3f s) from the start" % (STOP_PREFIX, command, format_duration(t), t)


def minutes_to_stop(t: float, stop_t: float) -> int:
    """Whole minutes from `t` to a stop at `stop_t`, rounded to nearest (as M73 R)."""
    return int(max(stop_t - t, 0.0) / SECONDS_PER_MINUTE + 0.5)


def marker_line(total_s: float, slicer_s: float | None, limits_source: str) -> str:
    """The one line that says a file was processed, by which version, with what result."""
    return "%s%s klipper_s=%.3f slicer_s=%s limits=%s" % (
        MARKER_PREFIX, __version__, total_s,
        "none" if slicer_s is None else "%.3f" % slicer_s,
        limits_source.replace("\n", " ") or "unknown")


def prep_line(prep_s: float) -> str:
    """The line that says how long the print takes before its first extrusion."""
    return "%s%s (%.3f s), not in the estimated printing time" % (
        PREP_PREFIX, format_duration(prep_s), prep_s)


@dataclasses.dataclass(frozen=True)
class Marker:
    """Our marker line, read back: `slicer_s` is None when absent or not believable."""

    version: str
    klipper_s: float
    slicer_s: float | None
    limits: str


def _plausible_seconds(value: float) -> float | None:
    return value if math.isfinite(value) and 0.0 <= value <= MAX_SLICER_ESTIMATE_S else None


def _marker_from_match(match: re.Match[bytes]) -> Marker:
    slicer = match.group("slicer_s")
    return Marker(version=match.group("version").decode("ascii"),
                  klipper_s=float(match.group("klipper_s")),
                  slicer_s=None if slicer == b"none" else _plausible_seconds(float(slicer)),
                  limits=match.group("limits").decode("utf-8", "replace"))


def parse_marker(line: str | bytes) -> Marker | None:
    """The marker on `line` (leading blanks and its line ending allowed), or None if the
    line is not exactly in our format: a user's `; kestimator ...` comment is not ours."""
    raw = line.encode("utf-8", "surrogateescape") if isinstance(line, str) else line
    match = _MARKER_RE.match(raw.lstrip())
    return None if match is None else _marker_from_match(match)


def find_marker(text: bytes) -> Marker | None:
    """The first marker line in `text` (a file's head), or None."""
    if _MARKER_PREFIX_B not in text:  # every marker holds it: skip the regex's slow scan
        return None
    match = _MARKER_IN_TEXT.search(text)
    return None if match is None else _marker_from_match(match)


def slicer_estimate_from_head(head: bytes, detected: SlicerInfo) -> float | None:
    """The slicer's own estimate: from our marker in `head` if a previous run rewrote it.

    A marker is believed only in its exact format, and its `slicer_s` only when it is a
    plausible time (finite, 0 to a year); a forged one counts as no estimate.
    """
    marker = find_marker(head)
    if marker is None:
        return detected.estimate_s
    return marker.slicer_s


def slicer_of_file(path: str | os.PathLike[str]) -> SlicerInfo:
    """Which slicer wrote the file and what it estimated, looking through our own marker.

    In a file `inject` (or Moonraker through kestimator-compat) already rewrote, the time
    comments hold Klipper's time; the slicer's own estimate is the one the marker recorded,
    and its first-layer estimate is no longer known.
    """
    head, tail = read_file_ends(path)
    detected = detect(head, tail)
    if find_marker(head) is None:
        return detected
    return dataclasses.replace(detected, estimate_s=slicer_estimate_from_head(head, detected),
                               first_layer_estimate_s=None)


def table_settings(limits: Limits, homing_time: float = 0.0, heat_time: float = 0.0,
                   macros: MacroTimes | None = None) -> Settings:
    """Every setting an estimate's times depend on besides the file, as a progress table
    records them (kestimator.progress_table, "The printer it was made for"): each `Limits`
    field (the machine limits, kinematics, extruders, shaper, arcs, retraction, the Klipper
    generation, the config's sections and macros), the kinematics' own sections of the
    printer's config (steppers, probe, homing, bed mesh; values only, not where they were
    read; [printer]'s options that are `Limits` fields only once, resolved, above), the
    seconds per G28 and per heater wait, the stop commands the slicer's settings and the
    profile name (kestimator.stops), and the macro times (the profile's and the learned
    ones). `inject` writes them into the table and the worker compares them with
    the printer's: both call this with what they give the estimate."""
    pairs: list[tuple[str, object]] = []
    for name in Limits.field_names():
        value = getattr(limits, name)
        if name == "configured_sections":
            value = sorted(value)  # the printer's set of sections, in any order
        elif isinstance(value, tuple):
            value = json_value(value)
        pairs.append((name, value))
    machine = limits.machine
    # [printer]'s options that are Limits fields are recorded above, as resolved.
    fields = frozenset(Limits.field_names())
    pairs.append(("kinematics_sections", None if machine is None else [
        [section, [[option, text] for option, text, _source in options
                   if section != "printer" or option not in fields]]
        for section, options in machine.sections]))
    pairs += [("homing_time_s", homing_time), ("heat_time_s", heat_time)]
    if limits.stop_commands:
        # The slicer's and the profile's stop commands (the defaults and the printer's
        # macros calling one are known from the above): each runs the look-ahead out.
        pairs.append(("stop_commands", list(limits.stop_commands)))
    macros = macros if macros is not None else MacroTimes()
    prep, ratio = macros.before_first_extrusion, macros.motion_ratio
    pairs += [("macro_times", sorted([name, t.seconds] for name, t in macros.macros.items())
               if macros.macros else None),
              ("learned_prep_s", None if prep is None else prep.seconds),
              ("learned_motion_ratio", None if ratio is None else ratio.seconds)]
    return tuple((name, setting_text(value)) for name, value in pairs)


@dataclasses.dataclass(frozen=True)
class InjectPlan:
    """Everything pass 2 needs from pass 1."""

    total_s: float
    sample_lines: array
    sample_times: array
    layer_lines: TimedLines
    """The layer markers (membership by bisection: `index_of`)."""
    attention_lines: array
    """The lines `attention_pattern` matches (pass 1 notes them), in file order."""
    last_move_line: int | None
    times: KlipperTimes
    adapter: SlicerAdapter
    marker: str
    prep_line: str | None = None
    """Written after the marker when time is counted before the first extrusion."""
    # A time comment Moonraker reads, added where the file has none (SlicerAdapter.
    # moonraker_time_comment): before the marker (head) or at the end of the file (tail).
    head_comment: str | None = None
    tail_comment: str | None = None
    # Layers for SET_PRINT_STATS_INFO TOTAL_LAYER / CURRENT_LAYER lines; 0 writes none.
    layer_info_total: int = 0
    table: Selection | None = None
    """The progress table's points (kestimator.progress_table), by line: `copy_stream`
    writes the table with their offsets in the output; None writes none."""
    table_settings: Settings | None = None
    """The printer settings the table records (`table_settings`)."""
    table_line: int | None = None
    """The line the table is written before (`table_place`); None: at the file's end."""
    stops: tuple[Stop, ...] = ()
    """The stops (kestimator.stops): a comment with the time goes before each, and an M73
    with a time-to-change (C) parameter gets the minutes to the next one."""
    stop_lines: array = dataclasses.field(default_factory=lambda: array("q"))
    """The stops' lines, in file order."""

    @classmethod
    def from_estimate(cls, est: Estimate, adapter: SlicerAdapter, slicer_s: float | None,
                      limits_source: str,
                      moonraker_comment: tuple[str, str] | None = None,
                      layer_info: bool = False, table: bool = False) -> InjectPlan:
        """Build the plan from a sampled estimate (estimate_file(..., sample=True)).

        The time comments get what print_duration will measure: the total less the time
        counted before the first extrusion (M73 lines count down the whole total).
        """
        prep_s = est.parts.before_first_extrusion_s
        model_s = est.total_s - est.layers[0][1] if est.layers else None
        marks = est.marks.by_line(-prep_s)
        times = KlipperTimes(total_s=est.total_s - prep_s, first_layer_s=est.first_layer_s,
                             model_s=model_s, marks=marks)
        return cls(total_s=est.total_s, sample_lines=est.sample_lines,
                   sample_times=est.sample_times,
                   layer_lines=est.layers, attention_lines=est.noted_lines,
                   last_move_line=est.last_move_line, times=times, adapter=adapter,
                   marker=marker_line(est.total_s, slicer_s, limits_source),
                   prep_line=prep_line(prep_s) if prep_s > 0.0 else None,
                   head_comment=moonraker_comment[1] if moonraker_comment is not None
                   and moonraker_comment[0] == HEAD else None,
                   tail_comment=moonraker_comment[1] if moonraker_comment is not None
                   and moonraker_comment[0] == TAIL else None,
                   layer_info_total=len(est.layers) if layer_info else 0,
                   table=select(est) if table else None, stops=tuple(est.stops),
                   stop_lines=array("q", (stop.line for stop in est.stops)))


class Rewriter:
    """Pass 2, one line at a time: `process(raw)` returns the bytes to write for it."""

    def __init__(self, plan: InjectPlan) -> None:
        self.plan = plan
        self.lineno = 0
        self.eol = b"\n"
        self._sample = 0
        self._t = 0.0
        self._last_pr: tuple[int, int] | None = None
        self._started = False
        # After the last move's M73 P100 R0 no other M73 follows (the dwells and waits after
        # it would otherwise read as progress going back, e.g. P97 after P100).
        self._finished = False
        self._prefixes = plan.adapter.time_comment_prefixes
        # The same prefixes as UTF-8: a line is decoded only if its bytes start with one.
        self._prefixes_b = tuple(prefix.encode("utf-8") for prefix in self._prefixes)
        self.m73_written = 0
        self._layer = 0
        # Fast path: up to this line, a line starting with "G" is copied as it is (no
        # progress sample is crossed and the last move is not reached before it).
        self._quiet_until = 0
        # The last line copied by the fast path: its line ending becomes `eol` lazily.
        self._eol_line: bytes | None = None
        # (last progress written, index of the first sample showing other progress).
        self._quiet_scan: tuple[tuple[int, int] | None, int] = (None, 0)
        # The lines `_copy_quiet` stops before, in order: the layer markers and the lines
        # needing attention; and the index of the first one not yet passed.
        # The progress table (plan.table): the lines whose output offsets it needs (they
        # are stops too), the offsets found so far, the output's length so far (counted by
        # `copy_stream`), and the table once written.
        self._table_lines = array("q", plan.table.wanted_lines() if plan.table else ())
        self._table_next = 0
        self._table_offsets: dict[int, int] = {}
        self._out_pos = self._crc = 0  # the output's length and CRC-32 so far
        self._ends_in_lf = False
        self._old_table = False  # an old table's header was met: its base64 lines go
        self.table: ProgressTable | None = None
        table_line = () if plan.table is None or plan.table_line is None else (plan.table_line,)
        self._stops = array("q", heapq.merge(plan.layer_lines.lines, plan.attention_lines,
                                             self._table_lines, table_line, plan.stop_lines))
        self._next_stop = 0

    def _m73(self, percent: int, minutes: int, eol: bytes) -> bytes:
        self._last_pr = (percent, minutes)
        self.m73_written += 1
        return b"M73 P%d R%d" % (percent, minutes) + eol

    def _advance(self, line: int) -> bool:
        """Move the progress pointer to `line`; True if the time changed."""
        lines = self.plan.sample_lines
        i = self._sample
        n = len(lines)
        if i >= n or lines[i] >= line:
            return False
        while i < n and lines[i] < line:
            i += 1
        self._sample = i
        self._t = self.plan.sample_times[i - 1]
        return True

    def _set_quiet_until(self) -> None:
        """Up to which line no M73 is due: until the progress shown would change.

        Progress only grows, so the first sample at or after the pointer whose whole
        percent or minute differs from the last M73 written is the first one that can
        put an M73 before a command; lines up to its line are quiet. (A layer-marker M73
        in between only makes the quiet stretch end early, never late: the line that
        ends it is then processed in full and writes no M73 if none is due.)
        """
        plan = self.plan
        lines = plan.sample_lines
        i = self._sample
        n = len(lines)
        last_pr = self._last_pr
        scan_pr, j = self._quiet_scan
        if scan_pr != last_pr or j < i:
            j = i
        times = plan.sample_times
        total_s = plan.total_s
        if j < n and progress_pr(times[j], total_s) == last_pr:
            # The samples showing last_pr from j on are a run: the times grow, and whole
            # percent done and whole minutes left each change one way only as time grows.
            # So the run's end is found by bisection.
            lo, hi = j + 1, n
            while lo < hi:
                mid = (lo + hi) // 2
                if progress_pr(times[mid], total_s) == last_pr:
                    lo = mid + 1
                else:
                    hi = mid
            j = lo
        self._quiet_scan = (last_pr, j)
        quiet = lines[j] if j < n else _NO_LINE_LIMIT
        last = plan.last_move_line
        if last is not None and last > self.lineno and last - 1 < quiet:
            quiet = last - 1
        self._quiet_until = quiet

    def process(self, raw: bytes) -> list[bytes]:
        """The output for one input line (with its line ending, if it has one)."""
        lineno = self.lineno = self.lineno + 1
        if lineno <= self._quiet_until and raw[:1] == b"G":
            self._eol_line = raw
            return [raw]
        pending = self._eol_line
        if pending is not None:
            # Not the last line of the file, so it ends in LF.
            self._eol_line = None
            self.eol = b"\r\n" if pending.endswith(b"\r\n") else b"\n"
        if raw.endswith(b"\n"):
            eol = b"\r\n" if raw.endswith(b"\r\n") else b"\n"
            self.eol = eol
        else:
            eol = b""
        code = raw.lstrip()
        if not code:
            return [raw]
        if code[:1] == b";":
            return self._comment(raw, code, eol)
        if _is_m73(code):
            return time_to_stop(self.plan, lineno, code, eol or self.eol)
        if is_layer_info_line(code):
            return []  # ours: written again at the layer markers
        plan = self.plan
        line_eol = eol or self.eol
        out = stop_comment(plan, lineno, line_eol)
        if not self._started:
            self._started = True
            self._advance(self.lineno)
            if plan.head_comment is not None:
                out.append(plan.head_comment.encode("utf-8") + line_eol)
            out.append(plan.marker.encode() + line_eol)
            if plan.prep_line is not None:
                out.append(plan.prep_line.encode() + line_eol)
            out.append(self._m73(*progress_pr(self._t, plan.total_s), line_eol))
        elif not self._finished and self._advance(self.lineno):
            pr = progress_pr(self._t, plan.total_s)
            if pr != self._last_pr:
                out.append(self._m73(pr[0], pr[1], line_eol))
        self._set_quiet_until()
        if self.lineno == plan.last_move_line:
            self._finished = True
            if eol:
                out.append(raw)
                out.append(self._m73(100, 0, eol))
            else:
                # The file ends in this move without a line ending: never add one to it.
                out.append(self._m73(100, 0, self.eol))
                out.append(raw)
            return out
        out.append(raw)
        return out

    def copy_stream(self, inp: BinaryIO, write: Callable[[bytes], object],
                    progress: Callable[[int], None] | None = None) -> None:
        """Pass 2 over a whole file: the same bytes as `process` line by line, faster.

        Reads blocks; a run of quiet lines (see `_copy_quiet`) is measured with C-level
        line counts and written as one slice, so Python code runs only for the lines where
        an M73 is due, layer markers and the lines `attention_pattern` matches.
        `progress` hears the bytes read so far.
        """
        if self.plan.table is not None:
            write, process = self._table_tracking(write)
        else:
            process = self.process
        # The start of a line that continues in the next block (a list, so a line over
        # many blocks is joined once, not copied again at every block).
        carry: list[bytes] = []
        carry_bytes = 0
        # Inside a line over MAX_LINE_BYTES: True while its bytes are copied through, False
        # while they are dropped (the line was replaced), None outside such a line.
        long_copy: bool | None = None
        long_after: list[bytes] = []  # what `process` put after that line
        long_replaced = False  # `process` put something else in that line's place
        done = 0
        while True:
            block = inp.read(COPY_BLOCK_BYTES)
            if not block:
                break
            done += len(block)
            if long_copy is not None:
                nl = block.find(b"\n") + 1
                if long_copy:
                    write(block[:nl] if nl else block)
                if not nl:
                    if progress is not None:
                        progress(done)
                    continue
                if long_replaced:
                    # `process` replaced the line from its start, which has no line ending:
                    # the one the line ends with follows the replacement.
                    write(b"\r\n" if block[nl - 2:nl] == b"\r\n" else b"\n")
                for piece in long_after:
                    write(piece)
                long_copy = None
                long_after = []
                block = block[nl:]
            end = block.rfind(b"\n") + 1
            if not end:
                carry.append(block)
                carry_bytes += len(block)
                if carry_bytes > MAX_LINE_BYTES:
                    # A line too long to hold (pass 1 took its start for it, see
                    # estimate.over_long_line): its start goes through `process`, the rest
                    # is copied through (or dropped with it) as it is read.
                    data = b"".join(carry)
                    head = data[:MAX_LINE_BYTES]
                    carry = []
                    carry_bytes = 0
                    long_copy = False
                    pieces = process(head)
                    long_replaced = bool(pieces) and not any(p is head for p in pieces)
                    for index, piece in enumerate(pieces):
                        if piece is head:
                            write(data)
                            long_copy = True
                            long_after = pieces[index + 1:]
                            break
                        write(piece)
                if progress is not None:
                    progress(done)
                continue
            if carry:
                carry.append(block)
                data = b"".join(carry)
                end += len(data) - len(block)
            else:
                data = block
            carry = [data[end:]] if end < len(data) else []
            carry_bytes = len(data) - end
            pos = 0
            while pos < end:
                pos = self._copy_quiet(data, pos, end, write)
                if pos >= end:
                    break
                nl = data.index(b"\n", pos) + 1
                for piece in process(data[pos:nl]):
                    write(piece)
                pos = nl
            if progress is not None:
                progress(done)
        tail = self.finish()
        if long_copy is not None:
            # The file ended inside the long line, already written: the tail time comment
            # can only follow it, on a line of its own.
            for piece in long_after:
                write(piece)
            if tail:
                write(self.eol)
        # The table, not yet written in an old one's place, goes at the end.
        table = self.plan.table is not None and self.table is None
        if table and carry:
            # The table's line ending ends the last line too: it is processed as the line it
            # becomes, and the tail comment follows it, as in a second run's input.
            last = b"".join(carry)
            carry = []
            for piece in process(last + (b"\n" if last.endswith(b"\r") else self.eol)):
                write(piece)
        if table:
            # The file's end, line n + 1 (a second run finds the line after a last move
            # there: the M73 P100 R0 it drops), before the tail comment.
            self._note_table_line()
        # The tail time comment ends the file; before a last line without a line ending, so
        # that none is ever added to the file (but for the table's, above).
        for piece in tail:
            write(piece)
        if carry:
            for piece in process(b"".join(carry)):
                write(piece)
        if table:
            if self._out_pos and not self._ends_in_lf:
                write(self.eol)  # the table's lines stand on their own
            write(self._table_block(self.eol))

    def _table_tracking(self, write: Callable[[bytes], object]
                        ) -> tuple[Callable[[bytes], object], Callable[[bytes], list[bytes]]]:
        """`write` counting the output's bytes and their CRC-32, and `process` writing the
        table before `plan.table_line` and noting where the output of each line the table
        needs starts: after every line before it, so at the time that line is reached (an
        M73 put before it takes no time). A line kestimator drops (an old M73) starts where
        the next line's output starts, so a second run finds the same offsets."""
        self._ends_in_lf = False

        def counted(data: bytes) -> object:
            if data:
                self._out_pos += len(data)
                self._crc = zlib.crc32(data, self._crc)
                self._ends_in_lf = data[-1:] == b"\n"
            return write(data)

        process_line = noting_stop_lines(self)
        table_line = self.plan.table_line

        def process(raw: bytes) -> list[bytes]:
            self._note_table_line()
            if self.lineno + 1 == table_line and self.table is None:
                eol = _line_ending(raw, self._eol_line, self.eol)
                return [self._table_block(eol)] + process_line(raw)
            return process_line(raw)
        return counted, process

    def _note_table_line(self) -> None:
        """Note where the next line's output starts, if the table needs it."""
        k = self._table_next
        if k < len(self._table_lines) and self._table_lines[k] == self.lineno + 1:
            self._table_offsets[self._table_lines[k]] = self._out_pos
            self._table_next = k + 1

    def _table_block(self, eol: bytes) -> bytes:
        """The progress table's lines, here: every byte written so far is before it."""
        assert self.plan.table is not None
        self.table = ProgressTable.from_selection(self.plan.table, self._table_offsets,
                                                  self._out_pos, self.plan.table_settings,
                                                  self._crc & 0xFFFFFFFF)
        return self.table.encode(eol)

    def finish(self) -> list[bytes]:
        """The tail time comment (if the plan has one) with its line ending: it goes after
        the file's last whole line (`copy_stream` calls this)."""
        if self.plan.tail_comment is None:
            return []
        pending = self._eol_line
        if pending is not None:
            self._eol_line = None
            self.eol = b"\r\n" if pending.endswith(b"\r\n") else b"\n"
        return [self.plan.tail_comment.encode("utf-8") + self.eol]

    def _copy_quiet(self, data: bytes, pos: int, end: int,
                    write: Callable[[bytes], object]) -> int:
        """Write the quiet lines from `pos` on as they are; where the next line starts.

        Before the next change of progress, the next layer marker, the next line that
        `attention_pattern` matches (pass 1 noted their numbers) and the last move, `process`
        writes every line as it is (and the lines it skips over leave no state behind that
        a later line would not catch up on), so the run up to the first of them is copied
        in one slice: no Python code runs per line, and no search looks at every line.
        """
        lineno = self.lineno
        allowed = self._quiet_until - lineno
        stops = self._stops
        k = self._next_stop
        if k < len(stops) and stops[k] <= lineno:
            k = self._next_stop = bisect_right(stops, lineno, k)
        if k < len(stops) and stops[k] - 1 - lineno < allowed:
            allowed = stops[k] - 1 - lineno
        if allowed <= 0:
            return pos
        count, stop = _lines_upto(data, pos, end, allowed)
        write(data[pos:stop])
        self.lineno += count
        # The last line copied decides the line ending of a later inserted line.
        self._eol_line = data[stop - 2:stop]
        return stop

    def _layer_marker(self, raw: bytes, eol: bytes) -> list[bytes]:
        """A layer marker: an M73 after it (once the print started) and, when the plan
        asks, SET_PRINT_STATS_INFO TOTAL_LAYER before the first and CURRENT_LAYER after
        each, so Mainsail, Fluidd and KlipperScreen show layer numbers."""
        line_eol = eol or self.eol
        before: list[bytes] = []
        after: list[bytes] = []
        total = self.plan.layer_info_total
        if total:
            self._layer += 1
            if self._layer == 1:
                before.append(b"%s TOTAL_LAYER=%d%s" % (LAYER_INFO_COMMAND, total,
                                                        LAYER_INFO_SUFFIX) + line_eol)
            after.append(b"%s CURRENT_LAYER=%d%s" % (LAYER_INFO_COMMAND, self._layer,
                                                     LAYER_INFO_SUFFIX) + line_eol)
        if self._started and not self._finished:
            self._advance(self.lineno)
            pr = progress_pr(self._t, self.plan.total_s)
            after.insert(0, self._m73(pr[0], pr[1], line_eol))
        if not eol:  # the file ends in this marker: never add a line ending to it
            return before + after + [raw]
        return before + [raw] + after

    def _comment(self, raw: bytes, code: bytes, eol: bytes) -> list[bytes]:
        if code.startswith(_PREP_PREFIX_B) or code.startswith(_STOP_PREFIX_B) or (
                code.startswith(_MARKER_PREFIX_B) and _MARKER_RE.match(code) is not None):
            return []
        if code.startswith(HEADER_PREFIX) and is_header_line(code):
            # An old progress table: dropped (the new one goes where `table_place` says).
            self._old_table = True
            return []
        if self._old_table and code.startswith(CHUNK_PREFIX) and is_chunk_line(code):
            return []
        if self.plan.layer_lines.index_of(self.lineno) >= 0:
            return self._layer_marker(raw, eol)
        if self._prefixes and code.startswith(self._prefixes_b):
            text = code.decode("utf-8", "surrogateescape").rstrip("\r\n")
            if text.startswith(self._prefixes):
                new = self.plan.adapter.rewrite_time_comment(text, self.lineno,
                                                             self.plan.times)
                if new is not None and new != text:
                    indent = raw[:len(raw) - len(code)]
                    return [indent + new.encode("utf-8", "surrogateescape") + eol]
        return [raw]


def noting_stop_lines(rewriter: Rewriter) -> Callable[[bytes], list[bytes]]:
    """`rewriter.process`, noting where each stop's own line starts in the output (after
    the stop's time comment and any M73 written before it) as its table offset: the table
    says the stop is on that line, and no time passes on the lines put before it."""
    table = rewriter.plan.table
    stop_lines = frozenset(table.stop_lines if table is not None else ())
    process_line = rewriter.process

    def process(raw: bytes) -> list[bytes]:
        out = process_line(raw)
        if rewriter.lineno in stop_lines:
            pos = rewriter._out_pos  # the start of this line's output (written after)
            for part in out:
                if part is raw:
                    rewriter._table_offsets[rewriter.lineno] = pos
                    break
                pos += len(part)
        return out
    return process


def stop_comment(plan: InjectPlan, line: int, eol: bytes) -> list[bytes]:
    """The comment with the time at the stop on `line` (none if no stop is there)."""
    index = bisect_left(plan.stop_lines, line)
    if index < len(plan.stop_lines) and plan.stop_lines[index] == line:
        stop = plan.stops[index]
        return [stop_line(stop.command, stop.time_s).encode() + eol]
    return []


def time_to_stop(plan: InjectPlan, line: int, code: bytes, eol: bytes) -> list[bytes]:
    """An M73 line of the slicer's (`code`, on `line`): dropped, but for its time-to-change
    form (C, Prusa firmware's minutes to the next colour change or pause), written
    Klipper-true from this line's time while a stop is still ahead."""
    if _M73_C_RE.search(code.split(b";", 1)[0]) is None:
        return []
    index = bisect_left(plan.stop_lines, line)
    if index >= len(plan.stop_lines):
        return []
    sample = bisect_left(plan.sample_lines, line)
    t = plan.sample_times[sample - 1] if sample else 0.0
    return [b"M73 C%d" % minutes_to_stop(t, plan.stops[index].time_s) + eol]


@dataclasses.dataclass(frozen=True)
class InjectResult:
    """What an inject run did."""

    path: str
    output: str
    estimate: Estimate
    slicer: SlicerInfo
    slicer_estimate_s: float | None
    m73_written: int
    table: ProgressTable | None = None
    """The progress table written at the end of the output (None: none written)."""


NO_MOVES = "the file has no moves: nothing to estimate"
"""Every command's refusal of a file without a move (a text file, a picture, a macro)."""


def check_gcode_file(path: str) -> os.stat_result:
    """Stat a file we are about to read, refusing what is not a text G-code file."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise KestimatorError("cannot read file: %s" % (exc.strerror or exc), path) from None
    if stat.S_ISDIR(st.st_mode):
        raise KestimatorError("is a directory, not a G-code file", path)
    try:
        with open_regular(path) as f:
            start = f.read(SNIFF_BYTES)
    except OSError as exc:
        raise KestimatorError("cannot read file: %s" % (exc.strerror or exc), path) from None
    if start[:len(BGCODE_MAGIC)] == BGCODE_MAGIC:
        raise KestimatorError(
            "binary G-code (.bgcode) is not supported: export plain G-code instead", path, 1)
    if st.st_size == 0:
        raise KestimatorError("the file is empty", path)
    what = what_is_not_gcode(start, st.st_size, os.fspath(path))
    if what is not None:
        raise KestimatorError(what, path)
    return st


PlanResult = tuple[InjectPlan, Estimate, SlicerInfo, "float | None"]


def knows_layer_info(limits: Limits) -> bool:
    """Whether the printer knows SET_PRINT_STATS_INFO ([print_stats], which
    [virtual_sdcard] loads), or its config is not known."""
    known = printer_commands(limits)
    return known is None or LAYER_INFO_COMMAND.decode() in known


def plan_lines(lines: Iterable[bytes], head: bytes, tail: bytes, limits: Limits,
               limits_source: str, homing_time: float = 0.0, heat_time: float = 0.0,
               path: str = "<input>", macros: MacroTimes | None = None,
               layer_info: bool = True, table: bool = False) -> PlanResult:
    """Pass 1 over byte lines: estimate with progress samples, build the rewrite plan.

    `head` and `tail` are the first and last MiB (the same bytes for small input); they
    tell the slicer and its own estimate. Hosts that hold G-code in memory (Cura's layer
    chunks) call this; `plan_file` is the same for a file. `table`: the plan holds the
    progress table's points (`copy_stream` then writes the table at the end).
    """
    slicer = detect(head, tail)
    adapter = adapter_for(slicer.family)
    slicer_s = slicer_estimate_from_head(head, slicer)
    est = estimate_lines(lines, limits, path, homing_time=homing_time, heat_time=heat_time,
                         sample=True, mark_prefixes=adapter.mark_prefixes, macros=macros,
                         note=attention_matcher(adapter.time_comment_prefixes))
    if est.last_move_line is None:
        raise KestimatorError(NO_MOVES, path)
    plan = InjectPlan.from_estimate(
        est, adapter, slicer_s, limits_source,
        # What the rewritten time comments hold: print_duration, without the time before the
        # first extrusion.
        adapter.moonraker_time_comment(slicer, FileEnds.from_bytes(head, tail),
                                       est.total_s - est.parts.before_first_extrusion_s),
        # Layer numbers only where the file sets none itself (its first and last MiB), and
        # only for a printer that knows the command (or one whose config is not known).
        layer_info=layer_info and _FOREIGN_LAYER_INFO_RE.search(head) is None
        and _FOREIGN_LAYER_INFO_RE.search(tail) is None and knows_layer_info(limits),
        table=table)
    if plan.table is not None:
        plan = dataclasses.replace(plan, table_settings=table_settings(
            limits, homing_time, heat_time, macros),
            table_line=table_place(tail, est.n_lines, plan.table))
    return plan, est, slicer, slicer_s


def table_place(tail: bytes, n_lines: int, selection: Selection) -> int | None:
    """The line of the input the progress table is written before (None: at the end).

    Before the slicer's settings block that ends the file when a slicer reads that block
    back from the file's end without delimiters (PrusaSlicer before 2.4, Slic3r, Slic3r PE,
    SuperSlicer: `settings_block_start`), so that it still reads it; else in the place of
    an old table when what follows that one may follow a table (`replaceable_table_at`:
    what a post-processor appended after it stays after it); else at the end. Never where
    a point of the table would be after it. `tail` is the input's last bytes (from a line
    start, to its end) and `n_lines` its number of lines: the same place in a second run's
    input, whose old table is dropped, so the output is the same."""
    start = settings_block_start(tail)
    if start is None:
        start = replaceable_table_at(tail)
    if start is None:
        return None
    line = n_lines - tail.count(b"\n", start) - (0 if tail.endswith(b"\n") else 1) + 1
    wanted = selection.wanted_lines()
    return None if wanted and wanted[-1] > line else line


def plan_file(path: str, limits: Limits, limits_source: str, homing_time: float = 0.0,
              heat_time: float = 0.0, progress: ProgressCallback | None = None,
              macros: MacroTimes | None = None, layer_info: bool = True,
              table: bool = False) -> PlanResult:
    """Pass 1 over a file (streamed; only its first and last MiB are read twice)."""
    head, tail = read_file_ends(path)
    return plan_lines(iter_lines(path, progress), head, tail, limits, limits_source, homing_time,
                      heat_time, path, macros, layer_info, table)


def inject_file(path: str | os.PathLike[str], limits: Limits, output: str | None = None,
                limits_source: str = "", homing_time: float = 0.0,
                heat_time: float = 0.0,
                progress: ProgressCallback | None = None,
                macros: MacroTimes | None = None,
                layer_info: bool = True,
                finish: Callable[[str], object] | None = None,
                table: bool = True) -> InjectResult:
    """Rewrite `path` (or write `output`) with Klipper's times; atomic, never partial.

    `progress` hears the bytes read so far over both passes: the file is read twice, so
    the count ends at twice its size. `layer_info`: add SET_PRINT_STATS_INFO TOTAL_LAYER /
    CURRENT_LAYER lines where the file sets no layer numbers itself. `finish` is called with
    the temporary file's name once pass 2 has written it, before it is synced and replaced
    (compat appends its line). `table`: end the file with the progress table
    (kestimator.progress_table), replacing an old one.
    """
    src = os.fspath(path)
    dest = os.fspath(output) if output is not None else src
    if not dest:
        raise KestimatorError("the output name is empty", src)
    check_gcode_file(src)
    target = output_target(dest)
    in_place = not target.stream and target.exists and same_file(src, target.path)
    with exclusive(src) if in_place else contextlib.nullcontext():
        before = check_gcode_file(src)
        plan, est, slicer, slicer_s = plan_file(src, limits, limits_source, homing_time,
                                                heat_time, progress, macros, layer_info,
                                                table)
        rewriter = Rewriter(plan)
        _write_output(src, target, rewriter, before, in_place, progress, finish)
    return InjectResult(path=src, output=dest, estimate=est, slicer=slicer,
                        slicer_estimate_s=slicer_s, m73_written=rewriter.m73_written,
                        table=rewriter.table)


GONE = "the file was removed while it was being processed: nothing was written"


def _write_output(src: str, target: OutputTarget, rewriter: Rewriter,
                  before: os.stat_result, in_place: bool,
                  progress: ProgressCallback | None = None,
                  finish: Callable[[str], object] | None = None) -> None:
    """Pass 2 from `src` into `target` through `kestimator.files.write_atomically`.

    Refused if the source is not the file pass 1 read (identity, size, mtime): when pass 2
    opens it, when it has read it, and at the last moment before the replace (a writer that
    takes no lock, such as a slicer still saving, or a file swapped in by rename). In place
    the file is then left as it is now; with -o the output is not written (a new file is not
    left behind, an old one keeps its content). A device or FIFO output has its bytes
    already when the check after pass 2 fails: the run still fails, one line saying so.
    """
    copied = None
    if progress is not None:
        def copied(done: int) -> None:
            progress(before.st_size + done)

    def refuse() -> None:
        if in_place:
            raise KestimatorError("the file changed while it was being processed; "
                                  "it was left as it is now", src)
        if target.stream:
            raise KestimatorError("the file changed while it was being processed: what was "
                                  "written to %s is not its output" % target.path, src)
        raise KestimatorError("the file changed while it was being processed: %s was not "
                              "written" % target.path, src)

    def check(now: os.stat_result) -> None:
        if (now.st_size, now.st_mtime_ns, now.st_ino, now.st_dev) != (
                before.st_size, before.st_mtime_ns, before.st_ino, before.st_dev):
            refuse()

    def fill(write: Write) -> None:
        try:
            inp = open(src, "rb")
        except FileNotFoundError:
            raise KestimatorError(GONE, src) from None
        with inp:
            check(os.fstat(inp.fileno()))
            rewriter.copy_stream(inp, write, copied)
            check(os.fstat(inp.fileno()))

    def unchanged() -> None:
        try:
            now = os.stat(src)
        except FileNotFoundError:
            raise KestimatorError(GONE, src) from None
        check(now)

    write_atomically(target, fill,
                     # A new file: the source's mode, and writable by its owner (who made it).
                     new_mode=stat.S_IMODE(before.st_mode) | stat.S_IWUSR,
                     before_sync=finish, before_replace=unchanged)
    if target.stream:
        unchanged()
