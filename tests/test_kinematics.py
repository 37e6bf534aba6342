"""The kinematics package: how each one is chosen and built, and what it says it does not model.

Times against real Klipper are in test_kinematics_oracle.py; these pin the parts around them:
the machine description from Moonraker equals the printer.cfg one, fallbacks say so, Klipper's
config errors stop with file and line, and the start convention (homed at X=Y=Z=0).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.config.moonraker import machine_from_settings, settings_values
from kestimator.config.printer_cfg import limits_from_printer_cfg, read_printer_cfg
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_file, estimate_text
from kestimator.kinematics import KINEMATICS, load_kinematics
from kestimator.kinematics.polar import PolarKinematics
from kestimator.kinematics.standin import StandInKinematics
from kestimator.limits import Limits

from .conftest import PROJECT
from .fake_moonraker import FakeMoonraker

REFS = Path(__file__).parent / "oracle_refs"


def _typed(text: str) -> object:
    """A printer.cfg value as Klipper's configfile.settings reports it (typed)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return {"true": True, "false": False}.get(text.lower(), text)


@pytest.mark.parametrize("config", ["delta", "polar", "corexy_maxend"])
def test_moonraker_settings_give_the_same_kinematics_as_the_printer_cfg(config: str) -> None:
    cfg = REFS / config / "printer.cfg"
    settings = {name: {option: _typed(value.value) for option, value in options.items()}
                for name, options in read_printer_cfg(cfg).items()}
    found = settings_values(settings, "moonraker http://printer")
    assert found.machine is not None
    from_moonraker = Limits.from_values(found.values).replace(machine=found.machine)
    from_cfg, _ = limits_from_printer_cfg(cfg)
    snippet = {"delta": "delta_radius", "polar": "polar_center",
               "corexy_maxend": "home_then_move"}[config]
    gcode = REFS / "snippets" / (snippet + ".gcode")
    a, b = estimate_file(gcode, from_moonraker), estimate_file(gcode, from_cfg)
    assert a.total_s == b.total_s and a.layers == b.layers
    assert type(load_kinematics(from_moonraker)) is type(load_kinematics(from_cfg))


def test_moonraker_gear_ratio_lists_read_as_printer_cfg_text() -> None:
    machine = machine_from_settings({"stepper_bed": {"gear_ratio": [[80, 16], [3, 1]]}}, "m")
    section = machine.section("stepper_bed")
    assert section is not None and section.get("gear_ratio") == "80:16, 3:1"


def test_every_kinematics_klipper_ships_loads_without_a_printer_cfg() -> None:
    for name in KINEMATICS:
        kin = load_kinematics(Limits.from_values({"kinematics": name}))
        assert kin.name == name
        if name in ("cartesian", "corexy", "corexz", "hybrid_corexy", "hybrid_corexz",
                    "generic_cartesian", "none"):
            assert not kin.warnings, name
        else:
            # Never a silent number: what is not modelled is named.
            assert kin.warnings and name in kin.warnings[0], name


def test_without_the_printers_sections_other_kinematics_are_named_in_the_estimate() -> None:
    for name in ("delta", "deltesian", "rotary_delta", "polar", "winch"):
        est = estimate_text("G1 X10 Z1 F600\n", Limits.from_values({"kinematics": name}))
        assert any(name in w and "needs the printer's" in w for w in est.warnings), name


def test_a_kinematics_mainline_klipper_does_not_ship_is_named() -> None:
    est = estimate_text("G1 X10 F600\n", Limits.from_values({"kinematics": "scara"}))
    assert any("scara is not a kinematics mainline Klipper ships" in w for w in est.warnings)


def test_a_printer_cfg_without_stepper_sections_falls_back_and_says_so(tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: corexz\nmax_velocity: 300\nmax_accel: 3000\n"
                   "max_z_velocity: 5\n")
    limits, _ = limits_from_printer_cfg(cfg)
    kin = load_kinematics(limits)
    assert isinstance(kin, StandInKinematics)
    assert "no [stepper_x] section" in kin.warnings[0]
    # Z is still limited as Klipper's corexz limits it.
    assert estimate_text("G1 Z10 F6000\n", limits).total_s == pytest.approx(
        estimate_text("G1 Z10 F300\n", limits).total_s)


def test_a_rail_klipper_refuses_is_an_error_with_file_and_line(tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    text = (REFS / "corexz" / "printer.cfg").read_text()
    cfg.write_text(text.replace("position_endstop: 0\nposition_min: -5\nposition_max: 250",
                                "position_endstop: 300\nposition_min: -5\nposition_max: 250",
                                1))
    limits, _ = limits_from_printer_cfg(cfg)
    with pytest.raises(KestimatorError) as refused:
        load_kinematics(limits)
    assert "position_endstop in section 'stepper_x' must be between position_min and " \
           "position_max" in str(refused.value)
    assert str(refused.value).startswith(str(cfg) + ":")


def test_before_any_g28_the_head_is_homed_at_zero_so_ranges_apply_from_the_first_move() -> None:
    limits, _ = limits_from_printer_cfg(REFS / "corexz" / "printer.cfg")
    est = estimate_text("G1 X-6 F6000\nG1 X10 F6000\n", limits)
    assert any(":1: " in w and "Move out of range: -6.000 0.000 0.000 [0.000]" in w
               for w in est.warnings)


def test_g28_homes_to_max_endstops_and_delta_home_position() -> None:
    maxend, _ = limits_from_printer_cfg(REFS / "corexy_maxend" / "printer.cfg")
    kin = load_kinematics(maxend)
    assert kin.home((1.0, 2.0, 3.0, 4.0), [0, 1]) == ((250.0, 250.0, 3.0, 4.0), "xy")
    delta, _ = limits_from_printer_cfg(REFS / "delta" / "printer.cfg")
    pos, homed = load_kinematics(delta).home((1.0, 2.0, 3.0, 4.0), [0])
    assert homed == "xyz" and pos[3] == 4.0 and 100.0 < pos[2] < 101.0


def test_a_dual_carriage_says_what_it_changes_that_is_not_modelled() -> None:
    limits, _ = limits_from_printer_cfg(REFS / "cartesian_idex" / "printer.cfg")
    kin = load_kinematics(limits)
    assert kin.warnings == [
        "[dual_carriage]: after G28 Klipper narrows X's range by the parked carriage and "
        "safe_distance (30 mm); moves are range-checked against stepper_x's own range only"]
    est = estimate_text("G1 X10 F6000\nSET_DUAL_CARRIAGE CARRIAGE=1\nG1 X20 F6000\n", limits)
    assert any(":2: [dual_carriage]: SET_DUAL_CARRIAGE switches carriages" in w
               for w in est.warnings)


def test_the_cli_times_a_delta_from_its_printer_cfg_as_klipper_does() -> None:
    ref = json.loads((REFS / "delta" / "delta_radius.json").read_text())
    proc = subprocess.run(
        [sys.executable, "-m", "kestimator", "estimate",
         str(REFS / "snippets" / "delta_radius.gcode"),
         "--printer-cfg", str(REFS / "delta" / "printer.cfg"), "--json"],
        capture_output=True, text=True, check=True, cwd=PROJECT)
    out = json.loads(proc.stdout)
    assert abs(out["total_s"] - ref["total_s"]) <= 0.01 + 1e-6 * ref["total_s"]


def test_moonraker_gives_the_kinematics_its_sections_and_the_cache_keeps_them(
        tmp_path: Path) -> None:
    cfg = REFS / "polar" / "printer.cfg"
    settings = {name: {option: _typed(value.value) for option, value in options.items()}
                for name, options in read_printer_cfg(cfg).items()}
    fake = FakeMoonraker(settings).start()
    try:
        resolved = resolve_limits(LimitRequest(
            moonraker_url=fake.url, use_profile=False, cache_directory=tmp_path,
            environ={}))
    finally:
        fake.stop()
    assert resolved.limits.machine is not None
    assert isinstance(load_kinematics(resolved.limits), PolarKinematics)
    offline = resolve_limits(LimitRequest(
        moonraker_url=fake.url, use_profile=False, cache_directory=tmp_path, environ={}))
    def values(limits: Limits) -> set[tuple[str, str, str]]:
        assert limits.machine is not None
        return {(name, option, value) for name, options in limits.machine.sections
                for option, value, _ in options}
    assert "printer offline" in (offline.machine or "")
    assert values(offline.limits) == values(resolved.limits)
    gcode = REFS / "snippets" / "polar_center.gcode"
    ref = json.loads((REFS / "polar" / "polar_center.json").read_text())
    assert abs(estimate_file(gcode, offline.limits).total_s - ref["total_s"]) <= 0.01
