"""Klipper's look-ahead: one requested move (`Move`) and the queue that plans them.

Re-implemented from mainline Klipper, `klippy/toolhead.py` at commit 84104bbbd
(Copyright (C) 2016-2025 Kevin O'Connor, GNU GPLv3), the `Move` and `LookAheadQueue`
classes, with the extruder's junction limit from `klippy/kinematics/extruder.py`.
Names follow upstream so the two can be read side by side; the arithmetic is done in the
same order as upstream so results agree to the last bit where possible.

The planner does no I/O and knows no G-code. Positions are (x, y, z, e) in mm.

Unit suffixes (Klipper's legend): _d is distance (mm), _v is velocity (mm/s), _v2 is
velocity squared (mm^2/s^2), _t is time (s), _r is a ratio.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from math import sqrt
from typing import Final

# Klipper's accel for extrude-only moves ("unlimited" before the extruder limits apply).
EXTRUDE_ONLY_ACCEL: Final = 99999999.9
# No limit yet on the next junction.
UNLIMITED_JUNCTION_V2: Final = 999999999.9
# A move shorter than this in XYZ is an extrude-only move.
MIN_KINEMATIC_MOVE_D: Final = 0.000000001
# Seconds of queued moves after which the queue tries a lazy flush.
LOOKAHEAD_FLUSH_TIME: Final = 0.150
# LookAheadQueue.flush: this move cannot accelerate (upstream's cruise_v2 = None); every
# real cruise_v2 is >= 0.
NO_CRUISE_V2: Final = -1.0



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

    def __init__(self, start_x: float, start_y: float, start_z: float, start_e: float,
                 end_x: float, end_y: float, end_z: float, end_e: float, speed: float,
                 max_velocity: float, max_accel: float, junction_deviation: float,
                 mcr_pseudo_accel: float, instant_corner_v: float, tag: int = 0) -> None:
        self.start_x = start_x
        self.start_y = start_y
        self.start_z = start_z
        self.start_e = start_e
        self.end_x = end_x
        self.end_y = end_y
        self.end_z = end_z
        self.end_e = end_e
        self.accel = max_accel
        self.junction_deviation = junction_deviation
        self.instant_corner_v = instant_corner_v
        # The source line of the move (0 when not from a file).
        self.tag = tag
        self.timing_callbacks: list[Callable[[float], None]] | None = None
        # min(speed, max_velocity), written out (this runs once per move)
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
        self.max_cruise_v2 = math.pow(velocity, 2.0)  # upstream: velocity**2
        self.delta_v2 = 2.0 * move_d * self.accel
        self.next_junction_v2 = UNLIMITED_JUNCTION_V2
        # Setup for minimum_cruise_ratio checks
        self.max_mcr_start_v2 = 0.0
        self.mcr_delta_v2 = 2.0 * move_d * mcr_pseudo_accel
        # Every attribute set here, though flush and set_junction set them again: PyPy
        # then gives each Move one fixed layout (estimate on the 40 MB file: 1.73 s CPU
        # without these lines, 1.35 s with; CPython and the compiled build unchanged).
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
        speed2 = math.pow(speed, 2.0)  # upstream: speed**2
        if speed2 < self.max_cruise_v2:
            self.max_cruise_v2 = speed2
            self.min_move_t = self.move_d / speed
        self.accel = min(self.accel, accel)
        self.delta_v2 = 2.0 * self.move_d * self.accel
        self.mcr_delta_v2 = min(self.mcr_delta_v2, self.delta_v2)

    def calc_junction(self, prev_move: "Move") -> None:
        """Maximum start speed from the corner with `prev_move` (junction deviation)."""
        if not self.is_kinematic_move or not prev_move.is_kinematic_move:
            return
        # The extruder is an extra axis: it limits the junction by its change of E/mm.
        max_cruise_v2 = self.max_cruise_v2
        diff_r = self.axes_r_e - prev_move.axes_r_e
        if diff_r:
            ea_v2 = math.pow(self.instant_corner_v / abs(diff_r), 2.0)
        else:
            ea_v2 = max_cruise_v2
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
        self.junction_flush -= move.min_move_t
        # Check if enough moves have been queued to reach the target flush time.
        return self.junction_flush <= 0.0
