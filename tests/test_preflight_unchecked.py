"""`check` never says Klipper runs every command when moves were not range-checked
(issue 29 item 4): the pre-flight carries an `unchecked` finding, in text and in --json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kestimator import cli
from kestimator.preflight import KIND_UNCHECKED

from .conftest import CORPUS_CFG

EVERY_COMMAND = "Klipper runs every command of this file"
MOVES = "G28\nG90\nM83\nG1 X10 Y10 F3000\nG1 X30 Y10 E1\n"


def _files(tmp_path: Path, printer_cfg: str | None = None) -> tuple[Path, list[str]]:
    gcode = tmp_path / "part.gcode"
    gcode.write_text(MOVES)
    if printer_cfg is None:
        return gcode, ["--printer-cfg", str(CORPUS_CFG)]
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(printer_cfg)
    return gcode, ["--printer-cfg", str(cfg)]


FORK_KINEMATICS = "[printer]\nkinematics: limited_corexy\nmax_velocity: 300\nmax_accel: 3000\n"
NO_STEPPERS = "[printer]\nkinematics: delta\nmax_velocity: 300\nmax_accel: 3000\n"


@pytest.mark.parametrize("printer_cfg, extra", [
    (FORK_KINEMATICS, []),
    (NO_STEPPERS, []),
    (None, ["--set", "kinematics=delta"]),
], ids=["fork-kinematics", "delta-without-steppers", "set-kinematics-on-cartesian"])
def test_check_says_moves_were_not_range_checked(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], printer_cfg: str | None,
        extra: list[str]) -> None:
    gcode, args = _files(tmp_path, printer_cfg)
    assert cli.main(["check", str(gcode), *args, *extra]) == 0
    out = capsys.readouterr().out
    assert EVERY_COMMAND not in out
    assert "Pre-flight: moves not range-checked" in out
    assert "not range-checked" in out.splitlines()[2]
    assert cli.main(["check", str(gcode), *args, *extra, "--json"]) == 0
    (finding,) = json.loads(capsys.readouterr().out)["preflight"]
    assert (finding["kind"], finding["severity"], finding["line"]) == (
        KIND_UNCHECKED, "warning", None)
    assert cli.main(["estimate", str(gcode), *args, *extra, "--json"]) == 0
    assert [f["kind"] for f in json.loads(capsys.readouterr().out)["preflight"]] == [
        KIND_UNCHECKED]


def test_check_on_a_fully_known_printer_still_says_every_command_runs(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gcode, args = _files(tmp_path)
    assert cli.main(["check", str(gcode), *args]) == 0
    assert EVERY_COMMAND in capsys.readouterr().out
