"""Mirrors klippy/extras/bed_mesh.py at Klipper commit 84104bbbd (GNU GPLv3).

The part of bed_mesh that changes a print's time: with a mesh loaded, every G-code move goes
through `BedMesh.move` (upstream's gcode_move move transform), which adds the mesh's Z
(faded out between fade_start and fade_end) and splits an XY move wherever the Z offset
changes by split_delta_z, looking every move_check_distance mm (`MoveSplitter`). The mesh is
a saved profile ([bed_mesh NAME] in printer.cfg or its SAVE_CONFIG block) built into a
`ZMesh` with upstream's interpolation (lagrange, bicubic, direct) and read by bilinear
interpolation. Commands: BED_MESH_PROFILE (LOAD/SAVE/REMOVE), BED_MESH_CLEAR,
BED_MESH_OFFSET. Probing (BED_MESH_CALIBRATE) is not modelled: it measures the bed; the
command clears the mesh, as upstream does first, and says so in a warning.

Re-implemented, not copied; the arithmetic is upstream's, in its order, so that the moves
the toolhead gets are bit-identical to Klipper's.
"""

from __future__ import annotations

import math
from typing import Final

from kestimator.config.machine import MachineConfig, Section
from kestimator.errors import CommandError, KestimatorError
from kestimator.gcode import Command, command_params, get_float
from kestimator.gcode_move import GCodeMove, MoveTransform, WarnFn

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

PROFILE_VERSION: Final = 1
# A saved profile's mesh parameters and their types (upstream's PROFILE_OPTIONS).
_INT_OPTIONS: Final = ("x_count", "y_count", "mesh_x_pps", "mesh_y_pps")
_FLOAT_OPTIONS: Final = ("min_x", "max_x", "min_y", "max_y", "tension")
# upstream: the int 0x7FFFFFFF (exact as a float; only compared with heights)
FADE_DISABLE: Final = 2147483647.0
# A move longer than this many move_check_distance steps is refused: Klipper's splitter
# would step along it for hours (a 1e200 mm move never ends), stalling the printer.
MAX_SPLIT_CHECKS: Final = 1e7


class BedMeshError(Exception):
    """A mesh that cannot be built."""


def isclose(a: float, b: float, rel_tol: float = 1e-09, abs_tol: float = 0.0) -> bool:
    """PEP 485 isclose, as upstream writes it."""
    return abs(a - b) <= max(rel_tol * max(abs(a), abs(b)), abs_tol)


def constrain_float(val: float, min_val: float, max_val: float) -> float:
    """Constrain a value between min and max."""
    return min(max_val, max(min_val, val))


def constrain_int(val: int, min_val: int, max_val: int) -> int:
    """Constrain an index between min and max."""
    return min(max_val, max(min_val, val))


def lerp(t: float, v0: float, v1: float) -> float:
    """Linear interpolation between two values."""
    return (1. - t) * v0 + t * v1


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class MeshParams:
    """A profile's mesh parameters (upstream's mesh_params dict)."""

    def __init__(self, min_x: float, max_x: float, min_y: float, max_y: float,
                 x_count: int, y_count: int, mesh_x_pps: int, mesh_y_pps: int,
                 algo: str, tension: float) -> None:
        self.min_x = min_x
        self.max_x = max_x
        self.min_y = min_y
        self.max_y = max_y
        self.x_count = x_count
        self.y_count = y_count
        self.mesh_x_pps = mesh_x_pps
        self.mesh_y_pps = mesh_y_pps
        self.algo = algo
        self.tension = tension


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Profile:
    """A stored profile: the probed points (rows of Y, each a row of X) and parameters."""

    def __init__(self, points: list[list[float]], params: MeshParams) -> None:
        self.points = points
        self.params = params


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class MoveSplitter:
    """Splits a move where the mesh's Z offset changes (upstream's MoveSplitter)."""

    def __init__(self, split_delta_z: float, move_check_distance: float) -> None:
        self.split_delta_z = split_delta_z
        self.move_check_distance = move_check_distance
        self.z_mesh: ZMesh | None = None
        self.fade_offset = 0.
        self.prev_pos: list[float] = [0., 0., 0., 0.]
        self.next_pos: list[float] = [0., 0., 0., 0.]
        self.current_pos: list[float] = [0., 0., 0., 0.]
        self.z_factor = 1.
        self.z_offset = 0.
        self.traverse_complete = True
        self.distance_checked = 0.
        self.total_move_length = 0.
        self.axis_move: list[bool] = [False, False, False, False]

    def initialize(self, mesh: ZMesh | None, fade_offset: float) -> None:
        """A new mesh (or none) and its fade target."""
        self.z_mesh = mesh
        self.fade_offset = fade_offset

    def build_move(self, prev_pos: list[float], next_pos: list[float],
                   factor: float) -> None:
        """Start splitting the move prev_pos -> next_pos."""
        self.prev_pos = list(prev_pos)
        self.next_pos = list(next_pos)
        self.current_pos = list(prev_pos)
        self.z_factor = factor
        self.z_offset = self._calc_z_offset(prev_pos)
        self.traverse_complete = False
        self.distance_checked = 0.
        axes_d = [self.next_pos[i] - self.prev_pos[i] for i in range(len(self.next_pos))]
        # upstream: sqrt(sum([d*d for d in axes_d[:3]])), summed from 0 in that order
        self.total_move_length = math.sqrt(
            axes_d[0] * axes_d[0] + axes_d[1] * axes_d[1] + axes_d[2] * axes_d[2])
        self.axis_move = [not isclose(d, 0., abs_tol=1e-10) for d in axes_d]
        if not self.total_move_length / self.move_check_distance <= MAX_SPLIT_CHECKS:
            self.traverse_complete = True
            raise CommandError("bed_mesh: a move of %.3f mm is too long to split (Klipper "
                               "would check it every %g mm for hours)"
                               % (self.total_move_length, self.move_check_distance))

    def _calc_z_offset(self, pos: list[float]) -> float:
        z_mesh = self.z_mesh
        assert z_mesh is not None
        z = z_mesh.calc_z(pos[0], pos[1])
        offset = self.fade_offset
        return self.z_factor * (z - offset) + offset

    def _set_next_move(self, distance_from_prev: float) -> None:
        t = distance_from_prev / self.total_move_length
        if t > 1. or t < 0.:
            raise CommandError("bed_mesh: Slice distance is negative "
                               "or greater than entire move length")
        for i in range(len(self.next_pos)):
            if self.axis_move[i]:
                self.current_pos[i] = lerp(t, self.prev_pos[i], self.next_pos[i])

    def split(self) -> list[float] | None:
        """The next piece of the move (its end with the Z offset), None once done."""
        if self.traverse_complete:
            return None
        if self.axis_move[0] or self.axis_move[1]:
            # X and/or Y axis move, traverse if necessary
            while self.distance_checked + self.move_check_distance < self.total_move_length:
                self.distance_checked += self.move_check_distance
                self._set_next_move(self.distance_checked)
                next_z = self._calc_z_offset(self.current_pos)
                if abs(next_z - self.z_offset) >= self.split_delta_z:
                    self.z_offset = next_z
                    newpos = list(self.current_pos)
                    newpos[2] += self.z_offset
                    return newpos
        # end of move reached
        self.current_pos[:] = self.next_pos
        self.z_offset = self._calc_z_offset(self.current_pos)
        self.current_pos[2] += self.z_offset
        self.traverse_complete = True
        return self.current_pos


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ZMesh:
    """A mesh built from probed points (upstream's ZMesh)."""

    def __init__(self, params: MeshParams, name: str) -> None:
        self.profile_name = name
        self.probed_matrix: list[list[float]] | None = None
        self.mesh_matrix: list[list[float]] | None = None
        self.mesh_params = params
        self.mesh_offsets: list[float] = [0., 0.]
        self.mesh_x_min = params.min_x
        self.mesh_x_max = params.max_x
        self.mesh_y_min = params.min_y
        self.mesh_y_max = params.max_y
        # Number of points to interpolate per segment
        mesh_x_pps = params.mesh_x_pps
        mesh_y_pps = params.mesh_y_pps
        px_cnt = params.x_count
        py_cnt = params.y_count
        self.mesh_x_count = (px_cnt - 1) * mesh_x_pps + px_cnt
        self.mesh_y_count = (py_cnt - 1) * mesh_y_pps + py_cnt
        self.x_mult = mesh_x_pps + 1
        self.y_mult = mesh_y_pps + 1
        self.mesh_x_dist = (self.mesh_x_max - self.mesh_x_min) / (self.mesh_x_count - 1)
        self.mesh_y_dist = (self.mesh_y_max - self.mesh_y_min) / (self.mesh_y_count - 1)

    def build_mesh(self, z_matrix: list[list[float]]) -> None:
        """Interpolate the probed points into the mesh the moves read."""
        self.probed_matrix = z_matrix
        algo = self.mesh_params.algo
        if algo == "lagrange":
            self._sample_lagrange(z_matrix)
        elif algo == "bicubic":
            self._sample_bicubic(z_matrix)
        elif algo == "direct":
            self.mesh_matrix = z_matrix
        else:
            # upstream calls None: Klipper stops with an internal error
            raise BedMeshError("bed_mesh: unknown algorithm <%s>" % algo)

    def set_mesh_offsets(self, offsets: list[float | None]) -> None:
        """BED_MESH_OFFSET X/Y."""
        for i, o in enumerate(offsets):
            if o is not None:
                self.mesh_offsets[i] = o

    def get_x_coordinate(self, index: int) -> float:
        """X of a mesh column."""
        return self.mesh_x_min + self.mesh_x_dist * index

    def get_y_coordinate(self, index: int) -> float:
        """Y of a mesh row."""
        return self.mesh_y_min + self.mesh_y_dist * index

    def calc_z(self, x: float, y: float) -> float:
        """The mesh's Z at (x, y): bilinear in the mesh cell, the border outside."""
        tbl = self.mesh_matrix
        if tbl is None:
            # No mesh table generated, no z-adjustment
            return 0.
        tx, xidx = self._get_linear_index(x + self.mesh_offsets[0], 0)
        ty, yidx = self._get_linear_index(y + self.mesh_offsets[1], 1)
        z0 = lerp(tx, tbl[yidx][xidx], tbl[yidx][xidx + 1])
        z1 = lerp(tx, tbl[yidx + 1][xidx], tbl[yidx + 1][xidx + 1])
        return lerp(ty, z0, z1)

    def get_z_range(self) -> tuple[float, float]:
        """The lowest and highest Z of the mesh."""
        tbl = self.mesh_matrix
        if tbl is None:
            return 0., 0.
        return min([min(x) for x in tbl]), max([max(x) for x in tbl])

    def get_z_average(self) -> float:
        """The mesh's average Z rounded to 0.01 (the default fade target)."""
        tbl = self.mesh_matrix
        if tbl is None:
            return 0.
        total = 0.
        count = 0
        for row in tbl:
            # upstream: sum(sum(x) for rows) / count; sum() of a row starts from int 0
            row_sum = 0.
            for z in row:
                row_sum += z
            total += row_sum
            count += len(row)
        return round(total / count, 2)

    def _get_linear_index(self, coord: float, axis: int) -> tuple[float, int]:
        if axis == 0:
            mesh_min = self.mesh_x_min
            mesh_cnt = self.mesh_x_count
            mesh_dist = self.mesh_x_dist
        else:
            mesh_min = self.mesh_y_min
            mesh_cnt = self.mesh_y_count
            mesh_dist = self.mesh_y_dist
        idx = int(math.floor((coord - mesh_min) / mesh_dist))
        idx = constrain_int(idx, 0, mesh_cnt - 2)
        t = (coord - (mesh_min + mesh_dist * idx)) / mesh_dist
        return constrain_float(t, 0., 1.), idx

    def _sparse_matrix(self, z_matrix: list[list[float]]) -> list[list[float]]:
        x_mult = self.x_mult
        y_mult = self.y_mult
        return [[0. if ((i % x_mult) or (j % y_mult)) else z_matrix[j // y_mult][i // x_mult]
                 for i in range(self.mesh_x_count)]
                for j in range(self.mesh_y_count)]

    def _sample_lagrange(self, z_matrix: list[list[float]]) -> None:
        x_mult = self.x_mult
        y_mult = self.y_mult
        matrix = self._sparse_matrix(z_matrix)
        self.mesh_matrix = matrix
        xpts: list[float] = []
        ypts: list[float] = []
        for i in range(self.mesh_params.x_count):
            xpts.append(self.get_x_coordinate(i * x_mult))
        for j in range(self.mesh_params.y_count):
            ypts.append(self.get_y_coordinate(j * y_mult))
        # Interpolate X coordinates (only the rows that have probed points)
        for i in range(self.mesh_y_count):
            if i % y_mult != 0:
                continue
            for j in range(self.mesh_x_count):
                if j % x_mult == 0:
                    continue
                x = self.get_x_coordinate(j)
                matrix[i][j] = self._calc_lagrange(matrix, xpts, x, i, 0)
        # Interpolate Y coordinates
        for i in range(self.mesh_x_count):
            for j in range(self.mesh_y_count):
                if j % y_mult == 0:
                    continue
                y = self.get_y_coordinate(j)
                matrix[j][i] = self._calc_lagrange(matrix, ypts, y, i, 1)

    def _calc_lagrange(self, matrix: list[list[float]], lpts: list[float], c: float,
                       vec: int, axis: int) -> float:
        pt_cnt = len(lpts)
        total = 0.
        for i in range(pt_cnt):
            n = 1.
            d = 1.
            for j in range(pt_cnt):
                if j == i:
                    continue
                n *= (c - lpts[j])
                d *= (lpts[i] - lpts[j])
            if axis == 0:
                z = matrix[vec][i * self.x_mult]
            else:
                z = matrix[i * self.y_mult][vec]
            total += z * n / d
        return total

    def _sample_bicubic(self, z_matrix: list[list[float]]) -> None:
        # should work for any number of probe points above 3x3
        x_mult = self.x_mult
        y_mult = self.y_mult
        c = self.mesh_params.tension
        matrix = self._sparse_matrix(z_matrix)
        self.mesh_matrix = matrix
        # Interpolate X values
        for y in range(self.mesh_y_count):
            if y % y_mult != 0:
                continue
            for x in range(self.mesh_x_count):
                if x % x_mult == 0:
                    continue
                matrix[y][x] = self._cardinal_spline(self._get_x_ctl_pts(matrix, x, y), c)
        # Interpolate Y values
        for x in range(self.mesh_x_count):
            for y in range(self.mesh_y_count):
                if y % y_mult == 0:
                    continue
                matrix[y][x] = self._cardinal_spline(self._get_y_ctl_pts(matrix, x, y), c)

    def _get_x_ctl_pts(self, matrix: list[list[float]], x: int,
                       y: int) -> tuple[float, float, float, float, float]:
        x_mult = self.x_mult
        x_row = matrix[y]
        last_pt = self.mesh_x_count - 1 - x_mult
        if x < x_mult:
            p0 = p1 = x_row[0]
            p2 = x_row[x_mult]
            p3 = x_row[2 * x_mult]
            t = x / float(x_mult)
        elif x > last_pt:
            p0 = x_row[last_pt - x_mult]
            p1 = x_row[last_pt]
            p2 = p3 = x_row[last_pt + x_mult]
            t = (x - last_pt) / float(x_mult)
        else:
            for i in range(x_mult, last_pt, x_mult):
                if i < x < i + x_mult:
                    p0 = x_row[i - x_mult]
                    p1 = x_row[i]
                    p2 = x_row[i + x_mult]
                    p3 = x_row[i + 2 * x_mult]
                    t = (x - i) / float(x_mult)
                    break
            else:
                raise BedMeshError("bed_mesh: Error finding x control points")
        return p0, p1, p2, p3, t

    def _get_y_ctl_pts(self, matrix: list[list[float]], x: int,
                       y: int) -> tuple[float, float, float, float, float]:
        y_mult = self.y_mult
        last_pt = self.mesh_y_count - 1 - y_mult
        if y < y_mult:
            p0 = p1 = matrix[0][x]
            p2 = matrix[y_mult][x]
            p3 = matrix[2 * y_mult][x]
            t = y / float(y_mult)
        elif y > last_pt:
            p0 = matrix[last_pt - y_mult][x]
            p1 = matrix[last_pt][x]
            p2 = p3 = matrix[last_pt + y_mult][x]
            t = (y - last_pt) / float(y_mult)
        else:
            for i in range(y_mult, last_pt, y_mult):
                if i < y < i + y_mult:
                    p0 = matrix[i - y_mult][x]
                    p1 = matrix[i][x]
                    p2 = matrix[i + y_mult][x]
                    p3 = matrix[i + 2 * y_mult][x]
                    t = (y - i) / float(y_mult)
                    break
            else:
                raise BedMeshError("bed_mesh: Error finding y control points")
        return p0, p1, p2, p3, t

    @staticmethod
    def _cardinal_spline(p: tuple[float, float, float, float, float],
                         tension: float) -> float:
        t = p[4]
        t2 = t * t
        t3 = t2 * t
        m1 = tension * (p[2] - p[0])
        m2 = tension * (p[3] - p[1])
        a = p[1] * (2 * t3 - 3 * t2 + 1)
        b = p[2] * (-2 * t3 + 3 * t2)
        c = m1 * (t3 - 2 * t2 + t)
        d = m2 * (t3 - t2)
        return a + b + c + d


def _parse_points(text: str) -> list[list[float]]:
    """configfile's getlists(seps=(',', '\\n'), parser=float) on a profile's points (rows
    of Moonraker's settings come as "a:b, c:d"... are handled as rows too)."""
    if ":" in text and "\n" not in text:
        rows = [row.split(":") for row in text.split(",")]
    else:
        rows = [row.split(",") for row in text.split("\n")]
    points = []
    for row in rows:
        values = [float(v.strip()) for v in row if v.strip()]
        if values:
            points.append(values)
    return points


def _read_profile(section: Section) -> Profile | None:
    """A [bed_mesh NAME] section as upstream's ProfileManager reads it (None: another
    version of the profile format, which Klipper skips)."""
    if section.getint("version", 0) != PROFILE_VERSION:
        return None
    text = section.get("points")
    try:
        points = _parse_points(text or "")
    except ValueError:
        source = section.source("points") or ""
        path, _, line = source.rpartition(":")
        raise KestimatorError("[%s] option 'points' is not a list of numbers"
                              % section.get_name(), path or None,
                              int(line) if line.isdigit() else None) from None
    ints = [section.getint(key) for key in _INT_OPTIONS]
    floats = [section.getfloat(key) for key in _FLOAT_OPTIONS]
    params = MeshParams(floats[0], floats[1], floats[2], floats[3], ints[0], ints[1],
                        ints[2], ints[3], section.get("algo") or "", floats[4])
    return Profile(points, params)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class BedMesh:
    """[bed_mesh]: the move transform and its commands (upstream's BedMesh, with its
    ProfileManager's profiles)."""

    def __init__(self, config: MachineConfig, gcode_move: GCodeMove, warn: WarnFn) -> None:
        section = config.getsection("bed_mesh")
        self.gcode_move = gcode_move
        self.warn = warn
        self.last_position: list[float] = [0., 0., 0., 0.]
        self.z_mesh: ZMesh | None = None
        self.fade_start = section.getfloat("fade_start", 1.)
        self.fade_end = section.getfloat("fade_end", 0.)
        self.fade_dist = self.fade_end - self.fade_start
        if self.fade_dist <= 0.:
            self.fade_start = self.fade_end = FADE_DISABLE
        target = section.get("fade_target", None)
        self.base_fade_target: float | None = (
            None if target is None else section.getfloat("fade_target"))
        self.fade_target = 0.
        self.tool_offset = 0.
        self.splitter = MoveSplitter(
            section.getfloat("split_delta_z", .025, minval=0.01),
            section.getfloat("move_check_distance", 5., minval=3.))
        self.profiles: dict[str, Profile] = {}
        for profile_section in config.get_prefix_sections("bed_mesh"):
            name = profile_section.get_name()
            if name == "bed_mesh" or " " not in name:
                continue
            profile = _read_profile(profile_section)
            if profile is not None:
                self.profiles[name.split(" ", 1)[1]] = profile
        self.next_transform: MoveTransform = gcode_move.set_move_transform(self)
        # Whether the file loaded a mesh at all (else a start macro may have: said).
        self.ever_loaded = False

    def set_mesh(self, mesh: ZMesh | None) -> None:
        """Use `mesh` (None: no mesh) from the next move on."""
        if mesh is not None:
            self.ever_loaded = True
        if mesh is not None and self.fade_end != FADE_DISABLE:
            base = self.base_fade_target
            if base is None:
                self.fade_target = mesh.get_z_average()
            else:
                self.fade_target = base
                min_z, max_z = mesh.get_z_range()
                if not min_z <= self.fade_target <= max_z and self.fade_target != 0.:
                    # fade target is non-zero, out of mesh range
                    err_target = self.fade_target
                    self.z_mesh = None
                    self.fade_target = 0.
                    raise CommandError(
                        "bed_mesh: ERROR, fade_target lies outside of mesh z "
                        "range\nmin: %.4f, max: %.4f, fade_target: %.4f"
                        % (min_z, max_z, err_target))
            min_z, max_z = mesh.get_z_range()
            if self.fade_dist <= max(abs(min_z), abs(max_z)):
                self.z_mesh = None
                self.fade_target = 0.
                raise CommandError(
                    "bed_mesh:  Mesh extends outside of the fade range, "
                    "please see the fade_start and fade_end options in"
                    "example-extras.cfg. fade distance: %.2f mesh min: %.4f"
                    "mesh max: %.4f" % (self.fade_dist, min_z, max_z))
        else:
            self.fade_target = 0.
        self.tool_offset = 0.
        self.z_mesh = mesh
        self.splitter.initialize(mesh, self.fade_target)
        # cache the current position before a transform takes place
        self.gcode_move.reset_last_position()

    def get_z_factor(self, z_pos: float) -> float:
        """How much of the mesh applies at G-code height z_pos (the fade)."""
        z_pos += self.tool_offset
        if z_pos >= self.fade_end:
            return 0.
        elif z_pos >= self.fade_start:
            return (self.fade_end - z_pos) / self.fade_dist
        else:
            return 1.

    def get_position(self) -> list[float]:
        """The G-code position of the toolhead's (its Z without the mesh's offset)."""
        cur_pos = self.next_transform.get_position()
        z_mesh = self.z_mesh
        if z_mesh is None:
            # No mesh calibrated, so send toolhead position
            self.last_position[:] = cur_pos
            self.last_position[2] -= self.fade_target
        else:
            # return current position minus the current z-adjustment
            x = cur_pos[0]
            y = cur_pos[1]
            z = cur_pos[2]
            max_adj = z_mesh.calc_z(x, y)
            factor = 1.
            z_adj = max_adj - self.fade_target
            fade_z_pos = z + self.tool_offset
            if min(fade_z_pos, (fade_z_pos - max_adj)) >= self.fade_end:
                # Fade out is complete, no factor
                factor = 0.
            elif max(fade_z_pos, (fade_z_pos - max_adj)) >= self.fade_start:
                # Likely in the process of fading out adjustment: the factor from the
                # toolhead position, as upstream solves it
                factor = ((self.fade_end + self.fade_target - fade_z_pos)
                          / (self.fade_dist - z_adj))
                factor = constrain_float(factor, 0., 1.)
            final_z_adj = factor * z_adj + self.fade_target
            self.last_position[:] = [x, y, z - final_z_adj] + cur_pos[3:]
        return list(self.last_position)

    def move(self, newpos: list[float], speed: float, tag: int) -> None:
        """A G-code move: to the toolhead with the mesh's Z, split where it changes."""
        factor = self.get_z_factor(newpos[2])
        if self.z_mesh is None or not factor:
            # No mesh calibrated, or mesh leveling phased out.
            self.next_transform.move(
                [newpos[0], newpos[1], newpos[2] + self.fade_target] + newpos[3:], speed, tag)
        else:
            splitter = self.splitter
            splitter.build_move(self.last_position, newpos, factor)
            while not splitter.traverse_complete:
                split_move = splitter.split()
                if split_move:
                    self.next_transform.move(split_move, speed, tag)
                else:
                    raise CommandError("Mesh Leveling: Error splitting move ")
        self.last_position[:] = newpos

    # Commands
    def cmd_BED_MESH_CLEAR(self, cmd: Command) -> None:
        """No mesh from now on."""
        self.set_mesh(None)

    def cmd_BED_MESH_OFFSET(self, cmd: Command) -> None:
        """Shift where the mesh is read (X, Y) and the height the fade sees (ZFADE)."""
        z_mesh = self.z_mesh
        if z_mesh is None:
            return
        params = command_params(cmd)
        z_mesh.set_mesh_offsets([get_float(params, "X"), get_float(params, "Y")])
        tool_offset = get_float(params, "ZFADE")
        if tool_offset is not None:
            self.tool_offset = tool_offset
        self.gcode_move.reset_last_position()

    def cmd_BED_MESH_CALIBRATE(self, cmd: Command) -> None:
        """Probing: upstream first clears the mesh, then probes and loads what it measured,
        which the file cannot tell. The mesh is cleared; the warning says the rest."""
        self.set_mesh(None)
        self.warn("BED_MESH_CALIBRATE probes the bed: the probing time and the mesh it "
                  "measures are unknown (0 s, and later moves are timed without a mesh; a "
                  "mesh splits moves and changes Klipper's time by up to a few tenths of a "
                  "second)", "bed_mesh_calibrate")

    def cmd_BED_MESH_PROFILE(self, cmd: Command) -> None:
        """LOAD, SAVE or REMOVE a profile (the first of these the command gives)."""
        params = command_params(cmd)
        for key in ("LOAD", "SAVE", "REMOVE"):
            name = params.get(key)
            if name is None:
                continue
            if not name.strip():
                raise CommandError("Value for parameter '%s' must be specified" % key)
            if key == "LOAD":
                self.load_profile(name)
            elif key == "SAVE":
                if name != "default":
                    self.save_profile(name)
            else:
                self.profiles.pop(name, None)
            return

    def load_profile(self, prof_name: str) -> None:
        """BED_MESH_PROFILE LOAD=prof_name."""
        profile = self.profiles.get(prof_name)
        if profile is None:
            raise CommandError("bed_mesh: Unknown profile [%s]" % prof_name)
        z_mesh = ZMesh(profile.params, prof_name)
        try:
            z_mesh.build_mesh(profile.points)
        except (BedMeshError, IndexError, ZeroDivisionError) as e:
            raise CommandError(str(e)) from None
        self.set_mesh(z_mesh)

    def save_profile(self, prof_name: str) -> None:
        """BED_MESH_PROFILE SAVE=prof_name: the loaded mesh under that name."""
        z_mesh = self.z_mesh
        if z_mesh is None or z_mesh.probed_matrix is None:
            return
        # upstream saves the probed points rounded to 6 decimals
        points = [[round(z, 6) for z in row] for row in z_mesh.probed_matrix]
        self.profiles = dict(self.profiles)
        self.profiles[prof_name] = Profile(points, z_mesh.mesh_params)
