"""What "the post-processing hook wrote Klipper's times" means, checked on a file alone.

The slicer hook tests (PrusaSlicer end to end, the OrcaSlicer/Bambu Studio corpus, the
zipapp) share these checks: the `; kestimator <version>` marker, every M73 line, and the
slicer's time comments, each compared with `kestimator estimate --json` on the same file.
Klipper's time at an M73 line is read without trusting `inject`: a probe copy gets a layer
marker in front of every M73 line, and `estimate`'s `layers` then say when every move before
that line has finished. The tests here prove the checks reject files no hook has touched, so
a hook test that passes them has shown something.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

import pytest

from kestimator import __version__
from kestimator.slicers import parse_prusa_duration

from .conftest import CORPUS_CFG, IN_CI, PROJECT, corpus_files, without_progress_table

# M73's P is a whole percent and R whole minutes: any rounding (down, nearest, up) of
# Klipper's value is within one unit of it.
PERCENT_TOLERANCE = 1.0
MINUTES_TOLERANCE = 1.0
# Time comments are written in whole seconds (Orca's first layer line in fractions).
COMMENT_TOLERANCE_S = 1.0
SECONDS_PER_MINUTE = 60.0
ESTIMATE_TIMEOUT_S = 300

PROBE_MARKER = b";LAYER_CHANGE"
MARKER_RE = re.compile(r"^; kestimator %s(?:\s|$)" % re.escape(__version__))
M73_RE = re.compile(rb"^M73(?:[ \t;]|$)")
M73_PR_RE = re.compile(rb"^M73 P(\d+) R(\d+)\s*$")
TOTAL_COMMENT_RES = (
    # PrusaSlicer, SuperSlicer, OrcaSlicer (footer; Orca 1.5 also in its header)
    re.compile(r"^; estimated printing time \(normal mode\) = (.+?)\s*$"),
    # Bambu Studio's header
    re.compile(r"^; model printing time: .*?; total estimated time: (.+?)\s*$"),
)
FIRST_LAYER_COMMENT_RE = re.compile(
    r"^; estimated first layer printing time \(normal mode\) = (.+?)\s*$")
# Lines inject may change: M73, its marker, the slicers' time comments. Every other byte stays.
REWRITTEN_PREFIXES = (b"; kestimator ", b"SET_PRINT_STATS_INFO ", b"; estimated printing time",
                      b"; estimated first layer printing time", b"; model printing time:")

EXAMPLE_CFG = PROJECT / "examples" / "printer.cfg"
HOOK_CORPUS = corpus_files("orcaslicer/*.gcode") + corpus_files("bambustudio/*.gcode")


@dataclasses.dataclass(frozen=True)
class M73Line:
    """One `M73 P R` line of a file and Klipper's time where it stands."""

    line: int
    percent: int
    minutes: int
    t: float


def installed_command() -> Path:
    """The `kestimator` console script of the environment running the tests."""
    bindir = Path(sys.executable).parent
    found = shutil.which("kestimator", path=str(bindir))
    if found is None:
        message = "the kestimator command is not installed beside %s" % sys.executable
        if IN_CI:
            pytest.fail(message)
        pytest.skip(message)
    return Path(found)


def paste_line(entry: str, zipapp: Path, printer_cfg: Path | None) -> str:
    """The Linux line the hosts' READMEs tell users to paste, with this machine's paths.

    `entry` is "command" (the installed `kestimator`) or "zipapp" (`python3 kestimator.pyz`).
    """
    if entry == "command":
        line = shlex.quote(str(installed_command()))
    else:
        line = shlex.quote(sys.executable) + " " + shlex.quote(str(zipapp))
    line += " inject"
    if printer_cfg is not None:
        line += " --printer-cfg " + shlex.quote(str(printer_cfg))
    return line


def isolated_environment(home: Path) -> dict[str, str]:
    """This process's environment minus what could reach kestimator from outside the test.

    No slicer (`SLIC3R_*`), no Moonraker key, and empty XDG config and cache folders, so that
    a developer's own kestimator profile cannot change what the hook or `estimate` computes.
    """
    env = {key: value for key, value in os.environ.items()
           if not key.startswith("SLIC3R_") and key != "MOONRAKER_API_KEY"}
    env["XDG_CONFIG_HOME"] = str(home / "xdg-config")
    env["XDG_CACHE_HOME"] = str(home / "xdg-cache")
    return env


def build_zipapp(directory: Path) -> Path:
    """Build kestimator.pyz into `directory` with the repository's build script."""
    target = directory / "kestimator.pyz"
    proc = subprocess.run(
        [sys.executable, str(PROJECT / "tools" / "build_zipapp.py"), "-o", str(target)],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return target


def estimate_json(path: Path, printer_cfg: Path | None, env: Mapping[str, str]) -> dict:
    """`kestimator estimate PATH [--printer-cfg CFG] --json` in `env`, parsed."""
    cfg_args = [] if printer_cfg is None else ["--printer-cfg", str(printer_cfg)]
    proc = subprocess.run(
        [sys.executable, "-m", "kestimator", "estimate", str(path), *cfg_args, "--json"],
        env=env, capture_output=True, text=True, timeout=ESTIMATE_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def m73_lines_with_klipper_time(path: Path, printer_cfg: Path | None, env: Mapping[str, str],
                                workdir: Path) -> list[M73Line]:
    """Every `M73 P R` line of `path`, with the time all moves before it have finished."""
    probe: list[bytes] = []
    found: dict[int, tuple[int, int, int]] = {}
    for number, raw in enumerate(path.read_bytes().split(b"\n"), start=1):
        match = M73_PR_RE.match(raw.strip())
        if match is not None:
            probe.append(PROBE_MARKER)
            found[len(probe)] = (number, int(match.group(1)), int(match.group(2)))
        probe.append(raw)
    probe_path = workdir / ("probe-" + path.name)
    probe_path.write_bytes(b"\n".join(probe))
    layers = estimate_json(probe_path, printer_cfg, env)["layers"]
    layer_t = {layer["line"]: layer["t"] for layer in layers}
    probe_path.unlink()
    return [M73Line(number, percent, minutes, layer_t[probe_line])
            for probe_line, (number, percent, minutes) in sorted(found.items())]


def untouched_lines(data: bytes) -> list[bytes]:
    """The lines inject must keep byte for byte (the progress table it appends, and the
    line ending it gives a last line before it, are its own)."""
    lines = without_progress_table(data).split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()
    return [raw for raw in lines
            if not M73_RE.match(raw.strip()) and not raw.lstrip().startswith(REWRITTEN_PREFIXES)]


def _comment_problems(text_lines: list[str], total_s: float,
                      first_layer_s: float | None) -> list[str]:
    problems = []
    n_total = 0
    for number, text in enumerate(text_lines, start=1):
        for pattern in TOTAL_COMMENT_RES:
            match = pattern.match(text)
            if match is not None:
                n_total += 1
                said = parse_prusa_duration(match.group(1))
                if said is None or abs(said - total_s) >= COMMENT_TOLERANCE_S:
                    problems.append("line %d: %r, but Klipper's total is %.3f s"
                                    % (number, text, total_s))
        match = FIRST_LAYER_COMMENT_RE.match(text)
        if match is not None:
            said = parse_prusa_duration(match.group(1))
            if (said is None or first_layer_s is None
                    or abs(said - first_layer_s) >= COMMENT_TOLERANCE_S):
                problems.append("line %d: %r, but Klipper's first layer is %s s"
                                % (number, text, first_layer_s))
    if not n_total:
        problems.append("no total print time comment")
    return problems


def _m73_problems(path: Path, text_lines: list[str], total_s: float, printer_cfg: Path | None,
                  env: Mapping[str, str], workdir: Path) -> list[str]:
    problems = ["line %d: %r is not 'M73 P<percent> R<minutes>'" % (number, text)
                for number, text in enumerate(text_lines, start=1)
                if M73_RE.match(text.strip().encode()) and not M73_PR_RE.match(
                    text.strip().encode())]
    m73 = m73_lines_with_klipper_time(path, printer_cfg, env, workdir)
    if len(m73) < 2:
        problems.append("%d M73 P R lines; at least a start and an end are needed" % len(m73))
    for item in m73:
        true_percent = 100.0 * item.t / total_s
        true_minutes = (total_s - item.t) / SECONDS_PER_MINUTE
        if (abs(item.percent - true_percent) >= PERCENT_TOLERANCE
                or abs(item.minutes - true_minutes) >= MINUTES_TOLERANCE):
            problems.append("line %d: M73 P%d R%d, but Klipper is at %.3f s of %.3f s "
                            "(%.2f %%, %.2f min left)" % (
                                item.line, item.percent, item.minutes, item.t, total_s,
                                true_percent, true_minutes))
    return problems


def hook_problems(path: Path, printer_cfg: Path | None, workdir: Path,
                  env: Mapping[str, str] | None = None) -> list[str]:
    """Why `path` does not carry Klipper's times as `inject` promises; empty if it does.

    Klipper's times are `estimate`'s with the same printer.cfg, in `env` (by default an
    isolated environment, as a user's terminal would be).
    """
    if env is None:
        env = isolated_environment(workdir)
    text_lines = path.read_bytes().decode("utf-8", "replace").splitlines()
    markers = [text for text in text_lines if text.startswith("; kestimator ")]
    problems = []
    if len(markers) != 1 or not MARKER_RE.match(markers[0]):
        problems.append("marker lines %r: want one '; kestimator %s ...'" % (
            markers, __version__))
    doc = estimate_json(path, printer_cfg, env)
    problems += _m73_problems(path, text_lines, doc["total_s"], printer_cfg, env, workdir)
    problems += _comment_problems(text_lines, doc["total_s"], doc["first_layer_s"])
    return problems


@pytest.mark.parametrize("path", HOOK_CORPUS, ids=lambda p: p.name)
def test_the_checks_reject_a_slicers_own_times(path: Path, corpus_root: Path,
                                               tmp_path: Path) -> None:
    problems = hook_problems(path, CORPUS_CFG, tmp_path)
    assert any("marker" in p for p in problems)
    assert any("M73" in p for p in problems)
    assert any("Klipper's total" in p for p in problems)


def test_the_probe_reads_klipper_time_at_the_lines_asked(tmp_path: Path) -> None:
    # Hand-made: 100 mm at 50 mm/s with accel 3000 mm/s^2 cruises most of the way, so the
    # move ends a little after 2 s; an M73 before it stands at 0 s and one after it at its end.
    gcode = tmp_path / "line.gcode"
    gcode.write_text("G90\nM83\nSET_VELOCITY_LIMIT ACCEL=3000\nM73 P0 R1\n"
                     "G1 X100 F3000\nM73 P100 R0\n")
    env = isolated_environment(tmp_path)
    total_s = estimate_json(gcode, EXAMPLE_CFG, env)["total_s"]
    assert 2.0 < total_s < 2.1
    start, end = m73_lines_with_klipper_time(gcode, EXAMPLE_CFG, env, tmp_path)
    assert (start.line, start.t) == (4, 0.0)
    assert (end.line, end.t) == (6, pytest.approx(total_s))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["line.gcode"]


def test_the_checks_accept_a_file_that_carries_klipper_times(tmp_path: Path) -> None:
    gcode = tmp_path / "line.gcode"
    body = "G90\nM83\nSET_VELOCITY_LIMIT ACCEL=3000\n%s\nG1 X100 F3000\nM73 P100 R0\n"
    gcode.write_text(body % "")
    total_s = estimate_json(gcode, EXAMPLE_CFG, isolated_environment(tmp_path))["total_s"]
    gcode.write_text("; kestimator %s\nM73 P0 R0\n" % __version__ + body % (
        "; estimated printing time (normal mode) = %ds" % round(total_s)))
    assert hook_problems(gcode, EXAMPLE_CFG, tmp_path) == []
