"""The user's kestimator profile: a TOML file that names their printer and settings once, so a
slicer's post-processing line needs no arguments.

Owns where the profile lives (``--profile``, else ``$XDG_CONFIG_HOME/kestimator/config.toml``,
``~/.config/kestimator/config.toml`` when that is unset), its keys, and the choice of a
``[printers."<name>"]`` table: by ``--printer NAME``, else the one named like the slicer's
printer preset (``printer_settings_id``), else none. A table's keys replace the top-level ones
and its ``[limits]`` and ``[macros]`` add to the top-level ones::

    printer_cfg = "~/printer_data/config/printer.cfg"  # or: moonraker = "http://voron.local"
    api_key = "..."                                    # Moonraker's, if it asks for one
    moonraker_timeout_s = 3
    homing_time_s = 25          # what one G28 takes on this printer (default 0)
    heat_time_s = 90            # what one heater wait takes (default 0)
    stop_commands = ["FILAMENT_SWAP"]  # commands that wait for you, beyond M600, PAUSE...

    [macros]                     # seconds one run of a macro takes on this printer
    PRINT_START = 420
    TIMELAPSE_TAKE_FRAME = 3.2

    [limits]                     # any Limits field (docs/LIMITS.md), e.g.
    klipper_generation = "mcr"

    [printers."Voron 2.4 0.4 nozzle"]
    moonraker = "http://voron.local:7125"

A relative ``printer_cfg`` is relative to the profile's folder. The profile ranks below the real
machine: its ``[limits]`` only decide what no printer.cfg or Moonraker decides.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

from kestimator.config.fields import check_limit_value
from kestimator.durations import MAX_PRINT_S
from kestimator.errors import KestimatorError
from kestimator.files import read_config_bytes
from kestimator.macros import check_seconds

PROFILE_RELATIVE_PATH = Path("kestimator") / "config.toml"
_MACHINE_KEYS = ("printer_cfg", "moonraker")
_TEXT_KEYS = ("printer_cfg", "moonraker", "api_key")
# Durations the file cannot tell (seconds per G28, per heater wait); the command line's
# --homing-time / --heat-time win over them.
DURATION_KEYS = ("homing_time_s", "heat_time_s")
MAX_MOONRAKER_TIMEOUT_S = 3600.0
"""An hour: beyond, a deadline is no deadline (and 1e308 s overflows the clock)."""

_TOP_KEYS = frozenset((*_TEXT_KEYS, *DURATION_KEYS, "moonraker_timeout_s", "limits",
                       "macros", "printers", "stop_commands"))
# A command name as Klipper's G-code dispatch looks it up (letters, digits, underscores).
_COMMAND_NAME_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_")
MAX_STOP_COMMANDS = 100
_TABLE_KEYS = _TOP_KEYS - {"printers"}


@dataclasses.dataclass(frozen=True)
class Profile:
    """What a profile says, for the printer table chosen (if any)."""

    path: str
    printer: str | None
    """The ``[printers."<name>"]`` table applied, None for the top level alone."""
    printer_cfg: str | None
    """Absolute path (``~`` expanded, relative to the profile's folder)."""
    moonraker: str | None
    api_key: str | None = dataclasses.field(repr=False)
    moonraker_timeout_s: float | None
    limits: Mapping[str, object]
    limit_sources: Mapping[str, str]
    """Field -> ``profile <path>`` (with the table, if the value is the table's)."""
    homing_time_s: float | None = None
    heat_time_s: float | None = None
    macros: Mapping[str, float] = dataclasses.field(default_factory=dict)
    """Macro name (upper case, as Klipper looks it up) -> seconds one run takes."""
    stop_commands: tuple[str, ...] = ()
    """The user's own commands at which the print waits for them (upper case)."""

    @property
    def description(self) -> str:
        """``profile <path>``, with the printer table if one was chosen."""
        return _describe(self.path, self.printer)


def _describe(path: str, printer: str | None) -> str:
    return f"profile {path}" + ("" if printer is None else f' [printers."{printer}"]')


def default_profile_path(environ: Mapping[str, str]) -> Path:
    """``$XDG_CONFIG_HOME/kestimator/config.toml`` (``~/.config/...`` when it is unset)."""
    base = environ.get("XDG_CONFIG_HOME") or os.path.join(
        environ.get("HOME") or os.path.expanduser("~"), ".config")
    return Path(base) / PROFILE_RELATIVE_PATH


def load_profile(path: str | os.PathLike[str], printer: str | None = None,
                 slicer_preset: str | None = None) -> Profile:
    """The profile at ``path``, with the printer table ``printer`` (an error if there is none
    of that name) or else the one named ``slicer_preset`` (if any).

    Raises KestimatorError (naming the file) for unreadable TOML, unknown keys, values of the
    wrong type or that Klipper would refuse, or both a printer.cfg and a Moonraker URL.
    """
    name = os.fspath(path)
    toml = _toml_reader(name)
    try:
        # Bounded, and refusing devices and FIFOs (/dev/zero as --profile).
        data = read_config_bytes(name, "profile")
    except KestimatorError as exc:
        if exc.message.startswith("cannot read file: "):
            raise KestimatorError("cannot read profile: " + exc.message[len("cannot read file: "):],
                                  name) from None
        raise
    try:
        document = toml.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise KestimatorError(f"not UTF-8 text ({exc.reason})", name, line) from None
    except RecursionError:
        raise KestimatorError("not valid TOML: nested too deeply", name) from None
    except toml.TOMLDecodeError as exc:
        raise KestimatorError(f"not valid TOML: {exc}", name) from None
    _check_keys(document, _TOP_KEYS, "", name)
    tables = document.get("printers", {})
    if not isinstance(tables, dict) or not all(isinstance(t, dict) for t in tables.values()):
        raise KestimatorError('[printers] must hold tables: [printers."<name>"]', name)
    # Every table is checked, not only the one chosen: a typo shows on the first run.
    checked_limits: dict[str, dict[str, object]] = {}
    checked_macros: dict[str, dict[str, float]] = {}
    for table_name, table in tables.items():
        where = f'[printers."{table_name}"]'
        _check_keys(table, _TABLE_KEYS, where + " ", name)
        checked_limits[table_name] = _limits(table.get("limits", {}), where + ".limits", name)
        checked_macros[table_name] = _macros(table.get("macros", {}), where + ".macros", name)
    chosen = printer if printer is not None else (
        slicer_preset if slicer_preset in tables else None)
    if chosen is not None and chosen not in tables:
        known = ", ".join(sorted(tables)) or "none"
        raise KestimatorError(f'no [printers."{chosen}"] table (there are: {known})', name)
    settings: dict[str, Any] = {key: value for key, value in document.items()
                                if key not in ("printers", "limits", "macros")}
    limits = _limits(document.get("limits", {}), "[limits]", name)
    macros = _macros(document.get("macros", {}), "[macros]", name)
    limit_sources = dict.fromkeys(limits, _describe(name, None))
    if chosen is not None:
        table = tables[chosen]
        if any(key in table for key in _MACHINE_KEYS):
            for key in _MACHINE_KEYS:
                settings.pop(key, None)
        settings.update({key: value for key, value in table.items()
                         if key not in ("limits", "macros")})
        macros.update(checked_macros[chosen])
        table_limits = checked_limits[chosen]
        limits.update(table_limits)
        limit_sources.update(dict.fromkeys(table_limits, _describe(name, chosen)))
    for key in _TEXT_KEYS:
        if key in settings and (not isinstance(settings[key], str) or not settings[key]):
            raise KestimatorError(f"{key} must be a non-empty text", name)
    if all(key in settings for key in _MACHINE_KEYS):
        raise KestimatorError("names both printer_cfg and moonraker: keep one", name)
    timeout_s = settings.get("moonraker_timeout_s")
    if timeout_s is not None and (isinstance(timeout_s, bool) or not isinstance(
            timeout_s, (int, float)) or not 0.0 < timeout_s <= MAX_MOONRAKER_TIMEOUT_S):
        raise KestimatorError("moonraker_timeout_s must be a number of seconds above 0 and "
                              "at most %g" % MAX_MOONRAKER_TIMEOUT_S, name)
    durations: dict[str, float | None] = {}
    for key in DURATION_KEYS:
        value = settings.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(
                value, (int, float)) or not 0.0 <= value <= MAX_PRINT_S):
            raise KestimatorError(f"{key} must be a number of seconds, 0 or more and at most "
                                  f"a year ({MAX_PRINT_S:g})", name)
        durations[key] = None if value is None else float(value)
    stops = _stop_commands(settings.get("stop_commands", []), name)
    printer_cfg = settings.get("printer_cfg")
    if printer_cfg is not None:
        printer_cfg = os.path.join(os.path.dirname(os.path.abspath(name)),
                                   os.path.expanduser(printer_cfg))
    return Profile(path=name, printer=chosen, printer_cfg=printer_cfg,
                   moonraker=settings.get("moonraker"), api_key=settings.get("api_key"),
                   moonraker_timeout_s=None if timeout_s is None else float(timeout_s),
                   limits=limits, limit_sources=limit_sources,
                   homing_time_s=durations["homing_time_s"],
                   heat_time_s=durations["heat_time_s"], macros=macros,
                   stop_commands=stops)


def _stop_commands(value: object, path: str) -> tuple[str, ...]:
    """``stop_commands``: a list of command names, upper-cased as Klipper looks them up."""
    if not isinstance(value, list) or len(value) > MAX_STOP_COMMANDS or not all(
            isinstance(item, str) and item.strip() and len(item) <= 64
            and set(item.strip().upper()) <= _COMMAND_NAME_CHARS for item in value):
        raise KestimatorError("stop_commands must be a list of at most %d command names "
                              '(letters, digits, "_"), e.g. ["M600", "FILAMENT_SWAP"]'
                              % MAX_STOP_COMMANDS, path)
    return tuple(item.strip().upper() for item in value)


def toml_available() -> bool:
    """True when a profile can be read (Python 3.11+, or tomli installed)."""
    if sys.version_info >= (3, 11):
        return True
    return importlib.util.find_spec("tomli") is not None


def _toml_reader(path: str) -> ModuleType:
    """``tomllib``, or ``tomli`` before Python 3.11; imported only when a profile is read, so
    kestimator without a profile runs on a bare Python 3.10 (Cura's, say)."""
    if sys.version_info >= (3, 11):
        import tomllib
        return tomllib
    try:
        import tomli
    except ImportError:
        raise KestimatorError("reading a profile needs Python 3.11 or the tomli package "
                              "(pip install tomli)", path) from None
    return tomli


def _check_keys(table: Mapping[str, Any], allowed: frozenset[str], where: str,
                path: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise KestimatorError(f"{where}unknown key(s) {', '.join(unknown)} (known: "
                              f"{', '.join(sorted(allowed))})", path)


def _limits(table: object, where: str, path: str) -> dict[str, object]:
    """A ``[limits]`` table, each value checked as Klipper would."""
    if not isinstance(table, dict):
        raise KestimatorError(f"{where} must be a table", path)
    checked: dict[str, object] = {}
    for field, value in table.items():
        try:
            checked[field] = check_limit_value(field, value)
        except ValueError as exc:
            raise KestimatorError(f"{where}: {exc}", path) from None
    return checked


def _macros(table: object, where: str, path: str) -> dict[str, float]:
    """A ``[macros]`` table: macro name -> seconds, names upper-cased as Klipper does."""
    if not isinstance(table, dict):
        raise KestimatorError(f"{where} must be a table of macro name = seconds", path)
    checked: dict[str, float] = {}
    for macro, value in table.items():
        name = macro.strip().upper()
        if not name or any(c.isspace() for c in name):
            raise KestimatorError(f"{where}: {macro!r} is not a macro name", path)
        try:
            checked[name] = check_seconds(value)
        except ValueError as exc:
            raise KestimatorError(f"{where}: {macro} {exc}", path) from None
        if checked[name] > MAX_PRINT_S:
            raise KestimatorError(f"{where}: {macro} = {value:g} s is over a year "
                                  f"({MAX_PRINT_S:g} s): no macro takes that long", path)
    return checked
