"""Every kinematics mainline Klipper (commit 84104bbbd) ships, and Kalico's limited_* ones,
one module each, and the one place that picks the module for a printer: `load_kinematics`.

A kinematics (`base.Kinematics`) does three things for the toolhead, as its
`klippy/kinematics/<name>.py` does: `check_move` (range checks raising Klipper's "Move out of
range: ..." and the speed/accel limits of its axes), `set_position` (which axes are homed),
and `home` (where G28 leaves the head: each axis at its position_endstop, or the delta-style
home position). It is built from `Limits.machine` (the [printer] / [stepper_*] sections of a
printer.cfg or Moonraker); sources without steppers fall back to a stand-in that applies only
the Z speed limit and says so.

Convention shared with the oracle (../shared/tools/oracle): before any G28 in the file the
head is homed at X=Y=Z=0 (`ToolHead` calls `set_position((0, 0, 0, 0), "xyz")`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig, MissingSectionError
from kestimator.errors import KestimatorError
from kestimator.kinematics import (
    cartesian,
    corexy,
    corexz,
    delta,
    deltesian,
    generic_cartesian,
    hybrid_corexy,
    hybrid_corexz,
    limited_cartesian,
    limited_corexy,
    limited_corexz,
    none,
    polar,
    rotary_delta,
    winch,
)
from kestimator.kinematics.base import Kinematics
from kestimator.kinematics.standin import StandInKinematics
from kestimator.limits import klipper_release

if TYPE_CHECKING:
    from kestimator.limits import Limits

__all__ = ["KALICO_KINEMATICS", "KINEMATICS", "Kinematics", "load_kinematics"]

# [printer] kinematics -> its module's load_kinematics(config, limits)
_LOADERS: dict[str, Callable[[MachineConfig, Limits], Kinematics]] = {
    "cartesian": cartesian.load_kinematics,
    "corexy": corexy.load_kinematics,
    "corexz": corexz.load_kinematics,
    "hybrid_corexy": hybrid_corexy.load_kinematics,
    "hybrid_corexz": hybrid_corexz.load_kinematics,
    "generic_cartesian": generic_cartesian.load_kinematics,
    "delta": delta.load_kinematics,
    "deltesian": deltesian.load_kinematics,
    "rotary_delta": rotary_delta.load_kinematics,
    "polar": polar.load_kinematics,
    "winch": winch.load_kinematics,
    "none": none.load_kinematics,
}
KINEMATICS = tuple(_LOADERS)
"""The [printer] kinematics values mainline Klipper 84104bbbd accepts."""
# Kalico's own (v2026.07.00): modelled where klipper_version names Kalico or no version.
_KALICO_LOADERS: dict[str, Callable[[MachineConfig, Limits], Kinematics]] = {
    "limited_cartesian": limited_cartesian.load_kinematics,
    "limited_corexy": limited_corexy.load_kinematics,
    "limited_corexz": limited_corexz.load_kinematics,
}
KALICO_KINEMATICS = tuple(_KALICO_LOADERS)

# Kinematics whose Z moves are limited by max_z_velocity/max_z_accel scaled along Z
# (and, from forks, the limited_* names that behave so for Z).
Z_SCALED = frozenset(("cartesian", "corexy", "corexz", "hybrid_corexy", "hybrid_corexz",
                      "generic_cartesian", "delta", "deltesian", "polar", "limited_cartesian",
                      "limited_corexy", "limited_corexz"))


def _z_rule(name: str) -> str | None:
    """How the kinematics limits Z moves (for the stand-in)."""
    if name == "rotary_delta":
        return "velocity"
    return "scaled" if name in Z_SCALED else None
# Kinematics that need the printer's own sections to be modelled.
_NEED_MACHINE = frozenset(("cartesian", "corexy", "corexz", "hybrid_corexy", "hybrid_corexz",
                           "generic_cartesian", "delta", "deltesian", "rotary_delta", "polar",
                           "winch", "limited_cartesian", "limited_corexy", "limited_corexz"))
_CARTESIAN_LIKE = frozenset(("cartesian", "corexy", "corexz", "hybrid_corexy",
                             "hybrid_corexz", "generic_cartesian"))


def load_kinematics(limits: Limits) -> Kinematics:
    """The kinematics `limits.kinematics` names, built from `limits.machine`.

    Raises KestimatorError (file and line) for a value of the printer's config that Klipper
    refuses. Without the printer's sections (no printer.cfg or Moonraker, or one lacking the
    [stepper_*] sections the kinematics reads) returns a stand-in that only limits Z speed;
    its `warnings` say so, except for cartesian-like printers without any printer config
    (the limits' own warning already says no printer.cfg is known).
    """
    name = limits.kinematics
    machine = limits.machine
    loader = _LOADERS.get(name)
    if name in _KALICO_LOADERS:
        release = klipper_release(limits.klipper_version) if limits.klipper_version else None
        if release is not None and not release.is_kalico:
            raise KestimatorError(
                "[printer] kinematics: %s is Kalico's: %s %s has no such kinematics and "
                "refuses to start (Error loading kinematics '%s'); set klipper_version to "
                "the Kalico the printer runs" % (name, release.app, limits.klipper_version,
                                                 name),
                machine.description if machine is not None else None)
        loader = _KALICO_LOADERS[name]
    if loader is None:
        return StandInKinematics(
            name, limits, _z_rule(name),
            "[printer] kinematics: %s is not a kinematics mainline Klipper ships: moves are "
            "not range-checked, G28 homes to 0%s" % (
                name, " and only max_z_velocity/max_z_accel are applied" if name in Z_SCALED
                else " and no axis limit is applied"))
    if name not in _NEED_MACHINE:
        return none.NoneKinematics()
    if machine is None:
        warning = None
        if name not in _CARTESIAN_LIKE:
            warning = ("[printer] kinematics: %s needs the printer's [printer] and [stepper_*] "
                       "sections (a printer.cfg or Moonraker) to be modelled: without them "
                       "moves are not range-checked, G28 homes to 0 and only the Z speed "
                       "limit is applied, so times may be off" % name)
        return StandInKinematics(name, limits, _z_rule(name), warning)
    try:
        kin = loader(machine, limits)
    except MissingSectionError as exc:
        return StandInKinematics(
            name, limits, _z_rule(name),
            "%s: %s: moves are not range-checked, G28 homes to 0 and only the Z speed limit "
            "is applied" % (machine.description, exc.message))
    except (ArithmeticError, ValueError) as exc:
        # Values each within Klipper's bounds can still give a geometry its arithmetic
        # breaks on (Klipper itself then stops at start-up with a traceback).
        raise KestimatorError(
            "[printer] kinematics: %s: Klipper cannot compute this printer's geometry from "
            "its config (%s: %s): check the arm lengths, radii, angles and endstop positions"
            % (name, type(exc).__name__, exc), machine.description) from None
    return kin
