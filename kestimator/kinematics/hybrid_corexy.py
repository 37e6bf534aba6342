"""Mirrors klippy/kinematics/hybrid_corexy.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `hybrid_corexy` (Markforged) kinematics.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/hybrid_corexy.py`
(GNU GPLv3): the same rails, ranges and Z limits as cartesian; [dual_carriage] is on X only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig
from kestimator.kinematics.base import Kinematics
from kestimator.kinematics.cartesian import CartKinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits


class HybridCoreXYKinematics(CartKinematics):
    """Rails stepper_x/y/z (and an optional [dual_carriage] on X)."""

    name = "hybrid_corexy"
    dual_carriage_axes: tuple[str, ...] = ("x",)


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: hybrid_corexy."""
    return HybridCoreXYKinematics(config, limits)
