"""Settings a slicer embedded in a file (or handed over in the environment), and the shape in
which every family reports what they stand for in Klipper.

Owns the value syntax the Slic3r lineage (PrusaSlicer, SuperSlicer, Slic3r, OrcaSlicer, Bambu
Studio) writes, in its config blocks and in the ``SLIC3R_<KEY>`` environment of a
post-processing script: ``; key = value`` lines, comma-joined per-extruder or "normal,stealth"
vectors, ``nil`` for "not set", and ``80%`` values. It also owns the one rule shape the families
share: a Klipper setting guessed from the least of some slicer limits. Which keys a family writes,
and what each one means for Klipper, stay in the family's own module; docs/LIMITS.md has the
table.

Everything a slicer says about the machine is a guess about the printer: the resolver
(``kestimator.config.resolve``) only uses it when no real printer configuration is known.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterable, Mapping

ENVIRONMENT_PREFIX = "SLIC3R_"
"""PrusaSlicer and its forks hand every config key to a post-processing script as this prefix
plus the upper-case key (``DynamicPrintConfig::setenv_`` in src/libslic3r/Config.cpp)."""
# Set by the post-processing contract itself; they are not config keys.
_ENVIRONMENT_NOT_CONFIG = frozenset(("SLIC3R_PP_HOST", "SLIC3R_PP_OUTPUT_NAME"))

NIL = "nil"
"""Written for an unset element of a nullable vector (e.g. a filament override left alone)."""

# `; key = value` as the Slic3r lineage writes its config (value may be empty).
_KEY_VALUE_RE = re.compile(r"^; ([A-Za-z_][A-Za-z0-9_]*) =(?: (.*))?$")


@dataclasses.dataclass(frozen=True)
class SlicerValue:
    """One setting as the slicer wrote it."""

    label: str
    """The key as written: ``machine_max_acceleration_x`` in a file,
    ``SLIC3R_MACHINE_MAX_ACCELERATION_X`` in the environment."""
    text: str
    """The value as written (vectors comma-joined)."""

    @property
    def source(self) -> str:
        """Provenance text: ``slicer: <key> = <value>`` (a header line as it stands)."""
        if self.label.startswith(";"):
            return f"slicer: {self.label}{self.text}"
        return f"slicer: {self.label} = {self.text}"


SlicerConfig = dict[str, SlicerValue]
"""Lower-case slicer key -> value as written."""


@dataclasses.dataclass(frozen=True)
class SlicerLimit:
    """A Klipper setting (a ``Limits`` field) and the value a slicer's settings stand for."""

    field: str
    value: float | bool | str
    source: str
    """Which slicer key(s) gave the value, as ``slicer: <key> = <value> ...``."""


@dataclasses.dataclass(frozen=True)
class SlicerSettings:
    """What a file's slicer settings say about the printer, already mapped to Klipper."""

    origin: str = ""
    """Where the settings were read: "config block", "SLIC3R_* environment", ";SETTING_3";
    empty when none were found."""
    limits: tuple[SlicerLimit, ...] = ()
    notes: tuple[str, ...] = ()
    """Facts worth reporting: values not used and why, commands Klipper will ignore."""
    accelerations: tuple[tuple[str, float], ...] = ()
    """The accelerations the slicer writes into the file itself (M204 S / SET_VELOCITY_LIMIT),
    key -> mm/s^2 with percentages resolved: not Klipper settings, the file applies them."""
    printer_preset: str | None = None
    """The slicer's printer preset name (selects a printer table in the user's profile)."""
    flavour: str | None = None
    """One line when the file was sliced for another firmware's G-code flavour (its settings
    or its commands say so), naming how to choose Klipper's in that slicer; else None."""
    stop_gcode: tuple[tuple[str, str], ...] = ()
    """The slicer's colour-change and pause G-code (kestimator.stops.SLICER_STOP_KEYS), key
    -> text as written: the commands it runs are stops."""

    def by_field(self) -> dict[str, SlicerLimit]:
        """The mapped values keyed by ``Limits`` field."""
        return {limit.field: limit for limit in self.limits}

    def extended(self, limits: Iterable[SlicerLimit] = (),
                 notes: Iterable[str] = ()) -> SlicerSettings:
        """A copy with more mapped values and notes."""
        return dataclasses.replace(self, limits=self.limits + tuple(limits),
                                   notes=self.notes + tuple(notes))


NO_SETTINGS = SlicerSettings()


def read_key_values(lines: Iterable[str]) -> SlicerConfig:
    """The ``; key = value`` lines among ``lines`` (later duplicates win)."""
    config: SlicerConfig = {}
    for line in lines:
        match = _KEY_VALUE_RE.match(line.rstrip())
        if match is not None:
            key = match.group(1)
            config[key.lower()] = SlicerValue(key, match.group(2) or "")
    return config


def config_between(text: str, begin: str, end: str) -> SlicerConfig | None:
    """The settings between the last ``begin`` line in ``text`` and the ``end`` line after it,
    or None if there is no such block. A block cut by the end of ``text`` counts to there."""
    start = text.rfind("\n" + begin)
    if start < 0:
        if not text.startswith(begin):
            return None
    else:
        start += 1
    stop = text.find("\n" + end, start)
    body = text[start:] if stop < 0 else text[start:stop]
    return read_key_values(body.splitlines()[1:])


def trailing_config(text: str) -> SlicerConfig:
    """The ``; key = value`` lines of the comment block that ends ``text``.

    Slic3r, Slic3r PE and PrusaSlicer/SuperSlicer before 2.4 append their config after the
    last G-code line without begin/end markers; reading back to the first line that is not a
    comment keeps a ``; key = value`` comment inside the G-code from passing for a setting.
    """
    lines = text.splitlines()
    first = len(lines)
    while first > 0:
        line = lines[first - 1].strip()
        if line and not line.startswith(";"):
            break
        first -= 1
    return read_key_values(lines[first:])


def environment_config(environ: Mapping[str, str]) -> SlicerConfig:
    """The slicer config a post-processing script finds in its environment (``SLIC3R_*``)."""
    return {name[len(ENVIRONMENT_PREFIX):].lower(): SlicerValue(name, value)
            for name, value in environ.items()
            if name.startswith(ENVIRONMENT_PREFIX) and name not in _ENVIRONMENT_NOT_CONFIG}


def first_item(text: str) -> str | None:
    """The first element of a comma-joined vector ("normal,stealth" pairs, per-extruder
    values), or None when it is empty or ``nil``. A plain value is its own first element."""
    item = text.split(",", 1)[0].strip()
    return None if item in ("", NIL) else item


def number(value: SlicerValue | None) -> float | None:
    """The first element as a finite number, or None (absent, nil, a percentage, not a number)."""
    if value is None:
        return None
    item = first_item(value.text)
    if item is None:
        return None
    try:
        result = float(item)
    except ValueError:
        return None
    return result if math.isfinite(result) else None


def number_or_percent(value: SlicerValue | None) -> tuple[float, bool] | None:
    """(number, is_percent) for ``1500`` or ``80%`` (first element), None otherwise."""
    if value is None:
        return None
    item = first_item(value.text)
    if item is None:
        return None
    is_percent = item.endswith("%")
    try:
        result = float(item[:-1] if is_percent else item)
    except ValueError:
        return None
    return (result, is_percent) if math.isfinite(result) else None


def flag(value: SlicerValue | None) -> bool | None:
    """A boolean setting (``1``/``0``, ``true``/``false``), None when absent or unreadable."""
    if value is None:
        return None
    item = first_item(value.text)
    if item is None:
        return None
    lowered = item.lower()
    if lowered in ("1", "true"):
        return True
    if lowered in ("0", "false"):
        return False
    return None


@dataclasses.dataclass(frozen=True)
class LeastOf:
    """A Klipper setting guessed as the least positive value among some slicer keys.

    Klipper has one limit where Marlin-minded slicers keep one per axis (and per move kind);
    the least of them is the one a Klipper user would have had to configure to honour all.
    """

    field: str
    keys: tuple[str, ...]

    def apply(self, config: Mapping[str, SlicerValue]) -> SlicerLimit | None:
        """The mapped value, or None when no key has a positive number."""
        found = [(value_n, config[key]) for key in self.keys
                 if (value_n := number(config.get(key))) is not None and value_n > 0.0]
        if not found:
            return None
        value_n, value = min(found, key=lambda item: item[0])
        source = value.source
        if len(self.keys) > 1:
            source += " (least of %s)" % ", ".join(self.keys)
        return SlicerLimit(self.field, value_n, source)


def resolve_accelerations(config: Mapping[str, SlicerValue],
                          keys: Iterable[tuple[str, str | None]],
                          base_values: Mapping[str, float] | None = None
                          ) -> tuple[tuple[str, float], ...]:
    """The per-feature accelerations a slicer writes, in mm/s^2, percentages resolved.

    ``keys`` are (key, key a percentage refers to, or None); keys must come after the key they
    refer to. ``base_values`` adds bases that are not accelerations themselves. Zero means
    "unset" in these slicers and is left out, as is a percentage of an unknown base.
    """
    known: dict[str, float] = dict(base_values or {})
    result: list[tuple[str, float]] = []
    for key, percent_of in keys:
        parsed = number_or_percent(config.get(key))
        if parsed is None:
            continue
        value_n, is_percent = parsed
        if is_percent:
            base = known.get(percent_of) if percent_of is not None else None
            if base is None:
                continue
            value_n = base * value_n / 100.0
        if value_n > 0.0:
            known[key] = value_n
            result.append((key, value_n))
    return tuple(result)
