"""The statistics and the store of `kestimator learn` (against Moonraker: the e2e test)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kestimator import learn
from kestimator.learn import JobTiming, LearnedTimes, LearnedValue, learn_from, robust
from kestimator.macros import MacroTime

URL = "http://voron.local:7125"


def _job(n: int, prep: float, print_s: float, motion_after: float, frames: int = 0,
         tools: int = 0) -> JobTiming:
    return JobTiming(job_id="%06X" % n, filename="f%d.gcode" % n,
                     total_duration=print_s + prep + 10.0, print_duration=print_s,
                     motion_before_s=10.0, motion_after_s=motion_after, frames=frames,
                     tool_changes=tools)


def test_robust_takes_the_median_and_rejects_a_paused_job() -> None:
    value, rejected = robust([421.0, 418.0, 1320.0, 420.0, 419.0])
    assert rejected == [2]
    assert value == LearnedValue(419.5, pytest.approx(1.4826 * 1.0), 4, 1)


def test_robust_needs_three_jobs() -> None:
    assert robust([420.0, 421.0]) == (None, [])
    assert robust([420.0, 421.0, 2000.0])[0] is None


def test_motion_correction_only_when_measurably_slower() -> None:
    exact = [_job(i, 420.0, 1000.0 + d, 1000.0) for i, d in enumerate((0.0, 1.0, -1.0))]
    assert learn_from(exact, URL, "2026-11-23T10:00:00Z", 3, []).motion_ratio is None
    slow = [_job(i, 420.0, 1050.0 + d, 1000.0) for i, d in enumerate((0.0, 2.0, -2.0))]
    ratio = learn_from(slow, URL, "2026-11-23T10:00:00Z", 3, []).motion_ratio
    assert ratio is not None and ratio.value == pytest.approx(1.05)


def test_frames_and_tool_changes_are_learned_from_files_that_show_only_one_kind() -> None:
    jobs = [_job(0, 420.0, 1000.0 + 50 * 3.2, 1000.0, frames=50),
            _job(1, 420.0, 500.0 + 25 * 3.3, 500.0, frames=25),
            _job(2, 420.0, 800.0 + 10 * 3.1, 800.0, frames=10),
            _job(3, 420.0, 800.0 + 4 * 30.0, 800.0, tools=4),
            _job(4, 420.0, 800.0 + 4 * 30.0 + 10 * 3.2, 800.0, frames=10, tools=4)]
    learned = learn_from(jobs, URL, "2026-11-23T10:00:00Z", 5, [])
    assert learned.per_run_s[learn.FRAME_MACRO].value == pytest.approx(3.2)
    assert learned.per_run_s[learn.FRAME_MACRO].jobs == 3
    assert learn.TOOL_CHANGE not in learned.per_run_s  # one job only
    times = learned.macro_times({"PRINT_END": MacroTime(30.0, "profile p")})
    assert times.time_of("TIMELAPSE_TAKE_FRAME").seconds == pytest.approx(3.2)
    assert times.time_of("PRINT_END").source == "profile p"
    assert times.before_first_extrusion is not None
    assert times.before_first_extrusion.seconds == pytest.approx(420.0)
    assert "learned from 5 prints" in times.before_first_extrusion.source


def test_a_tool_change_time_serves_every_tool() -> None:
    learned = LearnedTimes(URL, "2026-11-23T10:00:00Z",
                           per_run_s={"T": LearnedValue(25.0, 1.0, 3, 0)})
    times = learned.macro_times()
    assert times.time_of("T3").seconds == 25.0 and times.time_of("TX") is None


def test_the_store_round_trips_and_refuses_what_it_did_not_write(tmp_path: Path) -> None:
    learned = learn_from([_job(i, 420.0 + i, 1000.0, 1000.0) for i in range(3)], URL,
                         "2026-11-23T10:00:00Z", 3, ["job 1: not used, status cancelled"])
    path = learn.save(learned, tmp_path)
    assert path.parent == tmp_path and path.name.startswith("learned-")
    assert learn.load(URL + "/", tmp_path) == learned
    assert learn.load("http://other:7125", tmp_path) is None
    document = json.loads(path.read_text())
    document["before_first_extrusion_s"]["value"] = "lots"
    path.write_text(json.dumps(document))
    # The damaged value alone is dropped, and said (tests/test_learn_reliability.py).
    loaded, warnings = learn.load_with_warnings(URL, tmp_path)
    assert loaded is not None and loaded.before_first_extrusion_s is None
    assert len(warnings) == 1 and "not used" in warnings[0]


def test_what_a_server_sends_is_shown_filtered() -> None:
    assert learn._shown("a\x1b[31mb\nc" + "x" * 100) == "a?[31mb?c" + "x" * 51
    assert learn._job_problem({"status": "completed", "exists": True, "filename": "a",
                               "total_duration": "1", "print_duration": 1.0}) == (
        "no usable total_duration")
    assert learn._job_problem({"status": "klippy_shutdown"}) == "status klippy_shutdown"


def test_compat_uses_the_learned_times_of_the_profiles_moonraker(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    import datetime
    import shutil

    from kestimator import compat
    from kestimator.config.moonraker import _write_cache, cache_path
    from kestimator.config.resolve import LimitRequest, resolve_limits
    from kestimator.estimate import estimate_file
    from kestimator.rewrite import PREP_PREFIX
    from tests.conftest import CORPUS, CORPUS_CFG
    from tests.fake_moonraker import CORPUS_SETTINGS

    offline = "http://127.0.0.1:9"  # nothing listens: the printer is offline
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("MOONRAKER_API_KEY", raising=False)
    (tmp_path / "config" / "kestimator").mkdir(parents=True)
    (tmp_path / "config" / "kestimator" / "config.toml").write_text(
        'moonraker = "%s"\n' % offline)
    cache = tmp_path / "cache" / "kestimator"
    _write_cache(cache_path(offline, cache), offline, CORPUS_SETTINGS,
                 datetime.datetime(2026, 11, 20, tzinfo=datetime.timezone.utc))
    learn.save(LearnedTimes(offline, "2026-11-23T10:00:00Z",
                            before_first_extrusion_s=LearnedValue(300.0, 2.0, 4, 1)), cache)
    nut = CORPUS / "gcode" / "prusaslicer" / "ps25_nut_accelA_small.gcode"
    plain = estimate_file(nut, resolve_limits(LimitRequest(
        printer_cfg=str(CORPUS_CFG), use_profile=False)).limits)
    assert compat.main(["estimate", "-f", "json", str(nut)]) == 0
    sequence = json.loads(capsys.readouterr().out)["sequences"][0]
    assert sequence["total_time"] == pytest.approx(plain.total_s + 300.0, abs=1e-6)
    assert sequence["kestimator_parts"]["print_duration_s"] == pytest.approx(
        plain.total_s, abs=1e-6)
    copy = tmp_path / nut.name
    shutil.copyfile(nut, copy)
    assert compat.main(["post-process", str(copy)]) == 0
    data = copy.read_bytes()
    assert (PREP_PREFIX + "5m 00s (300.000 s)").encode() in data
    assert b"; estimated printing time (normal mode) = 3m 42s" in data
