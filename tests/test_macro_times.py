"""Macro times: the profile's [macros] table, ESTIMATOR_ADD_TIME, and the parts of a total.

The corpus file ps25_nut_accelA_small.gcode runs PRINT_START (line 17, before any extrusion)
and PRINT_END (after the last extrusion); its Klipper time with the corpus printer.cfg is
pinned by the accuracy tests, so the motion part here must stay that time exactly.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from kestimator import cli
from kestimator.config.profile import load_profile
from kestimator.errors import KestimatorError
from kestimator.estimate import estimate_file, estimate_text
from kestimator.limits import Limits
from kestimator.macros import MacroTime, MacroTimes
from kestimator.rewrite import PREP_PREFIX, inject_file
from tests.conftest import CORPUS, CORPUS_CFG

NUT = CORPUS / "gcode" / "prusaslicer" / "ps25_nut_accelA_small.gcode"
START_S = 420.0
END_S = 30.0
PRUSA_TIME_RE = re.compile(rb"; estimated printing time \(normal mode\) = (?:(\d+)h )?"
                           rb"(?:(\d+)m )?(\d+)s")


def _resolved_limits() -> Limits:
    from kestimator.config.resolve import LimitRequest, resolve_limits
    return resolve_limits(LimitRequest(printer_cfg=str(CORPUS_CFG), use_profile=False)).limits


def _macros() -> MacroTimes:
    return MacroTimes(macros={"PRINT_START": MacroTime(START_S, "profile test"),
                              "PRINT_END": MacroTime(END_S, "profile test")})


def _profile(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _comment_seconds(data: bytes) -> int:
    match = PRUSA_TIME_RE.search(data)
    assert match is not None
    h, m, s = (int(g) if g else 0 for g in match.groups())
    return h * 3600 + m * 60 + s


def test_profile_macros_table_is_read_upper_cased_and_printer_tables_add_to_it(
        tmp_path: Path) -> None:
    path = _profile(tmp_path, '[macros]\nprint_start = 420\nT0 = 25\n'
                              '[printers."v"]\n[printers."v".macros]\nT0 = 30\n'
                              'TIMELAPSE_TAKE_FRAME = 3.2\n')
    assert load_profile(path).macros == {"PRINT_START": 420.0, "T0": 25.0}
    assert load_profile(path, printer="v").macros == {
        "PRINT_START": 420.0, "T0": 30.0, "TIMELAPSE_TAKE_FRAME": 3.2}


@pytest.mark.parametrize("body", ['[macros]\nPRINT_START = "7 min"\n',
                                  '[macros]\nPRINT_START = -1\n',
                                  '[macros]\nPRINT_START = true\n',
                                  '[macros]\nPRINT_START = inf\n',
                                  'macros = 3\n'])
def test_profile_macros_refuses_what_is_not_seconds(tmp_path: Path, body: str) -> None:
    with pytest.raises(KestimatorError, match=r"macros"):
        load_profile(_profile(tmp_path, body))


def test_macro_times_count_where_the_macro_runs_and_motion_stays_klippers() -> None:
    limits = _resolved_limits()
    plain = estimate_file(NUT, limits)
    timed = estimate_file(NUT, limits, macros=_macros())
    parts = timed.parts
    assert parts.motion_s == pytest.approx(plain.total_s, abs=1e-9)
    assert parts.added_s == START_S + END_S
    assert timed.total_s == pytest.approx(plain.total_s + START_S + END_S, abs=1e-9)
    assert parts.before_first_extrusion_s == START_S
    assert parts.print_duration_s == pytest.approx(plain.total_s + END_S, abs=1e-9)
    by_name = {p.name: p for p in timed.timed_parts}
    assert (by_name["PRINT_START"].count, by_name["PRINT_START"].seconds) == (1, START_S)
    assert by_name["PRINT_END"].before_first_extrusion_s == 0.0
    assert timed.untimed_macros == {}
    # The first layer starts after the start macro, so its time is unchanged.
    assert timed.first_layer_s == pytest.approx(plain.first_layer_s, abs=1e-9)


def test_without_macro_times_nothing_changes_but_the_untimed_macros_are_named() -> None:
    limits = _resolved_limits()
    est = estimate_file(NUT, limits)
    assert est.timed_parts == []
    assert est.parts.motion_s == est.total_s == est.parts.print_duration_s
    assert est.untimed_macros == {"PRINT_END": 1, "PRINT_START": 1}


def test_add_time_before_and_after_the_first_extrusion() -> None:
    gcode = ("G28\nM83\n; ESTIMATOR_ADD_TIME 60 heat soak\nG1 X10 E1 F600\n"
             ";ESTIMATOR_ADD_TIME 5\nG1 X20 E1\n")
    limits = Limits()
    plain = estimate_text(gcode.replace("ESTIMATOR_ADD_TIME", "nothing"), limits)
    est = estimate_text(gcode, limits)
    assert [(p.name, p.count, p.seconds, p.before_first_extrusion_s)
            for p in est.timed_parts] == [
        ("ESTIMATOR_ADD_TIME heat soak", 1, 60.0, 60.0), ("ESTIMATOR_ADD_TIME", 1, 5.0, 0.0)]
    assert est.parts.before_first_extrusion_s == 60.0
    # A stop between the two moves: Klipper's motion is the planner's with that stop.
    assert est.parts.motion_s > plain.total_s
    assert est.first_extrusion_t == pytest.approx(60.0 + 0.0, abs=1e-3)


def test_a_learned_start_stands_in_for_the_added_times_before_the_first_extrusion() -> None:
    limits = _resolved_limits()
    plain = estimate_file(NUT, limits)
    learned = MacroTimes(macros=_macros().macros,
                         before_first_extrusion=MacroTime(300.0, "learned from 5 prints"))
    est = estimate_file(NUT, limits, macros=learned)
    by_name = {p.name: p for p in est.timed_parts}
    assert by_name["PRINT_START"].covered == 1 and by_name["PRINT_START"].seconds == 0.0
    assert est.parts.before_first_extrusion_s == 300.0
    assert est.total_s == pytest.approx(plain.total_s + 300.0 + END_S, abs=1e-9)


def test_inject_writes_print_duration_in_the_comments_and_prep_on_its_own_line(
        tmp_path: Path) -> None:
    limits = _resolved_limits()
    copy = tmp_path / NUT.name
    shutil.copyfile(NUT, copy)
    result = inject_file(copy, limits, limits_source="test", macros=_macros())
    data = copy.read_bytes()
    parts = result.estimate.parts
    assert _comment_seconds(data) == round(parts.print_duration_s)
    prep = [line for line in data.splitlines() if line.startswith(PREP_PREFIX.encode())]
    assert prep == [(PREP_PREFIX + "7m 00s (420.000 s), not in the estimated printing "
                     "time").encode()]
    first_m73 = re.search(rb"^M73 P0 R(\d+)", data, re.MULTILINE)
    assert first_m73 is not None and int(first_m73.group(1)) == round(parts.total_s / 60)
    inject_file(copy, limits, limits_source="test", macros=_macros())
    assert copy.read_bytes() == data
    # Without macro times the prep line goes and the comment is the motion time again.
    inject_file(copy, limits, limits_source="test")
    again = copy.read_bytes()
    assert PREP_PREFIX.encode() not in again
    assert _comment_seconds(again) == round(parts.motion_s)


def test_cli_shows_the_parts_and_their_sources(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    profile = _profile(tmp_path, "[macros]\nPRINT_START = 420\n")
    args = [str(NUT), "--printer-cfg", str(CORPUS_CFG), "--profile", str(profile)]
    assert cli.main(["estimate", *args, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    parts = doc["parts"]
    assert parts["before_first_extrusion_s"] == 420.0
    assert parts["total_s"] == doc["total_s"]
    assert parts["motion_s"] == pytest.approx(doc["total_s"] - 420.0, abs=1e-6)
    assert parts["sources"] == [{"name": "PRINT_START", "source": "profile %s" % profile,
                                 "count": 1, "seconds": 420.0,
                                 "before_first_extrusion_s": 420.0,
                                 "covered_by_learned": 0}]
    assert parts["untimed_macros"] == {"PRINT_END": 1}
    assert doc["slicer"]["difference_s"] == pytest.approx(200.0 - parts["motion_s"], abs=1e-6)
    assert cli.main(["estimate", *args]) == 0
    text = capsys.readouterr().out
    assert "Total        : 10m 42s" in text
    assert "Motion       : 3m 42s (222.102 s)" in text
    assert "PRINT_START x1: 7m 00s, profile %s" % profile in text
    # PRINT_START has a time: only PRINT_END is left untimed.
    assert "  1 macro: its time is not counted (--verbose lists them)" in text
    copy = tmp_path / NUT.name
    shutil.copyfile(NUT, copy)
    assert cli.main(["inject", str(copy), *args[1:]]) == 0
    assert ("Klipper time 10m 42s (motion 3m 42s + macros and prep 7m 00s, 7m 00s of it "
            "before the first extrusion)") in capsys.readouterr().out


def test_report_shows_the_parts(tmp_path: Path) -> None:
    profile = _profile(tmp_path, "[macros]\nPRINT_START = 420\n")
    out = tmp_path / "report.html"
    assert cli.main(["report", str(NUT), "-o", str(out), "--printer-cfg", str(CORPUS_CFG),
                     "--profile", str(profile), "-q"]) == 0
    page = out.read_text(encoding="utf-8")
    assert "<span>Motion (Klipper&#x27;s planner)</span><b>3m 42s</b>" in page
    assert "<span>PRINT_START x1</span><b>7m 00s, profile %s</b>" % profile in page
    assert "<span>Before the first extrusion</span><b>7m 00s</b>" in page


def test_a_learned_motion_ratio_stretches_the_time_after_the_first_extrusion() -> None:
    limits = _resolved_limits()
    plain = estimate_file(NUT, limits, sample=True)
    first = plain.first_extrusion_t
    assert first is not None
    slow = MacroTimes(motion_ratio=MacroTime(1.05, "learned from 4 prints"))
    est = estimate_file(NUT, limits, macros=slow, sample=True)
    extra = 0.05 * (plain.total_s - first)
    assert est.total_s == pytest.approx(plain.total_s + extra, abs=1e-9)
    assert est.parts.motion_s == pytest.approx(plain.total_s, abs=1e-9)
    assert est.parts.print_duration_s == pytest.approx(est.total_s, abs=1e-9)
    assert est.timed_parts[0].name.startswith("motion correction")
    (_, start), (_, second) = plain.layers[0], plain.layers[1]
    assert start <= first < second  # the first layer's marker comes before its extrusion
    assert est.first_layer_s == pytest.approx(first + (second - first) * 1.05 - start,
                                              abs=1e-9)
    assert est.sample_times[-1] == pytest.approx(
        first + (plain.sample_times[-1] - first) * 1.05, abs=1e-9)
    assert sum(est.features.values()) == pytest.approx(est.total_s, abs=1e-6)
    # Not slower: nothing changes.
    same = estimate_file(NUT, limits, macros=MacroTimes(
        motion_ratio=MacroTime(1.0, "x")))
    assert same.total_s == plain.total_s and same.timed_parts == []
