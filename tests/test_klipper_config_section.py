"""plugins/klipper/config_section.py against Klipper's own config reader: the `[kestimator]`
sections it finds are those Klipper reads from printer.cfg and its includes, and once it has
commented them out Klipper reads every other section and option as before and no kestimator.

Klipper's side is the oracle's configfile.py (84104bbbd) run by the oracle's Python, reading
the files as Klipper does at start (ConfigAutoSave.load_main_config: the SAVE_CONFIG block
split off, includes spliced in, the block's sections read after).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import PROJECT, require_klipper

sys.path.insert(0, str(PROJECT / "plugins" / "klipper"))
import config_section  # noqa: E402

KLIPPER_READS = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
import configfile
reader = configfile.ConfigFileReader()
data = reader.read_config_file(sys.argv[2])
regular, autosave = configfile.ConfigAutoSave._find_autosave_data(None, data)
fileconfig = reader.build_fileconfig_with_includes(regular, sys.argv[2])
saved = reader.build_fileconfig(autosave, sys.argv[2])
print(json.dumps({"regular": {s: dict(fileconfig.items(s)) for s in fileconfig.sections()},
                  "autosave": {s: dict(saved.items(s)) for s in saved.sections()}}))
"""

SAVE_CONFIG = (b"\n#*# <---------------------- SAVE_CONFIG ---------------------->\n"
               b"#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n"
               b"#*#\n#*# [extruder]\n#*# pid_kp = 22.2\n")

# name -> {file: bytes}; printer.cfg is the one Klipper starts with.
CASES: dict[str, dict[str, bytes]] = {
    "in_printer_cfg_crlf": {
        "printer.cfg": (b"[printer]\r\nkinematics: none\r\n# [kestimator] in a comment\r\n"
                        b"[gcode_macro START]\r\ngcode:\r\n  M117 [kestimator]\r\n"
                        b"[kestimator] # on\r\nupdate_interval: 1.0 # fast\r\n"
                        b"set_progress:\r\n   False\r\n; theirs\r\n\r\n[pause_resume]\r\n"),
    },
    "in_globbed_includes": {
        "printer.cfg": b"[printer]\nkinematics: none\n[include conf.d/*.cfg]\n" + SAVE_CONFIG,
        "conf.d/a.cfg": b"[kestimator]\nupdate_interval: 2\n[idle_timeout]\ntimeout: 60\n",
        "conf.d/b.cfg": b"[include ../more.cfg]\n[kestimator]\nset_progress: False",
        "more.cfg": b"[respond]\n",
    },
    "none": {
        "printer.cfg": b"[printer]\nkinematics: none\n[kestimator_like]\nx: 1\n#[kestimator]\n",
    },
}


def _write(root: Path, files: dict[str, bytes]) -> Path:
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    return root / "printer.cfg"


def _klipper_reads(printer_cfg: Path) -> dict[str, dict[str, dict[str, str]]]:
    klipper, python = require_klipper()
    proc = subprocess.run([python, "-c", KLIPPER_READS, os.path.join(klipper, "klippy"),
                           str(printer_cfg)], capture_output=True, text=True, timeout=60,
                          check=True)
    result: dict[str, dict[str, dict[str, str]]] = json.loads(proc.stdout)
    return result


@pytest.mark.parametrize("case", sorted(CASES))
def test_config_section_comments_out_what_klipper_reads_as_kestimator_and_nothing_else(
        case: str, tmp_path: Path) -> None:
    printer_cfg = _write(tmp_path, CASES[case])
    before = _klipper_reads(printer_cfg)
    found = config_section.find_sections(str(printer_cfg))
    assert bool(found) == ("kestimator" in before["regular"])
    commented = config_section.comment_sections(str(printer_cfg))
    assert [(s.filename, s.header_line) for s in commented] == \
        [(s.filename, s.header_line) for s in found]
    after = _klipper_reads(printer_cfg)
    before["regular"].pop("kestimator", None)
    assert after == before
    assert config_section.find_sections(str(printer_cfg)) == []
    # Only '#'s were added, at the starts of the lines named.
    for name, data in CASES[case].items():
        now = (tmp_path / name).read_bytes().split(b"\n")
        lines = {index for s in commented if s.filename.endswith(name) for index in s.read_lines}
        assert [line[1:] if index in lines else line for index, line in enumerate(now)] == \
            data.split(b"\n")
        assert all(now[index].startswith(b"#") for index in lines)


def test_config_section_edits_an_included_file_through_its_link(tmp_path: Path) -> None:
    kept = tmp_path / "git-configs" / "kestimator.cfg"
    kept.parent.mkdir()
    kept.write_bytes(b"[kestimator]\n")
    kept.chmod(0o640)
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "kestimator.cfg").symlink_to(kept)
    printer_cfg = tmp_path / "config" / "printer.cfg"
    printer_cfg.write_bytes(b"[include kestimator.cfg]\n")
    config_section.comment_sections(str(printer_cfg))
    assert os.readlink(tmp_path / "config" / "kestimator.cfg") == str(kept)
    assert kept.read_bytes() == b"#[kestimator]\n"
    assert kept.stat().st_mode & 0o777 == 0o640


def test_config_section_refuses_a_read_only_file_and_changes_nothing(tmp_path: Path) -> None:
    printer_cfg = _write(tmp_path, CASES["in_globbed_includes"])
    (tmp_path / "conf.d" / "b.cfg").chmod(0o444)  # read-only for root too
    with pytest.raises(config_section.ConfigError, match=r"b\.cfg:2: cannot write"):
        config_section.comment_sections(str(printer_cfg))
    assert (tmp_path / "conf.d" / "a.cfg").read_bytes() == CASES["in_globbed_includes"][
        "conf.d/a.cfg"]


def test_config_section_names_a_missing_include_in_one_line(tmp_path: Path) -> None:
    printer_cfg = tmp_path / "printer.cfg"
    printer_cfg.write_bytes(b"[include missing.cfg]\n")
    proc = subprocess.run([sys.executable, str(PROJECT / "plugins" / "klipper" /
                                               "config_section.py"), "find", str(printer_cfg)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr == "config_section.py: Include file '%s' does not exist\n" % (
        tmp_path / "missing.cfg")
