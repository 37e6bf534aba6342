"""The bed_mesh / skew_correction references: which config runs which G-code, and the
G-code itself (a corpus file with the commands that load a mesh or skew profile inserted
after its first G28, or first when it has none: what a start macro does before the print).

Regenerate with the oracle (mainline Klipper 84104bbbd):
    ORACLE_KLIPPER=... ORACLE_PYTHON=... python3 tests/oracle_refs/transforms/runs.py
`<config>/<file>.json` is the corpus reference format (`--reference`, `--mark-every 0`).
The oracle includes the config from a wrapper, and Klipper reads a SAVE_CONFIG block only in
the main file: so the profiles are regular `[bed_mesh default]` sections here (the tests read
the same profile from a SAVE_CONFIG block too).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
SNIPPETS = HERE.parent / "snippets"
CORPUS_GCODE = HERE.parents[2].parent / "shared" / "corpus" / "gcode"
ORACLE = HERE.parents[2].parent / "shared" / "tools" / "oracle" / "oracle.py"

MESH = ("BED_MESH_PROFILE LOAD=default",)
SKEW = ("SKEW_PROFILE LOAD=my_skew",)
# (config folder, G-code: corpus-relative or snippets/..., commands inserted after G28)
RUNS: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("bed_mesh", "cura/cura413_ender3_nut_small.gcode", MESH),
    ("bed_mesh", "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", MESH),
    ("bed_mesh", "snippets/mesh_commands.gcode", ()),
    ("bed_mesh_bicubic", "cura/cura413_ender3_nut_small.gcode", MESH),
    ("bed_mesh_bicubic", "snippets/mesh_commands.gcode", ()),
    ("skew", "cura/cura413_ender3_nut_small.gcode", SKEW),
    ("skew", "snippets/skew_commands.gcode", ()),
    ("mesh_skew", "cura/cura413_ender3_nut_small.gcode", SKEW + MESH),
    ("mesh_skew", "snippets/mesh_skew_commands.gcode", ()),
)


def source(gcode: str, corpus_gcode: Path = CORPUS_GCODE) -> Path:
    """Where a run's G-code is read from."""
    if gcode.startswith("snippets/"):
        return SNIPPETS / gcode[len("snippets/"):]
    return corpus_gcode / gcode


def derive(gcode: str, commands: tuple[str, ...], out_dir: Path,
           corpus_gcode: Path = CORPUS_GCODE) -> Path:
    """The run's G-code file in out_dir (same name): the commands after the first G28."""
    data = source(gcode, corpus_gcode).read_bytes()
    out = out_dir / Path(gcode).name
    if commands:
        lines = data.split(b"\n")
        insert = [c.encode() for c in commands]
        at = next((i + 1 for i, line in enumerate(lines) if line.startswith(b"G28")), 0)
        data = b"\n".join(lines[:at] + insert + lines[at:])
    out.write_bytes(data)
    return out


def main() -> int:
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        for cfg, gcode, commands in RUNS:
            run_dir = Path(tmp) / cfg
            run_dir.mkdir(exist_ok=True)
            path = derive(gcode, commands, run_dir)
            out = HERE / cfg / (Path(gcode).stem + ".json")
            done = subprocess.run(
                [sys.executable, os.fspath(ORACLE), os.fspath(path), "--cfg",
                 os.fspath(HERE / cfg / "printer.cfg"), "--mark-every", "0", "--reference"],
                capture_output=True, check=False)
            if done.returncode:
                print("oracle failed:", cfg, gcode, done.stderr.decode()[-500:])
                failed += 1
                continue
            out.write_bytes(done.stdout)
            print("wrote", out.relative_to(HERE))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
