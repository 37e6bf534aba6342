"""`kestimator inject` on every corpus file: true M73, rewritten time comments, no byte lost.

Progress is checked against Klipper's own reference checkpoints (layer markers and every
500 moves): each M73 P must lie between Klipper's progress at the checkpoints around it
(within half a percentage point) and R within a minute of the remaining time there.
"""

from __future__ import annotations

import bisect
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.estimate import estimate_file
from kestimator.progress_table import HEADER_PREFIX, is_chunk_line, is_header_line, read_table_file
from kestimator.rewrite import MARKER_PREFIX, inject_file, is_layer_info_line, progress_pr

from .conftest import CORPUS, CORPUS_CFG, PROJECT, corpus_files, require_program

M73_RE = re.compile(rb"^\s*[Mm]73(?=[\s;]|$)")
M73_PR_RE = re.compile(rb"^M73 P(\d+) R(\d+)\r?\n?$")
LARGE_FILE_BYTES = 10_000_000

# Lines each slicer family's time comments start with (what inject may rewrite).
TIME_COMMENT_RE = re.compile(
    rb"^(; estimated (first layer )?printing time|; model printing time:|;TIME:|;PRINT\.TIME:"
    rb"|;TIME_ELAPSED:|;PRINTING_TIME:|;REMAINING_TIME:|;Print Time:|; --- print time:"
    rb"|; Calculated-during-export Build Time:|; estimated_print_time_s :)")


def _params() -> list[object]:
    out: list[object] = []
    for path in corpus_files():
        marks = [pytest.mark.slow] if path.stat().st_size > LARGE_FILE_BYTES else []
        out.append(pytest.param(path, id=path.parent.name + "/" + path.stem, marks=marks))
    return out


def _owned(line: bytes) -> bool:
    return (M73_RE.match(line) is not None or line.startswith(MARKER_PREFIX.encode())
            or TIME_COMMENT_RE.match(line) is not None
            or is_layer_info_line(line.lstrip()) or is_header_line(line)
            or is_chunk_line(line))


def _strip_owned(data: bytes) -> list[bytes]:
    return [line for line in data.splitlines(keepends=True) if not _owned(line)]


def _reference(path: Path) -> dict | None:
    ref = CORPUS / "reference" / path.parent.name / (path.stem + ".json")
    return json.loads(ref.read_text()) if ref.exists() else None


@pytest.fixture(scope="module")
def corpus_limits():  # type: ignore[no-untyped-def]
    return limits_from_printer_cfg(CORPUS_CFG)[0]


@pytest.mark.parametrize("src", _params())
def test_inject_keeps_every_other_byte_and_is_idempotent(src: Path, tmp_path: Path,
                                                         corpus_limits, corpus_root) -> None:
    work = tmp_path / src.name
    shutil.copyfile(src, work)
    original = src.read_bytes()
    result = inject_file(work, corpus_limits, limits_source="printer.cfg")
    first = work.read_bytes()
    assert _strip_owned(first) == _strip_owned(original)
    inject_file(work, corpus_limits, limits_source="printer.cfg")
    assert work.read_bytes() == first

    lines = first.splitlines(keepends=True)
    markers = [line for line in lines if line.startswith(MARKER_PREFIX.encode())]
    assert len(markers) == 1
    m73 = [line for line in lines if M73_RE.match(line)]
    parsed = [M73_PR_RE.match(line) for line in m73]
    assert all(parsed), [line for line, p in zip(m73, parsed, strict=True) if not p][:3]
    percents = [int(p.group(1)) for p in parsed if p]
    assert percents[0] == 0 and percents[-1] == 100
    assert percents == sorted(percents)
    total = result.estimate.total_s
    assert parsed[0] and int(parsed[0].group(2)) == progress_pr(0.0, total)[1]
    assert parsed[-1] and int(parsed[-1].group(2)) == 0


@pytest.mark.parametrize("src", [p for p in corpus_files()
                                 if _reference(p) and p.stat().st_size <= LARGE_FILE_BYTES],
                         ids=lambda p: p.parent.name + "/" + p.stem)
def test_every_m73_agrees_with_klipper_progress(src: Path, tmp_path: Path, corpus_limits,
                                                corpus_root) -> None:
    ref = _reference(src)
    assert ref is not None
    total = ref["total_s"]
    cps = sorted((cp["line"], cp["t"]) for cp in ref["checkpoints"])
    cp_lines = [line for line, _ in cps]
    out = tmp_path / src.name
    inject_file(src, corpus_limits, output=str(out), limits_source="printer.cfg")
    # Input line numbers of the lines that survive (everything but the slicer's M73s).
    # (Time comments and layer-number lines inject adds or rewrites are left out on both
    # sides.)
    kept_input_lines = [i + 1 for i, line in enumerate(src.read_bytes().splitlines())
                        if not _owned(line)]
    kept = 0
    checked = 0
    for line in out.read_bytes().splitlines():
        match = M73_PR_RE.match(line)
        if match is None:
            if not _owned(line):
                kept += 1
            continue
        # The M73 stands before input line L: its progress is the time at L.
        at = kept_input_lines[kept] if kept < len(kept_input_lines) else 10**12
        i = bisect.bisect_right(cp_lines, at)
        t_lo = cps[i - 1][1] if i else 0.0
        t_hi = cps[i][1] if i < len(cps) else total
        if i and cps[i - 1][0] == at:
            t_hi = max(t_hi, t_lo)
        percent, minutes = int(match.group(1)), int(match.group(2))
        assert 100 * t_lo / total - 0.5 <= percent <= 100 * t_hi / total + 0.5, (line, at)
        assert (total - t_hi) / 60 - 1 <= minutes <= (total - t_lo) / 60 + 1, (line, at)
        checked += 1
    assert checked > 100


@pytest.mark.parametrize("name", ["prusaslicer/ps25_nut_accelA_small.gcode",
                                  "orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode",
                                  "cura/cura413_ender3_nut_small.gcode",
                                  "bambustudio/gcodeparsersharp_bs1.6.2.gcode",
                                  "kirimoto/cancelobj_kirimoto3.0.gcode"])
def test_rewritten_slicer_time_equals_the_estimate(name: str, tmp_path: Path, corpus_limits,
                                                   corpus_root) -> None:
    out = tmp_path / "out.gcode"
    inject_file(corpus_root / "gcode" / name, corpus_limits, output=str(out))
    est = estimate_file(out, corpus_limits)
    text = out.read_text(encoding="utf-8", errors="replace")
    total = round(est.total_s)
    if "estimated printing time (normal mode)" in text:
        from kestimator.slicers import parse_prusa_duration
        values = re.findall(r"^; estimated printing time \(normal mode\) = (.+)$", text, re.M)
        assert values and all(parse_prusa_duration(v) == total for v in values)
    elif ";TIME:" in text:
        assert re.findall(r"^;TIME:(\d+)$", text, re.M) == [str(total)]
        elapsed = [float(v) for v in re.findall(r"^;TIME_ELAPSED:(\S+)$", text, re.M)]
        assert elapsed == sorted(elapsed) and elapsed[-1] <= est.total_s + 1e-6
    elif "total estimated time" in text:
        from kestimator.slicers import detect_file
        assert detect_file(out).estimate_s == total
    else:
        assert re.findall(r"^; --- print time: (\d+)s ---$", text, re.M) == [str(total)]


def test_line_endings_bytes_and_missing_final_newline_are_kept(tmp_path: Path,
                                                              corpus_limits) -> None:
    body = (b"; generated by PrusaSlicer 2.6.0 on 2024-01-01 at 00:00:00 UTC\r\n"
            b"M73 P0 R1\r\n; caf\xe9 \xff\xfe not utf-8\n;LAYER_CHANGE\r\nG1 X10 F3000\r\n"
            b"M73 Q50 S1\nG1 X20 ; mixed ending\n;LAYER_CHANGE\nG1 X30")
    work = tmp_path / "mixed.gcode"
    work.write_bytes(body)
    inject_file(work, corpus_limits, table=False)
    out = work.read_bytes()
    assert _strip_owned(out) == _strip_owned(body)
    assert not out.endswith(b"\n")
    assert b"M73 Q" not in out
    assert out.count(b"M73 P") >= 4
    for line in out.splitlines(keepends=True):
        if line.startswith(b"M73 P"):
            assert line.endswith(b"\n")
    # With the progress table (after everything else), the last line gets the line ending
    # the table's lines stand on: the only byte added to the file's own lines.
    work.write_bytes(body)
    inject_file(work, corpus_limits)
    with_table = work.read_bytes()
    content, _, table = with_table.partition(b"; kestimator_table ")
    assert with_table.endswith(b"\n") and not table.endswith(b"\r\n")
    # That last line is then processed as the line it becomes (here a move: M73 P100 R0
    # after it, not before), as a second run reads it (issue 38 item 5).
    work.write_bytes(body + b"\n")
    inject_file(work, corpus_limits, table=False)
    assert content == work.read_bytes()


PRUSA_HEAD = b"; generated by PrusaSlicer 2.5.0 on 2026-11-21 at 22:23:06 UTC\n"
BODY = (b"G28\nG90\nM83\n;LAYER_CHANGE\n;Z:0.2\nG1 Z0.2 F600\nG1 X10 Y10 E1 F3000\n"
        b";LAYER_CHANGE\n;Z:0.4\nG1 Z0.4\nG1 X20 Y10 E1\nG1 X20 Y20 E1")
ENDINGS = {
    "move_without_newline": BODY,
    "move_with_newline": BODY + b"\n",
    "layer_marker_without_newline": BODY + b"\n;LAYER_CHANGE",
    "lone_trailing_cr": BODY + b"\n\r",
    "move_ending_in_cr": BODY + b"\r",
    "layer_marker_ending_in_cr": BODY + b"\n;LAYER_CHANGE\r",
    "comment_ending_in_cr": BODY + b"\n; end\r",
    "crlf_without_final_newline": BODY.replace(b"\n", b"\r\n"),
    "dwell_without_newline": BODY + b"\nG4 P1000",
}


@pytest.mark.parametrize("head", [PRUSA_HEAD, b""], ids=["prusaslicer", "no_slicer"])
@pytest.mark.parametrize("ending", sorted(ENDINGS))
def test_inject_twice_is_byte_identical_whatever_the_file_ends_in(
        tmp_path: Path, corpus_limits, ending: str, head: bytes) -> None:
    """Issue 38 item 5: a file ending in a move or a layer marker without a final newline,
    or in a lone CR, is written once and for all by the first run."""
    work = tmp_path / "end.gcode"
    body = head + ENDINGS[ending]
    work.write_bytes(body)
    inject_file(work, corpus_limits)
    first = work.read_bytes()
    # The file's own lines, the last one given the line ending the table stands on.
    if not body.endswith(b"\n"):
        body += b"\n" if body.endswith(b"\r") or b"\r\n" not in body else b"\r\n"
    assert _strip_owned(first) == _strip_owned(body)
    inject_file(work, corpus_limits)
    assert work.read_bytes() == first


def test_output_option_leaves_the_input_untouched(tmp_path: Path, corpus_limits,
                                                  corpus_root) -> None:
    src = tmp_path / "in.gcode"
    shutil.copyfile(corpus_root / "gcode/prusaslicer/ps25_nut_accelA_small.gcode", src)
    before = src.read_bytes()
    inject_file(src, corpus_limits, output=str(tmp_path / "out.gcode"))
    assert src.read_bytes() == before
    assert (tmp_path / "out.gcode").read_bytes() != before


def _run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(PROJECT))
    return subprocess.run([sys.executable, "-m", "kestimator", *args], capture_output=True,
                          text=True, env=env)


def test_cli_inject_reports_klipper_time(tmp_path: Path, corpus_root) -> None:
    work = tmp_path / "nut.gcode"
    shutil.copyfile(corpus_root / "gcode/prusaslicer/ps25_nut_accelA_small.gcode", work)
    proc = _run_cli("inject", str(work), "--printer-cfg", str(CORPUS_CFG))
    assert proc.returncode == 0, proc.stderr
    assert "Klipper time 3m 42s" in proc.stdout
    assert "; estimated printing time (normal mode) = 3m 42s" in work.read_text()


def test_failure_on_unreadable_file_leaves_it_intact(tmp_path: Path) -> None:
    if os.geteuid() == 0:
        pytest.skip("root can read any file")
    work = tmp_path / "locked.gcode"
    work.write_bytes(b"G1 X10 F3000\n")
    work.chmod(0)
    proc = _run_cli("inject", str(work))
    work.chmod(0o644)
    assert proc.returncode == 1
    assert work.read_bytes() == b"G1 X10 F3000\n"


def test_failure_in_a_read_only_directory_leaves_the_file_intact(tmp_path: Path) -> None:
    if os.geteuid() == 0:
        pytest.skip("root may write into read-only directories")
    folder = tmp_path / "ro"
    folder.mkdir()
    work = folder / "print.gcode"
    work.write_bytes(b"G1 X10 F3000\n")
    folder.chmod(0o555)
    try:
        proc = _run_cli("inject", str(work))
    finally:
        folder.chmod(0o755)
    assert proc.returncode == 1
    assert len(proc.stderr.strip().splitlines()) == 1
    assert str(work) in proc.stderr
    assert work.read_bytes() == b"G1 X10 F3000\n"


def test_failure_while_writing_leaves_the_original_and_no_temp_file(
        tmp_path: Path, corpus_limits, monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    from kestimator import rewrite
    from kestimator.errors import KestimatorError

    work = tmp_path / "print.gcode"
    body = b"M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\n;LAYER_CHANGE\nG1 X20 E1\n"
    work.write_bytes(body)
    real_process = rewrite.Rewriter.process

    def disk_full(self, raw: bytes) -> list[bytes]:  # type: ignore[no-untyped-def]
        if self.lineno >= 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_process(self, raw)

    monkeypatch.setattr(rewrite.Rewriter, "process", disk_full)
    with pytest.raises(KestimatorError, match="No space left on device"):
        inject_file(work, corpus_limits)
    assert work.read_bytes() == body
    assert os.listdir(tmp_path) == ["print.gcode"]


def test_missing_file_and_binary_gcode_give_one_line_errors(tmp_path: Path) -> None:
    proc = _run_cli("inject", str(tmp_path / "nope.gcode"))
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and "nope.gcode" in proc.stderr
    binary = tmp_path / "print.bgcode"
    binary.write_bytes(b"GCDE\x01\x00\x00\x00" + b"\x00" * 64)
    proc = _run_cli("inject", str(binary))
    assert proc.returncode == 1
    assert "binary G-code" in proc.stderr and "Traceback" not in proc.stderr
    assert binary.read_bytes().startswith(b"GCDE")


@pytest.mark.parametrize("where", ["mkstemp", "replace", "open"])
def test_permission_denied_anywhere_exits_1_with_one_line_and_the_file_intact(
        where: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    import errno

    from kestimator import cli, rewrite

    work = tmp_path / "print.gcode"
    body = b"M83\nG1 X10 E1 F3000\nG1 X20 E1\n"
    work.write_bytes(body)

    def denied(*args: object, **kwargs: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied")

    if where == "mkstemp":
        monkeypatch.setattr(tempfile, "mkstemp", denied)
    elif where == "replace":
        monkeypatch.setattr(rewrite.os, "replace", denied)
    else:
        real_open = open

        def open_denied(path, mode="r", *args, **kwargs):  # type: ignore[no-untyped-def]
            if str(path) == str(work) and "b" in mode and getattr(open_denied, "armed", 0):
                denied()
            return real_open(path, mode, *args, **kwargs)

        monkeypatch.setattr(rewrite, "open", open_denied, raising=False)
        monkeypatch.setattr(rewrite.Rewriter, "__init__", _arming(open_denied,
                                                                  rewrite.Rewriter.__init__))
    status = cli.main(["inject", str(work)])
    err = capsys.readouterr().err
    assert status == 1
    assert err.count("\n") == 1 and "Permission denied" in err and str(work) in err
    assert work.read_bytes() == body
    assert os.listdir(tmp_path) == ["print.gcode"]


def _arming(target, init):  # type: ignore[no-untyped-def]
    """Wrap Rewriter.__init__ so the pass-2 open of the source fails (pass 1 succeeded)."""
    def wrapped(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        target.armed = 1
        init(self, *args, **kwargs)
    return wrapped


# Files whose slicer reads its settings back from the file's end without delimiters
# (PrusaSlicer before 2.4, Slic3r, Slic3r PE, SuperSlicer before 2.4).
UNDELIMITED_SETTINGS = ("prusaslicer/cancelobj_ps2.3.3_issue1.gcode",
                        "slic3r/gcodepreview_benchy_slic3rpe1.33.3_arcwelder.gcode",
                        "slic3r/cancelobj_slic3r1.3.1dev.gcode",
                        "slic3r/slic3r130_torus_x3_accel.gcode",
                        "superslicer/cancelobj_ss2.3.56_arcwelder.gcode")


def _legacy_settings(data: bytes) -> list[bytes]:
    """The settings PrusaSlicer's loader for files without delimiters reads (Config.cpp,
    load_from_gcode_string_legacy): the file's last 65535 bytes back to front, empty lines
    skipped, while each line is "; key = value"."""
    window = data[-65535:]
    lines = re.split(rb"[\r\n]+", window)[1:]  # the first may be cut
    found = []
    for line in reversed(lines):
        if not line:
            continue
        match = re.fullmatch(rb"; ([A-Za-z][A-Za-z0-9_]{2,}) = (.*)", line)
        if match is None or len(line) < 10:
            break
        found.append(line)
    return found


def _prusaslicer_settings(prusa: str, path: Path, tmp_path: Path) -> str:
    """What the real PrusaSlicer CLI reads back from `path`: the settings it saves, or the
    one line that says why it could not read them."""
    saved = tmp_path / (path.name + ".ini")
    done = subprocess.run([prusa, "--load", str(path), "--save", str(saved)],
                          capture_output=True, text=True, timeout=300)
    if done.returncode == 0:  # without its first line, which says when it was saved
        return saved.read_text().split("\n", 1)[1]
    why = [line for line in (done.stdout + done.stderr).splitlines() if "[trace]" not in line]
    return re.sub(r"\S*/", "", why[-1] if why else "failed")


@pytest.mark.parametrize("name", UNDELIMITED_SETTINGS)
def test_a_slicer_reads_its_settings_back_from_an_injected_file(
        name: str, tmp_path: Path, corpus_limits, corpus_root) -> None:
    """Issue 38 item 3: these slicers read their settings block from the file's last lines;
    the table goes before that block, so they read as many settings as from the original
    (the real PrusaSlicer CLI: 274 from PrusaSlicer 2.3.3's file), and our reader, which
    reads from the file's end, still finds the table."""
    src = corpus_root / "gcode" / name
    work = tmp_path / src.name
    shutil.copyfile(src, work)
    inject_file(work, corpus_limits, limits_source="printer.cfg")
    original = _legacy_settings(src.read_bytes())
    injected = work.read_bytes()
    assert len(original) >= 20
    assert _legacy_settings(injected) == original
    table = read_table_file(work)
    assert injected[table.content_bytes:].startswith(HEADER_PREFIX)
    prusa = require_program("prusa-slicer")
    copy = tmp_path / "original" / src.name
    copy.parent.mkdir()
    shutil.copyfile(src, copy)
    assert (_prusaslicer_settings(prusa, work, tmp_path)
            == _prusaslicer_settings(prusa, copy, tmp_path / "original"))
    if name.startswith("prusaslicer/"):
        assert len(_prusaslicer_settings(prusa, work, tmp_path).splitlines()) >= 80
