"""Mirrors klippy/extras/heaters.py at Klipper commit 84104bbbd (GNU GPLv3).

The printer's heaters as the G-code sees them (`PrinterHeaters`): each heater's range
(`Heater.set_temp` refuses a target outside min_temp..max_temp, except 0, which turns it
off), the commands that set or wait for a temperature, and the extruders' cold-extrusion
check (`Heater.can_extrude`, which upstream's `PrinterExtruder.check_move` reads). As upstream,
the commands are registered by the objects that own the heaters: M104/M109 with [extruder]
(kinematics/extruder.py `cmd_M104`, with its T parameter), M140/M190 with [heater_bed]
(extras/heater_bed.py), SET_HEATER_TEMPERATURE per heater on HEATER= and TEMPERATURE_WAIT
per sensor on SENSOR= (`register_mux_command`, gcode.py `_cmd_mux`).

Batch mode has no temperatures: a wait brings the toolhead to rest and takes the heat time
given (0 s by default). Cold extrusion: upstream refuses an extrusion while the heater's
measured temperature is below `min_extrude_temp`. The file cannot show temperatures, so a
heater counts as hot from the first command that sets it to `min_extrude_temp` or more, and
stays hot (it cools slowly: the moves after an `M104 S0` at the end are fine); so do all
extruders after a template macro whose text sets a heater. An extrusion (or retraction)
before that is Klipper's error, unless a macro whose commands are not known ran before it
(Moonraker's macros, known by name only, or one calling other macros: a start macro may
heat): then the pre-flight only says Klipper may stop there.

Without the printer's config nothing is checked: M104/M140/SET_HEATER_TEMPERATURE take no
time, M109/M190/TEMPERATURE_WAIT only wait.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import TYPE_CHECKING

from kestimator.errors import CommandError, MoveError, ParamError
from kestimator.gcode import Command, command_params, get_float, mux_error
from kestimator.limits import HeaterLimits, Limits, heater_sections
from kestimator.macros import HEAT_SOURCE

if TYPE_CHECKING:
    from kestimator.extruder import PrinterExtruder, PrinterExtruders
    from kestimator.toolhead import ToolHead

# PrinterExtruder.check_move's error while the heater is below min_extrude_temp.
COLD_EXTRUDE_ERROR = ("Extrude below minimum temp\n"
                      "See the 'min_extrude_temp' config option for details")
# Sections whose objects register a TEMPERATURE_WAIT sensor besides the heaters
# (extras/temperature_sensor.py, temperature_fan.py, temperature_probe.py,
# z_thermal_adjust.py: `register_sensor`).
SENSOR_PREFIXES = ("temperature_sensor ", "temperature_fan ", "temperature_probe ")
SENSOR_SECTIONS = ("z_thermal_adjust",)
# Commands of a macro's text that set a heater (a macro whose text has none of these and
# calls no other macro does not heat).
_HEATING_RE = re.compile(r"\b(M104|M109|SET_HEATER_TEMPERATURE)\b", re.IGNORECASE)

# add_time(seconds, name, source), as the interpreter's.
AddTimeFn = Callable[[float, str, str], None]


class Heater:
    """One heater: its range (None when the config does not give it) and its target."""

    def __init__(self, name: str, limits: HeaterLimits | None) -> None:
        self.name = name
        self.short_name = name.split()[-1]
        self.limits = limits
        self.target_temp = 0.0

    def set_temp(self, degrees: float) -> None:
        """Set the target; outside min_temp..max_temp (0 aside) is Klipper's error."""
        limits = self.limits
        if limits is not None and degrees and (degrees < limits.min_temp
                                               or degrees > limits.max_temp):
            raise CommandError("Requested temperature (%.1f) out of range (%.1f:%.1f)"
                               % (degrees, limits.min_temp, limits.max_temp))
        self.target_temp = degrees


class PrinterHeaters:
    """Every heater and sensor of the printer, and the commands that set and wait for them."""

    def __init__(self, limits: Limits, toolhead: ToolHead, extruders: PrinterExtruders,
                 heat_time: float, add_time: AddTimeFn) -> None:
        self.toolhead = toolhead
        self.extruders = extruders
        self.heat_time = heat_time
        # Heater waits that took no time (no heat time given).
        self.untimed_waits = 0
        self.add_time = add_time
        sections = limits.configured_sections
        # Heaters by their lower-case short name (SET_HEATER_TEMPERATURE's HEATER=); Klipper
        # compares names exactly, here case is ignored (never a false error).
        self.heaters: dict[str, Heater] = {}
        for name in heater_sections(sections):
            heater = Heater(name, limits.heater(name))
            self.heaters[heater.short_name.lower()] = heater
        self.sensors = [h.name for h in self.heaters.values()] + [
            s for s in sections if s.startswith(SENSOR_PREFIXES) or s in SENSOR_SECTIONS]
        # Macros whose commands are not known ran: they may have heated the extruders.
        self.may_have_heated: str | None = None
        self.macro_names = frozenset(name for name, _ in limits.gcode_macros)
        # Said when an extrusion comes before any heating but a macro may have heated.
        self.on_maybe_cold: Callable[[str], None] | None = None
        for name, extruder in extruders.extruders.items():
            own = self.heaters.get(name)
            if own is not None and own.limits is not None \
                    and own.limits.min_extrude_temp > 0.0:
                extruder.can_extrude = False
                extruder.cold_extrude = self.cold_extrude

    def heater_of(self, section: str) -> Heater | None:
        """The heater of a config section, if the printer has it."""
        return self.heaters.get(section.split()[-1].lower())

    def set_temperature(self, heater: Heater, temp: float, wait: bool = False,
                        name: str = "") -> None:
        """Set a heater's target (Klipper's range check) and, with `wait`, wait for it."""
        self.toolhead.lookahead_callback_barrier()
        heater.set_temp(temp)
        limits = heater.limits
        if limits is not None and temp >= limits.min_extrude_temp:
            extruder = self.extruders.extruders.get(heater.name)
            if extruder is not None:
                extruder.can_extrude = True
        if wait and temp:
            self.wait(name)

    def wait(self, name: str) -> None:
        """A heater wait: the toolhead comes to rest, then the heat time given passes."""
        self.toolhead.wait_heater()
        if self.heat_time > 0.0:
            self.add_time(self.heat_time, name, HEAT_SOURCE)
        else:
            self.untimed_waits += 1

    def macro_ran(self, name: str, template: str) -> None:
        """A [gcode_macro] ran whose commands are not run here (a template). Its text sets
        a heater (M104, M109, SET_HEATER_TEMPERATURE): the extruders count as heated. Its
        text is not known (Moonraker's) or it calls another macro: it may have heated. Its
        text is known and does neither: it heated nothing."""
        if _HEATING_RE.search(template):
            for extruder in self.extruders.extruders.values():
                extruder.can_extrude = True
            return
        words = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", template.upper()))
        if self.may_have_heated is None and (
                not template.strip() or (words & self.macro_names) - {name}):
            self.may_have_heated = name

    def cold_extrude(self, extruder: PrinterExtruder) -> None:
        """An extrusion while `extruder`'s heater was never set hot: Klipper's error, or,
        after a macro that may heat, a note that Klipper may stop here. Said once."""
        extruder.can_extrude = True
        if self.may_have_heated is not None:
            if self.on_maybe_cold is not None:
                self.on_maybe_cold(
                    "%s (if '%s', which ran before, did not heat [%s] to its "
                    "min_extrude_temp)" % (COLD_EXTRUDE_ERROR.split("\n")[0],
                                           self.may_have_heated, extruder.name))
            return
        raise MoveError(COLD_EXTRUDE_ERROR)

    # kinematics/extruder.py PrinterExtruder.cmd_M104 / cmd_M109
    def cmd_M104(self, cmd: Command, wait: bool = False) -> None:
        """Set the active extruder's (or extruder T's) temperature."""
        temp = get_float(cmd.params, "S", 0.0)
        index = _get_index(cmd.params)
        if index is not None:
            section = "extruder%d" % index if index else "extruder"
            if section not in self.extruders.extruders:
                if temp <= 0.0:
                    return
                raise CommandError("Extruder not configured")
        else:
            section = self.extruders.active
        heater = self.heater_of(section)
        if heater is None:
            raise CommandError("Extruder not configured")
        self.set_temperature(heater, temp, wait, cmd.name)

    def cmd_M109(self, cmd: Command) -> None:
        """Set an extruder's temperature and wait for it."""
        self.cmd_M104(cmd, wait=True)

    # heater_bed.py PrinterHeaterBed.cmd_M140 / cmd_M190
    def cmd_M140(self, cmd: Command, wait: bool = False) -> None:
        """Set the bed's temperature."""
        temp = get_float(cmd.params, "S", 0.0)
        heater = self.heater_of("heater_bed")
        if heater is not None:
            self.set_temperature(heater, temp, wait, cmd.name)

    def cmd_M190(self, cmd: Command) -> None:
        """Set the bed's temperature and wait for it."""
        self.cmd_M140(cmd, wait=True)

    # Heater.cmd_SET_HEATER_TEMPERATURE (registered per heater on HEATER=)
    def cmd_SET_HEATER_TEMPERATURE(self, cmd: Command) -> None:
        """Set a heater's target."""
        params = command_params(cmd)
        key = params.get("HEATER")
        if key is None:
            raise ParamError("missing HEATER")
        heater = self.heaters.get(key.lower())
        if heater is None:
            raise mux_error(key, "HEATER", [h.short_name for h in self.heaters.values()])
        temp = get_float(params, "TARGET", 0.0)
        self.set_temperature(heater, temp)

    # PrinterHeaters.cmd_TEMPERATURE_WAIT (registered per sensor on SENSOR=)
    def cmd_TEMPERATURE_WAIT(self, cmd: Command) -> None:
        """Wait until a sensor is in range (Klipper does not compare the range with the
        sensor's: a MINIMUM above a heater's max_temp waits for ever on a printer)."""
        params = command_params(cmd)
        key = params.get("SENSOR")
        if key is None:
            raise ParamError("missing SENSOR")
        if self.sensors and key.lower() not in self.sensors:
            raise mux_error(key, "SENSOR", self.sensors)
        low = get_float(params, "MINIMUM", -math.inf)
        high = get_float(params, "MAXIMUM", math.inf, above=low)
        if low == -math.inf and high == math.inf:
            raise CommandError("Error on 'TEMPERATURE_WAIT': missing MINIMUM or MAXIMUM.")
        self.wait("TEMPERATURE_WAIT")


def _get_index(params: dict[str, str]) -> int | None:
    """`gcmd.get_int('T', None, minval=0)`."""
    raw = params.get("T")
    if raw is None:
        return None
    try:
        value = int(raw)
    except ValueError:
        raise ParamError("unable to parse %s" % raw) from None
    if value < 0:
        raise ParamError("T must have minimum of 0")
    return value

