"""What `estimate` and `inject` print: the documented JSON, plain text, rich, progress, errors."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from kestimator import __version__, cli, cli_render
from kestimator.cli_output import read_slicer_filament
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file
from kestimator.rewrite import inject_file

from .conftest import CORPUS, CORPUS_CFG, PROJECT, isolate_user_environment

NUT = CORPUS / "gcode/prusaslicer/ps25_nut_accelA_small.gcode"          # M204 P warnings
TORUS = CORPUS / "gcode/prusaslicer/ps25_torus_x4_labels_marlin.gcode"  # warnings, M73
NO_ESTIMATE = CORPUS / "gcode/slic3r/slic3r130_torus_x3_accel.gcode"    # Slic3r writes none
CURA = CORPUS / "gcode/cura/cura413_ender3_nut_small.gcode"
ORCA = CORPUS / "gcode/orcaslicer/helixscreen_stand_orca2.3.1_klipper.gcode"
# Every field docs/CLI.md documents for `estimate --json`, with its JSON type(s).
ESTIMATE_FIELDS: dict[str, tuple[type, ...]] = {
    "schema": (int,), "kestimator": (str,), "file": (str,), "total_s": (float, int),
    "first_layer_s": (float, type(None)), "layer_count": (int,), "layers": (list,),
    "features": (dict,), "objects": (dict,), "object_remaining": (list,), "slicer": (dict,),
    "filament": (dict,),
    "limits_source": (str,),
    "n_moves": (int,), "n_lines": (int,), "ignored_commands": (dict,), "warnings": (list,),
    "ignored_commands_unlisted": (int,),
    "warnings_dropped": (int,), "limits_guessed": (bool,), "untimed_commands": (dict,),
    "parts": (dict,), "commands": (dict,), "preflight": (list,),
    "stops": (list,), "stops_unlisted": (int,),
}
SLICER_FIELDS = ("name", "version", "estimate_s", "first_layer_estimate_s", "difference_s",
                 "difference_pct")
PARTS_FIELDS = ("motion_s", "added_s", "before_first_extrusion_s", "print_duration_s",
                "total_s", "first_extrusion_t", "sources", "untimed_macros", "untimed_waits")
FILAMENT_FIELDS = ("extruded_mm", "diameter_mm", "volume_cm3", "density_g_cm3", "weight_g",
                   "slicer_mm", "slicer_g")


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No profile, a private cache, no slicer hook environment, no forced rich."""
    return isolate_user_environment(tmp_path, monkeypatch)


def run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    full_env = dict(os.environ, PYTHONPATH=str(PROJECT), COLUMNS="100", **(env or {}))
    full_env.pop("NO_COLOR", None)
    return subprocess.run([sys.executable, "-m", "kestimator", *args], capture_output=True,
                          text=True, env=full_env, timeout=300)


def estimate_json(capsys: pytest.CaptureFixture[str], path: Path, *argv: str) -> dict[str, Any]:
    assert cli.main(["estimate", str(path), "--printer-cfg", str(CORPUS_CFG), "--json",
                     *argv]) == cli.EXIT_OK
    return json.loads(capsys.readouterr().out)


def estimate_text(capsys: pytest.CaptureFixture[str], path: Path, *argv: str) -> str:
    assert cli.main(["estimate", str(path), "--printer-cfg", str(CORPUS_CFG), *argv]) == 0
    return capsys.readouterr().out


def test_json_has_every_documented_field_with_its_type(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    doc = estimate_json(capsys, NUT)
    assert set(doc) == set(ESTIMATE_FIELDS)
    for field, types in ESTIMATE_FIELDS.items():
        assert isinstance(doc[field], types), field
    assert doc["schema"] == cli.JSON_SCHEMA_VERSION == 1 and doc["kestimator"] == __version__
    assert tuple(doc["slicer"]) == SLICER_FIELDS
    assert tuple(doc["filament"]) == FILAMENT_FIELDS
    assert tuple(doc["parts"]) == PARTS_FIELDS
    docs = (PROJECT / "docs/CLI.md").read_text(encoding="utf-8")
    for field in (*ESTIMATE_FIELDS, *SLICER_FIELDS, *FILAMENT_FIELDS, *PARTS_FIELDS,
                  "duration_s",
                  "output", "m73_written"):
        assert "`%s`" % field in docs, field


def test_json_summary_figures_agree_with_each_other(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    doc = estimate_json(capsys, NUT)
    assert doc["total_s"] == pytest.approx(222.102, abs=0.01)
    slicer = doc["slicer"]
    assert slicer["name"] == "PrusaSlicer" and slicer["estimate_s"] == 200.0
    assert slicer["difference_s"] == pytest.approx(200.0 - doc["total_s"], abs=1e-6)
    assert slicer["difference_pct"] == pytest.approx(
        100 * slicer["difference_s"] / doc["total_s"], abs=1e-3)
    layers = doc["layers"]
    assert doc["layer_count"] == len(layers) == 27
    assert doc["first_layer_s"] == layers[0]["duration_s"]
    assert sum(layer["duration_s"] for layer in layers) == pytest.approx(
        doc["total_s"] - layers[0]["t"], abs=1e-4)
    assert sum(doc["features"].values()) == pytest.approx(doc["total_s"], abs=1e-4)
    assert any("M204" in warning and ":39:" in warning for warning in doc["warnings"])


def test_filament_is_what_the_moves_extrude_and_matches_the_slicer(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    doc = estimate_json(capsys, NUT)
    filament = doc["filament"]
    assert filament["slicer_mm"] == 280.19 and filament["diameter_mm"] == 1.75
    # PrusaSlicer counts the extrusion; its total differs from the net E by the wipe only.
    assert filament["extruded_mm"] == pytest.approx(filament["slicer_mm"], rel=0.005)
    area_mm2 = math.pi * 1.75 ** 2 / 4
    assert filament["volume_cm3"] == pytest.approx(filament["extruded_mm"] * area_mm2 / 1000,
                                                   abs=1e-3)
    # The file's filament_density = 0 means "not set": no weight is made up.
    assert filament["density_g_cm3"] is None and filament["weight_g"] is None


def test_filament_weight_comes_from_the_density_the_slicer_states(corpus_root: Path) -> None:
    stated = read_slicer_filament(str(ORCA))
    # Four extruders, only the second used: lengths are summed, density is the first set.
    assert stated == {"slicer_mm": 3022.64, "slicer_g": 9.02, "diameter_mm": 1.75,
                      "density_g_cm3": 1.24}
    assert read_slicer_filament(str(CURA))["slicer_mm"] == pytest.approx(271.185)
    limits, _ = limits_from_printer_cfg(CORPUS_CFG)
    est = estimate_file(str(ORCA), limits)
    assert est.filament_mm == pytest.approx(3022.64, rel=0.005)


def test_file_without_a_slicer_estimate_says_so_in_json_and_text(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    doc = estimate_json(capsys, NO_ESTIMATE)
    assert doc["slicer"]["name"] == "Slic3r" and doc["slicer"]["estimate_s"] is None
    assert doc["slicer"]["difference_s"] is None and doc["slicer"]["difference_pct"] is None
    assert doc["first_layer_s"] is None and doc["layers"] == []
    out = estimate_text(capsys, NO_ESTIMATE)
    assert "  Slicer       : Slic3r 1.3.0, no estimate in the file\n" in out
    assert "Difference" not in out and "First layer" not in out
    assert "  Filament     : 7723.4 mm (18.58 cm3); the slicer says 7725.4 mm\n" in out


def test_plain_text_summary_shows_times_difference_filament_source_and_warnings(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    out = estimate_text(capsys, NUT)
    assert out.splitlines()[:8] == [
        str(NUT),
        "  Klipper time : 3m 42s (222.102 s)",
        "  Slicer       : 3m 20s, PrusaSlicer 2.5.0",
        "  Difference   : 22s shorter than Klipper (-10.0 %)",
        "  First layer  : 26s",
        "  Layers       : 27",
        "  Filament     : 279.4 mm (0.67 cm3); the slicer says 280.2 mm",
        "  Limits from  : %s" % CORPUS_CFG]
    assert "  Time per feature:\n    Internal infill                  1m 03s  28.2 %\n" in out
    assert "Time per layer" not in out and "\x1b[" not in out
    assert "  warning: %s:39: M204 without S needs both P and T" % NUT in out
    torus = estimate_text(capsys, TORUS)
    assert "Difference   : " in torus
    assert "  Pre-flight: 2 commands skipped" in torus
    # Macros are one grouped line at the end, not a warning each; then, once, the heater
    # waits and homing that count as 0 s (issue 36).
    assert torus.endswith("\n  2 macros: their time is not counted (--verbose lists them)\n"
                          "  2 heater waits count as 0 s: time each with --heat-time S (or "
                          "heat_time_s in the profile), or let `kestimator learn` time the "
                          "printer's start\n")
    assert "is not a Klipper command" not in torus


def test_layers_option_adds_one_row_per_layer(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    out = estimate_text(capsys, NUT, "--layers")
    assert out.startswith("Time per layer (the summary follows the table):\n")
    table = out.split("Time per layer (the summary follows the table):\n")[1].splitlines()
    assert table[0].split() == ["layer", "line", "starts", "takes"]
    assert table[1].split() == ["1", "25", "0s", "26s"]
    assert table[27].split()[:2] == ["27", "5034"]
    # The summary comes after the 27 rows, so it is what stays on screen.
    assert table[28] == str(NUT) and table[29].startswith("  Klipper time : 3m 42s")


def test_quiet_estimate_prints_only_the_seconds(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    total = estimate_json(capsys, NUT)["total_s"]
    out = estimate_text(capsys, NUT, "-q")
    assert out == "%.3f\n" % total


def test_rich_output_when_forced_draws_panel_and_tables(corpus_root: Path) -> None:
    pytest.importorskip("rich")
    proc = run("estimate", str(NUT), "--printer-cfg", str(CORPUS_CFG), "--layers",
               env={cli.RICH_ENV: "1"})
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "\x1b[" in out and "╭" in out and "╰" in out
    for text in ("Klipper time", "3m 42s", "PrusaSlicer 2.5.0", "22s shorter than Klipper",
                 "279.4 mm (0.67 cm³)", "Time per feature", "Internal infill",
                 "Time per layer", "warning: "):
        assert text in out, text
    assert max(len(line) for line in _strip_ansi(out).splitlines()) <= 100


def test_rich_is_not_used_when_piped_or_turned_off(corpus_root: Path) -> None:
    piped = run("estimate", str(NUT), "--printer-cfg", str(CORPUS_CFG))
    off = run("estimate", str(NUT), "--printer-cfg", str(CORPUS_CFG), env={cli.RICH_ENV: "0"})
    assert piped.stdout == off.stdout and piped.stdout.startswith(str(NUT) + "\n")
    assert "\x1b[" not in piped.stdout and "╭" not in piped.stdout


def test_everything_works_without_rich_installed(tmp_path: Path, corpus_root: Path) -> None:
    blocker = tmp_path / "no_rich"
    blocker.mkdir()
    # A `rich` that cannot be imported shadows the installed one.
    (blocker / "rich").mkdir()
    (blocker / "rich" / "__init__.py").write_text("raise ImportError('no rich here')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join((str(blocker), str(PROJECT))),
               **{cli.RICH_ENV: "1"})
    out = tmp_path / "r.html"
    for argv in (["estimate", str(NUT), "--layers"], ["report", str(NUT), "-o", str(out)],
                 ["inject", str(NUT), "-o", str(tmp_path / "o.gcode")]):
        proc = subprocess.run([sys.executable, "-m", "kestimator", *argv], env=env,
                              capture_output=True, text=True, timeout=300)
        # Without a printer.cfg the only stderr line says the limits are guessed.
        assert proc.returncode == 0 and proc.stderr.startswith(
            "kestimator: warning: no printer.cfg or Moonraker given: ") and \
            proc.stderr.count("\n") == 1, (argv, proc.stderr)
        assert "\x1b[" not in proc.stdout
    proc = subprocess.run([sys.executable, "-c", "import kestimator.cli, sys; "
                           "print('rich' in sys.modules)"], env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.stdout == "False\n"


def test_inject_json_adds_output_and_m73_count_and_text_stays_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    out = tmp_path / "out.gcode"
    argv = ["inject", str(NUT), "-o", str(out), "--printer-cfg", str(CORPUS_CFG)]
    assert cli.main([*argv, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == set(ESTIMATE_FIELDS) | {"output", "m73_written"}
    assert doc["output"] == str(out) and doc["m73_written"] > 27
    assert doc["slicer"]["estimate_s"] == 200.0 and doc["slicer"]["difference_s"] < 0
    # A second run reads the slicer's estimate through kestimator's own marker.
    assert cli.main(["inject", str(out), "--printer-cfg", str(CORPUS_CFG), "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["slicer"]["difference_s"] == doc["slicer"]["difference_s"]
    assert cli.main(argv) == 0
    assert capsys.readouterr().out == (
        "kestimator: %s: Klipper time 3m 42s, the slicer said 3m 20s; wrote %d M73 lines; "
        "pre-flight: 2 commands skipped (kestimator check FILE shows each)\n"
        % (out, doc["m73_written"]))


def test_version_and_help_with_examples_and_exit_codes() -> None:
    for flag in ("--version", "-V"):
        proc = run(flag)
        assert proc.returncode == 0 and proc.stdout == "kestimator %s (pure Python)\n" % __version__
    top = run("--help").stdout
    assert "examples:" in top and "exit status: 0 success, 1" in top
    assert "KESTIMATOR_RICH" in top
    est = run("estimate", "--help").stdout
    for text in ("--json", "--quiet", "--layers", "docs/cli.md", "examples:", "exit status"):
        assert text in est.lower(), text
    for command in ("inject", "limits", "report"):
        proc = run(command, "--help")
        assert proc.returncode == 0 and "examples:" in proc.stdout, command


def test_json_and_quiet_together_are_a_usage_error(corpus_root: Path) -> None:
    proc = run("estimate", str(NUT), "--json", "-q")
    assert proc.returncode == cli.EXIT_USAGE and "not allowed with" in proc.stderr


def test_bad_input_is_one_line_with_file_and_line(tmp_path: Path) -> None:
    bgcode = tmp_path / "print.bgcode"
    bgcode.write_bytes(b"GCDE\x01\x00\x00\x00")
    for command in ("estimate", "inject"):
        proc = run(command, str(bgcode))
        assert proc.returncode == cli.EXIT_FAILURE and proc.stdout == ""
        assert proc.stderr == ("kestimator: error: %s:1: binary G-code (.bgcode) is not "
                               "supported: export plain G-code instead\n" % bgcode)


def test_a_bug_is_one_line_exit_3_and_a_traceback_only_with_debug(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        corpus_root: Path) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("planner exploded\nsecond line")
    monkeypatch.setattr(cli, "estimate_lines", broken)
    assert cli.main(["estimate", str(NUT)]) == cli.EXIT_INTERNAL == 3
    err = capsys.readouterr().err
    assert err == ("kestimator: internal error: RuntimeError: planner exploded second line "
                   "(run with --debug for the traceback and please report it)\n")
    assert cli.main(["estimate", str(NUT), "--debug"]) == cli.EXIT_INTERNAL
    assert "Traceback" in capsys.readouterr().err


def test_progress_bar_on_a_terminal_for_large_files_only(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        corpus_root: Path) -> None:
    monkeypatch.setattr(cli_render, "is_terminal", lambda stream: stream is sys.stderr)
    monkeypatch.setenv(cli.RICH_ENV, "0")
    argv = ["estimate", str(NUT), "--printer-cfg", str(CORPUS_CFG)]
    assert cli.main(argv) == 0
    assert capsys.readouterr().err == ""  # 139 kB is not large
    monkeypatch.setattr(cli_render, "PROGRESS_MIN_BYTES", 1000)
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert "\rtiming ps25_nut_accelA_small.gcode 100 %" in err and err.endswith("\r")
    for quiet in ("--json", "-q"):
        assert cli.main([*argv, quiet]) == 0
        assert capsys.readouterr().err == ""


def test_progress_callbacks_count_every_byte_once_per_pass(
        tmp_path: Path, corpus_root: Path) -> None:
    limits, _ = limits_from_printer_cfg(CORPUS_CFG)
    size = NUT.stat().st_size
    heard: list[int] = []
    estimate_file(str(NUT), limits, progress=heard.append)
    assert heard == sorted(heard) and heard[-1] == size
    heard.clear()
    inject_file(str(NUT), limits, output=str(tmp_path / "o.gcode"), progress=heard.append)
    assert heard == sorted(heard) and heard[-1] == 2 * size and size in heard


def _strip_ansi(text: str) -> str:
    return re.sub(r"\x1b\[[0-9;]*m", "", text)


# Issue 36, item 4: small things a new user meets.


def test_help_names_every_exit_status_including_klipper_stops() -> None:
    for args in (["--help"], ["inject", "--help"]):
        proc = run(*args)
        assert proc.returncode == 0
        assert re.search(r"\b4 [^.]{0,30}Klipper\s+will\s+stop\s+this\s+print", proc.stdout), args


def test_at_without_exclude_is_a_usage_error(tmp_path: Path) -> None:
    gcode = tmp_path / "p.gcode"
    gcode.write_text("G28\nG1 X10 Y10 F3000\n")
    proc = run("estimate", str(gcode), "--at", "2")
    assert proc.returncode == 2
    assert proc.stderr.strip().endswith("--at needs --exclude (the objects to cancel at that "
                                        "line)")


def test_the_summary_says_once_that_heater_waits_and_homing_count_as_0_s(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    gcode = tmp_path / "p.gcode"
    gcode.write_text("G28\nM190 S60\nM109 S200\nM83\nG1 X10 Y10 F3000\nG1 X20 E1\nG28 X\n"
                     "M109 S210\n")
    out = estimate_text(capsys, gcode)
    said = [line for line in out.splitlines() if "count as 0 s" in line]
    assert said == ["  3 heater waits and 2 homings (G28) count as 0 s: time each with "
                    "--heat-time S and --homing-time S (or heat_time_s and homing_time_s in "
                    "the profile), or let `kestimator learn` time the printer's start"]
    doc = estimate_json(capsys, gcode)
    assert doc["parts"]["untimed_waits"] == {"heater_waits": 3, "homings": 2}
    # Timed, nothing is said.
    out = estimate_text(capsys, gcode, "--heat-time", "30", "--homing-time", "10")
    assert "count as 0 s" not in out and "counts as 0 s" not in out
    assert estimate_json(capsys, gcode, "--heat-time", "30", "--homing-time", "10")[
        "parts"]["untimed_waits"] == {}
