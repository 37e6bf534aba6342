"""`kestimator learn` against bad stores (issue 29, item 3).

Learn never stores a value the loader would reject, and the loader drops a bad value alone
and says so.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kestimator import cli, learn
from kestimator.learn import JobTiming, LearnedTimes, LearnedValue, learn_from

URL = "http://voron.local:7125"


@pytest.fixture
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("MOONRAKER_API_KEY", raising=False)
    return tmp_path


def _timing(n: int, prep: float, print_s: float, motion_after: float) -> JobTiming:
    return JobTiming(job_id="%06X" % n, filename="f%d.gcode" % n,
                     total_duration=print_s + prep + 10.0, print_duration=print_s,
                     motion_before_s=10.0, motion_after_s=motion_after, frames=0,
                     tool_changes=0)


# Item 3: learn stores only what the loader uses; the loader drops a bad value alone.

def test_a_negative_start_time_is_not_stored_and_the_motion_correction_survives(
        tmp_path: Path) -> None:
    # total - print is 1.8 s shorter than Klipper's motion before the first extrusion.
    jobs = [_timing(i, -1.8 + d, 1050.0 + 2 * d, 1000.0) for i, d in enumerate((0, 0.1, -0.1))]
    learned = learn_from(jobs, URL, "2026-11-23T10:00:00Z", 3, [])
    assert learned.before_first_extrusion_s is None
    assert any("before the first extrusion not stored" in n and "-1.8 s is negative" in n
               for n in learned.notes), learned.notes
    assert learned.motion_ratio is not None
    assert learned.motion_ratio.value == pytest.approx(1.05)
    learn.save(learned, tmp_path)
    loaded, warnings = learn.load_with_warnings(URL, tmp_path)
    assert loaded == learned and warnings == ()


def test_the_loader_keeps_the_valid_values_beside_an_invalid_one_and_warns(
        tmp_path: Path) -> None:
    learned = LearnedTimes(URL, "2026-11-23T10:00:00Z",
                           before_first_extrusion_s=LearnedValue(-1.8, 0.1, 3, 0),
                           per_run_s={"T": LearnedValue(25.0, 1.0, 3, 0),
                                      learn.FRAME_MACRO: LearnedValue(3.2, 0.1, 2, 0)},
                           motion_ratio=LearnedValue(1.05, 0.002, 3, 0))
    path = learn.save(learned, tmp_path)  # as an older kestimator stored it
    loaded, warnings = learn.load_with_warnings(URL, tmp_path)
    assert loaded is not None
    assert loaded.before_first_extrusion_s is None
    assert loaded.motion_ratio == LearnedValue(1.05, 0.002, 3, 0)
    assert loaded.per_run_s == {"T": LearnedValue(25.0, 1.0, 3, 0)}
    assert len(warnings) == 2 and all(str(path) in w for w in warnings)
    assert "-1.8 s is negative" in warnings[0] and "2 jobs are fewer than 3" in warnings[1]


@pytest.mark.parametrize("text", ["{not json", "[" * 100_000, '{"format": 1}', "[]"])
def test_an_unusable_store_is_warned_about(tmp_path: Path, text: str) -> None:
    path = learn.store_path(URL, tmp_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    loaded, warnings = learn.load_with_warnings(URL, tmp_path)
    assert loaded is None
    assert len(warnings) == 1 and str(path) in warnings[0] and "not used" in warnings[0]
    assert learn.load_with_warnings("http://other:7125", tmp_path) == (None, ())


def test_limits_json_shows_the_valid_learned_value_and_the_warning(
        home: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import datetime

    from kestimator.config.moonraker import _write_cache, cache_path
    from tests.fake_moonraker import CORPUS_SETTINGS

    offline = "http://127.0.0.1:9"  # nothing listens: the cached settings stand in
    cache = home / "cache" / "kestimator"
    _write_cache(cache_path(offline, cache), offline, CORPUS_SETTINGS,
                 datetime.datetime(2026, 11, 20, tzinfo=datetime.timezone.utc))
    learn.save(LearnedTimes(offline, "2026-11-23T10:00:00Z",
                            before_first_extrusion_s=LearnedValue(-1.8, 0.1, 3, 0),
                            motion_ratio=LearnedValue(1.05, 0.002, 3, 0)), cache)
    assert cli.main(["limits", "--moonraker", offline, "--no-profile", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["learned"]["motion_ratio"]["value"] == pytest.approx(1.05)
    assert doc["learned"]["before_first_extrusion_s"] is None
    assert any("learned time before the first extrusion" in w and "not used" in w
               for w in doc["warnings"]), doc["warnings"]
