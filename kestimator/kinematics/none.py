"""Mirrors klippy/kinematics/none.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `none` kinematics: no steppers, no limits, homing does nothing.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/none.py`
(GNU GPLv3): `check_move` accepts every move at the toolhead's own limits.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig
from kestimator.kinematics.base import Kinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits


class NoneKinematics(Kinematics):
    """Nothing to check."""

    name = "none"


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: none (needs no config)."""
    return NoneKinematics()
