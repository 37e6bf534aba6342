"""End to end with Debian's real `prusa-slicer`: slice, run our hook, check the exported G-code.

The test writes an STL, slices it with the PrusaSlicer CLI (`--export-gcode`, headless: the CLI
needs no display) and `--post-process` set to the line plugins/prusaslicer/README.md tells users
to paste, once with the installed `kestimator` command and once with the zipapp. The CLI runs
the scripts on the final file, as `$SHELL -c "<line> '<file>'"`. The exported file must then
carry our marker, Klipper-true M73 lines and Klipper's time in
`; estimated printing time (normal mode)`, all equal to `kestimator estimate` on that file,
with every other line as PrusaSlicer wrote it. A hook that fails must make PrusaSlicer fail
the export, show our one-line reason, and leave the G-code as PrusaSlicer wrote it.

PrusaSlicer 2.5 does not slice the same model to the same bytes twice (seams and infill order
vary run to run), so "as PrusaSlicer wrote it" is a snapshot taken by a first post-processing
line, the way users chain scripts: one line per script, run in turn on the same file.

Outside CI a missing prusa-slicer skips these tests; under CI (CI=true) it fails them:
.ci/run installs it.
"""

from __future__ import annotations

import math
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import PROJECT, require_program
from .test_hook_checks import (
    build_zipapp,
    hook_problems,
    isolated_environment,
    paste_line,
    untouched_lines,
)

EXAMPLE_CFG = PROJECT / "examples" / "printer.cfg"
# Where users keep things: folders with spaces, names with quotes. The README tells them to
# quote their own paths; PrusaSlicer quotes the G-code path it appends.
EXPORT_PARTS = ("My Prints", "tube's.gcode")
CFG_PARTS = ("Klipper config", "printer.cfg")
SLICE_TIMEOUT_S = 300
# What a Klipper user's PrusaSlicer 2.5 profile writes: 2.5 has no "klipper" flavor, so Marlin 2
# it is; M73 on; Klipper has no silent mode.
SLICER_OPTIONS = ("--gcode-flavor", "marlin2", "--remaining-times", "--no-silent-mode",
                  "--layer-height", "0.3", "--first-layer-height", "0.3")
# A first post-processing line that copies the file it is handed (argv[2], appended last by
# PrusaSlicer) to argv[1]. No ";": PrusaSlicer's CLI splits --post-process values there.
SNAPSHOT_CODE = ('__import__("shutil").copyfile(__import__("sys").argv[2], '
                 '__import__("sys").argv[1])')
# A tube: round walls make the look-ahead work, the hole gives inner perimeters.
TUBE_OUTER_R_MM = 12.0
TUBE_INNER_R_MM = 6.0
TUBE_HEIGHT_MM = 6.0
TUBE_SEGMENTS = 48
BED_CENTRE_MM = 100.0


def write_tube_stl(path: Path) -> None:
    """An ASCII STL of a closed tube standing on the bed, outward normals."""
    rings = []
    for radius in (TUBE_OUTER_R_MM, TUBE_INNER_R_MM):
        ring = []
        for i in range(TUBE_SEGMENTS):
            a = 2.0 * math.pi * i / TUBE_SEGMENTS
            ring.append((BED_CENTRE_MM + radius * math.cos(a),
                         BED_CENTRE_MM + radius * math.sin(a)))
        rings.append(ring)
    outer, inner = rings
    z0, z1 = 0.0, TUBE_HEIGHT_MM
    facets = []
    for i in range(TUBE_SEGMENTS):
        j = (i + 1) % TUBE_SEGMENTS
        o0, o1, i0, i1 = outer[i], outer[j], inner[i], inner[j]
        # outer wall faces out, inner wall faces the hole, top up, bottom down
        facets += [((*o0, z0), (*o1, z0), (*o1, z1)), ((*o0, z0), (*o1, z1), (*o0, z1)),
                   ((*i1, z0), (*i0, z0), (*i0, z1)), ((*i1, z0), (*i0, z1), (*i1, z1)),
                   ((*o0, z1), (*o1, z1), (*i1, z1)), ((*o0, z1), (*i1, z1), (*i0, z1)),
                   ((*o1, z0), (*o0, z0), (*i0, z0)), ((*o1, z0), (*i0, z0), (*i1, z0))]
    out = ["solid tube"]
    for facet in facets:
        out.append(" facet normal 0 0 0\n  outer loop")
        out += ["   vertex %.6f %.6f %.6f" % vertex for vertex in facet]
        out.append("  endloop\n endfacet")
    out.append("endsolid tube\n")
    path.write_text("\n".join(out), encoding="ascii")


@pytest.fixture(scope="module")
def prusa_slicer() -> Path:
    return Path(require_program("prusa-slicer"))


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("prusaslicer")


@pytest.fixture(scope="module")
def stl(workdir: Path) -> Path:
    path = workdir / "tube.stl"
    write_tube_stl(path)
    return path


@pytest.fixture(scope="module")
def zipapp(workdir: Path) -> Path:
    return build_zipapp(workdir)


@pytest.fixture(scope="module")
def printer_cfg(workdir: Path) -> Path:
    path = workdir.joinpath(*CFG_PARTS)
    path.parent.mkdir()
    shutil.copyfile(EXAMPLE_CFG, path)
    return path


def export_path(tmp_path: Path) -> Path:
    path = tmp_path.joinpath(*EXPORT_PARTS)
    path.parent.mkdir()
    return path


def export_gcode(prusa_slicer: Path, stl: Path, out: Path, datadir: Path,
                 post_process: str | None) -> subprocess.CompletedProcess[str]:
    """`prusa-slicer --export-gcode` as a user would run it, without any display."""
    env = {key: value for key, value in isolated_environment(datadir.parent).items()
           if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    args = [str(prusa_slicer), "--datadir", str(datadir), "--loglevel", "1",
            "--export-gcode", *SLICER_OPTIONS, "--output", str(out)]
    if post_process is not None:
        args += ["--post-process", post_process]
    return subprocess.run(args + [str(stl)], env=env, capture_output=True, text=True,
                          timeout=SLICE_TIMEOUT_S)


@pytest.fixture(scope="module")
def as_sliced(prusa_slicer: Path, stl: Path, workdir: Path) -> Path:
    """The G-code PrusaSlicer exports without any post-processing."""
    out = workdir / "plain" / "tube.gcode"
    out.parent.mkdir()
    proc = export_gcode(prusa_slicer, stl, out, workdir / "datadir", None)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


def snapshot_then(line: str, snapshot: Path) -> str:
    """Post-processing lines: copy what PrusaSlicer hands over to `snapshot`, then `line`."""
    return shlex.join([sys.executable, "-c", SNAPSHOT_CODE, str(snapshot)]) + "\n" + line


def test_prusaslicers_own_times_are_not_klippers(as_sliced: Path, printer_cfg: Path,
                                                 tmp_path: Path) -> None:
    # Without this the end-to-end test below could pass on a file the hook never touched.
    problems = hook_problems(as_sliced, printer_cfg, tmp_path)
    assert any("M73" in p for p in problems)
    assert any("Klipper's total" in p for p in problems)


@pytest.mark.parametrize("entry", ["command", "zipapp"])
def test_prusaslicer_exports_gcode_with_klipper_times_through_the_hook(
        entry: str, prusa_slicer: Path, stl: Path, zipapp: Path, printer_cfg: Path,
        workdir: Path, tmp_path: Path) -> None:
    out = export_path(tmp_path)
    snapshot = tmp_path / "as-sliced.gcode"

    proc = export_gcode(prusa_slicer, stl, out, workdir / "datadir",
                        snapshot_then(paste_line(entry, zipapp, printer_cfg), snapshot))

    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert sorted(p.name for p in out.parent.iterdir()) == [out.name]
    assert hook_problems(out, printer_cfg, tmp_path) == []
    assert untouched_lines(out.read_bytes()) == untouched_lines(snapshot.read_bytes())


@pytest.mark.parametrize("entry", ["command", "zipapp"])
def test_prusaslicer_reports_a_failing_hook_and_the_gcode_stays_as_sliced(
        entry: str, prusa_slicer: Path, stl: Path, zipapp: Path, workdir: Path,
        tmp_path: Path) -> None:
    out = export_path(tmp_path)
    snapshot = tmp_path / "as-sliced.gcode"
    missing_cfg = tmp_path.joinpath("no such folder", *CFG_PARTS)

    proc = export_gcode(prusa_slicer, stl, out, workdir / "datadir",
                        snapshot_then(paste_line(entry, zipapp, missing_cfg), snapshot))

    assert proc.returncode != 0
    report = proc.stdout + proc.stderr
    assert "Post-processing script" in report and "failed" in report
    ours = [line for line in report.splitlines() if line.startswith("kestimator: error: ")]
    assert ours and all(str(missing_cfg) in line for line in ours), report
    assert sorted(p.name for p in out.parent.iterdir()) == [out.name]
    assert out.read_bytes() == snapshot.read_bytes()
