"""kestimator-compat: klipper_estimator's command line and config files, answered by kestimator."""

from __future__ import annotations

import copy
import json
import re
import shutil
from pathlib import Path

import pytest

from kestimator import __version__, compat
from kestimator.config.klipper_estimator import (
    dump_config,
    estimator_config_values,
    json5_to_json,
)
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.estimate import estimate_file

from .conftest import CORPUS_CFG
from .fake_moonraker import API_KEY, CORPUS_SETTINGS, FakeMoonraker

NUT = "prusaslicer/ps25_nut_accelA_small.gcode"
# Moonraker's analysis.py: _detect_estimator_version and IDENT_REGEX.
MOONRAKER_VERSION_RE = r"klipper_estimator (v?\d+(?:\.\d+)*)"
MOONRAKER_IDENT_RE = r"^; Processed by klipper_estimator (?P<version>v?\d+(?:\.\d+)*)"

JSON5_CONFIG = """
// dumped by klipper_estimator, then edited by hand
{
  max_velocity: 350,
  'max_acceleration': 7000, /* inline */
  "max_accel_to_decel": 3500,
  square_corner_velocity: 8.0,
  instant_corner_velocity: 1.5,
  move_checkers: [
    {axis_limiter: {axis: [0.0, 0.0, 1.0], max_velocity: 15, max_accel: 300,},},
    {axis_limiter: {axis: [1.0, 0.0, 0.0], max_velocity: 300, max_accel: 7000}},
    {extruder_limiter: {max_velocity: 120, max_accel: 1500}},
  ],
  firmware_retraction: {retract_length: 0.5, unretract_extra_length: 0.0,
                        unretract_speed: 30, retract_speed: 40, lift_z: 0.0},
}
"""


@pytest.fixture(autouse=True)
def no_user_profile(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg-config"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg-cache"))


def _corpus_copy(corpus_root: Path, tmp_path: Path, relative: str = NUT) -> Path:
    local = tmp_path / Path(relative).name
    shutil.copyfile(corpus_root / "gcode" / relative, local)
    local.chmod(0o644)
    return local


def test_version_answers_moonrakers_version_regex_with_kestimators_version(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert compat.main(["--version"]) == 0
    out, err = capsys.readouterr()
    match = re.match(MOONRAKER_VERSION_RE, out + err)
    assert match is not None and match.group(1) == __version__
    assert "kestimator" in out


def test_json5_config_maps_klipper_estimator_keys_with_provenance(tmp_path: Path) -> None:
    path = tmp_path / "estimator.json5"
    path.write_text(JSON5_CONFIG)
    found = estimator_config_values(path)
    assert found.values == {
        "max_velocity": 350.0, "max_accel": 7000.0, "max_accel_to_decel": 3500.0,
        "square_corner_velocity": 8.0, "instantaneous_corner_velocity": 1.5,
        "max_z_velocity": 15.0, "max_z_accel": 300.0,
        "max_extrude_only_velocity": 120.0, "max_extrude_only_accel": 1500.0,
        "firmware_retraction_enabled": True, "retract_length": 0.5, "retract_speed": 40.0,
        "unretract_extra_length": 0.0, "unretract_speed": 30.0}
    assert found.sources["max_accel"] == "klipper_estimator config %s: max_acceleration" % path
    assert found.sources["max_z_accel"].endswith("move_checkers[0].axis_limiter.max_accel")
    assert len(found.warnings) == 1 and "move_checkers[1]" in found.warnings[0]


def test_json5_reader_keeps_strings_and_line_numbers() -> None:
    text = "{\n // c\n a: 'it''s',\n}"
    assert json5_to_json("{'a': \"x // not a comment\", b: 'q\\'t',}") == \
        '{"a": "x // not a comment", "b": "q\'t"}'
    with pytest.raises(json.JSONDecodeError) as err:
        json.loads(json5_to_json(text))
    assert err.value.lineno == 3


def test_a_value_klipper_would_refuse_names_the_file_and_key(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], corpus_root: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text('{"max_acceleration": -5}')
    gcode = _corpus_copy(corpus_root, tmp_path)
    before = gcode.read_bytes()
    assert compat.main(["--config_file", str(path), "post-process", str(gcode)]) == 1
    err = capsys.readouterr().err
    assert "bad.json" in err and "max_acceleration" in err
    assert gcode.read_bytes() == before


def test_dumped_config_reads_back_as_the_same_limits(tmp_path: Path) -> None:
    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    path = tmp_path / "estimator.json"
    path.write_text(json.dumps(dump_config(machine.limits, machine.sources)))
    again = resolve_limits(LimitRequest(estimator_config=path, use_profile=False))
    assert again.limits == machine.limits
    assert again.sources["max_accel"] == (
        "klipper_estimator config %s: kestimator_limits.max_accel" % path)
    document = json.loads(path.read_text())
    assert document["max_acceleration"] == machine.limits.max_accel
    assert document["max_accel_to_decel"] == pytest.approx(
        machine.limits.max_accel * (1.0 - machine.limits.minimum_cruise_ratio))


def test_a_printer_cfg_outranks_the_klipper_estimator_config(tmp_path: Path) -> None:
    path = tmp_path / "estimator.json"
    path.write_text('{"max_acceleration": 1234}')
    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    both = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, estimator_config=path,
                                       use_profile=False))
    assert both.limits == machine.limits
    assert [c.value for c in both.shadowed["max_accel"]] == [1234.0]
    alone = resolve_limits(LimitRequest(estimator_config=path, use_profile=False))
    assert alone.limits.max_accel == 1234.0
    assert alone.summary.startswith("klipper_estimator config %s" % path)


def test_post_process_injects_true_times_ends_with_moonrakers_ident_and_is_idempotent(
        tmp_path: Path, corpus_root: Path) -> None:
    gcode = _corpus_copy(corpus_root, tmp_path)
    limits = resolve_limits(LimitRequest(gcode=gcode, use_profile=False,
                                         read_slicer_environment=False)).limits
    expected = estimate_file(gcode, limits).total_s
    assert compat.main(["post-process", str(gcode)]) == 0
    once = gcode.read_bytes()
    assert b"; kestimator %s klipper_s=%.3f " % (__version__.encode(), expected) in once
    assert re.search(rb"^M73 P0 R%d\r?$" % int(expected / 60 + 0.5), once, re.MULTILINE)
    idents = re.findall(MOONRAKER_IDENT_RE, once[-64 * 1024:].decode(), re.MULTILINE)
    assert idents == [__version__]
    assert once.endswith(compat.IDENT_LINE.encode() + b"\n")
    assert compat.main(["post-process", str(gcode)]) == 0
    assert gcode.read_bytes() == once


def test_the_ident_line_takes_the_files_crlf_ending_and_stands_on_its_own_line(
        tmp_path: Path) -> None:
    crlf = tmp_path / "crlf.gcode"
    crlf.write_bytes(b"G1 X1 F600\r\nG1 X2\r\n")
    assert compat.append_ident_line(str(crlf))
    assert crlf.read_bytes().endswith(b"G1 X2\r\n" + compat.IDENT_LINE.encode() + b"\r\n")
    assert not compat.append_ident_line(str(crlf))
    open_end = tmp_path / "open.gcode"
    open_end.write_bytes(b"G1 X1 F600\nG1 X2")
    compat.append_ident_line(str(open_end))
    assert open_end.read_bytes() == b"G1 X1 F600\nG1 X2\n" + compat.IDENT_LINE.encode() + b"\n"


def test_estimate_json_is_one_sequence_of_kestimators_time_and_nothing_on_stderr(
        tmp_path: Path, corpus_root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gcode = corpus_root / "gcode" / NUT
    limits = resolve_limits(LimitRequest(gcode=gcode, use_profile=False,
                                         read_slicer_environment=False)).limits
    est = estimate_file(gcode, limits)
    assert compat.main(["estimate", "-f", "json", str(gcode)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    document = json.loads(out)
    assert len(document["sequences"]) == 1
    seq = document["sequences"][0]
    assert seq["total_time"] == pytest.approx(est.total_s, abs=1e-9)
    assert seq["num_moves"] == est.n_moves
    phases = seq["phase_times"]
    moving = phases["acceleration"] + phases["cruise"] + phases["deceleration"]
    assert moving == pytest.approx(sum(est.features.values()), rel=1e-9)
    assert sum(t for _, t in seq["layer_times"]) + seq["total_z_time"] == pytest.approx(
        moving, rel=1e-9)
    assert "External perimeter" in seq["kind_times"]
    assert seq["total_extrude_distance"] > 0.0
    assert any("no printer.cfg" in w for w in seq["kestimator_warnings"])


def test_dump_config_from_moonraker_writes_the_printers_limits(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    fake = FakeMoonraker(copy.deepcopy(CORPUS_SETTINGS), api_key=API_KEY).start()
    try:
        code = compat.main(["--config_moonraker_url", fake.url,
                            "--config_moonraker_api_key", API_KEY, "dump-config"])
        from_moonraker = resolve_limits(LimitRequest(
            moonraker_url=fake.url, api_key=API_KEY, use_profile=False,
            cache_directory=tmp_path / "cache"))
    finally:
        fake.stop()
    assert code == 0
    out = capsys.readouterr().out
    path = tmp_path / "dumped.json"
    path.write_text(out)
    from_config = resolve_limits(LimitRequest(estimator_config=path, use_profile=False))
    assert from_config.limits == from_moonraker.limits
    assert json.loads(out)["kestimator_sources"]["max_accel"].startswith("moonraker ")
    assert API_KEY not in out

