"""The command line: exit codes, one-line errors, no tracebacks unless asked, report."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from .conftest import CORPUS_CFG, PROJECT

NUT = "gcode/prusaslicer/ps25_nut_accelA_small.gcode"


def run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    full_env = dict(os.environ, PYTHONPATH=str(PROJECT), **(env or {}))
    return subprocess.run([sys.executable, "-m", "kestimator", *args], capture_output=True,
                          text=True, env=full_env, timeout=300)


def test_missing_file_is_one_line_exit_1_without_traceback(tmp_path: Path) -> None:
    for command in ("estimate", "inject", "report"):
        extra = ["-o", str(tmp_path / "r.html")] if command == "report" else []
        proc = run(command, str(tmp_path / "missing.gcode"), *extra)
        assert proc.returncode == 1, command
        assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
        assert proc.stderr.startswith("kestimator: error: ") and "missing.gcode" in proc.stderr


def test_debug_shows_the_traceback_before_or_after_the_command(tmp_path: Path) -> None:
    missing = str(tmp_path / "missing.gcode")
    assert "Traceback" in run("--debug", "estimate", missing).stderr
    assert "Traceback" in run("estimate", missing, "--debug").stderr


def test_usage_errors_exit_2() -> None:
    assert run("estimate").returncode == 2
    assert run("no-such-command").returncode == 2
    assert run().returncode == 2


def test_errors_name_the_slicers_final_file_when_run_on_its_temp_copy(tmp_path: Path) -> None:
    temp_copy = tmp_path / ".4242_0.gcode.pp"
    proc = run("inject", str(temp_copy), env={"SLIC3R_PP_OUTPUT_NAME": "/home/u/tube.gcode"})
    assert proc.returncode == 1
    assert "(slicer output /home/u/tube.gcode)" in proc.stderr
    assert str(temp_copy) in proc.stderr and proc.stderr.count("\n") == 1


def test_closed_stdout_is_not_a_traceback(corpus_root: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(PROJECT))
    proc = subprocess.run(
        "%s -m kestimator estimate '%s' --json | head -c 10 >/dev/null" % (
            sys.executable, corpus_root / NUT),
        shell=True, capture_output=True, text=True, env=env, timeout=300)
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr


def test_report_command_writes_one_page(tmp_path: Path, corpus_root: Path) -> None:
    out = tmp_path / "report.html"
    proc = run("report", str(corpus_root / NUT), "-o", str(out), "--printer-cfg",
               str(CORPUS_CFG))
    assert proc.returncode == 0, proc.stderr
    page = out.read_text(encoding="utf-8")
    assert page.startswith("<!DOCTYPE html>") and "3m 42s" in page
    assert "chart-layers" in page and "chart-speed" in page
