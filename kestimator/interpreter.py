"""What each G-code command does to the toolhead, as Klipper's command handlers do it.

Owns the G-code coordinate state (Klipper's `klippy/extras/gcode_move.py`: absolute and
relative modes, G92 offsets, M220/M221 factors, saved states), arcs
(`klippy/extras/gcode_arcs.py`), firmware retraction (`klippy/extras/firmware_retraction.py`),
and the command side of `klippy/toolhead.py` (G4, M400, M204, SET_VELOCITY_LIMIT), all at
Klipper commit 84104bbbd. Every unit conversion happens here: F is mm/min, G4 P is ms.

A command Klipper would reject is reported through `warn` and skipped, and the G-code
position is reset to the toolhead's as Klipper does after a command error.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Final, overload

from kestimator.gcode import ABSENT, Command, extended_params, parse_line
from kestimator.klipper_modules import (
    COMMAND_MODULE,
    HEATER_BED_WAIT,
    loaded_modules,
    silently_ignored,
)
from kestimator.limits import ExtruderLimits, Limits
from kestimator.macros import HEAT_SOURCE, HOMING_SOURCE
from kestimator.preflight import Preflight
from kestimator.stepgen import (
    MAX_SMOOTH_TIME_T,
    SHAPER_MAX_DAMPING,
    ShaperError,
    kin_flush_delay,
    pressure_advance_window,
    shaper_name,
    shaper_pulses,
    shaper_window,
)
from kestimator.toolhead import MoveError, ToolHead

# Klipper's default G-code speed: 25 mm/s.
DEFAULT_SPEED_V: Final = 25.0
MM_PER_MIN_TO_MM_PER_S: Final = 1.0 / 60.0
MS_TO_S: Final = 1.0 / 1000.0
PERCENT: Final = 100.0

# Commands Klipper knows (with a typical printer.cfg) that take no time and change nothing
# we model. Everything else is an unknown command to Klipper: ignored, and counted.
NO_TIME_COMMANDS: Final = frozenset((
    "M73", "M104", "M140", "M105", "M106", "M107", "M110", "M112", "M114", "M115", "M117",
    "M118", "M119", "M21", "G21", "ECHO", "STATUS", "HELP", "GET_POSITION", "QUERY_ENDSTOPS",
    "SET_HEATER_TEMPERATURE", "TURN_OFF_HEATERS", "SET_IDLE_TIMEOUT",
    "GET_RETRACTION", "TUNING_TOWER", "SET_FAN_SPEED", "RESPOND", "SET_DISPLAY_TEXT",
    "M300",
))
# Kinds of commands recorded in `Interpreter.command_kinds` (and `Estimate.commands`):
# a [gcode_macro] with a Jinja template (not run: 0 s), a literal [gcode_macro] whose
# commands were run one by one (their time is included).
KIND_MACRO = "macro"
KIND_EXPANDED_MACRO = "expanded_macro"
# A no-time command of a module the printer's config has (EXCLUDE_OBJECT_START, M117, ...).
KIND_MODULE = "module"
# With the printer's config known: what Klipper knows whatever its sections (gcode.py,
# the default modules toolhead.py loads, extruder.py); module commands come from
# kestimator.klipper_modules.
ALWAYS_KNOWN_COMMANDS = NO_TIME_COMMANDS - frozenset(COMMAND_MODULE) - frozenset(("M300",))
# Commands whose text argument may hold digits and spaces ("M117 12% done").
TEXT_COMMANDS: Final = frozenset(("M117", "M118", "M23"))

ARC_PLANE_X_Y, ARC_PLANE_X_Z, ARC_PLANE_Y_Z = 0, 1, 2
# An arc that would need more segments than this (100 m at 1 mm resolution) is refused.
MAX_ARC_SEGMENTS: Final = 100_000
# Distinct names of unknown commands recorded with their counts; lines with further names
# are counted together (`ignored_unlisted`), so memory stays bounded whatever the file.
MAX_COMMAND_NAMES: Final = 1000
_AXES: Final = (("X", 0), ("Y", 1), ("Z", 2), ("E", 3))
# Parameters a G0/G1 may carry (G is the command letter itself).
_MOVE_PARAMS: Final = frozenset("XYZEFG")

# warn(message, key): warnings with the same key are reported once, with a count.
WarnFn = Callable[[str, "str | None"], None]
# add_time(seconds, name, source): time with the toolhead at rest that the file cannot show.
AddTimeFn = Callable[[float, str, str], None]


class CommandError(Exception):
    """Klipper would answer this command with an error and not run it."""


class ParamError(CommandError):
    """A parameter error of Klipper's `gcmd.get*`: Klipper words it
    "Error on '<command line>': <this text>"."""


@overload
def _float(params: dict[str, str], name: str, default: float, *,
           minval: float | None = None, above: float | None = None,
           below: float | None = None) -> float: ...


@overload
def _float(params: dict[str, str], name: str, default: None = None, *,
           minval: float | None = None, above: float | None = None,
           below: float | None = None) -> float | None: ...


def _float(params: dict[str, str], name: str, default: float | None = None, *,
           minval: float | None = None, above: float | None = None,
           below: float | None = None) -> float | None:
    """Klipper's `gcmd.get_float` with its range checks; NaN and inf are refused."""
    raw = params.get(name)
    if raw is None:
        return default
    try:
        value = float(raw)
    except ValueError:
        raise ParamError("unable to parse %s" % raw) from None
    if not math.isfinite(value):
        raise ParamError("%s must be a finite number, not %r" % (name, raw))
    if minval is not None and value < minval:
        raise ParamError("%s must have minimum of %s" % (name, minval))
    if above is not None and value <= above:
        raise ParamError("%s must be above %s" % (name, above))
    if below is not None and value >= below:
        raise ParamError("%s must be below %s" % (name, below))
    return value


class Interpreter:
    """Runs commands against a ToolHead, keeping Klipper's G-code state."""

    def __init__(self, limits: Limits, toolhead: ToolHead, warn: WarnFn,
                 homing_time: float = 0.0, heat_time: float = 0.0,
                 add_time: AddTimeFn | None = None) -> None:
        self.limits = limits
        self.toolhead = toolhead
        self.warn = warn
        self.add_time: AddTimeFn = add_time or (lambda seconds, name, source:
                                                 toolhead.add_time(seconds))
        # Called with the name of every command Klipper does not know (a macro, maybe).
        self.on_unknown: Callable[[str], None] | None = None
        self.homing_time = homing_time
        self.heat_time = heat_time
        # gcode_move state
        self.absolute_coord = True
        self.absolute_extrude = True
        self.base_position = [0.0, 0.0, 0.0, 0.0]
        self.last_position = [0.0, 0.0, 0.0, 0.0]
        self.homing_position = [0.0, 0.0, 0.0, 0.0]
        self.speed = DEFAULT_SPEED_V
        self.speed_factor = MM_PER_MIN_TO_MM_PER_S
        self.extrude_factor = 1.0
        self.saved_states: dict[str, dict[str, object]] = {}
        # gcode_arcs / firmware_retraction state
        self.plane = ARC_PLANE_X_Y
        self.retract_length = limits.retract_length
        self.retract_speed = limits.retract_speed
        self.unretract_extra_length = limits.unretract_extra_length
        self.unretract_speed = limits.unretract_speed
        self.is_retracted = False
        # Old Klipper's absolute accel_to_decel ("absolute" generation only).
        self.requested_accel_to_decel = limits.max_accel_to_decel or limits.max_accel * 0.5
        # What the file told us about itself.
        self.extrude_mode_set = False
        self.moved_e_before_mode = False
        self.ignored: dict[str, int] = {}
        # Lines whose unknown command came after MAX_COMMAND_NAMES other names.
        self.ignored_unlisted = 0
        # Commands that are not Klipper's own, by kind (KIND_*): name -> times run.
        self.command_kinds: dict[str, dict[str, int]] = {}
        self.macros = dict(limits.gcode_macros)
        # The modules the printer's config loads; None when no config is known.
        self.modules = (loaded_modules(limits.configured_sections)
                        if limits.configured_sections else None)
        # Where commands Klipper skips are recorded (kestimator.preflight), if anywhere.
        self.preflight: Preflight | None = None
        self._running_macros: set[str] = set()
        # The source line of the command being run (moves carry it).
        self.tag = 0
        if limits.klipper_generation == "absolute":
            self._apply_absolute_accel_to_decel()
        # Extruders (kinematics/extruder.py): by section name; the active one; each
        # one's E position while inactive; pressure advance (advance, smooth time) and
        # whether its stepper is synced to a motion queue, for extruders with a stepper.
        self.extruders: dict[str, ExtruderLimits] = {"extruder": limits.primary_extruder}
        for extruder in limits.extruders:
            self.extruders[extruder.name] = extruder
        self.active_extruder = "extruder"
        self.extruder_e: dict[str, float] = {name: 0.0 for name in self.extruders}
        self.pressure_advance: dict[str, tuple[float, float]] = {
            name: (e.pressure_advance, e.pressure_advance_smooth_time)
            for name, e in self.extruders.items() if e.has_stepper}
        self.extruder_synced: dict[str, bool] = {name: True for name in self.pressure_advance}
        # [extruder_stepper NAME]: its commands are valid (EXTRUDER=NAME), but its own
        # pressure advance is not read; it counts as off in the flush delay (warned once).
        self.extra_steppers = [section.split(None, 1)[1].strip()
                               for section in limits.configured_sections
                               if section.startswith("extruder_stepper ")
                               and len(section.split(None, 1)) == 2]
        for name in self.extra_steppers:
            self.pressure_advance[name] = (0.0, 0.040)
            self.extruder_synced[name] = True
        # [input_shaper] (extras/input_shaper.py): axis -> (shaper_type, freq, damping).
        self.shapers: dict[str, tuple[str, float, float]] = {}
        if limits.input_shaper_enabled:
            for axis in "xyz":
                self.shapers[axis] = (getattr(limits, "shaper_type_" + axis),
                                      getattr(limits, "shaper_freq_" + axis),
                                      getattr(limits, "damping_ratio_" + axis))
        self._update_kin_flush_delay()
        self._handlers: dict[str, Callable[[Command], None]] = {
            "G0": self.cmd_G1, "G1": self.cmd_G1, "G4": self.cmd_G4, "G20": self.cmd_G20,
            "G28": self.cmd_G28, "G90": self.cmd_G90, "G91": self.cmd_G91,
            "G92": self.cmd_G92, "M82": self.cmd_M82, "M83": self.cmd_M83,
            "M18": self.cmd_M84, "M84": self.cmd_M84, "M109": self.cmd_M109,
            "M190": self.cmd_M109, "M204": self.cmd_M204, "M220": self.cmd_M220,
            "M221": self.cmd_M221, "M400": self.cmd_M400,
            "SET_VELOCITY_LIMIT": self.cmd_SET_VELOCITY_LIMIT,
            "TEMPERATURE_WAIT": self.cmd_TEMPERATURE_WAIT,
            "SET_GCODE_OFFSET": self.cmd_SET_GCODE_OFFSET,
            "SAVE_GCODE_STATE": self.cmd_SAVE_GCODE_STATE,
            "RESTORE_GCODE_STATE": self.cmd_RESTORE_GCODE_STATE,
            "SET_KINEMATIC_POSITION": self.cmd_SET_KINEMATIC_POSITION,
            "ACTIVATE_EXTRUDER": self.cmd_ACTIVATE_EXTRUDER,
            "SET_PRESSURE_ADVANCE": self.cmd_SET_PRESSURE_ADVANCE,
            "SET_EXTRUDER_ROTATION_DISTANCE": self.cmd_SET_EXTRUDER_ROTATION_DISTANCE,
            "SYNC_EXTRUDER_MOTION": self.cmd_SYNC_EXTRUDER_MOTION,
        }
        if limits.input_shaper_enabled:
            self._handlers["SET_INPUT_SHAPER"] = self.cmd_SET_INPUT_SHAPER
        if self.modules is not None and "heater_bed" not in self.modules:
            del self._handlers[HEATER_BED_WAIT]
        if limits.arcs_enabled:
            self._handlers.update({
                "G2": self.cmd_G2, "G3": self.cmd_G3, "G17": self.cmd_G17,
                "G18": self.cmd_G18, "G19": self.cmd_G19})
        if limits.firmware_retraction_enabled:
            self._handlers.update({
                "G10": self.cmd_G10, "G11": self.cmd_G11,
                "SET_RETRACTION": self.cmd_SET_RETRACTION})

    # Dispatch
    def execute(self, cmd: Command) -> None:
        """Run one command; raises CommandError (state already reset) if Klipper would."""
        handler = self._handlers.get(cmd.name)
        if handler is None:
            # "M117 12%" reaches Klipper as the command "M117 12%": only M117, M118 and
            # M23 are looked up again by their first word.
            name = cmd.name.split()[0] if " " in cmd.name else cmd.name
            template = self.macros.get(name) if name == cmd.name else None
            if template is not None:
                self._run_macro(name, template)
                return
            known = self._is_known(name, cmd) and (name == cmd.name or name in TEXT_COMMANDS)
            if name and not known and self._silent(name, cmd):
                return
            if name and not known:
                ignored = self.ignored
                if name in ignored:
                    ignored[name] += 1
                elif len(ignored) < MAX_COMMAND_NAMES:
                    ignored[name] = 1
                else:
                    self.ignored_unlisted += 1
                if self.preflight is not None and self.modules is not None:
                    self.preflight.unknown_command(name, self.tag)
                if self.on_unknown is not None:
                    self.on_unknown(name)
            return
        try:
            handler(cmd)
        except (CommandError, MoveError):
            self.reset_last_position()
            raise

    def _is_known(self, name: str, cmd: Command) -> bool:
        """Klipper knows this no-time command (on this printer, when its config is known)."""
        if self.modules is None:
            return name in NO_TIME_COMMANDS
        module = COMMAND_MODULE.get(name)
        if module is not None:
            if module in self.modules:
                self._count(KIND_MODULE, name)
                return True
            return False
        return name in ALWAYS_KNOWN_COMMANDS

    def _silent(self, name: str, cmd: Command) -> bool:
        """cmd_default skips it without a word (only decidable with the printer's config)."""
        return self.modules is not None and silently_ignored(name, cmd.params)

    def _run_macro(self, name: str, template: str) -> None:
        """A [gcode_macro]: a literal one (no Jinja) runs its commands; others take 0 s
        unless the profile's [macros] table times them (`on_unknown`).

        An empty template is a macro whose text is not known (Moonraker's cache).
        """
        if not template.strip() or "{" in template or "%" in template:
            self._count(KIND_MACRO, name)
            if self.on_unknown is not None:
                self.on_unknown(name)
            return
        if name in self._running_macros:
            raise CommandError("Macro %s called recursively" % name)
        self._count(KIND_EXPANDED_MACRO, name)
        self._running_macros.add(name)
        try:
            for line in template.split("\n"):
                sub = parse_line(line.strip())
                if sub.name:
                    self.execute(sub)
        finally:
            self._running_macros.discard(name)

    def _count(self, kind: str, name: str) -> None:
        counts = self.command_kinds.setdefault(kind, {})
        counts[name] = counts.get(name, 0) + 1

    def reset_last_position(self) -> None:
        """After an error or a jump, the G-code position is the toolhead's again."""
        self.last_position = list(self.toolhead.commanded_pos)

    def _params(self, cmd: Command) -> dict[str, str]:
        if cmd.params or not cmd.code:
            return cmd.params
        try:
            return extended_params(cmd.code)
        except ValueError as exc:
            raise CommandError(str(exc)) from None

    # Moves (gcode_move.py)
    def cmd_G1(self, cmd: Command) -> None:
        """G0/G1: a straight move; positions in mm, F in mm/min."""
        params = cmd.params
        last_position = self.last_position
        for axis, pos in _AXES:
            raw = params.get(axis)
            if raw is None:
                continue
            try:
                v = float(raw)
            except ValueError:
                raise CommandError("Unable to parse move '%s'" % cmd.code) from None
            if not math.isfinite(v):
                raise CommandError("Unable to parse move '%s'" % cmd.code)
            absolute_coord = self.absolute_coord
            if pos == 3:
                v *= self.extrude_factor
                if not self.absolute_extrude:
                    absolute_coord = False
                if not self.extrude_mode_set:
                    self.moved_e_before_mode = True
            if not absolute_coord:
                last_position[pos] += v
            else:
                last_position[pos] = v + self.base_position[pos]
        raw_f = params.get("F")
        if raw_f is not None:
            try:
                gcode_speed = float(raw_f)
            except ValueError:
                raise CommandError("Unable to parse move '%s'" % cmd.code) from None
            if not gcode_speed > 0.0 or math.isinf(gcode_speed):
                raise CommandError("Invalid speed in '%s'" % cmd.code)
            self.speed = gcode_speed * self.speed_factor
        for key in params:
            if key not in _MOVE_PARAMS:
                self.warn("Klipper ignores parameter %s in '%s'" % (key, cmd.code.strip()),
                          "move-param:" + key)
        self._move(self.speed)

    def plain_move(self, x: float, y: float, z: float, e: float, f: float) -> None:
        """G0/G1 from already parsed, valid values (`gcode.parse_plain_move_scan` or `_regex`).

        The same arithmetic as `cmd_G1`, in the same order, without the text handling. A
        parameter the line does not give is `gcode.ABSENT` (NaN, so `v == v` is "given").
        """
        lp = self.last_position
        base = self.base_position
        if self.absolute_coord:
            if x == x:
                lp[0] = x + base[0]
            if y == y:
                lp[1] = y + base[1]
            if z == z:
                lp[2] = z + base[2]
        else:
            # Upstream's `last_position[pos] += v`, written out: the same float addition,
            # which mypyc compiles to a machine add (`+=` on a list item boxes v first).
            if x == x:
                lp[0] = lp[0] + x
            if y == y:
                lp[1] = lp[1] + y
            if z == z:
                lp[2] = lp[2] + z
        if e == e:
            e *= self.extrude_factor
            if self.absolute_coord and self.absolute_extrude:
                lp[3] = e + base[3]
            else:
                lp[3] = lp[3] + e
            if not self.extrude_mode_set:
                self.moved_e_before_mode = True
        if f == f:
            self.speed = f * self.speed_factor
        self.toolhead.move_to(lp[0], lp[1], lp[2], lp[3], self.speed, self.tag)

    def _move(self, speed: float) -> None:
        lp = self.last_position
        self.toolhead.move_to(lp[0], lp[1], lp[2], lp[3], speed, self.tag)

    def cmd_G20(self, cmd: Command) -> None:
        """G20 (inches): Klipper refuses it."""
        raise CommandError("Machine does not support G20 (inches) command")

    def cmd_M82(self, cmd: Command) -> None:
        """Absolute extrusion."""
        self.absolute_extrude = True
        self.extrude_mode_set = True

    def cmd_M83(self, cmd: Command) -> None:
        """Relative extrusion."""
        self.absolute_extrude = False
        self.extrude_mode_set = True

    def cmd_G90(self, cmd: Command) -> None:
        """Absolute coordinates (E too, unless M83 made it relative)."""
        self.absolute_coord = True

    def cmd_G91(self, cmd: Command) -> None:
        """Relative coordinates, E included."""
        self.absolute_coord = False

    def cmd_G92(self, cmd: Command) -> None:
        """Set the G-code position without moving."""
        offsets = [_float(cmd.params, a) for a in "XYZE"]
        for i, offset in enumerate(offsets):
            if offset is not None:
                if i == 3:
                    offset *= self.extrude_factor
                self.base_position[i] = self.last_position[i] - offset
        if offsets == [None, None, None, None]:
            self.base_position[:4] = self.last_position[:4]

    def cmd_M220(self, cmd: Command) -> None:
        """Speed factor override in percent."""
        value = _float(cmd.params, "S", PERCENT, above=0.0) / (60.0 * PERCENT)
        self.speed = (self.speed / self.speed_factor) * value
        self.speed_factor = value

    def cmd_M221(self, cmd: Command) -> None:
        """Extrusion factor override in percent."""
        new_extrude_factor = _float(cmd.params, "S", PERCENT, above=0.0) / PERCENT
        last_e_pos = self.last_position[3]
        e_value = (last_e_pos - self.base_position[3]) / self.extrude_factor
        self.base_position[3] = last_e_pos - e_value * new_extrude_factor
        self.extrude_factor = new_extrude_factor

    def cmd_SET_GCODE_OFFSET(self, cmd: Command) -> None:
        """Shift the G-code origin; MOVE=1 moves by the change."""
        params = self._params(cmd)
        move_delta = [0.0, 0.0, 0.0, 0.0]
        for pos, axis in enumerate("XYZE"):
            offset = _float(params, axis)
            if offset is None:
                offset = _float(params, axis + "_ADJUST")
                if offset is None:
                    continue
                offset += self.homing_position[pos]
            delta = offset - self.homing_position[pos]
            move_delta[pos] = delta
            self.base_position[pos] += delta
            self.homing_position[pos] = offset
        if self._int(params, "MOVE"):
            speed = _float(params, "MOVE_SPEED", self.speed, above=0.0)
            for pos, delta in enumerate(move_delta):
                self.last_position[pos] += delta
            self._move(speed)

    @staticmethod
    def _int(params: dict[str, str], name: str) -> int:
        raw = params.get(name)
        if raw is None:
            return 0
        try:
            return int(raw)
        except ValueError:
            raise ParamError("unable to parse %s" % raw) from None

    def _save_state(self) -> dict[str, object]:
        return {
            "absolute_coord": self.absolute_coord,
            "absolute_extrude": self.absolute_extrude,
            "base_position": list(self.base_position),
            "last_position": list(self.last_position),
            "homing_position": list(self.homing_position),
            "speed": self.speed, "speed_factor": self.speed_factor,
            "extrude_factor": self.extrude_factor,
        }

    def _restore_state(self, state: dict[str, object]) -> None:
        self.absolute_coord = bool(state["absolute_coord"])
        self.absolute_extrude = bool(state["absolute_extrude"])
        self.base_position[:4] = list(state["base_position"])[:4]  # type: ignore[call-overload]
        self.homing_position = list(state["homing_position"])  # type: ignore[call-overload]
        self.speed = float(state["speed"])  # type: ignore[arg-type]
        self.speed_factor = float(state["speed_factor"])  # type: ignore[arg-type]
        self.extrude_factor = float(state["extrude_factor"])  # type: ignore[arg-type]
        saved_last = state["last_position"]
        e_diff = self.last_position[3] - saved_last[3]  # type: ignore[index]
        self.base_position[3] += e_diff

    def cmd_SAVE_GCODE_STATE(self, cmd: Command) -> None:
        """Remember the coordinate state under NAME."""
        name = self._params(cmd).get("NAME", "default")
        self.saved_states[name] = self._save_state()

    def cmd_RESTORE_GCODE_STATE(self, cmd: Command) -> None:
        """Bring back a saved coordinate state; MOVE=1 returns to its XYZ."""
        params = self._params(cmd)
        state = self.saved_states.get(params.get("NAME", "default"))
        if state is None:
            raise CommandError("Unknown g-code state: %s" % params.get("NAME", "default"))
        self._restore_state(state)
        if self._int(params, "MOVE"):
            speed = _float(params, "MOVE_SPEED", self.speed, above=0.0)
            self.last_position[:3] = list(state["last_position"])[:3]  # type: ignore[call-overload]
            self._move(speed)

    # Homing and position jumps
    def cmd_G28(self, cmd: Command) -> None:
        """Home the named axes (all of XYZ if none): after a full stop the head is where the
        kinematics' homing leaves it (each axis at its position_endstop, a delta at its
        home position), and the G-code offsets of the homed axes are reset."""
        axes = [pos for pos, axis in enumerate("XYZ") if axis in cmd.params]
        if not axes:
            axes = [0, 1, 2]
        newpos, homed = self.toolhead.kin.home(self.toolhead.commanded_pos, axes)
        self.toolhead.set_position(newpos, homed)
        if self.homing_time > 0.0:
            self.add_time(self.homing_time, "G28", HOMING_SOURCE)
        self.reset_last_position()
        for axis in ("xyz".index(a) for a in homed):
            self.base_position[axis] = self.homing_position[axis]

    def cmd_SET_KINEMATIC_POSITION(self, cmd: Command) -> None:
        """Declare the toolhead position without moving (force_move); SET_HOMED (default
        all of XYZ) are homed from now on, CLEAR_HOMED (or CLEAR) no longer."""
        params = self._params(cmd)
        pos = list(self.toolhead.commanded_pos)
        for i, axis in enumerate("XYZ"):
            value = _float(params, axis)
            if value is not None:
                pos[i] = value
        set_homed = params.get("SET_HOMED", "xyz").lower()
        homed = "".join(a for a in "xyz" if a in set_homed)
        clear = params.get("CLEAR_HOMED")
        if clear is None:
            # "CLEAR" is an alias for "CLEAR_HOMED"
            clear = params.get("CLEAR", "")
        cleared = "".join(a for a in "xyz" if a in clear.lower())
        self.toolhead.set_position((pos[0], pos[1], pos[2], pos[3]), homed)
        self.toolhead.kin.clear_homing_state(cleared)
        self.reset_last_position()

    # Toolhead commands (toolhead.py)
    def cmd_G4(self, cmd: Command) -> None:
        """Dwell P milliseconds (Klipper ignores S)."""
        delay = _float(cmd.params, "P", 0.0, minval=0.0) * MS_TO_S
        self.toolhead.dwell(delay)

    def cmd_M400(self, cmd: Command) -> None:
        """Wait for all moves to finish."""
        self.toolhead.wait_moves()

    def cmd_M204(self, cmd: Command) -> None:
        """M204 S<accel>, or both P and T (their minimum); P alone changes nothing."""
        accel = _float(cmd.params, "S", above=0.0)
        if accel is None:
            p = _float(cmd.params, "P", above=0.0)
            t = _float(cmd.params, "T", above=0.0)
            if p is None or t is None:
                self.warn("M204 without S needs both P and T; Klipper ignores '%s'"
                          % cmd.code.strip(), "m204-incomplete")
                return
            accel = min(p, t)
        self.toolhead.set_max_velocities(None, accel, None, None)
        self._apply_absolute_accel_to_decel()

    def cmd_SET_VELOCITY_LIMIT(self, cmd: Command) -> None:
        """Change velocity, accel, square corner velocity or minimum cruise ratio."""
        params = self._params(cmd)
        max_velocity = _float(params, "VELOCITY", above=0.0)
        max_accel = _float(params, "ACCEL", above=0.0)
        scv = _float(params, "SQUARE_CORNER_VELOCITY", minval=0.0)
        mcr = _float(params, "MINIMUM_CRUISE_RATIO", minval=0.0, below=1.0)
        generation = self.limits.klipper_generation
        if generation != "mainline":
            accel_to_decel = _float(params, "ACCEL_TO_DECEL", above=0.0)
            if accel_to_decel is not None and generation == "mcr" and mcr is None:
                accel = max_accel if max_accel is not None else self.toolhead.max_accel
                mcr = 1.0 - min(1.0, accel_to_decel / accel)
            elif accel_to_decel is not None and generation == "absolute":
                self.requested_accel_to_decel = accel_to_decel
        self.toolhead.set_max_velocities(max_velocity, max_accel, scv, mcr)
        self._apply_absolute_accel_to_decel()

    def _apply_absolute_accel_to_decel(self) -> None:
        """Old Klipper: the cruise-smoothing accel is min(accel_to_decel, max_accel)."""
        if self.limits.klipper_generation != "absolute":
            return
        toolhead = self.toolhead
        toolhead.mcr_pseudo_accel = min(self.requested_accel_to_decel, toolhead.max_accel)

    # Heaters and motors
    def cmd_M109(self, cmd: Command) -> None:
        """M109/M190: set a temperature and, when S is not 0, wait for it."""
        temp = _float(cmd.params, "S", 0.0)
        if temp:
            self.toolhead.wait_heater()
            if self.heat_time > 0.0:
                self.add_time(self.heat_time, cmd.name, HEAT_SOURCE)

    def cmd_TEMPERATURE_WAIT(self, cmd: Command) -> None:
        """Wait until a sensor is in range."""
        params = self._params(cmd)
        if "SENSOR" not in params:
            raise ParamError("missing SENSOR")
        low = _float(params, "MINIMUM")
        high = _float(params, "MAXIMUM")
        if low is None and high is None:
            raise CommandError("Error on 'TEMPERATURE_WAIT': missing MINIMUM or MAXIMUM.")
        self.toolhead.wait_heater()
        if self.heat_time > 0.0:
            self.add_time(self.heat_time, "TEMPERATURE_WAIT", HEAT_SOURCE)

    def cmd_M84(self, cmd: Command) -> None:
        """Motors off: Klipper dwells 0.1 s before and after when a motor was on."""
        self.toolhead.motor_off()

    # Extruders and step generation (kinematics/extruder.py, extras/input_shaper.py)
    def _update_kin_flush_delay(self) -> None:
        """motion_queuing.check_step_generation_scan_windows."""
        windows = [pressure_advance_window(*self.pressure_advance[name])
                   for name, synced in self.extruder_synced.items() if synced]
        for shaper_type, freq, damping in self.shapers.values():
            try:
                windows.append(shaper_window(*shaper_pulses(shaper_type, freq, damping)))
            except ShaperError:
                continue
        self.toolhead.kin_flush_delay = kin_flush_delay(windows)

    def _mux(self, cmd: Command, params: dict[str, str], choices: list[str],
             default: str | None) -> str:
        """The EXTRUDER= a mux command names (gcode.py _cmd_mux), checked."""
        key = params.get("EXTRUDER")
        if key is None:
            if default is not None:
                return default
            raise ParamError("missing EXTRUDER")
        if key not in choices:
            guess = next((". Did you mean '%s'?" % c for c in choices if key and key in c),
                         ". Options: %s" % ", ".join("'%s'" % c for c in choices))
            raise CommandError("The value '%s' is not valid for EXTRUDER%s" % (key, guess))
        return key

    def cmd_ACTIVATE_EXTRUDER(self, cmd: Command) -> None:
        """Full stop of step generation, then that extruder's limits and E position."""
        params = self._params(cmd)
        name = self._mux(cmd, params, list(self.extruders), None)
        if name == self.active_extruder:
            return
        toolhead = self.toolhead
        toolhead.flush_step_generation()
        self.extruder_e[self.active_extruder] = toolhead.commanded_pos[3]
        self.active_extruder = name
        toolhead.set_extruder(self.extruders[name], self.extruder_e[name])
        # gcode_move._handle_activate_extruder
        self.reset_last_position()
        self.extrude_factor = 1.0
        self.base_position[3] = self.last_position[3]

    def cmd_SET_PRESSURE_ADVANCE(self, cmd: Command) -> None:
        """Change pressure advance; a changed smoothing window stops step generation."""
        params = self._params(cmd)
        default = None
        if "extruder" in self.pressure_advance:
            default = self.active_extruder
        name = self._mux(cmd, params, list(self.pressure_advance), default)
        if name not in self.pressure_advance:
            raise CommandError("Active extruder does not have a stepper")
        if "EXTRUDER" not in params and not self.extruder_synced.get(name):
            raise CommandError("Unable to infer active extruder stepper")
        old_advance, old_smooth = self.pressure_advance[name]
        advance = _float(params, "ADVANCE", old_advance, minval=0.0)
        smooth_time = _float(params, "SMOOTH_TIME", old_smooth, minval=0.0)
        if smooth_time > MAX_SMOOTH_TIME_T:
            raise ParamError("SMOOTH_TIME must have maximum of %s" % MAX_SMOOTH_TIME_T)
        self.pressure_advance[name] = (advance, smooth_time)
        if (pressure_advance_window(advance, smooth_time)
                != pressure_advance_window(old_advance, old_smooth)):
            self.pressure_advance[name] = (old_advance, old_smooth)
            self.toolhead.flush_step_generation()
            self.pressure_advance[name] = (advance, smooth_time)
            self._update_kin_flush_delay()

    def cmd_SET_EXTRUDER_ROTATION_DISTANCE(self, cmd: Command) -> None:
        """A new rotation distance stops step generation first."""
        params = self._params(cmd)
        self._mux(cmd, params, list(self.pressure_advance), None)
        distance = _float(params, "DISTANCE")
        if distance is not None:
            if not distance:
                raise CommandError("Rotation distance can not be zero")
            self.toolhead.flush_step_generation()

    def cmd_SYNC_EXTRUDER_MOTION(self, cmd: Command) -> None:
        """Stop step generation, then move an extruder stepper to another motion queue."""
        params = self._params(cmd)
        name = self._mux(cmd, params, list(self.pressure_advance), None)
        queue = params.get("MOTION_QUEUE")
        if queue is None:
            raise ParamError("missing MOTION_QUEUE")
        self.toolhead.flush_step_generation()
        if queue and queue not in self.extruders:
            raise CommandError("'%s' is not a valid extruder." % queue)
        self.extruder_synced[name] = bool(queue)
        self._update_kin_flush_delay()

    def cmd_SET_INPUT_SHAPER(self, cmd: Command) -> None:
        """New shaper parameters: a full stop of step generation, then the new window."""
        params = self._params(cmd)
        if not params:
            return
        for axis in "xyz":
            shaper_type, freq, damping = self.shapers[axis]
            up = axis.upper()
            new_type = params.get("SHAPER_TYPE", params.get("SHAPER_TYPE_" + up, shaper_type))
            name = shaper_name(new_type.lower())
            if name not in SHAPER_MAX_DAMPING:
                raise CommandError("Unsupported shaper type: %s" % new_type)
            new_damping = _float(params, "DAMPING_RATIO_" + up, damping, minval=0.0)
            if new_damping > SHAPER_MAX_DAMPING[name]:
                raise CommandError("Too high value of damping_ratio=%.3f for shaper %s on "
                                   "axis %s" % (new_damping, new_type, up))
            new_freq = _float(params, "SHAPER_FREQ_" + up, freq, minval=0.0)
            try:
                shaper_pulses(new_type.lower(), new_freq, new_damping)
            except ShaperError as exc:
                raise CommandError(str(exc)) from None
            self.shapers[axis] = (new_type.lower(), new_freq, new_damping)
        self.toolhead.flush_step_generation()
        self._update_kin_flush_delay()

    # Arcs (gcode_arcs.py)
    def cmd_G17(self, cmd: Command) -> None:
        """Arcs in the XY plane."""
        self.plane = ARC_PLANE_X_Y

    def cmd_G18(self, cmd: Command) -> None:
        """Arcs in the XZ plane."""
        self.plane = ARC_PLANE_X_Z

    def cmd_G19(self, cmd: Command) -> None:
        """Arcs in the YZ plane."""
        self.plane = ARC_PLANE_Y_Z

    def cmd_G2(self, cmd: Command) -> None:
        """Clockwise arc."""
        self._arc(cmd, True)

    def cmd_G3(self, cmd: Command) -> None:
        """Counter-clockwise arc."""
        self._arc(cmd, False)

    def _arc(self, cmd: Command, clockwise: bool) -> None:
        if not self.absolute_coord:
            raise CommandError("G2/G3 does not support relative move mode")
        params = cmd.params
        current = [lp - bp for lp, bp in zip(self.last_position, self.base_position)]
        current[3] /= self.extrude_factor
        target = [_float(params, "X", current[0]), _float(params, "Y", current[1]),
                  _float(params, "Z", current[2])]
        if _float(params, "R") is not None:
            raise CommandError("G2/G3 does not support R moves")
        i_off = _float(params, "I", 0.0)
        j_off = _float(params, "J", 0.0)
        planar = (i_off, j_off)
        axes = (0, 1, 2)
        if self.plane == ARC_PLANE_X_Z:
            planar = (i_off, _float(params, "K", 0.0))
            axes = (0, 2, 1)
        elif self.plane == ARC_PLANE_Y_Z:
            planar = (j_off, _float(params, "K", 0.0))
            axes = (1, 2, 0)
        if not (planar[0] or planar[1]):
            raise CommandError("G2/G3 requires IJ, IK or JK parameters")
        as_e = _float(params, "E")
        as_f = _float(params, "F")
        self._plan_arc(current, target, planar, clockwise, as_e, as_f, *axes)

    def _plan_arc(self, current: list[float], target: list[float],
                  offset: tuple[float, float], clockwise: bool, as_e: float | None,
                  as_f: float | None, alpha_axis: int, beta_axis: int,
                  helical_axis: int) -> None:
        r_p = -offset[0]
        r_q = -offset[1]
        center_p = current[alpha_axis] - r_p
        center_q = current[beta_axis] - r_q
        rt_alpha = target[alpha_axis] - center_p
        rt_beta = target[beta_axis] - center_q
        angular_travel = math.atan2(r_p * rt_beta - r_q * rt_alpha,
                                    r_p * rt_alpha + r_q * rt_beta)
        if angular_travel < 0.0:
            angular_travel += 2.0 * math.pi
        if clockwise:
            angular_travel -= 2.0 * math.pi
        if (angular_travel == 0.0
                and current[alpha_axis] == target[alpha_axis]
                and current[beta_axis] == target[beta_axis]):
            # Same start and end: a full circle.
            angular_travel = 2.0 * math.pi
        linear_travel = target[helical_axis] - current[helical_axis]
        radius = math.hypot(r_p, r_q)
        flat_mm = radius * angular_travel
        if linear_travel:
            mm_of_travel = math.hypot(flat_mm, linear_travel)
        else:
            mm_of_travel = math.fabs(flat_mm)
        if not mm_of_travel / self.limits.arc_resolution <= MAX_ARC_SEGMENTS:
            # Klipper would grind through millions of segments; no real arc has them.
            raise CommandError("arc of %.6g mm would be split into more than %d segments"
                               % (mm_of_travel, MAX_ARC_SEGMENTS))
        segments = max(1.0, math.floor(mm_of_travel / self.limits.arc_resolution))
        theta_per_segment = angular_travel / segments
        linear_per_segment = linear_travel / segments
        absolute_extrude = self.absolute_extrude
        e_per_move = e_base = 0.0
        if as_e is not None:
            if absolute_extrude:
                e_base = current[3]
            e_per_move = (as_e - e_base) / segments
        for i in range(1, int(segments) + 1):
            dist_helical = i * linear_per_segment
            c_theta = i * theta_per_segment
            cos_ti = math.cos(c_theta)
            sin_ti = math.sin(c_theta)
            r_p = -offset[0] * cos_ti + offset[1] * sin_ti
            r_q = -offset[0] * sin_ti - offset[1] * cos_ti
            c = [0.0, 0.0, 0.0]
            c[alpha_axis] = center_p + r_p
            c[beta_axis] = center_q + r_q
            c[helical_axis] = current[helical_axis] + dist_helical
            if i == segments:
                c = target  # type: ignore[assignment]
            seg_e: float | None = None
            if e_per_move:
                seg_e = e_base + e_per_move
                if absolute_extrude:
                    e_base += e_per_move
            self._g1_values(c[0], c[1], c[2], seg_e, as_f)

    def _g1_values(self, x: float, y: float, z: float, e: float | None,
                   f: float | None) -> None:
        """cmd_G1 with numeric parameters (what gcode_arcs sends)."""
        if f is not None and not f > 0.0:
            raise CommandError("Invalid speed in arc (F%s)" % f)
        self.plain_move(x, y, z, ABSENT if e is None else e, ABSENT if f is None else f)

    # Firmware retraction (firmware_retraction.py)
    def cmd_G10(self, cmd: Command) -> None:
        """Retract by retract_length at retract_speed (once until G11)."""
        if not self.is_retracted:
            self._relative_e_move(-self.retract_length, self.retract_speed)
            self.is_retracted = True

    def cmd_G11(self, cmd: Command) -> None:
        """Unretract by retract_length + unretract_extra_length at unretract_speed."""
        if self.is_retracted:
            self._relative_e_move(self.retract_length + self.unretract_extra_length,
                                  self.unretract_speed)
            self.is_retracted = False

    def _relative_e_move(self, length: float, speed: float) -> None:
        # Klipper runs "G91 / G1 E%.5f F%d" inside SAVE/RESTORE_GCODE_STATE.
        state = self._save_state()
        self.absolute_coord = False
        e = float("%.5f" % length) * self.extrude_factor
        self.last_position[3] += e
        self.speed = float("%d" % (speed * 60)) * self.speed_factor
        try:
            self._move(self.speed)
        finally:
            self._restore_state(state)

    def cmd_SET_RETRACTION(self, cmd: Command) -> None:
        """Change the firmware retraction lengths and speeds."""
        params = self._params(cmd)
        self.retract_length = _float(params, "RETRACT_LENGTH", self.retract_length,
                                     minval=0.0)
        self.retract_speed = _float(params, "RETRACT_SPEED", self.retract_speed, minval=1.0)
        self.unretract_extra_length = _float(
            params, "UNRETRACT_EXTRA_LENGTH", self.unretract_extra_length, minval=0.0)
        self.unretract_speed = _float(params, "UNRETRACT_SPEED", self.unretract_speed,
                                      minval=1.0)
        self.is_retracted = False
