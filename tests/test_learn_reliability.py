"""`kestimator learn` against bad answers and bad stores (issue 29, items 2, 3 and 8).

One deadline bounds the whole command (a server dripping the history or a file cannot hold
it), kestimator keeps --jobs N itself, learn never stores a value the loader would reject,
the loader drops a bad value alone and says so, a deeply nested answer is one line naming
the server, and an unwritable cache fails before any download. Every server is on 127.0.0.1
and stops itself (tests/history_moonraker.py).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from kestimator import cli, learn
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.errors import KestimatorError
from kestimator.learn import JobTiming, LearnedTimes, LearnedValue, learn_from
from tests.conftest import CORPUS, CORPUS_CFG
from tests.history_moonraker import HistoryMoonraker, completed_job

URL = "http://voron.local:7125"
NUT = CORPUS / "gcode" / "prusaslicer" / "ps25_nut_accelA_small.gcode"
# A run may take its deadline plus scheduling slack on a loaded machine, never more.
SLACK_S = 4.0


@pytest.fixture
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("MOONRAKER_API_KEY", raising=False)
    return tmp_path


def _limits():  # type: ignore[no-untyped-def]
    return resolve_limits(LimitRequest(printer_cfg=str(CORPUS_CFG), use_profile=False)).limits


def _learn_cli(url: str, *extra: str) -> tuple[int, str, str, float]:
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    started = time.monotonic()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = cli.main(["learn", "--moonraker", url, "--no-profile", *extra])
    return status, out.getvalue(), err.getvalue(), time.monotonic() - started


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


# Item 2: one deadline for the whole command; --jobs N kept by kestimator.

@pytest.mark.parametrize("drip", ["history", "files"])
def test_one_deadline_bounds_the_whole_learn(home: Path, drip: str) -> None:
    jobs = [completed_job(1, NUT.name, 700.0, 400.0)]
    with HistoryMoonraker(jobs, {NUT.name: NUT.read_bytes()}, drip=(drip,)) as server:
        status, out, err, took = _learn_cli(server.url, "--timeout", "1.5")
    assert took < 1.5 + SLACK_S, took
    assert status == 1 and out == ""
    assert err.count("\n") == 1 and "did not finish within 1.5 s" in err, err
    assert "internal error" not in err
    assert not list((home / "cache" / "kestimator").glob("learned-*"))


def test_the_timeout_option_is_documented_and_checked(
        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.main(["learn", "--help"])
    assert "--timeout S" in capsys.readouterr().out
    doc = (Path(__file__).parent.parent / "docs" / "CLI.md").read_text()
    assert "--timeout S" in doc
    for bad in (["--timeout", "0"], ["--timeout", "nan"], ["--jobs", "0"]):
        assert cli.main(["learn", "--moonraker", "http://127.0.0.1:9", "--no-profile",
                         *bad]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "must be" in err


def test_only_the_newest_n_jobs_are_read_whatever_the_server_sends() -> None:
    jobs = [completed_job(n, "f%d.gcode" % n, 700.0, 400.0) for n in range(2000)]
    with HistoryMoonraker(jobs) as server:
        learned = learn.learn_from_moonraker(server.url, _limits(), max_jobs=3,
                                             deadline_s=10.0)
        downloads = server.downloads()
    assert learned.jobs_read == 3
    assert downloads == ["f0.gcode", "f1.gcode", "f2.gcode"]


def test_a_history_answer_too_large_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(learn, "MAX_HISTORY_BYTES", 1000)
    jobs = [completed_job(n, "f%d.gcode" % n, 700.0, 400.0) for n in range(50)]
    with HistoryMoonraker(jobs) as server, pytest.raises(KestimatorError) as info:
        learn.learn_from_moonraker(server.url, _limits(), deadline_s=10.0)
    assert "answered more than 1000 bytes" in str(info.value)
    assert server.url in str(info.value)


# Item 8: a nested answer and an unwritable cache are one line each.

def test_a_deeply_nested_history_is_one_line_naming_the_server(home: Path) -> None:
    body = b"[" * 100_000 + b"]" * 100_000
    with HistoryMoonraker([], history_body=body) as server:
        status, _out, err, _took = _learn_cli(server.url)
    assert status == 1 and err.count("\n") == 1, err
    assert "internal error" not in err and server.url in err
    assert "did not answer with its job history" in err


def test_an_unwritable_cache_fails_before_any_download(home: Path) -> None:
    (home / "cache").write_text("a file where the cache directory should be")
    jobs = [completed_job(1, NUT.name, 700.0, 400.0)]
    with HistoryMoonraker(jobs, {NUT.name: NUT.read_bytes()}) as server:
        status, _out, err, _took = _learn_cli(server.url)
        downloads = server.downloads()
    assert status == 1 and err.count("\n") == 1, err
    assert "cannot store the learned times in" in err and "internal error" not in err
    assert downloads == []
