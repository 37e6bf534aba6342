"""Issue 29: values a print cannot have end in one line naming file and line (exit status 1),
never an absurd number written with exit status 0, never `internal error`, never a hang.

Times: a print that would last over a year (`durations.MAX_PRINT_S`) is refused at the line
where time passed a year, whatever made it so (an acceleration of 1e-300, a dwell, an added
time, a macro time, a kinematics limit).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.config.profile import load_profile
from kestimator.durations import MAX_PRINT_S
from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_text
from kestimator.limits import Limits
from kestimator.macros import MacroTime, MacroTimes

from .conftest import CORPUS_CFG, PROJECT

REFS = PROJECT / "tests" / "oracle_refs"
MOVES = "M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\nG1 X20 E1\n"


def _run(*args: str) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PROJECT) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "kestimator", *args], env=env,
                          capture_output=True, timeout=120)


def _one_line_failure(run: subprocess.CompletedProcess[bytes], expected: bytes) -> None:
    assert run.returncode == 1, run.stderr
    assert b"internal error" not in run.stderr, run.stderr
    assert expected in run.stderr and len(run.stderr.splitlines()) == 1, run.stderr
    assert run.stdout == b"", run.stdout


def _refused_at(text: str, line: int, limits: Limits | None = None, **kwargs: object) -> str:
    with pytest.raises(KestimatorError) as caught:
        estimate_text(text, limits or Limits(), **kwargs)  # type: ignore[arg-type]
    assert caught.value.path == "<text>" and caught.value.line == line, str(caught.value)
    assert "over a year" in caught.value.message
    return caught.value.message


# Item 7: absurd finite totals.

def test_a_tiny_acceleration_is_refused_at_the_first_move_it_slows() -> None:
    message = _refused_at("SET_VELOCITY_LIMIT ACCEL=1e-300\n" + MOVES, 4)
    assert "acceleration 1e-300" in message


def test_an_added_time_of_1e300_s_is_refused_at_its_comment() -> None:
    message = _refused_at(MOVES + "; ESTIMATOR_ADD_TIME 1e300 cooling\n", 5)
    assert "ESTIMATOR_ADD_TIME cooling adds 1e+300 s" in message


def test_a_dwell_of_1e40_ms_is_refused_at_the_g4() -> None:
    message = _refused_at(MOVES + "G4 P1" + "0" * 40 + "\n" + MOVES, 5)
    assert "G4 P1000" in message


def test_a_homing_time_of_1e300_s_is_refused_at_the_g28() -> None:
    message = _refused_at("G28\n" + MOVES, 1, homing_time=1e300)
    assert "G28 adds 1e+300 s" in message and "--homing-time" in message


def test_a_macro_time_of_1e300_s_is_refused_at_the_macro() -> None:
    macros = MacroTimes({"PRINT_START": MacroTime(1e300, "profile p.toml")})
    message = _refused_at("PRINT_START\n" + MOVES, 1, macros=macros)
    assert "PRINT_START adds 1e+300 s here (profile p.toml)" in message


def test_many_added_times_are_refused_where_the_total_passes_a_year() -> None:
    day = 86400.0
    text = "".join("; ESTIMATOR_ADD_TIME %g\n" % day for _ in range(400))
    _refused_at(text, 367)


def test_a_print_just_under_a_year_is_still_timed() -> None:
    est = estimate_text("; ESTIMATOR_ADD_TIME %r\n" % (MAX_PRINT_S - 1.0), Limits())
    assert est.total_s == MAX_PRINT_S - 1.0


def test_a_polar_with_a_tiny_max_angular_velocity_is_refused_not_written(
        tmp_path: Path) -> None:
    cfg = (REFS / "polar" / "printer.cfg").read_text()
    cfg = cfg.replace("max_angular_velocity: 1.5", "max_angular_velocity: 1e-90")
    assert "1e-90" in cfg
    path = tmp_path / "printer.cfg"
    path.write_text(cfg)
    limits, _ = limits_from_printer_cfg(path)
    _refused_at("G28\nG1 X10 Y10 F3000\nG1 X-10 Y10\n", 2, limits)


def test_a_profile_macro_or_duration_over_a_year_is_refused_naming_the_profile(
        tmp_path: Path) -> None:
    path = tmp_path / "p.toml"
    path.write_text("[macros]\nPRINT_START = 1e300\n")
    with pytest.raises(KestimatorError, match=r"PRINT_START = 1e\+300 s is over a year"):
        load_profile(path)
    path.write_text("homing_time_s = 1e300\n")
    with pytest.raises(KestimatorError, match="homing_time_s .* at most a year"):
        load_profile(path)


def test_inject_refuses_an_absurd_total_and_leaves_the_file(tmp_path: Path) -> None:
    gcode = tmp_path / "print.gcode"
    body = ("SET_VELOCITY_LIMIT ACCEL=1e-300\n" + MOVES).encode()
    gcode.write_bytes(body)
    run = _run("inject", str(gcode), "--printer-cfg", str(CORPUS_CFG))
    _one_line_failure(run, b"print.gcode:4: the print would last over a year")
    assert gcode.read_bytes() == body
