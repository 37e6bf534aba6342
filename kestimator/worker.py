"""`python3 -m kestimator.worker`: a file's progress table for the Klipper module, on request.

Owns the worker the Klipper extras module (plugins/klipper/) starts beside Klipper, so that
no estimate runs in Klipper's process: a long-lived process that reads one JSON request per
line on standard input and writes one JSON answer per line on standard output (flushed
after each), in the order asked. A request::

    {"id": 1, "file": "/abs/x.gcode", "config": "/abs/printer.cfg" or null,
     "events": [[byte_offset, "EXCLUDE_OBJECT NAME=A"], ...], "use_table": true,
     "encoding": "b64" (optional)}

The answer: ``{"id": 1, "ok": true, "source": "table" | "estimate", "total_s": ...,
"offsets": [...], "times": [...], "object_names": [...], "object_offsets": [...],
"object_remaining": [[...], ...], "warnings": [...], "elapsed_s": ...}``, or
``{"id": 1, "ok": false, "error": "one line"}``. With ``"encoding": "b64"`` the lists come
as base64 machine arrays instead (`ProgressTable.to_json`: ``offsets_b64``, ...).

With `use_table`, no events and a valid table at the file's end (`kestimator inject` wrote
it), the answer is that table, read from the file's end only. Otherwise the file is
estimated as ``kestimator estimate FILE --printer-cfg CONFIG`` would (the profile, the
slicer's settings and the learned times resolved the same way, the printer.cfg winning),
each event run before the line that starts at (or after) its byte offset, and the table
built from that estimate with the file's own byte offsets. Every request gets an answer
(no error ends the process); end of input ends it with status 0. The answer's size is
bounded by the table's (kestimator.progress_table). Only the standard library and the
table's module are imported up front; the estimator loads on the first estimate.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from typing import IO, Any

from kestimator.progress_table import (
    ProgressTable,
    TableError,
    line_offsets,
    lines_at_offsets,
    read_table,
    select,
)

# A request line longer than this is refused without being parsed (memory stays bounded).
MAX_REQUEST_BYTES = 1 << 20
MAX_EVENTS = 10000
MAX_ERROR_CHARS = 500


class RequestError(Exception):
    """A request that cannot be answered: its message is the answer's error."""


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
    if request["use_table"] and not request["events"]:
        try:
            with open(path, "rb") as f:
                table = read_table(f)
            source = "table"
        except TableError as exc:
            warnings.append("no usable progress table (%s): estimated" % exc)
    if table is None:
        table, more = estimate_table(path, request.get("config"), request["events"])
        warnings += more
    doc: dict[str, Any] = {"id": request.get("id"), "ok": True, "source": source}
    doc.update(table.to_json(request.get("encoding")))
    doc["warnings"] = warnings
    doc["elapsed_s"] = round(time.monotonic() - started, 3)
    return doc


def estimate_table(path: str, config: str | None,
                   events: list[tuple[int, str]]) -> tuple[ProgressTable, list[str]]:
    """Estimate `path` as `kestimator estimate --printer-cfg CONFIG` would, with `events`
    (byte offset, command) run at their lines; the table with the file's offsets."""
    from kestimator import learn
    from kestimator.config.resolve import LimitRequest, resolve_limits
    from kestimator.estimate import estimate_lines, iter_lines
    from kestimator.rewrite import check_gcode_file

    lines: list[int] = []
    if events:
        with open(path, "rb") as f:
            lines = lines_at_offsets(f.read, [offset for offset, _ in events])
    check_gcode_file(path)
    resolved = resolve_limits(LimitRequest(gcode=path, printer_cfg=config))
    macros = learn.macro_times_for(resolved, True)
    warnings = list(resolved.warnings) + list(macros.warnings)
    est = estimate_lines(iter_lines(path), resolved.limits, path,
                         homing_time=resolved.homing_time_s or 0.0,
                         heat_time=resolved.heat_time_s or 0.0, sample=True, macros=macros,
                         events=list(zip(lines, (text for _, text in events))))
    warnings += est.warnings
    selection = select(est, precision=WORKER_PRECISION)
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        offsets = line_offsets(f.read, selection.wanted_lines())
    return ProgressTable.from_selection(selection, offsets.get, size), warnings


def handle(line: bytes) -> dict[str, Any]:
    """The answer to one request line, whatever goes wrong."""
    request_id: Any = None
    try:
        request = parse_request(line)
        request_id = request.get("id")
        return answer(request)
    except RequestError as exc:
        return {"id": request_id, "ok": False, "error": _one_line(str(exc))}
    except MemoryError:
        return {"id": request_id, "ok": False, "error": "out of memory"}
    except Exception as exc:  # noqa: BLE001 - every request gets an answer
        text = str(exc) or type(exc).__name__
        return {"id": request_id, "ok": False, "error": _one_line(text)}


def _dumps(doc: dict[str, Any]) -> str:
    try:
        return json.dumps(doc, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        return json.dumps({"id": doc.get("id") if _plain(doc.get("id")) else None,
                           "ok": False, "error": _one_line("cannot encode: %s" % exc)})


def _plain(value: object) -> bool:
    return value is None or isinstance(value, (str, int)) or (
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


def main() -> int:
    """The program: standard input and output as the JSON-lines channel."""
    try:
        return serve(sys.stdin.buffer, sys.stdout)
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
