# kestimator: Klipper-exact remaining print time, kept true during the print.
#
# A Klipper extras module (link it into klippy/extras/ and add a [kestimator]
# section). During a virtual-SD print it publishes `printer.kestimator`:
#   remaining_s, eta, progress, total_s, source, objects, next_stop, state,
#   error, ...
# (next_stop: the next colour change or pause the table lists, and the time to
# it, Klipper's as remaining_s is; optionally the display message), and answers
# for display_status with progress D / (D + R) (print duration, remaining
# time), so the front ends' own D / progress - D is Klipper's time.
#
# How: a table maps byte offsets of the file to the time Klipper's planner
# needs to reach them (read from the table `kestimator inject` wrote into the
# file, or estimated by kestimator). The table and every re-estimate (after an
# EXCLUDE_OBJECT or an M220 typed during the print) come from a separate
# process, `python3 -m kestimator.worker`, whose answers the reactor polls.
# Klipper's own print_time ties the table to the clock: at a line start (the
# update timer asks; virtual_sdcard's next line, or a command typed at the
# console, takes it: on a printer the timer runs while a line waits inside
# toolhead._check_pause, when an arc or a macro may be half queued) the module
# notes the print_time at which the moves queued so far end (a timing callback
# on the last queued move, as toolhead.register_lookahead_callback does,
# without flushing anything), so
#   remaining = (total - table_time(position)) + (anchor_print_time - now)
# holds through pauses, heater waits and speed changes (past the anchor, only
# while the toolhead still moves, and never past the line being run). The
# status is computed at the eventtime Klipper asks it for. What the user set
# at the console before the print (limits, M220/M221, offsets, pressure
# advance, retraction, input shaper) is part of the estimate.
#
# It can never hurt a print: every entry point catches everything; an error
# disables the module with one line in klippy.log and an `error` field in its
# status, and Klipper goes on as without it. No callback does more than a
# bisection or a C-speed decode of a bounded answer; memory is bounded by the
# worker's table size (answers past its limits are refused).
#
# Copyright (C) 2026 the kestimator authors
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later). It re-implements no Klipper code; it reads Klipper's
# objects through the interfaces named above.
from __future__ import annotations

import array
import base64
import bisect
import json
import logging
import math
import os
import shlex
import subprocess
import sys
import time
from typing import Any, Callable

# Seconds of reactor time between updates.
UPDATE_INTERVAL = 0.5
# What the worker's table writer keeps at most (kestimator/progress_table.py:
# MAX_TABLE_POINTS, MAX_OBJECT_POINTS, MAX_OBJECTS, MAX_NAME_BYTES); an answer with
# more is refused. (Copied, not imported: this module runs in Klipper's Python without
# kestimator; tests/test_klipper_module.py holds the two to each other.)
MAX_TIME_POINTS = 20002
MAX_OBJECT_POINTS = 500
MAX_OBJECTS = 200
MAX_NAME_CHARS = 256
# The stops a table holds at most and a stop command's length (progress_table.py's
# MAX_TABLE_STOPS, MAX_STOP_COMMAND_BYTES).
MAX_STOPS = 1000
MAX_STOP_COMMAND_CHARS = 64
# A stop the file was read past is behind once the head is within this of it.
STOP_REACHED_S = 0.05
# The worker's answer is refused past this many bytes: the largest table the
# limits above allow is under 2 MiB with base64 (kestimator/worker.py answers
# at most its own MAX_ANSWER_BYTES, 3.5 MiB).
MAX_ANSWER_BYTES = 4 << 20
# Bytes read from the worker's pipes per callback.
READ_CHUNK = 1 << 16
# The end of the worker's stderr kept, to say why it stopped.
STDERR_TAIL_BYTES = 4096
# A request is never longer (the worker's own MAX_REQUEST_BYTES is 1 MiB).
MAX_REQUEST_BYTES = 1 << 20
# Events (exclusions, speed changes) kept per print; past this the module
# says it can no longer follow the print instead of growing.
MAX_EVENTS = 256
# A command typed during the print longer than this is not followed.
MAX_EVENT_CHARS = 2 * MAX_NAME_CHARS
# Worker restarts per print (after it stopped while an answer was awaited),
# and the wait before each.
MAX_RESTARTS = 3
RESTART_DELAYS = (2., 10., 30.)
# Anchors kept (print_time, table time) pending their move's planning.
MAX_PENDING_ANCHORS = 64
# Objects reported in the status at most (largest remaining first).
MAX_STATUS_OBJECTS = 64
# Commands that change the time of what follows (besides M220 and EXCLUDE_OBJECT): typed
# during a print, each is an event the rest of the file is estimated again with.
FOLLOWED_COMMANDS = ("SET_VELOCITY_LIMIT", "M204", "SET_PRESSURE_ADVANCE",
                     "SET_INPUT_SHAPER", "SET_RETRACTION")
# Every Klipper internal the module takes: (object, attribute path, needed). A path's
# first part may name alternatives (older releases' toolhead.move_queue). Checked at
# klippy:ready (the gcode ones when the section loads); a Klipper without one of them
# (a newer one that renamed or dropped it) gets one line in klippy.log and the status's
# `error` and `missing_hooks`, display_status stays exactly Klipper's, the print goes on.
# Beside these the module listens to the events klippy:ready, klippy:shutdown,
# klippy:disconnect, toolhead:sync_print_time and virtual_sdcard:reset_file, and appends
# to a queued move's `timing_callbacks` list (checked when first used).
KLIPPER_HOOKS: tuple[tuple[str, str, bool], ...] = (
    ("gcode", "run_script", True),
    ("gcode", "register_command", True),
    ("gcode", "register_output_handler", True),
    ("toolhead", "lookahead|move_queue.get_last", True),
    ("toolhead", "print_time", True),
    ("toolhead", "mcu.estimated_print_time", True),
    ("virtual_sdcard", "file_path", True),
    ("virtual_sdcard", "is_active", True),
    ("virtual_sdcard", "is_cmd_from_sd", True),
    ("virtual_sdcard", "file_position", True),
    ("virtual_sdcard", "cmd_from_sd", True),
    ("print_stats", "get_status", False),
    ("gcode_move", "get_status", False),
    ("display_status", "get_status", False),
)
# Worker niceness: estimating must never compete with Klipper for the CPU.
WORKER_NICE = 10
# `python3 -m kestimator.worker`. The build in the checkout's .venv-host (install.sh's,
# compiled where it could be) runs when it was built from the commit the checkout is on
# (.venv-host/kestimator-commit, written last by plugins/moonraker/build-venv); else (an
# update not built yet, or no venv) the checkout's own source: always the checkout's code.
WORKER_BOOT = """
import os, runpy, subprocess, sys
root = sys.argv.pop(1)
try:
    with open(os.path.join(root, ".venv-host", "kestimator-commit")) as f:
        built = f.read().strip()
    head = subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True,
                          text=True, timeout=30).stdout.strip()
except (OSError, subprocess.SubprocessError):
    built, head = "", "?"
if built and built == head:
    sys.path.append(root)
else:
    sys.path.insert(0, root)
runpy.run_module("kestimator.worker", run_name="__main__", alter_sys=True)
"""


def _repo_root() -> str:
    # plugins/klipper/kestimator.py in a kestimator checkout, linked into
    # klippy/extras/: the checkout is two folders above the real file.
    here = os.path.dirname(os.path.realpath(__file__))
    return os.path.dirname(os.path.dirname(here))


def default_python() -> str:
    """The Python that runs the worker: install.sh's virtualenv when there,
    else Klipper's own Python with the checkout on its path."""
    root = _repo_root()
    venv_python = os.path.join(root, ".venv-host", "bin", "python")
    if os.path.exists(venv_python):
        return venv_python
    return sys.executable


def _b64_chars(nbytes: int) -> int:
    return 4 * ((nbytes + 2) // 3)


def _decode_array(kind: str, text: Any, max_items: int,
                  what: str) -> array.array[Any]:
    """The machine array base64 `text` holds, refused past `max_items` items
    before anything is decoded."""
    out = array.array(kind)
    if not isinstance(text, str):
        raise ValueError("%s is not base64 text" % (what,))
    if len(text) > _b64_chars(max_items * out.itemsize):
        raise ValueError("more than %d %s" % (max_items, what))
    if text:
        out.frombytes(base64.b64decode(text, validate=True))
    return out


def _check_values(values: array.array[Any], what: str, low: float,
                  high: float | None = None, grow: bool = False) -> None:
    """All of `values` finite, within [low, high] and, with `grow`, in
    non-decreasing order (C-speed passes)."""
    if not len(values):
        return
    items = values.tolist()
    if not math.isfinite(sum(items)):
        raise ValueError("%s are not finite" % (what,))
    if grow:
        # (sorting what is already sorted is one pass)
        ordered = sorted(items)
        if items != ordered:
            raise ValueError("%s do not grow" % (what,))
        least, most = ordered[0], ordered[-1]
    else:
        least, most = min(items), max(items)
    if least < low or (high is not None and most > high):
        raise ValueError("%s are out of range" % (what,))


class Table:
    """One answer of the worker: byte offsets of line starts and the Klipper
    time at which every move on earlier lines has finished. Refused (ValueError)
    when it is not one: past the worker's own limits, or values that cannot be
    times."""

    def __init__(self, answer: dict[str, Any]) -> None:
        self.source = str(answer.get("source", "estimate"))[:20]
        total = answer.get("total_s")
        if (not isinstance(total, (int, float)) or isinstance(total, bool)
                or not math.isfinite(total) or total < 0.):
            raise ValueError("total_s is not a time")
        self.total_s = float(total)
        self.offsets = _decode_array("q", answer.get("offsets_b64", ""),
                                     MAX_TIME_POINTS, "time points")
        self.times = _decode_array("d", answer.get("times_b64", ""),
                                   MAX_TIME_POINTS, "time points")
        if len(self.offsets) != len(self.times) or not len(self.offsets):
            raise ValueError("table without points")
        _check_values(self.offsets, "offsets", 0, grow=True)
        _check_values(self.times, "times", 0., grow=True)
        names = answer.get("object_names") or []
        if not isinstance(names, list) or len(names) > MAX_OBJECTS:
            raise ValueError("more than %d objects" % (MAX_OBJECTS,))
        for name in names:
            if not isinstance(name, str) or len(name) > MAX_NAME_CHARS:
                raise ValueError("an object name is not a string of at most %d "
                                 "characters" % (MAX_NAME_CHARS,))
        self.object_names = list(names)
        # Klipper upper-cases object names; the file may not.
        self.object_keys = [name.upper() for name in names]
        self.object_offsets = _decode_array(
            "q", answer.get("object_offsets_b64", ""), MAX_OBJECT_POINTS,
            "object points")
        _check_values(self.object_offsets, "object offsets", 0, grow=True)
        n = len(self.object_offsets)
        flat = _decode_array("d", answer.get("object_remaining_b64", ""),
                             n * len(self.object_names), "object times")
        if len(flat) != n * len(self.object_names):
            raise ValueError("object table of the wrong size")
        _check_values(flat, "object times", 0.,
                      self.total_s * (1. + 1e-9) + 1e-6)
        self.object_remaining = [flat[i * n:(i + 1) * n]
                                 for i in range(len(self.object_names))]
        self._read_stops(answer)
        warnings = answer.get("warnings") or []
        if not isinstance(warnings, list):
            warnings = []
        self.warnings = [str(w)[:500] for w in warnings[:20]]
        # What the table holds in memory (its arrays), bytes.
        self.nbytes = sum(a.buffer_info()[1] * a.itemsize for a in
                          [self.offsets, self.times, self.object_offsets]
                          + self.object_remaining)

    def _read_stops(self, answer: dict[str, Any]) -> None:
        """The stops (where the print waits for a person): each one's byte offset,
        Klipper's time there, command and line (None when the answer has no lines)."""
        offsets = answer.get("stop_offsets") or []
        times = answer.get("stop_times") or []
        commands = answer.get("stop_commands") or []
        lines = answer.get("stop_lines")
        if not (isinstance(offsets, list) and isinstance(times, list)
                and isinstance(commands, list)) or len(offsets) > MAX_STOPS:
            raise ValueError("more than %d stops" % (MAX_STOPS,))
        if not len(offsets) == len(times) == len(commands):
            raise ValueError("stops of the wrong size")
        if not isinstance(lines, list) or len(lines) != len(offsets):
            lines = [None] * len(offsets)
        for offset, line in zip(offsets, lines):
            if not (_is_int(offset) and (line is None or _is_int(line))):
                raise ValueError("a stop's offset or line is not a whole number")
        for command in commands:
            if not isinstance(command, str) or len(command) > MAX_STOP_COMMAND_CHARS:
                raise ValueError("a stop's command is not a string of at most %d "
                                 "characters" % (MAX_STOP_COMMAND_CHARS,))
        self.stop_offsets = array.array("q", offsets)
        _check_values(self.stop_offsets, "stop offsets", 0, grow=True)
        for t in times:
            if not isinstance(t, (int, float)) or isinstance(t, bool):
                raise ValueError("a stop's time is not a number")
        self.stop_times = array.array("d", times)
        _check_values(self.stop_times, "stop times", 0.,
                      self.total_s * (1. + 1e-9) + 1e-6, grow=True)
        self.stop_commands = list(commands)
        self.stop_lines: list[int | None] = list(lines)

    def stop_after(self, position: int, passed: int) -> int:
        """The index of the first stop at or after file `position` and past the stop at
        offset `passed` (-1: none passed); len(stop_offsets) when no stop is left."""
        return max(bisect.bisect_left(self.stop_offsets, position),
                   bisect.bisect_right(self.stop_offsets, passed) if passed >= 0 else 0)

    def time_at(self, offset: int) -> float:
        """Table time at byte offset `offset`: that of the last point at or
        before it (exact at a point; between points the time lies between
        theirs, and the worker keeps them close; interpolating by bytes
        would guess wrong inside one long move)."""
        i = bisect.bisect_right(self.offsets, offset) - 1
        return self.times[max(0, i)]

    def objects_at(self, offset: int) -> dict[str, float]:
        """Each object's remaining seconds from byte offset `offset`."""
        if not self.object_names or not len(self.object_offsets):
            return {}
        j = bisect.bisect_right(self.object_offsets, offset) - 1
        j = max(0, j)
        return dict((name, self.object_remaining[i][j])
                    for i, name in enumerate(self.object_names))


class Worker:
    """The estimating process: JSON lines in, JSON lines out, read through
    the reactor without ever blocking it. Every callback it registers is
    wrapped in `guard`; what it reads per callback is bounded."""

    def __init__(self, reactor: Any, python: str,
                 guard: Callable[[Callable[..., Any]], Callable[..., Any]],
                 on_line: Callable[[bytes | None], Any],
                 on_exit: Callable[[str], Any]) -> None:
        self.reactor = reactor
        self.on_line = on_line
        self.on_exit = on_exit
        env = dict(os.environ)
        env["PYTHONDONTWRITEBYTECODE"] = "1"
        self.proc = subprocess.Popen(
            [python, "-c", WORKER_BOOT, _repo_root()], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            close_fds=True, env=env, cwd="/")
        try:
            os.setpriority(os.PRIO_PROCESS, self.proc.pid, WORKER_NICE)
        except (OSError, AttributeError):
            pass
        assert (self.proc.stdout is not None and self.proc.stdin is not None
                and self.proc.stderr is not None)
        self.out_fd = self.proc.stdout.fileno()
        self.in_fd = self.proc.stdin.fileno()
        self.err_fd = self.proc.stderr.fileno()
        for fd in (self.out_fd, self.in_fd, self.err_fd):
            os.set_blocking(fd, False)
        self.buf = bytearray()
        # Past MAX_ANSWER_BYTES: the rest of that line is dropped as it comes.
        self.skipping = False
        self.err_tail = bytearray()
        # A request not yet taken by the pipe (written as it empties).
        self.unsent = b""
        self.closed = False
        self.fd_handle: Any = reactor.register_fd(self.out_fd,
                                                  guard(self._readable))
        self.err_handle: Any = reactor.register_fd(self.err_fd,
                                                   guard(self._err_readable))

    def send(self, request: dict[str, Any]) -> None:
        data = (json.dumps(request, separators=(",", ":")) + "\n").encode()
        if len(data) > MAX_REQUEST_BYTES:
            raise ValueError("a request over %d bytes" % (MAX_REQUEST_BYTES,))
        self.unsent = data
        self.flush()

    def flush(self) -> bool:
        """Write what the pipe takes of the request; True once all is sent.
        OSError (BrokenPipeError: the worker stopped) for the caller."""
        while self.unsent:
            try:
                written = os.write(self.in_fd, self.unsent[:READ_CHUNK])
            except BlockingIOError:
                return False
            self.unsent = self.unsent[written:]
        return True

    def _readable(self, eventtime: float) -> None:
        if self.closed:
            return
        try:
            data = os.read(self.out_fd, READ_CHUNK)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._read_err()
            self.close()
            self.on_exit(self.cause())
            return
        if self.skipping:
            end = data.find(b"\n")
            if end < 0:
                return
            self.skipping = False
            data = data[end + 1:]
        start = len(self.buf)
        self.buf += data
        end = self.buf.find(b"\n", start)
        while end >= 0 and not self.closed:
            line = bytes(self.buf[:end])
            del self.buf[:end + 1]
            if line.strip():
                self.on_line(line)
            end = self.buf.find(b"\n")
        if len(self.buf) > MAX_ANSWER_BYTES:
            self.buf = bytearray()
            self.skipping = True
            self.on_line(None)

    def _err_readable(self, eventtime: float) -> None:
        self._read_err(1)

    def _read_err(self, reads: int = 16) -> None:
        """Keep the last STDERR_TAIL_BYTES of what the worker said on stderr."""
        for _ in range(reads):
            try:
                data = os.read(self.err_fd, READ_CHUNK)
            except OSError:
                return
            if not data:
                if self.err_handle is not None:
                    self.reactor.unregister_fd(self.err_handle)
                    self.err_handle = None
                return
            self.err_tail += data
            del self.err_tail[:-STDERR_TAIL_BYTES]

    def cause(self) -> str:
        """Why it stopped, on one line: the last line it said on stderr."""
        lines = [line.strip() for line in
                 bytes(self.err_tail).decode("utf-8", "replace").split("\n")]
        lines = [line for line in lines if line]
        code = self.proc.poll()
        status = "exit status %d" % (code,) if code is not None else "stopped"
        if lines:
            return "%s (%s)" % (lines[-1][:300], status)
        return status

    def close(self, kill: bool = False) -> None:
        """Stop it (`kill`: at once, SIGKILL, as when its work is of no use any more: it
        writes nothing but its answers)."""
        self.closed = True
        for attr in ("fd_handle", "err_handle"):
            handle = getattr(self, attr)
            if handle is not None:
                setattr(self, attr, None)
                try:
                    self.reactor.unregister_fd(handle)
                except Exception:
                    pass
        proc = self.proc
        for stream in (proc.stdin, proc.stdout, proc.stderr):
            try:
                if stream is not None:
                    stream.close()
            except Exception:
                pass
        if proc.poll() is None:
            try:
                if kill:
                    proc.kill()
                else:
                    proc.terminate()
            except OSError:
                pass
        # Reap it later without waiting now.
        self.reactor.register_callback(lambda e: self._reap())

    def _reap(self) -> None:
        try:
            self.proc.wait(timeout=0)
        except Exception:
            pass


class KlipperChangedError(Exception):
    """A hook the module takes from Klipper (KLIPPER_HOOKS) is missing or changed."""

    def __init__(self, missing: list[str]) -> None:
        self.missing = missing
        super().__init__(
            "Klipper's %s %s missing or changed (a Klipper newer than this module "
            "knows): not following prints; display_status is Klipper's own"
            % (", ".join(missing), "is" if len(missing) == 1 else "are"))


def _has_path(obj: Any, path: str) -> bool:
    """`obj` has the attribute `path` (dotted; a part may be alternatives, `a|b`)."""
    for part in path.split("."):
        for name in part.split("|"):
            if hasattr(obj, name):
                obj = getattr(obj, name)
                break
        else:
            return False
    return True


def missing_hooks(printer: Any, objects: tuple[str, ...] | None = None) -> list[str]:
    """The KLIPPER_HOOKS (of `objects`, default all) this Klipper lacks, as
    `object.path`; an optional object that is not configured lacks nothing."""
    missing = []
    for name, path, needed in KLIPPER_HOOKS:
        if objects is not None and name not in objects:
            continue
        obj = printer.lookup_object(name, None)
        if obj is None:
            if needed:
                missing.append(name)
        elif not _has_path(obj, path):
            missing.append("%s.%s" % (name, path))
    return missing


def running_klipper_version(printer: Any) -> str | None:
    """The Klipper this runs in as Moonraker's printer.info reports it: its start args'
    software_version, with the app's name first where it is not Klipper (Kalico's klippy
    package names itself in APP_NAME); None when unknown (absent, or Klipper's "?"). The
    worker takes it as the printer's klipper_version unless the user's settings name one."""
    try:
        version = printer.get_start_args().get("software_version")
        # "?": Klipper's own "unknown" (a tree without git or a .version file).
        if (not isinstance(version, str) or version.strip() in ("", "?")
                or len(version) > 100):
            return None
        package = sys.modules.get(type(printer).__module__.split(".")[0])
        app = getattr(package, "APP_NAME", None)
        if (isinstance(app, str) and app.isalnum() and app.lower() != "klipper"
                and not version.startswith(app)):
            version = "%s %s" % (app, version.strip())
        return version.strip()
    except Exception:  # noqa: BLE001 - a Klipper without it: the user's settings decide
        logging.exception("kestimator: the Klipper version is not known")
        return None


class Kestimator:
    """The [kestimator] section: status, updates, the worker."""

    def __init__(self, config: Any) -> None:
        self.printer = printer = config.get_printer()
        self.reactor = printer.get_reactor()
        python = config.get("python", None)
        self.python = os.path.expanduser(python) if python else default_python()
        self.use_table = config.getboolean("use_file_table", True)
        self.set_progress = config.getboolean("set_progress", True)
        self.display_next_stop = config.getboolean("display_next_stop", False)
        # The display message we set last (display_next_stop); another is the user's.
        self.shown_message: str | None = None
        self.interval = config.getfloat("update_interval", UPDATE_INTERVAL,
                                        minval=0.1, maxval=10.)
        start_args = printer.get_start_args()
        config_file = start_args.get("config_file")
        self.config_file = os.path.abspath(config_file) if config_file else None
        self.klipper_version = running_klipper_version(printer)
        self.gcode = printer.lookup_object("gcode")
        # The KLIPPER_HOOKS this Klipper lacks (then the module stays off).
        self.missing_hooks: list[str] = []
        # What the user left set before the print (state_before_print), taken when
        # virtual_sdcard resets for a new file.
        self.state_at_start: list[str] | None = None
        self.state_warnings: list[str] = []
        # Klipper's objects (klippy:ready).
        self.toolhead: Any = None
        self.vsd: Any = None
        self.print_stats: Any = None
        self.display_status: Any = None
        self.gcode_move: Any = None
        self.worker: Worker | None = None
        # The id of the request the worker is working on (at most one is sent at a
        # time: a change while it works is asked once it answers, with the latest
        # events), and whether this print's state changed since that request.
        self.in_flight: int | None = None
        # The file of the print followed (set by _reset_print).
        self.path: str | None = None
        self.want_request = False
        self.error: str | None = None
        self.disabled = False
        self.timer: Any = None
        # Restarts the worker after a back-off and writes a request the pipe
        # could not take at once.
        self.worker_timer = self.reactor.register_timer(self._worker_tick)
        self.retry_at: float | None = None
        self.max_callback_ms = 0.
        self.asked_at = 0.
        # Request ids keep counting across prints: a late answer for an earlier print
        # can never pass for this one's.
        self.request_id = 0
        # Wall clock = reactor time + this (for the ETA).
        self.wall_offset = time.time() - self.reactor.monotonic()
        # Clock in print_time: Klipper's estimate of where the head is now.
        self.now_print_time = self._est_print_time
        # The worker's answers arrive here (from the reactor's fd callback).
        self.on_answer = self._guard(self._handle_answer)
        self.on_line = self._guard(self._handle_line)
        self._reset_print(None)
        missing = missing_hooks(printer, ("gcode",))
        if missing:
            self._disable(KlipperChangedError(missing))
            return
        printer.register_event_handler("klippy:ready", self._guard(
            self._handle_ready))
        printer.register_event_handler("klippy:shutdown", self._guard(
            self._stop_worker))
        printer.register_event_handler("klippy:disconnect", self._guard(
            self._stop_worker))
        printer.register_event_handler("toolhead:sync_print_time", self._guard(
            self._handle_sync_print_time))
        printer.register_event_handler("virtual_sdcard:reset_file",
                                       self._guard(self._handle_reset_file))
        self.gcode.register_output_handler(self._guard(self._handle_output))
        self.gcode.register_command("KESTIMATOR_STATUS",
                                    self._guard(self.cmd_KESTIMATOR_STATUS,
                                                always=True),
                                    desc=self.cmd_KESTIMATOR_STATUS_help)

    # Never let anything out
    def _guard(self, func: Callable[..., Any],
               always: bool = False) -> Callable[..., Any]:
        """`func` made harmless: an exception disables the module; once
        disabled it no longer runs (unless `always`: the status command)."""
        def guarded(*args: Any, **kw: Any) -> Any:
            if self.disabled and not always:
                return None
            start = time.perf_counter()
            try:
                return func(*args, **kw)
            except Exception as e:
                self._disable(e)
            finally:
                ms = (time.perf_counter() - start) * 1000.
                if ms > self.max_callback_ms:
                    self.max_callback_ms = ms
            return None
        return guarded

    def _disable(self, exc: BaseException) -> None:
        if self.disabled:
            return
        self.disabled = True
        if isinstance(exc, KlipperChangedError):
            self.missing_hooks = list(exc.missing)
            self.error = str(exc)[:400]
            logging.warning("kestimator: %s", self.error)
        else:
            self.error = "%s: %s" % (type(exc).__name__, str(exc)[:200])
            logging.error("kestimator: disabled after an error: %s", self.error)
        try:
            self._stop_worker()
        except Exception:
            pass
        try:
            self.reactor.update_timer(self.worker_timer, self.reactor.NEVER)
        except Exception:
            pass

    def _worker_tick(self, eventtime: float) -> float:
        """The worker timer: restart a stopped worker when its back-off is
        over, write what the pipe did not take."""
        self._guard(self._worker_due)(eventtime)
        if self.disabled:
            return self.reactor.NEVER
        if self.worker is not None and self.worker.unsent:
            return eventtime + 0.05
        if self.retry_at is not None:
            return max(self.retry_at, eventtime + 0.05)
        return self.reactor.NEVER

    def _worker_due(self, eventtime: float) -> None:
        worker = self.worker
        if worker is not None and worker.unsent:
            try:
                worker.flush()
            except OSError as e:
                self._worker_failed("cannot write to it: %s" % (e,))
        if self.retry_at is not None and eventtime >= self.retry_at:
            self.retry_at = None
            self._send_if_idle()

    # Set-up
    def _handle_ready(self) -> None:
        missing = missing_hooks(self.printer)
        if missing:
            raise KlipperChangedError(missing)
        lookup = self.printer.lookup_object
        self.toolhead = lookup("toolhead")
        self.vsd = lookup("virtual_sdcard", None)
        self.print_stats = lookup("print_stats", None)
        self.display_status = lookup("display_status", None)
        self.gcode_move = lookup("gcode_move", None)
        if self.vsd is None:
            raise ValueError("needs [virtual_sdcard]")
        self._wrap("M220", self._after_M220)
        for name in FOLLOWED_COMMANDS:
            self._wrap(name, self._after_followed)
        if self.set_progress and self.display_status is not None:
            self._answer_display_status()
        self._hook_line_starts()
        self.timer = self.reactor.register_timer(self._update_timer,
                                                 self.reactor.NOW)
        # Start the worker now, outside a print (Popen takes milliseconds),
        # and keep it.
        self._start_worker()

    def _wrap(self, name: str, after: Callable[[Any], None]) -> None:
        """Run `after` once Klipper's own `name` has run (as gcode_macro's
        rename_existing keeps the original); our part can never fail it."""
        original = self.gcode.register_command(name, None)
        if original is None:
            return
        guarded_after = self._guard(after)

        def wrapper(gcmd: Any) -> None:
            original(gcmd)
            guarded_after(gcmd)
        try:
            self.gcode.register_command(name, wrapper)
        except Exception:
            self.gcode.register_command(name, original)
            raise

    def _hook_line_starts(self) -> None:
        """Anchor at the start of a line, where every earlier line's moves are queued.

        On a printer virtual_sdcard spends its waiting time inside a line (a G1 pauses in
        toolhead._check_pause with cmd_from_sd true), which is when the reactor runs our
        timer; and an arc, a macro or a bed-mesh split may have queued only part of that
        line's moves. So the timer only asks for an anchor, and it is taken just before
        virtual_sdcard hands Klipper its next line (gcode.run_script, which it calls once a
        line): a boolean test per line when none is wanted. A command typed at the console
        (run_script with cmd_from_sd false) is also a line boundary: anchored before it
        runs, so that a PAUSE's park move or a typed move never counts as the file's. A
        script called while Klipper's G-code mutex is held (a delayed_gcode or a typed
        command while virtual_sdcard waits inside a line: it runs once that line is done)
        is no line boundary: the line start after it anchors."""
        gcode = self.gcode
        original = gcode.run_script
        vsd = self.vsd
        anchor = self._guard(self._anchor_line_start)
        get_mutex = getattr(gcode, "get_mutex", None)
        mutex = get_mutex() if get_mutex is not None else None

        def run_script(script: str) -> Any:
            if ((self.want_anchor or not vsd.cmd_from_sd)
                    and (mutex is None or not mutex.test())):
                anchor()
            return original(script)
        gcode.run_script = run_script

    def _anchor_line_start(self) -> None:
        vsd = self.vsd
        if self.path is None or not vsd.is_active() or vsd.file_path() != self.path:
            return
        self.want_anchor = False
        self.anchor_here(vsd.file_position)

    def _stop_worker(self, kill: bool = False) -> None:
        worker, self.worker = self.worker, None
        self.in_flight = None
        if worker is not None:
            worker.close(kill)

    def _start_worker(self) -> Worker | None:
        """The worker, started if it is not running (None if it cannot be:
        the error says why)."""
        if self.worker is not None:
            return self.worker
        if self.path is not None:
            # It stopped since klippy:ready (or an earlier print).
            if self.restarts >= MAX_RESTARTS:
                self._fail("no more restarts of the worker for this print: %s"
                           % (self.error,))
                return None
            self.restarts += 1
            logging.info("kestimator: restarting the worker (restart %d of at "
                         "most %d for this print)", self.restarts, MAX_RESTARTS)
        return self._spawn_worker()

    def _spawn_worker(self) -> Worker | None:
        try:
            self.worker = Worker(self.reactor, self.python, self._guard,
                                 self.on_line, self._guard(self._worker_exit))
        except (OSError, ValueError, subprocess.SubprocessError) as e:
            self._worker_failed("cannot start it: %s: %s" % (
                type(e).__name__, str(e)[:200]))
            return None
        return self.worker

    def _worker_exit(self, cause: str) -> None:
        self._worker_failed(cause)

    def _worker_failed(self, cause: str) -> None:
        """The worker stopped (or cannot be used): say why; during a print
        that waits for an answer, start it again after a back-off."""
        worker, self.worker = self.worker, None
        if worker is not None:
            worker.close()
        waiting = self.in_flight is not None or self.want_request
        self.in_flight = None
        self.error = "the kestimator worker stopped (python: %s): %s" % (
            self.python, cause)
        if self.path is None or self.failed is not None or not waiting:
            logging.info("kestimator: %s", self.error)
            return
        if self.restarts >= MAX_RESTARTS:
            self._fail("%s; no more restarts for this print" % (self.error,))
            return
        self.want_request = True
        delay = RESTART_DELAYS[min(len(RESTART_DELAYS) - 1, self.restarts)]
        self.error += "; restarting it in %.0f s" % (delay,)
        logging.info("kestimator: %s", self.error)
        self.retry_at = self.reactor.monotonic() + delay
        self.reactor.update_timer(self.worker_timer, self.retry_at)

    def _reset_print(self, path: str | None) -> None:
        # A request still in flight is an earlier print's (cancelled, or another file):
        # the worker estimating it is stopped, so this print never waits behind it, and
        # a fresh one takes its place (not a restart: nothing went wrong).
        busy = getattr(self, "in_flight", None) is not None and self.worker is not None
        if busy:
            logging.info("kestimator: a new print: the estimate of %s is of no use any "
                         "more, its worker stopped", self.path)
            self._stop_worker(kill=True)
        self.path = path
        self.table: Table | None = None
        self.pending_id: int | None = None
        self.want_request = False
        self.retry_at = None
        # Why this print's time is no longer known (an error not retried).
        self.failed: str | None = None
        self.restarts = 0
        # The speed factor the table was estimated with.
        self.table_speed: float | None = None
        self.asked_speed: float | None = None
        self.events: list[tuple[int, str]] = []
        # (print_time, file position) last planned
        self.anchor: tuple[float, int] | None = None
        # Taken with nothing queued (its print_time may be before an idle gap), or
        # followed by one: the head's progress past it is not known from print_time.
        self.anchor_idle = False
        self.anchor_stale = False
        self.anchor_pending = 0
        # The update timer asks; the next line start (or typed command) anchors.
        self.want_anchor = False
        # ("speed", factor) or ("exclude", names) until the exact answer
        self.provisional: tuple[str, Any] | None = None
        self.excluded: list[str] = []
        self.speed_factor: float | None = None
        # The offset of the last stop the print paused at (-1: none yet).
        self.stop_passed = -1
        self.status = self._idle_status()
        if busy:
            self._spawn_worker()

    def _idle_status(self) -> dict[str, Any]:
        return {"state": "idle", "remaining_s": None, "eta": None,
                "progress": None, "total_s": None, "source": None,
                "objects": {}, "excluded_objects": [], "file": None,
                "error": self.error, "max_callback_ms": 0., "table_bytes": 0,
                "warnings": [], "next_stop": None,
                "missing_hooks": list(getattr(self, "missing_hooks", []))}

    def _unknown_status(self, state: str) -> dict[str, Any]:
        """The status when the time is not known (`error` says why)."""
        status = self._idle_status()
        status.update({"state": state, "file": getattr(self, "path", None),
                       "excluded_objects": list(getattr(self, "excluded", [])),
                       "max_callback_ms": round(self.max_callback_ms, 3)})
        return status

    def _fail(self, reason: str) -> None:
        """This print's time is no longer known (not retried): say why."""
        self.failed = self.error = reason
        self.table = None
        self.provisional = None
        self.want_request = False
        self.retry_at = None
        logging.warning("kestimator: %s", reason)
        self.status = self._unknown_status("error")

    # One print
    def _handle_reset_file(self) -> None:
        self._reset_print(None)
        # SDCARD_PRINT_FILE resets before it loads and starts the file: the state now is
        # the one the user left, before the file's own first line changes it.
        self.state_at_start = None
        if self.toolhead is not None:
            self.state_at_start = self.state_before_print(self.reactor.monotonic())
        if self.timer is not None:
            # A print is starting (SDCARD_PRINT_FILE): look at it as soon as it has.
            self.reactor.update_timer(self.timer, self.reactor.NOW)

    def _request(self) -> None:
        """Ask the worker for the file's table with every event so far: now
        if it is idle, else once it answers (only the latest state is asked)."""
        if self.path is None or self.failed is not None:
            return
        self.want_request = True
        self._send_if_idle()

    def _send_if_idle(self) -> None:
        if (not self.want_request or self.in_flight is not None
                or self.path is None or self.failed is not None
                or self.retry_at is not None):
            return
        worker = self._start_worker()
        if worker is None:
            return
        self.want_request = False
        self.request_id += 1
        self.pending_id = self.in_flight = self.request_id
        self.asked_at = self.reactor.monotonic()
        self.asked_speed = self.speed_factor
        try:
            worker.send({
                "id": self.request_id, "file": self.path,
                "config": self.config_file or None,
                "events": [[pos, text] for pos, text in self.events],
                "use_table": self.use_table and not self.events,
                "encoding": "b64",
                **({} if self.klipper_version is None
                   else {"klipper_version": self.klipper_version})})
        except OSError as e:
            # BrokenPipeError: it stopped before reading the request.
            self._worker_failed("cannot write to it: %s" % (e,))
            return
        if worker.unsent:
            self.reactor.update_timer(self.worker_timer,
                                      self.reactor.monotonic() + 0.05)

    def _handle_line(self, line: bytes | None) -> None:
        """One line the worker wrote (None: one over MAX_ANSWER_BYTES)."""
        if line is None:
            request_id, self.in_flight = self.in_flight, None
            if request_id is not None and request_id == self.pending_id:
                self._fail("the worker's answer was refused: it is too large "
                           "(over %d bytes)" % (MAX_ANSWER_BYTES,))
            self._send_if_idle()
            return
        try:
            answer = json.loads(line)
        except ValueError:
            answer = None
        if not isinstance(answer, dict):
            self._worker_failed("it wrote a line that is not JSON: %r" % (
                line[:80].decode("utf-8", "replace"),))
            return
        self._handle_answer(answer)

    def _handle_answer(self, answer: dict[str, Any]) -> None:
        request_id = answer.get("id")
        if request_id == self.in_flight:
            self.in_flight = None
        if (request_id != self.pending_id or request_id is None
                or self.want_request or self.failed is not None):
            # For an earlier print, or superseded: the latest state is asked.
            self._send_if_idle()
            return
        self.pending_id = None
        if not answer.get("ok"):
            # A file or config error: asking again would answer the same.
            self._fail("estimate failed: %s" % (
                str(answer.get("error", "?"))[:200],))
            return
        try:
            table = Table(answer)
        except (ValueError, TypeError) as e:
            self._fail("the worker's answer was refused: %s" % (str(e)[:200],))
            return
        self.table = table
        self.table_speed = self.asked_speed
        self.provisional = None
        self.error = None
        logging.info("kestimator: %s for %s: %d points, %.1f s in all, after %.2f s",
                     self.table.source, self.path, len(self.table.offsets),
                     self.table.total_s, self.reactor.monotonic() - self.asked_at)

    # Events typed during the print
    def _from_file(self) -> bool:
        return self.vsd is not None and self.vsd.is_cmd_from_sd()

    def _add_event(self, text: str) -> None:
        if self.path is None or self._from_file() or self.failed is not None:
            return
        position = self.vsd.file_position
        if len(text) > MAX_EVENT_CHARS:
            self._fail("a command over %d characters typed during the print "
                       "cannot be followed" % (MAX_EVENT_CHARS,))
            return
        last = self.events[-1] if self.events else None
        if last is not None and last[0] == position and (
                last[1] == text or (_is_m220(last[1]) and _is_m220(text))):
            # No line of the file ran in between: the same setting twice is
            # the setting once, and of two speed factors only the last counts.
            self.events[-1] = (position, text)
        elif len(self.events) >= MAX_EVENTS:
            self._fail("more than %d changes in one print: it is no longer "
                       "followed" % (MAX_EVENTS,))
            return
        else:
            self.events.append((position, text))
        self._request()

    def _after_M220(self, gcmd: Any) -> None:
        if self.gcode_move is None:
            return
        factor = self.gcode_move.get_status(
            self.reactor.monotonic())["speed_factor"]
        self.speed_factor = factor
        if self.path is None or self._from_file() or self.failed is not None:
            return
        # Scaled from the factor the table was estimated with (several
        # changes may come before it is estimated again).
        old = self.table_speed or 1.
        self.provisional = ("speed", old / factor if factor > 0. else 1.)
        self._add_event("M220 S%.10g" % (factor * 100.,))

    def _after_followed(self, gcmd: Any) -> None:
        """SET_VELOCITY_LIMIT and the like typed during the print: estimated again with
        the command as typed; the time stands (provisional) until then."""
        if self.path is None or self._from_file():
            return
        text = " ".join(str(gcmd.get_commandline()).split())
        if text and self.failed is None:
            self.provisional = ("changed", None)
            self._add_event(text)

    def _handle_output(self, msg: str) -> None:
        if self.path is None or not msg.startswith("// "):
            return
        text = msg[3:]
        for prefix, command in (("Excluding object ", "EXCLUDE_OBJECT NAME="),
                                ("Unexcluding object ",
                                 "EXCLUDE_OBJECT RESET=1 NAME=")):
            if text.startswith(prefix):
                name = text[len(prefix):].split("\n")[0].strip()
                if not name or self._from_file() or self.failed is not None:
                    return
                if command.startswith("EXCLUDE_OBJECT NAME"):
                    if name not in self.excluded:
                        self.excluded.append(name)
                        self.provisional = ("exclude", list(self.excluded))
                elif name in self.excluded:
                    self.excluded.remove(name)
                # Quoted as Klipper's gcode parser (shlex) reads NAME="it's"
                # and NAME='my part'; kestimator's interpreter reads it alike.
                self._add_event(command + shlex.quote(name))
                return

    # Time
    def _est_print_time(self, eventtime: float) -> float:
        return self.toolhead.mcu.estimated_print_time(eventtime)

    def anchor_here(self, position: int) -> None:
        """Note the print_time at which the moves queued so far end, with file
        `position` (the start of the next line to run): a timing callback on
        the last queued move, as register_lookahead_callback does, but never
        flushing or priming anything when the queue is empty."""
        if self.anchor_pending >= MAX_PENDING_ANCHORS:
            return
        toolhead = self.toolhead
        queue = getattr(toolhead, "lookahead", None)
        if queue is None:
            queue = getattr(toolhead, "move_queue", None)
        last = queue.get_last() if queue is not None else None
        if last is None:
            # Nothing queued: every earlier move ends at print_time. If the queue ran
            # dry, the next moves start when Klipper primes it again
            # (toolhead:sync_print_time), which moves this anchor there.
            self.anchor = (toolhead.print_time, position)
            self.anchor_idle = True
            self.anchor_stale = False
            return
        if not isinstance(getattr(last, "timing_callbacks", None), list):
            raise KlipperChangedError(["toolhead move.timing_callbacks"])
        self.anchor_pending += 1

        def planned(print_time: float, position: int = position) -> None:
            self.anchor_pending -= 1
            self.anchor = (print_time, position)
            self.anchor_idle = self.anchor_stale = False
        last.timing_callbacks.append(self._guard(planned))

    def _handle_sync_print_time(self, curtime: float, est_print_time: float,
                                print_time: float) -> None:
        """Klipper primed an empty queue again (after a heater wait, a pause, an M400):
        the head was idle until `print_time`, where the next moves start."""
        anchor = self.anchor
        if anchor is None or anchor[0] >= print_time:
            return
        if self.anchor_idle:
            # Taken with nothing queued: the moves from its position on start here.
            self.anchor = (print_time, anchor[1])
            self.anchor_idle = False
        else:
            # Moves after it ran, then the head idled: no longer a base to go on from;
            # the next line start anchors again.
            self.anchor_stale = True
            self.want_anchor = True

    def remaining_at(self, print_time: float) -> float | None:
        """Seconds of printing left when the head is at `print_time`.

        From the last anchor (position P, its moves ending at print_time A): the table's
        time from P to the end, plus what was queued ahead of the head (A - now). Past A,
        while the toolhead is still moving (the line in flight queues moves that no anchor
        has seen yet: an arc, a macro), the head is that much further into the table, but
        never past the end of the line being run; when the toolhead is idle (a heater wait,
        a pause) nothing is taken off."""
        left = self._table_left(print_time)
        table = self.table
        if left is None or table is None or self.anchor is None:
            return None
        position = self.anchor[1]
        provisional = self.provisional
        if provisional is not None and provisional[0] == "speed":
            left *= provisional[1]
        elif provisional is not None and provisional[0] == "exclude":
            # Klipper upper-cases object names; the file may not.
            gone = set(provisional[1])
            cut = sum([left for name, left in table.objects_at(position).items()
                       if name.upper() in gone])
            left = max(0., left - cut)
        return left

    def _table_left(self, print_time: float) -> float | None:
        """`remaining_at` as the table says it, before a provisional change."""
        table = self.table
        anchor = self.anchor
        if table is None or anchor is None:
            return None
        anchor_pt, position = anchor
        left = max(0., table.total_s - table.time_at(position))
        if anchor_pt >= print_time:
            left += anchor_pt - print_time
        elif not self.anchor_idle and not self.anchor_stale:
            moving_until = self._moving_until()
            if moving_until > anchor_pt:
                floor = max(0., table.total_s - table.time_at(self._line_end()))
                elapsed = min(print_time, moving_until) - anchor_pt
                left = max(min(left, floor), left - elapsed)
        return left

    def next_stop_at(self, print_time: float, eventtime: float,
                     paused: bool) -> dict[str, Any] | None:
        """The next stop (where the print waits for a person) with the head at
        `print_time`: its command, line, seconds until the head stands there (`in_s`,
        Klipper's time from the table, as `remaining_s`) and wall-clock `eta`; None when
        no stop is left or the time is not known. A stop the file has been read past is
        behind once the head has reached it by the table, or once the print was `paused`
        with the head standing (every planned move done) after it: it stays behind after
        the resume."""
        table = self.table
        left = self._table_left(print_time)
        if table is None or left is None or self.anchor is None:
            return None
        done = table.total_s - left
        n = len(table.stop_offsets)
        i = table.stop_after(self.anchor[1], self.stop_passed)
        position = int(self.vsd.file_position)
        standing = paused and self._head_stands(print_time)
        while i < n and table.stop_offsets[i] < position:
            if standing:
                self.stop_passed = int(table.stop_offsets[i])
            elif table.stop_times[i] > done + STOP_REACHED_S:
                break
            i += 1
        if i >= n:
            return None
        in_s = max(0., table.stop_times[i] - done)
        provisional = self.provisional
        if provisional is not None and provisional[0] == "speed":
            in_s *= provisional[1]
        return {"command": table.stop_commands[i], "line": table.stop_lines[i],
                "in_s": round(in_s, 3),
                "eta": round(self.wall_offset + eventtime + in_s, 3)}

    def _moving_until(self) -> float:
        """The print_time up to which the toolhead is known to move: the end of the
        moves Klipper has planned. Moves still in the look-ahead queue are not yet
        timed: after a heater wait or a pause they wait for Klipper to prime the queue
        again, and the head is idle meanwhile."""
        return float(self.toolhead.print_time)

    def _head_stands(self, print_time: float) -> bool:
        """Every move is planned (the look-ahead queue empty) and done by `print_time`."""
        toolhead = self.toolhead
        queue = getattr(toolhead, "lookahead", None)
        if queue is None:
            queue = getattr(toolhead, "move_queue", None)
        if queue is not None and queue.get_last() is not None:
            return False
        return print_time >= self._moving_until()

    def _line_end(self) -> int:
        """File position after the line virtual_sdcard is running (its start between
        lines): the head cannot be past it."""
        vsd = self.vsd
        if vsd.cmd_from_sd:
            return int(getattr(vsd, "next_file_position", vsd.file_position))
        return int(vsd.file_position)

    def status_at(self, print_time: float, eventtime: float) -> dict[str, Any]:
        """The status dict with the head at `print_time`."""
        table = self.table
        status = self._idle_status()
        status["file"] = self.path
        status["max_callback_ms"] = round(self.max_callback_ms, 3)
        status["excluded_objects"] = list(self.excluded)
        if self.path is None:
            return status
        if self.failed is not None:
            return self._unknown_status("error")
        state = "printing"
        if self.print_stats is not None:
            state = self.print_stats.get_status(eventtime)["state"]
        status["state"] = state if table is not None else "estimating"
        if table is None or state in ("cancelled", "error"):
            # Nothing is left to print (print_stats says why).
            return status
        status["table_bytes"] = table.nbytes
        status["warnings"] = list(table.warnings) + self.state_warnings
        remaining = self.remaining_at(print_time)
        if state == "complete" and remaining is None:
            remaining = 0.
        if remaining is None:
            return status
        status.update(self._time_fields(remaining, eventtime))
        status["next_stop"] = (None if state == "complete" else
                               self.next_stop_at(print_time, eventtime, state == "paused"))
        status["source"] = "provisional" if self.provisional else table.source
        # Keyed as Klipper names objects (upper-cased), as exclude_object's status does.
        at = table.objects_at(self.vsd.file_position)
        excluded = set(self.excluded)
        objects = {}
        for name, key in zip(table.object_names, table.object_keys):
            if name in at:
                objects[key] = (0. if state == "complete" or key in excluded
                                else at[name])
        ranked = sorted(objects.items(), key=lambda kv: -kv[1])
        status["objects"] = dict(
            (name, round(left, 3)) for name, left in ranked[:MAX_STATUS_OBJECTS])
        return status

    def _time_fields(self, remaining: float, eventtime: float) -> dict[str, Any]:
        """remaining_s, eta, total_s and progress with `remaining` seconds left."""
        total = self.table.total_s if self.table is not None else 0.
        return {"remaining_s": round(remaining, 3),
                "eta": round(self.wall_offset + eventtime + remaining, 3),
                "total_s": round(total, 3),
                "progress": round(min(1., max(0., 1. - remaining / total)), 6)
                if total > 0. else 1.}

    def _answer_display_status(self) -> None:
        """display_status answers with progress D / (D + R) while a print is followed.

        D is print_stats' print_duration and R the remaining time, both at the eventtime
        asked: webhooks asks every subscribed object with one eventtime per cycle, so the
        front ends' own arithmetic on that cycle, D / progress - D (Mainsail's "file"
        estimate with its progress from M73), gives R exactly, through pauses, heater
        waits, exclusions and speed changes; and the progress is the share of the print's
        time done. Klipper's own value (the file's M73, else the file position) is what
        display_status says at any other time, on any error, once the module is disabled,
        and with `set_progress: False` (then display_status is not touched at all)."""
        ds = self.display_status
        original = ds.get_status

        def get_status(eventtime: float) -> Any:
            status = original(eventtime)
            if self.disabled:
                return status
            try:
                progress = self.display_progress(eventtime)
            except Exception:
                return status
            if progress is None:
                return status
            status = dict(status)
            status["progress"] = progress
            return status
        ds.get_status = get_status

    def display_progress(self, eventtime: float) -> float | None:
        """D / (D + R) at `eventtime` while a print is followed with a known time, else
        None."""
        if (self.path is None or self.table is None or self.failed is not None
                or self.print_stats is None or self.anchor is None):
            return None
        stats = self.print_stats.get_status(eventtime)
        state = stats.get("state")
        if state not in ("printing", "paused", "complete"):
            return None
        remaining = self.remaining_at(self.now_print_time(eventtime))
        if remaining is None:
            return None
        duration = float(stats.get("print_duration", 0.))
        if duration + remaining <= 0.:
            return 1. if state == "complete" else 0.
        progress = duration / (duration + remaining)
        if state == "paused":
            # Paused, D and R stand still, and so would the progress: Mainsail would then
            # not recompute its ETA (a cached getter, now + D / progress - D), which must
            # move on with the clock. A change of one part in 1e12, every other cycle,
            # has it recomputed; its estimate moves by under a microsecond.
            if int(eventtime * 4.) % 2:
                progress *= 1. - 1e-12
        return progress

    def _update_timer(self, eventtime: float) -> float:
        self._guard(self.update)(eventtime)
        if self.disabled:
            return self.reactor.NEVER
        return eventtime + self.interval

    def update(self, eventtime: float) -> None:
        """Once per interval: follow the print, refresh status and progress."""
        vsd = self.vsd
        path = vsd.file_path() if vsd is not None else None
        if self.gcode_move is not None:
            factor = self.gcode_move.get_status(eventtime)["speed_factor"]
        else:
            factor = 1.
        if path is not None and vsd.is_active() and path != self.path:
            logging.info("kestimator: following the print of %s", path)
            self._reset_print(path)
            state, self.state_at_start = self.state_at_start, None
            if state is None:
                # Not started by SDCARD_PRINT_FILE (no reset seen): the state now.
                state = self.state_before_print(eventtime)
            for text in state:
                # Set at the console before the print: it applies to all of it.
                self.events.append((0, text))
            self._request()
        if self.provisional is None:
            self.speed_factor = factor
        if self.path is None:
            self.status = self._idle_status()
            return
        if not vsd.is_active() and self.print_stats is not None and self.anchor is not None:
            if (self.print_stats.get_status(eventtime)["state"] == "complete"
                    and self.anchor[1] != vsd.file_position):
                # The file is read to its end; its last moves may still run.
                self.anchor_here(vsd.file_position)
        if vsd.is_active():
            if vsd.is_cmd_from_sd():
                # Inside a line (a G1 waiting for the queue): anchor at the next line start.
                self.want_anchor = True
            else:
                self.want_anchor = False
                self.anchor_here(vsd.file_position)
        self.status = self.status_at(self.now_print_time(eventtime), eventtime)
        if self.display_next_stop and self.display_status is not None:
            self._show_next_stop()

    def _show_next_stop(self) -> None:
        """display_next_stop: the time to the next stop as display_status's message
        (M117's), never over a message the user set (shown again once it is cleared);
        cleared when no stop is left."""
        stop = self.status.get("next_stop")
        text = None
        if stop is not None and self.status.get("state") in ("printing", "paused"):
            text = "%s in %s" % (stop["command"], _duration(stop["in_s"]))
        ds = self.display_status
        current = getattr(ds, "message", None)
        if current is not None and current != self.shown_message:
            self.shown_message = None  # the user's message: left alone
            return
        if text != current:
            ds.message = text
        self.shown_message = text

    def state_before_print(self, eventtime: float) -> list[str]:
        """Commands that take the printer from its printer.cfg to the state it is in as a
        print starts (StateBeforePrint); a part that cannot be read is said in the
        status's warnings, never an error."""
        events, self.state_warnings = StateBeforePrint(self).read(eventtime)
        for warning in self.state_warnings:
            logging.warning("kestimator: %s", warning)
        return events

    def get_status(self, eventtime: float) -> dict[str, Any]:
        if self.disabled:
            status = self._unknown_status("error")
        else:
            status = dict(self.status)
            if status.get("remaining_s") is not None:
                # The time as of this eventtime, not the last update's: webhooks asks
                # every object with one eventtime per cycle (Moonraker's 250 ms), and
                # print_stats' duration in the same cycle is of this moment.
                try:
                    print_time = self.now_print_time(eventtime)
                    remaining = self.remaining_at(print_time)
                    if remaining is not None:
                        status.update(self._time_fields(remaining, eventtime))
                        if status.get("next_stop") is not None:
                            status["next_stop"] = self.next_stop_at(
                                print_time, eventtime, status.get("state") == "paused")
                except Exception:
                    pass
        status["error"] = self.error
        return status

    cmd_KESTIMATOR_STATUS_help = "Report kestimator's remaining print time"  # noqa: N815

    def cmd_KESTIMATOR_STATUS(self, gcmd: Any) -> None:
        status = self.get_status(self.reactor.monotonic())
        if status["error"]:
            gcmd.respond_info("kestimator: %s" % (status["error"],))
        if status["remaining_s"] is None:
            gcmd.respond_info("kestimator: %s" % (status["state"],))
            return
        gcmd.respond_info(
            "kestimator: %d s left of %d s (%.1f %%), source %s" % (
                status["remaining_s"], status["total_s"],
                status["progress"] * 100., status["source"]))



def _duration(seconds: float) -> str:
    """`1h 02m`, `9m 58s`, `42s`."""
    s = int(max(0., seconds) + 0.5)
    if s >= 3600:
        return "%dh %02dm" % (s // 3600, s % 3600 // 60)
    if s >= 60:
        return "%dm %02ds" % (s // 60, s % 60)
    return "%ds" % (s,)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 1 << 62


def _differ(live: Any, conf: Any) -> bool:
    try:
        return abs(float(live) - float(conf)) > 1e-9 * max(1., abs(float(conf)))
    except (TypeError, ValueError):
        return False


def _words(pairs: list[tuple[str, Any]]) -> str:
    return " ".join("%s=%.10g" % (word, float(value)) for word, value in pairs)


class StateBeforePrint:
    """What the user set at the console before a print, as commands: Mainsail's and
    Fluidd's limit and speed sliders, a Z offset, pressure advance, retraction and input
    shaper stay until a restart, and the print runs with them. Klipper's own status is
    compared with configfile's settings (printer.cfg as loaded, defaults included); each
    difference is one command, an event at the file's start."""

    def __init__(self, kest: Kestimator) -> None:
        self.kest = kest
        self.lookup = kest.printer.lookup_object

    def read(self, eventtime: float) -> tuple[list[str], list[str]]:
        """(commands, warnings): each part read on its own, so that one Klipper object
        laid out otherwise costs only its part, said in a warning."""
        configfile = self.lookup("configfile", None)
        settings: dict[str, Any] = {}
        if configfile is not None:
            settings = configfile.get_status(eventtime).get("settings", {})
        events: list[str] = []
        warnings = []
        for name, part in (("toolhead limits", self.toolhead),
                           ("speed, flow and offsets", self.gcode_move),
                           ("pressure advance", self.extruders),
                           ("firmware retraction", self.retraction),
                           ("input shaper", self.input_shaper)):
            try:
                events += part(eventtime, settings)
            except Exception as e:
                warnings.append("the %s set before the print could not be read (%s: %s); "
                                "the estimate uses printer.cfg's"
                                % (name, type(e).__name__, str(e)[:100]))
        return events, warnings

    def toolhead(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_VELOCITY_LIMIT (and M204)."""
        th = self.kest.toolhead.get_status(eventtime)
        printer_cfg = settings.get("printer", {})
        limits = [(word, th[key]) for key, word, default in (
            ("max_velocity", "VELOCITY", None), ("max_accel", "ACCEL", None),
            ("square_corner_velocity", "SQUARE_CORNER_VELOCITY", 5.),
            ("minimum_cruise_ratio", "MINIMUM_CRUISE_RATIO", .5))
            if key in th and _differ(th[key], printer_cfg.get(key, default))]
        return ["SET_VELOCITY_LIMIT " + _words(limits)] if limits else []

    def gcode_move(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """M220, M221, SET_GCODE_OFFSET."""
        events: list[str] = []
        if self.kest.gcode_move is None:
            return events
        gm = self.kest.gcode_move.get_status(eventtime)
        if _differ(gm.get("speed_factor", 1.), 1.):
            events.append("M220 S%.10g" % (gm["speed_factor"] * 100.,))
        if _differ(gm.get("extrude_factor", 1.), 1.):
            events.append("M221 S%.10g" % (gm["extrude_factor"] * 100.,))
        origin = list(gm.get("homing_origin", [0., 0., 0.]))[:3]
        offsets = [(axis, v) for axis, v in zip("XYZ", origin) if _differ(v, 0.)]
        if offsets:
            events.append("SET_GCODE_OFFSET " + _words(offsets))
        return events

    def extruders(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_PRESSURE_ADVANCE, per extruder."""
        events: list[str] = []
        for name, obj in self.kest.printer.lookup_objects():
            if (not name.startswith("extruder") or not name[8:].isdigit() and name[8:]
                    or not hasattr(obj, "get_status")):
                continue
            status = obj.get_status(eventtime)
            conf = settings.get(name, {})
            pa = [(word, status[key]) for key, word, option, default in (
                ("pressure_advance", "ADVANCE", "pressure_advance", 0.),
                ("smooth_time", "SMOOTH_TIME", "pressure_advance_smooth_time", .04))
                if key in status and _differ(status[key], conf.get(option, default))]
            if pa:
                events.append("SET_PRESSURE_ADVANCE EXTRUDER=%s %s" % (name, _words(pa)))
        return events

    def retraction(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_RETRACTION."""
        retraction = self.lookup("firmware_retraction", None)
        if retraction is None:
            return []
        status = retraction.get_status(eventtime)
        conf = settings.get("firmware_retraction", {})
        defaults = {"retract_length": 0., "retract_speed": 20.,
                    "unretract_extra_length": 0., "unretract_speed": 10.}
        changed = [(key.upper(), status[key]) for key in sorted(defaults)
                   if key in status and _differ(status[key], conf.get(key, defaults[key]))]
        return ["SET_RETRACTION " + _words(changed)] if changed else []

    def input_shaper(self, eventtime: float, settings: dict[str, Any]) -> list[str]:
        """SET_INPUT_SHAPER (input_shaper has no status: its shapers' parameters)."""
        shaper = self.lookup("input_shaper", None)
        if shaper is None:
            return []
        conf = settings.get("input_shaper", {})
        parts = []
        for axis_shaper in shaper.get_shapers():
            axis = str(axis_shaper.axis)
            params = axis_shaper.params
            live_type = str(params.shaper_type)
            conf_type = str(conf.get("shaper_type_" + axis,
                                     conf.get("shaper_type", "mzv"))).lower()
            if (_differ(params.shaper_freq, conf.get("shaper_freq_" + axis, 0.))
                    or _differ(params.damping_ratio, conf.get("damping_ratio_" + axis, .1))
                    or live_type != conf_type):
                parts.append("SHAPER_TYPE_%s=%s SHAPER_FREQ_%s=%.10g DAMPING_RATIO_%s=%.10g"
                             % (axis.upper(), live_type, axis.upper(), params.shaper_freq,
                                axis.upper(), params.damping_ratio))
        return ["SET_INPUT_SHAPER " + " ".join(parts)] if parts else []

def _is_m220(text: str) -> bool:
    return text.startswith("M220 ")


def load_config(config: Any) -> Kestimator:
    return Kestimator(config)
