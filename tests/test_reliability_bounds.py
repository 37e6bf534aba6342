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


@pytest.mark.parametrize("option", ["--homing-time", "--heat-time"])
def test_a_time_option_over_a_year_is_refused_even_in_a_file_that_never_uses_it(
        tmp_path: Path, option: str) -> None:
    gcode = tmp_path / "print.gcode"
    gcode.write_text("G1 X1 Y1 F3000\n")
    run = _run("estimate", str(gcode), "--printer-cfg", str(CORPUS_CFG), option, "1e300")
    _one_line_failure(run, option.encode() + b" must be a number of seconds from 0 to a year")


# Items 8 and 13: a printer's geometry Klipper's arithmetic breaks on, or that leaves no
# range, is one line naming the file, the section and the option the user wrote.

GCODE = "G28\nG1 X1 Y1 Z5 F3000\n"


def _cfg(tmp_path: Path, kinematics: str, old: str, new: str) -> Path:
    text = (REFS / kinematics / "printer.cfg").read_text()
    assert old in text, old
    path = tmp_path / "printer.cfg"
    # The delta case sets every tower's step (Klipper's bound is on the finest).
    path.write_text(text.replace(old, new, -1 if kinematics == "delta" else 1))
    return path


def _cfg_line(path: Path, text: str) -> int:
    return path.read_text().splitlines().index(text) + 1


def _config_error(path: Path) -> KestimatorError:
    with pytest.raises(KestimatorError) as caught:
        limits, _ = limits_from_printer_cfg(path)
        estimate_text(GCODE, limits)
    return caught.value


CONFIG_CASES = {
    # case: (kinematics, old text, new text, the option named, words of the message)
    "delta_coarse_step": ("delta", "rotation_distance: 40\n", "rotation_distance: 200000\n",
                          "rotation_distance: 200000", "too coarse for arm_length 28"),
    "rotary_delta_long_upper_arm": ("rotary_delta", "upper_arm_length: 170.000",
                                    "upper_arm_length: 500", "upper_arm_length: 500",
                                    "cannot reach its position_endstop 252"),
    "deltesian_huge_slow_ratio": ("deltesian", "kinematics: deltesian\n",
                                  "kinematics: deltesian\nslow_ratio: 1e300\n",
                                  "slow_ratio: 1e300", "'slow_ratio' must be at most 1e+100"),
    "polar_huge_position_max": ("polar", "position_max: 250\n", "position_max: 1e200\n",
                                "position_max: 1e200", "'position_max' must be at most"),
    "deltesian_min_angle_90": ("deltesian", "kinematics: deltesian\n",
                               "kinematics: deltesian\nmin_angle: 90\n", "min_angle: 90",
                               "'min_angle' 90 leaves the arms no X range"),
    "deltesian_arm_barely_longer": ("deltesian", "arm_x_length: 160", "arm_x_length: 216.99",
                                    "arm_length: 217", "'arm_length' 217 is too short"),
}


@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_a_geometry_klipper_cannot_use_is_one_line_at_the_option(tmp_path: Path,
                                                                 case: str) -> None:
    kinematics, old, new, option_line, words = CONFIG_CASES[case]
    path = _cfg(tmp_path, kinematics, old, new)
    error = _config_error(path)
    assert error.path == str(path) and error.line == _cfg_line(path, option_line), str(error)
    assert words in error.message and "print_width" not in error.message, str(error)


def test_a_blank_carriage_name_is_named_not_an_index_error(tmp_path: Path) -> None:
    path = _cfg(tmp_path, "generic_cartesian", "[carriage x]", "[carriage  ]")
    error = _config_error(path)
    assert error.path == str(path) and "[carriage  ] has no carriage name" in error.message


def test_a_delta_geometry_with_no_solution_is_one_line_not_a_zero_division(
        tmp_path: Path) -> None:
    path = _cfg(tmp_path, "delta", "angle: 92", "angle: 210")
    text = path.read_text().replace("[stepper_b]\n", "[stepper_b]\nangle: 210\n", 1)
    path.write_text(text)
    error = _config_error(path)
    assert error.path == str(path) and "kinematics: delta" in error.message


def test_the_same_delta_values_from_moonraker_name_the_setting() -> None:
    from kestimator.config.moonraker import settings_values
    from kestimator.config.printer_cfg import read_printer_cfg
    from kestimator.kinematics import load_kinematics

    def typed(text: str) -> object:
        for kind in (int, float):
            try:
                return kind(text)
            except ValueError:
                pass
        return text
    settings = {name: {option: typed(value.value) for option, value in options.items()}
                for name, options in read_printer_cfg(REFS / "delta" / "printer.cfg").items()}
    for tower in "abc":
        settings["stepper_" + tower]["rotation_distance"] = 200000.0
    found = settings_values(settings, "moonraker http://printer")
    limits = Limits.from_values(found.values).replace(machine=found.machine)
    with pytest.raises(KestimatorError) as caught:
        load_kinematics(limits)
    text = str(caught.value)
    assert text.startswith("moonraker http://printer: [stepper_a] rotation_distance: "), text
    assert "too coarse" in text
    for tower in "abc":
        settings["stepper_" + tower]["rotation_distance"] = 40.0
    settings["printer"]["delta_radius"] = 1e200
    found = settings_values(settings, "moonraker http://printer")
    limits = Limits.from_values(found.values).replace(machine=found.machine)
    with pytest.raises(KestimatorError, match=r"\[printer\] delta_radius: .*at most 1e\+100"):
        load_kinematics(limits)


def test_a_klipper_estimator_axis_of_1e200_is_read_not_an_overflow(tmp_path: Path) -> None:
    from kestimator.config.klipper_estimator import estimator_config_values
    path = tmp_path / "estimator.json"
    path.write_text('{"max_velocity": 300, "max_acceleration": 3000, "move_checkers": ['
                    '{"axis_limiter": {"axis": [0, 0, 1e200], "max_velocity": 12, '
                    '"max_accel": 1e200}}, {"axis_limiter": {"axis": [1e200, 0, 0], '
                    '"max_velocity": 1e200}}]}')
    with pytest.raises(KestimatorError, match="max_accel: max_z_accel must be at most"):
        estimator_config_values(path)
    path.write_text(path.read_text().replace('"max_accel": 1e200', '"max_accel": 100'))
    found = estimator_config_values(path)
    assert found.values["max_z_velocity"] == 12 and found.values["max_z_accel"] == 100
    assert any("[1e+200, 0, 0]" in w for w in found.warnings)


def test_kestimator_compat_refuses_an_axis_limit_of_1e200_in_one_line(tmp_path: Path) -> None:
    config = tmp_path / "estimator.json"
    config.write_text('{"move_checkers": [{"axis_limiter": {"axis": [0, 0, 1e200], '
                      '"max_velocity": 1e200}}]}')
    gcode = tmp_path / "print.gcode"
    gcode.write_text(MOVES)
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PROJECT) + os.pathsep + env.get("PYTHONPATH", "")
    run = subprocess.run([sys.executable, "-m", "kestimator.compat", "--config_file",
                          str(config), "estimate", str(gcode)], env=env, capture_output=True,
                         timeout=120)
    assert run.returncode == 1 and b"internal error" not in run.stderr, run.stderr
    assert b"max_z_velocity must be at most 1e+100" in run.stderr, run.stderr


# Item 9: includes that multiply are bounded in total work, at the [include] line.

def _diamond(folder: Path, depth: int) -> Path:
    """f0 includes f1 twice, f1 includes f2 twice, ...: 2^depth files read in all."""
    for i in range(depth):
        (folder / ("f%d.cfg" % i)).write_text(
            "[include f%d.cfg]\n[include f%d.cfg]\n" % (i + 1, i + 1))
    (folder / ("f%d.cfg" % depth)).write_text(
        "[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n")
    return folder / "f0.cfg"


def test_an_include_diamond_stops_at_the_file_budget_fast(tmp_path: Path) -> None:
    import time

    from kestimator.config.printer_cfg import MAX_INCLUDED_FILES
    path = _diamond(tmp_path, 26)
    started = time.monotonic()
    with pytest.raises(KestimatorError) as caught:
        limits_from_printer_cfg(path)
    assert time.monotonic() - started < 20.0
    error = caught.value
    assert error.path is not None and error.path.endswith(".cfg") and error.line in (1, 2)
    assert "passes %d files read in all" % MAX_INCLUDED_FILES in error.message


def test_a_small_diamond_within_the_budget_is_read(tmp_path: Path) -> None:
    limits, _ = limits_from_printer_cfg(_diamond(tmp_path, 8))
    assert limits.max_velocity == 300


def test_included_text_is_bounded_in_total(tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from kestimator.config import printer_cfg
    monkeypatch.setattr(printer_cfg, "MAX_INCLUDED_CHARS", 1000)
    (tmp_path / "big.cfg").write_text("# " + "x" * 400 + "\n")
    main = tmp_path / "printer.cfg"
    main.write_text("[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n"
                    + "[include big.cfg]\n" * 3)
    with pytest.raises(KestimatorError) as caught:
        limits_from_printer_cfg(main)
    assert caught.value.path == str(main) and caught.value.line == 7
    assert "MiB of config text" in caught.value.message


def test_a_move_of_150_digits_is_refused_not_timed() -> None:
    message = _refused_at("G1 X1" + "0" * 150 + " F3000\n", 1)
    assert "1e+150 mm" in message
