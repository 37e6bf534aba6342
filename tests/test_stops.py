"""The stops: the commands at which a print waits for a person, and Klipper's time at each.

Multi-colour files from real slicers (tests/stop_refs: Debian's PrusaSlicer 2.5 with
a colour change and a pause made by its layer slider, Debian's CuraEngine 4.13 with Cura's
own Pause at Height script run twice), with references from the oracle (mainline Klipper
84104bbbd; tests/stop_refs/runs.py says how a pause is timed there). A real-time print
in real Klipper (a virtual-SD print that really pauses at M600 and PAUSE, then resumes)
holds that this is the time a real pause gives.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.estimate import estimate_file, estimate_text
from kestimator.limits import Limits
from kestimator.rewrite import STOP_PREFIX
from kestimator.slicers import read_slicer_settings
from kestimator.stops import (
    DEFAULT_STOP_COMMANDS,
    command_word,
    slicer_stop_commands,
    stop_commands,
)

from .conftest import CORPUS, CORPUS_CFG, PROJECT, isolate_user_environment, require_klipper

STOPS = Path(__file__).parent / "stop_refs"
STOPS_CFG = STOPS / "printer.cfg"
FILES = ("ps25_box_color_pause.gcode", "cura413_box_pause_at_height.gcode")
# The oracle's times are rounded to the microsecond.
TOLERANCE_S = 2e-6


def _estimate(path: Path, cfg: Path = STOPS_CFG):
    resolved = resolve_limits(LimitRequest(gcode=str(path), printer_cfg=str(cfg),
                                           use_profile=False))
    return estimate_file(path, resolved.limits)


@pytest.mark.parametrize("name", FILES)
def test_every_stop_time_equals_klippers_time_at_that_line(name: str) -> None:
    ref = json.loads((STOPS / name).with_suffix(".json").read_text())
    est = _estimate(STOPS / name)
    assert [(s.command, s.line) for s in est.stops] == [
        (s["command"], s["line"]) for s in ref["stops"]]
    for stop, expected in zip(est.stops, ref["stops"]):
        assert stop.time_s == pytest.approx(expected["t"], abs=TOLERANCE_S), stop
    # The pauses run the look-ahead out: the rest of the print is Klipper's too.
    assert est.total_s == pytest.approx(ref["total_s"], abs=TOLERANCE_S)
    layers = dict(est.layers)
    for checkpoint in ref["checkpoints"]:
        assert layers[checkpoint["line"]] == pytest.approx(checkpoint["t"], abs=TOLERANCE_S)


def test_stop_layer_counts_the_layer_markers_before_it() -> None:
    est = _estimate(STOPS / FILES[0])
    layer_lines = [line for line, _ in est.layers]
    for stop in est.stops:
        assert stop.layer == sum(1 for line in layer_lines if line < stop.line)
    assert [s.layer for s in est.stops] == [4, 7]


def test_a_stop_command_klipper_does_not_know_is_no_stop() -> None:
    """On the corpus printer (no M600 macro, no [pause_resume]) Klipper skips M600 and
    PAUSE and prints on: no stop, and no run-out of the look-ahead."""
    est = _estimate(STOPS / FILES[0], CORPUS_CFG)
    assert est.stops == []
    ref = json.loads((STOPS / FILES[0]).with_suffix(".json").read_text())
    assert est.total_s < ref["total_s"]


def test_without_a_printer_config_every_stop_command_is_a_stop() -> None:
    est = estimate_text("G1 X10 F3000\nM600\nG1 X20\nM601\nPAUSE\nM0\nM1\nM25\nG1 X0\n",
                        Limits())
    assert [(s.command, s.line) for s in est.stops] == [
        ("M600", 2), ("M601", 4), ("PAUSE", 5), ("M0", 6), ("M1", 7), ("M25", 8)]


def test_a_tool_change_is_no_stop() -> None:
    est = estimate_text("G1 X10 F3000\nT1\nG1 X20\nT0\nG1 X0\n", Limits())
    assert est.stops == []
    assert "T1" not in stop_commands(["T1"], [("T1", "M600")])


def test_a_stop_runs_the_look_ahead_out_as_m400_does() -> None:
    moves = "G1 X10 F6000\nG1 X20 Y5\n%s\nG1 X40 Y0\nG1 X60 Y10\n"
    with_stop = estimate_text(moves % "M600", Limits())
    with_m400 = estimate_text(moves % "M400", Limits())
    with_nothing = estimate_text(moves % "M117 hello", Limits())
    assert with_stop.total_s == with_m400.total_s > with_nothing.total_s
    assert with_stop.stops[0].time_s == pytest.approx(dict(
        estimate_text(moves % ";LAYER_CHANGE\nM400", Limits()).layers)[3])


def test_macros_that_call_a_stop_are_stops() -> None:
    macros = [("FILAMENT_SWAP", "SAVE_GCODE_STATE NAME=swap\n  M600\n"),
              ("COLOR_CHANGE", "{% if true %}FILAMENT_SWAP{% endif %}"),
              ("PRINT_END", "G1 X0\nM84"), ("_PARK", "G1 X10")]
    names = stop_commands([], macros)
    assert {"FILAMENT_SWAP", "COLOR_CHANGE"} <= names
    assert not {"PRINT_END", "_PARK"} & names
    assert set(DEFAULT_STOP_COMMANDS) <= names


def test_a_printer_cfg_macro_calling_pause_is_a_stop(tmp_path: Path) -> None:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(STOPS_CFG.read_text() + "\n[gcode_macro FILAMENT_SWAP]\ngcode:\n"
                   "    M600\n")
    gcode = tmp_path / "swap.gcode"
    gcode.write_text("G28\nG1 X10 F3000\nFILAMENT_SWAP\nG1 X20\n")
    assert [(s.command, s.line) for s in _estimate(gcode, cfg).stops] == [
        ("FILAMENT_SWAP", 3)]


def test_the_slicers_own_pause_and_colour_change_gcode_name_stops() -> None:
    assert command_word("  M600 B1 ; swap") == "M600"
    assert command_word("{% if x %}PAUSE{% endif %}") == "PAUSE"
    assert command_word("; a comment") is None
    assert slicer_stop_commands([("color_change_gcode", "M600\\nG1 E0.3 F1500 ; prime"),
                                 ("machine_pause_gcode", "M400 U1"),
                                 ("pause_print_gcode", "M117 Pause\\nMY_PAUSE")]) == {
        "M600", "MY_PAUSE"}
    # Real files' embedded settings: SuperSlicer's M601, OrcaSlicer's machine_pause_gcode.
    _, settings = read_slicer_settings(
        CORPUS / "gcode" / "superslicer" / "cancelobj_ss2.3.56_arcwelder.gcode")
    assert dict(settings.stop_gcode) == {"color_change_gcode": "M600",
                                         "pause_print_gcode": "M601"}
    _, settings = read_slicer_settings(
        CORPUS / "gcode" / "orcaslicer" / "accelctl_orca1.5.0_klipper_m204.gcode")
    assert dict(settings.stop_gcode) == {"machine_pause_gcode": "PAUSE"}


def test_stop_commands_from_the_slicer_and_profile_reach_the_limits(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    home = isolate_user_environment(tmp_path, monkeypatch)
    profile = tmp_path / "config.toml"
    profile.write_text('stop_commands = ["filament_swap", "TAKE_A_LOOK"]\n')
    gcode = tmp_path / "orca.gcode"
    shutil.copyfile(CORPUS / "gcode" / "orcaslicer" / "accelctl_orca1.5.0_klipper_m204.gcode",
                    gcode)
    resolved = resolve_limits(LimitRequest(gcode=str(gcode), profile=str(profile)))
    # PAUSE (the file's machine_pause_gcode) is a default: every estimate knows it.
    assert resolved.limits.stop_commands == ("FILAMENT_SWAP", "TAKE_A_LOOK")
    assert home.is_dir()


def test_a_bad_stop_commands_setting_names_the_profile(tmp_path: Path) -> None:
    profile = tmp_path / "config.toml"
    profile.write_text('stop_commands = "M600"\n')
    with pytest.raises(Exception) as info:
        resolve_limits(LimitRequest(gcode=None, profile=str(profile)))
    assert str(profile) in str(info.value) and "stop_commands" in str(info.value)


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "kestimator", *args], capture_output=True,
                          text=True, check=False, cwd=PROJECT,
                          env=dict(os.environ, KESTIMATOR_RICH="0"))


def test_estimate_json_lists_the_stops() -> None:
    done = _cli("estimate", "--no-profile", "--printer-cfg", str(STOPS_CFG), "--json",
                str(STOPS / FILES[1]))
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    ref = json.loads((STOPS / FILES[1]).with_suffix(".json").read_text())
    assert [{k: s[k] for k in ("command", "line", "layer")} for s in doc["stops"]] == [
        {"command": "M0", "line": 1406, "layer": 4}, {"command": "M25", "line": 1744,
                                                       "layer": 7}]
    for stop, expected in zip(doc["stops"], ref["stops"]):
        assert stop["time_s"] == pytest.approx(expected["t"], abs=TOLERANCE_S)
    assert doc["stops_unlisted"] == 0


def test_estimate_text_lists_each_stop_and_the_time_between() -> None:
    done = _cli("estimate", "--no-profile", "--printer-cfg", str(STOPS_CFG),
                str(STOPS / FILES[0]))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith("Stops"))
    rows = [line.split() for line in lines[start + 2:start + 5]]
    assert rows == [["M600", "494", "4", "1m", "07s", "1m", "07s"],
                    ["PAUSE", "682", "7", "1m", "25s", "17s"],
                    ["end", "2m", "32s", "1m", "07s"]]


def test_inject_writes_the_time_at_each_stop_and_a_klipper_true_m73_c(tmp_path: Path) -> None:
    src = STOPS / FILES[0]
    out = tmp_path / "out.gcode"
    done = _cli("inject", "--no-profile", "--printer-cfg", str(STOPS_CFG), "-o", str(out),
                str(src))
    assert done.returncode == 0, done.stderr
    ref = json.loads(src.with_suffix(".json").read_text())
    lines = out.read_text().splitlines()
    stop_comments = [(i, line) for i, line in enumerate(lines) if line.startswith(STOP_PREFIX)]
    assert [lines[i + 1] for i, _ in stop_comments] == ["M600", "PAUSE"]
    for (_, line), expected in zip(stop_comments, ref["stops"]):
        assert line.startswith("%s%s = " % (STOP_PREFIX, expected["command"]))
        assert "(%.3f s)" % expected["t"] in line
    # The slicer's M73 C (Prusa firmware's minutes to the next stop): one before the first
    # stop at the start (1 min 07 s to go: 1), one just before it (0).
    m73_c = [line for line in lines if line.startswith("M73 C")]
    assert m73_c == ["M73 C1", "M73 C0"]
    assert not [line for line in lines if line.startswith(("M73 D", "M73 Q"))]
    again = tmp_path / "again.gcode"
    done = _cli("inject", "--no-profile", "--printer-cfg", str(STOPS_CFG), "-o", str(again),
                str(out))
    assert done.returncode == 0, done.stderr
    assert again.read_bytes() == out.read_bytes()


def test_a_real_klipper_pause_stands_at_the_stops_time(tmp_path: Path) -> None:
    """Real Klipper prints the PrusaSlicer file from its virtual SD card at wall-clock speed;
    M600 (a macro running PAUSE) and PAUSE really pause it, RESUME is typed 8 s later. The
    printing time Klipper then took from each pause to the end (the idle gaps left out) is
    the total less the stop's time (measured: within 1 microsecond)."""
    require_klipper()
    sys.path.insert(0, str(Path(__file__).parent / "klipper_module"))
    import run_realtime

    src = STOPS / FILES[0]
    data = src.read_bytes()
    starts = [0]
    for line in data.split(b"\n"):
        starts.append(starts[-1] + len(line) + 1)
    est = _estimate(src)
    script: list[dict[str, object]] = []
    for stop in est.stops:
        script += [{"at": starts[stop.line - 16] / len(data), "cmd": "ECHO MSG=soon"},
                   {"after": 8.0, "cmd": "RESUME"}]
    result = run_realtime.run_realtime(str(src), str(tmp_path / "print"), script=script,
                                       base_cfg=str(STOPS_CFG))
    assert result["state"] == "complete" and not result["errors"]
    assert [entry.get("error") for entry in result["typed"]] == [None] * len(script)
    # The idle gaps of the pauses (print_time re-synced after the head stood for seconds);
    # the 2 ms step-generation restarts after G28 and M84 are Klipper's time, counted.
    end = result["end_print_time"]
    idle = [(old, new) for old, new in result["gaps"] if old > 0.0 and new - old > 1.0]
    assert len(idle) == len(est.stops)
    for stop, (paused_at, _) in zip(est.stops, idle):
        klipper_left = run_realtime.truth_at(paused_at, end, [list(gap) for gap in idle])
        assert est.total_s - stop.time_s == pytest.approx(klipper_left, abs=1e-5)


def test_the_report_marks_each_stop_on_the_time_chart_and_lists_it() -> None:
    from kestimator.report import PAD_L, PLOT_W, Axis, collect, render_html

    resolved = resolve_limits(LimitRequest(gcode=str(STOPS / FILES[0]),
                                           printer_cfg=str(STOPS_CFG), use_profile=False))
    data = collect(str(STOPS / FILES[0]), resolved.limits, resolved.summary)
    page = render_html(data)
    chart = page[page.index('id="chart-remaining"'):]
    chart = chart[:chart.index("</svg>")]
    marks = re.findall(r'<line class="stop" x1="([0-9.]+)".*?<title>(.*?)</title>', chart)
    assert [title for _, title in marks] == ["M600, line 494: 1m 07s",
                                             "PAUSE, line 682: 1m 25s"]
    # Where the time axis puts the stop's time.
    axis = Axis(data.estimate.total_s, timed=True)
    for (x, _), stop in zip(marks, data.estimate.stops):
        assert float(x) == pytest.approx(PAD_L + PLOT_W * stop.time_s / axis.max, abs=0.06)
    table = page[page.index('<table class="stops">'):]
    table = table[:table.index("</table>")]
    assert re.findall(r"<tr><td>(.*?)</td><td>(.*?)</td>", table) == [
        ("M600", "494"), ("PAUSE", "682"), ("end", "")]


def test_a_progress_table_records_the_stop_commands_it_was_made_with() -> None:
    """The worker follows a file's table only for the same settings: a profile's own stop
    command (the look-ahead runs out there) makes other times."""
    from kestimator.rewrite import table_settings

    plain = dict(table_settings(Limits()))
    named = dict(table_settings(Limits().replace(stop_commands=("TAKE_A_LOOK",))))
    assert "stop_commands" not in plain
    assert named["stop_commands"] != plain.get("stop_commands")
    assert {k: v for k, v in named.items() if k != "stop_commands"} == plain


# Held out (tests/stop_refs/make_files.py): multi-colour files from PrusaSlicer, Cura and
# OrcaSlicer made after the code, never used to write it; the OrcaSlicer one is the corpus
# file with its pauses written in as OrcaSlicer writes them.
HELDOUT = ("ps25_bar_two_colours_pause.gcode", "cura413_bar_pause_at_height.gcode",
           "orca150_accelctl_pauses.gcode")


def _heldout(name: str, tmp_path: Path) -> Path:
    if (STOPS / name).exists():
        return STOPS / name
    sys.path.insert(0, str(STOPS))
    import make_files

    path = tmp_path / name
    path.write_bytes(make_files.orca_paused(CORPUS / "gcode" / "orcaslicer"
                                            / "accelctl_orca1.5.0_klipper_m204.gcode"))
    return path


@pytest.mark.parametrize("name", HELDOUT)
def test_on_held_out_files_every_stop_time_is_klippers_in_the_estimate_and_the_module(
        name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each stop of a held-out file at Klipper's time to that line (the oracle's, within a
    microsecond's rounding), in the estimate and in what the Klipper module is given: the
    worker's answer from an estimate, and from the table `inject` wrote (whole
    milliseconds), each stop at its own line of the file printed."""
    from kestimator import worker
    from kestimator.rewrite import inject_file

    ref = json.loads((STOPS / name).with_suffix(".json").read_text())
    expected = [(s["command"], s["line"]) for s in ref["stops"]]
    assert len(expected) >= 2
    src = _heldout(name, tmp_path)
    isolate_user_environment(tmp_path / "home", monkeypatch)  # the worker reads no profile
    est = _estimate(src)
    assert [(s.command, s.line) for s in est.stops] == expected
    for stop, want in zip(est.stops, ref["stops"]):
        assert stop.time_s == pytest.approx(want["t"], abs=TOLERANCE_S), stop
    assert est.total_s == pytest.approx(ref["total_s"], abs=TOLERANCE_S)
    injected = tmp_path / ("injected_" + name)
    shutil.copyfile(src, injected)
    inject_file(injected, resolve_limits(LimitRequest(
        gcode=str(src), printer_cfg=str(STOPS_CFG), use_profile=False)).limits)
    for path, source, tolerance in ((src, "estimate", TOLERANCE_S),
                                    (injected, "table", 5e-4 + TOLERANCE_S)):
        answer = worker.handle(json.dumps({"id": 1, "file": str(path),
                                           "config": str(STOPS_CFG)}).encode())
        assert answer["ok"] and answer["source"] == source, answer
        assert answer["stop_commands"] == [command for command, _ in expected]
        assert len(answer["stop_times"]) == len(ref["stops"])
        for t, want in zip(answer["stop_times"], ref["stops"]):
            assert t == pytest.approx(want["t"], abs=tolerance)
        lines = path.read_bytes().split(b"\n")
        assert [command_word(lines[n - 1].decode()) for n in answer["stop_lines"]] == [
            command for command, _ in expected]
