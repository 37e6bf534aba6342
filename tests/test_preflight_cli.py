"""The pre-flight in every front end of the CLI: estimate, inject (status 4), check."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kestimator import cli
from kestimator.preflight import EXIT_KLIPPER_STOPS

REFS = Path(__file__).resolve().parent / "oracle_refs"
NO_ARCS = str(REFS / "configs" / "no_arcs.cfg")
STOPPING = ("G28\nG90\nM83\nG1 X10 Y10 F3000\nG2 X20 Y10 I5 J0\nG1 X30 Y10 E1\n"
            "M221 S\nG1 X40 Y10 E1\nM221 S\n")


def _gcode(tmp_path: Path, text: str = STOPPING) -> Path:
    path = tmp_path / "part.gcode"
    path.write_text(text)
    return path


def test_inject_writes_times_but_exits_4_with_one_stderr_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _gcode(tmp_path)
    status = cli.main(["inject", str(path), "--printer-cfg", NO_ARCS])
    out, err = capsys.readouterr()
    assert status == EXIT_KLIPPER_STOPS == 4
    assert err == ("kestimator: Klipper will stop this print at line 7: Error on 'M221 S': "
                   "unable to parse \n")
    (line,) = out.splitlines()
    assert line.endswith("; pre-flight: Klipper will stop the print at line 7, 1s in; "
                         "1 command skipped (kestimator check FILE shows each)")
    assert "; kestimator" in path.read_text()  # the times were written


def test_estimate_json_carries_the_preflight(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    path = _gcode(tmp_path)
    assert cli.main(["estimate", str(path), "--printer-cfg", NO_ARCS, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    stop, arcs = doc["preflight"]
    assert (stop["severity"], stop["line"], stop["kind"], stop["count"]) == (
        "error", 7, "stop", 2)
    assert stop["t"] > 0
    assert (arcs["severity"], arcs["line"], arcs["kind"]) == ("warning", 5, "skipped")


def test_check_runs_only_the_preflight(tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    path = _gcode(tmp_path)
    assert cli.main(["check", str(path), "--printer-cfg", NO_ARCS]) == EXIT_KLIPPER_STOPS
    out, _ = capsys.readouterr()
    assert "Klipper time" not in out and "line 7: Klipper stops the print here" in out
    clean = _gcode(tmp_path, "G28\nG1 X10 Y10 F3000\n")
    assert cli.main(["check", str(clean), "--printer-cfg", NO_ARCS, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["preflight"] == []
