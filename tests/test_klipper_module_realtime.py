"""The Klipper module in real Klipper printing at wall-clock speed, as a printer prints
(tests/klipper_module/run_realtime.py): the module's timers and anchoring left to
themselves, its status read as Moonraker reads it (Klipper's objects/subscribe, every
250 ms, one eventtime per cycle), commands typed as Moonraker's console types them. At
every status cycle from 10 s of print_duration on, `remaining_s` is held against the time
Klipper then really took: within 0.5 s + 0.2 % on a plain print, within 1 s + 1 % from 2 s
after a change typed mid-print.

Real-printer configs beyond the corpus's: pressure advance with input shaper, a delta; and
state typed before the print. A change typed mid-print is checked from 2 s after it, one
change (that alters the time) per print. The prints all run at once (they mostly wait on the
wall clock); together they take as long as the longest, about 5 minutes.
"""
from __future__ import annotations

import concurrent.futures
import os
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "klipper_module"))
import run_print  # noqa: E402
import run_realtime  # noqa: E402

from tests.conftest import require_klipper, require_program  # noqa: E402

pytestmark = pytest.mark.wall_clock  # tests/conftest.py starts it first
CORPUS = Path(run_print.SHARED) / "corpus" / "gcode"
REFS = Path(__file__).parent / "oracle_refs"
PLAIN_ABS, PLAIN_REL = 0.5, 0.002
CHANGED_ABS, CHANGED_REL = 1.0, 0.01
SETTLE_S = 2.0          # the bar after a change holds from this long after it
FROM_DURATION_S = 10.0  # ... and from this long after the first extrusion
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


def _case_exclusion_pause_heater_wait(work: Path) -> dict[str, Any]:
    """Arcs (ArcWelder), labelled objects, a speed factor set before the print; an object
    excluded, then a pause, typed mid-print; a heater wait in the file."""
    work.mkdir(parents=True, exist_ok=True)
    src = CORPUS / "prusaslicer" / "cancelobj_ps2.4.0a1_arcwelder.gcode"
    labelled = _labelled(src, work / "labelled.gcode")
    names = [line.split(b"NAME=")[1].split()[0].decode()
             for line in labelled.read_bytes().split(b"\n")
             if line.startswith(b"EXCLUDE_OBJECT_DEFINE")]
    test_file = _with_heater_wait(labelled, work / "test_src.gcode", 0.8)
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


CASES = {
    "exclusion_pause_heater_wait": _case_exclusion_pause_heater_wait,
    "delta_state_typed_before": _case_delta_with_state_typed_before,
    "injected_table": _case_injected_table,
    "plain_pa_shaper": _case_plain_pa_shaper,
    "velocity_limit": _case_velocity_limit,
    "speed_change": _case_speed_change,
}
# Typed commands that do not change the time left (a pause's time is left out).
TIMELESS = ("PAUSE", "RESUME")


@pytest.fixture(scope="module")
def prints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Every case's print, started at once; each test waits for its own."""
    require_klipper()
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=len(CASES))
    futures = {name: pool.submit(case, tmp_path_factory.mktemp(name))
               for name, case in CASES.items()}
    pool.shutdown(wait=False)
    return futures


def _result(prints: dict[str, Any], name: str) -> dict[str, Any]:
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


def _checked(samples: list[dict[str, Any]],
             typed: list[dict[str, Any]]) -> list[tuple[dict[str, Any], float, float]]:
    """The samples the bars apply to, each with its bar (absolute, relative): from 10 s of
    print_duration, leaving out the 2 s after each typed command. A change typed later
    makes what Klipper then takes differ from what anyone could know before it: a print
    with a change is checked from 2 s after it (its only one that changes the time)."""
    changes = [t for t in typed if t["cmd"].split()[0] not in TIMELESS]
    start = changes[-1]["done_eventtime"] + SETTLE_S if changes else 0.
    out = []
    for sample in samples:
        stats = sample["status"].get("print_stats", {})
        if stats.get("state") not in ("printing", "paused"):
            continue
        if stats.get("print_duration", 0.) < FROM_DURATION_S:
            continue
        eventtime = sample["eventtime"]
        if eventtime < start:
            continue
        if any(t["eventtime"] <= eventtime < t["done_eventtime"] + SETTLE_S for t in typed):
            continue
        changed = any(t["done_eventtime"] <= eventtime for t in typed)
        bar = (CHANGED_ABS, CHANGED_REL) if changed else (PLAIN_ABS, PLAIN_REL)
        out.append((sample, bar[0], bar[1]))
    return out


def _off(result: dict[str, Any]) -> list[Any]:
    checked = _checked(result["samples"], result["typed"])
    assert len(checked) > 200
    return [(round(s["print_time"], 2), s["remaining_s"], round(s["truth_s"], 3))
            for s, absolute, relative in checked
            if s["remaining_s"] is None
            or abs(s["error_s"]) > absolute + relative * s["truth_s"]]


@pytest.mark.parametrize("name", sorted(CASES))
def test_remaining_time_follows_klipper_at_every_status_cycle(prints: dict[str, Any],
                                                              name: str) -> None:
    result = _result(prints, name)
    assert _off(result) == []


@pytest.mark.parametrize("name", sorted(CASES))
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


@pytest.mark.parametrize("name", sorted(CASES))
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
