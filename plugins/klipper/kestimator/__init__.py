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
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later). It re-implements no Klipper code; it reads Klipper's
# objects through the interfaces hooks.py lists.
"""The package Klipper loads for a [kestimator] section (as `extras.kestimator`; Kalico
as `klippy.extras.kestimator`): `load_config`, which makes the section's object.

Its files, one concern each: hooks.py (what the module takes from Klipper, every
release), table.py (the worker's answer), worker.py (the worker process and its pipe),
guard.py (nothing gets out; the state the parts share), anchor.py (the table anchored
on Klipper's print_time), status.py (printer.kestimator and display_status),
estimates.py (asking the worker), events.py (what is typed during a print),
state_before_print.py (what was set before it) and section.py (the section: set-up and
the update timer).
"""
from __future__ import annotations

from typing import Any

from . import section


def load_config(config: Any) -> section.Kestimator:
    return section.Kestimator(config)
