"""Mirrors klippy/extras/gcode_move.py at Klipper commit 84104bbbd (GNU GPLv3).

Owns the G-code coordinate state and turns G0/G1 into toolhead moves: absolute and relative
modes (G90/G91, M82/M83), G92 and SET_GCODE_OFFSET origins, M220/M221 factors, saved
states (SAVE_GCODE_STATE/RESTORE_GCODE_STATE), and the position bookkeeping after homing,
an extruder change or a command error. Every unit conversion of a move happens here: F is
mm/min, speeds reach the toolhead in mm/s.

`plain_move` is `cmd_G1` for a line the fast parser (`gcode.parse_plain_move_*`) already
read: the same arithmetic in the same order, run for nearly every line of a file. Where
this file differs from upstream for speed: the G-code position is four float attributes
(`last_x` ... `last_e`), which the `last_position` property gives as upstream's list.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Final, Protocol

from kestimator.errors import CommandError
from kestimator.gcode import Command, command_params, get_float, get_int
from kestimator.toolhead import ToolHead

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

# Klipper's default G-code speed: 25 mm/s.
DEFAULT_SPEED_V: Final = 25.0
MM_PER_MIN_TO_MM_PER_S: Final = 1.0 / 60.0
PERCENT: Final = 100.0
_AXES: Final = (("X", 0), ("Y", 1), ("Z", 2), ("E", 3))
# Parameters a G0/G1 may carry (G is the command letter itself).
_MOVE_PARAMS: Final = frozenset("XYZEFG")

# warn(message, key): warnings with the same key are reported once, with a count.
WarnFn = Callable[[str, "str | None"], None]
SavedState = dict[str, object]


class MoveTransform(Protocol):
    """What upstream's `set_move_transform` takes (bed_mesh, skew_correction): a move to a
    G-code position (x, y, z, e) and the G-code position of the toolhead's; `tag` is the
    source line every toolhead move carries."""

    def move(self, newpos: list[float], speed: float, tag: int) -> None: ...

    def get_position(self) -> list[float]: ...


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ToolHeadTransform:
    """The toolhead as the last transform of the chain (upstream passes the toolhead)."""

    def __init__(self, toolhead: ToolHead) -> None:
        self.toolhead = toolhead

    def move(self, newpos: list[float], speed: float, tag: int) -> None:
        """toolhead.move"""
        self.toolhead.move_to(newpos[0], newpos[1], newpos[2], newpos[3], speed, tag)

    def get_position(self) -> list[float]:
        """toolhead.get_position"""
        return list(self.toolhead.commanded_pos)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class GCodeMove:
    """The G-code position and modes, and the moves they make."""

    def __init__(self, toolhead: ToolHead, warn: WarnFn) -> None:
        self.toolhead = toolhead
        self.warn = warn
        self.absolute_coord = True
        self.absolute_extrude = True
        self.base_position = [0.0, 0.0, 0.0, 0.0]
        # Upstream's last_position list, one float per axis (the last_position property
        # gives the list): plain_move sets three or four of them on nearly every line,
        # which the compiled build stores unboxed, where a list boxes each float.
        self.last_x = self.last_y = self.last_z = self.last_e = 0.0
        self.homing_position = [0.0, 0.0, 0.0, 0.0]
        self.speed = DEFAULT_SPEED_V
        self.speed_factor = MM_PER_MIN_TO_MM_PER_S
        self.extrude_factor = 1.0
        self.saved_states: dict[str, SavedState] = {}
        # The source line of the command being run (every move carries it).
        self.tag = 0
        # What the file told us about itself.
        self.extrude_mode_set = False
        self.moved_e_before_mode = False
        # bed_mesh / skew_correction / exclude_object (upstream's move_transform); None
        # moves the toolhead.
        self.move_transform: MoveTransform | None = None

    @property
    def last_position(self) -> list[float]:
        """Upstream's last_position (x, y, z, e), as a new list: assign one to change it."""
        return [self.last_x, self.last_y, self.last_z, self.last_e]

    @last_position.setter
    def last_position(self, pos: list[float]) -> None:
        self.last_x, self.last_y, self.last_z, self.last_e = pos[0], pos[1], pos[2], pos[3]

    def set_move_transform(self, transform: MoveTransform,
                           force: bool = False) -> MoveTransform:
        """Route every move through `transform`; returns the transform it replaces (the
        toolhead first), which `transform` passes its moves on to."""
        if self.move_transform is not None and not force:
            raise CommandError("G-Code move transform already specified")
        old_transform = self.move_transform
        if old_transform is None:
            old_transform = ToolHeadTransform(self.toolhead)
        # The toolhead given back (exclude_object's unregister) is no transform: moves go
        # to it directly again, the fast way.
        self.move_transform = None if isinstance(transform, ToolHeadTransform) else transform
        return old_transform

    def _handle_activate_extruder(self) -> None:
        """ACTIVATE_EXTRUDER: the new extruder's E position, no extrusion factor."""
        self.reset_last_position()
        self.extrude_factor = 1.0
        self.base_position[3] = self.last_e

    def _handle_home_rails_end(self, homed_axes: str) -> None:
        """After homing: the G-code offsets of the homed axes ("xyz" letters) are reset."""
        self.reset_last_position()
        for axis in ("xyz".index(a) for a in homed_axes):
            self.base_position[axis] = self.homing_position[axis]

    def reset_last_position(self) -> None:
        """After an error or a jump, the G-code position is the toolhead's again."""
        transform = self.move_transform
        if transform is None:
            self.last_position = list(self.toolhead.commanded_pos)
        else:
            self.last_position = transform.get_position()

    # G-Code movement commands
    def cmd_G1(self, cmd: Command) -> None:
        """G0/G1: a straight move; positions in mm, F in mm/min."""
        params = cmd.params
        last_position = self.last_position
        try:
            for axis, pos in _AXES:
                raw = params.get(axis)
                if raw is None:
                    continue
                try:
                    v = float(raw)
                except ValueError:
                    raise CommandError("Unable to parse move '%s'" % cmd.code) from None
                if not math.isfinite(v):
                    raise CommandError("Unable to parse move '%s'" % cmd.code)
                absolute_coord = self.absolute_coord
                if pos == 3:
                    v *= self.extrude_factor
                    if not self.absolute_extrude:
                        absolute_coord = False
                    if not self.extrude_mode_set:
                        self.moved_e_before_mode = True
                if not absolute_coord:
                    last_position[pos] += v
                else:
                    last_position[pos] = v + self.base_position[pos]
        finally:  # upstream's list changes axis by axis, kept when a later one fails
            self.last_position = last_position
        raw_f = params.get("F")
        if raw_f is not None:
            try:
                gcode_speed = float(raw_f)
            except ValueError:
                raise CommandError("Unable to parse move '%s'" % cmd.code) from None
            if not gcode_speed > 0.0 or math.isinf(gcode_speed):
                raise CommandError("Invalid speed in '%s'" % cmd.code)
            self.speed = gcode_speed * self.speed_factor
        for key in params:
            if key not in _MOVE_PARAMS:
                self.warn("Klipper ignores parameter %s in '%s'" % (key, cmd.code.strip()),
                          "move-param:" + key)
        self.move_with_speed(self.speed)

    def plain_move(self, x: float, y: float, z: float, e: float, f: float) -> None:
        """G0/G1 from already parsed, valid values (`gcode.parse_plain_move_scan` or `_regex`).

        The same arithmetic as `cmd_G1`, in the same order, without the text handling. A
        parameter the line does not give is `gcode.ABSENT` (NaN, so `v == v` is "given").
        """
        # The new position is kept in locals as it is set, so the toolhead gets it without
        # reading the attributes back.
        base = self.base_position
        if self.absolute_coord:
            if x == x:
                self.last_x = px = x + base[0]
            else:
                px = self.last_x
            if y == y:
                self.last_y = py = y + base[1]
            else:
                py = self.last_y
            if z == z:
                self.last_z = pz = z + base[2]
            else:
                pz = self.last_z
        else:
            # Upstream's `last_position[pos] += v`: the same float addition.
            px, py, pz = self.last_x, self.last_y, self.last_z
            if x == x:
                self.last_x = px = px + x
            if y == y:
                self.last_y = py = py + y
            if z == z:
                self.last_z = pz = pz + z
        if e == e:
            e *= self.extrude_factor
            if self.absolute_coord and self.absolute_extrude:
                self.last_e = pe = e + base[3]
            else:
                self.last_e = pe = self.last_e + e
            if not self.extrude_mode_set:
                self.moved_e_before_mode = True
        else:
            pe = self.last_e
        if f == f:
            self.speed = f * self.speed_factor
        transform = self.move_transform
        if transform is None:
            self.toolhead.move_to(px, py, pz, pe, self.speed, self.tag)
        else:
            transform.move([px, py, pz, pe], self.speed, self.tag)

    def move_with_speed(self, speed: float) -> None:
        """Move to last_position at `speed` (mm/s): upstream's `move_with_transform`."""
        transform = self.move_transform
        if transform is None:
            self.toolhead.move_to(self.last_x, self.last_y, self.last_z, self.last_e, speed,
                                  self.tag)
        else:
            transform.move(self.last_position, speed, self.tag)

    # G-Code coordinate manipulation
    def cmd_G20(self, cmd: Command) -> None:
        """G20 (inches): Klipper refuses it."""
        raise CommandError("Machine does not support G20 (inches) command")

    def cmd_M82(self, cmd: Command) -> None:
        """Absolute extrusion."""
        self.absolute_extrude = True
        self.extrude_mode_set = True

    def cmd_M83(self, cmd: Command) -> None:
        """Relative extrusion."""
        self.absolute_extrude = False
        self.extrude_mode_set = True

    def cmd_G90(self, cmd: Command) -> None:
        """Absolute coordinates (E too, unless M83 made it relative)."""
        self.absolute_coord = True

    def cmd_G91(self, cmd: Command) -> None:
        """Relative coordinates, E included."""
        self.absolute_coord = False

    def cmd_G92(self, cmd: Command) -> None:
        """Set the G-code position without moving."""
        offsets = [get_float(cmd.params, a) for a in "XYZE"]
        last_position = self.last_position
        for i, offset in enumerate(offsets):
            if offset is not None:
                if i == 3:
                    offset *= self.extrude_factor
                self.base_position[i] = last_position[i] - offset
        if offsets == [None, None, None, None]:
            self.base_position[:4] = last_position[:4]

    def cmd_M220(self, cmd: Command) -> None:
        """Speed factor override in percent."""
        value = get_float(cmd.params, "S", PERCENT, above=0.0) / (60.0 * PERCENT)
        self.speed = (self.speed / self.speed_factor) * value
        self.speed_factor = value

    def cmd_M221(self, cmd: Command) -> None:
        """Extrusion factor override in percent."""
        new_extrude_factor = get_float(cmd.params, "S", PERCENT, above=0.0) / PERCENT
        last_e_pos = self.last_e
        e_value = (last_e_pos - self.base_position[3]) / self.extrude_factor
        self.base_position[3] = last_e_pos - e_value * new_extrude_factor
        self.extrude_factor = new_extrude_factor

    def cmd_SET_GCODE_OFFSET(self, cmd: Command) -> None:
        """Shift the G-code origin; MOVE=1 moves by the change."""
        params = command_params(cmd)
        move_delta = [0.0, 0.0, 0.0, 0.0]
        for pos, axis in enumerate("XYZE"):
            offset = get_float(params, axis)
            if offset is None:
                offset = get_float(params, axis + "_ADJUST")
                if offset is None:
                    continue
                offset += self.homing_position[pos]
            delta = offset - self.homing_position[pos]
            move_delta[pos] = delta
            self.base_position[pos] += delta
            self.homing_position[pos] = offset
        # Move the toolhead the given offset if requested
        if get_int(params, "MOVE"):
            speed = get_float(params, "MOVE_SPEED", self.speed, above=0.0)
            last_position = self.last_position
            for pos, delta in enumerate(move_delta):
                last_position[pos] += delta
            self.last_position = last_position
            self.move_with_speed(speed)

    def save_state(self) -> SavedState:
        """The coordinate state, as SAVE_GCODE_STATE keeps it."""
        return {
            "absolute_coord": self.absolute_coord,
            "absolute_extrude": self.absolute_extrude,
            "base_position": list(self.base_position),
            "last_position": self.last_position,
            "homing_position": list(self.homing_position),
            "speed": self.speed, "speed_factor": self.speed_factor,
            "extrude_factor": self.extrude_factor,
        }

    def restore_state(self, state: SavedState) -> None:
        """RESTORE_GCODE_STATE without MOVE: the modes, origins and factors of `state`,
        the E origin shifted so that E does not jump."""
        self.absolute_coord = bool(state["absolute_coord"])
        self.absolute_extrude = bool(state["absolute_extrude"])
        self.base_position[:4] = list(state["base_position"])[:4]  # type: ignore[call-overload]
        self.homing_position = list(state["homing_position"])  # type: ignore[call-overload]
        self.speed = float(state["speed"])  # type: ignore[arg-type]
        self.speed_factor = float(state["speed_factor"])  # type: ignore[arg-type]
        self.extrude_factor = float(state["extrude_factor"])  # type: ignore[arg-type]
        # Restore the relative E position
        saved_last = state["last_position"]
        e_diff = self.last_e - saved_last[3]  # type: ignore[index]
        self.base_position[3] += e_diff

    def cmd_SAVE_GCODE_STATE(self, cmd: Command) -> None:
        """Remember the coordinate state under NAME."""
        name = command_params(cmd).get("NAME", "default")
        self.saved_states[name] = self.save_state()

    def cmd_RESTORE_GCODE_STATE(self, cmd: Command) -> None:
        """Bring back a saved coordinate state; MOVE=1 returns to its XYZ."""
        params = command_params(cmd)
        state = self.saved_states.get(params.get("NAME", "default"))
        if state is None:
            raise CommandError("Unknown g-code state: %s" % params.get("NAME", "default"))
        self.restore_state(state)
        # Move the toolhead back if requested
        if get_int(params, "MOVE"):
            speed = get_float(params, "MOVE_SPEED", self.speed, above=0.0)
            last_position = self.last_position
            last_position[:3] = list(state["last_position"])[:3]  # type: ignore[call-overload]
            self.last_position = last_position
            self.move_with_speed(speed)
