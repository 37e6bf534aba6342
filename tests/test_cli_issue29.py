"""Issue 29: bad input gets one clear line and a documented exit status, never `internal
error`, never a silent or absurd number, and the user's file is never damaged.

- `inject -o OUT` refuses a source replaced or changed while it is processed (as in place);
- `report` on a file whose name is not valid UTF-8 writes its page;
- `kestimator-compat ... | head` is not an internal error;
- `-` is standard input (estimate, check, report, limits, inject with -o) and standard
  output (`inject -o -`, `report -o -`), refused in one line where it cannot be;
- the HTML report shows bidi controls and control characters in names as escapes;
- a binary STL that is not exactly the size its triangle count says is still an STL.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg

from .conftest import CORPUS, CORPUS_CFG, PROJECT, isolate_user_environment

NUT = CORPUS / "gcode/prusaslicer/ps25_nut_accelA_small.gcode"
SMALL_BODY = b"M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\n;LAYER_CHANGE\nG1 X20 E1\nG1 Y20 E1\n"
OTHER_BODY = b"G1 X1 F60\n"
BIDI = "\u202e"


@pytest.fixture(autouse=True)
def private_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No profile, a private cache, no slicer hook environment, no forced rich."""
    return isolate_user_environment(tmp_path, monkeypatch)


def run(*args: str | bytes | Path, program: str = "kestimator", stdin: bytes | None = None,
        ) -> subprocess.CompletedProcess[bytes]:
    module = "kestimator" if program == "kestimator" else "kestimator.compat"
    return subprocess.run([sys.executable, "-m", module, *args],
                          env=dict(os.environ, PYTHONPATH=str(PROJECT)),
                          input=stdin if stdin is not None else b"",
                          capture_output=True, timeout=300)


@pytest.fixture(scope="module")
def limits():  # type: ignore[no-untyped-def]
    return limits_from_printer_cfg(CORPUS_CFG)[0]


# 12. The report escapes what could disguise a name


def test_the_report_shows_bidi_controls_in_file_and_object_names_as_escapes(
        tmp_path: Path) -> None:
    path = tmp_path / ("evil%sedoc.gcode" % BIDI)
    path.write_bytes(b"EXCLUDE_OBJECT_START NAME=part" + BIDI.encode() + b"gpj.exe\n"
                     + SMALL_BODY + b"EXCLUDE_OBJECT_END NAME=part\n")
    page = tmp_path / "r.html"
    proc = run("report", path, "-o", page, "-q")
    assert proc.returncode == 0, proc.stderr
    text = page.read_text(encoding="utf-8")
    assert BIDI not in text
    assert "evil\\u202eedoc.gcode" in text
    for char in ("\u2066", "\u2067", "\u2068", "\u2069", "\u202a", "\u202b", "\u200f"):
        assert char not in text


# 5. A file name that is not UTF-8


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX file names are bytes")
def test_report_on_a_file_whose_name_is_not_utf8_writes_the_page(tmp_path: Path) -> None:
    name = os.fsencode(tmp_path) + b"/caf\xe9.gcode"
    with open(name, "wb") as f:
        f.write(SMALL_BODY)
    page = tmp_path / "r.html"
    proc = run("report", name, "-o", page)
    assert proc.returncode == 0, proc.stderr
    assert b"internal error" not in proc.stderr
    assert "caf\\xe9.gcode" in page.read_text(encoding="utf-8")


# 10. kestimator-compat ... | head


@pytest.mark.parametrize("argv", [["estimate", "-f", "json", str(NUT)],
                                  ["estimate", str(NUT)], ["--version"]])
def test_compat_into_a_closed_pipe_is_no_internal_error(argv: list[str]) -> None:
    """The reader is gone before the first byte is written, as `| head -0` does."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run([sys.executable, "-m", "kestimator.compat", *argv],
                              env=dict(os.environ, PYTHONPATH=str(PROJECT)),
                              stdout=write_end, stderr=subprocess.PIPE, timeout=300)
    finally:
        os.close(write_end)
    assert proc.stderr == b"", proc.stderr
    assert proc.returncode == 0
