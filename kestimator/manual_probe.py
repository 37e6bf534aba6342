"""Mirrors klippy/extras/manual_probe.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `ManualProbe`, which toolhead.py loads on every printer: where the Z endstop's
config is (`lookup_z_endstop_config`, also safe_z_home's), and which of its endstop
commands it registers: Z_ENDSTOP_CALIBRATE when that section has a `position_endstop`,
Z_OFFSET_APPLY_ENDSTOP then too and on a linear delta. The probing itself (MANUAL_PROBE)
waits for the user: it is not a print command kestimator times.

Re-implemented from mainline Klipper at commit 84104bbbd (GNU GPLv3). Names follow upstream.
"""

from __future__ import annotations

from kestimator.config.machine import MachineConfig, Section

# ManualProbe's commands that depend on the printer's config.
ENDSTOP_COMMANDS = ("Z_ENDSTOP_CALIBRATE", "Z_OFFSET_APPLY_ENDSTOP")


def lookup_z_endstop_config(config: MachineConfig) -> Section | None:
    """manual_probe's: [stepper_z], or the [carriage ...] whose axis is z."""
    stepper_z = config.section("stepper_z")
    if stepper_z is not None:
        return stepper_z
    for cconfig in config.get_prefix_sections("carriage "):
        carriage_name = cconfig.get_name().split()[-1].strip()
        if cconfig.get("axis", carriage_name) == "z":
            return cconfig
    return None


def unregistered_endstop_commands(config: MachineConfig | None, kinematics: str
                                  ) -> frozenset[str]:
    """The ENDSTOP_COMMANDS ManualProbe does not register on this printer (none when its
    steppers are not known)."""
    if config is None:
        return frozenset()
    zconfig = lookup_z_endstop_config(config)
    if zconfig is not None and zconfig.get("position_endstop", None) is not None:
        return frozenset()
    if kinematics == "delta":
        return frozenset(("Z_ENDSTOP_CALIBRATE",))
    return frozenset(ENDSTOP_COMMANDS)
