"""Which Klipper limits the plugin uses: Cura's active machine, a printer.cfg, or Moonraker.

Owns the plugin's choice of limit source (`LimitsChoice`, kept in Cura's preferences) and
the turn of each source into a ``Limits``, with no Cura import: the Cura-facing layer reads
the setting values off the global stack into a plain dict and passes them here.

- ``machine`` (the default): the values of `MACHINE_KEYS` (global stack) and
  `EXTRUDER_KEYS` (first extruder) are handed to the core's Cura adapter, which alone knows
  what each Cura setting means in Klipper (``map_cura_settings``), together with what the
  G-code itself says (its ``;FLAVOR:`` header). They are the slicer's guesses about the
  printer, and the source says so.
- ``printer_cfg`` / ``moonraker``: the core's resolver decides every value from the real
  machine, exactly as ``kestimator estimate --no-profile --printer-cfg/--moonraker`` does
  (``kestimator.api.resolve_machine_limits``; the Moonraker API key comes from
  ``MOONRAKER_API_KEY`` in ``environ``: the Cura-facing layer puts the key from the plugin's
  preferences there when one is set). Should the resolver not import in some Cura's Python
  (it once needed ``tomli`` on Python 3.10, which Cura 5.0 to 5.6 bundle without it), the
  printer.cfg or Moonraker values are read directly, which under these options gives the
  same limits.

Like every module of the plugin, this one imports the core only through ``kestimator.api``.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping

from kestimator.api import (
    FileEnds,
    KestimatorError,
    Limits,
    MacroTimes,
    SlicerConfig,
    SlicerValue,
    adapter_for,
    learned_macro_times,
    limits_from_printer_cfg,
    moonraker_values,
    resolve_machine_limits,
)

SOURCE_MACHINE = "machine"
SOURCE_PRINTER_CFG = "printer_cfg"
SOURCE_MOONRAKER = "moonraker"
SOURCES = (SOURCE_MACHINE, SOURCE_PRINTER_CFG, SOURCE_MOONRAKER)
CURA_FAMILY = "cura"
API_KEY_ENVIRONMENT = "MOONRAKER_API_KEY"
MACHINE_SOURCE_TEXT = "Cura machine settings (guesses) + defaults"
MACHINE_MARKER_SOURCE = "guessed:cura_machine_settings+defaults"

MACHINE_KEYS = (
    "machine_max_feedrate_x", "machine_max_feedrate_y", "machine_max_feedrate_z",
    "machine_max_feedrate_e",
    "machine_max_acceleration_x", "machine_max_acceleration_y", "machine_max_acceleration_z",
    "machine_max_acceleration_e", "machine_acceleration",
    "machine_max_jerk_xy", "machine_max_jerk_z", "machine_max_jerk_e",
    "acceleration_enabled", "acceleration_print", "acceleration_travel",
    "jerk_enabled", "jerk_print", "jerk_travel",
    "machine_gcode_flavor", "relative_extrusion", "machine_firmware_retract",
)
"""Machine-wide settings read from Cura's global stack."""
EXTRUDER_KEYS = (
    "machine_nozzle_size", "material_diameter", "retraction_amount",
    "retraction_retract_speed", "retraction_prime_speed", "retraction_speed",
)
"""Per-extruder settings, read from the first extruder's stack (the global stack holds
only a default for them)."""


@dataclasses.dataclass(frozen=True)
class LimitsChoice:
    """Where the user wants the limits from (the plugin's preferences)."""

    source: str = SOURCE_MACHINE
    printer_cfg: str = ""
    moonraker_url: str = ""

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError("source must be one of " + ", ".join(SOURCES))

    @property
    def description(self) -> str:
        """For people: which source is in use."""
        if self.source == SOURCE_PRINTER_CFG:
            return "printer.cfg " + self.printer_cfg
        if self.source == SOURCE_MOONRAKER:
            return "Moonraker " + self.moonraker_url
        return "Cura's machine settings"


@dataclasses.dataclass(frozen=True)
class ChosenLimits:
    """The limits to time with, where they came from, and what is worth telling the user."""

    limits: Limits
    source: str
    notes: tuple[str, ...] = ()
    macros: MacroTimes | None = None
    """Times learned from the printer's job history (``kestimator learn``), if any."""
    marker_source: str = MACHINE_MARKER_SOURCE
    """What the file's marker line records: the kind of source and a file or host name,
    never a directory (the core's ``ResolvedLimits.marker_source``)."""


def _setting_text(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def cura_config(settings: Mapping[str, object]) -> SlicerConfig:
    """Cura setting values (as ``getProperty(key, "value")`` returns them) as the core's
    slicer config; unset (None) values are left out."""
    return {key: SlicerValue(key, _setting_text(value))
            for key, value in settings.items() if value is not None}


def limits_from_machine(settings: Mapping[str, object], head: bytes,
                        tail: bytes) -> ChosenLimits:
    """Limits from Cura's machine settings plus what the G-code's own header says."""
    adapter = adapter_for(CURA_FAMILY)
    config = adapter.read_settings(FileEnds.from_bytes(head, tail))
    config.update(cura_config(settings))
    mapped = adapter.map_settings(config)
    try:
        limits = Limits.from_values({limit.field: limit.value for limit in mapped.limits})
    except (KeyError, TypeError, ValueError) as exc:
        raise KestimatorError("Cura's machine settings give no usable limits: %s"
                              % exc) from None
    return ChosenLimits(limits, MACHINE_SOURCE_TEXT, mapped.notes)


def limits_from_klipper(choice: LimitsChoice,
                        environ: Mapping[str, str] | None = None) -> ChosenLimits:
    """Limits from the printer.cfg or Moonraker the choice names (may use the network)."""
    if choice.source == SOURCE_PRINTER_CFG and not choice.printer_cfg:
        raise KestimatorError("no printer.cfg chosen in the plugin's settings")
    if choice.source == SOURCE_MOONRAKER and not choice.moonraker_url:
        raise KestimatorError("no Moonraker URL set in the plugin's settings")
    try:
        resolved = resolve_machine_limits(
            printer_cfg=choice.printer_cfg if choice.source == SOURCE_PRINTER_CFG else None,
            moonraker_url=choice.moonraker_url if choice.source == SOURCE_MOONRAKER else None,
            environ=environ)
    except ImportError:
        return limits_from_klipper_directly(choice, environ)
    macros = learned_macro_times(resolved) if choice.source == SOURCE_MOONRAKER else None
    return ChosenLimits(resolved.limits, resolved.summary, tuple(resolved.warnings), macros,
                        resolved.marker_source)


def limits_from_klipper_directly(choice: LimitsChoice,
                                 environ: Mapping[str, str] | None = None) -> ChosenLimits:
    """`limits_from_klipper` without the core's resolver (see the module docstring)."""
    if choice.source == SOURCE_PRINTER_CFG:
        limits, _ = limits_from_printer_cfg(choice.printer_cfg)
        return ChosenLimits(limits, os.fspath(choice.printer_cfg),
                            marker_source="printer_cfg:" + os.path.basename(
                                os.fspath(choice.printer_cfg)).replace(" ", "_"))
    environ = environ if environ is not None else os.environ
    found = moonraker_values(choice.moonraker_url,
                             environ.get(API_KEY_ENVIRONMENT) or None)
    try:
        limits = Limits.from_values(dict(found.values))
    except (KeyError, TypeError, ValueError) as exc:
        raise KestimatorError("%s gives no usable limits: %s" % (found.description, exc)) from None
    return ChosenLimits(limits, found.description, tuple(found.warnings),
                        marker_source="moonraker")


def choose_limits(choice: LimitsChoice, settings: Mapping[str, object], head: bytes,
                  tail: bytes, environ: Mapping[str, str] | None = None) -> ChosenLimits:
    """The limits the user chose; raises KestimatorError when that source fails."""
    if choice.source == SOURCE_MACHINE:
        return limits_from_machine(settings, head, tail)
    return limits_from_klipper(choice, environ)
