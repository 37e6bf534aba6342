# kestimator: nothing gets out
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""The base of the section's object: the guard every callback runs in (an exception
disables the module, never Klipper), and the state its parts share, declared once
(set in section.py).
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any, Callable

from .hooks import KlipperChangedError

if TYPE_CHECKING:
    from .table import Table
    from .worker import Worker


class Guarded:
    """What every part of the [kestimator] section stands on: `_guard`, `_disable`,
    `_stop_worker`, and the state they share (section.py sets it)."""

    # Klipper's objects and the section's settings (section.py's __init__).
    printer: Any
    reactor: Any
    gcode: Any
    toolhead: Any
    vsd: Any
    print_stats: Any
    display_status: Any
    gcode_move: Any
    python: str
    use_table: bool
    display_next_stop: bool
    shown_message: str | None
    config_file: str | None
    klipper_version: str | None
    missing_hooks: list[str]
    state_warnings: list[str]
    # The worker and the requests (section.py's __init__).
    worker: Worker | None
    worker_timer: Any
    in_flight: int | None
    request_id: int
    asked_at: float
    retry_at: float | None
    want_request: bool
    on_line: Callable[..., Any]
    error: str | None
    disabled: bool
    max_callback_ms: float
    wall_offset: float
    now_print_time: Callable[[float], float]
    # One print (section.py's _reset_print).
    path: str | None
    table: Table | None
    pending_id: int | None
    failed: str | None
    restarts: int
    table_speed: float | None
    asked_speed: float | None
    events: list[tuple[int, str]]
    anchor: tuple[float, int] | None
    anchor_idle: bool
    anchor_stale: bool
    anchor_pending: int
    want_anchor: bool
    provisional: tuple[str, Any] | None
    excluded: list[str]
    speed_factor: float | None
    stop_passed: int
    status: dict[str, Any]

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

    def _stop_worker(self, kill: bool = False) -> None:
        worker, self.worker = self.worker, None
        self.in_flight = None
        if worker is not None:
            worker.close(kill)
