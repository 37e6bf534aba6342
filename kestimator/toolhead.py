"""Mirrors klippy/toolhead.py at Klipper commit 84104bbbd (GNU GPLv3).

Owns the motion planner and print time, in upstream's order: `Move` (one requested move
and, once planned, its trapezoidal velocity profile), `LookAheadQueue` (junction speeds
and lazy flushes), `ToolHead` (queuing moves, print-time tracking, flushes where the head
comes to rest) and `ToolHeadCommandHelper` (G4, M400, SET_VELOCITY_LIMIT, M204).
Re-implemented from upstream (Copyright (C) 2016-2025 Kevin O'Connor); names follow
upstream so the two read side by side, and the arithmetic is done in the same order, so
results agree to the last bit.

Where this file differs from upstream for speed, a comment says so: `Move` keeps each axis
in its own float attribute instead of 4-element lists, `min()` calls on the hot path are
written out as comparisons, and `Move.calc_junction` includes the extruder's junction limit.
Batch mode has no MCU: the reactor, pause checks, priming timer and trapq are left out,
and print time starts at 0 when the first move (or dwell) starts. The head starts homed at
X=Y=Z=0 (the oracle's convention: the start macro that homes is not in the file).

Where an older Klipper's toolhead.py differs and `klipper_version` names it, its rule sits
beside today's, written as that release has it: `ClampedJunctionMove` (junctions before
847331260, v0.12.0-384), `ForceFlushToolHead` (print time before b7b13588c, v0.12.0-23) and
`MinRestartToolHead` (print time from v0.12.0-69 to v0.13.0-237), chosen by `make_toolhead`
(the version table is `kestimator.limits`').

The planner does no I/O and knows no G-code. Positions are (x, y, z, e) in mm. Unit
suffixes (Klipper's legend): _d is distance (mm), _v is velocity (mm/s), _v2 is velocity
squared (mm^2/s^2), _t is time (s), _r is a ratio.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from math import sqrt
from typing import ClassVar, Final

from kestimator.errors import MoveError, ParamError, fixed
from kestimator.extruder import PrinterExtruder
from kestimator.gcode import Command, command_params, get_float
from kestimator.kinematics import load_kinematics
from kestimator.limits import Limits, klipper_release
from kestimator.motion_queuing import PrinterMotionQueuing

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

__all__ = ["ClampedJunctionMove", "ForceFlushToolHead", "LookAheadQueue", "MinRestartToolHead",
           "Move", "MoveError", "ToolHead", "ToolHeadCommandHelper", "make_toolhead"]

# Klipper's accel for extrude-only moves ("unlimited" before the extruder limits apply).
EXTRUDE_ONLY_ACCEL: Final = 99999999.9
# No limit yet on the next junction.
UNLIMITED_JUNCTION_V2: Final = 999999999.9
# A move shorter than this in XYZ is an extrude-only move.
MIN_KINEMATIC_MOVE_D: Final = 0.000000001
# Where upstream squares with `**` (C's pow(), whose result can differ from v * v in
# its last bit), pow() is taken only where it can matter: where it may be below a limit.
# pow(v, 2.0) and v * v each lie within an ulp of the exact square (glibc's pow: 0.54
# ulp), far inside the margin of 2**-40, so v * v * POW2_BELOW >= limit proves
# pow(v, 2.0) >= limit; outside POW2_TINY..POW2_INF (subnormal, overflow, NaN) pow()
# itself is taken. tests/test_toolhead_pow.py pins both shortcuts against pow().
POW2_BELOW: Final = 1.0 - 2.0**-40
POW2_TINY: Final = 1e-290
POW2_INF: Final = math.inf
# LookAheadQueue.flush: this move cannot accelerate (upstream's cruise_v2 = None); every
# real cruise_v2 is >= 0.
NO_CRUISE_V2: Final = -1.0
# Move.__init__ sets every attribute on PyPy only (see there).
_PYPY: Final = sys.implementation.name == "pypy"

TimingCallback = Callable[[float], None]


# Class to track each move request
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Move:
    """One straight-line move and, once planned, its trapezoidal velocity profile.

    Upstream keeps positions and per-axis values as 4-element lists; here each axis is its
    own float attribute (`start_x`, `axes_d_x`, `axes_r_e`, ...) so that a compiled build
    stores them unboxed and no tuple is built per move. `start_pos`, `end_pos`, `axes_d`
    and `axes_r` give upstream's tuples for code off the hot path.
    """

    __slots__ = (
        "start_x", "start_y", "start_z", "start_e", "end_x", "end_y", "end_z", "end_e",
        "accel", "junction_deviation", "is_kinematic_move",
        "axes_d_x", "axes_d_y", "axes_d_z", "axes_d_e", "move_d",
        "axes_r_x", "axes_r_y", "axes_r_z", "axes_r_e", "min_move_t", "max_start_v2",
        "max_cruise_v2", "delta_v2", "next_junction_v2", "max_mcr_start_v2", "mcr_delta_v2",
        "start_v", "cruise_v", "end_v", "accel_t", "cruise_t", "decel_t",
        "instant_corner_v", "tag", "timing_callbacks",
        "flush_start_v2", "flush_cruise_v2", "flush_next_start_v2",
    )

    # Set by LookAheadQueue.flush: its junction_info for this move (upstream keeps a tuple
    # per move in a list; NO_CRUISE_V2 stands for its cruise_v2 of None).
    flush_start_v2: float
    flush_cruise_v2: float
    flush_next_start_v2: float
    # Set by set_junction: the planned profile.
    start_v: float
    cruise_v: float
    end_v: float
    accel_t: float
    cruise_t: float
    decel_t: float

    def __init__(self, toolhead: ToolHead, start_x: float, start_y: float, start_z: float,
                 start_e: float, end_x: float, end_y: float, end_z: float, end_e: float,
                 speed: float, tag: int = 0) -> None:
        self.start_x = start_x
        self.start_y = start_y
        self.start_z = start_z
        self.start_e = start_e
        self.end_x = end_x
        self.end_y = end_y
        self.end_z = end_z
        self.end_e = end_e
        self.accel = toolhead.max_accel
        self.junction_deviation = toolhead.junction_deviation
        # The active extruder's, for its junction limit (see calc_junction).
        self.instant_corner_v = toolhead.instant_corner_v
        # The source line of the move (0 when not from a file).
        self.tag = tag
        self.timing_callbacks: list[Callable[[float], None]] | None = None
        # min(speed, max_velocity), written out (this runs once per move)
        max_velocity = toolhead.max_velocity
        velocity = max_velocity if max_velocity < speed else speed
        self.is_kinematic_move = True
        dx = end_x - start_x
        dy = end_y - start_y
        dz = end_z - start_z
        de = end_e - start_e
        move_d = sqrt(dx * dx + dy * dy + dz * dz)
        if move_d < MIN_KINEMATIC_MOVE_D:
            # Extrude only move
            self.end_x = start_x
            self.end_y = start_y
            self.end_z = start_z
            dx = dy = dz = 0.0
            move_d = abs(de)
            inv_move_d = 0.0
            if move_d:
                inv_move_d = 1.0 / move_d
            self.accel = EXTRUDE_ONLY_ACCEL
            velocity = speed
            self.is_kinematic_move = False
        else:
            inv_move_d = 1.0 / move_d
        self.move_d = move_d
        self.axes_d_x = dx
        self.axes_d_y = dy
        self.axes_d_z = dz
        self.axes_d_e = de
        self.axes_r_x = dx * inv_move_d
        self.axes_r_y = dy * inv_move_d
        self.axes_r_z = dz * inv_move_d
        self.axes_r_e = de * inv_move_d
        self.min_move_t = move_d / velocity if move_d else 0.0
        # Junction speeds are tracked in velocity squared.  The delta_v2 is the maximum
        # amount of this squared-velocity that can change in this move.
        self.max_start_v2 = 0.0
        # upstream: velocity**2, which is C's pow() (its last bit can differ from
        # velocity * velocity). pow() is dear on every line and moves in a row mostly
        # share one speed, so the toolhead keeps the last square it took.
        if velocity == toolhead.last_velocity:
            self.max_cruise_v2 = toolhead.last_velocity2
        else:
            self.max_cruise_v2 = toolhead.last_velocity2 = math.pow(velocity, 2.0)
            toolhead.last_velocity = velocity
        self.delta_v2 = 2.0 * move_d * self.accel
        self.next_junction_v2 = UNLIMITED_JUNCTION_V2
        # Setup for minimum_cruise_ratio checks
        self.max_mcr_start_v2 = 0.0
        self.mcr_delta_v2 = 2.0 * move_d * toolhead.mcr_pseudo_accel
        # Every attribute set here, though flush and set_junction set them again: PyPy
        # then gives each Move one fixed layout (estimate on the 40 MB file: 1.73 s CPU
        # without these lines, 1.35 s with). CPython and the compiled build gain nothing
        # from them and skip the stores (1.4 % fewer instructions in pure CPython).
        if _PYPY:
            self.start_v = self.cruise_v = self.end_v = 0.0
            self.accel_t = self.cruise_t = self.decel_t = 0.0
            self.flush_start_v2 = self.flush_cruise_v2 = self.flush_next_start_v2 = 0.0

    @property
    def start_pos(self) -> tuple[float, float, float, float]:
        """Upstream's start_pos (x, y, z, e)."""
        return (self.start_x, self.start_y, self.start_z, self.start_e)

    @property
    def end_pos(self) -> tuple[float, float, float, float]:
        """Upstream's end_pos (x, y, z, e); XYZ stay put for an extrude-only move."""
        return (self.end_x, self.end_y, self.end_z, self.end_e)

    @property
    def axes_d(self) -> tuple[float, float, float, float]:
        """Upstream's axes_d: distance moved per axis (mm)."""
        return (self.axes_d_x, self.axes_d_y, self.axes_d_z, self.axes_d_e)

    @property
    def axes_r(self) -> tuple[float, float, float, float]:
        """Upstream's axes_r: distance per axis divided by move_d."""
        return (self.axes_r_x, self.axes_r_y, self.axes_r_z, self.axes_r_e)

    def limit_speed(self, speed: float, accel: float) -> None:
        """Lower the cruise speed and acceleration (kinematic or extruder limits)."""
        # upstream: speed2 = speed**2 (C's pow()), then `if speed2 < self.max_cruise_v2`.
        # pow() lies within an ulp or two of speed * speed, so it is taken only where it
        # can be below (or overflows and raises, as upstream's `**`).
        max_cruise_v2 = self.max_cruise_v2
        square = speed * speed
        if square * POW2_BELOW < max_cruise_v2 or not POW2_TINY < square < POW2_INF:
            speed2 = math.pow(speed, 2.0)
            if speed2 < max_cruise_v2:
                self.max_cruise_v2 = speed2
                self.min_move_t = self.move_d / speed
        self.accel = min(self.accel, accel)
        self.delta_v2 = 2.0 * self.move_d * self.accel
        self.mcr_delta_v2 = min(self.mcr_delta_v2, self.delta_v2)

    def move_error(self, msg: str = "Move out of range") -> MoveError:
        """The error Klipper raises for this move: the message with its end position."""
        return MoveError("%s: %s %s %s [%s]" % (msg, fixed(self.end_x), fixed(self.end_y),
                                                fixed(self.end_z), fixed(self.end_e)))

    def calc_junction(self, prev_move: Move) -> None:
        """Maximum start speed from the corner with `prev_move` (junction deviation)."""
        if not self.is_kinematic_move or not prev_move.is_kinematic_move:
            return
        # The extruder is an extra axis: it limits the junction by its change of E/mm
        # (upstream's `ea.calc_junction`, kinematics/extruder.py, written in here).
        max_cruise_v2 = self.max_cruise_v2
        # min() of the limits, written out as comparisons (the hot path; min() keeps the
        # first of equal values, and so does `b if b < a else a`).
        max_start_v2 = max_cruise_v2
        v2 = prev_move.max_cruise_v2
        if v2 < max_start_v2:
            max_start_v2 = v2
        v2 = prev_move.next_junction_v2
        if v2 < max_start_v2:
            max_start_v2 = v2
        v2 = prev_move.max_start_v2 + prev_move.delta_v2
        if v2 < max_start_v2:
            max_start_v2 = v2
        # The extruder's limit: upstream's ea_v2 = (instant_corner_v / abs(diff_r))**2
        # (max_cruise_v2 when diff_r is 0, which changes no minimum). C's pow() lies
        # within an ulp or two of v * v, so it is taken only where it can be the minimum
        # (or overflows and raises, as upstream's `**`).
        diff_r = self.axes_r_e - prev_move.axes_r_e
        if diff_r:
            v = self.instant_corner_v / abs(diff_r)
            square = v * v
            if square * POW2_BELOW < max_start_v2 or not POW2_TINY < square < POW2_INF:
                ea_v2 = math.pow(v, 2.0)
                if ea_v2 < max_start_v2:
                    max_start_v2 = ea_v2
        # Find max velocity using "approximated centripetal velocity"
        junction_cos_theta = -(self.axes_r_x * prev_move.axes_r_x
                               + self.axes_r_y * prev_move.axes_r_y
                               + self.axes_r_z * prev_move.axes_r_z)
        # max(v2, 0.0) written out: max() keeps v2 unless 0.0 > v2.
        v2 = 0.5 * (1.0 - junction_cos_theta)
        sin_theta_d2 = sqrt(0.0 if 0.0 > v2 else v2)
        v2 = 0.5 * (1.0 + junction_cos_theta)
        cos_theta_d2 = sqrt(0.0 if 0.0 > v2 else v2)
        one_minus_sin_theta_d2 = 1.0 - sin_theta_d2
        if one_minus_sin_theta_d2 > 0.0 and cos_theta_d2 > 0.0:
            R_jd = sin_theta_d2 / one_minus_sin_theta_d2
            move_jd_v2 = R_jd * self.junction_deviation * self.accel
            pmove_jd_v2 = R_jd * prev_move.junction_deviation * prev_move.accel
            # Approximated circle must contact moves no further than mid-move
            quarter_tan_theta_d2 = 0.25 * sin_theta_d2 / cos_theta_d2
            move_centripetal_v2 = self.delta_v2 * quarter_tan_theta_d2
            pmove_centripetal_v2 = prev_move.delta_v2 * quarter_tan_theta_d2
            if move_jd_v2 < max_start_v2:
                max_start_v2 = move_jd_v2
            if pmove_jd_v2 < max_start_v2:
                max_start_v2 = pmove_jd_v2
            if move_centripetal_v2 < max_start_v2:
                max_start_v2 = move_centripetal_v2
            if pmove_centripetal_v2 < max_start_v2:
                max_start_v2 = pmove_centripetal_v2
        # Apply limits
        self.max_start_v2 = max_start_v2
        v2 = prev_move.max_mcr_start_v2 + prev_move.mcr_delta_v2
        self.max_mcr_start_v2 = v2 if v2 < max_start_v2 else max_start_v2

    def set_junction(self, start_v2: float, cruise_v2: float, end_v2: float) -> None:
        """Fix the velocity profile: accelerate, cruise, decelerate."""
        half_inv_accel = 0.5 / self.accel
        accel_d = (cruise_v2 - start_v2) * half_inv_accel
        decel_d = (cruise_v2 - end_v2) * half_inv_accel
        cruise_d = self.move_d - accel_d - decel_d
        self.start_v = start_v = sqrt(start_v2)
        self.cruise_v = cruise_v = sqrt(cruise_v2)
        self.end_v = end_v = sqrt(end_v2)
        # Time is the distance divided by the average velocity.
        self.accel_t = accel_d / ((start_v + cruise_v) * 0.5)
        self.cruise_t = cruise_d / cruise_v
        self.decel_t = decel_d / ((end_v + cruise_v) * 0.5)

    @property
    def move_t(self) -> float:
        """Planned duration of the move in seconds (after set_junction)."""
        return self.accel_t + self.cruise_t + self.decel_t


# Seconds of queued moves after which the queue tries a lazy flush.
LOOKAHEAD_FLUSH_TIME: Final = 0.150


# Class to track a list of pending move requests and to facilitate
# "look-ahead" across moves to reduce acceleration between moves.
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ClampedJunctionMove(Move):
    """A move of a Klipper before 847331260 (v0.12.0-384, 2024-11): its junction rule, as
    klippy/toolhead.py of Klipper v0.12.0 (and v0.12.0-383) has it. A reversal starts from
    rest; a straight junction is clamped at cos -0.999999, which limits it (by the angle)
    where the mainline rule leaves it unlimited. ``delta_v2_centripetal`` is 8291788f4's
    arithmetic (v0.12.0-383): delta_v2 * .25 * tan_theta_d2 for .5 * move_d * tan_theta_d2
    * accel. The ToolHead makes these when `klipper_version` names such a release."""

    __slots__ = ()
    delta_v2_centripetal: ClassVar[bool] = False

    def calc_junction(self, prev_move: Move) -> None:
        """Maximum start speed from the corner with `prev_move` (v0.12.0's rule)."""
        if not self.is_kinematic_move or not prev_move.is_kinematic_move:
            return
        # Allow extruder to calculate its maximum junction (see Move.calc_junction: the
        # extruder's limit is taken only where it can be the minimum)
        max_start_v2 = self.max_cruise_v2
        diff_r = self.axes_r_e - prev_move.axes_r_e
        if diff_r:
            v = self.instant_corner_v / abs(diff_r)
            square = v * v
            if square * POW2_BELOW < max_start_v2 or not POW2_TINY < square < POW2_INF:
                ea_v2 = math.pow(v, 2.0)
                if ea_v2 < max_start_v2:
                    max_start_v2 = ea_v2
        # Find max velocity using "approximated centripetal velocity"
        junction_cos_theta = -(self.axes_r_x * prev_move.axes_r_x
                               + self.axes_r_y * prev_move.axes_r_y
                               + self.axes_r_z * prev_move.axes_r_z)
        if junction_cos_theta > 0.999999:
            return
        junction_cos_theta = max(junction_cos_theta, -0.999999)
        sin_theta_d2 = sqrt(0.5 * (1.0 - junction_cos_theta))
        R_jd = sin_theta_d2 / (1. - sin_theta_d2)
        # Approximated circle must contact moves no further away than mid-move
        if self.delta_v2_centripetal:
            cos_theta_d2 = sqrt(0.5 * (1.0 + junction_cos_theta))
            quarter_tan_theta_d2 = .25 * sin_theta_d2 / cos_theta_d2
            move_centripetal_v2 = self.delta_v2 * quarter_tan_theta_d2
            prev_move_centripetal_v2 = prev_move.delta_v2 * quarter_tan_theta_d2
        else:
            tan_theta_d2 = sin_theta_d2 / sqrt(0.5 * (1.0 + junction_cos_theta))
            move_centripetal_v2 = .5 * self.move_d * tan_theta_d2 * self.accel
            prev_move_centripetal_v2 = (.5 * prev_move.move_d * tan_theta_d2
                                        * prev_move.accel)
        # Apply limits
        self.max_start_v2 = min(
            R_jd * self.junction_deviation * self.accel,
            R_jd * prev_move.junction_deviation * prev_move.accel,
            move_centripetal_v2, prev_move_centripetal_v2,
            max_start_v2, prev_move.max_cruise_v2,
            prev_move.max_start_v2 + prev_move.delta_v2)
        # upstream's max_smoothed_v2 / smooth_delta_v2 (the mcr names here)
        self.max_mcr_start_v2 = min(
            self.max_start_v2, prev_move.max_mcr_start_v2 + prev_move.mcr_delta_v2)


class DeltaV2ClampedJunctionMove(ClampedJunctionMove):
    """A move of Klipper v0.12.0-383 (8291788f4): v0.12.0's junction rule with the
    centripetal limit computed from delta_v2."""

    __slots__ = ()
    delta_v2_centripetal: ClassVar[bool] = True


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class LookAheadQueue:
    """Pending moves, planned when enough are queued or when motion must stop."""

    __slots__ = ("queue", "junction_flush")

    def __init__(self) -> None:
        self.queue: list[Move] = []
        self.junction_flush = LOOKAHEAD_FLUSH_TIME

    def set_flush_time(self, flush_time: float) -> None:
        """Seconds of queued moves before the next lazy flush."""
        self.junction_flush = flush_time

    def is_empty(self) -> bool:
        """True when no move is pending."""
        return not self.queue

    def get_last(self) -> Move | None:
        """The most recently queued move, if any."""
        if self.queue:
            return self.queue[-1]
        return None

    def flush(self, lazy: bool = False) -> list[Move]:
        """Plan and remove the moves whose profile is final (all of them unless lazy)."""
        self.junction_flush = LOOKAHEAD_FLUSH_TIME
        update_flush_count = lazy
        queue = self.queue
        flush_count = len(queue)
        # Traverse queue from last to first move and determine maximum junction speed
        # assuming the robot comes to a complete stop after the last move.
        next_start_v2 = next_mcr_start_v2 = peak_cruise_v2 = 0.0
        pending_cv2_assign = 0
        for i in range(flush_count - 1, -1, -1):
            move = queue[i]
            reachable_start_v2 = next_start_v2 + move.delta_v2
            # min() written out as comparisons in this loop (same result, see calc_junction)
            start_v2 = move.max_start_v2
            if reachable_start_v2 < start_v2:
                start_v2 = reachable_start_v2
            cruise_v2 = NO_CRUISE_V2
            pending_cv2_assign += 1
            reach_mcr_start_v2 = next_mcr_start_v2 + move.mcr_delta_v2
            mcr_start_v2 = move.max_mcr_start_v2
            if reach_mcr_start_v2 < mcr_start_v2:
                mcr_start_v2 = reach_mcr_start_v2
            if mcr_start_v2 < reach_mcr_start_v2:
                # It's possible for this move to accelerate
                if (mcr_start_v2 + move.mcr_delta_v2 > next_mcr_start_v2
                        or pending_cv2_assign > 1):
                    # This move can both accel and decel, or this is a full accel
                    # move followed by a full decel move
                    if update_flush_count and peak_cruise_v2:
                        flush_count = i + pending_cv2_assign
                        update_flush_count = False
                    peak_cruise_v2 = (mcr_start_v2 + reach_mcr_start_v2) * 0.5
                cruise_v2 = (start_v2 + reachable_start_v2) * 0.5
                if move.max_cruise_v2 < cruise_v2:
                    cruise_v2 = move.max_cruise_v2
                if peak_cruise_v2 < cruise_v2:
                    cruise_v2 = peak_cruise_v2
                pending_cv2_assign = 0
            # junction_info[i] = (move, start_v2, cruise_v2, next_start_v2)
            move.flush_start_v2 = start_v2
            move.flush_cruise_v2 = cruise_v2
            move.flush_next_start_v2 = next_start_v2
            next_start_v2 = start_v2
            next_mcr_start_v2 = mcr_start_v2
        if update_flush_count or not flush_count:
            return []
        # Traverse queue in forward direction to propagate cruise_v2
        prev_cruise_v2 = 0.0
        for i in range(flush_count):
            move = queue[i]
            start_v2 = move.flush_start_v2
            cruise_v2 = move.flush_cruise_v2
            next_start_v2 = move.flush_next_start_v2
            if cruise_v2 == NO_CRUISE_V2:
                # This move can't accelerate - propagate cruise_v2 from previous
                cruise_v2 = start_v2 if start_v2 < prev_cruise_v2 else prev_cruise_v2
            move.set_junction(cruise_v2 if cruise_v2 < start_v2 else start_v2, cruise_v2,
                              cruise_v2 if cruise_v2 < next_start_v2 else next_start_v2)
            prev_cruise_v2 = cruise_v2
        # Remove processed moves from the queue
        res = queue[:flush_count]
        del queue[:flush_count]
        return res

    def add_move(self, move: Move) -> bool:
        """Queue a move; True when enough time is queued for a lazy flush."""
        queue = self.queue
        queue.append(move)
        if len(queue) == 1:
            return False
        move.calc_junction(queue[-2])
        junction_flush = self.junction_flush - move.min_move_t
        self.junction_flush = junction_flush
        # Check if enough moves have been queued to reach the target flush time.
        return junction_flush <= 0.0


# The lazy-flush time of Klipper before 16fc46fe5 (v0.13.0-340, 2025-10) and of Kalico.
LOOKAHEAD_FLUSH_TIME_V0_13: Final = 0.250


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class DelayedLookAheadQueue(LookAheadQueue):
    """The look-ahead of a Klipper before 41901ec38 (v0.13.0-300, 2025-09) and of Kalico
    v2026.07.00: flush() as klippy/toolhead.py of Klipper v0.13.0 has it (there the
    LookAheadQueue; in v0.12.0 the MoveQueue, the same code), upstream's max_smoothed_v2 /
    smooth_delta_v2 under the mcr names. Two differences in the plan: the peak cruise of a
    move that can accelerate is capped by that move's own max_cruise_v2, and the moves that
    cannot accelerate after it ("delayed") cruise at no more than that peak (mainline: no
    more than the cruise of the move before them). Where a lazy flush cuts (flush_count = i,
    LOOKAHEAD_FLUSH_TIME 0.250; 6118525c1, 16fc46fe5 changed them) changes no plan. The
    ToolHead makes it when `klipper_version` names such a release."""

    __slots__ = ()

    def __init__(self) -> None:
        super().__init__()
        self.junction_flush = LOOKAHEAD_FLUSH_TIME_V0_13

    def flush(self, lazy: bool = False) -> list[Move]:
        """Plan and remove the moves whose profile is final (all of them unless lazy)."""
        self.junction_flush = LOOKAHEAD_FLUSH_TIME_V0_13
        update_flush_count = lazy
        queue = self.queue
        flush_count = len(queue)
        # Traverse queue from last to first move and determine maximum junction speed
        # assuming the robot comes to a complete stop after the last move.
        delayed: list[Move] = []
        next_end_v2 = next_mcr_start_v2 = peak_cruise_v2 = 0.0
        for i in range(flush_count - 1, -1, -1):
            move = queue[i]
            reachable_start_v2 = next_end_v2 + move.delta_v2
            # min() written out as comparisons (same result, see LookAheadQueue.flush)
            start_v2 = move.max_start_v2
            if reachable_start_v2 < start_v2:
                start_v2 = reachable_start_v2
            reach_mcr_start_v2 = next_mcr_start_v2 + move.mcr_delta_v2
            mcr_start_v2 = move.max_mcr_start_v2
            if reach_mcr_start_v2 < mcr_start_v2:
                mcr_start_v2 = reach_mcr_start_v2
            if mcr_start_v2 < reach_mcr_start_v2:
                # It's possible for this move to accelerate
                if mcr_start_v2 + move.mcr_delta_v2 > next_mcr_start_v2 or delayed:
                    # This move can decelerate or this is a full accel move after a full
                    # decel move
                    if update_flush_count and peak_cruise_v2:
                        flush_count = i
                        update_flush_count = False
                    # upstream: min(move.max_cruise_v2, (smoothed_v2 + reachable...) * .5)
                    peak_cruise_v2 = (mcr_start_v2 + reach_mcr_start_v2) * 0.5
                    if move.max_cruise_v2 < peak_cruise_v2:
                        peak_cruise_v2 = move.max_cruise_v2
                    if delayed:
                        # Propagate peak_cruise_v2 to any delayed moves
                        if not update_flush_count and i < flush_count:
                            mc_v2 = peak_cruise_v2
                            for m in reversed(delayed):
                                ms_v2 = m.flush_start_v2
                                me_v2 = m.flush_next_start_v2
                                if ms_v2 < mc_v2:
                                    mc_v2 = ms_v2
                                m.set_junction(mc_v2 if mc_v2 < ms_v2 else ms_v2, mc_v2,
                                               mc_v2 if mc_v2 < me_v2 else me_v2)
                        del delayed[:]
                if not update_flush_count and i < flush_count:
                    cruise_v2 = (start_v2 + reachable_start_v2) * 0.5
                    if move.max_cruise_v2 < cruise_v2:
                        cruise_v2 = move.max_cruise_v2
                    if peak_cruise_v2 < cruise_v2:
                        cruise_v2 = peak_cruise_v2
                    move.set_junction(cruise_v2 if cruise_v2 < start_v2 else start_v2,
                                      cruise_v2,
                                      cruise_v2 if cruise_v2 < next_end_v2 else next_end_v2)
            else:
                # Delay calculating this move until peak_cruise_v2 is known
                # (upstream keeps (move, start_v2, next_end_v2) in the list)
                move.flush_start_v2 = start_v2
                move.flush_next_start_v2 = next_end_v2
                delayed.append(move)
            next_end_v2 = start_v2
            next_mcr_start_v2 = mcr_start_v2
        if update_flush_count or not flush_count:
            return []
        # Remove processed moves from the queue
        res = queue[:flush_count]
        del queue[:flush_count]
        return res


# Seconds of moves queued before the first flush after the toolhead was at rest.
BUFFER_TIME_HIGH: Final = 1.0
# Klipper v0.12.0's [printer] buffer_time_high default (the option went in bafb126ab,
# v0.12.0-20): how much a flushed look-ahead queues before it plans (ForceFlushToolHead).
BUFFER_TIME_HIGH_V0_12: Final = 2.0
# Junction deviation scale: sqrt(2) - 1.
_JD_FACTOR: Final = 2.0**0.5 - 1.0


# Main code to track events (and their timing) on the printer toolhead
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ToolHead:
    """Accumulates print time exactly as Klipper's toolhead does in batch mode."""

    def __init__(self, limits: Limits,
                 on_moves: Callable[[list[Move], float], None] | None = None) -> None:
        self.limits = limits
        release = klipper_release(limits.klipper_version) if limits.klipper_version else None
        # The look-ahead of the Klipper named by klipper_version (mainline without one).
        self.lookahead: LookAheadQueue = (
            DelayedLookAheadQueue() if release is not None and release.lookahead == "delayed"
            else LookAheadQueue())
        self.lookahead.set_flush_time(BUFFER_TIME_HIGH)
        # Upstream's commanded_pos list, one float per axis (see the commanded_pos property).
        self.commanded_x = self.commanded_y = self.commanded_z = self.commanded_e = 0.0
        # The last velocity a Move squared, and its square (see Move.__init__).
        self.last_velocity = self.last_velocity2 = math.nan
        # Velocity and acceleration control
        self.max_velocity = limits.max_velocity
        self.max_accel = limits.max_accel
        self.min_cruise_ratio = limits.minimum_cruise_ratio
        self.square_corner_velocity = limits.square_corner_velocity
        self.junction_deviation = self.mcr_pseudo_accel = 0.0
        self._calc_junction_deviation()
        # The junction rule of the Klipper named by klipper_version (mainline without one):
        # None for Move's, else the Move class with that release's calc_junction.
        self.old_junction_move: type[Move] | None = {
            "clamped": ClampedJunctionMove,
            "clamped_delta_v2": DeltaV2ClampedJunctionMove}.get(
                release.junction if release is not None else "mainline")
        # Whether a new pressure-advance window also waits for the toolhead
        # (kestimator.extruder's SET_PRESSURE_ADVANCE; the releases in KLIPPER_TOOLHEAD_RULES).
        self.pressure_advance_waits = (release is not None
                                       and release.pressure_advance_waits)
        # Whether every SET_PRESSURE_ADVANCE flushes step generation (Kalico), not only one
        # that changes the scan window.
        self.pressure_advance_always_flushes = (release is not None
                                                and release.pressure_advance_always_flushes)
        # M84/M18 as extras/stepper_enable.py's motor_off had it before set_motors_enable
        # (kestimator.interpreter's cmd_M84): the older toolheads' releases.
        self.old_motor_off = False
        # Print time tracking
        self.print_time = 0.0
        self.special_queuing_state = "NeedPrime"
        # End of the last planned move: what "every move so far has finished" means.
        self.last_move_end_t = 0.0
        # The tag (source line) of the last move queued.
        self.last_move_line: int | None = None
        # Whether a motor has moved since the last M84 (extras/stepper_enable.py).
        self.motors_enabled = False
        # Setup for generating moves
        self.motion_queuing = PrinterMotionQueuing()
        # Called with each batch of planned moves and the time the first of them starts.
        self.on_moves = on_moves
        # The active extruder (upstream's extra_axes[0]) and its corner velocity, kept
        # here for the Move built on every line.
        self.extruder = PrinterExtruder(limits.primary_extruder)
        self.instant_corner_v = self.extruder.instant_corner_v
        # Create kinematics class: homed at X=Y=Z=0 before the file's first line.
        self.kin = load_kinematics(limits)
        self.kin.attach_toolhead(self)
        self.kin.set_position(self.commanded_pos, "xyz")

    # Print time tracking
    def _calc_print_time(self) -> None:
        kin_time = self.motion_queuing.calc_step_gen_restart()
        if kin_time > self.print_time:
            self.print_time = kin_time

    def _process_lookahead(self, lazy: bool = False) -> None:
        moves = self.lookahead.flush(lazy=lazy)
        if not moves:
            return
        # Resync print_time if necessary
        if self.special_queuing_state:
            # Transition from "NeedPrime" to the main state
            self.special_queuing_state = ""
            self._calc_print_time()
        start_time = next_move_time = self.print_time
        for move in moves:
            next_move_time = next_move_time + move.accel_t + move.cruise_t + move.decel_t
            if move.timing_callbacks is not None:
                for cb in move.timing_callbacks:
                    cb(next_move_time)
        # Upstream queues the moves into its trapq here; we tell the observer.
        if self.on_moves is not None:
            self.on_moves(moves, start_time)
        self.motors_enabled = True
        self.last_move_end_t = next_move_time
        # Generate steps for moves (upstream's _advance_move_time)
        if next_move_time > self.print_time:
            self.print_time = next_move_time
        self.motion_queuing.note_mcu_movequeue_activity(next_move_time)

    def _flush_lookahead(self) -> None:
        # Transit from "NeedPrime"/main state to "NeedPrime"
        self._process_lookahead()
        self.special_queuing_state = "NeedPrime"
        self.lookahead.set_flush_time(BUFFER_TIME_HIGH)

    def flush_step_generation(self) -> None:
        """Bring the toolhead to rest and generate every step (homing, motors off)."""
        self._flush_lookahead()
        self.motion_queuing.flush_all_steps()

    def get_last_move_time(self) -> float:
        """Flush the look-ahead and return the time the next command would run at."""
        if self.special_queuing_state:
            self._flush_lookahead()
            self._calc_print_time()
        else:
            self._process_lookahead()
        return self.print_time

    # Movement commands
    @property
    def commanded_pos(self) -> tuple[float, float, float, float]:
        """Where the last queued move ends (x, y, z, e): upstream's get_position()."""
        return (self.commanded_x, self.commanded_y, self.commanded_z, self.commanded_e)

    def set_position(self, newpos: tuple[float, float, float, float],
                     homing_axes: str = "") -> None:
        """Homing / SET_KINEMATIC_POSITION: rest, then jump to newpos without moving;
        `homing_axes` ("xyz" letters) are homed from now on."""
        self.flush_step_generation()
        self.commanded_x, self.commanded_y, self.commanded_z, self.commanded_e = newpos
        self.kin.set_position(newpos, homing_axes)

    def move(self, newpos: tuple[float, float, float, float], speed: float,
             tag: int = 0) -> Move | None:
        """Queue a move to newpos at speed (mm/s); None when nothing moves."""
        return self.move_to(newpos[0], newpos[1], newpos[2], newpos[3], speed, tag)

    def move_to(self, x: float, y: float, z: float, e: float, speed: float,
                tag: int = 0) -> Move | None:
        """`move` with the new position as four floats (the hot path: no tuple per move);
        `tag` is the move's source line."""
        if self.old_junction_move is None:
            move = Move(self, self.commanded_x, self.commanded_y, self.commanded_z,
                        self.commanded_e, x, y, z, e, speed, tag)
        else:
            move = self.old_junction_move(self, self.commanded_x, self.commanded_y,
                                          self.commanded_z, self.commanded_e, x, y, z, e,
                                          speed, tag)
        if not move.move_d:
            return None
        if move.is_kinematic_move:
            self.kin.check_move(move)
        if move.axes_d_e:
            self.extruder.check_move(move)
        self.commanded_x = move.end_x
        self.commanded_y = move.end_y
        self.commanded_z = move.end_z
        self.commanded_e = move.end_e
        self.last_move_line = tag
        if self.lookahead.add_move(move):
            self._process_lookahead(lazy=True)
        return move

    def untimed_manual_move(self, coord: list[float | None], speed: float) -> None:
        """upstream's manual_move (coordinates given, None: unchanged) as the homing
        modules make it inside G28: checked as that move would be, then the head is set
        there without taking time (G28 takes no time: the oracle's convention, which
        --homing-time completes)."""
        pos = [self.commanded_x, self.commanded_y, self.commanded_z, self.commanded_e]
        for i, value in enumerate(coord):
            if value is not None:
                pos[i] = value
        move = Move(self, self.commanded_x, self.commanded_y, self.commanded_z,
                    self.commanded_e, pos[0], pos[1], pos[2], pos[3], speed, 0)
        if not move.move_d:
            return
        if move.is_kinematic_move:
            self.kin.check_move(move)
        self.set_position((pos[0], pos[1], pos[2], pos[3]))

    def dwell(self, delay: float) -> None:
        """G4: stop, then wait delay seconds."""
        self._flush_lookahead()
        next_print_time = self.get_last_move_time() + max(0.0, delay)
        if next_print_time > self.print_time:
            self.print_time = next_print_time

    def wait_moves(self) -> None:
        """M400: stop until every queued move has finished."""
        self._flush_lookahead()

    def run_out(self) -> None:
        """The input stops (a pause waits for a person): Klipper's step-flush handler runs
        the look-ahead out (`_handle_step_flush` -> `_flush_lookahead(is_runout=True)`),
        every queued move planned to end at rest, as M400 plans them."""
        self._flush_lookahead()

    def set_extruder(self, extruder: PrinterExtruder, extrude_pos: float) -> None:
        """ACTIVATE_EXTRUDER (after a full stop): that extruder's limits and E position."""
        self.extruder = extruder
        self.instant_corner_v = extruder.instant_corner_v
        self.commanded_e = extrude_pos

    def get_extruder(self) -> PrinterExtruder:
        """The active extruder."""
        return self.extruder

    def register_lookahead_callback(self, callback: TimingCallback) -> None:
        """Call back with the time at which every move queued so far has finished.

        Upstream calls back with get_last_move_time() when nothing is queued; a callback
        here only records a time, so the flush that would do is left out."""
        last_move = self.lookahead.get_last()
        if last_move is None:
            callback(self.last_move_end_t)
            return
        if last_move.timing_callbacks is None:
            last_move.timing_callbacks = [callback]
        else:
            last_move.timing_callbacks.append(callback)

    def lookahead_callback_barrier(self) -> None:
        """Upstream's register_lookahead_callback of a callback that only keeps order
        (extras/heaters.py set_temperature: M104, M140, M109, M190, SET_HEATER_TEMPERATURE;
        extras/fan.py set_speed_from_command: M106, M107, SET_FAN_SPEED).
        With nothing queued Klipper calls get_last_move_time, which moves no time with
        today's print-time rule (left out); the older rules' toolheads do it."""

    def _calc_junction_deviation(self) -> None:
        # upstream: square_corner_velocity**2 (math.pow: the same bits, and an overflow
        # is OverflowError on PyPy as on CPython, where ** gives PyPy inf)
        scv2 = math.pow(self.square_corner_velocity, 2.0)
        self.junction_deviation = scv2 * _JD_FACTOR / self.max_accel
        self.mcr_pseudo_accel = self.max_accel * (1.0 - self.min_cruise_ratio)

    def set_max_velocities(self, max_velocity: float | None, max_accel: float | None,
                           square_corner_velocity: float | None,
                           min_cruise_ratio: float | None) -> None:
        """SET_VELOCITY_LIMIT / M204: change limits for the moves that follow."""
        if max_velocity is not None:
            self.max_velocity = max_velocity
        if max_accel is not None:
            self.max_accel = max_accel
        if square_corner_velocity is not None:
            self.square_corner_velocity = square_corner_velocity
        if min_cruise_ratio is not None:
            self.min_cruise_ratio = min_cruise_ratio
        self._calc_junction_deviation()

    # Batch mode: what the printer does with the head at rest, and the end of the file.
    def wait_heater(self) -> None:
        """A heater wait: the toolhead comes to rest (its duration is added elsewhere)."""
        self.get_last_move_time()

    def add_time(self, seconds: float) -> None:
        """Time that passes with the toolhead at rest (homing, heating, user additions)."""
        self.dwell(seconds)

    def finish(self) -> float:
        """Flush everything; the total print time in seconds."""
        self._flush_lookahead()
        return self.print_time


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ForceFlushToolHead(ToolHead):
    """The print-time tracking of a Klipper before b7b13588c (v0.12.0-23, 2023-11), as
    klippy/toolhead.py of Klipper v0.12.0 has it (its `force_flush_time`): a full flush of
    step generation (`flush_step_generation`) takes the steps to at least
    print_time - kin_flush_delay (later than the last move after a dwell), and motion
    restarts kin_flush_delay after that, the delay as it is then (a new pressure-advance
    window after a dwell costs the difference of the two). G4 and M400 in the main state
    only flush the look-ahead, with no restart; a flushed look-ahead queues 2 s (its
    buffer_time_high) before it plans. Made by `make_toolhead` when
    `klipper_version` names such a release."""

    def __init__(self, limits: Limits,
                 on_moves: Callable[[list[Move], float], None] | None = None) -> None:
        super().__init__(limits, on_moves)
        self.old_motor_off = True
        self.lookahead.set_flush_time(BUFFER_TIME_HIGH_V0_12)
        # Klipper's force_flush_time and last_kin_move_time: before the origin (the
        # oracle's pre-roll dwell leaves both over a second before the first line).
        self.force_flush_time = -math.inf
        self.last_kin_move_time = -math.inf

    def _calc_print_time(self) -> None:
        kin_time = self.force_flush_time + self.motion_queuing.kin_flush_delay
        if kin_time > self.print_time:
            self.print_time = kin_time

    def _process_lookahead(self, lazy: bool = False) -> None:
        super()._process_lookahead(lazy)
        # upstream: last_kin_move_time = max(last_kin_move_time, next_move_time) once moves
        # are queued (need_step_gen_time is -inf until the first are)
        if (self.motion_queuing.need_step_gen_time > -math.inf
                and self.last_move_end_t > self.last_kin_move_time):
            self.last_kin_move_time = self.last_move_end_t

    def _flush_lookahead(self) -> None:
        if self.special_queuing_state:
            self.flush_step_generation()
            return
        self._process_lookahead()

    def flush_step_generation(self) -> None:
        """Bring the toolhead to rest and take step generation past the last move."""
        # Transition from "Flushed"/"Priming"/main state to "Flushed" state
        self._process_lookahead()
        self.special_queuing_state = "Flushed"
        self.lookahead.set_flush_time(BUFFER_TIME_HIGH_V0_12)
        self.motion_queuing.flush_all_steps()
        kin_flush_delay = self.motion_queuing.kin_flush_delay
        # Determine actual last "itersolve" flush time
        lastf = self.print_time - kin_flush_delay
        # Calculate flush time that includes kinematic scan windows
        flush_time = max(lastf, self.last_kin_move_time + kin_flush_delay)
        if flush_time > self.print_time:
            self.print_time = flush_time
        # Flush kinematic scan windows and step buffers
        self.force_flush_time = max(self.force_flush_time, flush_time)
        if self.force_flush_time > self.print_time:
            self.print_time = self.force_flush_time

    def get_last_move_time(self) -> float:
        """Flush the look-ahead and return the time the next command would run at."""
        self._flush_lookahead()
        if self.special_queuing_state:
            self._calc_print_time()
        return self.print_time

    def dwell(self, delay: float) -> None:
        """G4: flush the look-ahead, then wait delay seconds."""
        next_print_time = self.get_last_move_time() + max(0.0, delay)
        if next_print_time > self.print_time:
            self.print_time = next_print_time

    def wait_moves(self) -> None:
        """M400: flush the look-ahead."""
        self._flush_lookahead()


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class MinRestartToolHead(ToolHead):
    """The print-time tracking of Klipper 3d3b87f97 (v0.12.0-69, 2024-01) to v0.13.0-237
    (its `min_restart_time`, replaced in 1e7c67919), as klippy/toolhead.py of Klipper v0.13.0
    has it: a full flush of step generation (`flush_step_generation`) also takes the restart
    to print_time, so motion restarts at least kin_flush_delay after the flush (after a dwell
    too), and the homing flush at the origin delays the first move by it. Kalico
    v2026.07.00's klippy/toolhead.py has it too. Made by `make_toolhead` when
    `klipper_version` names such a release."""

    def __init__(self, limits: Limits,
                 on_moves: Callable[[list[Move], float], None] | None = None) -> None:
        super().__init__(limits, on_moves)
        # v0.13.0's and Kalico v2026.07.00's stepper_enable.py: motor_off without a flush.
        self.old_motor_off = True
        # The head starts homed: the homing's flush_step_generation at the origin.
        self.motion_queuing.last_step_gen_time = 0.0

    def lookahead_callback_barrier(self) -> None:
        """With nothing queued, get_last_move_time: in a flushed state that takes
        print_time to min_restart_time + kin_flush_delay (before the first move too)."""
        if self.lookahead.get_last() is None:
            self.get_last_move_time()

    def flush_step_generation(self) -> None:
        """Bring the toolhead to rest; motion restarts no sooner than after this time."""
        super().flush_step_generation()
        # upstream: self.min_restart_time = max(self.min_restart_time, self.print_time)
        if self.print_time > self.motion_queuing.last_step_gen_time:
            self.motion_queuing.last_step_gen_time = self.print_time


def make_toolhead(limits: Limits,
                  on_moves: Callable[[list[Move], float], None] | None = None) -> ToolHead:
    """The ToolHead of the Klipper `limits.klipper_version` names (today's without one)."""
    rule = klipper_release(limits.klipper_version).print_time if limits.klipper_version else ""
    if rule == "force_flush":
        return ForceFlushToolHead(limits, on_moves)
    if rule == "min_restart":
        return MinRestartToolHead(limits, on_moves)
    return ToolHead(limits, on_moves)


# Support common G-Code commands relative to the toolhead
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ToolHeadCommandHelper:
    """G4, M400, SET_VELOCITY_LIMIT and M204.

    `limits.klipper_generation` makes SET_VELOCITY_LIMIT ACCEL_TO_DECEL mean what it meant
    on the printer's Klipper: ignored by mainline (as upstream), a minimum cruise ratio from
    2024-03 to 2025-08 ("mcr"), the absolute cruise-smoothing accel before ("absolute").
    """

    def __init__(self, limits: Limits, toolhead: ToolHead,
                 warn: Callable[[str, str | None], None]) -> None:
        self.limits = limits
        self.toolhead = toolhead
        self.warn = warn
        # Old Klipper's absolute accel_to_decel ("absolute" generation only).
        self.requested_accel_to_decel = limits.max_accel_to_decel or limits.max_accel * 0.5
        # Kalico's SET_VELOCITY_LIMIT and RESET_VELOCITY_LIMIT (klipper_version names Kalico).
        self.kalico = bool(limits.klipper_version) and klipper_release(
            limits.klipper_version).is_kalico
        # Kalico's orig_cfg: the kinematics' per-axis limits as [printer] gave them.
        self.configured_axis_limits: dict[str, float] = {
            attr: getattr(toolhead.kin, attr) for _, attr, _ in self.KALICO_AXIS_LIMITS
            if self.kalico and hasattr(toolhead.kin, attr)}
        if limits.klipper_generation == "absolute":
            self._apply_absolute_accel_to_decel()

    def cmd_G4(self, cmd: Command) -> None:
        """Dwell P milliseconds (Klipper ignores S)."""
        delay = get_float(cmd.params, "P", 0.0, minval=0.0) / 1000.0
        self.toolhead.dwell(delay)

    def cmd_M400(self, cmd: Command) -> None:
        """Wait for all moves to finish."""
        self.toolhead.wait_moves()

    def cmd_SET_VELOCITY_LIMIT(self, cmd: Command) -> None:
        """Change velocity, accel, square corner velocity or minimum cruise ratio."""
        params = command_params(cmd)
        max_velocity = get_float(params, "VELOCITY", above=0.0)
        max_accel = get_float(params, "ACCEL", above=0.0)
        scv = get_float(params, "SQUARE_CORNER_VELOCITY", minval=0.0)
        mcr = get_float(params, "MINIMUM_CRUISE_RATIO", minval=0.0, below=1.0)
        generation = self.limits.klipper_generation
        if generation != "mainline":
            accel_to_decel = get_float(params, "ACCEL_TO_DECEL", above=0.0)
            if accel_to_decel is not None and generation == "mcr" and mcr is None:
                accel = max_accel if max_accel is not None else self.toolhead.max_accel
                mcr = 1.0 - min(1.0, accel_to_decel / accel)
            elif accel_to_decel is not None and generation == "absolute":
                self.requested_accel_to_decel = accel_to_decel
        if self.kalico:
            # Kalico reads them after setting the above, before _calc_junction_deviation.
            try:
                self.set_kalico_axis_limits(params)
            finally:
                self.toolhead.set_max_velocities(max_velocity, max_accel, scv, mcr)
            return
        self.toolhead.set_max_velocities(max_velocity, max_accel, scv, mcr)
        self._apply_absolute_accel_to_decel()

    # Kalico's toolhead.py: SET_VELOCITY_LIMIT also sets the kinematics' per-axis limits
    # it has (X_VELOCITY ... Z_ACCEL: hasattr(self.kin, "max_x_velocity") ...), and
    # RESET_VELOCITY_LIMIT restores what [printer] gave (its orig_cfg); neither flushes.
    KALICO_AXIS_LIMITS = (("X_VELOCITY", "max_x_velocity", None),
                          ("X_ACCEL", "max_x_accel", None),
                          ("Y_VELOCITY", "max_y_velocity", None),
                          ("Y_ACCEL", "max_y_accel", None),
                          ("Z_VELOCITY", "max_z_velocity", 0.0),
                          ("Z_ACCEL", "max_z_accel", 0.0))

    def set_kalico_axis_limits(self, params: dict[str, str]) -> None:
        """Kalico's SET_VELOCITY_LIMIT X_VELOCITY=, X_ACCEL=, ... Z_ACCEL= (read after the
        other parameters, set on the kinematics where it has the attribute)."""
        kin = self.toolhead.kin
        for param, attr, above in self.KALICO_AXIS_LIMITS:
            if hasattr(kin, attr):
                value = get_float(params, param, above=above)
                if value is not None:
                    setattr(kin, attr, value)

    def cmd_SET_KINEMATICS_LIMIT(self, cmd: Command) -> None:
        """Kalico's limited_* kinematics (kestimator.kinematics.limited_*): X_VELOCITY=,
        Y_VELOCITY=, Z_VELOCITY= (where it has velocities), X_ACCEL=, Y_ACCEL=, Z_ACCEL=,
        SCALE=0|1, each the current value when not given, set in that order."""
        params = command_params(cmd)
        kin = self.toolhead.kin
        known = kin.kinematics_limits()
        if known is None:
            return
        velocities, accels, _scale = known
        if velocities is not None:
            velocities = [get_float(params, ax + "_VELOCITY", max_v, above=0.0)
                          for max_v, ax in zip(velocities, "XYZ")]
            kin.set_kinematics_limits(velocities, None, None)
        accels = [get_float(params, ax + "_ACCEL", max_a, above=0.0)
                  for max_a, ax in zip(accels, "XYZ")]
        kin.set_kinematics_limits(None, accels, None)
        text = params.get("SCALE")
        if text is not None:
            try:
                value = int(text)
            except ValueError:
                raise ParamError("unable to parse %s" % text) from None
            if value < 0:
                raise ParamError("SCALE must have minimum of 0")
            if value > 1:
                raise ParamError("SCALE must have maximum of 1")
            kin.set_kinematics_limits(None, None, bool(value))

    def cmd_RESET_VELOCITY_LIMIT(self, cmd: Command) -> None:
        """Kalico: [printer]'s velocity, accel, kinematics' per-axis limits, square corner
        velocity and minimum cruise ratio again."""
        limits, kin = self.limits, self.toolhead.kin
        for attr, value in self.configured_axis_limits.items():
            setattr(kin, attr, value)
        self.toolhead.set_max_velocities(limits.max_velocity, limits.max_accel,
                                         limits.square_corner_velocity,
                                         limits.minimum_cruise_ratio)

    def cmd_M204(self, cmd: Command) -> None:
        """M204 S<accel>, or both P and T (their minimum); P alone changes nothing."""
        accel = get_float(cmd.params, "S", above=0.0)
        if accel is None:
            p = get_float(cmd.params, "P", above=0.0)
            t = get_float(cmd.params, "T", above=0.0)
            if p is None or t is None:
                self.warn("M204 without S needs both P and T; Klipper ignores '%s'"
                          % cmd.code.strip(), "m204-incomplete")
                return
            accel = min(p, t)
        self.toolhead.set_max_velocities(None, accel, None, None)
        self._apply_absolute_accel_to_decel()

    def _apply_absolute_accel_to_decel(self) -> None:
        """Old Klipper: the cruise-smoothing accel is min(accel_to_decel, max_accel)."""
        if self.limits.klipper_generation != "absolute":
            return
        toolhead = self.toolhead
        toolhead.mcr_pseudo_accel = min(self.requested_accel_to_decel, toolhead.max_accel)
