"""Reading a Klipper printer.cfg as Klipper reads it, and mapping it to `Limits`.

This module owns the printer.cfg syntax and nothing else of Klipper's configuration:
sections and options, comments, indented continuation lines, `[include]` files and the
SAVE_CONFIG block, with the file and line every value came from; and the mapping of the
motion options kestimator models onto `Limits` fields, checked against the same bounds
Klipper enforces. Defaults for absent options stay in `kestimator.limits`.

Klipper has no option for the Klipper generation a printer runs; a comment
``# kestimator: klipper_generation = mcr`` in the main file names it (Klipper ignores comments),
as ``# kestimator: klipper_version = v0.12.0`` names the Klipper the printer runs.

The rules follow mainline Klipper at commit 84104bbbd, klippy/configfile.py (Python's
configparser as Klipper configures it: no interpolation, later duplicates win, `#` and `;`
comments), re-implemented here so that every value keeps its file and line.
"""

from __future__ import annotations

import dataclasses
import glob
import math
import operator
import os
import re

from kestimator.config.klipper_options import (
    ANY_KLIPPY_OPTION,
    BUILT_OPTION_NAMES,
    KINEMATICS_OPTIONS,
    PRINTER_OPTIONS,
    SECTION_OPTIONS,
)
from kestimator.config.machine import MachineConfig, arithmetic_violation
from kestimator.errors import KestimatorError
from kestimator.files import read_config_bytes
from kestimator.limits import (
    KLIPPER_GENERATIONS,
    ExtruderLimits,
    ExtruderStepperLimits,
    HeaterLimits,
    Limits,
    find_generation_directive,
    find_version_directive,
    heater_limits,
    heater_sections,
    klipper_release,
)
from kestimator.stepgen import (
    DEFAULT_DAMPING_RATIO,
    MAX_SMOOTH_TIME_T,
    SHAPER_MAX_DAMPING,
    ShaperError,
    shaper_name,
    shaper_pulses,
)

# Klipper recognises the SAVE_CONFIG block only by these three whole lines, preceded by a
# line break and followed by one.
_AUTOSAVE_HEADER = (
    "#*# <---------------------- SAVE_CONFIG ---------------------->",
    "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.",
    "#*#",
)
_AUTOSAVE_PREFIX = "#*# "
_INCLUDE_PREFIX = "include "

KLIPPER_DEFAULT = "klipper default"
KESTIMATOR_DEFAULT = "kestimator default"
REQUIRED_FALLBACK = "guessed: required by Klipper but not in the config"


@dataclasses.dataclass(frozen=True)
class ConfigValue:
    """One option's value as written, and where it was written."""

    value: str      # raw text
    path: str       # file it came from
    line: int       # 1-based line in that file

    @property
    def location(self) -> str:
        """`<file>:<line>`."""
        return f"{self.path}:{self.line}"


Sections = dict[str, dict[str, ConfigValue]]


@dataclasses.dataclass
class _Config:
    """Sections being read, and where each section was first declared."""

    sections: Sections = dataclasses.field(default_factory=dict)
    headers: dict[str, str] = dataclasses.field(default_factory=dict)
    # What the [include]s have read so far (each inclusion counted, see MAX_INCLUDED_FILES).
    files_included: int = 0
    chars_included: int = 0
    # What was read, in order: ("file", path, its bytes) and ("glob", pattern, matches).
    reads: list[tuple[str, str, object]] = dataclasses.field(default_factory=list)

    def section(self, name: str, path: str, line: int) -> dict[str, ConfigValue]:
        """The section called `name` (any case), created at path:line if new."""
        key = name.lower()
        if key not in self.sections:
            self.sections[key] = {}
            self.headers[key] = f"{path}:{line}"
        return self.sections[key]


@dataclasses.dataclass
class _Option:
    """An option whose continuation lines may still follow."""

    section: dict[str, ConfigValue]
    name: str
    line: int
    parts: list[str]

    def store(self, path: str) -> None:
        """Write the value to its section as configparser joins it."""
        self.section[self.name] = ConfigValue("\n".join(self.parts).rstrip(), path,
                                              self.line)


_NumberedLines = list[tuple[int, str]]


def read_printer_cfg(path: str | os.PathLike[str]) -> Sections:
    """sections (lower-case names, e.g. 'printer', 'extruder', 'gcode_arcs') -> options
    (lower-case) -> value, after includes and the SAVE_CONFIG block, as Klipper merges them.

    Raises KestimatorError for an unreadable file, a missing include, an include cycle or
    a line that is not config syntax.
    """
    config = _Config()
    _read_config(os.fspath(path), config)
    return config.sections


def limits_from_printer_cfg(path: str | os.PathLike[str]) -> tuple[Limits, dict[str, str]]:
    """Limits plus, for every Limits field, where it came from.

    A value read from the config is reported as "<file>:<line>"; the rest as
    "klipper default", "derived from <option>", "kestimator default" (klipper_generation)
    or, for options Klipper requires but the config lacks, `REQUIRED_FALLBACK`.
    """
    values, provenance, machine = printer_cfg_values(path)
    limits = Limits.from_values(values).replace(machine=machine)
    for field in Limits.field_names():
        provenance.setdefault(field, ABSENT_PROVENANCE.get(field, KLIPPER_DEFAULT))
    return limits, provenance


def _machine_config(path: str, config: _Config) -> MachineConfig:
    """The sections the kinematics reads ([printer], [stepper_*], [dual_carriage], probes),
    each option with its "<file>:<line>"."""
    return MachineConfig.build(path, {
        name: {option: (raw.value, raw.location) for option, raw in options.items()}
        for name, options in config.sections.items()})


_Values = tuple[dict[str, object], dict[str, str], MachineConfig]

# The last printer_cfg_values: its path, what it read (_Config.reads) and its result.
_last: tuple[str, list[tuple[str, str, object]], _Values] | None = None


def printer_cfg_values(path: str | os.PathLike[str]) -> _Values:
    """Only the Limits fields the config sets, the "<file>:<line>" each came from, and the
    sections the kinematics reads (`MachineConfig`), from one reading of the files.

    A field the config leaves out is Klipper's default (``Limits.from_values`` fills it in);
    ``arcs_enabled`` and ``firmware_retraction_enabled`` are set, to True, where their
    section is declared; ``klipper_generation`` where a comment of the main file says
    ``kestimator: klipper_generation = <name>``. Raises KestimatorError (file and line) for
    values Klipper rejects.

    The last result is kept with what it read: asked again for the same path, when every
    file read then reads the same bytes and every [include] pattern matches the same
    files, it is that result again (the worker resolves the printer for each answer: the
    parse was 1 of its 3 ms).
    """
    global _last
    name = os.fspath(path)
    last = _last
    if last is not None and last[0] == name and _reads_again(last[1]):
        values, provenance, machine = last[2]
        return dict(values), dict(provenance), machine
    config = _Config()
    result = _printer_cfg_values(name, config)
    _last = (name, config.reads, (dict(result[0]), dict(result[1]), result[2]))
    return result


def _reads_again(reads: list[tuple[str, str, object]]) -> bool:
    """Whether the files and patterns read give what they gave (`_Config.reads`)."""
    for kind, name, seen in reads:
        if kind == "glob":
            if sorted(glob.glob(name)) != seen:
                return False
        else:
            try:
                if read_config_bytes(name, "config") != seen:
                    return False
            except KestimatorError:
                return False
    return True


def _printer_cfg_values(path: str, config: _Config) -> _Values:
    _read_config(path, config)
    values: dict[str, object] = {}
    provenance: dict[str, str] = {}
    read_from: dict[str, ConfigValue] = {}
    directive = _generation_directive(path, config)
    version = _version_directive(path, config)
    check_options(config.sections)
    if directive is not None:
        values["klipper_generation"] = directive.value
        read_from["klipper_generation"] = directive
    if version is not None:
        values["klipper_version"] = version.value
        read_from["klipper_version"] = version
    for spec in FLOAT_OPTIONS:
        raw = config.sections.get(spec.section, {}).get(spec.option)
        if raw is not None:
            values[spec.field] = spec.parse(raw)
            read_from[spec.field] = raw
    kinematics = config.sections.get("printer", {}).get("kinematics")
    if kinematics is not None:
        if not kinematics.value:
            raise KestimatorError("[printer] kinematics is empty", kinematics.path,
                                  kinematics.line)
        values["kinematics"] = kinematics.value
        read_from["kinematics"] = kinematics
    for section, field in (("gcode_arcs", "arcs_enabled"),
                           ("firmware_retraction", "firmware_retraction_enabled"),
                           ("input_shaper", "input_shaper_enabled")):
        if section in config.sections:
            values[field] = True
            provenance[field] = config.headers[section]
    if "input_shaper" in config.sections:
        _read_input_shaper(config.sections["input_shaper"], values, read_from)
    values["configured_sections"] = tuple(config.sections)
    # A config of comments only (Klipper's config/example.cfg) has no section to point at.
    provenance["configured_sections"] = (next(iter(config.headers.values())) if config.headers
                                         else f"{os.fspath(path)}: no sections")
    macros = _read_macros(config)
    if macros:
        values["gcode_macros"] = macros
        provenance["gcode_macros"] = ", ".join(
            config.headers["gcode_macro " + name.lower()] for name, _ in macros)
    limits = Limits.from_values(values)
    extruders = _read_extra_extruders(config, limits)
    if extruders:
        values["extruders"] = extruders
        provenance["extruders"] = ", ".join(
            config.headers[e.name] for e in extruders)
        limits = limits.replace(extruders=extruders)
    steppers = _read_extruder_steppers(config)
    if steppers:
        values["extruder_steppers"] = steppers
        provenance["extruder_steppers"] = ", ".join(
            config.headers["extruder_stepper " + e.name] for e in steppers)
    heaters = _read_heaters(config)
    if heaters:
        values["heaters"] = heaters
        provenance["heaters"] = ", ".join(config.headers[h.name] for h in heaters)
    for field, bound, allowed, text in RELATIVE_BOUNDS:
        raw = read_from.get(field)
        if raw is not None and not allowed(getattr(limits, field), getattr(limits, bound)):
            raise KestimatorError(
                f"{field} must be {text} {bound} ({getattr(limits, bound):g}), "
                f"got {raw.value}", raw.path, raw.line)
    for field, raw in read_from.items():
        provenance[field] = raw.location
    return values, provenance, _machine_config(path, config)


def check_options(sections: Sections) -> None:
    """Raise KestimatorError (file, line, a suggestion) for the first option Klipper would
    refuse to start with in a section kestimator reads; other sections are left alone.

    The accepted names come from Klipper's own config reads (`klipper_options`).
    ``max_accel_to_decel`` in [printer] is left to the resolver: older Klipper generations
    read it, and the generation may still be set on the command line (mainline's refusal is
    a warning there).
    """
    printer = sections.get("printer", {})
    kinematics = printer.get("kinematics")
    for name, options in sections.items():
        accepted = _accepted_options(name, kinematics.value if kinematics else None)
        if accepted is None:
            continue
        for option, raw in options.items():
            if option in accepted or (_EXTRUDER_SECTION.match(name)
                                      and _NUMBERED_OPTION.match(option)):
                continue
            import difflib  # here: only an error needs it (1 ms of every start)

            close = difflib.get_close_matches(option, sorted(accepted), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise KestimatorError(f"[{name}] has no option '{option}'{hint}: Klipper "
                                  "refuses to start with it", raw.path, raw.line)


def _accepted_options(section: str, kinematics: str | None) -> frozenset[str] | None:
    """The options Klipper accepts in ``section``; None for a section not checked."""
    if section == "printer":
        if kinematics is None or kinematics not in KINEMATICS_OPTIONS:
            return None  # the kinematics' own error comes first
        return PRINTER_OPTIONS | KINEMATICS_OPTIONS[kinematics] | {"max_accel_to_decel"}
    if _EXTRUDER_SECTION.match(section):
        return ANY_KLIPPY_OPTION | BUILT_OPTION_NAMES
    return SECTION_OPTIONS.get(section)


_EXTRUDER_SECTION = re.compile(r"extruder[0-9]*$")
# Sensor tables ([extruder] sensor_type of adc_temperature / thermistor): temperature1, ...
_NUMBERED_OPTION = re.compile(r"(temperature|voltage|resistance)[0-9]+$")


def _read_input_shaper(section: dict[str, ConfigValue], values: dict[str, object],
                       read_from: dict[str, ConfigValue]) -> None:
    """shaper_type(_<axis>) of [input_shaper], each shaper checked as Klipper checks it."""
    common = section.get("shaper_type")
    for axis in "xyz":
        raw = section.get("shaper_type_" + axis, common)
        shaper_type = raw.value if raw is not None else "mzv"
        field = "shaper_type_" + axis
        if raw is not None:
            values[field] = shaper_type
            read_from[field] = raw
        where = raw or section.get("shaper_freq_" + axis)
        name = shaper_name(shaper_type)
        if name not in SHAPER_MAX_DAMPING:
            at = where or next(iter(section.values()), None)
            raise KestimatorError(f"[input_shaper] Unsupported shaper type: {shaper_type}",
                                  at.path if at else None, at.line if at else None)
        damping = float(values.get("damping_ratio_" + axis, DEFAULT_DAMPING_RATIO))  # type: ignore[arg-type]
        damping_raw = section.get("damping_ratio_" + axis)
        if damping > SHAPER_MAX_DAMPING[name] and damping_raw is not None:
            raise KestimatorError(
                f"[input_shaper] damping_ratio_{axis} must be at most "
                f"{SHAPER_MAX_DAMPING[name]:g} for shaper {name}, got {damping_raw.value}",
                damping_raw.path, damping_raw.line)
        try:
            shaper_pulses(shaper_type, float(values.get("shaper_freq_" + axis, 0.0)),  # type: ignore[arg-type]
                          damping)
        except ShaperError as exc:
            at = where or damping_raw
            raise KestimatorError(f"[input_shaper] {exc}", at.path if at else None,
                                  at.line if at else None) from None


def _read_macros(config: _Config) -> tuple[tuple[str, str], ...]:
    """(NAME, gcode template) of every [gcode_macro NAME] (extras/gcode_macro.py)."""
    macros = []
    for section, options in config.sections.items():
        if not section.startswith(MACRO_PREFIX):
            continue
        name = section[len(MACRO_PREFIX):].strip().upper()
        template = options.get("gcode")
        if name and template is not None:
            macros.append((name, template.value.strip()))
    return tuple(macros)


MACRO_PREFIX = "gcode_macro "


def _read_extra_extruders(config: _Config, limits: Limits) -> tuple[ExtruderLimits, ...]:
    """[extruder1] ... in order, as kinematics/extruder.py add_printer_objects finds them."""
    extruders = []
    for index in range(1, MAX_EXTRUDERS):
        name = f"extruder{index}"
        section = config.sections.get(name)
        if section is None:
            break
        values: dict[str, object] = {}
        for spec in FLOAT_OPTIONS:
            raw = section.get(spec.option)
            if spec.section == "extruder" and raw is not None:
                values[spec.option] = dataclasses.replace(spec, section=name).parse(raw)
        values["has_stepper"] = any(option in section for option in STEPPER_OPTIONS)
        extruder = ExtruderLimits.from_values(name, values, limits.max_velocity,
                                              limits.max_accel)
        if extruder.filament_diameter < extruder.nozzle_diameter:
            raw = section["filament_diameter"]
            raise KestimatorError(f"[{name}] filament_diameter must be at least "
                                  f"nozzle_diameter ({extruder.nozzle_diameter:g}), "
                                  f"got {raw.value}", raw.path, raw.line)
        extruders.append(extruder)
    return tuple(extruders)


def _read_heaters(config: _Config) -> tuple[HeaterLimits, ...]:
    """The range of each heater (klippy/extras/heaters.py `Heater`) whose min_temp and
    max_temp the config gives (Klipper requires both: without them the range is unknown and
    not checked)."""
    heaters = []
    for name in heater_sections(list(config.sections)):
        section = config.sections[name]
        raws = [section.get(option) for option in HEATER_OPTIONS]
        if raws[0] is None or raws[1] is None:
            continue
        numbers = [None if raw is None else
                   FloatOption(name, option, option).parse(raw)
                   for option, raw in zip(HEATER_OPTIONS, raws)]
        found = heater_limits(name, numbers[0] or 0.0, numbers[1] or 0.0, numbers[2])
        if isinstance(found, str):
            raw = next(r for option, r in zip(HEATER_OPTIONS, raws)
                       if r is not None and found.startswith(option))
            raise KestimatorError(f"[{name}] {found}", raw.path, raw.line)
        heaters.append(found)
    return tuple(heaters)


def _read_extruder_steppers(config: _Config) -> tuple[ExtruderStepperLimits, ...]:
    """Each [extruder_stepper NAME]: the extruder it follows (Klipper requires the option;
    empty for none) and its pressure advance (kinematics/extruder.py `ExtruderStepper`)."""
    steppers = []
    for section_name, section in config.sections.items():
        words = section_name.split()
        if len(words) < 2 or words[0] != "extruder_stepper":
            continue
        extruder = section.get("extruder")
        if extruder is None:
            path, _, line = config.headers[section_name].rpartition(":")
            raise KestimatorError(f"[{section_name}] needs an 'extruder' option (the extruder "
                                  "it follows; Klipper requires it)", path, int(line))
        found = {}
        for option, spec in EXTRUDER_STEPPER_OPTIONS.items():
            raw = section.get(option)
            if raw is not None:
                found[option] = dataclasses.replace(spec, section=section_name).parse(raw)
        steppers.append(ExtruderStepperLimits(words[-1], extruder.value.strip(), **found))
    return tuple(steppers)


# A heater's options that kestimator reads (the first two are required by Klipper).
HEATER_OPTIONS = ("min_temp", "max_temp", "min_extrude_temp")


# Klipper loads [extruder] ... [extruder98] while the sections follow on without a gap.
MAX_EXTRUDERS = 99
# An [extruderN] with one of these has its own stepper (PrinterExtruder.__init__).
STEPPER_OPTIONS = ("step_pin", "dir_pin", "rotation_distance")


def _version_directive(path: str, config: _Config) -> ConfigValue | None:
    """The Klipper version a ``kestimator: klipper_version = <version>`` comment of the main
    file names, checked (`klipper_release`), with its line."""
    for number, text in enumerate(_read_lines(path, None, config), start=1):
        stripped = text.lstrip()
        if not stripped.startswith(("#", ";")):
            continue
        version = find_version_directive(stripped)
        if version is None:
            continue
        try:
            klipper_release(version)
        except ValueError as exc:
            raise KestimatorError(str(exc), path, number) from None
        return ConfigValue(version, path, number)
    return None


def _generation_directive(path: str, config: _Config) -> ConfigValue | None:
    """The Klipper generation a comment of the main file names, checked, with its line."""
    for number, text in enumerate(_read_lines(path, None, config), start=1):
        stripped = text.lstrip()
        if not stripped.startswith(("#", ";")):
            continue
        name = find_generation_directive(stripped)
        if name is None:
            continue
        if name not in KLIPPER_GENERATIONS:
            raise KestimatorError(f"klipper_generation must be one of "
                                  f"{', '.join(KLIPPER_GENERATIONS)}, not {name!r}",
                                  path, number)
        return ConfigValue(name, path, number)
    return None


@dataclasses.dataclass(frozen=True)
class FloatOption:
    """A numeric option, its Limits field and the bounds Klipper's getfloat() enforces."""

    section: str
    option: str
    field: str
    minval: float | None = None
    above: float | None = None
    below: float | None = None
    maxval: float | None = None

    def parse(self, raw: ConfigValue) -> float:
        """The option's value as a number, or a KestimatorError naming file and line."""
        name = f"[{self.section}] {self.option}"
        try:
            value = float(raw.value)
        except ValueError:
            raise KestimatorError(f"{name}: {raw.value!r} is not a number",
                                  raw.path, raw.line) from None
        if not math.isfinite(value):
            raise KestimatorError(f"{name}: {raw.value!r} is not a finite number",
                                  raw.path, raw.line)
        problem = self.violation(value)
        if problem is not None:
            raise KestimatorError(f"{name} {problem}, got {raw.value}", raw.path, raw.line)
        return value

    def violation(self, value: float) -> str | None:
        """A text such as "must be at least 1" if Klipper refuses ``value``, else None."""
        problem = arithmetic_violation(value)
        if problem is not None:
            return problem
        for bound, allowed, text in ((self.minval, operator.ge, "at least"),
                                     (self.above, operator.gt, "above"),
                                     (self.below, operator.lt, "below"),
                                     (self.maxval, operator.le, "at most")):
            if bound is not None and not allowed(value, bound):
                return f"must be {text} {bound:g}"
        return None


# Bounds as in klippy/toolhead.py, kinematics/*.py, kinematics/extruder.py,
# extras/gcode_arcs.py and extras/firmware_retraction.py at 84104bbbd
# (max_accel_to_decel as in the Klipper releases that still read it).
FLOAT_OPTIONS = (
    FloatOption("printer", "max_velocity", "max_velocity", above=0.0),
    FloatOption("printer", "max_accel", "max_accel", above=0.0),
    FloatOption("printer", "minimum_cruise_ratio", "minimum_cruise_ratio",
                 minval=0.0, below=1.0),
    FloatOption("printer", "square_corner_velocity", "square_corner_velocity", minval=0.0),
    FloatOption("printer", "max_z_velocity", "max_z_velocity", above=0.0),
    FloatOption("printer", "max_z_accel", "max_z_accel", above=0.0),
    FloatOption("printer", "max_accel_to_decel", "max_accel_to_decel", above=0.0),
    FloatOption("extruder", "nozzle_diameter", "nozzle_diameter", above=0.0),
    FloatOption("extruder", "filament_diameter", "filament_diameter", above=0.0),
    FloatOption("extruder", "max_extrude_cross_section", "max_extrude_cross_section",
                 above=0.0),
    FloatOption("extruder", "max_extrude_only_velocity", "max_extrude_only_velocity",
                 above=0.0),
    FloatOption("extruder", "max_extrude_only_accel", "max_extrude_only_accel", above=0.0),
    FloatOption("extruder", "max_extrude_only_distance", "max_extrude_only_distance",
                 minval=0.0),
    FloatOption("extruder", "instantaneous_corner_velocity",
                 "instantaneous_corner_velocity", minval=0.0),
    FloatOption("extruder", "pressure_advance", "pressure_advance", minval=0.0),
    FloatOption("extruder", "pressure_advance_smooth_time", "pressure_advance_smooth_time",
                above=0.0, maxval=MAX_SMOOTH_TIME_T),
    FloatOption("input_shaper", "shaper_freq_x", "shaper_freq_x", minval=0.0),
    FloatOption("input_shaper", "shaper_freq_y", "shaper_freq_y", minval=0.0),
    FloatOption("input_shaper", "shaper_freq_z", "shaper_freq_z", minval=0.0),
    FloatOption("input_shaper", "damping_ratio_x", "damping_ratio_x", minval=0.0),
    FloatOption("input_shaper", "damping_ratio_y", "damping_ratio_y", minval=0.0),
    FloatOption("input_shaper", "damping_ratio_z", "damping_ratio_z", minval=0.0),
    FloatOption("gcode_arcs", "resolution", "arc_resolution", above=0.0),
    FloatOption("firmware_retraction", "retract_length", "retract_length", minval=0.0),
    FloatOption("firmware_retraction", "retract_speed", "retract_speed", minval=1.0),
    FloatOption("firmware_retraction", "unretract_extra_length", "unretract_extra_length",
                 minval=0.0),
    FloatOption("firmware_retraction", "unretract_speed", "unretract_speed", minval=1.0),
)


# An [extruder_stepper]'s options that change time, with Klipper's bounds.
EXTRUDER_STEPPER_OPTIONS = {
    "pressure_advance": FloatOption("extruder_stepper", "pressure_advance",
                                    "pressure_advance", minval=0.0),
    "pressure_advance_smooth_time": FloatOption(
        "extruder_stepper", "pressure_advance_smooth_time", "pressure_advance_smooth_time",
        above=0.0, maxval=MAX_SMOOTH_TIME_T),
}


# Bounds Klipper sets from another option: (field, other field, test, wording).
RELATIVE_BOUNDS = (
    ("max_z_velocity", "max_velocity", operator.le, "at most"),
    ("max_z_accel", "max_accel", operator.le, "at most"),
    ("filament_diameter", "nozzle_diameter", operator.ge, "at least"),
)

# Where an absent field's value comes from, when it is not simply Klipper's default.
ABSENT_PROVENANCE = {
    "kinematics": REQUIRED_FALLBACK,
    "max_velocity": REQUIRED_FALLBACK,
    "max_accel": REQUIRED_FALLBACK,
    "nozzle_diameter": REQUIRED_FALLBACK,
    "filament_diameter": REQUIRED_FALLBACK,
    "max_z_velocity": "derived from max_velocity",
    "max_z_accel": "derived from max_accel",
    "max_extrude_cross_section": "derived from nozzle_diameter",
    "max_extrude_only_velocity": "derived from max_velocity",
    "max_extrude_only_accel": "derived from max_accel",
    "klipper_generation": KESTIMATOR_DEFAULT,
    "klipper_version": "kestimator default: not known (no klipper_version set): "
                       "klipper_generation decides",
}


def _read_config(path: str, config: _Config) -> None:
    """The whole configuration into `config`: the main file, its includes, then its
    SAVE_CONFIG block."""
    regular, autosave = _split_autosave(_read_lines(path, None, config))
    _parse_file(path, regular, config, [])
    saved = _Config()
    _parse_chunk([(number, _strip_hash(text)) for number, text in autosave], path, saved)
    # Klipper drops SAVE_CONFIG options the regular config already sets.
    for name, options in saved.sections.items():
        if name not in config.sections:
            config.sections[name] = {}
            config.headers[name] = saved.headers[name]
        for option, value in options.items():
            config.sections[name].setdefault(option, value)


_CANNOT_READ = "cannot read file: "
MAX_INCLUDE_DEPTH = 100
"""How deep [include]s may nest (a chain, not a count: any number may sit side by side)."""
MAX_INCLUDED_FILES = 1000
"""How many files [include]s may read in all, each inclusion counted: files that each include
the next one twice (a diamond) would otherwise read 2^depth files."""
MAX_INCLUDED_CHARS = 16 * 1024 * 1024
"""How much text [include]s may read in all: as much as one config file may hold."""


def _read_lines(path: str, included_from: tuple[str, int] | None,
               config: _Config) -> list[str]:
    """The file's lines (universal newlines), its bytes noted in `config.reads`; errors
    name the include line if any."""
    try:
        # Bounded, and refusing devices and FIFOs: /dev/zero as an [include] must not
        # read forever or block.
        data = read_config_bytes(path, "config")
    except KestimatorError as exc:
        reason = exc.message
        if reason.startswith(_CANNOT_READ):
            reason = reason[len(_CANNOT_READ):]
        if included_from is not None:
            raise KestimatorError(f"cannot read included file {path}: {reason}",
                                  *included_from) from None
        if exc.message.startswith(_CANNOT_READ):
            raise KestimatorError(f"cannot read config file: {reason}", path) from None
        raise
    config.reads.append(("file", path, data))
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise KestimatorError(f"not UTF-8 text ({exc.reason})", path, line) from None
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def _split_autosave(lines: list[str]) -> tuple[list[str], _NumberedLines]:
    """(regular lines, SAVE_CONFIG lines without their '#*# ' and with line numbers).

    As Klipper, a block with anything after the header but '#*#' lines, or a '#*# ' line
    above it, is ignored: its lines are then plain comments.
    """
    size = len(_AUTOSAVE_HEADER)
    start = _find_header(lines)
    if start is None or any(line.startswith(_AUTOSAVE_PREFIX) for line in lines[1:start]):
        return lines, []
    block = list(enumerate(lines[start + size:], start=start + size + 1))
    # Klipper strip()s the block as a whole.
    while block and not block[0][1].strip():
        block.pop(0)
    while block and not block[-1][1].strip():
        block.pop()
    if block:
        block[0] = (block[0][0], block[0][1].lstrip())
        block[-1] = (block[-1][0], block[-1][1].rstrip())
    found_again = _find_header([text for _, text in block])
    if found_again is not None or not all(
            text.startswith(_AUTOSAVE_PREFIX) or text == "#*#" for _, text in block):
        return lines, []
    return lines[:start], [(number, text[len(_AUTOSAVE_PREFIX):]) for number, text in block]


def _find_header(lines: list[str]) -> int | None:
    """Index of the SAVE_CONFIG header's first line, where Klipper would find it."""
    size = len(_AUTOSAVE_HEADER)
    for index in range(1, len(lines) - size):
        if tuple(lines[index:index + size]) == _AUTOSAVE_HEADER:
            return index
    return None


def _strip_hash(text: str) -> str:
    """The line without its `#` comment: Klipper cuts every line at its first `#`."""
    return text.split("#", 1)[0]


def _section_header(text: str) -> str | None:
    """The name in a `[name]` line (to its last `]`, as configparser), else None."""
    end = text.rfind("]")
    if text.startswith("[") and end > 1:
        return text[1:end]
    return None


def _parse_file(path: str, lines: list[str], config: _Config,
                stack: list[tuple[str, str]]) -> None:
    """Parse one file's lines, splicing its `[include]`s in where they stand.

    `stack` holds (real path, path as named) of the files being parsed, outermost first.
    """
    if len(stack) >= MAX_INCLUDE_DEPTH:
        raise KestimatorError(f"[include]s nested more than {MAX_INCLUDE_DEPTH} deep "
                              "(an include chain this long is a mistake)",
                              stack[-1][1])
    stack.append((os.path.realpath(path), path))
    # As Klipper, the text between two includes is parsed on its own: after an include
    # an option needs a new [section] header.
    chunk: _NumberedLines = []
    for number, text in enumerate(lines, start=1):
        text = _strip_hash(text)
        header = _section_header(text)
        if header is not None and header.startswith(_INCLUDE_PREFIX):
            _parse_chunk(chunk, path, config)
            chunk = []
            _include(path, number, header[len(_INCLUDE_PREFIX):].strip(), config, stack)
        else:
            chunk.append((number, text))
    _parse_chunk(chunk, path, config)
    stack.pop()


def _include(path: str, line: int, spec: str, config: _Config,
             stack: list[tuple[str, str]]) -> None:
    """Parse the files `[include spec]` on path:line names, in sorted order."""
    pattern = os.path.join(os.path.dirname(path), spec)
    names = sorted(glob.glob(pattern))
    config.reads.append(("glob", pattern, names))
    if not names and not any(c in pattern for c in "*?["):
        raise KestimatorError(f"include file {pattern} does not exist: copy the whole config "
                              "folder (printer.cfg and the files it includes, e.g. "
                              "mainsail.cfg), or read the live settings with --moonraker URL",
                              path, line)
    for name in names:
        if any(os.path.realpath(name) == real for real, _ in stack):
            chain = " -> ".join([shown for _, shown in stack] + [name])
            raise KestimatorError("include cycle: " + chain, path, line)
        config.files_included += 1
        if config.files_included > MAX_INCLUDED_FILES:
            raise KestimatorError(
                f"this [include] passes {MAX_INCLUDED_FILES} files read in all: a file "
                "included more than once is read each time, so files that each include the "
                "next one twice read 2^depth files", path, line)
        lines = _read_lines(name, (path, line), config)
        # The text's length: its lines and the line breaks between them.
        config.chars_included += sum(len(text) for text in lines) + len(lines) - 1
        if config.chars_included > MAX_INCLUDED_CHARS:
            raise KestimatorError(
                f"this [include] passes {MAX_INCLUDED_CHARS >> 20} MiB of config text read in "
                "all (a file included more than once is read each time)", path, line)
        _parse_file(name, lines, config, stack)


def _parse_chunk(lines: _NumberedLines, path: str, config: _Config) -> None:
    """Parse `#`-free lines as one configparser read (strict=False, `;` inline comments)."""
    section: dict[str, ConfigValue] | None = None
    option: _Option | None = None
    indent_level = 0
    for number, text in lines:
        if not text.strip():
            # A blank line belongs to the value being read (trailing ones are dropped).
            if option is not None:
                option.parts.append("")
            continue
        value = _strip_semicolon(text).strip()
        if not value:
            continue
        indent = len(text) - len(text.lstrip())
        if option is not None and indent > indent_level:
            option.parts.append(value)
            continue
        indent_level = indent
        if option is not None:
            option.store(path)
            option = None
        header = _section_header(value)
        if header is not None:
            section = config.section(header, path, number)
            continue
        if section is None:
            raise KestimatorError("option before any [section] header (an [include] "
                                  "line also ends the section above it)", path, number)
        cut = min((i for i in (value.find(":"), value.find("=")) if i >= 0), default=-1)
        name = value[:cut].strip()
        if cut < 0 or not name:
            raise KestimatorError(f"cannot parse {value!r}: expected 'option: value', a "
                                  "[section] header or an indented continuation line",
                                  path, number)
        option = _Option(section, name.lower(), number, [value[cut + 1:].strip()])
    if option is not None:
        option.store(path)


def _strip_semicolon(text: str) -> str:
    """The line without its `;` comment: one at the start or after whitespace."""
    start = text.find(";")
    while start > 0 and not text[start - 1].isspace():
        start = text.find(";", start + 1)
    return text if start < 0 else text[:start]
