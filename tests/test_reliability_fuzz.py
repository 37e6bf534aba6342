"""Fuzzing the parser, the interpreter and `inject`: no input crashes or hangs them.

Every input either gives a result or a `KestimatorError` naming the file (and the line,
where the planner failed); each input finishes within a time bounded by its line count
(TIME_LIMIT_S + TIME_PER_LINE_S per line: the longest arc kestimator splits takes about
0.3 s, an infinite loop takes forever); and when
`inject` succeeds every line it does not own is in the output byte for byte, while when
it fails the file is untouched and no temporary file is left.

Inputs tried per run, with the fixed seeds CI uses (KESTIMATOR_FUZZ_EXAMPLES unset):
  hypothesis, 3 properties x 200 examples (derandomized)      600
  seeded mutations of real corpus lines (estimate + inject)     300 files
  total                                                         900 inputs
About 15 s. A longer local run, e.g. 20 000 examples per property and 10 000 mutants:
  KESTIMATOR_FUZZ_EXAMPLES=20000 KESTIMATOR_FUZZ_MUTANTS=10000 \\
      python -m pytest tests/test_reliability_fuzz.py
(KESTIMATOR_FUZZ_SEED changes the mutation seed; hypothesis stays derandomized.)
Finding of the long run, fixed: an arc with I/J in the millions of mm would be split into
millions of segments, as Klipper would split it; arcs over MAX_ARC_SEGMENTS are now refused
with a warning (tests/test_klipper_behaviour.py pins it).
"""

from __future__ import annotations

import contextlib
import io
import os
import random
import re
import signal
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_lines
from kestimator.gcode import extended_params, parse_line
from kestimator.limits import Limits
from kestimator.rewrite import MARKER_PREFIX, _is_m73, inject_file, is_layer_info_line
from kestimator.slicers import ADAPTERS

from .conftest import corpus_files, without_progress_table

EXAMPLES = int(os.environ.get("KESTIMATOR_FUZZ_EXAMPLES", "200"))
MUTANTS = int(os.environ.get("KESTIMATOR_FUZZ_MUTANTS", "300"))
MUTATION_SEED = int(os.environ.get("KESTIMATOR_FUZZ_SEED", "9"))
TIME_LIMIT_S = 10.0
TIME_PER_LINE_S = 0.5
HUGE_LINE_BYTES = 100_000
LINES_PER_MUTANT = 120
CORPUS_LINES_PER_FILE = 4000

settings.register_profile(
    "kestimator-fuzz", max_examples=EXAMPLES, derandomize=True, deadline=None,
    database=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FUZZ = settings.get_profile("kestimator-fuzz")

LIMITS = Limits.from_values({"arcs_enabled": True, "firmware_retraction_enabled": True})
TIME_PREFIXES = tuple(sorted({p.encode() for a in ADAPTERS for p in a.time_comment_prefixes}))


class InputHung(BaseException):
    """One input took longer than its bound (BaseException: nothing swallows it)."""


@contextlib.contextmanager
def _time_limit(data: bytes) -> Iterator[None]:
    limit_s = TIME_LIMIT_S + TIME_PER_LINE_S * len(_lines(data))

    def expire(signum: int, frame: object) -> None:
        raise InputHung("no result within %g s for %r" % (limit_s, data[:300]))

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, limit_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)


# What inputs look like
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**9, 10**9).map(str),
    # Letter parameters cannot use exponents (Klipper reads "1e5" as 1 then E5).
    st.floats(allow_nan=False, allow_infinity=False).map(lambda v: "%.20f" % v),
    st.sampled_from(["9" * 400, "-" + "9" * 400, "0." + "0" * 330 + "1"]),
    st.sampled_from(["", "-", ".", "0", "-0", "1e999", "-1e999", "1e-320", "nan", "inf",
                     "-inf", "1e308", "0x10", "1_000", "--1", "1e", "+5", "-1"]))
LETTERS = st.sampled_from(list("XYZEFPSRIJKTABCDGHLMNOQUVW*xyzef"))
CODES = st.sampled_from(
    ["G0", "G1", "G2", "G3", "G4", "G10", "G11", "G17", "G18", "G19", "G28", "G90", "G91",
     "G92", "M82", "M83", "M84", "M104", "M109", "M140", "M190", "M204", "M220", "M221",
     "M400", "M73", "M117", "T0", "N10 G1", "g1", "G1.5", "G", "M", "G01", "MYMACRO"])
EXTENDED = st.sampled_from(
    ["SET_VELOCITY_LIMIT", "SET_RETRACTION", "TEMPERATURE_WAIT", "EXCLUDE_OBJECT_START",
     "SET_PRESSURE_ADVANCE", "G4", "M204"])
KEYS = st.sampled_from(
    ["VELOCITY", "ACCEL", "SQUARE_CORNER_VELOCITY", "MINIMUM_CRUISE_RATIO", "ACCEL_TO_DECEL",
     "RETRACT_LENGTH", "RETRACT_SPEED", "UNRETRACT_EXTRA_LENGTH", "UNRETRACT_SPEED",
     "SENSOR", "MINIMUM", "MAXIMUM", "NAME", "X"])
COMMENTS = st.sampled_from(
    [";LAYER_CHANGE", ";LAYER:", ";LAYER:-1", "; CHANGE_LAYER", ";TYPE:External perimeter",
     "; FEATURE: Outer wall", ";TIME_ELAPSED:", ";TIME:", "; ESTIMATOR_ADD_TIME ",
     ";ESTIMATOR_ADD_TIME", "; estimated printing time (normal mode) = ", ";PRINTING_TIME:",
     MARKER_PREFIX, ";", ""])

GCODE_LINE = st.builds(lambda code, words, sep: code + sep + sep.join(words), CODES,
                       st.lists(st.builds(str.__add__, LETTERS, NUMBERS), max_size=6),
                       st.sampled_from([" ", "", "\t"]))
EXTENDED_LINE = st.builds(
    lambda name, pairs: " ".join([name] + ["%s=%s" % kv for kv in pairs]), EXTENDED,
    st.lists(st.tuples(KEYS, st.one_of(NUMBERS, st.text(max_size=8))), max_size=4))
COMMENT_LINE = st.builds(str.__add__, COMMENTS, st.one_of(NUMBERS, st.text(max_size=20)))
LINE = st.one_of(
    GCODE_LINE, EXTENDED_LINE, COMMENT_LINE,
    st.builds(lambda code, comment: code + " ;" + comment, GCODE_LINE, st.text(max_size=10)),
    st.text(max_size=40).map(lambda s: s.replace("\n", "")),
    st.binary(max_size=40).map(lambda b: b.replace(b"\n", b"").decode("latin-1")))


@st.composite
def gcode_files(draw: st.DrawFn) -> bytes:
    lines = draw(st.lists(LINE, max_size=60))
    eol = draw(st.sampled_from([b"\n", b"\r\n"]))
    data = eol.join(line.encode("utf-8", "surrogatepass") for line in lines)
    if lines and draw(st.booleans()):
        data += eol
    return data


# What must hold
def _lines(data: bytes) -> list[bytes]:
    """Lines as kestimator splits them: at LF only, endings kept."""
    return re.findall(rb"[^\n]*\n|[^\n]+$", data)


def _owned(line: bytes) -> bool:
    code = line.lstrip()
    return (_is_m73(code) or code.startswith(MARKER_PREFIX.encode())
            or code.startswith(TIME_PREFIXES) or is_layer_info_line(code))


def _not_owned(data: bytes) -> list[bytes]:
    return [line.rstrip(b"\r\n") for line in _lines(data) if not _owned(line)]


def _check_estimate(data: bytes) -> None:
    with _time_limit(data):
        try:
            est = estimate_lines(io.BytesIO(data), LIMITS, "fuzz.gcode")
        except KestimatorError as exc:
            assert exc.path == "fuzz.gcode"
            assert exc.line is not None and 1 <= exc.line <= len(_lines(data))
            return
    assert est.total_s >= 0.0


def _check_inject(data: bytes, folder: str) -> None:
    path = os.path.join(folder, "fuzz.gcode")
    with open(path, "wb") as f:
        f.write(data)
    with _time_limit(data):
        try:
            inject_file(path, LIMITS)
        except KestimatorError as exc:
            assert exc.path == path
            with open(path, "rb") as f:
                assert f.read() == data
            assert os.listdir(folder) == ["fuzz.gcode"]
            return
    with open(path, "rb") as f:
        out = without_progress_table(f.read())
    assert _not_owned(out) == _not_owned(data)
    assert os.listdir(folder) == ["fuzz.gcode"]
    os.unlink(path)


@FUZZ
@given(st.text(max_size=200))
def test_parsing_any_text_gives_a_command_and_only_documented_errors(text: str) -> None:
    cmd = parse_line(text)
    assert cmd.name == cmd.name.upper() and cmd.name == cmd.name.strip()
    with contextlib.suppress(ValueError):
        extended_params(cmd.code)


@FUZZ
@given(gcode_files())
def test_estimating_any_gcode_gives_a_time_or_a_located_error_in_bounded_time(
        data: bytes) -> None:
    _check_estimate(data)


@FUZZ
@given(gcode_files())
def test_injecting_any_gcode_keeps_every_line_it_does_not_own_or_the_whole_file(
        data: bytes) -> None:
    with tempfile.TemporaryDirectory() as folder:
        _check_inject(data, folder)


# Mutations of real slicer lines
MUTATIONS = (
    "cut", "garbage", "nul", "huge", "tiny", "nan", "inf", "negate", "zero_f", "negative_f",
    "g4_negative", "unknown_letter", "long_line", "drop_eol", "crlf", "duplicate")
NUMBER_RE = re.compile(rb"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def _replace_number(line: bytes, rng: random.Random, new: bytes) -> bytes:
    spots = list(NUMBER_RE.finditer(line))
    if not spots:
        return line + b" X" + new
    spot = rng.choice(spots)
    return line[:spot.start()] + new + line[spot.end():]


def _mutate(line: bytes, rng: random.Random) -> bytes:
    kind = rng.choice(MUTATIONS)
    body = line.rstrip(b"\n")
    eol = line[len(body):]
    if kind == "cut":
        return body[:rng.randrange(len(body) + 1)] + eol
    if kind == "garbage":
        at = rng.randrange(len(body) + 1)
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 12)))
        return body[:at] + junk.replace(b"\n", b"") + body[at:] + eol
    if kind == "nul":
        at = rng.randrange(len(body) + 1)
        return body[:at] + b"\0" * rng.randrange(1, 4) + body[at:] + eol
    if kind in ("huge", "tiny", "nan", "inf"):
        new = {"huge": rng.choice([b"1e308", b"-1e308", b"9" * 400, b"1e999"]),
               "tiny": rng.choice([b"1e-320", b"5e-324", b"0.0000000001", b"-1e-300"]),
               "nan": b"nan", "inf": rng.choice([b"inf", b"-inf"])}[kind]
        return _replace_number(body, rng, new) + eol
    if kind == "negate":
        return _replace_number(body, rng, b"-" + rng.choice([b"1", b"1000", b"0.5"])) + eol
    if kind == "zero_f":
        return body + b" F0" + eol
    if kind == "negative_f":
        return body + b" F-" + str(rng.randrange(1, 9000)).encode() + eol
    if kind == "g4_negative":
        return b"G4 P-1\n" + line
    if kind == "unknown_letter":
        return body + b" " + bytes([rng.choice(b"ABCDHLOQUVW*")]) + b"12" + eol
    if kind == "long_line":
        filler = rng.choice([b"X1", b";", b"9", b" "])
        return body + filler * (HUGE_LINE_BYTES // len(filler)) + eol
    if kind == "drop_eol":
        return body
    if kind == "crlf":
        return body + b"\r\n"
    return line + line


@pytest.fixture(scope="module")
def corpus_lines(corpus_root: Path) -> list[bytes]:
    lines: list[bytes] = []
    for path in corpus_files():
        with open(path, "rb") as f:
            for i, line in enumerate(f):
                if i >= CORPUS_LINES_PER_FILE:
                    break
                lines.append(line)
    return lines


def test_mutated_corpus_lines_never_crash_estimate_or_inject(corpus_lines: list[bytes],
                                                             tmp_path: Path) -> None:
    rng = random.Random(MUTATION_SEED)
    folder = tmp_path / "work"
    folder.mkdir()
    for _ in range(MUTANTS):
        start = rng.randrange(len(corpus_lines) - LINES_PER_MUTANT)
        window = corpus_lines[start:start + LINES_PER_MUTANT]
        mutated = [_mutate(line, rng) if rng.random() < 0.2 else line for line in window]
        data = b"".join(mutated)
        _check_estimate(data)
        _check_inject(data, str(folder))
