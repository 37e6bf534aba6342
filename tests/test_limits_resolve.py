"""The resolver: precedence (--set, machine, profile, slicer, defaults), provenance, the
Klipper generation, and the rule that slicer guesses never touch what a printer.cfg decides."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.config.resolve import (
    ASSUMPTIONS,
    GENERATION_DEFAULT,
    NO_CONFIG_FALLBACK,
    LimitRequest,
    resolve_limits,
)
from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_file
from kestimator.limits import Limits

from .conftest import CORPUS, CORPUS_CFG, corpus_files

MK4S = CORPUS / "gcode/prusaslicer/libbgcode_mini_cube_ps2.8.1_arcs.gcode"
ORCA = CORPUS / "gcode/orcaslicer/accelctl_orca1.5.0_klipper_m204.gcode"
# A hook's environment that disagrees with everything, to show it cannot leak.
HOSTILE_SLICER_ENVIRONMENT = {
    "SLIC3R_MACHINE_LIMITS_USAGE": "emit_to_gcode", "SLIC3R_MACHINE_MAX_FEEDRATE_X": "77",
    "SLIC3R_MACHINE_MAX_FEEDRATE_Y": "77", "SLIC3R_MACHINE_MAX_ACCELERATION_EXTRUDING": "333",
    "SLIC3R_MACHINE_MAX_JERK_X": "1", "SLIC3R_NOZZLE_DIAMETER": "0.25",
    "SLIC3R_USE_FIRMWARE_RETRACTION": "1", "SLIC3R_RETRACT_LENGTH": "9",
}


@pytest.fixture
def environ(tmp_path: Path) -> dict[str, str]:
    """No profile, a private cache, the hostile slicer environment."""
    return {"HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / "config"),
            "XDG_CACHE_HOME": str(tmp_path / "cache"), **HOSTILE_SLICER_ENVIRONMENT}


def write_profile(environ: dict[str, str], text: str) -> Path:
    path = Path(environ["XDG_CONFIG_HOME"]) / "kestimator" / "config.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("path", corpus_files(), ids=lambda p: p.parent.name + "/" + p.name)
def test_with_a_printer_cfg_no_slicer_setting_or_profile_value_changes_a_limit(
        path: Path, environ: dict[str, str], corpus_root: Path) -> None:
    write_profile(environ, "[limits]\nmax_accel = 1234\nsquare_corner_velocity = 2\n"
                           "arcs_enabled = false\n")
    resolved = resolve_limits(LimitRequest(gcode=path, printer_cfg=CORPUS_CFG,
                                           environ=environ))
    assert resolved.limits == limits_from_printer_cfg(CORPUS_CFG)[0]
    assert not any(source.startswith(("slicer:", "profile ", "kestimator assumption"))
                   for source in resolved.sources.values())


def test_the_corpus_reference_is_reproduced_through_the_resolver(
        environ: dict[str, str], corpus_root: Path) -> None:
    # PrusaSlicer 2.3.3 emits its machine limits (500 mm/s, 1500 mm/s^2): guesses that would
    # change the time, and must not.
    ref = json.loads((CORPUS / "reference/prusaslicer/cancelobj_ps2.3.3_issue1.json")
                     .read_text())
    gcode = CORPUS / ref["file"]
    resolved = resolve_limits(LimitRequest(gcode=gcode, printer_cfg=CORPUS_CFG,
                                           environ=environ))
    assert abs(estimate_file(gcode, resolved.limits).total_s - ref["total_s"]) <= 0.01


def test_set_beats_the_printer_cfg_and_keeps_what_it_overrode(
        environ: dict[str, str], corpus_root: Path) -> None:
    resolved = resolve_limits(LimitRequest(gcode=MK4S, printer_cfg=CORPUS_CFG,
                                           overrides={"max_accel": "5000"}, environ=environ))
    assert resolved.limits.max_accel == 5000.0
    assert resolved.sources["max_accel"] == "--set"
    overridden = [(c.value, c.source) for c in resolved.shadowed["max_accel"]]
    assert overridden[0] == (3000.0, f"{CORPUS_CFG}:8")
    assert overridden[1][0] == 4000.0 and overridden[1][1].startswith("slicer: ")
    assert resolved.summary == f"{CORPUS_CFG} + --set"


def test_without_a_machine_the_profile_beats_the_slicer_and_the_slicer_beats_defaults(
        environ: dict[str, str], corpus_root: Path) -> None:
    profile = write_profile(environ, "[limits]\nmax_accel = 2500\n")
    resolved = resolve_limits(LimitRequest(gcode=MK4S, environ={
        key: value for key, value in environ.items() if not key.startswith("SLIC3R_")}))
    assert resolved.limits.max_accel == 2500.0
    assert resolved.sources["max_accel"] == f"profile {profile}"
    assert resolved.limits.max_velocity == 300.0
    assert resolved.sources["max_velocity"].startswith("slicer: machine_max_feedrate_x = 300,160")
    assert resolved.sources["minimum_cruise_ratio"] == "klipper default"
    assert resolved.sources["kinematics"] == NO_CONFIG_FALLBACK
    assert resolved.machine is None
    assert resolved.summary == (f"profile {profile} + PrusaSlicer settings in the file "
                                "(guesses) + defaults")
    assert any("no printer.cfg or Moonraker given" in w for w in resolved.warnings)


def test_the_profile_names_the_printer_cfg_so_no_argument_is_needed(
        environ: dict[str, str], tmp_path: Path, corpus_root: Path) -> None:
    write_profile(environ, f'printer_cfg = "{CORPUS_CFG}"\n')
    resolved = resolve_limits(LimitRequest(gcode=ORCA, environ=environ))
    assert resolved.limits == limits_from_printer_cfg(CORPUS_CFG)[0]
    assert resolved.machine == str(CORPUS_CFG)
    assert resolved.warnings == ()


def test_a_printer_cfg_on_the_command_line_replaces_the_profiles_machine(
        environ: dict[str, str], tmp_path: Path) -> None:
    write_profile(environ, 'moonraker = "http://127.0.0.1:9"\n')
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: corexy\nmax_velocity: 200\nmax_accel: 2000\n")
    resolved = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ))
    assert (resolved.limits.kinematics, resolved.limits.max_accel) == ("corexy", 2000.0)
    assert resolved.sources["max_z_velocity"] == "derived from max_velocity"


def test_without_a_machine_arcs_and_firmware_retraction_are_assumed_and_can_be_refused(
        environ: dict[str, str], tmp_path: Path) -> None:
    plain = {key: value for key, value in environ.items() if not key.startswith("SLIC3R_")}
    resolved = resolve_limits(LimitRequest(environ=plain))
    assert resolved.limits.arcs_enabled and resolved.limits.firmware_retraction_enabled
    assert resolved.sources["arcs_enabled"] == ASSUMPTIONS["arcs_enabled"]
    write_profile(environ, "[limits]\narcs_enabled = false\n")
    assert not resolve_limits(LimitRequest(environ=plain)).limits.arcs_enabled
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: cartesian\nmax_velocity: 200\nmax_accel: 2000\n")
    with_cfg = resolve_limits(LimitRequest(printer_cfg=cfg, environ=plain))
    assert not with_cfg.limits.arcs_enabled and not with_cfg.limits.firmware_retraction_enabled
    assert with_cfg.sources["arcs_enabled"] == "klipper default"


def test_the_generation_defaults_to_mainline_and_is_settable_in_every_source(
        environ: dict[str, str], tmp_path: Path) -> None:
    plain = {key: value for key, value in environ.items() if not key.startswith("SLIC3R_")}
    assert resolve_limits(LimitRequest(environ=plain)).sources["klipper_generation"] == (
        GENERATION_DEFAULT)
    gcode = tmp_path / "notes.gcode"
    gcode.write_text("; generated by PrusaSlicer 2.9.0 on 2025-01-01 at 10:00:00 UTC\nG1 X1\n"
                     "; printer_notes = my voron\\nkestimator: klipper_generation = absolute\n")
    from_slicer = resolve_limits(LimitRequest(gcode=gcode, environ=plain))
    assert from_slicer.limits.klipper_generation == "absolute"
    write_profile(environ, '[limits]\nklipper_generation = "mcr"\n')
    from_profile = resolve_limits(LimitRequest(gcode=gcode, environ=plain))
    assert from_profile.limits.klipper_generation == "mcr"
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("# kestimator: klipper_generation = absolute\n[printer]\n"
                   "kinematics: cartesian\nmax_velocity: 200\nmax_accel: 2000\n")
    from_cfg = resolve_limits(LimitRequest(printer_cfg=cfg, environ=plain))
    assert (from_cfg.limits.klipper_generation, from_cfg.sources["klipper_generation"]) == (
        "absolute", f"{cfg}:1")
    from_set = resolve_limits(LimitRequest(printer_cfg=cfg, environ=plain,
                                           overrides={"klipper_generation": "mainline"}))
    assert from_set.limits.klipper_generation == "mainline"


def test_mcr_generation_converts_max_accel_to_decel_into_minimum_cruise_ratio(
        environ: dict[str, str], tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 4000\n"
                   "max_accel_to_decel: 1000\n")
    resolved = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                           overrides={"klipper_generation": "mcr"}))
    assert resolved.limits.minimum_cruise_ratio == pytest.approx(0.75)
    assert resolved.sources["minimum_cruise_ratio"].startswith(
        f"converted from max_accel_to_decel ({cfg}:5)")
    mainline = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ))
    assert mainline.limits.minimum_cruise_ratio == 0.5
    assert any("max_accel_to_decel" in w and "mainline Klipper refuses" in w
               for w in mainline.warnings)
    cfg.write_text(cfg.read_text() + "minimum_cruise_ratio: 0.1\n")
    explicit = resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ,
                                           overrides={"klipper_generation": "mcr"}))
    assert explicit.limits.minimum_cruise_ratio == 0.1


def test_an_accel_to_decel_above_max_accel_gives_a_cruise_ratio_of_zero(
        environ: dict[str, str], tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("# kestimator: klipper_generation = mcr\n[printer]\nkinematics: cartesian\n"
                   "max_velocity: 300\nmax_accel: 2000\nmax_accel_to_decel: 5000\n")
    assert resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ)
                          ).limits.minimum_cruise_ratio == 0.0


def test_a_slicer_guess_beyond_a_klipper_bound_is_capped_a_users_value_is_an_error(
        environ: dict[str, str], corpus_root: Path) -> None:
    plain = {key: value for key, value in environ.items() if not key.startswith("SLIC3R_")}
    capped = resolve_limits(LimitRequest(gcode=MK4S, environ=plain,
                                         overrides={"max_velocity": "30"}))
    assert capped.limits.max_z_velocity == 30.0
    assert "(capped: Klipper requires max_z_velocity at most max_velocity)" in (
        capped.sources["max_z_velocity"])
    with pytest.raises(KestimatorError, match="max_z_velocity 50 .--set. must be at most "
                                              "max_velocity 30"):
        resolve_limits(LimitRequest(gcode=MK4S, environ=plain,
                                    overrides={"max_velocity": "30", "max_z_velocity": "50"}))


def test_a_slicer_value_klipper_would_refuse_is_left_out_with_a_warning(
        environ: dict[str, str], tmp_path: Path) -> None:
    gcode = tmp_path / "slow.gcode"
    gcode.write_text("; generated by PrusaSlicer 2.9.0 on 2025-01-01 at 10:00:00 UTC\nG1 X1\n"
                     "; use_firmware_retraction = 1\n; retract_speed = 0.5\n")
    plain = {key: value for key, value in environ.items() if not key.startswith("SLIC3R_")}
    resolved = resolve_limits(LimitRequest(gcode=gcode, environ=plain))
    assert resolved.limits.retract_speed == Limits().retract_speed
    assert any(w.startswith("slicer: retract_speed = 0.5: not used") for w in resolved.warnings)


@pytest.mark.parametrize(("overrides", "message"), [
    ({"max_acel": "1"}, "unknown setting 'max_acel'"),
    ({"max_accel": "fast"}, "max_accel must be a number"),
    ({"max_accel": "0"}, "max_accel must be above 0"),
    ({"minimum_cruise_ratio": "1"}, "minimum_cruise_ratio must be below 1"),
    ({"arcs_enabled": "maybe"}, "arcs_enabled must be true or false"),
    ({"klipper_generation": "2023"}, "klipper_generation must be one of mainline, mcr"),
])
def test_bad_set_values_are_errors(overrides: dict[str, str], message: str,
                                   environ: dict[str, str]) -> None:
    with pytest.raises(KestimatorError, match=message):
        resolve_limits(LimitRequest(overrides=overrides, environ=environ))


def test_set_accepts_flags_and_text(environ: dict[str, str]) -> None:
    resolved = resolve_limits(LimitRequest(environ=environ, overrides={
        "arcs_enabled": "off", "kinematics": "corexy", "max_accel": "7000"}))
    assert (resolved.limits.arcs_enabled, resolved.limits.kinematics,
            resolved.limits.max_accel) == (False, "corexy", 7000.0)


def test_both_a_printer_cfg_and_moonraker_is_an_error(environ: dict[str, str]) -> None:
    with pytest.raises(KestimatorError, match="not both"):
        resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, moonraker_url="http://x",
                                    environ=environ))


def test_the_slicer_environment_is_read_only_when_asked(
        environ: dict[str, str], tmp_path: Path) -> None:
    gcode = tmp_path / "raw.gcode"
    gcode.write_text("G1 X1\n")
    read = resolve_limits(LimitRequest(gcode=gcode, environ=environ))
    assert read.limits.max_velocity == 77.0
    ignored = resolve_limits(LimitRequest(gcode=gcode, environ=environ,
                                          read_slicer_environment=False))
    assert ignored.limits.max_velocity == 300.0


def test_a_generation_directive_naming_no_generation_is_an_error_at_its_line(
        environ: dict[str, str], tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\n# kestimator: klipper_generation = 2024\nkinematics: cartesian\n"
                   "max_velocity: 300\nmax_accel: 2000\n")
    with pytest.raises(KestimatorError, match="klipper_generation must be one of") as error:
        resolve_limits(LimitRequest(printer_cfg=cfg, environ=environ))
    assert (error.value.path, error.value.line) == (str(cfg), 2)


def test_summary_names_the_slicer_environment_when_the_file_has_no_settings(
        tmp_path: Path, environ: dict[str, str]) -> None:
    gcode = tmp_path / "print.gcode"
    gcode.write_bytes(b"; generated by PrusaSlicer 2.6.0 on 2024-01-01 at 00:00:00 UTC\n"
                      b"M83\nG1 X10 E1 F3000\n")
    resolved = resolve_limits(LimitRequest(gcode=gcode, environ=environ))
    assert "SLIC3R_* environment (guesses)" in resolved.summary
    assert "settings in the file" not in resolved.summary


def test_default_profile_is_skipped_with_a_warning_when_toml_cannot_be_read(
        environ: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> None:
    from kestimator.config import resolve as resolve_module

    write_profile(environ, "printer_cfg = '/nowhere/printer.cfg'\n")
    monkeypatch.setattr(resolve_module, "toml_available", lambda: False)
    resolved = resolve_limits(LimitRequest(environ=environ))
    assert resolved.profile is None
    assert any("needs the tomli package" in w for w in resolved.warnings)
