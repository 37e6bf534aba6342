"""Which commands a Klipper printer knows, from the sections of its config.

Owns what the table of `kestimator.klipper_commands` (every command real Klipper 84104bbbd
registers, by module, derived from Klipper itself) means for one printer: which modules a
config's sections load as klippy loads them (a section "name x" loads `extras/name.py`, an
[extruderN] the extruder, the kinematics its own helpers, each module what it
`load_object`s, toolhead.py its defaults), the commands those register, and `klippy/gcode.py`
`cmd_default`'s silent cases (commands it neither runs nor reports when no module has them).
Commands that move or wait are the interpreter's (`kestimator.interpreter`).
"""

from __future__ import annotations

import re

from kestimator.klipper_commands import (
    CORE_COMMANDS,
    DEFAULT_MODULES,
    MODULE_COMMANDS,
    MODULE_LOADS,
)

__all__ = ["CORE_COMMANDS", "HEATER_BED_WAIT", "MODULE_COMMANDS", "loaded_modules",
           "registered_commands", "section_module", "silently_ignored"]

# M190 needs [heater_bed] too, but it waits: the interpreter runs it.
HEATER_BED_WAIT = "M190"
# [extruder], [extruder1], ...: kinematics/extruder.py's objects.
_EXTRUDER_SECTION = re.compile(r"extruder\d*$")


def section_module(section: str) -> str:
    """The module a config section loads ("tmc2209 stepper_x" -> "tmc2209")."""
    words = section.split()
    if not words:
        return ""
    name = words[0].lower()
    return "extruder" if _EXTRUDER_SECTION.match(name) else name


def loaded_modules(sections: tuple[str, ...], kinematics: str | None = None
                   ) -> frozenset[str]:
    """Every module a config with these sections loads (with its kinematics, when given:
    "kinematics/NAME"), as klippy loads them."""
    loaded = set()
    pending = [section_module(section) for section in sections if section.strip()]
    pending += DEFAULT_MODULES
    if kinematics:
        pending.append("kinematics/" + kinematics)
    while pending:
        module = pending.pop()
        if module in loaded:
            continue
        loaded.add(module)
        pending.extend(MODULE_LOADS.get(module, ()))
    return frozenset(loaded)


def registered_commands(modules: frozenset[str]) -> frozenset[str]:
    """The commands Klipper holds once ready with these modules loaded (not counting the
    config's [gcode_macro]s)."""
    known = set(CORE_COMMANDS)
    for module in modules:
        known.update(MODULE_COMMANDS.get(module, ()))
    return frozenset(known)


def silently_ignored(name: str, params: dict[str, str]) -> bool:
    """Klipper's cmd_default skips these without "Unknown command" when no module has them
    (a print from a file): M107, M106, and M104/M140 that turn a heater off."""
    if name in ("M107", "M106"):
        return True
    if name in ("M104", "M140"):
        try:
            return not float(params.get("S", "0"))
        except ValueError:
            return False
    return False
