"""What a command Klipper knows does to the print (issue 36): RESTART, FIRMWARE_RESTART and
M112 end it at their line; SAVE_CONFIG may (it restarts Klipper only with settings left to
save); probing and calibration commands take time the file cannot show.

M112 and SAVE_CONFIG are held to real Klipper by their oracle references
(tests/oracle_refs/preflight_m112 and preflight_save_config, in
test_real_printer_configs.py); RESTART here, by running it in the oracle's Klipper.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_text
from kestimator.limits import Limits
from kestimator.macros import MacroTime, MacroTimes

from .conftest import SHARED, require_klipper

REFS = Path(__file__).resolve().parent / "oracle_refs"
HEATERS_CFG = REFS / "configs" / "heaters.cfg"
MOVES = "G28\nG1 X10 Y10 F3000\nG1 X20 Y10\nG1 X30 Y20\n"
AFTER = "G1 X40 Y10\nG1 X10 Y10\n"


def _limits(tmp_path: Path, extra: str = "") -> Limits:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(HEATERS_CFG.read_text() + extra)
    return limits_from_printer_cfg(cfg)[0]


@pytest.mark.parametrize("command", ["RESTART", "FIRMWARE_RESTART", "M112"])
def test_restart_and_emergency_stop_end_the_print_at_their_line(
        tmp_path: Path, command: str) -> None:
    est = estimate_text(MOVES + command + "\n" + AFTER, _limits(tmp_path))
    (stop,) = [f for f in est.preflight if f.kind == "stop"]
    assert est.stops_print and stop.line == 5
    if command == "M112":
        assert stop.message.endswith("Shutdown due to M112 command")
    else:
        assert stop.message.endswith("%s restarts Klipper: the print ends here" % command)
    # Where the print ends: when the move on line 4 has finished, as real Klipper times
    # that move on the same lines (preflight_save_config's reference).
    ref = json.loads((REFS / "preflight_save_config.preflight.json").read_text())
    (line_4,) = [mark["t"] for mark in ref["marks"] if mark["line"] == 4]
    assert stop.t == pytest.approx(line_4, abs=0.01)


@pytest.mark.parametrize("command", ["RESTART", "FIRMWARE_RESTART"])
def test_real_klipper_runs_nothing_after_a_restart(command: str, tmp_path: Path) -> None:
    klipper, python = require_klipper()
    gcode = tmp_path / "restart.gcode"
    gcode.write_text(MOVES + command + "\n" + AFTER)
    env = dict(os.environ, ORACLE_KLIPPER=klipper, ORACLE_PYTHON=python)
    out = subprocess.run([sys.executable, str(SHARED / "tools" / "oracle" / "oracle.py"),
                          str(gcode), "--cfg", str(HEATERS_CFG)], capture_output=True,
                         text=True, env=env, timeout=300)
    doc = json.loads(out.stdout)
    # Klipper exits (batch mode cannot restart) before the oracle's end of file: no move
    # is timed, the file is not finished.
    assert doc["ok"] is False and doc["n_moves"] == 0 and not doc["errors"]
    assert any(line.startswith("Exiting") for line in doc["log_tail"])


def test_save_config_may_end_the_print(tmp_path: Path) -> None:
    est = estimate_text(MOVES + "SAVE_CONFIG\n" + AFTER, _limits(tmp_path))
    (maybe,) = [f for f in est.preflight if f.kind == "may_stop"]
    assert maybe.line == 5 and "restarts Klipper" in maybe.message
    assert not est.stops_print


def test_a_macro_of_the_same_name_takes_restart_over(tmp_path: Path) -> None:
    limits = _limits(tmp_path, "\n[gcode_macro RESTART]\ngcode:\n  G4 P1\n")
    est = estimate_text(MOVES + "RESTART\n" + AFTER, limits)
    assert not est.stops_print


Z_TILT = ("\n[z_tilt]\nz_positions:\n  -50, 18\n  150, 348\n  350, 18\n"
          "points:\n  30, 5\n  150, 245\n  270, 5\n\n[probe]\npin: gpio40\nz_offset: 1\n")


def test_probing_commands_take_time_the_file_cannot_show(tmp_path: Path) -> None:
    limits = _limits(tmp_path, Z_TILT)
    text = MOVES + "Z_TILT_ADJUST\nPROBE\n" + AFTER
    est = estimate_text(text, limits)
    said = [w for w in est.warnings if "takes time the file cannot show" in str(w)]
    assert len(said) == 2
    assert not [f for f in est.preflight if f.kind == "skipped"]
    timed = estimate_text(text, limits, macros=MacroTimes(macros={
        "Z_TILT_ADJUST": MacroTime(30.0, "profile test")}))
    # (with the full stop an added time makes, a few ms)
    assert timed.total_s == pytest.approx(est.total_s + 30.0, abs=0.01)
    assert len([w for w in timed.warnings if "takes time the file cannot show" in str(w)]) == 1


def test_without_the_module_a_probing_command_is_skipped(tmp_path: Path) -> None:
    est = estimate_text(MOVES + "Z_TILT_ADJUST\n", _limits(tmp_path))
    (skipped,) = [f for f in est.preflight if f.kind == "skipped"]
    assert '"Z_TILT_ADJUST"' in skipped.message
