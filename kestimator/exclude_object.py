"""Mirrors klippy/extras/exclude_object.py at Klipper commit 84104bbbd (GNU GPLv3).

[exclude_object]: EXCLUDE_OBJECT_DEFINE, EXCLUDE_OBJECT_START/END label the objects of a
file; EXCLUDE_OBJECT NAME=... (or CURRENT=1) cancels one. The first exclusion puts a move
transform in front of GCodeMove's chain (forced, so ahead of bed_mesh and skew_correction);
from then on a move inside an excluded object is never sent to the toolhead (it takes no
time) and the moves after it are shifted by the offsets the skipped moves built up, as
upstream does (`_ignore_move`, `_move_from_excluded_region` with its extruder adjustment,
the Z and XY offsets cleared on the first move away from where the skipped object ended).
Until the transform has seen `initial_extrusion_moves` (5) moves that change E, moves inside
an excluded object are still sent. EXCLUDE_OBJECT_DEFINE RESET=1 forgets every object and
takes the transform out again (`_unregister_transform`).

Not modelled: the tuning_tower check (upstream loads no transform while TUNING_TOWER is
active; kestimator does not model TUNING_TOWER at all); the object polygons are parsed (a
malformed one is an error, as upstream's json.loads) but not kept. Replies
(`respond_info`) take no time and are not kept.

Re-implemented, not copied; the arithmetic is upstream's, in its order.
"""

from __future__ import annotations

import json

from kestimator.errors import CommandError, ParamError
from kestimator.gcode import Command, command_params
from kestimator.gcode_move import GCodeMove, MoveTransform

# Moves that change E the transform lets through after it is loaded, whatever the object.
INITIAL_EXTRUSION_MOVES = 5


class ExcludeObject:
    """The objects of a print, the excluded ones, and the transform that skips them."""

    def __init__(self, gcode_move: GCodeMove) -> None:
        self.gcode_move = gcode_move
        self.toolhead = gcode_move.toolhead
        self.next_transform: MoveTransform | None = None
        self.last_position_extruded = [0., 0., 0., 0.]
        self.last_position_excluded = [0., 0., 0., 0.]
        # Set when the transform is registered (upstream sets them there only).
        self.extrusion_offsets: dict[str, list[float]] = {}
        self.max_position_extruded = 0.
        self.max_position_excluded = 0.
        self.extruder_adj = 0.
        self.initial_extrusion_moves = INITIAL_EXTRUSION_MOVES
        self.last_position = [0., 0., 0., 0.]
        self.last_speed = 0.
        self.was_excluded_at_start = False
        # Every name an EXCLUDE_OBJECT_DEFINE or EXCLUDE_OBJECT_START gave (upper case).
        self.objects: set[str] = set()
        self.excluded_objects: set[str] = set()
        self.current_object: str | None = None
        self.in_excluded_region = False
        self._reset_state()

    def _register_transform(self) -> None:
        if self.next_transform is None:
            next_transform = self.gcode_move.set_move_transform(self, force=True)
            self.next_transform = next_transform
            self.extrusion_offsets = {}
            self.max_position_extruded = 0.
            self.max_position_excluded = 0.
            self.extruder_adj = 0.
            self.initial_extrusion_moves = INITIAL_EXTRUSION_MOVES
            self.last_position = [0., 0., 0., 0.]

            self.get_position()
            self.last_position_extruded[:] = self.last_position
            self.last_position_excluded[:] = self.last_position

    def _unregister_transform(self) -> None:
        if self.next_transform is not None:
            self.gcode_move.set_move_transform(self.next_transform, force=True)
            self.next_transform = None
            self.gcode_move.reset_last_position()

    def _reset_state(self) -> None:
        self.objects = set()
        self.excluded_objects = set()
        self.current_object = None
        self.in_excluded_region = False

    def _reset_file(self) -> None:
        self._reset_state()
        self._unregister_transform()

    def _get_extrusion_offsets(self, num_coord: int) -> list[float]:
        ename = self.toolhead.get_extruder().name
        offset = self.extrusion_offsets.get(ename)
        if offset is None:
            offset = [0.] * num_coord
            self.extrusion_offsets[ename] = offset
        if len(offset) < num_coord:
            offset.extend([0.] * (num_coord - len(offset)))
        return offset

    def get_position(self) -> list[float]:
        """The G-code position: the next transform's plus the offsets skipped moves made."""
        assert self.next_transform is not None
        pos = self.next_transform.get_position()
        offset = self._get_extrusion_offsets(len(pos))
        for i in range(len(pos)):
            self.last_position[i] = pos[i] + offset[i]
        return list(self.last_position)

    def _normal_move(self, newpos: list[float], speed: float, tag: int) -> None:
        offset = self._get_extrusion_offsets(len(newpos))

        if self.initial_extrusion_moves > 0 and self.last_position[3] != newpos[3]:
            # The transform is loaded only at the first exclusion: it lets a few
            # extrusions through to learn the extruder's state.
            self.initial_extrusion_moves -= 1

        self.last_position[:] = newpos
        self.last_position_extruded[:] = self.last_position
        self.max_position_extruded = max(self.max_position_extruded, newpos[3])

        # Just after an excluded object the toolhead is where the last printed object
        # ended and the G-code where the excluded one did: the first Z and E moves take the
        # offsets back, the first XY move whatever remains.
        last_excluded = self.last_position_excluded
        if (offset[0] != 0 or offset[1] != 0) and \
                (newpos[0] != last_excluded[0] or newpos[1] != last_excluded[1]):
            for i in range(len(newpos)):
                if i != 3:
                    offset[i] = 0
            offset[3] += self.extruder_adj
            self.extruder_adj = 0

        if offset[2] != 0 and newpos[2] != last_excluded[2]:
            offset[2] = 0

        if self.extruder_adj != 0 and newpos[3] != last_excluded[3]:
            offset[3] += self.extruder_adj
            self.extruder_adj = 0

        tx_pos = newpos[:]
        for i in range(len(newpos)):
            tx_pos[i] = newpos[i] - offset[i]
        assert self.next_transform is not None
        self.next_transform.move(tx_pos, speed, tag)

    def _ignore_move(self, newpos: list[float], speed: float, tag: int) -> None:
        offset = self._get_extrusion_offsets(len(newpos))
        for i in range(len(newpos)):
            if i != 3:
                offset[i] = newpos[i] - self.last_position_extruded[i]
        offset[3] = offset[3] + newpos[3] - self.last_position[3]
        self.last_position[:] = newpos
        self.last_position_excluded[:] = self.last_position
        self.max_position_excluded = max(self.max_position_excluded, newpos[3])

    def _move_into_excluded_region(self, newpos: list[float], speed: float, tag: int) -> None:
        self.in_excluded_region = True
        self._ignore_move(newpos, speed, tag)

    def _move_from_excluded_region(self, newpos: list[float], speed: float, tag: int) -> None:
        self.in_excluded_region = False

        # Makes up for a different retraction of the last object printed and the
        # excluded one.
        self.extruder_adj = self.max_position_excluded \
            - self.last_position_excluded[3] \
            - (self.max_position_extruded - self.last_position_extruded[3])
        self._normal_move(newpos, speed, tag)

    def _test_in_excluded_region(self) -> bool:
        # Inside a cancelled object
        return self.current_object in self.excluded_objects \
            and self.initial_extrusion_moves == 0

    def move(self, newpos: list[float], speed: float, tag: int) -> None:
        """A G-code move: skipped inside an excluded object, else shifted and passed on."""
        move_in_excluded_region = self._test_in_excluded_region()
        self.last_speed = speed

        if move_in_excluded_region:
            if self.in_excluded_region:
                self._ignore_move(newpos, speed, tag)
            else:
                self._move_into_excluded_region(newpos, speed, tag)
        else:
            if self.in_excluded_region:
                self._move_from_excluded_region(newpos, speed, tag)
            else:
                self._normal_move(newpos, speed, tag)

    def cmd_EXCLUDE_OBJECT_START(self, cmd: Command) -> None:
        """The moves that follow belong to object NAME."""
        params = command_params(cmd)
        if "NAME" not in params:
            raise ParamError("missing NAME")
        name = params["NAME"].upper()
        if name not in self.objects:
            self._add_object_definition(name)
        self.current_object = name
        self.was_excluded_at_start = self._test_in_excluded_region()

    def cmd_EXCLUDE_OBJECT_END(self, cmd: Command) -> None:
        """The moves that follow belong to no object (a wrong NAME is only reported)."""
        command_params(cmd)  # Klipper parses the parameters before running the command
        if self.current_object is None and self.next_transform is not None:
            return  # "EXCLUDE_OBJECT_END called, but no object is currently active"
        self.current_object = None

    def cmd_EXCLUDE_OBJECT(self, cmd: Command) -> None:
        """NAME=: exclude it; CURRENT=1: the current object; RESET=1: un-exclude NAME (or
        every object); nothing: list the excluded ones. As upstream, any non-empty value of
        RESET or CURRENT counts (RESET=0 too)."""
        params = command_params(cmd)
        reset = params.get("RESET")
        current = params.get("CURRENT")
        name = params.get("NAME", "").upper()

        if reset:
            if name:
                self._unexclude_object(name)
            else:
                self.excluded_objects = set()
        elif name:
            if name not in self.excluded_objects:
                self._exclude_object(name)
        elif current:
            if not self.current_object:
                raise CommandError("There is no current object to cancel")
            self._exclude_object(self.current_object)

    def cmd_EXCLUDE_OBJECT_DEFINE(self, cmd: Command) -> None:
        """NAME= (with CENTER= and POLYGON=): an object; RESET=1: forget every object and
        take the transform out."""
        params = command_params(cmd)
        reset = params.get("RESET")
        name = params.get("NAME", "").upper()

        if reset:
            self._reset_file()
        elif name:
            center = params.get("CENTER")
            polygon = params.get("POLYGON")
            try:
                if center is not None:
                    json.loads("[%s]" % center)
                if polygon is not None:
                    json.loads(polygon)
            except ValueError as exc:
                # Upstream's json.loads raises: Klipper's "Internal error on command".
                raise CommandError('Internal error on command:"EXCLUDE_OBJECT_DEFINE" (%s)'
                                   % exc) from None
            self._add_object_definition(name)

    def _add_object_definition(self, name: str) -> None:
        self.objects.add(name)

    def _exclude_object(self, name: str) -> None:
        self._register_transform()
        self.excluded_objects.add(name)

    def _unexclude_object(self, name: str) -> None:
        self.excluded_objects.discard(name)
