"""The user's TOML profile: where it is, what it may say, and which printer table applies."""

from __future__ import annotations

from pathlib import Path

import pytest

from kestimator.config.profile import default_profile_path, load_profile
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.errors import KestimatorError

from .conftest import CORPUS, CORPUS_CFG

ORCA = CORPUS / "gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode"
ORCA_PRESET = "Flashforge Adventurer 5M Pro 0.4 Nozzle - Pond Cottage"


def profile(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_the_default_profile_is_under_xdg_config_home_or_dot_config() -> None:
    assert default_profile_path({"XDG_CONFIG_HOME": "/x", "HOME": "/h"}) == Path(
        "/x/kestimator/config.toml")
    assert default_profile_path({"HOME": "/h"}) == Path("/h/.config/kestimator/config.toml")


def test_a_relative_printer_cfg_is_relative_to_the_profile(tmp_path: Path) -> None:
    loaded = load_profile(profile(tmp_path, 'printer_cfg = "klipper/printer.cfg"\n'))
    assert loaded.printer_cfg == str(tmp_path / "klipper" / "printer.cfg")
    assert loaded.moonraker is None


def test_limits_are_checked_and_typed(tmp_path: Path) -> None:
    loaded = load_profile(profile(tmp_path, "[limits]\nmax_accel = 5000\n"
                                            'klipper_generation = "mcr"\narcs_enabled = true\n'))
    assert loaded.limits == {"max_accel": 5000.0, "klipper_generation": "mcr",
                             "arcs_enabled": True}
    assert loaded.limit_sources["max_accel"] == f"profile {tmp_path / 'config.toml'}"


@pytest.mark.parametrize(("text", "message"), [
    ("printer_cfg = [", "not valid TOML"),
    ('printercfg = "x"\n', "unknown key.*printercfg"),
    ('printer_cfg = "a"\nmoonraker = "http://b"\n', "both printer_cfg and moonraker"),
    ("[limits]\nmax_accel = -1\n", r"\[limits\]: max_accel must be above 0"),
    ('[limits]\nmax_accel = "fast"\n', "max_accel must be a number"),
    ("[limits]\nmax_acel = 1\n", "unknown setting 'max_acel'"),
    ("moonraker_timeout_s = 0\n", "moonraker_timeout_s must be a number of seconds above 0"),
    ("api_key = 5\n", "api_key must be a non-empty text"),
    ('[printers.voron]\nprinter = "x"\n', r'\[printers."voron"\] unknown key'),
])
def test_mistakes_are_errors_naming_the_profile(tmp_path: Path, text: str,
                                                message: str) -> None:
    path = profile(tmp_path, text)
    with pytest.raises(KestimatorError, match=message) as error:
        load_profile(path)
    assert error.value.path == str(path)


def test_a_wrong_api_key_type_is_reported_without_echoing_a_key(tmp_path: Path) -> None:
    with pytest.raises(KestimatorError) as error:
        load_profile(profile(tmp_path, 'api_key = ""\n'))
    assert "api_key must be a non-empty text" in str(error.value)


PRINTERS = f'''printer_cfg = "{CORPUS_CFG}"
[limits]
square_corner_velocity = 4
klipper_generation = "mcr"

[printers."{ORCA_PRESET}"]
moonraker = "http://adventurer.local:7125"
api_key = "secret"
[printers."{ORCA_PRESET}".limits]
square_corner_velocity = 8

[printers.voron]
[printers.voron.limits]
max_accel = 9000
'''


def test_a_printer_table_is_chosen_by_name_and_replaces_the_machine(tmp_path: Path) -> None:
    loaded = load_profile(profile(tmp_path, PRINTERS), printer="voron")
    assert loaded.printer == "voron"
    assert loaded.printer_cfg == str(CORPUS_CFG)
    assert loaded.limits == {"square_corner_velocity": 4.0, "klipper_generation": "mcr",
                             "max_accel": 9000.0}
    assert loaded.limit_sources["max_accel"].endswith('[printers."voron"]')
    by_preset = load_profile(profile(tmp_path, PRINTERS), slicer_preset=ORCA_PRESET)
    assert (by_preset.printer_cfg, by_preset.moonraker) == (None, "http://adventurer.local:7125")
    assert by_preset.limits["square_corner_velocity"] == 8.0
    assert "secret" not in repr(by_preset)


def test_no_table_matches_an_unknown_slicer_preset_but_an_unknown_name_is_an_error(
        tmp_path: Path) -> None:
    assert load_profile(profile(tmp_path, PRINTERS), slicer_preset="Other").printer is None
    with pytest.raises(KestimatorError, match=r'no \[printers."prusa"\] table .there are: '):
        load_profile(profile(tmp_path, PRINTERS), printer="prusa")


def test_the_slicer_preset_picks_the_printer_table_when_resolving(
        tmp_path: Path, corpus_root: Path) -> None:
    config_home = tmp_path / "config"
    (config_home / "kestimator").mkdir(parents=True)
    (config_home / "kestimator" / "config.toml").write_text(
        f'[printers."{ORCA_PRESET}"]\nprinter_cfg = "{CORPUS_CFG}"\n', encoding="utf-8")
    resolved = resolve_limits(LimitRequest(gcode=ORCA, environ={
        "HOME": str(tmp_path), "XDG_CONFIG_HOME": str(config_home)}))
    assert resolved.machine == str(CORPUS_CFG)
    assert resolved.profile is not None and resolved.profile.endswith(f'"{ORCA_PRESET}"]')


def test_an_explicit_profile_must_exist_and_printer_needs_a_profile(tmp_path: Path) -> None:
    with pytest.raises(KestimatorError, match="cannot read profile"):
        resolve_limits(LimitRequest(profile=tmp_path / "missing.toml",
                                    environ={"HOME": str(tmp_path)}))
    with pytest.raises(KestimatorError, match="--printer needs a profile"):
        resolve_limits(LimitRequest(printer="voron", environ={"HOME": str(tmp_path)}))


def test_homing_and_heat_times_come_from_the_profile_unless_given(tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    from .conftest import PROJECT

    config_home = tmp_path / "config"
    (config_home / "kestimator").mkdir(parents=True)
    (config_home / "kestimator" / "config.toml").write_text(
        'printer_cfg = "%s"\nhoming_time_s = 20\nheat_time_s = 100\n' % CORPUS_CFG)
    gcode = tmp_path / "print.gcode"
    gcode.write_text("G28\nM109 S200\nM83\nG1 X10 E1 F3000\n")
    env = dict(os.environ, PYTHONPATH=str(PROJECT), XDG_CONFIG_HOME=str(config_home))

    def total(*extra: str) -> float:
        proc = subprocess.run([sys.executable, "-m", "kestimator", "estimate", str(gcode),
                               "-q", *extra], capture_output=True, text=True, env=env)
        assert proc.returncode == 0, proc.stderr
        return float(proc.stdout)

    plain = total("--no-profile", "--printer-cfg", str(CORPUS_CFG))
    assert total() == pytest.approx(plain + 120.0, abs=1e-6)
    assert total("--homing-time", "0", "--heat-time", "1") == pytest.approx(plain + 1.0,
                                                                           abs=1e-6)


def test_negative_profile_durations_are_errors(tmp_path: Path) -> None:
    path = profile(tmp_path, "heat_time_s = -5\n")
    with pytest.raises(KestimatorError, match="heat_time_s"):
        load_profile(path)
