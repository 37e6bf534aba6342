"""Tests for kestimator.config.printer_cfg: printer.cfg read as Klipper reads it."""

from __future__ import annotations

import configparser
import dataclasses
import os
from pathlib import Path
from typing import Any

import pytest

from kestimator.config.printer_cfg import (
    KESTIMATOR_DEFAULT,
    KLIPPER_DEFAULT,
    REQUIRED_FALLBACK,
    ConfigValue,
    limits_from_printer_cfg,
    printer_cfg_values,
    read_printer_cfg,
)
from kestimator.errors import KestimatorError
from kestimator.limits import HeaterLimits, Limits

CORPUS_CFG = Path(__file__).resolve().parents[2] / "shared" / "corpus" / "printer.cfg"

SAVE_CONFIG_HEADER = (
    "#*# <---------------------- SAVE_CONFIG ---------------------->\n"
    "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n"
    "#*#\n"
)


def write(base: Path, name: str, text: str) -> Path:
    """Write text to base/name (creating folders) and return the path."""
    path = base / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def values(sections: dict[str, dict[str, ConfigValue]]) -> dict[str, dict[str, str]]:
    """Sections with the raw text only."""
    return {name: {opt: v.value for opt, v in opts.items()}
            for name, opts in sections.items()}


# --- syntax -----------------------------------------------------------------------------

def test_colon_and_equals_both_separate_option_from_value(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nmax_velocity: 250\nmax_accel = 4000\nkinematics:corexy\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "250", "max_accel": "4000", "kinematics": "corexy"}}


def test_first_separator_ends_the_option_name(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[gcode_macro X]\nvariable_a = {'k': 1}\ndescription: a=b: c\n")
    assert values(read_printer_cfg(cfg))["gcode_macro x"] == {
        "variable_a": "{'k': 1}", "description": "a=b: c"}


def test_option_and_section_names_are_read_case_insensitively(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[Printer]\nMAX_Velocity: 250\n")
    sections = read_printer_cfg(cfg)
    assert sections["printer"]["max_velocity"].value == "250"


def test_hash_starts_a_comment_anywhere_on_a_line(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "# header comment\n[printer] # trailing\nmax_velocity: 250 # fast\n"
                "max_accel: 4000#no space needed\n    # indented comment\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "250", "max_accel": "4000"}}


def test_semicolon_is_a_comment_only_at_line_start_or_after_whitespace(
        tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "; whole line\n[printer]\nmax_velocity: 250 ; note\n"
                "  ; indented whole line\nkinematics: corexy;not a comment\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "250", "kinematics": "corexy;not a comment"}}


def test_semicolon_glued_to_a_number_makes_it_a_bad_value(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[printer]\nmax_accel: 3000;fast\n")
    with pytest.raises(KestimatorError) as info:
        limits_from_printer_cfg(cfg)
    assert (info.value.path, info.value.line) == (str(cfg), 2)


def test_gcode_template_continuation_lines_stay_in_their_value(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", (
        "[gcode_macro PRINT_START]\n"
        "gcode:\n"
        "    {% set bed = params.BED|default(60)|float %}\n"
        "    M190 S{bed} ; wait for bed\n"
        "# a comment between template lines\n"
        "\n"
        "    [not_a_section]\n"
        "    max_velocity: 1\n"
        "    G28\n"
        "\n"
        "[printer]\n"
        "max_velocity: 250\n"))
    sections = read_printer_cfg(cfg)
    assert sections["gcode_macro print_start"]["gcode"].value == (
        "\n{% set bed = params.BED|default(60)|float %}\nM190 S{bed}\n\n\n"
        "[not_a_section]\nmax_velocity: 1\nG28")
    assert "not_a_section" not in sections
    assert sections["printer"]["max_velocity"] == ConfigValue("250", str(cfg), 12)


def test_a_line_indented_like_its_option_is_not_a_continuation(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\n  max_velocity: 250\n  max_accel: 4000\n    ignored: x\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "250", "max_accel": "4000\nignored: x"}}


def test_parsing_matches_configparser_set_up_as_klipper_does(tmp_path: Path) -> None:
    text = ("[printer]\nmax_velocity = 250 ; c\nmax_accel:4000\n\n[gcode_macro m]\n"
            "gcode:\n  G1 X1;x\n\n  ; skipped\n  G1 X2\n\n\n[printer]\nmax_accel: 5000\n"
            "[stepper_x]\n  step_pin: PA1\n     dir_pin: PA2\n")
    cfg = write(tmp_path, "printer.cfg", text)
    parser = configparser.RawConfigParser(strict=False, inline_comment_prefixes=(";", "#"))
    parser.read_string(text)
    expected = {section: dict(parser.items(section)) for section in parser.sections()}
    assert values(read_printer_cfg(cfg)) == expected


def test_crlf_line_endings_are_read_like_lf(tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_bytes(b"[printer]\r\nmax_velocity: 250\r\ngcode:\r\n  G28\r\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "250", "gcode": "\nG28"}}


# --- duplicates ---------------------------------------------------------------------------

def test_later_duplicate_option_overrides_earlier_and_moves_provenance(
        tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nmax_velocity: 250\nmax_velocity: 280\n")
    assert read_printer_cfg(cfg)["printer"]["max_velocity"] == ConfigValue(
        "280", str(cfg), 3)


def test_repeated_section_merges_into_the_first(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nmax_velocity: 250\nmax_accel: 4000\n[extruder]\n"
                "nozzle_diameter: 0.6\n[printer]\nmax_accel: 5000\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "250", "max_accel": "5000"},
        "extruder": {"nozzle_diameter": "0.6"}}


# --- includes -----------------------------------------------------------------------------

def test_include_is_relative_to_the_including_files_directory(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[include conf/motion.cfg]\n")
    write(tmp_path, "conf/motion.cfg",
          "[printer]\nmax_velocity: 250\n[include extra.cfg]\n")
    write(tmp_path, "conf/extra.cfg", "[extruder]\nnozzle_diameter: 0.6\n")
    sections = read_printer_cfg(cfg)
    assert sections["printer"]["max_velocity"] == ConfigValue(
        "250", str(tmp_path / "conf" / "motion.cfg"), 2)
    assert sections["extruder"]["nozzle_diameter"] == ConfigValue(
        "0.6", str(tmp_path / "conf" / "extra.cfg"), 2)


def test_include_glob_reads_matches_in_sorted_order(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[include parts/*.cfg]\n")
    write(tmp_path, "parts/b.cfg", "[printer]\nmax_velocity: 200\nmax_accel: 2000\n")
    write(tmp_path, "parts/a.cfg", "[printer]\nmax_velocity: 100\n")
    write(tmp_path, "parts/c.txt", "[printer]\nmax_velocity: 999\n")
    sections = read_printer_cfg(cfg)
    assert values(sections) == {"printer": {"max_velocity": "200", "max_accel": "2000"}}
    assert sections["printer"]["max_velocity"].path == str(tmp_path / "parts" / "b.cfg")


def test_include_glob_matching_nothing_is_allowed(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[include macros/*.cfg]\n[printer]\nmax_accel: 1\n")
    assert values(read_printer_cfg(cfg)) == {"printer": {"max_accel": "1"}}


def test_missing_plain_include_is_an_error_at_the_include_line(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[printer]\nmax_accel: 1\n[include absent.cfg]\n")
    with pytest.raises(KestimatorError, match="does not exist") as info:
        read_printer_cfg(cfg)
    assert (info.value.path, info.value.line) == (str(cfg), 3)


def test_included_values_apply_in_file_order(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nmax_velocity: 100\nmax_accel: 1000\n[include over.cfg]\n"
                "[printer]\nmax_accel: 3000\n")
    write(tmp_path, "over.cfg", "[printer]\nmax_velocity: 200\nmax_accel: 2000\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "200", "max_accel": "3000"}}


def test_option_right_after_an_include_needs_a_section_header(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\n[include other.cfg]\nmax_velocity: 300\n")
    write(tmp_path, "other.cfg", "[extruder]\n")
    with pytest.raises(KestimatorError, match="section") as info:
        read_printer_cfg(cfg)
    assert (info.value.path, info.value.line) == (str(cfg), 3)


def test_include_cycle_is_reported_with_the_chain(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[include a.cfg]\n")
    write(tmp_path, "a.cfg", "[printer]\n[include sub/b.cfg]\n")
    write(tmp_path, "sub/b.cfg", "[include ../a.cfg]\n")
    with pytest.raises(KestimatorError, match="include cycle") as info:
        read_printer_cfg(cfg)
    assert "a.cfg -> " in info.value.message
    assert (info.value.path, info.value.line) == (str(tmp_path / "sub" / "b.cfg"), 1)


def test_including_the_same_file_twice_is_not_a_cycle(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[include common.cfg]\n[printer]\nmax_accel: 1\n[include common.cfg]\n")
    write(tmp_path, "common.cfg", "[printer]\nmax_velocity: 123\n")
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "123", "max_accel": "1"}}


def test_unreadable_include_names_the_include_line(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[printer]\n[include folder*]\n")
    (tmp_path / "folder1").mkdir()
    with pytest.raises(KestimatorError, match="cannot read included file") as info:
        read_printer_cfg(cfg)
    assert (info.value.path, info.value.line) == (str(cfg), 2)


# --- SAVE_CONFIG --------------------------------------------------------------------------

def test_save_config_block_adds_its_options_with_their_lines(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nmax_velocity: 250\n\n" + SAVE_CONFIG_HEADER
                + "#*# [printer]\n#*# max_accel = 4321\n#*#\n#*# [bed_mesh default]\n"
                "#*# points =\n#*# \t  0.1, 0.2\n#*# \t  0.3, 0.4\n")
    sections = read_printer_cfg(cfg)
    assert sections["printer"]["max_accel"] == ConfigValue("4321", str(cfg), 8)
    assert sections["bed_mesh default"]["points"].value == "\n0.1, 0.2\n0.3, 0.4"


def test_save_config_option_joins_a_section_declared_in_an_include(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[include base.cfg]\n\n" + SAVE_CONFIG_HEADER
                + "#*# [extruder]\n#*# nozzle_diameter = 0.6\n")
    write(tmp_path, "base.cfg", "[extruder]\nfilament_diameter: 1.75\n")
    limits, provenance = limits_from_printer_cfg(cfg)
    assert limits.nozzle_diameter == 0.6
    assert provenance["nozzle_diameter"] == f"{cfg}:7"


def test_option_set_above_save_config_wins_as_in_klipper(tmp_path: Path) -> None:
    # Klipper comments out the SAVE_CONFIG copy of an option the regular config sets
    # (its SAVE_CONFIG command comments out the regular one when it saves).
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nmax_accel: 1000\n\n" + SAVE_CONFIG_HEADER
                + "#*# [printer]\n#*# max_accel = 4321\n#*# max_velocity = 222\n")
    sections = read_printer_cfg(cfg)
    assert sections["printer"]["max_accel"] == ConfigValue("1000", str(cfg), 2)
    assert sections["printer"]["max_velocity"] == ConfigValue("222", str(cfg), 9)


def test_save_config_block_edited_after_its_header_is_ignored(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nmax_velocity: 250\n\n" + SAVE_CONFIG_HEADER
                + "#*# [printer]\n#*# max_accel = 4321\nmax_accel: 5\n")
    # Klipper ignores the block (it warns "modifications after header"); the plain line
    # then belongs to [printer] above.
    assert values(read_printer_cfg(cfg)) == {
        "printer": {"max_velocity": "250", "max_accel": "5"}}


def test_save_config_block_is_read_only_from_the_main_file(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[include other.cfg]\n")
    write(tmp_path, "other.cfg",
          "[printer]\nmax_velocity: 250\n\n" + SAVE_CONFIG_HEADER
          + "#*# [printer]\n#*# max_accel = 4321\n")
    assert values(read_printer_cfg(cfg)) == {"printer": {"max_velocity": "250"}}


# --- Limits -------------------------------------------------------------------------------

def test_absent_options_get_klippers_defaults_and_say_so(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[printer]\nmax_velocity: 200\nmax_accel: 2000\n")
    limits, provenance = limits_from_printer_cfg(cfg)
    assert limits == Limits.from_values({"max_velocity": 200.0, "max_accel": 2000.0,
                                         "configured_sections": limits.configured_sections})
    assert set(provenance) == set(Limits.field_names())
    assert provenance["max_velocity"] == f"{cfg}:2"
    assert provenance["square_corner_velocity"] == KLIPPER_DEFAULT
    assert provenance["arcs_enabled"] == KLIPPER_DEFAULT
    assert provenance["max_z_velocity"] == "derived from max_velocity"
    assert provenance["max_extrude_only_accel"] == "derived from max_accel"
    assert provenance["kinematics"] == REQUIRED_FALLBACK
    assert provenance["klipper_generation"] == KESTIMATOR_DEFAULT
    assert not limits.arcs_enabled and not limits.firmware_retraction_enabled


def test_empty_config_gives_the_stand_in_limits(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "")
    limits, provenance = limits_from_printer_cfg(cfg)
    assert limits == Limits.from_values({})
    assert provenance["max_velocity"] == REQUIRED_FALLBACK


def test_section_presence_enables_arcs_and_firmware_retraction(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg", "[printer]\n[gcode_arcs]\n[firmware_retraction]\n")
    limits, provenance = limits_from_printer_cfg(cfg)
    assert limits.arcs_enabled and limits.firmware_retraction_enabled
    assert (limits.arc_resolution, limits.retract_speed, limits.unretract_speed) == (
        1.0, 20.0, 10.0)
    assert provenance["arcs_enabled"] == f"{cfg}:2"
    assert provenance["firmware_retraction_enabled"] == f"{cfg}:3"
    assert provenance["arc_resolution"] == KLIPPER_DEFAULT


def test_extruder_options_map_to_limits(tmp_path: Path) -> None:
    cfg = write(tmp_path, "printer.cfg",
                "[printer]\nkinematics: corexy\nmax_velocity: 500\nmax_accel: 10000\n"
                "max_accel_to_decel: 5000\n[extruder]\nnozzle_diameter: 0.6\n"
                "filament_diameter: 2.85\n")
    limits, provenance = limits_from_printer_cfg(cfg)
    assert limits == Limits.from_values({
        "kinematics": "corexy", "max_velocity": 500.0, "max_accel": 10000.0,
        "max_accel_to_decel": 5000.0, "nozzle_diameter": 0.6, "filament_diameter": 2.85,
        "configured_sections": ("printer", "extruder")})
    assert limits.max_extrude_cross_section == pytest.approx(4 * 0.6**2)
    assert provenance["filament_diameter"] == f"{cfg}:8"
    assert provenance["max_extrude_cross_section"] == "derived from nozzle_diameter"


@pytest.mark.parametrize("line", [
    "max_velocity: fast", "max_velocity: 300 mm/s", "max_velocity: nan",
    "max_velocity:", "max_velocity: 300\n  400"])
def test_value_that_is_not_a_number_names_file_and_line(tmp_path: Path, line: str) -> None:
    cfg = write(tmp_path, "printer.cfg", "[include motion.cfg]\n")
    motion = write(tmp_path, "motion.cfg", "# motion\n[printer]\n" + line + "\n")
    with pytest.raises(KestimatorError, match="max_velocity") as info:
        limits_from_printer_cfg(cfg)
    assert (info.value.path, info.value.line) == (str(motion), 3)
    assert str(info.value).startswith(f"{motion}:3: ")


@pytest.mark.parametrize(("section", "line"), [
    ("printer", "max_accel: 0"),
    ("printer", "minimum_cruise_ratio: 1"),
    ("printer", "square_corner_velocity: -1"),
    ("printer", "max_z_velocity: 301"),
    ("extruder", "filament_diameter: 0.3"),
    ("gcode_arcs", "resolution: 0"),
    ("firmware_retraction", "retract_speed: 0.5"),
])
def test_value_outside_klippers_bounds_names_file_and_line(
        tmp_path: Path, section: str, line: str) -> None:
    cfg = write(tmp_path, "printer.cfg",
                f"[printer]\nmax_velocity: 300\nmax_accel: 3000\n[{section}]\n{line}\n")
    with pytest.raises(KestimatorError, match="must be") as info:
        limits_from_printer_cfg(cfg)
    assert (info.value.path, info.value.line) == (str(cfg), 5)


@pytest.mark.parametrize("text", [
    "max_velocity: 300\n", "[printer]\nG28\n", "[printer]\n: 5\n"])
def test_line_that_is_not_config_syntax_names_file_and_line(
        tmp_path: Path, text: str) -> None:
    cfg = write(tmp_path, "printer.cfg", text)
    with pytest.raises(KestimatorError) as info:
        read_printer_cfg(cfg)
    assert (info.value.path, info.value.line) == (str(cfg), text.count("\n"))


def test_missing_config_file_raises_kestimator_error(tmp_path: Path) -> None:
    missing = tmp_path / "nope.cfg"
    with pytest.raises(KestimatorError, match="cannot read config file") as info:
        limits_from_printer_cfg(missing)
    assert info.value.path == str(missing)


def test_non_utf8_config_raises_with_the_line(tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_bytes(b"[printer]\n# 60\xb0C\n")
    with pytest.raises(KestimatorError, match="UTF-8") as info:
        read_printer_cfg(cfg)
    assert info.value.line == 2


def test_path_like_and_relative_paths_are_accepted(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    write(tmp_path, "cfg/printer.cfg", "[include motion.cfg]\n")
    write(tmp_path, "cfg/motion.cfg", "[printer]\nmax_velocity: 250\n")
    monkeypatch.chdir(tmp_path)
    limits, provenance = limits_from_printer_cfg(Path("cfg") / "printer.cfg")
    assert limits.max_velocity == 250.0
    assert provenance["max_velocity"] == os.path.join("cfg", "motion.cfg") + ":2"


# --- the corpus's printer.cfg -------------------------------------------------------------

def test_corpus_printer_cfg_gives_the_reference_limits() -> None:
    limits, provenance = limits_from_printer_cfg(CORPUS_CFG)
    expected = {
        "kinematics": "cartesian", "max_velocity": 300.0, "max_accel": 3000.0,
        "square_corner_velocity": 5.0, "minimum_cruise_ratio": 0.5,
        "max_z_velocity": 15.0, "max_z_accel": 100.0,
        "max_extrude_only_velocity": 120.0, "max_extrude_only_accel": 1500.0,
        "max_extrude_only_distance": 10000.0, "max_extrude_cross_section": 1000.0,
        "instantaneous_corner_velocity": 1.0, "nozzle_diameter": 0.4,
        "filament_diameter": 1.75, "arcs_enabled": True, "arc_resolution": 1.0,
        "firmware_retraction_enabled": True, "retract_length": 0.8, "retract_speed": 35.0,
        "unretract_extra_length": 0.0, "unretract_speed": 35.0,
    }
    assert {name: getattr(limits, name) for name in expected} == expected
    # The corpus config also has an [extruder1], the same as [extruder] but for its name.
    assert limits.extruders == (dataclasses.replace(limits.primary_extruder,
                                                    name="extruder1"),)
    # Every heater 0..300 C; the extruders extrude at any temperature (min_extrude_temp 0).
    assert limits.heaters == (HeaterLimits("extruder", 0.0, 300.0, 0.0),
                              HeaterLimits("extruder1", 0.0, 300.0, 0.0),
                              HeaterLimits("heater_bed", 0.0, 300.0, 170.0))
    assert limits == dataclasses.replace(Limits.from_values({}), extruders=limits.extruders,
                                         configured_sections=limits.configured_sections,
                                         heaters=limits.heaters, **expected)
    for name in expected:
        assert provenance[name].startswith(str(CORPUS_CFG) + ":"), name
    assert provenance["max_velocity"] == f"{CORPUS_CFG}:7"


def test_corpus_printer_cfg_reads_every_section() -> None:
    sections = read_printer_cfg(CORPUS_CFG)
    assert list(sections) == ["mcu", "printer", "stepper_x", "stepper_y", "stepper_z",
                              "extruder", "heater_bed", "gcode_arcs", "firmware_retraction",
                              "display_status", "extruder1"]
    assert sections["display_status"] == {}
    assert sections["extruder"]["sensor_type"].value == "EPCOS 100K B57560G104F"


def test_a_config_of_comments_only_is_a_config_without_sections(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Klipper's config/example.cfg is only comments: it was "internal error: KeyError:
    # 'configured_sections'". Now it is a config that gives nothing (every value guessed).
    from kestimator import cli

    cfg = tmp_path / "example.cfg"
    cfg.write_text("# This file serves as documentation for config parameters.\n#[printer]\n"
                   "#kinematics: cartesian\n")
    limits, provenance = limits_from_printer_cfg(cfg)
    assert limits.configured_sections == ()
    assert provenance["configured_sections"] == f"{cfg}: no sections"
    gcode = tmp_path / "a.gcode"
    gcode.write_text("G28\nG1 X10 F3000\n")
    for command in ("estimate", "check", "limits"):
        assert cli.main([command, str(gcode), "--printer-cfg", str(cfg)]) == 0, command
    assert "internal error" not in capsys.readouterr().err


def test_the_last_values_are_kept_while_every_file_and_include_pattern_reads_the_same(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from kestimator.config import printer_cfg

    parsed: list[str] = []
    real = printer_cfg._printer_cfg_values

    def counting(path: str, config: Any) -> Any:
        parsed.append(path)
        return real(path, config)

    monkeypatch.setattr(printer_cfg, "_printer_cfg_values", counting)
    monkeypatch.setattr(printer_cfg, "_last", None)
    main = write(tmp_path, "printer.cfg",
                 CORPUS_CFG.read_text().replace("max_accel: 3000", "max_accel: 3000\n"
                                                "[include extra/*.cfg]\n[printer]"))
    extra = write(tmp_path, "extra/speed.cfg", "[printer]\nmax_velocity: 250\n")

    def velocity() -> object:
        values, provenance, _machine = printer_cfg_values(main)
        values["max_velocity"] = -1.0  # the caller's copy: the next answer is unchanged
        provenance.clear()
        return printer_cfg_values(main)[0]["max_velocity"]

    assert velocity() == 250.0 and len(parsed) == 1
    assert velocity() == 250.0 and len(parsed) == 1  # kept: nothing changed
    stat = extra.stat()
    extra.write_text("[printer]\nmax_velocity: 260\n")  # same size, same times
    os.utime(extra, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert velocity() == 260.0 and len(parsed) == 2
    write(tmp_path, "extra/zz_more.cfg", "[printer]\nmax_velocity: 270\n")  # a new match
    assert velocity() == 270.0 and len(parsed) == 3
    (tmp_path / "extra" / "zz_more.cfg").unlink()
    assert velocity() == 260.0 and len(parsed) == 4
    main.write_text(main.read_text().replace("max_accel: 3000", "max_accel: 2500"))
    assert printer_cfg_values(main)[0]["max_accel"] == 2500.0 and len(parsed) == 5
    main.unlink()  # gone: read again, and the error raised
    with pytest.raises(KestimatorError):
        printer_cfg_values(main)
