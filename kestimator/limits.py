"""The one value that describes what a Klipper printer allows: `Limits`.

This module owns Klipper's own defaults for every motion setting we model and the values
derived from them (junction deviation, the minimum_cruise_ratio pseudo-acceleration), the
``kestimator: klipper_generation = <name>`` directive by which a file may name the Klipper
generation, and what a Klipper version means (``klipper_release``: the releases known, the
generation each has, the ``kestimator: klipper_version = <version>`` directive).

Sources of limits (printer.cfg, slicer settings, the command line) build a `Limits` through
`Limits.from_values`, so a default lives in exactly one place: here.

Defaults follow mainline Klipper at commit 84104bbbd: klippy/toolhead.py ([printer]),
klippy/kinematics/extruder.py ([extruder]), klippy/extras/gcode_arcs.py and
klippy/extras/firmware_retraction.py.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from typing import Any

from kestimator.config.machine import MachineConfig
from kestimator.stepgen import DEFAULT_DAMPING_RATIO

# What `SET_VELOCITY_LIMIT ACCEL_TO_DECEL` (and [printer] max_accel_to_decel) means depends
# on the Klipper generation the printer runs.
KLIPPER_GENERATIONS = ("mainline", "mcr", "absolute")

# No Klipper setting says which generation a printer runs, so a printer.cfg comment or a
# slicer's printer notes may: "kestimator: klipper_generation = mcr".
GENERATION_DIRECTIVE_RE = re.compile(
    r"\bkestimator\s*:\s*klipper_generation\s*[=:]\s*([^\s,;\"']+)")


def find_generation_directive(text: str) -> str | None:
    """The generation a ``kestimator: klipper_generation = <name>`` directive in ``text``
    names (not checked against ``KLIPPER_GENERATIONS``), or None."""
    match = GENERATION_DIRECTIVE_RE.search(text)
    return None if match is None else match.group(1)


# "kestimator: klipper_version = v0.12.0-455-g5f2d7bc8" (or "= Kalico v2026.07.00-0-g30c65e09").
VERSION_DIRECTIVE_RE = re.compile(
    r"\bkestimator\s*:\s*klipper_version\s*[=:]\s*((?:[A-Za-z][\w-]*[ \t]+)?[^\s,;\"']+)")


def find_version_directive(text: str) -> str | None:
    """The version a ``kestimator: klipper_version = <version>`` directive in ``text`` names
    (not checked), or None."""
    match = VERSION_DIRECTIVE_RE.search(text)
    return None if match is None else match.group(1)


# A version as Moonraker's printer.info reports it (`software_version`, what `git describe`
# said when klippy started), the app's name first where it is not Klipper:
# "v0.12.0-455-g5f2d7bc8", "v0.13.0-730-g84104bbbd-dirty", "Kalico v2026.07.00-0-g30c65e09".
_VERSION_RE = re.compile(r"(?:(?P<app>[A-Za-z][\w-]*)\s+)?v?(?P<release>\d+(?:\.\d+)+)"
                         r"(?:-(?P<commits>\d+))?(?:-g[0-9a-fA-F]+)?(?:-dirty)?")

# Each app's releases, oldest first, as (git describe position, the generation from there
# on, what that position is). Klipper's history is linear, so "v0.12.0-119" means every
# commit up to Klipper's 119th after v0.12.0. The last row of an app is the newest its
# semantics are known for; a version past it is taken as that one.
KLIPPER_RELEASE_RULES: dict[str, tuple[tuple[tuple[int, ...], int, str, str], ...]] = {
    "klipper": (
        ((0,), 0, "absolute", "Klipper before 0105aa330 (v0.12.0-119, 2024-03): "
                              "max_accel_to_decel, ACCEL_TO_DECEL absolute"),
        ((0, 12, 0), 119, "mcr", "Klipper 0105aa330 (v0.12.0-119, 2024-03) to v0.13.0-191: "
                                 "minimum_cruise_ratio, max_accel_to_decel converted to it"),
        ((0, 13, 0), 192, "mainline", "Klipper 3ef760c18 (v0.13.0-192, 2025-08) on: "
                                      "minimum_cruise_ratio only"),
        ((0, 13, 0), 730, "mainline", "Klipper 84104bbbd (v0.13.0-730, 2026-08)"),
    ),
    # Kalico keeps Klipper's 2024-03 rules (toolhead.py of v2026.07.00 reads both options).
    "kalico": (
        ((0,), 0, "mcr", "Kalico: minimum_cruise_ratio, max_accel_to_decel converted to it"),
        ((2026, 7, 0), 0, "mcr", "Kalico v2026.07.00"),
    ),
}
APP_NAMES = {"klipper": "Klipper", "kalico": "Kalico"}

# Each app's toolhead rules, oldest first, as (git describe position, the junction rule and
# the print-time rule from there on); independent of the generation. Junction rules
# (toolhead.py's Move.calc_junction): "clamped", the junction cosine clamped at -0.999999 and
# a reversal (cosine above 0.999999) starting from rest, the centripetal limit as
# .5 * move_d * tan_theta_d2 * accel (Klipper v0.12.0 and before); "clamped_delta_v2", the
# same computed as delta_v2 * quarter_tan_theta_d2 (8291788f4, v0.12.0-383); "mainline", no
# clamp (847331260, v0.12.0-384, 2024-11). Print-time rules (toolhead.py's flush of step
# generation): "force_flush", a full flush remembers how far steps were generated (at least
# print_time - kin_flush_delay, after a dwell) and motion restarts kin_flush_delay after it
# (Klipper v0.12.0 and before; G4 and M400 in the main state leave it); "min_restart", a full
# flush also takes the restart to print_time (min_restart_time: 3d3b87f97, v0.12.0-69, 2024-01,
# to v0.13.0-237); "mainline", step generation restarts after the last move's steps
# (1e7c67919, v0.13.0-238, 2025-08; v0.12.0-23 to -68 are not told apart from it). Kalico
# v2026.07.00 has the mainline junction rule and v0.13.0's min_restart_time (its
# klippy/toolhead.py is v0.13.0's with per-axis limits and RESET_VELOCITY_LIMIT added). The
# fifth column: a new pressure-advance window waits for the toolhead as well
# (SET_PRESSURE_ADVANCE's look-ahead callback after its flush, which with nothing queued is
# get_last_move_time: c84d78f3f, v0.12.0-262, 2024-07, to v0.13.0-245; 542694350 took it
# out). The sixth: every SET_PRESSURE_ADVANCE flushes step generation, whether its scan window
# changes or not (kinematics/extruder.py calls note_step_generation_scan_time unconditionally:
# Klipper before c84d78f3f, v0.12.0-262, 2024-07, and Kalico; from there only for a new
# window). The seventh, the look-ahead's plan
# (toolhead.py's LookAheadQueue.flush): "delayed", the moves that cannot accelerate wait in a
# list for the peak cruise of the move before them, which is capped by that move's
# max_cruise_v2 (Klipper before 41901ec38, v0.13.0-300, 2025-09, and Kalico v2026.07.00);
# "mainline", no cap, and such a move cruises at no more than the move before it.
KLIPPER_TOOLHEAD_RULES: dict[str, tuple[tuple[tuple[int, ...], int, str, str, bool, bool, str],
                                        ...]] = {
    "klipper": (((0,), 0, "clamped", "force_flush", False, True, "delayed"),
                ((0, 12, 0), 23, "clamped", "mainline", False, True, "delayed"),
                ((0, 12, 0), 69, "clamped", "min_restart", False, True, "delayed"),
                ((0, 12, 0), 262, "clamped", "min_restart", True, False, "delayed"),
                ((0, 12, 0), 383, "clamped_delta_v2", "min_restart", True, False, "delayed"),
                ((0, 12, 0), 384, "mainline", "min_restart", True, False, "delayed"),
                ((0, 13, 0), 238, "mainline", "mainline", True, False, "delayed"),
                ((0, 13, 0), 246, "mainline", "mainline", False, False, "delayed"),
                ((0, 13, 0), 300, "mainline", "mainline", False, False, "mainline")),
    "kalico": (((0,), 0, "mainline", "min_restart", False, True, "delayed"),),
}


@dataclasses.dataclass(frozen=True)
class KlipperRelease:
    """What a ``klipper_version`` means: the app, its release and the generation (the
    meaning of max_accel_to_decel / ACCEL_TO_DECEL) it has; ``note`` is the one line said
    when the version is newer than the newest known."""

    app: str
    release: tuple[int, ...]
    commits: int
    generation: str
    rule: str
    note: str | None = None
    # The junction, print-time, pressure-advance and look-ahead rules
    # (KLIPPER_TOOLHEAD_RULES) of this release.
    junction: str = "mainline"
    print_time: str = "mainline"
    pressure_advance_waits: bool = False
    pressure_advance_always_flushes: bool = False
    lookahead: str = "mainline"

    @property
    def is_kalico(self) -> bool:
        """Whether this is Kalico (its own commands and kinematics)."""
        return self.app == "Kalico"

    @property
    def accepts_max_accel_to_decel(self) -> bool:
        """Whether [printer] max_accel_to_decel is an option this release reads."""
        return self.generation != "mainline"

    @property
    def accepts_minimum_cruise_ratio(self) -> bool:
        """Whether [printer] minimum_cruise_ratio is an option this release reads."""
        return self.generation != "absolute"


def klipper_release(version: str) -> KlipperRelease:
    """The semantics of ``version`` (Moonraker's printer.info ``software_version``, with the
    app's name first where it is not Klipper). Raises ValueError for text that is not such a
    version, or an app kestimator does not know."""
    match = _VERSION_RE.fullmatch(version.strip())
    if match is None:
        raise ValueError(f"klipper_version {version!r} is not a version as Moonraker's "
                         "printer.info reports it (e.g. v0.12.0-455-g5f2d7bc8, or "
                         "Kalico v2026.07.00-0-g30c65e09)")
    app = (match.group("app") or "Klipper").lower()
    rules = KLIPPER_RELEASE_RULES.get(app)
    if rules is None:
        raise ValueError(f"klipper_version {version!r}: unknown app {match.group('app')!r} "
                         "(known: " + ", ".join(APP_NAMES.values()) + ")")
    release = tuple(int(part) for part in match.group("release").split("."))
    commits = int(match.group("commits") or 0)
    name = APP_NAMES[app]
    newest_release, newest_commits, generation, rule = rules[-1]
    junction, print_time, waits, always, lookahead = KLIPPER_TOOLHEAD_RULES[app][-1][2:]
    if (release, commits) > (newest_release, newest_commits):
        return KlipperRelease(name, release, commits, generation, rule,
                              f"klipper_version {version.strip()} is newer than the newest "
                              f"{name} kestimator knows: taken as {rule}", junction, print_time,
                              waits, always, lookahead)
    for start, start_commits, start_generation, start_rule in rules:
        if (release, commits) >= (start, start_commits):
            generation, rule = start_generation, start_rule
    for row in KLIPPER_TOOLHEAD_RULES[app]:
        if (release, commits) >= (row[0], row[1]):
            junction, print_time, waits, always, lookahead = row[2:]
    return KlipperRelease(name, release, commits, generation, rule, junction=junction,
                          print_time=print_time, pressure_advance_waits=waits,
                          pressure_advance_always_flushes=always, lookahead=lookahead)


# Options of an [extruderN] section that change motion time (kinematics/extruder.py).
EXTRUDER_FIELDS = ("nozzle_diameter", "filament_diameter", "max_extrude_cross_section",
                   "max_extrude_only_velocity", "max_extrude_only_accel",
                   "max_extrude_only_distance", "instantaneous_corner_velocity",
                   "pressure_advance", "pressure_advance_smooth_time")


@dataclasses.dataclass(frozen=True)
class ExtruderLimits:
    """One extruder's limits (Klipper's PrinterExtruder and its ExtruderStepper)."""

    name: str = "extruder"
    nozzle_diameter: float = 0.4
    filament_diameter: float = 1.75
    max_extrude_cross_section: float = 4.0 * 0.4**2
    max_extrude_only_velocity: float = 0.0
    max_extrude_only_accel: float = 0.0
    max_extrude_only_distance: float = 50.0
    instantaneous_corner_velocity: float = 1.0
    pressure_advance: float = 0.0
    pressure_advance_smooth_time: float = 0.040
    # False for an [extruderN] without step_pin/dir_pin/rotation_distance (a shared one).
    has_stepper: bool = True

    @property
    def filament_area(self) -> float:
        """Cross-section of the filament in mm^2."""
        return math.pi * math.pow(self.filament_diameter * 0.5, 2.0)

    @property
    def max_extrude_ratio(self) -> float:
        """Largest allowed E mm per XY mm (max_extrude_cross_section / filament area)."""
        return self.max_extrude_cross_section / self.filament_area

    @classmethod
    def from_values(cls, name: str, values: Mapping[str, Any], max_velocity: float,
                    max_accel: float) -> "ExtruderLimits":
        """An extruder from its explicit options, the rest derived as Klipper does."""
        v = {key: values[key] for key in EXTRUDER_FIELDS if key in values}
        nozzle_d = float(v.get("nozzle_diameter", cls.nozzle_diameter))
        filament_d = float(v.get("filament_diameter", cls.filament_diameter))
        def_cross_section = 4.0 * math.pow(nozzle_d, 2.0)
        def_extrude_ratio = def_cross_section / (math.pi * math.pow(filament_d * 0.5, 2.0))
        v.setdefault("max_extrude_cross_section", def_cross_section)
        if not v.get("max_extrude_only_velocity"):
            v["max_extrude_only_velocity"] = max_velocity * def_extrude_ratio
        if not v.get("max_extrude_only_accel"):
            v["max_extrude_only_accel"] = max_accel * def_extrude_ratio
        return cls(name=name, has_stepper=bool(values.get("has_stepper", True)), **v)


@dataclasses.dataclass(frozen=True)
class ExtruderStepperLimits:
    """An [extruder_stepper NAME] (kinematics/extruder.py `ExtruderStepper`, as
    extras/extruder_stepper.py sets it up): the extruder whose motion it follows from the
    start ('' for none) and its own pressure advance, which widens the step-generation scan
    window while it follows one."""

    name: str = ""
    extruder: str = ""
    pressure_advance: float = 0.0
    pressure_advance_smooth_time: float = 0.040


# Klipper's lowest temperature (klippy/extras/heaters.py KELVIN_TO_CELSIUS) and the default
# min_extrude_temp of a heater.
KELVIN_TO_CELSIUS = -273.15
DEFAULT_MIN_EXTRUDE_TEMP = 170.0


@dataclasses.dataclass(frozen=True)
class HeaterLimits:
    """One heater's temperature range (klippy/extras/heaters.py `Heater`): its config section
    ('extruder', 'extruder1', 'heater_bed', 'heater_generic chamber'), `min_temp`/`max_temp`
    (what M104/M140/SET_HEATER_TEMPERATURE accept) and `min_extrude_temp` (below it an
    extruder refuses to extrude)."""

    name: str = "extruder"
    min_temp: float = 0.0
    max_temp: float = 0.0
    min_extrude_temp: float = DEFAULT_MIN_EXTRUDE_TEMP

    @property
    def short_name(self) -> str:
        """The name SET_HEATER_TEMPERATURE HEATER= takes (the section's last word)."""
        return self.name.split()[-1]


# Klipper loads [extruder] ... [extruder98] while the sections follow on without a gap.
MAX_EXTRUDERS = 99


def heater_sections(sections: tuple[str, ...] | list[str]) -> list[str]:
    """The heaters a config with these (lower-case) sections has, in Klipper's load order:
    the extruders first (the toolhead loads them), then [heater_bed] and each
    [heater_generic NAME] in the order of the config."""
    present = set(sections)
    names = []
    if "extruder" in present:
        names.append("extruder")
        for index in range(1, MAX_EXTRUDERS):
            if "extruder%d" % index not in present:
                break
            names.append("extruder%d" % index)
    names += [s for s in sections if s == "heater_bed"
              or (s.startswith("heater_generic ") and len(s.split()) > 1)]
    return names


def heater_limits(name: str, min_temp: float, max_temp: float,
                  min_extrude_temp: float | None, given: bool = True) -> HeaterLimits | str:
    """A heater's range checked as Klipper's config reads it, or what is wrong with it
    (``min_temp`` at least -273.15, ``max_temp`` above it, ``min_extrude_temp`` within).

    Klipper does not check a default: where ``min_extrude_temp`` may be its default (not
    ``given``: Klipper's settings list defaults too), it is not checked."""
    if min_temp < KELVIN_TO_CELSIUS:
        return "min_temp must be at least %g, got %g" % (KELVIN_TO_CELSIUS, min_temp)
    if not max_temp > min_temp:
        return "max_temp must be above min_temp (%g), got %g" % (min_temp, max_temp)
    if min_extrude_temp is None:
        min_extrude_temp = DEFAULT_MIN_EXTRUDE_TEMP
    elif given and not min_temp <= min_extrude_temp <= max_temp:
        return "min_extrude_temp must be between min_temp (%g) and max_temp (%g), got %g" % (
            min_temp, max_temp, min_extrude_temp)
    return HeaterLimits(name, min_temp, max_temp, min_extrude_temp)


def json_value(value: object) -> object:
    """A Limits field's value as JSON holds it (extruders and heaters as objects, pairs as
    lists)."""
    if isinstance(value, tuple):
        return [dataclasses.asdict(item) if isinstance(
                    item, (ExtruderLimits, HeaterLimits, ExtruderStepperLimits))
                else json_value(item) for item in value]
    return value


def tuple_field_value(field: str, value: object) -> tuple[Any, ...]:
    """``extruders``, ``heaters`` or ``gcode_macros`` back from their JSON form (``json_value``).

    Raises ValueError for anything else.
    """
    if isinstance(value, tuple):
        value = json_value(value)
    if not isinstance(value, list):
        raise ValueError(f"{field} must be a list, not {value!r}")
    if field == "configured_sections":
        if not all(isinstance(x, str) for x in value):
            raise ValueError("configured_sections must be a list of section names")
        return tuple(str(x) for x in value)
    if field == "gcode_macros":
        if not all(isinstance(m, list) and len(m) == 2 and all(isinstance(x, str) for x in m)
                   for m in value):
            raise ValueError("gcode_macros must be a list of [name, template] pairs")
        return tuple((str(m[0]), str(m[1])) for m in value)
    if field in _ITEM_KINDS:
        kind: Any = _ITEM_KINDS[field]
        names = {f.name: type(f.default) for f in dataclasses.fields(kind)}
        result = []
        for item in value:
            if not isinstance(item, dict) or set(item) - set(names) or not all(
                    isinstance(v, names[k]) or (names[k] is float and isinstance(v, int)
                                                and not isinstance(v, bool))
                    for k, v in item.items()):
                what = {"extruders": "an extruder", "heaters": "a heater"}.get(
                    field, "an extruder stepper")
                raise ValueError(f"{field}: not {what}: {item!r}")
            fields: dict[str, Any] = {k: float(v) if names[k] is float else v
                                      for k, v in item.items()}
            result.append(kind(**fields))
        return tuple(result)
    raise ValueError(f"{field} is not a list setting")


# The list settings whose items are dataclasses, and their class.
_ITEM_KINDS: dict[str, Any] = {"extruders": ExtruderLimits, "heaters": HeaterLimits,
                               "extruder_steppers": ExtruderStepperLimits}


# Values [printer] requires in Klipper but that a user without a printer.cfg may not give;
# these stand in for them and are reported as guesses.
FALLBACK_MAX_VELOCITY_V = 300.0
FALLBACK_MAX_ACCEL = 3000.0


@dataclasses.dataclass(frozen=True)
class Limits:
    """Resolved motion settings, in Klipper's units (mm, mm/s, mm/s^2, s)."""

    kinematics: str = "cartesian"
    max_velocity: float = FALLBACK_MAX_VELOCITY_V
    max_accel: float = FALLBACK_MAX_ACCEL
    minimum_cruise_ratio: float = 0.5
    square_corner_velocity: float = 5.0
    max_z_velocity: float = FALLBACK_MAX_VELOCITY_V
    max_z_accel: float = FALLBACK_MAX_ACCEL
    # [extruder]
    nozzle_diameter: float = 0.4
    filament_diameter: float = 1.75
    max_extrude_cross_section: float = 4.0 * 0.4**2
    max_extrude_only_velocity: float = 0.0  # 0 means "derive as Klipper does"
    max_extrude_only_accel: float = 0.0
    max_extrude_only_distance: float = 50.0
    instantaneous_corner_velocity: float = 1.0
    pressure_advance: float = 0.0
    pressure_advance_smooth_time: float = 0.040
    # [extruder1] ... [extruderN], in order (ACTIVATE_EXTRUDER switches to them).
    extruders: tuple[ExtruderLimits, ...] = ()
    # Every heater whose min_temp and max_temp are known ([extruder]..., [heater_bed],
    # [heater_generic NAME]), in the order Klipper loads them: their temperature ranges are
    # checked (kestimator.heaters). Empty when no printer config is known.
    heaters: tuple[HeaterLimits, ...] = ()
    # Each [extruder_stepper NAME] (empty when no printer config gives their options).
    extruder_steppers: tuple[ExtruderStepperLimits, ...] = ()
    # [input_shaper] (shaper_type_<axis> defaults to shaper_type; a frequency of 0 is off)
    input_shaper_enabled: bool = False
    shaper_type_x: str = "mzv"
    shaper_freq_x: float = 0.0
    damping_ratio_x: float = DEFAULT_DAMPING_RATIO
    shaper_type_y: str = "mzv"
    shaper_freq_y: float = 0.0
    damping_ratio_y: float = DEFAULT_DAMPING_RATIO
    shaper_type_z: str = "mzv"
    shaper_freq_z: float = 0.0
    damping_ratio_z: float = DEFAULT_DAMPING_RATIO
    # Every section of the printer's config (lower-case names); empty when no printer
    # config is known. Decides which module commands Klipper knows (klipper_modules).
    configured_sections: tuple[str, ...] = ()
    # [gcode_macro NAME] sections: (NAME upper-case, its gcode template), in file order.
    gcode_macros: tuple[tuple[str, str], ...] = ()
    # [gcode_arcs]
    arcs_enabled: bool = False
    arc_resolution: float = 1.0
    # [firmware_retraction]
    firmware_retraction_enabled: bool = False
    retract_length: float = 0.0
    retract_speed: float = 20.0
    unretract_extra_length: float = 0.0
    unretract_speed: float = 10.0
    # Which meaning ACCEL_TO_DECEL has (see KLIPPER_GENERATIONS).
    klipper_generation: str = "mainline"
    # The Klipper the printer runs, as Moonraker's printer.info reports it ("" unknown): it
    # selects klipper_generation where that is not given (`klipper_release`).
    klipper_version: str = ""
    # Only read by the "absolute" and "mcr" generations; 0 means "not set".
    max_accel_to_decel: float = 0.0
    # The printer's [printer] / [stepper_*] / [dual_carriage] sections, for the kinematics
    # (kestimator.kinematics): None when the limits come from a source without steppers.
    # Not a settable limit: not among `field_names()`, and not compared (two Limits with the
    # same values are equal whether or not they know the printer's steppers).
    machine: MachineConfig | None = dataclasses.field(default=None, compare=False)
    # The stop commands the file's slicer settings and the user's profile name beyond the
    # defaults (kestimator.stops; the printer's macros that call one are added where the
    # estimate runs). Not a settable limit either: resolve_limits sets it.
    stop_commands: tuple[str, ...] = ()

    @property
    def filament_area(self) -> float:
        """Cross-section of the filament in mm^2."""
        return math.pi * math.pow(self.filament_diameter * 0.5, 2.0)

    @property
    def max_extrude_ratio(self) -> float:
        """Largest allowed E mm per XY mm (max_extrude_cross_section / filament area)."""
        return self.max_extrude_cross_section / self.filament_area

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """Every settable key, in declaration order (`machine` and `stop_commands` are not
        ones)."""
        return tuple(f.name for f in dataclasses.fields(cls)
                     if f.name not in ("machine", "stop_commands"))

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> "Limits":
        """Build Limits from explicit values, filling every absent key as Klipper does.

        Derived defaults: max_z_velocity/max_z_accel default to max_velocity/max_accel;
        max_extrude_cross_section to 4 * nozzle_diameter^2; max_extrude_only_velocity and
        max_extrude_only_accel to max_velocity/max_accel times the default extrude ratio.
        """
        unknown = set(values) - set(cls.field_names())
        if unknown:
            raise KeyError("unknown limit(s): " + ", ".join(sorted(unknown)))
        v = dict(values)
        v.setdefault("max_velocity", FALLBACK_MAX_VELOCITY_V)
        v.setdefault("max_accel", FALLBACK_MAX_ACCEL)
        v.setdefault("max_z_velocity", v["max_velocity"])
        v.setdefault("max_z_accel", v["max_accel"])
        nozzle_d = float(v.get("nozzle_diameter", cls.nozzle_diameter))
        filament_d = float(v.get("filament_diameter", cls.filament_diameter))
        def_cross_section = 4.0 * math.pow(nozzle_d, 2.0)
        def_extrude_ratio = def_cross_section / (math.pi * math.pow(filament_d * 0.5, 2.0))
        v.setdefault("max_extrude_cross_section", def_cross_section)
        if not v.get("max_extrude_only_velocity"):
            v["max_extrude_only_velocity"] = float(v["max_velocity"]) * def_extrude_ratio
        if not v.get("max_extrude_only_accel"):
            v["max_extrude_only_accel"] = float(v["max_accel"]) * def_extrude_ratio
        if v.get("klipper_generation", "mainline") not in KLIPPER_GENERATIONS:
            raise ValueError(
                "klipper_generation must be one of " + ", ".join(KLIPPER_GENERATIONS))
        if v.get("klipper_version"):
            klipper_release(str(v["klipper_version"]))
        sections = v.get("configured_sections", ())
        if not isinstance(sections, tuple) or not all(isinstance(x, str) for x in sections):
            raise ValueError("configured_sections must be a tuple of section names")
        macros = v.get("gcode_macros", ())
        if not isinstance(macros, tuple) or not all(
                isinstance(m, tuple) and len(m) == 2 for m in macros):
            raise ValueError("gcode_macros must be a tuple of (name, template) pairs")
        extruders = v.get("extruders", ())
        if not isinstance(extruders, tuple) or not all(
                isinstance(e, ExtruderLimits) for e in extruders):
            raise ValueError("extruders must be a tuple of ExtruderLimits")
        heaters = v.get("heaters", ())
        if not isinstance(heaters, tuple) or not all(
                isinstance(h, HeaterLimits) for h in heaters):
            raise ValueError("heaters must be a tuple of HeaterLimits")
        steppers = v.get("extruder_steppers", ())
        if not isinstance(steppers, tuple) or not all(
                isinstance(e, ExtruderStepperLimits) for e in steppers):
            raise ValueError("extruder_steppers must be a tuple of ExtruderStepperLimits")
        return cls(**v)

    @property
    def primary_extruder(self) -> ExtruderLimits:
        """[extruder] as an ExtruderLimits."""
        return ExtruderLimits(name="extruder", **{key: getattr(self, key)
                                                  for key in EXTRUDER_FIELDS})

    def extruder(self, name: str) -> ExtruderLimits | None:
        """The extruder section called ``name`` ('extruder', 'extruder1', ...), or None."""
        if name == "extruder":
            return self.primary_extruder
        for extruder in self.extruders:
            if extruder.name == name:
                return extruder
        return None

    def heater(self, name: str) -> HeaterLimits | None:
        """The heater of the config section ``name``, if its range is known."""
        for heater in self.heaters:
            if heater.name == name:
                return heater
        return None

    def replace(self, **changes: Any) -> "Limits":
        """A copy with some values changed (no re-derivation of defaults)."""
        return dataclasses.replace(self, **changes)
