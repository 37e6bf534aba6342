"""Mirrors klippy/kinematics/corexz.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `corexz` kinematics.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/corexz.py`
(GNU GPLv3): the same rails, ranges and Z limits as cartesian (its `check_move`,
`set_position` and homing positions are cartesian's), without [dual_carriage].
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig
from kestimator.kinematics.base import Kinematics
from kestimator.kinematics.cartesian import CartKinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits


class CoreXZKinematics(CartKinematics):
    """Rails stepper_x/y/z; motor mixing does not change the limits."""

    name = "corexz"
    dual_carriage_axes: tuple[str, ...] = ()


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: corexz."""
    return CoreXZKinematics(config, limits)
