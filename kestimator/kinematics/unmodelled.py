"""Stand-ins for kinematics whose own rules kestimator does not model yet, and for printers
whose [stepper_*] sections are not known.

`rotary_delta` (mainline Klipper 84104bbbd, `klippy/kinematics/rotary_delta.py`) checks a
build radius and height and homes to the top, which are not reproduced here; its Z moves are
capped at max_z_velocity (velocity only). The stand-in does that, checks no range, homes to 0,
and always says so in a warning: never a silent number.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.kinematics.base import Kinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.planner import Move

WHAT_IS_MISSING = {
    "rotary_delta": "its build radius and height, homing to the top and its Z speed rule",
}


class UnmodelledKinematics(Kinematics):
    """Z speed limits only, with a warning naming what is not modelled."""

    def __init__(self, name: str, limits: Limits, reason: str) -> None:
        super().__init__()
        self.name = name
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        self.scale_z = name != "rotary_delta"
        self.warnings.append(
            "[printer] kinematics: %s: kestimator does not model %s (%s): moves are not "
            "range-checked, G28 homes to 0 and only its Z speed limit is applied, so times "
            "may be off" % (name, WHAT_IS_MISSING.get(name, "its rules"), reason))

    def check_move(self, move: Move) -> None:
        """The Z speed limit Klipper applies to this kinematics."""
        if not move.axes_d[2]:
            return
        if self.scale_z:
            z_ratio = move.move_d / abs(move.axes_d[2])
            move.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
        else:
            move.limit_speed(self.max_z_velocity, move.accel)


class StandInKinematics(Kinematics):
    """Without the printer's [stepper_*] sections: the Z speed limit (scaled along Z, as the
    rail-based kinematics and delta do), no range checks, G28 homes to 0."""

    def __init__(self, name: str, limits: Limits, z_limited: bool,
                 warning: str | None) -> None:
        super().__init__()
        self.name = name
        self.z_limited = z_limited
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        if warning is not None:
            self.warnings.append(warning)

    def check_move(self, move: Move) -> None:
        """Z moves slowed to max_z_velocity/accel along Z (when the kinematics does)."""
        if self.z_limited and move.axes_d[2]:
            z_ratio = move.move_d / abs(move.axes_d[2])
            move.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
