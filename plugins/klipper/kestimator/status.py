# kestimator: status and display
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""printer.kestimator's status, display_status's progress while a print is followed,
the next stop as the display's message, and KESTIMATOR_STATUS.
"""
from __future__ import annotations

from typing import Any

from .anchor import Anchoring

# Objects reported in the status at most (largest remaining first).
MAX_STATUS_OBJECTS = 64


class Status(Anchoring):
    """What the section says: its status, display_status's progress, the message."""

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
