"""What a user sees (issue 17): the exact lines on stdout and stderr, in plain text and rich.

Guessed limits are said in one line with the fix in every command and in kestimator-compat;
files that are not G-code (3MF, STL, a Klipper config) are refused in one line; no control
byte from a file reaches the terminal; an injected file's slicer estimate comes from our
marker; the marker names no directory; untimed commands are one grouped line.
"""

from __future__ import annotations

import os
import re
import shutil
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from kestimator import cli, compat
from kestimator.config.resolve import GUESS_FIX

from .conftest import CORPUS, CORPUS_CFG, PROJECT, isolate_user_environment

NUT = CORPUS / "gcode/prusaslicer/ps25_nut_accelA_small.gcode"
TORUS = CORPUS / "gcode/prusaslicer/ps25_torus_x4_labels_marlin.gcode"
GUESSED_NUT = (
    "kestimator: warning: no printer.cfg or Moonraker given: limits are the slicer's guesses "
    "and Klipper's defaults (max_velocity 300, max_accel 3000), so times are approximate, "
    "moves are not range-checked and G28 homes to 0; "
    "pass --printer-cfg PATH or --moonraker URL, or set printer_cfg or moonraker in the "
    "profile (~/.config/kestimator/config.toml)\n")
ANSI_RE = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No profile, a private cache, no slicer hook environment, no forced rich."""
    return isolate_user_environment(tmp_path, monkeypatch)


def run(*args: str, env: dict[str, str] | None = None,
        program: str = "kestimator") -> subprocess.CompletedProcess[str]:
    module = "kestimator" if program == "kestimator" else "kestimator.compat"
    return subprocess.run([sys.executable, "-m", module, *args],
                          env=dict(os.environ, PYTHONPATH=str(PROJECT), **(env or {})),
                          capture_output=True, text=True, timeout=300)


# Honest: guessed limits


def test_every_command_says_guessed_limits_on_stderr_in_one_line_with_the_fix(
        tmp_path: Path, corpus_root: Path) -> None:
    out = tmp_path / "out.gcode"
    for argv in (["estimate", str(NUT)], ["estimate", str(NUT), "-q"],
                 ["estimate", str(NUT), "--json"], ["inject", str(NUT), "-o", str(out)],
                 ["report", str(NUT), "-o", str(tmp_path / "r.html")],
                 ["limits", str(NUT)]):
        proc = run(*argv)
        assert proc.returncode == 0, proc.stderr
        assert proc.stderr == GUESSED_NUT, argv
    proc = run("inject", str(NUT), "-o", str(out))
    assert proc.stdout == ("kestimator: %s: Klipper time 3m 32s (approximate: the limits are "
                           "guesses), the slicer said 3m 20s; wrote 133 M73 lines\n" % out)
    proc = run("report", str(NUT), "-o", str(tmp_path / "r.html"))
    assert proc.stdout == ("kestimator: wrote %s (Klipper time 3m 32s, approximate: the "
                           "limits are guesses)\n" % (tmp_path / "r.html"))


def test_the_summary_marks_a_guessed_time_approximate_and_a_real_one_not(
        corpus_root: Path) -> None:
    guessed = run("estimate", str(NUT))
    lines = guessed.stdout.splitlines()
    assert lines[1] == "  Klipper time : 3m 32s (211.793 s), approximate: the limits are guesses"
    # Said once, on stderr: not repeated among the summary's warnings.
    assert "no printer.cfg or Moonraker given" not in guessed.stdout
    real = run("estimate", str(NUT), "--printer-cfg", str(CORPUS_CFG))
    assert real.stderr == "" and real.stdout.splitlines()[1] == \
        "  Klipper time : 3m 42s (222.102 s)"
    doc = __import__("json").loads(run("estimate", str(NUT), "--json").stdout)
    assert doc["limits_guessed"] is True
    assert any(w.startswith("no printer.cfg or Moonraker given") and w.endswith(GUESS_FIX)
               for w in doc["warnings"])


def test_rich_summary_marks_a_guessed_time_approximate(corpus_root: Path) -> None:
    pytest.importorskip("rich")
    proc = run("estimate", str(NUT), env={cli.RICH_ENV: "1", "COLUMNS": "100"})
    plain = ANSI_RE.sub("", proc.stdout)
    assert "│ Klipper time  3m 32s  211.793 s  approximate: the limits are guesses" in plain
    assert proc.stderr == GUESSED_NUT


def test_a_failing_run_is_still_one_line(tmp_path: Path, corpus_root: Path) -> None:
    empty = tmp_path / "empty.gcode"
    empty.write_bytes(b"")
    proc = run("estimate", str(empty))
    assert proc.returncode == 1
    assert proc.stderr == "kestimator: error: %s: the file is empty\n" % empty


def test_compat_post_process_says_guessed_limits_with_a_fix_it_accepts(
        tmp_path: Path, corpus_root: Path) -> None:
    work = tmp_path / "nut.gcode"
    shutil.copyfile(NUT, work)
    proc = run("post-process", str(work), program="compat")
    assert proc.returncode == 0, proc.stderr
    warning = [line for line in proc.stderr.splitlines()
               if "no printer.cfg or Moonraker given" in line]
    assert warning == ["kestimator-compat: warning: no printer.cfg or Moonraker given: limits "
                       "are the slicer's guesses and Klipper's defaults (max_velocity 300, "
                       "max_accel 3000), so times are approximate, moves are not "
                       "range-checked and G28 homes to 0; " + compat.COMPAT_GUESS_FIX]
    # It never advises an option it rejects.
    assert "--printer-cfg" not in proc.stderr
    rejected = run("--printer-cfg", str(CORPUS_CFG), "estimate", str(NUT), program="compat")
    assert rejected.returncode == 2
    assert "--config_moonraker_url" in compat.COMPAT_GUESS_FIX


# Honest: files that are not G-code


def _binary_stl(triangles: int) -> bytes:
    header = b"binary STL written by the test".ljust(80, b" ")
    facet = struct.pack("<12fH", 0, 0, 1, 0, 0, 0, 10, 0, 0, 0, 10, 0, 0)
    return header + struct.pack("<I", triangles) + facet * triangles


ASCII_STL = (b"solid cube\n  facet normal 0 0 1\n    outer loop\n      vertex 0 0 0\n"
             b"      vertex 10 0 0\n      vertex 0 10 0\n    endloop\n  endfacet\n"
             b"endsolid cube\n")


def _three_mf(path: Path, with_gcode: bool) -> None:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("[Content_Types].xml", "<Types/>")
        z.writestr("3D/3dmodel.model", "<model/>")
        if with_gcode:  # Bambu Studio / OrcaSlicer's plate.gcode.3mf
            z.writestr("Metadata/plate_1.gcode", NUT.read_bytes())


@pytest.mark.parametrize("name, make, said", [
    ("plate.gcode.3mf", lambda p: _three_mf(p, True),
     "a 3MF project, not G-code: export plain G-code from the slicer and give that file"),
    ("model.3mf", lambda p: _three_mf(p, False),
     "a 3MF project, not G-code: export plain G-code from the slicer and give that file"),
    ("cube.stl", lambda p: p.write_bytes(_binary_stl(12)),
     "an STL model, not G-code: slice it first and give the G-code file"),
    ("cube_ascii.gcode", lambda p: p.write_bytes(ASCII_STL),
     "an STL model, not G-code: slice it first and give the G-code file"),
    ("printer.cfg", lambda p: shutil.copyfile(CORPUS_CFG, p),
     "a Klipper config file, not G-code: did you mean --printer-cfg?"),
])
def test_files_that_are_not_gcode_are_refused_in_one_line_and_left_intact(
        tmp_path: Path, corpus_root: Path, name: str, make: object, said: str) -> None:
    path = tmp_path / name
    make(path)  # type: ignore[operator]
    before = path.read_bytes()
    for command in (["estimate"], ["inject"], ["report", "-o", str(tmp_path / "r.html")],
                    ["limits"]):
        proc = run(command[0], str(path), *command[1:])
        assert proc.returncode == 1, (command, proc.stderr)
        assert proc.stderr == "kestimator: error: %s: %s\n" % (path, said), command
        assert proc.stdout == ""
    assert path.read_bytes() == before
    proc = run("post-process", str(path), program="compat")
    assert proc.returncode == 1 and proc.stderr == "kestimator-compat: error: %s: %s\n" % (
        path, said)
    assert path.read_bytes() == before


@pytest.mark.parametrize("real", [
    "/usr/share/cura/resources/meshes/kossel_platform.3mf",
    "/usr/share/cura/resources/meshes/anycubic_vyper_platform.stl",
])
def test_real_3mf_and_stl_files_from_cura_are_refused(real: str) -> None:
    if not os.path.exists(real):
        pytest.skip("Cura's meshes are not installed")
    proc = run("estimate", real)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1
    assert ("a 3MF project" if real.endswith(".3mf") else "an STL model") in proc.stderr


def test_no_control_byte_from_the_file_reaches_the_terminal(
        tmp_path: Path, corpus_root: Path) -> None:
    path = tmp_path / "hostile\x1b[2Jname.gcode"
    data = NUT.read_bytes().replace(
        b"M73 P0 R3\n", b"M73 P0 R3\nEVIL\x1b]0;owned\x07MACRO\n\xc2\x9bX\x1b[31m\n", 1)
    assert data != NUT.read_bytes()
    path.write_bytes(data)
    for argv in (["estimate", str(path), "-v"], ["estimate", str(path)],
                 ["inject", str(path), "-o", str(tmp_path / "o.gcode")],
                 ["limits", str(path)]):
        for env in ({}, {cli.RICH_ENV: "1"}):
            proc = run(*argv, env=env)
            assert proc.returncode == 0, proc.stderr
            text = ANSI_RE.sub("", proc.stdout) if env else proc.stdout
            for shown in (text, proc.stderr):
                assert not re.search("[\x00-\x08\x0b-\x1f\x7f-\x9f]", shown), (argv, shown)
    verbose = run("estimate", str(path), "-v").stdout
    assert "hostile\\x1b[2Jname.gcode" in verbose
    assert "EVIL\\x1b]0" in verbose
    missing = run("estimate", str(tmp_path / "gone\x07.gcode"))
    assert missing.returncode == 1 and "gone\\x07.gcode" in missing.stderr


# Honest: an injected file's slicer estimate, and the marker


def test_an_injected_file_reports_the_slicers_own_estimate_from_the_marker(
        tmp_path: Path, corpus_root: Path) -> None:
    out = tmp_path / "out.gcode"
    assert run("inject", str(NUT), "-o", str(out), "--printer-cfg",
               str(CORPUS_CFG)).returncode == 0
    proc = run("estimate", str(out), "--printer-cfg", str(CORPUS_CFG))
    assert proc.stdout.splitlines()[1:4] == [
        "  Klipper time : 3m 42s (222.102 s)",
        "  Slicer       : 3m 20s, PrusaSlicer 2.5.0",
        "  Difference   : 22s shorter than Klipper (-10.0 %)"]
    report = tmp_path / "r.html"
    assert run("report", str(out), "-o", str(report), "--printer-cfg",
               str(CORPUS_CFG)).returncode == 0
    assert "3m 20s" in report.read_text(encoding="utf-8")


def test_the_marker_records_the_kind_of_source_and_a_file_name_never_a_directory(
        tmp_path: Path, corpus_root: Path) -> None:
    home = tmp_path / "home" / "pi" / "printer_data" / "config"
    home.mkdir(parents=True)
    shutil.copyfile(CORPUS_CFG, home / "printer.cfg")
    cases = ((["--printer-cfg", str(home / "printer.cfg")], "printer_cfg:printer.cfg"),
             (["--printer-cfg", str(home / "printer.cfg"), "--set", "max_accel=2000"],
              "printer_cfg:printer.cfg+set"),
             ([], "guessed:slicer+defaults"))
    for options, recorded in cases:
        out = tmp_path / "out.gcode"
        assert run("inject", str(NUT), "-o", str(out), *options).returncode == 0
        marker = [line for line in out.read_text().splitlines()
                  if line.startswith("; kestimator ")]
        assert len(marker) == 1 and marker[0].endswith(" limits=" + recorded), marker
        assert str(tmp_path) not in out.read_text()


# Quiet: untimed commands grouped


def test_untimed_commands_are_one_grouped_line_and_listed_with_verbose(
        tmp_path: Path, corpus_root: Path) -> None:
    path = tmp_path / "klipper.gcode"
    extra = (b"EXCLUDE_OBJECT_DEFINE NAME=a\nSET_PRINT_STATS_INFO TOTAL_LAYER=27\n"
             b"PRINT_START\nTIMELAPSE_TAKE_FRAME\nEXCLUDE_OBJECT_START NAME=a\n"
             b"M900 K0.04\n")
    path.write_bytes(NUT.read_bytes().replace(b"M73 P0 R3\n", b"M73 P0 R3\n" + extra, 1))
    proc = run("estimate", str(path), "--printer-cfg", str(CORPUS_CFG))
    lines = proc.stdout.splitlines()
    assert ("  3 macros, 3 module commands and 1 unknown command: their time is not counted "
            "(--verbose lists them)") in lines
    assert "is not a Klipper command" not in proc.stdout
    verbose = run("estimate", str(path), "--printer-cfg", str(CORPUS_CFG), "-v").stdout
    # The file's own start and end macros, and the ones added.
    assert "  Not counted, macros: PRINT_END x1, PRINT_START x2, TIMELAPSE_TAKE_FRAME x1" \
        in verbose
    assert ("  Not counted, module commands: EXCLUDE_OBJECT_DEFINE x1, EXCLUDE_OBJECT_START x1, "
            "SET_PRINT_STATS_INFO x1") in verbose
    assert "  Not counted, unknown commands: M900 x1" in verbose
    assert "'PRINT_START' is not a Klipper command" in verbose
    doc = __import__("json").loads(run("estimate", str(path), "--printer-cfg",
                                       str(CORPUS_CFG), "--json").stdout)
    assert doc["untimed_commands"] == {
        "macro": {"PRINT_END": 1, "PRINT_START": 2, "TIMELAPSE_TAKE_FRAME": 1},
        "module": {"EXCLUDE_OBJECT_DEFINE": 1, "EXCLUDE_OBJECT_START": 1,
                   "SET_PRINT_STATS_INFO": 1},
        "unknown": {"M900": 1}}
    rich = ANSI_RE.sub("", run("estimate", str(path), "--printer-cfg", str(CORPUS_CFG),
                               env={cli.RICH_ENV: "1", "COLUMNS": "120"}).stdout)
    assert ("3 macros, 3 module commands and 1 unknown command: their time is not counted "
            "(--verbose lists them)") in rich
