"""Reading a printer's config sections as Klipper's configfile does: typed options with
Klipper's checks, and the rails (steppers) built from them.

Re-implemented from mainline Klipper at commit 84104bbbd (GNU GPLv3): `klippy/configfile.py`
(getfloat/getint/getboolean bounds) and `klippy/stepper.py` (`GenericPrinterRail`'s
position_endstop / position_min / position_max / homing_positive_dir, `parse_step_distance`).

A `MachineConfig` is the part of the printer's configuration a kinematics reads: [printer],
the [stepper_*] sections, [dual_carriage] and the probe sections a Z endstop may be (and the
[safe_z_home] / [homing_override] that decide where G28 leaves the head), as raw
option text (from a printer.cfg) or as Klipper's own settings (from Moonraker, turned to
text the same way), each option with where it came from. It is frozen and travels inside
`Limits.machine`; sources without steppers (profile, slicer settings, --set) leave it None.
`Section` reads one section with Klipper's getters; `lookup_rail` / `rail_from_section` turn a
[stepper_*] (or carriage) section into a `Rail`.

A ground-floor module: it imports only the standard library and `kestimator.errors`, so the
config readers (`config.printer_cfg`, `config.moonraker`, `config.fields`), `limits` and the
kinematics above them can all use it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

from kestimator.errors import KestimatorError

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

# Sections (lower-case) a kinematics may read, besides [printer] and every [stepper_*].
# [safe_z_home] and [homing_override] decide where G28 leaves the head, [force_move] whether
# SET_KINEMATIC_POSITION exists (kestimator.force_move).
EXTRA_SECTIONS = ("dual_carriage", "probe", "bltouch", "smart_effector",
                  "load_cell_probe", "safe_z_home", "homing_override", "force_move")
# The same, named ("probe_eddy_current my_eddy": Klipper loads it by prefix only).
NAMED_EXTRA_SECTIONS = ("probe_eddy_current",)
_TRUE = frozenset(("1", "yes", "true", "on"))
_FALSE = frozenset(("0", "no", "false", "off"))


# Prefixes of the sections generic_cartesian reads ([carriage x], [stepper a], ...).
MACHINE_SECTION_PREFIXES = ("stepper_", "stepper ", "carriage ", "dual_carriage ",
                            "extra_carriage ")
# Move transforms that change where the toolhead goes (kestimator.bed_mesh,
# kestimator.skew_correction): the section and its saved profiles ("bed_mesh default").
TRANSFORM_SECTIONS = ("bed_mesh", "skew_correction")


def is_machine_section(name: str) -> bool:
    """Whether a kinematics reads the section called ``name`` (lower-case)."""
    return (name == "printer" or name.startswith(MACHINE_SECTION_PREFIXES)
            or name in EXTRA_SECTIONS or name.split(" ", 1)[0] in TRANSFORM_SECTIONS
            or (" " in name and name.split(" ", 1)[0] in NAMED_EXTRA_SECTIONS))


# Beyond getfloat()'s bounds, Klipper cannot start with a number its arithmetic breaks on:
# ToolHead squares square_corner_velocity (OverflowError above ~1.3e154, toolhead.py at
# 84104bbbd), the planner squares speeds and multiplies accelerations by distances, and the
# extruder divides by the filament's area (0 for 1e-200). Every settings source (and every
# option a kinematics reads, `Section.getfloat`) refuses a magnitude outside
# [ARITHMETIC_MIN, ARITHMETIC_MAX] (0 itself stays allowed): squares and products of two
# such values stay finite and non-zero (docs/CLI.md, "Values no print can have").
ARITHMETIC_MAX = 1e100
ARITHMETIC_MIN = 1e-100


def arithmetic_violation(value: float) -> str | None:
    """A text if ``value`` is one Klipper's arithmetic cannot run with, else None."""
    if not math.isfinite(value):
        return "must be a finite number"
    if abs(value) > ARITHMETIC_MAX:
        return f"must be at most {ARITHMETIC_MAX:g} (Klipper's arithmetic overflows beyond)"
    if value and abs(value) < ARITHMETIC_MIN:
        return (f"must be 0 or at least {ARITHMETIC_MIN:g} (Klipper's arithmetic "
                "underflows below)")
    return None


class MissingSectionError(KestimatorError):
    """The printer's config lacks a section the kinematics reads."""


@dataclasses.dataclass(frozen=True)
class MachineConfig:
    """The configuration sections a kinematics reads, with where each option came from."""

    def __reduce__(self) -> tuple[type[MachineConfig], tuple[object, ...]]:
        # A frozen dataclass pickles by its fields (the worker pickles the planner,
        # kestimator.resume; the compiled class cannot take its state afterwards).
        return type(self), tuple(getattr(self, f.name) for f in dataclasses.fields(self))

    description: str
    """The printer.cfg path or "moonraker <url>"."""
    sections: tuple[tuple[str, tuple[tuple[str, str, str], ...]], ...]
    """(section, ((option, value text, source), ...)) for every section kept."""

    @classmethod
    def build(cls, description: str,
              sections: Mapping[str, Mapping[str, tuple[str, str]]]) -> "MachineConfig":
        """From section -> option -> (value text, source), keeping the machine sections."""
        kept = tuple(
            (name, tuple((option, value, source)
                         for option, (value, source) in sorted(options.items())))
            for name, options in sorted(sections.items()) if is_machine_section(name))
        return cls(description, kept)

    def section(self, name: str) -> Section | None:
        """The section called ``name``, or None when the config lacks it."""
        for section_name, options in self.sections:
            if section_name == name:
                return Section(self, name, {o: (v, s) for o, v, s in options})
        return None

    def get_prefix_sections(self, prefix: str) -> list[Section]:
        """Every section whose name starts with ``prefix``, in the config's order."""
        found = []
        for section_name, _ in self.sections:
            if section_name.startswith(prefix):
                section = self.section(section_name)
                if section is not None:
                    found.append(section)
        return found

    def has_section(self, name: str) -> bool:
        """Whether the config declares ``[name]``."""
        return any(section_name == name for section_name, _ in self.sections)

    def getsection(self, name: str) -> Section:
        """The section, or a KestimatorError as Klipper refuses to start without it."""
        found = self.section(name)
        if found is None:
            raise MissingSectionError("no [%s] section, which [printer] kinematics needs" % name)
        return found


_NO_DEFAULT = object()


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Section:
    """One section, read with Klipper's getters (the same bounds, the same defaults)."""

    def __init__(self, config: MachineConfig, name: str,
                 options: dict[str, tuple[str, str]]) -> None:
        self.config = config
        self.name = name
        self.options = options

    def get_name(self) -> str:
        """The section's name."""
        return self.name

    def _error(self, option: str, message: str) -> KestimatorError:
        source = self.options.get(option, ("", self.config.description))[1]
        path, _, line = source.rpartition(":")
        if path and line.isdigit():
            return KestimatorError("[%s] %s" % (self.name, message), path, int(line))
        return KestimatorError("%s: [%s] %s" % (source, self.name, message))

    def source(self, option: str) -> str | None:
        """Where ``option`` was set, or None when it was not."""
        found = self.options.get(option)
        return None if found is None else found[1]

    def get(self, option: str, default: object = _NO_DEFAULT) -> str | None:
        """The option's text; its default (a str or None; an error without one) when absent."""
        value = self._lookup(option, default)
        if value is not None and not isinstance(value, str):
            raise TypeError("the default of get(%r) must be a str or None" % option)
        return value

    def _lookup(self, option: str, default: object) -> object:
        """The option's text, or `default` (any value) when absent; an error without one."""
        found = self.options.get(option)
        if found is None:
            if default is _NO_DEFAULT:
                raise self._error(option, "needs option '%s'" % option)
            return default
        return found[0]

    def getfloat(self, option: str, default: object = _NO_DEFAULT, *,
                 minval: float | None = None, maxval: float | None = None,
                 above: float | None = None, below: float | None = None) -> float:
        """configfile's getfloat with its bounds."""
        text = self._lookup(option, default)
        if text is None or isinstance(text, float):
            if text is None:
                raise self._error(option, "needs option '%s'" % option)
            value = text
        else:
            try:
                value = float(str(text))
            except ValueError:
                raise self._error(option, "option '%s': %r is not a number"
                                  % (option, text)) from None
            if not math.isfinite(value):
                raise self._error(option, "option '%s' must be a finite number" % option)
            problem = arithmetic_violation(value)
            if problem is not None:
                raise self._error(option, "option '%s' %s" % (option, problem))
        for bound, bad, words in ((minval, lambda v, b: v < b, "have minimum of"),
                                  (maxval, lambda v, b: v > b, "have maximum of"),
                                  (above, lambda v, b: v <= b, "be above"),
                                  (below, lambda v, b: v >= b, "be below")):
            if bound is not None and bad(value, bound):
                raise self._error(option, "option '%s' must %s %s" % (option, words, bound))
        return value

    def getfloatlist(self, option: str, default: object = _NO_DEFAULT, *,
                     count: int | None = None) -> tuple[float, ...]:
        """configfile's getfloatlist: comma-separated numbers (exactly ``count`` of them)."""
        text = self._lookup(option, default)
        if isinstance(text, tuple):
            return text
        parts = [p.strip() for p in str(text).split(",")] if str(text).strip() else []
        values = []
        for part in parts:
            try:
                value = float(part)
            except ValueError:
                raise self._error(option, "option '%s': %r is not a list of numbers"
                                  % (option, text)) from None
            problem = arithmetic_violation(value)
            if problem is not None:
                raise self._error(option, "option '%s' %s" % (option, problem))
            values.append(value)
        if count is not None and len(values) != count:
            raise self._error(option, "option '%s' must have %d elements" % (option, count))
        return tuple(values)

    def getint(self, option: str, default: object = _NO_DEFAULT, *,
               minval: int | None = None) -> int:
        """configfile's getint."""
        text = self._lookup(option, default)
        if isinstance(text, int):
            value = text
        else:
            try:
                value = int(str(text))
            except ValueError:
                raise self._error(option, "option '%s': %r is not an integer"
                                  % (option, text)) from None
        if minval is not None and value < minval:
            raise self._error(option, "option '%s' must have minimum of %s" % (option, minval))
        return value

    def getboolean(self, option: str, default: object = _NO_DEFAULT) -> bool | None:
        """configfile's getboolean (None when absent and the default is None)."""
        text = self._lookup(option, default)
        if text is None or isinstance(text, bool):
            return text
        word = str(text).strip().lower()
        if word in _TRUE:
            return True
        if word in _FALSE:
            return False
        raise self._error(option, "option '%s': %r is not a boolean" % (option, text))


@dataclasses.dataclass(frozen=True)
class Rail:
    """A [stepper_*] rail as `stepper.GenericPrinterRail` reads it (what homing and range
    checks need)."""

    def __reduce__(self) -> tuple[type[Rail], tuple[object, ...]]:
        # A frozen dataclass pickles by its fields (the worker pickles the planner,
        # kestimator.resume; the compiled class cannot take its state afterwards).
        return type(self), tuple(getattr(self, f.name) for f in dataclasses.fields(self))

    name: str
    position_endstop: float
    position_min: float
    position_max: float
    homing_positive_dir: bool
    step_dist: float
    """mm (or radians) per microstep; 0 for a generic_cartesian carriage (no stepper)."""

    def get_range(self) -> tuple[float, float]:
        """(position_min, position_max)."""
        return self.position_min, self.position_max


def _probe_z_offset(config: MachineConfig, section: Section) -> float | None:
    """position_endstop of a rail whose endstop is a probe's virtual endstop (the
    `HomingViaProbeHelper` the probe registers as chip 'probe'): a probe's z_offset
    (`ProbeOffsetsHelper`); for `[probe_eddy_current NAME]` its descend_z, or the deprecated
    z_offset when descend_z is not given (probe_eddy_current.py `EddyDescend`)."""
    pin = (section.get("endstop_pin", None) or "").strip().lstrip("^~!").strip()
    if not pin.startswith("probe:"):
        return None
    for name in ("probe", "bltouch", "smart_effector", "load_cell_probe"):
        probe = config.section(name)
        if probe is not None:
            return probe.getfloat("z_offset")
    for eddy in config.get_prefix_sections("probe_eddy_current "):
        if eddy.get("z_offset", None) is not None and eddy.get("descend_z", None) is None:
            return eddy.getfloat("z_offset")
        return eddy.getfloat("descend_z")
    raise section._error("endstop_pin", "endstop_pin %s needs a [probe] section" % pin)


def step_distance(section: Section, units_in_radians: bool | None = None) -> float:
    """`stepper.parse_step_distance`: mm (or radians) per full microstep."""
    if units_in_radians is None:
        units_in_radians = (section.get("rotation_distance", None) is None
                            and section.get("gear_ratio", None) is not None)
    if units_in_radians:
        rotation_dist = 2.0 * math.pi
    else:
        rotation_dist = section.getfloat("rotation_distance", above=0.0)
    microsteps = section.getint("microsteps", minval=1)
    full_steps = section.getint("full_steps_per_rotation", 200, minval=1)
    if full_steps % 4:
        raise section._error("full_steps_per_rotation",
                             "full_steps_per_rotation invalid in section '%s'" % section.name)
    gearing = 1.0
    ratio_text = section.get("gear_ratio", None)
    if ratio_text:
        for pair in str(ratio_text).split(","):
            parts = [p.strip() for p in pair.split(":")]
            try:
                g1, g2 = float(parts[0]), float(parts[1])
            except (ValueError, IndexError):
                raise section._error("gear_ratio", "Invalid gear_ratio '%s'"
                                     % ratio_text) from None
            gearing *= g1 / g2
    return rotation_dist / (full_steps * microsteps * gearing)


def lookup_rail(config: MachineConfig, name: str, need_position_minmax: bool = True,
                default_position_endstop: float | None = None,
                units_in_radians: bool = False, has_stepper: bool = True) -> Rail:
    """`stepper.LookupMultiRail` / `GenericPrinterRail` for ``[name]``: positions, range and
    homing direction, with Klipper's defaults and the checks that stop Klipper starting."""
    return rail_from_section(config, config.getsection(name), need_position_minmax,
                             default_position_endstop, units_in_radians, has_stepper)


def rail_from_section(config: MachineConfig, section: Section,
                      need_position_minmax: bool = True,
                      default_position_endstop: float | None = None,
                      units_in_radians: bool = False, has_stepper: bool = True) -> Rail:
    """`lookup_rail` for a section already looked up."""
    name = section.name
    position_endstop = _probe_z_offset(config, section)
    if position_endstop is None:
        if default_position_endstop is None:
            position_endstop = section.getfloat("position_endstop")
        else:
            position_endstop = section.getfloat("position_endstop", default_position_endstop)
    if need_position_minmax:
        position_min = section.getfloat("position_min", 0.0)
        position_max = section.getfloat("position_max", above=position_min)
    else:
        position_min = 0.0
        position_max = position_endstop
    if position_endstop < position_min or position_endstop > position_max:
        raise section._error("position_endstop",
                             "position_endstop in section '%s' must be between position_min "
                             "and position_max" % name)
    positive_dir = section.getboolean("homing_positive_dir", None)
    if positive_dir is None:
        axis_len = position_max - position_min
        if position_endstop <= position_min + axis_len / 4.0:
            positive_dir = False
        elif position_endstop >= position_max - axis_len / 4.0:
            positive_dir = True
        else:
            raise section._error("position_endstop",
                                 "Unable to infer homing_positive_dir in section '%s'" % name)
    elif ((positive_dir and position_endstop == position_min)
          or (not positive_dir and position_endstop == position_max)):
        raise section._error("homing_positive_dir",
                             "Invalid homing_positive_dir / position_endstop in '%s'" % name)
    return Rail(name, position_endstop, position_min, position_max, positive_dir,
                step_distance(section, units_in_radians) if has_stepper else 0.0)
