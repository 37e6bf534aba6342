"""The table of commands Klipper registers (kestimator/klipper_commands.py) against real Klipper.

Real Klipper 84104bbbd (the oracle's, batch mode) is started on every printer config it
ships and on its own test configs, each with a [gcode_macro], a [delayed_gcode] and the
sections every Mainsail/Fluidd setup adds (tools/klipper_commands.py `ADDED_SECTIONS`), and
on the modules no shipped config has (`EXTRA_PROBES`); once ready, the commands its gcode
object holds are what the pre-flight must know there, on every one of those configs: no
"Unknown command" for any of them, one for each command no loaded module registers.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest

from kestimator import klipper_commands
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_text
from kestimator.interpreter import printer_commands
from kestimator.klipper_modules import MODULE_COMMANDS, silently_ignored
from kestimator.limits import Limits

from .conftest import PROJECT, require_klipper

sys.path.insert(0, str(PROJECT / "tools"))
import klipper_commands as tool  # type: ignore[import-not-found]  # noqa: E402

# Names no Klipper module registers (a Marlin M-code, RepRapFirmware's, a typo'd command).
NEVER_REGISTERED = ("M600", "M486", "M900", "G29", "BED_MESH_CALIBRATES", "SET_Z_FADE")


@pytest.fixture(scope="module")
def survey() -> dict[str, dict[str, Any]]:
    """What Klipper registered on each config it ships (with ADDED_SECTIONS)."""
    klipper, _ = require_klipper()
    done, failed = tool.probe_all(tool.shipped_configs(klipper))
    assert not failed, failed
    assert len(done) > 200
    return done


# Configs Klipper starts with that kestimator's reader refuses (a bug of its own, not of
# the table): input_shaper.cfg's `ei(v_tol=0.02)` (stepgen.shaper_pulses takes no ei
# parameters).
UNREADABLE = {"klippy/input_shaper.cfg"}
# Configs whose G28 kestimator refuses (a limit of its own): none since machine.py reads a
# named [probe_eddy_current NAME]'s Z endstop (tests/oracle_refs/corexy_eddy).
ESTIMATE_REFUSES: set[str] = set()
# What the table cannot tell from section names: query_adc.py is loaded only for an ADC
# sensor, and linuxtest.cfg's one temperature_sensor is a DS18B20. The table's answer
# errs to the side of knowing.
OPTION_CONDITIONAL = {("klippy/linuxtest.cfg", "QUERY_ADC")}


def config_text(name: str) -> str:
    """A probed config's text, as Klipper's tree holds it (with what the probe added)."""
    klipper, _ = require_klipper()
    path, extra = tool.config_path(klipper, name)
    return Path(path).read_text(errors="replace") + extra


def printer_limits(text: str) -> Limits:
    """The limits kestimator reads from a config with ADDED_SECTIONS."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "printer.cfg"
        cfg.write_text(text + "\n" + tool.ADDED_SECTIONS % {"dir": tmp})
        limits, _ = limits_from_printer_cfg(cfg)
    return limits


def predicted(name: str, result: dict[str, Any]) -> set[str]:
    """The commands kestimator says Klipper holds with this config (and its macros)."""
    known = printer_commands(printer_limits(config_text(name)))
    assert known is not None
    return set(known) | tool.macro_commands(result)


def test_the_table_is_what_klipper_registers_over_its_shipped_configs(
        survey: dict[str, dict[str, Any]]) -> None:
    klipper, _ = require_klipper()
    source = tool.table_source(tool.build_table(survey), tool.shipped_configs(klipper))
    assert (PROJECT / "kestimator" / "klipper_commands.py").read_text() == source, (
        "run: python3 tools/klipper_commands.py table > kestimator/klipper_commands.py")


def test_each_config_knows_exactly_the_commands_klipper_registers_for_it(
        survey: dict[str, dict[str, Any]]) -> None:
    wrong = {}
    unreadable = set()
    for name, result in survey.items():
        actual = set(result["commands"])
        try:
            mine = predicted(name, result)
        except KestimatorError:
            unreadable.add(name)
            continue
        over = {cmd for cmd in mine - actual if (name, cmd) not in OPTION_CONDITIONAL}
        if actual - mine or over:
            wrong[name] = {"called unknown": sorted(actual - mine),
                           "not registered": sorted(over)}
    assert not wrong, wrong
    assert unreadable == UNREADABLE


def test_klipper_commands_from_the_issue_are_known_on_every_config(
        survey: dict[str, dict[str, Any]]) -> None:
    everywhere = {"SET_GCODE_VARIABLE", "UPDATE_DELAYED_GCODE", "SAVE_CONFIG", "RESTART",
                  "FIRMWARE_RESTART", "SET_STEPPER_ENABLE", "STEPPER_BUZZ", "MANUAL_PROBE",
                  "M28", "M29", "M30", "Z_ENDSTOP_CALIBRATE", "Z_OFFSET_APPLY_ENDSTOP"}
    for name, result in survey.items():
        if result["kinematics"] == "none" or name in UNREADABLE:
            continue
        mine = predicted(name, result)
        assert everywhere - {"Z_ENDSTOP_CALIBRATE", "Z_OFFSET_APPLY_ENDSTOP"} <= mine, name
        assert everywhere & set(result["commands"]) <= mine, name
    assert {"PROBE", "QUERY_PROBE", "PROBE_ACCURACY", "PROBE_CALIBRATE",
            "Z_OFFSET_APPLY_PROBE", "BLTOUCH_DEBUG", "BLTOUCH_STORE"} <= set(
                MODULE_COMMANDS["bltouch"])
    assert {"SET_DUAL_CARRIAGE", "SAVE_DUAL_CARRIAGE_STATE",
            "RESTORE_DUAL_CARRIAGE_STATE"} <= set(MODULE_COMMANDS["dual_carriage"])
    assert "SET_STEPPER_CARRIAGES" in MODULE_COMMANDS["kinematics/generic_cartesian"]


def _skipped(cfg_text: str, commands: list[str]) -> dict[str, int]:
    """The pre-flight's skipped commands (name -> count) for a file naming `commands`, one
    a line, on a printer with this config."""
    est = estimate_text("".join(c + "\n" for c in commands), printer_limits(cfg_text))
    return {f.message.split('"')[1]: f.count for f in est.preflight if f.kind == "skipped"}


def test_preflight_calls_no_registered_command_unknown_and_every_other_one(
        survey: dict[str, dict[str, Any]]) -> None:
    every = sorted({c for names in MODULE_COMMANDS.values() for c in names})
    wrong = {}
    refused = set()
    for config, result in survey.items():
        if config in UNREADABLE:
            continue
        text = config_text(config)
        registered = sorted(result["commands"])
        try:
            called_unknown = _skipped(text, registered)
        except KestimatorError:
            refused.add(config)
            continue
        others = [c for c in every + list(NEVER_REGISTERED)
                  if c not in result["commands"] and not silently_ignored(c, {})
                  and (config, c) not in OPTION_CONDITIONAL]
        found = _skipped(text, others)
        if called_unknown or found != {name: 1 for name in others}:
            wrong[config] = {"called unknown": called_unknown,
                             "not found": sorted(set(others) - set(found))}
    assert not wrong, wrong
    assert refused == ESTIMATE_REFUSES


def test_the_table_names_its_klipper() -> None:
    assert klipper_commands.KLIPPER_COMMIT == "84104bbbd"
