"""Heater limits and cold extrusion in the pre-flight (issue 26).

Klipper's own answers for these cases are in tests/oracle_refs/ (preflight_heater_*,
preflight_cold_*; test_real_printer_configs.py runs them): here the cases the oracle cannot
show (Moonraker's settings, no printer config, macros, heat-up before extrusion), each
against the oracle references' heaters.cfg ([extruder] 0..250 with min_extrude_temp 170,
[extruder1] 10..280, [heater_bed] 0..100, [heater_generic chamber] 0..80).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from kestimator.config.moonraker import settings_values
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.errors import KestimatorError
from kestimator.estimate import Estimate, estimate_text
from kestimator.limits import HeaterLimits, Limits

REFS = Path(__file__).parent / "oracle_refs"
HEATERS_CFG = REFS / "configs" / "heaters.cfg"
COLD = "Extrude below minimum temp See the 'min_extrude_temp' config option for details"
STOP = "Klipper stops the print here: "


@pytest.fixture(scope="module")
def limits() -> Limits:
    return limits_from_printer_cfg(HEATERS_CFG)[0]


def _kinds(est: Estimate) -> dict[str, tuple[int | None, str]]:
    return {f.kind: (f.line, f.message) for f in est.preflight}


def test_printer_cfg_gives_every_heaters_range_in_klippers_order(limits: Limits) -> None:
    assert limits.heaters == (
        HeaterLimits("extruder", 0.0, 250.0, 170.0),
        HeaterLimits("extruder1", 10.0, 280.0, 170.0),
        HeaterLimits("heater_bed", 0.0, 100.0, 170.0),
        HeaterLimits("heater_generic chamber", 0.0, 80.0, 170.0))


def test_a_heater_range_klipper_refuses_is_an_error_with_file_and_line(
        tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: none\nmax_velocity: 100\nmax_accel: 100\n"
                   "[extruder]\nmin_temp: 0\nmax_temp: 250\nmin_extrude_temp: 300\n")
    with pytest.raises(KestimatorError, match=r"printer.cfg:8.*min_extrude_temp must be "
                                              r"between min_temp \(0\) and max_temp \(250\)"):
        limits_from_printer_cfg(cfg)


def test_moonraker_settings_give_the_heaters_ranges(limits: Limits) -> None:
    settings = {
        "printer": {"kinematics": "cartesian", "max_velocity": 300.0, "max_accel": 3000.0},
        "extruder": {"min_temp": 0.0, "max_temp": 250.0, "min_extrude_temp": 170.0},
        "extruder1": {"min_temp": 10.0, "max_temp": 280.0, "min_extrude_temp": 170.0},
        "heater_bed": {"min_temp": 0.0, "max_temp": 100.0, "min_extrude_temp": 170.0},
        "heater_generic chamber": {"min_temp": 0.0, "max_temp": 80.0},
    }
    found = Limits.from_values(settings_values(settings, "moonraker test").values)
    assert found.heaters == limits.heaters
    est = estimate_text("M140 S105\n", found)
    assert _kinds(est)["stop"] == (
        1, STOP + "Requested temperature (105.0) out of range (0.0:100.0)")


def test_without_a_printer_config_no_temperature_is_checked() -> None:
    est = estimate_text("M104 S999\nM109 S999\nM140 S999\nM104 T7 S200\n"
                        "SET_HEATER_TEMPERATURE HEATER=x TARGET=999\nG1 X10 E0.1\n",
                        Limits.from_values({}))
    assert not est.preflight


def test_a_heater_without_min_and_max_temp_is_not_checked(limits: Limits) -> None:
    # Klipper requires both: a config without them is not the printer's whole story.
    unknown = limits.replace(heaters=())
    est = estimate_text("M104 S999\nG1 X10 E0.1\n", unknown)
    assert not est.preflight


@pytest.mark.parametrize("text, line, message", [
    ("G28\nM104 S260\n", 2, "Requested temperature (260.0) out of range (0.0:250.0)"),
    ("M104 T1 S9\n", 1, "Requested temperature (9.0) out of range (10.0:280.0)"),
    ("M109 T3 S200\n", 1, "Extruder not configured"),
    ("M104 T-1 S200\n", 1, "Error on 'M104 T-1 S200': T must have minimum of 0"),
    ("SET_HEATER_TEMPERATURE HEATER=extruder1 TARGET=281\n", 1,
     "Requested temperature (281.0) out of range (10.0:280.0)"),
    ("SET_HEATER_TEMPERATURE TARGET=20\n", 1,
     "Error on 'SET_HEATER_TEMPERATURE TARGET=20': missing HEATER"),
    ("SET_HEATER_TEMPERATURE HEATER=xyz TARGET=20\n", 1,
     "The value 'xyz' is not valid for HEATER. Options: 'extruder', 'extruder1', "
     "'heater_bed', 'chamber'"),
    ("TEMPERATURE_WAIT SENSOR=extruder\n", 1,
     "Error on 'TEMPERATURE_WAIT': missing MINIMUM or MAXIMUM."),
])
def test_what_klipper_refuses_stops_the_print_there(limits: Limits, text: str, line: int,
                                                     message: str) -> None:
    est = estimate_text(text, limits)
    assert _kinds(est)["stop"] == (line, STOP + message)


def test_turning_heaters_off_and_waiting_beyond_a_sensors_range_are_fine(
        limits: Limits) -> None:
    est = estimate_text("M104 S0\nM104 T1 S0\nM104 T5 S0\nM109 T5\nM140 S0\nM190\n"
                        "SET_HEATER_TEMPERATURE HEATER=chamber\nTURN_OFF_HEATERS\n"
                        "TEMPERATURE_WAIT SENSOR=extruder MINIMUM=1000\n", limits)
    assert not est.preflight


def test_m140_needs_a_heater_bed_and_stays_a_module_command(limits: Limits) -> None:
    est = estimate_text("M140 S60\nM140 S60\n", limits)
    assert est.commands["module"]["M140"] == 2
    sections = tuple(s for s in limits.configured_sections if s != "heater_bed")
    bedless = limits.replace(configured_sections=sections)
    est = estimate_text("M140 S0\nM140 S150\nM190 S150\n", bedless)
    assert [(f.kind, f.line, f.message) for f in est.preflight] == [
        ("skipped", 2, 'Unknown command:"M140": Klipper skips it'),
        ("skipped", 3, 'Unknown command:"M190": Klipper skips it')]


def test_a_macro_named_like_a_heater_command_runs_instead(limits: Limits) -> None:
    macro = limits.replace(gcode_macros=(("M104", "{% set s = params.S %}"),))
    est = estimate_text("M104 S999\n", macro)
    assert not est.preflight


# --- cold extrusion ------------------------------------------------------------------------

def test_extruding_before_any_heat_up_stops_the_print(limits: Limits) -> None:
    est = estimate_text("G28\nG1 X10 Y10 F3000\nG1 X20 E1\nG1 X30 E1\n", limits)
    assert _kinds(est)["stop"] == (3, STOP + COLD)


def test_a_retraction_before_any_heat_up_stops_it_too(limits: Limits) -> None:
    est = estimate_text("G28\nG1 E-1 F1800\nM109 S200\nG1 X20 E1\n", limits)
    assert _kinds(est)["stop"] == (2, STOP + COLD)


@pytest.mark.parametrize("heat", ["M104 S170", "M109 S210", "M104 T0 S200",
                                  "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=200"])
def test_a_heater_set_hot_before_extruding_is_fine(limits: Limits, heat: str) -> None:
    est = estimate_text("G28\n%s\nG1 X10 Y10 F3000\nG1 X20 E1\nM104 S0\nG1 E-2\n"
                        "G1 X0 Y0 E0.5\n" % heat, limits)
    assert not est.preflight


def test_a_heater_set_below_min_extrude_temp_is_still_cold(limits: Limits) -> None:
    est = estimate_text("M109 S150\nG1 X20 E1\n", limits)
    assert _kinds(est)["stop"] == (2, STOP + COLD)


def test_each_extruder_is_heated_on_its_own(limits: Limits) -> None:
    text = ("M104 S200\nG1 X10 E1\nACTIVATE_EXTRUDER EXTRUDER=extruder1\nG1 X20 E1\n")
    assert _kinds(estimate_text(text, limits))["stop"] == (4, STOP + COLD)
    text = ("M104 T1 S200\nACTIVATE_EXTRUDER EXTRUDER=extruder1\nG1 X20 E1\n"
            "ACTIVATE_EXTRUDER EXTRUDER=extruder\nM104 S200\nG1 X30 E1\n")
    assert not estimate_text(text, limits).preflight


def test_a_start_macro_whose_commands_are_unknown_may_heat(limits: Limits) -> None:
    # Moonraker knows macros by name only.
    named = limits.replace(gcode_macros=(("START_PRINT", ""),))
    est = estimate_text("START_PRINT\nG1 X10 F3000\nG1 X20 E1\nG1 X30 E1\n", named)
    assert [(f.kind, f.severity, f.line) for f in est.preflight] == [
        ("may_stop", "warning", 3)]
    assert est.preflight[0].message.startswith(
        "Klipper may stop the print here: Extrude below minimum temp (if 'START_PRINT'")
    assert not est.stops_print


def test_a_start_macro_that_sets_a_heater_heats(limits: Limits) -> None:
    heating = limits.replace(gcode_macros=(
        ("START_PRINT", "{% set t = params.T|default(210) %}\nG28\nM109 S{t}"),))
    assert not estimate_text("START_PRINT\nG1 X20 E1\n", heating).preflight
    literal = limits.replace(gcode_macros=(("START_PRINT", "G28\nM109 S210"),))
    assert not estimate_text("START_PRINT\nG1 X20 E1\n", literal).preflight


def test_a_macro_known_not_to_heat_does_not(limits: Limits) -> None:
    homing = limits.replace(gcode_macros=(("START_PRINT", "{% if true %}G28{% endif %}"),))
    est = estimate_text("START_PRINT\nG1 X20 E1\n", homing)
    assert _kinds(est)["stop"] == (2, STOP + COLD)
    # A macro the printer does not have is skipped by Klipper: it heats nothing either.
    est = estimate_text("START_PRINT\nG1 X20 E1\n", limits)
    assert _kinds(est)["stop"] == (2, STOP + COLD)


def test_a_macro_calling_another_macro_may_heat(limits: Limits) -> None:
    calling = limits.replace(gcode_macros=(("START_PRINT", "{% if true %}HEAT_UP{% endif %}"),
                                           ("HEAT_UP", "{% set t = 1 %}")))
    est = estimate_text("START_PRINT\nG1 X20 E1\n", calling)
    assert [f.kind for f in est.preflight] == ["may_stop"]


def test_min_extrude_temp_0_never_checks(limits: Limits) -> None:
    heaters = tuple(dataclasses.replace(h, min_extrude_temp=0.0) for h in limits.heaters)
    assert not estimate_text("G1 X20 E1\n", limits.replace(heaters=heaters)).preflight


def test_a_cold_extrusion_costs_no_time_beyond_its_move(limits: Limits) -> None:
    # The print once fixed: the refused move is skipped as for any stop, the rest is timed.
    text = "G28\nG1 X10 Y10 F3000\nG1 X20 E1\nG1 X30 E1\n"
    cold = estimate_text(text, limits)
    hot = estimate_text("M104 S200\n" + text, limits)
    assert 0.0 < cold.total_s < hot.total_s
