"""What `kestimator estimate` and `inject` report: the `--json` document and its plain text.

Owns the documented JSON object (docs/CLI.md, schema JSON_SCHEMA_VERSION), the plain-text
summary printed when stdout is not a terminal or `rich` is missing, and the few figures
the summary adds to an `Estimate`: the slicer's own filament numbers read from its
comments, and the filament's volume and weight where its diameter and density are known.
Standard library only: the slicer hooks and the zipapp run it without `rich`. The `rich`
rendering of the same document lives in `kestimator.cli`.
"""

from __future__ import annotations

import math
import re
from typing import Any, TextIO

from kestimator import __version__
from kestimator.durations import format_duration
from kestimator.estimate import Estimate
from kestimator.preflight import summary_lines
from kestimator.slicers import SlicerInfo, read_file_ends

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
        match = regex.search(text)
        if match is not None:
            slicer_mm = sum(_numbers(match.group(1))) or None
            break
    if slicer_mm is None:
        match = _SLICER_M_RE.search(text)
        if match is not None:
            slicer_mm = float(match.group(1)) * MM_PER_M or None
    match = _SLICER_G_RE.search(text)
    slicer_g = (sum(_numbers(match.group(1))) or None) if match else None
    match = _DIAMETER_RE.search(text)
    diameter = _first_positive(match.group(1)) if match else None
    match = _DENSITY_RE.search(text)
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


def estimate_to_json(est: Estimate, slicer: SlicerInfo, limits_source: str,
                     extra_warnings: list[str],
                     filament: dict[str, Any] | None = None) -> dict[str, Any]:
    """The documented `--json` object (schema version JSON_SCHEMA_VERSION, docs/CLI.md)."""
    ends = [t for _, t in est.layers[1:]] + [est.total_s] if est.layers else []
    slicer_s = slicer.estimate_s
    # The slicer times the moves: it is compared with Klipper's motion time.
    motion_s = est.parts.motion_s
    difference = None if slicer_s is None else slicer_s - motion_s
    return {
        "schema": JSON_SCHEMA_VERSION,
        "kestimator": __version__,
        "file": est.path,
        "total_s": round(est.total_s, 6),
        "first_layer_s": _rounded(est.first_layer_s),
        "layer_count": len(est.layers),
        "layers": [{"line": line, "t": round(t, 6), "duration_s": round(max(end - t, 0.0), 6)}
                   for (line, t), end in zip(est.layers, ends)],
        "features": {name: round(t, 6) for name, t in est.features.items()},
        "objects": {name: round(t, 6) for name, t in est.objects.items()},
        "slicer": {"name": slicer.name, "version": slicer.version, "estimate_s": slicer_s,
                   "first_layer_estimate_s": slicer.first_layer_estimate_s,
                   "difference_s": _rounded(difference),
                   "difference_pct": None if difference is None or not motion_s
                   else round(PERCENT * difference / motion_s, 3)},
        "filament": filament if filament is not None
        else filament_to_json(est, read_slicer_filament(est.path)),
        "limits_source": limits_source,
        "n_moves": est.n_moves,
        "n_lines": est.n_lines,
        "ignored_commands": est.ignored_commands,
        "commands": est.commands,
        "preflight": [finding.to_json() for finding in est.preflight],
        "parts": parts_to_json(est),
        "warnings": extra_warnings + est.warnings,
        "warnings_dropped": est.warnings_dropped,
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


def untimed_commands(doc: dict[str, Any]) -> dict[str, int]:
    """Commands Klipper does not know that no time was given for (they count 0 s)."""
    timed = {source["name"] for source in doc["parts"]["sources"]}
    return {name: count for name, count in doc["ignored_commands"].items()
            if name not in timed}


def set_slicer_estimate(doc: dict[str, Any], slicer_s: float | None) -> None:
    """Replace the slicer's estimate in `doc` (inject looks through its own marker)."""
    total = doc["parts"]["motion_s"]
    slicer = doc["slicer"]
    slicer["estimate_s"] = slicer_s
    difference = None if slicer_s is None else slicer_s - total
    slicer["difference_s"] = _rounded(difference)
    slicer["difference_pct"] = (None if difference is None or not total
                                else round(PERCENT * difference / total, 3))


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
    text = "%.1f mm" % fil["extruded_mm"]
    extra = []
    if fil["volume_cm3"] is not None:
        extra.append("%.2f cm3" % fil["volume_cm3"])
    if fil["weight_g"] is not None:
        extra.append("%.2f g" % fil["weight_g"])
    if extra:
        text += " (%s)" % ", ".join(extra)
    said = []
    if fil["slicer_mm"] is not None:
        said.append("%.1f mm" % fil["slicer_mm"])
    if fil["slicer_g"] is not None:
        said.append("%.2f g" % fil["slicer_g"])
    if said:
        text += "; the slicer says " + ", ".join(said)
    return text


def feature_rows(doc: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(feature, seconds, percent of the total), longest first."""
    total = doc["total_s"]
    return [(name, t, PERCENT * t / total if total else 0.0)
            for name, t in sorted(doc["features"].items(), key=lambda kv: -kv[1])]


def print_text(doc: dict[str, Any], out: TextIO, layers: bool = False) -> None:
    """The plain-text summary (stdout is not a terminal, or rich is not installed)."""
    total = doc["total_s"]
    parts = parts_rows(doc)
    lines = ["%s" % doc["file"]]
    if parts:
        lines.append("  %-12s : %s" % parts[0])
    else:
        lines.append("  Klipper time : %s (%.3f s)" % (format_duration(total), total))
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
    rows = feature_rows(doc)
    if rows:
        lines.append("  Time per feature:")
        for feature, t, share in rows:
            lines.append("    %-*s %10s %5.1f %%" % (
                FEATURE_NAME_WIDTH, feature[:FEATURE_NAME_WIDTH], format_duration(t), share))
    if layers and doc["layers"]:
        lines.append("  Time per layer:")
        lines.append("    %5s %8s %10s %10s" % ("layer", "line", "starts", "takes"))
        for number, layer in enumerate(doc["layers"], 1):
            lines.append("    %5d %8d %10s %10s" % (number, layer["line"],
                                                    format_duration(layer["t"]),
                                                    format_duration(layer["duration_s"])))
    untimed = untimed_commands(doc)
    if untimed:
        lines.append("  Not Klipper commands (0 s): " + ", ".join(
            "%s x%d" % kv for kv in untimed.items()))
    lines.extend("  " + line for line in summary_lines(doc["preflight"]))
    for warning in doc["warnings"]:
        lines.append("  warning: " + warning)
    if doc["warnings_dropped"]:
        lines.append("  warning: %d more warnings not shown" % doc["warnings_dropped"])
    out.write("\n".join(lines) + "\n")
