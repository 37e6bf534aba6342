"""The real Moonraker (PyPI `moonraker`) in a temporary data folder, for the end-to-end tests.

Moonraker is installed into a throwaway venv once per run, for every process (it pins many
packages of its own); set KESTIMATOR_MOONRAKER_PYTHON to a Python that already has it to skip
the install.
It runs on 127.0.0.1 without Klipper (its socket does not exist) and without systemd
(`[machine] provider: none`).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import IN_CI, once_per_run

MOONRAKER_REQUIREMENT = "moonraker==0.11.0"
PYTHON_ENVIRONMENT = "KESTIMATOR_MOONRAKER_PYTHON"
INSTALL_TIMEOUT_S = 600.0
START_TIMEOUT_S = 60.0
METADATA_TIMEOUT_S = 120.0
HTTP_TIMEOUT_S = 60.0

def _missing(reason: str) -> None:
    if IN_CI:
        pytest.fail(reason)
    pytest.skip(reason)


@pytest.fixture(scope="session")
def moonraker_python() -> str:
    """A Python that can run `python -m moonraker` (one venv for the whole run)."""
    given = os.environ.get(PYTHON_ENVIRONMENT)
    if given:
        return given
    return once_per_run("moonraker-venv " + MOONRAKER_REQUIREMENT, _install_moonraker)


def _install_moonraker(folder: Path) -> str:
    venv = folder / "venv"
    try:
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True,
                       capture_output=True, timeout=INSTALL_TIMEOUT_S)
        python = str(venv / "bin" / "python")
        subprocess.run([python, "-m", "pip", "install", "-q", MOONRAKER_REQUIREMENT],
                       check=True, capture_output=True, timeout=INSTALL_TIMEOUT_S)
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired, OSError) as exc:
        detail = getattr(exc, "stderr", b"") or b""
        _missing("cannot install %s into a venv: %s %s" % (
            MOONRAKER_REQUIREMENT, exc, detail.decode(errors="replace")[-2000:]))
    return python


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _request(url: str, method: str = "GET", body: bytes | None = None,
             headers: dict[str, str] | None = None,
             timeout: float = HTTP_TIMEOUT_S) -> dict:
    request = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    with opener.open(request, timeout=timeout) as response:
        return json.loads(response.read())


def _upload(base: str, path: Path) -> dict:
    boundary = uuid.uuid4().hex
    body = b"".join([
        b"--%s\r\n" % boundary.encode(),
        b'Content-Disposition: form-data; name="root"\r\n\r\ngcodes\r\n',
        b"--%s\r\n" % boundary.encode(),
        b'Content-Disposition: form-data; name="file"; filename="%s"\r\n'
        % path.name.encode(),
        b"Content-Type: application/octet-stream\r\n\r\n",
        path.read_bytes(),
        b"\r\n--%s--\r\n" % boundary.encode(),
    ])
    return _request(base + "/server/files/upload", "POST", body,
                    {"Content-Type": "multipart/form-data; boundary=" + boundary})


@contextlib.contextmanager
def _moonraker(python: str, data: Path, port: int,
               home: Path | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """Moonraker on `data`, its HOME `home` (default: the data folder)."""
    log = open(data / "logs" / "stdout.log", "wb")
    env = dict(os.environ, HOME=str(home or data), XDG_CONFIG_HOME=str(data / "xdg-config"),
               XDG_CACHE_HOME=str(data / "xdg-cache"))
    env.pop(PYTHON_ENVIRONMENT, None)
    process = subprocess.Popen(
        [python, "-m", "moonraker", "-d", str(data), "-c", str(data / "config" /
                                                                "moonraker.conf"),
         "-l", str(data / "logs" / "moonraker.log")],
        stdout=log, stderr=subprocess.STDOUT, env=env, cwd=str(data))
    try:
        yield process
    finally:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=20)
        log.close()


def _wait_ready(base: str, process: subprocess.Popen[bytes], log: Path) -> dict:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail("Moonraker exited (%s):\n%s" % (process.returncode,
                                                         log.read_text(errors="replace")[-4000:]))
        with contextlib.suppress(OSError, ValueError):
            return _request(base + "/server/info")["result"]
        time.sleep(0.2)
    pytest.fail("Moonraker did not answer /server/info in %g s" % START_TIMEOUT_S)


def _metadata(base: str, name: str) -> dict:
    deadline = time.monotonic() + METADATA_TIMEOUT_S
    query = urllib.parse.urlencode({"filename": name})
    while time.monotonic() < deadline:
        try:
            meta = _request(base + "/server/files/metadata?" + query)["result"]
        except urllib.error.HTTPError:
            meta = {}
        if "klipper_estimator" in meta.get("file_processors", []):
            return meta
        time.sleep(0.2)
    pytest.fail("no metadata with klipper_estimator processing for %s" % name)
