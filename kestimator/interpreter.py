"""Mirrors the dispatch of klippy/gcode.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's G-code dispatch (`GCodeDispatch`: `register_command`, `cmd_default`): which
object runs each command, and what happens to commands Klipper does not know. It also sets
the printer's objects up as klippy does from its config sections: `GCodeMove` (gcode_move.py),
`ToolHeadCommandHelper` (toolhead.py), `PrinterExtruders` (extruder.py), `PrinterHeaters`
(heaters.py: M104/M109 with [extruder], M140/M190 with [heater_bed], SET_HEATER_TEMPERATURE
and TEMPERATURE_WAIT), `InputShaper` (input_shaper.py), `ArcSupport` (gcode_arcs.py) with
[gcode_arcs], `FirmwareRetraction` (firmware_retraction.py) with [firmware_retraction]. The
few commands whose upstream object holds nothing else are here, each naming its file: G28
(homing.py; [safe_z_home] and [homing_override] take it over: kestimator/safe_z_home.py,
kestimator/homing_override.py), SET_KINEMATIC_POSITION (force_move.py), M84/M18
(stepper_enable.py), and, when no printer config is known, M109/M190 (heaters.py: the wait
only, nothing to check). Bed mesh and skew correction are move transforms of GCodeMove
(bed_mesh.py, skew_correction.py), and so is exclude_object's after the first
EXCLUDE_OBJECT (exclude_object.py). Literal
[gcode_macro]s run their commands; macros with a template are counted (gcode_macro.py's
templates are not rendered).

A command Klipper would reject raises `CommandError`/`MoveError` after the G-code position
is reset to the toolhead's, as Klipper does after a command error.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from functools import partial
from typing import Final

from kestimator.bed_mesh import BedMesh
from kestimator.errors import CommandError, MoveError, ParamError, PrintEndsError
from kestimator.exclude_object import ExcludeObject
from kestimator.extruder import PrinterExtruders
from kestimator.firmware_retraction import FirmwareRetraction
from kestimator.force_move import enabled_force_move_commands
from kestimator.gcode import Command, command_params, get_float, parse_line
from kestimator.gcode_arcs import ArcSupport
from kestimator.gcode_move import GCodeMove
from kestimator.heaters import PrinterHeaters
from kestimator.homing_override import HomingOverride
from kestimator.input_shaper import InputShaper
from kestimator.klipper_modules import (
    HEATER_BED_WAIT,
    loaded_modules,
    registered_commands,
    silently_ignored,
)
from kestimator.limits import Limits
from kestimator.macros import HOMING_SOURCE
from kestimator.manual_probe import unregistered_endstop_commands
from kestimator.preflight import Preflight
from kestimator.safe_z_home import SafeZHoming
from kestimator.skew_correction import PrinterSkew
from kestimator.toolhead import ToolHead, ToolHeadCommandHelper

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

__all__ = ["CommandError", "Interpreter", "MoveError", "ParamError", "printer_commands"]

# Without the printer's config: the commands Klipper knows with a typical printer.cfg that
# take no time and change nothing we model. Everything else is an unknown command to
# Klipper: ignored, and counted. With the config, kestimator.klipper_modules says which
# commands Klipper registers.
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
# Commands Klipper runs that take time the file cannot show: they probe, calibrate or
# measure. Counted as 0 s, and said, unless the profile's [macros] table times them, as
# for macros (a learned start time holds those before the first extrusion).
UNSHOWN_TIME_COMMANDS: Final = frozenset((
    "PROBE", "PROBE_ACCURACY", "PROBE_CALIBRATE", "BED_MESH_CALIBRATE", "Z_TILT_ADJUST",
    "QUAD_GANTRY_LEVEL", "PID_CALIBRATE", "SCREWS_TILT_CALCULATE", "BED_TILT_CALIBRATE",
    "DELTA_CALIBRATE", "SHAPER_CALIBRATE", "TEST_RESONANCES",
))
# What SAVE_CONFIG may do to a print (configfile.py cmd_SAVE_CONFIG: with settings left to
# save it writes them and restarts Klipper; with none it returns at once).
SAVE_CONFIG_MAY_STOP: Final = (
    "SAVE_CONFIG restarts Klipper, ending the print, when a command before it (a "
    "calibration, BED_MESH_CALIBRATE saving its mesh, a macro) left settings to save; "
    "with none it does nothing")
# Commands whose text argument may hold digits and spaces ("M117 12% done").
TEXT_COMMANDS: Final = frozenset(("M117", "M118", "M23"))

# Distinct names of unknown commands recorded with their counts; lines with further names
# are counted together (`ignored_unlisted`), so memory stays bounded whatever the file.
MAX_COMMAND_NAMES: Final = 1000

# A macro text that loads or makes a bed mesh.
_MESH_COMMAND_RE = re.compile(r"\bBED_MESH_(?:PROFILE|CALIBRATE)\b", re.IGNORECASE)
# stepper_enable's dwell before and after turning motors off.
DISABLE_STALL_T: Final = 0.100
# extras/fan.py's and fan_generic.py's commands: set_speed_from_command queues the speed in a
# look-ahead callback (kestimator.toolhead's lookahead_callback_barrier).
FAN_COMMANDS: Final = frozenset(("M106", "M107", "SET_FAN_SPEED"))

# warn(message, key): warnings with the same key are reported once, with a count.
WarnFn = Callable[[str, "str | None"], None]
# add_time(seconds, name, source): time with the toolhead at rest that the file cannot show.
AddTimeFn = Callable[[float, str, str], None]
Handler = Callable[[Command], None]


def printer_commands(limits: Limits) -> frozenset[str] | None:
    """The commands Klipper holds once ready on this printer (its [gcode_macro]s aside), or
    None when its config is not known."""
    if not limits.configured_sections:
        return None
    modules = loaded_modules(limits.configured_sections, limits.kinematics)
    return (registered_commands(modules)
            - unregistered_endstop_commands(limits.machine, limits.kinematics)
            | enabled_force_move_commands(limits.machine))


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Interpreter:
    """Runs commands against a ToolHead through the printer's objects."""

    def __init__(self, limits: Limits, toolhead: ToolHead, warn: WarnFn,
                 homing_time: float = 0.0, heat_time: float = 0.0,
                 add_time: AddTimeFn | None = None) -> None:
        self.limits = limits
        self.toolhead = toolhead
        self.warn = warn
        # Bound methods and partials, not closures, throughout: the worker pickles the
        # whole planner to resume it (kestimator.resume), and pickle takes no closure.
        self.add_time: AddTimeFn = add_time or self._rest
        # Called with the name of every command Klipper does not know (a macro, maybe).
        self.on_unknown: Callable[[str], object] | None = None
        # Called with the name of a command that takes time the file cannot show
        # (UNSHOWN_TIME_COMMANDS); True when it was timed.
        self.on_unshown: Callable[[str], bool] | None = None
        self.homing_time = homing_time
        self.heat_time = heat_time
        self.ignored: dict[str, int] = {}
        # Lines whose unknown command came after MAX_COMMAND_NAMES other names.
        self.ignored_unlisted = 0
        # Commands that are not Klipper's own, by kind (KIND_*): name -> times run.
        self.command_kinds: dict[str, dict[str, int]] = {}
        self.macros = dict(limits.gcode_macros)
        # The modules the printer's config loads; None when no config is known.
        self.modules = (loaded_modules(limits.configured_sections, limits.kinematics)
                        if limits.configured_sections else None)
        # The commands Klipper registers with them, and those it has whatever the sections.
        self.registered = printer_commands(limits) or frozenset()
        self._registered_anyway = registered_commands(loaded_modules((), limits.kinematics))
        # Where commands Klipper skips are recorded (kestimator.preflight), if anywhere.
        self.preflight: Preflight | None = None
        self._running_macros: set[str] = set()
        # The printer's objects, and the commands each registers.
        self.gcode_handlers: dict[str, Handler] = {}
        self.gcode_move = gcode_move = GCodeMove(toolhead, warn)
        for name in ("G0", "G1"):
            self.register_command(name, gcode_move.cmd_G1)
        for name in ("G20", "M82", "M83", "G90", "G91", "G92", "M220", "M221",
                     "SET_GCODE_OFFSET", "SAVE_GCODE_STATE", "RESTORE_GCODE_STATE"):
            self.register_command(name, getattr(gcode_move, "cmd_" + name))
        helper = ToolHeadCommandHelper(limits, toolhead, warn)
        for name in ("G4", "M400", "SET_VELOCITY_LIMIT", "M204"):
            self.register_command(name, getattr(helper, "cmd_" + name))
        for name, kalicos in (("RESET_VELOCITY_LIMIT", helper.kalico),  # its limited_*'s:
                              ("SET_KINEMATICS_LIMIT", toolhead.kin.kinematics_limits())):
            if kalicos and name not in self.macros:
                self.register_command(name, getattr(helper, "cmd_" + name))
        self.extruders = extruders = PrinterExtruders(
            limits, toolhead, gcode_move._handle_activate_extruder)
        # The extruders' commands (an [extruder] or [extruder_stepper] registers them) and
        # stepper_enable's (every kinematics but "none" loads it): only where Klipper has them.
        for name, handler in (
                ("ACTIVATE_EXTRUDER", extruders.cmd_ACTIVATE_EXTRUDER),
                ("SET_PRESSURE_ADVANCE", extruders.cmd_SET_PRESSURE_ADVANCE),
                ("SET_EXTRUDER_ROTATION_DISTANCE", extruders.cmd_SET_E_ROTATION_DISTANCE),
                ("SYNC_EXTRUDER_MOTION", extruders.cmd_SYNC_EXTRUDER_MOTION),
                ("M18", self.cmd_M84), ("M84", self.cmd_M84)):
            if self.modules is None or name in self.registered:
                self.register_command(name, handler)
        self.input_shaper = InputShaper(limits, toolhead)
        if limits.input_shaper_enabled:
            self.register_command("SET_INPUT_SHAPER", self.input_shaper.cmd_SET_INPUT_SHAPER)
        motion_queuing = toolhead.motion_queuing
        motion_queuing.register_scan_windows(extruders.scan_windows)
        motion_queuing.register_scan_windows(self.input_shaper.scan_windows)
        motion_queuing.check_step_generation_scan_windows()
        self.register_command("G28", self.cmd_G28)
        self._load_homing_modules(limits)
        # The G28 a line runs: the module's that took it over, with the homing time.
        self._home_G28 = self.gcode_handlers["G28"]
        self._homing_depth = 0
        # G28 lines that took no time (no homing time given).
        self.untimed_homings = 0
        self.register_command("G28", self._cmd_G28_timed)
        if self.modules is None or "SET_KINEMATIC_POSITION" in self.registered:
            self.register_command("SET_KINEMATIC_POSITION", self.cmd_SET_KINEMATIC_POSITION)
        self.heaters = heaters = PrinterHeaters(limits, toolhead, extruders, heat_time,
                                                self.add_time)
        heaters.on_maybe_cold = self._maybe_cold
        if self.modules is None:
            # No printer config: nothing to check, the waits only wait.
            self.register_command("M109", self.cmd_M109)
            self.register_command(HEATER_BED_WAIT, self.cmd_M109)
            self.register_command("TEMPERATURE_WAIT", heaters.cmd_TEMPERATURE_WAIT)
        else:
            self._register_heater_commands(heaters, self.modules)
        for name, handler in (("M112", self.cmd_M112), ("RESTART", self.cmd_RESTART),
                              ("FIRMWARE_RESTART", self.cmd_RESTART),
                              ("SAVE_CONFIG", self.cmd_SAVE_CONFIG)):
            if name not in self.macros:
                self.register_command(name, handler)
        if limits.arcs_enabled:
            arcs = ArcSupport(gcode_move, limits.arc_resolution)
            for name in ("G2", "G3", "G17", "G18", "G19"):
                self.register_command(name, getattr(arcs, "cmd_" + name))
        if limits.firmware_retraction_enabled:
            retraction = FirmwareRetraction(limits, gcode_move)
            for name in ("G10", "G11", "SET_RETRACTION"):
                self.register_command(name, getattr(retraction, "cmd_" + name))
        self.exclude_object: ExcludeObject | None = None
        if self.modules is None or "exclude_object" in self.modules:
            self._load_exclude_object(gcode_move)
        # Move transforms, in upstream's order: bed_mesh at config load, skew_correction at
        # connect (forced in front of it); exclude_object's at the first exclusion (forced
        # in front of both).
        machine = limits.machine
        self.bed_mesh: BedMesh | None = None
        if machine is not None and machine.has_section("bed_mesh"):
            self.bed_mesh = bed_mesh = BedMesh(machine, gcode_move, warn)
            for name in ("BED_MESH_PROFILE", "BED_MESH_CLEAR", "BED_MESH_OFFSET",
                         "BED_MESH_CALIBRATE"):
                self.register_command(name, getattr(bed_mesh, "cmd_" + name))
        if machine is not None and machine.has_section("skew_correction"):
            skew = PrinterSkew(machine, gcode_move)
            for name in ("SKEW_PROFILE", "SET_SKEW", "GET_CURRENT_SKEW",
                         "CALC_MEASURED_SKEW"):
                self.register_command(name, getattr(skew, "cmd_" + name))

    def _load_exclude_object(self, gcode_move: GCodeMove) -> None:
        """[exclude_object] (also when no printer config is known: a file that labels its
        objects is printed with it). Its commands stay counted as before: module commands
        with the config, unknown ones without (the printer may lack the module)."""
        self.exclude_object = exclude = ExcludeObject(gcode_move)
        for name in ("EXCLUDE_OBJECT_START", "EXCLUDE_OBJECT_END", "EXCLUDE_OBJECT",
                     "EXCLUDE_OBJECT_DEFINE"):
            if name in self.macros:
                continue
            handler: Handler = getattr(exclude, "cmd_" + name)
            self.register_command(name, partial(self._counted, handler))

    def _register_heater_commands(self, heaters: PrinterHeaters,
                                  modules: frozenset[str]) -> None:
        """The heater commands each configured object registers (a [gcode_macro] of the
        same name, renaming the original, takes its place)."""
        commands: list[tuple[str, Handler]] = []
        if "extruder" in modules:
            commands += [("M104", heaters.cmd_M104), ("M109", heaters.cmd_M109)]
        if "heater_bed" in modules:
            commands += [("M140", self._cmd_M140), (HEATER_BED_WAIT, heaters.cmd_M190)]
        if heaters.heaters:
            commands.append(("SET_HEATER_TEMPERATURE", heaters.cmd_SET_HEATER_TEMPERATURE))
        if heaters.sensors:
            commands.append(("TEMPERATURE_WAIT", heaters.cmd_TEMPERATURE_WAIT))
        for name, handler in commands:
            if name not in self.macros:
                self.register_command(name, handler)

    def _rest(self, seconds: float, name: str, source: str) -> None:
        """Added time without a timeline: the toolhead rests that long."""
        self.toolhead.add_time(seconds)

    def _counted(self, handler: Handler, cmd: Command) -> None:
        """An exclude_object command, counted as before: a module command with the
        config, an unknown one without (the printer may lack the module)."""
        if self.modules is None:
            self._unknown(cmd.name)
        else:
            self._count(KIND_MODULE, cmd.name)
        handler(cmd)

    def _cmd_M140(self, cmd: Command) -> None:
        """M140, counted as a module command (Estimate.commands), as before."""
        self._count(KIND_MODULE, "M140")
        self.heaters.cmd_M140(cmd)

    def _maybe_cold(self, message: str) -> None:
        """Klipper may refuse this extrusion (a macro may have heated the extruder)."""
        if self.preflight is not None:
            self.preflight.may_stop(self.gcode_move.tag, message)

    def unloaded_mesh_note(self) -> str | None:
        """Why the times may lack a bed mesh: the printer has saved mesh profiles, the file
        loaded none, and a macro kestimator does not run loads one (its text says
        BED_MESH_PROFILE or BED_MESH_CALIBRATE) or may (its text is not known). None when
        the file is explicit about the mesh."""
        bed_mesh = self.bed_mesh
        ran = self.command_kinds.get(KIND_MACRO, {})
        if bed_mesh is None or not bed_mesh.profiles or bed_mesh.ever_loaded or not ran:
            return None
        effect = ("with a mesh Klipper splits moves and follows it, which changes the time "
                  "a little (tenths of a second on a typical print); add "
                  "'BED_MESH_PROFILE LOAD=<name>' to the file to have it timed")
        loaders = [name for name in ran
                   if _MESH_COMMAND_RE.search(self.macros.get(name, ""))]
        if loaders:
            return ("macro %s loads a bed mesh, which kestimator does not run (a template): "
                    "these times are without a mesh; %s" % (", ".join(loaders), effect))
        if any(not self.macros.get(name, "").strip() for name in ran):
            return ("the printer has saved bed mesh profiles (%s) and this file loads none: "
                    "if its start macro does, %s" % (", ".join(sorted(bed_mesh.profiles)),
                                                      effect))
        return None

    def register_command(self, name: str, handler: Handler) -> None:
        """`handler` runs the command `name` from now on."""
        self.gcode_handlers[name] = handler

    # Dispatch
    def execute(self, cmd: Command) -> None:
        """Run one command; raises CommandError (state already reset) if Klipper would."""
        if cmd.name in UNSHOWN_TIME_COMMANDS and cmd.name in self.registered and \
                cmd.name not in self.macros:
            self._unshown(cmd.name)
        handler = self.gcode_handlers.get(cmd.name)
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
                self._unknown(name)
            return
        try:
            handler(cmd)
        except (CommandError, MoveError):
            self.gcode_move.reset_last_position()
            raise

    def _unshown(self, name: str) -> None:
        """A command whose time the file cannot show: timed by `on_unshown`, or said (by
        its own handler, if it has one: bed_mesh's BED_MESH_CALIBRATE)."""
        if self.on_unshown is not None and self.on_unshown(name):
            return
        if name in self.gcode_handlers:
            return
        self.warn("%s takes time the file cannot show (it probes, calibrates or measures): "
                  "counted as 0 s unless the profile's [macros] table times it (a start "
                  "time `learn` found holds it when it runs before the first extrusion)"
                  % name, "unshown:" + name)

    def _unknown(self, name: str) -> None:
        """Count a command Klipper does not know (cmd_default's "Unknown command")."""
        ignored = self.ignored
        if name in ignored:
            ignored[name] += 1
        elif len(ignored) < MAX_COMMAND_NAMES:
            ignored[name] = 1
        else:
            self.ignored_unlisted += 1
        if self.preflight is not None and self.modules is not None:
            self.preflight.unknown_command(name, self.gcode_move.tag)
        if self.on_unknown is not None:
            self.on_unknown(name)

    def _is_known(self, name: str, cmd: Command) -> bool:
        """Klipper knows this no-time command (on this printer, when its config is known)."""
        if self.modules is None:
            return name in NO_TIME_COMMANDS
        if name not in self.registered:
            return False
        if name in FAN_COMMANDS:
            self.toolhead.lookahead_callback_barrier()
        if name not in self._registered_anyway:
            self._count(KIND_MODULE, name)
        return True

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
            self.heaters.macro_ran(name, template)
            if self.on_unknown is not None:
                self.on_unknown(name)
            return
        if name in self._running_macros:
            raise CommandError("Macro %s called recursively" % name)
        self._count(KIND_EXPANDED_MACRO, name)
        self._running_macros.add(name)
        try:
            self.run_script(template)
        finally:
            self._running_macros.discard(name)

    def run_script(self, script: str) -> None:
        """gcode.run_script_from_command: each line of a literal script, in turn."""
        for line in script.split("\n"):
            sub = parse_line(line.strip())
            if sub.name:
                self.execute(sub)

    def _count(self, kind: str, name: str) -> None:
        counts = self.command_kinds.setdefault(kind, {})
        counts[name] = counts.get(name, 0) + 1

    # Homing (homing.py PrinterHoming.cmd_G28)
    def cmd_G28(self, cmd: Command) -> None:
        """Home the named axes (all of XYZ if none): after a full stop the head is where the
        kinematics' homing leaves it (each axis at its position_endstop, a delta at its
        home position), and the G-code offsets of the homed axes are reset."""
        axes = [pos for pos, axis in enumerate("XYZ") if axis in cmd.params]
        if not axes:
            axes = [0, 1, 2]
        toolhead = self.toolhead
        newpos, homed = toolhead.kin.home(toolhead.commanded_pos, axes)
        toolhead.set_position(newpos, homed)
        self.gcode_move._handle_home_rails_end(homed)

    def _load_homing_modules(self, limits: Limits) -> None:
        """[safe_z_home] and [homing_override] take G28 over, as their modules do when
        klippy loads them (safe_z_home refuses to share it with homing_override)."""
        machine = limits.machine
        if machine is None:
            return
        section = machine.section("safe_z_home")
        if section is not None:
            safe_z_home = SafeZHoming(section, machine, self.toolhead,
                                      self.gcode_handlers["G28"],
                                      self.gcode_move.reset_last_position)
            self.register_command("G28", safe_z_home.cmd_G28)
        section = machine.section("homing_override")
        if section is not None:
            override = HomingOverride(section, self.toolhead, self.gcode_handlers["G28"],
                                      self.run_script, self.gcode_move.reset_last_position,
                                      self.warn)
            self.register_command("G28", override.cmd_G28)

    def _cmd_G28_timed(self, cmd: Command) -> None:
        """A G28 line: the G28 of the module that owns it; the homing time once per line
        (a G28 a homing_override runs is part of its line's)."""
        self._homing_depth += 1
        try:
            self._home_G28(cmd)
        finally:
            self._homing_depth -= 1
        if self._homing_depth == 0 and self.homing_time > 0.0:
            self.add_time(self.homing_time, "G28", HOMING_SOURCE)
        elif self._homing_depth == 0:
            self.untimed_homings += 1

    # force_move.py ForceMove.cmd_SET_KINEMATIC_POSITION
    def cmd_SET_KINEMATIC_POSITION(self, cmd: Command) -> None:
        """Declare the toolhead position without moving; SET_HOMED (default all of XYZ)
        are homed from now on, CLEAR_HOMED (or CLEAR) no longer."""
        params = command_params(cmd)
        toolhead = self.toolhead
        pos = list(toolhead.commanded_pos)
        for i, axis in enumerate("XYZ"):
            value = get_float(params, axis)
            if value is not None:
                pos[i] = value
        set_homed = params.get("SET_HOMED", "xyz").lower()
        homed = "".join(a for a in "xyz" if a in set_homed)
        clear = params.get("CLEAR_HOMED")
        if clear is None:
            # "CLEAR" is an alias for "CLEAR_HOMED"
            clear = params.get("CLEAR", "")
        cleared = "".join(a for a in "xyz" if a in clear.lower())
        toolhead.set_position((pos[0], pos[1], pos[2], pos[3]), homed)
        toolhead.kin.clear_homing_state(cleared)
        self.gcode_move.reset_last_position()

    # Heaters (heaters.py) without the printer's config: only the wait
    def cmd_M109(self, cmd: Command) -> None:
        """M109/M190: set a temperature and, when S is not 0, wait for it."""
        if get_float(cmd.params, "S", 0.0):
            self.heaters.wait(cmd.name)

    # gcode.py GCodeDispatch.cmd_M112 (Klipper's emergency stop: a shutdown)
    def cmd_M112(self, cmd: Command) -> None:
        """Klipper shuts down: the print ends here, with Klipper's message."""
        raise CommandError("Shutdown due to M112 command")

    # gcode.py GCodeDispatch.cmd_RESTART / cmd_FIRMWARE_RESTART (request_restart)
    def cmd_RESTART(self, cmd: Command) -> None:
        """Klipper restarts once every move before has finished: the print ends here."""
        raise PrintEndsError("%s restarts Klipper: the print ends here" % cmd.name)

    # configfile.py PrinterConfig.cmd_SAVE_CONFIG
    def cmd_SAVE_CONFIG(self, cmd: Command) -> None:
        """A restart if settings were left to save, which the file may not show."""
        if self.preflight is not None:
            self.preflight.may_stop(self.gcode_move.tag, SAVE_CONFIG_MAY_STOP)

    def cmd_M84(self, cmd: Command) -> None:
        """stepper_enable.py motor_off, set_motors_enable's or older (`old_motor_off`)."""
        toolhead = self.toolhead
        if not toolhead.old_motor_off:
            toolhead.flush_step_generation()
        if toolhead.motors_enabled or toolhead.old_motor_off:
            toolhead.dwell(DISABLE_STALL_T)
            toolhead.get_last_move_time()
            toolhead.dwell(DISABLE_STALL_T)
            toolhead.motors_enabled = False
        toolhead.kin.clear_homing_state("xyz")
