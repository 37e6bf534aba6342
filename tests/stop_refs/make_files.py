"""Make the multi-colour G-code files of this folder with real slicers (kept in the folder:
the slicers' versions drift, the references must not).

    python3 tests/stop_refs/make_files.py     (Debian's prusa-slicer, CuraEngine, cura)

- `ps25_box_color_pause.gcode`: Debian's PrusaSlicer 2.5 (marlin2 flavour, remaining times on,
  so it writes Prusa firmware's `M73 C` time-to-change lines), a 14 x 14 x 2 mm box with a
  colour change at Z 0.8 (its color_change_gcode, M600) and a pause at Z 1.4 (pause_print_gcode
  set to PAUSE, as for Klipper), both made as PrusaSlicer's layer slider makes them: the
  3MF's `Metadata/Prusa_Slicer_custom_gcode_per_print_z.xml`.
- `cura413_box_pause_at_height.gcode`: Debian's CuraEngine 4.13 (creality_ender3 definition,
  layer height 0.2; `{machine_depth}` in its end G-code filled in as Cura's front end does),
  the same box, then Cura 4.13's own Pause at Height post-processing script
  (`PauseAtHeight.py` of Debian's cura package, run on the engine's layer chunks as Cura runs
  it) twice: at layer 4 with the Marlin method (M0), at layer 7 with the BQ method (M25).

Held out (made after the code they test, never used to write it; tests/test_stops.py holds
them to the oracle):

- `ps25_bar_two_colours_pause.gcode`: Debian's PrusaSlicer 2.5, a 24 x 10 x 2.4 mm bar at
  0.15 mm layers (0.2 mm first), two colour changes (M600 at Z 0.65 and Z 1.55) and a pause
  (PAUSE at Z 2.0) from the 3MF's layer-slider codes, the marlin2 flavour (2.5 has no klipper
  one) without remaining times.
- `cura413_bar_pause_at_height.gcode`: Debian's CuraEngine 4.13 (creality_ender3, layer
  height 0.15), the same bar, Cura's Pause at Height script at height 1.0 mm with the
  Marlin method (M0), then at layer 12 with the BQ method (M25).
- `orca150_accelctl_pauses.gcode` (made where it is used, `orca_paused`: the corpus stays
  out of the project): the corpus's OrcaSlicer 1.5.0 file
  (orcaslicer/accelctl_orca1.5.0_klipper_m204.gcode: its machine_pause_gcode is PAUSE; the
  corpus has no OrcaSlicer file with a pause in it), with a pause written in by hand at
  layers 8 and 17 as OrcaSlicer writes one from its layer slider (GCode.cpp's
  emit_custom_gcode_per_print_z): after the layer change and its layer_change_gcode, the
  processor's tag `; PAUSE_PRINTING` and then the machine_pause_gcode.

    python3 tests/stop_refs/make_files.py heldout      (only the held-out files)
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
CURA_RESOURCES = Path("/usr/share/cura/resources")
CURA_SCRIPTS = Path("/usr/lib/cura/plugins/PostProcessingPlugin")
BOX_MM = (14.0, 14.0, 2.0)
CUSTOM_GCODES = """<?xml version="1.0" encoding="utf-8"?>
<custom_gcodes_per_print_z>
<code print_z="0.8" type="0" extruder="1" color="#FF0000" extra="" gcode="M600"/>
<code print_z="1.4" type="1" extruder="1" color="" extra="Insert magnets" gcode="PAUSE"/>
<mode value="SingleExtruder"/>
</custom_gcodes_per_print_z>
"""


def write_box_stl(path: Path, size: tuple[float, float, float] = BOX_MM) -> Path:
    """An ASCII STL of a box."""
    corners = [(x * size[0], y * size[1], z * size[2]) for x, y, z in (
        (0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))]
    facets = ((0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4), (1, 2, 6),
              (1, 6, 5), (2, 3, 7), (2, 7, 6), (3, 0, 4), (3, 4, 7))
    lines = ["solid box"]
    for facet in facets:
        lines += [" facet normal 0 0 0", "  outer loop"]
        lines += ["   vertex %g %g %g" % corners[i] for i in facet]
        lines += ["  endloop", " endfacet"]
    path.write_text("\n".join(lines + ["endsolid box"]) + "\n", encoding="ascii")
    return path


def prusaslicer(work: Path) -> Path:
    stl = write_box_stl(work / "box.stl")
    plain = work / "box.3mf"
    subprocess.run(["prusa-slicer", "--export-3mf", "--center", "100,100", str(stl), "-o",
                    str(plain)], check=True, capture_output=True)
    stops = work / "box_stops.3mf"
    with zipfile.ZipFile(plain) as src, zipfile.ZipFile(stops, "w") as dst:
        for item in src.infolist():
            dst.writestr(item, src.read(item.filename))
        dst.writestr("Metadata/Prusa_Slicer_custom_gcode_per_print_z.xml", CUSTOM_GCODES)
    out = HERE / "ps25_box_color_pause.gcode"
    subprocess.run(["prusa-slicer", "--export-gcode", "--gcode-flavor", "marlin2",
                    "--remaining-times", "--pause-print-gcode", "PAUSE", "--layer-height", "0.2",
                    "--first-layer-height", "0.2", str(stops), "-o", str(out)],
                   check=True, capture_output=True)
    return out


class _Stack:
    """The global stack PauseAtHeight reads three machine settings from."""

    values = {"machine_firmware_retract": False, "machine_nozzle_temp_enabled": True,
              "layer_height_0": 0.2, "relative_extrusion": False}

    def getProperty(self, key: str, _what: str) -> object:  # noqa: N802 (Cura's name)
        return self.values[key]


class _Application:
    def getGlobalContainerStack(self) -> _Stack:  # noqa: N802 (Cura's name)
        return _Stack()


def _pause_at_height(layers: list[str], settings: dict[str, object]) -> list[str]:
    import importlib
    sys.path.insert(0, str(CURA_SCRIPTS.parent))
    from UM.Application import Application
    Application.getInstance = staticmethod(lambda *a, **k: _Application())  # type: ignore
    module = importlib.import_module("PostProcessingPlugin.scripts.PauseAtHeight")
    PauseAtHeight = module.PauseAtHeight  # noqa: N806 (Cura's class)
    script = PauseAtHeight.__new__(PauseAtHeight)
    defaults = {"pause_at": "height", "pause_layer": 1, "disarm_timeout": 0,
                "retraction_amount": 0, "retraction_speed": 25, "extrude_amount": 0,
                "extrude_speed": 3.3333, "head_park_enabled": True, "head_park_x": 190,
                "head_park_y": 190, "head_move_z": 15.0, "redo_layer": False,
                "standby_temperature": 0, "display_text": "",
                "custom_gcode_before_pause": "", "custom_gcode_after_pause": ""}
    values = {**defaults, **settings}
    script.getSettingValueByKey = values.get  # type: ignore[method-assign]
    return script.execute(layers)


def _chunks(text: str) -> list[str]:
    """The engine's output as Cura holds it: the header, then one chunk per ;LAYER:."""
    chunks = [""]
    for line in text.splitlines(keepends=True):
        if line.startswith(";LAYER:"):
            chunks.append("")
        chunks[-1] += line
    return chunks


def cura(work: Path) -> Path:
    stl = write_box_stl(work / "box.stl")
    raw = work / "box.gcode"
    env = dict(os.environ, CURA_ENGINE_SEARCH_PATH=os.pathsep.join(
        str(CURA_RESOURCES / sub) for sub in ("definitions", "extruders")))
    subprocess.run(["CuraEngine", "slice", "-j",
                    str(CURA_RESOURCES / "definitions" / "creality_ender3.def.json"),
                    "-s", "center_object=true", "-s", "layer_height=0.2", "-l", str(stl),
                    "-o", str(raw)], check=True, capture_output=True, env=env)
    # Cura's front end fills the machine settings into the start/end G-code before the engine
    # runs; the engine run alone leaves the ender3's one placeholder (machine_depth: 235).
    layers = _chunks(raw.read_text().replace("{machine_depth}", "235"))
    layers = _pause_at_height(layers, {"pause_at": "layer_no", "pause_layer": 4,
                                       "pause_method": "marlin"})
    layers = _pause_at_height(layers, {"pause_at": "layer_no", "pause_layer": 7,
                                       "pause_method": "bq"})
    out = HERE / "cura413_box_pause_at_height.gcode"
    out.write_text("".join(layers))
    return out


HELDOUT_CODES = """<?xml version="1.0" encoding="utf-8"?>
<custom_gcodes_per_print_z>
<code print_z="0.65" type="0" extruder="1" color="#FF0000" extra="" gcode="M600"/>
<code print_z="1.55" type="0" extruder="1" color="#00FF00" extra="" gcode="M600"/>
<code print_z="2" type="1" extruder="1" color="" extra="Check the bridge" gcode="PAUSE"/>
<mode value="SingleExtruder"/>
</custom_gcodes_per_print_z>
"""
BAR_MM = (24.0, 10.0, 2.4)
ORCA_SRC = HERE.parents[2] / "shared" / "corpus" / "gcode" / "orcaslicer" / \
    "accelctl_orca1.5.0_klipper_m204.gcode"
ORCA_PAUSE_LAYERS = (8, 17)


def prusaslicer_heldout(work: Path) -> Path:
    stl = write_box_stl(work / "bar.stl", BAR_MM)
    plain = work / "bar.3mf"
    subprocess.run(["prusa-slicer", "--export-3mf", "--center", "110,90", str(stl), "-o",
                    str(plain)], check=True, capture_output=True)
    stops = work / "bar_stops.3mf"
    with zipfile.ZipFile(plain) as src, zipfile.ZipFile(stops, "w") as dst:
        for item in src.infolist():
            dst.writestr(item, src.read(item.filename))
        dst.writestr("Metadata/Prusa_Slicer_custom_gcode_per_print_z.xml", HELDOUT_CODES)
    out = HERE / "ps25_bar_two_colours_pause.gcode"
    subprocess.run(["prusa-slicer", "--export-gcode", "--gcode-flavor", "marlin2",
                    "--pause-print-gcode", "PAUSE", "--layer-height", "0.15",
                    "--first-layer-height", "0.2", str(stops), "-o", str(out)],
                   check=True, capture_output=True)
    return out


def cura_heldout(work: Path) -> Path:
    stl = write_box_stl(work / "bar.stl", BAR_MM)
    raw = work / "bar.gcode"
    env = dict(os.environ, CURA_ENGINE_SEARCH_PATH=os.pathsep.join(
        str(CURA_RESOURCES / sub) for sub in ("definitions", "extruders")))
    subprocess.run(["CuraEngine", "slice", "-j",
                    str(CURA_RESOURCES / "definitions" / "creality_ender3.def.json"),
                    "-s", "center_object=true", "-s", "layer_height=0.15", "-l", str(stl),
                    "-o", str(raw)], check=True, capture_output=True, env=env)
    layers = _chunks(raw.read_text().replace("{machine_depth}", "235"))
    layers = _pause_at_height(layers, {"pause_at": "height", "pause_height": 1.0,
                                       "pause_method": "marlin"})
    layers = _pause_at_height(layers, {"pause_at": "layer_no", "pause_layer": 12,
                                       "pause_method": "bq"})
    out = HERE / "cura413_bar_pause_at_height.gcode"
    out.write_text("".join(layers))
    return out


def orca_paused(src: Path = ORCA_SRC) -> bytes:
    """The OrcaSlicer file with its pauses written in (see the module's docstring)."""
    lines = src.read_bytes().split(b"\n")
    pause = [b"; machine_pause_gcode = "]
    gcode = [line for line in lines if line.startswith(pause[0])][0][len(pause[0]):]
    out_lines: list[bytes] = []
    layer = 0
    waiting = False
    for line in lines:
        if line.startswith(b";LAYER_CHANGE"):
            layer += 1
            waiting = layer in ORCA_PAUSE_LAYERS
        out_lines.append(line)
        # layer_change_gcode = ;AFTER_LAYER_CHANGE\n;[layer_z]: after its second line.
        if waiting and out_lines[-2:-1] == [b";AFTER_LAYER_CHANGE"]:
            out_lines += [b"; PAUSE_PRINTING", gcode]
            waiting = False
    return b"\n".join(out_lines)


def main() -> int:
    makers = (prusaslicer, cura)
    if sys.argv[1:] == ["heldout"]:
        makers = (prusaslicer_heldout, cura_heldout)
    with tempfile.TemporaryDirectory() as tmp:
        for make in makers:
            work = Path(tmp) / make.__name__
            work.mkdir()
            print("wrote", make(work).relative_to(HERE))
    return 0


if __name__ == "__main__":
    shutil.which("prusa-slicer") or sys.exit("needs Debian's prusa-slicer")
    sys.exit(main())
