"""Where the time goes: each planned move's time summed per feature and per object.

Owns the labels a file puts on its moves (features from `;TYPE:` / `; FEATURE:` comments,
objects from EXCLUDE_OBJECT_START/END, M486 and `; printing object` comments) and the time
summed under each. Time is summed per segment, one per (feature, object) pair seen, so the
move loop pays one addition per move whatever is tracked. A label applies from its line
on: moves are tagged with their line, and a change waits until the planner has flushed
every move before it. Time with the head at rest (dwells, flush delays, homing) goes to
the segment of the last move before it.
"""

from __future__ import annotations

import re
from array import array
from collections import deque
from typing import Final

from kestimator.gcode import Command, extended_params
from kestimator.toolhead import ToolHead

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

# Commands that say which object the following moves belong to.
OBJECT_COMMANDS = frozenset(("EXCLUDE_OBJECT_DEFINE", "EXCLUDE_OBJECT_START",
                             "EXCLUDE_OBJECT_END", "M486"))
# M486's A parameter: the current object's name, to the end of the code.
_M486_LABEL_RE = re.compile(r"^\s*M486\b.*?\sA(\S.*)$", re.IGNORECASE)
# Feature name for moves before the first feature marker.
NO_FEATURE: Final = "(none)"
# Object name for moves outside every labelled object (start, travel between objects, end).
NO_OBJECT: Final = "(no object)"
# Per-object time still to come at each layer marker (`Segments.remaining`): at most this
# many layers are kept (when full, every other one is dropped and only every 2nd, 4th, ...
# marker is kept from then on), each with the first this many objects (in the order they
# first print): at most 2048 * 256 floats.
MAX_REMAINING_LAYERS: Final = 2048
MAX_REMAINING_OBJECTS: Final = 256
# `; printing object NAME` / `; stop printing object NAME` (PrusaSlicer, SuperSlicer, Orca).
OBJECT_COMMENT: Final = ";printing object"
OBJECT_STOP_COMMENT: Final = ";stop printing object"


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Segments:
    """Time per (feature, object) segment, as the planner releases moves."""

    def __init__(self, toolhead: ToolHead) -> None:
        self.toolhead = toolhead
        self.feature_names: list[str] = [NO_FEATURE]
        self.feature_ids: dict[str, int] = {NO_FEATURE: 0}
        # Objects by key (EXCLUDE_OBJECT NAME, M486 id or comment label) and their names.
        self.object_keys: list[str] = [NO_OBJECT]
        self.object_ids: dict[str, int] = {NO_OBJECT: 0}
        self.object_names: dict[str, str] = {}
        # Comment labels count until a command labels objects (EXCLUDE_OBJECT_*, M486):
        # then Klipper's own labels win and the comments are ignored.
        self.object_commands = False
        self.queued_object = 0
        self.queued_feature = 0
        self.segments: list[tuple[int, int]] = [(0, 0)]
        self.segment_ids: dict[tuple[int, int], int] = {(0, 0): 0}
        self.segment_time: list[float] = [0.0]
        # Segment changes (line, segment id) waiting until the planner has flushed every
        # move before them; a negative id -1-i is layer marker i's snapshot (`snapshot`).
        self.changes: deque[tuple[int, int]] = deque()
        # Each kept layer marker's index and every object's time before it (by object id):
        # snapshot i is snapshot_times[snapshot_ends[i - 1]:snapshot_ends[i]] (0 for i = 0).
        # Flat arrays, not a list per layer: a checkpoint (kestimator.resume) pickles them
        # as three blocks of bytes, where 600 lists of floats were half its objects.
        self.snapshot_layers = array("q")
        self.snapshot_ends = array("q")
        self.snapshot_times = array("d")
        self._snapshot_stride = 1
        # The segment of the moves being timed, and of the last line read.
        self.segment = 0
        self.queued_segment = 0
        # Where the time already given to a segment ends.
        self.counted_until = 0.0

    def rest_until(self, t: float) -> None:
        """The head was at rest until `t`: that time goes to the current segment."""
        if t > self.counted_until:
            self.segment_time[self.segment] += t - self.counted_until
            self.counted_until = t

    def set_feature(self, name: str, lineno: int) -> None:
        """Moves from line `lineno` on are of feature `name`."""
        fid = self.feature_ids.get(name)
        if fid is None:
            fid = self.feature_ids[name] = len(self.feature_names)
            self.feature_names.append(name)
        self.queued_feature = fid
        self._set_segment(lineno)

    def set_object(self, key: str | None, lineno: int) -> None:
        """Moves from line `lineno` on belong to object `key` (None: to no object)."""
        if key is None:
            oid = 0
        else:
            found = self.object_ids.get(key)
            if found is None:
                found = self.object_ids[key] = len(self.object_keys)
                self.object_keys.append(key)
            oid = found
        if oid != self.queued_object:
            self.queued_object = oid
            self._set_segment(lineno)

    def _set_segment(self, lineno: int) -> None:
        key = (self.queued_feature, self.queued_object)
        sid = self.segment_ids.get(key)
        if sid is None:
            sid = self.segment_ids[key] = len(self.segments)
            self.segments.append(key)
            self.segment_time.append(0.0)
        toolhead = self.toolhead
        if toolhead.lookahead.is_empty():
            # Every move so far has been timed: rest until now belongs to the old segment.
            self.rest_until(toolhead.print_time)
            self.flush_snapshots()
            self.changes.clear()
            self.segment = sid
        else:
            self.changes.append((lineno, sid))
        self.queued_segment = sid

    def layer_marker(self, index: int, lineno: int) -> None:
        """Layer marker number `index` is on line `lineno`: each object's time so far is
        taken when the first move from that line on is timed (`snapshot`)."""
        if index % self._snapshot_stride:
            return
        if self.toolhead.lookahead.is_empty():
            self.rest_until(self.toolhead.print_time)
            self.snapshot(index)
        else:
            self.changes.append((lineno, -1 - index))

    def snapshot(self, index: int) -> None:
        """Keep each object's time so far for layer marker `index`."""
        if index % self._snapshot_stride:
            return
        if len(self.snapshot_layers) >= MAX_REMAINING_LAYERS:
            self._drop_every_other_snapshot()
            self._snapshot_stride *= 2
            if index % self._snapshot_stride:
                return
        times = [0.0] * min(len(self.object_keys), MAX_REMAINING_OBJECTS)
        n = len(times)
        segment_time = self.segment_time
        for sid, (_fid, oid) in enumerate(self.segments):
            if oid < n:
                times[oid] += segment_time[sid]
        self.snapshot_layers.append(index)
        self.snapshot_times.extend(array("d", times))
        self.snapshot_ends.append(len(self.snapshot_times))

    def _drop_every_other_snapshot(self) -> None:
        """Keep snapshots 0, 2, 4, ..."""
        ends, times = self.snapshot_ends, self.snapshot_times
        kept_ends = array("q")
        kept_times = array("d")
        for i in range(0, len(ends), 2):
            kept_times.extend(times[ends[i - 1] if i else 0:ends[i]])
            kept_ends.append(len(kept_times))
        del self.snapshot_layers[1::2]
        self.snapshot_ends = kept_ends
        self.snapshot_times = kept_times

    def flush_snapshots(self) -> None:
        """Take the snapshots still waiting for a move (the head is at rest)."""
        changes = self.changes
        if any(sid < 0 for _, sid in changes):
            kept = [change for change in changes if change[1] >= 0]
            for change in changes:
                if change[1] < 0:
                    self.snapshot(-1 - change[1])
            changes.clear()
            changes.extend(kept)

    def object_command(self, cmd: Command, lineno: int) -> None:
        """EXCLUDE_OBJECT_START/END or M486: the object the following moves belong to."""
        self.object_commands = True
        name = cmd.name
        if name == "M486":
            if "S" in cmd.params:
                try:
                    index = int(float(cmd.params["S"]))
                except ValueError:
                    return
                self.set_object(None if index < 0 else "M486 S%d" % index, lineno)
            found = _M486_LABEL_RE.search(cmd.code)
            label = found.group(1).strip() if found else ""
            if label and self.queued_object:
                self.object_names[self.object_keys[self.queued_object]] = label
            return
        if name == "EXCLUDE_OBJECT_END":
            self.set_object(None, lineno)
            return
        if name == "EXCLUDE_OBJECT_START":
            try:
                params = extended_params(cmd.code)
            except ValueError:
                return  # Klipper rejects the line; the interpreter says so
            object_name = params.get("NAME", "").strip().upper()
            if object_name:
                self.set_object(object_name, lineno)
                self.object_names.setdefault(object_name, params["NAME"].strip())

    def object_comment(self, text: str, lineno: int) -> bool:
        """`; printing object NAME` / `; stop printing object NAME`: True if it was one."""
        body = ";" + text.lstrip(";").strip()
        if body.startswith(OBJECT_STOP_COMMENT):
            if not self.object_commands:
                self.set_object(None, lineno)
            return True
        if body.startswith(OBJECT_COMMENT):
            label = body[len(OBJECT_COMMENT):].strip()
            if label and not self.object_commands:
                self.set_object("; " + label, lineno)
                self.object_names.setdefault("; " + label, label)
            return True
        return False

    def scale(self, factor: float) -> None:
        """Every segment's time grows by `factor` (a learned motion correction)."""
        self.segment_time = [t * factor for t in self.segment_time]
        self.snapshot_times = array("d", [t * factor for t in self.snapshot_times])

    def remaining(self, layers: list[tuple[int, float]]) -> list[
            tuple[int, float, dict[str, float]]]:
        """(line, t, object name -> seconds from that layer marker to the end) for each kept
        layer marker (`layers`: every marker's line and time), from the per-object snapshots
        (time at rest before a layer's first move counts as before it). Empty when no
        object is labelled."""
        if len(self.object_keys) <= 1:
            return []
        totals = [0.0] * len(self.object_keys)
        for sid, (_fid, oid) in enumerate(self.segments):
            totals[oid] += self.segment_time[sid]
        names = [self.object_names.get(key, key) for key in self.object_keys]
        result: list[tuple[int, float, dict[str, float]]] = []
        times = self.snapshot_times
        start = 0
        for index, end in zip(self.snapshot_layers, self.snapshot_ends):
            before, start = times[start:end], end
            if index >= len(layers):
                continue
            remaining: dict[str, float] = {}
            for oid in range(1, min(len(names), MAX_REMAINING_OBJECTS)):
                done = before[oid] if oid < len(before) else 0.0
                left = max(0.0, totals[oid] - done)
                remaining[names[oid]] = remaining.get(names[oid], 0.0) + left
            line, t = layers[index]
            result.append((line, t, remaining))
        return result

    def totals(self) -> tuple[dict[str, float], dict[str, float]]:
        """Seconds per feature and per object name (empty when no object is labelled)."""
        feature_time = [0.0] * len(self.feature_names)
        object_time = [0.0] * len(self.object_keys)
        for i, (fid, oid) in enumerate(self.segments):
            seconds = self.segment_time[i]
            feature_time[fid] += seconds
            object_time[oid] += seconds
        features = {name: feature_time[i] for i, name in enumerate(self.feature_names)
                    if feature_time[i] > 0.0 or name != NO_FEATURE}
        objects: dict[str, float] = {}
        if len(self.object_keys) > 1:
            for i, key in enumerate(self.object_keys):
                name = self.object_names.get(key, key)
                if object_time[i] > 0.0:
                    objects[name] = objects.get(name, 0.0) + object_time[i]
        return features, objects
