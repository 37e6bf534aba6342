"""The Moonraker API key never leaves the request, and Moonraker cannot hang kestimator.

A local HTTP server plays Moonraker (answering settings, refusing the key, failing with
500, or never answering); whatever it does, the key is sent in the X-Api-Key header only,
and is in no output, no error message and no cache file.
"""

from __future__ import annotations

import http.server
import json
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from kestimator import cli
from kestimator.config.moonraker import MoonrakerUnreachableError, fetch_settings

SECRET = "k3y-9f1c2a7e-never-print-me"
GCODE = b"M83\nG1 X10 E1 F3000\nG1 X20 E1\n"
SETTINGS = {"result": {"eventtime": 1.0, "status": {"configfile": {"settings": {
    "printer": {"kinematics": "cartesian", "max_velocity": 250.0, "max_accel": 2500.0,
                "square_corner_velocity": 5.0, "max_z_velocity": 10.0, "max_z_accel": 100.0},
    "extruder": {"nozzle_diameter": 0.4, "filament_diameter": 1.75}}}}}}
TIMEOUT_S = 0.5


def _server(status: int) -> tuple[http.server.ThreadingHTTPServer, list[str | None]]:
    seen: list[str | None] = []

    class Moonraker(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802
            seen.append(self.headers.get("X-Api-Key"))
            body = (json.dumps(SETTINGS) if status == 200 else
                    json.dumps({"error": {"code": status, "message": "Unauthorized"}})).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Moonraker)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, seen


@pytest.fixture
def cache_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    home = tmp_path / "cache"
    home.mkdir()
    monkeypatch.setenv("XDG_CACHE_HOME", str(home))
    monkeypatch.delenv("MOONRAKER_API_KEY", raising=False)
    return home


def _everything_written(folder: Path) -> bytes:
    return b"".join(p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file())


@pytest.mark.parametrize("status", [200, 401, 500])
@pytest.mark.parametrize("command", ["estimate", "inject"])
def test_the_api_key_is_sent_only_in_its_header_and_never_printed_or_cached(
        status: int, command: str, tmp_path: Path, cache_home: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    server, seen = _server(status)
    try:
        url = "http://127.0.0.1:%d" % server.server_address[1]
        work = tmp_path / "print.gcode"
        work.write_bytes(GCODE)
        for extra in ([], ["--json"]):
            code = cli.main([command, str(work), "--moonraker", url, "--api-key", SECRET,
                             "--debug", *extra])
            out, err = capsys.readouterr()
            assert code == (0 if status == 200 else 1), err
            assert SECRET not in out and SECRET not in err
    finally:
        server.shutdown()
        server.server_close()
    assert seen and set(seen) == {SECRET}
    assert SECRET.encode() not in _everything_written(cache_home)
    assert SECRET.encode() not in work.read_bytes()
    if status == 200:
        assert _everything_written(cache_home)


def test_the_api_key_from_the_environment_is_never_printed(
        tmp_path: Path, cache_home: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    server, seen = _server(401)
    monkeypatch.setenv("MOONRAKER_API_KEY", SECRET)
    try:
        work = tmp_path / "print.gcode"
        work.write_bytes(GCODE)
        url = "http://127.0.0.1:%d" % server.server_address[1]
        assert cli.main(["estimate", str(work), "--moonraker", url, "--debug"]) == 1
    finally:
        server.shutdown()
        server.server_close()
    out, err = capsys.readouterr()
    assert seen == [SECRET]
    assert SECRET not in out + err and "API key" in err


@pytest.fixture
def silent_moonraker() -> Iterator[str]:
    """A port that accepts connections and never answers."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    try:
        yield "http://127.0.0.1:%d" % listener.getsockname()[1]
    finally:
        listener.close()


def test_a_moonraker_that_never_answers_times_out(silent_moonraker: str) -> None:
    started = time.monotonic()
    with pytest.raises(MoonrakerUnreachableError) as info:
        fetch_settings(silent_moonraker, SECRET, timeout_s=TIMEOUT_S)
    assert time.monotonic() - started < TIMEOUT_S + 2.0
    assert SECRET not in str(info.value)


def test_the_cache_holds_no_credentials_even_when_named_like_one(
        tmp_path: Path, cache_home: Path, capsys: pytest.CaptureFixture[str]) -> None:
    server, _seen = _server(200)
    try:
        work = tmp_path / "print.gcode"
        work.write_bytes(GCODE)
        url = "http://user:%s@127.0.0.1:%d" % (SECRET, server.server_address[1])
        cli.main(["estimate", str(work), "--moonraker", url])
    finally:
        server.shutdown()
        server.server_close()
    out, err = capsys.readouterr()
    assert SECRET not in out + err
    assert SECRET.encode() not in _everything_written(cache_home)
    assert os.listdir(tmp_path) == ["cache", "print.gcode"]
