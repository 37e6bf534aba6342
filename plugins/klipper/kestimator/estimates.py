# kestimator: asking the worker
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""The worker of a print: one request at a time with the latest events, its answers,
restarts after a back-off when it stops, and a print's time given up for good.
"""
from __future__ import annotations

import json
import logging
import subprocess
from typing import Any

from .status import Status
from .table import Table
from .worker import MAX_ANSWER_BYTES, Worker

# Worker restarts per print (after it stopped while an answer was awaited),
# and the wait before each.
MAX_RESTARTS = 3
RESTART_DELAYS = (2., 10., 30.)


class Estimates(Status):
    """The requests to the worker and its answers."""

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

    def _fail(self, reason: str) -> None:
        """This print's time is no longer known (not retried): say why."""
        self.failed = self.error = reason
        self.table = None
        self.provisional = None
        self.want_request = False
        self.retry_at = None
        logging.warning("kestimator: %s", reason)
        self.status = self._unknown_status("error")

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
