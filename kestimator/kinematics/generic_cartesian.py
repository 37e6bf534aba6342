"""Mirrors klippy/kinematics/generic_cartesian.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `generic_cartesian` kinematics: [carriage <name>] rails (one primary per axis),
[stepper <name>] steppers that mix them, optional [dual_carriage <name>] and
[extra_carriage <name>] sections.

Re-implemented from mainline Klipper at commit 84104bbbd,
`klippy/kinematics/generic_cartesian.py` (GNU GPLv3). Its `check_move` is cartesian's: each
axis's range is its active carriage's (the primary one until SET_DUAL_CARRIAGE), Z moves are
limited by max_z_velocity / max_z_accel scaled along Z. G28 leaves each homed axis at its
primary carriage's position_endstop. Switching carriages (SET_DUAL_CARRIAGE) and remapping
steppers (SET_STEPPER_CARRIAGES) are named as not modelled where they run.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig, Rail, rail_from_section
from kestimator.errors import KestimatorError
from kestimator.kinematics.base import Kinematics
from kestimator.kinematics.cartesian import DUAL_CARRIAGE_NOTE, CartKinematics

if TYPE_CHECKING:
    from kestimator.limits import Limits

VALID_AXES = ("x", "y", "z")
STEPPER_CARRIAGES_NOTE = ("generic_cartesian: SET_STEPPER_CARRIAGES remaps steppers to "
                          "carriages, which kestimator does not model; times after it may be off")


class GenericCartesianKinematics(CartKinematics):
    """Primary carriages as the three rails of cartesian."""

    name = "generic_cartesian"

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        Kinematics.__init__(self)
        rails: dict[int, Rail] = {}
        for section in config.get_prefix_sections("carriage "):
            parts = section.name.split(None, 1)
            if len(parts) < 2:
                raise KestimatorError("[%s] has no carriage name: name it as [carriage x]"
                                      % section.name, config.description)
            carriage_name = parts[1].strip()
            default_axis = carriage_name if carriage_name in VALID_AXES else None
            axis_name = (section.get("axis", default_axis) or "").strip().lower()
            if axis_name not in VALID_AXES:
                raise section._error("axis", "Choice '%s' for option 'axis' in section '%s' "
                                     "is not a valid choice" % (axis_name, section.name))
            axis = VALID_AXES.index(axis_name)
            if axis in rails:
                raise KestimatorError(
                    "Axis '%s' is set for multiple primary carriages (%s, %s)"
                    % (axis_name, rails[axis].name, section.name), config.description)
            rails[axis] = rail_from_section(config, section, has_stepper=False)
        for axis, axis_name in enumerate(VALID_AXES):
            if axis not in rails:
                raise KestimatorError("No carriage defined for axis '%s'" % axis_name,
                                      config.description)
        self.rails = [rails[0], rails[1], rails[2]]
        if config.get_prefix_sections("dual_carriage "):
            self.commands["SET_DUAL_CARRIAGE"] = DUAL_CARRIAGE_NOTE
        self.commands["SET_STEPPER_CARRIAGES"] = STEPPER_CARRIAGES_NOTE
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        self.limits = [(1.0, -1.0)] * 3
        self._note_xy_range()


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: generic_cartesian."""
    return GenericCartesianKinematics(config, limits)
