"""Mirrors klippy/extras/gcode_arcs.py at Klipper commit 84104bbbd (GNU GPLv3).

Owns G2/G3 arcs and their plane (G17/G18/G19), present when the printer's config has
[gcode_arcs]: each arc becomes `max(1, floor(length / resolution))` straight G1 segments
with E split evenly, as upstream's `planArc` cuts it.
"""

from __future__ import annotations

import math
from typing import Final

from kestimator.errors import CommandError
from kestimator.gcode import ABSENT, Command, get_float
from kestimator.gcode_move import GCodeMove

try:  # mypyc reads the decorator by this name (kestimator/mypyc_attr.py says why)
    from mypy_extensions import mypyc_attr
except ImportError:
    from kestimator.mypyc_attr import mypyc_attr  # type: ignore[assignment]

# Coordinates of the arc's plane: the plane's two axes and the helical one.
ARC_PLANE_X_Y, ARC_PLANE_X_Z, ARC_PLANE_Y_Z = 0, 1, 2
# An arc that would need more segments than this (100 m at 1 mm resolution) is refused.
MAX_ARC_SEGMENTS: Final = 100_000


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ArcSupport:
    """G2/G3 (and the plane commands) of [gcode_arcs]."""

    def __init__(self, gcode_move: GCodeMove, resolution: float) -> None:
        self.gcode_move = gcode_move
        self.mm_per_arc_segment = resolution
        self.plane = ARC_PLANE_X_Y

    def cmd_G2(self, cmd: Command) -> None:
        """Clockwise arc."""
        self._cmd_inner(cmd, True)

    def cmd_G3(self, cmd: Command) -> None:
        """Counter-clockwise arc."""
        self._cmd_inner(cmd, False)

    def cmd_G17(self, cmd: Command) -> None:
        """Arcs in the XY plane."""
        self.plane = ARC_PLANE_X_Y

    def cmd_G18(self, cmd: Command) -> None:
        """Arcs in the XZ plane."""
        self.plane = ARC_PLANE_X_Z

    def cmd_G19(self, cmd: Command) -> None:
        """Arcs in the YZ plane."""
        self.plane = ARC_PLANE_Y_Z

    def _cmd_inner(self, cmd: Command, clockwise: bool) -> None:
        gcode_move = self.gcode_move
        if not gcode_move.absolute_coord:
            raise CommandError("G2/G3 does not support relative move mode")
        params = cmd.params
        current = [lp - bp for lp, bp in zip(gcode_move.last_position,
                                             gcode_move.base_position)]
        current[3] /= gcode_move.extrude_factor
        target = [get_float(params, "X", current[0]), get_float(params, "Y", current[1]),
                  get_float(params, "Z", current[2])]
        if get_float(params, "R") is not None:
            raise CommandError("G2/G3 does not support R moves")
        # Determine plane coordinates and the helical axis
        i_off = get_float(params, "I", 0.0)
        j_off = get_float(params, "J", 0.0)
        planar = (i_off, j_off)
        axes = (0, 1, 2)
        if self.plane == ARC_PLANE_X_Z:
            planar = (i_off, get_float(params, "K", 0.0))
            axes = (0, 2, 1)
        elif self.plane == ARC_PLANE_Y_Z:
            planar = (j_off, get_float(params, "K", 0.0))
            axes = (1, 2, 0)
        if not (planar[0] or planar[1]):
            raise CommandError("G2/G3 requires IJ, IK or JK parameters")
        as_e = get_float(params, "E")
        as_f = get_float(params, "F")
        self.planArc(current, target, planar, clockwise, as_e, as_f, *axes)

    def planArc(self, currentPos: list[float], targetPos: list[float],
                offset: tuple[float, float], clockwise: bool, as_e: float | None,
                as_f: float | None, alpha_axis: int, beta_axis: int,
                helical_axis: int) -> None:
        """Cut the arc into segments and move along them (upstream's name and order)."""
        current = currentPos
        target = targetPos
        r_p = -offset[0]
        r_q = -offset[1]
        # Radius vector from center to current location
        center_p = current[alpha_axis] - r_p
        center_q = current[beta_axis] - r_q
        rt_alpha = target[alpha_axis] - center_p
        rt_beta = target[beta_axis] - center_q
        angular_travel = math.atan2(r_p * rt_beta - r_q * rt_alpha,
                                    r_p * rt_alpha + r_q * rt_beta)
        if angular_travel < 0.0:
            angular_travel += 2.0 * math.pi
        if clockwise:
            angular_travel -= 2.0 * math.pi
        if (angular_travel == 0.0
                and current[alpha_axis] == target[alpha_axis]
                and current[beta_axis] == target[beta_axis]):
            # Make a circle if the angular rotation is 0 and the target is current pos
            angular_travel = 2.0 * math.pi
        # Determine number of segments
        linear_travel = target[helical_axis] - current[helical_axis]
        radius = math.hypot(r_p, r_q)
        flat_mm = radius * angular_travel
        if linear_travel:
            mm_of_travel = math.hypot(flat_mm, linear_travel)
        else:
            mm_of_travel = math.fabs(flat_mm)
        if not mm_of_travel / self.mm_per_arc_segment <= MAX_ARC_SEGMENTS:
            # Klipper would grind through millions of segments; no real arc has them.
            raise CommandError("arc of %.6g mm would be split into more than %d segments"
                               % (mm_of_travel, MAX_ARC_SEGMENTS))
        segments = max(1.0, math.floor(mm_of_travel / self.mm_per_arc_segment))
        # Generate coordinates
        theta_per_segment = angular_travel / segments
        linear_per_segment = linear_travel / segments
        absolute_extrude = self.gcode_move.absolute_extrude
        e_per_move = e_base = 0.0
        if as_e is not None:
            if absolute_extrude:
                e_base = current[3]
            e_per_move = (as_e - e_base) / segments
        for i in range(1, int(segments) + 1):
            dist_helical = i * linear_per_segment
            c_theta = i * theta_per_segment
            cos_ti = math.cos(c_theta)
            sin_ti = math.sin(c_theta)
            r_p = -offset[0] * cos_ti + offset[1] * sin_ti
            r_q = -offset[0] * sin_ti - offset[1] * cos_ti
            c = [0.0, 0.0, 0.0]
            c[alpha_axis] = center_p + r_p
            c[beta_axis] = center_q + r_q
            c[helical_axis] = current[helical_axis] + dist_helical
            if i == segments:
                c = target  # type: ignore[assignment]
            seg_e: float | None = None
            if e_per_move:
                seg_e = e_base + e_per_move
                if absolute_extrude:
                    e_base += e_per_move
            self._g1(c[0], c[1], c[2], seg_e, as_f)

    def _g1(self, x: float, y: float, z: float, e: float | None, f: float | None) -> None:
        """The G1 upstream builds for a segment, run by gcode_move (values, not text)."""
        if f is not None and not f > 0.0:
            raise CommandError("Invalid speed in arc (F%s)" % f)
        self.gcode_move.plain_move(x, y, z, ABSENT if e is None else e,
                                   ABSENT if f is None else f)
