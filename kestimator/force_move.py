"""Mirrors klippy/extras/force_move.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `ForceMove`, which every kinematics loads: STEPPER_BUZZ for each stepper always
(kestimator.klipper_commands), and only with `[force_move] enable_force_move: True` also
SET_KINEMATIC_POSITION and FORCE_MOVE (`ForceMove.__init__`, `register_stepper`). Without it
Klipper answers both with "Unknown command" and the head's position stays as it was, so a
file that sets the position on such a printer must not move it here either.

SET_KINEMATIC_POSITION's handler is the interpreter's (`Interpreter.cmd_SET_KINEMATIC_POSITION`,
`ForceMove.cmd_SET_KINEMATIC_POSITION`); FORCE_MOVE drives one stepper outside the toolhead
and is not timed (a known command whose time is not counted).

Re-implemented from mainline Klipper at commit 84104bbbd (GNU GPLv3). Names follow upstream.
"""

from __future__ import annotations

from kestimator.config.machine import MachineConfig

# The commands ForceMove registers only with enable_force_move.
FORCE_MOVE_COMMANDS = ("SET_KINEMATIC_POSITION", "FORCE_MOVE")


def enabled_force_move_commands(config: MachineConfig | None) -> frozenset[str]:
    """FORCE_MOVE_COMMANDS when the printer's [force_move] says enable_force_move: True; none
    when it does not, or when the printer's config is not known."""
    if config is None:
        return frozenset()
    section = config.section("force_move")
    if section is None or not section.getboolean("enable_force_move", False):
        return frozenset()
    return frozenset(FORCE_MOVE_COMMANDS)
