"""Where G28 leaves the head with [safe_z_home] or [homing_override] (extras/safe_z_home.py,
extras/homing_override.py at Klipper 84104bbbd), beyond what the oracle references pin
(tests/oracle_refs/safe_z_home*, compared in test_kinematics_oracle.py): what the oracle's
homing stand-in does not model (the z_hop before homing X or Y alone, "Must home X and Y
axes first", the range check of safe_z_home's moves), Moonraker's settings, config errors,
and the override's gcode.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from kestimator.config.moonraker import machine_from_settings, settings_values
from kestimator.config.printer_cfg import limits_from_printer_cfg, read_printer_cfg
from kestimator.errors import KestimatorError
from kestimator.estimate import Timeline, estimate_file, estimate_text
from kestimator.limits import Limits

REFS = Path(__file__).parent / "oracle_refs"
SAFE = REFS / "safe_z_home" / "printer.cfg"
PREVIOUS = REFS / "safe_z_home_previous" / "printer.cfg"


def _cfg(tmp_path: Path, base: Path, extra: str, drop: str | None = None) -> Path:
    """``base`` with ``extra`` appended (and the section ``drop`` left out)."""
    text = base.read_text()
    if drop is not None:
        start = text.index("\n[%s]" % drop) + 1
        end = text.find("\n[", start)
        text = text[:start] + (text[end + 1:] if end >= 0 else "")
    path = tmp_path / "printer.cfg"
    path.write_text(text + "\n" + extra)
    return path


def _position_after(limits: Limits, gcode: str) -> tuple[float, ...]:
    timeline = Timeline(limits, "<test>")
    timeline.feed_lines(line.encode() + b"\n" for line in gcode.splitlines())
    return tuple(round(v, 6) for v in timeline.toolhead.commanded_pos[:3])


def test_g28_ends_at_home_xy_position_and_z_hop() -> None:
    limits, _ = limits_from_printer_cfg(SAFE)
    assert _position_after(limits, "G28") == (117.5, 117.5, 0.0)
    assert _position_after(limits, "G1 X10 Y20 Z5 F6000\nG28 Z") == (117.5, 117.5, 0.0)
    # G28 X homes X alone: safe_z_home leaves Y and Z alone
    assert _position_after(limits, "G1 X10 Y20 Z5 F6000\nG28 X") == (0.0, 20.0, 5.0)
    limits, _ = limits_from_printer_cfg(PREVIOUS)
    # X/Y home to 250, Z to the probe's z_offset 1.7, then z_hop 10 and back to X/Y
    assert _position_after(limits, "G28") == (250.0, 250.0, 10.0)
    assert _position_after(limits, "G1 X10 Y20 Z5 F6000\nG28 Z") == (10.0, 20.0, 10.0)


def test_z_hop_before_homing_x_alone_lifts_z_as_klipper_does() -> None:
    # safe_z_home lifts a homed Z below z_hop before homing X or Y (the oracle's homing
    # stand-in skips this: its references home Z with X and Y, or start above z_hop)
    limits, _ = limits_from_printer_cfg(PREVIOUS)
    assert _position_after(limits, "G1 X10 Y20 Z5 F6000\nG28 X") == (250.0, 20.0, 10.0)
    assert _position_after(limits, "G1 X10 Y20 Z15 F6000\nG28 X") == (250.0, 20.0, 15.0)
    # an unhomed Z is taken as 0, lifted, and stays unhomed: a Z move needs G28 again
    est = estimate_text("G1 X10 Y20 Z5 F6000\nM84\nG28 X Y\nG1 Z3 F600\n", limits)
    rejects = [w for w in est.warnings if "Klipper rejects" in w]
    assert rejects and ":4: " in rejects[0] and "Must home axis first" in rejects[0]


def test_homing_z_with_x_or_y_unhomed_is_klippers_error() -> None:
    limits, _ = limits_from_printer_cfg(SAFE)
    est = estimate_text("G1 X10 F6000\nM84\nG28 Z\nG1 X20 F6000\n", limits)
    rejects = [w for w in est.warnings if "Klipper rejects" in w]
    assert rejects and ":3: " in rejects[0], est.warnings
    assert rejects[0].endswith("Must home X and Y axes first")


def test_a_home_xy_position_out_of_range_stops_the_print_at_g28(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, SAFE, "[safe_z_home]\nhome_xy_position: 300, 100\n",
               drop="safe_z_home")
    limits, _ = limits_from_printer_cfg(cfg)
    est = estimate_text("G1 X10 F6000\nG28\n", limits)
    rejects = [w for w in est.warnings if "Klipper rejects" in w]
    assert rejects and ":2: " in rejects[0]
    assert rejects[0].endswith("Move out of range: 300.000 100.000 0.000 [0.000]")


def test_homing_time_is_added_once_per_g28_line() -> None:
    limits, _ = limits_from_printer_cfg(SAFE)
    plain = estimate_text("G28\nG1 X10 F6000\n", limits)
    timed = estimate_text("G28\nG1 X10 F6000\n", limits, homing_time=30.0)
    assert timed.total_s == pytest.approx(plain.total_s + 30.0)


def test_moonraker_settings_give_the_same_g28_as_the_printer_cfg() -> None:
    settings: dict[str, dict[str, object]] = {
        name: {option: value.value for option, value in options.items()}
        for name, options in read_printer_cfg(PREVIOUS).items()}
    # Moonraker reports Klipper's parsed values: the list as a list, numbers as numbers
    settings["safe_z_home"] = {"home_xy_position": [125.0, 125.0], "speed": 150.0,
                               "z_hop": 10.0, "z_hop_speed": 20.0, "move_to_previous": True}
    found = settings_values(settings, "moonraker http://printer")
    limits = Limits.from_values(found.values).replace(machine=found.machine)
    assert _position_after(limits, "G28") == (250.0, 250.0, 10.0)
    gcode = REFS / "snippets" / "safe_z_home.gcode"
    from_cfg, _ = limits_from_printer_cfg(PREVIOUS)
    assert estimate_file(gcode, limits).total_s == estimate_file(gcode, from_cfg).total_s


def test_homing_override_gcode_is_never_taken_from_moonraker() -> None:
    machine = machine_from_settings(
        {"homing_override": {"gcode": "G28 X\nG1 X5", "axes": "xyz"}}, "moonraker x")
    section = machine.section("homing_override")
    assert section is not None and section.get("gcode", None) is None
    assert section.get("axes") == "xyz"


@pytest.mark.parametrize("extra, message", [
    ("[homing_override]\ngcode:\n  G28\n", "cannot be used simultaneously"),
    ("[safe_z_home]\nhome_xy_position: 1, 2, 3\n", "must have 2 elements"),
    ("[safe_z_home]\nhome_xy_position: 1, 2\nz_hop_speed: 0\n", "must be above 0"),
    ("[safe_z_home]\nhome_xy_position: 1, 2\nspedd: 5\n", "spedd"),
])
def test_safe_z_home_config_errors(tmp_path: Path, extra: str, message: str) -> None:
    drop = "safe_z_home" if extra.startswith("[safe_z_home]") else None
    cfg = _cfg(tmp_path, SAFE, extra, drop=drop)
    with pytest.raises(KestimatorError, match=message):
        limits, _ = limits_from_printer_cfg(cfg)
        estimate_text("G28\n", limits)


def test_safe_z_home_on_a_delta_is_klippers_config_error(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, REFS / "delta" / "printer.cfg",
               "[safe_z_home]\nhome_xy_position: 0, 0\n")
    limits, _ = limits_from_printer_cfg(cfg)
    with pytest.raises(KestimatorError, match="Missing Z endstop config for safe_z_homing"):
        estimate_text("G28\n", limits)


OVERRIDE = """[homing_override]
set_position_z: 0
axes: z
gcode:
  G90
  G1 Z5 F600
  G28 X Y
  G1 X100 Y100 F6000
  G28 Z
  G1 Z10 F600
"""


def test_a_literal_homing_override_runs_its_gcode(tmp_path: Path) -> None:
    limits, _ = limits_from_printer_cfg(_cfg(tmp_path, SAFE, OVERRIDE, drop="safe_z_home"))
    assert _position_after(limits, "G1 X10 Y20 Z3 F6000\nG28") == (100.0, 100.0, 10.0)
    est = estimate_text("G28\n", limits)
    assert any("[homing_override]'s gcode: its commands are run" in w for w in est.warnings)
    # Z5 at 10 mm/s max_z_velocity, X/Y 100 mm diagonal, Z10: the moves take their time
    assert est.total_s > 1.0 + 1.0
    # G28 X is not one of `axes`: a plain G28 of X, no warning
    assert _position_after(limits, "G1 X10 Y20 Z3 F6000\nG28 X") == (0.0, 20.0, 3.0)
    est = estimate_text("G28 X\n", limits)
    assert not [w for w in est.warnings if "homing_override" in w]


def test_a_templated_homing_override_is_a_plain_g28_with_a_warning(tmp_path: Path) -> None:
    override = OVERRIDE.replace("G1 X100 Y100 F6000", "G1 X{100} Y100 F6000")
    limits, _ = limits_from_printer_cfg(_cfg(tmp_path, SAFE, override, drop="safe_z_home"))
    assert _position_after(limits, "G1 X10 Y20 Z3 F6000\nG28") == (0.0, 0.0, 0.0)
    est = estimate_text("G28\nG28\n", limits)
    warned = [w for w in est.warnings if "homing_override" in w]
    assert len(warned) == 1 and "a template kestimator does not render" in warned[0]
