"""The real Moonraker (PyPI `moonraker`) runs kestimator-compat as its klipper_estimator.

Moonraker is started on 127.0.0.1 with `[analysis]` auto-analysis on and our launcher at
`<data>/tools/klipper_estimator/klipper_estimator_linux`, without Klipper (its socket does
not exist). Corpus files are uploaded through `/server/files/upload`; the stored files,
`/server/files/metadata` and `/server/analysis/estimate` must carry kestimator's times.

Moonraker is installed into a throwaway venv (it pins many packages of its own); set
KESTIMATOR_MOONRAKER_PYTHON to a Python that already has it to skip the install.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from kestimator import __version__, compat
from kestimator.config.klipper_estimator import dump_config
from kestimator.config.resolve import LimitRequest, resolve_limits
from kestimator.estimate import estimate_file
from tests.conftest import CORPUS, CORPUS_CFG, IN_CI, PROJECT

MOONRAKER_REQUIREMENT = "moonraker==0.11.0"
PYTHON_ENVIRONMENT = "KESTIMATOR_MOONRAKER_PYTHON"
INSTALL_TIMEOUT_S = 600.0
START_TIMEOUT_S = 60.0
METADATA_TIMEOUT_S = 120.0
HTTP_TIMEOUT_S = 60.0
UPLOADS = (
    "prusaslicer/ps25_nut_accelA_small.gcode",
    "cura/cura413_ender3_nut_small.gcode",
)
M73_RE = re.compile(rb"^M73\b.*$", re.MULTILINE)


def _missing(reason: str) -> None:
    if IN_CI:
        pytest.fail(reason)
    pytest.skip(reason)


@pytest.fixture(scope="session")
def moonraker_python(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A Python that can run `python -m moonraker`."""
    given = os.environ.get(PYTHON_ENVIRONMENT)
    if given:
        return given
    venv = tmp_path_factory.mktemp("moonraker-venv")
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
             headers: dict[str, str] | None = None) -> dict:
    request = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    with opener.open(request, timeout=HTTP_TIMEOUT_S) as response:
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
def _moonraker(python: str, data: Path, port: int) -> Iterator[subprocess.Popen[bytes]]:
    log = open(data / "logs" / "stdout.log", "wb")
    env = dict(os.environ, HOME=str(data), XDG_CONFIG_HOME=str(data / "xdg-config"),
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


def _install_estimator(data: Path) -> None:
    """What plugins/moonraker/README.md tells a user to do, pointed at this checkout."""
    tools = data / "tools" / "klipper_estimator"
    tools.mkdir(parents=True)
    launcher = tools / "klipper_estimator_linux"
    script = Path(sys.executable).with_name("kestimator-compat")
    if script.is_file():
        launcher.symlink_to(script)
        return
    launcher.write_text("#!/bin/sh\nPYTHONPATH=%s exec %s -m kestimator.compat \"$@\"\n"
                        % (_sh(str(PROJECT)), _sh(sys.executable)))
    launcher.chmod(0o755)


def _sh(text: str) -> str:
    return "'" + text.replace("'", "'\\''") + "'"


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


def test_moonraker_upload_stores_kestimator_times_metadata_and_analysis_estimate(
        moonraker_python: str, corpus_root: Path, tmp_path: Path) -> None:
    data = tmp_path / "printer_data"
    for folder in ("config", "gcodes", "logs", "comms", "database"):
        (data / folder).mkdir(parents=True)
    _install_estimator(data)
    machine = resolve_limits(LimitRequest(printer_cfg=CORPUS_CFG, use_profile=False))
    config = data / "config" / "estimator.json"
    config.write_text(json.dumps(dump_config(machine.limits, machine.sources), indent=2))
    port = _free_port()
    (data / "config" / "moonraker.conf").write_text(
        "[server]\nhost: 127.0.0.1\nport: %d\nklippy_uds_address: %s\n\n"
        "[machine]\nprovider: none\nvalidate_service: False\n\n"
        "[authorization]\ntrusted_clients:\n  127.0.0.0/8\n\n"
        "[file_manager]\nenable_object_processing: False\n\n"
        "[analysis]\nplatform: linux\nenable_auto_analysis: True\n"
        "estimator_config: estimator.json\n"
        % (port, data / "comms" / "klippy.sock"))
    base = "http://127.0.0.1:%d" % port
    log = data / "logs" / "stdout.log"
    started = time.monotonic()
    with _moonraker(moonraker_python, data, port) as process:
        info = _wait_ready(base, process, log)
        assert info["klippy_state"] != "ready"  # no Klipper behind it
        status = _request(base + "/server/analysis/status")["result"]
        assert status["estimator_ready"] is True
        assert status["estimator_version"] == __version__
        for relative in UPLOADS:
            source = CORPUS / "gcode" / relative
            limits = resolve_limits(LimitRequest(
                gcode=source, estimator_config=config, use_profile=False,
                read_slicer_environment=False)).limits
            assert limits == machine.limits
            expected = estimate_file(source, limits).total_s
            local = tmp_path / source.name
            shutil.copyfile(source, local)
            assert compat.main(["--config_file", str(config), "post-process",
                                str(local)]) == 0

            _upload(base, source)
            meta = _metadata(base, source.name)
            stored = (data / "gcodes" / source.name).read_bytes()
            # Moonraker stored exactly what kestimator-compat writes (true M73, rewritten
            # time comments, our marker) and ran it once.
            assert stored == local.read_bytes()
            assert stored != source.read_bytes()
            m73 = M73_RE.findall(stored)
            assert m73[0] == b"M73 P0 R%d" % int(expected / 60.0 + 0.5)
            assert m73[-1] == b"M73 P100 R0"
            assert all(re.fullmatch(rb"M73 P\d+ R\d+\r?", line) for line in m73)
            assert b"; kestimator %s klipper_s=%.3f " % (__version__.encode(), expected) \
                in stored
            assert stored.rstrip(b"\r\n").endswith(compat.IDENT_LINE.encode())
            # Moonraker's own slicer parser reads our rewritten estimate.
            assert abs(meta["estimated_time"] - expected) <= 1.0
            assert meta["estimated_time"] != pytest.approx(
                _metadata_of_original(moonraker_python, source), abs=1.0)

            answer = _request(base + "/server/analysis/estimate?" + urllib.parse.urlencode(
                {"filename": source.name}), "POST")["result"]
            assert answer["total_time"] == pytest.approx(expected, abs=1e-6)
            assert answer["num_moves"] > 0
            again = _request(base + "/server/analysis/process?" + urllib.parse.urlencode(
                {"filename": source.name}), "POST")["result"]
            assert again == {"prev_processed": True, "version": __version__,
                             "bypassed": True}
            assert (data / "gcodes" / source.name).read_bytes() == stored
    assert time.monotonic() - started < START_TIMEOUT_S + len(UPLOADS) * METADATA_TIMEOUT_S


def _metadata_of_original(python: str, source: Path) -> float:
    """Moonraker's own estimated_time of the unprocessed file (the slicer's number).

    Read from a copy: Moonraker's parser writes thumbnails beside the file it reads, and
    `source` is in the shared corpus."""
    script = ("import json,sys\nfrom moonraker.components.file_manager import metadata\n"
              "print(json.dumps(metadata.extract_metadata(sys.argv[1], [])))")
    with tempfile.TemporaryDirectory() as scratch:
        copy = Path(scratch) / source.name
        shutil.copyfile(source, copy)
        out = subprocess.run([python, "-c", script, str(copy)], check=True,
                             capture_output=True, timeout=HTTP_TIMEOUT_S).stdout
    return float(json.loads(out)["estimated_time"])
