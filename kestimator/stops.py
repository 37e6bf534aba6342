"""The stops: the commands at which a print waits for a person, and the times it gets there.

Owns which command names are stops on one printer for one file: the colour-change and
pause commands every firmware family knows (`DEFAULT_STOP_COMMANDS`), the slicer's own
colour-change and pause G-code as its embedded settings name it (`SLICER_STOP_KEYS`),
the user's `stop_commands` setting, and every `[gcode_macro]` of the printer's config whose
body calls one of them (a macro calling such a macro too). A tool change (`T1`: an MMU's,
no person attends it) is never a stop. `Stop` is one stop of a file: its command, line
(counted from 1), layer and Klipper time from the start.

What a stop does to the time (kestimator.estimate): a print that pauses stops reading the
file, so Klipper's toolhead runs its look-ahead out (toolhead.py `_handle_step_flush` ->
`_flush_lookahead(is_runout=True)` at Klipper 84104bbbd) and every earlier move ends at
rest; the time at the stop is that moment, and the print goes on from rest after it.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Container, Iterable
from typing import Final

from kestimator.klipper_commands import CORE_COMMANDS, MODULE_COMMANDS
from kestimator.timedlines import TimedLines

# Colour change (M600), pause (M601: Prusa firmware; PAUSE: Klipper's pause_resume),
# unconditional and conditional stop (M0, M1) and SD pause (M25: Klipper's virtual_sdcard).
DEFAULT_STOP_COMMANDS: Final = ("M600", "M601", "PAUSE", "M0", "M1", "M25")
DEFAULT_STOP_COMMANDS_SET: Final = frozenset(DEFAULT_STOP_COMMANDS)
# The slicer settings whose G-code a slicer writes where the print stops for a person:
# PrusaSlicer/SuperSlicer's colour change and pause, OrcaSlicer/Bambu Studio's pause (their
# colour change on a printer without an AMS is M600, a default). Their tool-change G-code
# (change_filament_gcode, toolchange_gcode) runs at every tool change: not a stop.
SLICER_STOP_KEYS: Final = ("color_change_gcode", "pause_print_gcode", "machine_pause_gcode")
# At most this many stops are listed; the print's further stops are counted.
MAX_STOPS: Final = 1000

# Every command Klipper itself registers on some printer (none of them waits for a person,
# but PAUSE and M25, defaults): a word of the slicer's pause G-code such as `M400` (Bambu's
# `M400 U1`) or `M117` is not a stop.
_KLIPPER_COMMANDS: Final = frozenset(
    CORE_COMMANDS.union(*(frozenset(names) for names in MODULE_COMMANDS.values())))
# How Klipper's gcode.py finds a line's command word (`_process_commands`: the upper-case
# line split by this, the command is the first two parts: "M600", "PAUSE", "SET_X").
_ARGS_RE: Final = re.compile(r"([A-Z_]+|[A-Z*])")
# Where a command word ends: a space, a comment, a template expression.
_WORD_END_RE: Final = re.compile(r"[\s;{]")
_TOOL_RE: Final = re.compile(r"T[0-9]+$")
# Jinja statements and comments at the start of a macro line ({% if ... %}PAUSE).
_LEADING_TEMPLATE_RE: Final = re.compile(r"^(?:\{%.*?%\}|\{#.*?#\})\s*")


@dataclasses.dataclass(frozen=True)
class Stop:
    """One stop of a file: the command, its line (from 1), the layer it is in (the number
    of layer markers before it; 0 before the first) and Klipper's time from the start to
    when the printer stands there (every earlier move done)."""

    command: str
    line: int
    layer: int
    time_s: float


class StopLog:
    """The stop commands of one estimate and the stops met so far: the first MAX_STOPS
    listed (command, layer; their times recorded into `times` by the estimate), the rest
    counted."""

    def __init__(self, names: frozenset[str]) -> None:
        self.names = names
        self.times = TimedLines()
        self.commands: list[str] = []
        self.layers: list[int] = []
        self.unlisted = 0

    def note(self, name: str, layer: int) -> bool:
        """A stop of command `name` in `layer`; True when it is listed (its time is to be
        recorded)."""
        if len(self.commands) >= MAX_STOPS:
            self.unlisted += 1
            return False
        self.commands.append(name)
        self.layers.append(layer)
        return True

    def listed(self) -> list[Stop]:
        """The stops listed, in file order."""
        return [Stop(name, line, layer, t) for name, layer, (line, t)
                in zip(self.commands, self.layers, self.times)]


def command_word(line: str) -> str | None:
    """The command a G-code line (or a macro's line) runs, upper-case; None for a comment,
    a blank line or a template expression."""
    text = line.strip()
    while True:
        stripped = _LEADING_TEMPLATE_RE.sub("", text)
        if stripped == text:
            break
        text = stripped
    if not text or text[0] in ";#{":
        return None
    parts = _ARGS_RE.split(text.upper())
    word = _WORD_END_RE.split("".join(parts[:3]).strip(), 1)[0]
    return word or None


def _words(gcode: str) -> list[str]:
    """The commands a G-code text runs, line by line (a slicer setting's `\\n` escapes
    are line breaks)."""
    lines = gcode.replace("\\n", "\n").splitlines()
    return [word for word in map(command_word, lines) if word is not None]


def is_tool_change(name: str) -> bool:
    """`T0`, `T1`...: a tool change, which no person attends."""
    return _TOOL_RE.match(name) is not None


def slicer_stop_commands(settings: Iterable[tuple[str, str]]) -> frozenset[str]:
    """The stop commands a slicer's pause / colour-change G-code (key, text) runs: its
    words that Klipper does not run itself (a macro of the printer's, `M600`), and the
    defaults among them."""
    names: set[str] = set()
    for _key, text in settings:
        for word in _words(text):
            if is_tool_change(word):
                continue
            if word in DEFAULT_STOP_COMMANDS or word not in _KLIPPER_COMMANDS:
                names.add(word)
    return frozenset(names)


def stop_commands(extra: Iterable[str], macros: Iterable[tuple[str, str]]) -> frozenset[str]:
    """Every stop command on a printer: the defaults, `extra` (the slicer's and the user's),
    and each macro (name, body) whose body calls one of them, a stop macro too."""
    names = {name.upper() for name in DEFAULT_STOP_COMMANDS}
    names.update(name.strip().upper() for name in extra if name.strip())
    bodies = [(name.upper(), set(_words(body))) for name, body in macros]
    grown = True
    while grown:
        grown = False
        for name, calls in bodies:
            if name not in names and calls & names:
                names.add(name)
                grown = True
    return frozenset(name for name in names if not is_tool_change(name))


def known_stops(names: frozenset[str], known: Container[str] | None) -> frozenset[str]:
    """The stop commands among `names` the printer runs: all of them when its commands are
    not known (`known` None), else those it knows (a command Klipper does not know is
    skipped, and the print goes on)."""
    if known is None:
        return names
    return frozenset(name for name in names if name in known)
