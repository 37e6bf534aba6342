"""Mirrors klippy/extras/skew_correction.py at Klipper commit 84104bbbd (GNU GPLv3).

[skew_correction]: a move transform that shears every position by the loaded skew factors
(XY, XZ, YZ), so that the toolhead's moves (and their lengths, hence their times) are the
skewed ones. It is the outermost transform (upstream installs it at connect with force, in
front of bed_mesh). Commands: SKEW_PROFILE (LOAD/SAVE/REMOVE), SET_SKEW (XY/XZ/YZ lengths,
CLEAR); GET_CURRENT_SKEW and CALC_MEASURED_SKEW only report.

Re-implemented, not copied; the arithmetic is upstream's, in its order.
"""

from __future__ import annotations

import math

from kestimator.config.machine import MachineConfig
from kestimator.errors import CommandError
from kestimator.gcode import Command, command_params, get_int
from kestimator.gcode_move import GCodeMove, MoveTransform

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]


def calc_skew_factor(ac: float, bd: float, ad: float) -> float:
    """The skew factor of a measured square's diagonals AC, BD and side AD."""
    side = math.sqrt(2 * ac * ac + 2 * bd * bd - 4 * ad * ad) / 2.
    return math.tan(math.pi / 2 - math.acos(
        (ac * ac - side * side - ad * ad) / (2 * side * ad)))


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class PrinterSkew:
    """The skew transform and its profiles (upstream's PrinterSkew)."""

    def __init__(self, config: MachineConfig, gcode_move: GCodeMove) -> None:
        self.gcode_move = gcode_move
        self.xy_factor = 0.
        self.xz_factor = 0.
        self.yz_factor = 0.
        self.skew_profiles: dict[str, tuple[float, float, float]] = {}
        for profile in config.get_prefix_sections("skew_correction"):
            name = profile.get_name()
            if name == "skew_correction" or " " not in name:
                continue
            self.skew_profiles[name.split(" ", 1)[1]] = (
                profile.getfloat("xy_skew"), profile.getfloat("xz_skew"),
                profile.getfloat("yz_skew"))
        self.next_transform: MoveTransform = gcode_move.set_move_transform(self, force=True)

    def calc_skew(self, pos: list[float]) -> list[float]:
        """The toolhead position of a G-code position."""
        skewed_x = pos[0] - pos[1] * self.xy_factor \
            - pos[2] * (self.xz_factor - (self.xy_factor * self.yz_factor))
        skewed_y = pos[1] - pos[2] * self.yz_factor
        return [skewed_x, skewed_y] + pos[2:]

    def calc_unskew(self, pos: list[float]) -> list[float]:
        """The G-code position of a toolhead position."""
        skewed_x = pos[0] + pos[1] * self.xy_factor + pos[2] * self.xz_factor
        skewed_y = pos[1] + pos[2] * self.yz_factor
        return [skewed_x, skewed_y] + pos[2:]

    def get_position(self) -> list[float]:
        """The G-code position of the next transform's."""
        return self.calc_unskew(self.next_transform.get_position())

    def move(self, newpos: list[float], speed: float, tag: int) -> None:
        """A G-code move, skewed."""
        self.next_transform.move(self.calc_skew(newpos), speed, tag)

    def _update_skew(self, xy_factor: float, xz_factor: float, yz_factor: float) -> None:
        self.xy_factor = xy_factor
        self.xz_factor = xz_factor
        self.yz_factor = yz_factor
        self.gcode_move.reset_last_position()

    def cmd_SET_SKEW(self, cmd: Command) -> None:
        """Skew factors from measured lengths "AC,BD,AD" per plane; CLEAR=1 resets them.

        As upstream, the factors of the lengths apply from the next move on without the
        G-code position being read again."""
        params = command_params(cmd)
        if get_int(params, "CLEAR"):
            self._update_skew(0., 0., 0.)
            return
        for plane in ("XY", "XZ", "YZ"):
            text = params.get(plane)
            if text is None:
                continue
            try:
                lengths = [float(part.strip()) for part in text.strip().split(",", 2)]
                if len(lengths) != 3:
                    raise ValueError(text)
                factor = calc_skew_factor(lengths[0], lengths[1], lengths[2])
            except (ValueError, ZeroDivisionError):
                raise CommandError(
                    "skew_correction: improperly formatted entry for plane [%s]\n%s"
                    % (plane, cmd.code.strip())) from None
            if plane == "XY":
                self.xy_factor = factor
            elif plane == "XZ":
                self.xz_factor = factor
            else:
                self.yz_factor = factor

    def cmd_SKEW_PROFILE(self, cmd: Command) -> None:
        """LOAD (an unknown name only says so), SAVE or REMOVE a profile."""
        params = command_params(cmd)
        name = params.get("LOAD")
        if name is not None:
            prof = self.skew_profiles.get(name)
            if prof is None:
                return
            self._update_skew(prof[0], prof[1], prof[2])
            return
        name = params.get("SAVE")
        if name is not None:
            self.skew_profiles[name] = (self.xy_factor, self.xz_factor, self.yz_factor)
            return
        name = params.get("REMOVE")
        if name is not None:
            self.skew_profiles.pop(name, None)

    def cmd_GET_CURRENT_SKEW(self, cmd: Command) -> None:
        """Reports the factors: no time, no change."""

    def cmd_CALC_MEASURED_SKEW(self, cmd: Command) -> None:
        """Reports a factor: no time, no change."""
