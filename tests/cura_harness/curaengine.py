"""Real CuraEngine G-code for the tests: a cube sliced by Debian's ``CuraEngine`` 4.13.

Owns the STL the tests slice (a 10 mm cube, written as ASCII STL) and the command line, the
one the corpus' CuraEngine files were made with, less the resolved profile:
``CuraEngine slice -j <definition> -s key=value ... -l model.stl -o out.gcode`` with Debian's
``creality_ender3`` machine definition. ``CURA_ENGINE_SEARCH_PATH`` lets the engine find the
definitions it inherits from and the extruder definitions.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

CURA_RESOURCES = Path("/usr/share/cura/resources")
MACHINE_DEFINITION = CURA_RESOURCES / "definitions" / "creality_ender3.def.json"
CUBE_MM = 10.0
SLICE_TIMEOUT_S = 120
SETTINGS = {"center_object": "true"}
# The cube's corners and its 12 triangles (outward normals, counter-clockwise).
_CORNERS = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1),
            (0, 1, 1))
_FACETS = ((0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4), (1, 2, 6),
           (1, 6, 5), (2, 3, 7), (2, 7, 6), (3, 0, 4), (3, 4, 7))


def find_curaengine() -> str | None:
    """The CuraEngine program and Debian's machine definitions, or None without either."""
    program = shutil.which("CuraEngine")
    if program is None or not MACHINE_DEFINITION.is_file():
        return None
    return program


def write_cube_stl(path: Path, size_mm: float = CUBE_MM) -> Path:
    """An ASCII STL of a cube with ``size_mm`` sides."""
    lines = ["solid cube"]
    for facet in _FACETS:
        lines.append(" facet normal 0 0 0")
        lines.append("  outer loop")
        for corner in facet:
            lines.append("   vertex %g %g %g" % tuple(c * size_mm for c in _CORNERS[corner]))
        lines.append("  endloop")
        lines.append(" endfacet")
    lines.append("endsolid cube")
    path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return path


def slice_cube(program: str, directory: Path) -> Path:
    """Slice the cube with CuraEngine into ``directory``; the G-code's path."""
    model = write_cube_stl(directory / "cube.stl")
    output = directory / "cube.gcode"
    argv = [program, "slice", "-j", str(MACHINE_DEFINITION)]
    for key, value in SETTINGS.items():
        argv += ["-s", "%s=%s" % (key, value)]
    argv += ["-l", str(model), "-o", str(output)]
    search_path = os.pathsep.join(str(CURA_RESOURCES / sub) for sub in ("definitions",
                                                                           "extruders"))
    env = dict(os.environ, CURA_ENGINE_SEARCH_PATH=search_path)
    proc = subprocess.run(argv, capture_output=True, text=True, env=env,
                          timeout=SLICE_TIMEOUT_S)
    if proc.returncode != 0 or not output.is_file():
        raise RuntimeError("CuraEngine failed (%d): %s" % (proc.returncode, proc.stderr[-2000:]))
    return output
