"""Mirrors klippy/kinematics/extruder.py at Klipper commit 84104bbbd (GNU GPLv3).

Owns the extruders: each extruder stepper's pressure advance and motion queue
(`ExtruderStepper`: SET_PRESSURE_ADVANCE, SET_EXTRUDER_ROTATION_DISTANCE,
SYNC_EXTRUDER_MOTION), each [extruderN]'s move checks and limits (`PrinterExtruder`:
check_move, ACTIVATE_EXTRUDER), and, as upstream's `register_mux_command` does, which of
them a command's EXTRUDER= names (`PrinterExtruders`).

The extruder's junction limit (upstream's `PrinterExtruder.calc_junction`) is computed in
`toolhead.Move.calc_junction`, where it runs once per move. Heaters (M104/M109, with
`check_move`'s `heater.can_extrude`) are `kestimator.heaters`'.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from kestimator.errors import CommandError, MoveError, ParamError, fixed
from kestimator.gcode import Command, command_params, get_float, mux_error
from kestimator.limits import ExtruderLimits, Limits
from kestimator.stepgen import MAX_SMOOTH_TIME_T, pressure_advance_window

if TYPE_CHECKING:
    from kestimator.toolhead import Move, ToolHead

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

# pressure_advance_smooth_time's default (of an [extruder_stepper] whose options are unknown).
EXTRUDER_STEPPER_SMOOTH_TIME = 0.040


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ExtruderStepper:
    """One extruder stepper: its pressure advance and whether it follows a motion queue."""

    def __init__(self, name: str, pressure_advance: float, smooth_time: float) -> None:
        self.name = name
        self.pressure_advance = pressure_advance
        self.pressure_advance_smooth_time = smooth_time
        # Synced to an extruder's motion queue (upstream's motion_queue is its name).
        self.motion_queue = True

    def get_scan_window(self) -> float:
        """Its step-generation scan window (while synced to a motion queue)."""
        return pressure_advance_window(self.pressure_advance, self.pressure_advance_smooth_time)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class PrinterExtruder:
    """One [extruder] / [extruderN]: the limits `check_move` applies to moves that extrude."""

    def __init__(self, limits: ExtruderLimits) -> None:
        self.name = limits.name
        self.limits = limits
        self.nozzle_diameter = limits.nozzle_diameter
        self.filament_area = limits.filament_area
        self.max_extrude_ratio = limits.max_extrude_ratio
        self.max_e_velocity = limits.max_extrude_only_velocity
        self.max_e_accel = limits.max_extrude_only_accel
        self.max_e_dist = limits.max_extrude_only_distance
        self.instant_corner_v = limits.instantaneous_corner_velocity
        # Its E position while another extruder is active.
        self.last_position = 0.0
        # Upstream's heater.can_extrude; False until kestimator.heaters sees the heater
        # set hot, and then `cold_extrude` decides (Klipper's error or a pre-flight note).
        self.can_extrude = True
        self.cold_extrude: Callable[[PrinterExtruder], None] | None = None

    def check_move(self, move: Move) -> None:
        """Refuse extruding while cold; limit an extrude-only or retracting move; refuse
        over-extrusion."""
        if not self.can_extrude and self.cold_extrude is not None:
            self.cold_extrude(self)
        axis_r = move.axes_r_e
        axis_d = move.axes_d_e
        if (not move.axes_d_x and not move.axes_d_y) or axis_r < 0.0:
            # Extrude only move (or retraction move) - limit accel and velocity
            if abs(axis_d) > self.max_e_dist:
                raise MoveError(
                    "Extrude only move too long (%smm vs %smm)\nSee the "
                    "'max_extrude_only_distance' config option for details"
                    % (fixed(axis_d), fixed(self.max_e_dist)))
            inv_extrude_r = 1.0 / abs(axis_r)
            move.limit_speed(self.max_e_velocity * inv_extrude_r,
                             self.max_e_accel * inv_extrude_r)
        elif axis_r > self.max_extrude_ratio:
            if axis_d <= self.nozzle_diameter * self.max_extrude_ratio:
                # Permit extrusion if amount extruded is tiny
                return
            area = axis_r * self.filament_area
            raise MoveError(
                "Move exceeds maximum extrusion (%smm^2 vs %smm^2)\nSee the "
                "'max_extrude_cross_section' config option for details"
                % (fixed(area), fixed(self.max_extrude_ratio * self.filament_area)))


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class PrinterExtruders:
    """Every extruder and extruder stepper of the printer, and their commands.

    Upstream registers each command once per object with `register_mux_command` on
    EXTRUDER=; here one handler looks the object up the same way (`_mux`).
    """

    def __init__(self, limits: Limits, toolhead: ToolHead,
                 on_activate: Callable[[], None]) -> None:
        self.toolhead = toolhead
        # gcode_move's handler of the "extruder:activate_extruder" event.
        self.on_activate = on_activate
        self.extruders: dict[str, PrinterExtruder] = {"extruder": toolhead.get_extruder()}
        for extruder in limits.extruders:
            self.extruders[extruder.name] = PrinterExtruder(extruder)
        self.active = "extruder"
        # Extruders with a stepper, then each [extruder_stepper NAME] with its own
        # pressure advance, following its extruder's motion queue from the start (as
        # extras/extruder_stepper.py syncs it at connect) or none.
        self.steppers: dict[str, ExtruderStepper] = {
            name: ExtruderStepper(name, e.limits.pressure_advance,
                                  e.limits.pressure_advance_smooth_time)
            for name, e in self.extruders.items() if e.limits.has_stepper}
        for config in limits.extruder_steppers:
            stepper = ExtruderStepper(config.name, config.pressure_advance,
                                      config.pressure_advance_smooth_time)
            stepper.motion_queue = config.extruder in self.extruders
            self.steppers[config.name] = stepper
        # [extruder_stepper NAME]s known by name only (a Moonraker cache of an older
        # kestimator): their pressure advance is not known and counts as off.
        self.extra_steppers = [section.split(None, 1)[1].strip()
                               for section in limits.configured_sections
                               if section.startswith("extruder_stepper ")
                               and len(section.split(None, 1)) == 2
                               and section.split()[-1] not in self.steppers]
        for name in self.extra_steppers:
            self.steppers[name] = ExtruderStepper(name, 0.0, EXTRUDER_STEPPER_SMOOTH_TIME)

    def scan_windows(self) -> list[float]:
        """The scan window of every stepper synced to a motion queue."""
        return [stepper.get_scan_window() for stepper in self.steppers.values()
                if stepper.motion_queue]

    def _check_scan_windows(self) -> None:
        self.toolhead.motion_queuing.check_step_generation_scan_windows()

    @staticmethod
    def _mux(params: dict[str, str], choices: list[str], default: str | None) -> str:
        """The EXTRUDER= a mux command names (gcode.py _cmd_mux), checked."""
        key = params.get("EXTRUDER")
        if key is None:
            if default is not None:
                return default
            raise ParamError("missing EXTRUDER")
        if key not in choices:
            raise mux_error(key, "EXTRUDER", choices)
        return key

    # PrinterExtruder
    def cmd_ACTIVATE_EXTRUDER(self, cmd: Command) -> None:
        """Full stop of step generation, then that extruder's limits and E position."""
        params = command_params(cmd)
        name = self._mux(params, list(self.extruders), None)
        if name == self.active:
            return
        toolhead = self.toolhead
        toolhead.flush_step_generation()
        self.extruders[self.active].last_position = toolhead.commanded_pos[3]
        self.active = name
        extruder = self.extruders[name]
        toolhead.set_extruder(extruder, extruder.last_position)
        self.on_activate()

    # ExtruderStepper
    def cmd_SET_PRESSURE_ADVANCE(self, cmd: Command) -> None:
        """Change pressure advance; a changed smoothing window stops step generation."""
        params = command_params(cmd)
        default = None
        if "extruder" in self.steppers:
            default = self.active
        name = self._mux(params, list(self.steppers), default)
        stepper = self.steppers.get(name)
        if stepper is None:
            raise CommandError("Active extruder does not have a stepper")
        if "EXTRUDER" not in params and not stepper.motion_queue:
            raise CommandError("Unable to infer active extruder stepper")
        old_advance = stepper.pressure_advance
        old_smooth = stepper.pressure_advance_smooth_time
        advance = get_float(params, "ADVANCE", old_advance, minval=0.0)
        smooth_time = get_float(params, "SMOOTH_TIME", old_smooth, minval=0.0)
        if smooth_time > MAX_SMOOTH_TIME_T:
            raise ParamError("SMOOTH_TIME must have maximum of %s" % MAX_SMOOTH_TIME_T)
        new_window = (pressure_advance_window(advance, smooth_time)
                      != pressure_advance_window(old_advance, old_smooth))
        if new_window or self.toolhead.pressure_advance_always_flushes:
            # Need full kinematic flush to change the smooth time (Klipper before
            # v0.12.0-262 and Kalico: always)
            self.toolhead.flush_step_generation()
        stepper.pressure_advance = advance
        stepper.pressure_advance_smooth_time = smooth_time
        if new_window:
            self._check_scan_windows()
        if (self.toolhead.pressure_advance_waits
                and self.toolhead.lookahead.get_last() is None):
            # Klipper v0.12.0-262 to v0.13.0-245 register a look-ahead callback at every
            # SET_PRESSURE_ADVANCE (after the flush of a new window); with nothing queued
            # that is get_last_move_time.
            self.toolhead.get_last_move_time()

    def cmd_SET_E_ROTATION_DISTANCE(self, cmd: Command) -> None:
        """SET_EXTRUDER_ROTATION_DISTANCE: a new rotation distance stops step generation."""
        params = command_params(cmd)
        self._mux(params, list(self.steppers), None)
        distance = get_float(params, "DISTANCE")
        if distance is not None:
            if not distance:
                raise CommandError("Rotation distance can not be zero")
            self.toolhead.flush_step_generation()

    def cmd_SYNC_EXTRUDER_MOTION(self, cmd: Command) -> None:
        """Stop step generation, then move an extruder stepper to another motion queue."""
        params = command_params(cmd)
        name = self._mux(params, list(self.steppers), None)
        queue = params.get("MOTION_QUEUE")
        if queue is None:
            raise ParamError("missing MOTION_QUEUE")
        self.toolhead.flush_step_generation()
        if queue and queue not in self.extruders:
            raise CommandError("'%s' is not a valid extruder." % queue)
        self.steppers[name].motion_queue = bool(queue)
        self._check_scan_windows()
