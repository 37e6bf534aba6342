"""`python3 -m kestimator.worker`: a file's progress table for the Klipper module, on request.

Owns the worker the Klipper extras module (plugins/klipper/) starts beside Klipper, so that
no estimate runs in Klipper's process: a long-lived process that reads one JSON request per
line on standard input and writes one JSON answer per line on standard output (flushed
after each), in the order asked. A request::

    {"id": 1, "file": "/abs/x.gcode", "config": "/abs/printer.cfg" or null,
     "events": [[byte_offset, "EXCLUDE_OBJECT NAME=A"], ...], "use_table": true,
     "encoding": "b64" (optional), "klipper_version": "v0.12.0-455-g5f2d7bc8" (optional)}

``klipper_version`` is the software_version of the Klipper the module runs in ("Kalico
v2026.07.00-..." for Kalico): the printer's klipper_version unless the user's settings (the
printer.cfg comment, the profile) name one. A table made without a version holds for a
Klipper whose version selects today's rules (`_same_release_as`).

The answer: ``{"id": 1, "ok": true, "source": "table" | "estimate", "total_s": ...,
"offsets": [...], "times": [...], "object_names": [...], "object_offsets": [...],
"object_remaining": [[...], ...], "stop_offsets": [...], "stop_times": [...],
"stop_commands": [...], "stop_lines": [...], "warnings": [...], "elapsed_s": ...}``, or
``{"id": 1, "ok": false, "error": "one line"}``. With ``"encoding": "b64"`` the lists come
as base64 machine arrays instead (`ProgressTable.to_json`: ``offsets_b64``, ...; the
stops, at most 1,000, stay JSON lists). The stops (kestimator.stops: where the print waits
for a person) are each one's byte offset and line, Klipper's time there and its command;
from a table, their lines are counted in the file.

With `use_table`, no events and a valid table at the file's end (`kestimator inject` wrote
it), the answer is that table, read from the file's end (and the bytes it covers read once,
their CRC-32 compared with the one it records: a file edited after inject, even to the same
length, is estimated afresh, with a warning), if it was made for this printer: given
`config`, the worker resolves the settings an estimate would use (below) and compares them
with those the table records (kestimator.progress_table, "The printer it was made for").
When they differ (another printer, a changed max_accel, another homing time in
the profile, ...) the file is estimated afresh, with a warning naming the first differing
settings ("the file's table was made for max_accel 3000, this printer has 5000: estimated
afresh"); a version-1 table, which records no settings, and a version-2 table, which
records no stops (its times were made without the look-ahead running out at a colour change
or a pause: under a second off at each), are estimated afresh too, with a warning saying
so. When the settings cannot be resolved (a printer.cfg kestimator cannot
read) the table is used, with a warning that it could not be checked; with `config` null
nothing is known to check it against, and it is used as it is. Otherwise the file is
estimated as ``kestimator estimate FILE --printer-cfg CONFIG`` would (the profile, the
slicer's settings and the learned times resolved the same way, the printer.cfg winning),
each event run before the line that starts at (or after) its byte offset, and the table
built from that estimate with the file's own byte offsets. The estimate keeps checkpoints
of the planner (kestimator.resume) for the file estimated last: the next estimate of that
very file (device, inode, size, modification and change times) for the very same settings
(a change during the print: the events so far and a new one) goes on from the last
checkpoint before the first event that differs, so it reads only the file from there on
(at most 5 % of the rest more), and its answer is byte for byte a whole pass's. The
checkpoints take at most resume.MAX_CHECKPOINT_BYTES (64 MiB; 11.3 MiB for the 40 MB
corpus file) and are dropped when another file or other settings are estimated. Every
request gets an answer
(no error ends the process); end of input ends it with status 0. Only the standard library
and the table's module are imported up front; the estimator loads on the first estimate
(or the first check of a table against a printer.cfg).

Files are hostile, and the Klipper module reads every answer inside Klipper's process, so
every answer is bounded whatever the file holds. A table read from a file is refused past
the writer's own limits (kestimator.progress_table: MAX_TABLE_POINTS time points,
MAX_OBJECTS objects named in at most MAX_NAME_BYTES bytes, MAX_OBJECT_POINTS object points)
before anything proportional to what it declares is allocated, and refused when a value is
one the writer never writes (a negative or growing time left, a time past the total, ...):
the file is then estimated, with a warning. An estimate's table keeps the same limits:
objects past MAX_OBJECTS, or whose name is over MAX_NAME_BYTES, are left out of it (their
time still counts in the total), with a warning. At most MAX_WARNINGS warnings of at most
MAX_ERROR_CHARS characters each are sent (the last says how many more); an `id` is an
integer, null or a string of at most MAX_ID_CHARS characters. Within these limits an answer
is under 4 MiB as JSON lists (20,002 points and 100,000 object values as JSON numbers, 200
names escaped six characters a byte: 3.3 MiB at worst) and under 2 MiB with "b64"; one that
would still pass MAX_ANSWER_BYTES (3.5 MiB, under the 4 MiB past which the Klipper module
refuses an answer) is sent as ``ok: false`` instead. The worker's memory stays bounded
likewise (the estimate's is bounded by its own design).

Standard output is the channel and holds nothing else: the worker keeps it for its answers
and points file descriptor 1 and `sys.stdout` at standard error, so that whatever library
code prints goes there (and standard input is read only by the worker).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from bisect import bisect_right
from collections.abc import Sequence
from typing import IO, TYPE_CHECKING, Any

from kestimator.progress_table import (
    MAX_NAME_BYTES,
    MAX_OBJECTS,
    TABLE_VERSION,
    ProgressTable,
    Settings,
    TableError,
    describe_differences,
    lines_at_offsets,
    read_table,
    select,
    settings_differences,
)

if TYPE_CHECKING:
    from kestimator.config.resolve import ResolvedLimits
    from kestimator.estimate import Estimate, Event
    from kestimator.macros import MacroTimes
    from kestimator.resume import Resumable
    from kestimator.slicers import SettingsCache

# A request line longer than this is refused without being parsed (memory stays bounded).
MAX_REQUEST_BYTES = 1 << 20
MAX_EVENTS = 10000
MAX_ERROR_CHARS = 500
MAX_ID_CHARS = 100
MAX_VERSION_CHARS = 100
# Warnings sent at most (the Klipper module keeps 20); past them one line says how many more.
MAX_WARNINGS = 20
# No answer line is longer (see the module's docstring).
MAX_ANSWER_BYTES = 7 << 19


class RequestError(Exception):
    """A request that cannot be answered: its message is the answer's error, `request_id`
    the request's id once it is known to be a valid one."""

    def __init__(self, message: str, request_id: int | str | None = None) -> None:
        super().__init__(message)
        self.request_id = request_id


# The worker's own tables stay in memory, never in a file: ten times finer than a file's
# (points at most max(0.04 s, 0.015 % of the time left) apart, as the samples allow).
WORKER_PRECISION = 0.1


def _one_line(text: str) -> str:
    return " ".join(text.split())[:MAX_ERROR_CHARS] or "error"


def parse_request(line: bytes) -> dict[str, Any]:
    """The request on `line`, checked (RequestError says what is wrong)."""
    if len(line) > MAX_REQUEST_BYTES:
        raise RequestError("the request is over %d bytes" % MAX_REQUEST_BYTES)
    try:
        request = json.loads(line)
    except ValueError as exc:
        raise RequestError("invalid JSON: %s" % exc) from None
    if not isinstance(request, dict):
        raise RequestError("a request is a JSON object")
    request_id = request.get("id")
    if not (request_id is None or (isinstance(request_id, int) and abs(request_id) < 1 << 63)
            or (isinstance(request_id, str) and len(request_id) <= MAX_ID_CHARS)):
        raise RequestError("'id' must be an integer, null or a string of at most %d "
                           "characters" % MAX_ID_CHARS)
    try:
        return _checked(request)
    except RequestError as exc:
        exc.request_id = request_id
        raise


def _checked(request: dict[str, Any]) -> dict[str, Any]:
    path = request.get("file")
    if not isinstance(path, str) or not path:
        raise RequestError("'file' must be the G-code file's path")
    config = request.get("config")
    if config is not None and not isinstance(config, str):
        raise RequestError("'config' must be a printer.cfg path or null")
    events = request.get("events") or []
    if not isinstance(events, list) or len(events) > MAX_EVENTS:
        raise RequestError("'events' must be a list of at most %d [byte_offset, command]"
                           % MAX_EVENTS)
    checked = []
    for event in events:
        if (not isinstance(event, (list, tuple)) or len(event) != 2
                or not isinstance(event[0], int) or isinstance(event[0], bool)
                or event[0] < 0 or not isinstance(event[1], str)):
            raise RequestError("each event is [byte_offset, \"COMMAND TEXT\"]")
        checked.append((event[0], event[1]))
    request["events"] = checked
    request["use_table"] = bool(request.get("use_table", True))
    version = request.get("klipper_version")
    if version is not None and (not isinstance(version, str)
                                or len(version) > MAX_VERSION_CHARS):
        raise RequestError("'klipper_version' must be the Klipper's software_version (at "
                           "most %d characters) or null" % MAX_VERSION_CHARS)
    return request


def answer(request: dict[str, Any]) -> dict[str, Any]:
    """The answer to a checked request (raises on failure; `handle` turns that into one)."""
    started = time.monotonic()
    path = request["file"]
    if not os.path.isfile(path):
        raise RequestError("no such file: %s" % path)
    warnings: list[str] = []
    table: ProgressTable | None = None
    source = "estimate"
    printer: Printer | None = None
    if request["use_table"] and not request["events"]:
        try:
            with open(path, "rb") as f:
                table = read_table(f, check_content=True)
            source = "table"
        except TableError as exc:
            warnings.append("no usable progress table (%s): estimated" % exc)
        config = request.get("config")
        if table is not None and config is not None:
            try:
                printer = resolve_printer(path, config, request.get("klipper_version"))
            except Exception as exc:  # noqa: BLE001 - the table is still the best answer
                warnings.append("the file's table could not be checked against %s (%s): "
                                "used as it is" % (config, _one_line(str(exc)
                                                                     or type(exc).__name__)))
            else:
                why = table_mismatch(table, printer)
                if why is not None:
                    warnings.append(why)
                    table = None
                    source = "estimate"
    if table is None:
        table, more = estimate_table(path, request.get("config"), request["events"], printer,
                                     request.get("klipper_version"))
        warnings += more
    elif table.stop_offsets:
        table = dataclasses.replace(table, stop_lines=stop_lines(path, table.stop_offsets))
    doc: dict[str, Any] = {"id": request.get("id"), "ok": True, "source": source}
    doc.update(table.to_json(request.get("encoding")))
    doc["warnings"] = _bounded_warnings(warnings)
    doc["elapsed_s"] = round(time.monotonic() - started, 3)
    return doc


def table_mismatch(table: ProgressTable, printer: Printer) -> str | None:
    """Why the file's table does not hold for this printer (a warning), or None when it was
    made for the very settings this printer has."""
    if table.settings is None:
        return ("the file's table records no printer settings (a version-1 table, written "
                "before kestimator recorded them), so it may be for another printer: "
                "estimated afresh")
    if table.version < TABLE_VERSION:
        return ("the file's table records no stops (a version-%d table, written before "
                "kestimator recorded them: its times do not stand at a colour change or a "
                "pause): estimated afresh" % table.version)
    made_for = _same_release_as(table.settings, printer.settings)
    if made_for == printer.settings:
        return None
    return ("the file's table was made for %s: estimated afresh"
            % describe_differences(settings_differences(made_for, printer.settings)))


def _release_rules(version: str | None) -> object:
    """What a recorded klipper_version changes in an estimate beside the recorded
    klipper_generation: its toolhead's rules and whether it is Kalico (no version: today's
    Klipper's); the text itself when it is no version."""
    from kestimator.limits import klipper_release
    if not version:
        return ("mainline", "mainline", False, False, "mainline", False)
    try:
        release = klipper_release(version)
    except ValueError:
        return version
    return (release.junction, release.print_time, release.pressure_advance_waits,
            release.pressure_advance_always_flushes, release.lookahead, release.is_kalico)


def _same_release_as(made_for: Settings, here: Settings) -> Settings:
    """`made_for` with this printer's klipper_version where the two select the same rules
    (a table injected without a version holds on a host whose Klipper reports today's)."""
    theirs, ours = dict(made_for).get("klipper_version"), dict(here).get("klipper_version")
    if theirs == ours or theirs is None or ours is None or (
            _release_rules(theirs) != _release_rules(ours)):
        return made_for
    return tuple((name, ours if name == "klipper_version" else value)
                 for name, value in made_for)


def stop_lines(path: str, offsets: list[int]) -> list[int]:
    """The line (from 1) that starts at each of a table's stop offsets: counted in one
    pass up to the last."""
    with open(path, "rb") as f:
        return lines_at_offsets(f.read, offsets)


def _bounded_warnings(warnings: list[str]) -> list[str]:
    """At most MAX_WARNINGS lines of at most MAX_ERROR_CHARS: the first, and how many more."""
    if len(warnings) <= MAX_WARNINGS:
        return [str(w)[:MAX_ERROR_CHARS] for w in warnings]
    kept = [str(w)[:MAX_ERROR_CHARS] for w in warnings[:MAX_WARNINGS - 1]]
    return kept + ["and %d more warnings" % (len(warnings) - len(kept))]


@dataclasses.dataclass(frozen=True)
class Printer:
    """What an estimate of one file for one printer.cfg is given, resolved once."""

    resolved: ResolvedLimits
    macros: MacroTimes
    settings: Settings
    """`kestimator.rewrite.table_settings` of the above: what a table made for it records."""

    @property
    def homing_time(self) -> float:
        return float(self.resolved.homing_time_s or 0.0)

    @property
    def heat_time(self) -> float:
        return float(self.resolved.heat_time_s or 0.0)


# The slicer's settings of the file asked about last, by the bytes they were read from.
_slicer_cache: SettingsCache | None = None


def resolve_printer(path: str, config: str | None,
                    klipper_version: str | None = None) -> Printer:
    """The settings `path` is estimated with for the printer.cfg `config`, as
    ``kestimator estimate --printer-cfg CONFIG`` resolves them (the profile, the slicer's
    settings and the learned times, the printer.cfg winning). `klipper_version`: the
    software_version of the Klipper the module runs in, the printer's klipper_version
    unless the user's settings name one."""
    global _slicer_cache
    from kestimator import learn
    from kestimator.config.resolve import LimitRequest, resolve_limits
    from kestimator.rewrite import table_settings
    from kestimator.slicers import SettingsCache

    if _slicer_cache is None:
        _slicer_cache = SettingsCache()
    resolved = resolve_limits(LimitRequest(gcode=path, printer_cfg=config,
                                           slicer_cache=_slicer_cache,
                                           running_klipper_version=klipper_version))
    macros = learn.macro_times_for(resolved, True)
    homing = resolved.homing_time_s or 0.0
    heat = resolved.heat_time_s or 0.0
    return Printer(resolved, macros, table_settings(resolved.limits, homing, heat, macros))


def estimate_table(path: str, config: str | None, events: list[tuple[int, str]],
                   printer: Printer | None = None, klipper_version: str | None = None
                   ) -> tuple[ProgressTable, list[str]]:
    """Estimate `path` as `kestimator estimate --printer-cfg CONFIG` would, with `events`
    (byte offset, command) run at their lines; the table with the file's offsets. `printer`:
    the settings already resolved for `config` (`resolve_printer`), else resolved here."""
    from kestimator.rewrite import check_gcode_file

    check_gcode_file(path)
    if printer is None:
        printer = resolve_printer(path, config, klipper_version)
    lines = event_lines(path, [offset for offset, _ in events])
    resolved, macros = printer.resolved, printer.macros
    warnings = list(resolved.warnings) + list(macros.warnings)
    est, resumable = estimate_resuming(path, printer,
                                       list(zip(lines, (text for _, text in events))))
    warnings += est.warnings
    selection = select(est, precision=WORKER_PRECISION, previous=resumable.made_from)
    if selection.objects_left_out:
        warnings.append("%d objects left out of the table (over %d objects, or a name over "
                        "%d bytes): their time counts in the total only"
                        % (selection.objects_left_out, MAX_OBJECTS, MAX_NAME_BYTES))
    size = os.path.getsize(path)
    line_bytes = size / max(1, est.n_lines)
    offsets, object_offsets = resumable.line_offsets(path, selection, line_bytes)
    stop_offsets = resumable.stop_offsets(path, selection, line_bytes)
    return ProgressTable.from_offsets(selection, offsets, object_offsets, size,
                                      printer.settings, stop_offsets=stop_offsets), warnings


# The checkpoints of the file estimated last (kestimator.resume): one file at a time.
_resumable: Resumable | None = None


def _file_id(path: str, st: os.stat_result) -> tuple[object, ...]:
    """What says a file is still the one checkpoints were taken of."""
    return (path, st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def event_lines(path: str, offsets: list[int]) -> list[int]:
    """The line each byte offset falls on (`lines_at_offsets`), each counted from the last
    checkpoint of this very file at or before it (a checkpoint knows its line and the byte
    offset of the next) rather than from the file's start: a few gaps are read, not the
    file between the first event and the last. The lines found are kept with the
    checkpoints (the Klipper module sends every change so far each time: only the new
    one is counted)."""
    if not offsets:
        return []
    anchors = [(0, 0)]  # (line, byte offset of the next line), ascending
    found: dict[int, int] = {}
    resumable = _resumable
    if resumable is not None and isinstance(resumable.key, tuple):
        file_id = _file_id(path, os.stat(path))
        if resumable.key[:len(file_id)] == file_id:
            anchors += [(c.lineno, c.offset) for c in resumable.checkpoints if c.offset > 0]
            found = resumable.event_lines
    starts = [offset for _, offset in anchors]
    groups: dict[int, list[int]] = {}  # anchor index -> indexes of the offsets after it
    result = [0] * len(offsets)
    for i, offset in enumerate(offsets):
        line = found.get(offset)
        if line is not None:
            result[i] = line
        else:
            groups.setdefault(max(0, bisect_right(starts, offset) - 1), []).append(i)
    with open(path, "rb") as f:
        for anchor, indexes in groups.items():
            line0, offset0 = anchors[anchor]
            f.seek(offset0)
            wanted = [offsets[i] - offset0 for i in indexes]
            # Read no further than the last one needs (a fresh MiB was half the time).
            relative = lines_at_offsets(f.read, wanted, min(1 << 20, max(wanted) + 1))
            for i, line in zip(indexes, relative):
                result[i] = line0 + line
    if resumable is not None and found is resumable.event_lines:
        if len(found) + len(offsets) > MAX_EVENTS:
            found.clear()
        found.update(zip(offsets, result))
    return result


def estimate_resuming(path: str, printer: Printer, events: list[Event]
                      ) -> tuple[Estimate, Resumable]:
    """The estimate of `path` for `printer` with `events` (line, command), going on from
    the checkpoints of the last estimate when they are of this very file (device, inode,
    size, times) for these very settings, and keeping them for the next; and those
    checkpoints (`Resumable`, which also finds the table's line offsets)."""
    global _resumable
    from kestimator.estimate import Timeline
    from kestimator.resume import Resumable

    st = os.stat(path)
    resolved, macros = printer.resolved, printer.macros
    key = _file_id(path, st) + (resolved.limits, macros, printer.homing_time,
                                printer.heat_time)
    if _resumable is None or _resumable.key != key:
        _resumable = None  # the old checkpoints go before new ones are taken
        _resumable = Resumable(key, st.st_size)
    resumable = _resumable

    def new_timeline(ordered: Sequence[Event]) -> Timeline:
        return Timeline(resolved.limits, path, homing_time=printer.homing_time,
                        heat_time=printer.heat_time, sample=True, macros=macros,
                        events=ordered)
    try:
        return resumable.estimate(path, new_timeline, events), resumable
    except BaseException:
        _resumable = None  # what a failed pass left is not kept
        raise


def handle(line: bytes) -> dict[str, Any]:
    """The answer to one request line, whatever goes wrong."""
    request_id: Any = None
    try:
        request = parse_request(line)
        request_id = request.get("id")
        return answer(request)
    except RequestError as exc:
        if exc.request_id is not None:
            request_id = exc.request_id
        return {"id": request_id, "ok": False, "error": _one_line(str(exc))}
    except MemoryError:
        return {"id": request_id, "ok": False, "error": "out of memory"}
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - every request gets an answer
        text = str(exc) or type(exc).__name__
        if isinstance(exc, SystemExit):  # library code called sys.exit: the worker lives on
            text = "SystemExit(%s)" % text
        return {"id": request_id, "ok": False, "error": _one_line(text)}


def _dumps(doc: dict[str, Any]) -> str:
    """`doc` as one JSON line (no newline) of at most MAX_ANSWER_BYTES, or an error
    answer in its place."""
    request_id = doc.get("id") if _plain(doc.get("id")) else None
    try:
        text = json.dumps(doc, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError, RecursionError) as exc:
        return json.dumps({"id": request_id, "ok": False,
                           "error": _one_line("cannot encode: %s" % exc)})
    if len(text) > MAX_ANSWER_BYTES:  # ASCII (json.dumps escapes the rest): chars = bytes
        return json.dumps({"id": request_id, "ok": False,
                           "error": "the answer is over %d bytes" % MAX_ANSWER_BYTES})
    return text


def _plain(value: object) -> bool:
    return value is None or (isinstance(value, str) and len(value) <= MAX_ID_CHARS) or (
        isinstance(value, int) and abs(value) < 1 << 63) or (
        isinstance(value, float) and math.isfinite(value))


def serve(inp: IO[bytes], out: IO[str]) -> int:
    """Answer every request line of `inp` on `out` until end of input; 0."""
    while True:
        line = inp.readline(MAX_REQUEST_BYTES + 1)
        if not line:
            return 0
        if len(line) > MAX_REQUEST_BYTES and not line.endswith(b"\n"):
            while line and not line.endswith(b"\n"):  # skip the rest of the long line
                line = inp.readline(MAX_REQUEST_BYTES)
            doc: dict[str, Any] = {"id": None, "ok": False,
                                   "error": "the request is over %d bytes" % MAX_REQUEST_BYTES}
        elif not line.strip():
            continue
        else:
            doc = handle(line)
        out.write(_dumps(doc) + "\n")
        out.flush()


def take_channel() -> tuple[IO[bytes], IO[str]]:
    """Standard input and output, kept for the JSON-lines channel alone: the channel gets
    duplicates of file descriptors 0 and 1; then descriptor 1 and `sys.stdout` point at
    standard error and descriptor 0 and `sys.stdin` at /dev/null, so that nothing library
    code prints or reads touches the channel."""
    sys.stdout.flush()
    inp = os.fdopen(os.dup(0), "rb")
    out = os.fdopen(os.dup(1), "w", encoding="utf-8", newline="\n")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    sys.stdin = open(os.devnull, encoding="utf-8")  # for the process's life
    return inp, out


def main() -> int:
    """The program: standard input and output as the JSON-lines channel."""
    try:
        inp, out = take_channel()
        return serve(inp, out)
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
