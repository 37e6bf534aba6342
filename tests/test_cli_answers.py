"""Honest answers to a newcomer's mistakes, from the `kestimator` command.

- A file that is not G-code but passes for text (a README, a picture) is refused by every
  command with the line `inject` gives, and exit status 1 (never `0.000` and exit 0).
- A `--printer-cfg` without a [printer] section (a moonraker.conf) is named as guessed,
  with "is this your printer.cfg?", by every command that times a file.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import pytest

from kestimator import cli

from .conftest import PROJECT, isolate_user_environment

EXAMPLE = PROJECT / "examples" / "hex_nut_prusaslicer.gcode"
MOONRAKER_CONF = ("[server]\nhost: 0.0.0.0\nport: 7125\n\n[authorization]\n"
                  "trusted_clients:\n    127.0.0.1\n\n[update_manager]\n")
NO_MOVES_LINE = "the file has no moves: nothing to estimate"


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(tmp_path)
    return isolate_user_environment(tmp_path, monkeypatch)


def _png() -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00\xff\x00\x00")) + chunk(b"IEND", b""))


@pytest.mark.parametrize("name", ["README.md", "picture.png"])
@pytest.mark.parametrize("command", [["estimate", "-q"], ["estimate", "--json"], ["check"],
                                     ["report", "-o", "page.html"], ["inject"]])
def test_a_readme_or_a_picture_is_refused_by_every_command_alike(
        name: str, command: list[str], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / name
    body = (PROJECT / "README.md").read_bytes() if name == "README.md" else _png()
    path.write_bytes(body)
    assert cli.main([command[0], name, *command[1:]]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err == "kestimator: error: %s: %s\n" % (name, NO_MOVES_LINE)
    assert path.read_bytes() == body
    assert sorted(os.listdir(tmp_path)) == [name]


@pytest.mark.parametrize("command", [["estimate"], ["check"], ["inject", "-o", "out.gcode"],
                                     ["report", "-o", "page.html"], ["limits"]])
def test_a_config_without_a_printer_section_is_named_as_guessed(
        command: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    conf = tmp_path / "moonraker.conf"
    conf.write_text(MOONRAKER_CONF)
    assert cli.main([command[0], str(EXAMPLE), *command[1:], "--printer-cfg", str(conf)]) == 0
    out, err = capsys.readouterr()
    warnings = [line for line in err.splitlines() if "is this your printer.cfg?" in line]
    assert warnings == [
        "kestimator: warning: no [printer] section in %s: is this your printer.cfg? Klipper "
        "would not start with it, so its limits are Klipper's defaults and guesses "
        "(max_velocity 300, max_accel 3000) and the times are approximate; give the "
        "printer.cfg Klipper runs with, or --moonraker URL" % conf]
    assert "is this your printer.cfg?" not in out  # said once, last, on stderr
    if command[0] in ("estimate", "inject", "report"):
        assert "approximate" in out


def test_a_config_without_a_printer_section_is_guessed_in_the_json_too(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    conf = tmp_path / "moonraker.conf"
    conf.write_text(MOONRAKER_CONF)
    assert cli.main(["estimate", str(EXAMPLE), "--printer-cfg", str(conf), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["limits_guessed"] is True
    assert any("is this your printer.cfg?" in w for w in doc["warnings"])


def test_a_real_printer_cfg_is_not_called_a_guess(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["estimate", str(EXAMPLE), "--printer-cfg",
                     str(PROJECT / "examples" / "printer.cfg"), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["limits_guessed"] is False
    assert "is this your printer.cfg?" not in err



def _usage_error(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[str, str]:
    """(the command the usage shown is for, the error line) of a refused command line."""
    assert cli.main(list(argv)) == 2
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.splitlines()
    assert lines[0].startswith("usage: kestimator ")
    return lines[0].split()[2], lines[-1]


@pytest.mark.parametrize("argv", [
    ["limits", "--set", "max_accel", "5000"],           # limits' FILE is optional
    ["estimate", str(EXAMPLE), "--set=max_accel", "5000"],
    ["--set", "max_accel", "5000", "check", str(EXAMPLE)],
    ["inject", str(EXAMPLE), "--set", "max_accel", "5000", "-o", "out.gcode"],
])
def test_every_form_of_a_set_value_without_equals_is_told_to_use_it(
        argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    command = next(word for word in argv if word in cli.COMMANDS)
    usage, error = _usage_error(capsys, *argv)
    assert usage == command
    assert error == ("kestimator %s: error: --set takes KEY=VALUE, a value needs '=': --set "
                     "max_accel=5000" % command)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("command", ["estimate", "inject", "check", "limits"])
def test_an_option_spelt_with_an_underscore_gets_the_right_spelling(
        command: str, capsys: pytest.CaptureFixture[str]) -> None:
    usage, error = _usage_error(capsys, command, str(EXAMPLE), "--printer_cfg", "printer.cfg")
    assert usage == command
    assert error == ("kestimator %s: error: unrecognized arguments: --printer_cfg printer.cfg "
                     "(did you mean --printer-cfg?)" % command)


@pytest.mark.parametrize("command", ["estimate", "inject", "check", "report"])
def test_several_files_are_told_one_file_per_run(
        command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name in ("a.gcode", "b.gcode"):
        (tmp_path / name).write_bytes(EXAMPLE.read_bytes())
    extra = ["-o", "page.html"] if command == "report" else []
    usage, error = _usage_error(capsys, command, "a.gcode", "b.gcode", *extra)
    assert usage == command
    page = ' -o "${f%.gcode}.html"' if command == "report" else ""
    assert error == ("kestimator %s: error: unrecognized arguments: b.gcode (one file per "
                     "run: for several, run kestimator once per file, e.g. for f in *.gcode; "
                     "do kestimator %s \"$f\"%s; done)" % (command, command, page))
    assert (tmp_path / "a.gcode").read_bytes() == EXAMPLE.read_bytes()


def test_an_unknown_set_key_points_to_limits_instead_of_listing_every_key(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["estimate", str(EXAMPLE), "--set", "max_acel=5000"]) == 1
    assert capsys.readouterr().err == (
        "kestimator: error: --set max_acel: unknown setting 'max_acel': did you mean "
        "max_accel? (`kestimator limits` lists every setting)\n")


def test_report_to_a_directory_says_it_is_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "reports"
    folder.mkdir()
    assert cli.main(["report", str(EXAMPLE), "-o", str(folder)]) == 2
    assert capsys.readouterr().err == (
        "kestimator: error: -o %s is a directory: give the page's file name, e.g. -o %s\n"
        % (folder, folder / "report.html"))
    assert os.listdir(folder) == []


def test_learn_offers_no_printer_cfg_and_says_what_it_needs(
        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.main(["learn", "--help"])
    assert "--printer-cfg" not in capsys.readouterr().out
    usage, error = _usage_error(capsys, "learn", "--printer-cfg", "printer.cfg")
    assert usage == "learn"
    assert error == ("kestimator learn: error: unrecognized arguments: --printer-cfg "
                     "printer.cfg (learn reads the printer's job history from Moonraker: give "
                     "--moonraker URL)")
