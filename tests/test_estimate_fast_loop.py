"""`Timeline.feed_lines` (the hot loop) gives exactly what `Timeline.feed` gives.

`feed` runs each line through the interpreter and toolhead methods; `feed_lines` writes
the plain-move path out in one loop with the G-code state in locals. Every field of the
estimate must be identical: totals and layer times to the bit, samples, marks, features,
filament, warnings. Checked on real corpus files, on files with every command that
changes the G-code state between moves, and on fuzzed command sequences.
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Iterable
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import Estimate, Timeline
from kestimator.limits import Limits

from .conftest import CORPUS_CFG, corpus_files

MAX_FILE_BYTES = 3_000_000
MARKS = (";TIME_ELAPSED:",)


def run(lines: Iterable[bytes], limits: Limits, fast: bool) -> Estimate:
    timeline = Timeline(limits, "x.gcode", homing_time=1.5, heat_time=2.0, sample=True,
                        mark_prefixes=MARKS)
    if fast:
        timeline.feed_lines(lines)
    else:
        for raw in lines:
            timeline.feed(raw)
    return timeline.finish()


def assert_identical(a: Estimate, b: Estimate) -> None:
    da, db = dataclasses.asdict(a), dataclasses.asdict(b)
    for key in da:
        assert da[key] == db[key], key
    # == treats 0.0 and -0.0 alike and arrays compare by value: compare the bits too.
    assert a.total_s.hex() == b.total_s.hex()
    assert [t.hex() for _, t in a.layers] == [t.hex() for _, t in b.layers]
    assert a.sample_times.tobytes() == b.sample_times.tobytes()


@pytest.fixture(scope="module")
def limits() -> Limits:
    return limits_from_printer_cfg(CORPUS_CFG)[0]


SMALL_FILES = [p for p in corpus_files() if p.stat().st_size <= MAX_FILE_BYTES]


@pytest.mark.parametrize("path", SMALL_FILES, ids=lambda p: p.parent.name + "/" + p.name)
def test_fast_loop_matches_line_by_line_on_corpus_file(path: Path, limits: Limits) -> None:
    data = path.read_bytes()
    slow = run(io.BytesIO(data), limits, fast=False)
    fast = run(io.BytesIO(data), limits, fast=True)
    assert fast.n_moves > 0
    assert_identical(fast, slow)


STATE_CHANGING_FILE = b"""\
;LAYER_CHANGE
G28
M83
G1 X10 Y10 Z0.2 F6000
G1 X20 Y10 E1.5 F1200
G91
G1 X5 Y5 E0.5
G1 X-5 Z0.1
G90
M82
G92 E0
G1 X30 Y30 E2 F3000
M221 S90
G1 X35 Y30 E3
M220 S150
G1 X40 Y30 E4
;TYPE:Perimeter
SET_GCODE_OFFSET Z=0.05 MOVE=1
G1 X45 Y35 E5
SAVE_GCODE_STATE NAME=a
G91
G1 X1 Y1
RESTORE_GCODE_STATE NAME=a MOVE=1
G1 X50 Y35 E6
M204 S500
G1 X60 Y35 E7
SET_VELOCITY_LIMIT VELOCITY=50 ACCEL=800 SQUARE_CORNER_VELOCITY=2 MINIMUM_CRUISE_RATIO=0.2
G1 X70 Y45 E8
G10
G1 X80 Y45
G11
G2 X90 Y45 I5 J0 E9
;TIME_ELAPSED:12.5
G1 X90 Y60 E9000
G1 E-30 F100
G4 P250
M400
G1 X1 Y1 E9001 F999999
;LAYER_CHANGE
G1 Z5 F600
G1 X100 Y100 Z10 E9002
SET_KINEMATIC_POSITION X=0 Y=0 Z=0
G1 X10 Y10
M109 S200
G92 X0 Y0
G1 X5 Y5 E9003
M84
G1 X1 Y1
"""


def test_fast_loop_matches_line_by_line_across_state_changes(limits: Limits) -> None:
    lines = STATE_CHANGING_FILE.splitlines(keepends=True)
    slow = run(lines, limits, fast=False)
    fast = run(lines, limits, fast=True)
    assert fast.n_moves > 20
    assert fast.warnings  # the E9000 move exceeds max_extrude_cross_section
    assert_identical(fast, slow)


_MOVE = st.builds(
    lambda g, x, y, z, e, f: "G%d%s%s%s%s%s" % (
        g, x and " X%s" % x, y and " Y%s" % y, z and " Z%s" % z, e and " E%s" % e,
        f and " F%s" % f),
    st.sampled_from([0, 1]),
    *[st.one_of(st.just(""), st.decimals(-200, 200, places=3).map(str))] * 4,
    st.one_of(st.just(""), st.sampled_from(["60", "1200", "9000", "0", "-5", "1e9"])))
_OTHER = st.sampled_from([
    "G90", "G91", "M82", "M83", "G92 E0", "G92 X1", "M221 S80", "M220 S120", "G10", "G11",
    "M204 S700", "SET_VELOCITY_LIMIT VELOCITY=40", "G4 P10", "M400", "G28 X", ";TYPE:Skirt",
    ";LAYER_CHANGE", "SAVE_GCODE_STATE", "RESTORE_GCODE_STATE MOVE=1", "g1 x3 y4",
    "G1 X1 Y2 ; comment", "G1 F1500 X3 Y3 E0.1", "G2 X5 Y5 I1 J1", "M84", ";TIME_ELAPSED:1"])
_PROGRAM = st.lists(st.one_of(_MOVE, _MOVE, _OTHER), min_size=1, max_size=60)


@settings(max_examples=150, derandomize=True, deadline=None, database=None)
@given(_PROGRAM)
def test_fast_loop_matches_line_by_line_on_fuzzed_programs(program: list[str]) -> None:
    limits = limits_from_printer_cfg(CORPUS_CFG)[0]
    lines = [(line + "\n").encode() for line in program]
    try:
        slow = run(lines, limits, fast=False)
    except ArithmeticError:
        with pytest.raises(ArithmeticError):
            run(lines, limits, fast=True)
        return
    assert_identical(run(lines, limits, fast=True), slow)


def test_command_cache_changes_nothing_and_stays_bounded(limits: Limits,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from kestimator import estimate

    program = []
    for i in range(3000):
        program += ["M204 S%d" % (500 + i % 2500), "G1 X%d Y%d F6000" % (i % 50, i % 7), "G10",
                    "G1 X%d" % (i % 13), "G11", "SET_VELOCITY_LIMIT ACCEL=%d" % (1000 + i)]
    lines = [(line + "\n").encode() for line in program]
    timeline = Timeline(limits, "x.gcode", sample=True)
    timeline.feed_lines(lines)
    cached = timeline.finish()
    assert 0 < len(timeline._commands) <= estimate.MAX_CACHED_COMMANDS
    monkeypatch.setattr(estimate, "MAX_CACHED_COMMAND_CHARS", -1)  # no line is cached
    timeline = Timeline(limits, "x.gcode", sample=True)
    timeline.feed_lines(lines)
    assert not timeline._commands
    assert_identical(timeline.finish(), cached)
