"""Mirrors klippy/kinematics/rotary_delta.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `rotary_delta` kinematics: three rotating shoulders (stepper_a/b/c, in radians)
with upper and lower arms to one effector.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/rotary_delta.py`
and `klippy/chelper/kin_rotary_delta.c` (the shoulder angle for a position, used for the home
position) (GNU GPLv3). Names follow upstream.

The build volume is a cylinder (radius from the arm lengths, height up to the lowest endstop,
the radius tapered near the top); Z moves are capped at max_z_velocity (velocity only, not
scaled along Z and not accel: upstream's rule). G28 homes all three shoulders and leaves the
head at `home_position`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig, Section, lookup_rail
from kestimator.kinematics.base import (
    Kinematics,
    Position,
)
from kestimator.kinematics.delta import trilateration

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move

Vec3 = tuple[float, float, float]


def rotary_two_arm_calc(dx: float, dy: float, upper_arm2: float, lower_arm2: float) -> float:
    """The shoulder angle (radians) whose elbow reaches (dx, dy) with the lower arm."""
    # Determine constants such that: elbow_y = c1 - c2*elbow_x
    inv_dy = 1.0 / dy
    c1 = 0.5 * inv_dy * (dx * dx + dy * dy + upper_arm2 - lower_arm2)
    c2 = dx * inv_dy
    # Calculate scaled elbow coordinates via quadratic equation.
    scale = c2 * c2 + 1.0
    scaled_elbow_x = c1 * c2 + math.sqrt(scale * upper_arm2 - c1 * c1)
    scaled_elbow_y = c1 * scale - c2 * scaled_elbow_x
    # Calculate angle in radians
    return math.atan2(scaled_elbow_y, scaled_elbow_x)


class RotaryDeltaKinematics(Kinematics):
    """Three shoulders at `angle` around the centre."""

    name = "rotary_delta"

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__()
        printer = config.getsection("printer")
        stepper_configs = [config.getsection("stepper_" + a) for a in "abc"]
        rail_a = lookup_rail(config, "stepper_a", need_position_minmax=False,
                             units_in_radians=True)
        a_endstop = rail_a.position_endstop
        self.rails = [rail_a] + [
            lookup_rail(config, "stepper_" + a, need_position_minmax=False,
                        default_position_endstop=a_endstop, units_in_radians=True)
            for a in "bc"]
        self.max_z_velocity = limits.max_z_velocity
        self.shoulder_radius = shoulder_radius = printer.getfloat("shoulder_radius", above=0.0)
        self.shoulder_height = printer.getfloat("shoulder_height", above=0.0)
        a_upper_arm = stepper_configs[0].getfloat("upper_arm_length", above=0.0)
        self.upper_arms = upper_arms = [
            sconfig.getfloat("upper_arm_length", a_upper_arm, above=0.0)
            for sconfig in stepper_configs]
        a_lower_arm = stepper_configs[0].getfloat("lower_arm_length", above=0.0)
        self.lower_arms = lower_arms = [
            sconfig.getfloat("lower_arm_length", a_lower_arm, above=0.0)
            for sconfig in stepper_configs]
        default_angles = (30.0, 150.0, 270.0)
        self.angles = [stepper_configs[i].getfloat("angle", default_angles[i])
                       for i in range(3)]
        endstops = [rail.position_endstop for rail in self.rails]
        # Setup boundary checks
        self.need_home = True
        self.limit_xy2 = -1.0
        eangles = [self._endstop_angle(stepper_configs, i, endstops[i]) for i in range(3)]
        self.home_position = self._actuator_to_cartesian(eangles)
        self.max_z = min(endstops)
        self.min_z = printer.getfloat("minimum_z_position", 0.0, maxval=self.max_z)
        min_ua = min([shoulder_radius + ua for ua in upper_arms])
        min_la = min([la - shoulder_radius for la in lower_arms])
        self.max_xy2 = min(min_ua, min_la)**2
        arm_z = [self._elbow_coord(i, eangles[i])[2] for i in range(3)]
        self.limit_z = min([arm_z[i] - lower_arms[i] for i in range(3)])

    def _endstop_angle(self, stepper_configs: list[Section], i: int, endstop: float
                       ) -> float:
        """Shoulder i's angle with the head at its endstop; an error naming the arms when
        they cannot reach it (Klipper's C code then yields NaN and no home position)."""
        try:
            return self._calc_position_from_coord(i, (0.0, 0.0, endstop))
        except (ValueError, ZeroDivisionError):
            pass
        section = stepper_configs[i]
        if section.source("upper_arm_length") is None:
            section = stepper_configs[0]
        raise section._error(
            "upper_arm_length", "the arms of %s cannot reach its position_endstop %g "
            "(upper_arm_length %g, lower_arm_length %g, shoulder_radius %g, shoulder_height "
            "%g): Klipper computes no home position for this geometry"
            % (stepper_configs[i].name, endstop, self.upper_arms[i], self.lower_arms[i],
               self.shoulder_radius, self.shoulder_height))

    def _calc_position_from_coord(self, i: int, c: Vec3) -> float:
        """kin_rotary_delta.c's rotary_stepper_calc_position for shoulder i at c."""
        angle = math.radians(self.angles[i])
        cos, sin = math.cos(angle), math.sin(angle)
        # Rotate and shift axes to an origin at shoulder joint with upper
        # arm constrained to xy plane and x aligned to shoulder platform.
        sjz = c[1] * cos - c[0] * sin
        sjx = c[0] * cos + c[1] * sin - self.shoulder_radius
        sjy = c[2] - self.shoulder_height
        return rotary_two_arm_calc(sjx, sjy, self.upper_arms[i] * self.upper_arms[i],
                                   self.lower_arms[i] * self.lower_arms[i] - sjz * sjz)

    def _elbow_coord(self, elbow_id: int, spos: float) -> Vec3:
        # Calculate elbow position in coordinate system at shoulder joint
        sj_elbow_x = self.upper_arms[elbow_id] * math.cos(spos)
        sj_elbow_y = self.upper_arms[elbow_id] * math.sin(spos)
        # Shift and rotate to main cartesian coordinate system
        angle = math.radians(self.angles[elbow_id])
        x = (sj_elbow_x + self.shoulder_radius) * math.cos(angle)
        y = (sj_elbow_x + self.shoulder_radius) * math.sin(angle)
        z = sj_elbow_y + self.shoulder_height
        return (x, y, z)

    def _actuator_to_cartesian(self, spos: list[float]) -> Vec3:
        sphere_coords = [self._elbow_coord(i, spos[i]) for i in range(3)]
        lower_arm2 = [la**2 for la in self.lower_arms]
        return trilateration(sphere_coords, lower_arm2)

    def set_position(self, newpos: Position, homing_axes: str) -> None:
        """Homing all of XYZ together clears need_home; any jump resets the XY cache."""
        self.limit_xy2 = -1.0
        if homing_axes == "xyz":
            self.need_home = False

    def clear_homing_state(self, clear_axes: str) -> None:
        """Clearing any axis unhomes the whole head (upstream clears no axis alone)."""
        if clear_axes:
            self.limit_xy2 = -1.0
            self.need_home = True

    def homed_axes(self) -> str:
        """All or nothing (get_status's homed_axes)."""
        return "" if self.need_home else "xyz"

    def home(self, pos: Position, axes: list[int]) -> tuple[Position, str]:
        """All shoulders home together: the head ends at home_position."""
        hp = self.home_position
        return (hp[0], hp[1], hp[2], pos[3]), "xyz"

    def check_move(self, move: Move) -> None:
        """Range (radius tapered near the top) and the Z velocity cap."""
        end_x, end_y, end_z = move.end_x, move.end_y, move.end_z
        # Squares of positions from the file: math.pow (upstream: x**2), the same bits, and an
        # overflow raises on PyPy as it does on CPython, where PyPy's ** would give inf.
        end_xy2 = math.pow(end_x, 2.0) + math.pow(end_y, 2.0)
        if end_xy2 <= self.limit_xy2 and not move.axes_d_z:
            # Normal XY move
            return
        if self.need_home:
            raise move.move_error("Must home first")
        limit_xy2 = self.max_xy2
        if end_z > self.limit_z:
            limit_xy2 = min(limit_xy2, math.pow(self.max_z - end_z, 2.0))
        if end_xy2 > limit_xy2 or end_z > self.max_z or end_z < self.min_z:
            # Move out of range - verify not a homing move
            if ((end_x, end_y) != (self.home_position[0], self.home_position[1])
                    or end_z < self.min_z or end_z > self.home_position[2]):
                raise move.move_error()
            limit_xy2 = -1.0
        if move.axes_d_z:
            move.limit_speed(self.max_z_velocity, move.accel)
            limit_xy2 = -1.0
        self.limit_xy2 = limit_xy2


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: rotary_delta."""
    return RotaryDeltaKinematics(config, limits)
