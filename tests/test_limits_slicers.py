"""What each slicer family's embedded settings stand for in Klipper, read from real corpus files.

The corpus is read in place. Every mapped value and its provenance is pinned against the
file's own config lines (quoted in the comments), so a wrong key, a wrong vector element or a
machine limit used against ``machine_limits_usage`` shows up here.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from kestimator.slicers import read_slicer_settings
from kestimator.slicers.cura import map_cura_settings, read_setting_3
from kestimator.slicers.settings import SlicerValue, first_item, trailing_config

from .conftest import CORPUS

GCODE = CORPUS / "gcode"


def mapped(path: Path, environ: dict[str, str] | None = None) -> dict[str, object]:
    """Field -> mapped value for a file (and environment)."""
    _info, settings = read_slicer_settings(path, environ)
    return {limit.field: limit.value for limit in settings.limits}


def sources(path: Path, environ: dict[str, str] | None = None) -> dict[str, str]:
    _info, settings = read_slicer_settings(path, environ)
    return {limit.field: limit.source for limit in settings.limits}


# --- PrusaSlicer / SuperSlicer / Slic3r -----------------------------------------------------

def test_prusaslicer_machine_limits_used_when_emitted_to_gcode(corpus_root: Path) -> None:
    # PrusaSlicer 2.8.1, MK4S: machine_limits_usage = emit_to_gcode, "normal,stealth" pairs,
    # arc_fitting = emit_center.
    path = GCODE / "prusaslicer/libbgcode_mini_cube_ps2.8.1_arcs.gcode"
    assert mapped(path) == {
        "max_velocity": 300.0,            # machine_max_feedrate_x/y = 300,160
        "max_accel": 4000.0,              # extruding/x/y = 4000,2500
        "max_z_velocity": 40.0,           # machine_max_feedrate_z = 40,40
        "max_z_accel": 200.0,             # machine_max_acceleration_z = 200,200
        "max_extrude_only_velocity": 100.0,   # machine_max_feedrate_e = 100,100
        "max_extrude_only_accel": 1200.0,     # machine_max_acceleration_retracting = 1200,1200
        "square_corner_velocity": 8.0,    # machine_max_jerk_x/y = 8,8 (a guess)
        "nozzle_diameter": 0.4,
        "filament_diameter": 1.75,
        "arcs_enabled": True,
    }
    assert sources(path)["arcs_enabled"] == "slicer: arc_fitting = emit_center"


def test_the_least_of_the_extruding_and_axis_limits_becomes_max_accel(corpus_root: Path) -> None:
    # PrusaSlicer 2.3.3 writes its config without begin/end markers; extruding 1500,1250 is
    # below x/y 9000,1000 (normal column).
    path = GCODE / "prusaslicer/cancelobj_ps2.3.3_issue1.gcode"
    assert mapped(path)["max_accel"] == 1500.0
    assert sources(path)["max_accel"] == (
        "slicer: machine_max_acceleration_extruding = 1500,1250 (least of "
        "machine_max_acceleration_extruding, machine_max_acceleration_x, "
        "machine_max_acceleration_y)")
    assert mapped(path)["max_velocity"] == 500.0


def test_single_value_limits_of_printers_without_stealth_mode(corpus_root: Path) -> None:
    # PrusaSlicer 2.6.1, MINI: one value per limit; extruding 1250 below x/y 2500.
    values = mapped(GCODE / "prusaslicer/gcodepreview_benchy_ps2.6.1.gcode")
    assert (values["max_velocity"], values["max_accel"], values["max_z_velocity"],
            values["max_extrude_only_accel"]) == (180.0, 1250.0, 12.0, 1250.0)


@pytest.mark.parametrize("name", [
    "prusaslicer/bricklayers_cube10_ps2.9.0_klipper.gcode",
    "prusaslicer/cancelobj_ps2.4.0a1_arcwelder.gcode",
    "prusaslicer/ps25_nut_accelA_small.gcode",
    "superslicer/cancelobj_ss2.3.56_arcwelder.gcode",
])
def test_machine_limits_for_time_estimate_only_are_not_the_printers(
        name: str, corpus_root: Path) -> None:
    info, settings = read_slicer_settings(GCODE / name)
    fields = {limit.field for limit in settings.limits}
    assert fields.isdisjoint({"max_velocity", "max_accel", "max_z_velocity", "max_z_accel",
                              "square_corner_velocity", "max_extrude_only_velocity",
                              "max_extrude_only_accel"})
    assert any("machine_limits_usage = time_estimate_only" in note for note in settings.notes)
    assert {limit.field: limit.value for limit in settings.limits}["nozzle_diameter"] == 0.4


def test_firmware_retraction_follows_use_firmware_retraction(corpus_root: Path) -> None:
    # The 40 MB file: use_firmware_retraction = 1, retract_length = 0.8, retract_speed = 35,
    # deretract_speed = 0 (as fast as the retraction), retract_restart_extra = 0.
    path = GCODE / "prusaslicer/ps25_bunny120_fast_fwretract_large.gcode"
    values = mapped(path)
    assert {key: values[key] for key in (
        "firmware_retraction_enabled", "retract_length", "retract_speed", "unretract_speed",
        "unretract_extra_length")} == {
        "firmware_retraction_enabled": True, "retract_length": 0.8, "retract_speed": 35.0,
        "unretract_speed": 35.0, "unretract_extra_length": 0.0}
    assert "deretract_speed = 0" in sources(path)["unretract_speed"]
    assert "firmware_retraction_enabled" not in mapped(
        GCODE / "prusaslicer/ps25_nut_accelA_small.gcode")


def test_a_nil_filament_override_falls_back_to_the_printer_value(tmp_path: Path) -> None:
    block = ["; prusaslicer_config = begin", "; use_firmware_retraction = 1",
             "; filament_retract_length = nil", "; retract_length = 0.6,0.9",
             "; filament_retract_speed = 45", "; retract_speed = 30",
             "; deretract_speed = 25", "; prusaslicer_config = end"]
    path = tmp_path / "p.gcode"
    path.write_text("; generated by PrusaSlicer 2.9.0 on 2025-01-01 at 10:00:00 UTC\n"
                    "G1 X1\n" + "\n".join(block) + "\n")
    values = mapped(path)
    assert (values["retract_length"], values["retract_speed"], values["unretract_speed"]) == (
        0.6, 45.0, 25.0)
    assert sources(path)["retract_speed"] == "slicer: filament_retract_speed = 45"


def test_superslicer_percentages_are_resolved_for_the_accelerations_the_file_sets(
        tmp_path: Path) -> None:
    path = tmp_path / "s.gcode"
    path.write_text("; generated by SuperSlicer 2.5.59 on 2024-01-01 at 10:00:00 UTC\n"
                    "G1 X1\n; SuperSlicer_config = begin\n"
                    "; machine_max_acceleration_x = 4000,1000\n"
                    "; machine_max_acceleration_y = 5000,1000\n"
                    "; default_acceleration = 50%\n; perimeter_acceleration = 80%\n"
                    "; infill_acceleration = 0\n; travel_acceleration = 3000\n"
                    "; machine_limits_usage = time_estimate_only\n"
                    "; SuperSlicer_config = end\n")
    _info, settings = read_slicer_settings(path)
    assert dict(settings.accelerations) == {"default_acceleration": 2500.0,
                                            "perimeter_acceleration": 2000.0,
                                            "travel_acceleration": 3000.0}


def test_slic3r_config_without_markers_is_read_to_the_last_gcode_line() -> None:
    text = ("G1 X1 ; speed = 99\n; not = a setting above the last move\nG1 X2\n"
            "; cog_x = 1.5\n\n; nozzle_diameter = 0.5\n; gcode_arcs = 0\n")
    config = trailing_config(text)
    assert set(config) == {"cog_x", "nozzle_diameter", "gcode_arcs"}


def test_marlin2_flavor_is_reported_as_writing_accelerations_klipper_ignores(
        corpus_root: Path) -> None:
    _info, settings = read_slicer_settings(GCODE / "prusaslicer/ps25_nut_accelA_small.gcode")
    assert any(note.startswith("slicer: gcode_flavor = marlin2") for note in settings.notes)
    _info, klipper = read_slicer_settings(
        GCODE / "prusaslicer/bricklayers_cube10_ps2.9.0_klipper.gcode")
    assert not any("gcode_flavor" in note for note in klipper.notes)


# --- OrcaSlicer / Bambu Studio --------------------------------------------------------------

def test_orcaslicer_config_block_with_per_extruder_vectors(corpus_root: Path) -> None:
    path = GCODE / "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode"
    info, settings = read_slicer_settings(path)
    assert info.name == "OrcaSlicer"
    assert settings.by_field()["filament_diameter"].source == (
        "slicer: filament_diameter = 1.75,1.75,1.75,1.75")
    assert mapped(path) == {
        "max_velocity": 600.0, "max_accel": 20000.0, "max_z_velocity": 20.0,
        "max_z_accel": 500.0, "max_extrude_only_velocity": 30.0,
        "max_extrude_only_accel": 5000.0, "square_corner_velocity": 9.0,
        "nozzle_diameter": 0.4, "filament_diameter": 1.75}
    # bridge_acceleration = 50% of outer_wall_acceleration = 5000.
    assert dict(settings.accelerations)["bridge_acceleration"] == 2500.0
    assert settings.printer_preset == "Flashforge Adventurer 5M Pro 0.4 Nozzle - Pond Cottage"


def test_orcaslicer_1_5_without_emit_key_uses_its_machine_limits(corpus_root: Path) -> None:
    values = mapped(GCODE / "orcaslicer/accelctl_orca1.5.0_klipper_m204.gcode")
    assert (values["max_velocity"], values["max_z_velocity"],
            values["max_extrude_only_velocity"]) == (500.0, 12.0, 25.0)


def test_bambu_studio_config_block_at_the_top_with_arc_fitting(corpus_root: Path) -> None:
    path = GCODE / "bambustudio/gcodeparsersharp_bs1.6.2.gcode"
    values = mapped(path)
    assert values["arcs_enabled"] is True
    assert sources(path)["arcs_enabled"] == "slicer: enable_arc_fitting = 1"
    assert values["max_z_accel"] == 500.0


def test_orca_accel_to_decel_and_nil_and_structure(tmp_path: Path) -> None:
    path = tmp_path / "o.gcode"
    path.write_text("; generated by OrcaSlicer 2.3.1 on 2025-11-26 at 23:53:47\nG1 X1\n"
                    "; CONFIG_BLOCK_START\n; accel_to_decel_enable = 1\n"
                    "; accel_to_decel_factor = 50%\n; printer_structure = corexy\n"
                    "; nozzle_diameter = nil,0.6\n; emit_machine_limits_to_gcode = 0\n"
                    "; machine_max_speed_x = 500,500\n; CONFIG_BLOCK_END\n")
    _info, settings = read_slicer_settings(path)
    values = {limit.field: limit.value for limit in settings.limits}
    assert values == {"kinematics": "corexy"}
    assert any("ACCEL_TO_DECEL" in note and "klipper_generation" in note
               for note in settings.notes)
    assert any("emit_machine_limits_to_gcode = 0" in note for note in settings.notes)


# --- Cura -----------------------------------------------------------------------------------

def test_cura_setting_3_material_diameter(corpus_root: Path) -> None:
    # Cura 2.3.1: ";SETTING_3 ... material_diameter = 1.75 ..." among formulas.
    path = GCODE / "cura/gcodepreview_puzzle_cura2.3.1.gcode"
    assert mapped(path) == {"filament_diameter": 1.75}
    assert sources(path) == {"filament_diameter": "slicer: material_diameter = 1.75"}


def test_cura_setting_3_is_unescaped_as_cura_writes_it(corpus_root: Path) -> None:
    text = (GCODE / "cura/cancelobj_cura4.10.0.gcode").read_text(encoding="utf-8")
    config = read_setting_3(text)
    assert config["material_flow"].text == "92.0"        # the extruder's quality changes
    assert config["support_structure"].text == "tree"    # the global ones


def test_cura_machine_settings_map_and_unlimited_and_formulas_do_not(tmp_path: Path) -> None:
    profile = ("[general]\nversion = 4\n\n[values]\nmachine_max_feedrate_x = 300\n"
               "machine_max_feedrate_y = 299792458000\nmachine_max_acceleration_x = =9*1000\n"
               "machine_max_acceleration_y = 2500\nmachine_max_jerk_xy = 10\n"
               "machine_firmware_retract = True\nretraction_amount = 0.7\n"
               "retraction_speed = 40\n")
    escaped = json.dumps({"global_quality": profile}).replace("\\", "\\\\")
    lines = [";SETTING_3 " + escaped[i:i + 69] for i in range(0, len(escaped), 69)]
    path = tmp_path / "c.gcode"
    path.write_text(";FLAVOR:Marlin\n;Generated with Cura_SteamEngine 5.7.0\nG1 X1\n"
                    + "\n".join(lines) + "\n")
    _info, settings = read_slicer_settings(path)
    assert {limit.field: limit.value for limit in settings.limits} == {
        "max_velocity": 300.0, "max_accel": 2500.0, "square_corner_velocity": 10.0,
        "firmware_retraction_enabled": True, "retract_length": 0.7, "retract_speed": 40.0,
        "unretract_speed": 40.0}
    assert any("machine_max_acceleration_x = =9*1000" in note for note in settings.notes)


def test_cura_reprap_flavor_is_reported(corpus_root: Path) -> None:
    _info, settings = read_slicer_settings(GCODE / "cura/cancelobj_cura4.10.0.gcode")
    assert any(note.startswith("slicer: ;FLAVOR:RepRap") for note in settings.notes)


def test_map_cura_settings_takes_the_cura_plugins_values() -> None:
    settings = map_cura_settings({"material_diameter": SlicerValue("material_diameter", "2.85"),
                                  "machine_nozzle_size": SlicerValue("machine_nozzle_size",
                                                                     "0.6")})
    assert settings.by_field()["filament_diameter"].value == 2.85
    assert settings.by_field()["nozzle_diameter"].value == 0.6


# --- the environment of a post-processing script ---------------------------------------------

def test_slic3r_environment_fills_in_what_the_file_lacks(corpus_root: Path) -> None:
    # SuperSlicer 2.4's file has no config block; the hook's environment has the config.
    path = GCODE / "superslicer/cancelobj_ss2.4_inverted_pyramid.gcode"
    assert mapped(path) == {}
    environ = {"SLIC3R_MACHINE_LIMITS_USAGE": "emit_to_gcode",
               "SLIC3R_MACHINE_MAX_FEEDRATE_X": "250,100",
               "SLIC3R_MACHINE_MAX_FEEDRATE_Y": "240,100",
               "SLIC3R_PP_OUTPUT_NAME": "/tmp/x.gcode", "PATH": "/usr/bin"}
    info, settings = read_slicer_settings(path, environ)
    assert settings.origin == "SLIC3R_* environment"
    assert settings.by_field()["max_velocity"].source == (
        "slicer: SLIC3R_MACHINE_MAX_FEEDRATE_Y = 240,100 (least of machine_max_feedrate_x, "
        "machine_max_feedrate_y)")


def test_the_file_wins_over_the_environment_key_by_key(corpus_root: Path) -> None:
    path = GCODE / "prusaslicer/libbgcode_mini_cube_ps2.8.1_arcs.gcode"
    environ = {"SLIC3R_MACHINE_MAX_FEEDRATE_Z": "5", "SLIC3R_NOZZLE_DIAMETER": "0.25"}
    _info, settings = read_slicer_settings(path, environ)
    assert settings.origin == "settings in the file + SLIC3R_* environment"
    assert settings.by_field()["max_z_velocity"].value == 40.0
    assert settings.by_field()["nozzle_diameter"].value == 0.4


def test_an_unrecognised_file_takes_its_family_from_the_environment(tmp_path: Path) -> None:
    path = tmp_path / "binary.bgcode"
    path.write_bytes(b"GCDE\x01\x00\x00\x00")
    orca = {"SLIC3R_MACHINE_MAX_SPEED_X": "400", "SLIC3R_MACHINE_MAX_SPEED_Y": "300",
            "SLIC3R_OUTER_WALL_ACCELERATION": "3000"}
    assert mapped(path, orca) == {"max_velocity": 300.0}
    prusa = {"SLIC3R_MACHINE_MAX_FEEDRATE_X": "200", "SLIC3R_MACHINE_MAX_FEEDRATE_Y": "150"}
    assert mapped(path, prusa) == {"max_velocity": 150.0}


def test_vector_first_items_and_nil() -> None:
    assert first_item("1500,1250") == "1500"
    assert first_item("nil,0.4") is None
    assert first_item("") is None
    assert first_item("80%") == "80%"


def test_the_settings_cache_answers_again_only_for_the_same_bytes_and_environment(
        corpus_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import kestimator.slicers as slicers

    parsed: list[int] = []
    parse = slicers._read_slicer_settings

    def counting(ends: Any, environ: Any) -> Any:
        parsed.append(1)
        return parse(ends, environ)
    monkeypatch.setattr(slicers, "_read_slicer_settings", counting)
    path = tmp_path / "a.gcode"
    data = (GCODE / "prusaslicer/libbgcode_mini_cube_ps2.8.1_arcs.gcode").read_bytes()
    path.write_bytes(data)
    cache = slicers.SettingsCache()
    environ = {"SLIC3R_NOZZLE_DIAMETER": "0.25"}
    first = read_slicer_settings(path, environ, cache)
    assert first == read_slicer_settings(path, environ)  # as without a cache
    assert read_slicer_settings(path, dict(environ), cache) is first and len(parsed) == 2
    # The same size, another value: parsed again, as without a cache.
    changed = data.replace(b"max_feedrate_z = 40", b"max_feedrate_z = 41")
    assert changed != data and len(changed) == len(data)
    path.write_bytes(changed)
    _info, second = read_slicer_settings(path, environ, cache)
    assert second.by_field()["max_z_velocity"].value == 41.0 and len(parsed) == 3
    # Another environment: parsed again.
    _info, third = read_slicer_settings(path, {}, cache)
    assert third.origin == "settings in the file" and len(parsed) == 4
    # A large file (ends of a MiB each, read again a block at a time): an edit between the
    # ends changes nothing read; one in the last MiB is parsed again; the file cut short
    # too.
    middle = b"; padding line of a large file\n" * 100_000
    head, tail = data[:4000], data[4000:]
    path.write_bytes(head + middle + tail)
    big = read_slicer_settings(path, environ, cache)
    assert big == read_slicer_settings(path, environ) and len(parsed) == 6
    half = len(middle) // 2  # 1.5 MiB from either end
    path.write_bytes(head + middle[:half] + middle[half:].replace(b"padding", b"PADDING", 9)
                     + tail)
    assert read_slicer_settings(path, environ, cache) is big and len(parsed) == 6
    path.write_bytes(head + middle + tail.replace(b"max_feedrate_z = 40",
                                                  b"max_feedrate_z = 42"))
    _info, edited = read_slicer_settings(path, environ, cache)
    assert edited.by_field()["max_z_velocity"].value == 42.0 and len(parsed) == 7
    path.write_bytes(data)
    assert read_slicer_settings(path, environ, cache) == first and len(parsed) == 8
    path.write_bytes(data + b"; one line more\n")  # a small file grown: read again
    read_slicer_settings(path, environ, cache)
    assert len(parsed) == 9
