"""The Moonraker API key never leaves the request, and Moonraker cannot hang kestimator.

A local HTTP server plays Moonraker (answering settings, refusing the key, failing with
500, or never answering); whatever it does, the key is sent in the X-Api-Key header only,
and is in no output, no error message and no cache file.
"""

from __future__ import annotations

import copy
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from kestimator import cli
from kestimator.config.moonraker import MoonrakerUnreachableError, fetch_settings

from .fake_moonraker import FakeMoonraker

SECRET = "k3y-9f1c2a7e-never-print-me"
GCODE = b"M83\nG1 X10 E1 F3000\nG1 X20 E1\n"
SETTINGS = {
    "printer": {"kinematics": "cartesian", "max_velocity": 250.0, "max_accel": 2500.0,
                "square_corner_velocity": 5.0, "max_z_velocity": 10.0, "max_z_accel": 100.0},
    "extruder": {"nozzle_diameter": 0.4, "filament_diameter": 1.75}}
TIMEOUT_S = 0.5


def _server(status: int) -> FakeMoonraker:
    """A fake Moonraker answering every settings query with `status` (key not checked)."""
    return FakeMoonraker(copy.deepcopy(SETTINGS), status=status).start()


def _keys_seen(fake: FakeMoonraker) -> list[str | None]:
    return [key for _path, key in fake.requests]


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
    server = _server(status)
    try:
        url = server.url
        work = tmp_path / "print.gcode"
        work.write_bytes(GCODE)
        for extra in ([], ["--json"]):
            code = cli.main([command, str(work), "--moonraker", url, "--api-key", SECRET,
                             "--debug", *extra])
            out, err = capsys.readouterr()
            assert code == (0 if status == 200 else 1), err
            assert SECRET not in out and SECRET not in err
    finally:
        server.stop()
    seen = _keys_seen(server)
    assert seen and set(seen) == {SECRET}
    assert SECRET.encode() not in _everything_written(cache_home)
    assert SECRET.encode() not in work.read_bytes()
    if status == 200:
        assert _everything_written(cache_home)


def test_the_api_key_from_the_environment_is_never_printed(
        tmp_path: Path, cache_home: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    server = _server(401)
    monkeypatch.setenv("MOONRAKER_API_KEY", SECRET)
    try:
        work = tmp_path / "print.gcode"
        work.write_bytes(GCODE)
        assert cli.main(["estimate", str(work), "--moonraker", server.url, "--debug"]) == 1
    finally:
        server.stop()
    out, err = capsys.readouterr()
    assert _keys_seen(server) == [SECRET]
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
    server = _server(200)
    try:
        work = tmp_path / "print.gcode"
        work.write_bytes(GCODE)
        url = server.url.replace("http://", "http://user:%s@" % SECRET)
        cli.main(["estimate", str(work), "--moonraker", url])
    finally:
        server.stop()
    out, err = capsys.readouterr()
    assert SECRET not in out + err
    assert SECRET.encode() not in _everything_written(cache_home)
    assert os.listdir(tmp_path) == ["cache", "print.gcode"]
