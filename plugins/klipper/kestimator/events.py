# kestimator: what is typed during a print
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""Commands typed during a print that change the time of what follows (M220, an
exclusion, the FOLLOWED_COMMANDS): each an event the rest of the file is estimated
again with, the time provisional until then.
"""
from __future__ import annotations

import shlex
from typing import Any

from .estimates import Estimates
from .table import MAX_NAME_CHARS

# Events (exclusions, speed changes) kept per print; past this the module
# says it can no longer follow the print instead of growing.
MAX_EVENTS = 256
# A command typed during the print longer than this is not followed.
MAX_EVENT_CHARS = 2 * MAX_NAME_CHARS


class Events(Estimates):
    """The events of a print, as typed at the console."""

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


def _is_m220(text: str) -> bool:
    return text.startswith("M220 ")
