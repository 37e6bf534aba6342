"""Mirrors klippy/kinematics/limited_corexy.py of Kalico v2026.07.00 (GNU GPLv3).

Kalico's `limited_corexy` kinematics: corexy's rails, ranges, homing and Z limits, and the
XY acceleration limited per axis: [printer] max_x_accel / max_y_accel (default max_accel)
bound the acceleration along the move through the A and B motors' mixing; with
scale_xy_accel they are scaled by the toolhead's current acceleration over the larger of the
two. XY velocity is max_velocity scaled by the move's length over its largest motor share.
SET_KINEMATICS_LIMIT X_ACCEL= Y_ACCEL= Z_ACCEL= SCALE= changes them during the print (its
parameters are read by `kestimator.toolhead.ToolHeadCommandHelper`), as does Kalico's
SET_VELOCITY_LIMIT X_ACCEL= ... Z_VELOCITY= (max_z_velocity and max_z_accel are corexy's).

Re-implemented from Kalico v2026.07.00 (30c65e09de06), `klippy/kinematics/limited_corexy.py`
(Mael Kerbiriou, GNU GPLv3).
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig
from kestimator.kinematics.base import Kinematics
from kestimator.kinematics.corexy import CoreXYKinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move, ToolHead

EPSILON = 2 * sys.float_info.epsilon


class LimitedCoreXYKinematics(CoreXYKinematics):
    """corexy with per-axis XY acceleration limits."""

    name = "limited_corexy"

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__(config, limits)
        printer = config.getsection("printer")
        max_accel = limits.max_accel
        self.max_x_accel = (max_accel if printer.source("max_x_accel") is None
                            else printer.getfloat("max_x_accel", above=0.0))
        self.max_y_accel = (max_accel if printer.source("max_y_accel") is None
                            else printer.getfloat("max_y_accel", above=0.0))
        self.scale_per_axis = bool(printer.getboolean("scale_xy_accel", False))
        self.toolhead: ToolHead | None = None

    def attach_toolhead(self, toolhead: ToolHead) -> None:
        """Upstream's move.toolhead: its current velocity and acceleration."""
        self.toolhead = toolhead

    def kinematics_limits(self) -> tuple[list[float] | None, list[float], bool]:
        """What SET_KINEMATICS_LIMIT changes: no velocities, the X, Y, Z accelerations and
        scale_xy_accel."""
        return None, [self.max_x_accel, self.max_y_accel, self.max_z_accel], self.scale_per_axis

    def set_kinematics_limits(self, velocities: list[float] | None,
                              accels: list[float] | None, scale: bool | None) -> None:
        """SET_KINEMATICS_LIMIT: what is given (there are no velocities to set)."""
        if accels is not None:
            self.max_x_accel, self.max_y_accel, self.max_z_accel = accels
        if scale is not None:
            self.scale_per_axis = scale

    def check_move(self, move: Move) -> None:
        """Range checks on every move, then the A/B motor limits and corexy's Z limits."""
        if not move.is_kinematic_move:
            return
        self._check_endstops(move)
        toolhead = self.toolhead
        assert toolhead is not None
        max_v, max_a = toolhead.max_velocity, toolhead.max_accel
        move_d = move.move_d
        x, y, z = move.axes_d_x, move.axes_d_y, move.axes_d_z
        ab_linf = max(abs(x + y), abs(x - y))
        if ab_linf > EPSILON:
            max_v *= move_d / ab_linf
            max_x_accel = self.max_x_accel
            max_y_accel = self.max_y_accel
            x_o_a = x / max_x_accel
            y_o_a = y / max_y_accel
            if self.scale_per_axis:
                max_a *= move_d / (max(abs(x_o_a + y_o_a), abs(x_o_a - y_o_a))
                                   * max(max_x_accel, max_y_accel))
            else:
                max_a = move_d / max(abs(x_o_a + y_o_a), abs(x_o_a - y_o_a))
        if z:
            z_ratio = move_d / abs(z)
            max_v = min(max_v, self.max_z_velocity * z_ratio)
            max_a = min(max_a, self.max_z_accel * z_ratio)
        move.limit_speed(max_v, max_a)


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: limited_corexy (Kalico)."""
    return LimitedCoreXYKinematics(config, limits)
