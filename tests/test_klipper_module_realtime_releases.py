"""The Klipper module on every release it supports, at wall-clock speed
(tests/klipper_module/run_realtime.py, as tests/test_klipper_module_realtime.py runs it on
84104bbbd): one print each in Klipper v0.12.0, v0.13.0 and Kalico v2026.07.00, each with its
own printer.cfg (the one tests/oracle_refs_releases/ made its references with; its tree
found by tests/conftest.py's require_release: a missing tree skips, but under CI it fails).

One print covers what the real-time cases of 84104bbbd cover one by one: arcs (ArcWelder),
objects labelled as Moonraker labels them, a speed factor set before the print; an object
excluded, then a speed change, then a pause resumed 6 s later, typed mid-print as
Moonraker's console types them; a heater wait in the file. At every status cycle from 2 s
after the speed change (the module's exact answer due by then, run_print.ANSWER_WITHIN_S)
`remaining_s` is within run_print's bar after a change (1 s + 1 %) of the time Klipper then
really took, and so is Mainsail's own arithmetic on the status within 1 s. The three prints
run at once (they mostly wait on the wall clock).
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

from tests.conftest import require_program, require_release  # noqa: E402

pytestmark = pytest.mark.wall_clock  # tests/conftest.py starts it first
CORPUS = Path(run_print.SHARED) / "corpus" / "gcode"
# 84104bbbd's real-time prints are tests/test_klipper_module_realtime.py's.
RELEASES = ["v0.12.0", "v0.13.0", "kalico-v2026.07.00"]
HEAT_WAIT_S = 3.0
PAUSED_S = 6.0
TYPED = ["EXCLUDE_OBJECT", "M220", "PAUSE", "RESUME"]


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


def _print(work: Path, tree: tuple[str, str], cfg: str) -> dict[str, Any]:
    """The one print of a release: a speed factor set before it; an object excluded, a
    slower speed, a pause and its resume typed; a heater wait in the file."""
    work.mkdir(parents=True, exist_ok=True)
    src = CORPUS / "prusaslicer" / "cancelobj_ps2.4.0a1_arcwelder.gcode"
    labelled = _labelled(src, work / "labelled.gcode")
    names = [line.split(b"NAME=")[1].split()[0].decode()
             for line in labelled.read_bytes().split(b"\n")
             if line.startswith(b"EXCLUDE_OBJECT_DEFINE")]
    test_file = _with_heater_wait(labelled, work / "test_src.gcode", 0.8)
    result = run_realtime.run_realtime(
        str(test_file), str(work / "print"), heat_wait=HEAT_WAIT_S, before=["M220 S200"],
        base_cfg=cfg, klipper_tree=tree,
        script=[{"at": 0.15, "cmd": "EXCLUDE_OBJECT NAME=%s" % names[-1]},
                {"at": 0.3, "cmd": "M220 S170"},
                {"at": 0.5, "cmd": "PAUSE"},
                {"after": PAUSED_S, "cmd": "RESUME"}])
    result["excluded_name"] = names[-1]
    return result


@pytest.fixture(scope="module")
def prints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Each release's print, started at once; each test waits for its own. A release whose
    tree is missing gets its skip (or, under CI, its failure) instead."""
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=len(RELEASES))
    started: dict[str, Any] = {}
    for release in RELEASES:
        try:
            tree, cfg = require_release(release)
        except (pytest.skip.Exception, pytest.fail.Exception) as outcome:
            started[release] = outcome
            continue
        started[release] = pool.submit(_print, tmp_path_factory.mktemp(release), tree, cfg)
    pool.shutdown(wait=False)
    return started


def _result(prints: dict[str, Any], release: str) -> dict[str, Any]:
    started = prints[release]
    if isinstance(started, BaseException):
        raise started
    result: dict[str, Any] = started.result()
    # Klipper finished the print as a printer would: no error, never starved of moves.
    assert result["state"] == "complete", result["state"]
    assert result["errors"] == []
    assert result["stalls"] == 0
    assert result["returncode"] == 0
    log = Path(result["klippy_log"]).read_text(errors="replace")
    assert "kestimator: disabled" not in log
    assert [t["cmd"].split()[0] for t in result["typed"]] == TYPED
    assert all("error" not in t for t in result["typed"])
    return result


def _kest(sample: dict[str, Any]) -> dict[str, Any]:
    return dict(sample["status"].get("kestimator", {}))


@pytest.mark.parametrize("release", RELEASES)
def test_remaining_time_follows_each_release_at_every_status_cycle(
        prints: dict[str, Any], release: str) -> None:
    result = _result(prints, release)
    checked = run_realtime.checked_samples(result["samples"], result["typed"])
    assert len(checked) > 200
    for bar in {(absolute, relative) for _, absolute, relative in checked}:
        samples = [s for s, absolute, relative in checked if (absolute, relative) == bar]
        assert run_print.samples_off_bar(samples, *bar) == []


@pytest.mark.parametrize("release", RELEASES)
def test_the_changes_typed_mid_print_are_answered_on_each_release(
        prints: dict[str, Any], release: str) -> None:
    """From 2 s after the speed change the module's own exact answer, not a provisional
    one, with the excluded object's time left 0; while the head stands paused the time left
    stands; Klipper was idle through the pause and the heater waits (the file's two at its
    start and the one put in at 80 %)."""
    result = _result(prints, release)
    checked = [s for s, _, _ in run_realtime.checked_samples(result["samples"],
                                                             result["typed"])]
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


@pytest.mark.parametrize("release", RELEASES)
def test_mainsail_by_its_own_code_shows_each_releases_remaining_time(
        prints: dict[str, Any], release: str) -> None:
    """The recorded status stream fed to Mainsail's own store code (tests/frontends/) with
    the three settings of the module's guide: its remaining time and its ETA are within 1 s
    of what Klipper then really took at every checked cycle; its progress and Fluidd's are
    display_status's."""
    sys.path.insert(0, str(Path(__file__).parent / "frontends"))
    import frontends

    require_program("node")
    require_program("npm")
    result = _result(prints, release)
    checked = {id(s) for s, _, _ in run_realtime.checked_samples(result["samples"],
                                                                 result["typed"])}
    off = []
    for sample, view in zip(result["samples"], frontends.realtime_view(result)):
        if id(sample) not in checked:
            continue
        progress = sample["status"]["display_status"]["progress"]
        assert view["mainsail_progress"] == pytest.approx(progress, abs=1e-9)
        assert view["fluidd_progress"] == pytest.approx(progress, abs=1e-9)
        for field in ("mainsail_estimate_error_s", "mainsail_eta_left_error_s"):
            if view[field] is None or abs(view[field]) > 1.:
                off.append((round(sample["print_time"], 2), field, view[field]))
    assert off == []
