"""The Klipper module in real Klipper printing at wall-clock speed, as a printer prints
(tests/klipper_module/run_realtime.py): the module's timers and anchoring left to
themselves, its status read as Moonraker reads it (Klipper's objects/subscribe, every
250 ms, one eventtime per cycle), commands typed as Moonraker's console types them. At
every status cycle from 10 s of print_duration on, `remaining_s` is held against the time
Klipper then really took: within 0.5 s + 0.2 % on a plain print, within 1 s + 1 % from 2 s
after a change typed mid-print.

Real-printer configs beyond the corpus's: pressure advance with input shaper, a delta; and
state typed before the print. A change typed mid-print is checked from 2 s after it, one
change (that alters the time) per print. Two multi-colour prints (tests/stop_refs) pause
at their colour changes and pauses and are resumed: `next_stop` is held to the same bars
against the time Klipper then took to stand at the next stop, and the guide's stop notice
and `display_next_stop` are run there.

On every release the module supports: one print each in Klipper v0.12.0, v0.13.0 and Kalico
v2026.07.00 (RELEASES, each with its own printer.cfg, the one tests/oracle_refs_releases/
made its references with; its tree found by tests/conftest.py's require_release: a missing
tree skips, but under CI it fails) covers what 84104bbbd's cases cover one by one: arcs,
labelled objects, a speed factor set before the print; an object excluded, a speed change,
a pause resumed, typed; a heater wait in the file. Each is held to the same bars at every
status cycle, and so is Mainsail's arithmetic.

The prints all run at once (they mostly wait on the wall clock); together they take as long
as the longest.
"""
from __future__ import annotations

import concurrent.futures
import math
import os
import re
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "klipper_module"))
import run_print  # noqa: E402
import run_realtime  # noqa: E402

from tests.conftest import require_klipper, require_program, require_release  # noqa: E402

pytestmark = pytest.mark.wall_clock  # tests/conftest.py starts it first
CORPUS = Path(run_print.SHARED) / "corpus" / "gcode"
REFS = Path(__file__).parent / "oracle_refs"
HEAT_WAIT_S = 3.0


def _labelled(src: Path, dest: Path) -> Path:
    """`src` with its objects labelled as Moonraker labels them."""
    sys.path.insert(0, str(Path(__file__).parent / "exclude_refs"))
    import runs

    dest.write_bytes(runs.label(src))
    return dest


def _with_heater_wait(src: Path, dest: Path, fraction: float) -> Path:
    """`src` with an M109 (a heater wait with a target) before the move at `fraction` of
    its lines."""
    lines = src.read_bytes().split(b"\n")
    at = int(len(lines) * fraction)
    while not lines[at].startswith(b"G1 "):
        at += 1
    dest.write_bytes(b"\n".join(lines[:at] + [b"M109 S215"] + lines[at:]))
    return dest


def _case_plain_pa_shaper(work: Path) -> dict[str, Any]:
    return run_realtime.run_realtime(
        str(CORPUS / "prusaslicer" / "ps25_nut_accelA_small.gcode"), str(work),
        base_cfg=str(REFS / "configs" / "pa_is.cfg"))


def _case_delta_with_state_typed_before(work: Path) -> dict[str, Any]:
    return run_realtime.run_realtime(
        str(CORPUS / "orcaslicer" / "helixscreen_xyzcube_orca2.3.1_klipper.gcode"),
        str(work), base_cfg=str(REFS / "delta" / "printer.cfg"),
        before=["SET_VELOCITY_LIMIT ACCEL=2000 SQUARE_CORNER_VELOCITY=3", "M220 S140"])


def _case_injected_table(work: Path) -> dict[str, Any]:
    return run_realtime.run_realtime(
        str(CORPUS / "orcaslicer" / "accelctl_orca1.5.0_klipper_m204.gcode"), str(work),
        inject=True)


def _arcwelder_labelled_with_heater_wait(work: Path) -> tuple[Path, list[str]]:
    """PrusaSlicer's ArcWelder file with its objects labelled and a heater wait at 80 %
    (written into `work`), and its objects' names."""
    work.mkdir(parents=True, exist_ok=True)
    src = CORPUS / "prusaslicer" / "cancelobj_ps2.4.0a1_arcwelder.gcode"
    labelled = _labelled(src, work / "labelled.gcode")
    names = [line.split(b"NAME=")[1].split()[0].decode()
             for line in labelled.read_bytes().split(b"\n")
             if line.startswith(b"EXCLUDE_OBJECT_DEFINE")]
    return _with_heater_wait(labelled, work / "test_src.gcode", 0.8), names


def _case_exclusion_pause_heater_wait(work: Path) -> dict[str, Any]:
    """Arcs (ArcWelder), labelled objects, a speed factor set before the print; an object
    excluded, then a pause, typed mid-print; a heater wait in the file."""
    test_file, names = _arcwelder_labelled_with_heater_wait(work)
    return run_realtime.run_realtime(
        str(test_file), str(work / "print"), heat_wait=HEAT_WAIT_S, before=["M220 S200"],
        script=[{"at": 0.2, "cmd": "EXCLUDE_OBJECT NAME=%s" % names[-1]},
                {"at": 0.5, "cmd": "PAUSE"},
                {"after": 4.0, "cmd": "RESUME"}])


def _case_speed_change(work: Path) -> dict[str, Any]:
    return run_realtime.run_realtime(
        str(CORPUS / "prusaslicer" / "ps25_nut_accelA_small.gcode"), str(work),
        script=[{"at": 0.3, "cmd": "M220 S150"}])


def _case_velocity_limit(work: Path) -> dict[str, Any]:
    """Mainsail's and Fluidd's limit sliders send SET_VELOCITY_LIMIT."""
    return run_realtime.run_realtime(
        str(CORPUS / "orcaslicer" / "accelctl_orca1.5.0_klipper_m204.gcode"), str(work),
        script=[{"at": 0.35, "cmd": "SET_VELOCITY_LIMIT ACCEL=8000 SQUARE_CORNER_VELOCITY=8"}])


STOPS = Path(__file__).parent / "stop_refs"
STOPS_FILE = STOPS / "ps25_box_color_pause.gcode"
# The guide's stop-notice macro, told 20 s ahead (its loop asks every 10 s).
NOTICE_LEAD_S = 20
NOTICE_PERIOD_S = 10


def _guide_block(marker: str) -> str:
    """The ini block of plugins/klipper/README.md that starts with `marker`, as written."""
    guide = (Path(run_print.ROOT) / "plugins" / "klipper" / "README.md").read_text()
    return marker + guide.split("```ini\n" + marker)[1].split("```")[0]


def _line_fraction(path: Path, line: int) -> float:
    """Where `line` (from 1) starts, as a fraction of the file's bytes."""
    data = path.read_bytes()
    return sum(len(text) + 1 for text in data.split(b"\n")[:line - 1]) / len(data)


def _case_colour_change_pause_resume(work: Path) -> dict[str, Any]:
    """PrusaSlicer's colour change (M600, a macro running PAUSE) and pause (PAUSE) from
    its layer slider really pause the print, each resumed 8 s later; a PAUSE and a RESUME
    typed before them; a display message set and cleared by the user meanwhile. The
    module shows the next stop as the display message, and the guide's macro notifies
    through Moonraker's notifier."""
    stops = [(494, "M600"), (682, "PAUSE")]
    script: list[dict[str, Any]] = [{"at": 0.12, "cmd": "PAUSE"}, {"after": 4.0, "cmd": "RESUME"},
                                    {"after": 3.0, "cmd": "M117 Hello"},
                                    {"after": 6.0, "cmd": "M117"}]
    for line, _ in stops:
        script += [{"at": _line_fraction(STOPS_FILE, line - 16), "cmd": "ECHO MSG=soon"},
                   {"after": 8.0, "cmd": "RESUME"}]
    notice = _guide_block("# Notify through Moonraker's [notifier kestimator]")
    return run_realtime.run_realtime(
        str(STOPS_FILE), str(work), base_cfg=str(STOPS / "printer.cfg"), script=script,
        extra_cfg="display_next_stop: True\n\n" + notice,
        before=["SET_GCODE_VARIABLE MACRO=KESTIMATOR_STOP_NOTICE VARIABLE=lead_s VALUE=%d"
                % NOTICE_LEAD_S])


def _case_speed_change_before_stops(work: Path) -> dict[str, Any]:
    """A held-out PrusaSlicer file (tests/stop_refs: two colour changes and a pause), a
    speed change typed before its stops (slower: a faster print of its short moves starved
    the busy test host's real-time Klipper of input); each stop's pause resumed 6 s later."""
    src = STOPS / "ps25_bar_two_colours_pause.gcode"
    script: list[dict[str, Any]] = [{"at": 0.15, "cmd": "M220 S80"}]
    for line in (463, 808, 982):
        script += [{"at": _line_fraction(src, line - 16), "cmd": "ECHO MSG=soon"},
                   {"after": 6.0, "cmd": "RESUME"}]
    return run_realtime.run_realtime(str(src), str(work), base_cfg=str(STOPS / "printer.cfg"),
                                     script=script)


# The older releases the module runs on (84104bbbd's prints are the cases above), each with
# one print: _case_release.
RELEASES = ["v0.12.0", "v0.13.0", "kalico-v2026.07.00"]
RELEASE_TYPED = ["EXCLUDE_OBJECT", "M220", "PAUSE", "RESUME"]
RELEASE_PAUSED_S = 6.0


def _case_release(work: Path, tree: tuple[str, str], cfg: str) -> dict[str, Any]:
    """A release's one print (tree: (Klipper tree, its Python); cfg: its printer.cfg): the
    labelled ArcWelder file, a speed factor set before the print; an object excluded, a
    slower speed, a pause and its resume typed; a heater wait in the file."""
    test_file, names = _arcwelder_labelled_with_heater_wait(work)
    result = run_realtime.run_realtime(
        str(test_file), str(work / "print"), heat_wait=HEAT_WAIT_S, before=["M220 S200"],
        base_cfg=cfg, klipper_tree=tree,
        script=[{"at": 0.15, "cmd": "EXCLUDE_OBJECT NAME=%s" % names[-1]},
                {"at": 0.3, "cmd": "M220 S170"},
                {"at": 0.5, "cmd": "PAUSE"},
                {"after": RELEASE_PAUSED_S, "cmd": "RESUME"}])
    result["excluded_name"] = names[-1]
    return result


CASES = {
    "speed_change_before_stops": _case_speed_change_before_stops,
    "exclusion_pause_heater_wait": _case_exclusion_pause_heater_wait,
    "colour_change_pause_resume": _case_colour_change_pause_resume,
    "delta_state_typed_before": _case_delta_with_state_typed_before,
    "injected_table": _case_injected_table,
    "plain_pa_shaper": _case_plain_pa_shaper,
    "velocity_limit": _case_velocity_limit,
    "speed_change": _case_speed_change,
}


@pytest.fixture(scope="module")
def prints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Every case's print and every release's, started at once; each test waits for its
    own. A release whose tree is missing gets its skip (or, under CI, its failure)
    instead."""
    require_klipper()
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=len(CASES) + len(RELEASES))
    started: dict[str, Any] = {name: pool.submit(case, tmp_path_factory.mktemp(name))
                               for name, case in CASES.items()}
    for release in RELEASES:
        try:
            tree, cfg = require_release(release)
        except (pytest.skip.Exception, pytest.fail.Exception) as outcome:
            started[release] = outcome
            continue
        started[release] = pool.submit(_case_release, tmp_path_factory.mktemp(release), tree,
                                       cfg)
    pool.shutdown(wait=False)
    return started


def _result(prints: dict[str, Any], name: str) -> dict[str, Any]:
    if isinstance(prints[name], BaseException):
        raise prints[name]
    result: dict[str, Any] = prints[name].result()
    # Klipper finished the print as a printer would: no error, never starved of moves.
    assert result["state"] == "complete", result["state"]
    assert result["errors"] == []
    assert result["stalls"] == 0
    assert result["returncode"] == 0
    log = Path(result["klippy_log"]).read_text(errors="replace")
    assert "kestimator: disabled" not in log
    return result


def _kest(sample: dict[str, Any]) -> dict[str, Any]:
    return dict(sample["status"].get("kestimator", {}))


_checked = run_realtime.checked_samples


def _off(result: dict[str, Any]) -> list[Any]:
    checked = _checked(result["samples"], result["typed"])
    assert len(checked) > 200
    return [(round(s["print_time"], 2), s["remaining_s"], round(s["truth_s"], 3))
            for s, absolute, relative in checked
            if s["remaining_s"] is None
            or abs(s["error_s"]) > absolute + relative * s["truth_s"]]


@pytest.mark.parametrize("name", sorted(CASES) + RELEASES)
def test_remaining_time_follows_klipper_at_every_status_cycle(prints: dict[str, Any],
                                                              name: str) -> None:
    result = _result(prints, name)
    assert _off(result) == []


@pytest.mark.parametrize("name", sorted(CASES) + RELEASES)
def test_display_status_gives_the_front_ends_klippers_remaining_time(prints: dict[str, Any],
                                                                      name: str) -> None:
    """display_status's progress is D / (D + R) in the very status cycle that carries D
    (print_stats' print_duration): the front ends' own D / progress - D is Klipper's
    remaining time (the full front-end code: tests/test_frontends.py)."""
    result = _result(prints, name)
    off = []
    for sample, absolute, relative in _checked(result["samples"], result["typed"]):
        duration = sample["status"]["print_stats"]["print_duration"]
        progress = sample["status"]["display_status"]["progress"]
        remaining = _kest(sample)["remaining_s"]
        assert progress == pytest.approx(duration / (duration + remaining), abs=1e-5)
        shown = duration / progress - duration
        if abs(shown - sample["truth_s"]) > absolute + relative * sample["truth_s"]:
            off.append((round(sample["print_time"], 2), round(shown, 3),
                        round(sample["truth_s"], 3)))
    assert off == []


def test_a_file_table_is_used_from_the_start(prints: dict[str, Any]) -> None:
    result = _result(prints, "injected_table")
    sources = {_kest(s).get("source") for s, _, _ in _checked(result["samples"], [])}
    assert sources == {"table"}


def test_state_typed_before_the_print_is_in_the_estimate(prints: dict[str, Any]) -> None:
    result = _result(prints, "delta_state_typed_before")
    sources = {_kest(s).get("source") for s, _, _ in _checked(result["samples"], [])}
    assert sources == {"estimate"}


@pytest.mark.parametrize("name, first", [("exclusion_pause_heater_wait", "EXCLUDE_OBJECT"),
                                         ("speed_change", "M220"),
                                         ("velocity_limit", "SET_VELOCITY_LIMIT")])
def test_a_change_typed_mid_print_is_taken_and_answered(prints: dict[str, Any], name: str,
                                                        first: str) -> None:
    result = _result(prints, name)
    typed = result["typed"]
    assert typed[0]["cmd"].split()[0] == first
    assert all("error" not in t for t in typed)
    checked = _checked(result["samples"], typed)
    # The module's own exact answer, not a provisional one, from 2 s after the change.
    assert {_kest(s)["source"] for s, _, _ in checked} == {"estimate"}


def test_a_pause_and_a_heater_wait_leave_the_time_left_standing(prints: dict[str, Any]) -> None:
    result = _result(prints, "exclusion_pause_heater_wait")
    assert [t["cmd"].split()[0] for t in result["typed"]] == [
        "EXCLUDE_OBJECT", "PAUSE", "RESUME"]
    # Klipper was idle through the pause and the heater waits (the file's two at its
    # start and the one put in at 80 %).
    idle = [new - old for old, new in result["gaps"] if new - old > HEAT_WAIT_S - 0.5]
    assert len(idle) >= 4
    paused = [s for s, _, _ in _checked(result["samples"], result["typed"])
              if s["status"]["print_stats"]["state"] == "paused"]
    assert len(paused) >= 4
    assert len({_kest(s)["remaining_s"] for s in paused}) == 1
    assert _kest(paused[-1])["excluded_objects"]


@pytest.mark.parametrize("name", sorted(CASES) + RELEASES)
def test_mainsail_by_its_own_code_shows_klippers_remaining_time(prints: dict[str, Any],
                                                                name: str) -> None:
    """The recorded status stream fed to Mainsail's own store code (tests/frontends/) with
    the three settings of the module's guide: its remaining time and its ETA are within 1 s
    of what Klipper then really took at every checked cycle (through the pause, the
    heater waits, the exclusion and the speed and limit changes); its progress and Fluidd's
    (set to M73) are display_status's, Klipper-time-true."""
    sys.path.insert(0, str(Path(__file__).parent / "frontends"))
    import frontends

    require_program("node")
    require_program("npm")
    result = _result(prints, name)
    checked = {id(s) for s, _, _ in _checked(result["samples"], result["typed"])}
    views = frontends.realtime_view(result)
    off = []
    for sample, view in zip(result["samples"], views):
        if id(sample) not in checked:
            continue
        progress = sample["status"]["display_status"]["progress"]
        assert view["mainsail_progress"] == pytest.approx(progress, abs=1e-9)
        assert view["fluidd_progress"] == pytest.approx(progress, abs=1e-9)
        for field in ("mainsail_estimate_error_s", "mainsail_eta_left_error_s"):
            if view[field] is None or abs(view[field]) > 1.:
                off.append((round(sample["print_time"], 2), field, view[field]))
    assert off == []


@pytest.mark.parametrize("release", RELEASES)
def test_the_changes_typed_mid_print_are_answered_on_each_release(
        prints: dict[str, Any], release: str) -> None:
    """From 2 s after the speed change (run_print.ANSWER_WITHIN_S) the module's own exact
    answer, not a provisional one, with the excluded object's time left 0; while the head
    stands paused the time left stands; Klipper was idle through the pause and the heater
    waits (the file's two at its start and the one put in at 80 %)."""
    result = _result(prints, release)
    assert [t["cmd"].split()[0] for t in result["typed"]] == RELEASE_TYPED
    assert all("error" not in t for t in result["typed"])
    checked = [s for s, _, _ in _checked(result["samples"], result["typed"])]
    assert {_kest(s)["source"] for s in checked} == {"estimate"}
    excluded = result["excluded_name"].upper()
    for sample in checked:
        left = {name.upper(): t for name, t in _kest(sample)["objects"].items()}
        assert left[excluded] == 0.
    # The head runs out what was queued (up to 2.3 s here) after PAUSE returns: the time left
    # stands from where it stood (the idle gap Klipper re-synced after).
    standing = [s for s in checked if s["status"]["print_stats"]["state"] == "paused"
                and any(old <= s["print_time"] < new for old, new in result["gaps"])]
    assert len(standing) >= 4
    assert len({_kest(s)["remaining_s"] for s in standing}) == 1
    idle = [new - old for old, new in result["gaps"] if new - old > HEAT_WAIT_S - 0.5]
    assert len(idle) >= 4


# Each case's stops (command, line), and whether a pause is typed before them.
CASE_STOPS = {"colour_change_pause_resume": ([("M600", 494), ("PAUSE", 682)], True),
              "speed_change_before_stops": ([("M600", 463), ("M600", 808), ("PAUSE", 982)],
                                            False)}


def _stop_pauses(result: dict[str, Any], name: str) -> list[tuple[str, int, float]]:
    """The file's stops (command, line) with the print_time at which the head stood at each:
    the start of the idle gap each left (a typed pause's comes first)."""
    stops, typed_pause = CASE_STOPS[name]
    idle = [old for old, new in result["gaps"] if old > 0.0 and new - old > 1.0]
    assert len(idle) == len(stops) + typed_pause, result["gaps"]
    if typed_pause:
        typed = result["typed"][0]
        assert typed["cmd"] == "PAUSE"
        assert idle[0] < typed["done_eventtime"] + result["clock_offset"] + 3.0 < idle[1]
        idle = idle[1:]
    return [(command, line, at) for (command, line), at in zip(stops, idle)]


def _next_stop_truth(sample: dict[str, Any], result: dict[str, Any],
                     stops: list[tuple[str, int, float]]) -> tuple[str, int, float] | None:
    """The stop the head has not reached yet at the sample, with the printing time Klipper
    then took to stand there (idle gaps left out); None after the last."""
    for command, line, at in stops:
        if at > sample["print_time"]:
            return command, line, run_realtime.truth_at(sample["print_time"], at,
                                                        result["gaps"])
    return None


@pytest.mark.parametrize("name", sorted(CASE_STOPS))
def test_the_next_stop_follows_klipper_at_every_status_cycle(prints: dict[str, Any],
                                                             name: str) -> None:
    """`next_stop`: the command and line of the stop the head has not reached, and
    `in_s` within the bar `remaining_s` is held to (0.5 s + 0.2 % of the printing time
    Klipper then took to stand there; 1 s + 1 % after a speed change), through a typed
    pause, the colour changes' and the pauses' own pauses (while paused at one it names
    the next) and their resumes; null after the last."""
    result = _result(prints, name)
    stops = _stop_pauses(result, name)
    checked = _checked(result["samples"], result["typed"])
    assert len(checked) > 200
    off = []
    seen = set()
    for sample, absolute, relative in checked:
        truth = _next_stop_truth(sample, result, stops)
        shown = _kest(sample).get("next_stop")
        if truth is None:
            if shown is not None:
                off.append((round(sample["print_time"], 2), shown, None))
            continue
        command, line, in_s = truth
        seen.add((command, sample["status"]["print_stats"]["state"]))
        if (shown is None or (shown["command"], shown["line"]) != (command, line)
                or abs(shown["in_s"] - in_s) > absolute + relative * in_s):
            off.append((round(sample["print_time"], 2), shown, (command, line, round(in_s, 3))))
            continue
        assert shown["eta"] == pytest.approx(_kest(sample)["eta"] - _kest(sample)["remaining_s"]
                                             + shown["in_s"], abs=0.002)
    assert off == []
    # Checked printing toward each stop, and paused (at the stop before it, or typed).
    assert {(command, "printing") for command, _, _ in stops} <= seen
    assert {(command, "paused") for command, _, _ in stops[1:]} <= seen


def test_the_guides_macro_notifies_through_moonrakers_notifier_before_each_stop(
        prints: dict[str, Any]) -> None:
    """plugins/klipper/README.md's macro, as written there, in real Klipper: one call of
    Moonraker's "notify" remote method per stop, to the notifier it names, saying the stop
    and its line, once the stop is at most `lead_s` ahead (it asks every 10 s)."""
    result = _result(prints, "colour_change_pause_resume")
    stops = _stop_pauses(result, "colour_change_pause_resume")
    calls = result["remote_calls"]
    assert [call["params"]["name"] for call in calls] == ["kestimator", "kestimator"]
    for call, (command, line, at) in zip(calls, stops):
        message = call["params"]["message"]
        assert message.startswith("%s in " % command) and message.endswith("(line %d)" % line)
        print_time = call["eventtime"] + result["clock_offset"]
        left = run_realtime.truth_at(print_time, at, result["gaps"])
        assert NOTICE_LEAD_S - NOTICE_PERIOD_S - 1.0 < left <= NOTICE_LEAD_S + 1.0
        assert message == "%s in %d min (line %d)" % (command, math.ceil(left / 60), line)


def test_display_next_stop_shows_the_time_to_it_but_never_over_the_users_message(
        prints: dict[str, Any]) -> None:
    """`display_next_stop: True`: the display message is the next stop and the time to it
    (as the status says it, within the 0.5 s between updates), but the user's own M117
    stays until the user clears it; after the last stop, no message."""
    result = _result(prints, "colour_change_pause_resume")
    typed = {t["cmd"]: t for t in result["typed"]}
    set_at, cleared_at = typed["M117 Hello"]["done_eventtime"], typed["M117"]["done_eventtime"]
    # The message is set at the module's updates (every 0.5 s): at a stop it names the
    # next one up to then after the status does.
    turns = [b["eventtime"] for a, b in zip(result["samples"], result["samples"][1:])
             if (_kest(a).get("next_stop") or {}).get("command")
             != (_kest(b).get("next_stop") or {}).get("command")]
    shown = users = 0
    for sample in result["samples"]:
        message = sample["status"].get("display_status", {}).get("message")
        stop = _kest(sample).get("next_stop")
        state = sample["status"].get("print_stats", {}).get("state")
        if any(abs(sample["eventtime"] - turn) < 1.0 for turn in turns):
            continue
        if set_at + 0.1 < sample["eventtime"] < cleared_at:
            assert message == "Hello"
            users += 1
        elif sample["eventtime"] > cleared_at + 1.0 and stop is not None and state == "printing":
            match = re.fullmatch(r"(\w+) in (?:(\d+)m )?(\d+)s", message or "")
            assert match is not None and match[1] == stop["command"], message
            seconds = int(match[2] or 0) * 60 + int(match[3])
            assert abs(seconds - stop["in_s"]) <= 1.5
            shown += 1
        elif state == "complete":
            # The file's own M117 at its pause stays (PrusaSlicer's "Insert magnets").
            assert message == "Insert magnets"
    assert users > 10 and shown > 100
