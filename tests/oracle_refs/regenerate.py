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

REFERENCES = (
    ("pa_shaper_commands", "snippets/pa_shaper_commands.gcode", "pa_is.cfg", 1),
    ("shaper_types", "snippets/shaper_types.gcode", "pa_is.cfg", 1),
    ("tool_changes", "snippets/tool_changes.gcode", "two_extruders.cfg", 1),
    ("cura_nut_pa_is", "corpus:gcode/cura/cura413_ender3_nut_small.gcode", "pa_is.cfg", 500),
    ("orca_cube_pa_is",
     "corpus:gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", "pa_is.cfg", 500),
)


def gcode_path(name: str) -> Path:
    """Where a reference's G-code file is."""
    if name.startswith("corpus:"):
        return CORPUS / name[len("corpus:"):]
    return HERE / name


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
    return 0


if __name__ == "__main__":
    sys.exit(main())
