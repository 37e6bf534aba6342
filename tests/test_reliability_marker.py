"""Our marker line and the numbers read from files (issue 20, items 3 and 4).

Only a line in the marker's exact format is ours (`kestimator.rewrite.parse_marker`): a
user's `; kestimator is my favourite tool` survives inject and does not make the Cura plugin
think the file was processed. A forged marker's `slicer_s` (negative, 1e308, nan, inf) and a
slicer's non-finite estimate (a 400-digit `;TIME:`) are treated as absent. `--json` is
strict JSON, and a closed or full stdout never hides what happened to the file.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.rewrite import inject_file, marker_line, parse_marker

from .conftest import CORPUS_CFG, PROJECT

sys.path.insert(0, str(PROJECT / "plugins" / "cura"))
from kestimator_cura.chunks import is_processed  # noqa: E402

BODY = b"M83\n;LAYER_CHANGE\nG1 X10 E1 F3000\n;LAYER_CHANGE\nG1 X20 E1\nG1 Y20 E1\n"
USER_COMMENTS = [b"; kestimator is my favourite tool", b"; kestimator notes: keep",
                 b"; kestimator 0.1.0 but not really a marker",
                 b"; kestimator 0.1.0 klipper_s=abc slicer_s=none limits=x"]


@pytest.fixture(scope="module")
def limits():  # type: ignore[no-untyped-def]
    return limits_from_printer_cfg(CORPUS_CFG)[0]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PROJECT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _cli(*args: str, **kwargs) -> subprocess.CompletedProcess[bytes]:  # type: ignore[no-untyped-def]
    return subprocess.run([sys.executable, "-m", "kestimator", *args], env=_env(),
                          capture_output=True, timeout=60, **kwargs)


@pytest.mark.parametrize("comment", USER_COMMENTS)
def test_a_users_comment_that_starts_like_our_marker_survives_inject(
        comment: bytes, tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "print.gcode"
    work.write_bytes(comment + b"\n" + BODY)
    inject_file(work, limits)
    lines = work.read_bytes().splitlines()
    assert comment in lines
    assert sum(parse_marker(line) is not None for line in lines) == 1


@pytest.mark.parametrize("comment", USER_COMMENTS)
def test_the_cura_plugin_takes_only_our_exact_marker_as_processed(comment: bytes) -> None:
    assert not is_processed([";FLAVOR:Klipper\n" + comment.decode() + "\n", "G1 X1\n"])
    ours = marker_line(12.0, None, "printer.cfg")
    assert is_processed([";FLAVOR:Klipper\n", ours + "\nG1 X1\n"])


@pytest.mark.parametrize("limits_field", ["printer.cfg", "Moonraker http://h:7125 (cached)",
                                          "guessed: no printer.cfg; a=b c=d", ""])
def test_the_marker_parser_reads_back_every_limits_field(limits_field: str) -> None:
    line = marker_line(100.0, 90.5, limits_field)
    marker = parse_marker(line)
    assert marker is not None and marker.slicer_s == 90.5 and marker.klipper_s == 100.0


@pytest.mark.parametrize("forged", ["-5.000", "1e308", "nan", "inf", "99999999999999.000"])
def test_a_forged_markers_slicer_estimate_is_not_trusted(
        forged: str, tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "print.gcode"
    work.write_bytes(b"; kestimator 0.1.0 klipper_s=1.000 slicer_s=%s limits=x\n"
                     % forged.encode() + BODY)
    result = inject_file(work, limits)
    assert result.slicer_estimate_s is None
    assert b"slicer_s=none" in work.read_bytes()


def test_a_400_digit_slicer_time_is_absent_and_the_run_succeeds(tmp_path: Path) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(b";FLAVOR:Marlin\n;TIME:" + b"9" * 400
                     + b"\n;Generated with Cura_SteamEngine 5.0\n" + BODY)
    run = _cli("inject", "--json", "--printer-cfg", str(CORPUS_CFG), str(work))
    assert run.returncode == 0, run.stderr
    doc = json.loads(run.stdout, parse_constant=lambda name: pytest.fail(name))
    assert doc["total_s"] > 0


def test_json_never_holds_nan_or_infinity(tmp_path: Path) -> None:
    work = tmp_path / "print.gcode"
    work.write_bytes(b"; kestimator 0.1.0 klipper_s=1.000 slicer_s=inf limits=x\n" + BODY)
    for command in ("estimate", "inject"):
        run = _cli(command, "--json", "--printer-cfg", str(CORPUS_CFG), str(work))
        assert run.returncode == 0, run.stderr
        json.loads(run.stdout, parse_constant=lambda name: pytest.fail(name))


@pytest.mark.parametrize("stdout", ["closed", "full"])
def test_inject_with_a_broken_stdout_says_the_file_was_written(
        stdout: str, tmp_path: Path, limits) -> None:  # type: ignore[no-untyped-def]
    if stdout == "full" and not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    work = tmp_path / "print.gcode"
    work.write_bytes(BODY)
    ref = tmp_path / "ref.gcode"
    ref.write_bytes(BODY)
    inject_file(ref, limits, limits_source="printer_cfg:" + CORPUS_CFG.name)
    with open("/dev/full" if stdout == "full" else os.devnull, "wb") as sink:
        run = subprocess.run(
            [sys.executable, "-m", "kestimator", "inject", "--printer-cfg", str(CORPUS_CFG),
             str(work)], env=_env(), stderr=subprocess.PIPE, timeout=60,
            stdout=sink if stdout == "full" else None,
            **({"pass_fds": ()} if stdout == "full" else {}),
            preexec_fn=(None if stdout == "full" else lambda: os.close(1)))
    assert work.read_bytes() == ref.read_bytes()
    assert run.returncode == 0, run.stderr
    assert b"Traceback" not in run.stderr
    assert len(run.stderr.splitlines()) == 1 and b"written" in run.stderr
