"""The stand-in for a printer whose [printer] / [stepper_*] sections are not known (no
printer.cfg or Moonraker, or one lacking them), or whose kinematics mainline Klipper does not
ship: it applies only the Z speed limit (scaled along Z where the kinematics does), checks no
range, homes to 0, and its warning says so (never a silent number).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.kinematics.base import Kinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move


class StandInKinematics(Kinematics):
    """The Z speed limit only (``z_rule``: "scaled" along Z as the rail-based kinematics,
    delta, deltesian and polar do; "velocity", rotary_delta's cap of the velocity alone; or
    None), no range checks, G28 homes to 0."""

    def __init__(self, name: str, limits: Limits, z_rule: str | None,
                 warning: str | None) -> None:
        super().__init__()
        self.name = name
        self.z_rule = z_rule
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        if warning is not None:
            self.warnings.append(warning)
            self.unchecked = warning

    def homed_axes(self) -> str:
        """Homing is not tracked without the steppers: every axis counts as homed."""
        return "xyz"

    def check_move(self, move: Move) -> None:
        """Z moves limited as the kinematics limits them."""
        if not move.axes_d_z or self.z_rule is None:
            return
        if self.z_rule == "velocity":
            move.limit_speed(self.max_z_velocity, move.accel)
            return
        z_ratio = move.move_d / abs(move.axes_d_z)
        move.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
