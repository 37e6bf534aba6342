"""Mirrors klippy/kinematics/cartesian.py at Klipper commit 84104bbbd (GNU GPLv3).

Klipper's `cartesian` kinematics: per-axis ranges from [stepper_x/y/z], Z speed limits.

Re-implemented from mainline Klipper at commit 84104bbbd, `klippy/kinematics/cartesian.py`
(GNU GPLv3). corexy, corexz, hybrid_corexy and hybrid_corexz check moves the same way
(their `check_move` is this one); their modules subclass `CartKinematics`.

`[dual_carriage]` changes nothing until SET_DUAL_CARRIAGE (or a COPY/MIRROR mode) switches
carriages (`klippy/kinematics/idex_modes.py`): that command is named as not modelled.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kestimator.config.machine import MachineConfig, lookup_rail
from kestimator.kinematics.base import Kinematics, Position

if TYPE_CHECKING:
    from kestimator.limits import Limits
    from kestimator.toolhead import Move

UNHOMED = (1.0, -1.0)
DUAL_CARRIAGE_NOTE = ("[dual_carriage]: SET_DUAL_CARRIAGE switches carriages, offsets and "
                      "limits, which kestimator does not model; times after it may be off")


class CartKinematics(Kinematics):
    """Three rails, each with its own range; Z moves limited by max_z_velocity/accel."""

    name = "cartesian"
    dual_carriage_axes: tuple[str, ...] = ("x", "y")

    def __init__(self, config: MachineConfig, limits: Limits) -> None:
        super().__init__()
        self.rails = [lookup_rail(config, "stepper_" + n) for n in "xyz"]
        if self.dual_carriage_axes and config.has_section("dual_carriage"):
            dc_config = config.getsection("dual_carriage")
            axis = (dc_config.get("axis", "x") or "x").strip().lower()
            if axis not in self.dual_carriage_axes:
                raise dc_config._error("axis", "Choice '%s' for option 'axis' is not a valid "
                                       "choice" % axis)
            self.commands["SET_DUAL_CARRIAGE"] = DUAL_CARRIAGE_NOTE
            self._dual_carriage_range_note(config, axis, dc_config.getfloat(
                "safe_distance", -1.0))
        self.max_z_velocity = limits.max_z_velocity
        self.max_z_accel = limits.max_z_accel
        self.limits = [UNHOMED] * 3
        self._note_xy_range()

    def _note_xy_range(self) -> None:
        """check_move's X and Y ranges, from self.limits, as four floats (set wherever
        self.limits changes): the check on every move reads no list of tuples."""
        (self.x_low, self.x_high), (self.y_low, self.y_high) = self.limits[0], self.limits[1]

    def _dual_carriage_range_note(self, config: MachineConfig, axis: str,
                                  safe_distance: float) -> None:
        """idex_modes narrows the axis's range after G28 by the parked carriage when the
        carriages keep a safe distance: said, as it is not modelled."""
        primary = self.rails["xy".index(axis)]
        dual = lookup_rail(config, "dual_carriage")
        if safe_distance < 0.0:
            safe_distance = min(abs(primary.position_min - dual.position_min),
                                abs(primary.position_max - dual.position_max))
        if safe_distance:
            self.warnings.append(
                "[dual_carriage]: after G28 Klipper narrows %s's range by the parked carriage "
                "and safe_distance (%g mm); moves are range-checked against %s's own range "
                "only" % (axis.upper(), safe_distance, primary.name))

    def set_position(self, newpos: Position, homing_axes: str) -> None:
        """Homed axes get their rail's range as limits."""
        for axis_name in homing_axes:
            axis = "xyz".index(axis_name)
            self.limits[axis] = self.rails[axis].get_range()
        self._note_xy_range()

    def clear_homing_state(self, clear_axes: str) -> None:
        """Cleared axes must be homed again before they move."""
        for axis, axis_name in enumerate("xyz"):
            if axis_name in clear_axes:
                self.limits[axis] = UNHOMED
        self._note_xy_range()

    def homed_axes(self) -> str:
        """The axes whose limits are set (get_status's homed_axes)."""
        return "".join(a for a, (low, high) in zip("xyz", self.limits) if low <= high)

    def home(self, pos: Position, axes: list[int]) -> tuple[Position, str]:
        """Each homed axis ends at its position_endstop."""
        newpos = list(pos)
        for axis in axes:
            newpos[axis] = self.rails[axis].position_endstop
        return (newpos[0], newpos[1], newpos[2], newpos[3]), "".join("xyz"[a] for a in axes)

    def _check_endstops(self, move: Move) -> None:
        end_pos = (move.end_x, move.end_y, move.end_z)
        axes_d = (move.axes_d_x, move.axes_d_y, move.axes_d_z)
        for i in (0, 1, 2):
            if (axes_d[i]
                    and (end_pos[i] < self.limits[i][0]
                         or end_pos[i] > self.limits[i][1])):
                if self.limits[i][0] > self.limits[i][1]:
                    raise move.move_error("Must home axis first")
                raise move.move_error()

    def check_move(self, move: Move) -> None:
        """Range checks, and Z moves slowed to max_z_velocity/accel along Z."""
        xpos, ypos = move.end_x, move.end_y
        if (xpos < self.x_low or xpos > self.x_high
                or ypos < self.y_low or ypos > self.y_high):
            self._check_endstops(move)
        if not move.axes_d_z:
            # Normal XY move - use defaults
            return
        # Move with Z - update velocity and accel for slower Z axis
        self._check_endstops(move)
        z_ratio = move.move_d / abs(move.axes_d_z)
        move.limit_speed(self.max_z_velocity * z_ratio, self.max_z_accel * z_ratio)


def load_kinematics(config: MachineConfig, limits: Limits) -> Kinematics:
    """The kinematics for [printer] kinematics: cartesian."""
    return CartKinematics(config, limits)
