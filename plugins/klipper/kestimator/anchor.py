# kestimator: anchoring on Klipper's clock
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""The table anchored on Klipper's print_time at line starts, and the time left (to the
end and to the next stop) with the head at a print_time.
"""
from __future__ import annotations

from typing import Any

from .guard import Guarded
from .hooks import KlipperChangedError

# A stop the file was read past is behind once the head is within this of it.
STOP_REACHED_S = 0.05
# Anchors kept (print_time, table time) pending their move's planning.
MAX_PENDING_ANCHORS = 64


class Anchoring(Guarded):
    """The anchor: the print_time at which the moves of the lines before a file
    position end, and what it says of the time left."""

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
