"""The Moonraker client against a local HTTP server that answers as Moonraker does.

The server listens on 127.0.0.1 only, shuts itself down after SERVER_LIFETIME_S whatever
happens, and answers ``GET /printer/objects/query?configfile=settings`` in Moonraker's format:
``{"result": {"eventtime": ..., "status": {"configfile": {"settings": ...}}}}`` with Klipper's
lower-case, typed settings (defaults included), refusing a wrong ``X-Api-Key`` with 401 and
``{"error": {"code": 401, "message": "Unauthorized"}}`` as Moonraker's app.py writes errors.
"""

from __future__ import annotations

import copy
import datetime
import http.server
import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

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

SERVER_LIFETIME_S = 30.0
TIMEOUT_S = 2.0
POLL_S = 0.02
API_KEY = "0123456789abcdef0123456789abcdef"
QUERY = "/printer/objects/query?configfile=settings"

# What Klipper reports for ../shared/corpus/printer.cfg (values typed, defaults it read
# included), plus sections kestimator must neither read nor cache.
CORPUS_SETTINGS: dict[str, dict[str, Any]] = {
    "mcu": {"serial": "/tmp/klipper_host_mcu", "baud": 250000},
    "printer": {"kinematics": "cartesian", "max_velocity": 300.0, "max_accel": 3000.0,
                "minimum_cruise_ratio": 0.5, "square_corner_velocity": 5.0,
                "max_z_velocity": 15.0, "max_z_accel": 100.0},
    "extruder": {"step_pin": "gpio12", "rotation_distance": 33.5, "nozzle_diameter": 0.4,
                 "filament_diameter": 1.75, "max_extrude_only_velocity": 120.0,
                 "max_extrude_only_accel": 1500.0, "max_extrude_only_distance": 10000.0,
                 "max_extrude_cross_section": 1000.0, "instantaneous_corner_velocity": 1.0,
                 "pressure_advance": 0.0, "min_extrude_temp": 0.0},
    "gcode_arcs": {"resolution": 1.0},
    "firmware_retraction": {"retract_length": 0.8, "retract_speed": 35.0,
                            "unretract_extra_length": 0.0, "unretract_speed": 35.0},
    "display_status": {},
    "gcode_macro secret": {"gcode": "M118 the-wifi-password"},
}


class FakeMoonraker:
    """A bounded local HTTP server speaking Moonraker's printer-object query."""

    def __init__(self, settings: dict[str, dict[str, Any]], api_key: str | None = None,
                 status: int = 200, redirect_to: str | None = None) -> None:
        self.settings = settings
        self.api_key = api_key
        self.status = status
        self.redirect_to = redirect_to
        self.requests: list[tuple[str, str | None]] = []
        fake = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                fake.requests.append((self.path, self.headers.get("X-Api-Key")))
                if fake.redirect_to is not None:
                    self.send_response(302)
                    self.send_header("Location", fake.redirect_to + self.path)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                if fake.api_key is not None and self.headers.get("X-Api-Key") != fake.api_key:
                    self._answer(401, {"error": {"code": 401, "message": "Unauthorized"}})
                elif fake.status != 200:
                    self._answer(fake.status, {"error": {"code": fake.status,
                                                         "message": "Klippy Disconnected"}})
                elif self.path != QUERY:
                    self._answer(404, {"error": {"code": 404, "message": "Not Found"}})
                else:
                    self._answer(200, {"result": {"eventtime": 578243.57824499, "status": {
                        "configfile": {"settings": fake.settings}}}})

            def _answer(self, status: int, document: dict[str, Any]) -> None:
                body = json.dumps(document).encode("utf-8")
                self.send_response(status)
                self.send_header("Content-Type", "application/json; charset=UTF-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                """Quiet: the test reports what matters."""

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = "http://127.0.0.1:%d" % self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever,
                                       kwargs={"poll_interval": POLL_S}, daemon=True)
        self.timer = threading.Timer(SERVER_LIFETIME_S, self.server.shutdown)
        self.timer.daemon = True

    def start(self) -> FakeMoonraker:
        self.thread.start()
        self.timer.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the port: the printer is now offline."""
        self.timer.cancel()
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(TIMEOUT_S)


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
    assert Limits.from_values(found.values) == limits_from_printer_cfg(CORPUS_CFG)[0]
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
    assert sorted(document["settings"]) == [
        "extruder", "firmware_retraction", "gcode_arcs", "printer"]
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
    assert resolved.limits == limits_from_printer_cfg(CORPUS_CFG)[0]
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
