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
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator import rewrite
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.errors import KestimatorError
from kestimator.filekind import STL, what_is_not_gcode
from kestimator.rewrite import inject_file

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


# 1. inject -o OUT while the input is replaced


def _between_passes(monkeypatch: pytest.MonkeyPatch, action) -> None:  # type: ignore[no-untyped-def]
    real_plan = rewrite.plan_file

    def plan_then_act(*args, **kwargs):  # type: ignore[no-untyped-def]
        result = real_plan(*args, **kwargs)
        action()
        return result

    monkeypatch.setattr(rewrite, "plan_file", plan_then_act)


def _replace(path: Path, data: bytes) -> None:
    other = path.with_name("other")
    other.write_bytes(data)
    os.replace(other, path)


@pytest.mark.parametrize("how", ["replace_file", "append", "truncate", "remove"])
@pytest.mark.parametrize("old_out", [False, True])
def test_inject_to_another_file_refuses_a_source_changed_between_the_passes(
        how: str, old_out: bool, tmp_path: Path, limits,
        monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(SMALL_BODY)
    out = tmp_path / "out.gcode"
    if old_out:
        out.write_bytes(b"; the user's old output\n")

    def change() -> None:
        if how == "replace_file":
            _replace(work, OTHER_BODY)
        elif how == "remove":
            work.unlink()
        else:
            with open(work, "r+b") as f:
                f.truncate(0)
                f.write(SMALL_BODY + b"G1 X30 E1\n" if how == "append" else SMALL_BODY[:20])

    _between_passes(monkeypatch, change)
    with pytest.raises(KestimatorError, match="while it was being processed") as info:
        inject_file(work, limits, output=str(out))
    assert info.value.path == str(work)
    if old_out:
        assert out.read_bytes() == b"; the user's old output\n"
    else:
        assert not out.exists()
    assert sorted(os.listdir(tmp_path)) == sorted(
        ["out.gcode"] * old_out + ["print.gcode"] * (how != "remove"))


def test_inject_to_another_file_refuses_a_source_replaced_during_the_second_pass(
        tmp_path: Path, limits, monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(SMALL_BODY)
    out = tmp_path / "out.gcode"
    real_fsync = os.fsync

    def fsync_while_the_slicer_saves(fd: int) -> None:
        real_fsync(fd)
        _replace(work, OTHER_BODY)

    monkeypatch.setattr(rewrite.os, "fsync", fsync_while_the_slicer_saves)
    with pytest.raises(KestimatorError, match="out.gcode was not written"):
        inject_file(work, limits, output=str(out))
    assert not out.exists()
    assert sorted(os.listdir(tmp_path)) == ["print.gcode"]
    assert work.read_bytes() == OTHER_BODY


def test_inject_to_another_file_still_writes_an_unchanged_source(
        tmp_path: Path, limits) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(SMALL_BODY)
    out = tmp_path / "out.gcode"
    inject_file(work, limits, output=str(out))
    assert b"M73 P0 R" in out.read_bytes() and work.read_bytes() == SMALL_BODY


# 14. A binary STL whose size does not match its triangle count


def _binary_stl(triangles: int, count: int | None = None, extra: bytes = b"") -> bytes:
    header = b"binary STL written by the test".ljust(80, b" ")
    facet = struct.pack("<12fH", 0, 0, 1, 0, 0, 0, 10, 0, 0, 0, 10, 0, 0)
    return (header + struct.pack("<I", triangles if count is None else count)
            + facet * triangles + extra)


ODD_STLS = {
    "padded.stl": _binary_stl(12, extra=b"\0\0"),
    "cut_short.stl": _binary_stl(12)[:-30],
    "wrong_count.stl": _binary_stl(12, count=1000),
    "no_extension": _binary_stl(3, extra=b"trailing junk"),
    "empty.stl": _binary_stl(0),
}


@pytest.mark.parametrize("name", sorted(ODD_STLS))
def test_an_odd_binary_stl_is_refused_by_every_command(name: str, tmp_path: Path) -> None:
    path = tmp_path / name
    path.write_bytes(ODD_STLS[name])
    said = ("kestimator: error: %s: %s\n" % (path, STL)).encode()
    for argv in (["estimate", path], ["check", path], ["report", path, "-o", tmp_path / "r.html"],
                 ["inject", path]):
        proc = run(*argv)
        assert (proc.returncode, proc.stderr, proc.stdout) == (1, said, b""), argv
    proc = run("estimate", path, program="compat")
    assert proc.returncode == 1
    assert proc.stderr == ("kestimator-compat: error: %s: %s\n" % (path, STL)).encode()
    assert path.read_bytes() == ODD_STLS[name]
    assert sorted(os.listdir(tmp_path)) == [name]


def test_text_gcode_is_never_taken_for_a_binary_stl(corpus_root: Path) -> None:
    for path in sorted((CORPUS / "gcode").rglob("*")):
        if path.is_file():
            with open(path, "rb") as f:
                start = f.read(64 * 1024)
            assert what_is_not_gcode(start, path.stat().st_size, str(path)) is None, path


# 11. `-` is standard input and standard output


def test_estimate_check_report_and_limits_read_dash_from_standard_input(
        tmp_path: Path, corpus_root: Path) -> None:
    data = NUT.read_bytes()
    named = run("estimate", NUT, "-q", "--printer-cfg", CORPUS_CFG)
    piped = run("estimate", "-", "-q", "--printer-cfg", CORPUS_CFG, stdin=data)
    assert piped.returncode == 0, piped.stderr
    assert piped.stdout == named.stdout and float(piped.stdout) > 100
    doc = run("estimate", "-", "--json", "--printer-cfg", CORPUS_CFG, stdin=data)
    assert b'"file": "<stdin>"' in doc.stdout
    check = run("check", "-", "--printer-cfg", CORPUS_CFG, stdin=data)
    assert check.returncode == 0 and check.stdout.startswith(b"<stdin>\n")
    page = tmp_path / "r.html"
    report = run("report", "-", "-o", page, "-q", "--printer-cfg", CORPUS_CFG, stdin=data)
    assert report.returncode == 0, report.stderr
    assert "Klipper time for &lt;stdin&gt;" in page.read_text(encoding="utf-8")
    limits = run("limits", "-", stdin=data)
    assert limits.returncode == 0 and b"<stdin>" in limits.stdout
    # The temporary copy is gone and never named.
    for proc in (piped, doc, check, report, limits):
        assert b"kestimator-stdin" not in proc.stdout + proc.stderr


def test_inject_dash_o_dash_writes_the_gcode_to_standard_output(
        tmp_path: Path, corpus_root: Path) -> None:
    out = tmp_path / "out.gcode"
    assert run("inject", NUT, "-o", out, "-q").returncode == 0
    to_stdout = run("inject", NUT, "-o", "-")
    assert to_stdout.returncode == 0, to_stdout.stderr
    assert to_stdout.stdout == out.read_bytes()
    assert b"<stdout>: Klipper time" in to_stdout.stderr
    piped = run("inject", "-", "-o", "-", "-q", stdin=NUT.read_bytes())
    assert piped.returncode == 0 and piped.stdout == out.read_bytes()
    from_stdin = run("inject", "-", "-o", tmp_path / "o2.gcode", "-q", stdin=NUT.read_bytes())
    assert from_stdin.returncode == 0
    assert (tmp_path / "o2.gcode").read_bytes() == out.read_bytes()
    page = run("report", NUT, "-o", "-")
    assert page.returncode == 0 and page.stdout.startswith(b"<!DOCTYPE html>")
    assert not os.path.exists("-") and sorted(os.listdir(tmp_path)) == [
        "o2.gcode", "out.gcode"]


@pytest.mark.parametrize("argv, stdin, said", [
    (["inject", "-"], NUT, b"kestimator: error: standard input cannot be rewritten in "
                           b"place: give -o OUT, or -o - for standard output\n"),
    (["inject", str(NUT), "-o", "-", "--json"], None,
     b"kestimator: error: -o - writes the G-code to standard output, where --json would go "
     b"too: give -o FILE, or -q\n"),
    (["estimate", "-"], None, b"kestimator: error: <stdin>: the file is empty\n"),
])
def test_dash_where_it_cannot_be_used_is_one_line(
        argv: list[str], stdin: Path | None, said: bytes, corpus_root: Path) -> None:
    proc = run(*argv, stdin=stdin.read_bytes() if stdin else b"")
    assert proc.stderr == said
    assert proc.returncode == (1 if argv[0] == "estimate" else 2)
    assert proc.stdout == b""


def test_stdin_from_a_terminal_is_refused_not_waited_for(corpus_root: Path) -> None:
    import pty

    leader, follower = pty.openpty()
    try:
        proc = subprocess.run([sys.executable, "-m", "kestimator", "estimate", "-"],
                              env=dict(os.environ, PYTHONPATH=str(PROJECT)), stdin=follower,
                              capture_output=True, timeout=60)
    finally:
        os.close(leader)
        os.close(follower)
    assert proc.returncode == 1
    assert proc.stderr.startswith(b"kestimator: error: <stdin>: standard input is a terminal")


def test_compat_reads_dash_as_stdin_with_the_checks_of_a_file(
        tmp_path: Path, corpus_root: Path) -> None:
    proc = run("estimate", "-f", "json", "-", program="compat", stdin=NUT.read_bytes())
    assert proc.returncode == 0 and b'"total_time"' in proc.stdout
    stl = run("estimate", "-", program="compat", stdin=ODD_STLS["padded.stl"])
    assert stl.returncode == 1
    assert stl.stderr == ("kestimator-compat: error: <stdin>: %s\n" % STL).encode()
    post = run("post-process", "-", program="compat", stdin=NUT.read_bytes())
    assert post.returncode == 1 and post.stderr.count(b"\n") == 1
    assert b"standard input cannot be" in post.stderr


def test_the_command_line_exits_1_when_the_source_is_swapped_under_inject_o(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from kestimator import cli

    big = tmp_path / "print.gcode"
    big.write_bytes(SMALL_BODY * 50)
    out = tmp_path / "out.gcode"
    _between_passes(monkeypatch, lambda: _replace(big, OTHER_BODY))
    assert cli.main(["inject", str(big), "-o", str(out), "--printer-cfg",
                     str(CORPUS_CFG)]) == cli.EXIT_FAILURE
    err = capsys.readouterr().err
    assert err == ("kestimator: error: %s: the file changed while it was being processed: "
                   "%s was not written\n" % (big, out))
    assert not out.exists()


@pytest.mark.parametrize("program, prefix", [("kestimator", "kestimator"),
                                             ("compat", "kestimator-compat")])
def test_dash_with_standard_input_closed_is_one_line(program: str, prefix: str) -> None:
    module = "kestimator" if program == "kestimator" else "kestimator.compat"
    proc = subprocess.run(["sh", "-c", 'exec "$0" -m %s estimate - <&-' % module,
                           sys.executable],
                          env=dict(os.environ, PYTHONPATH=str(PROJECT)), capture_output=True,
                          timeout=60)
    assert proc.returncode == 1
    assert proc.stderr == ("%s: error: <stdin>: standard input is closed: there is no G-code "
                           "to read\n" % prefix).encode()
