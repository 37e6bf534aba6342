"""Mirrors klippy/kinematics/deltesian.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `deltesian` kinematics: two delta-style towers (stepper_left / stepper_right) move
X and Z, a cartesian stepper_y moves Y.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/deltesian.py`
(GNU GPLv3). X's range comes from the arm geometry (or print_width), Y's from stepper_y, Z's
from the pillars (tapered at the top by X); Z moves are limited by max_z_velocity / max_z_accel
scaled along Z. G28 of X or Z homes both towers: X=0 and Z at the top (home_z); G28 Y homes Y
to its position_endstop.

Klipper 84104bbbd's own slow-down of X moves beyond `slow_ratio` reads attributes its
`__init__` never sets (`self.max_velocity`), so such a move raises an internal error and the
print stops there: that move is reported as Klipper's error, with Klipper's text.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig, Section, lookup_rail
from kestimator.errors import KestimatorError, MoveError
from kestimator.kinematics.base import Kinematics, Position

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move

SLOW_RATIO = 3.0
MIN_ANGLE = 5.0
# What Python says when Klipper 84104bbbd's check_move reaches its slow-down branch.
SLOW_DOWN_BUG = "'DeltesianKinematics' object has no attribute 'max_velocity'"


class DeltesianKinematics(Kinematics):
    """Left/right towers with arms, and a Y rail."""

    name = "deltesian"

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__()
        printer = config.getsection("printer")
        stepper_configs = [config.getsection("stepper_" + s) for s in ("left", "right", "y")]
        rail_left = lookup_rail(config, "stepper_left", need_position_minmax=False)
        rail_right = lookup_rail(config, "stepper_right", need_position_minmax=False,
                                 default_position_endstop=rail_left.position_endstop)
        self.rails = [rail_left, rail_right, lookup_rail(config, "stepper_y")]
        arm_x0 = stepper_configs[0].getfloat("arm_x_length", above=0.0)
        arm_x1 = stepper_configs[1].getfloat("arm_x_length", arm_x0, above=0.0)
        self.arm_x = arm_x = [arm_x0, arm_x1]
        arm0 = stepper_configs[0].getfloat("arm_length", above=arm_x0)
        arm1 = stepper_configs[1].getfloat("arm_length", arm0, above=arm_x1)
        arm = [arm0, arm1]
        self.arm2 = arm2 = [a**2 for a in arm]
        self.limits: list[tuple[float, float]] = [(1.0, -1.0)] * 3
        # X axis limits
        min_angle = printer.getfloat("min_angle", MIN_ANGLE, minval=0.0, maxval=90.0)
        cos_angle = math.cos(math.radians(min_angle))
        x_kin_min = math.ceil(-min(arm_x[0], cos_angle * arm[1] - arm_x[1]))
        x_kin_max = math.floor(min(arm_x[1], cos_angle * arm[0] - arm_x[0]))
        x_kin_range = min(x_kin_max - x_kin_min, x_kin_max * 2, -x_kin_min * 2)
        if x_kin_range <= 0:
            # Klipper starts (an absent print_width's bound is not checked) with an empty X
            # range and refuses every X move; say which option leaves no range.
            raise _no_x_range(printer, stepper_configs, arm, arm_x, min_angle)
        print_width = printer.getfloat("print_width", 0.0, minval=0.0, maxval=x_kin_range)
        if print_width:
            self.limits[0] = (-print_width * 0.5, print_width * 0.5)
        else:
            self.limits[0] = (float(x_kin_min), float(x_kin_max))
        # Y axis limits
        self.limits[1] = self.rails[2].get_range()
        # Z axis limits
        pmax = [r.position_endstop for r in self.rails[:2]]
        self._abs_endstop = [pmax[i] + math.sqrt(arm2[i] - arm_x[i]**2) for i in range(2)]
        self.home_z = self._actuator_to_cartesian(self._abs_endstop)[1]
        z_max = min([self._pillars_z_max(x) for x in self.limits[0]])
        z_min = printer.getfloat("minimum_z_position", 0.0, maxval=z_max)
        self.limits[2] = (z_min, z_max)
        # The speed/accel limit at the extreme values of the x axis (see SLOW_DOWN_BUG)
        slow_ratio = printer.getfloat("slow_ratio", SLOW_RATIO, minval=0.0)
        self.slow_x2 = self.very_slow_x2 = 0.0
        if slow_ratio > 0.0:
            sr2 = slow_ratio ** 2
            self.slow_x2 = min([math.sqrt((sr2 * arm2[i]) / (sr2 + 1)) - arm_x[i]
                                for i in range(2)]) ** 2
            self.very_slow_x2 = min([math.sqrt((2 * sr2 * arm2[i]) / (2 * sr2 + 1))
                                     - arm_x[i] for i in range(2)]) ** 2
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        self.homed_axis = [False] * 3

    def _actuator_to_cartesian(self, sp: list[float]) -> tuple[float, float]:
        arm_x, arm2 = self.arm_x, self.arm2
        dx, dz = sum(arm_x), sp[1] - sp[0]
        pivots = math.sqrt(dx**2 + dz**2)
        # Trilateration w/ reference frame along left to right pivots
        xt = (pivots**2 + arm2[0] - arm2[1]) / (2 * pivots)
        zt = math.sqrt(arm2[0] - xt**2)
        # Rotation and translation of the reference frame
        x = xt * dx / pivots + zt * dz / pivots - arm_x[0]
        z = xt * dz / pivots - zt * dx / pivots + sp[0]
        return x, z

    def _pillars_z_max(self, x: float) -> float:
        arm_x, arm2 = self.arm_x, self.arm2
        # math.pow (upstream: **): x comes from the file, see check_move.
        dz = (math.sqrt(arm2[0] - math.pow(arm_x[0] + x, 2.0)),
              math.sqrt(arm2[1] - math.pow(arm_x[1] - x, 2.0)))
        return min([self._abs_endstop[i] - dz[i] for i in range(2)])

    def set_position(self, newpos: Position, homing_axes: str) -> None:
        """Homed axes are remembered one by one."""
        for axis_name in homing_axes:
            self.homed_axis["xyz".index(axis_name)] = True

    def clear_homing_state(self, clear_axes: str) -> None:
        """Cleared axes must be homed again before they move."""
        for axis, axis_name in enumerate("xyz"):
            if axis_name in clear_axes:
                self.homed_axis[axis] = False

    def homed_axes(self) -> str:
        """The axes homed one by one (get_status's homed_axes)."""
        return "".join(a for a, homed in zip("xyz", self.homed_axis) if homed)

    def home(self, pos: Position, axes: list[int]) -> tuple[Position, str]:
        """X or Z: both towers, to X=0 and the top; Y: to stepper_y's position_endstop."""
        newpos = list(pos)
        home_xz = 0 in axes or 2 in axes
        home_y = 1 in axes
        homed = ""
        if home_xz:
            newpos[0], newpos[2] = 0.0, self.home_z
            homed = "xz"
        if home_y:
            newpos[1] = self.rails[2].position_endstop
            homed = "xyz" if home_xz else "y"
        return (newpos[0], newpos[1], newpos[2], newpos[3]), homed

    def check_move(self, move: Move) -> None:
        """Ranges (Z tapered at the top by X), Z speed, and the X slow-down's failure."""
        limits = [list(lim) for lim in self.limits]
        spos, epos = move.start_pos, move.end_pos
        homing_move = False
        if epos[0] == 0.0 and epos[2] == self.home_z and not move.axes_d[1]:
            # Identify a homing move
            homing_move = True
        elif epos[2] > limits[2][1]:
            # Moves at the very top - adapt limits depending on the X position
            limits[2][1] = self._pillars_z_max(epos[0])
        for i in (i for i, v in enumerate(move.axes_d[:3]) if v):
            if not self.homed_axis[i]:
                raise move.move_error("Must home axis first")
            # Move out of range - verify not a homing move
            if epos[i] < limits[i][0] or epos[i] > limits[i][1]:
                if not homing_move:
                    raise move.move_error()
        if move.axes_d[2]:
            z_ratio = move.move_d / abs(move.axes_d[2])
            move.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)
        if move.axes_d[0] and self.slow_x2 and self.very_slow_x2:
            # Squares of positions from the file: math.pow (upstream: x**2), the same bits,
            # and an overflow raises on PyPy as it does on CPython (PyPy's ** gives inf).
            move_x2 = max(math.pow(spos[0], 2.0), math.pow(epos[0], 2.0))
            if move_x2 > self.very_slow_x2 or move_x2 > self.slow_x2:
                raise MoveError("Internal error: %s (Klipper 84104bbbd's deltesian fails on "
                                "moves beyond its slow-down X and shuts down)" % SLOW_DOWN_BUG)


def _no_x_range(printer: Section, stepper_configs: list[Section], arm: list[float],
                arm_x: list[float], min_angle: float) -> KestimatorError:
    """The error for arms that reach no X position at min_angle, naming the option the
    user wrote: min_angle when the arms would do at the default angle, else the arm."""
    widest = min(math.degrees(math.acos(arm_x[i] / arm[i])) for i in range(2))
    if printer.source("min_angle") is not None and min_angle > MIN_ANGLE and (
            widest > MIN_ANGLE):
        return printer._error(
            "min_angle", "option 'min_angle' %g leaves the arms no X range: with arm_length "
            "%g and arm_x_length %g they reach X only at angles below %.4g degrees, so "
            "Klipper would refuse every X move" % (min_angle, arm[0], arm_x[0], widest))
    cos_angle = math.cos(math.radians(min_angle))
    side = 0 if cos_angle * arm[0] - arm_x[0] <= cos_angle * arm[1] - arm_x[1] else 1
    section = stepper_configs[side]
    if section.source("arm_length") is None:
        section = stepper_configs[0]
    return section._error(
        "arm_length", "option 'arm_length' %g is too short for arm_x_length %g at min_angle "
        "%g degrees: it must be well over arm_x_length / cos(min_angle) = %.6g, or the arms "
        "reach no X position and Klipper would refuse every X move"
        % (arm[side], arm_x[side], min_angle, arm_x[side] / cos_angle))


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: deltesian."""
    return DeltesianKinematics(config, limits)
