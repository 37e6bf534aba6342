# kestimator: the [kestimator] section
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""The section's object: its settings, Klipper's objects at klippy:ready, the commands
it wraps, one print's state and the update timer that follows it.
"""
from __future__ import annotations

import logging
import os
import time
from typing import Any, Callable

from .events import Events
from .hooks import FOLLOWED_COMMANDS, KlipperChangedError, missing_hooks, running_klipper_version
from .state_before_print import StateBeforePrint
from .table import Table
from .worker import Worker, default_python

# Seconds of reactor time between updates.
UPDATE_INTERVAL = 0.5


class Kestimator(Events):
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


    def state_before_print(self, eventtime: float) -> list[str]:
        """Commands that take the printer from its printer.cfg to the state it is in as a
        print starts (StateBeforePrint); a part that cannot be read is said in the
        status's warnings, never an error."""
        events, self.state_warnings = StateBeforePrint(self).read(eventtime)
        for warning in self.state_warnings:
            logging.warning("kestimator: %s", warning)
        return events
