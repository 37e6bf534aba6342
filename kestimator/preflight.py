"""The pre-flight check: what Klipper will do with this file on this printer.

Owns the findings the one streaming pass collects (`Preflight`) and their wording:

- ``stop`` (severity ``error``): the first command Klipper answers with an error. Klipper
  (84104bbbd, `klippy/gcode.py` `_process_commands` / `extras/virtual_sdcard.py`) stops a
  print at the first command error: a move out of range, a parameter it cannot parse, an
  extrusion over `max_extrude_cross_section`, relative G2/G3, ... Nothing after that line
  prints. The message is Klipper's own text. Later errors are counted in the same finding.
- ``unchecked`` (severity ``warning``): Klipper will range-check this file's moves, but
  kestimator could not (a kinematics mainline does not ship, or the printer's [printer] /
  [stepper_*] sections are not known): a move Klipper refuses would not be found, so the
  pre-flight cannot say Klipper runs every command.
- ``may_stop`` (severity ``warning``): Klipper stops the print here unless something the
  file cannot show happened before: an extrusion before any command heats the extruder,
  after a macro whose commands are not known (a start macro may heat). Its first line.
- ``skipped`` (severity ``warning``): commands Klipper answers with ``Unknown command`` and
  skips while the print goes on: G2/G3 without ``[gcode_arcs]``, G10/G11 without
  ``[firmware_retraction]``, M-codes of modules the printer does not have, macros the
  printer does not define. The time is right, the part is not what the slicer meant.

Each finding is one kind (a command name for skipped commands) with its first line, its
message and how often it occurred: memory stays bounded whatever the file.

The time reported when Klipper stops the print: `total_s` stays the time of the whole file
(what the print takes once the problem is fixed, as the slicer meant it), and the stop
finding carries ``t``, the time at which every move before the stopping line has finished:
where a real print would end.
"""

from __future__ import annotations

import dataclasses

from kestimator.durations import format_duration

SEVERITY_ERROR = "error"
SEVERITY_WARNING = "warning"
KIND_STOP = "stop"
KIND_SKIPPED = "skipped"
KIND_UNCHECKED = "unchecked"
KIND_MAY_STOP = "may_stop"
# Skipped commands listed one finding per name, at most; the rest share one finding.
MAX_SKIPPED_NAMES = 1000
# Commands that need a section, and the section (extras/gcode_arcs.py,
# extras/firmware_retraction.py).
SECTION_OF_COMMAND = {
    "G2": "gcode_arcs", "G3": "gcode_arcs", "G17": "gcode_arcs", "G18": "gcode_arcs",
    "G19": "gcode_arcs", "G10": "firmware_retraction", "G11": "firmware_retraction",
    "SET_RETRACTION": "firmware_retraction", "GET_RETRACTION": "firmware_retraction",
}
# What a missing section means for the print.
_MISSING_SECTION_EFFECT = {
    "gcode_arcs": "the file's arcs are not printed",
    "firmware_retraction": "the file's retractions are not done",
}
STOP_PREFIX = "Klipper stops the print here: "
MAY_STOP_PREFIX = "Klipper may stop the print here: "
SUMMARY_HEAD = "Pre-flight: "
# Exit status of `inject` and `check` when Klipper will stop the print (docs/CLI.md).
EXIT_KLIPPER_STOPS = 4


@dataclasses.dataclass
class Finding:
    """One kind of thing Klipper will do: its first line, its message, how often."""

    severity: str
    kind: str
    line: int | None
    message: str
    count: int = 1
    # Only for the stop: seconds at which every move before `line` has finished.
    t: float | None = None

    def set_time(self, t: float) -> None:
        """The stop's time: every move before its line has finished at `t` seconds."""
        self.t = t

    def to_json(self) -> dict[str, object]:
        """``{severity, line, message, kind, count}`` (and ``t`` for the stop)."""
        doc: dict[str, object] = {"severity": self.severity, "line": self.line,
                                  "message": self.message, "kind": self.kind,
                                  "count": self.count}
        if self.t is not None:
            doc["t"] = round(self.t, 6)
        return doc


class Preflight:
    """Collects findings during the estimate's pass."""

    def __init__(self) -> None:
        self.stop: Finding | None = None
        self.skipped: dict[str, Finding] = {}
        # Skipped commands whose name came after MAX_SKIPPED_NAMES others: one finding.
        self.skipped_unlisted: Finding | None = None
        # Why moves were not range-checked, if they were not.
        self.unchecked: Finding | None = None
        self.maybe: Finding | None = None

    def moves_unchecked(self, why: str) -> None:
        """Moves are not range-checked as Klipper checks them; `why` says why."""
        if self.unchecked is None:
            self.unchecked = Finding(SEVERITY_WARNING, KIND_UNCHECKED, None, why)

    def command_error(self, line: int, message: str) -> Finding | None:
        """Klipper answers this line with an error; the new stop finding, if it is the first."""
        if self.stop is not None:
            self.stop.count += 1
            return None
        self.stop = Finding(SEVERITY_ERROR, KIND_STOP, line, STOP_PREFIX + message)
        return self.stop

    def may_stop(self, line: int, message: str) -> None:
        """Klipper may answer this line with an error (`message`), depending on what the
        file cannot show; later ones are counted in the first."""
        if self.maybe is not None:
            self.maybe.count += 1
            return
        self.maybe = Finding(SEVERITY_WARNING, KIND_MAY_STOP, line, MAY_STOP_PREFIX + message)

    def unknown_command(self, name: str, line: int) -> None:
        """Klipper answers `Unknown command` to ``name`` and goes on."""
        found = self.skipped.get(name)
        if found is not None:
            found.count += 1
            return
        if len(self.skipped) >= MAX_SKIPPED_NAMES:
            if self.skipped_unlisted is None:
                self.skipped_unlisted = Finding(
                    SEVERITY_WARNING, KIND_SKIPPED, line,
                    "Unknown commands of more than %d names (the others are not listed): "
                    "Klipper skips them" % MAX_SKIPPED_NAMES)
            else:
                self.skipped_unlisted.count += 1
            return
        section = SECTION_OF_COMMAND.get(name)
        if section is not None:
            message = ('Unknown command:"%s": the printer config has no [%s], so Klipper '
                       "skips it: %s" % (name, section, _MISSING_SECTION_EFFECT[section]))
        else:
            message = 'Unknown command:"%s": Klipper skips it' % name
        self.skipped[name] = Finding(SEVERITY_WARNING, KIND_SKIPPED, line, message)

    def findings(self) -> list[Finding]:
        """The stop first, then a possible stop, unchecked moves, then skipped commands in
        the order first seen."""
        found = [self.stop] if self.stop is not None else []
        if self.maybe is not None:
            found.append(self.maybe)
        if self.unchecked is not None:
            found.append(self.unchecked)
        found += sorted(self.skipped.values(), key=lambda f: f.line or 0)
        if self.skipped_unlisted is not None:
            found.append(self.skipped_unlisted)
        return found


def summary_lines(findings: list[dict[str, object]]) -> list[str]:
    """The pre-flight block as plain lines: counts, then the first line of each kind."""
    if not findings:
        return []
    stops = [f for f in findings if f["kind"] == KIND_STOP]
    skipped = [f for f in findings if f["kind"] == KIND_SKIPPED]
    unchecked = [f for f in findings if f["kind"] == KIND_UNCHECKED]
    maybe = [f for f in findings if f["kind"] == KIND_MAY_STOP]
    head = []
    if stops:
        when = stops[0].get("t")
        head.append("Klipper will stop the print at line %s%s" % (
            stops[0]["line"], "" if when is None
            else ", %s in" % format_duration(float(str(when)))))
    if maybe:
        head.append("Klipper may stop the print at line %s" % maybe[0]["line"])
    if unchecked:
        head.append("moves not range-checked")
    if skipped:
        head.append("%d command%s skipped" % (
            sum(int(str(f["count"])) for f in skipped), "" if len(skipped) == 1 and
            skipped[0]["count"] == 1 else "s"))
    lines = [SUMMARY_HEAD + "; ".join(head)]
    for finding in findings:
        more = int(str(finding["count"])) - 1
        suffix = ""
        if more:
            suffix = (" (%d more line%s)" % (more, "" if more == 1 else "s")
                      if finding["kind"] == KIND_SKIPPED else
                      " (%d more error%s after it)" % (more, "" if more == 1 else "s"))
        where = "" if finding["line"] is None else "line %s: " % finding["line"]
        lines.append("  %s%s%s" % (where, _printable(str(finding["message"])), suffix))
    return lines


def _printable(text: str) -> str:
    """Text from the file with control characters shown as '?' (for a terminal)."""
    return "".join(c if c.isprintable() else "?" for c in text)


def stderr_line(findings: list[dict[str, object]]) -> str | None:
    """One line for a slicer's dialog when Klipper will stop the print, else None."""
    for finding in findings:
        if finding["kind"] == KIND_STOP:
            return "kestimator: Klipper will stop this print at line %s: %s" % (
                finding["line"], _printable(str(finding["message"])[len(STOP_PREFIX):]))
    return None
