"""Mirrors klippy/extras/firmware_retraction.py at Klipper commit 84104bbbd (GNU GPLv3).

Owns G10/G11 and SET_RETRACTION, present when the printer's config has
[firmware_retraction]. Upstream runs "SAVE_GCODE_STATE / G91 / G1 E.. F.. /
RESTORE_GCODE_STATE" as a script; here the same steps act on `GCodeMove` directly, with
the length rounded to 5 decimals and the speed to whole mm/min as the script's text does.
"""

from __future__ import annotations

from kestimator.errors import fixed
from kestimator.gcode import Command, command_params, get_float
from kestimator.gcode_move import GCodeMove
from kestimator.limits import Limits

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class FirmwareRetraction:
    """The retraction lengths and speeds, and whether the filament is retracted."""

    def __init__(self, limits: Limits, gcode_move: GCodeMove) -> None:
        self.gcode_move = gcode_move
        self.retract_length = limits.retract_length
        self.retract_speed = limits.retract_speed
        self.unretract_extra_length = limits.unretract_extra_length
        self.unretract_speed = limits.unretract_speed
        self.is_retracted = False
        # G10's and G11's script values (E, F), formatted once after a change (_script_values).
        self._retract: tuple[float, float] | None = None
        self._unretract: tuple[float, float] | None = None

    def cmd_SET_RETRACTION(self, cmd: Command) -> None:
        """Change the firmware retraction lengths and speeds."""
        params = command_params(cmd)
        self.retract_length = get_float(params, "RETRACT_LENGTH", self.retract_length,
                                        minval=0.0)
        self.retract_speed = get_float(params, "RETRACT_SPEED", self.retract_speed,
                                       minval=1.0)
        self.unretract_extra_length = get_float(
            params, "UNRETRACT_EXTRA_LENGTH", self.unretract_extra_length, minval=0.0)
        self.unretract_speed = get_float(params, "UNRETRACT_SPEED", self.unretract_speed,
                                         minval=1.0)
        self.is_retracted = False
        self._retract = self._unretract = None

    def cmd_G10(self, cmd: Command) -> None:
        """Retract by retract_length at retract_speed (once until G11)."""
        if not self.is_retracted:
            values = self._retract
            if values is None:
                values = self._retract = _script_values(-self.retract_length,
                                                        self.retract_speed)
            self._relative_e_move(values[0], values[1])
            self.is_retracted = True

    def cmd_G11(self, cmd: Command) -> None:
        """Unretract by retract_length + unretract_extra_length at unretract_speed."""
        if self.is_retracted:
            values = self._unretract
            if values is None:
                values = self._unretract = _script_values(
                    self.retract_length + self.unretract_extra_length, self.unretract_speed)
            self._relative_e_move(values[0], values[1])
            self.is_retracted = False

    def _relative_e_move(self, e_value: float, f_value: float) -> None:
        # "SAVE_GCODE_STATE / G91 / G1 E%.5f F%d / RESTORE_GCODE_STATE", E and F as the
        # text has them (_script_values)
        gcode_move = self.gcode_move
        state = gcode_move.save_state()
        gcode_move.absolute_coord = False
        e = e_value * gcode_move.extrude_factor
        gcode_move.last_e += e  # upstream's last_position[3] += v
        gcode_move.speed = f_value * gcode_move.speed_factor
        try:
            gcode_move.move_with_speed(gcode_move.speed)
        finally:
            gcode_move.restore_state(state)


def _script_values(length: float, speed: float) -> tuple[float, float]:
    """E and F of the script's "G1 E%.5f F%d" line as its text has them. Upstream formats
    the script at every G10 and G11; the values change only with SET_RETRACTION, so
    FirmwareRetraction formats them at the first G10 (G11) after a change and keeps them
    (12,000 of them on the 40 MB corpus file: 2 % of a compiled estimate); an error ("F%d"
    of an infinite speed) still comes at that G10 (G11)."""
    return float(fixed(length, 5)), float("%d" % (speed * 60))
