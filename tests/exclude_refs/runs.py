"""The exclude_object references: corpus files labelled as Moonraker labels them, with
EXCLUDE_OBJECT commands inserted, timed by real Klipper.

Each case names a corpus file (read in place), labels it with `preprocess_cancellation`
0.2.1 (the tool Moonraker runs on upload: it adds EXCLUDE_OBJECT_DEFINE/START/END to
PrusaSlicer, SuperSlicer, Slic3r, Cura and ideaMaker files; OrcaSlicer files are labelled
already and pass unchanged) and inserts commands before given lines of the labelled file,
as a user typing them at that moment would run them. `printer.cfg` is the corpus's with an
`[exclude_object]` section.

Regenerate with the oracle (mainline Klipper 84104bbbd):
    ORACLE_KLIPPER=... ORACLE_PYTHON=... python3 tests/exclude_refs/runs.py
It writes `refs.json`: per case the labelled file's sha256 (a changed labelling tool shows
up as a clear failure), the inserted commands with their concrete line numbers, and the
oracle's `total_s`, `n_moves` and layer checkpoints (corpus reference format,
`--mark-every 0`).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
CORPUS_GCODE = HERE.parents[1].parent / "shared" / "corpus" / "gcode"
ORACLE = HERE.parents[1].parent / "shared" / "tools" / "oracle" / "oracle.py"
CFG = HERE / "printer.cfg"
REFS = HERE / "refs.json"
ORACLE_KLIPPER = "mainline Klipper 84104bbbd (2026-08-07), klippy batch mode"
LABEL_TOOL = "preprocess_cancellation 0.2.1 (shapely off)"

# Where a command goes, in the labelled file: ("start",) before line 1; ("layer", k) before
# the k-th layer marker (0-based); ("object_start", k) before the k-th
# EXCLUDE_OBJECT_START; ("in_object", k, n) n lines after the k-th EXCLUDE_OBJECT_START.
Where = tuple[object, ...]
# name -> (corpus file, [(where, command), ...], "cli" when the case is one --exclude --at)
CASES: dict[str, tuple[str, list[tuple[Where, str]], bool]] = {
    "orca_only_object_at_its_start": (
        "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode",
        [(("object_start", 0), "EXCLUDE_OBJECT NAME=xyz-10mm-calibration-cube.stl_id_0_copy_0")],
        True),
    "orca_only_object_mid_print": (
        "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode",
        [(("layer", 25), "EXCLUDE_OBJECT NAME=xyz-10mm-calibration-cube.stl_id_0_copy_0")],
        True),
    "prusaslicer_one_of_four_at_start": (
        "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode",
        [(("start",), "EXCLUDE_OBJECT NAME=cube_1_id_0_copy_0")], True),
    "prusaslicer_two_mid_print": (
        "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode",
        [(("layer", 12), "EXCLUDE_OBJECT NAME=cylinder_2_id_1_copy_0"),
         (("layer", 12), "EXCLUDE_OBJECT NAME=union_3_id_2_copy_0")], True),
    "superslicer_current_mid_object": (
        "superslicer/cancelobj_ss2.4_inverted_pyramid.gcode",
        [(("in_object", 40, 30), "EXCLUDE_OBJECT CURRENT=1")], False),
    "superslicer_every_object_at_start": (
        "superslicer/cancelobj_ss2.3.56_arcwelder.gcode",
        [(("start",), "EXCLUDE_OBJECT NAME=cube_1_id_0_copy_0"),
         (("start",), "EXCLUDE_OBJECT NAME=cube_1_id_0_copy_1"),
         (("start",), "EXCLUDE_OBJECT NAME=union_3_id_2_copy_0"),
         (("start",), "EXCLUDE_OBJECT NAME=cylinder_2_id_1_copy_0")], True),
    "slic3r_one_mid_print": (
        "slic3r/cancelobj_slic3r1.3.1dev.gcode",
        [(("object_start", 30), "EXCLUDE_OBJECT NAME=cylinder_2_stl_id_1_copy_0")], True),
    "cura_excluded_then_reset": (
        "cura/cancelobj_cura5.0.0_inverted_pyramid.gcode",
        [(("layer", 10), "EXCLUDE_OBJECT NAME=inverted_pyramid_stl_1"),
         (("layer", 30), "EXCLUDE_OBJECT RESET=1 NAME=inverted_pyramid_stl_1")], False),
    "cura_reset_all_mid_print": (
        "cura/cancelobj_cura4.10.0.gcode",
        [(("start",), "EXCLUDE_OBJECT NAME=cube_1_stl"),
         (("start",), "EXCLUDE_OBJECT NAME=union_3_stl"),
         (("layer", 15), "EXCLUDE_OBJECT RESET=1")], False),
    "cura_define_reset_unregisters": (
        "cura/cura413_ender3_nut_small.gcode",
        [(("layer", 5), "EXCLUDE_OBJECT NAME=M3_hex_nut_stl"),
         (("layer", 20), "EXCLUDE_OBJECT_DEFINE RESET=1")], False),
    "ideamaker_every_object_mid_print": (
        "ideamaker/cancelobj_ideamaker4.2.0.gcode",
        [(("layer", 20), "EXCLUDE_OBJECT NAME=test_bed_part0_3mf"),
         (("layer", 20), "EXCLUDE_OBJECT NAME=test_bed_part1_3mf"),
         (("layer", 20), "EXCLUDE_OBJECT NAME=test_bed_part2_3mf"),
         (("layer", 20), "EXCLUDE_OBJECT NAME=test_bed_part0_1_3mf")], True),
}
LAYER_MARKERS = (b";LAYER_CHANGE", b";LAYER:", b"; CHANGE_LAYER")


def label(source: Path) -> bytes:
    """The file as preprocess_cancellation labels it (bytes kept as they are)."""
    import preprocess_cancellation as pc  # the test extras; imported only here

    pc.shapely = None  # the hull polygons would depend on whether shapely is installed
    out = io.StringIO(newline="")
    with open(source, encoding="utf-8", errors="surrogateescape", newline="") as fin:
        pc.preprocessor(fin, out)
    return out.getvalue().encode("utf-8", "surrogateescape")


def locate(data: bytes, where: Where) -> int:
    """The 1-based line of the labelled file a command goes before."""
    lines = data.split(b"\n")
    kind = where[0]
    if kind == "start":
        return 1
    if kind == "layer":
        found = [i + 1 for i, line in enumerate(lines) if line.startswith(LAYER_MARKERS)]
        return found[int(where[1])]  # type: ignore[call-overload]
    starts = [i + 1 for i, line in enumerate(lines)
              if line.startswith(b"EXCLUDE_OBJECT_START")]
    if kind == "object_start":
        return starts[int(where[1])]  # type: ignore[call-overload]
    return starts[int(where[1])] + int(where[2])  # type: ignore[call-overload]


def insert(data: bytes, events: list[tuple[int, str]]) -> bytes:
    """The file with each command on its own line before its line (same line: in order)."""
    lines = data.split(b"\n")
    out: list[bytes] = []
    pending = sorted(events, key=lambda event: event[0])
    i = 0
    for number, line in enumerate(lines, 1):
        while i < len(pending) and pending[i][0] <= number:
            out.append(pending[i][1].encode())
            i += 1
        out.append(line)
    return b"\n".join(out)


def original_line(line: int, events: list[tuple[int, str]]) -> int | None:
    """The labelled file's line of line `line` of the file with the commands inserted
    (None for an inserted line)."""
    shift = 0
    for at in sorted(event[0] for event in events):
        if at + shift <= line:
            if at + shift == line:
                return None
            shift += 1
    return line - shift


def main() -> int:
    refs: dict[str, object] = {"klipper": ORACLE_KLIPPER, "label_tool": LABEL_TOOL,
                               "cfg": "tests/exclude_refs/printer.cfg", "cases": {}}
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        for name, (gcode, commands, cli) in CASES.items():
            labelled = label(CORPUS_GCODE / gcode)
            events = [(locate(labelled, where), command) for where, command in commands]
            path = Path(tmp) / (name + ".gcode")
            path.write_bytes(insert(labelled, events))
            done = subprocess.run(
                [sys.executable, os.fspath(ORACLE), os.fspath(path), "--cfg", os.fspath(CFG),
                 "--mark-every", "0", "--reference"], capture_output=True, check=False)
            if done.returncode:
                print("oracle failed:", name, done.stderr.decode()[-500:])
                failed += 1
                continue
            ref = json.loads(done.stdout)
            refs["cases"][name] = {  # type: ignore[index]
                "gcode": gcode, "labelled_sha256": hashlib.sha256(labelled).hexdigest(),
                "events": events, "cli": cli, "total_s": ref["total_s"],
                "n_moves": ref["n_moves"],
                "layers": [[cp["line"], cp["t"]] for cp in ref["checkpoints"]
                           if cp["kind"] == "layer"]}
            print("%-36s total %.6f s" % (name, ref["total_s"]))
    REFS.write_text(json.dumps(refs, indent=1) + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
