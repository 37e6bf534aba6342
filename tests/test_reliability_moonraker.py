"""Moonraker answering badly (issue 20, items 7 and 8), against `tests/hostile_moonraker.py`.

One deadline bounds the whole request (a drip-fed answer cannot hold a run), an answer is
validated before it is cached, the API key is never printed (a key ending in CR or LF is
cleaned, one holding control characters is refused without being shown), and server text
reaches the user sanitised and bounded. Every server here is on 127.0.0.1 and stops itself.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from kestimator.config import moonraker
from kestimator.errors import KestimatorError

from .hostile_moonraker import HostileMoonraker

TIMEOUT_S = 1.0
# A request may take its deadline plus scheduling slack on a loaded machine, never more.
SLACK_S = 2.0
KEY = "TopSecret123"


def _error_of(url: str, api_key: str | None = None) -> tuple[str, float]:
    started = time.monotonic()
    with pytest.raises(KestimatorError) as info:
        moonraker.fetch_settings(url, api_key, TIMEOUT_S)
    return str(info.value), time.monotonic() - started


@pytest.mark.parametrize("behaviour", ["silent", "drip", "huge"])
def test_one_deadline_bounds_the_whole_request(behaviour: str) -> None:
    with HostileMoonraker(behaviour) as server:
        text, took = _error_of(server.url)
    assert took < TIMEOUT_S + SLACK_S, (behaviour, took)
    assert len(text.splitlines()) == 1


def test_garbage_is_one_clean_line() -> None:
    with HostileMoonraker("garbage") as server:
        text, _ = _error_of(server.url)
    assert text.isprintable() and len(text) < 400


def test_a_redirect_is_not_followed_and_the_key_goes_nowhere_else() -> None:
    with HostileMoonraker("redirect") as server:
        text, _ = _error_of(server.url, KEY)
        time.sleep(0.2)
        assert server.seen_headers == []
    assert KEY not in text


@pytest.mark.parametrize("key", [KEY, KEY + "\r", KEY + "\n", " " + KEY + "\r\n"])
def test_an_echoed_key_and_hostile_server_text_never_reach_the_user(key: str) -> None:
    with HostileMoonraker("echo_key") as server:
        text, _ = _error_of(server.url, key)
    assert KEY not in text
    assert text.isprintable() and len(text) < 600, text[:200]


def test_a_key_with_control_characters_inside_is_refused_without_showing_it() -> None:
    with pytest.raises(KestimatorError) as info:
        moonraker.fetch_settings("http://127.0.0.1:9", "Top\rSecret\n123", TIMEOUT_S)
    assert "Secret" not in str(info.value) and "Top" not in str(info.value)


def test_a_poisoned_answer_is_not_cached(tmp_path: Path) -> None:
    from .fake_moonraker import CORPUS_SETTINGS, FakeMoonraker

    poisoned = {section: dict(options) for section, options in CORPUS_SETTINGS.items()}
    poisoned["printer"]["square_corner_velocity"] = 1e200
    fake = FakeMoonraker(settings=poisoned).start()
    try:
        with pytest.raises(KestimatorError):
            moonraker.moonraker_values(fake.url, timeout_s=TIMEOUT_S, cache_directory=tmp_path)
    finally:
        fake.stop()
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("content", ["{not json", '{"format": 1}', "[]",
                                     '{"fetched": "2026-01-01T00:00:00Z", "url": "x", '
                                     '"settings": {"printer": 5}}'])
def test_a_corrupt_cache_is_reported_as_corrupt_not_as_missing(
        content: str, tmp_path: Path) -> None:
    with HostileMoonraker("garbage") as server:
        url = moonraker.normalise_url(server.url)
        path = moonraker.cache_path(url, tmp_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(content)
        with pytest.raises(KestimatorError) as info:
            moonraker.moonraker_values(url, timeout_s=TIMEOUT_S, cache_directory=tmp_path)
    assert "corrupt" in str(info.value) and "no settings" not in str(info.value)
