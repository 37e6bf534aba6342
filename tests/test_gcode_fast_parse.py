"""The fast G0/G1 parsers agree with Klipper's line splitting wherever they accept a line.

`gcode.parse_plain_move_regex` (pure CPython) and `gcode.parse_plain_move_scan` (PyPy,
the compiled build) may
refuse any line (the general parser then takes it), but a line they accept must give
exactly, to the bit and the sign of zero, what `parse_line` and Klipper's float() give.
Both run here under CPython, on real corpus lines and on fuzzed move-like lines.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kestimator.gcode import (
    NOT_PLAIN,
    parse_line,
    parse_plain_move_regex,
    parse_plain_move_scan,
)

from .conftest import corpus_files

PARSERS = [parse_plain_move_regex, parse_plain_move_scan]
LINES_PER_FILE = 20000
# (X, Y, Z, E, F) with None for a parameter the line does not give.
Values = tuple["float | None", "float | None", "float | None", "float | None", "float | None"]


def read(parser: object, raw: bytes) -> Values | None:
    """What `parser` makes of `raw`, None for NOT_PLAIN and for ABSENT (NaN) parameters."""
    got = parser(raw)  # type: ignore[operator]
    if not got[0]:
        assert got is NOT_PLAIN or all(math.isnan(v) for v in got[1:]), got
        return None
    x, y, z, e, f = (None if math.isnan(v) else v for v in got[1:])
    return (x, y, z, e, f)


def klipper_values(raw: bytes) -> Values | None:
    """(X, Y, Z, E, F) as Klipper reads this line, or None if it is no plain valid move."""
    cmd = parse_line(raw.decode("utf-8", "replace").strip())
    if cmd.name not in ("G0", "G1") or set(cmd.params) - set("XYZEF"):
        return None
    values = []
    for key in "XYZEF":
        text = cmd.params.get(key)
        if text is None:
            values.append(None)
            continue
        try:
            value = float(text)
        except ValueError:
            return None
        if not math.isfinite(value):
            return None
        values.append(value)
    speed = values[4]
    if speed is not None and not speed > 0.0:
        return None
    return (values[0], values[1], values[2], values[3], values[4])


def same_bits(a: Values, b: Values) -> bool:
    return all((u is None and v is None)
               or (u is not None and v is not None and u == v
                   and math.copysign(1.0, u) == math.copysign(1.0, v))
               for u, v in zip(a, b))


def check(parser: object, raw: bytes) -> bool:
    """True if the parser accepted the line; fails the test if it got it wrong."""
    got = read(parser, raw)
    if got is None:
        return False
    want = klipper_values(raw)
    assert want is not None, "%s accepted %r, which Klipper does not read as a plain move" % (
        parser.__name__, raw)  # type: ignore[attr-defined]
    assert same_bits(got, want), (raw, got, want)
    return True


@pytest.mark.parametrize("parser", PARSERS, ids=lambda p: p.__name__)
def test_fast_parser_reads_corpus_move_lines_exactly_as_klipper(parser: object) -> None:
    accepted = moves = 0
    for path in corpus_files():
        with open(path, "rb") as f:
            for count, raw in enumerate(f):
                if count >= LINES_PER_FILE:
                    break
                if check(parser, raw):
                    accepted += 1
                if raw.startswith((b"G1 ", b"G0 ")):
                    moves += 1
    # The fast path must carry nearly all moves, or it is no fast path.
    assert accepted >= 0.95 * moves


def test_both_fast_parsers_take_slicer_parameter_orders() -> None:
    lines = [b"G1 X10.5 Y-2 Z.3 E0.12345 F1800\n",  # PrusaSlicer, Orca, Slic3r order
             b"G1 F1500 X10.5 Y-2 E0.12345\r\n",  # Cura, ideaMaker: F first
             b"G0 F9000 X1 Y2 Z0.2 ; travel\n"]
    for parser in PARSERS:
        for raw in lines:
            assert check(parser, raw), (parser.__name__, raw)


@pytest.mark.parametrize("raw", [
    b"G1 X1e3\n", b"G1 X1E3\n", b"G1 X1Y2\n", b"G1 X 1\n", b"G1 x1\n", b"g1 X1\n",
    b"G1\tX1\n", b"G1 X1_0\n", b"G1 F0 X1\n", b"G1 X1 F-5\n", b"G1 XINF\n", b"G1 X--1\n",
    b"G1 X1.2.3\n", b"N10 G1 X1*33\n", b"G1 X1 A2\n", b"G1 X1\rY2\n", b"G10 X1\n",
    b"G1 X" + b"9" * 400 + b"\n"])
def test_fast_parsers_leave_irregular_lines_to_the_general_parser(raw: bytes) -> None:
    for parser in PARSERS:
        assert read(parser, raw) is None, (parser.__name__, raw)


def test_repeated_parameter_keeps_the_last_as_klipper_does() -> None:
    for parser in PARSERS:
        assert read(parser, b"G1 F100 X1 F200\n") == (1.0, None, None, None, 200.0)
        assert read(parser, b"G1 F200 X1 F0\n") is None


def test_scanner_falls_back_to_float_for_long_mantissas() -> None:
    raw = b"G1 X1234567890.123456789\n"
    assert read(parse_plain_move_scan, raw) == (1234567890.123456789, None, None, None, None)


_NUMBERS = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64).map(repr),
    st.decimals(allow_nan=False, allow_infinity=False, places=6).map(str),
    st.text(alphabet="0123456789.+-eE_ ", min_size=0, max_size=12))
_WORDS = st.tuples(st.sampled_from("XYZEFxyzefAGN*; "), _NUMBERS).map("".join)
_LINES = st.tuples(
    st.sampled_from(["G1 ", "G0 ", "G1", "G1  ", "g1 ", "G01 "]),
    st.lists(_WORDS, max_size=6).map(" ".join),
    st.sampled_from(["\n", "\r\n", "", " ;c\n", "\r", "\t\n"]),
).map(lambda parts: "".join(parts).encode("utf-8"))


@settings(max_examples=600, derandomize=True, deadline=None, database=None)
@given(_LINES)
def test_fast_parsers_agree_with_klipper_on_fuzzed_move_lines(raw: bytes) -> None:
    for parser in PARSERS:
        check(parser, raw)
