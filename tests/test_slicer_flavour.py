"""A file sliced for another firmware's G-code flavour says so in one line, with how to choose
Klipper's flavour in that slicer.

The slicer's own setting decides (PrusaSlicer/SuperSlicer/OrcaSlicer `gcode_flavor`, Cura's
`;FLAVOR:` header); a file whose settings name no flavour is judged by RepRapFirmware's own
commands (`G10 P<tool> S<temp>`, `M116`, `M568`). Pinned on the shared corpus's real files, on
files Debian's real PrusaSlicer 2.5 writes, and on the issue's hand-made RRF line. Klipper's
flavour is the slicer's Klipper flavour where its version has one (PrusaSlicer 2.6+,
SuperSlicer 2.3.56+, OrcaSlicer), else Marlin's (Klipper's docs/Slicers.md).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from kestimator import cli
from kestimator.slicers import read_slicer_settings

from .conftest import CORPUS, CORPUS_CFG, PROJECT, isolate_user_environment, require_program
from .test_hook_checks import isolated_environment
from .test_hook_prusaslicer import write_tube_stl

EXAMPLE = PROJECT / "examples" / "hex_nut_prusaslicer.gcode"
ABOUT = "not for Klipper, which skips or reads differently some of that firmware's commands"
PRUSA_MENU = "Printer Settings > General > Firmware > G-code flavor"
CURA_FIX = ("in Cura choose Preferences > Configure Cura > Printers > Machine Settings > "
            "G-code flavor: Marlin, and slice again")
PRUSA25_FIX = ("in PrusaSlicer choose %s: Marlin 2 (or Marlin), as Klipper's documentation "
               "advises, and slice again (PrusaSlicer 2.6 and newer offer Klipper)" % PRUSA_MENU)
GENERIC_FIX = ("choose the slicer's Klipper G-code flavor (Marlin where it has none) and slice "
               "again")
SLICE_TIMEOUT_S = 300


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    return isolate_user_environment(tmp_path, monkeypatch)


@pytest.mark.parametrize(("name", "expected"), [
    ("prusaslicer/gcodepreview_benchy_ps2.6.1.gcode",
     "sliced for Marlin 2 (slicer: gcode_flavor = marlin2), %s; in PrusaSlicer choose %s: "
     "Klipper, and slice again" % (ABOUT, PRUSA_MENU)),
    ("prusaslicer/libbgcode_mini_cube_ps2.8.1_arcs.gcode",
     "sliced for Marlin 2 (slicer: gcode_flavor = marlin2), %s; in PrusaSlicer choose %s: "
     "Klipper, and slice again" % (ABOUT, PRUSA_MENU)),
    ("cura/cura413_voron250_spiralize.gcode",
     "sliced for RepRapFirmware (slicer: ;FLAVOR:RepRap), %s; %s" % (ABOUT, CURA_FIX)),
    ("cura/cancelobj_cura5.0.0_inverted_pyramid.gcode",
     "sliced for RepRapFirmware (slicer: ;FLAVOR:RepRap), %s; %s" % (ABOUT, CURA_FIX)),
    # Klipper's flavour, or Marlin's where the slicer has no Klipper flavour: nothing to say.
    ("prusaslicer/bricklayers_cube10_ps2.9.0_klipper.gcode", None),
    ("orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode", None),
    ("superslicer/cancelobj_ss2.3.56_arcwelder.gcode", None),
    ("prusaslicer/ps25_nut_accelA_small.gcode", None),
    ("prusaslicer/ps25_torus_x4_labels_marlin.gcode", None),
    ("cura/cura413_ender3_nut_small.gcode", None),
    ("slic3r/slic3r130_torus_x3_accel.gcode", None),
    ("ideamaker/cancelobj_ideamaker4.2.0.gcode", None),
])
def test_a_corpus_files_flavour_is_judged_by_its_slicers_setting(
        name: str, expected: str | None, corpus_root: Path) -> None:
    _, settings = read_slicer_settings(CORPUS / "gcode" / name)
    assert settings.flavour == expected


def test_the_bundled_example_has_klippers_flavour_for_its_prusaslicer() -> None:
    # PrusaSlicer 2.5 has no Klipper flavour: Marlin 2 is what Klipper's documentation advises.
    assert read_slicer_settings(EXAMPLE)[1].flavour is None


def test_estimate_lists_the_flavour_line_and_its_json_carries_it(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    path = CORPUS / "gcode/cura/cura413_voron250_spiralize.gcode"
    line = "sliced for RepRapFirmware (slicer: ;FLAVOR:RepRap), %s; %s" % (ABOUT, CURA_FIX)
    assert cli.main(["estimate", str(path), "--printer-cfg", str(CORPUS_CFG)]) == 0
    out, err = capsys.readouterr()
    assert out.count(line) == 1 and "  warning: " + line in out
    assert line not in err
    assert cli.main(["estimate", str(path), "--printer-cfg", str(CORPUS_CFG), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["warnings"][0] == line


def test_the_issues_rrf_tool_temperature_line_tells_the_flavour_by_its_commands(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "print.gcode"
    path.write_text("G28\nG10 P0 S215 R150\nM116\nG1 X10 Y10 F3000\nG1 X20 E1\n")
    assert cli.main(["check", str(path)]) == 0
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if "sliced for" in line]
    assert said == ["kestimator: warning: %s: sliced for RepRapFirmware (its commands, e.g. "
                    "'G10 P0 S215 R150'), %s; %s" % (path, ABOUT, GENERIC_FIX)]


def test_klippers_own_g10_is_no_sign_of_another_firmware(tmp_path: Path) -> None:
    path = tmp_path / "print.gcode"
    path.write_text("G28\nG10\nG1 X10 Y10 F3000\nG11\nG1 X20 E1\nG10 ; retract\n")
    assert read_slicer_settings(path)[1].flavour is None


@pytest.fixture(scope="module")
def rrf_sliced(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tube Debian's real PrusaSlicer 2.5 slices for RepRapFirmware."""
    slicer = require_program("prusa-slicer")
    workdir = tmp_path_factory.mktemp("rrf")
    stl = workdir / "tube.stl"
    write_tube_stl(stl)
    out = workdir / "tube.gcode"
    env = {key: value for key, value in isolated_environment(workdir).items()
           if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run(
        [slicer, "--datadir", str(workdir / "datadir"), "--loglevel", "1", "--export-gcode",
         "--gcode-flavor", "reprapfirmware", "--layer-height", "0.3",
         "--first-layer-height", "0.3", "--output", str(out), str(stl)],
        env=env, capture_output=True, text=True, timeout=SLICE_TIMEOUT_S)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


def test_prusaslicer_25s_rrf_file_says_to_choose_marlin_2_on_inject(
        rrf_sliced: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out.gcode"
    assert cli.main(["inject", str(rrf_sliced), "-o", str(out), "--printer-cfg",
                     str(PROJECT / "examples" / "printer.cfg")]) == 0
    err = capsys.readouterr().err
    assert err == ("kestimator: warning: %s: sliced for RepRapFirmware (slicer: gcode_flavor "
                   "= reprapfirmware), %s; %s\n" % (rrf_sliced, ABOUT, PRUSA25_FIX))


def test_prusaslicers_rrf_file_without_its_settings_is_told_by_its_commands(
        rrf_sliced: Path, tmp_path: Path) -> None:
    path = tmp_path / "no-settings.gcode"
    lines = rrf_sliced.read_text().splitlines(keepends=True)
    path.write_text("".join(line for line in lines if not line.startswith("; gcode_flavor")))
    flavour = read_slicer_settings(path)[1].flavour
    # PrusaSlicer writes a tool's temperature as G10 S<temp> P<tool>, then waits with M116.
    assert flavour == ("sliced for RepRapFirmware (its commands, e.g. 'G10 S200 P0 ; set "
                       "temperature'), %s; %s" % (ABOUT, GENERIC_FIX))


def test_a_flavour_setting_decides_over_the_commands(tmp_path: Path, corpus_root: Path) -> None:
    # An OrcaSlicer file set to Klipper whose start G-code waits with M116: the setting says
    # Klipper, so nothing is said (the pre-flight names M116 as unknown).
    source = CORPUS / "gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode"
    path = tmp_path / "klipper-with-m116.gcode"
    path.write_bytes(b"M116\n" + source.read_bytes())
    assert read_slicer_settings(path)[1].flavour is None
