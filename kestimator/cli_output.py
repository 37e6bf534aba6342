"""What `kestimator estimate` and `inject` report: the `--json` documents and plain text.

Owns the documented JSON objects (docs/CLI.md, schema JSON_SCHEMA_VERSION: the estimate's
and `limits --json`'s), the plain-text summary printed when stdout is not a terminal or
`rich` is missing, and the few figures the summary adds to an `Estimate`: the slicer's own
filament numbers read from its comments, and the filament's volume and weight where its
diameter and density are known.
Standard library only: the slicer hooks and the zipapp run it without `rich`. The `rich`
rendering of the same document lives in `kestimator.cli_render`.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterator
from typing import Any, TextIO

from kestimator import __version__
from kestimator.config.resolve import GUESS_WARNING_STARTS, ResolvedLimits
from kestimator.durations import format_duration
from kestimator.errors import fixed
from kestimator.estimate import KIND_UNKNOWN, Estimate
from kestimator.interpreter import KIND_MACRO
from kestimator.klipper_commands import CORE_COMMANDS
from kestimator.klipper_commands import MODULE_COMMANDS as KLIPPER_MODULE_COMMANDS
from kestimator.limits import Limits, json_value
from kestimator.preflight import summary_lines
from kestimator.slicers import SlicerInfo, read_file_ends
from kestimator.textsearch import search

JSON_SCHEMA_VERSION = 1
MM_PER_M = 1000.0
MM3_PER_CM3 = 1000.0
PERCENT = 100.0
# Slicers give density in g/cm^3; ideaMaker's kg/m^3 would read as 1000 times that.
MAX_DENSITY_G_CM3 = 25.0
FEATURE_NAME_WIDTH = 28

# The slicer's own filament figures, as each family writes them (first match wins).
_SLICER_MM_RES = (
    re.compile(r"^; filament used \[mm\] = (.+)$", re.M),           # PrusaSlicer, Orca
    re.compile(r"^; filament used = ([\d.]+)mm", re.M),             # Slic3r 1.x
    re.compile(r"^; --- filament used: ([\d.]+) mm", re.M),         # Kiri:Moto
)
_SLICER_M_RE = re.compile(r"^;Filament used: ([\d.]+)m\s*$", re.M)  # Cura
_SLICER_G_RE = re.compile(r"^; (?:total )?filament used \[g\] = (.+)$", re.M)
_DIAMETER_RE = re.compile(r"^; filament_diameter ?[=:] ?([\d.,\s]+)$", re.M)
_DENSITY_RE = re.compile(r"^; filament_density ?[=:] ?([\d.,\s]+)$", re.M)


# Characters never written to a terminal as they are: C0 and C1 controls, DEL, the bidi
# overrides and isolates (they reorder what follows), and lone surrogates (undecodable bytes
# read with surrogateescape).
_UNSAFE_RE = re.compile("[\x00-\x1f\x7f-\x9f\u200e\u200f\u202a-\u202e\u2066-\u2069"
                        "\ud800-\udfff]")


def _escaped(match: re.Match[str]) -> str:
    code = ord(match.group())
    if code in _SPACES:  # a message stays one line: breaks and tabs shown as escapes
        return _SPACES[code]
    if 0xDC80 <= code <= 0xDCFF:  # a byte surrogateescape could not decode
        return "\\x%02x" % (code - 0xDC00)
    return "\\x%02x" % code if code < 0x100 else "\\u%04x" % code


_SPACES = {0x09: "\\t", 0x0A: "\\n", 0x0D: "\\r"}


def printable(text: str) -> str:
    """`text` safe for a terminal, on one line: every control character is shown as an
    escape (`\\n`, `\\x1b`).

    Everything kestimator prints that came from a file, a server or a path goes through
    this."""
    return _UNSAFE_RE.sub(_escaped, text)


def quiet_stdout() -> None:
    """Point fd 1 at the null device so the interpreter's last flush cannot fail again
    (what is still buffered goes nowhere): after a broken pipe (`... | head`), where the
    reader went away on purpose."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)
    except OSError:
        pass


def printable_doc(value: Any) -> Any:
    """A copy of a JSON-like document with every string (keys too) made `printable`."""
    if isinstance(value, str):
        return printable(value)
    if isinstance(value, dict):
        return {printable(k) if isinstance(k, str) else k: printable_doc(v)
                for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [printable_doc(v) for v in value]
    return value


def _numbers(text: str) -> list[float]:
    out = []
    for part in text.split(","):
        try:
            value = float(part)
        except ValueError:
            continue
        if math.isfinite(value):
            out.append(value)
    return out


def _first_positive(text: str) -> float | None:
    return next((v for v in _numbers(text) if v > 0.0), None)


def read_slicer_filament(path: str) -> dict[str, float | None]:
    """The slicer's filament comments: `slicer_mm`, `slicer_g`, `diameter_mm`, `density`.

    Per-extruder lists are summed (lengths, weights) or their first non-zero value taken
    (diameter, density); a value the file does not state, or states as 0, is None.
    """
    head, tail = read_file_ends(path)
    text = (head if head == tail else head + b"\n" + tail).decode("utf-8", "replace")
    slicer_mm = None
    for regex in _SLICER_MM_RES:
        match = search(regex, text)
        if match is not None:
            slicer_mm = sum(_numbers(match.group(1))) or None
            break
    if slicer_mm is None:
        match = search(_SLICER_M_RE, text)
        if match is not None:
            slicer_mm = float(match.group(1)) * MM_PER_M or None
    match = search(_SLICER_G_RE, text)
    slicer_g = (sum(_numbers(match.group(1))) or None) if match else None
    match = search(_DIAMETER_RE, text)
    diameter = _first_positive(match.group(1)) if match else None
    match = search(_DENSITY_RE, text)
    density = _first_positive(match.group(1)) if match else None
    if density is not None and density > MAX_DENSITY_G_CM3:
        density = None
    return {"slicer_mm": slicer_mm, "slicer_g": slicer_g, "diameter_mm": diameter,
            "density_g_cm3": density}


def filament_to_json(est: Estimate, from_slicer: dict[str, float | None]) -> dict[str, Any]:
    """The `filament` object: Klipper's extruded length, volume and weight, the slicer's."""
    extruded = est.filament_mm
    diameter = from_slicer["diameter_mm"]
    density = from_slicer["density_g_cm3"]
    volume = None if diameter is None else (
        extruded * math.pi * diameter * diameter / 4.0 / MM3_PER_CM3)
    weight = None if volume is None or density is None else volume * density
    return {
        "extruded_mm": round(extruded, 3),
        "diameter_mm": diameter,
        "volume_cm3": None if volume is None else round(volume, 3),
        "density_g_cm3": density,
        "weight_g": None if weight is None else round(weight, 3),
        "slicer_mm": None if from_slicer["slicer_mm"] is None
        else round(from_slicer["slicer_mm"], 3),
        "slicer_g": from_slicer["slicer_g"],
    }


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 6)


class LayerEntries:
    """The `layers` list of the `--json` object, made an entry at a time when iterated.

    A file may hold a million layer markers: the list of dicts (hundreds of MB) is never
    built; `write_json` writes it entry by entry, the text output reads it only for
    `--layers`."""

    def __init__(self, est: Estimate) -> None:
        self._layers = est.layers
        self._total_s = est.total_s

    def __len__(self) -> int:
        return len(self._layers)

    def __bool__(self) -> bool:
        return len(self._layers) > 0

    def __iter__(self) -> Iterator[dict[str, Any]]:
        times = self._layers.times
        last = len(times) - 1
        for i, (line, t) in enumerate(self._layers):
            end = times[i + 1] if i < last else self._total_s
            yield {"line": line, "t": round(t, 6), "duration_s": round(max(end - t, 0.0), 6)}


# Stands for the layer entries while the rest of the document is encoded.
_LAYERS_PLACEHOLDER = "\u0000kestimator-layers\u0000"


def _layer_json(entry: dict[str, Any]) -> str:
    """`json.dumps(entry, indent=1)` of a layer entry, two levels deep, written out: the
    encoder's own text for its int and its two finite floats (float.__repr__), without
    the pure-Python encoder that indent= takes (1 ms per 20 layers)."""
    t, duration = entry["t"], entry["duration_s"]
    if not (math.isfinite(t) and math.isfinite(duration)):
        return json.dumps(entry, indent=1).replace("\n", "\n  ")
    return '{\n   "line": %d,\n   "t": %s,\n   "duration_s": %s\n  }' % (
        entry["line"], float.__repr__(t), float.__repr__(duration))


def write_json(doc: dict[str, Any], out: TextIO) -> None:
    """`json.dump(doc, out, indent=1)` and a newline, byte for byte, with a `LayerEntries`
    written entry by entry (memory stays bounded however many layers there are)."""
    layers = doc.get("layers")
    if not isinstance(layers, LayerEntries) or not layers:
        json.dump({**doc, "layers": []} if isinstance(layers, LayerEntries) else doc, out,
                  indent=1)
        out.write("\n")
        return
    text = json.dumps({**doc, "layers": [_LAYERS_PLACEHOLDER]}, indent=1)
    at = text.index(json.dumps(_LAYERS_PLACEHOLDER))
    out.write(text[:at])
    # Each entry sits two levels deep: its inner lines take two more spaces.
    separator = ""
    for entry in layers:
        out.write(separator)
        out.write(_layer_json(entry))
        separator = ",\n  "
    out.write(text[at + len(json.dumps(_LAYERS_PLACEHOLDER)):])
    out.write("\n")


def estimate_to_json(est: Estimate, slicer: SlicerInfo, limits_source: str,
                     extra_warnings: list[str],
                     filament: dict[str, Any] | None = None,
                     limits_guessed: bool = False,
                     source: str | None = None) -> dict[str, Any]:
    """The documented `--json` object (schema version JSON_SCHEMA_VERSION, docs/CLI.md).

    `source` is the file the slicer's filament comments are read from when it is not
    `est.path` (standard input kept in a temporary file, `est.path` naming it `<stdin>`)."""
    slicer_s = slicer.estimate_s
    # The slicer times the moves: it is compared with Klipper's motion time.
    motion_s = est.parts.motion_s
    difference = None if slicer_s is None else slicer_s - motion_s
    parts = parts_to_json(est)
    return {
        "schema": JSON_SCHEMA_VERSION,
        "kestimator": __version__,
        "file": est.path,
        "total_s": round(est.total_s, 6),
        "first_layer_s": _rounded(est.first_layer_s),
        "layer_count": len(est.layers),
        "layers": LayerEntries(est),
        "features": {name: round(t, 6) for name, t in est.features.items()},
        "objects": {name: round(t, 6) for name, t in est.objects.items()},
        "object_remaining": [{"line": line, "t": round(t, 6),
                              "remaining": {name: round(left, 6)
                                            for name, left in remaining.items()}}
                             for line, t, remaining in est.object_remaining],
        "slicer": {"name": slicer.name, "version": slicer.version, "estimate_s": slicer_s,
                   "first_layer_estimate_s": slicer.first_layer_estimate_s,
                   "difference_s": _rounded(difference),
                   "difference_pct": None if difference is None or not motion_s
                   else round(PERCENT * difference / motion_s, 3)},
        "filament": filament if filament is not None
        else filament_to_json(est, read_slicer_filament(source or est.path)),
        "limits_source": limits_source,
        "limits_guessed": limits_guessed,
        "n_moves": est.n_moves,
        "n_lines": est.n_lines,
        "ignored_commands": est.ignored_commands,
        "ignored_commands_unlisted": est.ignored_unlisted,
        "commands": est.commands,
        "untimed_commands": untimed_by_kind(est, {source["name"]
                                                  for source in parts["sources"]}),
        "preflight": [finding.to_json() for finding in est.preflight],
        "stops": [{"command": stop.command, "line": stop.line, "layer": stop.layer,
                   "time_s": round(stop.time_s, 6)} for stop in est.stops],
        "stops_unlisted": est.stops_unlisted,
        "parts": parts,
        "warnings": extra_warnings + est.warnings,
        "warnings_dropped": est.warnings_dropped,
    }


def limits_to_json(resolved: ResolvedLimits, path: str | None) -> dict[str, Any]:
    """The documented `limits --json` object (schema version JSON_SCHEMA_VERSION)."""
    slicer = resolved.slicer
    settings = resolved.slicer_settings
    return {
        "schema": JSON_SCHEMA_VERSION,
        "kestimator": __version__,
        "file": path,
        "slicer": None if slicer is None else {"name": slicer.name, "version": slicer.version},
        "machine": resolved.machine,
        "profile": resolved.profile,
        "summary": resolved.summary,
        "limits": {
            field: {"value": json_value(getattr(resolved.limits, field)),
                    "source": resolved.sources[field],
                    "overridden": [{"value": json_value(c.value), "source": c.source}
                                   for c in resolved.shadowed.get(field, ())]}
            for field in Limits.field_names()},
        "slicer_settings": {"origin": settings.origin or None,
                            "accelerations": dict(settings.accelerations),
                            "notes": list(settings.notes)},
        "warnings": list(resolved.warnings),
    }


def parts_to_json(est: Estimate) -> dict[str, Any]:
    """The total split: Klipper's motion, the added times with their sources, the prep."""
    parts = est.parts
    return {
        "motion_s": round(parts.motion_s, 6),
        "added_s": round(parts.added_s, 6),
        "before_first_extrusion_s": round(parts.before_first_extrusion_s, 6),
        "print_duration_s": round(parts.print_duration_s, 6),
        "total_s": round(parts.total_s, 6),
        "first_extrusion_t": _rounded(est.first_extrusion_t),
        "sources": [{"name": p.name, "source": p.source, "count": p.count,
                     "seconds": round(p.seconds, 6),
                     "before_first_extrusion_s": round(p.before_first_extrusion_s, 6),
                     "covered_by_learned": p.covered}
                    for p in est.timed_parts],
        "untimed_macros": dict(est.untimed_macros),
        "untimed_waits": dict(est.untimed_waits),
    }


def parts_rows(doc: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, text) lines for the parts of the total; none when nothing was added."""
    parts = doc["parts"]
    if not parts["sources"]:
        return []
    rows = [("Total", "%s (%.3f s) until the part is done" % (
                format_duration(parts["total_s"]), parts["total_s"])),
            ("Motion", "%s (%.3f s), Klipper's planner" % (
                format_duration(parts["motion_s"]), parts["motion_s"])),
            ("Macros, prep", "%s (%.3f s)" % (format_duration(parts["added_s"]),
                                              parts["added_s"]))]
    for source in parts["sources"]:
        count = "x%d" % source["count"]
        if source["covered_by_learned"]:
            count += ", %d in the learned start" % source["covered_by_learned"]
        rows.append(("", "%s %s: %s, %s" % (source["name"], count,
                                                format_duration(source["seconds"]),
                                                source["source"])))
    if parts["before_first_extrusion_s"]:
        rows.append(("Printing", "%s after the first extrusion (print_duration; the "
                     "file's time comments)" % format_duration(parts["print_duration_s"])))
    return rows


def set_slicer_estimate(doc: dict[str, Any], slicer_s: float | None) -> None:
    """Replace the slicer's estimate in `doc` (inject looks through its own marker)."""
    total = doc["parts"]["motion_s"]
    slicer = doc["slicer"]
    slicer["estimate_s"] = slicer_s
    difference = None if slicer_s is None else slicer_s - total
    slicer["difference_s"] = _rounded(difference)
    slicer["difference_pct"] = (None if difference is None or not total
                                else round(PERCENT * difference / total, 3))


def approximate_text(doc: dict[str, Any]) -> str:
    """What follows Klipper's time when the limits were guessed ("" when they were not)."""
    return "approximate: the limits are guesses" if doc.get("limits_guessed") else ""


def shown_warnings(doc: dict[str, Any], verbose: bool = False) -> list[str]:
    """The warnings the summary lists: not the guessed-limits one (said on stderr), and the
    one-per-command ones only with --verbose (the grouped summary says what they say)."""
    return [w for w in doc["warnings"]
            if not (doc.get("limits_guessed") and w.startswith(GUESS_WARNING_STARTS))
            and (verbose or _PER_COMMAND_WARNING_RE.search(w) is None)]


# Commands of Klipper's optional modules (extras, a kinematics' own): known to a printer
# that configures the module (kestimator.klipper_commands, taken from Klipper itself).
MODULE_COMMANDS = frozenset(name for names in KLIPPER_MODULE_COMMANDS.values()
                            for name in names) - CORE_COMMANDS
# Kinds of untimed commands, in the order the summary names them: (kind, one, many).
UNTIMED_KINDS = (("macro", "macro", "macros"),
                 ("module", "module command", "module commands"),
                 ("unknown", "unknown command", "unknown commands"))
# Warnings that repeat, one per command, what the grouped summary says (shown with -v).
_PER_COMMAND_WARNING_RE = re.compile(r"'[^']*' is not a Klipper command: |: macros ran: |"
                                     r"^macros ran: |macros of the printer config ran: ")
# The estimate's record of untimed commands (Estimate.commands) uses these kinds.
_RECORD_MACRO = KIND_MACRO
_RECORD_UNKNOWN = KIND_UNKNOWN


def untimed_by_kind(est: Estimate, timed: set[str]) -> dict[str, dict[str, int]]:
    """The commands whose time is not counted, by kind (`UNTIMED_KINDS`): name -> runs.

    From the estimate's record (`Estimate.commands`): the printer config's template macros
    are macros (the no-time commands of modules it configures are timed right: 0 s); of the
    commands Klipper does not know, those of Klipper's optional modules are module commands,
    those
    that look like G-code (Marlin's M201, M900...) unknown commands, and the rest macros
    (of a printer whose config was not given; the pre-flight says when Klipper skips one).
    Commands the profile's [macros] or learned times give a time are left out.
    """
    record = est.commands
    groups: dict[str, dict[str, int]] = {kind: {} for kind, _, _ in UNTIMED_KINDS}
    groups["macro"].update({name: runs for name, runs in record.get(_RECORD_MACRO, {}).items()
                            if name not in timed})
    for name, runs in record.get(_RECORD_UNKNOWN, {}).items():
        if name in timed:
            continue
        if name in MODULE_COMMANDS:
            kind = "module"
        elif len(name) >= 2 and name[0] in "GMTD" and name[1].isdigit():
            kind = "unknown"
        else:
            kind = "macro"
        groups[kind][name] = groups[kind].get(name, 0) + runs
    return {kind: dict(sorted(names.items())) for kind, names in groups.items() if names}


def untimed_summary(doc: dict[str, Any]) -> str | None:
    """`3 macros and 2 module commands: their time is not counted (-v lists them)`."""
    groups = doc.get("untimed_commands") or {}
    parts = []
    for kind, one, many in UNTIMED_KINDS:
        count = len(groups.get(kind, {}))
        if count:
            parts.append("%d %s" % (count, one if count == 1 else many))
    if not parts:
        return None
    listed = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
    unlisted = doc.get("ignored_commands_unlisted") or 0
    if unlisted:
        listed += " (and %d more lines of commands with further names)" % unlisted
    return "%s: %s not counted (--verbose lists them)" % (
        listed, "its time is" if sum(len(v) for v in groups.values()) == 1
        else "their time is")


def untimed_waits_summary(doc: dict[str, Any]) -> str | None:
    """`2 heater waits count as 0 s: time each with --heat-time S ...`, said once, or None.

    Names only the options of the kinds the file has (no --homing-time without a G28)."""
    waits = (doc.get("parts") or {}).get("untimed_waits") or {}
    parts, options, keys = [], [], []
    for kind, one, many, option, key in (
            ("heater_waits", "heater wait", "heater waits", "--heat-time S", "heat_time_s"),
            ("homings", "homing (G28)", "homings (G28)", "--homing-time S", "homing_time_s")):
        count = int(waits.get(kind, 0))
        if count:
            parts.append("%d %s" % (count, one if count == 1 else many))
            options.append(option)
            keys.append(key)
    if not parts:
        return None
    single = len(parts) == 1 and parts[0].startswith("1 ")
    return ("%s count%s as 0 s: time %s with %s (or %s in the profile), or let `kestimator "
            "learn` time the printer's start" % (
                " and ".join(parts), "s" if single else "", "it" if single else "each",
                " and ".join(options), " and ".join(keys)))


def untimed_detail(doc: dict[str, Any]) -> list[str]:
    """One line per kind naming each untimed command and how often it ran (--verbose)."""
    groups = doc.get("untimed_commands") or {}
    return ["%s: %s" % (many, ", ".join("%s x%d" % kv for kv in groups[kind].items()))
            for kind, _, many in UNTIMED_KINDS if groups.get(kind)]


def slicer_label(doc: dict[str, Any]) -> str:
    """`PrusaSlicer 2.5.0+win64`, or the name alone when the file gives no version."""
    slicer = doc["slicer"]
    return slicer["name"] + (" " + slicer["version"] if slicer["version"] else "")


def difference_text(doc: dict[str, Any]) -> str:
    """`slicer 32s shorter (-14.4 %)`: how far the slicer's own estimate is from Klipper's."""
    difference = doc["slicer"]["difference_s"]
    if difference is None:
        return "no estimate in the file"
    word = "longer" if difference > 0 else "shorter"
    if round(difference) == 0:
        return "the same to the second"
    return "%s %s than Klipper (%+.1f %%)" % (format_duration(abs(difference)), word,
                                             doc["slicer"]["difference_pct"])


def filament_text(doc: dict[str, Any]) -> str:
    """`280.2 mm (0.67 cm³, 0.84 g); slicer: 280.2 mm`."""
    fil = doc["filament"]
    text = "%s mm" % fixed(fil["extruded_mm"], 1)
    extra = []
    if fil["volume_cm3"] is not None:
        extra.append("%s cm3" % fixed(fil["volume_cm3"], 2))
    if fil["weight_g"] is not None:
        extra.append("%s g" % fixed(fil["weight_g"], 2))
    if extra:
        text += " (%s)" % ", ".join(extra)
    said = []
    if fil["slicer_mm"] is not None:
        said.append("%s mm" % fixed(fil["slicer_mm"], 1))
    if fil["slicer_g"] is not None:
        said.append("%s g" % fixed(fil["slicer_g"], 2))
    if said:
        text += "; the slicer says " + ", ".join(said)
    return text


def excluded_text(doc: dict[str, Any]) -> str:
    """Which objects `--exclude` cancelled, and where."""
    excluded = doc["excluded"]
    saved = excluded.get("saved_s")
    return "%s, cancelled before line %d (EXCLUDE_OBJECT)%s" % (
        ", ".join(excluded["names"]), excluded["line"],
        "" if saved is None else ": saves %s" % format_duration(max(0.0, float(saved))))


def feature_rows(doc: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(feature, seconds, percent of the total), longest first."""
    total = doc["total_s"]
    return [(name, t, PERCENT * t / total if total else 0.0)
            for name, t in sorted(doc["features"].items(), key=lambda kv: -kv[1])]


def stop_rows(doc: dict[str, Any]) -> list[tuple[str, str, str, str, str]]:
    """The stops as rows (command, line, layer, Klipper time from the start, motion time
    since the last stop or the start), then the end of the print as one more row."""
    rows = []
    last = 0.0
    for stop in doc.get("stops", ()):
        rows.append((printable(stop["command"]), str(stop["line"]), str(stop["layer"]),
                     format_duration(stop["time_s"]), format_duration(stop["time_s"] - last)))
        last = stop["time_s"]
    if rows:
        rows.append(("end", "", "", format_duration(doc["total_s"]),
                     format_duration(doc["total_s"] - last)))
    return rows


def stops_note(doc: dict[str, Any]) -> str | None:
    """What the stop list leaves out, if anything."""
    unlisted = doc.get("stops_unlisted", 0)
    return "%d more stops not listed" % unlisted if unlisted else None


STOP_TITLES = ("stop", "line", "layer", "at", "after")


def print_text(doc: dict[str, Any], out: TextIO, layers: bool = False,
               verbose: bool = False) -> None:
    """The plain-text summary (stdout is not a terminal, or rich is not installed)."""
    total = doc["total_s"]
    approximate = approximate_text(doc)
    approximate = ", " + approximate if approximate else ""
    parts = parts_rows(doc)
    lines = ["%s" % doc["file"]]
    if parts:
        lines.append("  %-12s : %s%s" % (parts[0] + (approximate,)))
    else:
        lines.append("  Klipper time : %s (%.3f s)%s" % (format_duration(total), total,
                                                        approximate))
    for label, text in parts[1:]:
        lines.append("  %-12s %s %s" % (label, ":" if label else " ", text))
    slicer = doc["slicer"]
    if slicer["estimate_s"] is not None:
        lines.append("  Slicer       : %s, %s" % (format_duration(slicer["estimate_s"]),
                                                   slicer_label(doc)))
        lines.append("  Difference   : %s" % difference_text(doc))
    else:
        lines.append("  Slicer       : %s, no estimate in the file" % slicer_label(doc))
    if doc["first_layer_s"] is not None:
        lines.append("  First layer  : %s" % format_duration(doc["first_layer_s"]))
    lines.append("  Layers       : %d" % doc["layer_count"])
    lines.append("  Filament     : %s" % filament_text(doc))
    lines.append("  Limits from  : %s" % doc["limits_source"])
    if doc.get("excluded"):
        lines.append("  Excluded     : %s" % excluded_text(doc))
    rows = feature_rows(doc)
    if rows:
        lines.append("  Time per feature:")
        for feature, t, share in rows:
            lines.append("    %-*s %10s %5.1f %%" % (
                FEATURE_NAME_WIDTH, feature[:FEATURE_NAME_WIDTH], format_duration(t), share))
    stops = stop_rows(doc)
    if stops:
        lines.append("  Stops (the printer waits for you; Klipper time from the start, and "
                     "since the last stop):")
        for row in [STOP_TITLES] + stops:
            lines.append("    %-12s %7s %5s %10s %10s" % ((row[0][:12],) + tuple(row[1:])))
        note = stops_note(doc)
        if note is not None:
            lines.append("    " + note)
    lines.extend(summary_tail_lines(doc, verbose))
    # The layer table first and the summary last: with hundreds of layers the summary
    # stays on screen. Written a row at a time (a file may have a million layers).
    if layers and doc["layers"]:
        out.write("Time per layer (the summary follows the table):\n")
        out.write("  %5s %8s %10s %10s\n" % ("layer", "line", "starts", "takes"))
        for number, layer in enumerate(doc["layers"], 1):
            out.write("  %5d %8d %10s %10s\n" % (number, layer["line"],
                                                  format_duration(layer["t"]),
                                                  format_duration(layer["duration_s"])))
    out.write("\n".join(lines) + "\n")


def summary_tail_lines(doc: dict[str, Any], verbose: bool = False) -> list[str]:
    """The untimed commands (grouped, or per kind with --verbose) and the warnings."""
    lines = ["  " + printable(line) for line in summary_lines(doc["preflight"])]
    summary = untimed_summary(doc)
    if summary is not None:
        if verbose:
            lines.extend("  Not counted, " + text for text in untimed_detail(doc))
        else:
            lines.append("  " + summary)
    waits = untimed_waits_summary(doc)
    if waits is not None:
        lines.append("  " + waits)
    for warning in shown_warnings(doc, verbose):
        lines.append("  warning: " + warning)
    if doc["warnings_dropped"]:
        lines.append("  warning: %d more warnings not shown" % doc["warnings_dropped"])
    return lines
