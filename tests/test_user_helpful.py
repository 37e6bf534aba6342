"""Helpful output (issue 17): layer numbers for Mainsail/Fluidd/KlipperScreen, argument
mistakes, the missing-[include] hint, `report -o x.png`, progress bars with elapsed and left
time, and --help wrapped at the terminal's width. Each test asserts the exact lines a user
sees."""

from __future__ import annotations

import io
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator import cli, cli_render
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.rewrite import inject_file

from .conftest import CORPUS, CORPUS_CFG, PROJECT, isolate_user_environment

NUT = CORPUS / "gcode/prusaslicer/ps25_nut_accelA_small.gcode"
ORCA = CORPUS / "gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode"
CURA = CORPUS / "gcode/cura/cura413_ender3_nut_small.gcode"
LAYER_INFO_RE = re.compile(rb"^SET_PRINT_STATS_INFO (TOTAL_LAYER|CURRENT_LAYER)=(\d+) ; kestimator"
                           rb"\r?$", re.MULTILINE)


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No profile, a private cache, no slicer hook environment, no forced rich."""
    return isolate_user_environment(tmp_path, monkeypatch)


def run(*args: str, env: dict[str, str] | None = None,
        cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "kestimator", *args],
                          env=dict(os.environ, PYTHONPATH=str(PROJECT), **(env or {})),
                          capture_output=True, text=True, timeout=300, cwd=cwd)


# Layer numbers through SET_PRINT_STATS_INFO: written for a printer that knows the
# command (its [virtual_sdcard] loads [print_stats]), which the corpus printer.cfg lacks.


@pytest.fixture
def sdcard_cfg(tmp_path: Path) -> Path:
    """The corpus printer.cfg with the [virtual_sdcard] every Mainsail/Fluidd setup has."""
    cfg = tmp_path / "sdcard" / "printer.cfg"
    cfg.parent.mkdir()
    cfg.write_text(CORPUS_CFG.read_text() + "\n[virtual_sdcard]\npath: %s\n" % tmp_path)
    return cfg


@pytest.mark.parametrize("source", [NUT, CURA], ids=["prusaslicer", "cura"])
def test_inject_adds_total_layer_before_the_first_layer_and_current_layer_at_each(
        tmp_path: Path, corpus_root: Path, source: Path,
        sdcard_cfg: Path) -> None:
    limits, _ = limits_from_printer_cfg(sdcard_cfg)
    out = tmp_path / "out.gcode"
    result = inject_file(source, limits, output=str(out), table=False)
    data = out.read_bytes()
    layers = len(result.estimate.layers)
    found = [(kind, int(n)) for kind, n in LAYER_INFO_RE.findall(data)]
    assert found == [(b"TOTAL_LAYER", layers)] + [(b"CURRENT_LAYER", k)
                                                   for k in range(1, layers + 1)]
    lines = data.splitlines()
    markers = [i for i, line in enumerate(lines) if line.startswith((b";LAYER_CHANGE", b";LAYER:"))]
    assert lines[markers[0] - 1].startswith(b"SET_PRINT_STATS_INFO TOTAL_LAYER=")
    for k, i in enumerate(markers, 1):
        # The marker, Klipper's M73, then the layer number.
        assert lines[i + 1].startswith(b"M73 P")
        assert lines[i + 2] == b"SET_PRINT_STATS_INFO CURRENT_LAYER=%d ; kestimator" % k
    # Idempotent and byte-exact: a second run writes the same bytes; without the lines the
    # output is what --no-layer-info writes.
    again = tmp_path / "again.gcode"
    inject_file(out, limits, output=str(again), table=False)
    assert again.read_bytes() == data
    plain = tmp_path / "plain.gcode"
    inject_file(source, limits, output=str(plain), layer_info=False, table=False)
    assert LAYER_INFO_RE.sub(b"", data).replace(b"\n\n", b"\n") == plain.read_bytes() or \
        [line for line in lines if not LAYER_INFO_RE.match(line)] == \
        plain.read_bytes().splitlines()
    # The time is unchanged: SET_PRINT_STATS_INFO takes none.
    assert inject_file(out, limits, output=str(again), table=False).estimate.total_s == \
        result.estimate.total_s


def test_a_file_that_sets_layer_numbers_itself_gets_none_added(
        tmp_path: Path, corpus_root: Path, sdcard_cfg: Path) -> None:
    limits, _ = limits_from_printer_cfg(sdcard_cfg)
    out = tmp_path / "orca.gcode"
    inject_file(ORCA, limits, output=str(out))
    assert b"; kestimator\n" not in out.read_bytes().replace(b"\r", b"")
    assert out.read_bytes().count(b"SET_PRINT_STATS_INFO") == \
        ORCA.read_bytes().count(b"SET_PRINT_STATS_INFO")


def test_no_layer_info_switch_on_the_command_line(tmp_path: Path, corpus_root: Path,
                                                  sdcard_cfg: Path) -> None:
    out = tmp_path / "out.gcode"
    proc = run("inject", str(NUT), "-o", str(out), "--printer-cfg", str(sdcard_cfg),
               "--no-layer-info")
    assert proc.returncode == 0 and proc.stderr == ""
    assert b"SET_PRINT_STATS_INFO" not in out.read_bytes()
    assert run("inject", str(NUT), "-o", str(out), "--printer-cfg",
               str(sdcard_cfg)).returncode == 0
    assert out.read_bytes().count(b"SET_PRINT_STATS_INFO") == 28


# Argument mistakes


def test_a_file_without_a_command_is_estimated(corpus_root: Path) -> None:
    plain = run(str(NUT), "--printer-cfg", str(CORPUS_CFG))
    assert plain.returncode == 0, plain.stderr
    assert plain.stdout == run("estimate", str(NUT), "--printer-cfg",
                               str(CORPUS_CFG)).stdout


def test_options_before_the_command_work(corpus_root: Path) -> None:
    before = run("--printer-cfg", str(CORPUS_CFG), "estimate", str(NUT), "-q")
    assert before.returncode == 0 and before.stdout == "222.102\n"
    assert run("--debug", "estimate", str(NUT), "-q", "--printer-cfg",
               str(CORPUS_CFG)).stdout == "222.102\n"


def test_a_misspelt_set_key_suggests_the_right_one(corpus_root: Path) -> None:
    proc = run("estimate", str(NUT), "--set", "max_acel=5000")
    assert proc.returncode == 1
    assert proc.stderr == (
        "kestimator: error: --set max_acel: unknown setting 'max_acel': did you mean "
        "max_accel? (`kestimator limits` lists every setting)\n")


def test_a_hook_path_with_an_unquoted_space_or_backslashes_says_how_to_quote_it(
        tmp_path: Path, corpus_root: Path) -> None:
    folder = tmp_path / "My Printer"
    folder.mkdir()
    shutil.copyfile(CORPUS_CFG, folder / "printer.cfg")
    work = tmp_path / "print.gcode"
    shutil.copyfile(NUT, work)
    # What PrusaSlicer runs for `kestimator inject --printer-cfg <path with a space>`.
    proc = run("inject", "--printer-cfg", str(tmp_path / "My"), "Printer/printer.cfg",
               str(work), cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr == (
        'kestimator: error: --printer-cfg %s does not exist, but %s does: the path has a '
        'space, so quote it (in a slicer\'s post-processing line too): --printer-cfg "%s"\n'
        % (tmp_path / "My", tmp_path / "My Printer/printer.cfg",
           tmp_path / "My Printer/printer.cfg"))
    windows = run("inject", "--printer-cfg", "C:\\Users\\me\\printer.cfg", str(work))
    assert windows.returncode == 2
    assert windows.stderr == (
        "kestimator: error: --printer-cfg C:\\Users\\me\\printer.cfg does not exist: write the "
        "path with forward slashes (C:/Users/...) and quote it if it has a space, e.g. "
        '--printer-cfg "C:/Users/me/printer.cfg"\n')
    assert work.read_bytes() == NUT.read_bytes()


def test_a_missing_include_says_to_copy_the_folder_or_use_moonraker(
        tmp_path: Path, corpus_root: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[include mainsail.cfg]\n" + CORPUS_CFG.read_text())
    proc = run("estimate", str(NUT), "--printer-cfg", str(cfg))
    assert proc.returncode == 1
    assert proc.stderr == (
        "kestimator: error: %s:1: include file %s does not exist: copy the whole config folder "
        "(printer.cfg and the files it includes, e.g. mainsail.cfg), or read the live "
        "settings with --moonraker URL\n" % (cfg, tmp_path / "mainsail.cfg"))


def test_report_refuses_an_output_that_is_not_html(tmp_path: Path, corpus_root: Path) -> None:
    for name, shown in (("x.png", ".png"), ("report", "a file without an extension")):
        proc = run("report", str(NUT), "-o", str(tmp_path / name))
        assert proc.returncode == 2 and proc.stdout == ""
        assert proc.stderr == ("kestimator: error: report writes one HTML page, not %s: give "
                               "-o NAME.html (open it in a browser to save a picture)\n"
                               % shown)
        assert not (tmp_path / name).exists()


# Progress and help


def test_every_progress_bar_shows_elapsed_and_time_left(
        monkeypatch: pytest.MonkeyPatch) -> None:
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    monkeypatch.setenv(cli.RICH_ENV, "0")
    with cli_render.ProgressBar("timing big.gcode", 1000) as bar:
        bar(500)
        bar(1000)
    shown = [part for part in err.getvalue().split("\r") if part.strip()]
    assert shown[0].startswith("timing big.gcode  50 %  0:00 elapsed, 0:00 left")
    assert shown[1].startswith("timing big.gcode 100 %  0:00 elapsed, 0:00 left")
    assert err.getvalue().endswith("\r")  # cleared at the end


def test_report_shows_the_same_progress_bar(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                            corpus_root: Path) -> None:
    seen: list[str] = []

    class Recorder(cli_render.ProgressBar):
        def __call__(self, done: int) -> None:
            seen.append(self.label)

    monkeypatch.setattr(cli_render, "PROGRESS_MIN_BYTES", 0)
    monkeypatch.setattr(cli_render, "is_terminal", lambda stream: True)
    monkeypatch.setattr(cli_render, "ProgressBar", Recorder)
    assert cli.main(["report", str(NUT), "-o", str(tmp_path / "r.html"), "--printer-cfg",
                     str(CORPUS_CFG)]) == 0
    assert seen and seen[-1] == "timing " + NUT.name


def test_help_wraps_at_the_terminal_width(corpus_root: Path) -> None:
    for argv in ([], ["estimate"], ["inject"], ["limits"], ["report"]):
        proc = run(*argv, "--help", env={"COLUMNS": "60"})
        assert proc.returncode == 0
        prose = [line for line in proc.stdout.splitlines()
                 if not line.startswith("  ") and not line.startswith("usage:")]
        assert prose and max(len(line) for line in prose) <= 60, argv


def test_limits_is_a_table_with_units_sources_and_what_the_slicer_assumed(
        corpus_root: Path) -> None:
    gcode = CORPUS / "gcode/prusaslicer/cancelobj_ps2.3.3_issue1.gcode"
    proc = run("limits", str(gcode), "--printer-cfg", str(CORPUS_CFG))
    assert proc.returncode == 0 and proc.stderr == ""
    lines = proc.stdout.splitlines()
    assert lines[:5] == [
        "  file    : %s" % gcode, "  slicer  : PrusaSlicer 2.3.3+x64",
        "  machine : %s" % CORPUS_CFG, "  profile : none",
        "  setting                            value unit   source  | slicer assumed"]
    assert lines[5] == "  kinematics                     cartesian        %s:6" % CORPUS_CFG
    assert lines[7] == ("  max_accel                           3000 mm/s²  %s:8  | slicer: 1500"
                        % CORPUS_CFG)
    rich = run("limits", str(gcode), "--printer-cfg", str(CORPUS_CFG),
               env={cli.RICH_ENV: "1", "COLUMNS": "120"})
    plain = re.sub(r"\x1b\[[0-9;]*m", "", rich.stdout)
    assert re.search(r"max_accel +3000 +mm/s² +%s:8 +1500" % re.escape(str(CORPUS_CFG)), plain)
    assert "Slicer assumed" in plain
