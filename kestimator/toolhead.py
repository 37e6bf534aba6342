"""The toolhead: owns print time, kinematic and extruder limits, and when motion stops.

Re-implemented from mainline Klipper at commit 84104bbbd (GNU GPLv3):
`klippy/toolhead.py` (ToolHead: move, dwell, wait_moves, flush handling, print-time
tracking), `klippy/kinematics/extruder.py`
(extruder limits), `klippy/extras/motion_queuing.py` (the step-generation restart delay) and
`klippy/extras/stepper_enable.py` (M84 dwells).

Time starts at 0 when the first motion (or dwell) starts. A full look-ahead flush happens
exactly where Klipper's toolhead comes to rest: dwells, M400, homing, heater waits and
stepper disabling. After homing or a stepper-enable change, Klipper restarts step
generation 2 x kin_flush_delay after the last move; that gap is counted as Klipper does.

`ToolHead.move` calls the printer's kinematics (`kestimator.kinematics`) for every move with
XYZ motion, as upstream's `self.kin.check_move(move)`: range checks and the kinematics' own
speed limits. The head starts homed at X=Y=Z=0 (the oracle's convention: the start macro that
homes is not in the file).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

from kestimator.kinematics import MoveError, load_kinematics
from kestimator.limits import ExtruderLimits, Limits
from kestimator.planner import LookAheadQueue, Move
from kestimator.stepgen import SDS_CHECK_TIME_T

__all__ = ["MoveError", "ToolHead"]

# Seconds of moves queued before the first flush after the toolhead was at rest.
BUFFER_TIME_HIGH: Final = 1.0
# motion_queuing's step-generation scan window (SDS_CHECK_TIME) with no input shaper or
# pressure-advance smoothing: restarting after a full step flush waits this twice.
KIN_FLUSH_DELAY_T: Final = SDS_CHECK_TIME_T
# stepper_enable's dwell before and after turning motors off.
DISABLE_STALL_T: Final = 0.100
# Junction deviation scale: sqrt(2) - 1.
_JD_FACTOR: Final = 2.0**0.5 - 1.0

TimingCallback = Callable[[float], None]


class ToolHead:
    """Accumulates print time exactly as Klipper's toolhead does in batch mode."""

    def __init__(self, limits: Limits,
                 on_moves: Callable[[list[Move], float], None] | None = None) -> None:
        self.limits = limits
        self.lookahead = LookAheadQueue()
        self.lookahead.set_flush_time(BUFFER_TIME_HIGH)
        # Upstream's commanded_pos list, one float per axis (see the commanded_pos property).
        self.commanded_x = self.commanded_y = self.commanded_z = self.commanded_e = 0.0
        self.max_velocity = limits.max_velocity
        self.max_accel = limits.max_accel
        self.min_cruise_ratio = limits.minimum_cruise_ratio
        self.square_corner_velocity = limits.square_corner_velocity
        self.junction_deviation = self.mcr_pseudo_accel = 0.0
        self._calc_junction_deviation()
        self.print_time = 0.0
        # End of the last planned move: what "every move so far has finished" means.
        self.last_move_end_t = 0.0
        # The tag (source line) of the last move queued.
        self.last_move_line: int | None = None
        self.special_queuing_state = "NeedPrime"
        # motion_queuing state: how far steps have been generated, and how far they must be
        # (-inf until the first move: before it, Klipper's start buffer dominates).
        self.last_step_gen_t = float("-inf")
        self.need_step_gen_t = float("-inf")
        self.motors_enabled = False
        # motion_queuing.kin_flush_delay: the widest step-generation scan window (set by
        # the interpreter from pressure advance and the input shaper, kestimator.stepgen).
        self.kin_flush_delay = KIN_FLUSH_DELAY_T
        self.on_moves = on_moves
        # The printer's kinematics, homed at X=Y=Z=0 before the file's first line.
        self.kin = load_kinematics(limits)
        self.kin.set_position(self.commanded_pos, "xyz")
        # Extruder limits, looked up once.
        self.extruder = limits.primary_extruder
        self._set_extruder_limits(self.extruder)

    def _set_extruder_limits(self, extruder: ExtruderLimits) -> None:
        self._max_e_velocity = extruder.max_extrude_only_velocity
        self._max_e_accel = extruder.max_extrude_only_accel
        self._max_e_dist = extruder.max_extrude_only_distance
        self._max_extrude_ratio = extruder.max_extrude_ratio
        self._nozzle_diameter = extruder.nozzle_diameter
        self._filament_area = extruder.filament_area
        self._instant_corner_v = extruder.instantaneous_corner_velocity

    def set_extruder(self, extruder: ExtruderLimits, extrude_pos: float) -> None:
        """ACTIVATE_EXTRUDER (after a full stop): that extruder's limits and E position."""
        self.extruder = extruder
        self._set_extruder_limits(extruder)
        self.commanded_e = extrude_pos

    # Velocity and acceleration control
    def _calc_junction_deviation(self) -> None:
        scv2 = self.square_corner_velocity**2
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

    # Print time tracking
    def _calc_print_time(self) -> None:
        kin_time = self.last_step_gen_t + self.kin_flush_delay
        if kin_time > self.print_time:
            self.print_time = kin_time

    def _process_lookahead(self, lazy: bool = False) -> None:
        moves = self.lookahead.flush(lazy=lazy)
        if not moves:
            return
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
        if self.on_moves is not None:
            self.on_moves(moves, start_time)
        self.motors_enabled = True
        self.last_move_end_t = next_move_time
        if next_move_time > self.print_time:
            self.print_time = next_move_time
        need = next_move_time + self.kin_flush_delay
        if need > self.need_step_gen_t:
            self.need_step_gen_t = need

    def _flush_lookahead(self) -> None:
        self._process_lookahead()
        self.special_queuing_state = "NeedPrime"
        self.lookahead.set_flush_time(BUFFER_TIME_HIGH)

    def flush_step_generation(self) -> None:
        """Bring the toolhead to rest and generate every step (homing, motors off)."""
        self._flush_lookahead()
        if self.need_step_gen_t > self.last_step_gen_t:
            self.last_step_gen_t = self.need_step_gen_t

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
        """Where the last queued move ends (x, y, z, e)."""
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
        """`move` with the new position as four floats (the hot path: no tuple per move)."""
        move = Move(self.commanded_x, self.commanded_y, self.commanded_z, self.commanded_e,
                    x, y, z, e, speed, self.max_velocity, self.max_accel,
                    self.junction_deviation, self.mcr_pseudo_accel, self._instant_corner_v, tag)
        if not move.move_d:
            return None
        if move.is_kinematic_move:
            self.kin.check_move(move)
        if move.axes_d_e:
            self._check_extruder_move(move)
        self.commanded_x = move.end_x
        self.commanded_y = move.end_y
        self.commanded_z = move.end_z
        self.commanded_e = move.end_e
        self.last_move_line = tag
        if self.lookahead.add_move(move):
            self._process_lookahead(lazy=True)
        return move

    def _check_extruder_move(self, move: Move) -> None:
        axis_r = move.axes_r_e
        axis_d = move.axes_d_e
        if (not move.axes_d_x and not move.axes_d_y) or axis_r < 0.0:
            # Extrude only move (or retraction move) - limit accel and velocity
            if abs(axis_d) > self._max_e_dist:
                raise MoveError(
                    "Extrude only move too long (%.3fmm vs %.3fmm)\nSee the "
                    "'max_extrude_only_distance' config option for details"
                    % (axis_d, self._max_e_dist))
            inv_extrude_r = 1.0 / abs(axis_r)
            move.limit_speed(self._max_e_velocity * inv_extrude_r,
                             self._max_e_accel * inv_extrude_r)
        elif axis_r > self._max_extrude_ratio:
            if axis_d <= self._nozzle_diameter * self._max_extrude_ratio:
                # Permit extrusion if amount extruded is tiny
                return
            area = axis_r * self._filament_area
            raise MoveError(
                "Move exceeds maximum extrusion (%.3fmm^2 vs %.3fmm^2)\nSee the "
                "'max_extrude_cross_section' config option for details"
                % (area, self._max_extrude_ratio * self._filament_area))

    def dwell(self, delay: float) -> None:
        """G4: stop, then wait delay seconds."""
        self._flush_lookahead()
        next_print_time = self.get_last_move_time() + max(0.0, delay)
        if next_print_time > self.print_time:
            self.print_time = next_print_time

    def wait_moves(self) -> None:
        """M400: stop until every queued move has finished."""
        self._flush_lookahead()

    def wait_heater(self) -> None:
        """A heater wait: the toolhead comes to rest (its duration is added elsewhere)."""
        self.get_last_move_time()

    def motor_off(self) -> None:
        """M84/M18: stop, dwell, disable the motors that were on, dwell again; every axis is
        unhomed (a later XYZ move without G28 is "Must home axis first")."""
        self.flush_step_generation()
        if self.motors_enabled:
            self.dwell(DISABLE_STALL_T)
            self.get_last_move_time()
            self.dwell(DISABLE_STALL_T)
            self.motors_enabled = False
        self.kin.clear_homing_state("xyz")

    def register_lookahead_callback(self, callback: TimingCallback) -> None:
        """Call back with the time at which every move queued so far has finished."""
        last_move = self.lookahead.get_last()
        if last_move is None:
            callback(self.last_move_end_t)
            return
        if last_move.timing_callbacks is None:
            last_move.timing_callbacks = [callback]
        else:
            last_move.timing_callbacks.append(callback)

    def add_time(self, seconds: float) -> None:
        """Time that passes with the toolhead at rest (homing, heating, user additions)."""
        self.dwell(seconds)

    def finish(self) -> float:
        """Flush everything; the total print time in seconds."""
        self._flush_lookahead()
        return self.print_time
