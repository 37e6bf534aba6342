"""Mirrors klippy/kinematics/delta.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `delta` kinematics: build radius and height, the slow-down radii, homing to the
top of the towers.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/delta.py` and
`klippy/mathutil.py` (`trilateration`) (GNU GPLv3). Names follow upstream.

Moves whose start or end lies beyond the slow-down radius run at 50 % of [printer]
max_velocity / max_accel, beyond the very-slow radius at 25 % (the configured values, not
SET_VELOCITY_LIMIT's). G28 homes all three towers and leaves the head at `home_position`
(the bed centre, at the top of the tower range).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, TypeVar

from kestimator.config.machine import MachineConfig, Rail, Section, lookup_rail
from kestimator.errors import KestimatorError
from kestimator.kinematics.base import (
    Kinematics,
    Position,
)

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move

# Slow moves once the ratio of tower to XY movement exceeds SLOW_RATIO
SLOW_RATIO = 3.0

Vec3 = tuple[float, float, float]
_A = TypeVar("_A")
_B = TypeVar("_B")


def _pairs(a: list[_A], b: list[_B]) -> list[tuple[_A, _B]]:
    """The three towers' values side by side (zip without strict=, valid on Python 3.9)."""
    if len(a) != len(b):
        raise ValueError("tower lists differ in length")
    return [(a[i], b[i]) for i in range(len(a))]


def _sub(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _add(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _dot(a: Vec3, b: Vec3) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _magsq(a: Vec3) -> float:
    return a[0]**2 + a[1]**2 + a[2]**2


def _cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _mul(a: Vec3, s: float) -> Vec3:
    return (a[0] * s, a[1] * s, a[2] * s)


def trilateration(sphere_coords: list[Vec3], radius2: list[float]) -> Vec3:
    """The point at distance sqrt(radius2[i]) from each sphere centre, with mathutil's
    arithmetic in mathutil's order (the homing-move test compares it exactly)."""
    sphere_coord1, sphere_coord2, sphere_coord3 = sphere_coords
    s21 = _sub(sphere_coord2, sphere_coord1)
    s31 = _sub(sphere_coord3, sphere_coord1)
    d = math.sqrt(_magsq(s21))
    ex = _mul(s21, 1.0 / d)
    i = _dot(ex, s31)
    vect_ey = _sub(s31, _mul(ex, i))
    ey = _mul(vect_ey, 1.0 / math.sqrt(_magsq(vect_ey)))
    ez = _cross(ex, ey)
    j = _dot(ey, s31)
    x = (radius2[0] - radius2[1] + d**2) / (2.0 * d)
    y = (radius2[0] - radius2[2] - x**2 + (x - i)**2 + j**2) / (2.0 * j)
    z = -math.sqrt(radius2[0] - x**2 - y**2)
    return _add(sphere_coord1, _add(_mul(ex, x), _add(_mul(ey, y), _mul(ez, z))))


class DeltaKinematics(Kinematics):
    """Three towers (stepper_a/b/c) with arms to one effector."""

    name = "delta"

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__()
        printer = config.getsection("printer")
        stepper_configs = [config.getsection("stepper_" + a) for a in "abc"]
        rail_a = lookup_rail(config, "stepper_a", need_position_minmax=False)
        a_endstop = rail_a.position_endstop
        self.rails = [rail_a] + [
            lookup_rail(config, "stepper_" + a, need_position_minmax=False,
                        default_position_endstop=a_endstop) for a in "bc"]
        # Setup max velocity (the configured [printer] values)
        self.max_velocity, self.max_accel = limits.max_velocity, limits.max_accel
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        # Read radius and arm lengths
        self.radius = radius = printer.getfloat("delta_radius", above=0.0)
        print_radius = printer.getfloat("print_radius", radius, above=0.0)
        arm_length_a = stepper_configs[0].getfloat("arm_length", above=radius)
        self.arm_lengths = arm_lengths = [
            sconfig.getfloat("arm_length", arm_length_a, above=radius)
            for sconfig in stepper_configs]
        self.arm2 = [arm**2 for arm in arm_lengths]
        self.abs_endstops = [(rail.position_endstop + math.sqrt(arm2 - radius**2))
                             for rail, arm2 in _pairs(self.rails, self.arm2)]
        # Determine tower locations in cartesian space
        self.angles = [sconfig.getfloat("angle", angle)
                       for sconfig, angle in _pairs(stepper_configs, [210.0, 330.0, 90.0])]
        self.towers = [(math.cos(math.radians(angle)) * radius,
                        math.sin(math.radians(angle)) * radius)
                       for angle in self.angles]
        # Setup boundary checks
        self.need_home = True
        self.limit_xy2 = -1.0
        self.home_position = self._actuator_to_cartesian(self.abs_endstops)
        self.max_z = min([rail.position_endstop for rail in self.rails])
        self.min_z = printer.getfloat("minimum_z_position", 0.0, maxval=self.max_z)
        self.limit_z = min([ep - arm for ep, arm in _pairs(self.abs_endstops, arm_lengths)])
        self.min_arm_length = min_arm_length = min(arm_lengths)
        self.min_arm2 = min_arm_length**2
        # Find the point where an XY move could result in excessive tower movement
        half_min_step_dist = min([r.step_dist for r in self.rails]) * 0.5
        if min_arm_length**2 / ((4.0 * SLOW_RATIO)**2 + 1.0) < half_min_step_dist**2:
            # Klipper's ratio_to_xy takes the square root of a negative number and Klipper
            # does not start (ValueError); name the step that is too coarse.
            raise _coarse_step(stepper_configs, self.rails, min_arm_length)

        def ratio_to_xy(ratio: float) -> float:
            return (ratio * math.sqrt(min_arm_length**2 / (ratio**2 + 1.0)
                                      - half_min_step_dist**2)
                    + half_min_step_dist - radius)
        self.slow_xy2 = ratio_to_xy(SLOW_RATIO)**2
        self.very_slow_xy2 = ratio_to_xy(2.0 * SLOW_RATIO)**2
        self.max_xy2 = min(print_radius, min_arm_length - radius,
                           ratio_to_xy(4.0 * SLOW_RATIO))**2

    def _actuator_to_cartesian(self, spos: list[float]) -> Vec3:
        sphere_coords = [(t[0], t[1], sp) for t, sp in _pairs(self.towers, spos)]
        return trilateration(sphere_coords, self.arm2)

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
        """All towers home together: the head ends at home_position, whatever was asked."""
        hp = self.home_position
        return (hp[0], hp[1], hp[2], pos[3]), "xyz"

    def check_move(self, move: Move) -> None:
        """Range (radius tapered near the top), Z limits, and the slow-down radii."""
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
            above_z_limit = end_z - self.limit_z
            allowed_radius = self.radius - math.sqrt(
                self.min_arm2 - math.pow(self.min_arm_length - above_z_limit, 2.0))
            limit_xy2 = min(limit_xy2, math.pow(allowed_radius, 2.0))
        if end_xy2 > limit_xy2 or end_z > self.max_z or end_z < self.min_z:
            # Move out of range - verify not a homing move
            if ((end_x, end_y) != (self.home_position[0], self.home_position[1])
                    or end_z < self.min_z or end_z > self.home_position[2]):
                raise move.move_error()
            limit_xy2 = -1.0
        if move.axes_d_z:
            z_ratio = move.move_d / abs(move.axes_d_z)
            move.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
            limit_xy2 = -1.0
        # Limit the speed/accel of this move if is is at the extreme
        # end of the build envelope
        extreme_xy2 = max(end_xy2, math.pow(move.start_x, 2.0) + math.pow(move.start_y, 2.0))
        if extreme_xy2 > self.slow_xy2:
            r = 0.5
            if extreme_xy2 > self.very_slow_xy2:
                r = 0.25
            move.limit_speed(self.max_velocity * r, self.max_accel * r)
            limit_xy2 = -1.0
        self.limit_xy2 = min(limit_xy2, self.slow_xy2)


def _coarse_step(stepper_configs: list[Section], rails: list[Rail],
                 min_arm_length: float) -> KestimatorError:
    """The error for a step too coarse for the arms, at the option that sets the step."""
    index = min(range(len(rails)), key=lambda i: rails[i].step_dist)
    section = stepper_configs[index]
    option = next((name for name in ("rotation_distance", "gear_ratio", "microsteps",
                                     "full_steps_per_rotation")
                   if section.source(name) is not None), "rotation_distance")
    limit = 2.0 * min_arm_length / math.sqrt((4.0 * SLOW_RATIO)**2 + 1.0)
    return section._error(
        option, "option '%s': one microstep of %s moves its carriage %.6g mm, too coarse "
        "for arm_length %g: a delta's step must be under 2 x arm_length / sqrt(145) = "
        "%.4g mm, or Klipper cannot compute its slow-down radius and does not start"
        % (option, section.name, rails[index].step_dist, min_arm_length, limit))


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: delta."""
    return DeltaKinematics(config, limits)
