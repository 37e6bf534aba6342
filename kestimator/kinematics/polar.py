"""Mirrors klippy/kinematics/polar.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `polar` kinematics: a rotating bed (stepper_bed), an arm (stepper_arm) and Z.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/polar.py`
(GNU GPLv3). The XY range is a disc of radius stepper_arm's position_max; Z has its rail's
range and max_z_velocity/accel; with [printer] max_angular_velocity, moves passing near the
centre are slowed so the bed turns no faster than that (scaling the configured max_velocity
and max_accel).

G28 homes X and Y together (the arm to its position_endstop, Y to 0) and Z to stepper_z's
position_endstop, as Klipper's `PolarKinematics.home` does.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig, lookup_rail
from kestimator.kinematics.base import (
    Kinematics,
    Position,
)

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move


def distance_to_center(p1: tuple[float, float], p2: tuple[float, float]) -> float:
    """Distance from (0, 0) to the segment p1-p2."""
    ab_x = p2[0] - p1[0]
    ab_y = p2[1] - p1[1]
    ap_x = -p1[0]
    ap_y = -p1[1]
    ab_ap_dot_product = ab_x * ap_x + ab_y * ap_y
    # Squares of positions from the file: math.pow (upstream: x**2), the same bits, and an
    # overflow raises on PyPy as it does on CPython, where PyPy's ** would give inf.
    ab_length = math.sqrt(math.pow(ab_x, 2.0) + math.pow(ab_y, 2.0))
    # Check if the projected point lies on the bounded line segment
    if ab_ap_dot_product <= 0:
        dist = math.sqrt(math.pow(ap_x, 2.0) + math.pow(ap_y, 2.0))
    elif ab_ap_dot_product >= math.pow(ab_length, 2.0):
        dist = math.sqrt(math.pow(p2[0], 2.0) + math.pow(p2[1], 2.0))
    else:
        dist = abs(ab_x * ap_y - ab_y * ap_x) / ab_length
    return dist


class PolarKinematics(Kinematics):
    """stepper_bed (radians), stepper_arm (radius) and stepper_z."""

    name = "polar"

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__()
        printer = config.getsection("printer")
        config.getsection("stepper_bed")
        self.rails = [lookup_rail(config, "stepper_arm"), lookup_rail(config, "stepper_z")]
        self.max_velocity, self.max_accel = limits.max_velocity, limits.max_accel
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        # 0 (the default, as Moonraker reports it) is off.
        self.v_rad_max = printer.getfloat("max_angular_velocity", 0.0, minval=0.0)
        self.limit_z = (1.0, -1.0)
        self.limit_xy2 = -1.0

    def set_position(self, newpos: Position, homing_axes: str) -> None:
        """Z homed: its range; X and Y homed together: the arm's disc."""
        if "z" in homing_axes:
            self.limit_z = self.rails[1].get_range()
        if "x" in homing_axes and "y" in homing_axes:
            self.limit_xy2 = self.rails[0].get_range()[1]**2

    def clear_homing_state(self, clear_axes: str) -> None:
        """X and Y cannot be cleared separately."""
        if "x" in clear_axes or "y" in clear_axes:
            self.limit_xy2 = -1.0
        if "z" in clear_axes:
            self.limit_z = (1.0, -1.0)

    def homed_axes(self) -> str:
        """X and Y together, Z alone (get_status's homed_axes)."""
        xy_home = "xy" if self.limit_xy2 >= 0.0 else ""
        z_home = "z" if self.limit_z[0] <= self.limit_z[1] else ""
        return xy_home + z_home

    def home(self, pos: Position, axes: list[int]) -> tuple[Position, str]:
        """X or Y homes both (arm endstop, 0); Z homes to its position_endstop."""
        newpos = list(pos)
        homed = ""
        if 0 in axes or 1 in axes:
            newpos[0] = self.rails[0].position_endstop
            newpos[1] = 0.0
            homed = "xy"
        if 2 in axes:
            newpos[2] = self.rails[1].position_endstop
            homed += "z"
        return (newpos[0], newpos[1], newpos[2], newpos[3]), homed

    def check_move(self, move: Move) -> None:
        """The disc, Z's range and speed, and the slow-down near the centre."""
        end_x, end_y, end_z = move.end_x, move.end_y, move.end_z
        # Squares of positions from the file: math.pow (upstream: x**2), the same bits, and an
        # overflow raises on PyPy as it does on CPython, where PyPy's ** would give inf.
        xy2 = math.pow(end_x, 2.0) + math.pow(end_y, 2.0)
        if xy2 > self.limit_xy2:
            if self.limit_xy2 < 0.0:
                raise move.move_error("Must home axis first")
            raise move.move_error()
        if move.axes_d_z:
            if end_z < self.limit_z[0] or end_z > self.limit_z[1]:
                if self.limit_z[0] > self.limit_z[1]:
                    raise move.move_error("Must home axis first")
                raise move.move_error()
            # Move with Z - update velocity and accel for slower Z axis
            z_ratio = move.move_d / abs(move.axes_d_z)
            move.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
        # Slow down near center
        if move.axes_d_x or move.axes_d_y:
            if self.v_rad_max == 0:
                return
            min_dist = distance_to_center((move.start_x, move.start_y), (end_x, end_y))
            if min_dist == 0:
                return
            v_angular = math.sqrt(move.max_cruise_v2) / min_dist
            if self.v_rad_max < v_angular:
                scale_radius = self.v_rad_max / v_angular
                move.limit_speed(self.max_velocity * scale_radius,
                                 self.max_accel * scale_radius)


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: polar."""
    return PolarKinematics(config, limits)
