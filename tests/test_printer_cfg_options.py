"""Options Klipper refuses to start with, in the sections kestimator reads, are an error.

Each rejected case below was run through real Klipper 84104bbbd (the oracle,
../shared/tools/oracle) on the corpus printer.cfg with the option added: klippy stopped with
"Option '<name>' is not valid in section '<section>'" for every one of them.
"""

from __future__ import annotations

import glob
import os
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.errors import KestimatorError

from .conftest import CORPUS_CFG

KLIPPER_EXAMPLES = os.path.join(os.environ.get("ORACLE_KLIPPER", "/root/oracle/klipper"),
                                "config")


def _with_option(tmp_path: Path, section: str, option: str) -> Path:
    text = CORPUS_CFG.read_text().replace("[%s]\n" % section,
                                          "[%s]\n%s\n" % (section, option), 1)
    path = tmp_path / "printer.cfg"
    path.write_text(text)
    return path


@pytest.mark.parametrize(("section", "option", "expected"), [
    ("printer", "max_acel: 3000",
     "[printer] has no option 'max_acel' (did you mean 'max_accel'?)"),
    ("extruder", "max_extrude_only_velocty: 50",
     "[extruder] has no option 'max_extrude_only_velocty' "
     "(did you mean 'max_extrude_only_velocity'?)"),
    ("gcode_arcs", "resolutoin: 1",
     "[gcode_arcs] has no option 'resolutoin' (did you mean 'resolution'?)"),
    ("firmware_retraction", "retract_lenght: 1",
     "[firmware_retraction] has no option 'retract_lenght' (did you mean 'retract_length'?)"),
    ("printer", "delta_radius: 100", "[printer] has no option 'delta_radius'"),
])
def test_an_option_klipper_refuses_is_an_error_with_line_and_suggestion(
        tmp_path: Path, section: str, option: str, expected: str, corpus_root: Path) -> None:
    path = _with_option(tmp_path, section, option)
    with pytest.raises(KestimatorError) as refused:
        limits_from_printer_cfg(path)
    line = path.read_text().splitlines().index(option) + 1
    assert str(refused.value).startswith("%s:%d: %s" % (path, line, expected))


def test_sections_not_read_are_left_alone(tmp_path: Path, corpus_root: Path) -> None:
    path = _with_option(tmp_path, "heater_bed", "anything_at_all: 1")
    limits_from_printer_cfg(path)


def test_an_extruder_accepts_its_sensor_and_heater_options(tmp_path: Path,
                                                           corpus_root: Path) -> None:
    for option in ("spi_software_miso_pin: gpio1", "temperature1: 25", "pid_kp: 22.2",
                   "pressure_advance: 0.04"):
        limits_from_printer_cfg(_with_option(tmp_path, "extruder", option))


@pytest.mark.skipif(not os.path.isdir(KLIPPER_EXAMPLES),
                    reason="Klipper's example configs are not on this machine")
def test_every_klipper_example_config_is_accepted() -> None:
    refused = []
    for path in sorted(glob.glob(os.path.join(KLIPPER_EXAMPLES, "*.cfg"))):
        try:
            limits_from_printer_cfg(path)
        except KestimatorError as exc:
            if "has no option" in str(exc):
                refused.append(str(exc))
    assert not refused
