# kestimator: what the module takes from Klipper
#
# Copyright (C) 2026 the kestimator authors
#
# This file may be distributed under the terms of the GNU GPLv3 license
# (GPL-3.0-or-later).
"""Every Klipper internal the module takes, listed once for every release it runs in
(KLIPPER_HOOKS, the commands it follows), the check that a Klipper still has them,
and the Klipper version it runs in.
"""
from __future__ import annotations

import logging
import sys
from typing import Any

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
