"""The toolhead's squares, bit for bit as upstream's `**`.

Upstream squares speeds with `v**2`, which CPython computes with C's pow(); its last bit
can differ from `v * v` (1 in about 1,200 random values with glibc). kestimator's toolhead
takes pow() only where the square can change a result (kestimator/toolhead.py,
POW2_BELOW), and keeps the last velocity's square for the next Move. These tests hold
Move.calc_junction, Move.limit_speed and Move.__init__ to upstream's formulas written
out with `**` (klippy/toolhead.py and kinematics/extruder.py at 84104bbbd), on random
moves and on limits placed within a few ulps of the square, where v * v and pow() part.
"""

from __future__ import annotations

import math
import random

from kestimator.limits import Limits
from kestimator.toolhead import Move, ToolHead


def _toolhead() -> ToolHead:
    return ToolHead(Limits(max_velocity=500.0, max_accel=5000.0))


def _move(toolhead: ToolHead, rng: random.Random, start: tuple[float, float, float, float],
          speed: float) -> Move:
    end = (start[0] + rng.uniform(-30.0, 30.0), start[1] + rng.uniform(-30.0, 30.0),
           start[2] + rng.choice((0.0, 0.0, 0.0, rng.uniform(-1.0, 1.0))),
           start[3] + rng.choice((0.0, rng.uniform(0.0, 3.0), rng.uniform(-2.0, 2.0))))
    return Move(toolhead, *start, *end, speed, 1)


def _upstream_start_v2(move: Move, prev: Move) -> tuple[float, float]:
    """Upstream's calc_junction (the extruder's calc_junction inlined), with `**`."""
    diff_r = move.axes_r_e - prev.axes_r_e
    ea_v2 = (move.instant_corner_v / abs(diff_r))**2 if diff_r else move.max_cruise_v2
    max_start_v2 = min([move.max_cruise_v2, prev.max_cruise_v2, prev.next_junction_v2,
                        prev.max_start_v2 + prev.delta_v2] + [ea_v2])
    axes_r, prev_axes_r = move.axes_r, prev.axes_r
    junction_cos_theta = -(axes_r[0] * prev_axes_r[0] + axes_r[1] * prev_axes_r[1]
                           + axes_r[2] * prev_axes_r[2])
    sin_theta_d2 = math.sqrt(max(0.5 * (1.0 - junction_cos_theta), 0.))
    cos_theta_d2 = math.sqrt(max(0.5 * (1.0 + junction_cos_theta), 0.))
    one_minus_sin_theta_d2 = 1. - sin_theta_d2
    if one_minus_sin_theta_d2 > 0. and cos_theta_d2 > 0.:
        R_jd = sin_theta_d2 / one_minus_sin_theta_d2
        move_jd_v2 = R_jd * move.junction_deviation * move.accel
        pmove_jd_v2 = R_jd * prev.junction_deviation * prev.accel
        quarter_tan_theta_d2 = .25 * sin_theta_d2 / cos_theta_d2
        move_centripetal_v2 = move.delta_v2 * quarter_tan_theta_d2
        pmove_centripetal_v2 = prev.delta_v2 * quarter_tan_theta_d2
        max_start_v2 = min(max_start_v2, move_jd_v2, pmove_jd_v2,
                           move_centripetal_v2, pmove_centripetal_v2)
    return max_start_v2, min(max_start_v2, prev.max_mcr_start_v2 + prev.mcr_delta_v2)


def _near(value: float, rng: random.Random) -> float:
    """`value` moved by a few ulps either way (where pow() and the product part)."""
    for _ in range(rng.randint(0, 4)):
        value = math.nextafter(value, math.inf if rng.random() < 0.5 else -math.inf)
    return value


def test_calc_junction_gives_upstreams_start_speed_bit_for_bit() -> None:
    rng = random.Random(37)
    toolhead = _toolhead()
    checked = near_limit = 0
    for _ in range(20000):
        prev = _move(toolhead, rng, (100.0, 100.0, 1.0, 0.0), rng.uniform(5.0, 400.0))
        move = _move(toolhead, rng, prev.end_pos, rng.uniform(5.0, 400.0))
        if not (move.is_kinematic_move and prev.is_kinematic_move):
            continue
        prev.max_start_v2 = rng.uniform(0.0, prev.max_cruise_v2)
        diff_r = move.axes_r_e - prev.axes_r_e
        if diff_r and rng.random() < 0.5:
            # The extruder's limit a few ulps from the other limits: only pow() decides.
            near_limit += 1
            target = _near(min(move.max_cruise_v2, prev.max_cruise_v2), rng)
            move.instant_corner_v = _near(math.sqrt(target) * abs(diff_r), rng)
            prev.max_start_v2 = prev.max_cruise_v2
            prev.junction_deviation = move.junction_deviation = 0.0
        expected = _upstream_start_v2(move, prev)
        move.calc_junction(prev)
        assert (move.max_start_v2, move.max_mcr_start_v2) == expected
        checked += 1
    assert checked > 10000 and near_limit > 3000


def test_limit_speed_lowers_the_cruise_speed_as_upstreams_square_does() -> None:
    rng = random.Random(38)
    toolhead = _toolhead()
    lowered = 0
    for _ in range(20000):
        move = _move(toolhead, rng, (100.0, 100.0, 1.0, 0.0), rng.uniform(5.0, 400.0))
        cruise_v2, min_move_t = move.max_cruise_v2, move.min_move_t
        if rng.random() < 0.5:
            speed = _near(math.sqrt(cruise_v2), rng)
        else:
            speed = rng.uniform(1.0, 500.0)
        move.limit_speed(speed, 1000.0)
        speed2 = speed**2
        if speed2 < cruise_v2:
            lowered += 1
            assert (move.max_cruise_v2, move.min_move_t) == (speed2, move.move_d / speed)
        else:
            assert (move.max_cruise_v2, move.min_move_t) == (cruise_v2, min_move_t)
    assert lowered > 5000


def test_a_moves_cruise_square_is_upstreams_whatever_the_speed_before() -> None:
    rng = random.Random(39)
    toolhead = _toolhead()
    position = (100.0, 100.0, 1.0, 0.0)
    speeds = [rng.uniform(1.0, 600.0) for _ in range(50)] + [120.0, 7200.0 / 60.0, 25.0]
    for _ in range(20000):
        speed = rng.choice(speeds) if rng.random() < 0.7 else rng.uniform(1.0, 600.0)
        move = _move(toolhead, rng, position, speed)
        velocity = min(speed, toolhead.max_velocity) if move.is_kinematic_move else speed
        assert move.max_cruise_v2 == velocity**2


def test_squares_that_overflow_raise_as_upstreams_do() -> None:
    toolhead = _toolhead()
    prev = Move(toolhead, 0.0, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0, 1.0, 100.0, 1)
    move = Move(toolhead, 10.0, 0.0, 0.0, 1.0, 20.0, 0.0, 0.0, 2.0, 100.0, 2)
    move.instant_corner_v = 1e200
    prev.axes_r_e, move.axes_r_e = 0.0, 0.5
    try:
        (move.instant_corner_v / abs(move.axes_r_e - prev.axes_r_e))**2
    except OverflowError as exc:
        upstream = type(exc)
    try:
        move.calc_junction(prev)
    except OverflowError as exc:
        ours = type(exc)
    assert ours is upstream is OverflowError
