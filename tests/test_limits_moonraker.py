"""The Moonraker client against a local server that answers as Moonraker does
(tests/fake_moonraker.py): settings, API key, cache for an offline printer, redirects."""

from __future__ import annotations

import copy
import datetime
import json
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from kestimator import cli
from kestimator.config.moonraker import (
    MoonrakerUnreachableError,
    cache_path,
    fetch_settings,
    moonraker_values,
    normalise_url,
    settings_values,
)
from kestimator.config.printer_cfg import limits_from_printer_cfg
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.errors import KestimatorError
from kestimator.limits import Limits

from .conftest import CORPUS_CFG
from .fake_moonraker import (
    API_KEY,
    CORPUS_SETTINGS,
    QUERY,
    TIMEOUT_S,
    FakeMoonraker,
)


@pytest.fixture
def moonraker() -> Iterator[FakeMoonraker]:
    fake = FakeMoonraker(copy.deepcopy(CORPUS_SETTINGS), api_key=API_KEY).start()
    yield fake
    fake.stop()


def everything_in(folder: Path) -> str:
    return "".join(path.read_text(encoding="utf-8") for path in folder.rglob("*")
                   if path.is_file())


def test_moonraker_settings_give_the_limits_of_the_printer_cfg_they_come_from(
        moonraker: FakeMoonraker, tmp_path: Path) -> None:
    found = moonraker_values(moonraker.url, API_KEY, TIMEOUT_S, tmp_path)
    from_moonraker = Limits.from_values(found.values)
    # Moonraker also reports the macro the fake adds to the corpus printer.cfg.
    assert from_moonraker.gcode_macros == (("SECRET", ""),)
    from_cfg = limits_from_printer_cfg(CORPUS_CFG)[0]
    # The fake reports a few sections of its own (no steppers, a macro).
    assert {"printer", "extruder", "extruder1", "display_status"} <= set(
        from_moonraker.configured_sections)
    assert from_moonraker.replace(gcode_macros=(), configured_sections=()) == from_cfg.replace(
        configured_sections=())
    assert found.sources["max_accel"] == f"moonraker {moonraker.url}: [printer] max_accel"
    assert found.sources["arcs_enabled"] == f"moonraker {moonraker.url}: [gcode_arcs]"
    assert found.warnings == ()


def test_the_api_key_goes_in_the_x_api_key_header_of_the_settings_query(
        moonraker: FakeMoonraker) -> None:
    fetch_settings(moonraker.url, API_KEY, TIMEOUT_S)
    assert moonraker.requests == [(QUERY, API_KEY)]


def test_a_missing_or_wrong_api_key_is_refused_and_the_key_is_not_repeated(
        moonraker: FakeMoonraker, tmp_path: Path) -> None:
    for key in (None, "wrong-" + API_KEY):
        with pytest.raises(KestimatorError) as refused:
            moonraker_values(moonraker.url, key, TIMEOUT_S, tmp_path)
        assert "401 Unauthorized" in str(refused.value)
        assert API_KEY not in str(refused.value)
    assert not any(tmp_path.iterdir())


def test_an_offline_printer_falls_back_to_the_cache_and_says_so(
        moonraker: FakeMoonraker, tmp_path: Path) -> None:
    fetched = datetime.datetime(2026, 11, 21, 10, 0, 7, tzinfo=datetime.timezone.utc)
    live = moonraker_values(moonraker.url, API_KEY, TIMEOUT_S, tmp_path, now=lambda: fetched)
    moonraker.stop()
    offline = moonraker_values(moonraker.url, API_KEY, TIMEOUT_S, tmp_path)
    assert offline.values == live.values
    assert offline.description == (
        f"moonraker {moonraker.url} (cached 2026-11-21T10:00Z, printer offline)")
    assert offline.sources["max_velocity"].startswith(offline.description + ": ")
    assert len(offline.warnings) == 1 and "did not answer" in offline.warnings[0]


def test_the_cache_holds_the_sections_read_and_never_the_key(
        moonraker: FakeMoonraker, tmp_path: Path) -> None:
    moonraker_values(moonraker.url, API_KEY, TIMEOUT_S, tmp_path)
    document = json.loads(cache_path(moonraker.url, tmp_path).read_text(encoding="utf-8"))
    # The sections read are kept whole; of the others only the names (which commands
    # the printer knows), never a macro's text.
    assert {name for name, options in document["settings"].items() if options} == {
        "extruder", "extruder1", "firmware_retraction", "gcode_arcs", "printer", "heater_bed"}
    # Of a heater that is not an extruder, only its range (not its pins).
    assert document["settings"]["heater_bed"] == {"min_temp": 0.0, "max_temp": 300.0,
                                                  "min_extrude_temp": 170.0}
    assert "gcode_macro secret" in document["settings"]
    assert document["url"] == moonraker.url
    written = everything_in(tmp_path)
    assert API_KEY not in written and "wifi-password" not in written


def test_klipper_not_ready_behind_moonraker_uses_the_cache(tmp_path: Path) -> None:
    fake = FakeMoonraker(copy.deepcopy(CORPUS_SETTINGS)).start()
    try:
        moonraker_values(fake.url, None, TIMEOUT_S, tmp_path)
        fake.status = 503
        found = moonraker_values(fake.url, None, TIMEOUT_S, tmp_path)
    finally:
        fake.stop()
    assert "printer offline" in found.description
    assert "503 Klippy Disconnected" in found.warnings[0]


def test_offline_with_nothing_cached_is_an_error_naming_the_url(tmp_path: Path) -> None:
    fake = FakeMoonraker(CORPUS_SETTINGS).start()
    url = fake.url
    fake.stop()
    with pytest.raises(KestimatorError, match="did not answer.*no settings of it are cached"):
        moonraker_values(url, API_KEY, TIMEOUT_S, tmp_path)


def test_a_silent_printer_times_out(tmp_path: Path) -> None:
    # Accepts the connection (the backlog does) but never answers.
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        url = "http://127.0.0.1:%d" % listener.getsockname()[1]
        started = time.monotonic()
        with pytest.raises(MoonrakerUnreachableError):
            fetch_settings(url, API_KEY, 0.3)
        assert time.monotonic() - started < 5.0


def test_a_redirect_is_not_followed_so_the_key_stays_with_that_host(tmp_path: Path) -> None:
    target = FakeMoonraker(CORPUS_SETTINGS).start()
    redirecting = FakeMoonraker(CORPUS_SETTINGS, redirect_to=target.url).start()
    try:
        with pytest.raises(KestimatorError, match="302"):
            fetch_settings(redirecting.url, API_KEY, TIMEOUT_S)
    finally:
        redirecting.stop()
        target.stop()
    assert target.requests == []


def test_the_klipper_generation_is_inferred_where_the_settings_tell_it() -> None:
    printer = dict(CORPUS_SETTINGS["printer"])
    assert "klipper_generation" not in settings_values({"printer": printer}, "m").values
    printer["max_accel_to_decel"] = 1500.0
    assert settings_values({"printer": printer}, "m").values["klipper_generation"] == "mcr"
    del printer["minimum_cruise_ratio"]
    assert settings_values({"printer": printer}, "m").values["klipper_generation"] == "absolute"


def test_a_value_klipper_could_not_have_reported_is_an_error() -> None:
    with pytest.raises(KestimatorError, match=r"\[printer\] max_accel = -5.0 must be above 0"):
        settings_values({"printer": {"max_accel": -5.0}}, "moonraker http://x")


@pytest.mark.parametrize(("given", "normal"), [
    ("voron.local:7125", "http://voron.local:7125"),
    ("http://voron.local:7125/", "http://voron.local:7125"),
    ("https://printer.example/moonraker/", "https://printer.example/moonraker"),
])
def test_urls_are_normalised(given: str, normal: str) -> None:
    assert normalise_url(given) == normal


@pytest.mark.parametrize("given", ["http://user:secret@voron.local", "http://voron.local/?token=secret",
                                   "ftp://voron.local"])
def test_urls_with_credentials_or_other_schemes_are_refused_without_echo(given: str) -> None:
    with pytest.raises(KestimatorError) as refused:
        normalise_url(given)
    assert "secret" not in str(refused.value)


def test_resolver_and_cli_take_the_machine_from_moonraker_without_showing_the_key(
        moonraker: FakeMoonraker, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    environ = {"XDG_CACHE_HOME": str(tmp_path), "XDG_CONFIG_HOME": str(tmp_path / "none"),
               "HOME": str(tmp_path)}
    resolved = resolve_limits(LimitRequest(moonraker_url=moonraker.url, api_key=API_KEY,
                                           environ=environ))
    assert resolved.limits.replace(gcode_macros=(), configured_sections=()) == (
        limits_from_printer_cfg(CORPUS_CFG)[0].replace(configured_sections=()))
    assert resolved.machine == f"moonraker {moonraker.url}"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "none"))
    assert cli.main(["limits", "--moonraker", moonraker.url, "--api-key", API_KEY,
                     "--json"]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc["limits"]["max_z_accel"]["source"] == (
        f"moonraker {moonraker.url}: [printer] max_z_accel")
    assert API_KEY not in out + err + everything_in(tmp_path)
