"""Mirrors the line parsing of klippy/gcode.py at Klipper commit 84104bbbd (GNU GPLv3).

One G-code line to one command, exactly as Klipper's `klippy/gcode.py` splits it.

No state lives here. Klipper (commit 84104bbbd, `GCodeDispatch._process_commands`) strips
the line, cuts it at the first ';', upper-cases it and splits it on runs of letters: the
command is the first letter group with its number (`G1`, `M104`, `SET_VELOCITY_LIMIT`) and
every later letter group is a parameter whose value is the text up to the next letter.
Extended commands (names that are not a letter and a number) take `KEY=value` pairs as
`shlex` splits them. A line number `N123` before the command is skipped.

Also Klipper's parameter getters (`GCodeCommand.get_float`/`get_int`, with their range
checks), as functions of a command's parameters.
"""

from __future__ import annotations

import math
import re
import shlex
import sys
import types
from typing import TYPE_CHECKING, Final, NamedTuple, overload

from kestimator.errors import CommandError, ParamError

if TYPE_CHECKING:
    # 64-bit machine integers in the compiled build (plain ints when run as Python).
    from mypy_extensions import i64

_ARGS_RE = re.compile(r"([A-Z_]+|[A-Z*])")


class Command(NamedTuple):
    """A parsed line: upper-case name, letter parameters, code text and comment.

    `params` holds letter parameters of traditional commands only; an extended command's
    `KEY=value` pairs are parsed on demand by `extended_params(code)`, because Klipper
    only parses them for commands it knows (a malformed unknown command is no error).
    """

    name: str
    params: dict[str, str]
    code: str
    comment: str | None


def split_comment(line: str) -> tuple[str, str | None]:
    """The code part (stripped) and the comment after the first ';' (None if none)."""
    line = line.strip()
    cpos = line.find(";")
    if cpos < 0:
        return line, None
    return line[:cpos], line[cpos + 1:]


def is_traditional(name: str) -> bool:
    """True for `G1`-style names (a letter then a number), which take letter parameters."""
    if len(name) < 2 or not name[0].isalpha():
        return False
    try:
        float(name[1:].split()[0])
    except ValueError:
        return False
    return True


def parse_line(line: str) -> Command:
    """Split one line (without its line ending) into a Command; empty name for no command."""
    code, comment = split_comment(line)
    parts = _ARGS_RE.split(code.upper())
    if "".join(parts[:2]) == "N":
        # Skip line number at start of command
        name = "".join(parts[3:5]).strip()
        first = 5
    else:
        name = "".join(parts[:3]).strip()
        first = 3
    if name and not is_traditional(name):
        return Command(name.split()[0], {}, code, comment)
    params = {parts[i]: parts[i + 1].strip() for i in range(first, len(parts), 2)}
    return Command(name, params, code, comment)


# A plain move line: `G0`/`G1`, then space-separated parameters, each a letter of X Y Z E
# F and a number of digits, '.', '+' and '-' only, then an optional ';' comment. Anything
# else (lower case, tabs, `*`, exponents, no-space parameters, line numbers, other letters)
# goes through `parse_line`, which gives the same result for plain lines, only slower.
# Klipper keeps the last of repeated parameters (a dict), and so do both parsers below.
#
# Two implementations give identical results (tests/test_gcode_fast_parse.py pins both
# against `parse_line` on every corpus line and on fuzzed lines). Pure CPython runs the
# regex: its matching happens in C, which beats any per-byte Python loop. PyPy's JIT and the
# mypyc-compiled build (see setup.py) run the per-byte scanner, 3x faster than the regex
# there.
# Order X Y Z E F (PrusaSlicer, Orca, Slic3r) or F first (Cura, ideaMaker): F may stand
# first or last; if it stands in both places, the last one counts, as in Klipper.
# From Python 3.11 the number and each optional part are possessive (`++`, `?+`): what
# follows a number or a part can never start one, so giving back characters never finds
# another match, and the engine keeps no backtracking state (the regex 18 % faster).
_POSSESSIVE = b"+" if sys.version_info >= (3, 11) else b""
_NUMBER = rb"([-+.0-9]+%s)" % _POSSESSIVE
_PLAIN_MOVE_RE = re.compile(
    rb"G[01](?: F{n})?{p}(?: X{n})?{p}(?: Y{n})?{p}(?: Z{n})?{p}(?: E{n})?{p}(?: F{n})?{p}"
    rb" *{p}(?:;.*)?\r?\n?".replace(b"{n}", _NUMBER).replace(b"{p}", _POSSESSIVE),
    re.DOTALL)
_plain_move_match = _PLAIN_MOVE_RE.fullmatch
# Longer lines take the general path (no number there can overflow to inf).
_PLAIN_MOVE_MAX_BYTES: Final = 200
# What the plain-move parsers return: whether the line is a plain move, then X, Y, Z, E
# and F, with ABSENT (NaN) for a parameter the line does not give. NaN never comes from a
# number here (digits, '.', '+' and '-' only), so `v == v` means "given". A bool and five
# floats: the compiled build returns them in registers, with no object per line.
MoveValues = tuple[bool, float, float, float, float, float]
ABSENT: Final = float("nan")
NOT_PLAIN: Final = (False, ABSENT, ABSENT, ABSENT, ABSENT, ABSENT)


def parse_plain_move_regex(raw: bytes) -> MoveValues:
    """(True, X, Y, Z, E, F) of a plain `G0`/`G1` byte line (ABSENT for a missing one).

    Gives exactly what `parse_line` and float() give for the same line, or NOT_PLAIN when
    the line is not plain (or a value is not a number, or F is not above 0): the caller
    then uses `parse_line`, which reports the problem as Klipper would.
    """
    match = _plain_move_match(raw)
    if match is None or len(raw) > _PLAIN_MOVE_MAX_BYTES:
        return NOT_PLAIN
    f0, x, y, z, e, f = match.groups()
    if f is None:
        f = f0
    try:
        speed = ABSENT
        if f is not None:
            speed = float(f)
            if not speed > 0.0:
                return NOT_PLAIN
        return (True, ABSENT if x is None else float(x), ABSENT if y is None else float(y),
                ABSENT if z is None else float(z), ABSENT if e is None else float(e), speed)
    except ValueError:
        return NOT_PLAIN


# Up to this many digits the integer mantissa, and 10**k for its k decimals, are exact as
# floats (< 2**53).
_EXACT_DIGITS: Final = 15


def parse_plain_move_scan(raw: bytes) -> MoveValues:
    """The same as `parse_plain_move_regex`, by one pass over the bytes (PyPy, compiled).

    A number with at most 15 digits and k decimals is its integer mantissa divided by
    10**k: both are exact floats and IEEE division rounds correctly, so the result is the
    correctly rounded value float() gives. Longer numbers go through float() itself.
    """
    n: i64 = len(raw)
    if n < 3 or n > _PLAIN_MOVE_MAX_BYTES or raw[0] != 71 or raw[2] != 32:  # "G", " "
        return NOT_PLAIN
    code: i64 = raw[1]
    if code != 49 and code != 48:  # "1", "0"
        return NOT_PLAIN
    x = y = z = e = f = ABSENT
    i: i64 = 3
    while i < n:
        c: i64 = raw[i]
        if c == 32:  # " "
            i += 1
            continue
        if c == 59 or c == 10:  # ";", LF
            break
        if c == 13:  # CR: only as the line ending
            if i + 1 == n or (i + 2 == n and raw[i + 1] == 10):
                break
            return NOT_PLAIN
        i += 1
        start: i64 = i
        negative = False
        if i < n:
            d: i64 = raw[i]
            if d == 45:  # "-"
                negative = True
                i += 1
            elif d == 43:  # "+"
                i += 1
        # The mantissa is summed as an integer, used only when it has at most 15 digits
        # (one float conversion per number; no more digits are summed, so it stays far
        # below 2**63).
        mantissa: i64 = 0
        digits: i64 = 0
        point: i64 = -1
        while i < n:
            d = raw[i]
            if 48 <= d <= 57:
                if digits < _EXACT_DIGITS:
                    mantissa = mantissa * 10 + (d - 48)
                digits += 1
            elif d == 46 and point < 0:  # the first "."
                point = digits
            else:
                break
            i += 1
        if not digits:
            return NOT_PLAIN
        if i < n:
            d = raw[i]
            if d != 32 and d != 59 and d != 10 and d != 13:
                return NOT_PLAIN
        if digits <= _EXACT_DIGITS:
            scale: i64 = 1
            decimals: i64 = 0  # (an if statement: mypyc boxes a conditional expression)
            if point >= 0:
                decimals = digits - point
            while decimals > 0:
                scale *= 10
                decimals -= 1
            v = float(mantissa) / float(scale)
            if negative:
                v = -v
        else:
            v = float(raw[start:i])
        if c == 88:  # X
            x = v
        elif c == 89:  # Y
            y = v
        elif c == 69:  # E
            e = v
        elif c == 70:  # F
            f = v
        elif c == 90:  # Z
            z = v
        else:
            return NOT_PLAIN
    if f == f and not f > 0.0:
        return NOT_PLAIN
    return True, x, y, z, e, f


# True when this module is the mypyc-compiled extension (`pip install .` with a C compiler).
# (mypyc turns functions into builtins; a module's __file__ is not set while a compiled
# module initialises under every mypyc version, so it cannot tell.)
COMPILED: Final = not isinstance(split_comment, types.FunctionType)
# Which plain-move parser runs (see above); callers branch on this constant rather than
# calling through a variable, so the compiled build calls the parser directly.
SCAN_PLAIN_MOVES: Final = sys.implementation.name == "pypy" or COMPILED


def extended_params(code: str) -> dict[str, str]:
    """`NAME KEY=value KEY2="quoted value"` parameters, keys upper-cased (Klipper's rules).

    Raises ValueError for text Klipper calls a malformed command.
    """
    stripped = code.strip()
    space = stripped.find(" ")
    raw = "" if space < 0 else stripped[space + 1:]
    lexer = shlex.shlex(raw, posix=True)
    lexer.whitespace_split = True
    lexer.commenters = "#;"
    params: dict[str, str] = {}
    for arg in lexer:
        key, sep, value = arg.partition("=")
        if not sep:
            raise ValueError("Malformed command '%s'" % stripped)
        params[key.upper()] = value
    return params


def command_params(cmd: Command) -> dict[str, str]:
    """The parameters of a command: letter ones, or an extended command's `KEY=value`
    pairs (a malformed one is Klipper's "Malformed command" error)."""
    if cmd.params or not cmd.code:
        return cmd.params
    try:
        return extended_params(cmd.code)
    except ValueError as exc:
        raise CommandError(str(exc)) from None


@overload
def get_float(params: dict[str, str], name: str, default: float, *,
              minval: float | None = None, above: float | None = None,
              below: float | None = None) -> float: ...


@overload
def get_float(params: dict[str, str], name: str, default: None = None, *,
              minval: float | None = None, above: float | None = None,
              below: float | None = None) -> float | None: ...


def get_float(params: dict[str, str], name: str, default: float | None = None, *,
              minval: float | None = None, above: float | None = None,
              below: float | None = None) -> float | None:
    """Klipper's `gcmd.get_float` with its range checks; NaN and inf are refused."""
    raw = params.get(name)
    if raw is None:
        return default
    try:
        value = float(raw)
    except ValueError:
        raise ParamError("unable to parse %s" % raw) from None
    if not math.isfinite(value):
        raise ParamError("%s must be a finite number, not %r" % (name, raw))
    if minval is not None and value < minval:
        raise ParamError("%s must have minimum of %s" % (name, minval))
    if above is not None and value <= above:
        raise ParamError("%s must be above %s" % (name, above))
    if below is not None and value >= below:
        raise ParamError("%s must be below %s" % (name, below))
    return value


def get_int(params: dict[str, str], name: str) -> int:
    """Klipper's `gcmd.get_int(name, 0)`."""
    raw = params.get(name)
    if raw is None:
        return 0
    try:
        return int(raw)
    except ValueError:
        raise ParamError("unable to parse %s" % raw) from None


def mux_error(key: str, name: str, choices: list[str]) -> CommandError:
    """`_cmd_mux`'s error for a `name=key` no object registered: the last choice holding the
    key is the guess, as upstream's loop leaves it; else every choice is listed."""
    guesses = [". Did you mean '%s'?" % c for c in choices if key and key in c]
    guess = guesses[-1] if guesses else ". Options: %s" % ", ".join("'%s'" % c for c in choices)
    return CommandError("The value '%s' is not valid for %s%s" % (key, name, guess))
