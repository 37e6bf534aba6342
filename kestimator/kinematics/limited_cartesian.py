"""Mirrors klippy/kinematics/limited_cartesian.py of Kalico v2026.07.00 (GNU GPLv3).

Kalico's `limited_cartesian` kinematics: cartesian's rails, ranges and homing, and per-axis
limits on every move: [printer] max_x_velocity / max_y_velocity / max_z_velocity (default
sqrt(2) x max_velocity, at most max_velocity when given) and max_x_accel / max_y_accel /
max_z_accel (default max_accel, at most max_accel), each divided by the move's share along
that axis; with scale_xy_accel the acceleration limit is scaled by the toolhead's current
acceleration over the hypotenuse of max_x_accel and max_y_accel. SET_KINEMATICS_LIMIT
X_VELOCITY= ... Z_ACCEL= SCALE= changes them during the print (its parameters are read by
`kestimator.toolhead.ToolHeadCommandHelper`, as gcode's getters live on the storey above).

Re-implemented from Kalico v2026.07.00 (30c65e09de06), `klippy/kinematics/limited_cartesian.py`
(Mael Kerbiriou, GNU GPLv3), beside Kalico's own cartesian.py, which is mainline's for what
is modelled here (the range checks and Z limits of `kestimator.kinematics.cartesian`).
"""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig, Section
from kestimator.kinematics.base import Kinematics
from kestimator.kinematics.cartesian import CartKinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move, ToolHead

EPSILON = sys.float_info.epsilon
SQRT2 = math.hypot(1.0, 1.0)


def kalico_getfloat(section: Section, option: str, default: float, *,
                    maxval: float | None = None) -> float:
    """configfile's getfloat as Kalico calls it here (above=0.): the bounds apply to a value
    the config gives, never to the default (configfile returns a default unchecked)."""
    if section.source(option) is None:
        return default
    return section.getfloat(option, above=0.0, maxval=maxval)


class LimitedCartKinematics(CartKinematics):
    """cartesian with per-axis velocity and acceleration limits."""

    name = "limited_cartesian"
    # The per-axis velocities' default (x max_velocity), and whether a given limit may not
    # pass max_velocity / max_accel (limited_corexz, a copy of this, differs in both).
    velocity_default_ratio = SQRT2
    bounded = True

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__(config, limits)
        printer = config.getsection("printer")
        max_velocity, max_accel = limits.max_velocity, limits.max_accel
        bounded = self.bounded
        self.max_velocities = [
            kalico_getfloat(printer, "max_%s_velocity" % ax,
                            self.velocity_default_ratio * max_velocity,
                            maxval=max_velocity if bounded else None) for ax in "xyz"]
        self.max_accels = [
            kalico_getfloat(printer, "max_%s_accel" % ax, max_accel,
                            maxval=max_accel if bounded else None) for ax in "xyz"]
        self.xy_hypot_accel = math.hypot(self.max_accels[0], self.max_accels[1])
        self.scale_per_axis = bool(printer.getboolean("scale_xy_accel", False))
        self.toolhead: ToolHead | None = None

    def attach_toolhead(self, toolhead: ToolHead) -> None:
        """Upstream's move.toolhead: the current acceleration, which scale_xy_accel reads."""
        self.toolhead = toolhead

    def kinematics_limits(self) -> tuple[list[float] | None, list[float], bool]:
        """What SET_KINEMATICS_LIMIT changes: the X, Y, Z velocity and acceleration limits
        and scale_xy_accel."""
        return list(self.max_velocities), list(self.max_accels), self.scale_per_axis

    def set_kinematics_limits(self, velocities: list[float] | None,
                              accels: list[float] | None, scale: bool | None) -> None:
        """SET_KINEMATICS_LIMIT (kestimator.toolhead reads its parameters): what is given."""
        if velocities is not None:
            self.max_velocities = velocities
        if accels is not None:
            self.max_accels = accels
            self.xy_hypot_accel = math.hypot(accels[0], accels[1])
        if scale is not None:
            self.scale_per_axis = scale

    def check_move(self, move: Move) -> None:
        """Range checks on every move, then the per-axis limits along the move."""
        if not move.is_kinematic_move:
            return
        self._check_endstops(move)
        x_r, y_r, z_r = move.axes_r_x, move.axes_r_y, move.axes_r_z
        x_max_v, y_max_v, z_max_v = self.max_velocities
        x_max_a, y_max_a, z_max_a = self.max_accels
        x_r = max(abs(x_r), EPSILON)
        y_r = max(abs(y_r), EPSILON)
        max_v = min(x_max_v / x_r, y_max_v / y_r)
        max_a = min(x_max_a / x_r, y_max_a / y_r)
        if self.scale_per_axis and self.toolhead is not None:
            max_a *= self.toolhead.max_accel / self.xy_hypot_accel
        if z_r:
            z_r = abs(z_r)
            max_v = min(max_v, z_max_v / z_r)
            max_a = min(max_a, z_max_a / z_r)
        move.limit_speed(max_v, max_a)


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: limited_cartesian (Kalico)."""
    return LimitedCartKinematics(config, limits)
