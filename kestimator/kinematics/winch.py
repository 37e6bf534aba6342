"""Mirrors klippy/kinematics/winch.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `winch` (cable winch) kinematics: no range checks and no speed limits.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/winch.py`
(GNU GPLv3): its `check_move` does nothing (boundary checks and speed limits are not
implemented upstream either), and homing is not implemented (G28 declares the head at
X=Y=Z=0, as the oracle's homing stand-in does).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig
from kestimator.kinematics.base import Kinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits


class WinchKinematics(Kinematics):
    """Anchors stepper_a..; no limits of its own (not even Z's)."""

    name = "winch"

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__()
        for i in range(26):
            name = "stepper_" + chr(ord("a") + i)
            if i >= 3 and not config.has_section(name):
                break
            section = config.getsection(name)
            for axis in "xyz":
                section.getfloat("anchor_" + axis)


    def homed_axes(self) -> str:
        """Always all of them: upstream implements no homing checks (get_status)."""
        return "xyz"


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: winch."""
    return WinchKinematics(config, limits)
