"""Which commands a Klipper printer knows, from the sections of its config.

Owns the table of the G-code commands that Klipper's modules register (mainline Klipper
84104bbbd, `klippy/extras/*.py` `register_command`) for the modules whose commands take no
motion time, which modules load which others (`load_object`), and `klippy/gcode.py`
`cmd_default`'s silent cases (commands it neither runs nor reports when no module has them).
Commands that move or wait are the interpreter's (`kestimator.interpreter`).
"""

from __future__ import annotations

# Module (config section) -> the no-time commands it registers.
MODULE_COMMANDS: dict[str, tuple[str, ...]] = {
    "display_status": ("M73", "M117", "SET_DISPLAY_TEXT"),
    "respond": ("M118", "RESPOND"),
    "fan": ("M106", "M107"),
    "heater_bed": ("M140",),
    "exclude_object": ("EXCLUDE_OBJECT", "EXCLUDE_OBJECT_DEFINE", "EXCLUDE_OBJECT_START",
                       "EXCLUDE_OBJECT_END"),
    "print_stats": ("SET_PRINT_STATS_INFO",),
    "virtual_sdcard": ("M20", "M21", "M23", "M24", "M25", "M26", "M27",
                       "SDCARD_RESET_FILE", "SDCARD_PRINT_FILE"),
    "pause_resume": ("PAUSE", "RESUME", "CLEAR_PAUSE", "CANCEL_PRINT"),
    "save_variables": ("SAVE_VARIABLE",),
    "firmware_retraction": ("GET_RETRACTION",),
    "fan_generic": ("SET_FAN_SPEED",),
}
# Modules a module loads itself (display loads display_status, virtual_sdcard print_stats,
# a filament sensor pause_resume).
MODULE_LOADS: dict[str, tuple[str, ...]] = {
    "display": ("display_status",),
    "virtual_sdcard": ("print_stats",),
    "filament_switch_sensor": ("pause_resume",),
    "filament_motion_sensor": ("pause_resume",),
}
# The module of each command in MODULE_COMMANDS.
COMMAND_MODULE = {command: module for module, commands in MODULE_COMMANDS.items()
                  for command in commands}
# M190 needs [heater_bed] too, but it waits: the interpreter runs it.
HEATER_BED_WAIT = "M190"


def loaded_modules(sections: tuple[str, ...]) -> frozenset[str]:
    """Every module a config with these sections loads (a section "name x" loads "name")."""
    loaded = set()
    pending = [section.split()[0] for section in sections if section.strip()]
    while pending:
        module = pending.pop()
        if module in loaded:
            continue
        loaded.add(module)
        pending.extend(MODULE_LOADS.get(module, ()))
    return frozenset(loaded)


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
