"""The stops' references: Klipper's time at each stop of the multi-colour files of this folder
(made by make_files.py with real slicers), with this folder's printer.cfg.

Regenerate with the oracle (mainline Klipper 84104bbbd, batch mode):
    ORACLE_KLIPPER=... ORACLE_PYTHON=... python3 tests/stop_refs/runs.py [heldout]

A printer that pauses stops reading the file: Klipper's toolhead runs its look-ahead out
(`_handle_step_flush` -> `_flush_lookahead(is_runout=True)`) and stands there until RESUME.
Batch mode never pauses (it reads on), so the oracle runs a copy of the file with `M400`
after each pausing line (the same `_flush_lookahead`) and a layer marker after that, which the
oracle times (every earlier move done: the time at the stop); the real-time print of
tests/test_stops.py (real Klipper pausing a virtual-SD print at PAUSE) holds that this is
the time a real pause gives. `<file>.json` is the oracle's reference (`--reference`,
`--mark-every 0`) with its checkpoints back at the original file's lines, and `stops`: each
pausing line, its command and Klipper's time there.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ORACLE = HERE.parents[1].parent / "shared" / "tools" / "oracle" / "oracle.py"
# The commands that pause a print on this folder's printer.cfg: [pause_resume]'s PAUSE,
# [virtual_sdcard]'s M25, and its macros M600 and M0 (each runs PAUSE).
PAUSING = ("M600", "M0", "PAUSE", "M25")
FILES = ("ps25_box_color_pause.gcode", "cura413_box_pause_at_height.gcode")
# Held out (make_files.py): not used to write the code they test. The OrcaSlicer one is made
# from the corpus where it is used (make_files.orca_paused).
HELDOUT = ("ps25_bar_two_colours_pause.gcode", "cura413_bar_pause_at_height.gcode",
           "orca150_accelctl_pauses.gcode")
ORCA_DERIVED = "orca150_accelctl_pauses.gcode"
MARK = b";LAYER:999999"


def _command(line: bytes) -> str:
    code = line.split(b";", 1)[0].strip().upper()
    return code.split()[0].decode() if code else ""


def derive(src: Path, dest: Path) -> list[tuple[int, str]]:
    """`src` with M400 and a timed marker after each pausing line; its (line, command)s."""
    stops: list[tuple[int, str]] = []
    out: list[bytes] = []
    for number, line in enumerate(src.read_bytes().split(b"\n"), 1):
        out.append(line)
        command = _command(line)
        if command in PAUSING:
            stops.append((number, command))
            out += [b"M400", MARK]
    dest.write_bytes(b"\n".join(out))
    return stops


def reference(src: Path, work: Path) -> dict[str, object]:
    derived = work / src.name
    stops = derive(src, derived)
    done = subprocess.run(
        [sys.executable, os.fspath(ORACLE), os.fspath(derived), "--cfg",
         os.fspath(HERE / "printer.cfg"), "--mark-every", "0", "--reference"],
        capture_output=True, check=True)
    ref = json.loads(done.stdout)

    def original(line: int) -> int:
        """The original file's line of a line of the derived file."""
        return line - 2 * sum(1 for stop, _ in stops if stop + 2 < line)

    marks = [c for c in ref["checkpoints"] if c["kind"] == "layer"]
    stop_marks = [c for c in marks if c["line"] in {s + 2 + 2 * i for i, (s, _) in
                                                    enumerate(stops)}]
    assert len(stop_marks) == len(stops), (stop_marks, stops)
    ref["file"] = src.name
    ref["checkpoints"] = [dict(c, line=original(c["line"])) for c in marks
                          if c not in stop_marks]
    ref["stops"] = [{"command": command, "line": line, "t": mark["t"]}
                    for (line, command), mark in zip(stops, stop_marks)]
    return ref


def source(name: str, work: Path) -> Path:
    """The file `name` of this folder, or made in `work` (the OrcaSlicer one)."""
    if name != ORCA_DERIVED:
        return HERE / name
    sys.path.insert(0, str(HERE))
    import make_files

    path = work / "src" / name
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(make_files.orca_paused())
    return path


def main() -> int:
    names = HELDOUT if sys.argv[1:] == ["heldout"] else FILES + HELDOUT
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            ref = reference(source(name, Path(tmp)), Path(tmp))
            out = HERE / (Path(name).stem + ".json")
            out.write_text(json.dumps(ref, indent=1) + "\n")
            print("wrote", out.name, [(s["line"], s["t"]) for s in ref["stops"]])
    return 0


if __name__ == "__main__":
    sys.exit(main())
