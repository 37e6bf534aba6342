"""`kestimator limits` and the limit options every command shares."""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path
from typing import Any

import pytest

from kestimator import cli
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.limits import Limits, json_value

from .conftest import CORPUS, CORPUS_CFG, corpus_files
from .fake_moonraker import API_KEY, CORPUS_SETTINGS, FakeMoonraker

MANUAL_SOURCES = ("--set", "klipper default", "derived from ", "kestimator ", "slicer: ",
                  "guessed: ")


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No profile, a private cache, no slicer hook environment."""
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("MOONRAKER_API_KEY", raising=False)
    for name in [name for name in os.environ if name.startswith("SLIC3R_")]:
        monkeypatch.delenv(name)
    return tmp_path


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict[str, Any]:
    assert cli.main(["limits", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("path", corpus_files(), ids=lambda p: p.parent.name + "/" + p.name)
def test_limits_json_names_a_source_for_every_value_of_every_corpus_file(
        path: Path, capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    doc = run_json(capsys, str(path))
    assert list(doc["limits"]) == list(Limits.field_names())
    for field, entry in doc["limits"].items():
        assert isinstance(entry["source"], str) and entry["source"], field
        assert entry["source"].startswith(MANUAL_SOURCES), (field, entry["source"])
    assert doc["machine"] is None and doc["slicer"]["name"]
    with_cfg = run_json(capsys, str(path), "--printer-cfg", str(CORPUS_CFG))
    limits = limits_from_printer_cfg(CORPUS_CFG)[0]
    for field, entry in with_cfg["limits"].items():
        assert entry["value"] == json_value(getattr(limits, field))
        assert entry["source"].startswith((str(CORPUS_CFG) + ":", "klipper default",
                                           "derived from ", "kestimator default")), field


def test_limits_text_lists_every_setting_with_its_source(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    gcode = CORPUS / "gcode/prusaslicer/cancelobj_ps2.3.3_issue1.gcode"
    assert cli.main(["limits", str(gcode), "--set", "max_z_accel=50"]) == 0
    out, err = capsys.readouterr()
    assert "  slicer  : PrusaSlicer 2.3.3+x64" in out
    assert "  machine : none (no printer.cfg or Moonraker)" in out
    lines = {line.split()[0]: line for line in out.splitlines()[4:] if line.startswith("  ")}
    assert lines["max_accel"].split()[1:4] == ["1500", "mm/s²", "slicer:"]
    assert lines["max_z_accel"].split()[1:] == ["50", "mm/s²", "--set", "|", "slicer:", "500"]
    assert lines["arcs_enabled"].split()[1:4] == ["true", "kestimator", "assumption:"]
    assert err.startswith("kestimator: warning: no printer.cfg or Moonraker given")
    assert "no printer.cfg or Moonraker given" not in out


def test_limits_json_reports_the_slicers_accelerations_and_notes(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    doc = run_json(capsys, str(CORPUS / "gcode/prusaslicer/ps25_nut_accelA_small.gcode"))
    assert doc["slicer_settings"]["accelerations"]["perimeter_acceleration"] == 2000.0
    assert any("time_estimate_only" in note for note in doc["slicer_settings"]["notes"])
    assert doc["slicer_settings"]["origin"] == "settings in the file"


def test_limits_without_a_file_shows_the_machines_values(
        capsys: pytest.CaptureFixture[str]) -> None:
    doc = run_json(capsys, "--printer-cfg", str(CORPUS_CFG))
    assert doc["file"] is None and doc["slicer"] is None
    assert doc["limits"]["max_velocity"] == {"value": 300.0, "source": f"{CORPUS_CFG}:7",
                                             "overridden": []}


def test_overridden_values_are_listed_with_their_sources(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    gcode = CORPUS / "gcode/orcaslicer/accelctl_orca1.5.0_klipper_m204.gcode"
    doc = run_json(capsys, str(gcode), "--printer-cfg", str(CORPUS_CFG))
    assert doc["limits"]["max_velocity"]["overridden"] == [{
        "value": 500.0,
        "source": "slicer: machine_max_speed_x = 500,200 (least of machine_max_speed_x, "
                  "machine_max_speed_y)"}]


@pytest.mark.parametrize(("argv", "message"), [
    (["--set", "max_accel"], "--set takes KEY=VALUE"),
    (["--set", "max_accel=x"], "--set max_accel: max_accel must be a number"),
])
def test_bad_set_options_fail_with_one_line(argv: list[str], message: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["limits", *argv]) == cli.EXIT_FAILURE
    err = capsys.readouterr().err
    assert err.startswith("kestimator: error: ") and message in err


def test_printer_cfg_and_moonraker_together_are_a_usage_error(
        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["limits", "--printer-cfg", "a", "--moonraker", "http://b"])
    assert exit_info.value.code == cli.EXIT_USAGE


def test_estimate_through_moonraker_equals_klippers_reference_then_works_offline(
        capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    ref = json.loads((CORPUS / "reference/prusaslicer/ps25_nut_accelA_small.json").read_text())
    gcode = str(CORPUS / ref["file"])
    fake = FakeMoonraker(copy.deepcopy(CORPUS_SETTINGS), api_key=API_KEY).start()
    try:
        argv = ["estimate", gcode, "--moonraker", fake.url, "--api-key", API_KEY, "--json"]
        assert cli.main(argv) == 0
        online = json.loads(capsys.readouterr().out)
    finally:
        fake.stop()
    assert abs(online["total_s"] - ref["total_s"]) <= 0.01
    assert online["limits_source"] == f"moonraker {fake.url}"
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    offline = json.loads(captured.out)
    assert offline["total_s"] == online["total_s"]
    assert "printer offline" in offline["limits_source"]
    assert any("cached" in warning for warning in offline["warnings"])
    assert API_KEY not in captured.out + captured.err


def test_the_profile_gives_the_machine_to_the_hook_line_without_arguments(
        private_home: Path, capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    profile = private_home / "config" / "kestimator" / "config.toml"
    profile.parent.mkdir(parents=True)
    profile.write_text(f'printer_cfg = "{CORPUS_CFG}"\n', encoding="utf-8")
    gcode = CORPUS / "gcode/prusaslicer/ps25_nut_accelA_small.gcode"
    assert cli.main(["estimate", str(gcode), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["limits_source"] == str(CORPUS_CFG)
    assert not any("printer.cfg" in warning for warning in doc["warnings"])
    assert cli.main(["limits", str(gcode), "--no-profile", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["machine"] is None
