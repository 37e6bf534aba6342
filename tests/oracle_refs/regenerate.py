"""Regenerate the oracle references in this folder from real Klipper (not a test).

Each entry: (reference name, G-code file, config in configs/). A G-code path starting with
"corpus:" is read from ../shared/corpus in place. Needs ORACLE_KLIPPER / ORACLE_PYTHON
(see ../shared/tools/oracle/README.md); Klipper commit 84104bbbd.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
CORPUS = HERE.parents[2] / "shared" / "corpus"
ORACLE = CORPUS.parent / "tools" / "oracle" / "oracle.py"

# Pre-flight references: the oracle's full analysis (errors with their source line, unknown
# commands and their counts, timed marks), for files Klipper stops or skips commands in.
# (name, G-code, config, mark every N moves, (line, text) inserted before that line or None)
PREFLIGHT = (
    ("preflight_orca_no_arcs",
     "corpus:gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", "no_arcs.cfg",
     500, None),
    ("preflight_cura_no_fwretract",
     "corpus:gcode/cura/cura413_voron250_torus_relE_fwretract.gcode",
     "no_firmware_retraction.cfg", 2000, None),
    ("preflight_cura_m221_without_value", "corpus:gcode/cura/cura413_ender3_nut_small.gcode",
     "stock_cross_section.cfg", 1, (2000, "M221 S")),
    ("preflight_orca_overextrusion",
     "corpus:gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode",
     "stock_cross_section.cfg", 1, (3000, "G1 X100 Y100 E40")),
) + tuple(
    # Heater limits (issue 26): each snippet's first error, or none (heater_in_range).
    ("preflight_heater_" + name, "snippets/heater_%s.gcode" % name, "heaters.cfg", 1, None)
    for name in ("m104_over", "m109_over", "m140_over", "m190_over", "generic_over",
                 "t1_over", "t1_under", "negative", "t2_missing", "unknown_heater",
                 "wait_unknown_sensor", "wait_max_below_min", "in_range")) + (
    # Commands that end the print (issue 36): M112 is Klipper's emergency stop; SAVE_CONFIG
    # with no settings left to save does nothing (configfile.py returns at once).
    ("preflight_m112", "snippets/m112.gcode", "heaters.cfg", 1, None),
    ("preflight_save_config", "snippets/save_config.gcode", "heaters.cfg", 1, None))

# Cold extrusion: batch mode lets every extruder extrude (heaters.py sets `can_extrude` for
# file output), so these come from a copy of the same Klipper whose heaters.py line 39 lacks
# `or is_fileoutput` (ORACLE_KLIPPER_COLD): with no temperatures in batch mode, every
# extrusion there is cold, which is what a printer does before its hotend was heated.
COLD_KLIPPER = ("mainline Klipper 84104bbbd (2026-08-07), klippy batch mode, with "
                "extras/heaters.py line 39 `or is_fileoutput` removed (no temperatures: "
                "every extruder is cold)")
COLD_PREFLIGHT = (
    ("preflight_cold_extrude", "snippets/cold_extrude.gcode", "heaters.cfg", 1, None),
    ("preflight_cold_retract", "snippets/cold_retract.gcode", "heaters.cfg", 1, None),
)

REFERENCES = (
    ("pa_shaper_commands", "snippets/pa_shaper_commands.gcode", "pa_is.cfg", 1),
    ("shaper_types", "snippets/shaper_types.gcode", "pa_is.cfg", 1),
    ("tool_changes", "snippets/tool_changes.gcode", "two_extruders.cfg", 1),
    ("cura_nut_pa_is_max_endstops", "corpus:gcode/cura/cura413_ender3_nut_small.gcode",
     "pa_is_max_endstops.cfg", 500),
    ("cura_nut_pa_is", "corpus:gcode/cura/cura413_ender3_nut_small.gcode", "pa_is.cfg", 500),
    # An [extruder_stepper]'s own pressure advance widens the flush delay while it follows
    # an extruder (issue 26); without one, or unsynced, it adds nothing.
    ("cura_nut_extruder_stepper_pa", "corpus:gcode/cura/cura413_ender3_nut_small.gcode",
     "extruder_stepper_pa.cfg", 500),
    ("cura_nut_extruder_stepper_no_pa", "corpus:gcode/cura/cura413_ender3_nut_small.gcode",
     "extruder_stepper_no_pa.cfg", 500),
    ("cura_nut_extruder_stepper_unsynced",
     "corpus:gcode/cura/cura413_ender3_nut_small.gcode", "extruder_stepper_unsynced.cfg", 500),
    ("orca_cube_pa_is",
     "corpus:gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", "pa_is.cfg", 500),
)


def gcode_path(name: str) -> Path:
    """Where a reference's G-code file is."""
    if name.startswith("corpus:"):
        return CORPUS / name[len("corpus:"):]
    return HERE / name


def with_insert(source: Path, insert: tuple[int, str] | None, out_dir: Path) -> Path:
    """``source``, or a copy with ``insert``'s text as a line before its line number."""
    if insert is None:
        return source
    line, text = insert
    lines = source.read_bytes().split(b"\n")
    lines.insert(line - 1, text.encode())
    out = out_dir / (source.stem + "_inserted.gcode")
    out.write_bytes(b"\n".join(lines))
    return out


def main() -> int:
    wanted = set(sys.argv[1:])
    for ref, gcode, cfg, every in REFERENCES:
        if wanted and ref not in wanted:
            continue
        out = subprocess.run(
            [sys.executable, str(ORACLE), str(gcode_path(gcode)), "--cfg",
             str(HERE / "configs" / cfg), "--mark-every", str(every), "--reference"],
            capture_output=True, text=True, env=os.environ)
        doc = json.loads(out.stdout)
        doc["file"] = gcode
        doc["config"] = "configs/" + cfg
        (HERE / (ref + ".json")).write_text(json.dumps(doc, indent=1) + "\n")
        print(ref, doc["total_s"])
    import tempfile
    runs = [(entry, None, "mainline Klipper 84104bbbd (2026-08-07), klippy batch mode")
            for entry in PREFLIGHT]
    runs += [(entry, os.environ.get("ORACLE_KLIPPER_COLD"), COLD_KLIPPER)
             for entry in COLD_PREFLIGHT]
    for (ref, gcode, cfg, every, insert), klipper, label in runs:
        if wanted and ref not in wanted:
            continue
        env = dict(os.environ)
        if klipper is not None:
            env["ORACLE_KLIPPER"] = klipper
        elif label == COLD_KLIPPER:
            print(ref, "skipped: ORACLE_KLIPPER_COLD is not set")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            path = with_insert(gcode_path(gcode), insert, Path(tmp))
            out = subprocess.run(
                [sys.executable, str(ORACLE), str(path), "--cfg",
                 str(HERE / "configs" / cfg), "--mark-every", str(every)],
                capture_output=True, text=True, env=env)
        full = json.loads(out.stdout)
        doc = {"file": gcode, "insert": insert, "config": "configs/" + cfg,
               "klipper": label,
               "total_s": full["total_s"], "errors": full["errors"],
               "unknown_commands": full["unknown_commands"],
               "marks": [{"line": m["line"], "t": m["t"]} for m in full["marks"]]}
        if full["errors"]:
            # Every move is marked: keep the last one before the stopping line (when the
            # print stops) and drop the rest.
            stop = full["errors"][0]["src_line"]
            before = [m for m in doc["marks"] if m["line"] < stop]
            doc["marks"] = before[-1:]
        (HERE / (ref + ".preflight.json")).write_text(json.dumps(doc, indent=1) + "\n")
        print(ref, doc["errors"][:1], doc["unknown_commands"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
