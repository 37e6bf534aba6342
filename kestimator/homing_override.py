"""Mirrors klippy/extras/homing_override.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's [homing_override]: a G28 that homes one of its `axes` declares the head at
`set_position_<axis>` and runs the section's gcode instead of homing; a G28 inside that
gcode homes as G28 would.

Re-implemented from mainline Klipper at commit 84104bbbd,
`klippy/extras/homing_override.py` (GNU GPLv3). Names follow upstream.

kestimator runs the gcode when it is literal (no Jinja, as literal [gcode_macro]s): its
commands take the time they take anywhere else, its G28s none. A template is not rendered:
G28 then homes the axes it names as it would without the override, and a warning says so.
Moonraker's settings are read without the gcode (its text is never taken from Moonraker,
as a macro's), which is then a template not known.
"""

from __future__ import annotations

from collections.abc import Callable

from kestimator.config.machine import Section
from kestimator.gcode import Command
from kestimator.toolhead import ToolHead

Handler = Callable[[Command], None]
WarnFn = Callable[[str, "str | None"], None]

WARN_KEY = "homing_override"


def is_literal(template: str) -> bool:
    """Whether a gcode template is plain G-code (nothing for Jinja to render)."""
    return bool(template.strip()) and "{" not in template and "%" not in template


class HomingOverride:
    """[homing_override]: G28 runs the section's gcode."""

    def __init__(self, config: Section, toolhead: ToolHead, prev_G28: Handler,
                 run_script: Callable[[str], None], on_set_position: Callable[[], None],
                 warn: WarnFn) -> None:
        self.toolhead = toolhead
        # getfloat(option, None): None when the option is absent.
        self.start_pos = [config.getfloat("set_position_" + a)
                          if config.get("set_position_" + a, None) is not None else None
                          for a in "xyz"]
        self.axes = (config.get("axes", "XYZ") or "XYZ").upper()
        # None: not known (Moonraker's settings).
        self.template = config.get("gcode", None)
        self.in_script = False
        # The G28 this one replaces (homing.py's, or safe_z_home's).
        self.prev_G28 = prev_G28
        self.run_script = run_script
        # gcode_move's toolhead:set_position handler (reset_last_position).
        self.on_set_position = on_set_position
        self.warn = warn

    def cmd_G28(self, cmd: Command) -> None:
        """G28: the override's gcode when it homes one of `axes`, else a plain G28."""
        if self.in_script:
            # Was called recursively - invoke the real G28 command
            self.prev_G28(cmd)
            return

        # if no axis is given as parameter we assume the override
        no_axis = not any(axis in cmd.params for axis in "XYZ")
        if no_axis:
            override = True
        else:
            # check if we home an axis which needs the override
            override = any(axis in cmd.params for axis in self.axes)

        if not override:
            self.prev_G28(cmd)
            return

        template = self.template
        if template is None or not is_literal(template):
            self.warn("G28 runs [homing_override]'s gcode, %s: G28 is taken to home the axes "
                      "it names as without the override; where the override leaves the head "
                      "and the time its moves take may differ"
                      % ("not known from Moonraker's settings" if template is None
                         else "a template kestimator does not render"), WARN_KEY)
            self.prev_G28(cmd)
            return
        self.warn("G28 runs [homing_override]'s gcode: its commands are run (its G28s "
                  "take no time, its moves take theirs)", WARN_KEY)

        # Calculate forced position (if configured)
        toolhead = self.toolhead
        pos = list(toolhead.commanded_pos)
        homing_axes = ""
        for axis, loc in enumerate(self.start_pos):
            if loc is not None:
                pos[axis] = loc
                homing_axes += "xyz"[axis]
        toolhead.set_position((pos[0], pos[1], pos[2], pos[3]), homing_axes)
        self.on_set_position()
        # Perform homing
        try:
            self.in_script = True
            self.run_script(template)
        finally:
            self.in_script = False
